"""Issue 12's figures for adaptive screen-space sampling: rays cast, speed-up and ΔE for each tile statistic.

    .venv/bin/python benchmarks/bench_screen_space.py [--sizes 512 1024] [--repeat 2] [--json benchmarks/results/screen_space.json]

Volumes: the chest CT (ct-bone) and the engine CT (its aluminium block, with its steel parts as tf2 in the dual
rows), 16³ stores under benchmarks/results/, at {"reduction": 30}. For each statistic (max, average, rms) the
scene renders with `sampling.adaptive_screen` and is compared with the same scene without it (ΔE "vs plain", what
screen-space sampling alone costs) and with the full-resolution render (ΔE "vs full"). Times: the fastest of
`repeat` after a warm-up; kernel time, and wall time (which includes the host's pre-pass and reconstruction).
The machine is shared: compare ratios within one run. Prints a markdown table and writes JSON.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from bench_consistent_lod import DATA, RESULTS, best, store_of
from bench_dual_tf import ENGINE_BLOCK, ENGINE_STEEL

import lodcast
from lodcast.renderer.image.delta_e import delta_e_stats

CASES = [("chest CT", "ct_chest", "ct_chest_dicom", {"tf": "ct-bone"}),
         ("engine CT, dual TF", "engine", "engine.nii.gz", {"tf": ENGINE_BLOCK, "tf2": ENGINE_STEEL})]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[512, 1024])
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--json", type=Path, default=RESULTS / "screen_space.json")
    a = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    eng = lodcast.Renderer()
    rows, device = [], None
    for label, name, src, tfs in CASES:
        store = store_of(name, DATA / src)
        for size in a.sizes:
            scene = {"camera": {"azimuth": 30, "elevation": 15}, "width": size, "height": size, "format": "npy", **tfs}
            full = eng.render(store, scene)
            lod = {**scene, "quality": {"reduction": 30}}
            plain = best(eng, store, lod, a.repeat)
            device = plain.report["device"]
            for stat in ("max", "average", "rms"):
                r = best(eng, store, {**lod, "sampling": {"adaptive_screen": True, "screen_statistic": stat}}, a.repeat)
                rep = r.report["adaptive_screen"]
                rows.append({
                    "volume": label, "size": size, "statistic": stat, "rays": rep["rays"],
                    "rays_per_pixel": rep["rays_per_pixel"], "tiles": rep["tiles"],
                    "plain_kernel_ms": plain.report["kernel_ms"], "plain_wall_ms": plain.report["wall_ms"],
                    "kernel_ms": r.report["kernel_ms"], "wall_ms": r.report["wall_ms"],
                    "reconstruct_ms": rep["reconstruct_ms"],
                    "kernel_speedup": plain.report["kernel_ms"] / r.report["kernel_ms"],
                    "wall_speedup": plain.report["wall_ms"] / r.report["wall_ms"],
                    "delta_e_vs_plain": delta_e_stats(r.rgba, plain.rgba),
                    "delta_e_vs_full": delta_e_stats(r.rgba, full.rgba),
                    "plain_delta_e_vs_full": delta_e_stats(plain.rgba, full.rgba)["mean"],
                })
    lines = ["| volume | size | statistic | rays/pixel | kernel ms plain → adaptive | speed-up kernel / wall | "
             "reconstruct ms | ΔE vs plain mean / p95 | ΔE vs full (plain 30:1) |", "|" + "---|" * 9]
    for r in rows:
        lines.append(
            f"| {r['volume']} | {r['size']}² | {r['statistic']} | {r['rays_per_pixel']:.2f} | "
            f"{r['plain_kernel_ms']:.0f} → {r['kernel_ms']:.0f} | {r['kernel_speedup']:.2f}× / {r['wall_speedup']:.2f}× | "
            f"{r['reconstruct_ms']:.0f} | {r['delta_e_vs_plain']['mean']:.2f} / {r['delta_e_vs_plain']['p95']:.2f} | "
            f"{r['delta_e_vs_full']['mean']:.2f} ({r['plain_delta_e_vs_full']:.2f}) |")
    a.json.write_text(json.dumps({"device": device, "rows": rows}, indent=2, default=float))
    print("\n".join(lines))
    print(f"\ndevice: {device}\nJSON: {a.json}")


if __name__ == "__main__":
    main()
