"""The host's share of a large volume's warm frame (issue 44 item 2: host time of a warm frame <= 25 % of its wall
time), old and new alternating.

    .venv/bin/python benchmarks/bench_warm_host.py [--store benchmarks/results/large/body_1024x4096x4096.zarr]
        [--base OTHER/.venv/bin/python] [--pairs 3] [--frames 12] [--json docs/measurements/warm_host.json]

Per pair, each tree in a fresh process (the order alternates: the base first in even pairs, this tree first in odd
ones), at the scaling benchmark's budgets (LODCAST_BRICK_CACHE_MB=1024, LODCAST_DEVICE_BUDGET_MB=512): the store
opened and its first image rendered (not timed; the page cache is left as it is), then a turntable of `frames`
frames 2° apart at `"quality": {"budget_mb": 256}`, ct-bone, 512² (the selection does not depend on the view: the
frames read nothing and differ in the camera only). Per process the median wall ms, kernel ms and host ms (wall
less kernel) of the frames. `--base` is a Python whose `lodcast` is the code to compare with (another checkout's
virtual environment). Prints a table with the median ratios new ÷ base and their bootstrap 95 % intervals over the
pairs, and writes JSON and the table beside it (.md).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from bench_large_volume import LARGE  # noqa: E402
from record import alternating, base_revision, bootstrap, provenance, write_result  # noqa: E402

ENV = {"LODCAST_BRICK_CACHE_MB": "1024", "LODCAST_DEVICE_BUDGET_MB": "512"}
SCENE = {"tf": "ct-bone", "width": 512, "height": 512, "format": "npy", "quality": {"budget_mb": 256}}


def frames_step(store: str, frames: int) -> None:
    """Runs in the child: the first image, then the turntable's frames; one JSON line."""
    import time

    from lodcast.renderer.frame.render import Renderer

    r = Renderer()
    r.render(store, {**SCENE, "camera": {"azimuth": 0, "elevation": 15}})
    wall, kernel = [], []
    for i in range(1, frames + 1):
        t = time.perf_counter()
        rep = r.render(store, {**SCENE, "camera": {"azimuth": 2 * i, "elevation": 15}}).report
        wall.append((time.perf_counter() - t) * 1e3)
        kernel.append(float(rep["kernel_ms"]))
        assert rep["bricks_read"] == 0, rep["bricks_read"]
    w, k = np.array(wall), np.array(kernel)
    print(json.dumps({"wall_ms": float(np.median(w)), "kernel_ms": float(np.median(k)),
                      "host_ms": float(np.median(w - k)), "host_share": float(np.median((w - k) / w))}))


def child(python: str, store: Path, frames: int) -> dict:
    p = subprocess.run([python, __file__, "--frames-step", str(store), "--frames", str(frames)], capture_output=True,
                       text=True, env={**os.environ, **ENV})
    if p.returncode:
        raise SystemExit(f"{python} failed:\n{p.stderr[-3000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def table(res: dict) -> str:
    pairs = res["pairs"]
    lines = [f"Warm turntable frames, {res['store']}, 512², ct-bone, budget_mb 256, {res['frames']} frames per "
             f"process, medians per process. {res['date']}, {res['machine']}, base {res['base']} against this tree "
             f"{res['commit']}; `{res['command']}`", "",
             "| pair | order | base wall / kernel / host ms | this tree wall / kernel / host ms | host share base → this "
             "| load avg (1 min) |", "|---|---|---|---|---|---|"]
    for i, p in enumerate(pairs):
        o, n = p.get("base"), p["new"]
        this = f"{n['wall_ms']:.0f} / {n['kernel_ms']:.0f} / {n['host_ms']:.0f}"
        if o:
            lines.append(f"| {i} | {p['order']} | {o['wall_ms']:.0f} / {o['kernel_ms']:.0f} / {o['host_ms']:.0f} | "
                         f"{this} | {o['host_share']:.0%} → {n['host_share']:.0%} | {p['load']:.1f} |")
        else:
            lines.append(f"| {i} | new | - | {this} | {n['host_share']:.0%} | {p['load']:.1f} |")
    if pairs and pairs[0].get("base"):
        lines.append("")
        for what in ("wall_ms", "host_ms"):
            r = np.array([p["new"][what] / p["base"][what] for p in pairs])
            lo, hi = bootstrap(r)
            lines.append(f"- {what.replace('_ms', '')} ms, this tree ÷ base: median {np.median(r):.2f} "
                         f"(95 % interval {lo:.2f}–{hi:.2f}, {r.size} pairs)")
    share = float(np.median([p["new"]["host_share"] for p in pairs]))
    lines.append(f"- host share of a warm frame, this tree: median {share:.0%} (target ≤ 25 %)")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", type=Path, default=LARGE / "body_1024x4096x4096.zarr")
    ap.add_argument("--base", help="a Python whose lodcast is the code to compare with")
    ap.add_argument("--pairs", type=int, default=3)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--json", type=Path, default=ROOT / "docs" / "measurements" / "warm_host.json")
    ap.add_argument("--frames-step", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.frames_step:
        return frames_step(a.frames_step, a.frames)
    store = a.store.resolve()
    if not store.exists():
        raise SystemExit(f"{store}: no such store (make it with benchmarks/bench_scaling.py)")
    pairs = alternating(a.pairs, lambda who: child(a.base if who == "base" else sys.executable, store, a.frames),
                        bool(a.base))
    res = {**provenance("bench_warm_host.py"), "store": store.name, "frames": a.frames,
           "base": base_revision(a.base), "pairs": pairs}
    res["table"] = table(res)
    write_result(a.json, res)


if __name__ == "__main__":
    main()
