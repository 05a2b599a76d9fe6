"""What every source reader shares, the small internal API of the format modules: the `Reader` base (a
`VolumeSource` whose `read` checks the z range and converts what `_slab` returns to `info.dtype`), `source_info` to
build a `SourceInfo`, `finish` which checks empty axes, settles the stored dtype (narrowing 64-bit integers after a
value scan) and applies spacing/origin overrides, and helpers: `pick_volume` for 2D/3D/4D shapes and `index`,
`read_exact` / `skip_bytes` on a stream, `files_in` a folder, `UNITS` names, `tidy` spacings, `shape_text`,
`source_info`'s direction rows made unit, and `rescaled_type`, the stored-type rule for readers that rescale.
"""
from __future__ import annotations

import abc
import dataclasses
import io
import math
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import DTypeLike

from lodcast.errors import SourceError
from lodcast.store.source import SUPPORTED_DTYPES, SourceInfo, VolumeSource, narrowest_integer, whole_type

__all__ = ["Reader", "source_info", "finish", "pick_volume", "read_exact", "skip_bytes", "files_in", "tidy",
           "shape_text", "UNITS", "READ_CHUNK", "rescaled_type", "Rescale"]


_SLAB = 32  # ingest's block thickness, also the step of the 64-bit value scan
READ_CHUNK = 64 << 10  # bytes per read call, so that a decompressor's temporaries stay small beside a slab
UNITS = {"mm": "millimeter", "millimeter": "millimeter", "um": "micrometer", "\u00b5m": "micrometer",
          "\u03bcm": "micrometer", "micron": "micrometer", "micrometer": "micrometer", "nm": "nanometer",
          "nanometer": "nanometer", "cm": "centimeter", "centimeter": "centimeter", "m": "meter", "meter": "meter"}


class Reader(VolumeSource):
    """A reader sets `info` and returns slabs from `_slab` in any dtype that `info.dtype` holds exactly
    (the file's byte order, or 64-bit integers whose range was checked); `read` converts."""

    @abc.abstractmethod
    def _slab(self, z0: int, z1: int) -> np.ndarray:
        """Voxels [z0, z1) as (z1 - z0, Y, X)."""

    def read(self, z0: int, z1: int) -> np.ndarray:
        depth = self.info.shape[0]
        if not 0 <= z0 <= z1 <= depth:
            raise SourceError(f"slab z {z0}:{z1} is outside the volume's z range 0:{depth}")
        if z0 == z1:
            return np.empty((0, *self.info.shape[1:]), self.info.dtype)
        return np.ascontiguousarray(self._slab(z0, z1), dtype=self.info.dtype)


#: (slope, intercept): a stored pixel p stands for the value p * slope + intercept
Rescale = tuple[float, float]


def rescaled_type(pixel: np.dtype, declared: tuple[float, float], rescale: Sequence[Rescale],
                  pieces: Callable[[], Iterable[tuple[np.ndarray, Rescale]]]) -> np.dtype:
    """The stored type of pixels of type `pixel`, in `declared` (lo, hi) as the file says, each rescaled by one of
    `rescale`: the pixels' own type when nothing is rescaled; float32 when a slope or intercept is not whole (or
    the pixels are not integers); else `whole_type` of the rescaled values. The declared range decides when its
    type is no wider than the pixels; otherwise (16 stored bits of 0…4095 with intercept −1024 declare −1024…64511)
    `pieces()` is read once, each (stored pixels, their rescale) in turn, for the values actually present."""
    if all((s, i) == (1.0, 0.0) for s, i in rescale):
        return pixel
    if pixel.kind not in "iu" or not all(float(s).is_integer() and float(i).is_integer() for s, i in rescale):
        return np.dtype(np.float32)
    ends = _rescaled_ends([declared], rescale)
    narrow = narrowest_integer(*ends)
    # a read of every pixel could then narrow only below the file's own width, at the cost of a second pass
    if narrow is not None and narrow.itemsize <= pixel.itemsize:
        return narrow
    lo, hi = math.inf, -math.inf
    for values, r in pieces():
        if values.size:
            a, b = _rescaled_ends([(values.min(), values.max())], [r])
            lo, hi = min(lo, a), max(hi, b)
    return whole_type(lo, hi) if lo <= hi else whole_type(*ends)  # no pixels: an empty volume, refused later


def _rescaled_ends(ranges: Sequence[tuple[Any, Any]], rescale: Sequence[Rescale]) -> tuple[float, float]:
    """The least and greatest of each range's ends under each rescale (a negative slope swaps them); exact in
    float64 for whole slopes and intercepts below 2^53."""
    ends = [float(v) * s + i for lo, hi in ranges for s, i in rescale for v in (lo, hi)]
    return min(ends), max(ends)


def files_in(folder: Path, keep: Callable[[Path], bool]) -> list[Path]:
    """The plain files of `folder` that `keep(path)` accepts, sorted, leaving out any whose real path (symlinks
    resolved) lies outside the folder: a source folder can only ever read its own files."""
    real = folder.resolve()
    return sorted(f for f in folder.iterdir() if f.is_file() and f.resolve().parent == real and keep(f))


def source_info(shape: Sequence[int], dtype: DTypeLike, fmt: str, path: Path,
                spacing: Sequence[float] = (1.0, 1.0, 1.0), origin: Sequence[float] = (0.0, 0.0, 0.0),
                units: str = "millimeter", space: str | None = None,
                direction: Any = None, **provenance: Any) -> SourceInfo:
    """`direction`: rows of (x, y, z) vectors in `space` for the array's x, y, z axes, of any length."""
    direction = _unit_rows(direction)
    return SourceInfo(
        shape=tuple(int(s) for s in shape),  # type: ignore[arg-type]
        dtype=np.dtype(dtype),
        spacing=tuple(float(s) for s in spacing),  # type: ignore[arg-type]
        origin=tuple(float(o) for o in origin),  # type: ignore[arg-type]
        units=units,
        format=fmt,
        provenance={"format": fmt, "path": str(path), "dtype": str(np.dtype(dtype)), **provenance},
        space=space if direction is not None else None,
        direction=direction,
    )


def finish(reader: Reader, spacing: Sequence[float] | None, origin: Sequence[float] | None,
           units: str | None = None) -> Reader:
    """Checks what every format shares (empty axes, dtype), settles the stored dtype and applies user overrides."""
    info = reader.info
    name = info.provenance["path"]
    if 0 in info.shape:
        raise SourceError(f"{name} is empty: shape {shape_text(info.shape)} has an axis of length 0")
    prov = dict(info.provenance)
    dtype = _store_dtype(reader, name)
    if dtype != info.dtype.newbyteorder("="):
        prov["converted_to"] = dtype.name
    if spacing is not None:
        spacing = _triple("spacing", spacing, positive=True)
        # the user said what the file did not: its warnings about a missing spacing no longer apply
        prov["warnings"] = [w for w in prov.get("warnings", []) if "spacing 1" not in w and "1 used" not in w]
        if not prov["warnings"]:
            del prov["warnings"]
    elif all(math.isfinite(s) and s > 0 for s in info.spacing):
        spacing = info.spacing
    elif not all(math.isfinite(s) for s in info.spacing):
        raise SourceError(f"{name}: file spacing (z, y, x) {list(info.spacing)} is not finite; set it with "
                          f"--spacing z,y,x (spacing= in Python)")
    else:  # headers with zero spacing exist; a unit step keeps the volume usable
        prov.setdefault("warnings", []).append(f"file spacing {list(info.spacing)} is not positive; 1 used instead")
        spacing = tuple(s if math.isfinite(s) and s > 0 else 1.0 for s in info.spacing)
    origin = _triple("origin", origin, positive=False) if origin is not None else info.origin
    if units is not None:
        if str(units) not in UNITS:
            raise SourceError(f"units {units!r}: expected one of {', '.join(sorted(UNITS))}")
        units = UNITS[str(units)]
    reader.info = dataclasses.replace(info, dtype=dtype, provenance=prov,
                                      spacing=spacing,  # type: ignore[arg-type]  # three numbers on every branch
                                      origin=origin, units=units or info.units)
    return reader


def _store_dtype(reader: Reader, name: str) -> np.dtype:
    dt = reader.info.dtype
    if dt.fields:
        raise SourceError(f"non-scalar data: {name} has voxels with fields {', '.join(dt.fields)}; "
                          f"expected one scalar per voxel")
    supported = ", ".join(d.name for d in SUPPORTED_DTYPES)
    if dt.kind not in "iuf":  # bool, complex, strings, objects, dates
        raise SourceError(f"unsupported dtype {dt} in {name}; expected one of {supported} "
                          f"(int64/uint64 when their values fit)")
    native = dt.newbyteorder("=")
    if native in SUPPORTED_DTYPES:
        return native
    if native == np.float16:  # float32 holds every float16 exactly
        return np.dtype(np.float32)
    if native.kind in "iu" and native.itemsize == 8:
        lo, hi = _value_range(reader)
        narrow = np.dtype(np.int32 if native.kind == "i" else np.uint32)
        if np.iinfo(narrow).min <= lo and hi <= np.iinfo(narrow).max:
            return narrow
        if -(2**53) <= lo and hi <= 2**53:
            return np.dtype(np.float64)
        raise SourceError(f"{name} holds {native} values from {lo} to {hi}, which neither {narrow} nor float64 "
                          f"(integers up to ±2^53) holds exactly")
    raise SourceError(f"unsupported dtype {dt} in {name}; expected one of {supported}")


def _value_range(reader: Reader) -> tuple[int, int]:
    lo, hi = None, None
    for z in range(0, reader.info.shape[0], _SLAB):
        s = reader._slab(z, min(z + _SLAB, reader.info.shape[0]))
        lo = int(s.min()) if lo is None else min(lo, int(s.min()))
        hi = int(s.max()) if hi is None else max(hi, int(s.max()))
    return lo, hi  # type: ignore[return-value]


def _triple(what: str, value: Sequence[float], positive: bool) -> tuple[float, float, float]:
    try:
        t = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise SourceError(f"{what} must be three numbers (z, y, x), got {value!r}") from None
    if len(t) != 3 or not all(math.isfinite(v) and (v > 0 or not positive) for v in t):
        need = "positive " if positive else "finite "
        raise SourceError(f"{what} must be three {need}numbers (z, y, x), got {value!r}")
    return t


def tidy(value: float) -> float:
    """A spacing computed from positions or direction vectors, without the last bits of rounding noise
    (1.0000000000000007 is 1.0)."""
    return float(f"{value:.12g}")


def shape_text(shape: Sequence[int]) -> str:
    return "x".join(str(int(s)) for s in shape)


def pick_volume(shape: Sequence[int], index: int | None, what: str) -> tuple[tuple[int, int, int, int], int]:
    """(t, z, y, x) and the chosen t for an array of 2 (one slice), 3 or 4 (t first) dimensions."""
    shape = tuple(int(s) for s in shape)
    if len(shape) == 4:
        if shape[0] == 1 and index is None:
            return shape, 0
        if index is None:
            raise SourceError(f"{what} is 4D ({shape_text(shape)}) with {shape[0]} volumes along its first axis; "
                              f"choose one with index=0..{shape[0] - 1}")
        if not 0 <= index < shape[0]:
            raise SourceError(f"index {index} is out of range: {what} has {shape[0]} volumes (0..{shape[0] - 1})")
        return shape, index
    if index is not None:
        raise SourceError(f"index {index} given but {what} is not a 4D series (shape {shape_text(shape)})")
    if len(shape) == 3:
        return (1,) + shape, 0
    if len(shape) == 2:
        return (1, 1) + shape, 0
    raise SourceError(f"{what} has {len(shape)} dimensions (shape {shape_text(shape)}); expected 3 (z, y, x), "
                      f"2 (one slice) or 4 with an index")


def read_exact(f: io.BufferedIOBase, out: np.ndarray, name: object) -> None:
    # `.data` is memoryview(array); numpy declares the buffer protocol (for memoryview()) only from Python 3.12
    view = out.reshape(-1).view(np.uint8).data
    got = 0
    while got < len(view):  # in pieces: decompressors hold a copy or two of what one call returns
        n = f.readinto(view[got:got + READ_CHUNK])
        if not n:
            raise SourceError(f"{name} ends early: {got} of the {len(view)} bytes wanted for a slab")
        got += n


def skip_bytes(f: io.BufferedIOBase, n: int, name: object) -> None:
    while n > 0:
        chunk = f.read(min(n, 1 << 20))
        if not chunk:
            raise SourceError(f"{name} ends {n} bytes before the data it should hold")
        n -= len(chunk)


def _unit_rows(direction: Any) -> tuple[tuple[float, float, float], ...] | None:
    """Three unit rows, or None for a geometry that says nothing usable (missing, partial, degenerate): then the
    index axes stay the world's."""
    if direction is None:
        return None
    d = np.asarray(direction, dtype=np.float64)
    if d.shape != (3, 3) or not np.isfinite(d).all() or not np.abs(d).max(axis=1).all():
        return None
    d = d / np.abs(d).max(axis=1)[:, None]  # first: squares of 1e200 overflow, of 1e-200 underflow
    d = d / np.linalg.norm(d, axis=1)[:, None]
    if abs(np.linalg.det(d)) < 0.5:  # two axes nearly along one direction
        return None
    return tuple(tuple(float(v) for v in row) for row in d)  # type: ignore[misc]
