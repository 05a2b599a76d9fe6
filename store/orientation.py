"""Which patient direction each world axis of a store points to, from the source's own geometry: DICOM's
ImageOrientationPatient (LPS), NIfTI's affine (RAS), NRRD's space directions in its named space. Recorded at
ingest as `orientation: ["L", "P", "S"]` (world +x, +y, +z), so that a camera can ask for an anatomical view
(`"view": "anterior"`) whatever the format stored the volume as; None where the source says nothing (npy, raw,
TIFF, zarr).

The store's world axes stay the volume's index axes (voxel (z, y, x) at origin + index × spacing): lodcast does
not resample or flip data. A DICOM CT seen at azimuth 0 therefore shows the face (+y is posterior) and a NIfTI MR
in RAS shows the back of the head (+y is anterior); named views show both from the same side.
"""
from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["axis_codes", "VIEWS", "view_direction"]

OPPOSITE = {"L": "R", "R": "L", "A": "P", "P": "A", "S": "I", "I": "S"}
#: what +x, +y, +z of each patient frame point to
FRAMES = {"LPS": ("L", "P", "S"), "RAS": ("R", "A", "S"), "LAS": ("L", "A", "S")}
_NRRD_SPACES = {"left-posterior-superior": "LPS", "right-anterior-superior": "RAS", "left-anterior-superior": "LAS",
                "lps": "LPS", "ras": "RAS", "las": "LAS"}
#: a named view: the patient direction the eye looks from
VIEWS = {"anterior": "A", "posterior": "P", "left": "L", "right": "R", "superior": "S", "inferior": "I"}


def _code(vector: Any, frame: str) -> str | None:
    v = np.asarray(vector, dtype=np.float64)
    if v.shape != (3,) or not np.isfinite(v).all() or not v.any():
        return None
    k = int(np.argmax(np.abs(v)))
    letter = FRAMES[frame][k]
    return letter if v[k] > 0 else OPPOSITE[letter]


def axis_codes(provenance: dict[str, Any]) -> list[str] | None:
    """[code of world +x, +y, +z] from a source's provenance, or None."""
    fmt = provenance.get("format")
    vectors: list[Any] = []
    frame = None
    if fmt == "dicom" and provenance.get("orientation") is not None:
        o = np.asarray(provenance["orientation"], dtype=np.float64)
        if o.shape == (6,):
            vectors, frame = [o[:3], o[3:], np.cross(o[:3], o[3:])], "LPS"  # slices sorted along the normal
    elif fmt == "nifti" and provenance.get("affine") is not None:
        a = np.asarray(provenance["affine"], dtype=np.float64)
        if a.shape == (4, 4):
            vectors, frame = [a[:3, 0], a[:3, 1], a[:3, 2]], "RAS"  # the array's x, y, z are nibabel's i, j, k
    elif fmt == "nrrd" and provenance.get("space_directions") is not None:
        frame = _NRRD_SPACES.get(str(provenance.get("space", "")).lower())
        d = np.asarray(provenance["space_directions"], dtype=np.float64)
        if frame is not None and d.shape == (3, 3):
            vectors = [d[0], d[1], d[2]]  # NRRD's fastest axis first: world x, y, z
    if frame is None or len(vectors) != 3:
        return None
    codes = [_code(v, frame) for v in vectors]
    if None in codes or len({min(c, OPPOSITE[c]) for c in codes}) != 3:  # type: ignore[arg-type]
        return None  # degenerate: two axes along the same anatomical direction
    return codes  # type: ignore[return-value]


def view_direction(view: str, codes: list[str]) -> np.ndarray:
    """Unit vector (world x, y, z) from the volume's centre towards the eye of a named view."""
    want = VIEWS[view]
    for axis, code in enumerate(codes):
        if code in (want, OPPOSITE[want]):
            d = np.zeros(3)
            d[axis] = 1.0 if code == want else -1.0
            return d
    raise ValueError(f"camera.view: no axis of this volume points {view}")
