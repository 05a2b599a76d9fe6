"""Classification of coarse samples by the distribution of the level-0 values they stand for.

A level-k voxel of a store is the mean of a 2^k-cube of level-0 voxels; the store also keeps their standard
deviation (`std/{k}`). Classifying the mean, T(E[s]), loses thin opaque structures: the average of cortical bone
and soft tissue is a value the TF shows as nearly transparent. Classification by distribution (Younesy, Möller and
Carr, EuroVis 2006) takes the expectation of the optical properties instead, under a Gaussian N(mean, std²) of the
values behind the sample:

    σ̄(m, s) = E[σ_t(v)],        ε̄(m, s) = E[σ_t(v) · rgb(v)],        v ~ N(m, s²)

with σ_t = −ln(1 − a) the extinction per unit distance. The kernel composites in extinction form, α = 1 − exp(−σ̄·l)
for a segment of l units, with colour ε̄/σ̄; a perpendicular ray through a one-voxel slab keeps its optical depth
at every level (the slab's share of a coarse voxel times the coarse voxel's length), which the mean loses.

The table is exact in float64 for the kernel's point classification: σ_t and σ_t·rgb piecewise linear between the
LUT entries (the kernel's interpolant, constant beyond the ends). The expectation of a piecewise-linear function
under a Gaussian is a discrete convolution of its entries with the Gaussian-blurred hat function,
K(d) = R(d + 1) − 2R(d) + R(d − 1), R(x) = s·φ(x/s) + x·Φ(x/s) (s = std / entry spacing), evaluated by FFT.
An opacity of 1 has infinite extinction, and any Gaussian tail reaching it would make its voxel opaque: in the
table the extinction is capped at EXT_CAP per unit distance (opacity 1 − e^−30 over one unit), which only the
distribution path sees (a level-0 sample, std 0, is classified exactly as before).

Axes: the mean axis is the LUT's (entry k at lo + k/scale; a LUT of more than DIST_MAX_ENTRIES entries is
subsampled); the std axis is quadratic, s_j = std_max·(j/(J − 1))², so that the kernel finds j from √std with
one multiply and the rows are dense where the classification changes fastest, near std = 0.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from lodcast.renderer.cache import ByteLru
from lodcast.renderer.scene.transfer_function import Lut, build_lut, extinction

__all__ = ["EXT_CAP", "EXT_ZERO", "EXT_ZERO_REL", "DIST_STD_ROWS", "DIST_MAX_ENTRIES", "DistTable", "dist_table", "cached_dist_table",
           "gaussian_expectation"]

EXT_CAP = 30.0
EXT_ZERO = 1e-7
EXT_ZERO_REL = 1e-4
DIST_STD_ROWS = 64
DIST_MAX_ENTRIES = 4096


@dataclass(frozen=True, eq=False)  # identity hash: cached per object
class DistTable:
    """σ̄ and colour ε̄/σ̄ over (std row j, mean entry i); entry i at value lo + i/scale, row j at
    std_max·(j/(rows − 1))²."""

    lo: float
    scale: float
    n: int
    std_max: float
    rows: int
    ext: np.ndarray  # (rows, n) float64 expected extinction per unit distance
    emission: np.ndarray  # (rows, n, 3) float64 expected extinction × colour
    rgb: np.ndarray  # (n, 3) the TF colour at the entries (the point classification's)

    @property
    def stds(self) -> np.ndarray:
        return self.std_max * (np.arange(self.rows) / max(self.rows - 1, 1)) ** 2

    @property
    def std_scale(self) -> float:
        """Row coordinate per √std: j = √std · std_scale."""
        return (self.rows - 1) / np.sqrt(self.std_max) if self.std_max > 0 else 0.0

    def colour(self) -> np.ndarray:
        """ε̄/σ̄ (rows, n, 3); where σ̄ = 0 the colour of the point classification (nothing is emitted there, and
        the row std = 0 then equals the LUT's colours exactly)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            c = self.emission / self.ext[..., None]
        return np.where(self.ext[..., None] > 0, c, self.rgb[None])

    @functools.cached_property
    def kernel_table(self) -> np.ndarray:
        """(rows + 2, n + 1, 4) float32: colour and σ̄, the last entry and the last row repeated once so that the
        kernel's bilinear lookup reads (i + 1, j + 1) without a clamp; then one row of visible spans: entry j holds
        (first, last) entry index where σ̄ > 0 in row j or j + 1, so that the kernel skips the lookup outside."""
        t = np.empty((self.rows, self.n, 4), np.float32)
        t[..., :3] = self.colour()
        t[..., 3] = self.ext
        t = np.concatenate([t, t[:, -1:]], axis=1)
        t = np.concatenate([t, t[-1:]], axis=0)
        spans = np.zeros((1, self.n + 1, 4), np.float32)
        spans[0, :, 0], spans[0, :, 1] = self.n + 1.0, -2.0  # empty rows: nothing is visible
        vis = self.ext > 0
        vis = vis | np.concatenate([vis[1:], vis[-1:]], axis=0)
        for j in np.flatnonzero(vis.any(axis=1)):
            nz = np.flatnonzero(vis[j])
            spans[0, j, :2] = nz[0], nz[-1]
        return np.ascontiguousarray(np.concatenate([t, spans], axis=0))

    def visible(self, vmin: ArrayLike, vmax: ArrayLike, std: ArrayLike) -> np.ndarray:
        """True where a sample of mean in [vmin, vmax] and standard deviation in (0, std] may have a non-zero
        expected extinction: the kernel's test (the spans of `kernel_table`, for every row pair up to std's), half
        an entry wider each side for float32 rounding. False where std is 0 (such samples take the point
        classification) or the bounds are not finite."""
        vmin, vmax, std = (np.asarray(a, np.float64) for a in (vmin, vmax, std))
        spans = self.kernel_table[-1, : self.rows, :2].astype(np.float64)
        lo, hi = np.minimum.accumulate(spans[:, 0]), np.maximum.accumulate(spans[:, 1])
        ok = np.isfinite(vmin) & np.isfinite(vmax) & (std > 0)
        fj = np.minimum(np.sqrt(np.where(ok, std, 0.0)) * self.std_scale + 1e-3, self.rows - 1.0)  # rounding, too
        j = fj.astype(np.intp)
        with np.errstate(invalid="ignore"):
            return ok & ((vmax - self.lo) * self.scale > lo[j] - 1.5) & ((vmin - self.lo) * self.scale < hi[j] + 1.5)

    def interp(self, grid: np.ndarray, mean: ArrayLike, std: ArrayLike) -> np.ndarray:
        """Bilinear interpolation of `grid` (rows, n, C), any per-entry quantity of this table, at (mean, std), as
        the kernel looks the table up (clamped at both axes' ends), float64 (..., C)."""
        return self.lerp(grid, self.mean_axis(mean), self.std_axis(std))

    def mean_axis(self, mean: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(entry, next entry, weight[..., None]) of `mean` along the table's value axis, for `lerp`."""
        fi = np.clip((np.asarray(mean, np.float64) - self.lo) * self.scale, 0.0, self.n - 1.0)
        i = np.minimum(fi.astype(np.intp), max(self.n - 2, 0))
        return i, i + (self.n > 1), (fi - i)[..., None]

    def std_axis(self, std: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(row, next row, weight[..., None]) of `std` along the table's √σ axis, for `lerp`."""
        fj = np.clip(np.sqrt(np.maximum(np.asarray(std, np.float64), 0.0)) * self.std_scale, 0.0, self.rows - 1.0)
        j = np.minimum(fj.astype(np.intp), max(self.rows - 2, 0))
        return j, j + (self.rows > 1), (fj - j)[..., None]

    @staticmethod
    def lerp(grid: np.ndarray, mean_axis: tuple, std_axis: tuple) -> np.ndarray:
        """`interp` from the two axes' positions, which broadcast against each other: a caller that looks many
        deviations up at the same values (or one deviation per row of values) works each axis out once."""
        i, i1, wi = mean_axis
        j, j1, wj = std_axis
        # flat row indices and np.take: faster than grid[j, i], whose fancy indexing dominated a large grid's selection
        n = grid.shape[1]
        flat = grid.reshape((-1,) + grid.shape[2:])
        r0, r1 = j * n, j1 * n
        g00, g01 = np.take(flat, r0 + i, axis=0), np.take(flat, r0 + i1, axis=0)
        a = g00 + (g01 - g00) * wi
        if wj.size == 1 and not wj.any():  # the point classification's row (σ = 0): no second row to blend
            return a
        g10, g11 = np.take(flat, r1 + i, axis=0), np.take(flat, r1 + i1, axis=0)
        b = g10 + (g11 - g10) * wi
        return a + (b - a) * wj

    def lookup(self, mean: ArrayLike, std: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """(colour (..., 3), σ̄ (...)) as the kernel's bilinear lookup gives them (float64, for tests)."""
        e = self.interp(self.kernel_table[: self.rows, : self.n].astype(np.float64), mean, std)
        return e[..., :3], e[..., 3]


def _normal_cdf(z: np.ndarray) -> np.ndarray:
    """Φ(z) = erfc(−z/√2)/2 to double precision, element by element through math.erfc: importing SciPy's ndtr
    for it cost a first render far more than the few thousand values per row the tables need."""
    e = np.frompyfunc(math.erfc, 1, 1)(-np.asarray(z, np.float64) / math.sqrt(2.0))
    return 0.5 * np.asarray(e).astype(np.float64)


def _blurred_hat(s: float) -> np.ndarray:
    """K(d) for d = −R … R: the expectation of the hat function at offset d under N(0, s²) (entry units)."""
    if s <= 0.0:
        return np.ones(1)
    r = int(np.ceil(8.0 * s)) + 2
    x = np.arange(-r - 1, r + 2, dtype=np.float64)
    z = x / s
    ramp = s * np.exp(-0.5 * z * z) / np.sqrt(2.0 * np.pi) + x * _normal_cdf(z)  # E[(x + s Z)_+]
    k = ramp[2:] - 2.0 * ramp[1:-1] + ramp[:-2]
    return k / k.sum()  # the mass beyond 8 s (1e-15) goes back to the kernel


def _smooth_len(n: int) -> int:
    """The smallest 2^a 3^b 5^c >= n."""
    best = 1 << max(0, (n - 1).bit_length())
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            m = p35 << max(0, (-(-n // p35) - 1).bit_length())  # p35 * the smallest power of 2 reaching n
            best = min(best, m)
            p35 *= 3
        p5 *= 5
    return best


def gaussian_expectation(values: np.ndarray, s: float) -> np.ndarray:
    """E[g(i + s Z)] at every entry i of g (..., n) (piecewise linear between entries, constant beyond the ends):
    the convolution with the blurred hat function, by FFT."""
    g = np.asarray(values, np.float64)
    k = _blurred_hat(s)
    r = (k.size - 1) // 2
    if r == 0:
        return g.copy()
    ext = np.concatenate([np.repeat(g[..., :1], r, axis=-1), g, np.repeat(g[..., -1:], r, axis=-1)], axis=-1)
    # linear (not circular) convolution, the 'valid' part being what g needs; zero-padded to a 5-smooth length,
    # which pocketfft transforms several times faster than an arbitrary one
    size = _smooth_len(ext.shape[-1] + k.size - 1)
    full = np.fft.irfft(np.fft.rfft(ext, size, axis=-1) * np.fft.rfft(k, size), size, axis=-1)
    return full[..., 2 * r : 2 * r + g.shape[-1]]


def dist_table(lut: Lut, std_max: float, rows: int = DIST_STD_ROWS) -> DistTable:
    """The distribution table of a TF's LUT for standard deviations up to `std_max` (data units)."""
    stride = int(np.ceil(lut.n / DIST_MAX_ENTRIES))
    idx = np.arange(0, lut.n, stride)
    n = idx.size
    h = stride / lut.scale  # data units per table entry
    sigma = np.minimum(extinction(lut.opacity[idx]), EXT_CAP)
    rgb = lut.rgb[idx]
    chan = np.concatenate([sigma[None], (sigma[:, None] * rgb).T], axis=0)  # (4, n)
    std_max = float(std_max) if np.isfinite(std_max) and std_max > 0 else 0.0
    rows = rows if std_max > 0 else 1
    stds = std_max * (np.arange(rows) / max(rows - 1, 1)) ** 2
    out = np.empty((rows, 4, n))
    for j, sd in enumerate(stds):
        out[j] = gaussian_expectation(chan, sd / h)
    # FFT rounding leaves ~1e-16 of the largest value where the expectation is 0: below EXT_ZERO per unit distance
    # it is zeroed. In the coarse rows, expected extinctions below EXT_ZERO_REL of the TF's strongest are zeroed
    # too, so that the kernel's visible spans skip the cells only such a weak tail reaches: mostly tails from values
    # the TF shows nothing at (fat and muscle under a bone TF). That saves samples for an image error far below
    # what the eye sees; a much higher floor saved more but lost structure where a tail stands for real level-0
    # voxels just above the TF's threshold. Row 0 (std 0) stays the point classification exactly.
    np.copyto(out, 0.0, where=(out[:, :1, :] < EXT_ZERO))
    floor = EXT_ZERO_REL * float(sigma.max(initial=0.0))
    np.copyto(out[1:], 0.0, where=(out[1:, :1, :] < floor))
    return DistTable(lut.lo, lut.scale / stride, n, std_max, rows, out[:, 0, :], np.moveaxis(out[:, 1:, :], 1, 2), rgb)


def cached_dist_table(tf: Any, value_range: tuple[float, float], std_max: float,
                      kept: "ByteLru | None" = None) -> DistTable:
    """dist_table of the LUT the renderer builds for `tf` over `value_range`; `kept`: the tables of recent TFs
    (an engine's `tables.dist`: a turntable or a camera sweep builds each once)."""
    key = (tf.model_dump_json(), float(value_range[0]), float(value_range[1]), float(std_max))
    hit = None if kept is None else kept.get(key)
    if hit is None:
        hit = dist_table(build_lut(tf, (key[1], key[2])), key[3])
        if kept is not None:
            kept.put(key, hit, 1)
    return hit
