"""Source readers for ingest: `open_source(path)` turns a file or folder into a `VolumeSource`.

Formats: NumPy .npy, raw, NRRD, NIfTI, TIFF (multi-page or a folder of slices), a DICOM series folder and
zarr / OME-Zarr. Every reader reads one z-slab per call and keeps nothing else: uncompressed files are read with
plain file reads (a long-lived memmap would leave every page it touched resident), gzip/bzip2 streams are read
forwards and restarted only when a caller goes back, DICOM and TIFF folders open only the slab's files.
"""
from __future__ import annotations

import abc
import bz2
import dataclasses
import gzip
import math
import re
import zlib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np

from lodcast.errors import SourceError, SourceNotFound
from lodcast.store.source import SUPPORTED_DTYPES, SourceInfo, VolumeSource

__all__ = ["open_source", "FORMATS"]

FORMATS = ("npy", "raw", "nrrd", "nifti", "tiff", "dicom", "zarr")
_ALIASES = {"nii": "nifti", "nhdr": "nrrd", "tif": "tiff", "dcm": "dicom", "ome-zarr": "zarr"}
_SLAB = 32  # ingest's block thickness, also the step of the 64-bit value scan
_READ_CHUNK = 64 << 10  # bytes per read call, so that a decompressor's temporaries stay small beside a slab
_WINDOW_BYTES = 16 << 20  # read window for Fortran-ordered files, whose z-slabs are scattered over the whole file
_UNITS = {"mm": "millimeter", "millimeter": "millimeter", "um": "micrometer", "µm": "micrometer",
          "\\u00B5m": "micrometer", "micron": "micrometer", "micrometer": "micrometer", "nm": "nanometer",
          "nanometer": "nanometer", "cm": "centimeter", "centimeter": "centimeter", "m": "meter", "meter": "meter"}


def open_source(path: str | Path, *, format: str | None = None, shape: Sequence[int] | None = None,
                dtype: Any = None, byte_order: str = "little", header_bytes: int = 0,
                spacing: Sequence[float] | None = None, origin: Sequence[float] | None = None,
                index: int | None = None) -> VolumeSource:
    """Open a volume for ingest. `format` is guessed from the extension or folder content when None; `shape`
    (z, y, x), `dtype`, `byte_order` ('little' or 'big') and `header_bytes` describe raw files; `spacing` and
    `origin` (z, y, x) override the file's; `index` picks one volume of a 4D series (time or channel axis).
    Raises SourceNotFound for a missing path and SourceError for anything that cannot be ingested."""
    p = Path(path)
    if not p.exists():
        raise SourceNotFound(f"source not found: {p}")
    fmt = _format_name(format) if format is not None else _guess_format(p, shape is not None or dtype is not None)
    if fmt != "raw" and (shape is not None or dtype is not None or header_bytes):
        raise SourceError(f"shape, dtype and header_bytes describe raw files only, but {p} is read as {fmt}")
    if fmt in ("npy", "raw", "nrrd", "nifti") and p.is_dir():
        raise SourceError(f"a {fmt} source must be a file, but {p} is a folder")
    if fmt == "zarr" and not p.is_dir():
        raise SourceError(f"a zarr source must be a folder (a .zarr store), but {p} is a file")
    if index is not None and (isinstance(index, bool) or not isinstance(index, (int, np.integer))):
        raise SourceError(f"index must be a whole number, got {index!r}")
    if fmt == "raw":
        reader: _Reader = _raw(p, shape, dtype, byte_order, header_bytes, index)
    else:
        reader = {"npy": _npy, "nrrd": _nrrd, "nifti": _NiftiReader, "tiff": _tiff, "dicom": _DicomReader,
                  "zarr": _ZarrReader}[fmt](p, index)
    try:
        return _finish(reader, spacing, origin)
    except BaseException:
        reader.close()
        raise


# --- common part ----------------------------------------------------------------------------------------------

class _Reader(VolumeSource):
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


def _info(shape: Sequence[int], dtype: np.dtype, fmt: str, path: Path, spacing: Sequence[float] = (1.0, 1.0, 1.0),
          origin: Sequence[float] = (0.0, 0.0, 0.0), units: str = "millimeter", **provenance: Any) -> SourceInfo:
    return SourceInfo(
        shape=tuple(int(s) for s in shape),  # type: ignore[arg-type]
        dtype=np.dtype(dtype),
        spacing=tuple(float(s) for s in spacing),  # type: ignore[arg-type]
        origin=tuple(float(o) for o in origin),  # type: ignore[arg-type]
        units=units,
        format=fmt,
        provenance={"format": fmt, "path": str(path), "dtype": str(np.dtype(dtype)), **provenance},
    )


def _finish(reader: _Reader, spacing: Sequence[float] | None, origin: Sequence[float] | None) -> _Reader:
    """Checks what every format shares (empty axes, dtype), settles the stored dtype and applies user overrides."""
    info = reader.info
    name = info.provenance["path"]
    if 0 in info.shape:
        raise SourceError(f"{name} is empty: shape {_fmt(info.shape)} has an axis of length 0")
    prov = dict(info.provenance)
    dtype = _store_dtype(reader, name)
    if dtype != info.dtype.newbyteorder("="):
        prov["converted_to"] = dtype.name
    if spacing is not None:
        spacing = _triple("spacing", spacing, positive=True)
    elif all(math.isfinite(s) and s > 0 for s in info.spacing):
        spacing = info.spacing
    else:  # headers with zero spacing exist; a unit step keeps the volume usable
        prov.setdefault("warnings", []).append(f"file spacing {list(info.spacing)} is not positive; 1 used instead")
        spacing = tuple(s if math.isfinite(s) and s > 0 else 1.0 for s in info.spacing)
    origin = _triple("origin", origin, positive=False) if origin is not None else info.origin
    reader.info = dataclasses.replace(info, dtype=dtype, provenance=prov, spacing=spacing, origin=origin)
    return reader


def _store_dtype(reader: _Reader, name: str) -> np.dtype:
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


def _value_range(reader: _Reader) -> tuple[int, int]:
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
    return t  # type: ignore[return-value]


def _tidy(value: float) -> float:
    """A spacing computed from positions or direction vectors, without the last bits of rounding noise
    (1.0000000000000007 is 1.0)."""
    return float(f"{value:.12g}")


def _fmt(shape: Sequence[int]) -> str:
    return "x".join(str(int(s)) for s in shape)


def _pick(shape: Sequence[int], index: int | None, what: str) -> tuple[tuple[int, int, int, int], int]:
    """(t, z, y, x) and the chosen t for an array of 2 (one slice), 3 or 4 (t first) dimensions."""
    shape = tuple(int(s) for s in shape)
    if len(shape) == 4:
        if shape[0] == 1 and index is None:
            return shape, 0  # type: ignore[return-value]
        if index is None:
            raise SourceError(f"{what} is 4D ({_fmt(shape)}) with {shape[0]} volumes along its first axis; "
                              f"choose one with index=0..{shape[0] - 1}")
        if not 0 <= index < shape[0]:
            raise SourceError(f"index {index} is out of range: {what} has {shape[0]} volumes (0..{shape[0] - 1})")
        return shape, index  # type: ignore[return-value]
    if index is not None:
        raise SourceError(f"index {index} given but {what} is not a 4D series (shape {_fmt(shape)})")
    if len(shape) == 3:
        return (1,) + shape, 0  # type: ignore[return-value]
    if len(shape) == 2:
        return (1, 1) + shape, 0  # type: ignore[return-value]
    raise SourceError(f"{what} has {len(shape)} dimensions (shape {_fmt(shape)}); expected 3 (z, y, x), "
                      f"2 (one slice) or 4 with an index")


def _read_exact(f: IO[bytes], out: np.ndarray, name: object) -> None:
    view = memoryview(out.reshape(-1).view(np.uint8))
    got = 0
    while got < len(view):  # in pieces: decompressors hold a copy or two of what one call returns
        n = f.readinto(view[got:got + _READ_CHUNK])
        if not n:
            raise SourceError(f"{name} ends early: {got} of the {len(view)} bytes wanted for a slab")
        got += n


def _skip(f: IO[bytes], n: int, name: object) -> None:
    while n > 0:
        chunk = f.read(min(n, 1 << 20))
        if not chunk:
            raise SourceError(f"{name} ends {n} bytes before the data it should hold")
        n -= len(chunk)


# --- uncompressed and compressed arrays in a file (npy, raw, NRRD) ----------------------------------------------

class _BinaryReader(_Reader):
    """A (t, z, y, x) array stored uncompressed at `offset`, in C or Fortran order."""

    def __init__(self, path: Path, offset: int, shape4: tuple[int, int, int, int], dtype: np.dtype,
                 fortran: bool, index: int, info: SourceInfo) -> None:
        self._path, self._offset, self._shape4, self._dtype = path, offset, shape4, dtype
        self._fortran, self._index, self.info = fortran, index, info

    def _slab(self, z0: int, z1: int) -> np.ndarray:
        t, depth, ny, nx = self._shape4
        out = np.empty((z1 - z0, ny, nx), self._dtype)
        item = self._dtype.itemsize
        with open(self._path, "rb") as f:
            if not self._fortran:
                f.seek(self._offset + (self._index * depth + z0) * ny * nx * item)
                _read_exact(f, out, self._path)
                return out
            plane = t * depth * ny  # x is the slowest axis: one x holds every t, z, y
            step = max(1, _WINDOW_BYTES // (plane * item))
            for x0 in range(0, nx, step):
                x1 = min(nx, x0 + step)
                window = np.empty((x1 - x0, ny, depth, t), self._dtype)
                f.seek(self._offset + x0 * plane * item)
                _read_exact(f, window, self._path)
                out[:, :, x0:x1] = window[:, :, z0:z1, self._index].transpose(2, 1, 0)
        return out


class _StreamReader(_Reader):
    """A C-ordered (t, z, y, x) array in a forward-only stream (gzip, bzip2). `start` opens the file and returns it
    with the decompressed stream positioned at the first voxel."""

    def __init__(self, start: Callable[[], tuple[IO[bytes], IO[bytes]]], name: str,
                 shape4: tuple[int, int, int, int], dtype: np.dtype, index: int, info: SourceInfo) -> None:
        self._start, self._name, self._shape4, self._dtype, self._index = start, name, shape4, dtype, index
        self.info = info
        self._files: tuple[IO[bytes], IO[bytes]] | None = None
        self._pos = 0

    def _slab(self, z0: int, z1: int) -> np.ndarray:
        _, depth, ny, nx = self._shape4
        target = (self._index * depth + z0) * ny * nx * self._dtype.itemsize
        out = np.empty((z1 - z0, ny, nx), self._dtype)
        try:
            if self._files is None or target < self._pos:
                self.close()
                self._files, self._pos = self._start(), 0
            stream = self._files[0]
            _skip(stream, target - self._pos, self._name)
            _read_exact(stream, out, self._name)
        except (OSError, EOFError, zlib.error) as exc:
            raise SourceError(f"{self._name} is corrupt: {exc}") from None
        self._pos = target + out.nbytes
        return out

    def close(self) -> None:
        if self._files is not None:
            for f in self._files:
                f.close()
            self._files = None


def _npy(path: Path, index: int | None) -> _Reader:
    try:
        mm = np.load(path, mmap_mode="r", allow_pickle=False)
    except ValueError as exc:
        if "Python objects" in str(exc):
            raise SourceError(f"unsupported dtype object in {path}; expected a numeric array") from None
        raise SourceError(f"{path} is not a readable .npy file: {exc}") from None
    except (OSError, EOFError) as exc:
        raise SourceError(f"{path} is not a readable .npy file: {exc}") from None
    if not isinstance(mm, np.memmap):
        raise SourceError(f"{path} is not a single .npy array (an .npz archive?)")
    shape4, t = _pick(mm.shape, index, str(path))
    # only the header is used: the slab reads are plain file reads
    offset, dtype, fortran = mm.offset, mm.dtype, mm.ndim > 1 and mm.flags.f_contiguous and not mm.flags.c_contiguous
    del mm
    info = _info(shape4[1:], dtype, "npy", path, **({"index": t} if index is not None else {}))
    if fortran:
        info.provenance["order"] = "F"
    return _BinaryReader(path, offset, shape4, dtype, fortran, t, info)


def _raw(path: Path, shape: Sequence[int] | None, dtype: Any, byte_order: str, header_bytes: int,
         index: int | None) -> _Reader:
    if shape is None or dtype is None:
        raise SourceError(f"raw file {path} needs its shape (z, y, x) and dtype "
                          f"(on the command line: --shape z,y,x --dtype uint16)")
    try:
        dims = tuple(int(s) for s in shape)
        dt = np.dtype(dtype)
    except (TypeError, ValueError) as exc:
        raise SourceError(f"raw file {path}: bad shape {shape!r} or dtype {dtype!r} ({exc})") from None
    if any(d < 0 for d in dims):
        raise SourceError(f"raw file {path}: shape {shape!r} has a negative axis")
    orders = {"little": "<", "big": ">", "<": "<", ">": ">"}
    if byte_order not in orders:
        raise SourceError(f"byte_order must be 'little' or 'big', got {byte_order!r}")
    if header_bytes < 0:
        raise SourceError(f"header_bytes must be 0 or more, got {header_bytes}")
    dt = dt.newbyteorder(orders[byte_order])
    shape4, t = _pick(dims, index, f"raw file {path}")
    size, need = path.stat().st_size, header_bytes + math.prod(dims) * dt.itemsize
    if size != need:
        head = f" ({header_bytes}-byte header + {need - header_bytes} bytes of voxels)" if header_bytes else ""
        raise SourceError(f"raw file is {size} bytes but shape {_fmt(dims)} of {dt.name} needs {need} bytes{head}")
    info = _info(shape4[1:], dt, "raw", path, byte_order=byte_order, header_bytes=header_bytes)
    return _BinaryReader(path, header_bytes, shape4, dt, False, t, info)


# --- NRRD -------------------------------------------------------------------------------------------------------

_NRRD_SPATIAL = ("domain", "space", "time", "???", "none")


def _nrrd(path: Path, index: int | None) -> _Reader:
    import nrrd

    try:
        with open(path, "rb") as f:
            header = nrrd.read_header(f)
            data_start = f.tell()
        dtype = nrrd.reader._determine_datatype(header)  # pynrrd's own type table (with endian)
        sizes, encoding = [int(s) for s in header["sizes"]], str(header["encoding"]).lower()
    except (nrrd.NRRDError, OSError, ValueError, KeyError, UnicodeDecodeError, StopIteration) as exc:
        raise SourceError(f"{path} is not a readable NRRD file: {exc!s}") from None
    kinds = [str(k).lower() for k in header.get("kinds", ["domain"] * len(sizes))]
    # components of a non-spatial kind (vector, RGB-color, list…) on the slowest axis are whole volumes one after
    # another, which index can pick; anywhere else they are interleaved per voxel: non-scalar data
    last = len(sizes) - 1
    for axis, (size, kind) in enumerate(zip(sizes, kinds)):
        if size > 1 and kind not in _NRRD_SPATIAL and axis != last:
            raise SourceError(f"non-scalar data: NRRD axis {axis} of {path} is '{kind}' of size {size}; "
                              f"expected scalar data")
    keep = [a for a, kind in enumerate(kinds) if kind in _NRRD_SPATIAL or (a == last and sizes[a] > 1)]
    if len(keep) == 4 and sizes[keep[3]] == 1:
        keep = keep[:3]
    if any(kinds[a] == "time" for a in keep[:3]):
        raise SourceError(f"NRRD file {path} has its time axis among the first three (kinds {kinds}); expected it last")
    # NRRD lists the fastest axis first: sizes (x, y, z, t) are a C-ordered (t, z, y, x) array
    shape4, t = _pick([sizes[a] for a in reversed(keep)], index, f"NRRD file {path}")

    spatial = keep[:3]
    directions = header.get("space directions")
    provenance: dict[str, Any] = {"space": header.get("space"), "encoding": encoding}
    origin = [0.0, 0.0, 0.0]
    if directions is not None:
        d = np.asarray([directions[a] for a in spatial], dtype=float)
        spacing = [_tidy(v) for v in np.linalg.norm(d, axis=1)]
        provenance["space_directions"] = d.tolist()
        o = header.get("space origin")
        if o is not None:
            provenance["space_origin"] = [float(v) for v in o]
            if d.shape == (3, 3) and _axis_aligned(d):
                origin = [float(v) for v in o]
    else:
        spacing = [float(header.get("spacings", [1.0] * len(sizes))[a]) for a in spatial]
    spacing += [1.0] * (3 - len(spacing))  # a 2D image is one slice of unit thickness
    units = header.get("space units")
    info = _info(shape4[1:], dtype, "nrrd", path, spacing=spacing[::-1], origin=origin[::-1],
                 units=_UNITS.get(str(units[0]), "millimeter") if units else "millimeter", **provenance)

    data_path, start = path, data_start
    if "data file" in header or "datafile" in header:
        name = str(header.get("data file", header.get("datafile")))
        if name.startswith("LIST") or " " in name:
            raise SourceError(f"NRRD {path} splits its data over several files ({name!r}); expected one data file")
        data_path, start = path.parent / name, 0
        if not data_path.is_file():
            raise SourceError(f"data file {data_path} named by NRRD header {path} does not exist")
    with open(data_path, "rb") as f:
        f.seek(start)
        for _ in range(int(header.get("line skip", header.get("lineskip", 0)))):
            f.readline()
        start = f.tell()
    byte_skip = int(header.get("byte skip", header.get("byteskip", 0)))
    nbytes = math.prod(sizes) * dtype.itemsize
    if encoding == "raw":
        offset = data_path.stat().st_size - nbytes if byte_skip == -1 else start + byte_skip
        if offset < 0 or data_path.stat().st_size < offset + nbytes:
            raise SourceError(f"NRRD data in {data_path} is {data_path.stat().st_size - max(offset, 0)} bytes but "
                              f"sizes {_fmt(sizes)} of {dtype.name} need {nbytes}")
        return _BinaryReader(data_path, offset, shape4, dtype, False, t, info)
    decompress = {"gzip": _gunzip, "gz": _gunzip, "bzip2": bz2.BZ2File, "bz2": bz2.BZ2File}.get(encoding)
    if decompress is None:
        raise SourceError(f"NRRD encoding '{encoding}' of {path} is not supported; expected raw, gzip or bzip2")
    if byte_skip < 0:
        raise SourceError(f"NRRD {path}: byte skip {byte_skip} with {encoding} encoding is not supported; "
                          f"expected 0 or more")

    def opened() -> tuple[IO[bytes], IO[bytes]]:
        raw = open(data_path, "rb")
        raw.seek(start)
        stream = decompress(raw)
        _skip(stream, byte_skip, data_path)
        return stream, raw

    return _StreamReader(opened, str(data_path), shape4, dtype, t, info)


def _gunzip(f: IO[bytes]) -> IO[bytes]:
    return gzip.GzipFile(fileobj=f, mode="rb")  # type: ignore[return-value]


def _axis_aligned(m: np.ndarray) -> bool:
    """Whether the rows of `m` point along +x, +y, +z: then index × spacing + origin is the world position."""
    diag = np.diag(m)
    return bool(np.all(diag > 0) and np.allclose(m, np.diag(diag), atol=1e-6 * float(np.abs(diag).max())))


# --- NIfTI ------------------------------------------------------------------------------------------------------

_NIFTI_VECTOR_INTENTS = {"vector", "displacement vector", "rgb vector", "rgba vector", "quaternion",
                         "symmetric matrix", "general matrix", "pointset", "triangle", "fnirt disp field"}


class _NiftiReader(_Reader):
    """NIfTI-1/2 (and Analyze) through nibabel. Data axes (i, j, k) are the store's (x, y, z): no reorientation, so
    the store is exactly `transpose(data, (2, 1, 0))`. The proxy keeps its file open so that a .gz reads forwards."""

    def __init__(self, path: Path, index: int | None) -> None:
        import nibabel as nib

        try:
            img = nib.load(str(path), keep_file_open=True)
            ondisk = img.get_data_dtype()
        except Exception as exc:  # nibabel raises many types for files it cannot parse
            raise SourceError(f"{path} is not a readable NIfTI file: {exc}") from None
        shape = list(img.shape)
        while len(shape) > 3 and shape[-1] == 1:
            shape.pop()
        intent = img.header.get_intent()[0] if hasattr(img.header, "get_intent") else "none"
        if len(shape) > 4 or len(shape) < 2:
            raise SourceError(f"NIfTI file {path} has {len(shape)} dimensions (shape {_fmt(shape)}, intent {intent}); "
                              f"expected a scalar 3D volume, or 4D with an index")
        if len(shape) == 4 and intent in _NIFTI_VECTOR_INTENTS:
            raise SourceError(f"non-scalar data: NIfTI file {path} is 4D with intent '{intent}'; expected scalar data")
        # nibabel's order is (x, y, z, t); _pick wants t first
        shape4, t = _pick([shape[3], *shape[2::-1]] if len(shape) == 4 else shape[::-1], index, f"NIfTI file {path}")
        self._proxy = img.dataobj
        # a chosen t, then 0 for the trailing singleton axes dropped above
        self._tail = ((t,) if len(shape) == 4 else ()) + (0,) * (len(img.shape) - len(shape))
        self._flat = len(shape) == 2
        self._path = path
        slope, inter = float(getattr(self._proxy, "slope", 1.0)), float(getattr(self._proxy, "inter", 0.0))
        scaled = (slope, inter) != (1.0, 0.0)
        zooms = [float(z) for z in img.header.get_zooms()[:3]] + [1.0] * (3 - min(3, len(shape)))
        affine = np.asarray(img.affine, dtype=float)
        origin = affine[:3, 3][::-1] if _axis_aligned(affine[:3, :3]) else (0.0, 0.0, 0.0)
        units = img.header.get_xyzt_units()[0] if hasattr(img.header, "get_xyzt_units") else "unknown"
        provenance: dict[str, Any] = {"affine": affine.tolist(), "intent": intent}
        if scaled:
            provenance["scaling"] = {"slope": slope, "intercept": inter}
        if index is not None:
            provenance["index"] = t
        self.info = _info(shape4[1:], np.float32 if scaled else ondisk, "nifti", path, spacing=zooms[::-1],
                          origin=origin, units=_UNITS.get(units, "millimeter"), **provenance)
        self.info.provenance["dtype"] = str(ondisk)

    def _slab(self, z0: int, z1: int) -> np.ndarray:
        out = np.empty((z1 - z0, *self.info.shape[1:]), self.info.dtype)
        # nibabel holds a few copies of what it reads (compressed bytes, scaled float64): ask for pieces of a
        # slab so that those stay small beside it
        step = max(1, _READ_CHUNK // out[0].nbytes)
        try:
            if self._flat:
                out[0] = np.asarray(self._proxy[:, :]).T
                return out
            for z in range(z0, z1, step):
                piece = self._proxy[(slice(None), slice(None), slice(z, min(z + step, z1))) + self._tail]
                out[z - z0:z - z0 + piece.shape[2]] = np.asarray(piece).transpose(2, 1, 0)
        except (OSError, EOFError, ValueError, zlib.error) as exc:
            raise SourceError(f"NIfTI data of {self._path} is corrupt or truncated: {exc}") from None
        return out

    def close(self) -> None:
        self._proxy = None  # the proxy closes the file it kept open when it goes


# --- TIFF -------------------------------------------------------------------------------------------------------

def _tiff(path: Path, index: int | None) -> _Reader:
    return _TiffFolderReader(path, index) if path.is_dir() else _TiffFileReader(path, index)


def _tiff_geometry(tif: Any) -> dict[str, Any]:
    """Spacing and units from ImageJ metadata (z `spacing`, y/x from the resolution tags); none otherwise."""
    meta = tif.imagej_metadata if tif.is_imagej else None
    if not meta:
        return {}
    xres, yres = tif.pages[0].resolution
    spacing = (float(meta.get("spacing", 1.0)), 1.0 / yres if yres > 0 else 1.0, 1.0 / xres if xres > 0 else 1.0)
    return {"spacing": spacing, "units": _UNITS.get(str(meta.get("unit", "")), "millimeter")}


def _open_tiff(path: Path) -> Any:
    import tifffile

    try:
        return tifffile.TiffFile(path)
    except Exception as exc:  # tifffile raises many types for files it cannot parse
        raise SourceError(f"{path} is not a readable TIFF file: {exc}") from None


class _TiffFileReader(_Reader):
    """A multi-page TIFF: pages are z. ImageJ hyperstacks (TZYX, ZCYX…) take z from the Z axis and the other
    non-singleton axis from `index`. Read through tifffile's zarr view, which also serves ImageJ files whose
    pages after the first are not indexed."""

    def __init__(self, path: Path, index: int | None) -> None:
        import zarr

        self._tif = _open_tiff(path)
        try:
            series, page = self._tif.series[0], self._tif.pages[0]
            axes, shape = series.axes, series.shape
            if "S" in axes or page.samplesperpixel > 1:
                raise SourceError(f"non-scalar data: {path} is {page.photometric.name} with {page.samplesperpixel} "
                                  f"samples per pixel; expected one (grayscale)")
            lead = [a for a in range(len(shape) - 2) if shape[a] > 1]
            if len(lead) > 2:
                raise SourceError(f"{path} has axes {axes} of sizes {_fmt(shape)}; expected z plus at most one "
                                  f"time or channel axis")
            z_axis = next((a for a in lead if axes[a] == "Z"), lead[-1] if lead else None)
            stack = [a for a in lead if a != z_axis]
            shape4, t = _pick([shape[a] for a in stack] + [shape[z_axis] if lead else 1, *shape[-2:]], index, str(path))
            self._select: list[Any] = [t if a in stack else 0 for a in range(len(shape) - 2)]
            self._z_axis = z_axis
            self._array = zarr.open(self._tif.aszarr(series=0), mode="r")
            self.info = _info(shape4[1:], series.dtype, "tiff", path, axes=axes, **_tiff_geometry(self._tif))
        except BaseException:
            self._tif.close()
            raise

    def _slab(self, z0: int, z1: int) -> np.ndarray:
        select = list(self._select)
        if self._z_axis is not None:
            select[self._z_axis] = slice(z0, z1)
        return np.asarray(self._array[tuple(select)]).reshape((z1 - z0,) + self.info.shape[1:])

    def close(self) -> None:
        self._tif.close()


def _natural(p: Path) -> list[Any]:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", p.name)]


def _single_image(f: Path, folder: Path) -> tuple[tuple[int, ...], np.dtype, dict[str, Any]]:
    with _open_tiff(f) as tif:
        page = tif.pages[0]
        if page.samplesperpixel > 1:
            raise SourceError(f"non-scalar data: {f} has {page.samplesperpixel} samples per pixel; "
                              f"expected one (grayscale)")
        if len(tif.pages) > 1:
            raise SourceError(f"TIFF folder {folder} holds {f.name} with {len(tif.pages)} pages; "
                              f"expected one image per file")
        return tuple(page.shape), np.dtype(page.dtype), _tiff_geometry(tif)


class _TiffFolderReader(_Reader):
    """A folder of single-image TIFFs, one slice each, in natural name order (img2 before img10)."""

    def __init__(self, path: Path, index: int | None) -> None:
        self._files = sorted((f for f in path.iterdir() if f.suffix.lower() in (".tif", ".tiff") and f.is_file()),
                             key=_natural)
        if not self._files:
            raise SourceError(f"no .tif/.tiff files in folder {path}")
        if index is not None:
            raise SourceError(f"index {index} given but TIFF folder {path} is a single 3D volume")
        shape, dtype, geometry = _single_image(self._files[0], path)
        for f in self._files[1:]:
            other = _single_image(f, path)
            if other[:2] != (shape, dtype):
                raise SourceError(f"TIFF folder {path} has inconsistent images: {self._files[0].name} is "
                                  f"{_fmt(shape)} {dtype} but {f.name} is {_fmt(other[0])} {other[1]}")
        self.info = _info((len(self._files), *shape), dtype, "tiff", path, files=len(self._files), **geometry)

    def _slab(self, z0: int, z1: int) -> np.ndarray:
        import tifffile

        return np.stack([tifffile.imread(f).reshape(self.info.shape[1:]) for f in self._files[z0:z1]])


# --- DICOM ------------------------------------------------------------------------------------------------------

def _is_dicom(p: Path) -> bool:
    try:
        with open(p, "rb") as f:
            return f.read(132)[128:] == b"DICM"
    except OSError:
        return False


_PIXEL_DTYPES = {(8, 0): np.uint8, (8, 1): np.int8, (16, 0): np.uint16, (16, 1): np.int16,
                 (32, 0): np.uint32, (32, 1): np.int32}


_DICOM_KEYWORDS = ("SeriesInstanceUID", "Rows", "Columns", "SamplesPerPixel", "PhotometricInterpretation",
                   "NumberOfFrames", "BitsAllocated", "BitsStored", "PixelRepresentation", "PixelSpacing",
                   "SliceThickness", "SpacingBetweenSlices", "ImagePositionPatient", "ImageOrientationPatient",
                   "InstanceNumber", "RescaleSlope", "RescaleIntercept", "Modality", "SeriesDescription")


def _dicom_header(f: Path) -> dict[str, Any]:
    """The few header fields a series needs: a whole pydicom header is tens of kB, times thousands of slices."""
    import pydicom

    try:
        ds = pydicom.dcmread(f, stop_before_pixels=True)
        header = {k: ds.get(k) for k in _DICOM_KEYWORDS if ds.get(k) is not None}
        syntax = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
        header["compressed"] = syntax is None or syntax.is_compressed
    except Exception as exc:  # pydicom raises many types on corrupt files
        raise SourceError(f"unreadable DICOM file {f}: {exc}") from None
    return header


def _dicom_image(f: Path, ds: dict[str, Any]) -> tuple[int, int, int, int]:
    """(rows, columns, bits allocated, pixel representation) of one grayscale single-frame file."""
    if "Rows" not in ds or "Columns" not in ds:
        raise SourceError(f"unreadable DICOM file {f}: no Rows/Columns (corrupt, or not an image)")
    samples = int(ds.get("SamplesPerPixel", 1))
    if samples != 1:
        raise SourceError(f"non-scalar data: DICOM file {f} is {ds.get('PhotometricInterpretation', '?')} with "
                          f"{samples} samples per pixel; expected one (grayscale)")
    if int(ds.get("NumberOfFrames", 1) or 1) > 1:
        raise SourceError(f"DICOM file {f} holds {ds['NumberOfFrames']} frames; expected one slice per file")
    rows, cols, bits = int(ds["Rows"]), int(ds["Columns"]), int(ds.get("BitsAllocated", 16))
    need = rows * cols * bits // 8
    if not ds["compressed"] and f.stat().st_size < need:
        raise SourceError(f"DICOM file {f} is truncated: {f.stat().st_size} bytes, but its {rows}x{cols} pixels "
                          f"of {bits} bits need {need}")
    return rows, cols, bits, int(ds.get("PixelRepresentation", 0))


class _DicomReader(_Reader):
    """One DICOM series: a folder of single-frame files (or one file) with its slices sorted along the slice
    normal. Headers are read once; pixels only for the slab asked for. RescaleSlope/Intercept are applied."""

    def __init__(self, path: Path, index: int | None) -> None:
        if index is not None:
            raise SourceError(f"index {index} given but DICOM series {path} is a single 3D volume")
        files = [path] if path.is_file() else sorted(f for f in path.iterdir() if f.is_file() and _is_dicom(f))
        if not files or not _is_dicom(files[0]):
            raise SourceError(f"no DICOM files (with a DICM preamble) in {path}")
        by_series: dict[str, list[tuple[Path, dict[str, Any]]]] = {}
        for f in files:
            header = _dicom_header(f)
            by_series.setdefault(str(header.get("SeriesInstanceUID", "")), []).append((f, header))
        uid = max(sorted(by_series), key=lambda u: len(by_series[u]))
        slices = by_series[uid]
        provenance: dict[str, Any] = {"series_uid": uid, "warnings": []}
        if len(by_series) > 1:
            provenance["other_series"] = {u: len(v) for u, v in by_series.items() if u != uid}
            provenance["warnings"].append(f"{len(by_series)} series in {path}; "
                                          f"kept the largest, {uid} ({len(slices)} files)")
        ny, nx, pixel_dtype = self._check_images(slices)
        slices, dz, origin = self._sort(slices, provenance)
        self._files = [f for f, _ in slices]
        self._rescale = [(float(ds.get("RescaleSlope", 1) or 1), float(ds.get("RescaleIntercept", 0) or 0))
                         for _, ds in slices]
        dtype = self._rescaled_dtype(pixel_dtype, int(slices[0][1].get("BitsStored", pixel_dtype.itemsize * 8)))
        if dtype != pixel_dtype:
            provenance["scaling"] = {"slope": sorted({s for s, _ in self._rescale}),
                                     "intercept": sorted({i for _, i in self._rescale})}
        first = slices[0][1]
        pixel_spacing = first.get("PixelSpacing")
        if pixel_spacing is None:
            provenance["warnings"].append("no PixelSpacing; y and x spacing taken as 1")
            pixel_spacing = (1.0, 1.0)
        for key in ("Modality", "SeriesDescription"):
            if key in first:
                provenance[key.lower()] = str(first.get(key))
        if not provenance["warnings"]:
            del provenance["warnings"]
        # PixelSpacing is (between rows, between columns) = (y, x)
        self.info = _info((len(slices), ny, nx), dtype, "dicom", path, spacing=(dz, *map(float, pixel_spacing)),
                          origin=origin, **provenance)
        self.info.provenance["dtype"] = pixel_dtype.name

    @staticmethod
    def _check_images(slices: list[tuple[Path, dict[str, Any]]]) -> tuple[int, int, np.dtype]:
        """Rows, columns and pixel type, the same in every file of the series."""
        first = _dicom_image(*slices[0])
        for f, ds in slices[1:]:
            image = _dicom_image(f, ds)
            if image != first:
                raise SourceError(f"DICOM series has inconsistent images: {slices[0][0].name} is {first[0]}x{first[1]} "
                                  f"of {first[2]} bits but {f.name} is {image[0]}x{image[1]} of {image[2]} bits")
        if (first[2], first[3]) not in _PIXEL_DTYPES:
            raise SourceError(f"DICOM file {slices[0][0]} has {first[2]}-bit pixels; expected 8, 16 or 32")
        return first[0], first[1], np.dtype(_PIXEL_DTYPES[first[2], first[3]])

    @staticmethod
    def _sort(slices: list[tuple[Path, dict[str, Any]]], provenance: dict[str, Any]
              ) -> tuple[list[tuple[Path, dict[str, Any]]], float, tuple[float, float, float]]:
        """Slices in order along the normal of their orientation, z spacing and origin (z, y, x)."""
        first = slices[0][1]
        thickness = float(first.get("SpacingBetweenSlices", first.get("SliceThickness", 1.0)) or 1.0)
        if not all("ImagePositionPatient" in ds and "ImageOrientationPatient" in ds for _, ds in slices):
            provenance["warnings"].append("slices lack ImagePositionPatient/ImageOrientationPatient; "
                                          f"sorted by InstanceNumber, z spacing {thickness} from the header")
            return sorted(slices, key=lambda s: int(s[1].get("InstanceNumber", 0) or 0)), thickness, (0.0, 0.0, 0.0)
        orientation = np.array([float(v) for v in first["ImageOrientationPatient"]])
        for f, ds in slices:
            if not np.allclose([float(v) for v in ds["ImageOrientationPatient"]], orientation, atol=1e-4):
                raise SourceError(f"DICOM series mixes slice orientations: {f.name} differs from {slices[0][0].name}")
        normal = np.cross(orientation[:3], orientation[3:])
        placed = sorted(((float(np.dot([float(v) for v in ds["ImagePositionPatient"]], normal)), f.name, f, ds)
                         for f, ds in slices), key=lambda s: s[:2])
        slices = [(f, ds) for _, _, f, ds in placed]
        depth = [d for d, *_ in placed]
        steps = np.diff(depth)
        if len(steps) and steps.min() <= 1e-6 * max(1.0, abs(steps.max())):
            where = int(np.argmin(steps))
            raise SourceError(f"DICOM series has two slices at position {depth[where]:g} mm ({slices[where][0].name}, "
                              f"{slices[where + 1][0].name}); expected one slice per position")
        dz = _tidy(float(steps.mean())) if len(steps) else thickness
        if len(steps) and np.abs(steps - dz).max() > 0.01 * dz:
            provenance["warnings"].append(f"slice positions are not evenly spaced ({steps.min():g} to "
                                          f"{steps.max():g} mm); z spacing {thickness} taken from the header")
            dz = thickness
        ipp = [float(v) for v in slices[0][1]["ImagePositionPatient"]]
        provenance["orientation"] = orientation.tolist()
        provenance["first_position"] = ipp
        # world (z, y, x) = index × spacing + origin holds only when rows run along +x, columns along +y
        aligned = np.allclose(orientation, [1, 0, 0, 0, 1, 0], atol=1e-4)
        return slices, dz, (ipp[2], ipp[1], ipp[0]) if aligned else (0.0, 0.0, 0.0)

    def _rescaled_dtype(self, pixel: np.dtype, bits_stored: int) -> np.dtype:
        """The stored pixels' type when nothing is rescaled; else the smallest of int16/int32 that holds every
        rescaled value when slopes and intercepts are whole (CT Hounsfield units), float32 otherwise."""
        if all(r == (1.0, 0.0) for r in self._rescale):
            return pixel
        signed = pixel.kind == "i"
        lo, hi = (-(2 ** (bits_stored - 1)), 2 ** (bits_stored - 1) - 1) if signed else (0, 2**bits_stored - 1)
        if all(s.is_integer() and i.is_integer() for s, i in self._rescale):
            ends = [v for s, i in self._rescale for v in (s * lo + i, s * hi + i)]
            for candidate in (np.int16, np.int32):
                if np.iinfo(candidate).min <= min(ends) and max(ends) <= np.iinfo(candidate).max:
                    return np.dtype(candidate)
        return np.dtype(np.float32)

    def _slab(self, z0: int, z1: int) -> np.ndarray:
        import pydicom

        out = np.empty((z1 - z0, *self.info.shape[1:]), self.info.dtype)
        for k in range(z0, z1):
            f = self._files[k]
            try:
                pixels = pydicom.dcmread(f).pixel_array
            except Exception as exc:  # decoding errors come from pydicom and its image plugins
                raise SourceError(f"cannot decode the pixels of DICOM file {f}: {exc}") from None
            if pixels.shape != self.info.shape[1:]:
                raise SourceError(f"DICOM file {f} has pixels of shape {_fmt(pixels.shape)}; "
                                  f"expected {_fmt(self.info.shape[1:])}")
            slope, intercept = self._rescale[k]
            out[k - z0] = pixels if (slope, intercept) == (1.0, 0.0) else pixels * slope + intercept
        return out


# --- zarr / OME-Zarr --------------------------------------------------------------------------------------------

class _ZarrReader(_Reader):
    """A plain 2D/3D/4D zarr array, or an OME-Zarr 0.4/0.5 image group (a lodcast store is one): its first
    dataset, scaled and translated as its coordinate transformations say, singleton t/c axes dropped."""

    def __init__(self, path: Path, index: int | None) -> None:
        import zarr

        try:
            node = zarr.open(store=str(path), mode="r")
        except Exception as exc:  # zarr raises several types for folders that are not stores
            raise SourceError(f"{path} is not a readable zarr store: {exc}") from None
        provenance: dict[str, Any] = {}
        if isinstance(node, zarr.Array):
            array, image, dataset = node, None, None
            names = {2: "yx", 3: "zyx", 4: "tzyx"}.get(array.ndim) or _pick(array.shape, index, f"zarr array {path}")
            axes: list[dict[str, Any]] = [{"name": n} for n in names]
        else:
            ome = dict(node.attrs)
            ome = ome.get("ome", ome)  # 0.5 nests its metadata under "ome", 0.4 does not
            multiscales = ome.get("multiscales") if isinstance(ome, dict) else None
            if not multiscales:
                raise SourceError(f"zarr group {path} has no OME-Zarr 'multiscales' metadata; expected a zarr array "
                                  f"or an OME-Zarr image")
            image, dataset = multiscales[0], multiscales[0]["datasets"][0]
            try:
                array = node[dataset["path"]]
            except KeyError:
                raise SourceError(f"OME-Zarr {path} names dataset '{dataset['path']}', which does not exist") from None
            axes = [a if isinstance(a, dict) else {"name": a} for a in image.get("axes", [])] or \
                [{"name": n} for n in "tczyx"[-array.ndim:]]
            provenance.update(ome_version=str(ome.get("version", image.get("version", ""))),
                              dataset=str(dataset["path"]))
        spatial = [k for k, a in enumerate(axes) if a.get("type") == "space" or a["name"] in ("z", "y", "x")]
        lead = array.ndim - len(spatial)
        if len(axes) != array.ndim or len(spatial) not in (2, 3) or spatial != list(range(lead, array.ndim)):
            raise SourceError(f"zarr {path} has axes {[a['name'] for a in axes]} for shape {_fmt(array.shape)}; "
                              f"expected z, y, x (or y, x) after at most a t and a c axis")
        stacks = [k for k in range(lead) if array.shape[k] > 1]
        if len(stacks) > 1:
            raise SourceError(f"zarr {path} has axes {[a['name'] for a in axes]} of sizes {_fmt(array.shape)}; "
                              f"expected at most one non-singleton t or c axis (chosen by index)")
        shape4, t = _pick([array.shape[k] for k in stacks] + list(array.shape[lead:]), index, f"zarr {path}")
        self._array, self._select, self._flat = array, [t if k in stacks else 0 for k in range(lead)], len(spatial) == 2
        spacing, origin, units = [1.0] * 3, [0.0] * 3, "millimeter"
        if image is not None:
            scale, translation = _ome_transform(dataset, image, array.ndim)
            pad = 3 - len(spatial)  # a 2D image is one slice of unit thickness
            spacing, origin = [1.0] * pad + [scale[k] for k in spatial], [0.0] * pad + [translation[k] for k in spatial]
            unit = axes[spatial[-1]].get("unit")
            units = _UNITS.get(str(unit), str(unit)) if unit else units
        if index is not None:
            provenance["index"] = t
        self.info = _info(shape4[1:], array.dtype, "zarr", path, spacing=spacing, origin=origin, units=units,
                          **provenance)

    def _slab(self, z0: int, z1: int) -> np.ndarray:
        if self._flat:
            return np.asarray(self._array[tuple(self._select)])[None]
        return np.asarray(self._array[(*self._select, slice(z0, z1))])


def _ome_transform(dataset: dict[str, Any], image: dict[str, Any], ndim: int) -> tuple[list[float], list[float]]:
    """Scale and translation per axis of a dataset, followed by the image-wide transformations when present."""
    scale, translation = [1.0] * ndim, [0.0] * ndim
    for transforms in (dataset.get("coordinateTransformations", []), image.get("coordinateTransformations", [])):
        for tr in transforms:
            if tr.get("type") == "scale":
                s = [float(v) for v in tr["scale"]]
                scale, translation = [a * b for a, b in zip(scale, s)], [a * b for a, b in zip(translation, s)]
            elif tr.get("type") == "translation":
                translation = [a + float(b) for a, b in zip(translation, tr["translation"])]
    return scale, translation


# --- which format -----------------------------------------------------------------------------------------------

def _format_name(name: str) -> str:
    fmt = _ALIASES.get(str(name).lower(), str(name).lower())
    if fmt not in FORMATS:
        raise SourceError(f"unknown format '{name}'; expected one of {', '.join(FORMATS)}")
    return fmt


def _guess_format(p: Path, raw_options: bool) -> str:
    name = p.name.lower()
    if p.is_dir():
        if name.endswith(".zarr") or any((p / m).is_file() for m in ("zarr.json", ".zarray", ".zgroup")):
            return "zarr"
        files = [f for f in p.iterdir() if f.is_file()]
        if any(_is_dicom(f) for f in files):
            return "dicom"
        if any(f.suffix.lower() in (".tif", ".tiff") for f in files):
            return "tiff"
        raise SourceError(f"cannot tell the format of folder {p}: it holds no DICOM files, no .tif files and no "
                          f"zarr metadata")
    by_suffix = [(".nii.gz", "nifti"), (".nii", "nifti"), (".hdr", "nifti"), (".nrrd", "nrrd"), (".nhdr", "nrrd"),
                 (".npy", "npy"), (".raw", "raw"), (".bin", "raw"), (".tif", "tiff"), (".tiff", "tiff"),
                 (".dcm", "dicom")]
    for suffix, fmt in by_suffix:
        if name.endswith(suffix):
            return fmt
    if name.endswith(".img"):  # Analyze/NIfTI pairs an .img with an .hdr; otherwise it is headerless raw
        return "nifti" if p.with_suffix(".hdr").is_file() else "raw"
    with open(p, "rb") as f:
        head = f.read(132)
    for magic, fmt in ((b"\x93NUMPY", "npy"), (b"NRRD", "nrrd"), (b"II*\0", "tiff"), (b"MM\0*", "tiff"),
                       (b"II+\0", "tiff"), (b"MM\0+", "tiff")):
        if head.startswith(magic):
            return fmt
    if head[128:132] == b"DICM":
        return "dicom"
    if raw_options:
        return "raw"
    raise SourceError(f"unknown format of {p}: expected .npy, .raw/.bin/.img (with shape and dtype), .nrrd/.nhdr, "
                      f".nii/.nii.gz, .tif/.tiff, a DICOM or TIFF folder or a .zarr store, or pass format=")
