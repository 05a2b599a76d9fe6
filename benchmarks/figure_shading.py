"""The picture in docs/rendering.md of shading and clipping: the chest CT with ct-bone unlit, lit by a headlight, lit at 30:1,
and ct-skin-bone lit with its front half clipped away, each with its kernel time.

    .venv/bin/python benchmarks/figure_shading.py [--out docs/images/shading.png]

Uses the 16³ store bench_consistent_lod.py ingests (benchmarks/results/ct_chest_b16.zarr), ingesting it if absent.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import lodcast
from lodcast.renderer.tools.demo import SHADING

HERE = Path(__file__).resolve().parent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=HERE.parent / "docs" / "images" / "shading.png")
    a = ap.parse_args()
    import matplotlib
    from bench_consistent_lod import DATA, store_of

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    store = store_of("ct_chest", DATA / "ct_chest_dicom")
    c = [float(x) for x in (store.origin[2] + store.spacing[2] * store.shape[2] / 2,
                             store.origin[1] + store.spacing[1] * store.shape[1] / 2, 0.0)]
    base = {"camera": {"azimuth": 30, "elevation": 15}, "width": 320, "height": 320, "background": [0, 0, 0, 1]}
    panels = [("unlit", {"tf": "ct-bone"}), ("shading (headlight)", {"tf": "ct-bone", "shading": SHADING}),
              ("shading, 30:1", {"tf": "ct-bone", "shading": SHADING, "quality": {"reduction": 30}}),
              ("ct-skin-bone, front clipped", {"tf": "ct-skin-bone", "shading": SHADING,
                                               "clip": {"planes": [{"point": c, "normal": [0, 1, 0]}]}})]
    eng = lodcast.Renderer()
    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 4.8))
    for ax, (title, extra) in zip(axes, panels):
        r = eng.render(store, {**base, **extra})
        ax.imshow(r.rgba[..., :3].clip(0, 1))
        ax.set_title(f"{title}\n{r.report['kernel_ms']:.0f} ms kernel", fontsize=10)
        ax.axis("off")
    fig.tight_layout()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=80)
    print(a.out)


if __name__ == "__main__":
    main()
