"""Transfer function: evaluation (float64), exact opacity correction, the kernel's lookup table, and the
per-block visibility used by empty-space skipping.

docs/design.md: piecewise linear over data values between control points, constant outside; sRGB colour composited
as given; opacity `a` per *unit distance* (default: the smallest voxel spacing). A step of length Δ takes
α = 1 − (1 − a)^(Δ/unit), computed as −expm1((Δ/unit)·log1p(−a)) so that it stays exact for a → 1 and Δ → 0.

The kernel's LUT stores, per entry, the sRGB colour and (compositing) the opacity of one step,
α_Δ = 1 − (1 − a)^(Δ/unit), computed exactly in float64, so that tiny steps and a → 1 stay exact in float32 and
the kernel needs no transcendental function per sample; a shorter segment (the ray's last) of fraction r of a step
takes −expm1(r·log1p(−α_Δ)). Rays of very many samples (LC_PRECISE) get the step's optical depth (Δ/unit)·σ,
σ = −log1p(−a) (a = 1 ↦ SIGMA_OPAQUE, a finite stand-in for +∞ that keeps interpolation free of inf − inf), and
MIP the opacity as given. The kernel interpolates linearly between entries. Entries are placed so that every control point inside the data range
falls exactly on an entry when that fits in LUT_MAX entries (then the LUT's interpolant has the TF's kinks
exactly where the TF has them); otherwise the spacing is at most 1/64 of the smallest gap between control points.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike

from lodcast.renderer.scene.presets import PRESETS
from lodcast.renderer.scene.scene import TransferFunction

__all__ = [
    "SIGMA_OPAQUE",
    "LUT_MIN",
    "LUT_MAX",
    "Lut",
    "evaluate",
    "opacity_for_step",
    "extinction",
    "build_lut",
    "unit_distance",
    "CT_PRESETS",
]

# the CT presets (renderer/scene/presets.py), under the name the benchmarks and tests use
CT_PRESETS: dict[str, dict] = {k: v for k, v in PRESETS.items() if k.startswith("ct-")}

SIGMA_OPAQUE = 1.0e30  # extinction standing in for a = 1: exp(-r·1e30) == 0 for any r > 1e-20
LUT_MIN = 1024
LUT_MAX = 65536


def unit_distance(tf: TransferFunction, spacing: Sequence[float]) -> float:
    """World length over which opacity is given: the TF's own, else the smallest voxel spacing."""
    return float(tf.unit_distance) if tf.unit_distance is not None else float(min(spacing))


def evaluate(tf: TransferFunction, values: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """(rgb (..., 3), opacity (...)) in float64 at data values, piecewise linear, constant outside."""
    v = np.asarray(values, dtype=np.float64)
    xs = np.array([p.value for p in tf.points], dtype=np.float64)
    cols = np.array([p.color for p in tf.points], dtype=np.float64)
    ops = np.array([p.opacity for p in tf.points], dtype=np.float64)
    rgb = np.stack([np.interp(v, xs, cols[:, c]) for c in range(3)], axis=-1)
    return rgb, np.interp(v, xs, ops)


def opacity_for_step(a: ArrayLike, ratio: ArrayLike) -> np.ndarray:
    """α = 1 − (1 − a)^ratio for opacity `a` per unit distance and ratio = Δ/unit, exact for a → 1 and ratio → 0
    (a = 1 gives 1 for any ratio > 0; ratio = 0 gives 0)."""
    a = np.asarray(a, dtype=np.float64)
    r = np.asarray(ratio, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = -np.expm1(r * np.log1p(-a))
    out = np.where(r == 0.0, 0.0, out)
    return np.where((a >= 1.0) & (r > 0.0), 1.0, out)


def extinction(a: ArrayLike) -> np.ndarray:
    """σ = −log1p(−a) per unit distance (≥ 0), a = 1 ↦ SIGMA_OPAQUE."""
    a = np.asarray(a, dtype=np.float64)
    with np.errstate(divide="ignore"):
        s = -np.log1p(-np.minimum(a, 1.0))
    return np.minimum(s, SIGMA_OPAQUE)


@dataclass(frozen=True)
class Lut:
    """Uniform table over [lo, lo + (n − 1)/scale]: entry k at value lo + k/scale."""

    lo: float
    scale: float  # entries per data unit
    n: int
    rgb: np.ndarray  # (n, 3) float64 TF colour at the entries
    opacity: np.ndarray  # (n,) float64 TF opacity at the entries (what empty-space skipping tests)
    exact: bool  # every in-range control point lies on an entry

    @property
    def table(self) -> np.ndarray:
        """(n, 4) float32: r, g, b and the extinction σ = −log1p(−a) per unit distance."""
        return self.kernel_table("extinction")[:-1]

    def kernel_table(self, kind: str, ratio: float = 1.0) -> np.ndarray:
        """(n + 1, 4) float32 for the kernel (the last entry repeated once, so that the kernel reads entries i and
        i + 1 for any i <= n - 1 without a second clamp): colour and, in the fourth channel, per `kind`:
        "alpha": the opacity of one step of `ratio` = step/unit units, 1 − (1 − a)^ratio (exact, float64);
        "depth": that step's optical depth ratio·σ; "extinction": σ; "opacity": a as given (MIP)."""
        t = np.empty((self.n, 4), np.float32)
        t[:, :3] = self.rgb
        if kind == "alpha":
            t[:, 3] = opacity_for_step(self.opacity, ratio)
        elif kind == "depth":
            t[:, 3] = np.minimum(extinction(self.opacity) * ratio, SIGMA_OPAQUE)
        elif kind == "extinction":
            t[:, 3] = extinction(self.opacity)
        elif kind == "opacity":
            t[:, 3] = self.opacity
        else:
            raise ValueError(f"unknown LUT kind {kind!r}")
        return np.concatenate([t, t[-1:]])

    @property
    def values(self) -> np.ndarray:
        return self.lo + np.arange(self.n) / self.scale

    def visible_span(self) -> tuple[float, float]:
        """Open interval of LUT coordinates f (entry index, fractional) where the linear interpolant of the
        opacities is non-zero: (first non-zero entry − 1, last non-zero entry + 1); empty when all are zero."""
        nz = np.flatnonzero(self.opacity > 0.0)
        if not nz.size:
            return float(self.n + 1), -2.0
        return float(nz[0] - 1), float(nz[-1] + 1)

    def visible(self, vmin: ArrayLike, vmax: ArrayLike) -> np.ndarray:
        """True where the LUT's interpolant has non-zero opacity somewhere on [vmin, vmax] (arrays, any shape).
        Conservative: the index range is widened by one entry each side. Non-finite bounds (NaN-only blocks)
        are invisible."""
        # float32 when the ranges are (the cells' of full resolution: a million of them per TF) and its rounding
        # over the table's span moves an entry index by well under the one-entry widening
        span = max(abs(self.lo), abs(self.lo + (self.n - 1) / self.scale))
        exact32 = span * self.scale * 2.0**-22 < 0.25
        f32 = exact32 and np.asarray(vmin).dtype == np.float32 and np.asarray(vmax).dtype == np.float32
        ft = np.float32 if f32 else np.float64
        vmin = np.asarray(vmin, dtype=ft)
        vmax = np.asarray(vmax, dtype=ft)
        ok = np.isfinite(vmin) & np.isfinite(vmax)
        with np.errstate(over="ignore", invalid="ignore"):
            f0 = np.floor((np.where(ok, vmin, 0) - ft(self.lo)) * ft(self.scale)) - 1
            f1 = np.ceil((np.where(ok, vmax, 0) - ft(self.lo)) * ft(self.scale)) + 1
        i0 = np.clip(f0, 0, self.n - 1).astype(np.int64)
        i1 = np.clip(f1, 0, self.n - 1).astype(np.int64)
        nz = np.concatenate([[0], np.cumsum(self.opacity > 0.0)])
        return ok & ((nz[i1 + 1] - nz[i0]) > 0)


def _approx_gcd(gaps: np.ndarray, tol: float) -> float:
    g = float(gaps[0])
    for d in gaps[1:]:
        a, b = max(g, float(d)), min(g, float(d))
        while b > tol:
            a, b = b, math.fmod(a, b)
        g = a
    return g


def build_lut(tf: TransferFunction, value_range: tuple[float, float]) -> Lut:
    """The kernel's table over the data range (see module doc for how its resolution is chosen)."""
    lo, hi = float(value_range[0]), float(value_range[1])
    if not (math.isfinite(lo) and math.isfinite(hi)):
        lo, hi = 0.0, 1.0
    if hi <= lo:
        hi = lo + 1.0
    span = hi - lo
    xs = np.array(sorted({p.value for p in tf.points}), dtype=np.float64)
    dup = len(xs) < len(tf.points) and any(
        tf.points[k].value == tf.points[k - 1].value and lo <= tf.points[k].value <= hi for k in range(1, len(tf.points))
    )
    inside = xs[(xs >= lo) & (xs <= hi)]
    h_target = span / (LUT_MIN - 1)
    if len(inside) >= 2:
        h_target = min(h_target, float(np.diff(inside).min()) / 64.0)
    exact = False
    n = 0
    start = lo
    if len(inside) >= 1:
        gaps = np.diff(inside)
        g = _approx_gcd(gaps, 1e-9 * span) if len(gaps) else span
        if g > 1e-9 * span:
            h = g / math.ceil(g / h_target - 1e-9)
            start = float(inside[0]) - math.ceil((inside[0] - lo) / h - 1e-9) * h
            n = int(math.ceil((hi - start) / h - 1e-9)) + 1
            if 2 <= n <= LUT_MAX:
                exact = not dup and bool(np.all(np.abs((inside - start) / h - np.round((inside - start) / h)) < 1e-6))
            else:
                n = 0
    if not exact:
        n = int(min(LUT_MAX, max(LUT_MIN, math.ceil(span / h_target) + 1)))
        start, h = lo, span / (n - 1)
    vals = start + np.arange(n) * h
    rgb, a = evaluate(tf, vals)
    return Lut(lo=start, scale=1.0 / h, n=n, rgb=rgb, opacity=a, exact=exact)
