"""The brick cache (renderer/data/atlas.py): camera changes read nothing, a new selection reads only the bricks it
changes, reads are grouped by shard, the LRU is bounded by bytes, and each renderer has caches of its own."""
from __future__ import annotations

import numpy as np
import pytest

import lodcast
from lodcast.environment import EnvironmentInvalid, environment
from lodcast.renderer.cache import ByteLru, Spares
from lodcast.renderer.data import atlas as lod_atlas
from lodcast.renderer.data import bricks
from lodcast.renderer.data.volume import as_volume
from lodcast.renderer.frame.render import Renderer
from lodcast.renderer.pool import ROW_BYTES, BrickPool

B = 8
TF = {"points": [{"value": 0.0, "color": [1, 1, 1], "opacity": 0.0}, {"value": 1.0, "color": [1, 0.5, 0], "opacity": 0.2}]}


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    rng = np.random.default_rng(0)
    v = rng.random((40, 48, 72)).astype(np.float32)
    return lodcast.ingest(v, tmp_path_factory.mktemp("cache") / "v.zarr", block_size=B, progress=False)


@pytest.fixture
def eng():
    """A renderer of the test's own: its caches start empty."""
    r = Renderer()
    yield r
    r.close()


def _scene(az, tf=TF):
    return {"tf": tf, "width": 16, "height": 16, "camera": {"azimuth": az, "elevation": 15}, "format": "npy"}


def _pairs(lv):
    return {(int(k), z, y, x) for (z, y, x), k in np.ndenumerate(lv) if k >= 0}


def test_camera_change_reads_nothing_and_a_new_selection_reads_only_its_changes(store, eng):
    rng = np.random.default_rng(1)
    lv1 = rng.integers(-1, store.n_levels, store.grid).astype(np.int8)
    n1 = int((lv1 >= 0).sum())
    r = eng.render(store, _scene(0), levels=lv1).report
    assert (r["bricks_read"], r["bricks_cached"], r["bricks_skipped"]) == (n1, 0, lv1.size - n1)
    reads = eng.bricks.reads
    for az in (40, 170):  # camera only: nothing read, nothing packed again
        r = eng.render(store, _scene(az), levels=lv1).report
        assert (r["bricks_read"], r["bricks_cached"]) == (0, n1)
    eng.device_cache.clear()  # also from the host cache alone (e.g. after the device cache evicted it)
    r = eng.render(store, _scene(80), levels=lv1).report
    assert (r["bricks_read"], r["bricks_cached"]) == (0, n1)
    assert eng.bricks.reads == reads
    # a changed selection (what a TF change does): only the bricks it changes are read
    lv2 = lv1.copy()
    change = rng.random(lv1.shape) < 0.3
    lv2[change] = rng.integers(-1, store.n_levels, int(change.sum()))
    new = _pairs(lv2) - _pairs(lv1)
    assert new
    r = eng.render(store, _scene(80), levels=lv2).report
    assert r["bricks_read"] == len(new) and r["bricks_cached"] == len(_pairs(lv2)) - len(new)
    assert eng.bricks.reads == reads + len(new)


def test_tf_change_through_the_selection_reads_only_changed_bricks(store, eng):
    pytest.importorskip("lodcast.renderer.lod.selection")
    tf2 = {"points": [{"value": 0.5, "color": [1, 1, 1], "opacity": 0.0}, {"value": 1.0, "color": [0, 0.5, 1], "opacity": 0.6}]}
    # the view-independent selection (visibility.py's weight off): a camera change selects the same bricks
    fixed = {"quality": {"reduction": 8}, "sampling": {"lod_visibility": False}}
    a = eng.render(store, {**_scene(0), **fixed})
    b = eng.render(store, {**_scene(90), **fixed})
    assert b.report["bricks_read"] == 0 and b.report["bricks_cached"] == a.report["bricks_read"]
    c = eng.render(store, {**_scene(90, tf2), **fixed})
    from lodcast.renderer.lod.selection import select_lod
    from lodcast.renderer.scene.scene import Scene

    l1 = select_lod(store, [Scene.parse(_scene(0)).tf], {"reduction": 8}).levels
    l2 = select_lod(store, [Scene.parse(_scene(0, tf2)).tf], {"reduction": 8}).levels
    assert c.report["bricks_read"] == len(_pairs(l2) - _pairs(l1))


def test_reads_are_grouped_by_shard_and_run_in_parallel(store, eng):
    vol = as_volume(store)
    lay = store.layout
    lv = np.zeros(store.grid, np.int8)
    lv[:, :, 5:] = 2
    cache = BrickPool(2**30)
    ld = bricks.load_bricks(eng, vol, lv, cache)
    shards = {(int(k), *(b * lay.block_edge(int(k)) // s for b, s in zip((z, y, x), lay.shard_shape(int(k)))))
              for (z, y, x), k in np.ndenumerate(lv)}
    assert ld.shards == len(shards) < ld.read == lv.size
    for (z, y, x), k in list(np.ndenumerate(lv))[::7]:
        np.testing.assert_array_equal(ld.bricks[(int(k), z, y, x)], store.read_brick(int(k), (z, y, x)))
    again = bricks.load_bricks(eng, vol, lv, cache)
    assert (again.read, again.cached, again.shards) == (0, lv.size, 0)


@pytest.mark.parametrize("seed", range(4))
def test_eviction_takes_what_a_stable_sort_by_stamp_puts_first(seed):
    """The entries eviction takes, counted per stamp, are those a stable sort by stamp puts first until their
    costs reach the bytes to free: ties at the threshold in place order, all when the total falls short, and
    stamps too sparse to count per stamp."""
    from lodcast.renderer.pool import _least_recent

    rng = np.random.default_rng(seed)
    for n, span in ((1, 1), (50, 5), (2000, 40), (3000, 10**9)):
        stamps = rng.integers(7, 7 + span, size=n).astype(np.int64)
        costs = rng.choice([16 + 2, 16 + 1024, 16 + 8192], size=n).astype(np.int64)
        order = np.argsort(stamps, kind="stable")
        cum = np.cumsum(costs[order])
        for nbytes in (1, int(costs[0]), int(cum[-1]) // 3, int(cum[-1]) - 1, int(cum[-1]), int(cum[-1]) + 5):
            want = order[:int(np.searchsorted(cum, nbytes)) + 1]
            assert sorted(_least_recent(stamps, costs, nbytes).tolist()) == sorted(want.tolist())


def test_pool_is_an_lru_bounded_by_bytes():
    """Bricks of one arena (kind, store, level) by block index; eviction takes the least recently used bricks of the
    whole pool down to EVICT_TO of its bound once the bound is passed, a brick asked for counts as used, and what
    does not fit the bound at all is not kept."""
    cost = 4 * 64 + ROW_BYTES  # a 4x4x4 float32 brick
    c = BrickPool(8 * cost)
    fam = ("s", "key", 0)
    for i in range(8):
        c.put(fam, 100, np.array([i]), np.full((1, 4, 4, 4), i, np.float32))
    assert len(c) == 8 and c.nbytes == 8 * cost
    assert (c.find(fam, 100, np.arange(8)) >= 0).all()
    c.find(fam, 100, np.array([0]))  # touched: survives the next insertion
    c.put(fam, 100, np.array([9]), np.full((1, 4, 4, 4), 9, np.float32))
    rows = c.find(fam, 100, np.array([0, 1, 2, 9]))
    assert rows[0] >= 0 and rows[1] < 0 and rows[3] >= 0 and c.nbytes <= c.max_bytes
    held, got = c.get(fam, 100, np.array([0, 9]))
    assert held.all() and got is not None
    np.testing.assert_array_equal(got[:, 0, 0, 0], [0, 9])
    held, got = c.get(fam, 100, np.array([1, 9]))  # an evicted brick is not held, never another block's
    assert held.tolist() == [False, True] and got is not None
    np.testing.assert_array_equal(got[:, 0, 0, 0], [9])
    n, nbytes = len(c), c.nbytes
    c.put(fam, 100, np.array([9]), np.full((1, 4, 4, 4), 7, np.float32))  # held already: kept as it is
    assert (len(c), c.nbytes) == (n, nbytes)
    np.testing.assert_array_equal(c.get(fam, 100, np.array([9]))[1][:, 0, 0, 0], [9])
    c.put(("s", "key", 1), 100, np.array([0]), np.zeros((1, 16, 16, 16), np.float32))  # larger than the pool
    assert (c.find(("s", "key", 1), 100, np.array([0])) < 0).all() and c.nbytes <= c.max_bytes


def test_pool_holds_whole_arrays_by_the_same_recency():
    """Whole arrays (a pass's voxels) are held as they are (no copy), found by family, and age with the bricks:
    eviction takes whatever was used least recently, brick or array; an array larger than the bound is not kept."""
    cost = 4 * 64 + ROW_BYTES
    c = BrickPool(8 * cost)
    fam = ("s", "key", 0)
    for i in range(4):
        c.put(fam, 100, np.array([i]), np.full((1, 4, 4, 4), i, np.float32))
    whole = np.arange(3 * 64, dtype=np.float32)  # about three bricks' worth
    assert c.hold(("voxels", "key", 1), whole)
    assert c.held(("voxels", "key", 1)) is whole and len(c) == 5 and c.nbytes == 4 * cost + whole.nbytes + ROW_BYTES
    c.find(fam, 100, np.arange(4))  # the bricks are used after the array
    c.put(fam, 100, np.array([4, 5]), np.zeros((2, 4, 4, 4), np.float32))  # past the bound: the array is oldest
    assert c.held(("voxels", "key", 1)) is None and (c.find(fam, 100, np.arange(6)) >= 0).all()
    assert c.nbytes == 6 * cost and len(c) == 6
    assert c.hold(("voxels", "key", 2), np.zeros(64, np.float32))
    c.find(fam, 100, np.arange(1, 6))  # brick 0 is now the least recent; the array next
    c.put(fam, 100, np.array([6, 7]), np.zeros((2, 4, 4, 4), np.float32))
    assert c.find(fam, 100, np.array([0]))[0] < 0 and c.held(("voxels", "key", 2)) is None
    assert (c.find(fam, 100, np.arange(1, 8)) >= 0).all() and c.nbytes == 7 * cost
    assert not c.hold(("voxels", "key", 3), np.zeros(16 * 64, np.float32))  # larger than the whole pool
    assert c.held(("voxels", "key", 3)) is None and c.nbytes <= c.max_bytes
    c.clear()
    assert (len(c), c.nbytes) == (0, 0) and c.held(("voxels", "key", 2)) is None


def test_alternating_qualities_keep_both_working_sets(store):
    """One pool for every level and quality: a coarse selection and full resolution beyond the device budget,
    alternated, read from the store only the first time each is shown, and give the same images again."""
    eng = Renderer(brick_cache_mb=64, device_budget_mb=0.05)
    coarse, full = {**_scene(20), "quality": {"reduction": 8}}, {**_scene(20), "quality": "full"}
    first = [eng.render(store, sc) for sc in (coarse, full)]
    assert first[0].report["bricks_read"] > 0 and first[1].report["bricks_read"] > 0
    assert first[1].report["passes"] > 1
    for _ in range(2):
        again = [eng.render(store, sc) for sc in (coarse, full)]
        assert [r.report["bricks_read"] for r in again] == [0, 0]
        for a, b in zip(first, again):
            np.testing.assert_array_equal(a.rgba, b.rgba)


def test_each_renderer_has_its_own_caches_sized_once(store, monkeypatch):
    """A renderer reads its sizes when it is made (its keywords over the variables); two renderers in one process
    share no cache: what one reads, keeps or clears the other does not see."""
    monkeypatch.setenv("LODCAST_BRICK_CACHE_MB", "3")
    assert environment().brick_cache_bytes == 3 * 2**20
    a, b = Renderer(), Renderer(brick_cache_mb=5, device_cache_mb=7)
    monkeypatch.setenv("LODCAST_BRICK_CACHE_MB", "11")  # read once: later changes reach new renderers only
    assert a.settings.brick_cache_bytes == 3 * 2**20 and b.settings.brick_cache_bytes == 5 * 2**20
    assert b.settings.device_cache_bytes == 7 * 2**20 and Renderer().settings.brick_cache_bytes == 11 * 2**20
    monkeypatch.delenv("LODCAST_BRICK_CACHE_MB")
    a, b = Renderer(), Renderer()
    scene = {**_scene(0), "quality": {"reduction": 4}}
    first = a.render(store, scene).report
    assert first["bricks_read"] > 0 and a.bricks.reads == first["bricks_read"] and len(a.selections) == 1
    assert (len(b.bricks), len(b.device_cache), len(b.selections), b.bricks.reads) == (0, 0, 0, 0)
    other = b.render(store, scene)  # reads everything itself
    assert other.report["bricks_read"] == first["bricks_read"]
    a.close()  # drops a's caches, not b's
    assert len(a.bricks) == len(a.device_cache) == 0 and len(b.device_cache) > 0
    again = b.render(store, scene).report
    assert again["bricks_read"] == 0 and again["bricks_cached"] == first["bricks_read"]
    assert a.render(store, scene).report["bricks_read"] == first["bricks_read"]
    with pytest.raises(EnvironmentInvalid, match="brick_cache_mb"):
        Renderer(brick_cache_mb=-1)
    monkeypatch.setenv("LODCAST_BRICK_CACHE_MB", "lots")  # named, never a silent default
    with pytest.raises(EnvironmentInvalid, match="LODCAST_BRICK_CACHE_MB"):
        environment()


def test_device_cache_keeps_several_volumes_and_always_the_newest(tmp_path, eng):
    """Alternating renders of two stores upload each once (level 0 for "full", the atlas for an LOD selection);
    a budget smaller than one entry still keeps the newest."""
    stores = [lodcast.ingest(np.random.default_rng(i).random((24, 24, 24)).astype(np.float32),
                             tmp_path / f"{i}.zarr", block_size=B, progress=False) for i in range(2)]
    full = {**_scene(0), "quality": "full"}
    lossless = {**_scene(0), "quality": "lossless"}
    for st in stores:
        for scene in (full, lossless):
            first = eng.render(st, scene).report
            assert first["bricks_read"] > 0 and first["bricks_cached"] == 0, first
    for st in stores:  # all four entries still resident: nothing read again
        for scene in (full, lossless):
            again = eng.render(st, scene).report
            assert again["bricks_read"] == 0 and again["bricks_cached"] > 0, again
    assert len(eng.device_cache) == 4
    tiny = ByteLru(100, keep_last=True)
    tiny.put("a", "A", 60)
    tiny.put("b", "B", 1000)  # over the budget on its own: kept, and "a" evicted
    assert tiny.get("b") == "B" and tiny.get("a") is None and len(tiny) == 1
    tiny.put("c", "C", 10)
    assert tiny.get("c") == "C" and tiny.get("b") is None


def test_prefetch_reads_the_next_frames_bricks_so_its_render_reads_none(store, eng):
    """A job reads frame i + 1's bricks while frame i renders (Renderer.prefetch): the render after a
    prefetch reads nothing from the store and gives the image a cold render gives."""
    prefetch, prepare = eng.prefetch, eng.prepare
    scene = {**_scene(30), "quality": {"reduction": 4}}
    cold = eng.render(store, scene)
    assert cold.report["bricks_read"] > 0
    eng.bricks.clear()
    eng.device_cache.clear()
    n = prefetch(store, scene)
    coarse = int((prepare(store, scene).lod.levels >= 1).sum())  # their distributions are read too
    assert coarse > 0 and n == cold.report["bricks_read"] + coarse
    assert prefetch(store, scene) == 0  # all cached now
    warm = eng.render(store, scene)
    assert warm.report["bricks_read"] == 0 and warm.report["bricks_cached"] == cold.report["bricks_read"]
    assert np.array_equal(warm.rgba, cold.rgba)
    assert prefetch(store, {**scene, "quality": "full"}) == 0  # level 0 goes to the device whole


def test_a_camera_change_selects_nothing_again(store, eng, monkeypatch):
    """Without the view's weight (lod_visibility off) the level-of-detail selection depends on the TF, the quality
    and the clip region, not on the view: a turntable selects once; a TF change selects again. With it (the
    default) every new view selects, and a view seen before takes its kept selection."""
    import lodcast.renderer.lod.selection as selection

    calls = []
    real = selection.select_lod
    monkeypatch.setattr(selection, "select_lod", lambda *a, **k: calls.append(k.get("visibility")) or real(*a, **k))
    scene = {**_scene(0), "quality": {"reduction": 4}, "sampling": {"lod_visibility": False}}
    first = eng.render(store, scene)
    for az in (40, 200):
        r = eng.render(store, {**scene, "camera": {"azimuth": az, "elevation": 15}})
        assert r.report["reduction"] == first.report["reduction"]
    assert calls == [None]
    tf2 = {"points": [{"value": 0.5, "color": [1, 1, 1], "opacity": 0.0}, {"value": 1.0, "color": [1, 0, 0], "opacity": 0.5}]}
    eng.render(store, {**scene, "tf": tf2})
    assert calls == [None, None]
    calls.clear()
    seen = {**scene, "sampling": {}}
    for az in (0, 40, 0, 40):
        eng.render(store, {**seen, "camera": {"azimuth": az, "elevation": 15}})
    assert len(calls) == 2 and all(c is not None and c.shape == store.grid for c in calls)


def test_on_a_cpu_device_the_brick_cache_gives_way_to_the_device_cache(store, monkeypatch):
    """A CPU device's buffers are host memory: an atlas kept in the device cache holds the same bricks as the brick
    cache, so the brick cache's bound shrinks by what the device cache (and an atlas being filled) holds, down to
    an eighth of its cap. Without the shrink every brick of the selection would stay cached twice. A discrete
    GPU's atlas is not host memory: there the cache keeps its whole bound."""
    vol = as_volume(store)
    lv = np.zeros(store.grid, np.int8)
    plain = BrickPool(2**30)
    bricks.load_bricks(Renderer(), vol, lv, plain)
    cap = plain.nbytes  # every brick of the selection would fit
    eng = Renderer(brick_cache_mb=cap / 2**20)
    shared = eng.bricks
    da = lod_atlas.device_atlas(eng, vol, lv)
    held = eng.device_cache.nbytes
    assert held >= da.nbytes > cap // 2
    if eng.device.memory_is_host:  # PoCL, CI's device
        assert shared.nbytes <= max(cap // 8, cap - held) < plain.nbytes
        assert shared.max_bytes == max(cap // 8, cap - held)
    else:
        assert shared.nbytes == plain.nbytes and shared.max_bytes == cap
    eng.device_cache.clear()
    assert shared.max_bytes == cap


def test_full_resolution_passes_keep_their_voxels_whole(store, monkeypatch):
    """A full-resolution render beyond the device budget keeps each pass's voxels whole in the brick pool: the next
    frame, from any view, neither reads the store nor transposes bricks, and gives the unbudgeted image. Where the
    pool holds every level-0 brick already (an earlier selection at level 0), the first frame makes its passes'
    voxels from them without reading the store."""
    from lodcast.renderer.data import passes
    from lodcast.renderer.data.volume import VolumeView

    vol = as_volume(store)
    lv = np.zeros(store.grid, np.int8)
    budget = vol.n_voxels * 4 / 4 / 1e6
    eng = Renderer(brick_cache_mb=256, device_budget_mb=budget)
    first = eng.render(store, {**_scene(30), "quality": "full"})
    assert first.report["passes"] >= 4 and first.report["bricks_read"] > 0

    def refused(*_a, **_k):
        raise AssertionError("the pass's voxels were made again")

    refs = {az: Renderer().render(store, {**_scene(az), "quality": "full"}) for az in (30, 110)}
    np.testing.assert_array_equal(first.rgba, refs[30].rgba)
    with monkeypatch.context() as m:
        m.setattr(passes, "_level0_voxels", refused)
        m.setattr(VolumeView, "read_level0_region", refused)
        for az, ref in refs.items():
            r = eng.render(store, {**_scene(az), "quality": "full"})
            assert r.report["bricks_read"] == 0 and r.report["bricks_cached"] > 0
            np.testing.assert_array_equal(r.rgba, ref.rgba)
    again = Renderer(brick_cache_mb=256, device_budget_mb=budget)
    bricks.load_bricks(again, vol, lv)  # every level-0 brick in the pool
    with monkeypatch.context() as m:
        m.setattr(VolumeView, "read_level0_region", refused)
        r = again.render(store, {**_scene(30), "quality": "full"})
    assert r.report["bricks_read"] == 0
    np.testing.assert_array_equal(r.rgba, first.rgba)


@pytest.mark.parametrize("seed", range(3))
def test_the_free_rows_kept_between_insertions_are_those_a_scan_finds(seed):
    """The free rows an arena keeps from one insertion to the next (reset by eviction) are the ones a scan of its
    rows finds: a pool fed a random stream of insertions, look-ups and evictions, in two arenas, places every brick
    in the same row as one that scans at every insertion, and every brick found is its own block's."""
    rng = np.random.default_rng(seed)
    shape = (16, 16, 16)  # 16 KiB: 256 to a slab
    cost = int(np.prod(shape)) * 4 + ROW_BYTES
    pools = [BrickPool(700 * cost), BrickPool(700 * cost)]
    for step in range(120):
        fam = ("s", "key", int(rng.integers(0, 2)))
        blocks = np.unique(rng.integers(0, 5000, size=int(rng.integers(1, 90))))
        bricks = np.broadcast_to(blocks[:, None, None, None].astype(np.float32), (blocks.size, *shape))
        touch = rng.integers(0, 5000, size=40)
        for i, c in enumerate(pools):
            c.put(fam, 5000, blocks, np.ascontiguousarray(bricks))
            c.find(fam, 5000, touch)
            if i == 1:  # the reference: no rows kept, a scan at every insertion
                for a in c._arenas.values():
                    a.spare = None
        assert pools[0]._arenas.keys() == pools[1]._arenas.keys()
        for f in pools[0]._arenas:
            np.testing.assert_array_equal(pools[0]._arenas[f].slot, pools[1]._arenas[f].slot)
        for c in pools:
            held, got = c.get(fam, 5000, blocks)
            assert got is not None and (got[:, 0, 0, 0] == blocks[held]).all()


def test_pool_reuses_the_rows_eviction_frees():
    """Rows freed by eviction are filled again before any new slab is taken, and every brick found is its own
    block's: a long stream of insertions through a small pool keeps its first slabs."""
    from lodcast.renderer.pool import SLAB_BYTES

    shape = (64, 64, 64)  # a MiB each: four to a slab
    brick = int(np.prod(shape)) * 4
    assert SLAB_BYTES // brick == 4
    c = BrickPool(8 * (brick + ROW_BYTES))
    fam = ("s", "key", 0)
    for i in range(60):
        c.put(fam, 1000, np.array([i, i + 500]), np.stack([np.full(shape, i, np.float32),
                                                           np.full(shape, i + 500, np.float32)]))
        held, got = c.get(fam, 1000, np.array([i, i + 500]))
        assert held.all() and got is not None and got[:, 0, 0, 0].tolist() == [i, i + 500]
    arena = c._arenas[fam]
    live = sum(slab is not None for slab in arena.slabs)  # memory the pool holds beyond what it counts: none
    assert live <= 3 and arena.owner.size <= 16 and c.nbytes <= c.max_bytes and len(c) <= 8, (live, len(c))


def test_a_turntable_derives_its_selection_s_walk_info_once(store, eng, monkeypatch):
    """A kept selection comes back as the same read-only grid each frame, so what is derived from it (the block info
    with unloaded blocks marked, its digest for the walk's and the atlas's keys) is derived once: the frames after
    the first hash no grid. The marked info is the block info with unloaded blocks empty, and a caller's `levels`
    that change between renders are taken as they are each time."""
    import hashlib

    from lodcast.renderer import engine as engine_module

    scene = {**_scene(0), "quality": {"reduction": 4}, "sampling": {"lod_visibility": False}}
    pr = eng.prepare(store, scene)
    assert not pr.lod.levels.flags.writeable and not pr.block_info.flags.writeable
    base = eng.prepare(store, {**scene, "quality": "full"}).block_info
    want = np.where(pr.lod.levels >= 0, base, 0.0)
    np.testing.assert_array_equal(pr.block_info, want)
    hashed = []
    monkeypatch.setattr(engine_module, "_digest", lambda a: (hashed.append(a.shape), hashlib.blake2b(a.tobytes()).digest())[1])
    first = eng.render(store, scene).report
    n_first = len(hashed)
    for az in (10, 20, 30):
        r = eng.render(store, {**scene, "camera": {"azimuth": az, "elevation": 15}}).report
        assert r["bricks_read"] == 0 and r["reduction"] == first["reduction"]
        assert eng.prepare(store, {**scene, "camera": {"azimuth": az, "elevation": 15}}).block_info is pr.block_info
    assert pr.lod.levels.shape in hashed[:n_first] and pr.lod.levels.shape not in hashed[n_first:]  # a grid: once
    # explicit levels, changed in place between renders: each render takes them as they are now
    lv = np.asarray(pr.lod.levels).copy()
    a = eng.render(store, scene, levels=lv).rgba
    lv[lv >= 0] = 0
    b = eng.render(store, scene, levels=lv).rgba
    np.testing.assert_array_equal(b, eng.render(store, scene, levels=lv.copy()).rgba)
    assert not np.array_equal(a, b)


def test_spares_hand_over_the_smallest_buffer_that_fits_within_the_room_left():
    """Spares (renderer/cache.py): `take` gives the smallest buffer of at least the bytes asked and at most slack
    times them, once; the newest are kept, at most `most`, within a bound that is asked each time (the room a
    device cache leaves); ByteLru.make_room evicts, oldest first, what an entry of that size would."""
    room = [100]
    sp = Spares(lambda: room[0], most=3, slack=1.25)
    for name, n in (("a", 40), ("b", 30), ("c", 20)):
        sp.give(name, n)
    assert (len(sp), sp.nbytes) == (3, 90)
    assert sp.take(50) is None and sp.take(10) is None  # nothing large enough; c (20) is over 1.25 × 10
    assert sp.take(25) == "b" and sp.take(25) is None  # b (30) fits 25..31.25, once; a (40) does not
    sp.give("d", 50)  # 40 + 20 + 50 > 100: the oldest goes
    assert (len(sp), sp.nbytes) == (2, 70) and sp.take(39) is None and sp.take(18) == "c"
    room[0] = 10
    sp.trim()
    assert (len(sp), sp.nbytes) == (0, 0)
    sp = Spares(1000, most=1)
    sp.give("a", 1)
    sp.give("b", 1)
    assert len(sp) == 1 and sp.take(1) == "b"

    lru = ByteLru(100)
    for k, n in (("x", 30), ("y", 30), ("z", 30)):
        lru.put(k, k, n)
    lru.make_room(50)  # 90 + 50 > 100: x and y go, z stays
    assert (lru.get("x"), lru.get("y"), lru.get("z"), lru.nbytes) == (None, None, "z", 30)
    lru.make_room(70)
    assert lru.get("z") == "z"
    lru.make_room(71)
    assert len(lru) == 0
