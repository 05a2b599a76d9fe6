"""The multiresolution sampler (renderer/kernel/lc_atlas.h) against float64 evaluations of its formulas on random level
assignments: nearest block (eq. 3.5) and interblock interpolation (eq. 3.6 in 3D) with the edge weights
e(x) = clamp((x + delta_L) / (delta_L + delta_U), 0, 1). The three properties asked of the edge weights:
trilinear where neighbouring blocks share a level, C0 across arbitrary level differences, 1-sample blocks."""
from __future__ import annotations

import lod_reference as ref
import numpy as np
import pytest

B = 8
NL = 4  # levels 0..3; level 3 = one sample per block


def _volume(G, seed):
    rng = np.random.default_rng(seed)
    v0 = rng.random(tuple(g * B for g in G))
    return ref.pyramid(v0, NL)


def _points_in(G, n, rng):
    hi = np.array([G[2], G[1], G[0]]) * B - 0.5
    return rng.uniform(-0.5, hi, (n, 3))


@pytest.mark.parametrize("interp", ["interblock", "nearest_block"])
def test_kernel_matches_float64_formula_on_random_levels(interp):
    rng = np.random.default_rng(1)
    G = (3, 4, 5)
    pyr = _volume(G, 2)
    levels = rng.integers(-1, NL, G).astype(np.int8)
    levels[1, 1, 1] = 0
    br = ref.bricks_of(levels, pyr, B)
    pts = _points_in(G, 3000, rng)
    got = ref.probe(levels, br, B, pts, interp).astype(np.float64)
    want = np.array([ref.sample(levels, br, B, q, interp) for q in pts])
    assert np.array_equal(np.isnan(got), np.isnan(want))  # exactly the samples in missing blocks are NaN
    ok = ~np.isnan(want)
    assert ok.sum() > 1000
    np.testing.assert_allclose(got[ok], want[ok], atol=2e-6)


def test_equal_levels_give_trilinear_interpolation_of_that_level():
    rng = np.random.default_rng(3)
    G = (4, 4, 4)
    pyr = _volume(G, 4)
    # uniform 2x2x2 groups of blocks (so that many cells have eight blocks of one level) plus single changes
    levels = np.repeat(np.repeat(np.repeat(rng.integers(0, NL, (2, 2, 2)), 2, 0), 2, 1), 2, 2).astype(np.int8)
    levels[0, 3, 1] = 3
    br = ref.bricks_of(levels, pyr, B)
    pts = _points_in(G, 4000, rng)
    same = []
    for q in pts:
        p = (q + 0.5) / B
        c = np.floor(p + 0.5).astype(int)
        cells = {int(levels[min(max(c[2] - 1 + sz, 0), 3), min(max(c[1] - 1 + sy, 0), 3), min(max(c[0] - 1 + sx, 0), 3)])
                 for sx in (0, 1) for sy in (0, 1) for sz in (0, 1)}
        same.append(cells.pop() if len(cells) == 1 else -1)
    same = np.array(same)
    assert (same >= 0).sum() > 500 and len(set(same[same >= 0].tolist())) >= 2
    got = ref.probe(levels, br, B, pts[same >= 0]).astype(np.float64)
    f64 = np.array([ref.sample(levels, br, B, q) for q in pts[same >= 0]])
    tri = np.array([ref.trilinear_level(pyr, int(k), B, q) for q, k in zip(pts[same >= 0], same[same >= 0])])
    np.testing.assert_allclose(f64, tri, atol=1e-12)  # the formula is trilinear (exactly, in float64)
    np.testing.assert_allclose(got, tri, atol=2e-6)  # and so is the kernel (float32)
    # nearest block too where the eight are at level 0, through the bricks' aprons (its stencil's blocks are among
    # the cell's eight); coarse blocks have no apron
    zero = same[same >= 0] == 0
    assert zero.sum() > 100
    nb = ref.probe(levels, br, B, pts[same >= 0][zero], "nearest_block").astype(np.float64)
    np.testing.assert_allclose(nb, tri[zero], atol=2e-6)
    # every block at level 0: trilinear interpolation of the full-resolution volume everywhere, rim included
    lv0 = np.zeros(G, np.int8)
    want0 = [ref.trilinear_level(pyr, 0, B, q) for q in pts]
    for interp in ("interblock", "nearest_block"):
        got0 = ref.probe(lv0, ref.bricks_of(lv0, pyr, B), B, pts, interp).astype(np.float64)
        np.testing.assert_allclose(got0, want0, atol=2e-6)


def _boundary_points(G, rng, n):
    """Points on block faces, edges and corners (q = b B - 1/2) and on interblock cell boundaries (block centres,
    q = b B + B/2 - 1/2), with the other coordinates random; and the axes that cross the boundary there."""
    out = []
    hi = np.array([G[2], G[1], G[0]]) * B - 0.5
    for i in range(n):
        q = rng.uniform(0, hi)
        axes = [a for a in range(3) if rng.random() < 0.5] or [int(rng.integers(3))]
        for a in axes:
            g = G[2 - a]
            if rng.random() < 0.7:
                q[a] = int(rng.integers(1, g)) * B - 0.5  # interior block face
            else:
                q[a] = int(rng.integers(0, g)) * B + B / 2 - 0.5  # block centre: interblock cell face
        out.append((q, axes))
    return out


@pytest.mark.parametrize("seed", [5, 6])
def test_interblock_is_c0_across_arbitrary_level_differences(seed):
    rng = np.random.default_rng(seed)
    G = (3, 3, 4)
    pyr = _volume(G, seed)
    levels = rng.integers(0, NL, G).astype(np.int8)  # 1-sample blocks (level 3) included
    levels[0, 0, 0], levels[2, 2, 3] = 3, 0
    br = ref.bricks_of(levels, pyr, B)
    bp = _boundary_points(G, rng, 600)
    dirs = []
    for q, axes in bp:
        d = np.zeros(3)
        d[axes] = rng.choice([-1.0, 1.0], len(axes))
        dirs.append(d)
    q0 = np.array([q for q, _ in bp])
    d = np.array(dirs)
    # float64 formula: the two sides agree as eps -> 0 (Lipschitz: the jump shrinks with eps)
    for eps in (1e-6, 1e-9):
        jump = np.array([abs(ref.sample(levels, br, B, q + eps * v) - ref.sample(levels, br, B, q - eps * v))
                         for q, v in zip(q0, d)])
        assert jump.max() < 50 * eps, jump.max()
    # the kernel too (float32, eps = 1e-3 voxel: jumps bounded by the slope, far below the data's contrast)
    eps = 1e-3
    a = ref.probe(levels, br, B, q0 + eps * d).astype(np.float64)
    b = ref.probe(levels, br, B, q0 - eps * d).astype(np.float64)
    assert np.abs(a - b).max() < 50 * eps
    # nearest-block sampling is not continuous across faces: the same check catches it
    a = ref.probe(levels, br, B, q0 + eps * d, "nearest_block")
    b = ref.probe(levels, br, B, q0 - eps * d, "nearest_block")
    assert np.abs(a - b).max() > 0.1


def test_one_sample_blocks_and_missing_neighbours():
    """1-sample blocks: every block at the coarsest level gives trilinear interpolation between block centres
    (the block means); a missing (-1) neighbour gets weight 0 and never leaks: its own samples are NaN and the
    samples beside it are convex combinations of loaded blocks only."""
    rng = np.random.default_rng(7)
    G = (3, 3, 3)
    pyr = _volume(G, 8)
    coarse = np.full(G, NL - 1, np.int8)
    br = ref.bricks_of(coarse, pyr, B)
    pts = _points_in(G, 1000, rng)
    got = ref.probe(coarse, br, B, pts).astype(np.float64)
    np.testing.assert_allclose(got, [ref.trilinear_level(pyr, NL - 1, B, q) for q in pts], atol=2e-6)
    # a missing block in the middle, with huge values in the data it would have had
    lv = rng.integers(0, NL, G).astype(np.int8)
    lv[1, 1, 1] = -1
    pyr2 = [p.copy() for p in pyr]
    for k, p in enumerate(pyr2):
        n = B >> k
        p[n:2 * n, n:2 * n, n:2 * n] = 1e6
    br2 = ref.bricks_of(lv, pyr2, B)
    got = ref.probe(lv, br2, B, pts).astype(np.float64)
    inside = np.all((pts + 0.5 >= B) & (pts + 0.5 < 2 * B), axis=1)
    assert inside.any() and np.isnan(got[inside]).all()
    assert np.nanmax(got[~inside]) <= 1.0 and not np.isnan(got[~inside]).any()


@pytest.mark.parametrize("seed", range(3))
def test_neighbourhood_and_slice_maxima_are_those_of_every_neighbour(seed):
    """neighbourhood_max and slice_max (one pass per axis) against the maximum over every block of the 3x3x3
    neighbourhood, or of the 3x3 slice across each axis, edges repeated: levels (unloaded as 0) and float infos
    (-inf and NaN among them)."""
    from lodcast.renderer.data.atlas import neighbourhood_max, slice_max

    rng = np.random.default_rng(seed)
    for g in ((1, 1, 1), (1, 3, 7), (4, 5, 6), (9, 2, 3)):
        lv = rng.integers(-1, 6, size=g).astype(np.int8)
        info = rng.random(g).astype(np.float32)
        info[rng.random(g) < 0.2], info[rng.random(g) < 0.1] = -np.inf, np.nan
        for a, to in ((lv, np.maximum(lv.astype(np.int64), 0)), (info, info)):
            pad = np.pad(to, 1, mode="edge")
            want = np.max([pad[dz:dz + g[0], dy:dy + g[1], dx:dx + g[2]]
                           for dz in range(3) for dy in range(3) for dx in range(3)], axis=0)
            got = neighbourhood_max(a)
            assert got.dtype == to.dtype
            np.testing.assert_array_equal(got, want)
        pad = np.pad(np.maximum(lv.astype(np.int64), 0), 1, mode="edge")
        sl = slice_max(lv)
        for a, ax in enumerate((2, 1, 0)):
            want = np.max([pad[tuple(slice(1, 1 + g[i]) if i == ax else slice(d[i], d[i] + g[i]) for i in range(3))]
                           for d in np.ndindex(3, 3, 3)], axis=0)
            np.testing.assert_array_equal(sl[..., a], want)
