"""Thesis fig. 3.4 on a real CT volume: at 64:1, TF-based block significance (eq. 3.1) selects levels whose
image is closer to the full-resolution reference than data-error (L2) significance and uniform level
reduction, measured as DESIGN.md's mean ΔE of the rendered images."""
from __future__ import annotations

from pathlib import Path


import lodcast
from lodcast.renderer.image_error import delta_e_stats
from lodcast.renderer.scene import Scene
from lodcast.renderer.selection import select_lod

# engine.nii.gz (Open SciVis "Engine", industrial CT): an opaque TF on the dense metal parts
TF = {"points": [{"value": 150, "color": [1.0, 0.8, 0.5], "opacity": 0.0},
                 {"value": 200, "color": [1.0, 0.9, 0.7], "opacity": 0.8},
                 {"value": 255, "color": [1.0, 1.0, 1.0], "opacity": 0.9}]}


def test_tf_selection_beats_l2_and_uniform_at_64_to_1(tmp_path: Path, shared_data: Path):
    store = lodcast.ingest(shared_data / "engine.nii.gz", tmp_path / "engine.zarr")
    scene = {"camera": {"azimuth": 30, "elevation": 20, "distance": 2.2}, "width": 128, "height": 128, "tf": TF,
             "format": "npy", "sampling": {"step": 0.5, "early_termination": 1.0}}
    ref = lodcast.render(store, {**scene, "sampling": {"step": 0.25, "early_termination": 1.0}})
    errors, reductions = {}, {}
    for method in ("tf", "l2", "uniform"):
        sel = select_lod(store, [Scene.parse(scene).tf], {"reduction": 64}, method=method)
        img = lodcast.render(store, {**scene, "quality": {"reduction": 64}}, levels=sel.levels)
        errors[method] = delta_e_stats(img.rgba, ref.rgba)["mean"]
        reductions[method] = sel.reduction
    # every method keeps at least the 64:1 budget (uniform steps in whole levels, so it reduces more)
    assert min(reductions.values()) >= 63.5, reductions
    # measured here: tf 12.6, l2 16.0, uniform 21.1; the ordering is the claim, held with a 10 % margin. (On the chest
    # CT with a bone TF the ordering does not hold: tf 22.2 vs l2 16.0; see the issue 5 note.)
    assert errors["tf"] < 0.9 * errors["l2"], errors
    assert errors["tf"] < 0.9 * errors["uniform"], errors
