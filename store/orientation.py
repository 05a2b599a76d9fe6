"""Where a store's axes point in the patient, in one frame for every format: LPS (+x left, +y posterior, +z
superior; DICOM's and ITK's frame).

A reader that knows its geometry says so in `SourceInfo.space` (DICOM: "LPS"; NIfTI: "RAS", from its sform, else
qform; NRRD: its named space) and `SourceInfo.direction` (the unit vectors, in that space, of one step along the
array's x, y and z axes), with `origin` the position of voxel (0, 0, 0) in that space. Ingest records it in LPS as
the store's `orientation` (`space`, `axes`: the patient direction of world +x, +y, +z, `direction`) and writes
the origin as the patient frame rotated onto the array's axes (origin = direction · p0), so that world positions
are rigid: patient position = directionᵀ · (origin + index × spacing).

By default (`orient="LPS"`) ingest turns the array (store/readers/reorient.py), by permutations and flips only (no
resampling, no value changes), so that each world axis is the LPS axis closest to it; a DICOM CT and a NIfTI MR
then both show the face at azimuth 0. `orient="source"` keeps the file's axes: level 0 is the file's array, and a
NIfTI in RAS has +x pointing right. A source without patient geometry is never turned. Named views
(`"view": "anterior"`) put the eye on the same side of the patient either way. What a permutation cannot remove,
the tilt of an oblique acquisition, stays in `direction`.
"""
from __future__ import annotations

import dataclasses
import itertools
from typing import Any

import numpy as np

__all__ = ["PATIENT_SPACE", "FRAMES", "OPPOSITE", "VIEWS", "Turn", "space_name", "to_lps", "axis_codes",
           "legacy_axis_codes", "turn_of", "view_direction"]

PATIENT_SPACE = "LPS"
OPPOSITE = {"L": "R", "R": "L", "A": "P", "P": "A", "S": "I", "I": "S"}
#: what +x, +y, +z of each patient frame point to
FRAMES = {"LPS": ("L", "P", "S"), "RAS": ("R", "A", "S"), "LAS": ("L", "A", "S")}
_NAMES = {"left-posterior-superior": "LPS", "right-anterior-superior": "RAS", "left-anterior-superior": "LAS"}
#: a named view: the patient direction the eye looks from
VIEWS = {"anterior": "A", "posterior": "P", "left": "L", "right": "R", "superior": "S", "inferior": "I"}


def space_name(space: Any) -> str | None:
    """"LPS", "RAS" or "LAS" for a patient frame under any of its NRRD or short names; other spaces keep their
    name (NRRD's "scanner-xyz", "3D-right-handed"); None when there is none."""
    if space is None or str(space).strip() == "":
        return None
    s = str(space).strip()
    return _NAMES.get(s.lower(), s.upper() if s.upper() in FRAMES else s)


def to_lps(space: str, vectors: np.ndarray) -> np.ndarray:
    """Rows of (x, y, z) components in a patient `space`, in LPS."""
    signs = np.array([1.0 if a == b else -1.0 for a, b in zip(FRAMES[space], FRAMES["LPS"])])
    return vectors * signs


def axis_codes(space: str | None, direction: Any) -> list[str] | None:
    """The patient direction ("L", "P", …) of world +x, +y, +z, given `direction` rows in a patient `space`;
    None for other spaces or degenerate directions (two axes along one anatomical direction)."""
    if space not in FRAMES or direction is None:
        return None
    d = np.asarray(direction, dtype=np.float64)
    if d.shape != (3, 3) or not np.isfinite(d).all() or not np.abs(d).sum(axis=1).all():
        return None
    codes = []
    for v in d:
        k = int(np.argmax(np.abs(v)))
        codes.append(FRAMES[space][k] if v[k] > 0 else OPPOSITE[FRAMES[space][k]])
    if len({min(c, OPPOSITE[c]) for c in codes}) != 3:
        return None
    return codes


def legacy_axis_codes(provenance: dict[str, Any]) -> list[str] | None:
    """Codes of a store written before the `orientation` attribute: its world axes are the source's index axes,
    whose geometry its provenance recorded."""
    fmt = provenance.get("format")
    if fmt == "dicom" and provenance.get("orientation") is not None:
        o = np.asarray(provenance["orientation"], dtype=np.float64)
        if o.shape == (6,):
            return axis_codes("LPS", [o[:3], o[3:], np.cross(o[:3], o[3:])])
    elif fmt == "nifti" and provenance.get("affine") is not None:
        a = np.asarray(provenance["affine"], dtype=np.float64)
        if a.shape == (4, 4):
            return axis_codes("RAS", a[:3, :3].T)
    elif fmt == "nrrd" and provenance.get("space_directions") is not None:
        return axis_codes(space_name(provenance.get("space")), provenance["space_directions"])
    return None


@dataclasses.dataclass(frozen=True)
class Turn:
    """World axis j (x, y, z) is the source's axis `order[j]`, reversed where `flip[j]`."""

    order: tuple[int, int, int]
    flip: tuple[bool, bool, bool]

    @property
    def identity(self) -> bool:
        return self.order == (0, 1, 2) and not any(self.flip)

    def apply(self, slab: np.ndarray) -> np.ndarray:
        """A (z, y, x) array of the source's axes in the world's (array axis 2 − j holds world axis j)."""
        out = slab.transpose([2 - self.order[2], 2 - self.order[1], 2 - self.order[0]])
        return out[tuple(slice(None, None, -1) if self.flip[2 - a] else slice(None) for a in range(3))]


def turn_of(vectors: np.ndarray) -> Turn:
    """The permutation that puts each source axis (rows of `vectors`) on the world axis it is closest to (the
    largest total |cosine|: unambiguous even when one axis is tilted 45°), and the flips that make it point +."""
    order = max(itertools.permutations(range(3)), key=lambda p: sum(abs(vectors[p[j], j]) for j in range(3)))
    return Turn(tuple(order), tuple(bool(vectors[order[j], j] < 0) for j in range(3)))  # type: ignore[arg-type]


def view_direction(view: str, codes: list[str]) -> np.ndarray:
    """Unit vector (world x, y, z) from the volume's centre towards the eye of a named view."""
    want = VIEWS[view]
    for axis, code in enumerate(codes):
        if code in (want, OPPOSITE[want]):
            d = np.zeros(3)
            d[axis] = 1.0 if code == want else -1.0
            return d
    raise ValueError(f"camera.view: no axis of this volume points {view}")
