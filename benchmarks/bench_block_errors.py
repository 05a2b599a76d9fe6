"""The level-of-detail selection's per-block TF errors (level_error.block_zetas) on the device against NumPy.

    .venv/bin/python benchmarks/bench_block_errors.py [--store benchmarks/results/large/body_1024x2048x2048.zarr]
        [--rounds 3] [--json benchmarks/results/block_errors.json]

A large volume's first image, and every TF change after it, computes every visible block's error at every level.
Per classification ("distribution", "mean") and with or without the worst values ("lossless" needs them): the
NumPy path (a Tables without a device) and the engine's device (zeta.cl) alternate `rounds` times in one process
on the same store and TF (ct-bone), each timed whole (wall seconds, host gathers included), with the largest
difference between their outputs. Prints a table and writes JSON.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

import lodcast
from lodcast.renderer.engine import Tables
from lodcast.renderer.lod.level_error import block_zetas
from lodcast.renderer.lod.significance import meta_of_store, tf_visible
from lodcast.renderer.scene.presets import preset
from lodcast.store.store import open_store

HERE = Path(__file__).resolve().parent


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--store", type=Path, default=HERE / "results" / "large" / "body_1024x2048x2048.zarr")
    ap.add_argument("--tf", default="ct-bone")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--json", type=Path, default=HERE / "results" / "block_errors.json")
    a = ap.parse_args(argv)
    if not a.store.is_dir():
        print(f"--store: {a.store} is not a store (benchmarks/bench_large_volume.py makes one)", file=sys.stderr)
        return 2
    store = open_store(a.store)
    meta = meta_of_store(store)
    tf = preset(a.tf)
    vis = tf_visible(tf, meta.min_border, meta.max_border)
    eng = lodcast.Renderer()
    args = (meta, tf, vis, meta.value_range, meta.std_max)
    rows = []
    for cls in ("distribution", "mean"):
        for worst in (False, True):
            block_zetas(*args, cls, Tables(eng.device), worst)  # the kernel's first build, not timed
            t_np, t_dev, diff = [], [], 0.0
            for _ in range(a.rounds):
                t0 = time.perf_counter()
                ref = block_zetas(*args, cls, Tables(None), worst)
                t1 = time.perf_counter()
                got = block_zetas(*args, cls, Tables(eng.device), worst)
                t2 = time.perf_counter()
                t_np.append(t1 - t0)
                t_dev.append(t2 - t1)
                diff = max(diff, max(float(np.abs(r - g).max()) for r, g in zip(ref, got)))
            rows.append({"classification": cls, "worst_values": worst, "numpy_s": float(np.median(t_np)),
                         "device_s": float(np.median(t_dev)), "ratio": float(np.median(np.array(t_np) / t_dev)),
                         "max_abs_difference": diff})
    eng.close()
    res = {"date": time.strftime("%Y-%m-%d"), "machine": f"{platform.processor() or platform.machine()}, "
           f"nproc {os.cpu_count()}", "device": "PoCL (CPU)" if "pthread" in str(eng.device.info()["name"]) else
           str(eng.device.info()["name"]), "store": a.store.name, "blocks": int(meta.n), "visible": int(vis.sum()),
           "tf": a.tf, "rounds": a.rounds, "load_average": os.getloadavg(),
           "command": "benchmarks/bench_block_errors.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "rows": rows}
    print(f"\n{a.store.name}: {meta.n} blocks, {int(vis.sum())} visible under {a.tf}; median of {a.rounds} alternating"
          " rounds\n")
    print("| classification | worst values | NumPy (s) | device (s) | NumPy ÷ device | largest difference |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['classification']} | {'yes' if r['worst_values'] else 'no'} | {r['numpy_s']:.2f} | "
              f"{r['device_s']:.2f} | {r['ratio']:.1f} | {r['max_abs_difference']:.1e} |")
    a.json.parent.mkdir(parents=True, exist_ok=True)
    a.json.write_text(json.dumps(res, indent=1))
    print(f"\nwrote {a.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
