"""LOD selection (thesis eq. 3.2): the fast steepest-chord selection against a literal priority-queue greedy,
against exhaustive search where greedy is optimal, and the selection's properties (budget, lossless, crop)."""
from __future__ import annotations

import heapq
import itertools

import numpy as np
import pytest
from test_significance import SKIN_BONE, synthetic_meta

from lodcast.renderer.lod.selection import MB, _take_prefix, crop_mask, greedy, select_from_meta
from lodcast.renderer.lod.significance import BlockMeta, block_significance, level_profile
from lodcast.renderer.scene.scene import QualityBudget, QualityReduction, SceneError, TransferFunction
from lodcast.store.histogram import Bins


def heap_greedy(zeta: np.ndarray, maxlev: np.ndarray, nsamp: np.ndarray, budget: int) -> np.ndarray:
    """The thesis' modified priority queue, literally: every block starts at the coarsest level; the queue
    holds every transition γ → γ* (γ* any finer allowed level) with priority χ = (ζ(γ) − ζ(γ*))/(n_γ* − n_γ);
    the best is popped (ties: smaller block index, then the nearer target); a transition whose block has left
    γ is defunct and dropped (lazy removal); the selection stops at the first best transition that does not fit
    the remaining budget; after a transition the block's new transitions are inserted."""
    n, L = zeta.shape
    level = np.full(n, L - 1)
    heap: list = []

    def push(i: int) -> None:
        g = int(level[i])
        for t in range(g - 1, int(maxlev[i]) - 1, -1):
            chi = (float(zeta[i, g]) - float(zeta[i, t])) / float(nsamp[t] - nsamp[g])
            heapq.heappush(heap, (-chi, i, int(nsamp[t]), g, t))

    for i in range(n):
        push(i)
    remaining = int(budget)
    while heap:
        _, i, _, g, t = heapq.heappop(heap)
        if level[i] != g:
            continue  # defunct
        cost = int(nsamp[t] - nsamp[g])
        if cost > remaining:
            break
        remaining -= cost
        level[i] = t
        push(i)
    return level


def _nsamp(L: int) -> np.ndarray:
    return np.array([(1 << (L - 1 - k)) ** 3 for k in range(L)], np.int64)  # block edge 2^(L-1)


def _random_case(rng: np.random.Generator, profile_form: bool):
    n = int(rng.integers(1, 40))
    L = int(rng.integers(2, 7))
    nsamp = _nsamp(L)
    if profile_form:
        prof = level_profile(L)
        z0 = rng.integers(1, 4, n).astype(np.float64) if rng.random() < 0.5 else rng.random(n) * 10
        zeta = (z0[:, None] * prof[None, :]).astype(np.float32)
    else:
        prof = None
        if rng.random() < 0.5:  # small integers: many exact ties of χ, collinear points
            zeta = rng.integers(0, 5, (n, L)).astype(np.float32)
        else:
            zeta = (rng.random((n, L)) * 10).astype(np.float32)
        zeta[:, 0] = 0.0
    maxlev = rng.integers(0, L, n) if rng.random() < 0.5 else np.zeros(n, np.int64)
    full = int(sum(nsamp[m] - nsamp[L - 1] for m in maxlev))
    budget = int(rng.integers(0, full + 2)) if rng.random() < 0.85 else full + 10
    return zeta, maxlev, nsamp, budget, prof


@pytest.mark.parametrize("profile_form", [False, True])
def test_fast_selection_equals_priority_queue(profile_form: bool) -> None:
    rng = np.random.default_rng(7 + profile_form)
    for _ in range(400):
        zeta, maxlev, nsamp, budget, prof = _random_case(rng, profile_form)
        want = heap_greedy(zeta, maxlev, nsamp, budget)
        got = greedy(zeta, maxlev, nsamp, budget, profile=prof)
        np.testing.assert_array_equal(got, want)
        if prof is not None:  # the general chain walk agrees too
            np.testing.assert_array_equal(greedy(zeta, maxlev, nsamp, budget), want)
        used = int(sum(nsamp[got] - nsamp[-1]))
        assert used <= budget


def test_fast_selection_equals_priority_queue_at_scale_with_ties() -> None:
    """5,000 blocks (beyond the quickselect's small-case cut-off), ζ from few distinct values (ties)."""
    rng = np.random.default_rng(11)
    L = 6
    nsamp = _nsamp(L)
    n = 5000
    z0 = rng.integers(1, 30, n).astype(np.float64)
    zeta = (z0[:, None] * level_profile(L)[None, :]).astype(np.float32)
    maxlev = np.where(rng.random(n) < 0.1, rng.integers(0, L, n), 0)
    full = int((nsamp[maxlev] - nsamp[-1]).sum())
    for frac in (0.0, 0.013, 0.2, 0.5, 0.77, 0.999):
        budget = int(frac * full)
        want = heap_greedy(zeta, maxlev, nsamp, budget)
        np.testing.assert_array_equal(greedy(zeta, maxlev, nsamp, budget, profile=level_profile(L)), want)


def test_take_prefix_quickselect_equals_stable_sort() -> None:
    rng = np.random.default_rng(3)
    for m, distinct in ((20000, 7), (50000, 10**9), (9000, 2)):
        keys = rng.integers(0, distinct, m).astype(np.float64) * 0.37
        costs = rng.integers(1, 500, m)
        order = np.argsort(-keys, kind="stable")
        cs = np.cumsum(costs[order])
        for budget in (0, 1, int(cs[-1] * 0.3), int(cs[-1] * 0.9), int(cs[-1])):
            want = np.zeros(m, bool)
            want[order[: np.searchsorted(cs, budget, side="right")]] = True
            np.testing.assert_array_equal(_take_prefix(keys, costs, budget), want)


def test_greedy_matches_exhaustive_search_where_greedy_is_optimal() -> None:
    """Greedy is optimal for min Σ_i ζ_i(γ_i) s.t. Σ_i n_i(γ_i) ≤ budget when every block's (n, ζ) points are
    convex (ζ linear in level, n = 8^k: the thesis' distribution; every hull vertex is a level) and the budget is
    one the greedy uses up exactly (a breakpoint: the greedy's cost after some number of transitions). Then it is
    the Lagrangian optimum for the slope at the cut. Exhaustive: every level assignment of ≤ 5 blocks × ≤ 4 levels."""
    rng = np.random.default_rng(2)
    checked = 0
    for _ in range(60):
        n = int(rng.integers(1, 6))
        L = int(rng.integers(2, 5))
        nsamp = _nsamp(L)
        prof = level_profile(L)
        zeta = (rng.random(n)[:, None] * 10 * prof[None, :])
        maxlev = np.zeros(n, np.int64)
        # breakpoints: the costs after each transition of the queue
        costs = sorted({int((nsamp[heap_greedy(zeta, maxlev, nsamp, b)] - nsamp[-1]).sum()) for b in range(0, int((nsamp[0] - nsamp[-1]) * n) + 1, max(1, int(nsamp[0]) // 16))})
        for budget in costs:
            got = greedy(zeta, maxlev, nsamp, budget, profile=prof)
            g_obj = zeta[np.arange(n), got].sum()
            best = np.inf
            for assign in itertools.product(range(L), repeat=n):
                a = np.array(assign)
                if (nsamp[a] - nsamp[-1]).sum() <= budget:
                    best = min(best, zeta[np.arange(n), a].sum())
            assert g_obj <= best + 1e-9
            checked += 1
    assert checked > 100


# --------------------------------------------------------------------------------------------- select_from_meta
@pytest.fixture(scope="module")
def meta() -> BlockMeta:
    rng = np.random.default_rng(9)
    m = synthetic_meta(rng, 64, Bins.for_range(-1000.0, 2000.0, integer=False, max_bins=256), sd_max=0.02, clusters=2)
    return BlockMeta((4, 4, 4), m.n_levels, m.bins, m.mean, m.count, m.min_border, m.max_border, m.starts, m.heights, m.hist)


N_VOX = 64 * 32**3


def test_lossless_is_every_nonzero_block_at_full_level(meta: BlockMeta) -> None:
    sel = select_from_meta(meta, SKIN_BONE, "lossless", n_voxels=N_VOX, block_size=32)
    z0, vis = block_significance(meta, SKIN_BONE)
    lv = sel.levels.ravel()
    assert sel.levels.dtype == np.int8 and sel.levels.shape == (4, 4, 4)
    assert np.all(lv[(z0 > 0)] == 0)
    assert np.all(lv[~vis] == -1)
    assert np.all(lv[vis & (z0 == 0)] == 5)
    assert sel.blocks_skipped == int((~vis).sum()) > 0
    assert sel.predicted_delta_e == 0.0
    assert sel.bytes == 4 * (int((z0 > 0).sum()) * 32**3 + int((vis & (z0 == 0)).sum()))
    assert sel.reduction == pytest.approx(N_VOX * 4 / sel.bytes)
    # an unlimited budget is the same selection
    big = select_from_meta(meta, SKIN_BONE, {"budget_mb": 1e6}, n_voxels=N_VOX, block_size=32)
    np.testing.assert_array_equal(big.levels, sel.levels)


@pytest.mark.parametrize("method", ["tf", "tf_full_hist", "l2", "uniform"])
def test_budget_is_never_exceeded(meta: BlockMeta, method: str) -> None:
    rng = np.random.default_rng(4)
    lossless = select_from_meta(meta, SKIN_BONE, "lossless", n_voxels=N_VOX, block_size=32, method=method).bytes
    for _ in range(25):
        b = float(rng.uniform(0.0005, 1.2 * lossless / MB))
        try:
            sel = select_from_meta(meta, SKIN_BONE, QualityBudget(budget_mb=b), n_voxels=N_VOX, block_size=32, method=method)
        except SceneError:
            vis = block_significance(meta, SKIN_BONE)[1]
            assert b * MB < 4 * int(vis.sum())  # only below the coarsest selection
            continue
        assert sel.bytes <= b * MB
        if method != "uniform":  # the greedy stops within one transition (≤ 32³ − 16³ samples) of the budget
            assert sel.bytes >= min(lossless, b * MB) - 4 * (32**3 - 16**3)
    r = select_from_meta(meta, SKIN_BONE, QualityReduction(reduction=30), n_voxels=N_VOX, block_size=32, method=method)
    assert r.reduction >= 30.0
    assert r.zeta.shape == (4, 4, 4, 6) and r.zeta.dtype == np.float32


def test_tf_selection_predicts_less_error_than_baselines_at_equal_budget(meta: BlockMeta) -> None:
    q = {"reduction": 64}
    pred = {m: select_from_meta(meta, SKIN_BONE, q, n_voxels=N_VOX, block_size=32, method=m).predicted_delta_e for m in ("tf", "l2", "uniform")}
    assert pred["tf"] <= pred["l2"] + 1e-9 and pred["tf"] <= pred["uniform"] + 1e-9


def test_predicted_delta_e_is_count_weighted_rms(meta: BlockMeta) -> None:
    sel = select_from_meta(meta, SKIN_BONE, {"reduction": 64}, n_voxels=N_VOX, block_size=32)
    lv = sel.levels.ravel()
    z = sel.zeta.reshape(-1, 6)
    on = np.flatnonzero(lv >= 0)
    w = meta.count[on]
    want = np.sqrt((w * z[on, lv[on]].astype(np.float64) ** 2).sum() / w.sum())
    assert sel.predicted_delta_e == pytest.approx(want, rel=1e-12)
    assert sel.predicted_delta_e > 0


def test_uniform_takes_the_finest_level_that_fits(meta: BlockMeta) -> None:
    vis = block_significance(meta, SKIN_BONE)[1]
    nv = int(vis.sum())
    budget = nv * 8**3 * 4 + 100  # level 2 (8³) fits, level 1 (16³) does not
    sel = select_from_meta(meta, SKIN_BONE, {"budget_mb": budget / MB}, n_voxels=N_VOX, block_size=32, method="uniform")
    lv = sel.levels.ravel()
    assert np.all(lv[vis] == 2) and np.all(lv[~vis] == -1)


def test_crop_and_max_level(meta: BlockMeta) -> None:
    grid, shape = (4, 4, 4), (128, 128, 128)
    spacing, origin = (1.0, 2.0, 0.5), (10.0, -5.0, 0.0)
    # world box of voxels z 40..70, y all, x 0..20
    lo = (origin[0] + 40 * spacing[0], -1e9, origin[2])
    hi = (origin[0] + 70 * spacing[0], 1e9, origin[2] + 20 * spacing[2])
    m = crop_mask(grid, shape, spacing, origin, 32, (lo, hi))
    assert m[:, 0, 0].tolist() == [False, True, True, False]  # z blocks 1 (32..63) and 2 (64..95)
    assert m[1, :, 0].all() and not m[1, 0, 1:].any()
    # one voxel of margin: a box ending a voxel inside block 1's face also loads block 0 (interpolation stencil)
    m2 = crop_mask(grid, shape, spacing, origin, 32, {"lower": (origin[0] + 32.2, -1e9, -1e9), "upper": (1e9, 1e9, 1e9)})
    assert m2[:, 0, 0].tolist() == [True, True, True, True]
    maxlev = np.full(64, 2)
    sel = select_from_meta(meta, SKIN_BONE, "lossless", n_voxels=N_VOX, block_size=32, in_crop=m, max_level=maxlev)
    lv = sel.levels.ravel()
    assert np.all(lv[~m.ravel()] == -1)
    assert lv.max() <= 5 and lv[lv >= 0].min() >= 2
    z0, vis = block_significance(meta, SKIN_BONE)
    assert np.all(lv[m.ravel() & (z0 > 0)] == 2)
    assert sel.blocks_skipped == int((~(m.ravel() & vis)).sum())


def test_store_select_lod_end_to_end(tmp_path) -> None:
    """select_lod on an ingested store: TF-empty blocks skipped, budget respected, ζ from the store's histograms."""
    import lodcast
    from lodcast.renderer.lod.selection import select_lod

    rng = np.random.default_rng(0)
    z, y, x = np.meshgrid(*(np.arange(64),) * 3, indexing="ij")
    vol = np.where((z - 32) ** 2 + (y - 32) ** 2 + (x - 32) ** 2 < 20**2, 500, -900) + rng.normal(0, 20, (64, 64, 64))
    store = lodcast.ingest(vol.astype(np.int16), tmp_path / "s.zarr", progress=False, block_size=32)
    tf = {"points": [{"value": 0, "color": [1, 1, 1], "opacity": 0.0}, {"value": 600, "color": [1, 0.8, 0.7], "opacity": 0.8}]}
    sel = select_lod(store, [tf], "lossless")
    assert sel.levels.shape == store.grid and sel.zeta.shape == store.grid + (store.n_levels,)
    assert sel.blocks_skipped == 0  # every 32³ block of this sphere meets values above 0
    half = select_lod(store, TransferFunction.model_validate(tf), {"budget_mb": sel.bytes / MB / 8}, crop=((0, 0, 0), (40, 63, 63)))
    assert half.bytes <= sel.bytes / 8 and half.predicted_delta_e > 0
    none = select_lod(store, {"points": [{"value": 1000, "opacity": 0.0}, {"value": 1001, "opacity": 1.0}]}, "lossless")
    assert none.blocks_skipped == 8 and none.bytes == 0 and none.reduction == float("inf")
