"""What ingest reads: a scalar volume seen as a stack of z-slabs, whatever its file format.

Every reader in `lodcast.store.readers` returns a `VolumeSource`. Ingest asks for slabs in increasing z order
(`read(z0, z1)` with z0 equal to the previous z1), so a reader may stream (gzip, DICOM files one by one); peak
memory then stays one slab, whatever the depth.
"""
from __future__ import annotations

import abc
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["VolumeSource", "ArraySource", "SourceInfo", "SUPPORTED_DTYPES", "check_world_box", "narrowest_integer",
           "whole_type", "NARROW_TYPES"]

#: dtypes a store can hold; anything else (complex, object, bool, 64-bit ints beyond float64's exact range…) is refused.
SUPPORTED_DTYPES = tuple(
    np.dtype(t) for t in ("uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64")
)

#: the stored-type rule (store format 4): the first of these that holds every value exactly, else float32
NARROW_TYPES = tuple(np.dtype(t) for t in ("uint8", "int8", "uint16", "int16"))


def narrowest_integer(lo: float, hi: float) -> np.dtype | None:
    """The first of NARROW_TYPES that holds every integer in [lo, hi], or None when none does."""
    for t in NARROW_TYPES:
        info = np.iinfo(t)
        if info.min <= lo and hi <= info.max:
            return t
    return None


def whole_type(lo: float, hi: float) -> np.dtype:
    """The type of rescaled whole values in [lo, hi]: the first of NARROW_TYPES that holds them, else float32 (the
    stored-type rule) while it holds them exactly (|v| <= 2^24); past that int32, else float64 (float32 would round
    them)."""
    narrow = narrowest_integer(lo, hi)
    if narrow is not None:
        return narrow
    if -FLOAT32_WHOLE <= lo and hi <= FLOAT32_WHOLE:
        return np.dtype(np.float32)
    info = np.iinfo(np.int32)
    return np.dtype(np.int32) if info.min <= lo and hi <= info.max else np.dtype(np.float64)


#: float32 holds every whole number of at most this magnitude exactly
FLOAT32_WHOLE = float(2**24)


@dataclass(frozen=True)
class SourceInfo:
    """Geometry and provenance of a source volume, in the store's (z, y, x) order and world units. `space` and
    `direction` say which way the axes point where the source knows it: `direction` holds the unit vectors, in
    `space` (x, y, z components), of one step along the array's x, y and z (rows in that order), and `origin` is
    then voxel (0, 0, 0)'s position in that space (store/orientation.py)."""

    shape: tuple[int, int, int]
    dtype: np.dtype
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    units: str = "millimeter"
    format: str = ""
    provenance: dict[str, Any] = field(default_factory=dict)
    space: str | None = None
    direction: tuple[tuple[float, float, float], ...] | None = None


#: the world box's bounds, in world units: its coordinates, their squares and a voxel's reciprocal stay finite in the
#: renderer's float32, and a box thinner than RELATIVE_EXTENT of its distance from the world's origin (about eight
#: float32 steps across it) is degenerate there
MIN_SPACING, MAX_SPACING, WORLD_LIMIT, RELATIVE_EXTENT = 1e-12, 1e12, 1e15, 1e-6


def check_world_box(info: SourceInfo) -> None:
    """Refuses (SourceError naming the file and the field) spacing and origin that do not give a finite,
    non-degenerate world box: the box runs from origin − spacing/2 to origin + (shape − ½)·spacing."""
    from lodcast.errors import SourceError

    name = info.provenance.get("path") or f"the {info.format or 'volume'} source"
    spacing, origin = [float(v) for v in info.spacing], [float(v) for v in info.origin]
    if len(spacing) != 3 or not all(MIN_SPACING <= v <= MAX_SPACING for v in spacing):  # NaN fails too
        raise SourceError(f"{name}: spacing (z, y, x) {spacing} must be three numbers from {MIN_SPACING:g} to "
                          f"{MAX_SPACING:g} world units")
    if len(origin) != 3 or not all(math.isfinite(v) and abs(v) <= WORLD_LIMIT for v in origin):
        raise SourceError(f"{name}: origin (z, y, x) {origin} must be three finite numbers within "
                          f"±{WORLD_LIMIT:g} world units")
    for axis, n, s, o in zip("zyx", info.shape, spacing, origin):
        lo, hi = o - s / 2, o + (int(n) - 0.5) * s
        far = max(abs(lo), abs(hi))
        if far > WORLD_LIMIT:
            raise SourceError(f"{name}: the world box along {axis} runs from {lo:.6g} to {hi:.6g} (origin {o:g}, "
                              f"spacing {s:g}, {n} voxels), beyond ±{WORLD_LIMIT:g} world units")
        if hi - lo < RELATIVE_EXTENT * far:
            raise SourceError(f"{name}: the world box along {axis} is {hi - lo:.3g} thick (spacing {s:g}, {n} voxels) "
                              f"at origin {o:g}, less than {RELATIVE_EXTENT:g} of its distance from 0: too thin to "
                              f"place in float32 (set a smaller origin or a larger spacing)")


class VolumeSource(abc.ABC):
    """A scalar 3D volume readable in z-slabs. Use as a context manager."""

    info: SourceInfo
    # True when reading a slab again costs about what reading raw bytes does (arrays, plain binary files,
    # uncompressed DICOM): ingest's second pass then reads the source again instead of decompressing level 0
    rereads_cheaply: bool = False
    # memory the reader holds beside the slab it returns (a zarr source's decoded chunk row), counted by ingest
    # against its memory limit
    held_bytes: int = 0

    @abc.abstractmethod
    def read(self, z0: int, z1: int) -> np.ndarray:
        """Voxels [z0, z1) as an array of shape (z1 - z0, Y, X) and dtype `info.dtype`."""

    def close(self) -> None:
        """Release files; called once ingest is done."""

    def __enter__(self) -> "VolumeSource":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ArraySource(VolumeSource):
    """An in-memory (or memory-mapped) 3D array; 2D arrays are one slice thick."""

    rereads_cheaply = True

    def __init__(self, array: np.ndarray, *, spacing: Sequence[float] | None = None,
                 origin: Sequence[float] | None = None, units: str = "millimeter", format: str = "numpy") -> None:
        from lodcast.errors import SourceError

        a = np.asarray(array) if not isinstance(array, np.memmap) else array
        if a.ndim == 2:
            a = a[None]
        if a.ndim != 3:
            raise SourceError(f"a volume must be a 3D array (z, y, x), got {a.ndim} dimensions with shape {a.shape}")
        self._array = a
        self.info = SourceInfo(
            shape=tuple(int(s) for s in a.shape),  # type: ignore[arg-type]
            dtype=a.dtype,
            spacing=tuple(float(s) for s in (spacing or (1.0, 1.0, 1.0))),  # type: ignore[arg-type]
            origin=tuple(float(s) for s in (origin or (0.0, 0.0, 0.0))),  # type: ignore[arg-type]
            units=units,
            format=format,
        )

    def read(self, z0: int, z1: int) -> np.ndarray:
        return np.asarray(self._array[z0:z1])
