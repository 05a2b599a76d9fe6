"""LOD renders through the brick atlas (LC_SAMPLER_ATLAS) against the full-resolution path: every block at level 0
gives the full-resolution image (interblock and nearest block, the latter through the level-0 bricks' aprons), unloaded
blocks are empty space, the report carries the LOD keys."""
from __future__ import annotations

import lod_reference as ref
import numpy as np
import pytest

import lodcast
from lodcast.opencl import Device
from lodcast.renderer.data import atlas as lod_atlas
from lodcast.renderer.data import bricks, sampler
from lodcast.renderer.frame.render import Renderer
from lodcast.renderer.pool import BrickPool
from lodcast.store.layout import cell_edge


@pytest.fixture
def eng():
    """A renderer of the test's own: nothing kept from other tests."""
    r = Renderer()
    yield r
    r.close()


B = 16
TF = {"points": [{"value": -1.0, "color": [1, 0, 0], "opacity": 0.0}, {"value": 1.0, "color": [0, 1, 0], "opacity": 0.08},
                 {"value": 3.0, "color": [0.2, 0.3, 1], "opacity": 0.3}]}


def _field(shape):
    z, y, x = np.mgrid[0:shape[0], 0:shape[1], 0:shape[2]].astype(np.float64)
    return (np.sin(x / 5.0) + np.cos(y / 7.0) + 1.5 * z / shape[0] + 0.2 * np.sin((x + y + z) / 3.0)).astype(np.float32)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    # not a multiple of the block size on any axis: edge-padded bricks and docs/design.md's rim clamp are exercised
    return lodcast.ingest(_field((37, 45, 58)), tmp_path_factory.mktemp("lod") / "v.zarr", block_size=B,
                          spacing=(1.2, 1.0, 0.9), progress=False)


CAMERAS = [
    {"azimuth": 30, "elevation": 20, "distance": 2.2},
    {"azimuth": -110, "elevation": -35, "distance": 2.0, "projection": "orthographic", "view_height": 70},
    {"azimuth": 0, "elevation": 90, "distance": 1.6, "fov": 40},
]


def _scene(cam, interp="interblock", **sampling):
    """Fixed-step sampling unless asked (these tests compare samplers, not steps)."""
    return {"tf": TF, "width": 40, "height": 32, "camera": cam, "format": "npy",
            "sampling": {"interpolation": interp, "adaptive_object": False, **sampling}}


@pytest.mark.parametrize("cam", CAMERAS)
def test_interblock_all_level0_equals_full_resolution(eng, store, cam, monkeypatch):
    """Every block at level 0 through the atlas gives full resolution's image and, with full resolution's walk
    over the same 8³ cells as the atlas's half blocks (this small volume's own walk is over 4³ cells), its
    samples."""
    monkeypatch.setattr(sampler, "ess_cell", lambda shape, b: cell_edge(b))
    eng.device_cache.clear()  # (a level 0 uploaded with the finer cells)
    full = eng.render(store, _scene(cam))
    eng.device_cache.clear()
    lod = eng.render(store, _scene(cam), levels=np.zeros(store.grid, np.int8))
    assert np.abs(lod.rgba - full.rgba).max() <= 1e-4
    assert full.rgba[..., 3].max() > 0.3
    r = lod.report
    assert r["build_options"][:2] == ["-DLC_SAMPLER_ATLAS", "-DLC_INTERP_II"]
    assert r["reduction"] == 1.0 and r["bricks_skipped"] == 0
    assert r["bricks_read"] + r["bricks_cached"] == store.layout.n_blocks
    assert abs(r["samples"] - full.report["samples"]) <= 1e-3 * full.report["samples"]
    for k in ("wall_ms", "kernel_ms", "predicted_delta_e", "samples", "build_options"):
        assert k in r


@pytest.mark.parametrize("cam", CAMERAS)
def test_nearest_block_all_level0_equals_full_resolution(eng, store, cam):
    """Every block at level 0: the level-0 bricks' aprons hold the neighbours' samples, so nearest block is trilinear
    interpolation across the faces, the full-resolution image (eq. 3.5 alone clamps half a voxel inside every
    face: measured up to 0.1 of opacity here)."""
    full = eng.render(store, _scene(cam))
    lod = eng.render(store, _scene(cam, "nearest_block"), levels=np.zeros(store.grid, np.int8))
    assert "-DLC_INTERP_NB" in lod.report["build_options"]
    assert np.abs(lod.rgba - full.rgba).max() <= 1e-4


def test_nearest_block_is_eq_3_5_where_the_level_changes(eng):
    """Where the neighbour across a face is at another level the apron repeats the brick's edge: in the half-voxel
    slab before that face nearest block is eq. 3.5, the brick coordinate clamped, and not the trilinear
    interpolation it is across faces between blocks of one level."""
    rng = np.random.default_rng(11)
    G, b = (2, 2, 3), 8
    pyr = ref.pyramid(rng.random(tuple(g * b for g in G)), 4)
    lv = np.zeros(G, np.int8)
    lv[:, :, 2] = 1  # the face x = 16 - 1/2 joins level 0 (x < 16) to level 1
    br = ref.bricks_of(lv, pyr, b)
    n = 600
    pts = np.stack([rng.uniform(15.0, 15.5, n), rng.uniform(-0.5, 15.5, n), rng.uniform(-0.5, 15.5, n)], axis=1)
    got = ref.probe(lv, br, b, pts, "nearest_block").astype(np.float64)
    eq35 = np.array([ref.nb(lv, br, b, (1, int((q[1] + 0.5) // b), int((q[2] + 0.5) // b)), q) for q in pts])
    # off the other (same-level) faces eq. 3.5 is the answer; near them the stencil crosses into a level-0 block
    off = np.all(np.abs(((pts[:, 1:] + 0.5) % b) - b / 2) <= b / 2 - 0.5, axis=1)
    assert off.sum() > 300
    np.testing.assert_allclose(got[off], eq35[off], atol=2e-6)
    tri = np.array([ref.trilinear_level(pyr, 0, b, q) for q in pts])
    assert np.abs(got - tri).max() > 0.05


@pytest.mark.parametrize("interp", ["interblock", "nearest_block"])
def test_unloaded_blocks_are_empty_space_and_skipping_them_changes_nothing(eng, store, interp):
    rng = np.random.default_rng(3)
    lv = rng.integers(-1, store.n_levels, store.grid).astype(np.int8)
    lv[lv.shape[0] // 2] = -1  # a whole slab of blocks not loaded
    cam = CAMERAS[0]
    a = eng.render(store, _scene(cam, interp), levels=lv)
    b = eng.render(store, _scene(cam, interp, empty_space_skipping=False), levels=lv)
    assert np.abs(a.rgba - b.rgba).max() <= 1e-5  # NaN samples in unloaded blocks are transparent
    assert a.report["bricks_skipped"] == int((lv < 0).sum())
    assert a.report["samples"] < b.report["samples"]  # and they were skipped, not sampled
    assert np.isfinite(a.rgba).all() and a.rgba[..., 3].max() > 0.05


def test_mip_all_level0_equals_full(eng, store):
    sc = {**_scene(CAMERAS[1]), "mode": "mip"}
    full = eng.render(store, sc)
    lod = eng.render(store, sc, levels=np.zeros(store.grid, np.int8))
    assert np.abs(lod.rgba - full.rgba).max() <= 1e-4


def test_atlas_layout_and_max_alloc(eng, store):
    lv = np.random.default_rng(2).integers(-1, store.n_levels, store.grid).astype(np.int8)
    ld = bricks.load_bricks(eng, lodcast.renderer.data.volume.as_volume(store), lv, BrickPool(2**30))
    atlas, index = lod_atlas.pack(lv, ld.bricks, B, max_bytes=2**30)
    sizes = [((B >> int(k)) + 2 * (k == 0)) ** 3 for k in lv.ravel() if k >= 0]  # level 0 inside its apron
    assert atlas.size == sum(sizes) and index.dtype == np.uint64 and index.shape == lv.shape
    G = np.array(lv.shape)
    for (z, y, x), k in np.ndenumerate(lv):  # every entry decodes to its brick, exactly
        e = int(index[z, y, x])
        if k < 0:
            assert e == 0
            continue
        assert (e & 15) - 1 == k
        lv0 = np.maximum(lv, 0)
        zs, ys, xs = (slice(max(c - 1, 0), c + 2) for c in (z, y, x))
        # the coarsest level of the block's own 3x3 slice across x, y and z
        assert ((e >> 4) & 15) - 1 == lv0[zs, ys, x].max()
        assert ((e >> 8) & 15) - 1 == lv0[zs, y, xs].max()
        assert ((e >> 12) & 15) - 1 == lv0[z, ys, xs].max()
        n = B >> int(k)
        if k > 0:
            np.testing.assert_array_equal(atlas[e >> 16:(e >> 16) + n**3].reshape(n, n, n),
                                          store.read_brick(int(k), (z, y, x)))
            continue
        padded = atlas[e >> 16:(e >> 16) + (n + 2) ** 3].reshape(n + 2, n + 2, n + 2)
        np.testing.assert_array_equal(padded[1:-1, 1:-1, 1:-1], store.read_brick(int(k), (z, y, x)))
        # the apron, sample by sample: the level-0 neighbour's sample there, else the brick's own nearest one;
        # off the grid the brick's own edge along that axis
        for i in np.ndindex(n + 2, n + 2, n + 2):
            j = np.array(i) - 1
            d = np.where(j < 0, -1, np.where(j >= n, 1, 0))
            if not d.any():
                continue
            d = np.where((np.array((z, y, x)) + d < 0) | (np.array((z, y, x)) + d >= G), 0, d)
            o = np.array((z, y, x)) + d
            if d.any() and lv[tuple(o)] == k:
                want = store.read_brick(int(k), tuple(int(c) for c in o))[tuple(np.clip(j - d * n, 0, n - 1))]
            else:
                want = store.read_brick(int(k), (z, y, x))[tuple(np.clip(j, 0, n - 1))]
            assert padded[i] == want, (k, (z, y, x), i)
    big = lod_atlas.pack_index(np.array([2**40 + 3]), np.array([2]))  # 64-bit offsets survive the packing
    assert int(big[0]) >> 16 == 2**40 + 3 and int(big[0]) & 15 == 3
    with pytest.raises(lodcast.opencl.DeviceError, match="CL_DEVICE_MAX_MEM_ALLOC_SIZE"):
        lod_atlas.pack(lv, ld.bricks, B, max_bytes=atlas.nbytes - 4)
    lod_atlas.pack(lv, ld.bricks, B, max_bytes=atlas.nbytes)  # exactly at the limit is fine


def test_render_respects_the_device_max_alloc(eng, store, monkeypatch):
    """An atlas larger than one allocation renders in passes (tests/test_passes.py), the same image; only an
    allocation smaller than one block and its neighbours is an error."""
    lv = np.zeros(store.grid, np.int8)
    ref = eng.render(store, _scene(CAMERAS[0]), levels=lv)
    eng.device_cache.clear()
    monkeypatch.setattr(Device, "max_alloc_bytes", property(lambda self: int(ref.report["device_bytes"] * 0.8)))
    got = eng.render(store, _scene(CAMERAS[0]), levels=lv)
    assert got.report["passes"] > 1 and got.report["device_bytes"] <= ref.report["device_bytes"] * 0.8
    assert np.array_equal(got.rgba, ref.rgba)
    monkeypatch.setattr(Device, "max_alloc_bytes", property(lambda self: 1024))
    with pytest.raises(lodcast.opencl.DeviceError, match="largest allocation"):
        eng.render(store, _scene(CAMERAS[0]), levels=lv)
    assert eng.device.max_alloc_bytes == 1024
    monkeypatch.undo()
    assert eng.device.max_alloc_bytes == int(eng.device.info()["max_mem_alloc_size"])


@pytest.mark.parametrize("quality", ["lossless", {"reduction": 4}, {"budget_mb": 0.05}])
def test_quality_goes_through_the_selection(eng, store, quality):
    pytest.importorskip("lodcast.renderer.lod.selection")
    from lodcast.renderer.lod.selection import select_lod
    from lodcast.renderer.scene.scene import Scene

    sc = {**_scene(CAMERAS[0]), "quality": quality}
    r = eng.render(store, sc)
    from lodcast.renderer.lod.selection import step_delta_e
    from lodcast.renderer.lod.significance import meta_of_store

    tf = Scene.parse(sc).tf
    # the budgeted qualities weigh what the camera sees (lod_visibility, on by default); lossless does not
    sel = select_lod(store, [tf], quality, visibility=None if quality == "lossless" else eng.visibility(store, sc))
    assert r.report["lod_visibility"] is (quality != "lossless")
    rep = r.report
    assert rep["reduction"] == pytest.approx(float(sel.reduction))
    step = step_delta_e(meta_of_store(store), [tf], 0.5)  # the default step's own error, on top of the selection's
    assert step > 0 and rep["predicted_delta_e"] == pytest.approx(float(sel.predicted_delta_e) + step)
    assert rep["bricks_skipped"] == int((np.asarray(sel.levels) < 0).sum())
    assert rep["bricks_read"] + rep["bricks_cached"] == int((np.asarray(sel.levels) >= 0).sum())
    assert rep["quality"] == quality and "-DLC_SAMPLER_ATLAS" in rep["build_options"]
    assert np.isfinite(r.rgba).all() and r.rgba[..., 3].max() > 0.05
    if quality == "lossless":  # every block at a level whose predicted error is within the bounds: the same image
        from lodcast.renderer.image.delta_e import delta_e_stats

        full = eng.render(store, _scene(CAMERAS[0]))
        # on this smooth, translucent field a smooth gradient flattened into coarse samples adds up along every ray
        # (0.84 mean before lossless bounded each block's worst value and accumulation; issue 45)
        de = delta_e_stats(r.rgba, full.rgba)
        assert de["mean"] <= 0.3 and de["max"] <= 3.0, de


def test_lod_quality_on_an_array_is_refused(eng):
    with pytest.raises(lodcast.renderer.scene.scene.SceneError, match="^quality: .*lodcast store"):
        eng.render(np.zeros((8, 8, 8), np.float32), {"tf": TF, "width": 4, "height": 4, "quality": "lossless"})


@pytest.mark.parametrize("dtype", ["int16", "uint16", "uint8", "int8"])
def test_integer_voxels_pack_the_coarse_bricks_with_their_deviations(eng, tmp_path, monkeypatch, dtype):
    """With integer voxels the coarse bricks' values share one uint per sample with their deviations (lc_common.h:
    lc_sig; the atlas holds level 0 alone): the images and the samples taken (the half-block cells that
    empty-space skipping walks come from both buffers) are those of the same bricks in a float atlas beside 16-bit
    deviations (the layout before, kept for float voxels), at random levels with both interpolations."""
    from lodcast.renderer.data.volume import VolumeView

    info = np.iinfo(dtype)
    f = _field((35, 40, 29))
    vol = np.clip(np.rint((f - f.min()) / np.ptp(f) * 0.9 * (int(info.max) - int(info.min)) + int(info.min)),
                  info.min, info.max).astype(dtype)
    st = lodcast.ingest(vol, tmp_path / "i.zarr", block_size=8, progress=False)
    lo, hi = float(vol.min()), float(vol.max())
    tf = {"points": [{"value": lo + 0.3 * (hi - lo), "color": [1, 0.5, 0.2], "opacity": 0.0},
                     {"value": lo + 0.6 * (hi - lo), "color": [0.2, 0.6, 1], "opacity": 0.2},
                     {"value": hi, "color": [1, 1, 1], "opacity": 0.6}]}
    rng = np.random.default_rng(abs(hash(dtype)) % 2**32)
    levels = rng.integers(-1, st.n_levels, st.grid).astype(np.int8)
    levels[0, 0, 0] = 0
    levels[-1, -1, -1] = st.n_levels - 1
    images = {}
    for layout in ("packed", "float"):
        if layout == "float":
            monkeypatch.setattr(VolumeView, "voxel_dtype", property(lambda self: np.dtype(np.float32)))
        eng.device_cache.clear()
        for interp in ("nearest_block", "interblock"):
            r = eng.render(st, {"tf": tf, "width": 40, "height": 36, "format": "npy", "quality": {"reduction": 2},
                            "camera": {"azimuth": 35, "elevation": 25}, "sampling": {"interpolation": interp}},
                       levels=levels)
            assert ("-DLC_VOXEL" in " ".join(r.report["build_options"])) == (layout == "packed")
            assert "-DLC_DIST" in r.report["build_options"] and r.report["bricks_skipped"] > 0
            images[layout, interp] = (r.rgba, r.report["samples"])
        if layout == "packed":  # the coarse bricks in the uint deviations' buffer alone, level 0 in the atlas
            from lodcast.renderer.data.volume import as_volume

            da = lod_atlas.device_atlas(eng, as_volume(st), levels, with_std=True)
            n0 = int(lod_atlas.brick_elements(np.where(levels == 0, 0, -1), 8).sum())
            held = (4 * lod_atlas.coarse_elements(levels, 8), np.dtype(dtype).itemsize * n0)
            assert da.nbytes == sum(held)
            for buf, n in zip((da.std, da.atlas), held):  # (a buffer has room for a little more: atlas._mapped)
                assert n <= buf.size <= n * 1.0625
    for interp in ("nearest_block", "interblock"):
        (a, na), (b, nb) = images["packed", interp], images["float", interp]
        assert a[..., 3].max() > 0.2 and na == nb, interp
        np.testing.assert_allclose(a, b, rtol=0, atol=2e-6, err_msg=interp)
