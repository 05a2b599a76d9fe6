"""Block significance (thesis eq. 3.1) against brute-force float64 computations.

Brute force: a loop over bins, colour-science called per value (sRGB → XYZ → CIELUV, D65) on the unit-slab colour
rgb·a, T* at the block mean evaluated directly (not interpolated). The library interpolates T*(s̄) in a dense
table, which is where the stated tolerances come from (measured ≤ 2e-4 ΔE; asserted ≤ 5e-3 + 1e-4·ζ)."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from lodcast.renderer.lod.significance import (
    BlockMeta,
    block_significance,
    effective_starts,
    level_profile,
    srgb_to_luv,
    tf_visible,
    tstar,
    zeta0_full,
    zeta0_simplified,
    zeta_levels,
)
from lodcast.renderer.scene.scene import TransferFunction
from lodcast.renderer.scene.transfer_function import CT_PRESETS
from lodcast.store.histogram import Bins, expand, simplify

TOL_ABS, TOL_REL = 5e-3, 1e-4

SKIN_BONE = TransferFunction.model_validate(CT_PRESETS["ct-skin-bone"])


_LUV_CACHE: dict = {}


def _luv_scalar(tf: TransferFunction, v: float) -> np.ndarray:
    key = (tf.model_dump_json(), float(v))
    if key not in _LUV_CACHE:
        _LUV_CACHE[key] = _luv_scalar_uncached(tf, v)
    return _LUV_CACHE[key]


def _luv_scalar_uncached(tf: TransferFunction, v: float) -> np.ndarray:
    """T*(v) directly: piecewise-linear rgb and opacity from the control points (independent of the library's
    evaluate), premultiplied, converted by colour-science one value at a time."""
    xs = [p.value for p in tf.points]
    rgb = np.array([np.interp(v, xs, [p.color[c] for p in tf.points]) for c in range(3)])
    a = float(np.interp(v, xs, [p.opacity for p in tf.points]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import colour

        xyz = colour.sRGB_to_XYZ(rgb * a)
        return np.asarray(colour.XYZ_to_Luv(xyz, colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]))


def brute_zeta(tf: TransferFunction, hist: np.ndarray, centres: np.ndarray, mean: float) -> float:
    tbar = _luv_scalar(tf, mean)
    acc = 0.0
    n = 0.0
    for b in range(hist.size):
        if hist[b] == 0:
            continue
        de = float(np.linalg.norm(tbar - _luv_scalar(tf, float(centres[b]))))
        acc += de * de * float(hist[b])
        n += float(hist[b])
    return float(np.sqrt(acc / n)) if n > 0 else 0.0


def synthetic_meta(rng: np.random.Generator, n: int, bins: Bins, n_levels: int = 6, sd_max: float = 0.15, clusters: int = 3) -> BlockMeta:
    """Random block histograms: each block a mixture of one to three Gaussian value clusters."""
    nb = bins.count
    centres = np.arange(nb) + bins.lo if bins.integer else 0.5 * (bins.edges[:-1] + bins.edges[1:])
    hists = np.zeros((n, nb), np.uint32)
    for i in range(n):
        for _ in range(rng.integers(1, clusters + 1)):
            mu = rng.uniform(bins.lo, bins.hi)
            sd = rng.uniform(0.002, sd_max) * (bins.hi - bins.lo)
            vals = np.clip(rng.normal(mu, sd, rng.integers(50, 3000)), bins.lo, bins.hi)
            hists[i] += np.bincount(bins.index(vals), minlength=nb).astype(np.uint32)
    starts, heights = simplify(hists, 12, device=False)
    tot = hists.sum(1).astype(np.float64)
    mean = (hists @ centres) / tot
    nz = hists > 0
    lo_b = np.argmax(nz, axis=1)
    hi_b = nb - 1 - np.argmax(nz[:, ::-1], axis=1)
    return BlockMeta(
        grid=(1, 1, n),
        n_levels=n_levels,
        bins=bins,
        mean=mean,
        count=tot,
        min_border=centres[lo_b],
        max_border=centres[hi_b],
        starts=starts,
        heights=heights,
        hist=hists,
    )


@pytest.fixture(scope="module")
def metas():
    rng = np.random.default_rng(5)
    return {
        "float_bins": synthetic_meta(rng, 40, Bins.for_range(-1000.0, 2000.0, integer=False, max_bins=256)),
        "integer_bins": synthetic_meta(rng, 40, Bins.for_range(-600.0, -401.0, integer=True, max_bins=256)),
    }


@pytest.mark.parametrize("which", ["float_bins", "integer_bins"])
def test_full_histogram_significance_matches_brute_force(metas, which) -> None:
    meta = metas[which]
    tf = SKIN_BONE if which == "float_bins" else TransferFunction.model_validate(
        {"points": [{"value": -580, "color": [1, 0.2, 0.1], "opacity": 0.0}, {"value": -500, "color": [0.2, 0.4, 1], "opacity": 0.6},
                    {"value": -420, "color": [1, 1, 1], "opacity": 0.1}]}
    )
    ts = tstar(tf, meta.bins)
    vis = np.ones(meta.n, bool)
    got = zeta0_full(meta, ts, vis)
    want = np.array([brute_zeta(tf, meta.hist[i], ts.centres, meta.mean[i]) for i in range(meta.n)])
    assert want.max() > 5.0  # the case is not trivial
    np.testing.assert_allclose(got, want, rtol=TOL_REL, atol=TOL_ABS)


def test_simplified_O_K_equals_direct_sum_over_expanded_histogram(metas) -> None:
    """The prefix-sum evaluation equals Σ over bins of the expanded simplified histogram (same T*): 1e-9."""
    for meta in metas.values():
        ts = tstar(SKIN_BONE, meta.bins)
        vis = np.ones(meta.n, bool)
        fast = zeta0_simplified(meta, ts, vis)
        ex = expand(effective_starts(meta), meta.heights, meta.bins.count)
        direct = np.zeros(meta.n)
        tbar = ts.at(meta.mean)
        for i in range(meta.n):
            d2 = ((ts.luv - tbar[i]) ** 2).sum(axis=1)
            direct[i] = np.sqrt((ex[i] * d2).sum() / ex[i].sum())
        # compared as ζ²: the expansion |T̄|² − 2T̄·A/n + B/n cancels (|T̄|² ~ 1e4), so ζ² carries ~1e-11 absolute
        # rounding, which is 1e-9 in ζ only near ζ = 0
        np.testing.assert_allclose(fast**2, direct**2, rtol=1e-9, atol=1e-8)
        # and the full-histogram routine on the expanded histograms gives the same numbers
        np.testing.assert_allclose(zeta0_full(meta, ts, vis, hist=ex) ** 2, direct**2, rtol=1e-9, atol=1e-8)


def test_simplified_significance_against_brute_force_and_close_to_full(metas) -> None:
    meta = metas["float_bins"]
    ts = tstar(SKIN_BONE, meta.bins)
    vis = np.ones(meta.n, bool)
    fast = zeta0_simplified(meta, ts, vis)
    ex = expand(effective_starts(meta), meta.heights, meta.bins.count)
    want = np.array([brute_zeta(SKIN_BONE, ex[i], ts.centres, meta.mean[i]) for i in range(meta.n)])
    np.testing.assert_allclose(fast, want, rtol=TOL_REL, atol=TOL_ABS)
    # the simplified histogram approximates the full one (thesis: 'only marginally' worse): within 15 % RMS
    full = zeta0_full(meta, ts, vis)
    assert np.sqrt(np.mean((fast - full) ** 2)) <= 0.15 * np.sqrt(np.mean(full**2))


def test_transparent_ranges_give_zero_and_are_invisible() -> None:
    rng = np.random.default_rng(1)
    bins = Bins.for_range(0.0, 1000.0, integer=False, max_bins=128)
    meta = synthetic_meta(rng, 30, bins)
    # opaque only above 1000: every block is in the transparent range, whatever the colours written there
    tf = TransferFunction.model_validate(
        {"points": [{"value": 0, "color": [1, 0, 0], "opacity": 0.0}, {"value": 500, "color": [0, 1, 0], "opacity": 0.0},
                    {"value": 1000, "color": [0, 0, 1], "opacity": 0.0}, {"value": 1001, "color": [1, 1, 1], "opacity": 1.0}]}
    )
    for method in ("tf", "tf_full_hist", "l2"):
        z, vis = block_significance(meta, tf, method)
        assert not vis.any()
        assert np.all(z == 0.0)
    # unit-slab colour of a transparent value is black: T* = 0 exactly
    ts = tstar(tf, bins)
    assert np.all(ts.luv == 0.0)
    # a TF opaque only on (400, 600): blocks whose border-inclusive range avoids it are invisible and zero
    tf2 = TransferFunction.model_validate(
        {"points": [{"value": 400, "color": [1, 1, 1], "opacity": 0.0}, {"value": 500, "color": [1, 1, 1], "opacity": 0.5},
                    {"value": 600, "color": [1, 1, 1], "opacity": 0.0}]}
    )
    z, vis = block_significance(meta, tf2, "tf")
    outside = (meta.max_border <= 400) | (meta.min_border >= 600)
    assert outside.any() and (~outside).any()
    assert not vis[outside].any() and np.all(z[outside] == 0.0)
    assert vis[~outside].all()


def test_tf_visible_is_exact() -> None:
    tf = TransferFunction.model_validate(
        {"points": [{"value": 0, "opacity": 0.0}, {"value": 10, "opacity": 0.5}, {"value": 20, "opacity": 0.0}, {"value": 30, "opacity": 0.0}]}
    )
    lo = np.array([-5, -5, 0, 20, 21, 15, 9.99, np.nan])
    hi = np.array([0, 0.001, 20, 40, 22, 19.9, 10.01, 5])
    assert tf_visible(tf, lo, hi).tolist() == [False, True, True, False, False, True, True, False]


def test_constant_blocks_give_zero() -> None:
    bins = Bins.for_range(-1000.0, 2000.0, integer=False, max_bins=256)
    n = 8
    nb = bins.count
    vals = np.linspace(-400, 800, n)
    hists = np.zeros((n, nb), np.uint32)
    hists[np.arange(n), bins.index(vals)] = 35937
    starts, heights = simplify(hists, 12, device=False)
    meta = BlockMeta((1, 1, n), 6, bins, vals, np.full(n, 32768.0), vals, vals, starts, heights, hists)
    for method in ("tf", "tf_full_hist", "l2"):
        z, vis = block_significance(meta, SKIN_BONE, method)
        assert vis[(vals > -600) & (vals < 100) | (vals > 300)].all()
        assert np.all(z == 0.0)


def test_two_tfs_take_the_max_and_levels_are_linear(metas) -> None:
    meta = metas["float_bins"]
    tf_a = SKIN_BONE
    tf_b = TransferFunction.model_validate({"points": [{"value": 0, "color": [0, 1, 0], "opacity": 0.0}, {"value": 1500, "color": [0, 1, 0], "opacity": 0.7}]})
    za, va = block_significance(meta, tf_a)
    zb, vb = block_significance(meta, tf_b)
    z2, v2 = block_significance(meta, [tf_a, tf_b.model_dump()])
    np.testing.assert_array_equal(z2, np.maximum(za, zb))
    np.testing.assert_array_equal(v2, va | vb)
    zl = zeta_levels(z2, 6)
    assert zl.dtype == np.float32 and zl.shape == (meta.n, 6)
    np.testing.assert_allclose(zl[:, 5], z2, rtol=1e-6)
    assert np.all(zl[:, 0] == 0.0)
    np.testing.assert_allclose(zl[:, 2], z2 * 0.4, rtol=1e-6)
    assert level_profile(1).tolist() == [0.0]


def test_luv_of_black_white() -> None:
    luv = srgb_to_luv(np.array([[0.0, 0, 0], [1, 1, 1]]))
    np.testing.assert_allclose(luv, [[0, 0, 0], [100, 0, 0]], atol=0.02)  # colour-science D65 white: u*, v* ~ 0.01


def test_tf_visible_matches_dense_sampling_on_random_tfs() -> None:
    """The interval test against sampling the opacity densely on [lo, hi] (plus the control points inside)."""
    from lodcast.renderer.scene.transfer_function import evaluate

    rng = np.random.default_rng(8)
    for _ in range(200):
        m = int(rng.integers(1, 7))
        xs = np.sort(rng.integers(0, 20, m)).astype(float)
        ops = np.where(rng.random(m) < 0.5, 0.0, rng.random(m))
        tf = TransferFunction.model_validate({"points": [{"value": x, "opacity": a} for x, a in zip(xs, ops)]})
        if np.any(np.diff(xs) == 0):
            continue  # steps: value at the repeated point is a convention, covered by the invisible-ends logic
        lo = rng.integers(-3, 23, 50).astype(float) + rng.choice([0.0, 0.5], 50)
        hi = lo + rng.choice([0.0, 0.25, 1.0, 3.0, 10.0], 50)
        got = tf_visible(tf, lo, hi)
        for i in range(50):
            vals = np.concatenate([np.linspace(lo[i], hi[i], 401), xs[(xs >= lo[i]) & (xs <= hi[i])]])
            want = bool(np.any(evaluate(tf, vals)[1] > 0))
            assert got[i] == want, (xs, ops, lo[i], hi[i])


def test_tf_visible_with_steps_is_never_wrongly_invisible() -> None:
    """Repeated control values (steps): a range touching the value where opacity steps up counts as visible."""
    tf = TransferFunction.model_validate(
        {"points": [{"value": 0, "opacity": 0.0}, {"value": 10, "opacity": 0.0}, {"value": 10, "opacity": 1.0},
                    {"value": 20, "opacity": 1.0}, {"value": 20, "opacity": 0.0}]}
    )
    lo = np.array([0.0, 0.0, 5.0, 20.0, 21.0, 9.0, 25.0])
    hi = np.array([9.9, 10.0, 12.0, 30.0, 30.0, 9.5, 25.0])
    assert tf_visible(tf, lo, hi).tolist() == [False, True, True, True, False, False, False]


def test_numpy_and_scipy_paths_agree(metas, monkeypatch) -> None:
    """The O(K) sums as one SciPy CSR product and as the NumPy gather + batched product: ζ² within 1e-12
    relative + 1e-8 absolute (summation order differs; see the cancellation note above)."""
    import dataclasses

    pytest.importorskip("scipy")
    meta = metas["float_bins"]
    ts = tstar(SKIN_BONE, meta.bins)
    vis = np.ones(meta.n, bool)
    small = dataclasses.replace(meta)
    a = zeta0_simplified(small, ts, vis)
    monkeypatch.setenv("LODCAST_SIGNIFICANCE_NUMPY", "1")
    big = dataclasses.replace(meta)  # a new object: a new per-store cache entry
    b = zeta0_simplified(big, ts, vis)
    np.testing.assert_allclose(a**2, b**2, rtol=1e-12, atol=1e-8)
    # and a subset of visible blocks (the row-selection branch) on both paths
    vis2 = np.arange(meta.n) % 3 == 0
    np.testing.assert_allclose(zeta0_simplified(big, ts, vis2) ** 2, np.where(vis2, a, 0.0) ** 2, rtol=1e-12, atol=1e-8)
    np.testing.assert_array_equal(zeta0_simplified(small, ts, vis2), np.where(vis2, a, 0.0))


def test_effective_starts_keep_the_pieces_inside_the_value_range(metas) -> None:
    meta = metas["float_bins"]
    st = effective_starts(meta)
    ex = expand(st, meta.heights, meta.bins.count)
    lo, hi = meta.bins.index(meta.min_border), meta.bins.index(meta.max_border)
    b = np.arange(meta.bins.count)
    outside = (b[None, :] < lo[:, None]) | (b[None, :] > hi[:, None])
    assert np.all(ex[outside] == 0.0)
    full = np.asarray(meta.hist, np.float64)
    assert np.all(full[outside] == 0.0)  # the full histograms have nothing there either
    # inside the range the pieces are unchanged
    ex0 = expand(meta.starts, meta.heights, meta.bins.count)
    np.testing.assert_array_equal(ex[~outside], ex0[~outside])
