"""Empty-space skipping at full resolution walks cells finer than the store's blocks (sampler.ess_cell, issue 13
item 1): their border-inclusive value ranges, computed on the device (cells.cl), match a float64 NumPy reference,
and the finer walk takes fewer samples while the image stays exactly what no skipping gives."""
from __future__ import annotations

import numpy as np
import pyopencl as cl
import pytest

import lodcast
from lodcast.renderer.data import sampler
from lodcast.renderer.data.volume import as_volume, block_minmax_border

BONE = {"points": [{"value": 300, "color": [1, 0.9, 0.8], "opacity": 0.0},
                   {"value": 900, "color": [1, 1, 1], "opacity": 0.7}]}


def _buf(eng, a: np.ndarray) -> cl.Buffer:
    return cl.Buffer(eng.device.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(a))


@pytest.mark.parametrize("shape", [(37, 20, 45), (16, 16, 16), (1, 5, 33), (50, 47, 61)])
def test_cell_ranges_match_numpy(eng, shape):
    rng = np.random.default_rng(sum(shape))
    a = rng.normal(size=shape).astype(np.float32)
    a[a > 1.8] = np.nan
    vol = as_volume(a)
    C = sampler.ess_cell(a.shape, 16)
    ref_min, ref_max = block_minmax_border(a, C)  # float64, NaN-ignoring, one-voxel border
    mn, mx = sampler.level0_cells(eng.device, _buf(eng, a), a.shape, (0, 0, 0), tuple(slice(0, g) for g in vol.grid), vol)
    assert np.array_equal(mn, ref_min, equal_nan=True) and np.array_equal(mx, ref_max, equal_nan=True)
    G = vol.grid
    if all(g >= 3 for g in G):  # a pass's sub-volume: the middle blocks and a 3-voxel rim
        blocks = tuple(slice(1, g - 1) for g in G)
        lo = (13, 13, 13)
        hi = tuple(min(s, (g - 1) * 16 + 3) for s, g in zip(shape, G))
        sub = a[tuple(slice(b, h) for b, h in zip(lo, hi))]
        pmn, pmx = sampler.level0_cells(eng.device, _buf(eng, sub), sub.shape, lo, blocks, vol)
        k = 16 // C  # cells per block edge
        own = tuple(slice(k, k * (g - 1)) for g in G)
        assert np.array_equal(pmn[own], ref_min[own], equal_nan=True)
        assert np.array_equal(pmx[own], ref_max[own], equal_nan=True)
        rest = np.ones(pmn.shape, bool)
        rest[own] = False
        assert np.isnan(pmn[rest]).all() and np.isnan(pmx[rest]).all()  # not this pass's: nothing to see


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_a_store_gives_its_cell_ranges_as_the_device_computes_them(eng, monkeypatch, tmp_path, dtype):
    """Where the store keeps the ranges of the very cells the walk uses (format >= 3, cells of 8³), level0_cells
    takes them from the store instead of reading every voxel on the device: for a whole volume and for a pass's
    blocks alike they equal the float64 reference and what the device computes."""
    rng = np.random.default_rng(3)
    a = (rng.normal(size=(37, 50, 45)) * 300 + 1000).astype(dtype)
    if dtype == np.float32:
        a[a > 1600] = np.nan
    store = lodcast.ingest(a, tmp_path / "v.zarr", progress=False)
    monkeypatch.setattr(sampler, "FINE_CELLS", 0)  # the store's 8³ cells on this small volume too
    vol = as_volume(store)
    assert sampler.ess_cell(vol.shape, vol.block_size) == 8 and vol.has_cell_ranges
    ref_min, ref_max = block_minmax_border(a.astype(np.float32), 8)
    G = vol.grid
    whole = tuple(slice(0, g) for g in G)
    part = (slice(1, G[0]), slice(0, 2), slice(1, 2))
    lo = tuple(max(0, b.start * 16 - 3) for b in part)
    hi = tuple(min(s, b.stop * 16 + 3) for s, b in zip(a.shape, part))
    sub = a[tuple(slice(p, q) for p, q in zip(lo, hi))]
    cases = [(a, (0, 0, 0), whole), (sub, lo, part)]
    bufs = [_buf(eng, x) for x, _, _ in cases]
    with monkeypatch.context() as m:
        m.setattr(eng.device, "program", lambda *_a: pytest.fail("the device read the voxels"))
        got = [sampler.level0_cells(eng.device, d, x.shape, o, b, vol) for d, (x, o, b) in zip(bufs, cases)]
    monkeypatch.setattr(type(vol), "has_cell_ranges", property(lambda self: False))
    computed = [sampler.level0_cells(eng.device, _buf(eng, x), x.shape, o, b, vol) for x, o, b in cases]
    for (mn, mx), (cmn, cmx) in zip(got, computed):
        assert np.array_equal(mn, cmn, equal_nan=True) and np.array_equal(mx, cmx, equal_nan=True)
    assert np.array_equal(got[0][0], ref_min, equal_nan=True) and np.array_equal(got[0][1], ref_max, equal_nan=True)
    assert np.isnan(got[1][0]).sum() > 0 and not np.isnan(got[1][0][2:, :4, 2:4]).all()


def _ribs(shape=(48, 64, 64)) -> np.ndarray:
    """Thin bright shells in soft tissue: most 16³ blocks see a little bone, most 8³ cells none."""
    z, y, x = np.mgrid[: shape[0], : shape[1], : shape[2]].astype(np.float64)
    r = np.sqrt((y - 32) ** 2 + (x - 32) ** 2)
    a = 50 + 5 * np.sin(z / 3.0)
    for r0 in (9.0, 17.0, 25.0):
        a = np.where(np.abs(r - r0) < 1.0, 1000.0, a)
    return a.astype(np.float32)


@pytest.mark.parametrize("extra", [{}, {"mode": "mip"}, {"shading": {}, "sampling": {"preintegration": True}},
                                   {"tf2": {"points": [{"value": 950, "color": [1, 0.3, 0.2], "opacity": 0.0},
                                                       {"value": 1000, "color": [1, 0.3, 0.2], "opacity": 0.9}]}}])
def test_finer_cells_take_fewer_samples_and_change_nothing(eng, monkeypatch, extra):
    a = _ribs()
    scene = {"tf": BONE, "width": 64, "height": 64, "camera": {"azimuth": 30, "elevation": 20}, **extra}
    off = eng.render(a, {**scene, "sampling": {**scene.get("sampling", {}), "empty_space_skipping": False}})
    fine = eng.render(a, scene)
    monkeypatch.setattr(sampler, "ess_cell", lambda shape, B: B)  # the walk over the store's blocks, as before
    blocks = eng.render(a, scene)
    assert np.array_equal(fine.rgba, off.rgba), float(np.abs(fine.rgba - off.rgba).max())
    assert np.array_equal(blocks.rgba, off.rgba)
    n_fine, n_blocks, n_off = (r.report["samples"] for r in (fine, blocks, off))
    assert n_fine <= n_blocks <= n_off
    if "mode" not in extra:  # composite: the thin shells leave most 8³ cells of their 16³ blocks empty
        assert n_fine < 0.85 * n_blocks, (n_fine, n_blocks)


def test_cell_edge_follows_the_grid_size(eng):
    """4³ cells while their grid stays within FINE_CELLS, else the store's 8³ (or the block, below 8)."""
    assert sampler.ess_cell((128, 256, 256), 16) == 4  # the engine CT: 131,072 cells of 4³
    assert sampler.ess_cell((275, 512, 512), 16) == 4  # the chest CT: 1.1 million
    assert sampler.ess_cell((1024, 1024, 1024), 16) == 8 and sampler.ess_cell((1024, 1024, 1024), 32) == 8
    assert sampler.ess_cell((64, 64, 64), 8) == 4
    assert sampler.ess_cell((64, 64, 64), 4) == 4 and sampler.ess_cell((64, 64, 64), 2) == 2
    n = int(sampler.FINE_CELLS ** (1 / 3)) * 4
    assert sampler.ess_cell((n, n, n), 16) == 4 and sampler.ess_cell((n, n, n + 8), 16) == 8


def test_walk_info_is_kept_per_volume_visibility_and_clip(eng, monkeypatch, tmp_path):
    """Full resolution's walk info (cell visibility and leaps) is computed once per volume, TF zero pattern, mode
    and clip: a TF that only changes colours and non-zero opacities reuses it, any other change recomputes it, and
    every image equals one rendered with nothing kept."""
    from lodcast.renderer.walk import info as R

    calls = []
    orig = R.range_info
    monkeypatch.setattr(R, "range_info", lambda *a, **k: calls.append(1) or orig(*a, **k))
    a = _ribs()
    st = lodcast.ingest(a, tmp_path / "ribs.zarr", progress=False)
    base = {"width": 48, "height": 40, "camera": {"azimuth": 30, "elevation": 20}}
    recolour = {"points": [{"value": 300, "color": [0.2, 0.9, 0.8], "opacity": 0.0},
                           {"value": 900, "color": [1, 0.5, 1], "opacity": 0.3}]}
    wider = {"points": [{"value": 20, "color": [1, 0.9, 0.8], "opacity": 0.0},
                        {"value": 900, "color": [1, 1, 1], "opacity": 0.7}]}
    clip = {"planes": [{"normal": [1, 0, 0], "point": [30, 0, 0]}]}
    scenes = [{**base, "tf": BONE}, {**base, "tf": BONE}, {**base, "tf": recolour}, {**base, "tf": wider},
              {**base, "tf": BONE, "clip": clip}, {**base, "tf": BONE}, {**base, "tf": BONE, "mode": "mip"}]
    counts, images = [], []
    for sc in scenes:
        n0 = len(calls)
        images.append(eng.render(st, sc).rgba)
        counts.append(len(calls) - n0)
    # one call for the blocks' info per TF and mode (kept: the clip region applies after it); where the cells' walk
    # info is computed afresh two more (the 8³ parents, then the 4³ cells under them), MIP one (its cells' maxima)
    assert counts == [3, 0, 1, 3, 2, 0, 2], counts
    eng.walks.clear()
    for sc, img in zip(scenes, images):
        assert np.array_equal(eng.render(st, sc).rgba, img)


@pytest.mark.parametrize("step", [0.5, 0.9])
def test_fine_and_coarse_walks_give_the_same_image(eng, monkeypatch, step):
    """At steps up to FINE_STEP full resolution walks 4³ cells, classified under their 8³ parents; beyond it the
    parents themselves: the same image either way, the finer walk with fewer samples."""
    from lodcast.renderer.walk import info as R

    a = _ribs()
    scene = {"tf": BONE, "width": 48, "height": 48, "camera": {"azimuth": 30, "elevation": 20},
             "sampling": {"step": step}}
    fine = eng.render(a, scene)
    monkeypatch.setattr(R, "FINE_STEP", 0.0)
    coarse = eng.render(a, scene)
    off = eng.render(a, {**scene, "sampling": {"step": step, "empty_space_skipping": False}})
    assert np.abs(fine.rgba - coarse.rgba).max() <= 1e-6 and np.abs(fine.rgba - off.rgba).max() <= 1e-6
    assert fine.report["samples"] < 0.9 * coarse.report["samples"] < off.report["samples"]
