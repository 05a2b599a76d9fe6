"""Gradient opacity (a TF's `gradient_opacity`): the TF's extinction scaled by min(1, |gradient| / gradient_opacity).

On a linear ramp the gradient is the same everywhere a ray samples (away from the faces across the ramp), so the
weight w is a constant and the render must equal the plain render of the same TF with its extinction scaled by w,
i.e. its unit distance divided by w (DESIGN's opacity per unit distance), which the host tabulates in float64."""
from __future__ import annotations

import numpy as np
import pytest
from scenes import axis_camera

import lodcast
from lodcast.renderer.scene.scene import SceneError

SHAPE = (24, 20, 32)  # z, y, x: the ramp runs along x, the rays along z


def ramp(slope: float) -> np.ndarray:
    return np.broadcast_to(slope * np.arange(SHAPE[2], dtype=np.float32), SHAPE).copy()


def tf(unit: float = 1.0, gradient_opacity: float | None = None) -> dict:
    pts = [{"value": 0.0, "color": [0.2, 0.5, 1.0], "opacity": 0.12},
           {"value": 80.0, "color": [1.0, 0.6, 0.1], "opacity": 0.12}]
    out: dict = {"points": pts, "unit_distance": unit}
    if gradient_opacity is not None:
        out["gradient_opacity"] = gradient_opacity
    return out


def render(vol: np.ndarray, t: dict, **kw) -> lodcast.RenderResult:
    scene = {"camera": axis_camera("z", vol.shape), "width": 24, "height": 24, "tf": t, "format": "npy",
             "sampling": {"step": 0.5, "early_termination": 1.0}, **kw}
    return lodcast.render(vol, scene)


@pytest.mark.parametrize("w", [0.5, 0.2])
def test_a_weak_gradient_scales_the_extinction(w):
    slope = 2.0  # data units per voxel = per world unit (spacing 1): |gradient| = 2 everywhere inside
    got = render(ramp(slope), tf(1.0, gradient_opacity=slope / w))
    want = render(ramp(slope), tf(1.0 / w))  # extinction x w = unit distance / w
    assert "-DLC_GRADIENT_OPACITY" in got.report["build_options"]
    assert "-DLC_GRADIENT_OPACITY" not in want.report["build_options"]
    a, b = got.rgba.astype(np.float64), want.rgba.astype(np.float64)
    assert b[..., 3].min() > 0.2  # something to compare: every ray crosses 24 voxels of the ramp
    assert np.abs(a - b).max() <= 2e-5 and np.abs(a - b).mean() <= 2e-6
    plain = render(ramp(slope), tf(1.0))
    assert (plain.rgba[..., 3] - a[..., 3]).min() > 0.05  # the weight took opacity away everywhere


def test_a_strong_gradient_leaves_the_tf_as_it_is():
    vol = ramp(3.0)
    got = render(vol, tf(1.0, gradient_opacity=1.5))  # |gradient| 3 >= 1.5: weight 1
    want = render(vol, tf(1.0))
    assert np.array_equal(got.rgba, want.rgba)
    assert got.report["samples"] == want.report["samples"]


def test_a_homogeneous_region_disappears():
    vol = np.full(SHAPE, 40.0, np.float32)  # no gradient at all
    assert render(vol, tf(1.0)).rgba[..., 3].min() > 0.9
    assert render(vol, tf(1.0, gradient_opacity=1.0)).rgba.max() == 0.0


def test_each_transfer_function_has_its_own():
    """The second TF's weight is its own: the dual render equals one where only the first TF's is set, when the
    second's gradient opacity is below the gradient (weight 1)."""
    vol = ramp(2.0)
    t2 = {"points": [{"value": 30.0, "color": [1, 1, 1], "opacity": 0.0},
                     {"value": 40.0, "color": [1, 1, 1], "opacity": 0.5}]}
    a = render(vol, tf(1.0, gradient_opacity=4.0), tf2={**t2, "gradient_opacity": 1.0})
    b = render(vol, tf(1.0, gradient_opacity=4.0), tf2=t2)
    c = render(vol, tf(1.0, gradient_opacity=4.0), tf2={**t2, "gradient_opacity": 8.0})
    assert np.array_equal(a.rgba, b.rgba)
    assert np.abs(a.rgba - c.rgba).max() > 1e-3


@pytest.mark.parametrize("bad", [0.0, -1.0, float("inf")])
def test_refused_unless_positive_and_finite(bad):
    with pytest.raises(SceneError, match="gradient_opacity"):
        render(ramp(1.0), tf(1.0, gradient_opacity=bad))


def test_composite_only():
    with pytest.raises(SceneError, match="gradient"):
        render(ramp(1.0), tf(1.0, gradient_opacity=1.0), mode="mip")
