"""Transfer function: exact opacity correction (a -> 1, step -> 0), the kernel LUT's resolution and alignment,
and block visibility for empty-space skipping (max opacity over an interval, not the endpoints)."""
from __future__ import annotations

from decimal import Decimal, getcontext

import numpy as np
import pytest

from lodcast.renderer.scene.scene import TransferFunction
from lodcast.renderer.scene.transfer_function import (
    LUT_MAX,
    LUT_MIN,
    SIGMA_OPAQUE,
    build_lut,
    evaluate,
    extinction,
    opacity_for_step,
    unit_distance,
)

getcontext().prec = 60


def exact_alpha(a: float, r: float) -> float:
    """1 - (1 - a)^r with 60 significant digits."""
    if a == 1.0:
        return 1.0
    one = Decimal(1)
    return float(one - ((one - Decimal(a)).ln() * Decimal(r)).exp())


def tf(points, unit=None) -> TransferFunction:
    return TransferFunction.model_validate({"points": points, "unit_distance": unit})


@pytest.mark.parametrize("a", [1e-9, 1e-4, 0.1, 0.5, 0.9, 0.999, 0.999999, 1 - 1e-12])
@pytest.mark.parametrize("r", [1e-8, 1e-4, 1e-2, 0.25, 1.0, 3.0, 10.0])
def test_opacity_correction_is_exact(a, r):
    got = float(opacity_for_step(a, r))
    want = exact_alpha(a, r)
    assert abs(got - want) <= 4e-16 * max(want, 1e-300) + 1e-300, (got, want)  # relative 4e-16


def test_opacity_correction_limits():
    assert float(opacity_for_step(1.0, 1e-6)) == 1.0  # a = 1: opaque for any positive step
    assert float(opacity_for_step(1.0, 0.0)) == 0.0
    assert float(opacity_for_step(0.3, 0.0)) == 0.0
    assert float(opacity_for_step(0.3, 1.0)) == pytest.approx(0.3, abs=1e-16)
    assert float(opacity_for_step(0.0, 5.0)) == 0.0
    # composing two half steps equals one full step (the defining property, to rounding)
    a = 0.37
    h = float(opacity_for_step(a, 0.5))
    assert 1 - (1 - h) ** 2 == pytest.approx(a, abs=1e-15)


def test_extinction_float32_keeps_tiny_steps_exact():
    """What the kernel does: sigma (float32 from the LUT) and alpha = -expm1(-r sigma) in float32."""
    for a in (0.1, 0.999999):
        s32 = np.float32(extinction(a))
        for r in (1e-4, 1e-2, 1.0):
            got = -np.expm1(-np.float32(r) * s32, dtype=np.float32)
            want = exact_alpha(a, r)
            assert abs(float(got) - want) <= 3e-7 * want, (a, r, got, want)
    assert extinction(1.0) == SIGMA_OPAQUE
    assert -np.expm1(-np.float32(1e-4) * np.float32(SIGMA_OPAQUE), dtype=np.float32) == 1.0


def test_evaluate_piecewise_linear_constant_outside():
    t = tf([{"value": 0, "color": [0, 0, 0], "opacity": 0}, {"value": 10, "color": [1, 0.5, 0], "opacity": 0.8}])
    rgb, a = evaluate(t, [-5, 0, 5, 10, 20])
    assert np.allclose(a, [0, 0, 0.4, 0.8, 0.8])
    assert np.allclose(rgb[:, 1], [0, 0, 0.25, 0.5, 0.5])


def test_unit_distance_defaults_to_smallest_spacing():
    assert unit_distance(tf([{"value": 0}]), (5.0, 1.0, 0.3)) == 0.3
    assert unit_distance(tf([{"value": 0}], unit=2.0), (5.0, 1.0, 0.3)) == 2.0


def test_lut_puts_control_points_on_entries():
    t = tf([{"value": 300, "opacity": 0}, {"value": 1500, "opacity": 0.8}, {"value": 2000, "opacity": 0.2}])
    lut = build_lut(t, (-1024, 3071))
    assert lut.exact and LUT_MIN <= lut.n <= LUT_MAX
    assert lut.values[0] <= -1024 and lut.values[-1] >= 3071
    k = (np.array([300, 1500, 2000]) - lut.lo) * lut.scale
    assert np.allclose(k, np.round(k), atol=1e-6)
    # the LUT's interpolant equals the TF everywhere in the range (kinks sit on entries)
    v = np.linspace(-1024, 3071, 20011)
    f = (v - lut.lo) * lut.scale
    i0 = np.minimum(f.astype(int), lut.n - 2)
    w = f - i0
    interp_a = lut.opacity[i0] * (1 - w) + lut.opacity[i0 + 1] * w
    assert np.abs(interp_a - evaluate(t, v)[1]).max() < 1e-9


def test_lut_resolution_from_gaps_when_points_do_not_align():
    t = tf([{"value": 0.1, "opacity": 0}, {"value": 0.1 + np.pi * 1e-3, "opacity": 1}, {"value": 0.9, "opacity": 0.5}])
    lut = build_lut(t, (0.0, 1.0))
    assert lut.n >= (1.0 / (np.pi * 1e-3)) * 64  # at least 64 entries across the narrowest gap
    assert lut.n <= LUT_MAX


def test_lut_minimum_resolution_and_degenerate_ranges():
    t = tf([{"value": 0, "opacity": 0.5}])
    assert build_lut(t, (0, 1)).n >= LUT_MIN
    lut = build_lut(t, (5, 5))  # constant volume
    assert lut.n >= 2 and np.isfinite(lut.table).all()


def test_lut_table_holds_extinction_and_opaque_stand_in():
    t = tf([{"value": 0, "opacity": 0.0}, {"value": 1, "opacity": 1.0}])
    lut = build_lut(t, (0, 1))
    assert lut.table.dtype == np.float32 and lut.table.shape == (lut.n, 4)
    assert lut.table[-1, 3] == np.float32(SIGMA_OPAQUE) and lut.table[0, 3] == 0
    alpha = lut.kernel_table("alpha", 1e-4)
    assert alpha[-1, 3] == 1.0 and alpha[0, 3] == 0 and alpha.dtype == np.float32
    assert lut.kernel_table("opacity")[-1, 3] == 1.0
    assert np.isfinite(lut.table).all()


def test_visibility_uses_max_over_interval_not_endpoints():
    # zero at both ends, non-zero in between: a block spanning [0, 10] must be visible
    t = tf([{"value": 4, "opacity": 0}, {"value": 5, "opacity": 0.5}, {"value": 6, "opacity": 0}])
    lut = build_lut(t, (0, 10))
    vis = lut.visible(np.array([0.0, 0.0, 7.0, 6.5, np.nan]), np.array([10.0, 3.0, 10.0, 6.8, np.nan]))
    assert vis.tolist() == [True, False, False, False, False]
    # conservative at the edge of the support: a block reaching just into (4, 6) is visible
    assert lut.visible(np.array([0.0]), np.array([4.01]))[0]


def test_visible_span_bounds_the_interpolants_support():
    """The kernel skips lookup and blend for LUT coordinates outside visible_span(): the interpolated opacity
    must be exactly zero there, and the span must not be empty where the TF is not."""
    t = tf([{"value": 4, "opacity": 0}, {"value": 5, "opacity": 0.5}, {"value": 6, "opacity": 0}])
    lut = build_lut(t, (0, 10))
    lo, hi = lut.visible_span()
    f = np.linspace(0, lut.n - 1, 200001)
    i0 = np.minimum(f.astype(int), lut.n - 2)
    w = f - i0
    a = lut.opacity[i0] * (1 - w) + lut.opacity[i0 + 1] * w
    assert np.all(a[(f <= lo) | (f >= hi)] == 0)
    assert a[(f > lo) & (f < hi)].max() == 0.5
    empty = build_lut(tf([{"value": 0, "opacity": 0}]), (0, 1)).visible_span()
    assert empty[0] > empty[1]


def test_srgb_to_luv_equals_colour_science():
    """The NumPy sRGB → CIELUV (D65) used by ΔE and significance against colour-science on random colours, the
    primaries, black, white and the dark linear segment of the sRGB curve."""
    import warnings

    from lodcast.renderer.image.delta_e import srgb_to_luv

    rng = np.random.default_rng(11)
    rgb = np.concatenate([rng.random((2000, 3)), rng.random((200, 3)) * 0.04, np.eye(3), np.zeros((1, 3)),
                          np.ones((1, 3))])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import colour

        ref = colour.XYZ_to_Luv(colour.sRGB_to_XYZ(rgb), colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"])
    np.testing.assert_allclose(srgb_to_luv(rgb), ref, atol=1e-9, rtol=1e-9)


@pytest.mark.parametrize("seed", range(6))
def test_visible_is_conservative_from_float32_ranges(seed):
    """Cell ranges come as float32 (a million per TF at full resolution) and are tested in float32 where its
    rounding over the table moves an index by under a quarter entry, else in float64: either way a range on which
    the table's interpolant is non-zero anywhere is visible (dense float64 check), on tables near zero and far
    from it (offset 1e9: float64)."""
    rng = np.random.default_rng(seed)
    off = float(rng.choice([0.0, -1024.0, 3.0e4, 1.0e9]))
    xs = np.sort(rng.uniform(0, 100, 5)) + off
    ops = rng.choice([0.0, 0.0, 0.3, 0.9], 5)
    t = tf([{"value": float(x), "opacity": float(o)} for x, o in zip(xs, ops)])
    lut = build_lut(t, (off, off + 100))
    lo = (rng.uniform(-10, 110, 400) + off).astype(np.float32)
    hi = (lo + rng.uniform(0, 8, 400)).astype(np.float32)
    vis = lut.visible(lo, hi)
    grid = lut.lo + np.arange(lut.n) / lut.scale
    for a, b, v in zip(lo.astype(np.float64), hi.astype(np.float64), vis):
        dense = np.interp(np.linspace(a, b, 257), grid, lut.opacity)
        assert v or not (dense > 0).any(), (a, b)
