"""The picture in docs/rendering.md of dual-TF compositing ("X-ray vision", thesis §3.6.2 and fig. 3.16): the chest CT as an
opaque body (ct-body), the same with the densest bone, calcifications and contrast (ct-dense) composited over it as
tf2, and the engine CT's steel parts inside its aluminium block; the priority map of each dual image is the insert
in its lower left corner (white: pixels whose rays may meet tf2's blocks), the kernel times are with and without it.

    .venv/bin/python benchmarks/figure_dual_tf.py [--out docs/images/dual_tf.png]

Uses the 16³ stores bench_dual_tf.py ingests under benchmarks/results/, ingesting them if absent.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import lodcast
from lodcast.renderer.scene import camera as cam
from lodcast.renderer.tools.demo import SHADING

HERE = Path(__file__).resolve().parent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=HERE.parent / "docs" / "images" / "dual_tf.png")
    ap.add_argument("--size", type=int, default=320)
    a = ap.parse_args()
    import matplotlib
    from bench_consistent_lod import DATA, store_of
    from bench_dual_tf import ENGINE_BLOCK, ENGINE_STEEL

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    chest = store_of("ct_chest", DATA / "ct_chest_dicom")
    engine = store_of("engine", DATA / "engine.nii.gz")
    base = {"width": a.size, "height": a.size, "background": [0, 0, 0, 1], "shading": SHADING}
    panels = [("chest CT: ct-body", chest, {"tf": "ct-body"}),
              ("tf2 = ct-dense over it", chest, {"tf": "ct-body", "tf2": "ct-dense"}),
              ("engine CT: steel over aluminium", engine, {"tf": ENGINE_BLOCK, "tf2": ENGINE_STEEL})]
    eng = lodcast.Renderer()
    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 4.8))
    for ax, (title, store, extra) in zip(axes, panels):
        # the chest's whole box in the picture (its top slice is cut by the default orbit of 2.5 radii); the
        # engine's box has empty corners, and 2.5 shows all of the engine
        dist = 2.5 if store is engine else cam.fit_distance(*cam.box_world(store.shape, store.spacing, store.origin), 30, 15)
        scene = {**base, "camera": {"azimuth": 30, "elevation": 15, "distance": dist}, **extra}
        eng.render(store, scene)  # warm the program and brick caches
        r = eng.render(store, scene)
        img = r.rgba[..., :3].clip(0, 1).copy()
        note = f"{r.report['kernel_ms']:.0f} ms kernel"
        if "tf2" in extra:
            plain = eng.render(store, {**scene, "sampling": {"priority_map": False}})
            note += f" ({plain.report['kernel_ms']:.0f} ms without the priority map)"
            pm = eng.prepare(store, scene).priority.pixels(a.size, a.size).astype(np.float32)
            k = 4  # the insert: the map at a quarter of the size, framed
            ins = pm[::k, ::k]
            h, w = ins.shape
            img[-h - 2:, : w + 2] = 0.5
            img[-h - 1:-1, 1 : w + 1] = ins[..., None]
        ax.imshow(img)
        ax.set_title(f"{title}\n{note}", fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=80)
    print(a.out)


if __name__ == "__main__":
    main()
