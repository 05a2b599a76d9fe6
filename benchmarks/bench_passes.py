"""Figures for renders beyond the device budget (issue 14 item 1) and the finer cells of empty-space skipping at
full resolution (issue 13 item 1).

    .venv/bin/python benchmarks/bench_passes.py [--size 512] [--repeat 3] [--json benchmarks/results/passes.json]

Passes: the chest CT and the engine CT (16³ stores under benchmarks/results/) at quality "full" and "lossless",
uncapped and under device budgets below their volume data (a Renderer per budget, device_budget_mb); per row the passes, the most volume
data on the device at once, kernel / upload / wall ms (the fastest of `repeat` after a warm-up: a render in passes
keeps nothing on the device, so every repeat reads its regions again) and the largest difference from the
uncapped image (0: bit for bit) with its mean ΔE.

Cells: the same scenes at full resolution with the walk over the store's 16³ blocks and over its
cells (sampler.ess_cell: 4³ or 8³): samples taken and kernel ms, the fastest of `repeat`, ratios from this run. The machine is
shared: compare ratios within one run. Prints markdown tables and writes JSON.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np
from bench_consistent_lod import DATA, RESULTS, best, store_of

from lodcast.renderer.data import sampler
from lodcast.renderer.frame.render import Renderer
from lodcast.renderer.image.delta_e import delta_e_stats

CASES = [("chest CT", "ct_chest", "ct_chest_dicom", ["ct-bone", "ct-skin", "ct-body"]),
         ("engine CT", "engine", "engine.nii.gz", [None])]
ENGINE_TF = {"points": [{"value": 60, "color": [0.9, 0.7, 0.5], "opacity": 0.0},
                        {"value": 140, "color": [0.9, 0.7, 0.5], "opacity": 0.4},
                        {"value": 255, "color": [1, 1, 1], "opacity": 0.9}]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", type=Path, default=RESULTS / "passes.json")
    a = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    os.environ.pop("LODCAST_DEVICE_BUDGET_MB", None)  # uncapped: the engines read it when they are made
    eng = Renderer()
    passes, cells, device = [], [], None
    for label, name, src, tfs in CASES:
        store = store_of(name, DATA / src)
        for tf in tfs:
            scene = {"tf": tf or ENGINE_TF, "camera": {"azimuth": 30, "elevation": 15}, "width": a.size,
                     "height": a.size, "format": "npy"}
            for quality in ("full", "lossless"):
                sc = {**scene, "quality": quality}
                ref = best(eng, store, sc, a.repeat)
                device = ref.report["device"]
                data_mb = ref.report["device_bytes"] / 1e6
                for mb in (None, round(data_mb / 4.5, 1), round(data_mb / 18, 1)):
                    r = ref if mb is None else best(Renderer(device_budget_mb=mb), store, sc, a.repeat)
                    passes.append({
                        "volume": label, "tf": tf or "engine", "quality": quality, "budget_mb": mb,
                        "passes": r.report["passes"], "device_mb": r.report["device_bytes"] / 1e6,
                        "kernel_ms": r.report["kernel_ms"], "upload_ms": r.report["upload_ms"],
                        "wall_ms": r.report["wall_ms"], "max_abs_diff": float(np.abs(r.rgba - ref.rgba).max()),
                        "delta_e_mean": delta_e_stats(r.rgba, ref.rgba)["mean"],
                    })
                    print(passes[-1], flush=True)
            row = {"volume": label, "tf": tf or "engine"}
            for cell, key in ((lambda shape, B: B, "blocks"), (sampler.ess_cell, "cells")):
                orig = sampler.ess_cell
                sampler.ess_cell = cell
                eng.device_cache.clear()
                try:
                    r = best(eng, store, scene, a.repeat)
                finally:
                    sampler.ess_cell = orig
                row[f"{key}_samples"], row[f"{key}_kernel_ms"] = r.report["samples"], r.report["kernel_ms"]
            row["sample_ratio"] = row["cells_samples"] / row["blocks_samples"]
            row["kernel_speedup"] = row["blocks_kernel_ms"] / row["cells_kernel_ms"]
            cells.append(row)
            print(row, flush=True)
    eng.device_cache.clear()
    lines = ["| volume | TF | quality | budget MB | passes | device MB | kernel ms | upload ms | wall ms | "
             "max diff vs uncapped | ΔE mean |", "|" + "---|" * 11]
    for r in passes:
        lines.append(f"| {r['volume']} | {r['tf']} | {r['quality']} | {r['budget_mb'] or '—'} | {r['passes']} | "
                     f"{r['device_mb']:.1f} | {r['kernel_ms']:.0f} | {r['upload_ms']:.0f} | {r['wall_ms']:.0f} | "
                     f"{r['max_abs_diff']:.3g} | {r['delta_e_mean']:.3g} |")
    lines += ["", "| volume | TF | samples 16³ blocks → cells | kernel ms 16³ blocks → cells | kernel speed-up |",
              "|" + "---|" * 5]
    for r in cells:
        lines.append(f"| {r['volume']} | {r['tf']} | {r['blocks_samples'] / 1e6:.1f} M → {r['cells_samples'] / 1e6:.1f} M "
                     f"({r['sample_ratio']:.2f}) | {r['blocks_kernel_ms']:.0f} → {r['cells_kernel_ms']:.0f} | "
                     f"{r['kernel_speedup']:.2f}× |")
    table = "\n".join(lines)
    print(f"\n{a.size}², {device}\n\n{table}")
    a.json.write_text(json.dumps({"size": a.size, "device": device, "passes": passes, "cells": cells,
                                  "table": table}, indent=2))
    print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
