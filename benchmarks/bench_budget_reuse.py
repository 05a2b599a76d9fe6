"""Budgets that reuse, not re-read (issue 44 items 2 and 4): one store, two versions of the code, in alternating
processes on the same machine.

    .venv/bin/python benchmarks/bench_budget_reuse.py STORE --base DIR [--pairs 3] [--json docs/measurements/budget_reuse.json]

STORE: a lodcast store (benchmarks/bench_large_volume.py makes one: --shape 550,1024,1024 is the 1.15 GB volume).
DIR: a checkout of the code to compare with (`git archive <commit> | tar -x -C DIR`); each process imports lodcast
from DIR ("before") or from this tree ("after"), alternately, `--pairs` times. Each process, 512², ct-bone:
- full resolution unbudgeted (brick pool 4096 MiB), the second frame (level 0 on the device);
- full resolution with LODCAST_DEVICE_BUDGET_MB=256 (a Renderer of its own, brick pool 4096 MiB): two frames,
  wall ms, bricks read and found, passes, and whether the image equals the unbudgeted one;
- then on that renderer 30:1 and full alternated twice: bricks read per frame (a shared pool reads nothing);
- the memory-copy rate (a 256 MB np.copyto, best of three), for DESIGN.md's CPU-device bound:
  2 × (unbudgeted wall + level-0 bytes ÷ copy rate);
- four new views 2° apart at 30:1 with the selection weighed by the view (lod_visibility on): wall ms and bricks
  read per view.
Prints a table, writes JSON and the table beside it (.md).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
SIZE = 512


def _use(code: Path) -> None:
    """Import lodcast from `code` instead of this tree (the editable install's finder maps package to folder)."""
    import importlib

    finder = importlib.import_module("__editable___lodcast_0_1_0_finder")
    for name, path in list(finder.MAPPING.items()):
        finder.MAPPING[name] = path.replace(str(ROOT), str(code))


def _ms(f):  # noqa: ANN001, ANN202
    t = time.perf_counter()
    r = f()
    return (time.perf_counter() - t) * 1e3, r


def measure(store_path: str) -> dict:
    import lodcast

    st = lodcast.open_store(store_path)
    base = {"tf": "ct-bone", "width": SIZE, "height": SIZE, "format": "npy", "camera": {"azimuth": 30, "elevation": 15}}
    full, coarse = {**base, "quality": "full"}, {**base, "quality": {"reduction": 30}}
    out: dict = {}
    eng = lodcast.Renderer(brick_cache_mb=4096)
    eng.render(st, full)
    ms, ref = _ms(lambda: eng.render(st, full))
    out["unbudgeted_ms"] = ms
    views = []
    for i in range(4):
        sc = {**coarse, "camera": {"azimuth": 40 + 2 * i, "elevation": 15}, "sampling": {"lod_visibility": True}}
        ms, r = _ms(lambda: eng.render(st, sc))
        views.append({"ms": ms, "bricks_read": r.report["bricks_read"]})
    out["new_views_visibility"] = views
    eng.close()  # its caches go: the process holds one brick pool's worth, as with one renderer
    bud = lodcast.Renderer(brick_cache_mb=4096, device_budget_mb=256)
    frames = []
    for _ in range(2):
        ms, r = _ms(lambda: bud.render(st, full))
        frames.append({"ms": ms, "bricks_read": r.report["bricks_read"], "bricks_cached": r.report["bricks_cached"],
                       "passes": r.report["passes"], "same_image": bool(np.array_equal(r.rgba, ref.rgba))})
    out["budgeted_full"] = frames
    alt = []
    for sc in (coarse, full, coarse, full):
        ms, r = _ms(lambda: bud.render(st, sc))
        alt.append({"quality": "30:1" if sc is coarse else "full", "ms": ms, "bricks_read": r.report["bricks_read"]})
    out["alternating"] = alt
    a = np.ones(256_000_000, np.uint8)
    b = np.empty_like(a)
    out["copy_gb_s"] = max(a.nbytes / 1e9 / (_ms(lambda: np.copyto(b, a))[0] / 1e3) for _ in range(3))
    out["level0_bytes"] = int(np.prod(st.shape)) * 2
    return out


def table(runs: dict) -> str:
    def med(side: str, f) -> float:  # noqa: ANN001
        return float(np.median([f(r) for r in runs[side]]))

    rows = [
        ("full unbudgeted, warm (ms)", lambda r: r["unbudgeted_ms"]),
        ("full, 256 MB budget, frame 1 (ms)", lambda r: r["budgeted_full"][0]["ms"]),
        ("full, 256 MB budget, frame 2 (ms)", lambda r: r["budgeted_full"][1]["ms"]),
        ("  bricks read, frame 2", lambda r: r["budgeted_full"][1]["bricks_read"]),
        ("  bound 2 × (unbudgeted + level 0 ÷ copy rate) (ms)",
         lambda r: 2 * (r["unbudgeted_ms"] + r["level0_bytes"] / (r["copy_gb_s"] * 1e9) * 1e3)),
        ("  passes", lambda r: r["budgeted_full"][1]["passes"]),
        ("  image equals the unbudgeted one (1 = yes)", lambda r: float(r["budgeted_full"][1]["same_image"])),
        ("alternating 30:1 ↔ full, second round: bricks read", lambda r: sum(f["bricks_read"] for f in r["alternating"][2:])),
        ("alternating, second round 30:1 (ms)", lambda r: r["alternating"][2]["ms"]),
        ("alternating, second round full (ms)", lambda r: r["alternating"][3]["ms"]),
        ("new view 30:1, lod_visibility on (ms, median of 4)", lambda r: float(np.median([v["ms"] for v in r["new_views_visibility"]]))),
        ("  bricks read per new view", lambda r: float(np.mean([v["bricks_read"] for v in r["new_views_visibility"]]))),
    ]
    lines = ["| figure (median over processes) | before | after |", "|---|---|---|"]
    for name, f in rows:
        lines.append(f"| {name} | {med('before', f):.0f} | {med('after', f):.0f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("store")
    ap.add_argument("--base", type=Path)
    ap.add_argument("--pairs", type=int, default=3)
    ap.add_argument("--json", type=Path, default=ROOT / "docs" / "measurements" / "budget_reuse.json")
    ap.add_argument("--child", choices=["before", "after"], help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        if a.child == "before":
            _use(a.base)
        print(json.dumps(measure(a.store)))
        return
    runs: dict = {"before": [], "after": []}
    for i in range(a.pairs):
        for side in ("before", "after") if i % 2 == 0 else ("after", "before"):
            p = subprocess.run([sys.executable, __file__, a.store, "--base", str(a.base), "--child", side],
                               capture_output=True, text=True, env={**os.environ, "LODCAST_BRICK_CACHE_MB": "4096"})
            if p.returncode:
                raise SystemExit(p.stderr[-3000:])
            runs[side].append(json.loads(p.stdout.strip().splitlines()[-1]))
            print(side, runs[side][-1], flush=True)
    cpu = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                if ln.startswith("model name")), platform.processor())
    res = {"date": time.strftime("%Y-%m-%d"), "nproc": os.cpu_count(), "cpu": cpu, "command": " ".join(sys.argv),
           "store": a.store, "runs": runs, "table": table(runs)}
    print(res["table"])
    a.json.write_text(json.dumps(res, indent=2))
    a.json.with_suffix(".md").write_text(f"{res['date']}, {cpu}, nproc {res['nproc']}\n\n`{res['command']}`\n\n"
                                         f"{res['table']}\n")


if __name__ == "__main__":
    main()
