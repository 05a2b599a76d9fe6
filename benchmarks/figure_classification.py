"""The README's picture of distribution classification: the chest CT with ct-bone at full resolution and at 30:1,
classified by the mean and by distribution, each with its mean ΔE against the step-¼ reference.

    .venv/bin/python benchmarks/figure_classification.py [--out docs/images/lod_classification.png]

Uses the 16³ store bench_consistent_lod.py ingests (benchmarks/results/ct_chest_b16.zarr), ingesting it if absent.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import lodcast
from lodcast.renderer.image_error import delta_e_stats
from lodcast.renderer.transfer_function import CT_PRESETS

HERE = Path(__file__).resolve().parent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=HERE.parent / "docs" / "images" / "lod_classification.png")
    a = ap.parse_args()
    from bench_consistent_lod import DATA, store_of

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    st = store_of("ct_chest", DATA / "ct_chest_dicom")
    base = {"camera": {"azimuth": 30, "elevation": 10}, "width": 320, "height": 320, "tf": CT_PRESETS["ct-bone"],
            "format": "npy"}
    ref = lodcast.render(st, {**base, "sampling": {"step": 0.25}})
    panels = [("full resolution", {}),
              ("30:1, classified by the mean", {"quality": {"reduction": 30}, "sampling": {"classification": "mean"}}),
              ("30:1, by distribution (default)", {"quality": {"reduction": 30}})]
    fig, axs = plt.subplots(1, 3, figsize=(9.6, 3.7), dpi=100, facecolor="black")
    for ax, (title, extra) in zip(axs, panels):
        r = lodcast.render(st, {**base, **extra})
        ax.imshow(np.clip(r.rgba[..., :3], 0, 1))
        ax.set_axis_off()
        ax.set_title(f"{title}\nmean ΔE {delta_e_stats(r.rgba, ref.rgba)['mean']:.1f}", fontsize=9, color="white")
    fig.tight_layout()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, facecolor="black")
    print(a.out)


if __name__ == "__main__":
    main()
