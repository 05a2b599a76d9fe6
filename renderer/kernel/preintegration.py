"""Pre-integrated classification (Engel et al.; Real-Time Volume Graphics §4.5; Roettger et al. 2003).

A ray segment of length l0 (the base step) whose scalar runs linearly from s_f (front) to s_b (back) gets its
colour and opacity from a table over (s_f, s_b) built once per TF and step:

    tau(x)  = l0/unit · ∫_0^x σ(s(x')) dx',   σ(s) = −ln(1 − a(s))   (opacity per unit distance, docs/design.md)
    alpha   = 1 − exp(−tau(1))
    C       = ∫_0^1 c(s(x)) dτ/dx exp(−tau(x)) dx          (premultiplied, emission ∝ extinction as in the kernel)

computed in float64 without a Riemann sum: the segment is cut where s crosses a TF control point, so that a(x) and
c(x) are linear on every piece; there tau is exact in closed form (∫ −ln(1 − a) da = (1 − a)(ln(1 − a) − 1)),
and by parts C = Σ_pieces [c e^−tau]_end^start + c' ∫ e^−tau dx, whose last integrand is smooth and bounded, by
16-point Gauss–Legendre. Every entry is therefore exact for any TF, near-opaque and a = 1 included, hard steps in
the TF (two control points at one value) too.

Between entries the kernel interpolates bilinearly. So that interpolation never straddles a TF control point, the
table's axis is not uniform over the value range but piecewise uniform between the control points (`axis`): every
control point is a grid line, the lines between two control points are spread in proportion to their distance,
and a hard step at v takes two lines, v from below and v from above, one table interval apart in the kernel's
coordinate (the `warp` rows: values in [b_k, b_k+1) sit at table coordinate g_k + (s − b_k)·slope_k, found by a
binary search over the control points). A segment that crosses a hard step is cut where the (linear) field
crosses it, and each piece is looked up between its own ends on its own side of the step (lc_preint.h), so a hard
step is exact: on a ramp through one the image equals the float64 reference (tests/test_illumination_clip.py;
a uniform axis smeared the step over one table interval and did worse there than point sampling). A
TF of more than PREINT_N/2 control points has only its hard steps aligned (of those, at most PREINT_N/2).

Other segment lengths l (the last, shorter segment of a ray, clipped segments, adaptive steps of l0·2^k) scale the
entry as Roettger describes: alpha_l = 1 − (1 − alpha)^(l/l0) and the colour keeps its average (C/alpha): exact
for constant segments, and tested against the float64 reference for linear ones (tests/test_illumination_clip.py).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from lodcast.renderer.cache import ByteLru
from lodcast.renderer.scene.scene import TransferFunction

__all__ = ["PreintTable", "preintegrate", "segment_integral", "axis", "PREINT_N"]

PREINT_N = 256  # entries per axis: 16 B x 256² = 1 MiB
_GL_X, _GL_W = np.polynomial.legendre.leggauss(16)
_GL_X, _GL_W = 0.5 * (_GL_X + 1.0), 0.5 * _GL_W  # on [0, 1]


@dataclass(frozen=True)
class PreintTable:
    values: np.ndarray  # (n,) float64: the value of each grid line, on both axes (hard steps: just below, above)
    warp: np.ndarray  # (K, 4) float32: (b_k, g_k, slope_k, hard_k), s in [b_k, b_k+1) -> g_k + (s − b_k) slope_k;
    #                   hard_k = 1: a hard step at b_k (line g_k − 1 is b_k from below)
    n: int
    table: np.ndarray  # (n, n, 4) float32: [front, back] -> (C premultiplied rgb, alpha) for the base step
    build_ms: float

    @property
    def kernel_table(self) -> np.ndarray:
        """The table's n·n float4 entries, then the K warp rows (lc_preint.h)."""
        return np.ascontiguousarray(np.concatenate([self.table.reshape(-1, 4), self.warp]), dtype=np.float32)

    def coord(self, s: np.ndarray | float) -> np.ndarray:
        """The kernel's table coordinate of values s (float64): the last warp row at or below s, clamped."""
        w = self.warp.astype(np.float64)
        k = np.clip(np.searchsorted(w[:, 0], np.asarray(s, np.float64), side="right") - 1, 0, len(w) - 1)
        return np.clip(w[k, 1] + (s - w[k, 0]) * w[k, 2], 0.0, self.n - 1.0)


def axis(tf: TransferFunction, lo: float, hi: float, n: int = PREINT_N) -> tuple[np.ndarray, np.ndarray]:
    """(grid line values (n,), warp rows (K, 4)) of a table over [lo, hi] whose grid lines fall on the TF's
    control points (see the module's docstring)."""
    hi = hi if hi > lo else lo + 1.0
    v = np.array([p.value for p in tf.points], np.float64)
    inside = v[(v > lo) & (v < hi)]
    knots, counts = np.unique(inside, return_counts=True)
    hard = counts > 1
    if knots.size > n // 2:
        knots, hard = knots[hard][: n // 2], hard[hard][: n // 2]
    b = np.concatenate([[lo], knots, [hi]])
    jump = np.concatenate([hard, [False]])  # a hard step at the end of interval i (at b[i + 1])
    w = np.diff(b)
    units = n - 1 - int(jump.sum())  # table intervals left for the value intervals
    m = np.maximum(1, np.floor(w / w.sum() * units).astype(np.int64))
    while m.sum() > units:  # more intervals than lines: take from the widest
        m[np.argmax(m)] -= 1
    while m.sum() < units:  # hand out what rounding left, to the interval furthest below its share
        m[np.argmax(w / w.sum() * units - m)] += 1
    eps = 1e-9 * max(hi - lo, float(np.abs(b).max()))
    lines, rows, g = [], [], 0
    for i in range(len(w)):
        seg = b[i] + w[i] * np.arange(m[i] + 1) / m[i]
        if i and jump[i - 1]:
            seg[0] += eps  # a hard step from above
        if jump[i]:
            seg[-1] -= eps  # and from below
        lines.append(seg if i == 0 or jump[i - 1] else seg[1:])
        rows.append((b[i], g, m[i] / w[i], 1.0 if i and jump[i - 1] else 0.0))
        g += int(m[i]) + int(jump[i])
    values = np.concatenate(lines)
    assert values.size == n and g == n - 1, (values.size, g, n)
    return values, np.array(rows, np.float32)


def _tf_arrays(tf: TransferFunction) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    v = np.array([p.value for p in tf.points], np.float64)
    c = np.array([p.color for p in tf.points], np.float64)
    a = np.array([p.opacity for p in tf.points], np.float64)
    return v, c, a


def _eval(v: np.ndarray, c: np.ndarray, a: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """TF colour (…, 3) and opacity at values s, piecewise linear, constant outside (only evaluated strictly
    inside a piece, never on a knot)."""
    rgb = np.stack([np.interp(s, v, c[:, k]) for k in range(3)], -1)
    return rgb, np.interp(s, v, a)


def _tau_piece(a0: np.ndarray, a1: np.ndarray, w: np.ndarray) -> np.ndarray:
    """∫ −ln(1 − a) over a piece of width w on which a runs linearly from a0 to a1 (inf where a = 1 on a span)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        F = lambda a: np.where(a < 1.0, (1.0 - a) * (np.log1p(-np.minimum(a, 1.0)) - 1.0), 0.0)  # noqa: E731
        lin = w * (F(a1) - F(a0)) / (a1 - a0)
        flat = w * -np.log1p(-np.minimum(a0, 1.0))
        out = np.where(np.abs(a1 - a0) > 1e-12, lin, flat)
    return np.where(w > 0.0, out, 0.0)


def segment_integral(tf: TransferFunction, sf: ArrayLike, sb: ArrayLike,
                     ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """(C (…, 3) premultiplied, alpha (…)) of segments of `ratio` = length/unit from sf to sb (arrays, float64)."""
    v, c, a = _tf_arrays(tf)
    sf, sb = np.broadcast_arrays(np.asarray(sf, np.float64), np.asarray(sb, np.float64))
    shape = sf.shape
    sf, sb = sf.ravel(), sb.ravel()
    ds = sb - sf
    # breakpoints in x in [0, 1]: the ends and every knot crossing (a hard step is one crossing at which the TF's
    # value jumps: pieces on either side evaluate their own side's limit, below)
    with np.errstate(divide="ignore", invalid="ignore"):
        xk = (v[None, :] - sf[:, None]) / ds[:, None]
    xk = np.where(np.isfinite(xk) & (xk > 0.0) & (xk < 1.0), xk, 1.0)
    xs = np.sort(np.concatenate([np.zeros((sf.size, 1)), xk, np.ones((sf.size, 1))], 1), 1)
    tau = np.zeros(sf.size)
    C = np.zeros((sf.size, 3))
    for p in range(xs.shape[1] - 1):
        x0, x1 = xs[:, p], xs[:, p + 1]
        w = x1 - x0
        # the piece's end values: the TF is linear on the piece, so two interior points give them exactly (and a
        # hard step at an end belongs to the side the piece lies on)
        q1, q3 = sf + ds * (x0 + 0.25 * w), sf + ds * (x0 + 0.75 * w)
        c_1, a_1 = _eval(v, c, a, q1)
        c_3, a_3 = _eval(v, c, a, q3)
        a0, a1 = np.clip(1.5 * a_1 - 0.5 * a_3, 0, 1), np.clip(1.5 * a_3 - 0.5 * a_1, 0, 1)
        c0, c1 = np.clip(1.5 * c_1 - 0.5 * c_3, 0, 1), np.clip(1.5 * c_3 - 0.5 * c_1, 0, 1)
        t_end = tau + ratio * _tau_piece(a0, a1, w)
        # ∫ e^-tau(x) dx / w over the piece by Gauss-Legendre; tau at a node: tau + ratio * exact partial integral
        g = np.zeros(sf.size)
        for xg, wg in zip(_GL_X, _GL_W):
            an = a0 + (a1 - a0) * xg
            g += wg * np.exp(-(tau + ratio * _tau_piece(a0, an, w * xg)))
        # (c' = (c1 - c0) / w and ∫ dx = w Σ w_g: the widths cancel)
        with np.errstate(invalid="ignore"):
            C += c0 * np.exp(-tau)[:, None] - c1 * np.exp(-t_end)[:, None] + (c1 - c0) * g[:, None]
        tau = t_end
    alpha = -np.expm1(-tau)
    return np.nan_to_num(C).reshape(*shape, 3), alpha.reshape(shape)


def preintegrate(tf: TransferFunction, lo: float, hi: float, ratio: float, n: int = PREINT_N,
                 kept: "ByteLru | None" = None) -> PreintTable:
    """The table over [lo, hi]² for base segments of `ratio` = step/unit. `kept`: recent tables (an engine's
    `tables.preint`: a camera change rebuilds nothing, a TF or step change only this table)."""
    key = (tf.model_dump_json(), float(lo), float(hi), float(ratio), int(n))
    hit = None if kept is None else kept.get(key)
    if hit is not None:
        return hit
    t = time.perf_counter()
    s, warp = axis(tf, key[1], key[2], key[4])
    C, alpha = segment_integral(tf, s[:, None], s[None, :], key[3])
    tab = np.concatenate([C, alpha[..., None]], -1).astype(np.float32)
    out = PreintTable(s, warp, key[4], np.ascontiguousarray(tab), (time.perf_counter() - t) * 1e3)
    if kept is not None:
        kept.put(key, out, 1)
    return out
