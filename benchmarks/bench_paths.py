"""Warm new views of a large volume where users meet them: in-process, over HTTP, and per frame of a turntable job.

    .venv/bin/python benchmarks/bench_paths.py [--store benchmarks/results/large/body_1024x2048x2048.zarr]
        [--frames 12] [--size 512] [--reduction 30] [--json docs/measurements/paths.json]

The store is one bench_large_volume.py or bench_scaling.py made (never committed). Each path gets a fresh process
and renderer with the same settings (this process's LODCAST_* environment, brick pool LODCAST_BRICK_CACHE_MB
default 1024): a first frame at azimuth 30° (cold for the process, not counted), then `frames` new views 2° apart,
elevation 20°, ct-bone, `{"reduction": R}`, `size`² (docs/design.md: large volumes are measured at 512²).
- in-process: `lodcast.Renderer().render` in this process, wall time per call;
- HTTP: `lodcast serve` on loopback (the store hard-linked under a temporary root), `POST /volumes/{id}/render`
  from one client, wall time per request as the client sees it, and the server's own `wall_ms` beside;
- job: `lodcast worker` on the embedded SQLite queue, a turntable of 180 frames (2° apart) whose progress this
  process polls every 5 ms: the time between consecutive frames done, the job's PNG written included; the job
  is cancelled after `frames` + 1 frames.
Medians and p95 per path, with the in-process median's ratio. Prints a table and writes JSON.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_service import pct  # noqa: E402

import lodcast  # noqa: E402
from lodcast.service.testing import free_port, start_serve, start_worker  # noqa: E402

AZ0, STEP, ELEVATION = 30.0, 2.0, 20.0


def scene(azimuth: float, size: int, reduction: float) -> dict:
    return {"camera": {"azimuth": azimuth, "elevation": ELEVATION}, "width": size, "height": size,
            "tf": "ct-bone", "quality": {"reduction": reduction}}


def stats(ms: list[float]) -> dict:
    return {"n": len(ms), "median_ms": float(np.median(ms)), "p95_ms": pct(ms, 0.95), "frames_ms": ms}


def in_process(store: Path, frames: int, size: int, reduction: float) -> dict:
    eng = lodcast.Renderer()
    t0 = time.perf_counter()
    eng.render(str(store), scene(AZ0, size, reduction))
    first = (time.perf_counter() - t0) * 1e3
    ms, host = [], []
    for i in range(1, frames + 1):
        t0 = time.perf_counter()
        r = eng.render(str(store), scene(AZ0 + STEP * i, size, reduction))
        ms.append((time.perf_counter() - t0) * 1e3)
        host.append(1.0 - r.report["kernel_ms"] / r.report["wall_ms"])
    eng.close()
    return {**stats(ms), "first_ms": first, "host_share_median": float(np.median(host))}


def over_http(root: Path, volume: str, frames: int, size: int, reduction: float, logs: Path) -> dict:
    port = free_port()
    proc = start_serve(root, port, env={"LODCAST_TOKEN": ""}, log=logs / "serve.log")
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=900) as c:
            t0 = time.perf_counter()
            r = c.post(f"/volumes/{volume}/render", json=scene(AZ0, size, reduction))
            r.raise_for_status()
            first = (time.perf_counter() - t0) * 1e3
            ms, server = [], []
            for i in range(1, frames + 1):
                t0 = time.perf_counter()
                r = c.post(f"/volumes/{volume}/render", json=scene(AZ0 + STEP * i, size, reduction))
                r.raise_for_status()
                ms.append((time.perf_counter() - t0) * 1e3)
                server.append(json.loads(r.headers["X-Lodcast-Report"])["wall_ms"])
    finally:
        proc.stop()
    return {**stats(ms), "first_ms": first, "server_wall_median_ms": float(np.median(server))}


def per_job_frame(root: Path, volume: str, frames: int, size: int, reduction: float, logs: Path) -> dict:
    from lodcast.service.jobs import parse_job
    from lodcast.service.queue import JobQueue
    from lodcast.service.settings import Settings

    name = f"paths{time.monotonic_ns()}"
    jq = JobQueue(Settings(root=root, queue=None, queue_name=name, token=None))
    env = {"LODCAST_QUEUE_NAME": name, "LODCAST_POLL_S": "0.02", "LODCAST_TOKEN": ""}
    proc = start_worker(root, env=env, log=logs / "worker.log")
    try:
        job = parse_job({"kind": "turntable", "volume": volume, "scene": scene(AZ0, size, reduction),
                         "frames": int(round(360 / STEP)), "start_azimuth": AZ0})
        jid = jq.submit(job)["id"]
        seen, times = 0, []
        t_start = time.perf_counter()
        while seen < frames + 1:
            st = jq.get(jid)
            if st["state"] in ("failed", "cancelled"):
                raise RuntimeError(f"job {jid} {st['state']}: {st['error']}")
            done = int(st["done"] or 0)
            if done > seen:
                times += [time.perf_counter()] * (done - seen)
                seen = done
            time.sleep(0.005)
        jq.cancel(jid)
    finally:
        proc.stop()
    gaps = [(b - a) * 1e3 for a, b in zip(times, times[1:])]
    return {**stats(gaps[:frames]), "first_ms": (times[0] - t_start) * 1e3}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--store", type=Path, default=HERE / "results" / "large" / "body_1024x2048x2048.zarr")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--reduction", type=float, default=30.0)
    ap.add_argument("--json", type=Path, default=HERE / "results" / "paths.json")
    a = ap.parse_args(argv)
    if not a.store.is_dir():
        print(f"--store: {a.store} is not a store (make one with benchmarks/bench_large_volume.py)", file=sys.stderr)
        return 2
    tmp = Path(tempfile.mkdtemp(prefix="lodcast-paths-", dir=a.store.parent))  # same file system: hard links
    volume = "big"
    try:
        subprocess.run(["cp", "-al", str(a.store), str(tmp / volume)], check=True)
        logs = tmp / "logs"
        logs.mkdir()
        res = {"date": time.strftime("%Y-%m-%d"), "machine": f"{platform.processor() or platform.machine()}, "
               f"nproc {os.cpu_count()}", "store": a.store.name, "size": a.size, "reduction": a.reduction,
               "frames": a.frames, "step_deg": STEP,
               "command": "benchmarks/bench_paths.py " + " ".join(argv if argv is not None else sys.argv[1:]),
               "env": {k: v for k, v in os.environ.items() if k.startswith("LODCAST_")}}
        res["in_process"] = in_process(tmp / volume, a.frames, a.size, a.reduction)
        res["http"] = over_http(tmp, volume, a.frames, a.size, a.reduction, logs)
        res["job"] = per_job_frame(tmp, volume, a.frames, a.size, a.reduction, logs)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    base = res["in_process"]["median_ms"]
    print(f"\n{a.store.name}, {a.size}², reduction {a.reduction:g}, {a.frames} new views {STEP:g}° apart\n")
    print("| path | first frame (ms) | new view, median (ms) | p95 (ms) | ÷ in-process |")
    print("|---|---|---|---|---|")
    for k, label in (("in_process", "in-process `Renderer.render`"), ("http", "HTTP `POST /volumes/{id}/render`"),
                     ("job", "turntable job, per frame")):
        r = res[k]
        print(f"| {label} | {r['first_ms']:.0f} | {r['median_ms']:.0f} | {r['p95_ms']:.0f} | "
              f"{r['median_ms'] / base:.2f} |")
    a.json.parent.mkdir(parents=True, exist_ok=True)
    a.json.write_text(json.dumps(res, indent=1))
    print(f"\nwrote {a.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
