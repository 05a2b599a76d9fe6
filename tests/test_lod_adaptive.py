"""Adaptive object-space sampling (LC_ADAPTIVE, thesis §3.6.1): a thin full-resolution block between coarse ones.
The limited scheme cuts the coarse steps at the (half-)block boundaries, so the fine block is sampled at the base
step over its whole length, on full resolution's lattice — its opacity comes out exact up to one base step at its
near face — while the naive scheme lets a coarse step run into it and misses part of it."""
from __future__ import annotations

import numpy as np
import pytest

import lodcast
from lodcast.renderer.data import passes, sampler
from lodcast.renderer.frame.render import Renderer
from lodcast.store.layout import cell_edge

B = 16
A = 0.1  # TF opacity of value 1 per unit distance (1 voxel)
TF = {"points": [{"value": 0.25, "color": [1, 1, 1], "opacity": 0.0}, {"value": 1.0, "color": [1, 1, 1], "opacity": A}]}
SHAPE = (16, 16, 80)  # z, y, x: five blocks along x
LEVELS = np.array([4, 4, 0, 4, 4], np.int8).reshape(1, 1, 5)  # level 4 = one sample per block
W = H = 12


@pytest.fixture(autouse=True)
def block_walk(monkeypatch):
    """These tests count the adaptive march's samples over the block walk; the half-block cells of empty-space
    skipping (tests/test_atlas_cells.py) would also leave out the coarse blocks 1 and 3, whose samples are all 0."""
    monkeypatch.setattr(passes, "_cells", lambda pr, da, *a: None)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    v = np.zeros(SHAPE, np.float32)
    v[:, :, 2 * B:3 * B] = 1.0  # only the fine block holds material
    return lodcast.ingest(v, tmp_path_factory.mktemp("adaptive") / "v.zarr", block_size=B, progress=False)


def _cam(f):
    c = np.array([39.5, 7.5, 7.5])
    f = np.asarray(f, float) / np.linalg.norm(f)
    up = [0.0, 0.0, 1.0] if abs(f[2]) < 0.9 else [0.0, 1.0, 0.0]
    eye = c - 200 * f
    return {"eye": eye.tolist(), "target": c.tolist(), "up": up, "projection": "orthographic", "view_height": 8.0}


def _scene(cam, interp="nearest_block", step=0.7, **s):
    return {"tf": TF, "width": W, "height": H, "camera": cam, "format": "npy",
            "sampling": {"interpolation": interp, "step": step, **s}}


def _chord_in_fine_block(cam) -> np.ndarray:
    """Per pixel: length of the ray inside box ∩ the fine block's slab (x in [31.5, 47.5]), docs/design.md's camera."""
    eye, tgt, up = (np.asarray(cam[k], float) for k in ("eye", "target", "up"))
    f = (tgt - eye) / np.linalg.norm(tgt - eye)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    j, i = np.meshgrid(np.arange(W), np.arange(H))
    hh = cam["view_height"] / 2
    px = (2 * (j + 0.5) / W - 1) * hh * W / H
    py = (1 - 2 * (i + 0.5) / H) * hh
    o = eye + px[..., None] * r + py[..., None] * u
    lo = np.array([2 * B - 0.5, -0.5, -0.5])
    hi = np.array([3 * B - 0.5, SHAPE[1] - 0.5, SHAPE[0] - 0.5])
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o) / f, (hi - o) / f
    t0 = np.minimum(ta, tb).max(axis=-1)
    t1 = np.maximum(ta, tb).min(axis=-1)
    return np.maximum(t1 - t0, 0.0)


@pytest.mark.parametrize("f", [(1, 0, 0), (1, 0.35, 0.2), (-1, -0.2, 0.3)])
def test_limited_adaptive_samples_the_fine_block_over_its_whole_length(eng, store, f):
    """The fine block is sampled at the base step over its whole length: its opacity comes out exact; the naive
    steps, which run into the fine block, miss more than 0.02. At "lossless" (LC_LATTICE) the fine block's steps
    begin on full resolution's lattice (the coarse block's last step ends where the lattice's first step with its
    sample in the fine block begins, within one base step of the face): exact up to one base step of the fine
    block's extinction, here at most 0.014."""
    cam = _cam(f)
    L = _chord_in_fine_block(cam)
    assert L.min() > 10
    exact = 1 - (1 - A) ** L  # NB field: 1 in the fine block's whole region, 0 elsewhere
    step = 0.7
    lim = eng.render(store, _scene(cam, adaptive_object=True), levels=LEVELS)
    naive = eng.render(store, _scene(cam, adaptive_naive=True), levels=LEVELS)
    assert "-DLC_ADAPTIVE" in lim.report["build_options"] and "-DLC_ADAPTIVE_NAIVE" not in lim.report["build_options"]
    assert "-DLC_ADAPTIVE_NAIVE" in naive.report["build_options"]
    np.testing.assert_allclose(lim.rgba[..., 3], exact, atol=2e-5)
    assert np.abs(naive.rgba[..., 3] - exact).max() > 0.02  # the naive step runs into the fine block
    lat = eng.render(store, {**_scene(cam, adaptive_object=True), "quality": "lossless"}, levels=LEVELS)
    assert "-DLC_LATTICE" in lat.report["build_options"] and "-DLC_LATTICE" not in lim.report["build_options"]
    one_step = -np.log1p(-A) * step * (1 - A) ** (L - step)  # d(opacity)/dL times a step
    assert (np.abs(lat.rgba[..., 3] - exact) <= one_step + 2e-5).all()
    uniform = eng.render(store, _scene(cam, adaptive_object=False), levels=LEVELS)
    assert lim.report["samples"] < uniform.report["samples"]
    # adaptive sampling is the default at the budgeted qualities (the levels given replace the selection)
    default = eng.render(store, {**_scene(cam), "quality": {"reduction": 2}}, levels=LEVELS)
    assert default.report["adaptive"] == "limited" and default.report["samples"] == lim.report["samples"]


def test_samples_landing_in_the_fine_block_along_x(eng, store):
    """The cells are half blocks (8 voxels), each stepped at its own block's level. Along +x every ray crosses
    block 1 (one step of 11.2 voxels, cut at 8, in each half), the fine block (base steps of 0.7 from its face that
    run on from its first half into its second, ceil(16 / 0.7) = 23 over its whole length, the last cut at its far
    face; were they cut at the halves' common face too, 12 + 12) and block 3 (one step per half); NB: blocks 0 and
    4 are empty (skipped): exactly 2 + 23 + 2 = 27 samples per ray. With II blocks 0 and 4 are marched too, since
    the interblock interpolation of the coarse blocks 1 and 3 reaches into them: 8 + 23 = 31."""
    cam = _cam((1, 0, 0))
    lim = eng.render(store, _scene(cam, adaptive_object=True), levels=LEVELS)
    assert lim.report["samples"] == 27 * W * H
    ii = eng.render(store, _scene(cam, "interblock", adaptive_object=True), levels=LEVELS)
    assert ii.report["samples"] == 31 * W * H
    naive = eng.render(store, _scene(cam, adaptive_naive=True), levels=LEVELS)
    assert naive.report["samples"] < lim.report["samples"]


def test_interblock_limited_adaptive_keeps_the_coarse_step_next_to_a_finer_block(eng, store):
    """With II each half-block cell steps at its own block's level, the half next to the fine block too (atlas.py's
    step_levels: the blend towards a finer block spans half a coarse sample and holds no finer detail along the
    face's normal than the coarse field). Here the extreme case, level 4 (one sample per block) beside level 0,
    the ramp filling the whole coarse half: one cut step there leaves an opacity error of 8.4e-3 (of 0.91) against
    a fine reference, bounded below by 1e-2; the naive steps, which run into the fine block, miss 4.8e-2. The fine
    block itself is sampled at the base step over its whole length (its halves are level 0)."""
    cam = _cam((1, 0.3, 0.15))
    ref = eng.render(store, _scene(cam, "interblock", step=0.02), levels=LEVELS).rgba[..., 3]
    lim = eng.render(store, _scene(cam, "interblock", adaptive_object=True), levels=LEVELS)
    naive = eng.render(store, _scene(cam, "interblock", adaptive_naive=True), levels=LEVELS)
    e_lim = np.abs(lim.rgba[..., 3] - ref).max()
    e_naive = np.abs(naive.rgba[..., 3] - ref).max()
    assert e_lim < 1e-2 and e_naive > 4 * e_lim


@pytest.mark.parametrize("level, step", [(4, 0.5), (2, 0.5), (1, 0.3), (3, 0.7), (1, 0.45), (2, 0.7)])
def test_constant_coarse_regions_stay_exact(eng, tmp_path, level, step):
    """Opacity correction: a constant volume at a coarse level k, stepped at h = 2^(k + 1) x the base step (capped
    at 2^4 = B: renderer/data/atlas.py's step_levels; whole steps take their alpha from the per-level tables, the last
    one from the extinction), gives 1 - (1 - a)^(L / unit). Each half-block cell's 8 voxels take the nearest whole
    number of steps, at least one (h = 1.8: 4, not ceil's 5; h = 5.6: 1, not 2)."""
    st = lodcast.ingest(np.ones(SHAPE, np.float32), tmp_path / "c.zarr", block_size=B, progress=False)
    for f in ((1, 0, 0), (1, 0.3, -0.2)):
        cam = _cam(f)
        full = eng.render(st, _scene(cam, "interblock", step=step, early_termination=1.0)).rgba[..., 3]
        r = eng.render(st, _scene(cam, "interblock", step=step, adaptive_object=True, early_termination=1.0),
                   levels=np.full((1, 1, 5), level, np.int8))
        np.testing.assert_allclose(r.rgba[..., 3], full, atol=2e-5)
        if f[1] == 0:
            np.testing.assert_allclose(r.rgba[..., 3], 1 - (1 - A) ** 80, atol=2e-5)
            n_cells, cell = 10, B / 2
            assert r.report["samples"] == n_cells * max(1, int(np.floor(cell / (step * 2 ** min(level + 1, 4)) + 0.5))) * W * H


def test_default_interpolation_is_nearest_block(eng, store):
    """sampling.interpolation left out: nearest block at every quality that samples the atlas; a named
    interpolation is always kept. The default renders exactly what naming it renders."""
    cam = _cam((1, 0.35, 0.2))
    scene = {"tf": TF, "width": W, "height": H, "camera": cam, "format": "npy"}
    coarse = np.array([4, 4, 1, 4, 4], np.int8).reshape(1, 1, 5)
    for quality, levels in [({"reduction": 2}, LEVELS), ({"reduction": 2}, coarse), ({"budget_mb": 1}, coarse),
                            ("lossless", coarse)]:
        r = eng.render(store, {**scene, "quality": quality}, levels=levels)
        assert r.report["interpolation"] == "nearest_block", quality
        named = eng.render(store, {**scene, "quality": quality, "sampling": {"interpolation": "nearest_block"}},
                       levels=levels)
        np.testing.assert_array_equal(r.rgba, named.rgba)
        kept = eng.render(store, {**scene, "quality": quality, "sampling": {"interpolation": "interblock"}}, levels=levels)
        assert kept.report["interpolation"] == "interblock"


def test_huge_steps_still_cross_every_cell(eng, store):
    """A step longer than the volume: one cut step per half-block cell of a coarse block, one across the whole
    level-0 block (full resolution's lattice lies beyond it, and no step has its sample in the first half: the
    step runs on into the second half, where it is cut at the block's far face), and the march still reaches the
    far side."""
    cam = _cam((1, 0, 0))
    r = eng.render(store, _scene(cam, step=500.0, adaptive_object=True, early_termination=1.0), levels=LEVELS)
    assert r.report["samples"] == 5 * W * H  # NB: the halves of blocks 1 and 3, block 2 once
    np.testing.assert_allclose(r.rgba[..., 3], 1 - (1 - A) ** 16, atol=2e-5)


def test_step_levels_one_sample_per_coarse_voxel(eng):
    """Step level per cell: 0 where the cell's block is at level 0 (the base step), k + 1 where it is at level
    k >= 1 (one sample per level-k voxel at the default step 1/2), capped at log2 B, plus NEAR_LEVEL0 (8) in a
    coarse cell with a level-0 cell (or an unloaded one, passed as level 0) across a face; a skipped block's cells
    hold -(code + 1), an unloaded block's -1; the half-block cells of each block take its level."""
    from lodcast.renderer.data.atlas import NEAR_LEVEL0, skipped, step_levels

    assert NEAR_LEVEL0 == 8  # raycast.cl's v_ & 8
    lv = np.array([4, 3, 0, 1, 2, -1, 2], np.int8).reshape(1, 1, 7)
    st = step_levels(lv, 16)
    assert st.shape == (2, 2, 14) and (st == st[:1, :1]).all()
    assert st[0, 0].tolist() == [4, 4, 4, 12, 0, 0, 10, 2, 3, 11, -1, -1, 11, 3]
    skip = np.zeros(lv.shape, bool)
    skip[..., 6] = True
    skip[..., 2] = True
    assert step_levels(lv, 16, skip)[0, 0].tolist() == [4, 4, 4, 12, -1, -1, 10, 2, 3, 11, -1, -1, -12, -4]
    assert step_levels(lv, 8)[0, 0, ::2].tolist() == [3, 3, 0, 10, 3, -1, 11]
    # skipping more cells later keeps those skipped already
    assert skipped(st, np.ones(st.shape, bool))[0, 0, ::2].tolist() == [-5, -5, -1, -11, -4, -1, -12]


def _cellwise_step_levels(levels: np.ndarray, block_size: int, skip: np.ndarray | None) -> np.ndarray:
    """step_levels as its docstring states it, over the half-block cells themselves: every cell's code from its
    block, NEAR_LEVEL0 from its six face neighbours' codes, skipped cells -(code + 1)."""
    from lodcast.renderer.data.atlas import NEAR_LEVEL0, half_cells

    lv = levels.astype(np.int64)
    off = half_cells((lv < 0) | (False if skip is None else skip))
    s = half_cells(np.minimum(np.where(lv >= 1, lv + 1, np.maximum(lv, 0)), int(block_size).bit_length() - 1))
    fine = np.pad(s == 0, 1)
    near = np.zeros(s.shape, bool)
    for ax in range(3):
        for d in (0, 2):
            near |= fine[tuple(slice(d, d + n) if a == ax else slice(1, 1 + n) for a, n in enumerate(s.shape))]
    s = np.where((s > 0) & near, s | NEAR_LEVEL0, s)
    return np.where(off, -s - 1, s).astype(np.int8)


@pytest.mark.parametrize("seed", range(4))
def test_step_levels_from_the_blocks_are_the_cells_own(seed):
    """step_levels works per block and octant: the same codes as computed cell by cell, on random grids (one
    block thick, odd sizes, every level, unloaded and skipped blocks)."""
    from lodcast.renderer.data.atlas import step_levels

    rng = np.random.default_rng(seed)
    for g in ((1, 1, 7), (3, 4, 5), (6, 1, 9), (7, 8, 9)):
        lv = rng.integers(-1, 6, size=g).astype(np.int8)
        skip = rng.random(g) < 0.3
        for B in (8, 16, 32):
            for sk in (None, skip):
                np.testing.assert_array_equal(step_levels(lv, B, sk), _cellwise_step_levels(lv, B, sk))


@pytest.mark.parametrize("seed", range(3))
def test_step_levels_of_a_new_selection_from_the_last_one_are_step_levels(monkeypatch, seed):
    """A new selection's step levels computed from the newest ones of the same grid (frame/prepare.py), only for
    the blocks whose level, skip or a face neighbour's level-0 status changed, are step_levels over the
    whole grid: a run of random changes (levels, unloaded blocks, skips; blocks at the grid's faces), with and
    without skips, each from the one before."""
    from lodcast.renderer.data import atlas
    from lodcast.renderer.frame import prepare

    grids = []
    orig = atlas.step_levels
    monkeypatch.setattr(atlas, "step_levels", lambda lv, *a: grids.append(lv.shape) or orig(lv, *a))
    rng = np.random.default_rng(seed)
    g = (20, 21, 22)
    for B, with_skip in ((16, False), (8, True)):
        engine = Renderer()
        try:
            lv = rng.integers(-1, 6, size=g).astype(np.int8)
            skip = rng.random(g) < 0.3 if with_skip else None
            for frac in (0.002, 0.004, 0.001, 0.6, 0.003):
                lv = lv.copy()
                m = rng.random(g) < frac
                m[0, 0, 0] = m[-1, -1, -1] = m[0, -1, 5] = True
                lv[m] = rng.integers(-1, 6, size=int(m.sum()))
                if skip is not None:
                    skip = skip ^ (rng.random(g) < frac / 2)
                grids.clear()
                got = prepare._step_levels(engine, lv, B, skip)
                # block by block, no pass over the grid (the first has none to start from; 0.6 changes most blocks)
                assert (grids == []) == (frac not in (0.002, 0.6))
                np.testing.assert_array_equal(got, orig(lv, B, skip))
        finally:
            engine.close()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_level_zero_steps_lie_on_full_resolutions_lattice(eng, tmp_path, monkeypatch, seed):
    """Every block at level 0 and adaptive steps on: the walk over half-block cells takes full resolution's samples
    (runs of level-0 cells run on, and a skipped cell is passed as if sampled), so with
    the apron's trilinear interpolation the image is full resolution's to float rounding and the sample count is
    its own (up to a sample whose position lies within rounding of a skipped cell's face). Random smooth volumes
    with empty regions, random views, a TF with a sharp edge. (Steps restarted at every cell face, as before, took
    4.6% more samples on the chest CT and moved the image off full resolution's by up to 1.2 mean ΔE at
    "lossless".)"""
    monkeypatch.undo()  # the half-block cells skip what full resolution's cells skip
    from lodcast.renderer.kernel.config import KernelConfig

    # (and not the samples of their empty octants, which full resolution's cells of 8³ take)
    monkeypatch.setattr(KernelConfig, "octants", property(lambda self: False))
    rng = np.random.default_rng(seed)
    v = rng.random((6, 6, 6))
    v = np.kron(v, np.ones((8, 8, 8)))  # 48³
    for ax in range(3):  # smooth it a little: a field, not a checkerboard
        v = (v + np.roll(v, 1, ax) + np.roll(v, -1, ax)) / 3
    v[:, :, :16] = 0.0  # an empty slab: cells skipped, steps realigned after them
    st = lodcast.ingest(v.astype(np.float32), tmp_path / "r.zarr", block_size=B, progress=False)
    tf = {"points": [{"value": 0.45, "color": [1, 0.5, 0.2], "opacity": 0.0},
                     {"value": 0.5, "color": [1, 0.5, 0.2], "opacity": 0.3},
                     {"value": 0.7, "color": [0.2, 0.5, 1], "opacity": 0.6}]}
    for _ in range(2):
        cam = {"azimuth": float(rng.uniform(0, 360)), "elevation": float(rng.uniform(-60, 60))}
        scene = {"tf": tf, "width": 24, "height": 24, "camera": cam, "format": "npy",
                 "sampling": {"step": float(rng.uniform(0.3, 0.9)), "early_termination": 1.0}}
        with monkeypatch.context() as m:  # full resolution's walk over the atlas's cells (this volume's own: 4³)
            m.setattr(sampler, "ess_cell", lambda shape, b: cell_edge(b))
            eng.device_cache.clear()
            full = eng.render(st, scene)
            eng.device_cache.clear()
        lod = eng.render(st, {**scene, "quality": "lossless",
                          "sampling": {**scene["sampling"], "adaptive_object": True}},
                     levels=np.zeros(st.layout.grid, np.int8))
        assert "-DLC_ADAPTIVE" in lod.report["build_options"]
        assert full.rgba[..., 3].max() > 0.5
        np.testing.assert_allclose(lod.rgba, full.rgba, rtol=0, atol=1e-4)
        assert abs(lod.report["samples"] - full.report["samples"]) <= 2


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_skipped_codes_over_random_steps(eng, seed):
    """atlas.skipped in int8 (no int64 temporaries over a large grid's cells) against the rule in int64: a cell that
    `where` marks and that is sampled (code s >= 0, NEAR_LEVEL0 included) becomes -(s + 1), skipped ones stay."""
    from lodcast.renderer.data.atlas import NEAR_LEVEL0, skipped

    rng = np.random.default_rng(seed)
    st = rng.integers(-(NEAR_LEVEL0 + 8), NEAR_LEVEL0 + 8, size=(5, 6, 7)).astype(np.int8)
    where = rng.random(st.shape) < 0.5
    s64 = st.astype(np.int64)
    ref = np.where(where & (s64 >= 0), -s64 - 1, s64)
    got = skipped(st, where)
    assert got.dtype == np.int8 and got.flags.c_contiguous
    np.testing.assert_array_equal(got, ref)
    np.testing.assert_array_equal(st, skipped(st, np.zeros(st.shape, bool)))  # nothing marked: unchanged
