"""Issue 12's figures for dual-TF compositing: the priority map's speed-up and that it changes nothing.

    .venv/bin/python benchmarks/bench_dual_tf.py [--sizes 256 512] [--repeat 3] [--json benchmarks/results/dual_tf.json]

Volumes: the chest CT (../shared/data/ct_chest_dicom) with tf = ct-body (an opaque body surface) and tf2 = ct-dense
(the densest bone, calcifications, contrast: X-ray vision through the body), and the engine CT (engine.nii.gz) with
an opaque aluminium block as tf and its steel parts as tf2; both ingested with 16³ blocks under
benchmarks/results/. Each case renders at quality "full" and at {"reduction": 30}, with the priority map on and
off, and with empty-space skipping on (default) and off (the thesis' situation: without the block walk, a ray
without priority runs to its end). Kernel times are the fastest of `repeat` after a warm-up; the machine is
shared, so compare ratios within one run. ΔE (docs/design.md) is between the priority-map image and the plain dual-TF
image of the same settings. Prints a markdown table and writes JSON.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from bench_consistent_lod import DATA, RESULTS, best, store_of  # the 16³ stores every CT benchmark shares

from lodcast.renderer.frame.render import Renderer
from lodcast.renderer.image.delta_e import delta_e_stats

ENGINE_BLOCK = {"points": [{"value": 90, "color": [0.75, 0.8, 0.85], "opacity": 0.0},
                           {"value": 130, "color": [0.8, 0.85, 0.9], "opacity": 0.6}]}
ENGINE_STEEL = {"points": [{"value": 190, "color": [1.0, 0.45, 0.1], "opacity": 0.0},
                           {"value": 215, "color": [1.0, 0.55, 0.2], "opacity": 0.9}]}
CASES = [("chest CT", "ct_chest", "ct_chest_dicom", "ct-body", "ct-dense"),
         ("engine CT", "engine", "engine.nii.gz", ENGINE_BLOCK, ENGINE_STEEL)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", type=Path, default=RESULTS / "dual_tf.json")
    a = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    eng = Renderer()
    rows, device = [], None
    for label, name, src, tf, tf2 in CASES:
        store = store_of(name, DATA / src)
        for size in a.sizes:
            for quality in ("full", {"reduction": 30}):
                for ess in (True, False):
                    scene = {"camera": {"azimuth": 30, "elevation": 15}, "width": size, "height": size, "tf": tf,
                             "tf2": tf2, "quality": quality, "format": "npy"}
                    samp = {"empty_space_skipping": ess}
                    on = best(eng, store, {**scene, "sampling": samp}, a.repeat)
                    off = best(eng, store, {**scene, "sampling": {**samp, "priority_map": False}}, a.repeat)
                    single = best(eng, store, {**scene, "tf2": None, "sampling": samp}, a.repeat)
                    device = on.report["device"]
                    rows.append({
                        "volume": label, "size": size, "quality": quality, "ess": ess,
                        "single_ms": single.report["kernel_ms"], "single_samples": single.report["samples"],
                        "plain_ms": off.report["kernel_ms"], "plain_samples": off.report["samples"],
                        "priority_ms": on.report["kernel_ms"], "priority_samples": on.report["samples"],
                        "priority_pixels": on.report["priority_map"]["priority_pixels"],
                        "speedup": off.report["kernel_ms"] / on.report["kernel_ms"],
                        "delta_e": delta_e_stats(on.rgba, off.rgba),
                    })
    lines = ["| volume | size | quality | ESS | single TF ms | dual plain ms | dual + priority ms | speed-up | "
             "samples plain → priority | priority pixels | ΔE mean / max |", "|" + "---|" * 11]
    for r in rows:
        q = r["quality"] if isinstance(r["quality"], str) else f"{r['quality']['reduction']:g}:1"
        lines.append(
            f"| {r['volume']} | {r['size']}² | {q} | {'on' if r['ess'] else 'off'} | {r['single_ms']:.0f} | "
            f"{r['plain_ms']:.0f} | {r['priority_ms']:.0f} | {r['speedup']:.2f}× | "
            f"{r['plain_samples'] / 1e6:.1f}M → {r['priority_samples'] / 1e6:.1f}M | {100 * r['priority_pixels']:.0f}% | "
            f"{r['delta_e']['mean']:.3f} / {r['delta_e']['max']:.2f} |")
    a.json.write_text(json.dumps({"device": device, "rows": rows}, indent=2, default=float))
    print("\n".join(lines))
    print(f"\ndevice: {device}\nJSON: {a.json}")


if __name__ == "__main__":
    main()
