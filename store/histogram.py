"""Per-block value histograms and their simplified piecewise-constant form (thesis §3.2.1, fig. 3.3).

Histograms count every valid (non-NaN, non-padding) voxel of a block plus a one-voxel border taken from its
neighbours, because interpolation near a block face reads those voxels too (thesis §3.5.2, paper IX). Bins span
the volume's value range: one bin per integer value when an integer volume has at most `max_bins` values,
otherwise `max_bins` equal bins with the last one closed.

The simplified form is the least-squares-optimal segmentation of the histogram into at most K constant pieces,
found exactly by dynamic programming. Two facts keep it fast: bins are compressed into runs of equal counts
(an optimal boundary never falls strictly inside a run, because moving it through a run of equal values changes
the two segments' squared error by a concave function of the position, so an end of the run is at least as
good), and the dynamic programme runs vectorised over many blocks at once.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["Bins", "DEFAULT_BINS", "DEFAULT_SEGMENTS", "simplify", "segmentation_sse", "expand"]

DEFAULT_BINS = 256
DEFAULT_SEGMENTS = 12


@dataclass(frozen=True)
class Bins:
    """Histogram bins over a volume's value range [lo, hi]."""

    lo: float
    hi: float
    count: int
    integer: bool  # one bin per integer value, centred on it

    @classmethod
    def for_range(cls, lo: float, hi: float, integer: bool, max_bins: int = DEFAULT_BINS) -> "Bins":
        if not (np.isfinite(lo) and np.isfinite(hi)) or hi < lo:
            raise ValueError(f"value range must be finite with lo <= hi, got [{lo}, {hi}]")
        if integer and hi - lo + 1 <= max_bins:
            return cls(float(lo), float(hi), int(hi - lo) + 1, True)
        if hi == lo:
            return cls(float(lo), float(hi), 1, False)
        return cls(float(lo), float(hi), max_bins, False)

    @property
    def edges(self) -> np.ndarray:
        if self.integer:
            return np.arange(self.count + 1, dtype=np.float64) + self.lo - 0.5
        if self.count == 1:
            return np.array([self.lo - 0.5, self.lo + 0.5])
        return np.linspace(self.lo, self.hi, self.count + 1)

    def index(self, values: np.ndarray) -> np.ndarray:
        """Bin of each value as int32; NaN maps to -1 (counted nowhere)."""
        v = np.asarray(values)
        if self.integer:
            # values of an integer volume lie in [lo, hi] by construction: no clipping pass needed
            idx = v.astype(np.int32)
            idx -= np.int32(self.lo)
            return idx
        if v.dtype.kind in "iu" and self._lut is not None:
            return np.take(self._lut, v.astype(np.int64) - int(self.lo))
        vf = v.astype(np.float64, copy=False)
        if self.count == 1:
            idx = np.zeros(vf.shape, np.int32)
        else:
            idx = np.floor((vf - self.lo) * (self.count / (self.hi - self.lo)))
            idx = np.clip(np.nan_to_num(idx, nan=0.0), 0, self.count - 1).astype(np.int32)
            # the product can round across an edge; the stored edges are the truth (as np.histogram does)
            edges = self.edges
            idx -= (vf < edges[idx]) & (idx > 0)
            idx += (vf >= edges[idx + 1]) & (idx < self.count - 1)
        idx[np.isnan(vf)] = -1
        return idx

    @cached_property
    def _lut(self) -> np.ndarray | None:
        """Bin of every integer in [lo, hi], from the edges themselves: integer volumes (CT in HU, 16-bit
        microscopy) are binned by one table lookup instead of a float computation per voxel."""
        if self.integer or self.hi - self.lo > 1 << 22 or self.lo != int(self.lo):
            return None
        values = np.arange(int(self.lo), int(self.hi) + 1, dtype=np.float64)
        return np.clip(np.searchsorted(self.edges, values, side="right") - 1, 0, self.count - 1).astype(np.int32)

    def to_dict(self) -> dict:
        return {"lo": self.lo, "hi": self.hi, "count": self.count, "integer": self.integer}


def _runs(h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Run starts (bin indices, with the final end appended) and run values of one histogram."""
    change = np.flatnonzero(np.diff(h)) + 1
    starts = np.concatenate(([0], change, [h.size]))
    return starts, h[starts[:-1]]


def simplify(hists: np.ndarray, segments: int = DEFAULT_SEGMENTS, *,
             device: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """Optimal piecewise-constant approximation of each histogram with at most `segments` pieces.

    Returns (starts, heights): starts (N, segments + 1) uint16 bin indices with starts[:, 0] = 0 and
    starts[:, -1] = n_bins (equal neighbours mark unused, empty pieces), heights (N, segments) float32, the mean
    count per bin of each piece. Minimises sum over bins of (h − piece height)².

    Runs on an OpenCL device with float64 when there is one (`device`: a lodcast.opencl.Device to use, else
    NumPy; None: a new Device if one can be opened, else NumPy; True: a new Device, required; False: NumPy).
    Both solve the same programme exactly; among segmentations of equal error they may pick different ones.
    """
    hists = np.asarray(hists)
    if not 1 <= segments <= 64:
        raise ValueError(f"segments must be in 1..64, got {segments}")
    if device is not False and hists.shape[0]:
        try:
            from lodcast.opencl import Device

            return _simplify_device(Device() if device is None or device is True else device, hists, segments)
        except ImportError:
            if device is True:
                raise
        except Exception as exc:  # no OpenCL platform, no fp64: the NumPy path gives the same optimum
            from lodcast.opencl import DeviceError

            if device is True or not isinstance(exc, (DeviceError, RuntimeError)):
                raise
    return _simplify_numpy(hists.astype(np.float64), segments)


def _simplify_device(dev: Any, hists: np.ndarray, k: int, batch: int = 512) -> tuple[np.ndarray, np.ndarray]:
    import pyopencl as cl

    from lodcast.opencl import DeviceError

    ctx, queue = dev.context, dev.queue
    if "cl_khr_fp64" not in ctx.devices[0].extensions:
        raise DeviceError("the OpenCL device has no float64")
    kernel = cl.Kernel(dev.program("segment.cl", (), folder=Path(__file__).resolve().parent).program, "segment")
    n, nb = hists.shape
    starts = np.empty((n, k + 1), np.uint16)
    heights = np.empty((n, k), np.float32)
    mf = cl.mem_flags
    for b0 in range(0, n, batch):
        h = np.ascontiguousarray(hists[b0 : b0 + batch], dtype=np.uint32)
        m = h.shape[0]
        hb = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=h)
        scratch = cl.Buffer(ctx, mf.READ_WRITE, size=m * 5 * (nb + 1) * 8)
        runs = cl.Buffer(ctx, mf.READ_WRITE, size=m * (nb + 1) * 4)
        arg = cl.Buffer(ctx, mf.READ_WRITE, size=m * (k + 1) * (nb + 1) * 2)
        sb = cl.Buffer(ctx, mf.WRITE_ONLY, size=m * (k + 1) * 2)
        wb = cl.Buffer(ctx, mf.WRITE_ONLY, size=m * k * 4)
        kernel(queue, (m,), None, hb, np.int32(nb), np.int32(k), np.int32(m), scratch, runs, arg, sb, wb)
        cl.enqueue_copy(queue, starts[b0 : b0 + m], sb)
        cl.enqueue_copy(queue, heights[b0 : b0 + m], wb)
    queue.finish()
    return starts, heights


def _simplify_numpy(hists: np.ndarray, segments: int, group: int = 256) -> tuple[np.ndarray, np.ndarray]:
    n, n_bins = hists.shape
    k = segments
    starts = np.full((n, k + 1), n_bins, np.uint16)
    starts[:, 0] = 0
    heights = np.zeros((n, k), np.float32)
    runs = [_runs(h) for h in hists]
    order = np.argsort([len(v) for _, v in runs], kind="stable")
    for g0 in range(0, n, group):
        members = order[g0 : g0 + group]
        _simplify_group([runs[i] for i in members], k, starts, heights, members)
    return starts, heights


def _simplify_group(runs: list, k: int, starts: np.ndarray, heights: np.ndarray, members: np.ndarray) -> None:
    r = max(len(v) for _, v in runs)
    g = len(runs)
    length = np.zeros((g, r))
    value = np.zeros((g, r))
    for row, (s, v) in enumerate(runs):
        length[row, : len(v)] = np.diff(s)
        value[row, : len(v)] = v
    # prefix sums over runs: count of bins, sum of counts, sum of squared counts
    c = np.concatenate([np.zeros((g, 1)), np.cumsum(length, axis=1)], axis=1)
    s1 = np.concatenate([np.zeros((g, 1)), np.cumsum(length * value, axis=1)], axis=1)
    s2 = np.concatenate([np.zeros((g, 1)), np.cumsum(length * value * value, axis=1)], axis=1)

    def cost(i: np.ndarray | slice, j: int) -> np.ndarray:
        cnt = c[:, j : j + 1] - c[:, i]
        t1 = s1[:, j : j + 1] - s1[:, i]
        with np.errstate(invalid="ignore", divide="ignore"):
            e = s2[:, j : j + 1] - s2[:, i] - np.where(cnt > 0, t1 * t1 / cnt, 0.0)
        return np.maximum(e, 0.0)

    m_max = min(k, r)
    d = np.full((m_max + 1, g, r + 1), np.inf)
    arg = np.zeros((m_max + 1, g, r + 1), np.int32)
    for j in range(1, r + 1):
        d[1, :, j] = cost(slice(0, 1), j)[:, 0]
    for m in range(2, m_max + 1):
        for j in range(m, r + 1):
            cand = d[m - 1, :, m - 1 : j] + cost(slice(m - 1, j), j)
            best = np.argmin(cand, axis=1)
            d[m, :, j] = cand[np.arange(g), best]
            arg[m, :, j] = best + (m - 1)
    # at most k pieces: the best piece count per block (fewer pieces when the runs are fewer or it is no worse)
    total = d[1:, :, r]  # (m_max, g)
    m_best = np.argmin(total, axis=0) + 1
    for row in range(g):
        s, v = runs[row]
        bounds = [r]
        j, m = r, int(m_best[row])
        while m > 1:
            j = int(arg[m, row, j])
            bounds.append(j)
            m -= 1
        bounds.append(0)
        bounds = bounds[::-1]
        n_real = len(v)
        bins = [int(s[min(b, n_real)]) for b in bounds]  # padded runs (zero length) sit past the end
        out = members[row]
        piece_count = len(bins) - 1
        starts[out, : piece_count + 1] = bins
        starts[out, piece_count + 1 :] = bins[-1]
        for p in range(piece_count):
            width = bins[p + 1] - bins[p]
            if width > 0:
                lo_run, hi_run = bounds[p], bounds[p + 1]
                heights[out, p] = (s1[row, hi_run] - s1[row, lo_run]) / width


def expand(starts: np.ndarray, heights: np.ndarray, n_bins: int) -> np.ndarray:
    """The simplified histograms as per-bin counts, shape (N, n_bins) float64."""
    starts = np.asarray(starts, np.int64)
    n, k = heights.shape
    out = np.zeros((n, n_bins))
    bins = np.arange(n_bins)
    for p in range(k):
        inside = (bins[None, :] >= starts[:, p : p + 1]) & (bins[None, :] < starts[:, p + 1 : p + 2])
        out += inside * heights[:, p : p + 1].astype(np.float64)
    return out


def segmentation_sse(hists: np.ndarray, starts: np.ndarray, heights: np.ndarray) -> np.ndarray:
    """Squared error of each simplified histogram against its full histogram."""
    hists = np.asarray(hists, np.float64)
    return ((hists - expand(starts, heights, hists.shape[1])) ** 2).sum(axis=1)
