"""Issue 11, item 5: blend modes beside composite and MIP — MinIP, average intensity and isosurface — against
float64 references (tests/reference.py's exact MIP, a converged mean along each ray, a sphere's analytic surface),
each compiled in by its own -D option."""
from __future__ import annotations

import numpy as np
import pytest
from reference import box_bounds, camera_rays, reference_render, sample_field

import lodcast
from lodcast.renderer.scene.scene import SceneError

TF = {"points": [{"value": 0.0, "color": [1, 0.2, 0], "opacity": 0.9}, {"value": 1.0, "color": [0, 0.5, 1],
                                                                       "opacity": 0.3}]}
CAM = {"azimuth": 25, "elevation": 20, "distance": 2.6}


def _field(shape=(14, 16, 18), seed=5):
    rng = np.random.default_rng(seed)
    zz, yy, xx = np.mgrid[: shape[0], : shape[1], : shape[2]]
    v = 0.5 + 0.3 * np.sin(xx / 3.0) * np.cos(yy / 4.0) + 0.15 * np.sin(zz / 2.5) + 0.05 * rng.standard_normal(shape)
    return v.astype(np.float32)


def _mirrored(tf: dict) -> dict:
    """TF'(-v) = TF(v): MinIP of a volume with tf is MIP of its negative with TF'."""
    return {"points": [{**p, "value": -p["value"]} for p in reversed(tf["points"])]}


def test_minip_matches_the_exact_minimum():
    vol = _field()
    scene = {"camera": CAM, "width": 24, "height": 20, "tf": TF, "mode": "minip", "format": "npy",
             "sampling": {"step": 0.05}}
    got = lodcast.render(vol, scene)
    want = reference_render(-vol, {**scene, "mode": "mip", "tf": _mirrored(TF)})
    assert "-DLC_MINIP" in got.report["build_options"]
    foot = want[..., 3] > 0
    assert foot.sum() > 200
    assert np.abs(got.rgba - want).max() < 5e-3
    mip = lodcast.render(vol, {**scene, "mode": "mip"}).rgba
    assert np.abs(mip - got.rgba).max() > 0.2  # not MIP's image


def test_minip_block_walk_changes_nothing(tmp_path):
    vol = _field((32, 32, 32))
    vol[:16] += 2.0  # half the volume cannot hold the minimum: its blocks are skipped
    st = lodcast.ingest(vol, tmp_path / "m.zarr", block_size=8)
    scene = {"camera": CAM, "width": 24, "height": 24, "tf": TF, "mode": "minip", "format": "npy"}
    on = lodcast.render(st, scene)
    off = lodcast.render(st, {**scene, "sampling": {"empty_space_skipping": False}})
    assert np.abs(on.rgba - off.rgba).max() <= 1e-6
    assert on.report["samples"] < off.report["samples"]


def _mean_along_rays(vol, scene, m=6000):
    o, d = camera_rays(scene["camera"], scene["width"], scene["height"], vol.shape)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    lo, hi = box_bounds(vol.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o) / d, (hi - o) / d
    t0 = np.maximum(np.minimum(ta, tb).max(1), 0.0)
    t1 = np.maximum(ta, tb).min(1)
    hit = t1 > t0
    out = np.full(len(o), np.nan)
    x = (np.arange(m) + 0.5) / m
    for k in np.flatnonzero(hit):
        t = t0[k] + (t1[k] - t0[k]) * x
        out[k] = np.mean(sample_field(vol.astype(np.float64), o[k] + t[:, None] * d[k]))
    return out.reshape(scene["height"], scene["width"])


@pytest.mark.parametrize("quality", ["full", "lossless"])
def test_average_intensity_matches_the_mean_along_each_ray(tmp_path, quality):
    vol = _field()
    st = lodcast.ingest(vol, tmp_path / "a.zarr", block_size=8) if quality != "full" else vol
    scene = {"camera": CAM, "width": 20, "height": 16, "tf": TF, "mode": "average", "format": "npy",
             "quality": quality, "sampling": {"step": 0.1}}
    got = lodcast.render(st, scene)
    assert "-DLC_MODE_AVG" in got.report["build_options"] and "-DLC_ESS" not in got.report["build_options"]
    mean = _mean_along_rays(vol, scene)
    ok = np.isfinite(mean)
    assert ok.sum() > 150
    a = np.interp(mean[ok], [0, 1], [0.9, 0.3])
    rgb = np.stack([np.interp(mean[ok], [0, 1], [c0, c1]) for c0, c1 in ((1, 0), (0.2, 0.5), (0, 1))], -1)
    np.testing.assert_allclose(got.rgba[ok][:, 3], a, atol=2e-3)
    np.testing.assert_allclose(got.rgba[ok][:, :3], rgb * a[:, None], atol=2e-3)
    assert (got.rgba[~ok] == 0).all()


def _ball(n=40):
    zz, yy, xx = np.mgrid[:n, :n, :n] - (n - 1) / 2
    return np.sqrt(xx**2 + yy**2 + zz**2).astype(np.float32)


def test_isosurface_silhouette_colour_and_normals():
    n, R, W = 40, 14.0, 36
    c = (n - 1) / 2
    cam = {"eye": [c, -100, c], "target": [c, c, c], "up": [0, 0, 1], "projection": "orthographic", "view_height": 36}
    tf = {"points": [{"value": 0, "color": [0.2, 0.9, 0.4], "opacity": 0.05}, {"value": 30, "color": [0.2, 0.9, 0.4],
                                                                             "opacity": 0.05}]}
    base = {"camera": cam, "width": W, "height": W, "tf": tf, "mode": "iso", "isovalue": R, "format": "npy"}
    flat = lodcast.render(_ball(n), base)
    px = (np.arange(W) + 0.5) / W * 36 - 18
    X, Z = np.meshgrid(px, -px)
    r = np.hypot(X, Z)
    inside, outside = r < R - 0.75, r > R + 0.75
    assert (flat.rgba[inside][:, 3] == 1.0).all() and (flat.rgba[outside] == 0).all()
    np.testing.assert_allclose(flat.rgba[inside][:, :3], np.broadcast_to([0.2, 0.9, 0.4], (inside.sum(), 3)), atol=1e-6)  # the TF's colour, opaque
    assert "-DLC_MODE_ISO" in flat.report["build_options"]
    lit = lodcast.render(_ball(n), {**base, "shading": {"ambient": 0.0, "diffuse": 1.0, "specular": 0.0,
                                                       "light": [1, -1, 1]}}).rgba
    core = r < 0.8 * R
    Y = -np.sqrt(np.maximum(R**2 - r**2, 0))
    ndl = np.abs(np.stack([X, Y, Z], -1) / R @ (np.array([1, -1, 1]) / np.sqrt(3)))
    got = lit[..., 1] / 0.9
    assert np.abs(got[core] - ndl[core]).mean() < 0.01
    assert np.abs(got[core] - ndl[core]).max() < 0.04


def test_isosurface_needs_its_value():
    with pytest.raises(SceneError, match=r"isovalue: required with mode 'iso'"):
        lodcast.render(_ball(8), {"tf": TF, "mode": "iso", "width": 4, "height": 4})
