"""The picture in docs/rendering.md of `"tf": "auto"`: one scene, no transfer function written for any volume, on six real
volumes of different modalities and scales (CT in Hounsfield units, industrial and micro-CT, three MR heads); each
panel says the α-histogram's background and tissue peaks the template was placed on.

    .venv/bin/python benchmarks/figure_adaptive_tf.py [--out docs/images/adaptive_tf.png]

Ingests the volumes of ../shared/data into benchmarks/results/ (16³ blocks) where they are not there yet.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import lodcast
from lodcast.renderer.data.volume import as_volume
from lodcast.renderer.scene.adaptive_tf import volume_peaks
from lodcast.renderer.tools.demo import SHADING

HERE = Path(__file__).resolve().parent
VOLUMES = [("ct_chest", "ct_chest_dicom", 30), ("engine", "engine.nii.gz", 30), ("bonsai", "bonsai.nii.gz", 30),
           ("mr_head", "mr_head.nii.gz", 180), ("flair", "flair.nrrd", 180), ("avg152t1", "avg152t1.nii.gz", 180)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=HERE.parent / "docs" / "images" / "adaptive_tf.png")
    a = ap.parse_args()
    import matplotlib
    from bench_consistent_lod import DATA, store_of

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    eng = lodcast.Renderer()
    fig, axes = plt.subplots(1, len(VOLUMES), figsize=(3.2 * len(VOLUMES), 3.7))
    for ax, (name, source, azimuth) in zip(axes, VOLUMES):
        store = store_of(name, DATA / source)
        bg, tissue = volume_peaks(as_volume(store), eng.tables.peaks)  # kept for the render's "auto"
        r = eng.render(store, {"tf": "auto", "shading": SHADING, "width": 320, "height": 320,
                               "camera": {"azimuth": azimuth, "elevation": 15}, "background": [0, 0, 0, 1]})
        ax.imshow(r.rgba[..., :3].clip(0, 1))
        ax.set_title(f"{name}\npeaks {bg:.4g} / {tissue:.4g}", fontsize=9)
        ax.set_axis_off()
        print(f"{name:10s} background {bg:8g}  tissue {tissue:8g}  kernel {r.report['kernel_ms']:.0f} ms")
    fig.suptitle('"tf": "auto" with shading, the same scene on each volume', fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.9))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=100)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
