"""Service benchmark: render latency p50/p95 at 512² for 1, 4 and 8 concurrent clients against a live `lodcast serve`
on loopback, and batch-job throughput (frames/s) with 1 and 2 `lodcast worker` processes on the embedded SQLite queue
and on Redis. Optionally a soak: 8 clients rendering for N seconds, counting errors.

    .venv/bin/python benchmarks/bench_service.py                 # the demo volume (lodcast demo's), table + JSON
    .venv/bin/python benchmarks/bench_service.py --soak 30       # plus the 30-second 8-client soak
    .venv/bin/python benchmarks/bench_service.py --source FILE   # another volume (any format lodcast ingest reads)

Writes benchmarks/results/bench_service.json (and prints the same JSON after the table); the service's and workers'
logs stay in benchmarks/results/bench_service_logs/.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

import lodcast
from lodcast.service.testing import RedisServer, free_port, redis_available, start_serve, start_worker


def pct(values: list[float], q: float) -> float:
    v = sorted(values)
    if not v:
        return float("nan")
    k = (len(v) - 1) * q
    lo, hi = int(k), min(int(k) + 1, len(v) - 1)
    return v[lo] + (v[hi] - v[lo]) * (k - lo)


def scene_for(summary: dict, size: int, azimuth: float = 30.0) -> dict:
    lo, hi = summary["value_range"]
    span = hi - lo
    return {
        "camera": {"azimuth": azimuth, "elevation": 20, "distance": 2.2},
        "width": size, "height": size,
        "tf": {"points": [{"value": lo + 0.25 * span, "color": [0.9, 0.7, 0.6], "opacity": 0.0},
                          {"value": lo + 0.45 * span, "color": [1.0, 0.9, 0.8], "opacity": 0.15},
                          {"value": lo + 0.8 * span, "color": [1.0, 1.0, 1.0], "opacity": 0.8}]},
        "sampling": {"step": 0.5},
    }


def latency(url: str, volume: str, summary: dict, clients: int, per_client: int, size: int) -> dict:
    lat: list[float] = []
    errors: list[str] = []
    lock = threading.Lock()

    def run(i: int) -> None:
        with httpx.Client(base_url=url, timeout=600) as c:
            for k in range(per_client):
                t0 = time.perf_counter()
                try:
                    r = c.post(f"/volumes/{volume}/render", json=scene_for(summary, size, 37.0 * k + 11.0 * i))
                except httpx.HTTPError as exc:
                    with lock:
                        errors.append(repr(exc))
                    continue
                dt = time.perf_counter() - t0
                with lock:
                    (lat.append(dt) if r.status_code == 200 else errors.append(f"{r.status_code}: {r.text[:200]}"))

    t0 = time.perf_counter()
    threads = [threading.Thread(target=run, args=(i,)) for i in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    return {"clients": clients, "requests": len(lat), "errors": len(errors), "p50_ms": 1e3 * pct(lat, 0.5),
            "p95_ms": 1e3 * pct(lat, 0.95), "renders_per_s": len(lat) / wall}


def soak(url: str, volume: str, summary: dict, seconds: float, clients: int = 8, size: int = 256) -> dict:
    counts = [0] * clients
    errors: list[str] = []
    end = time.monotonic() + seconds

    def run(i: int) -> None:
        with httpx.Client(base_url=url, timeout=600) as c:
            k = 0
            while time.monotonic() < end and len(errors) < 50:  # a dead server is reported, not hammered
                try:
                    r = c.post(f"/volumes/{volume}/render", json=scene_for(summary, size, 13.0 * k + 45.0 * i))
                    if r.status_code != 200:
                        errors.append(f"{r.status_code}: {r.text[:200]}")
                except httpx.HTTPError as exc:
                    errors.append(repr(exc))
                counts[i] += 1
                k += 1

    threads = [threading.Thread(target=run, args=(i,)) for i in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return {"clients": clients, "seconds": seconds, "size": size, "requests": sum(counts), "per_client": counts,
            "errors": len(errors), "first_errors": errors[:3]}


def throughput(root: Path, volume: str, summary: dict, queue: str | None, workers: int, jobs: int, frames: int,
               size: int, logs: Path) -> dict:
    from lodcast.service.jobs import parse_job
    from lodcast.service.queue import JobQueue
    from lodcast.service.settings import Settings

    name = f"bench{time.monotonic_ns()}"
    jq = JobQueue(Settings(root=root, queue=queue, queue_name=name, token=None))
    env = {"LODCAST_QUEUE_NAME": name, "LODCAST_POLL_S": "0.05", "LODCAST_TOKEN": ""}
    procs = [start_worker(root, queue=queue, env=env, log=logs / f"worker-{name}-{i}.log") for i in range(workers)]
    try:
        # warm-up job: each worker compiles (or loads) its kernel and uploads the volume
        warm = [jq.submit(parse_job({"kind": "turntable", "volume": volume, "scene": scene_for(summary, 16), "frames": 1}))["id"]
                for _ in range(workers)]
        for w in warm:
            jq.wait(w, timeout=300, poll=0.05)
        time.sleep(0.5)
        t0 = time.perf_counter()
        ids = [jq.submit(parse_job({"kind": "turntable", "volume": volume, "scene": scene_for(summary, size),
                                    "frames": frames, "start_azimuth": 7.0 * j}))["id"] for j in range(jobs)]
        recs = [jq.wait(i, timeout=1800, poll=0.05) for i in ids]
        wall = time.perf_counter() - t0
        states = [r["state"] for r in recs]
        for r in recs:
            if r["state"] != "done":
                print(f"  job {r['id']} {r['state']}: {r['error']}", file=sys.stderr)
    finally:
        for p in procs:
            p.stop()
    done = sum(1 for s in states if s == "done")
    return {"queue": "redis" if queue else "sqlite", "workers": workers, "jobs": jobs, "frames": done * frames,
            "size": size, "jobs_done": done, "seconds": wall, "frames_per_s": done * frames / wall}


def run_latency(args: argparse.Namespace, root: Path, summary: dict, logs: Path, result: dict) -> None:
    port = free_port()
    env = {"LODCAST_RENDER_CONCURRENCY": str(args.render_concurrency), "LODCAST_TOKEN": "",
           "LODCAST_MAX_WIDTH": "4096", "LODCAST_MAX_HEIGHT": "4096"}
    serve = start_serve(root, port, env=env, log=logs / "serve.log", extra=["--workers", "0"])
    url = f"http://127.0.0.1:{port}"
    try:
        with httpx.Client(base_url=url, timeout=600) as c:  # warm-up: kernel build and volume upload
            r = c.post("/volumes/demo/render", json=scene_for(summary, args.size))
            r.raise_for_status()
            result["device"] = json.loads(r.headers["x-lodcast-report"]).get("device")
        for clients in (1, 4, 8):
            per = max(1, args.requests // clients)
            row = latency(url, "demo", summary, clients, per, args.size)
            result["latency"].append(row)
            print(f"  latency {clients} client(s): p50 {row['p50_ms']:.0f} ms  p95 {row['p95_ms']:.0f} ms", file=sys.stderr)
        if args.soak > 0:
            result["soak"] = soak(url, "demo", summary, args.soak)
            print(f"  soak: {result['soak']['requests']} requests, {result['soak']['errors']} errors", file=sys.stderr)
    finally:
        serve.stop()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--source", help="volume file to ingest (default: the demo volume of `lodcast demo`)")
    ap.add_argument("--size", type=int, default=512, help="render size for the latency runs (default 512)")
    ap.add_argument("--requests", type=int, default=24, help="requests per concurrency level (default 24)")
    ap.add_argument("--frame-size", type=int, default=256, help="frame size of the throughput jobs (default 256)")
    ap.add_argument("--jobs", type=int, default=4, help="turntable jobs per throughput run (default 4)")
    ap.add_argument("--frames", type=int, default=8, help="frames per job (default 8)")
    ap.add_argument("--soak", type=float, default=0.0, help="also run 8 clients for this many seconds (e.g. 30)")
    ap.add_argument("--render-concurrency", type=int, default=2)
    ap.add_argument("--no-latency", action="store_true", help="skip the latency runs (and the soak)")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "bench_service.json"))
    args = ap.parse_args(argv)

    with tempfile.TemporaryDirectory(prefix="lodcast-bench-") as tmp:
        tmpd = Path(tmp)
        root = tmpd / "root"
        root.mkdir()
        logs = Path(args.out).parent / "bench_service_logs"  # kept after the run (server and worker logs)
        shutil.rmtree(logs, ignore_errors=True)
        logs.mkdir(parents=True)
        if args.source:
            src, label = Path(args.source), Path(args.source).name
        else:
            from lodcast.service.demo import fetch_demo_volume

            demo = fetch_demo_volume()
            src, label = demo.path, demo.description
        t0 = time.perf_counter()
        store = lodcast.ingest(src, root / "demo")
        summary = store.summary()
        print(f"volume: {label}  shape {summary['shape']}  (ingest {time.perf_counter() - t0:.1f} s)", file=sys.stderr)

        result: dict = {"volume": label, "shape": summary["shape"], "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
                        "render_concurrency": args.render_concurrency, "latency": [], "throughput": []}
        if not args.no_latency:
            run_latency(args, root, summary, logs, result)

        redis = None
        queues: list[str | None] = [None]
        if redis_available():
            redis = RedisServer(tmpd / "redis")
            queues.append(redis.url)
        else:
            result["redis"] = "redis-server not installed: Redis rows skipped"
        try:
            for q in queues:
                for workers in (1, 2):
                    row = throughput(root, "demo", summary, q, workers, args.jobs, args.frames, args.frame_size, logs)
                    result["throughput"].append(row)
                    print(f"  throughput {row['queue']} x{workers}: {row['frames_per_s']:.2f} frames/s", file=sys.stderr)
        finally:
            if redis is not None:
                redis.stop()

    print(f"\nService benchmark: {result['volume']}, shape {result['shape']}, device {result.get('device')}, "
          f"{result['machine']['cpus']} CPUs, render concurrency {args.render_concurrency}")
    print(f"\nRender latency at {args.size}x{args.size}")
    print(f"{'clients':>8} {'requests':>9} {'errors':>7} {'p50 ms':>9} {'p95 ms':>9} {'renders/s':>10}")
    for r in result["latency"]:
        print(f"{r['clients']:>8} {r['requests']:>9} {r['errors']:>7} {r['p50_ms']:>9.0f} {r['p95_ms']:>9.0f} {r['renders_per_s']:>10.2f}")
    print(f"\nJob throughput ({args.jobs} turntable jobs x {args.frames} frames at {args.frame_size}x{args.frame_size})")
    print(f"{'queue':>8} {'workers':>8} {'frames':>7} {'seconds':>8} {'frames/s':>9}")
    for r in result["throughput"]:
        print(f"{r['queue']:>8} {r['workers']:>8} {r['frames']:>7} {r['seconds']:>8.1f} {r['frames_per_s']:>9.2f}")
    if "soak" in result:
        s = result["soak"]
        print(f"\nSoak: {s['clients']} clients x {s['seconds']:.0f} s at {s['size']}²: {s['requests']} requests, {s['errors']} errors")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print("\n" + json.dumps(result))
    bad = sum(r["errors"] for r in result["latency"]) + result.get("soak", {}).get("errors", 0) + sum(
        r["jobs"] - r["jobs_done"] for r in result["throughput"])
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
