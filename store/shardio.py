"""Shard-level reader for the sharded zarr v3 level arrays written by ingest, bypassing zarr-python's codec pipeline.

Why: zarr-python spends a fixed amount of Python per inner chunk, so a region of thousands of small blocks (16³
or 8³ samples) is slow to read. Here each needed shard file is opened once, its index (the trailing
16·n + 4 bytes: little-endian uint64 (offset, nbytes) per inner chunk in C order, then a crc32c) is parsed once
and cached per (path, mtime, size), the needed chunks' bytes are read as one span when they lie close together,
and blosc decodes them straight into a per-unit buffer on a shared thread pool (blosc releases the GIL), which is
then copied into the region. Only what ingest writes is handled: a regular chunk grid, one `sharding_indexed`
codec holding `bytes` (+ optional `blosc`, + optional `crc32c`), index codecs `bytes` (+ optional `crc32c`); every
checksum present is verified (a chunk or index that fails it is StoreCorrupt naming the file and the chunk), and a
shard is checked against the store's manifest when the caller gives one. In a LocalStore or an
fsspec store (object storage: the same reads as byte-range requests — per shard one suffix request for the index,
then one per span of needed chunks, one work unit per shard — where zarr-python issues one request per inner
chunk); and, on the local filesystem, unsharded arrays of `bytes` (+ optional `blosc` or `zstd`), the per-block
metadata (ChunkReader). A local array opens from its zarr.json alone, without importing zarr-python. Anything else
makes `fast_reader` return None so the caller keeps using zarr-python.
"""
from __future__ import annotations

import itertools
import json
import os
import threading
from collections import OrderedDict
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from math import ceil, prod
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numcodecs import blosc, zstd

from lodcast.errors import StoreCorrupt
from lodcast.store.checksum import crc32c

__all__ = ["ShardedReader", "ChunkReader", "fast_reader"]

_EMPTY = np.uint64(2**64 - 1)
#: shard indexes a reader keeps (each keyed by its file's size and modification time or ETag)
INDEX_CACHE_MAX = 2048


#: the largest local shard file read whole at once (`ShardedReader._whole`)
WHOLE_SHARD_BYTES = 16 << 20


def _workers() -> int:
    return min(32, os.cpu_count() or 1)


def _endian(codec: dict[str, Any]) -> Literal["<", ">"]:
    """'<' or '>' from a `bytes` codec (no configuration, as for 1-byte types, means little endian)."""
    orders: dict[str | None, Literal["<", ">"]] = {"little": "<", "big": ">", None: "<"}
    return orders[(codec.get("configuration") or {}).get("endian")]


class _LocalFiles:
    """Shard files on a local filesystem: positioned reads on a file descriptor."""

    def __init__(self, root: Path):
        self.root = root
        self._prefix = os.path.join(str(root), "")  # (joined as strings: a pathlib join per shard read shows)

    def name(self, key: str) -> str:
        return self._prefix + key

    def open(self, key: str) -> int:
        return os.open(self._prefix + key, os.O_RDONLY)

    def close(self, fd: int) -> None:
        os.close(fd)

    remote = False

    def stamp(self, fd: int) -> tuple[int | None, Any]:
        st = os.fstat(fd)
        return st.st_size, st.st_mtime_ns

    def pread(self, fd: int, n: int, off: int) -> bytes:
        return os.pread(fd, n, off)


class _RemoteFiles:
    """Shard objects through a (synchronous) fsspec filesystem: byte-range requests, the index by a suffix range
    (no size request). A store is immutable once ingest published it, so indexes are cached for this reader's
    lifetime (a new open_store reads them again); a missing object raises FileNotFoundError on its first read."""

    remote = True

    def __init__(self, fs: Any, root: str):
        self.fs, self.root = fs, root.rstrip("/")

    def name(self, key: str) -> str:
        return f"{self.root}/{key}"

    def open(self, key: str) -> str:
        return self.name(key)

    def close(self, path: str) -> None:
        pass

    def stamp(self, path: str) -> tuple[int | None, Any]:
        return None, None  # (a store replaced on object storage is opened anew, with new readers)

    def pread(self, path: str, n: int, off: int) -> bytes:
        return self.fs.cat_file(path, start=off, end=off + n) if n else b""

    def suffix(self, path: str, n: int) -> bytes:
        return self.fs.cat_file(path, start=-n)


def fast_reader(source: Any, complete: bool = False, url: str | None = None,
                digests: Mapping[str, list[int]] | None = None) -> ShardedReader | ChunkReader | None:
    """A reader for `source`, or None when its store or codecs are not handled (use zarr-python then). `source`:
    a zarr Array, or the folder of an array on the local filesystem, whose zarr.json is all that is read to open
    it (zarr-python is not imported until a read with steps needs it: importing it is a noticeable part of a first
    render). A sharded array gets a ShardedReader; an unsharded local one (the per-block metadata arrays) a
    ChunkReader. `complete`: ingest wrote every chunk, so a missing shard file or chunk is damage (StoreCorrupt),
    not empty. `url`: the group's fsspec URL, for an array in an fsspec store (read through a synchronous
    filesystem). `digests`: what the store's manifest (store/checksum.py) says of each data file, by chunk key:
    a shard whose index, or a chunk file whose bytes, are not the ones ingest wrote at that key is damage."""
    if isinstance(source, (str, os.PathLike)):
        folder = Path(source)
        try:
            meta = json.loads((folder / "zarr.json").read_bytes())
        except (OSError, ValueError):
            return None
        files: Any = _LocalFiles(folder)

        def array() -> Any:
            import zarr

            return zarr.open_array(folder, mode="r")
    else:
        try:
            store, meta = source.store, source.metadata.to_dict()
        except AttributeError:
            return None
        import zarr

        if isinstance(store, zarr.storage.LocalStore):
            files = _LocalFiles(Path(store.root) / source.path)
        elif url is not None and type(store).__name__ == "FsspecStore":
            import fsspec

            fs, root = fsspec.core.url_to_fs(url)
            files = _RemoteFiles(fs, f"{root.rstrip('/')}/{source.path}")
        else:
            return None

        def array() -> Any:
            return source
    geom = _geometry(meta)
    if geom is None:
        return None
    shape, dtype, fill, key = geom
    codecs = meta["codecs"]
    if codecs and codecs[0]["name"] == "sharding_indexed":
        if len(codecs) != 1:
            return None
        cfg = codecs[0]["configuration"]
        inner, index_codecs = cfg["codecs"], cfg["index_codecs"]
        if not inner or inner[0]["name"] != "bytes" or [c["name"] for c in inner[1:]] not in (
                [], ["blosc"], ["crc32c"], ["blosc", "crc32c"]):
            return None
        if not index_codecs or index_codecs[0]["name"] != "bytes" or [c["name"] for c in index_codecs[1:]] not in ([], ["crc32c"]):
            return None
        chunk, shard_shape = tuple(cfg["chunk_shape"]), tuple(meta["chunk_grid"]["configuration"]["chunk_shape"])
        if len(chunk) != len(shard_shape) or any(s % c for s, c in zip(shard_shape, chunk)):
            return None
        return ShardedReader(
            shape, dtype, fill, key, array, files, chunk, shard_shape,
            chunk_dtype=dtype.newbyteorder(_endian(inner[0])) if dtype.itemsize > 1 else dtype,
            compressed=any(c["name"] == "blosc" for c in inner), chunk_crc=inner[-1]["name"] == "crc32c",
            index_dtype=np.dtype(_endian(index_codecs[0]) + "u8"), index_crc=len(index_codecs) > 1,
            index_at_end=cfg.get("index_location", "end") == "end", complete=complete, digests=digests,
        )
    # unsharded: local files only (on object storage zarr-python's concurrent requests beat one request at a time)
    names = [c["name"] for c in codecs]
    chunk_crc = names[-1:] == ["crc32c"] and len(names) > 1
    if files.remote or not codecs or names[0] != "bytes" or names[1:len(names) - chunk_crc] not in (
            [], ["blosc"], ["zstd"]):
        return None
    chunk_dtype = dtype.newbyteorder(_endian(codecs[0])) if dtype.itemsize > 1 else dtype
    return ChunkReader(shape, dtype, fill, key, array, files, tuple(meta["chunk_grid"]["configuration"]["chunk_shape"]),
                       chunk_dtype=chunk_dtype, codec=names[1] if len(names) > 1 + chunk_crc else None,
                       chunk_crc=chunk_crc, digests=digests)


def _geometry(meta: dict) -> tuple[tuple[int, ...], np.dtype, Any, Any] | None:
    """(shape, dtype, fill value, chunk key function) of a zarr v3 array's metadata (its zarr.json), or None for
    what the readers leave to zarr-python: other formats, storage transformers, irregular grids, non-numeric or
    extension types, fill values other than numbers and the IEEE names."""
    if meta.get("zarr_format") != 3 or meta.get("node_type", "array") != "array" or meta.get("storage_transformers"):
        return None
    if meta.get("chunk_grid", {}).get("name") != "regular":
        return None
    try:
        dtype = np.dtype(meta["data_type"])
    except (TypeError, ValueError, KeyError):
        return None
    if dtype.kind not in "biufc":
        return None
    fill = meta.get("fill_value")
    if isinstance(fill, str):
        fill = {"NaN": np.nan, "Infinity": np.inf, "-Infinity": -np.inf}.get(fill)
        if fill is None:
            return None
    elif not isinstance(fill, (int, float, bool)):
        return None
    enc = meta.get("chunk_key_encoding", {"name": "default"})
    sep: Any = (enc.get("configuration") or {}).get("separator")  # JSON: a str when given
    if enc.get("name") == "default":
        sep = sep or "/"

        def key(coords: tuple[int, ...]) -> str:
            return sep.join(["c", *map(str, coords)])
    elif enc.get("name") == "v2":
        sep = sep or "."

        def key(coords: tuple[int, ...]) -> str:
            return sep.join(map(str, coords)) or "0"
    else:
        return None
    return tuple(int(n) for n in meta["shape"]), dtype, fill, key


#: CRC-32C of any bytes followed by their own CRC-32C (little endian), as zarr's `crc32c` codec appends it: one pass
#: over a chunk checks it, without slicing off its last four bytes first
_RESIDUE = 0x48674BC7


def _checked(raw: Any, name: str, what: str) -> Any:
    """`raw` without its trailing checksum (zarr's `crc32c` codec: the little-endian CRC-32C of the bytes before
    it), or StoreCorrupt naming the file and `what` (the chunk) when the checksum does not match."""
    if len(raw) < 4 or crc32c(raw) != _RESIDUE:
        raise StoreCorrupt(f"{name}: damaged shard: {what} fails its checksum: re-ingest the store")
    return raw[:-4]


class _Reader:
    """What both readers share: a region's bounds and output; reads with steps go through zarr-python."""

    def __init__(self, shape: tuple[int, ...], dtype: np.dtype, fill_value: Any, chunk_key: Any, array: Any,
                 files: Any, chunk: tuple[int, ...]) -> None:
        self.shape, self.dtype, self.fill_value, self.chunk = shape, np.dtype(dtype), fill_value, chunk
        self._key, self._array, self._files = chunk_key, array, files

    def read_region(self, region: Any, dtype: Any = None, out: np.ndarray | None = None) -> np.ndarray:
        """The same array as `np.asarray(array[region])` for a tuple of slices or ... (non-unit steps go through
        zarr), in `dtype` when given: each worker casts its chunks as it places them, so a conversion costs no
        pass of its own (one over level 0 would be a good part of a first render). `out`: an array of
        the region's shape (and `dtype`) to read into, e.g. a mapped device buffer, instead of a new one."""
        if region is ...:
            region = (slice(None),) * len(self.shape)
        if len(region) != len(self.shape) or not all(isinstance(s, slice) for s in region):
            raise TypeError(f"expected {len(self.shape)} slices, got {region!r}")
        bounds = [s.indices(n) for s, n in zip(region, self.shape)]
        if any(step != 1 for _, _, step in bounds):
            a = np.asarray(self._array()[region], dtype=dtype)
            if out is None:
                return a
            out[...] = a
            return out
        lo = tuple(a for a, _, _ in bounds)
        hi = tuple(max(a, b) for a, b, _ in bounds)
        shape = tuple(b - a for a, b in zip(lo, hi))
        if out is None:
            out = np.empty(shape, self.dtype if dtype is None else dtype)
        assert out.shape == shape and (dtype is None or out.dtype == np.dtype(dtype)), (out.shape, shape, out.dtype)
        if out.size:
            self._fill(out, lo, hi)
        return out

    def _fill(self, out: np.ndarray, lo: tuple[int, ...], hi: tuple[int, ...]) -> None:
        raise NotImplementedError


class ChunkReader(_Reader):
    """Reads regions of one unsharded zarr v3 array on the local filesystem: each chunk file read whole and
    decoded (blosc or zstd, or raw). The per-block metadata arrays are a few dozen such chunks, which zarr-python's
    asynchronous pipeline is slow to read for a first render."""

    def __init__(self, shape: tuple[int, ...], dtype: np.dtype, fill_value: Any, chunk_key: Any, array: Any,
                 files: Any, chunk: tuple[int, ...], *, chunk_dtype: np.dtype, codec: str | None,
                 chunk_crc: bool = False, digests: Mapping[str, list[int]] | None = None) -> None:
        super().__init__(shape, dtype, fill_value, chunk_key, array, files, chunk)
        self._chunk_dtype, self._codec, self._chunk_crc, self._digests = chunk_dtype, codec, chunk_crc, digests

    def read_chunk(self, coords: tuple[int, ...]) -> np.ndarray | None:
        """The chunk at chunk coordinates `coords`, decoded and checked (None: never written, the fill value)."""
        key = self._key(coords)
        name = self._files.name(key)
        try:
            with open(name, "rb") as f:
                raw = f.read()
        except FileNotFoundError:
            if self._digests is not None and key in self._digests:
                raise StoreCorrupt(f"{name}: chunk file missing (ingest wrote it): the store is damaged, "
                                   f"re-ingest it") from None
            return None
        if self._digests is not None:
            want = self._digests.get(key)
            if want is None or want[:2] != [len(raw), crc32c(raw)]:
                raise StoreCorrupt(f"{name}: damaged chunk (not the file ingest wrote at this place: "
                                   f"{'none was written' if want is None else 'its checksum differs'}): re-ingest "
                                   f"the store")
            if self._chunk_crc:  # the very bytes ingest wrote: their own trailing checksum holds
                raw = raw[:-4]
        elif self._chunk_crc:
            raw = _checked(raw, name, f"chunk {coords}")
        n = prod(self.chunk) * self._chunk_dtype.itemsize
        try:
            if self._codec == "blosc":
                data = blosc.decompress(raw)
            elif self._codec == "zstd":
                data = zstd.decompress(raw)
            else:
                data = raw
        except (ValueError, RuntimeError) as exc:
            raise StoreCorrupt(f"{name}: damaged chunk ({' '.join(str(exc).split())}): re-ingest "
                               f"the store") from None
        if len(data) != n:
            raise StoreCorrupt(f"{name}: chunk of {len(data)} bytes, expected {n}: re-ingest the store")
        return np.frombuffer(data, self._chunk_dtype).reshape(self.chunk)

    def _fill(self, out: np.ndarray, lo: tuple[int, ...], hi: tuple[int, ...]) -> None:
        ranges = [range(a // c, -(-b // c)) for a, b, c in zip(lo, hi, self.chunk)]
        for coords in itertools.product(*ranges):
            start = [i * c for i, c in zip(coords, self.chunk)]
            src = tuple(slice(max(a, s) - s, min(b, s + c) - s) for a, b, s, c in zip(lo, hi, start, self.chunk))
            dst = tuple(slice(max(a, s) - a, min(b, s + c) - a) for a, b, s, c in zip(lo, hi, start, self.chunk))
            a = self.read_chunk(coords)
            out[dst] = self.fill_value if a is None else a[src]


class ShardedReader(_Reader):
    """Reads regions of one sharded zarr v3 array, local or through fsspec; see the module docstring.

    The array's metadata is taken once: resizing the array afterwards needs a new reader (rewritten shards are
    picked up, since cached indexes are keyed by file mtime and size)."""

    def __init__(self, shape: tuple[int, ...], dtype: np.dtype, fill_value: Any, chunk_key: Any, array: Any,
                 files: Any, chunk: tuple[int, ...], shard: tuple[int, ...], *, chunk_dtype: np.dtype,
                 compressed: bool, index_dtype: np.dtype, index_crc: bool, index_at_end: bool,
                 complete: bool = False, chunk_crc: bool = False,
                 digests: Mapping[str, list[int]] | None = None) -> None:
        super().__init__(shape, dtype, fill_value, chunk_key, array, files, chunk)
        self.complete, self.shard = complete, shard
        self._chunk_dtype, self._compressed, self._chunk_crc = chunk_dtype, compressed, chunk_crc
        self._digests = digests
        self._per_shard = tuple(s // c for s, c in zip(shard, chunk))
        self._n_index = prod(self._per_shard)
        self._index_dtype, self._index_crc, self._index_at_end = index_dtype, index_crc, index_at_end
        self._index_bytes = 16 * self._n_index + 4 * index_crc
        self._indexes: OrderedDict[tuple[str, Any, Any], np.ndarray] = OrderedDict()
        self._lock = threading.Lock()

    def _fill(self, out: np.ndarray, lo: tuple[int, ...], hi: tuple[int, ...]) -> None:
        units = self._units(lo, hi)
        if len(units) == 1:
            self._read_unit(out, lo, hi, *units[0])
        else:
            with ThreadPoolExecutor(min(_workers(), len(units)), thread_name_prefix="shardio") as pool:
                for f in [pool.submit(self._read_unit, out, lo, hi, *u) for u in units]:
                    f.result()

    # --- work units: a box of chunks inside one shard ----------------------------------------------------------
    def _units(self, lo: tuple[int, ...], hi: tuple[int, ...]) -> list[tuple[tuple[int, ...], tuple[int, ...]]]:
        """Chunk boxes [c0, c1) of the region, one per shard, split along their leading axes into enough pieces
        to keep the pool busy (but at least a few chunks each, so a piece's Python overhead stays small)."""
        c0 = [a // c for a, c in zip(lo, self.chunk)]
        c1 = [-(-b // c) for b, c in zip(hi, self.chunk)]
        boxes = []
        for s in itertools.product(*(range(a // p, -(-b // p)) for a, b, p in zip(c0, c1, self._per_shard))):
            boxes.append((tuple(max(a, i * p) for a, i, p in zip(c0, s, self._per_shard)),
                          tuple(min(b, (i + 1) * p) for b, i, p in zip(c1, s, self._per_shard))))
        total = sum(prod(b - a for a, b in zip(*box)) for box in boxes)
        if self._files.remote:  # a request costs more than the bytes: one unit (index, then spans) per shard
            return boxes
        target = max(8, ceil(total / (4 * _workers())))
        units = []
        for a, b in boxes:
            axis = next(i for i in range(len(a)) if prod(y - x for x, y in zip(a[i + 1:], b[i + 1:])) <= target)
            step = max(1, target // prod(y - x for x, y in zip(a[axis + 1:], b[axis + 1:])))
            for pre in itertools.product(*(range(x, y) for x, y in zip(a[:axis], b[:axis]))):
                for k in range(a[axis], b[axis], step):
                    units.append((pre + (k,) + a[axis + 1:], tuple(x + 1 for x in pre) + (min(k + step, b[axis]),) + b[axis + 1:]))
        return units

    def read_chunks(self, coords: np.ndarray) -> np.ndarray:
        """The inner chunks at chunk coordinates `coords` (n, ndim), all in one shard: (n, *chunk) in the chunks'
        own type, whole (a chunk on the array's edge holds what ingest wrote beyond it). Only these chunks' bytes
        are read and decoded, where a region would take every chunk of its bounding box."""
        coords = np.asarray(coords, np.int64).reshape(-1, len(self.chunk))
        shard = coords[0] // np.array(self._per_shard)
        assert (coords // np.array(self._per_shard) == shard).all(), "read_chunks: chunks of more than one shard"
        return self._read_box(tuple(int(v) for v in shard), coords)

    def _read_box(self, shard: tuple[int, ...], coords: np.ndarray) -> np.ndarray:
        """Chunks `coords` (n, ndim) of shard `shard`, decoded into an (n, *chunk) buffer."""
        box = np.empty((len(coords), *self.chunk), self._chunk_dtype)
        key = self._key(shard)
        name = self._files.name(key)
        try:
            fd = self._files.open(key)
        except FileNotFoundError:
            fd = None
        try:
            whole = None if fd is None else self._whole(fd, len(coords))
            entries = None if fd is None else self._entries(fd, name, key, coords, whole)
            if entries is None:  # no shard file (remote: found on its first read)
                if self.complete:
                    raise StoreCorrupt(f"{name}: shard file missing (ingest wrote it): the store is damaged, "
                                       f"re-ingest it")
                box[...] = self.fill_value
            else:
                full = entries[:, 0] != _EMPTY
                if self.complete and not full.all():
                    raise StoreCorrupt(f"{name}: {int((~full).sum())} chunks missing from the shard "
                                       f"(ingest wrote them all): the store is damaged, re-ingest it")
                self._decode(fd, entries, full, box, name, coords, whole)
        except (ValueError, RuntimeError) as exc:  # a truncated or overwritten shard, a chunk blosc rejects
            if isinstance(exc, StoreCorrupt):
                raise
            raise StoreCorrupt(f"{name}: damaged shard ({' '.join(str(exc).split())}): re-ingest "
                               f"the store") from None
        finally:
            if fd is not None:
                self._files.close(fd)
        return box

    def _read_unit(self, out: np.ndarray, lo: tuple[int, ...], hi: tuple[int, ...], c0: tuple[int, ...], c1: tuple[int, ...]) -> None:
        counts = tuple(b - a for a, b in zip(c0, c1))
        shard = tuple(a // p for a, p in zip(c0, self._per_shard))
        coords = (np.indices(counts).reshape(len(counts), -1) + np.array(c0)[:, None]).T  # C order, like the box
        box = self._read_box(shard, coords)
        # box (k, cz, cy, cx) holds chunks in C order of the chunk box: seen as (kz, ky, kx, cz, cy, cx) it is
        # copied once into the region seen as (kz, cz, ky, cy, kx, cx); a box clipped by the region goes through
        # a contiguous copy of the whole box first
        nd = len(self.chunk)
        start = [a * c for a, c in zip(c0, self.chunk)]
        ends = [s + k * c for s, k, c in zip(start, counts, self.chunk)]
        dst = tuple(slice(max(a, s) - a, min(h, e) - a) for a, h, s, e in zip(lo, hi, start, ends))
        chunks = box.reshape(counts + self.chunk)
        if all(a <= s and e <= h for a, h, s, e in zip(lo, hi, start, ends)):
            target = out[dst].reshape(tuple(x for kc in zip(counts, self.chunk) for x in kc))
            target.transpose([2 * i for i in range(nd)] + [2 * i + 1 for i in range(nd)])[...] = chunks
        else:
            grid = chunks.transpose([i // 2 + (nd if i % 2 else 0) for i in range(2 * nd)])
            grid = grid.reshape(tuple(k * c for k, c in zip(counts, self.chunk)))
            out[dst] = grid[tuple(slice(max(a, s) - s, min(h, e) - s) for a, h, s, e in zip(lo, hi, start, ends))]

    def _whole(self, fd: Any, wanted: int) -> bytes | None:
        """The whole shard file in one read, where it is local, at most WHOLE_SHARD_BYTES and at least half of its
        chunks are `wanted`: its index at the end and its chunks at the start were two requests (on a cold disk,
        two seeks per shard), for bytes that are mostly wanted anyway. None otherwise."""
        if self._files.remote or 2 * wanted < self._n_index:
            return None
        size, _ = self._files.stamp(fd)
        if size is None or size > WHOLE_SHARD_BYTES:
            return None
        return self._files.pread(fd, size, 0)

    def _entries(self, fd: Any, name: str, key: str, coords: np.ndarray,
                 whole: bytes | None = None) -> np.ndarray | None:
        """The index entries of the chunks `coords` (n, ndim), in their order (None: the shard object does not
        exist); `whole`: the shard's bytes, read already."""
        try:
            index = self._index(fd, name, key, whole)
        except FileNotFoundError:
            return None
        return index[np.ravel_multi_index(tuple((coords % np.array(self._per_shard)).T), self._per_shard)]

    def _decode(self, fd: Any, entries: np.ndarray, full: np.ndarray, box: np.ndarray, name: str,
                coords: np.ndarray, whole: bytes | None = None) -> None:
        if not full.all():
            box[~full] = self.fill_value
        idx = np.flatnonzero(full)
        if not len(idx):
            return
        offsets, sizes = entries[idx, 0].astype(np.int64), entries[idx, 1].astype(np.int64)
        first, last = int(offsets.min()), int((offsets + sizes).max())
        pread = self._files.pread
        # one span when the gaps are small; on object storage always (a request costs more than the bytes between)
        one = last - first <= 2 * int(sizes.sum()) + 65536 or self._files.remote
        span = pread(fd, last - first, first) if one and whole is None else None
        if whole is not None:  # (the file from its first byte)
            span, first = whole, 0
        for i, off, n in zip(idx.tolist(), offsets.tolist(), sizes.tolist()):
            raw = memoryview(span)[off - first:off - first + n] if span is not None else pread(fd, n, off)
            if len(raw) != n:
                raise ValueError(f"{name}: shard truncated (chunk at {off}+{n})")
            if self._chunk_crc:
                if crc32c(raw) != _RESIDUE:
                    raise StoreCorrupt(f"{name}: damaged shard: chunk {tuple(coords[i].tolist())} (voxels from "
                                       f"{tuple((coords[i] * np.array(self.chunk)).tolist())}) fails its checksum: "
                                       f"re-ingest the store")
                raw = raw[:-4]
            if self._compressed:
                blosc.decompress(raw, box[i])
            else:
                box[i] = np.frombuffer(raw, self._chunk_dtype).reshape(self.chunk)

    def _index(self, fd: Any, path: str, chunk_key: str, whole: bytes | None = None) -> np.ndarray:
        """The shard's (offset, nbytes) table, shape (n, 2) uint64, from this reader's cache keyed by (path, size,
        mtime or ETag), else read (from `whole`, the shard's bytes, where given); checked against the manifest's
        entry for `chunk_key` when the reader has one."""
        size, version = self._files.stamp(fd)
        key = (path, size, version)
        with self._lock:
            if key in self._indexes:
                self._indexes.move_to_end(key)
                return self._indexes[key]
        n = self._index_bytes
        if size is not None and size < n:
            raise ValueError(f"{path}: shard shorter than its index")
        if whole is not None and len(whole) == size and size >= n:
            raw = whole[size - n:] if self._index_at_end else whole[:n]
        elif size is None and self._index_at_end:
            raw = self._files.suffix(fd, n)
        else:
            raw = self._files.pread(fd, n, size - n if self._index_at_end else 0)
        if len(raw) != n:
            raise ValueError(f"{path}: shard shorter than its index")
        body = raw[:16 * self._n_index]
        if self._index_crc and crc32c(body) != int.from_bytes(raw[-4:], "little"):
            raise ValueError(f"{path}: shard index checksum mismatch")
        if self._digests is not None:
            self._check_binding(path, chunk_key, size, raw)
        index = np.frombuffer(body, self._index_dtype).reshape(-1, 2).astype(np.uint64)
        full = index[:, 0] != _EMPTY
        if size is not None and full.any() and int((index[full, 0] + index[full, 1]).max()) > size:
            raise ValueError(f"{path}: shard index points past the end of the file")
        with self._lock:
            self._indexes[key] = index
            while len(self._indexes) > INDEX_CACHE_MAX:
                self._indexes.popitem(last=False)
        return index

    def _check_binding(self, path: str, chunk_key: str, size: int | None, raw: bytes) -> None:
        """StoreCorrupt unless this shard is the one ingest wrote at `chunk_key`: its size and its index's checksum
        as the manifest records them (a shard swapped with, or replaced by, another has other chunk sizes)."""
        want = self._digests.get(chunk_key) if self._digests is not None else None
        if want is None:
            raise StoreCorrupt(f"{path}: damaged shard: ingest wrote no shard at this place: re-ingest the store")
        if (size is not None and size != want[0]) or (self._index_crc and len(want) > 2 and int.from_bytes(raw[-4:], "little") != want[2]):
            raise StoreCorrupt(f"{path}: damaged shard: not the shard ingest wrote at this place (swapped or "
                               f"replaced: its index differs from the manifest's): re-ingest the store")
