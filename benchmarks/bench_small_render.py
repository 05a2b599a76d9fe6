"""A 32² render's wait with three big renders in flight on the same device (issue 49, item 4).

Three threads render big frames (768², step 0.1, full resolution) one after another on one Renderer; meanwhile a
32² render is timed `--tries` times. Prints the small render's wait alone and beside the big ones (median, p95,
max) and writes JSON with the date, machine and command.

    python benchmarks/bench_small_render.py --tries 20 --json docs/measurements/small_render.json
    python benchmarks/bench_small_render.py --tries 20 --before --json docs/measurements/small_render_before.json
"""
from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import os
import platform
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Iterator

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from phantoms import head  # noqa: E402

import lodcast  # noqa: E402
from lodcast.renderer.frame.render import Renderer, Turns  # noqa: E402

TF = {"points": [{"value": 0, "color": [1, 1, 1], "opacity": 0.0}, {"value": 200, "color": [1, 0.8, 0.6], "opacity": 0.05}]}
BIG = {"camera": {"azimuth": 30, "elevation": 10, "distance": 2.5}, "width": 768, "height": 768, "tf": TF,
       "quality": "full", "sampling": {"step": 0.1, "early_termination": 1.0}}
SMALL = {**BIG, "width": 32, "height": 32, "sampling": {"step": 0.5}}


class NoTurns(Turns):
    """--before: a small render holds nothing back."""

    @contextlib.contextmanager
    def small(self) -> Iterator[None]:
        yield


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tries", type=int, default=20)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--before", action="store_true", help="launch as before the turns (renderer/frame/render.py: "
                    "Turns): bands of 2·10⁷ samples, none taking turns, to measure before and after alike")
    args = ap.parse_args()
    if args.before:
        import lodcast.renderer.frame.render as R

        R.BAND_SAMPLES = 20_000_000
        real_launch = R.launch
        R.launch = lambda *a, **k: real_launch(*a, **{**k, "turns": None})  # type: ignore[assignment]
    with tempfile.TemporaryDirectory() as tmp:
        store = lodcast.ingest(head(96), Path(tmp) / "head.zarr", progress=False)
        eng = Renderer()
        if args.before:
            eng.turns = NoTurns()
        eng.render(store, BIG)
        alone = []
        for _ in range(args.tries):
            t = time.perf_counter()
            eng.render(store, SMALL)
            alone.append(time.perf_counter() - t)
        stop, big_s = threading.Event(), []

        def big() -> None:
            while not stop.is_set():
                t = time.perf_counter()
                eng.render(store, BIG)
                big_s.append(time.perf_counter() - t)

        threads = [threading.Thread(target=big) for _ in range(3)]
        for t in threads:
            t.start()
        time.sleep(2.0)
        beside = []
        for _ in range(args.tries):
            t = time.perf_counter()
            eng.render(store, SMALL)
            beside.append(time.perf_counter() - t)
            time.sleep(0.2)
        stop.set()
        for t in threads:
            t.join()
        eng.close()

    def stats(xs: list[float]) -> dict[str, float]:
        a = np.array(xs) * 1e3
        return {"median_ms": round(float(np.median(a)), 1), "p95_ms": round(float(np.percentile(a, 95)), 1),
                "max_ms": round(float(a.max()), 1)}

    out = {"date": datetime.date.today().isoformat(), "machine": f"{platform.node()} ({os.cpu_count()} CPUs, "
           f"{platform.processor() or platform.machine()})", "command": " ".join([Path(sys.argv[0]).as_posix(), *sys.argv[1:]]),
           "tries": args.tries, "launch": "before the turns" if args.before else "turns",
           "small_alone": stats(alone), "small_beside_three_big": stats(beside),
           "big_render_s_median": round(float(np.median(big_s)), 2) if big_s else None, "big_renders": len(big_s)}
    print(json.dumps(out, indent=1))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
