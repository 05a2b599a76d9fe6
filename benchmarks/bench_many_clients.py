"""Many volumes, many clients (issue 44 item 6): 4 clients orbiting 2 large volumes through one `lodcast serve`.

    .venv/bin/python benchmarks/bench_many_clients.py [--root DIR] [--volumes a,b] [--seconds 60] [--size 256]
    .venv/bin/python benchmarks/bench_many_clients.py --shape 256,512,512     # makes its two volumes first

A real `lodcast serve` process on loopback (no job workers), its caches bounded (LODCAST_BRICK_CACHE_MB,
LODCAST_DEVICE_CACHE_MB, LODCAST_OPEN_STORES), serves two volumes: those named in `--volumes` under `--root`, else
two made with bench_large_volume.py's `make` (the chest CT tiled, two different shapes) and ingested into a
temporary root. Each volume is rendered once first (kernel build, first image). Then `--clients-per-volume`
client threads per volume each orbit their volume (a new azimuth every frame, `ct-bone`, 30:1) for `--seconds`,
one request at a time, as a viewer does.

Per client: frames, p50 / p95 / max / mean latency, bricks read after its first frame. Fairness, the design's
"without one starving the others": each client's p95 ≤ 2 × the best client's p95. The server's resident memory is
sampled from /proc every half second against the cache bounds it was given: a bound that did not hold shows as a
resident set that grows past them with time, while a steady one is the bounds plus the process's own baseline.

Writes JSON (`--json`) and prints a markdown table.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_service import pct  # noqa: E402


def scene(azimuth: float, size: int, reduction: float) -> dict:
    return {"camera": {"azimuth": azimuth, "elevation": 15}, "width": size, "height": size, "tf": "ct-bone",
            "quality": {"reduction": reduction}}


def make_volumes(root: Path, shape: tuple[int, int, int]) -> list[str]:
    """Two volumes of about `shape` (the second 1/8 deeper, so that they differ) ingested under `root`."""
    from bench_large_volume import make

    from lodcast.service.cli import main as cli

    names = []
    for i, depth in enumerate((shape[0], shape[0] + shape[0] // 8)):
        name = f"body{i}_{depth}x{shape[1]}x{shape[2]}"
        raw = root.parent / f"{name}.npy"
        make(raw, (depth, shape[1], shape[2]))
        if cli(["ingest", str(raw), str(root / name), "--spacing", "1.0,0.78125,0.78125", "--no-progress"]):
            raise SystemExit(f"ingest of {raw} failed")
        raw.unlink()
        names.append(name)
    return names


def status_kb(pid: int, key: str) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def orbit(url: str, volume: str, client: int, start: float, end: float, size: int, reduction: float,
          out: dict, t_zero: float) -> None:
    """One viewer: from `start`, requests one after another until `end`, each frame 3° further round (each
    frame's send time kept in seconds since `t_zero`)."""
    lat, bricks, errors, waits, sent = [], [], [], [], []
    az = 37.0 * client
    with httpx.Client(base_url=url, timeout=600) as c:
        while time.monotonic() < start:
            time.sleep(0.001)
        while time.monotonic() < end:
            t0 = time.perf_counter()
            at = time.monotonic() - t_zero
            try:
                r = c.post(f"/volumes/{volume}/render", json=scene(az, size, reduction))
            except httpx.HTTPError as exc:
                errors.append(repr(exc))
                continue
            dt = time.perf_counter() - t0
            if r.status_code != 200:
                errors.append(f"{r.status_code}: {r.text[:200]}")
                continue
            rep = json.loads(r.headers["x-lodcast-report"])
            lat.append(dt)
            sent.append(round(at, 3))
            bricks.append(int(rep.get("bricks_read", 0)))
            waits.append(dt * 1e3 - float(rep.get("wall_ms", 0.0)))  # queueing and HTTP: the latency not rendering
            az += 3.0
    out.update(volume=volume, client=client, latencies_ms=[x * 1e3 for x in lat], bricks_read=bricks,
               errors=errors, outside_render_ms=waits, sent_s=sent)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, help="store root holding the volumes (default: make two, see --shape)")
    ap.add_argument("--volumes", default="", help="two volume ids under --root, comma-separated")
    ap.add_argument("--shape", default="256,512,512", help="shape z,y,x of the volumes to make without --root")
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--reduction", type=float, default=30.0)
    ap.add_argument("--clients-per-volume", type=int, default=2)
    ap.add_argument("--brick-cache-mb", type=int, default=512)
    ap.add_argument("--device-cache-mb", type=int, default=256)
    ap.add_argument("--open-stores", type=int, default=2)
    ap.add_argument("--render-concurrency", type=int, default=2)
    ap.add_argument("--small-render-samples", type=int, default=None,
                    help="LODCAST_SMALL_RENDER_SAMPLES for the server (default: its own; 0: every render takes a "
                         "main slot)")
    ap.add_argument("--join-after", type=float, default=0.0,
                    help="the second volume's clients join this many seconds after the first's, that volume not "
                         "rendered before (cold): what its first frames cost the others")
    ap.add_argument("--json", type=Path, default=HERE / "results" / "many_clients.json")
    args = ap.parse_args(argv)

    from lodcast.service.testing import free_port, start_serve

    with tempfile.TemporaryDirectory(prefix="lodcast-many-") as tmp:
        tmpd = Path(tmp)
        if args.root is None:
            root = tmpd / "root"
            root.mkdir()
            volumes = make_volumes(root, tuple(int(n) for n in args.shape.split(",")))  # type: ignore[arg-type]
        else:
            root, volumes = args.root, [v for v in args.volumes.split(",") if v]
            if len(volumes) != 2:
                raise SystemExit("--volumes: name two volumes under --root")
        env = {"LODCAST_TOKEN": "", "LODCAST_STATE_ROOT": str(tmpd / "state"),
               "LODCAST_BRICK_CACHE_MB": str(args.brick_cache_mb), "LODCAST_DEVICE_CACHE_MB": str(args.device_cache_mb),
               "LODCAST_OPEN_STORES": str(args.open_stores),
               "LODCAST_RENDER_CONCURRENCY": str(args.render_concurrency),
               **({} if args.small_render_samples is None
                  else {"LODCAST_SMALL_RENDER_SAMPLES": str(args.small_render_samples)})}
        port = free_port()
        log = tmpd / "serve.log"
        serve = start_serve(root, port, env=env, log=log, extra=["--workers", "0"])
        url = f"http://127.0.0.1:{port}"
        result: dict = {
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE, capture_output=True,
                                     text=True).stdout.strip(),
            "command": " ".join([Path(sys.executable).name, *sys.argv]),
            "machine": {"cpus": len(os.sched_getaffinity(0)), "cpu": cpu_model(), "python": platform.python_version(),
                        "load_average_before": os.getloadavg()},
            "settings": {k: v for k, v in env.items() if k != "LODCAST_TOKEN" and k != "LODCAST_STATE_ROOT"},
            "seconds": args.seconds, "size": args.size, "reduction": args.reduction, "volumes": {}, "clients": []}
        try:
            with httpx.Client(base_url=url, timeout=900) as c:
                for v in volumes[:1] if args.join_after > 0 else volumes:
                    info = c.get(f"/volumes/{v}").json()
                    t0 = time.perf_counter()
                    r = c.post(f"/volumes/{v}/render", json=scene(0.0, args.size, args.reduction))
                    r.raise_for_status()
                    rep = json.loads(r.headers["x-lodcast-report"])
                    result["volumes"][v] = {"shape": info.get("shape"), "bytes_on_disk": info.get("bytes_on_disk"),
                                            "first_ms": (time.perf_counter() - t0) * 1e3,
                                            "first_bricks_read": rep.get("bricks_read")}
                    result["device"] = rep.get("device")
                    print(f"{v}: shape {info.get('shape')}, first image {result['volumes'][v]['first_ms']:.0f} ms",
                          file=sys.stderr)
            rss_base = status_kb(serve.pid, "VmRSS")
            rss: list[tuple[float, int]] = []
            n = 2 * args.clients_per_volume
            start = time.monotonic() + 0.5
            end = start + args.seconds
            outs: list[dict] = [{} for _ in range(n)]
            threads = [threading.Thread(target=orbit, args=(url, volumes[i % 2], i, start + (i % 2) * args.join_after,
                                                            end, args.size, args.reduction, outs[i], start))
                       for i in range(n)]
            for t in threads:
                t.start()
            while any(t.is_alive() for t in threads):
                rss.append((time.monotonic() - start, status_kb(serve.pid, "VmRSS")))
                time.sleep(0.5)
            for t in threads:
                t.join()
            hwm = status_kb(serve.pid, "VmHWM")
        finally:
            serve.stop()
            result["serve_log_tail"] = log.read_text(errors="replace")[-2000:] if log.exists() else ""

    for o in outs:
        lat = o["latencies_ms"]
        o.update(frames=len(lat), p50_ms=pct(lat, 0.5), p95_ms=pct(lat, 0.95), max_ms=max(lat, default=float("nan")),
                 mean_ms=sum(lat) / len(lat) if lat else float("nan"),
                 bricks_read_after_first=sum(o["bricks_read"][1:]),
                 outside_render_p50_ms=pct(o["outside_render_ms"], 0.5))
        result["clients"].append(o)
    p95s = [o["p95_ms"] for o in outs]
    half = [v for t, v in rss if t >= args.seconds / 2]
    result["fairness"] = {"worst_p95_over_best": max(p95s) / min(p95s),
                          "frames_min_over_max": min(o["frames"] for o in outs) / max(o["frames"] for o in outs),
                          "holds": max(p95s) <= 2 * min(p95s) and all(o["frames"] > 0 for o in outs)}
    if args.join_after > 0:  # the cold volume's first frames: from its clients' joining until both have one
        joined = max(o["sent_s"][0] + o["latencies_ms"][0] / 1e3 for o in outs[1::2] if o["sent_s"])
        during = {o["client"]: [ms for t, ms in zip(o["sent_s"], o["latencies_ms"])
                                if t < joined and t + ms / 1e3 > args.join_after] for o in outs[0::2]}
        result["join"] = {"after_s": args.join_after, "cold_first_frames_ms": [o["latencies_ms"][:1] for o in outs[1::2]],
                          "until_s": joined, "warm_clients_frames_during": {k: len(v) for k, v in during.items()},
                          "warm_clients_max_ms_during": {k: max(v, default=float("nan")) for k, v in during.items()}}
    result["memory"] = {"rss_after_warmup_mib": rss_base / 1024, "rss_max_mib": max(v for _, v in rss) / 1024,
                        "rss_first_half_max_mib": max((v for t, v in rss if t < args.seconds / 2), default=0) / 1024,
                        "rss_second_half_max_mib": max(half, default=0) / 1024, "vm_hwm_mib": hwm / 1024,
                        "cache_bounds_mib": args.brick_cache_mb + args.device_cache_mb,
                        "samples_s_mib": [(round(t, 1), round(v / 1024, 1)) for t, v in rss]}
    result["machine"]["load_average_after"] = os.getloadavg()
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1))
    print(table(result))
    return 0


def table(res: dict) -> str:
    rows = ["| client | volume | frames | p50 ms | p95 ms | max ms | mean ms | outside the render, p50 ms | "
            "bricks read after its first frame | errors |", "|---|---|---|---|---|---|---|---|---|---|"]
    for o in res["clients"]:
        rows.append(f"| {o['client']} | {o['volume']} | {o['frames']} | {o['p50_ms']:.0f} | {o['p95_ms']:.0f} | "
                    f"{o['max_ms']:.0f} | {o['mean_ms']:.0f} | {o['outside_render_p50_ms']:.0f} | "
                    f"{o['bricks_read_after_first']} | {len(o['errors'])} |")
    f, m = res["fairness"], res["memory"]
    rows.append("")
    rows.append(f"worst p95 / best p95 = {f['worst_p95_over_best']:.2f} (holds: {f['holds']}); fewest frames / most "
                f"= {f['frames_min_over_max']:.2f}")
    rows.append(f"server RSS: {m['rss_after_warmup_mib']:.0f} MiB after the first images, max {m['rss_max_mib']:.0f} MiB "
                f"(first half {m['rss_first_half_max_mib']:.0f}, second half {m['rss_second_half_max_mib']:.0f}), "
                f"VmHWM {m['vm_hwm_mib']:.0f} MiB; cache bounds {m['cache_bounds_mib']} MiB")
    j = res.get("join")
    if j:
        rows.append(f"the second volume's clients joined at {j['after_s']:g} s, cold: first frames "
                    f"{', '.join(f'{x[0]:.0f}' for x in j['cold_first_frames_ms'] if x)} ms, both done at "
                    f"{j['until_s']:.1f} s; meanwhile the first volume's clients got "
                    f"{', '.join(str(n) for n in j['warm_clients_frames_during'].values())} frames, the slowest "
                    f"{', '.join(f'{x:.0f}' for x in j['warm_clients_max_ms_during'].values())} ms")
    return "\n".join(rows)


if __name__ == "__main__":
    sys.exit(main())
