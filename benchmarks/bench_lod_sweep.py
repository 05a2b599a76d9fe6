"""The level of detail's quality and sample count over a fixed sweep of 32 images: the yardstick for changes to the
selection or the adaptive steps (one number to compare before and after, and every image beside it).

    .venv/bin/python benchmarks/bench_lod_sweep.py [--size 256] [--json benchmarks/results/lod_sweep.json]

The chest CT (ct-bone, ct-skin, ct-skin-bone) and the engine CT (an opaque metal TF), two views each (azimuth
30°/elevation 15° and 200°/−20°), at 5:1, 10:1, 30:1 and 100:1 with default settings. Per image: mean ΔE against
the full-resolution reference at step ¼ (docs/design.md's ΔE over the footprint) and the samples taken as a fraction of
full resolution's at the default step. Prints a markdown table and the sums; references are cached beside the
stores (benchmarks/results/), keyed by volume, TF, view and size. Image errors and sample counts are deterministic;
the kernel times it also prints are not (the machine is shared).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_consistent_lod import DATA, ENGINE_TF, RESULTS, best, store_of  # noqa: E402

import lodcast  # noqa: E402
from lodcast.renderer.image.delta_e import delta_e_stats  # noqa: E402

VIEWS = [{"azimuth": 30, "elevation": 15}, {"azimuth": 200, "elevation": -20}]
REDUCTIONS = [5, 10, 30, 100]


def cases():
    chest = store_of("ct_chest", DATA / "ct_chest_dicom")
    engine = store_of("engine", DATA / "engine.nii.gz")
    return [(chest, "chest", tf, tf) for tf in ("ct-bone", "ct-skin", "ct-skin-bone")] + [
        (engine, "engine", "engine-metal", ENGINE_TF)]


def reference(eng, store, key: str, scene: dict) -> np.ndarray:
    path = RESULTS / "lod_sweep_refs" / f"{key}.npy"
    if path.exists():
        return np.load(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ref = eng.render(store, {**scene, "sampling": {"step": 0.25}}).rgba
    np.save(path, ref)
    return ref


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--json", type=Path, default=RESULTS / "lod_sweep.json")
    args = ap.parse_args()
    t0 = time.perf_counter()
    eng = lodcast.Renderer()
    rows = []
    for store, vname, tname, tf in cases():
        for vi, cam in enumerate(VIEWS):
            scene = {"tf": tf, "camera": cam, "width": args.size, "height": args.size}
            ref = reference(eng, store, f"{vname}_{tname}_{vi}_{args.size}", scene)
            full = best(eng, store, scene, 1)
            for red in REDUCTIONS:
                r = best(eng, store, {**scene, "quality": {"reduction": red}}, 1)
                rows.append({"volume": vname, "tf": tname, "view": vi, "reduction": red,
                             "delta_e": delta_e_stats(r.rgba, ref)["mean"],
                             "samples_vs_full": r.report["samples"] / full.report["samples"],
                             "kernel_ms": r.report["kernel_ms"], "full_kernel_ms": full.report["kernel_ms"]})
            print(f"{vname} {tname} view {vi}: done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    lines = [f"| volume, TF, view | {' | '.join(f'{r}:1' for r in REDUCTIONS)} |",
             "|---|" + "---|" * len(REDUCTIONS)]
    for i in range(0, len(rows), len(REDUCTIONS)):
        g = rows[i:i + len(REDUCTIONS)]
        lines.append(f"| {g[0]['volume']}, {g[0]['tf']}, {g[0]['view']} | "
                     + " | ".join(f"{r['delta_e']:.2f} · {r['samples_vs_full']:.2f}" for r in g) + " |")
    total = sum(r["delta_e"] for r in rows)
    samples = float(np.mean([r["samples_vs_full"] for r in rows]))
    ms = sum(r["kernel_ms"] for r in rows) / sum(r["full_kernel_ms"] for r in rows)
    print("mean ΔE against the step-¼ reference · samples ÷ full resolution's, "
          f"{args.size}², default settings\n\n" + "\n".join(lines))
    print(f"\nsum of mean ΔE over {len(rows)} images {total:.2f}; samples ÷ full, mean {samples:.3f}; "
          f"kernel time ÷ full resolution's, summed {ms:.2f}")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"size": args.size, "rows": rows, "sum_delta_e": total,
                                     "mean_samples_vs_full": samples, "kernel_vs_full": ms}, indent=1))


if __name__ == "__main__":
    main()
