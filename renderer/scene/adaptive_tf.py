"""Transfer functions that adapt to the volume: a template placed by the peaks of its α-histogram.

Thesis §3.3.2 ("Enhanced histograms", eq. 3.4; "Automatic tissue detection II", fig. 3.7): the α-histogram sums
the per-block histograms after a power α, h_α(s) = (Σ_i h(i, s)^α)^(1/α), so that a tissue filling a few blocks
shows as a peak even when the global histogram hides it under the background. A template TF is then rescaled on
the location of the second peak, as the thesis does for MR data sets whose intensity scale differs from scan to
scan. Here the first peak is the background (the most common value: air around a body, the empty space around a
specimen), the second the most prominent α-histogram peak above it, and the templates are written in the
coordinate u = (s − background) / (tissue − background): u = 0 is the background, u = 1 the tissue peak.

Used as `"tf": "auto"` (or another name in ADAPTIVE) in any scene: the renderer resolves it when it knows the
volume, and the report and the PNG carry the control points it chose.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from lodcast.renderer.cache import ByteLru
from lodcast.renderer.scene.presets import ADAPTIVE
from lodcast.renderer.scene.scene import AdaptiveTF, TransferFunction

__all__ = ["alpha_histogram", "tissue_peaks", "volume_peaks", "adaptive_tf", "resolve_tfs"]

ALPHA = 4.0  # the thesis' figures emphasise minor coherent features from α ≈ 2..8; noise grows with α
BINS = 256


def _distributions(hist: np.ndarray) -> np.ndarray:
    """Per-block histograms (…, bins) as distributions (N, bins), empty blocks left out: edge blocks with fewer
    voxels weigh as much as whole ones."""
    h = np.asarray(hist, dtype=np.float64).reshape(-1, np.shape(hist)[-1])
    total = h.sum(axis=1, keepdims=True)
    keep = total[:, 0] > 0
    return h[keep] / total[keep]


def _alpha(dist: np.ndarray, alpha: float) -> np.ndarray:
    return (dist**alpha).sum(axis=0) ** (1.0 / alpha)


def alpha_histogram(hist: np.ndarray, alpha: float = ALPHA) -> np.ndarray:
    """Eq. 3.4 over per-block histograms (…, bins), each normalised to a distribution first."""
    return _alpha(_distributions(hist), alpha)


def _block_histograms(a: np.ndarray, edges: np.ndarray, block: int = 16) -> np.ndarray:
    """Per-block histograms of an array (for volumes given as arrays; stores keep theirs from ingest)."""
    nz, ny, nx = a.shape
    z, y, x = np.meshgrid(np.arange(nz) // block, np.arange(ny) // block, np.arange(nx) // block, indexing="ij")
    gy, gx = -(-ny // block), -(-nx // block)
    ids = (z * gy + y) * gx + x
    ok = np.isfinite(a)
    b = np.clip(np.searchsorted(edges, a[ok], side="right") - 1, 0, len(edges) - 2)
    n_blocks = int(ids.max()) + 1
    return np.bincount(ids[ok] * (len(edges) - 1) + b, minlength=n_blocks * (len(edges) - 1)).reshape(n_blocks, -1)


def _histograms(vol: Any) -> tuple[np.ndarray, np.ndarray]:
    """(per-block histograms, bin centres) of a VolumeView: the store's own, else computed from level 0."""
    src = getattr(vol, "source", None)
    if src is not None and hasattr(src, "hist") and hasattr(src, "hist_edges"):
        edges = np.asarray(src.hist_edges, dtype=np.float64)
        return src.hist, 0.5 * (edges[1:] + edges[:-1])
    lo, hi = (float(v) for v in vol.value_range)
    edges = np.linspace(lo, hi if hi > lo else lo + 1.0, BINS + 1)
    return _block_histograms(np.asarray(vol.read_level0(), dtype=np.float64), edges), 0.5 * (edges[1:] + edges[:-1])


def tissue_peaks(hist: np.ndarray, centres: np.ndarray) -> tuple[float, float]:
    """(background, tissue): the most common value, and the α-histogram peak above it with the most weight."""
    dist = _distributions(hist)  # once: for a whole store it is blocks x bins float64
    plain = dist.sum(axis=0)
    if not plain.any():
        return float(centres[0]), float(centres[-1])
    bg = int(np.argmax(plain))
    ha = _alpha(dist, ALPHA)
    # in decades, smoothed over a few bins: peaks are shapes, not single noisy bins
    log = np.log10(ha + 1e-9 * ha.max())
    kernel = np.exp(-0.5 * (np.arange(-4, 5) / 1.5) ** 2)
    smooth = np.convolve(np.pad(log, 4, mode="edge"), kernel / kernel.sum(), mode="valid")
    n = len(smooth)
    # interior maxima only: the range's last bins pile up clipped values (CT's saturated metal), not a tissue
    peaks = [i for i in range(1, n - 2) if smooth[i] >= smooth[i - 1] and smooth[i] > smooth[i + 1]]
    # above the background: past the valley that ends its peak
    valley = bg
    while valley + 1 < n and smooth[valley + 1] <= smooth[valley]:
        valley += 1
    above = [i for i in peaks if i > valley]
    if not above:
        return float(centres[bg]), float(centres[min(n - 1, bg + (n - bg) // 2)])
    tissue = max(above, key=lambda i: (smooth[i], -i))  # the most weight: the tissue most blocks are made of
    return float(centres[bg]), float(centres[tissue])


def volume_peaks(vol: Any, kept: ByteLru | None = None) -> tuple[float, float]:
    """`tissue_peaks` of a VolumeView; `kept`: per store, those found before (an engine's `tables.peaks`: a
    turntable or a TF sweep finds them once)."""
    peaks = kept.get(vol.key) if kept is not None and vol.key is not None else None
    if peaks is None:
        peaks = tissue_peaks(*_histograms(vol))
        if kept is not None and vol.key is not None:
            kept.put(vol.key, peaks, 1)
    return peaks


def resolve_tfs(scene: Any, vol: Any, kept: ByteLru | None = None) -> dict[str, Any]:
    """The scene fields to replace for `vol`: each adaptive TF (AdaptiveTF) by the control points it takes on it
    (`kept`: see volume_peaks)."""
    return {key: TransferFunction.model_validate(adaptive_tf(tf.template, vol, tf.unit_distance, kept))
            for key in ("tf", "tf2") if isinstance(tf := getattr(scene, key), AdaptiveTF)}


def adaptive_tf(name: str, vol: Any, unit_distance: float | None = None,
                kept: ByteLru | None = None) -> dict[str, Any]:
    """The TF JSON of template `name` placed on `vol`'s α-histogram peaks (`kept`: see volume_peaks)."""
    template = ADAPTIVE[name]
    bg, tissue = volume_peaks(vol, kept)
    lo, hi = (float(v) for v in vol.value_range)
    span = tissue - bg if tissue != bg else (hi - lo) or 1.0
    points, last = [], -np.inf
    for u, colour, opacity in template["points"]:
        v = float(np.clip(bg + u * span, min(lo, hi), max(lo, hi)))
        v = max(v, last)  # non-decreasing even where the template runs past the range
        last = v
        points.append({"value": round(v, 6), "color": list(colour), "opacity": opacity})
    out: dict[str, Any] = {"points": points}
    if unit_distance is not None:
        out["unit_distance"] = unit_distance
    return out
