"""Transfer-function-based block significance (thesis §3.2.1, eq. 3.1) and its data-error baseline.

ζ(0), the significance of a block at its coarsest level (one sample: the block mean s̄), is the RMS colour
difference between the TF's colour at the mean and at every value the block holds::

    ζ(0) = [ (1/n) Σ_s ΔE(T*(s̄), T*(s))² h(s) ]^½                                        (eq. 3.1)

with h the block's border-inclusive histogram (the one-voxel border from the neighbours, because interpolation
near a face reads those voxels too), n its total count, T* the TF in CIELUV and ΔE the CIE76 distance there.

**How opacity enters the colour.** T*(s) is the CIELUV colour (sRGB input, D65; image_error.srgb_to_luv) of what a slab
of constant value s and length one *unit distance* (the TF's opacity unit, docs/design.md) contributes over black:
the premultiplied colour rgb(s)·a(s), a being the TF opacity per unit distance (a slab of length `unit` takes
opacity 1 − (1 − a)^1 = a, and its colour over black is rgb·a). Why: (1) a fully transparent value maps to black,
L*u*v* = 0, so every value of a transparent range has the same T* and a block whose values all lie in one gives
ΔE = 0 whatever the colours written at its control points; (2) a faint value weighs as little in the error as it
does in the image, and a change of opacity alone (same rgb) is a change of colour; (3) it does not depend on the
ray-marching step (opacity is per unit distance, not per sample). Colours are used as given (no linearisation),
as the compositing does.

Which blocks count as empty: a block is *TF-empty* when the TF opacity is zero over its whole border-inclusive
value range [min_border, max_border] (exact test on the piecewise-linear opacity); its ζ is 0 and it is never
read. A block whose value range is exactly one value (constant, border included) has ζ = 0 exactly: every level
of it is exact (the average of a constant), so it is read at the coarsest level and never refined.

Evaluation. T* is tabulated once per TF (colour-science on at most a few thousand values, never per block): at
the histogram bin centres, and on the renderer's LUT grid (`build_lut`: uniform, every control point on an entry
when that fits, capped at DENSE_MAX entries) in which T*(s̄) is interpolated linearly (measured against direct
colour-science evaluation at the mean: ≤ 2e-4 ΔE in ζ on the tests' CT-like TF). With the
simplified histogram (K piecewise-constant pieces, heights h_k = mean count per bin over bins [s_k, s_{k+1}))
the sum is O(K) per block (the pieces restricted to the block's exact value range [min_border, max_border], which
the store keeps beside the histogram: see `effective_starts`, which brings the simplified ζ much closer to the
full-histogram ζ) through prefix sums over bins of T*(b) and |T*(b)|²::

    Σ_{b∈piece} |T̄ − T*(b)|² = w|T̄|² − 2 T̄·Σ T*(b) + Σ |T*(b)|²

and Σ_k h_k (P(s_{k+1}) − P(s_k)) = Σ_j (h_{j−1} − h_j) P(s_j) (h_{−1} = h_K = 0): one gather of the 4-channel
prefix table at the K + 1 starts and one small matrix product per block, in float64 (the expansion cancels:
ζ² ≪ |T̄|²). Over all blocks that is one sparse × dense product M·P, M (N × (bins + 1)) holding each block's
coefficients at its starts: with SciPy installed it runs as a CSR product (one C loop), else as a NumPy gather +
batched product in chunks on a small thread pool (LODCAST_SIGNIFICANCE_NUMPY=1 forces the latter; both agree to
rounding: ζ² within 1e-12 relative + 1e-8). The coefficients, indices and M depend only on the store and are cached per store, so a TF change costs
only the per-TF part. Visibility is one searchsorted against the TF's zero-opacity intervals.

Over levels (store numbering: level 0 = full resolution, level L−1 = one sample per block; the thesis numbers
them the other way round), ζ is distributed linearly, as the thesis does: ζ(level k) = ζ(0)·k/(L−1), ζ0 at the
one-sample level, zero at full resolution.
"""
from __future__ import annotations

import functools
import os
import weakref
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike

from lodcast.environment import environment
from lodcast.renderer.image.delta_e import srgb_to_luv
from lodcast.renderer.scene.scene import TransferFunction
from lodcast.renderer.scene.transfer_function import build_lut, evaluate

__all__ = [
    "BlockMeta",
    "TStar",
    "srgb_to_luv",
    "unit_slab_colour",
    "tstar",
    "as_tf",
    "tf_visible",
    "zero_intervals",
    "zeta0_simplified",
    "zeta0_full",
    "zeta0_l2",
    "level_profile",
    "zeta_levels",
    "block_significance",
    "meta_of_store",
    "effective_starts",
]

DENSE_MAX = 8192  # cap on the dense T* table


# --------------------------------------------------------------------------------------------- colour

def unit_slab_colour(tf: TransferFunction, values: ArrayLike) -> np.ndarray:
    """Premultiplied sRGB colour over black of a slab of one unit distance at each value: rgb·a."""
    rgb, a = evaluate(tf, values)
    return rgb * a[..., None]


def as_tf(tf: Any) -> TransferFunction:
    """A TransferFunction from the scene's model or its JSON dict."""
    if isinstance(tf, TransferFunction):
        return tf
    if hasattr(tf, "model_dump"):
        tf = tf.model_dump()
    return TransferFunction.model_validate(tf)


@dataclass(frozen=True, eq=False)
class TStar:
    """T* of one TF, tabulated: at the bin centres (with a 4-channel prefix table over bins: L, u, v, |T*|²)
    and on a dense uniform value table (entry k at lo + k/scale) for T*(s̄)."""

    centres: np.ndarray  # (nb,) bin representative values
    luv: np.ndarray  # (nb, 3) T* at the centres
    prefix: np.ndarray  # (nb + 1, 4) prefix sums of [L, u, v, |T*|²] over bins
    dense_lo: float
    dense_scale: float  # entries per data unit
    dense_luv: np.ndarray  # (m, 3)

    @property
    def dense_values(self) -> np.ndarray:
        return self.dense_lo + np.arange(self.dense_luv.shape[0]) / self.dense_scale

    def at(self, values: np.ndarray) -> np.ndarray:
        """T*(values) by linear interpolation in the dense table (clamped at its ends), (..., 3)."""
        v = np.asarray(values, np.float64)
        m = self.dense_luv.shape[0]
        if m == 1:
            return np.broadcast_to(self.dense_luv[0], v.shape + (3,)).copy()
        f = np.clip((v - self.dense_lo) * self.dense_scale, 0.0, m - 1.0)
        i = np.minimum(f.astype(np.intp), m - 2)
        t = f - i
        # one 48-byte row per cell: (T*[k], T*[k+1] − T*[k])
        g = np.take(self._cells, i, axis=0).view(np.float64).reshape(v.shape + (2, 3))
        return g[..., 0, :] + g[..., 1, :] * t[..., None]

    @property
    def _cells(self) -> np.ndarray:
        c = self.__dict__.get("_cells_cache")
        if c is None:
            d = self.dense_luv
            c = np.ascontiguousarray(np.concatenate([d[:-1], d[1:] - d[:-1]], axis=1)).view(np.dtype((np.void, 48))).ravel()
            object.__setattr__(self, "_cells_cache", c)
        return c


def bin_centres(bins: Any) -> np.ndarray:
    e = bins.edges
    return np.arange(bins.count, dtype=np.float64) + bins.lo if bins.integer else 0.5 * (e[:-1] + e[1:])


def tstar(tf: TransferFunction, bins: Any, value_range: tuple[float, float] | None = None) -> TStar:
    """Tabulate T* of `tf` once (the only place colour-science runs per TF). The dense table is the renderer's
    LUT grid (`build_lut`: uniform, with every control point inside the range on an entry when that fits, else
    at least 64 entries per smallest control-point gap), or a uniform DENSE_MAX-entry grid when that is finer
    than DENSE_MAX entries."""
    tf = as_tf(tf)
    centres = bin_centres(bins)
    lo, hi = (float(bins.lo), float(bins.hi)) if value_range is None else (float(value_range[0]), float(value_range[1]))
    lo, hi = min(lo, float(centres[0])), max(hi, float(centres[-1]))
    lut = build_lut(tf, (lo, hi))
    if lut.n <= DENSE_MAX:
        d_lo, d_scale, d_n = lut.lo, lut.scale, lut.n
    else:
        d_n = DENSE_MAX
        d_lo, d_scale = lo, (d_n - 1) / (hi - lo)
    dense = d_lo + np.arange(d_n) / d_scale
    luv_all = srgb_to_luv(unit_slab_colour(tf, np.concatenate([centres, dense])))
    luv, dense_luv = luv_all[: centres.size], luv_all[centres.size :]
    q = np.concatenate([luv, (luv * luv).sum(axis=1, keepdims=True)], axis=1)
    prefix = np.concatenate([np.zeros((1, 4)), np.cumsum(q, axis=0)], axis=0)
    return TStar(centres, luv, prefix, float(d_lo), float(d_scale), np.ascontiguousarray(dense_luv))


def zero_intervals(tf: TransferFunction) -> tuple[np.ndarray, np.ndarray]:
    """Closed, disjoint, sorted value intervals (lo, hi) where the TF opacity is exactly zero (±inf ends): a
    segment between two zero control points, an isolated zero point, and the constant ends beyond the outer
    points. At a repeated value (a step) the point counts as zero only if every point there is zero."""
    xs = np.array([p.value for p in tf.points], np.float64)
    ops = np.array([p.opacity for p in tf.points], np.float64)

    def positive_at(x: float) -> bool:
        return bool(np.any((xs == x) & (ops > 0.0)))

    def lo_end(x: float) -> float:  # a step up at x: x itself is not in the zero interval (conservative)
        return float(np.nextafter(x, np.inf)) if positive_at(x) else float(x)

    def hi_end(x: float) -> float:
        return float(np.nextafter(x, -np.inf)) if positive_at(x) else float(x)

    ivs: list[tuple[float, float]] = []
    if ops[0] == 0.0:
        ivs.append((-np.inf, hi_end(xs[0])))
    for k in range(len(xs)):
        if ops[k] == 0.0 and not positive_at(xs[k]):
            ivs.append((float(xs[k]), float(xs[k])))
        if k + 1 < len(xs) and ops[k] == 0.0 and ops[k + 1] == 0.0 and xs[k] < xs[k + 1]:
            ivs.append((lo_end(xs[k]), hi_end(xs[k + 1])))
    if ops[-1] == 0.0:
        ivs.append((lo_end(xs[-1]), np.inf))
    ivs = [(lo, hi) for lo, hi in ivs if lo <= hi]
    ivs.sort()
    merged: list[list[float]] = []
    for lo, hi in ivs:
        if merged and lo <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], hi)
        else:
            merged.append([lo, hi])
    if not merged:
        return np.empty(0), np.empty(0)
    m = np.array(merged, np.float64)
    return m[:, 0], m[:, 1]


def tf_visible(tf: TransferFunction, vmin: ArrayLike, vmax: ArrayLike) -> np.ndarray:
    """True where the TF opacity is non-zero somewhere on [vmin, vmax] (exact for the piecewise-linear TF,
    constant outside its points): the range is invisible iff one zero-opacity interval contains it.
    Non-finite bounds (no valid voxel) are invisible."""
    tf = as_tf(tf)
    vmin = np.asarray(vmin, np.float64)
    vmax = np.asarray(vmax, np.float64)
    z_lo, z_hi = zero_intervals(tf)
    if z_lo.size == 0:
        vis = np.ones(vmin.shape, bool)
    else:
        j = np.searchsorted(z_lo, vmin, side="right") - 1
        jc = np.maximum(j, 0)
        vis = ~((j >= 0) & (vmax <= z_hi[jc]))
    vis &= np.isfinite(vmin)
    vis &= np.isfinite(vmax)
    return vis


# --------------------------------------------------------------------------------------------- block data
@dataclass(frozen=True, eq=False)  # identity hash: tables are kept per object
class BlockMeta:
    """What significance needs of a store, flattened over blocks (C order of the grid)."""

    grid: tuple[int, int, int]
    n_levels: int
    bins: Any  # store.histogram.Bins
    mean: np.ndarray  # (N,) float64, NaN when a block has no valid voxel
    count: np.ndarray  # (N,) own valid voxels
    min_border: np.ndarray  # (N,)
    max_border: np.ndarray  # (N,)
    starts: np.ndarray  # (N, K + 1) bin indices
    heights: np.ndarray  # (N, K) mean count per bin
    hist: Any = None  # (N, nb) full histograms, or a callable returning them (read on demand)
    level_std: np.ndarray | None = None  # (N, L) RMS spread of each block's level-k voxels; None: format-1 store
    value_range: tuple[float, float] | None = None
    std_max: float = 0.0
    own_min: np.ndarray | None = None  # (N,) the block's own voxels' range, without the neighbours' border
    own_max: np.ndarray | None = None

    @property
    def n(self) -> int:
        return self.mean.size

    def full_hist(self) -> np.ndarray:
        h = self.hist() if callable(self.hist) else self.hist
        if h is None:
            raise ValueError("full histograms are not available")
        return np.asarray(h).reshape(self.n, -1)

    @functools.cached_property
    def effective(self) -> np.ndarray:
        """effective_starts, computed once per metadata object: every TF's block errors (both of a selection's
        passes, and each TF change) take it, and on a million blocks it cost a good part of a pass."""
        starts = effective_starts(self)
        starts.flags.writeable = False
        return starts

    @functools.cached_property
    def pre(self) -> "_Pre":
        """The TF-independent part of eq. 3.1's O(K) evaluation, computed once per metadata object."""
        return _precompute(self)


def _hist_reader(ref: Callable[[], Any]) -> Callable[[], Any]:
    return lambda: ref().hist


def meta_of_store(store: Any, tables: Any = None) -> BlockMeta:
    """The store's block metadata, flattened; kept per store object in `tables` (an engine's Tables) when given."""
    kept = None if tables is None else tables.meta
    try:
        return kept[store]  # type: ignore[index]
    except (KeyError, TypeError):
        pass
    st = store.stats
    starts, heights = store.hist_simplified
    n = int(np.prod(store.grid))
    meta = BlockMeta(
        grid=tuple(store.grid),
        n_levels=int(store.layout.n_levels),
        bins=store.bins,
        mean=np.asarray(st.mean, np.float64).ravel(),
        count=np.asarray(st.count, np.float64).ravel(),
        min_border=np.asarray(st.min_border, np.float64).ravel(),
        max_border=np.asarray(st.max_border, np.float64).ravel(),
        starts=np.asarray(starts).reshape(n, -1),
        heights=np.asarray(heights).reshape(n, -1),
        hist=_hist_reader(weakref.ref(store)),  # weak: the cache's value must not keep its key alive
        level_std=None if getattr(store, "level_std", None) is None else np.asarray(store.level_std, np.float64).reshape(n, -1),
        value_range=(float(store.value_range[0]), float(store.value_range[1])),
        std_max=float(getattr(store, "std_max", 0.0)),
        own_min=np.asarray(st.min, np.float64).ravel(),
        own_max=np.asarray(st.max, np.float64).ravel(),
    )
    if kept is not None:
        try:
            kept[store] = meta
        except TypeError:
            pass
    return meta


@dataclass(frozen=True, eq=False)
class _Pre:
    """TF-independent part of the O(K) evaluation: gather indices (N, K+1) and coefficients (N, 1, K+1)."""

    idx: np.ndarray
    coef: np.ndarray
    total: np.ndarray  # (N,) n = Σ_k h_k w_k
    last: np.ndarray | None  # (N,) coefficient of P(nb) when the starts run from 0 to nb (gathered otherwise)
    csr: Any = None  # the same map as a SciPy CSR matrix (N × (nb + 1)) when SciPy is installed


def _csr(starts: np.ndarray, coef: np.ndarray, width: int) -> Any | None:
    """Σ_j c_j P(s_j) for every block is one sparse × dense product M @ P, M (N × (nb + 1)) with the coefficients
    at the starts: SciPy's CSR product does it in one C loop, faster than the NumPy gather + batched product."""
    if environment().significance_numpy:
        return None
    try:
        import scipy.sparse as sp
    except ImportError:
        return None
    n, k = starts.shape
    m = sp.csr_matrix((coef.ravel(), starts.ravel(), np.arange(0, n * k + 1, k)), shape=(n, width))
    m.sum_duplicates()
    m.eliminate_zeros()
    return m


def effective_starts(meta: BlockMeta) -> np.ndarray:
    """The simplified histograms' starts (N, K + 1) restricted to each block's exact border-inclusive value range:
    clipped to [bin(min_border), bin(max_border) + 1], so that no piece places counts in bins the block has no
    value in (a piece fitted over a long sparse tail spreads its mean height over the whole tail; the block's
    min and max are stored exactly beside the histogram). Blocks without a valid voxel keep theirs."""
    starts = np.asarray(meta.starts, np.intp)
    ok = np.isfinite(meta.min_border) & np.isfinite(meta.max_border)
    if not ok.any():
        return starts
    lo = np.where(ok, meta.bins.index(np.where(ok, meta.min_border, meta.bins.lo)), 0).astype(np.intp)
    hi = np.where(ok, meta.bins.index(np.where(ok, meta.max_border, meta.bins.lo)) + 1, meta.bins.count).astype(np.intp)
    return np.clip(starts, lo[:, None], hi[:, None])


def _precompute(meta: BlockMeta) -> _Pre:
    starts = meta.effective
    h = np.asarray(meta.heights, np.float64)
    n = h.shape[0]
    hp = np.concatenate([np.zeros((n, 1)), h, np.zeros((n, 1))], axis=1)
    coef = (hp[:, :-1] - hp[:, 1:])[:, None, :]  # c_j = h_{j-1} - h_j
    total = (h * np.diff(starts, axis=1)).sum(axis=1)
    csr = _csr(starts, coef[:, 0, :], int(meta.bins.count) + 1)
    last = None
    nb = int(meta.bins.count)
    if starts.shape[1] > 2 and np.all(starts[:, 0] == 0) and np.all(starts[:, -1] == nb):  # (unclipped starts)
        # what ingest writes: the first start is bin 0 (P(0) = 0: no term) and the last is the end (P(nb) is one
        # vector for every block: c_K·P(nb) without a gather); only the K − 1 inner starts are gathered
        last = np.ascontiguousarray(coef[:, 0, -1])
        starts, coef = starts[:, 1:-1], coef[:, :, 1:-1]
    return _Pre(np.ascontiguousarray(starts), np.ascontiguousarray(coef), total, last, csr)


def _zeta_from_sums(tbar: np.ndarray, s: np.ndarray, total: np.ndarray) -> np.ndarray:
    """ζ = sqrt(|T̄|² + (B − 2 T̄·A)/n) from A = s[:, :3], B = s[:, 3]; 0 where n = 0."""
    w = np.empty_like(s)
    np.multiply(tbar, -2.0, out=w[:, :3])
    w[:, 3] = 1.0
    with np.errstate(invalid="ignore", divide="ignore"):
        z2 = np.einsum("ij,ij->i", tbar, tbar) + np.einsum("ij,ij->i", w, s) / total
    z2[~(total > 0)] = 0.0
    np.maximum(z2, 0.0, out=z2)
    return np.sqrt(z2, out=z2)


def _blocks_to_eval(meta: BlockMeta, visible: np.ndarray) -> np.ndarray:
    """Blocks whose ζ needs computing: visible and not constant (ζ = 0 exactly otherwise)."""
    return visible & (meta.max_border > meta.min_border) & np.isfinite(meta.mean)


_CHUNK = 16384


def zeta0_simplified(meta: BlockMeta, ts: TStar, visible: np.ndarray) -> np.ndarray:
    """ζ(0) per block (N,) float64 from the simplified histograms, O(K) per block (see module doc). Chunks of
    blocks run on a small thread pool (NumPy releases the GIL in the gather and the batched product)."""
    pre = meta.pre
    todo = _blocks_to_eval(meta, visible)
    out = np.zeros(meta.n)
    if not todo.any():
        return out
    sel = None if todo.mean() > 0.75 else np.flatnonzero(todo)
    idx = pre.idx if sel is None else pre.idx[sel]
    coef = pre.coef if sel is None else pre.coef[sel]
    total = pre.total if sel is None else pre.total[sel]
    mean = meta.mean if sel is None else meta.mean[sel]
    if pre.csr is not None:
        sums_all = pre.csr @ ts.prefix
        z = _zeta_from_sums(ts.at(np.nan_to_num(mean)), sums_all if sel is None else sums_all[sel], total)
        if sel is None:
            z[~todo] = 0.0
            return z
        out[sel] = z
        return out
    last = pre.last if (pre.last is None or sel is None) else pre.last[sel]
    table = np.ascontiguousarray(ts.prefix).view(np.dtype((np.void, 32))).ravel()  # one 32-byte row per bin edge
    p_end = ts.prefix[-1]
    m = idx.shape[0]
    sums = np.empty((m, 1, 4))

    def work(a: int) -> None:
        e = min(a + _CHUNK, m)
        g = np.take(table, idx[a:e], axis=0).view(np.float64).reshape(e - a, idx.shape[1], 4)
        np.matmul(coef[a:e], g, out=sums[a:e])

    starts = range(0, m, _CHUNK)
    threads = min(4, os.cpu_count() or 1)
    if m > 2 * _CHUNK and threads > 1:
        with ThreadPoolExecutor(threads, thread_name_prefix="lodcast-significance") as pool:
            list(pool.map(work, starts))
    else:
        for a in starts:
            work(a)
    s4 = sums[:, 0, :]
    if last is not None:
        s4 += last[:, None] * p_end
    z = _zeta_from_sums(ts.at(np.nan_to_num(mean)), s4, total)
    if sel is None:
        z[~todo] = 0.0
        return z
    out[sel] = z
    return out


def zeta0_full(meta: BlockMeta, ts: TStar, visible: np.ndarray, hist: np.ndarray | None = None, chunk: int = 8192) -> np.ndarray:
    """ζ(0) from the full border-inclusive histograms (paper II's 'full histogram' variant; fig. 3.4 a)."""
    h_all = meta.full_hist() if hist is None else np.asarray(hist).reshape(meta.n, -1)
    todo = np.flatnonzero(_blocks_to_eval(meta, visible))
    out = np.zeros(meta.n)
    q = np.concatenate([ts.luv, (ts.luv**2).sum(axis=1, keepdims=True)], axis=1)  # (nb, 4)
    for c0 in range(0, todo.size, chunk):
        rows = todo[c0 : c0 + chunk]
        h = h_all[rows].astype(np.float64)
        sums = h @ q
        out[rows] = _zeta_from_sums(ts.at(meta.mean[rows]), sums, h.sum(axis=1))
    return out


def zeta0_l2(meta: BlockMeta, visible: np.ndarray, hist: np.ndarray | None = None, chunk: int = 8192) -> np.ndarray:
    """Data-error (L2) significance, fig. 3.4 c: RMS deviation of the data from the block mean,
    sqrt((1/n) Σ_b h(b)(c_b − s̄)²) over the full border-inclusive histogram (bin centres c_b), in data units and
    independent of the TF; TF-empty blocks still get 0 (they are skipped by every method alike)."""
    h_all = meta.full_hist() if hist is None else np.asarray(hist).reshape(meta.n, -1)
    todo = np.flatnonzero(_blocks_to_eval(meta, visible))
    out = np.zeros(meta.n)
    c = bin_centres(meta.bins)
    for c0 in range(0, todo.size, chunk):
        rows = todo[c0 : c0 + chunk]
        h = h_all[rows].astype(np.float64)
        n = h.sum(axis=1)
        mu = meta.mean[rows]
        with np.errstate(invalid="ignore", divide="ignore"):
            m1 = (h @ (c - 0.0)) / n
            m2 = (h @ (c * c)) / n
        var = m2 - 2.0 * mu * m1 + mu * mu
        out[rows] = np.sqrt(np.maximum(np.where(n > 0, var, 0.0), 0.0))
    return out


# --------------------------------------------------------------------------------------------- levels
def level_profile(n_levels: int) -> np.ndarray:
    """ζ(level k) / ζ(0) in store numbering: k/(L−1), 1 at the one-sample level, 0 at full resolution."""
    if n_levels <= 1:
        return np.zeros(max(n_levels, 1))
    return np.arange(n_levels, dtype=np.float64) / (n_levels - 1)


def zeta_levels(zeta0: np.ndarray, n_levels: int) -> np.ndarray:
    """zeta0 shape + (n_levels,) float32, linear from ζ(0) at level L−1 to 0 at level 0."""
    z0 = np.asarray(zeta0, np.float64)
    return (z0[..., None] * level_profile(n_levels)).astype(np.float32)


# --------------------------------------------------------------------------------------------- entry
def block_significance(meta: BlockMeta, tfs: Sequence[Any] | Any, method: str = "tf") -> tuple[np.ndarray, np.ndarray]:
    """(ζ(0) (N,) float64, visible (N,) bool) for one TF or several (ζ = max over TFs, visible = any).

    method: "tf" (eq. 3.1, simplified histograms), "tf_full_hist" (full histograms), "l2" (data error)."""
    if isinstance(tfs, (TransferFunction, dict)) or hasattr(tfs, "points"):
        tfs = [tfs]
    tfs = [as_tf(t) for t in tfs if t is not None]
    if not tfs:
        raise ValueError("at least one transfer function is needed")
    visible = np.zeros(meta.n, bool)
    for t in tfs:
        visible |= tf_visible(t, meta.min_border, meta.max_border)
    if method == "l2":
        return zeta0_l2(meta, visible), visible
    z = np.zeros(meta.n)
    for t in tfs:
        ts = tstar(t, meta.bins)
        vis_t = tf_visible(t, meta.min_border, meta.max_border) if len(tfs) > 1 else visible
        if method == "tf":
            z = np.maximum(z, zeta0_simplified(meta, ts, vis_t))
        elif method == "tf_full_hist":
            z = np.maximum(z, zeta0_full(meta, ts, vis_t))
        else:
            raise ValueError(f"unknown significance method {method!r}")
    return z, visible
