"""`/healthz` latency while 8 clients render continuously (issue 49, item 2).

A real `lodcast serve` process on loopback (SQLite queue, one in-process worker, the default render slots) serves a
96³ head phantom; 8 client threads each post renders one after another (mixed sizes: 128², 256², 384², 512²), while a
probe, in a process of its own, asks `GET /healthz` every `--every` seconds. Prints the probe's latency (median, p95,
p99, max, the count over 100 ms) and the renders answered by status, and writes JSON with the date, machine and
command. A control probe, alternating with it, asks a plain Python HTTP server in a process of its own for a small
file: what the machine's scheduling alone costs a probe under the same load.

    python benchmarks/bench_healthz.py --seconds 60 --json docs/measurements/healthz_load.json
"""
from __future__ import annotations

import argparse
import collections
import datetime
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
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from phantoms import head  # noqa: E402

import lodcast  # noqa: E402
from lodcast.service.testing import free_port, running, start_serve  # noqa: E402

TF = {"points": [{"value": 0, "color": [1, 1, 1], "opacity": 0.0}, {"value": 200, "color": [1, 0.8, 0.6], "opacity": 0.05}]}
SIZES = (128, 256, 384, 512)


def scene(k: int, size: int) -> dict:
    return {"camera": {"azimuth": (37 * k) % 360, "elevation": 15, "distance": 2.5}, "width": size, "height": size,
            "tf": TF, "sampling": {"step": 0.5}}


def probe(base: str, control: str, seconds: float, every: float) -> None:
    """`--probe`: GET /healthz and the control's file in turn for `seconds`; prints their latencies (s) as JSON."""
    lat, ctl, codes = [], [], collections.Counter()
    with httpx.Client(base_url=base, timeout=30) as c, httpx.Client(timeout=30) as other:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            t = time.perf_counter()
            r = c.get("/healthz")
            lat.append(time.perf_counter() - t)
            codes[str(r.status_code)] += 1
            time.sleep(every / 2)
            t = time.perf_counter()
            other.get(control)
            ctl.append(time.perf_counter() - t)
            time.sleep(every / 2)
    print(json.dumps({"healthz": lat, "control": ctl, "status": codes}))


def main() -> None:
    if sys.argv[1:2] == ["--probe"]:
        base, control, seconds, every = sys.argv[2:6]
        probe(base, control, float(seconds), float(every))
        return
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--clients", type=int, default=8)
    ap.add_argument("--every", type=float, default=0.05, help="seconds between probes")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "root"
        root.mkdir()
        lodcast.ingest(head(96), root / "head", progress=False)
        port = free_port()
        base = f"http://127.0.0.1:{port}"
        server = start_serve(root, port, log=Path(tmp) / "serve.log")
        with running(server):
            with httpx.Client(base_url=base, timeout=120) as c:  # kernels built, bricks read before the clock
                for size in SIZES:
                    c.post("/volumes/head/render", json=scene(0, size)).raise_for_status()
            stop = threading.Event()
            codes: collections.Counter[int] = collections.Counter()
            lock = threading.Lock()

            def client(i: int) -> None:
                with httpx.Client(base_url=base, timeout=300) as c:
                    k = i
                    while not stop.is_set():
                        r = c.post("/volumes/head/render", json=scene(k, SIZES[k % len(SIZES)]))
                        with lock:
                            codes[r.status_code] += 1
                        k += args.clients

            threads = [threading.Thread(target=client, args=(i,)) for i in range(args.clients)]
            for t in threads:
                t.start()
            (Path(tmp) / "static").mkdir()
            (Path(tmp) / "static" / "ok.txt").write_text("ok")
            cport = free_port()
            control = subprocess.Popen([sys.executable, "-m", "http.server", str(cport), "--bind", "127.0.0.1",
                                        "--directory", str(Path(tmp) / "static")], stdout=subprocess.DEVNULL,
                                       stderr=subprocess.DEVNULL)
            time.sleep(3.0)  # every client has a render in flight
            try:  # the probe in a process of its own: the clients' threads here would delay its answers
                out = subprocess.run([sys.executable, __file__, "--probe", base, f"http://127.0.0.1:{cport}/ok.txt",
                                      str(args.seconds), str(args.every)], capture_output=True, text=True, check=True)
                seen = json.loads(out.stdout)
            finally:
                control.terminate()
                control.wait()
            stop.set()
            for t in threads:
                t.join()
    lat, ctl = np.array(seen["healthz"]) * 1e3, np.array(seen["control"]) * 1e3

    def stats(x: np.ndarray) -> dict[str, float]:
        return {"median": round(float(np.median(x)), 1), "p95": round(float(np.percentile(x, 95)), 1),
                "p99": round(float(np.percentile(x, 99)), 1), "max": round(float(x.max()), 1),
                "over_100ms": int((x > 100).sum())}

    out = {"date": datetime.date.today().isoformat(),
           "machine": f"{platform.node()} ({os.cpu_count()} CPUs, {platform.processor() or platform.machine()})",
           "command": " ".join([Path(sys.argv[0]).as_posix(), *sys.argv[1:]]), "clients": args.clients,
           "seconds": args.seconds, "probes": len(lat), "probe_status": seen["status"],
           "healthz_ms": stats(lat), "control_ms": stats(ctl),
           "renders": {str(k): v for k, v in sorted(codes.items())}}
    print(json.dumps(out, indent=1))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
