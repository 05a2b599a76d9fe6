"""The pictures in docs/lod.md of the level of detail on the chest CT, each panel with its mean ΔE against the step-¼
reference:

- docs/images/lod_classification.png: ct-bone at full resolution and at 30:1, coarse data classified by the mean
  and by distribution;
- docs/images/lod_visibility.png: ct-skin-bone at full resolution and at 30:1, the selection without and with
  the weight of what the camera sees (sampling.lod_visibility).

    .venv/bin/python benchmarks/figure_lod.py [--out docs/images]

Uses the 16³ store bench_consistent_lod.py ingests (benchmarks/results/ct_chest_b16.zarr), ingesting it if absent.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import lodcast
from lodcast.renderer.image.delta_e import delta_e_stats
from lodcast.renderer.scene.transfer_function import CT_PRESETS

HERE = Path(__file__).resolve().parent
THIRTY = {"reduction": 30}
FIGURES = {
    "lod_classification.png": ("ct-bone", [
        ("full resolution", {}),
        ("30:1, classified by the mean", {"quality": THIRTY, "sampling": {"classification": "mean"}}),
        ("30:1, by distribution (default)", {"quality": THIRTY})]),
    "lod_visibility.png": ("ct-skin-bone", [
        ("full resolution", {}),
        ("30:1, without the view's weight", {"quality": THIRTY, "sampling": {"lod_visibility": False}}),
        ("30:1, weighed by the view (default)", {"quality": THIRTY})]),
}


def figure(eng, store, tf: str, panels: list, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    base = {"camera": {"azimuth": 30, "elevation": 10}, "width": 320, "height": 320, "tf": CT_PRESETS[tf],
            "format": "npy"}
    ref = eng.render(store, {**base, "sampling": {"step": 0.25}})
    fig, axs = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.7), dpi=100, facecolor="black")
    for ax, (title, extra) in zip(axs, panels):
        r = eng.render(store, {**base, **extra})
        ax.imshow(np.clip(r.rgba[..., :3], 0, 1))
        ax.set_axis_off()
        ax.set_title(f"{title}\nmean ΔE {delta_e_stats(r.rgba, ref.rgba)['mean']:.1f}", fontsize=9, color="white")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, facecolor="black")
    plt.close(fig)
    print(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=HERE.parent / "docs" / "images", help="folder of the pictures")
    a = ap.parse_args()
    from bench_consistent_lod import DATA, store_of

    st = store_of("ct_chest", DATA / "ct_chest_dicom")
    eng = lodcast.Renderer()
    for name, (tf, panels) in FIGURES.items():
        figure(eng, st, tf, panels, a.out / name)


if __name__ == "__main__":
    main()
