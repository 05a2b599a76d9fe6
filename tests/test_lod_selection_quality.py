"""Thesis fig. 3.4 on a real CT volume: at 64:1, TF-based block significance (eq. 3.1) selects levels whose
image is closer to the full-resolution reference than data-error (L2) significance and uniform level
reduction, measured as DESIGN.md's mean ΔE of the rendered images."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import lodcast
from lodcast.renderer.image_error import delta_e_stats
from lodcast.renderer.scene import Scene
from lodcast.renderer.selection import select_lod
from lodcast.renderer.transfer_function import CT_PRESETS

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
    # measured here: tf 12.6, l2 16.0, uniform 21.1; the ordering is the claim, held with a 10 % margin
    assert errors["tf"] < 0.9 * errors["l2"], errors
    assert errors["tf"] < 0.9 * errors["uniform"], errors


# chest CT (ct_chest_dicom, 275x512x512 HU) with the CT presets, each with the margin its ordering holds by
CT_MARGINS = {"ct-bone": 0.9, "ct-skin": 0.95}


@pytest.fixture(scope="module")
def ct16(tmp_path_factory: pytest.TempPathFactory, shared_data: Path):
    """The chest CT with the thesis' 16³ blocks."""
    return lodcast.ingest(shared_data / "ct_chest_dicom", tmp_path_factory.mktemp("ct") / "ct16.zarr", block_size=16,
                          progress=False)


def test_fig_3_4_ordering_on_the_chest_ct_with_the_thesis_block_size(ct16):
    """The same claim on a patient CT, with the thesis' 16³ blocks. Measured at 128²: bone tf 9.2, l2 11.7,
    uniform 22.8; skin tf 13.3, l2 14.4, uniform 16.7 (margins 10 % and 5 %). With lodcast's default 32³ blocks
    the bone case reverses (tf 18.6 vs l2 14.2 at 256²): a 32³ block holding a few rib voxels has a small RMS ΔE
    and is coarsened whole, see the issue 5 note."""
    store = ct16
    for name, margin in CT_MARGINS.items():
        tf = CT_PRESETS[name]
        scene = {"camera": {"azimuth": 30, "elevation": 15, "distance": 1.9}, "width": 128, "height": 128, "tf": tf,
                 "format": "npy", "sampling": {"step": 0.5, "interpolation": "nearest_block"}}
        ref = lodcast.render(store, {**scene, "sampling": {"step": 0.25}})
        errors = {}
        for method in ("tf", "l2", "uniform"):
            sel = select_lod(store, [Scene.parse(scene).tf], {"reduction": 64}, method=method)
            assert sel.reduction >= 63.5, (name, method, sel.reduction)
            img = lodcast.render(store, {**scene, "quality": {"reduction": 64}}, levels=sel.levels)
            errors[method] = delta_e_stats(img.rgba, ref.rgba)["mean"]
        assert errors["tf"] < margin * errors["l2"], (name, errors)
        assert errors["tf"] < margin * errors["uniform"], (name, errors)


def test_virtually_lossless_is_exact(ct16):
    """Virtually lossless (every block the TF can see, at full resolution, and nothing else) with interblock
    interpolation gives the full-resolution image: a block left out has a border-inclusive range where the TF is
    zero, so its neighbours' facing voxels are transparent too and nothing interpolates across. On the chest CT
    with the bone preset that leaves out 4.3:1 of the data at 16³ blocks (7.3:1 at 8³: bench_lod_quality.py)."""
    scene = {"camera": {"azimuth": 30, "elevation": 15, "distance": 1.9}, "width": 128, "height": 128,
             "tf": CT_PRESETS["ct-bone"], "format": "npy", "sampling": {"step": 0.5}}
    full = lodcast.render(ct16, scene)
    lossless = lodcast.render(ct16, {**scene, "quality": "lossless",
                                     "sampling": {"step": 0.5, "interpolation": "interblock"}})
    assert lossless.report["reduction"] >= 4.0, lossless.report["reduction"]
    assert lossless.report["bricks_skipped"] > 0.6 * ct16.layout.n_blocks
    assert full.rgba[..., 3].max() > 0.9  # the bone is there to be lost
    np.testing.assert_allclose(lossless.rgba, full.rgba, atol=1e-4, rtol=0)
