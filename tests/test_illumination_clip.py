"""Issue 11: clipping, local illumination, pre-integration and early termination, against analytic answers and
the independent float64 reference (tests/reference.py), on the full-resolution buffer and the brick atlas."""
from __future__ import annotations

import json

import numpy as np
import pytest
from reference import delta_e, reference_render

import lodcast
from lodcast.renderer.kernel.preintegration import axis, preintegrate, segment_integral
from lodcast.renderer.lod.selection import select_lod
from lodcast.renderer.scene.scene import Scene, SceneError, TransferFunction

RED = {"points": [{"value": 0, "color": [1, 0, 0], "opacity": 0.1}, {"value": 2, "color": [1, 0, 0], "opacity": 0.1}],
       "unit_distance": 1.0}
ORTHO_X = {"eye": [-50, 3.5, 3.5], "target": [20, 3.5, 3.5], "up": [0, 0, 1], "projection": "orthographic",
           "view_height": 4}


@pytest.fixture(scope="module")
def slab_store(tmp_path_factory):
    """Constant 1, 8 x 8 x 40 (x runs 0..39: the box spans x in [-0.5, 39.5]); 8³ blocks, so LOD has levels."""
    return lodcast.ingest(np.ones((8, 8, 40), np.float32), tmp_path_factory.mktemp("slab") / "s.zarr", block_size=8)


def _alpha(store, scene, **kw):
    return lodcast.render(store, {"camera": ORTHO_X, "width": 8, "height": 8, "tf": RED, "format": "npy", **scene},
                          **kw).rgba[..., 3]


# ------------------------------------------------------------------------------------------------- clipping
@pytest.mark.parametrize("step", [0.3, 0.5, 1.0, 3.0, 7.3])
@pytest.mark.parametrize("quality", ["full", "lossless", {"reduction": 4}])
def test_clip_plane_and_box_cut_a_constant_slab_exactly(slab_store, step, quality):
    for clip, length in (({"planes": [{"point": [9.75, 0, 0], "normal": [1, 0, 0]}]}, 39.5 - 9.75),
                         ({"planes": [{"point": [31.2, 0, 0], "normal": [-2, 0, 0]}]}, 31.2 + 0.5),
                         ({"box": {"min": [5.3, -10, -10], "max": [20.1, 10, 10]}}, 20.1 - 5.3),
                         ({"planes": [{"point": [9.75, 0, 0], "normal": [1, 0, 0]}],
                           "box": {"min": [-3, -10, -10], "max": [20.1, 10, 10]}}, 20.1 - 9.75)):
        a = _alpha(slab_store, {"clip": clip, "quality": quality, "sampling": {"step": step}})
        np.testing.assert_allclose(a, 1 - 0.9**length, atol=2e-5, err_msg=f"{clip} step {step}")


def test_clip_that_keeps_nothing_renders_nothing(slab_store):
    assert _alpha(slab_store, {"clip": {"box": {"min": [50, 0, 0], "max": [60, 1, 1]}}}).max() == 0.0
    assert _alpha(slab_store, {"clip": {"planes": [{"point": [0, 0, 0], "normal": [0, 0, 1]},
                                                   {"point": [0, 0, -1], "normal": [0, 0, -1]}]}}).max() == 0.0


def _blob(shape=(20, 22, 24), seed=0):
    zz, yy, xx = np.mgrid[: shape[0], : shape[1], : shape[2]]
    c = np.array(shape)[::-1] / 2
    r2 = ((xx - c[0]) / 7.0) ** 2 + ((yy - c[1]) / 6.0) ** 2 + ((zz - c[2]) / 5.0) ** 2
    return np.exp(-r2).astype(np.float32)


BLOB_TF = {"points": [{"value": 0.1, "color": [0.9, 0.6, 0.3], "opacity": 0.0},
                      {"value": 0.6, "color": [0.3, 0.8, 1.0], "opacity": 0.5},
                      {"value": 1.0, "color": [1.0, 1.0, 1.0], "opacity": 0.9}]}


def test_oblique_clip_matches_the_float64_reference():
    vol = _blob()
    scene = {"camera": {"azimuth": 35, "elevation": 25, "distance": 2.2}, "width": 40, "height": 36, "tf": BLOB_TF,
             "clip": {"planes": [{"point": [12, 11, 10], "normal": [1, 0.4, -0.3]},
                                 {"point": [4, 4, 4], "normal": [0, 0, 1]}],
                      "box": {"min": [2.2, 0, -1], "max": [30, 17.6, 30]}},
             "sampling": {"step": 0.1, "early_termination": 1.0}, "format": "npy"}
    got = lodcast.render(vol, scene).rgba.astype(np.float64)
    want = reference_render(vol, scene)
    unclipped = reference_render(vol, {**scene, "clip": None})
    assert np.abs(want - unclipped).max() > 0.2  # the clip matters here
    assert np.abs(got - want).max() < 3e-3
    assert delta_e(got, want)["mean"] < 0.1


def test_crop_box_limits_the_selection_and_skips_blocks(tmp_path):
    st = lodcast.ingest(_blob((32, 32, 32)), tmp_path / "b.zarr", block_size=8)
    crop = {"box": {"min": [-1, -1, -1], "max": [12, 40, 40]}}  # x < 12: block columns 0 and 1 only
    scene = {"camera": {"azimuth": 0}, "width": 16, "height": 16, "tf": BLOB_TF, "quality": "lossless",
             "clip": crop, "format": "npy"}
    r = lodcast.render(st, scene)
    whole = lodcast.render(st, {**scene, "clip": None})
    assert r.report["bricks_skipped"] > whole.report["bricks_skipped"]
    from lodcast.renderer.scene.clip import block_mask

    keep = block_mask(st.grid, st.shape, st.spacing, st.origin, st.block_size, Scene.parse(scene).clip)
    assert keep[:, :, :2].all() and not keep[:, :, 2:].any()
    lv = select_lod(st, [BLOB_TF], "lossless", crop=keep).levels
    assert (lv[:, :, 2:] == -1).all() and (lv[:, :, :2] >= 0).any()


def test_clip_validation_names_the_field():
    with pytest.raises(SceneError, match=r"clip.planes.0.normal: must not be the zero vector"):
        Scene.parse({"tf": RED, "clip": {"planes": [{"point": [0, 0, 0], "normal": [0, 0, 0]}]}})
    with pytest.raises(SceneError, match=r"clip.box: min x"):
        Scene.parse({"tf": RED, "clip": {"box": {"min": [1, 0, 0], "max": [1, 1, 1]}}})
    with pytest.raises(SceneError, match=r"clip.planes"):
        Scene.parse({"tf": RED, "clip": {"planes": [{"point": [0, 0, 0], "normal": [1, 0, 0]}] * 7}})


# ------------------------------------------------------------------------------------------------- shading
def _ramp(shape=(12, 12, 24)):
    return np.broadcast_to(np.arange(shape[2], dtype=np.float32)[None, None, :] * 10.0, shape).copy()


RAMP_TF = {"points": [{"value": 0, "color": [0.6, 0.5, 0.4], "opacity": 0.05},
                      {"value": 240, "color": [0.6, 0.5, 0.4], "opacity": 0.05}], "unit_distance": 1.0}
LOOK_Y = {"eye": [11.5, -40, 5.5], "target": [11.5, 5, 5.5], "up": [0, 0, 1], "projection": "orthographic",
          "view_height": 8}


@pytest.mark.parametrize("light,ndl,ndh", [
    ("headlight", 0.0, 0.0),  # the ramp's normal (x) is perpendicular to the view (y)
    ([1, 0, 0], 1.0, np.sqrt(0.5)),  # h = normalize(l + v), v = -y
    ([1, -1, 0], np.sqrt(0.5), np.sin(np.pi / 8)),
])
def test_linear_ramp_lit_from_a_known_direction(light, ndl, ndh):
    vol = _ramp()
    k = {"ambient": 0.25, "diffuse": 0.6, "specular": 0.3, "shininess": 8, "light": light}
    base = {"camera": LOOK_Y, "width": 24, "height": 12, "tf": RAMP_TF, "format": "npy"}
    flat = lodcast.render(vol, base).rgba
    lit = lodcast.render(vol, {**base, "shading": k}).rgba
    np.testing.assert_array_equal(lit[..., 3], flat[..., 3])  # shading changes colour, never opacity
    c = np.array(RAMP_TF["points"][0]["color"])
    want_col = c * (k["ambient"] + k["diffuse"] * ndl) + k["specular"] * ndh ** k["shininess"]
    inner = flat[3:-3, 4:-4]  # columns whose gradient stencil stays inside the volume
    a = inner[..., 3:4]
    np.testing.assert_allclose(lit[3:-3, 4:-4, :3], a * want_col, rtol=2e-4, atol=1e-6)


def test_zero_gradient_is_unlit_and_the_threshold_holds():
    vol = np.full((10, 10, 10), 5.0, np.float32)
    tf = {"points": [{"value": 0, "color": [0.8, 0.4, 0.2], "opacity": 0.1}, {"value": 10, "color": [0.8, 0.4, 0.2],
                                                                               "opacity": 0.1}]}
    base = {"camera": {"azimuth": 20, "elevation": 10}, "width": 16, "height": 16, "tf": tf, "format": "npy"}
    flat = lodcast.render(vol, base).rgba
    lit = lodcast.render(vol, {**base, "shading": {"ambient": 0.2, "diffuse": 0.5, "specular": 0.9}}).rgba
    np.testing.assert_allclose(lit[..., :3], 0.7 * flat[..., :3], rtol=1e-5, atol=1e-7)  # col (ka + kd)
    ramp = _ramp()  # gradient 10 per world unit: below a threshold of 11 unlit, above 9 lit
    base = {"camera": LOOK_Y, "width": 24, "height": 12, "tf": RAMP_TF, "format": "npy"}
    k = {"ambient": 0.25, "diffuse": 0.6, "specular": 0.0, "light": [1, 0, 0]}
    f = lodcast.render(ramp, base).rgba[3:-3, 4:-4]
    hi = lodcast.render(ramp, {**base, "shading": {**k, "min_gradient": 11}}).rgba[3:-3, 4:-4]
    lo = lodcast.render(ramp, {**base, "shading": {**k, "min_gradient": 9}}).rgba[3:-3, 4:-4]
    np.testing.assert_allclose(hi[..., :3], 0.85 * f[..., :3], rtol=1e-5)
    np.testing.assert_allclose(lo[..., :3], 0.85 * f[..., :3], rtol=1e-5)  # n.l = 1 here: the same colour
    k2 = {**k, "light": [1, -1, 0]}  # n.l = 0.707: lit differs from unlit
    hi2 = lodcast.render(ramp, {**base, "shading": {**k2, "min_gradient": 11}}).rgba[3:-3, 4:-4]
    lo2 = lodcast.render(ramp, {**base, "shading": {**k2, "min_gradient": 9}}).rgba[3:-3, 4:-4]
    np.testing.assert_allclose(hi2[..., :3], 0.85 * f[..., :3], rtol=1e-5)
    np.testing.assert_allclose(lo2[..., :3], (0.25 + 0.6 * np.sqrt(0.5)) * f[..., :3], rtol=2e-4)


def test_gradients_continuous_across_a_level_change(tmp_path):
    """A linear ramp coarsens to the same ramp (block means of a linear field), and interblock interpolation
    between blocks of levels 0 and 1 reproduces it exactly: the shaded image equals level 0's. Nearest block takes
    its normals from the interblock field too (issue 45, item 4), so it does as well; from its own samples, clamped
    at the coarse blocks' faces (zero gradient there), it did not (> 1e-2)."""
    vol = _ramp((16, 16, 32))
    st = lodcast.ingest(vol, tmp_path / "r.zarr", block_size=8)
    levels = np.zeros(st.grid, np.int8)
    levels[:, :, 1::2] = 1  # alternate x columns of blocks at levels 0 and 1
    # the threshold (8 per world unit, the ramp's gradient is 10) makes the gradient's magnitude visible: a
    # gradient from nearest block's clamped samples is halved at coarse faces, and those samples come out unlit
    k = {"ambient": 0.2, "diffuse": 0.8, "specular": 0.0, "light": [1, -1, 0], "min_gradient": 8.0}
    cam = {"eye": [15.5, -40, 7.5], "target": [15.5, 5, 7.5], "up": [0, 0, 1], "projection": "orthographic",
           "view_height": 10}
    base = {"camera": cam, "width": 32, "height": 16, "tf": RAMP_TF, "format": "npy", "shading": k,
            "sampling": {"classification": "mean", "interpolation": "interblock"}}
    l0 = lodcast.render(st, base, levels=np.zeros(st.grid, np.int8)).rgba
    ii = lodcast.render(st, base, levels=levels).rgba
    nb = lodcast.render(st, {**base, "sampling": {"interpolation": "nearest_block", "classification": "mean"}},
                        levels=levels).rgba
    inner = (slice(4, -4), slice(2, -2))
    np.testing.assert_allclose(ii[inner], l0[inner], atol=2e-5)
    np.testing.assert_allclose(nb[inner], l0[inner], atol=2e-5)


def test_shaded_sphere_matches_its_normals():
    """An opaque ball lit from a known direction: a pixel's colour follows n.l of the sphere's normal there."""
    n = 40
    zz, yy, xx = np.mgrid[:n, :n, :n] - (n - 1) / 2
    vol = np.sqrt(xx**2 + yy**2 + zz**2).astype(np.float32)  # distance from the centre; the ball: < 14
    tf = {"points": [{"value": 13.5, "color": [1, 1, 1], "opacity": 1.0}, {"value": 14.5, "color": [1, 1, 1],
                                                                         "opacity": 0.0}]}
    c = (n - 1) / 2
    cam = {"eye": [c, -100, c], "target": [c, c, c], "up": [0, 0, 1], "projection": "orthographic", "view_height": 36}
    W = 36
    r = lodcast.render(vol, {"camera": cam, "width": W, "height": W, "tf": tf, "format": "npy",
                             "sampling": {"step": 0.25},
                             "shading": {"ambient": 0.0, "diffuse": 1.0, "specular": 0.0, "light": [1, -1, 1]}}).rgba
    px = (np.arange(W) + 0.5) / W * 36 - 18  # world offsets of the pixel centres
    X, Z = np.meshgrid(px, -px)
    R = 14.0
    inside = X**2 + Z**2 < (0.8 * R) ** 2
    Y = -np.sqrt(np.maximum(R**2 - X**2 - Z**2, 0))
    nrm = np.stack([X, Y, Z], -1) / R
    ndl = np.abs(nrm @ (np.array([1, -1, 1]) / np.sqrt(3)))
    got = r[..., 0] / np.maximum(r[..., 3], 1e-6)
    assert np.abs(got[inside] - ndl[inside]).mean() < 0.02
    assert np.abs(got[inside] - ndl[inside]).max() < 0.08


# ------------------------------------------------------------------------------------------- pre-integration
def _brute(tf, sf, sb, ratio, m=400_000):
    """float64 Riemann sum of the segment integral with exact per-substep opacity (converges as 1/m²)."""
    pts = tf["points"]
    v = np.array([p["value"] for p in pts])
    x = (np.arange(m) + 0.5) / m
    s = sf + (sb - sf) * x
    a = np.interp(s, v, [p["opacity"] for p in pts])
    c = np.stack([np.interp(s, v, [p["color"][k] for p in pts]) for k in range(3)], -1)
    with np.errstate(divide="ignore"):
        sig = -np.log1p(-np.minimum(a, 1.0)) * ratio / m
    tau = np.concatenate([[0.0], np.cumsum(sig)[:-1]])
    w = np.exp(-tau) * -np.expm1(-sig)
    return (w[:, None] * c).sum(0), -np.expm1(-sig.sum())


@pytest.mark.parametrize("a_hi", [0.5, 0.999999, 1.0])
def test_preintegration_table_entries_against_float64_integration(a_hi):
    tf = {"points": [{"value": 0, "color": [1, 0, 0], "opacity": 0.0}, {"value": 1, "color": [0, 1, 0], "opacity": 0.3},
                     {"value": 2, "color": [0, 0, 1], "opacity": a_hi}, {"value": 3, "color": [1, 1, 1], "opacity": 0.2}]}
    model = TransferFunction.model_validate(tf)
    rng = np.random.default_rng(3)
    cases = [(1.5, 1.5, 2.0), (0.0, 3.0, 1.0), (3.0, 0.0, 1.0), (-1.0, 4.0, 0.5), (0.2, 0.2, 7.0)]
    cases += [tuple(x) for x in np.c_[rng.uniform(-0.5, 3.5, (6, 2)), rng.uniform(0.1, 3, 6)]]
    for sf, sb, ratio in cases:
        C, alpha = segment_integral(model, sf, sb, ratio)
        Cb, ab = _brute(tf, sf, sb, ratio)
        tol = 2e-4 if a_hi == 1.0 else 2e-6  # the brute sum converges slowly at a = 1's singularity
        assert abs(alpha - ab) < tol, (sf, sb, ratio)
        np.testing.assert_allclose(C, Cb, atol=tol, err_msg=str((sf, sb, ratio)))


def test_preintegration_resolves_a_hard_step_exactly():
    tf = {"points": [{"value": 0, "color": [1, 0, 0], "opacity": 0.2}, {"value": 1, "color": [1, 0, 0], "opacity": 0.2},
                     {"value": 1, "color": [0, 0, 1], "opacity": 0.9}, {"value": 2, "color": [0, 0, 1], "opacity": 0.9}]}
    C, alpha = segment_integral(TransferFunction.model_validate(tf), 0.0, 2.0, 1.0)
    # half the segment at 0.2 (red), then half at 0.9 (blue): closed form
    a1, a2 = 1 - 0.8**0.5, 1 - 0.1**0.5
    assert abs(alpha - (1 - (1 - a1) * (1 - a2))) < 1e-12
    np.testing.assert_allclose(C, [a1, 0, (1 - a1) * a2], atol=1e-12)


def test_preintegration_axis_puts_every_control_point_on_a_grid_line():
    tf = TransferFunction.model_validate(HARD_STEP)
    lo, hi = -0.1, 1.3
    values, warp = axis(tf, lo, hi, 64)
    assert values.size == 64 and np.all(np.diff(values) > 0)
    table = preintegrate(tf, lo, hi, 1.0, 64)
    for v in (0.2, 0.5137, 0.9):  # the knots: lines; the hard step: two lines one table interval apart
        v32 = np.float32(v)  # the kernel's values and warp rows are float32
        below, above = table.coord(float(np.nextafter(v32, np.float32(-np.inf)))), table.coord(float(v32))
        assert abs(below - round(below)) < 1e-5 and abs(above - round(above)) < 1e-5
        assert abs(above - below - (1.0 if v == 0.5137 else 0.0)) < 1e-5
    np.testing.assert_allclose(values[np.rint(table.coord(values)).astype(int)], values, rtol=0, atol=1e-7)


HARD_STEP = {"points": [{"value": 0.2, "color": [1, 0.2, 0.1], "opacity": 0.0},
                        {"value": 0.5137, "color": [1, 0.2, 0.1], "opacity": 0.08},
                        {"value": 0.5137, "color": [0.2, 0.4, 1], "opacity": 0.7},
                        {"value": 0.9, "color": [0.2, 0.4, 1], "opacity": 0.7}]}


@pytest.mark.parametrize("outlier", [None, 200.0])
@pytest.mark.parametrize("step", [0.25, 1.0])
def test_preintegration_is_exact_on_a_ramp_through_a_hard_step(step, outlier):
    """A linear ramp through a hard TF step (at a value no uniform table axis would hit): pre-integration cuts each
    segment where the field crosses the step and looks each piece up on its own side, so its image matches the
    float64 reference, where point sampling places the step only to within a sampling step. With an outlier voxel
    the table spans a value range 170x the ramp's, so that a table interval is many segments wide (a uniform axis
    measured mean ΔE 14.6 there)."""
    x = np.linspace(0.0, 1.2, 48)
    vol = np.broadcast_to(x[None, None, :], (20, 24, 48)).astype(np.float32).copy()
    if outlier is not None:
        vol[0, 0, 0] = outlier
    scene = {"camera": {"azimuth": 70, "elevation": 25}, "width": 40, "height": 32, "tf": HARD_STEP,
             "format": "npy"}
    want = reference_render(vol, scene)
    s = {"step": step, "early_termination": 1.0}
    pre = lodcast.render(vol, {**scene, "sampling": {**s, "preintegration": True}}).rgba
    pt = lodcast.render(vol, {**scene, "sampling": s}).rgba
    e_pre, e_pt = delta_e(pre, want), delta_e(pt, want)
    # measured: no outlier 0.000 (point sampling 0.13 at step 1/4, 0.56 at 1); outlier 0.037 and 0.022 (max 3.9,
    # in the pixels whose rays pass the outlier's steep neighbourhood) against 0.07 and 0.55
    mean, mx = (0.005, 0.1) if outlier is None else (0.06, 6.0)
    assert e_pre["mean"] < mean and e_pre["mean"] < 0.6 * e_pt["mean"], (e_pre, e_pt)
    assert e_pre["max"] < mx, e_pre


@pytest.mark.parametrize("step", [0.37, 1.0, 3.0, 8.0])
def test_preintegrated_constant_slab_any_step_and_clipped(slab_store, step):
    a = _alpha(slab_store, {"sampling": {"step": step, "preintegration": True}})
    np.testing.assert_allclose(a, 1 - 0.9**40, atol=2e-5)
    a = _alpha(slab_store, {"sampling": {"step": step, "preintegration": True},
                            "clip": {"planes": [{"point": [9.75, 0, 0], "normal": [1, 0, 0]}]}})
    np.testing.assert_allclose(a, 1 - 0.9 ** (39.5 - 9.75), atol=2e-5)


def test_preintegration_beats_point_sampling_at_a_long_step():
    """A thin, high-frequency TF band on a smooth field: pre-integration stays near the float64 integral where
    point sampling misses the band between samples."""
    vol = _blob((20, 22, 24))
    tf = {"points": [{"value": 0.40, "color": [1, 0.5, 0.2], "opacity": 0.0},
                     {"value": 0.45, "color": [1, 0.6, 0.3], "opacity": 0.95},
                     {"value": 0.50, "color": [1, 0.7, 0.4], "opacity": 0.0}]}
    scene = {"camera": {"azimuth": 20, "elevation": 30, "distance": 2.2}, "width": 32, "height": 32, "tf": tf,
             "format": "npy"}
    want = reference_render(vol, scene)
    for step, bound in ((0.5, 0.5), (2.0, 5.0)):  # measured 0.36 and 3.7 (point sampling: 5.2 and 35)
        pre = lodcast.render(vol, {**scene, "sampling": {"step": step, "preintegration": True, "early_termination": 1}})
        pt = lodcast.render(vol, {**scene, "sampling": {"step": step, "early_termination": 1}})
        e_pre, e_pt = delta_e(pre.rgba, want)["mean"], delta_e(pt.rgba, want)["mean"]
        assert e_pre < 0.2 * e_pt and e_pre < bound, (step, e_pre, e_pt)
    assert pre.report["preintegration_ms"] is not None and "-DLC_PREINT" in pre.report["build_options"]


# ----------------------------------------------------------------------------------------- early termination
def test_early_termination_bias_is_bounded_and_opaque_reaches_one(slab_store):
    vol = _blob()
    tf = {"points": [{"value": 0.2, "color": [0.9, 0.8, 0.7], "opacity": 0.0},
                     {"value": 0.5, "color": [1.0, 0.9, 0.8], "opacity": 0.9}]}
    sc = {"camera": {"azimuth": 30, "elevation": 20}, "width": 48, "height": 40, "tf": tf, "format": "npy"}
    for step in (0.25, 0.5):
        d = lodcast.render(vol, {**sc, "sampling": {"step": step}}).rgba
        e = lodcast.render(vol, {**sc, "sampling": {"step": step, "early_termination": 1.0}}).rgba
        assert delta_e(d, e)["mean"] <= 0.1
        assert np.abs(d - e).max() <= 0.01 + 1e-6  # at most the transmittance left at termination
    opaque = dict(RED, points=[dict(p, opacity=0.9) for p in RED["points"]])
    a = lodcast.render(slab_store, {"camera": ORTHO_X, "width": 8, "height": 8, "tf": opaque, "format": "npy"}).rgba
    assert (a[..., 3] == 1.0).all()  # 1 - 0.1^40 is 1 in float32 as well; the terminated ray says so exactly


# ------------------------------------------------------------------------------------------ compiled features
def test_unused_features_are_compiled_out(slab_store):
    r = lodcast.render(slab_store, {"camera": ORTHO_X, "width": 4, "height": 4, "tf": RED, "format": "npy"})
    for opt in ("-DLC_SHADE", "-DLC_CLIP", "-DLC_PREINT"):
        assert opt not in r.report["build_options"]
    r = lodcast.render(slab_store, {"camera": ORTHO_X, "width": 4, "height": 4, "tf": RED, "format": "npy",
                                    "shading": {}, "sampling": {"preintegration": True},
                                    "clip": {"planes": [{"point": [1, 0, 0], "normal": [1, 0, 0]}]}})
    for opt in ("-DLC_SHADE", "-DLC_CLIP", "-DLC_PREINT"):
        assert opt in r.report["build_options"]
    r = lodcast.render(slab_store, {"camera": ORTHO_X, "width": 4, "height": 4, "tf": RED, "format": "npy",
                                    "clip": {"box": {"min": [1, -9, -9], "max": [9, 9, 9]}}})
    assert "-DLC_CLIP" not in r.report["build_options"]  # a crop box alone shrinks the box on the host


# -------------------------------------------------------------------------------------------------- presets
def test_a_preset_name_is_a_tf_in_every_scene():
    from lodcast.renderer.scene.presets import PRESETS

    sc = Scene.parse({"tf": "ct-bone", "tf2": None})
    assert sc.tf == TransferFunction.model_validate(PRESETS["ct-bone"])
    with pytest.raises(SceneError, match=r"tf: unknown preset 'bone'; known: auto, (ct-[a-z-]+, )*ct-bone"):
        Scene.parse({"tf": "bone"})
    assert Scene.parse(json.dumps({"tf": "ct-skin"})).tf.points[1].value == -400


def test_demo_lighting_is_the_shading_default():
    from lodcast.renderer.scene.scene import Shading
    from lodcast.renderer.tools.demo import SHADING

    assert Shading.model_validate(SHADING) == Shading()


@pytest.mark.parametrize("az,el", [(0, 0), (30, 15), (120, 25), (210, -40), (75, 89)])
def test_fit_distance_puts_every_box_corner_in_the_picture(az, el):
    from reference import project_point

    from lodcast.renderer.scene.camera import box_world, fit_distance

    shape, spacing = (40, 90, 60), (2.0, 0.7, 1.1)
    lo, hi = box_world(shape, spacing, (0, 0, 0))
    W, H = 64, 64
    corners = [(x, y, z) for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]

    def extent(dist):  # the furthest corner from the image centre, in half-widths
        cam = {"azimuth": az, "elevation": el, "distance": dist, "fov": 30}
        pts = np.array([project_point(cam, W, H, c, shape, spacing) for c in corners])
        return np.abs((pts + 0.5) / np.array([H, W]) * 2 - 1).max()

    d = fit_distance(lo, hi, az, el)
    assert extent(d) == pytest.approx(0.95, abs=1e-6)  # the 5% margin, exactly, on the tightest corner
    assert extent(0.9 * d) > 1.0  # and no closer distance would do


def test_shading_weighted_by_gradient_magnitude():
    """The ramp's gradient is 10 per world unit: with gradient_weighting 20 the colour lies half-way between the
    unlit col (ka + kd) and the lit one; with 5 (or none) it is fully lit."""
    ramp = _ramp()
    base = {"camera": LOOK_Y, "width": 24, "height": 12, "tf": RAMP_TF, "format": "npy"}
    k = {"ambient": 0.25, "diffuse": 0.6, "specular": 0.0, "light": [1, -1, 0], "min_gradient": 1.0}
    f = lodcast.render(ramp, base).rgba[3:-3, 4:-4, :3]
    lit, unlit = 0.25 + 0.6 * np.sqrt(0.5), 0.85
    half = lodcast.render(ramp, {**base, "shading": {**k, "gradient_weighting": 20.0}}).rgba[3:-3, 4:-4, :3]
    full = lodcast.render(ramp, {**base, "shading": {**k, "gradient_weighting": 5.0}}).rgba[3:-3, 4:-4, :3]
    np.testing.assert_allclose(half, 0.5 * (lit + unlit) * f, rtol=2e-4)
    np.testing.assert_allclose(full, lit * f, rtol=2e-4)
