"""Issue 11's figures: pre-integration against step, the cost of shading and clipping, early termination's bias.

    .venv/bin/python benchmarks/bench_illumination.py [--size 256] [--repeat 3] [--json benchmarks/results/illumination.json]

Volume: the chest CT (../shared/data/ct_chest_dicom, 16³ store under benchmarks/results/), full resolution. TFs:
ct-skin (a thin band: high frequency) and ct-bone. Error: docs/design.md's mean ΔE against the point-sampled render
at step 1/8 (early termination off). Kernel times are the fastest of `repeat` after a warm-up; the machine is
shared, so compare ratios within one run. Prints a markdown table and writes JSON.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
DATA = Path(os.environ.get("LODCAST_SHARED_DATA", HERE.parents[1] / "shared" / "data"))
RESULTS = HERE / "results"

from bench_consistent_lod import best  # noqa: E402

import lodcast  # noqa: E402
from lodcast.renderer.image.delta_e import delta_e_stats  # noqa: E402
from lodcast.renderer.tools.demo import SHADING  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", type=Path, default=RESULTS / "illumination.json")
    a = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    dest = RESULTS / "ct_chest_b16.zarr"
    store = lodcast.open_store(dest) if dest.exists() else lodcast.ingest(DATA / "ct_chest_dicom", dest)
    eng = lodcast.Renderer()
    out: dict = {"size": a.size, "preintegration": [], "features": []}
    lines = []
    for tf in ("ct-skin", "ct-bone"):
        scene = {"camera": {"azimuth": 30, "elevation": 15}, "width": a.size, "height": a.size, "tf": tf, "format": "npy"}
        ref = eng.render(store, {**scene, "sampling": {"step": 0.125, "early_termination": 1.0}})
        for step in (2.0, 1.0, 0.5, 0.25):
            row = {"tf": tf, "step": step}
            for pre in (False, True):
                r = best(eng, store, {**scene, "sampling": {"step": step, "preintegration": pre}}, a.repeat)
                key = "pre" if pre else "point"
                row[f"{key}_ms"], row[f"{key}_delta_e"] = r.report["kernel_ms"], delta_e_stats(r.rgba, ref.rgba)["mean"]
                if pre:
                    row["table_ms"] = r.report["preintegration_ms"]
            out["preintegration"].append(row)
        base = best(eng, store, scene, a.repeat)
        et_off = eng.render(store, {**scene, "sampling": {"early_termination": 1.0}})
        yc = float(store.origin[1] + store.spacing[1] * (store.shape[1] - 1) / 2)  # world y of the volume's centre
        variants = {  # the plane and the box each keep the half y >= centre and y <= centre
            "shading": {**scene, "shading": SHADING},
            "clip plane": {**scene, "clip": {"planes": [{"point": [0, yc, 0], "normal": [0, 1, 0]}]}},
            "crop box": {**scene, "clip": {"box": {"min": [-1e4, -1e4, -1e4], "max": [1e4, yc, 1e4]}}},
            "pre-integration": {**scene, "sampling": {"preintegration": True}},
        }
        feat = {"tf": tf, "base_ms": base.report["kernel_ms"],
                "early_termination_delta_e": delta_e_stats(base.rgba, et_off.rgba)["mean"]}
        for name, sc in variants.items():
            feat[f"{name}_ms"] = best(eng, store, sc, a.repeat).report["kernel_ms"]
        out["features"].append(feat)
    lines.append("| TF | step | point ΔE | point ms | pre-int ΔE | pre-int ms | table ms |\n|---|---|---|---|---|---|---|")
    for r in out["preintegration"]:
        lines.append(f"| {r['tf']} | {r['step']:g} | {r['point_delta_e']:.2f} | {r['point_ms']:.0f} | "
                     f"{r['pre_delta_e']:.2f} | {r['pre_ms']:.0f} | {r['table_ms']:.0f} |")
    lines.append("\n| TF | plain ms | shading ms | clip plane ms | crop box ms | pre-int ms | ET 0.99 vs 1.0 ΔE |\n|---|---|---|---|---|---|---|")
    for f in out["features"]:
        lines.append(f"| {f['tf']} | {f['base_ms']:.0f} | {f['shading_ms']:.0f} | {f['clip plane_ms']:.0f} | "
                     f"{f['crop box_ms']:.0f} | {f['pre-integration_ms']:.0f} | {f['early_termination_delta_e']:.3f} |")
    out["device"] = base.report["device"]
    a.json.write_text(json.dumps(out, indent=2, default=float))
    print("\n".join(lines))
    print(f"\nJSON: {a.json}")


if __name__ == "__main__":
    t0 = time.perf_counter()
    main()
