"""A volume's histograms for the viewer's transfer-function editor (`GET /volumes/{id}/histogram`), from the store's
per-block histograms alone (no voxel is read):

- the plain histogram: the sum of the block histograms. Each block's histogram includes a one-voxel border taken
  from its neighbours (store/histogram.py), so a voxel on a block face is counted in two to eight blocks: the
  counts exceed the voxel count by at most (1 + 2/B)³ and the shape is the volume's;
- the α-histogram of thesis §3.3.2, eq. 3.4: h_α(s) = (Σ_i h(i, s)^α)^(1/α) over the blocks i, each block's histogram
  taken as a distribution first (renderer/scene/adaptive_tf.py: alpha_histogram), so that a tissue that fills a few
  blocks shows as a peak even where the plain histogram buries it under a larger tissue's tail; α = 1 is the plain
  histogram's shape (each block weighs the same, a partial block at the edge too), and as α grows each bin tends to the largest share any one block gives it;
- its peaks (§3.3.2, "Automatic tissue detection II": detected in the α-histogram, each with its extent and size):
  the local maxima of the α-histogram in decades, smoothed over a few bins, with their topographic prominence (how
  far the curve falls before it rises to a higher peak), most prominent first; each comes with a transfer function
  that shows that tissue alone, the viewer's one-click suggestion;
- the adaptive presets (renderer/scene/presets.py: ADAPTIVE) as placed on this volume by the renderer, the
  template adaptation of §3.3.2 fig. 3.7.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from lodcast.renderer.scene.adaptive_tf import ALPHA, alpha_histogram

__all__ = ["ALPHA", "MIN_PROMINENCE", "SUGGESTED_OPACITY", "Peak", "find_peaks", "block_histograms", "volume_histogram"]

#: decades the smoothed α-histogram must fall on both sides of a maximum before it counts as a peak: a factor 2
MIN_PROMINENCE = 0.3
#: the opacity a suggested TF accumulates across its tissue's typical extent (_suggestion)
SUGGESTED_OPACITY = 0.6
#: decades below the histogram's maximum where peak detection stops looking
FLOOR = 3.0
#: blocks per step of the α-sum: bounds the float64 working set for stores of millions of blocks
_CHUNK = 8192
# colours of the suggested TFs, one per peak in order of prominence (distinct on black and on the histogram)
_PALETTE = ((1.0, 0.45, 0.35), (0.35, 0.75, 1.0), (1.0, 0.85, 0.3), (0.5, 1.0, 0.5), (0.85, 0.5, 1.0),
            (1.0, 0.6, 0.8), (0.6, 0.95, 0.95), (0.95, 0.95, 0.95))


@dataclass(frozen=True)
class Peak:
    """A peak of the α-histogram: its value (bin centre), the values where it has fallen by half its prominence on
    either side (or reached a valley), its prominence in decades, and the share of the volume's voxels in that
    range (plain histogram)."""

    value: float
    lo: float
    hi: float
    prominence: float
    weight: float


def _smooth_log(h: np.ndarray) -> np.ndarray:
    """log10 of `h`, floored FLOOR decades below its maximum, smoothed by a Gaussian of 1.5 bins: peaks are shapes,
    not single noisy bins, and the sparse tail of a tissue (blocks holding a handful of its voxels, which the
    α-sum lifts) is not a row of peaks."""
    top = float(h.max()) if h.size and h.max() > 0 else 1.0
    log = np.log10(np.maximum(h, 10.0 ** -FLOOR * top))
    kernel = np.exp(-0.5 * (np.arange(-4, 5) / 1.5) ** 2)
    return np.asarray(np.convolve(np.pad(log, 4, mode="edge"), kernel / kernel.sum(), mode="valid"))


def find_peaks(h: np.ndarray, centres: np.ndarray, plain: np.ndarray | None = None,
               min_prominence: float = MIN_PROMINENCE) -> list[Peak]:
    """The peaks of histogram `h` (bins at `centres`) at least `min_prominence` decades prominent, most prominent
    first; `plain` (default `h`) gives each its share of the voxels."""
    h = np.asarray(h, np.float64)
    centres = np.asarray(centres, np.float64)
    plain = h if plain is None else np.asarray(plain, np.float64)
    s = _smooth_log(h)
    n = len(s)
    out: list[Peak] = []
    for i in range(n):
        left_ok = i == 0 or s[i] > s[i - 1]
        right_ok = i == n - 1 or s[i] >= s[i + 1]
        if not (left_ok and right_ok) or (i > 0 and s[i] == s[i - 1]):
            continue
        # prominence: on each side, the lowest point before a higher bin (or the end); the higher of those two
        # minima is the saddle towards the nearest higher ground
        bases = []
        for step in (-1, 1):
            j, low = i, s[i]
            while 0 <= j + step < n and s[j + step] <= s[i]:
                j += step
                low = min(low, s[j])
            bases.append(low)
        prom = float(s[i] - max(bases))
        if prom < min_prominence:
            continue
        lo, hi = i, i
        half = s[i] - prom / 2
        while lo > 0 and s[lo - 1] >= half and s[lo - 1] <= s[lo]:
            lo -= 1
        while hi < n - 1 and s[hi + 1] >= half and s[hi + 1] <= s[hi]:
            hi += 1
        total = float(plain.sum())
        weight = float(plain[lo:hi + 1].sum() / total) if total > 0 else 0.0
        out.append(Peak(float(centres[i]), float(centres[lo]), float(centres[hi]), prom, weight))
    return sorted(out, key=lambda p: -p.prominence)


def block_histograms(hist: np.ndarray, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """(plain, α-histogram) of per-block histograms (…, bins); the α-sum in chunks of blocks, in float64. The
    α-histogram is scaled so that its total is the plain one's: only its shape carries meaning, and on one axis
    the two compare."""
    h = np.asarray(hist).reshape(-1, np.shape(hist)[-1])
    plain = h.sum(axis=0, dtype=np.float64)
    # the α-th powers summed chunk by chunk, the root taken once: eq. 3.4 over all blocks
    acc = np.zeros(h.shape[1])
    for k in range(0, len(h), _CHUNK):
        acc += alpha_histogram(h[k:k + _CHUNK], alpha) ** alpha
    ha = acc ** (1.0 / alpha)
    total = float(ha.sum())
    return plain, ha * (float(plain.sum()) / total if total > 0 else 0.0)


def _suggestion(peak: Peak, colour: tuple[float, float, float], voxels: int) -> dict[str, Any]:
    """A TF that shows the peak's range and nothing else: a tent from `lo` to `hi` around the peak's value,
    transparent at its feet (half a range beyond them, so that the tissue's own values are all in it). Its opacity
    (per unit distance, about a voxel) makes a ray that crosses the tissue's typical extent, (share × voxels)^(1/3)
    voxels, keep SUGGESTED_OPACITY of it: a tissue that fills a fifth of a body is seen into, a small one stands out
    as a surface."""
    extent = max(1.0, (peak.weight * voxels) ** (1.0 / 3.0))
    opacity = round(1.0 - (1.0 - SUGGESTED_OPACITY) ** (1.0 / extent), 4)
    below = peak.lo - 0.5 * max(peak.value - peak.lo, 1e-9)
    above = peak.hi + 0.5 * max(peak.hi - peak.value, 1e-9)
    rgb = [round(c, 3) for c in colour]
    return {"points": [{"value": round(below, 6), "color": rgb, "opacity": 0.0},
                       {"value": round(peak.value, 6), "color": rgb, "opacity": opacity},
                       {"value": round(above, 6), "color": rgb, "opacity": 0.0}]}


def volume_histogram(store: Any, alpha: float = ALPHA, min_prominence: float = MIN_PROMINENCE) -> dict[str, Any]:
    """The histogram response of one store (without `adapted`, which needs the renderer): bin edges, plain and
    α-histogram counts, the background (the plain histogram's most common value) and the α-histogram's peaks with
    their suggested TFs (the background's peak last, with no suggestion: it is what a TF hides)."""
    edges = np.asarray(store.hist_edges, np.float64)
    centres = 0.5 * (edges[1:] + edges[:-1])
    plain, ha = block_histograms(store.hist, alpha)
    background = float(centres[int(np.argmax(plain))]) if plain.any() else float(centres[0])
    peaks = find_peaks(ha, centres, plain, min_prominence) if plain.any() else []
    listed, k = [], 0
    for p in peaks:
        is_bg = p.lo <= background <= p.hi
        entry: dict[str, Any] = {"value": p.value, "lo": p.lo, "hi": p.hi, "prominence": round(p.prominence, 4),
                                 "weight": p.weight, "background": is_bg, "tf": None}
        if not is_bg:
            entry["tf"] = _suggestion(p, _PALETTE[k % len(_PALETTE)], int(np.prod(store.shape, dtype=np.int64)))
            k += 1
        listed.append(entry)
    listed.sort(key=lambda e: e["background"])  # stable: by prominence within each group
    return {"value_range": [float(v) for v in store.value_range], "edges": edges.tolist(), "counts": plain.tolist(),
            "alpha": alpha, "alpha_counts": ha.tolist(), "background": background, "peaks": listed}
