"""Arrays stored in one file as plain bytes: NumPy .npy, headerless raw and NRRD (raw, gzip or bzip2 encoded, with a
detached data file or not). Uncompressed data is read with plain file reads per slab (`_BinaryReader`, in C or
Fortran order, the latter in windows of `WINDOW_BYTES` read from the package so that it can be tuned in one place);
compressed streams are read forwards and restarted only when a caller goes back (`_StreamReader`).
"""
from __future__ import annotations

import bz2
import gzip
import io
import math
import zlib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np

import lodcast.store.readers as _package
from lodcast.errors import SourceError
from lodcast.store.orientation import space_name
from lodcast.store.readers.base import (
    READ_CHUNK,
    UNITS,
    Reader,
    pick_volume,
    read_exact,
    shape_text,
    skip_bytes,
    source_info,
    tidy,
)
from lodcast.store.source import SourceInfo

__all__ = ["open_npy", "open_raw", "open_nrrd"]


class _BinaryReader(Reader):
    """A (t, z, y, x) array stored uncompressed at `offset`, in C or Fortran order."""

    rereads_cheaply = True

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
                read_exact(f, out, self._path)
                return out
            plane = t * depth * ny  # x is the slowest axis: one x holds every t, z, y
            step = max(1, _package.WINDOW_BYTES // (plane * item))
            for x0 in range(0, nx, step):
                x1 = min(nx, x0 + step)
                window = np.empty((x1 - x0, ny, depth, t), self._dtype)
                f.seek(self._offset + x0 * plane * item)
                read_exact(f, window, self._path)
                out[:, :, x0:x1] = window[:, :, z0:z1, self._index].transpose(2, 1, 0)
        return out


class _StreamReader(Reader):
    """A C-ordered (t, z, y, x) array in a forward-only stream (gzip, bzip2). `start` opens the file and returns it
    with the decompressed stream positioned at the first voxel."""

    def __init__(self, start: Callable[[], tuple[io.BufferedIOBase, io.BufferedIOBase]], name: str,
                 shape4: tuple[int, int, int, int], dtype: np.dtype, index: int, info: SourceInfo) -> None:
        self._start, self._name, self._shape4, self._dtype, self._index = start, name, shape4, dtype, index
        self.info = info
        self._files: tuple[io.BufferedIOBase, io.BufferedIOBase] | None = None
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
            skip_bytes(stream, target - self._pos, self._name)
            read_exact(stream, out, self._name)
        except (OSError, EOFError, zlib.error) as exc:
            raise SourceError(f"{self._name} is corrupt: {exc}") from None
        self._pos = target + out.nbytes
        return out

    def close(self) -> None:
        if self._files is not None:
            for f in self._files:
                f.close()
            self._files = None


def open_npy(path: Path, index: int | None) -> Reader:
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
    shape4, t = pick_volume(mm.shape, index, str(path))
    # only the header is used: the slab reads are plain file reads
    offset, dtype, fortran = mm.offset, mm.dtype, mm.ndim > 1 and mm.flags.f_contiguous and not mm.flags.c_contiguous
    del mm
    extra: dict[str, Any] = {"index": t} if index is not None else {}
    info = source_info(shape4[1:], dtype, "npy", path, **extra)
    if fortran:
        info.provenance["order"] = "F"
    return _BinaryReader(path, offset, shape4, dtype, fortran, t, info)


def open_raw(path: Path, shape: Sequence[int] | None, dtype: Any, byte_order: str, header_bytes: int,
         index: int | None) -> Reader:
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
    shape4, t = pick_volume(dims, index, f"raw file {path}")
    size, need = path.stat().st_size, header_bytes + math.prod(dims) * dt.itemsize
    if size != need:
        head = f" ({header_bytes}-byte header + {need - header_bytes} bytes of voxels)" if header_bytes else ""
        raise SourceError(f"raw file is {size} bytes but shape {shape_text(dims)} of {dt.name} needs {need} bytes{head}")
    info = source_info(shape4[1:], dt, "raw", path, byte_order=byte_order, header_bytes=header_bytes)
    return _BinaryReader(path, header_bytes, shape4, dt, False, t, info)


# --- NRRD -------------------------------------------------------------------------------------------------------

_NRRD_SPATIAL = ("domain", "space", "time", "???", "none")


def open_nrrd(path: Path, index: int | None, detached: bool = True) -> Reader:
    """detached=False refuses headers whose data lie in another file (uploads: only the uploaded file may be read);
    otherwise the data file must lie in the header's own folder, symlinks resolved."""
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
    shape4, t = pick_volume([sizes[a] for a in reversed(keep)], index, f"NRRD file {path}")

    spatial = keep[:3]
    directions = header.get("space directions")
    provenance: dict[str, Any] = {"encoding": encoding}
    geometry: dict[str, Any]
    origin, geometry = [0.0, 0.0, 0.0], {}
    if directions is not None:
        d = np.asarray([directions[a] for a in spatial], dtype=float)
        # each row scaled by its largest component first: squared, a 1e-320 step underflowed to 0 and 1e308 to inf
        big = np.abs(d).max(axis=1, initial=0.0)
        with np.errstate(invalid="ignore"):
            norms = big * np.linalg.norm(d / np.where(big > 0, big, 1.0)[:, None], axis=1)
        spacing = [tidy(v) for v in norms]
        provenance["space_directions"] = d.tolist()
        o = header.get("space origin")
        if o is not None:
            provenance["space_origin"] = [float(v) for v in o]
        if d.shape == (3, 3):
            geometry = {"space": space_name(header.get("space")), "direction": d}
            if o is not None and len(o) == 3:
                origin = [float(v) for v in o]
    else:
        spacing = [float(header.get("spacings", [1.0] * len(sizes))[a]) for a in spatial]
    spacing += [1.0] * (3 - len(spacing))  # a 2D image is one slice of unit thickness
    units = header.get("space units")
    info = source_info(shape4[1:], dtype, "nrrd", path, spacing=spacing[::-1], origin=origin[::-1],
                       units=UNITS.get(str(units[0]), "millimeter") if units else "millimeter", **geometry,
                       **provenance)
    info.provenance["space"] = header.get("space")

    data_path, start = path, data_start
    if "data file" in header or "datafile" in header:
        name = str(header.get("data file", header.get("datafile")))
        if name.startswith("LIST") or " " in name:
            raise SourceError(f"NRRD {path} splits its data over several files ({name!r}); expected one data file")
        if not detached:
            raise SourceError(f"NRRD {path} keeps its data in another file ({name!r}); only attached NRRD (data in "
                              f"the same file) is accepted here")
        data_path, start = path.parent / name, 0
        if Path(name).is_absolute() or data_path.resolve().parent != path.resolve().parent:
            raise SourceError(f"data file {name!r} named by NRRD header {path} is outside the header's folder; "
                              f"expected a file beside the header")
        if not data_path.is_file():
            raise SourceError(f"data file {data_path} named by NRRD header {path} does not exist")
    size = data_path.stat().st_size
    line_skip, byte_skip = (_skip(header, key, path) for key in ("line skip", "byte skip"))
    if line_skip > size - start:  # every line is at least its newline
        raise SourceError(f"NRRD {path}: line skip {line_skip} is more lines than the {size - start} bytes of "
                          f"{data_path.name} after the header can hold")
    with open(data_path, "rb") as f:
        f.seek(start)
        start = _skip_lines(f, line_skip, path)
    nbytes = math.prod(sizes) * dtype.itemsize
    if encoding == "raw":
        if byte_skip > size - start:
            raise SourceError(f"NRRD {path}: byte skip {byte_skip} is beyond the end of {data_path.name} "
                              f"({size - start} bytes after the header)")
        offset = size - nbytes if byte_skip == -1 else start + byte_skip
        if offset < 0 or size < offset + nbytes:
            raise SourceError(f"NRRD data in {data_path} is {size - max(offset, 0)} bytes but "
                              f"sizes {shape_text(sizes)} of {dtype.name} need {nbytes}")
        return _BinaryReader(data_path, offset, shape4, dtype, False, t, info)
    if encoding in ("gzip", "gz") and byte_skip > _DEFLATE_RATIO * (size - start):
        raise SourceError(f"NRRD {path}: byte skip {byte_skip} is more than the {size - start} gzip bytes of "
                          f"{data_path.name} can hold (at most {_DEFLATE_RATIO} times their size)")
    decoders: dict[str, Callable[[IO[bytes]], io.BufferedIOBase]] = {
        "gzip": _gunzip, "gz": _gunzip, "bzip2": bz2.BZ2File, "bz2": bz2.BZ2File}
    decompress = decoders.get(encoding)
    if decompress is None:
        raise SourceError(f"NRRD encoding '{encoding}' of {path} is not supported; expected raw, gzip or bzip2")
    if byte_skip < 0:
        raise SourceError(f"NRRD {path}: byte skip {byte_skip} with {encoding} encoding is not supported; "
                          f"expected 0 or more")

    def opened() -> tuple[io.BufferedIOBase, io.BufferedIOBase]:
        raw = open(data_path, "rb")
        raw.seek(start)
        stream = decompress(raw)
        skip_bytes(stream, byte_skip, data_path)
        return stream, raw

    return _StreamReader(opened, str(data_path), shape4, dtype, t, info)


#: the most bytes one byte of a deflate stream expands to (its longest match, 258 bytes, in about two bits)
_DEFLATE_RATIO = 1032


def _skip(header: dict[str, Any], key: str, path: Path) -> int:
    """The header's `line skip` or `byte skip` (also spelt without the space), 0 when absent."""
    value = header.get(key, header.get(key.replace(" ", ""), 0))
    try:
        n = int(value)
    except (TypeError, ValueError):
        raise SourceError(f"NRRD {path}: {key} {value!r} is not a whole number") from None
    if n < (-1 if key == "byte skip" else 0):
        raise SourceError(f"NRRD {path}: {key} {n} is negative")
    return n


def _skip_lines(f: IO[bytes], lines: int, path: Path) -> int:
    """Moves past `lines` lines (reading in pieces: one line may be the whole file) and returns the position."""
    pos = f.tell()
    while lines > 0:
        piece = f.read(READ_CHUNK)
        if not piece:
            raise SourceError(f"NRRD {path}: the data file ends {lines} lines short of its line skip")
        cut = 0
        while lines > 0:
            cut = piece.find(b"\n", cut) + 1
            if not cut:
                break
            lines -= 1
        pos += cut if lines == 0 else len(piece)
    return pos


def _gunzip(f: IO[bytes]) -> io.BufferedIOBase:
    return gzip.GzipFile(fileobj=f, mode="rb")
