"""Issue 12, dual-TF compositing (thesis §3.6.2, item 3): two TFs integrated concurrently in one pass, the second
integral composited over the first, and the priority map that restores early termination — against analytic
answers, the float64 reference extended to two integrals, and the host composite of two single-TF renders."""
from __future__ import annotations

import numpy as np
import pytest
from reference import delta_e, reference_render

import lodcast
from lodcast.renderer.data.atlas import neighbourhood_max
from lodcast.renderer.frame.render import prepare
from lodcast.renderer.lod.dual import dilate_bits, priority_map, visibility_bits
from lodcast.renderer.scene import camera as cam
from lodcast.renderer.scene.scene import Scene, SceneError


def _tf(lo, hi, rgb, a, unit=None):
    d = {"points": [{"value": lo, "color": rgb, "opacity": 0.0}, {"value": hi, "color": rgb, "opacity": a}]}
    if unit is not None:
        d["unit_distance"] = unit
    return d


def _flat(v, rgb, a, unit=None):
    d = {"points": [{"value": v, "color": rgb, "opacity": a}]}
    if unit is not None:
        d["unit_distance"] = unit
    return d


def _over(top: np.ndarray, under: np.ndarray) -> np.ndarray:
    """Premultiplied `top` composited over `under`, float64."""
    top, under = np.asarray(top, np.float64), np.asarray(under, np.float64)
    return top + (1.0 - top[..., 3:4]) * under


def _blob(shape=(24, 26, 28)):
    zz, yy, xx = np.mgrid[: shape[0], : shape[1], : shape[2]].astype(np.float64)
    c = np.array(shape, np.float64)[::-1] / 2
    r2 = ((xx - c[0]) / 8.0) ** 2 + ((yy - c[1]) / 7.0) ** 2 + ((zz - c[2]) / 6.0) ** 2
    v = np.exp(-r2)
    v += 0.8 * np.exp(-(((xx - 18) / 2.0) ** 2 + ((yy - 9) / 2.0) ** 2 + ((zz - 14) / 2.0) ** 2))  # a dense insert
    return v.astype(np.float32)


SHELL = _tf(0.15, 0.5, [0.9, 0.6, 0.4], 0.35)  # tf: the body, translucent
CORE = _tf(0.95, 1.2, [0.2, 0.5, 1.0], 0.9, unit=0.5)  # tf2: the dense insert, with its own unit distance


# ------------------------------------------------------------------------------------------------- analytic
@pytest.mark.parametrize("step", [0.5, 0.7, 3.0])
def test_constant_volume_second_integral_over_the_first(step):
    """A constant volume seen along x (orthographic): each integral is 1 - (1 - a)^(L / unit) exactly, and the
    image is the second composited over the first, whatever the step (the last, shorter segment included) and
    with different unit distances for the two TFs."""
    vol = np.full((6, 6, 23), 2.0, np.float32)  # x spans [-0.5, 22.5]: L = 23
    c1, a1, u1, c2, a2, u2 = np.array([1.0, 0.5, 0.0]), 0.05, 1.0, np.array([0.0, 0.3, 1.0]), 0.02, 2.5
    scene = {"camera": {"eye": [-40, 2.5, 2.5], "target": [10, 2.5, 2.5], "up": [0, 0, 1],
                        "projection": "orthographic", "view_height": 3},
             "width": 4, "height": 4, "format": "npy", "tf": _flat(2.0, list(c1), a1, u1),
             "tf2": _flat(2.0, list(c2), a2, u2), "sampling": {"step": step, "early_termination": 1.0}}
    got = lodcast.render(vol, scene).rgba.astype(np.float64)
    al1, al2 = 1 - (1 - a1) ** (23 / u1), 1 - (1 - a2) ** (23 / u2)
    want = np.array([*(c2 * al2 + (1 - al2) * c1 * al1), 1 - (1 - al1) * (1 - al2)])
    np.testing.assert_allclose(got.reshape(-1, 4), np.tile(want, (16, 1)), atol=2e-6, rtol=0)


def test_dual_tf_matches_the_float64_reference_with_two_integrals():
    vol = _blob()
    scene = {"camera": {"azimuth": 35, "elevation": 25, "distance": 2.5}, "width": 48, "height": 48, "tf": SHELL, "tf2": CORE,
             "format": "npy", "sampling": {"step": 0.25, "early_termination": 1.0}}
    ref = reference_render(vol, scene)
    got = lodcast.render(vol, scene)
    e = delta_e(got.rgba, ref)
    assert e["footprint"] > 500
    assert e["mean"] < 0.03 and e["p95"] < 0.05, e  # measured 0.008 / 0.012 (max 1.1 at the insert's rim)
    assert np.abs(got.rgba - ref).max() < 0.006
    # the second integral is really there: the reference of tf alone differs where the insert is
    alone = reference_render(vol, {**scene, "tf2": None})
    assert delta_e(alone, ref)["max"] > 20


# ------------------------------------------------------------------------- one pass = two integrals, every path
@pytest.fixture(scope="module")
def blob_store(tmp_path_factory):
    return lodcast.ingest(_blob((32, 32, 32)), tmp_path_factory.mktemp("dual") / "b.zarr", block_size=8)


CASES = {
    "full": {},
    "atlas-nb": {"sampling": {"interpolation": "nearest_block"}, "levels": True},
    "atlas-ii-dist": {"levels": True},
    "atlas-ii-mean-adaptive": {"sampling": {"classification": "mean", "adaptive_object": True}, "levels": True},
    "preint-shaded": {"sampling": {"preintegration": True}, "shading": {}},
    "lod-preint-shaded": {"sampling": {"preintegration": True}, "shading": {}, "levels": True},
    "precise": {"sampling": {"step": 0.008}, "width": 12, "height": 12},
    "jitter-clip-bg": {"sampling": {"jitter": True, "seed": 3},
                       "clip": {"planes": [{"point": [16, 16, 16], "normal": [1, 0.3, 0]}]},
                       "background": [0.1, 0.2, 0.3, 1.0]},
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_one_pass_equals_the_composite_of_two_single_tf_renders(blob_store, case):
    """Without early termination the concurrent integrals are each the single-TF render of their TF over the same
    samples, so the dual image is tf2's image over tf's — on every sampler, classification and integrator path
    (the second TF runs the same code with its own tables and unit distance)."""
    extra = dict(CASES[case])
    use_levels = extra.pop("levels", False)
    samp = {"early_termination": 1.0, **extra.pop("sampling", {})}
    bg = extra.pop("background", None)
    base = {"camera": {"azimuth": 20, "elevation": 15, "distance": 2.5}, "width": 32, "height": 32, "format": "npy",
            "tf": SHELL, "sampling": samp, **extra}
    kw = {}
    if use_levels:  # mixed levels (the same for every render: the selection of one TF differs from two's)
        g = np.indices(blob_store.grid).sum(axis=0)
        kw["levels"] = (g % 3).astype(np.int8)
    one = lodcast.render(blob_store, base, **kw).rgba
    two = lodcast.render(blob_store, {**base, "tf": CORE}, **kw).rgba
    dual = lodcast.render(blob_store, {**base, "tf2": CORE, **({"background": bg} if bg else {})}, **kw)
    want = _over(two, one)
    if bg:
        want = _over(want, np.array([bg[0] * bg[3], bg[1] * bg[3], bg[2] * bg[3], bg[3]]))
    assert "-DLC_TF2" in dual.report["build_options"]
    assert two[..., 3].max() > 5e-3 and one[..., 3].max() > 0.1  # both TFs show something
    np.testing.assert_allclose(dual.rgba, want, atol=3e-5, rtol=0)


# ------------------------------------------------------------------------------------------------ priority map
def _body_and_insert(shape=(64, 64, 64)):
    """A body (values up to 0.5, filling most of the box) and a small dense insert (up to 1.15) inside one 16³
    block near a corner (centre x, y, z = 40, 20, 40)."""
    zz, yy, xx = np.mgrid[: shape[0], : shape[1], : shape[2]].astype(np.float64)
    c = np.array(shape, np.float64)[::-1] / 2
    r = np.sqrt(((xx - c[0]) / (0.4 * shape[2])) ** 2 + ((yy - c[1]) / (0.4 * shape[1])) ** 2
                + ((zz - c[2]) / (0.4 * shape[0])) ** 2)
    v = 0.5 / (1.0 + np.exp((r - 1.0) * 12.0))
    v = np.maximum(v, 1.15 * np.exp(-((xx - 40) ** 2 + (yy - 20) ** 2 + (zz - 40) ** 2) / 18.0))
    return v.astype(np.float32)


def _opaque_scene(**kw):
    body = _tf(0.1, 0.3, [0.9, 0.7, 0.6], 0.95)  # nearly opaque: rays saturate early in the first integral
    return {"camera": {"azimuth": 30, "elevation": 20, "distance": 2.5}, "width": 64, "height": 64, "format": "npy", "tf": body,
            "tf2": CORE, **kw}


def test_priority_map_changes_nothing_and_ends_rays_where_tf2_is_absent():
    vol = _body_and_insert()
    on = lodcast.render(vol, _opaque_scene())
    off = lodcast.render(vol, _opaque_scene(sampling={"priority_map": False}))
    e = delta_e(on.rgba, off.rgba)
    assert e["mean"] <= 0.2 and np.abs(on.rgba - off.rgba).max() <= 1e-6  # zero priority: tf2 adds nothing there
    pm = on.report["priority_map"]
    assert off.report["priority_map"] is None
    assert 0.0 < pm["priority_pixels"] < 0.5  # tf2 occupies a small region
    assert on.report["samples"] < off.report["samples"]  # early termination is back where tf2 is absent
    assert pm["samples_priority"] + pm["samples_other"] == on.report["samples"]
    # and the tf2 content is really drawn: the insert shows through the opaque body
    body_only = lodcast.render(vol, _opaque_scene(tf2=None))
    assert delta_e(on.rgba, body_only.rgba)["max"] > 20
    shown = lodcast.render(vol, _opaque_scene(tf=CORE, tf2=None)).rgba[..., 3] > 0
    assert shown.sum() > 4 and not (shown & ~lodcast.renderer.frame.render.prepare(vol, _opaque_scene()).priority.pixels(64, 64)).any()


def test_without_empty_space_skipping_the_priority_map_saves_more():
    vol = _body_and_insert()
    s = {"empty_space_skipping": False}
    on = lodcast.render(vol, _opaque_scene(sampling=s))
    off = lodcast.render(vol, _opaque_scene(sampling={**s, "priority_map": False}))
    assert np.abs(on.rgba - off.rgba).max() <= 1e-6
    assert on.report["samples"] < 0.9 * off.report["samples"]  # the thesis' case: rays ran to the end (0.83)


@pytest.mark.parametrize("seed", range(6))
def test_priority_map_covers_every_pixel_tf2_shows(seed):
    """Property over random cameras (perspective, orthographic, close up): every pixel where tf2 alone leaves any
    opacity lies in the map."""
    rng = np.random.default_rng(seed)
    vol = _body_and_insert()
    far = True
    if seed % 3 == 2:
        camera = {"eye": list(rng.uniform(-30, 60, 3)), "target": [19, 17, 15], "up": [0, 0, 1],
                  "projection": "orthographic", "view_height": float(rng.uniform(10, 40))}
    else:
        camera = {"azimuth": float(rng.uniform(0, 360)), "elevation": float(rng.uniform(-80, 80)),
                  "distance": float(rng.uniform(0.6, 3.0)), "fov": float(rng.uniform(20, 70))}
        far = camera["distance"] > 1.5
    W, H = int(rng.integers(17, 70)), int(rng.integers(17, 70))
    scene = {"camera": camera, "width": W, "height": H, "format": "npy", "tf": SHELL, "tf2": CORE}
    pr = prepare(vol, scene)
    assert pr.priority is not None
    shown = lodcast.render(vol, {**scene, "tf": CORE, "tf2": None}).rgba[..., 3] > 0
    covered = pr.priority.pixels(W, H)
    assert not (shown & ~covered).any()
    if far:
        assert covered.mean() < 0.5  # not everything: the insert is small


def test_priority_map_of_a_box_behind_the_eye_is_everything():
    fr = cam.look_at(np.array([5.0, 5.0, 5.0]), np.array([5.0, 20.0, 5.0]), np.array([0.0, 0.0, 1.0]), 40, 16, 16)
    mask = np.ones((1, 1, 1), bool)  # a 10³ box around the eye
    pm = priority_map(fr, mask, (10, 10, 10), (1, 1, 1), (0, 0, 0), 16, 16, 16)
    assert pm.tiles.all()
    none = priority_map(fr, np.zeros((1, 1, 1), bool), (10, 10, 10), (1, 1, 1), (0, 0, 0), 16, 16, 16)
    assert not none.tiles.any()


# ------------------------------------------------------------------------------------- selection and skipping
def test_a_block_only_tf2_sees_is_loaded_and_rendered(tmp_path):
    vol = np.full((32, 32, 32), 0.6, np.float32)  # above tf's band and below tf2's: invisible to both
    vol[4:28, 4:28, 4:12] = 0.3  # what tf shows
    vol[18:22, 18:22, 20:26] = 1.0  # what only tf2 shows, in blocks tf leaves empty
    st = lodcast.ingest(vol, tmp_path / "v.zarr", block_size=8)
    tf = {"points": [{"value": 0.1, "color": [1, 0.8, 0.6], "opacity": 0.0},
                     {"value": 0.3, "color": [1, 0.8, 0.6], "opacity": 0.4},
                     {"value": 0.5, "color": [1, 0.8, 0.6], "opacity": 0.0}]}  # blind to 1.0
    scene = {"camera": {"azimuth": 70, "elevation": 10}, "width": 48, "height": 48, "format": "npy", "tf": tf,
             "tf2": CORE, "quality": {"reduction": 2}}
    pr = prepare(st, scene)
    bz, by, bx = 18 // 8, 18 // 8, 20 // 8
    assert pr.lod.levels[bz, by, bx] >= 0  # loaded for tf2
    assert int(pr.block_info[bz, by, bx]) & 2
    alone = prepare(st, {**scene, "tf2": None})
    assert alone.lod.levels[bz, by, bx] < 0  # tf alone would not load it
    dual = lodcast.render(st, scene).rgba
    only2 = lodcast.render(st, {**scene, "tf": CORE, "tf2": None, "quality": "full"}).rgba
    seen = only2[..., 3] > 0.2
    assert seen.sum() > 10
    assert (dual[seen, 2] > 0.5 * only2[seen, 2]).all()  # tf2's blue shows wherever tf2 alone shows


def test_visibility_bits_dilate_each_bit_on_its_own():
    info = np.zeros((3, 3, 3), np.float32)
    info[0, 0, 0] = 1  # tf
    info[2, 2, 2] = 2  # tf2
    d = dilate_bits(visibility_bits(info == 1, info == 2), neighbourhood_max)
    assert d[1, 1, 1] == 3  # sees both neighbours: the max of the flags (2) would drop tf's bit
    assert d[0, 0, 0] == 1 and d[2, 2, 2] == 2


def test_tf2_is_compiled_out_when_absent_and_validated():
    vol = _blob((16, 16, 16))
    r = lodcast.render(vol, {"tf": SHELL, "width": 8, "height": 8, "format": "npy"})
    assert "-DLC_TF2" not in r.report["build_options"] and r.report["priority_map"] is None
    assert r.report["tf2"] is False
    with pytest.raises(SceneError, match=r"^tf2: .*composite"):
        Scene.parse({"tf": SHELL, "tf2": CORE, "mode": "mip"})
    with pytest.raises(SceneError, match=r"tf2"):
        Scene.parse({"tf": SHELL, "tf2": "no-such-preset"})
    assert Scene.parse({"tf": "ct-body", "tf2": "ct-dense"}).tf2 is not None


def test_lodcast_report_shows_what_the_priority_map_buys(blob_store):
    from lodcast.renderer.tools.quality_report import Variant, default_variants, run_report

    vs = default_variants(adaptive=False, steps=False, dual=True)
    off = [v for v in vs if not v.priority_map]
    assert [v.quality for v in off] == ["full", {"reduction": 30}] and "no priority map" in off[0].label
    assert off[0].apply({"tf": SHELL})["sampling"]["priority_map"] is False
    assert all(v.priority_map for v in default_variants(adaptive=False, steps=False))
    scene = {"camera": {"azimuth": 20, "elevation": 15, "distance": 2.5}, "width": 24, "height": 24, "tf": SHELL, "tf2": CORE}
    res = run_report(blob_store, scene, [Variant("full"), Variant("full", priority_map=False)], repeat=1,
                     log=lambda m: None)
    on, plain = res["rows"]
    assert 0 < on["priority_pixels"] <= 1 and plain["priority_pixels"] is None
    assert on["delta_e_mean"] == pytest.approx(plain["delta_e_mean"], abs=1e-6)
    assert plain["speedup_vs_full"] == pytest.approx(on["kernel_ms"] / plain["kernel_ms"])
