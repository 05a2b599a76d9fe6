"""A new selection's atlas is built from the last one of the same store (renderer/data/atlas.py: reuse): the bricks of
blocks at the same level are copied across, only the others are read, and the octants' bounds are computed for
the blocks the change can reach. Everything must equal an atlas packed from nothing, element for element, over
random changes of levels (blocks loaded and dropped, level 0 against coarse, the aprons between them), for float
and integer voxels (the latter with the coarse values packed beside their deviations), and renders with the
view-weighted selection must not change by a bit."""
from __future__ import annotations

import gc

import numpy as np
import pyopencl as cl
import pytest

import lodcast
from lodcast.renderer.data import atlas as lod_atlas
from lodcast.renderer.data import atlas_cells
from lodcast.renderer.data.volume import as_volume, device_dtype
from lodcast.renderer.frame.render import Renderer
from lodcast.renderer.pool import BrickPool

BONE = {"points": [{"value": 300, "color": [1, 0.9, 0.8], "opacity": 0.0},
                   {"value": 900, "color": [1, 1, 1], "opacity": 0.7}]}


def _shells(shape=(40, 48, 56)) -> np.ndarray:
    z, y, x = np.mgrid[: shape[0], : shape[1], : shape[2]].astype(np.float64)
    r = np.sqrt((z - 20) ** 2 + (y - 24) ** 2 + (x - 28) ** 2)
    a = 50 + np.random.default_rng(4).normal(0, 20, shape)
    for r0 in (7.0, 15.0):
        a = np.where(np.abs(r - r0) < 1.0, 1000.0, a)
    return a


@pytest.fixture(scope="module", params=["float32", "int16"])
def store(request, tmp_path_factory):
    a = _shells()
    a = a.astype(np.float32) if request.param == "float32" else np.rint(a).astype(np.int16)
    if request.param == "float32":
        a[1:4, 1:4, 1:4] = np.nan
    return lodcast.ingest(a, tmp_path_factory.mktemp("reuse") / f"{request.param}.zarr", block_size=8)


@pytest.fixture(scope="module")
def eng():
    r = Renderer()
    yield r
    r.close()


def _forget(eng: Renderer) -> None:
    """Nothing kept: no atlas in the device cache, no cells, no last atlas to build from."""
    eng.close()


def _changed(levels: np.ndarray, rng, frac: float, top: int) -> np.ndarray:
    out = levels.copy()
    m = rng.random(levels.shape) < frac
    out[m] = rng.integers(-1, top + 1, size=int(m.sum()))
    return out


def _read(eng: Renderer, buf, dtype) -> np.ndarray:
    queue = eng.device.queue
    out = np.empty(buf.size // np.dtype(dtype).itemsize, dtype)
    cl.enqueue_copy(queue, out, buf)
    queue.finish()
    return out


def _same_atlas(eng: Renderer, a: lod_atlas.DeviceAtlas, b: lod_atlas.DeviceAtlas, vol,
                eng_b: Renderer | None = None) -> None:
    """Index and buffers equal, bit for bit (NaN included), over the elements the index reaches (a buffer may be
    a little larger: atlas.py `_mapped`); a buffer with nothing in it holds one element that nothing reads or
    writes."""
    np.testing.assert_array_equal(a.index_host, b.index_host)
    B = int(vol.block_size)
    levels = a.levels
    coarse = lod_atlas.coarse_elements(levels, B)
    packed = a.std is not None and lod_atlas.deviation_bytes(vol.voxel_dtype) == 4  # coarse values beside deviations
    held = int(lod_atlas.brick_elements(levels, B).sum()) - (coarse if packed else 0)
    sizes = (device_dtype(vol.voxel_dtype).itemsize, lod_atlas.deviation_bytes(vol.voxel_dtype))
    for x, y, used, size in ((a.atlas, b.atlas, held, sizes[0]), (a.std, b.std, coarse, sizes[1])):
        assert (x is None) == (y is None)
        if x is not None and used:
            assert min(x.size, y.size) >= used * size
            np.testing.assert_array_equal(_read(eng, x, np.uint8)[:used * size],
                                          _read(eng_b or eng, y, np.uint8)[:used * size])


@pytest.mark.parametrize("seed", range(3))
def test_the_atlas_layout_is_a_stable_sort_by_level(seed):
    """_offsets, level by level: every brick where a stable sort of the blocks by level, the coarsest first,
    unloaded blocks last, puts it, its predecessors' sizes summed (grids one block, all unloaded, one level)."""
    rng = np.random.default_rng(seed)
    for g in ((1, 1, 1), (2, 3, 4), (5, 6, 7)):
        for lo, hi in ((-1, -1), (-1, 0), (0, 0), (-1, 4), (2, 3), (0, 4)):
            lv = rng.integers(lo, hi + 1, size=g).astype(np.int8)
            flat = lv.astype(np.int64).ravel()
            sizes = lod_atlas.brick_elements(flat, 8)
            order = np.lexsort((np.arange(flat.size), -flat))
            want = np.zeros(flat.size, np.int64)
            want[order[1:]] = np.cumsum(sizes[order])[:-1]
            got_sizes, got = lod_atlas._offsets(lv, 8)
            np.testing.assert_array_equal(got_sizes, sizes)
            np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("seed", range(6))
def test_copy_kept_moves_each_kept_brick_to_its_new_place(seed):
    """The runs of kept bricks copied as slices land where a brick-by-brick copy puts them, over changes from a
    few blocks (long runs) to most (runs of one), with bricks added and dropped before, between and after them;
    nothing else of the new buffer is written."""
    rng = np.random.default_rng(seed)
    B, grid = 4, (5, 6, 7)
    old = rng.integers(-1, 3, size=grid).astype(np.int64).ravel()
    new = _changed(old.reshape(grid), rng, (0.02, 0.1, 0.5, 0.9, 0.3, 1.0)[seed], 2).astype(np.int64).ravel()
    old_sizes, old_off = lod_atlas._offsets(old.reshape(grid), B)
    sizes, off = lod_atlas._offsets(new.reshape(grid), B)
    src = rng.integers(0, 60000, size=int(old_sizes.sum())).astype(np.uint16)
    dst = np.zeros(int(sizes.sum()), np.uint16)
    kept = (old == new) & (new >= 0)
    n = lod_atlas.copy_kept(dst, src, new, off, old, old_off, kept, range(0, 3), B)
    want = np.zeros_like(dst)
    for b in np.flatnonzero(kept):
        want[off[b]:off[b] + sizes[b]] = src[old_off[b]:old_off[b] + old_sizes[b]]
    assert n == int(kept.sum())
    np.testing.assert_array_equal(dst, want)


@pytest.mark.parametrize("with_std", [True, False])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_an_atlas_built_from_the_last_one_is_the_atlas_packed_from_nothing(store, eng, with_std, seed):
    vol = as_volume(store)
    rng = np.random.default_rng(seed)
    top = store.n_levels - 1
    first = rng.integers(-1 if seed else 0, top + 1, size=vol.grid).astype(np.int8)
    first[rng.random(vol.grid) < 0.4] = 0  # runs of level-0 blocks: aprons between them
    _forget(eng)
    old = lod_atlas.device_atlas(eng, vol, first, with_std=with_std)
    for frac in (0.05, 0.3, 1.0):
        new_levels = _changed(first, rng, frac, top)
        new = lod_atlas.device_atlas(eng, vol, new_levels, with_std=with_std)
        assert new.base_key == old.key and new.cached >= int(((new_levels == first) & (first >= 0)).sum())
        _forget(eng)
        fresh = lod_atlas.device_atlas(eng, vol, new_levels, with_std=with_std)
        assert fresh.base_key is None
        _same_atlas(eng, new, fresh, vol)
        _forget(eng)
        old = lod_atlas.device_atlas(eng, vol, first, with_std=with_std)


@pytest.mark.parametrize("interp", ["nearest_block", "interblock"])
@pytest.mark.parametrize("cpb", [2, 4])
def test_cells_of_an_atlas_built_from_the_last_one_are_computed_where_they_changed(store, eng, interp, cpb):
    vol = as_volume(store)
    B, G = int(vol.block_size), vol.grid
    rng = np.random.default_rng(7)
    first = rng.integers(-1, store.n_levels, size=G).astype(np.int8)
    first[rng.random(G) < 0.5] = 0
    _forget(eng)
    atlas_cells.atlas_cells(eng, lod_atlas.device_atlas(eng, vol, first, with_std=True), G, B, interp, vol.std_unit, cpb=cpb)
    for frac in (0.02, 0.2, 0.6):
        levels = _changed(first, rng, frac, store.n_levels - 1)
        da = lod_atlas.device_atlas(eng, vol, levels, with_std=True)
        assert da.base_key is not None
        dirty = lod_atlas.dirty_blocks(da.base_levels.reshape(G), levels, interp)
        assert np.count_nonzero(dirty) < dirty.size or frac > 0.5  # some blocks are copied, not computed
        got = atlas_cells.atlas_cells(eng, da, G, B, interp, vol.std_unit, cpb=cpb)
        assert got.redone is not None
        if interp == "nearest_block":  # beside a change of level 0 only the cells towards it
            assert got.redone.size < np.count_nonzero(dirty) * cpb**3
        ref = atlas_cells._device_cells(eng.device, da, G, B, interp, vol.std_unit, None, cpb)
        for g, r in ((got.vmin, ref.vmin), (got.vmax, ref.vmax), (got.std, ref.std)):
            np.testing.assert_array_equal(g, r)
        first = levels


@pytest.mark.parametrize("interp", ["nearest_block", "interblock"])
@pytest.mark.parametrize("seed", range(3))
def test_dirty_blocks_name_the_blocks_whose_change_reaches_them(interp, seed):
    """Block by block and direction by direction: interblock, each neighbour (itself included) whose level
    changed; nearest block, its own change, and at level 0 each neighbour that became or stopped being level 0."""
    rng = np.random.default_rng(seed)
    G = (4, 5, 6)
    old = rng.integers(-1, 3, size=G).astype(np.int8)
    old[rng.random(G) < 0.4] = 0
    new = _changed(old, rng, 0.15, 2)
    want = np.zeros(G, np.uint32)
    for b in np.ndindex(*G):
        for bit, d in enumerate(np.ndindex(3, 3, 3)):
            n = tuple(i + e - 1 for i, e in zip(b, d))
            if not all(0 <= i < g for i, g in zip(n, G)):
                continue
            if interp == "interblock" or n == b:
                hit = old[n] != new[n]
            else:
                hit = new[b] == 0 and (old[n] == 0) != (new[n] == 0)
            want[b] |= np.uint32(hit) << np.uint32(bit)
    got = lod_atlas.dirty_blocks(old, new, interp)
    assert got.dtype == np.uint32 and (want != 0).any() and (want == 0).any()
    np.testing.assert_array_equal(got, want)


def test_only_the_bricks_of_blocks_whose_level_changed_are_read(store, eng):
    vol = as_volume(store)
    rng = np.random.default_rng(11)
    first = rng.integers(-1, store.n_levels, size=vol.grid).astype(np.int8)
    levels = _changed(first, rng, 0.25, store.n_levels - 1)
    _forget(eng)
    lod_atlas.device_atlas(eng, vol, first, with_std=True, cache=BrickPool(1 << 30))
    da = lod_atlas.device_atlas(eng, vol, levels, with_std=True, cache=BrickPool(1 << 30))  # nothing cached there
    new = int(((levels != first) & (levels >= 0)).sum())
    assert 0 < new < int((levels >= 0).sum())
    assert (da.read, da.cached) == (new, int((levels >= 0).sum()) - new)


def test_a_read_ahead_asks_only_for_what_the_newest_atlas_lacks(store, eng):
    """unplaced: the bricks the next atlas would take from the pool or the store, not the ones it copies from the
    newest atlas, so a read ahead beside a turntable reads nothing although the pool has let its bricks go."""
    vol = as_volume(store)
    rng = np.random.default_rng(12)
    first = rng.integers(-1, store.n_levels, size=vol.grid).astype(np.int8)
    levels = _changed(first, rng, 0.25, store.n_levels - 1)
    _forget(eng)
    np.testing.assert_array_equal(lod_atlas.unplaced(eng, vol, levels, True), levels)  # no atlas: all of them
    kept = lod_atlas.device_atlas(eng, vol, first, with_std=True, cache=BrickPool(1 << 30))
    todo = lod_atlas.unplaced(eng, vol, levels, True)
    np.testing.assert_array_equal(todo, np.where((levels == first) & (levels >= 0), -1, levels))
    np.testing.assert_array_equal(lod_atlas.unplaced(eng, vol, levels, False), levels)  # another family
    scene = {"tf": BONE, "quality": {"reduction": 20}, "width": 32, "height": 32,
             "sampling": {"lod_visibility": False}}  # one selection for every view, as a large volume's default
    _forget(eng)
    eng.render(store, scene)
    eng.bricks.clear()  # a pool smaller than the atlas: its bricks are gone, the atlas's are on the device
    assert eng.prefetch(store, {**scene, "camera": {"azimuth": 40}}) == 0
    assert eng.render(store, {**scene, "camera": {"azimuth": 40}}).report["bricks_read"] == 0
    del kept


def test_the_last_atlas_is_held_weakly(store, eng):
    """Reuse never keeps an atlas's device memory alive: once the device cache lets it go, it is gone."""
    vol = as_volume(store)
    _forget(eng)
    da = lod_atlas.device_atlas(eng, vol, np.zeros(vol.grid, np.int8))
    family = (vol.key, vol.grid, False, str(vol.voxel_dtype))
    assert eng.last_atlas(family) is da
    del da
    eng.device_cache.clear()
    gc.collect()
    assert eng.last_atlas(family) is None


def test_a_turntable_with_the_view_weighted_selection_renders_as_without_reuse(store, eng):
    scenes = [{"tf": BONE, "quality": {"reduction": 20}, "width": 64, "height": 64,
               "camera": {"azimuth": az, "elevation": 10}, "sampling": {"lod_visibility": True}}
              for az in (0, 4, 30, 31, 90)]
    _forget(eng)
    reused = [eng.render(store, s) for s in scenes]
    assert sum(r.report["bricks_cached"] for r in reused[1:]) > 0
    for s, r in zip(scenes, reused):
        _forget(eng)
        fresh = eng.render(store, s)
        np.testing.assert_array_equal(r.rgba, fresh.rgba)


@pytest.mark.parametrize("first, then", [("empty", "random"), ("random", "empty"), ("zero", "coarse"),
                                         ("coarse", "zero"), ("zero", "random")])
def test_edge_selections_build_from_each_other(store, eng, first, then):
    """Nothing loaded, everything at level 0 (no coarse brick: a deviations' buffer of one element), everything
    coarse: each built from the other equals the atlas packed from nothing."""
    vol = as_volume(store)
    rng = np.random.default_rng(13)
    make = {"empty": lambda: np.full(vol.grid, -1, np.int8), "zero": lambda: np.zeros(vol.grid, np.int8),
            "coarse": lambda: rng.integers(1, store.n_levels, size=vol.grid).astype(np.int8),
            "random": lambda: rng.integers(-1, store.n_levels, size=vol.grid).astype(np.int8)}
    a, b = make[first](), make[then]()
    _forget(eng)
    lod_atlas.device_atlas(eng, vol, a, with_std=True)
    new = lod_atlas.device_atlas(eng, vol, b, with_std=True)
    assert new.base_key is not None
    _forget(eng)
    _same_atlas(eng, new, lod_atlas.device_atlas(eng, vol, b, with_std=True), vol)


def test_a_new_atlas_takes_the_buffers_of_the_one_its_put_evicts(store):
    """With room for two atlases in the device cache, each new selection's atlas goes into the buffers of the one
    it is going to evict (renderer/cache.py: Spares): from the third on no new memory, and every atlas still the
    one packed from nothing. An atlas somebody still holds (a render that has it) keeps its buffers: the next
    one gets new memory, and the held one's bricks stay as they were."""
    vol = as_volume(store)
    rng = np.random.default_rng(21)
    top = store.n_levels - 1
    first = rng.integers(0, top + 1, size=vol.grid).astype(np.int8)
    probe = Renderer()
    one = lod_atlas.device_atlas(probe, vol, first, with_std=True)
    size = probe.device_cache.nbytes  # an atlas of about this selection's size, as the cache counts it
    probe.close()
    del one
    eng = Renderer(device_cache_mb=2.5 * size / 2**20)
    levels = [first]
    for _ in range(4):  # blocks trading levels: the same bricks' sizes, so that each atlas fits the last's buffers
        lv = levels[-1].copy().ravel()
        pick = rng.choice(lv.size, size=2 * max(1, lv.size // 20), replace=False)
        lv[pick] = lv[pick[::-1]]
        levels.append(lv.reshape(vol.grid))
    ptrs = []
    for lv in levels:
        da = lod_atlas.device_atlas(eng, vol, lv, with_std=True)
        ptrs.append((da.atlas.int_ptr, da.std.int_ptr))
        assert eng.device_cache.nbytes + eng.spares.nbytes <= eng.settings.device_cache_bound
        fresh = Renderer()
        _same_atlas(eng, da, lod_atlas.device_atlas(fresh, vol, lv, with_std=True), vol, fresh)
        fresh.close()
        del da
    assert ptrs[2] == ptrs[0] and ptrs[3] == ptrs[1] and ptrs[4] == ptrs[2]

    lod_atlas.device_atlas(eng, vol, levels[1], with_std=True)
    held = lod_atlas.device_atlas(eng, vol, levels[1], with_std=True)  # the cache's hit: a copy, with its lease
    assert held.reused
    before = _read(eng, held.atlas, np.uint8), _read(eng, held.std, np.uint8)
    eng.device_cache.clear()
    got = lod_atlas.device_atlas(eng, vol, _changed(levels[1], rng, 0.3, top), with_std=True)
    assert {got.atlas.int_ptr, got.std.int_ptr}.isdisjoint({held.atlas.int_ptr, held.std.int_ptr})
    np.testing.assert_array_equal(_read(eng, held.atlas, np.uint8), before[0])
    np.testing.assert_array_equal(_read(eng, held.std, np.uint8), before[1])
    # a pass's atlas (not kept) leaves no spare: beside the next pass's buffers it would pass the budget
    n = len(eng.spares)
    lod_atlas.device_atlas(eng, vol, levels[2], with_std=True, keep=False)
    gc.collect()
    assert len(eng.spares) == n
    eng.close()
