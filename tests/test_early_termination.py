"""Early termination within its bound (docs/design.md; issue 45, item 6): the default moves a composite image by at
most 0.1 mean ΔE against the same render with `early_termination: 1.0` at step ½, translucent TFs included. A ray
ends with what is left of it filled in its last colour, so the error grows with how far the TF's colours spread:
the threshold is tightened for TFs of widely differing colours (params.early_stop), and kept for one-hue TFs."""
from __future__ import annotations

import math
from pathlib import Path

import pytest

import lodcast
from lodcast.renderer.image.delta_e import delta_e_stats
from lodcast.renderer.kernel import params
from lodcast.renderer.scene.scene import Scene
from lodcast.renderer.scene.transfer_function import CT_PRESETS


def test_the_threshold_follows_the_colour_spread():
    bone = Scene.parse({"tf": CT_PRESETS["ct-bone"]})
    assert params.colour_spread(bone.tf) == pytest.approx(0.25)
    assert params.early_stop(bone) == pytest.approx(0.99)  # one hue: as given, so its cost is unchanged
    skin_bone = Scene.parse({"tf": CT_PRESETS["ct-skin-bone"]})
    assert params.colour_spread(skin_bone.tf) == pytest.approx(0.7)  # pink skin, red tissue, white bone
    assert 1.0 - params.early_stop(skin_bone) == pytest.approx(0.01 * 0.25 / 0.7)
    assert params.early_stop(Scene.parse({"tf": CT_PRESETS["ct-skin-bone"],
                                          "sampling": {"early_termination": 1.0}})) == 1.0
    lit = Scene.parse({"tf": CT_PRESETS["ct-bone"], "shading": {}})  # (lighting is left out: see early_stop)
    assert params.early_stop(lit) == pytest.approx(0.99)
    mip = Scene.parse({"tf": CT_PRESETS["ct-skin-bone"], "mode": "mip"})
    assert params.early_stop(mip) == 0.99


@pytest.fixture(scope="module")
def chest(tmp_path_factory: pytest.TempPathFactory, shared_data: Path):
    return lodcast.ingest(shared_data / "ct_chest_dicom", tmp_path_factory.mktemp("ct") / "ct.zarr", progress=False)


@pytest.mark.parametrize("view", [(30, 15), (200, -20)])
def test_default_moves_skin_over_bone_by_at_most_its_bound(eng, chest, monkeypatch, view):
    """ct-skin-bone on the chest CT: translucent skin in front of red tissue and white bone. With the threshold as
    given (the rule off) the default moved these images by 0.138 and 0.118 mean ΔE."""
    sc = {"camera": {"azimuth": view[0], "elevation": view[1], "distance": 1.9}, "width": 128, "height": 128,
          "tf": CT_PRESETS["ct-skin-bone"], "format": "npy", "sampling": {"step": 0.5}}
    off = eng.render(chest, {**sc, "sampling": {"step": 0.5, "early_termination": 1.0}})
    default = eng.render(chest, sc)
    assert delta_e_stats(default.rgba, off.rgba)["mean"] <= 0.1
    assert default.report["samples"] < 0.5 * off.report["samples"]  # it still ends rays early
    monkeypatch.setattr(params, "ET_SPREAD", math.inf)  # the threshold as given: what this replaces
    as_given = eng.render(chest, sc)
    assert delta_e_stats(as_given.rgba, off.rgba)["mean"] > 0.1
