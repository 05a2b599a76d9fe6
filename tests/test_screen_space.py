"""Issue 12, adaptive screen-space sampling (thesis §3.6.3): tiles at resolutions chosen from the block scales
along their rays, reconstructed by intertile interpolation (the 2D form of eq. 3.6)."""
from __future__ import annotations

import numpy as np
import pytest
from reference import delta_e

import lodcast
from lodcast.renderer.frame.screen import plan, reconstruct, resolutions, tile_priorities
from lodcast.renderer.scene import camera as cam


def _lattice_bilinear(vals: np.ndarray, n: int, tile: int, W: int, H: int) -> np.ndarray:
    """Independent bilinear interpolation of one uniform lattice (n samples per tile edge, spacing tile/n pixels,
    clamped at the ends) at the pixel centres, separably with np.interp."""
    gy, gx = vals.shape[:2]
    cx = (np.arange(gx) + 0.5) * tile / n
    cy = (np.arange(gy) + 0.5) * tile / n
    u = np.arange(W) + 0.5
    v = np.arange(H) + 0.5
    rows = np.stack([[np.interp(u, cx, vals[r, :, c]) for c in range(vals.shape[2])] for r in range(gy)])  # (gy, C, W)
    return np.stack([[np.interp(v, cy, rows[:, c, k]) for c in range(vals.shape[2])] for k in range(W)]).transpose(2, 0, 1)


@pytest.mark.parametrize("n, W, H", [(4, 64, 48), (2, 40, 40), (6, 37, 29), (16, 32, 16)])
def test_intertile_interpolation_is_bilinear_when_all_tiles_share_a_resolution(n, W, H):
    rng = np.random.default_rng(n + W)
    tile = 16
    th, tw = -(-H // tile), -(-W // tile)
    sp = plan(np.full((th, tw), n), W, H, tile)
    vals = rng.random((th * n, tw * n, 3))  # the global lattice, row-major
    # the samples in plan order: tile by tile, each tile's n x n row-major
    samples = vals.reshape(th, n, tw, n, 3).transpose(0, 2, 1, 3, 4).reshape(-1, 3)
    got = reconstruct(sp, samples)
    np.testing.assert_allclose(got, _lattice_bilinear(vals, n, tile, W, H), atol=1e-12)


@pytest.mark.parametrize("seed", range(4))
def test_intertile_interpolation_is_continuous_across_resolution_changes(seed):
    rng = np.random.default_rng(seed)
    tile, W, H = 16, 80, 64
    res = rng.choice([2, 4, 6, 8, 12, 16], size=(H // tile, W // tile))
    sp = plan(res, W, H, tile)
    samples = rng.random((sp.rays, 2))
    # fine lines across the image, through many tile boundaries and resolution changes
    x = np.linspace(0.0, W, 40001)
    for y in (3.3, 16.0, 31.7, 40.2):
        vals = reconstruct(sp, samples, at=np.stack([x, np.full_like(x, y)], -1))
        assert np.abs(np.diff(vals, axis=0)).max() < 0.01  # 0.002 px apart: no jump anywhere
    yv = np.linspace(0.0, H, 40001)
    vals = reconstruct(sp, samples, at=np.stack([np.full_like(yv, 47.9), yv], -1))
    assert np.abs(np.diff(vals, axis=0)).max() < 0.01
    # and it is an interpolant: a sample's own position (interior of its tile's sample hull) returns it
    t = np.argwhere(res >= 4)[0]
    n = res[t[0], t[1]]
    k = sp.offsets[t[0], t[1]] + (n // 2) * n + n // 2
    np.testing.assert_allclose(reconstruct(sp, samples, at=sp.positions[k:k + 1].astype(np.float64))[0], samples[k],
                               atol=1e-5)  # positions are float32


def test_tile_statistics_order_and_resolution_mapping():
    rng = np.random.default_rng(5)
    levels = rng.integers(-1, 4, size=(4, 5, 6)).astype(np.int8)
    visible = rng.random((4, 5, 6)) > 0.2
    fr = cam.frame(cam.OrbitCamera(azimuth=25, elevation=10), 96, 80, *cam.box_world((64, 80, 96), (1, 1, 1), (0, 0, 0)))
    pr = {s: tile_priorities(fr, levels, visible, (64, 80, 96), (1, 1, 1), (0, 0, 0), 16, 96, 80, 16, s)
          for s in ("max", "average", "rms")}
    assert (pr["max"] >= pr["rms"] - 1e-12).all() and (pr["rms"] >= pr["average"] - 1e-12).all()
    assert pr["max"].max() == 1.0 and (pr["average"] < pr["max"]).any()
    assert set(np.unique(pr["max"])) <= {0.0, 0.125, 0.25, 0.5, 1.0}
    assert resolutions(np.array([0.0, 0.01, 0.125, 0.3, 0.5, 0.99, 1.0]), 16).tolist() == [2, 2, 2, 6, 8, 16, 16]
    with pytest.raises(ValueError, match="statistic"):
        tile_priorities(fr, levels, visible, (64, 80, 96), (1, 1, 1), (0, 0, 0), 16, 96, 80, 16, "median")


def _blob(shape=(48, 48, 48)):
    zz, yy, xx = np.mgrid[: shape[0], : shape[1], : shape[2]].astype(np.float64)
    c = np.array(shape, np.float64)[::-1] / 2
    return np.exp(-(((xx - c[0]) / 12) ** 2 + ((yy - c[1]) / 10) ** 2 + ((zz - c[2]) / 9) ** 2)).astype(np.float32)


TF = {"points": [{"value": 0.1, "color": [0.9, 0.6, 0.3], "opacity": 0.0},
                 {"value": 0.6, "color": [0.3, 0.8, 1.0], "opacity": 0.5},
                 {"value": 1.0, "color": [1.0, 1.0, 1.0], "opacity": 0.9}]}


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return lodcast.ingest(_blob(), tmp_path_factory.mktemp("scr") / "b.zarr", block_size=8)


@pytest.mark.parametrize("size", [(64, 64), (50, 37)])
def test_every_tile_at_full_resolution_equals_the_plain_render_exactly(store, size):
    """Level 0 everywhere (full resolution, and the atlas with every block at level 0) and every ray in the box
    (orthographic, inside its silhouette; a TF visible at every value): every tile is at full resolution and its
    rays are the pixels' own, so the image is the plain one, bit for bit — also for image sizes that are not
    multiples of the tile."""
    W, H = size
    tf = {"points": [{"value": 0.0, "color": [0.2, 0.4, 0.9], "opacity": 0.02},
                     {"value": 1.0, "color": [1.0, 0.9, 0.8], "opacity": 0.6}]}
    scene = {"camera": {"eye": [23.5, -60, 23.5], "target": [23.5, 23.5, 23.5], "up": [0, 0, 1],
                        "projection": "orthographic", "view_height": 30},
             "width": W, "height": H, "tf": tf, "format": "npy"}
    for kw in ({}, {"levels": np.zeros(store.grid, np.int8)}):
        plain = lodcast.render(store, scene, **kw)
        adapt = lodcast.render(store, {**scene, "sampling": {"adaptive_screen": True, "screen_statistic": "average"}},
                               **kw)
        assert "-DLC_SCREEN" in adapt.report["build_options"]
        assert set(adapt.report["adaptive_screen"]["tiles"]) == {"16x16"}
        assert np.array_equal(adapt.rgba, plain.rgba)
        assert adapt.report["samples"] >= plain.report["samples"]  # partial edge tiles cast a few more rays


def test_coarse_levels_cast_fewer_rays_at_a_bounded_error(store):
    scene = {"camera": {"azimuth": 30, "elevation": 20}, "width": 96, "height": 96, "tf": TF, "format": "npy",
             "quality": {"reduction": 8}}
    plain = lodcast.render(store, scene)
    out = {}
    for stat in ("max", "average", "rms"):
        r = lodcast.render(store, {**scene, "sampling": {"adaptive_screen": True, "screen_statistic": stat}})
        rep = r.report["adaptive_screen"]
        assert rep["statistic"] == stat and rep["rays"] < 96 * 96
        assert sum(rep["tiles"].values()) == 36
        assert r.report["samples"] < plain.report["samples"]
        out[stat] = (rep["rays"], delta_e(r.rgba, plain.rgba)["mean"])
    assert out["max"][0] >= out["rms"][0] >= out["average"][0]  # max is the most conservative
    assert out["max"][1] < 2.0, out
