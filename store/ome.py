"""OME-Zarr 0.5 `multiscales` metadata for a store's level arrays, so napari, Neuroglancer and ome-zarr readers
open the same store at the right scale and position."""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

__all__ = ["multiscales", "omero", "is_ct", "SOFT_TISSUE"]

#: the soft-tissue window of a CT in Hounsfield units (level 40, width 400)
SOFT_TISSUE = (-160.0, 240.0)
_UNITS = {"mm": "millimeter", "um": "micrometer", "µm": "micrometer", "nm": "nanometer", "m": "meter", "cm": "centimeter"}


def ome_unit(units: str) -> str:
    """The OME (UDUNITS-2) name for a length unit, e.g. 'mm' -> 'millimeter'."""
    return _UNITS.get(units, units)


def omero(label: str, hist: ArrayLike, edges: ArrayLike, value_range: Sequence[float],
          clip: float = 0.005) -> dict:
    """The `omero` rendering settings viewers start from: for a CT in Hounsfield units (`is_ct`) the soft-tissue
    window (level 40, width 400: organs, muscle and fat told apart, bone white, air black), as a radiology viewer
    opens it; else a greyscale window over the values between the 0.5th and 99.5th percentiles of the volume's
    histogram, so that a 16-bit micrograph or an MR is not shown as black."""
    import numpy as np

    h = np.asarray(hist, dtype=np.float64)
    e = np.asarray(edges, dtype=np.float64)
    lo, hi = (float(v) for v in value_range)
    start, end = lo, hi
    if is_ct(h, e, (lo, hi)):
        start, end = SOFT_TISSUE
    elif h.sum() > 0:
        cdf = np.cumsum(h) / h.sum()
        start = float(e[int(np.searchsorted(cdf, clip))])
        end = float(e[min(len(e) - 1, int(np.searchsorted(cdf, 1.0 - clip)) + 1)])
    if not end > start:
        start, end = lo, hi if hi > lo else lo + 1.0
    return {"channels": [{"label": label, "color": "FFFFFF", "active": True, "coefficient": 1.0, "family": "linear",
                          "inverted": False,
                          "window": {"min": lo, "max": hi, "start": max(lo, start), "end": min(hi, end)}}],
            "rdefs": {"model": "greyscale", "defaultZ": 0, "defaultT": 0}}


def is_ct(hist: ArrayLike, edges: ArrayLike, value_range: Sequence[float]) -> bool:
    """Whether a volume's histogram looks like a CT in Hounsfield units: air at about -1000 (at least 1 % of the
    voxels between -1100 and -900: the air around and inside a body) and values up to soft tissue and beyond
    (the range reaching +100)."""
    import numpy as np

    h = np.asarray(hist, dtype=np.float64)
    e = np.asarray(edges, dtype=np.float64)
    lo, hi = (float(v) for v in value_range)
    if h.sum() <= 0 or lo > -900.0 or hi < 100.0:
        return False
    centres = (e[:-1] + e[1:]) / 2.0
    return bool(h[(centres >= -1100.0) & (centres <= -900.0)].sum() >= 0.01 * h.sum())


def multiscales(name: str, n_levels: int, spacing: Sequence[float], origin: Sequence[float], units: str) -> dict:
    """The `ome` attribute block. Level k averages 2^k-cubes of level-0 voxels, so its scale is 2^k·spacing and its
    first sample's centre sits (2^k − 1)/2 level-0 voxels past level 0's first centre."""
    datasets = []
    for k in range(n_levels):
        f = float(1 << k)
        datasets.append(
            {
                "path": str(k),
                "coordinateTransformations": [
                    {"type": "scale", "scale": [s * f for s in spacing]},
                    {"type": "translation", "translation": [o + s * (f - 1.0) / 2.0 for o, s in zip(origin, spacing)]},
                ],
            }
        )
    unit = ome_unit(units)
    return {
        "version": "0.5",
        "multiscales": [
            {
                "name": name,
                "axes": [{"name": a, "type": "space", "unit": unit} for a in ("z", "y", "x")],
                "datasets": datasets,
                "type": "mean",
                "metadata": {"description": "flat multiresolution blocks averaged within each block (lodcast)"},
            }
        ],
    }
