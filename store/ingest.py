"""Ingest: a source volume → a lodcast store (zarr v3), streamed in block-thick z-slabs.

Pass 1 reads the source once, slab by slab: every level is built by average downsampling within each block
(thesis §3.1: levels B, B/2, … 1 per block; padding by edge replication), written shard by shard, and the
per-block min/max/mean/count gathered. Pass 2 reads level 0 again in z order (the source in pieces of a few
slices when it re-reads cheaply, else the new store slab by slab) for the border-inclusive histograms, their
simplified forms and the border-inclusive min/max, which need the volume's value range first. Peak memory is a
few slabs whatever the depth.

The store is written under a hidden temporary name beside the destination and renamed into place when complete,
so a killed ingest never leaves anything at the destination that opens as a store.
"""
from __future__ import annotations

import datetime as _dt
import json
import math
import os
import shutil
import sys
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import zarr
from zarr.codecs import BloscCodec, BloscShuffle, Crc32cCodec, ZstdCodec

from lodcast.environment import environment
from lodcast.errors import SourceError, StoreExists
from lodcast.store.atomic import fsync_dir, fsync_tree, move_into_place, remove_stale
from lodcast.store.checksum import MANIFEST, attribute_digests, write_manifest
from lodcast.store.histogram import DEFAULT_BINS, DEFAULT_SEGMENTS, Bins, simplify
from lodcast.store.layout import Layout
from lodcast.store.ome import multiscales, omero
from lodcast.store.orientation import axis_codes
from lodcast.store.remote import is_url
from lodcast.store.shardwrite import ShardWriter
from lodcast.store.source import SUPPORTED_DTYPES, ArraySource, VolumeSource, check_world_box
from lodcast.store.store import FORMAT_VERSION, Store, data_manifest, open_store, parse_temp_name, temp_path

if TYPE_CHECKING:
    from zarr.core.array_spec import ArrayConfigParams

__all__ = ["ingest", "level_mean", "round_to_dtype", "std_dtype"]


def ingest(
    source: str | os.PathLike[str] | np.ndarray | VolumeSource,
    dest: str | os.PathLike[str],
    *,
    overwrite: bool = False,
    block_size: int = 16,
    progress: bool | None = None,
    bins: int = DEFAULT_BINS,
    segments: int = DEFAULT_SEGMENTS,
    workers: int | None = None,
    max_voxels: int | None = None,
    max_memory: int | None = None,
    **reader_options: Any,
) -> Store:
    """Write `source` (a file or folder path, a NumPy array, or a VolumeSource) as a store at `dest`.

    `reader_options` go to `lodcast.store.readers.open_source` (format, shape, dtype, byte_order, header_bytes,
    spacing, origin, units, index, orient); spacing and origin also apply to arrays. Raises SourceNotFound /
    SourceError for bad input and StoreExists when `dest` exists and `overwrite` is false; nothing is left behind
    in either case. A source that declares more than `max_voxels` voxels (default LODCAST_MAX_VOXELS, else no limit) is refused
    from its header, before anything is read or allocated: a small compressed file may declare a huge volume.
    Likewise one whose working set (`working_bytes`: it grows with the slice's Y × X, not with the depth) exceeds
    `max_memory` bytes (default LODCAST_MAX_INGEST_MEMORY_MB, else no limit).
    `dest` may be an fsspec URL (s3://bucket/prefix/ct.zarr): the store is written locally, then published there
    (store/remote.py: the root metadata last, so that no half store is ever visible).
    """
    if is_url(dest):
        from lodcast.store.remote import ingest_to_url

        return ingest_to_url(source, os.fspath(dest), overwrite=overwrite, block_size=block_size, progress=progress,
                             bins=bins, segments=segments, workers=workers, max_voxels=max_voxels,
                             max_memory=max_memory, **reader_options)
    dest = Path(dest)
    if dest.parent.is_dir():
        remove_stale(dest)  # first: it may put back a store that a killed `--overwrite` had moved aside
    if dest.exists() and not overwrite:
        raise StoreExists(f"destination {dest} exists (use --overwrite to replace it)")
    Layout((1, 1, 1), block_size)  # validates the block size before any file is opened
    src = _open(source, reader_options)
    try:
        info = src.info
        if np.dtype(info.dtype) not in SUPPORTED_DTYPES:
            raise SourceError(
                f"unsupported voxel type {np.dtype(info.dtype)}; expected one of {', '.join(d.name for d in SUPPORTED_DTYPES)}"
            )
        if len(info.shape) != 3 or min(info.shape) < 1:
            raise SourceError(f"volume shape must have three non-empty axes (z, y, x), got {tuple(info.shape)}")
        env = environment()
        # the bounds (_check_size, check_world_box): voxels in whole blocks, the store's files, memory, a finite box
        _check_size(info.shape, np.dtype(info.dtype), block_size, env.max_voxels if max_voxels is None else max_voxels,
                    env.max_ingest_bytes if max_memory is None else max_memory, src.held_bytes)
        check_world_box(info)
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp = temp_path(dest, "partial")
        try:
            label = type(source).__name__ if isinstance(source, (np.ndarray, VolumeSource)) else os.fspath(source)
            # batching lets zarr compress many inner chunks of a shard concurrently (faster writes)
            with zarr.config.set({"codec_pipeline.batch_size": 32}):
                _write(src, tmp, Layout(info.shape, block_size), bins, segments, workers, _show_progress(progress), label)
            fsync_tree(tmp)  # every file and folder on disk before the rename publishes them
            move_into_place(tmp, dest, overwrite)
            fsync_dir(dest.parent)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    finally:
        src.close()
    return open_store(dest)


#: ingest's working set per voxel of one block-slab (B slices of Y x X): the source slab, plus the levels and
#: standard deviations of the slab and float32 temporaries per row of blocks (the coarse levels' rows wait for their
#: shard depth in a temporary file, and the per-block statistics go to the store row by row, not held in memory).
#: The formula is an upper estimate: above ingest's peak memory measured on slices of several types and sizes, with
#: room for the base of another installation (docs/measurements/code-notes.md)
WORKING_BYTES_PER_ITEM, WORKING_BYTES_EXTRA = 1, 3
#: slabs up to this size are read while the last one is processed; larger ones after it (memory over speed)
READ_AHEAD_BYTES = 64 << 20
#: pass 2 (histograms) reads a cheaply re-read source in pieces of up to this many bytes (at least a slice), one
#: counted while the next is read (a whole 16-slice slab of 2048² uint16 slices is 128 MiB, all of it on the peak)
COUNT_BYTES = 32 << 20
#: the interpreter, NumPy, zarr, numcodecs, the thread pools and the OpenCL device (simplified histograms), before
#: any voxel
BASE_BYTES = 300_000_000


def working_bytes(shape: tuple[int, ...], dtype: np.dtype, block_size: int) -> int:
    """Ingest's peak memory, estimated from the declared shape before it starts: it grows with the slice, Y x X,
    not with the number of slices."""
    _, ny, nx = (int(s) for s in shape)
    per_voxel = WORKING_BYTES_PER_ITEM * np.dtype(dtype).itemsize + WORKING_BYTES_EXTRA
    return BASE_BYTES + block_size * ny * nx * per_voxel


#: a store's files (shards, per-block statistics, metadata): this many whatever the volume, plus one per
#: VOXELS_PER_FILE voxels. Ordinary volumes stay far inside (`store_files`: 512³ ~1,000 of the 2.1 million allowed,
#: 2 x 8192² ~6,900, 1000 x 16² ~900 of 6,048); a thin one does not (1x1x20000: 15,856 files, most of them per-block
#: statistics of one block each, for 20,000 voxels)
FILES_FLOOR = 2048
VOXELS_PER_FILE = 64


def store_files(lay: Layout) -> int:
    """The files `_write` makes, at most: the shards of every level and standard deviation array, a chunk per row of
    blocks of each of the ten per-block arrays, the cell ranges' chunks, and the metadata."""
    shards = sum(lay.shard_count(k) for k in range(lay.n_levels)) * 2 - lay.shard_count(0)
    cells = 2 * math.ceil(lay.cell_grid[0] / (lay.block_size // lay.cell_edge))
    return shards + 10 * lay.grid[0] + cells + 2 * lay.n_levels + 14


def _check_size(shape: tuple[int, ...], dtype: np.dtype, block_size: int, max_voxels: int | None,
                max_memory: int | None, held: int = 0) -> None:
    """What the declared shape costs, before anything is read: voxels of whole blocks (ingest pads every block to
    B³ and works on the padding) against `max_voxels`, the store's files, and the working set plus what the
    reader holds (`held`) against `max_memory`."""
    dims = "x".join(str(int(s)) for s in shape)
    voxels = math.prod(int(s) for s in shape)
    lay = Layout(tuple(int(s) for s in shape), block_size)  # type: ignore[arg-type]  # three lengths, checked above
    padded = lay.n_blocks * block_size**3
    if max_voxels is not None and padded > max_voxels:
        blocks = f" in blocks of {block_size}³ (padded to {padded:.4g} voxels)" if padded != voxels else ""
        raise SourceError(f"the source declares {dims} = {voxels:.4g} voxels{blocks}, more than the limit of "
                          f"{max_voxels:.4g} (LODCAST_MAX_VOXELS); nothing was read")
    files, allowed = store_files(lay), FILES_FLOOR + voxels // VOXELS_PER_FILE
    if files > allowed:
        raise SourceError(f"the source declares {dims} voxels, slices of {shape[1]}x{shape[2]}: its store would be "
                          f"{files} files in {lay.grid[0]} rows of blocks of {block_size}³, more than the {allowed} "
                          f"allowed for {voxels} voxels; nothing was read")
    need = working_bytes(shape, dtype, block_size) + held
    if max_memory is not None and need > max_memory:
        kept = f" ({held / 1e6:.0f} MB of it the reader's: a decoded row of chunks, and chunks decoding)" if held else ""
        raise SourceError(f"the source declares {dims} voxels: ingesting slices of {shape[1]}x{shape[2]} needs about "
                          f"{need / 1e6:.0f} MB{kept}, more than the limit of {max_memory / 1e6:.0f} MB "
                          f"(LODCAST_MAX_INGEST_MEMORY_MB); nothing was read")


# --- downsampling --------------------------------------------------------------------------------------------

def level_mean(block_sums: np.ndarray, counts: np.ndarray | None, level: int) -> np.ndarray:
    """Mean of each 2^level-cube from its sum (and its count of valid voxels when NaN were excluded)."""
    if counts is None:
        return block_sums / float(8**level)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, block_sums / np.maximum(counts, 1), np.nan)


def round_to_dtype(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """Integer levels hold the float64 mean rounded half to even (np.rint), clipped to the type's range;
    float levels keep the mean in their own precision."""
    dtype = np.dtype(dtype)
    if dtype.kind in "iu":
        lim = np.iinfo(dtype)
        return np.clip(np.rint(values), lim.min, lim.max).astype(dtype)
    return values.astype(dtype)


def std_dtype(dtype: np.dtype) -> np.dtype:
    """Storage type of the per-voxel standard deviations: float16 for integers of up to 16 bits (a spread of
    such values is at most 32768, inside float16's range, kept to 2^-11 relative), float32 otherwise."""
    dtype = np.dtype(dtype)
    return np.dtype(np.float16) if dtype.kind in "iu" and dtype.itemsize <= 2 else np.dtype(np.float32)


def _pool2(a: np.ndarray) -> np.ndarray:
    """Sums of 2×2×2 cubes (pairwise adds of strided views: several times faster than a 6-D reshape-sum)."""
    a = a[0::2] + a[1::2]
    a = a[:, 0::2] + a[:, 1::2]
    return a[:, :, 0::2] + a[:, :, 1::2]


# --- pass 1: levels and interior statistics ------------------------------------------------------------------

#: level and std arrays are written whole, fill-value chunks included, so that a missing shard file (or chunk) in
#: them is damage, never "empty here": the reader refuses it instead of rendering the fill value
COMPLETE: ArrayConfigParams = {"write_empty_chunks": True}


class _LevelWriter:
    """Collects level-k slabs until a whole shard depth is there, then writes those shards: shards are written once
    (no read-modify-write). The rows wait in a temporary file beside the store rather than in memory (a level-k
    shard is 4^k block-slabs deep: kept in memory, every level's rows came to another slab's worth), and are
    written one band of shards across y at a time, so memory holds one band, by store/shardwrite.py (the array at
    `folder`)."""

    def __init__(self, array: zarr.Array, folder: Path, depth: int, spill: Path):
        self.array = array
        self.shards = ShardWriter(folder)
        self.depth = min(depth, array.shape[0])
        self.spill = spill  # created on first use: level 0 never needs it
        self.file: Any = None
        self.start = 0  # level z of the first row waiting
        self.filled = 0
        self.row = int(np.prod(array.shape[1:])) * array.dtype.itemsize  # bytes of one level row

    def add(self, rows: np.ndarray) -> None:
        n = rows.shape[0]
        if self.filled == 0 and (n == self.depth or self.start + n == self.array.shape[0]):
            self._write(lambda y0, y1: rows[:, y0:y1], n)  # a whole shard depth: nothing to wait for
            return
        if self.file is None:
            self.file = open(self.spill, "w+b")
        self.file.seek(self.filled * self.row)
        self.file.write(np.ascontiguousarray(rows, self.array.dtype))  # its buffer, no bytes copy
        self.filled += n
        if self.filled == self.depth or self.start + self.filled == self.array.shape[0]:
            self.flush()

    def flush(self) -> None:
        if self.filled and self.file is not None:
            self.file.flush()
            self._write(self._waiting, self.filled)
            self.filled = 0

    def close(self) -> None:
        if self.file is not None:
            self.file.close()
            self.file = None
            self.spill.unlink(missing_ok=True)

    def _waiting(self, y0: int, y1: int) -> np.ndarray:
        """Rows [0, filled) of the waiting ones, y in [y0, y1), read back from the temporary file."""
        _, ny, nx = self.array.shape
        out = np.empty((self.filled, y1 - y0, nx), self.array.dtype)
        size = self.array.dtype.itemsize
        for z in range(self.filled):
            self.file.seek(z * self.row + y0 * nx * size)
            self.file.readinto(memoryview(out[z]).cast("B"))
        return out

    def _write(self, band_of: Any, n: int) -> None:
        """One band of shards across y at a time: every call writes whole shards, and the encoding temporaries stay
        a band's size rather than a slab's."""
        band = self.shards.shard[1]
        for y0 in range(0, self.array.shape[1], band):
            y1 = min(y0 + band, self.array.shape[1])
            self.shards.write((self.start, y0, 0), band_of(y0, y1))
        self.start += n


def _strip_levels(slab: np.ndarray, lay: Layout, bz: int, by: int,
                  below: np.ndarray | None) -> tuple[list[np.ndarray], list[np.ndarray], dict[str, Any]]:
    """Levels 1.. of one row of blocks (block row `by` of block-slab `bz`), each cut to its level's true extent,
    the standard deviation of the level-0 values behind every coarse voxel (NaN and edge padding left out: the
    distribution a coarse sample stands for), and the row's interior statistics, with the per-block mean
    within-voxel variance of every level and its cells' grown ranges (_strip_cells; `below`: the previous slab's
    last slice). Working per row keeps the float64 temporaries to a few MB."""
    b = lay.block_size
    strip = slab[:, by * b : (by + 1) * b]
    zs, ny, nx = strip.shape
    px = lay.padded_shape[2]
    padded = np.pad(strip, ((0, b - zs), (0, b - ny), (0, px - nx)), mode="edge") if (zs, ny, nx) != (b, b, px) else strip
    # sums of up to 8 voxels of <= 16-bit integers are exact in float32; everything after level 1 runs in float64
    values: np.ndarray = padded.astype(
        np.float32 if slab.dtype.kind in "iu" and slab.dtype.itemsize <= 2 else np.float64)
    counts = None
    if slab.dtype.kind == "f":
        valid = ~np.isnan(values)
        if not valid.all():
            counts = valid.astype(np.float64)
            values[~valid] = 0.0
    # the spread counts real voxels only: padding replicates the edge, which would shrink it
    real = counts
    if padded is not strip:
        real = np.zeros(padded.shape, np.float64)
        real[:zs, :ny, :nx] = 1.0
        if counts is not None:
            real *= counts
    # the spread from sums of squares about a shift c near the data (E[(v - c)²] − (E[v] − c)²): unshifted, the
    # two terms cancel for data far from zero (a float volume at 1e5 ± 0.01 lost 7 % of its spread)
    c = float(values[:zs, :ny, :nx].mean()) if values.size else 0.0
    if not np.isfinite(c):
        c = 0.0
    sq = np.square(values.astype(np.float64) - c)
    s1 = None
    if real is not None:
        sq *= real
        s1 = values * real
    levels, stds = [], []
    std_max = 0.0
    block_var = np.zeros((lay.grid[2], lay.n_levels))
    for k in range(1, lay.n_levels):
        values = _pool2(values).astype(np.float64, copy=False)
        counts = _pool2(counts) if counts is not None else None
        sq = _pool2(sq)
        mean = level_mean(values, counts, k)
        if real is None:
            n = float(8**k)
            var = sq / n - np.square(values / n - c)
        else:
            assert s1 is not None  # set beside `real`
            s1, real = _pool2(s1), _pool2(real)
            with np.errstate(invalid="ignore", divide="ignore"):
                var = np.where(real > 0, sq / np.maximum(real, 1e-300) - np.square(s1 / np.maximum(real, 1e-300) - c), 0.0)
        np.maximum(var, 0.0, out=var)  # rounding of E[v²] − E[v]² for constant cubes
        lz, ly, lx = lay.level_shape(k)
        e = lay.block_edge(k)
        rows, cols = min(e, lz - bz * e), min(e, ly - by * e)
        levels.append(round_to_dtype(mean[:rows, :cols, :lx], slab.dtype))
        v = var[:rows, :cols, :lx]
        sd = np.sqrt(v)
        std_max = max(std_max, float(sd.max(initial=0.0)))  # exact, before the storage type rounds it
        stds.append(sd.astype(std_dtype(slab.dtype)))  # stored so: a slab's float64 copy would be its size
        starts = np.arange(0, lx, e)
        widths = np.diff(np.append(starts, lx))
        block_var[:, k] = np.add.reduceat(v.sum(axis=(0, 1)), starts) / (rows * cols * widths)
    stats: dict[str, Any] = _interior_stats(strip, b)
    stats["cell_min"], stats["cell_max"] = _strip_cells(slab, lay, by, below)
    stats["level_var"] = block_var
    stats["std_max"] = std_max
    return levels, stds, stats


def _extrema3(lo: np.ndarray, hi: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Three-tap minimum of `lo` and maximum of `hi` along `axis`: each voxel's and its two neighbours' (NaN left
    out; at the ends, the two that exist)."""
    a, b = np.moveaxis(lo, axis, 0), np.moveaxis(hi, axis, 0)
    lo2, hi2 = a.copy(), b.copy()
    if a.shape[0] > 1:
        np.fmin(lo2[1:], a[:-1], out=lo2[1:])
        np.fmin(lo2[:-1], a[1:], out=lo2[:-1])
        np.fmax(hi2[1:], b[:-1], out=hi2[1:])
        np.fmax(hi2[:-1], b[1:], out=hi2[:-1])
    return np.moveaxis(lo2, 0, axis), np.moveaxis(hi2, 0, axis)


def _per_cell(lo: np.ndarray, hi: np.ndarray, cz: int, c: int) -> tuple[np.ndarray, np.ndarray]:
    """The extrema of `lo` and `hi` over cells of cz x c x c voxels from the first (the last ones cut short)."""
    pad = [(0, -n % e) for n, e in zip(lo.shape, (cz, c, c))]
    if any(w for _, w in pad):  # edge copies change no extremum
        lo, hi = np.pad(lo, pad, mode="edge"), np.pad(hi, pad, mode="edge")
    z, y, x = lo.shape
    shape = (z // cz, cz, y // c, c, x // c, c)
    return np.fmin.reduce(lo.reshape(shape), axis=(1, 3, 5)), np.fmax.reduce(hi.reshape(shape), axis=(1, 3, 5))


def _strip_cells(slab: np.ndarray, lay: Layout, by: int, below: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) over every cell (Layout.cell_edge) of block row `by` of a block-slab, grown by one voxel into its
    neighbours (the voxels trilinear interpolation reads for a sample in the cell: full resolution's empty-space
    skipping takes the same), NaN left out; `below`: the previous slab's last slice (None for the first slab). The
    upper border of the slab's last row of cells lies in the next slab: `_slice_cells` adds it."""
    b, c = lay.block_size, lay.cell_edge
    y0, y1 = max(0, by * b - 1), min(slab.shape[1], (by + 1) * b + 1)
    part = slab[:, y0:y1] if below is None else np.concatenate([below[None, y0:y1], slab[:, y0:y1]])
    z0 = 0 if below is None else 1
    # each row of cells over its slices and the one each side first (a c-fold smaller array for the 3-taps)
    rows = range(0, slab.shape[0], c)
    lo = np.stack([np.fmin.reduce(part[max(0, z0 + r - 1):z0 + r + c + 1], axis=0) for r in rows])
    hi = np.stack([np.fmax.reduce(part[max(0, z0 + r - 1):z0 + r + c + 1], axis=0) for r in rows])
    for ax in (1, 2):
        lo, hi = _extrema3(lo, hi, ax)
    ya, ny = by * b - y0, min(b, slab.shape[1] - by * b)
    return _per_cell(lo[:, ya:ya + ny], hi[:, ya:ya + ny], 1, c)


def _slice_cells(plane: np.ndarray, c: int) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) over every column of c x c voxels of one slice, grown by one voxel across y and x: the upper
    border that a slab's last row of cells takes from the next slab's first slice, (1, cells_y, cells_x)."""
    lo, hi = plane[None], plane[None]
    for ax in (1, 2):
        lo, hi = _extrema3(lo, hi, ax)
    return _per_cell(lo, hi, 1, c)


def _outward32(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float32 bounds that hold [lo, hi]: rounded outwards where float32 cannot hold a value."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    lo32, hi32 = lo.astype(np.float32), hi.astype(np.float32)
    with np.errstate(invalid="ignore"):
        lo32 = np.where(lo32 > lo, np.nextafter(lo32, np.float32(-np.inf)), lo32)
        hi32 = np.where(hi32 < hi, np.nextafter(hi32, np.float32(np.inf)), hi32)
    return lo32, hi32


def _interior_stats(strip: np.ndarray, b: int) -> dict[str, np.ndarray]:
    """min, max, sum and count of valid voxels per block of a row of blocks (blocks_x,), padding excluded."""
    xs = np.arange(0, strip.shape[2], b)
    flat = strip.reshape(-1, strip.shape[2])
    if strip.dtype.kind != "f":
        return {
            "min": np.minimum.reduceat(flat.min(axis=0), xs).astype(np.float64),
            "max": np.maximum.reduceat(flat.max(axis=0), xs).astype(np.float64),
            "sum": np.add.reduceat(flat.sum(axis=0, dtype=np.float64), xs),
            "count": np.add.reduceat(np.full(flat.shape[1], flat.shape[0], np.float64), xs),
        }
    v = flat.astype(np.float64)
    valid = ~np.isnan(v)
    return {
        "min": np.fmin.reduceat(np.fmin.reduce(v, axis=0), xs),
        "max": np.fmax.reduceat(np.fmax.reduce(v, axis=0), xs),
        "sum": np.add.reduceat(np.where(valid, v, 0.0).sum(axis=0), xs),
        "count": np.add.reduceat(valid.sum(axis=0, dtype=np.float64), xs),
    }


# --- the writer ----------------------------------------------------------------------------------------------

#: the codecs after every chunk's compressor (format 4: zarr's crc32c; benchmarks/bench_checksums.py writes a store
#: without them to measure what they cost)
CHECKSUMS: tuple[Any, ...] = (Crc32cCodec(),)


class _Unlisted:
    """Arrays at ROOT/PREFIX/NAME with no group node at PREFIX. The level arrays stay the root group's only
    members, so a reader that takes a group's members for the image sees the image alone: napari's built-in
    reader opens the first subgroup if there is one, else the root's arrays in order of name. lodcast opens these
    arrays by path (`std/1`, `blocks/hist`)."""

    def __init__(self, root: Path, prefix: str):
        self.folder = root / prefix

    def create_array(self, name: str, **kwargs: Any) -> zarr.Array:
        """A checksummed array (format 4): its compressor (zarr's default, zstd, unless given), then `crc32c`."""
        kwargs["compressors"] = [kwargs.get("compressors", ZstdCodec(level=0)), *CHECKSUMS]
        return zarr.create_array(store=str(self.folder / name), zarr_format=3, **kwargs)


def _write(src: VolumeSource, root: Path, lay: Layout, n_bins: int, segments: int,
           workers: int | None, show: bool, source_label: str, carried: dict[str, Any] | None = None) -> None:
    """The store of `src` at `root`; `carried`: root attributes that replace the ones ingest derives (what `upgrade`
    carries over from the store it rewrites: the original source, orientation and provenance)."""
    info = src.info
    dtype = np.dtype(info.dtype)
    gz, gy, gx = lay.grid
    group = zarr.open_group(str(root), mode="w", zarr_format=3)
    # the bricks' codec: blosc's lz4 decodes a 16³ chunk about five times faster than zstd for a tenth more bytes,
    # and reading a selection's bricks is mostly decoding them (a cold image, a new view, a pass past the budget)
    compressor = BloscCodec(cname="lz4", clevel=9, shuffle=BloscShuffle.bitshuffle if dtype.itemsize > 1 else BloscShuffle.shuffle)
    writers = []
    for k in range(lay.n_levels):
        arr = group.create_array(
            str(k), shape=lay.level_shape(k), dtype=dtype, chunks=lay.chunk_shape(k), shards=lay.shard_shape(k),
            compressors=[compressor, *CHECKSUMS], fill_value=np.nan if dtype.kind == "f" else 0,
            dimension_names=("z", "y", "x"),
            config=COMPLETE,
        )
        writers.append(_LevelWriter(arr, root / str(k), lay.shard_shape(k)[0], root / f".rows-{k}"))
    std_writers = []
    std_group = _Unlisted(root, "std")
    sdtype = std_dtype(dtype)
    for k in range(1, lay.n_levels):
        arr = std_group.create_array(
            str(k), shape=lay.level_shape(k), dtype=sdtype, chunks=lay.chunk_shape(k), shards=lay.shard_shape(k),
            compressors=BloscCodec(cname="lz4", clevel=9, shuffle=BloscShuffle.bitshuffle), fill_value=0,
            dimension_names=("z", "y", "x"), config=COMPLETE,
        )
        std_writers.append(_LevelWriter(arr, root / "std" / str(k), lay.shard_shape(k)[0], root / f".rows-std-{k}"))
    # per-block statistics go to the store a row of blocks at a time: held whole, they grew ingest's peak with the
    # volume's depth
    blocks = _Unlisted(root, "blocks")
    stats = {name: blocks.create_array(name, shape=lay.grid, dtype=np.float64, chunks=(1, gy, gx), fill_value=np.nan)
             for name in ("min", "max", "mean", "count", "min_border", "max_border")}
    level_std = blocks.create_array("level_std", shape=lay.grid + (lay.n_levels,), dtype=np.float64,
                                    chunks=(1, gy, gx, lay.n_levels), fill_value=0.0)
    cpb, cgrid = lay.block_size // lay.cell_edge, lay.cell_grid  # cells per block edge
    cells = {name: blocks.create_array(name, shape=cgrid, dtype=np.float32, chunks=(cpb,) + cgrid[1:],
                                       fill_value=np.nan) for name in ("cell_min", "cell_max")}
    lo, hi, std_max = np.inf, -np.inf, 0.0
    pool = ThreadPoolExecutor(max_workers=workers or os.cpu_count() or 1)
    reader = ThreadPoolExecutor(max_workers=1)  # sources are read in order, one slab ahead
    bar = _progress(3 * gz, show, f"ingest {Path(source_label).name}")
    try:
        # pass 1: the next slab is read while rows of this one are downsampled on the pool and level 0 is written
        nan_count = 0
        below, pending = None, None  # the last slice of the previous slab; its last row of cells, unwritten
        # a slab of wide slices is read after the last one is done with, not beside it: two would be its memory
        ahead = lay.block_size * lay.shape[1] * lay.shape[2] * dtype.itemsize <= READ_AHEAD_BYTES
        for bz, slab in enumerate(_read_ahead(lambda z: _read_slab(src, lay, z), gz, reader if ahead else None)):
            rows = [pool.submit(_strip_levels, slab, lay, bz, by, below) for by in range(gy)]
            writers[0].add(slab)
            parts = [f.result() for f in rows]
            for k, w in enumerate(writers[1:]):
                w.add(np.concatenate([levels[k] for levels, _, _ in parts], axis=1))
            for k, w in enumerate(std_writers):
                w.add(np.concatenate([stds[k] for _, stds, _ in parts], axis=1))
            std_max = max([std_max] + [p[2]["std_max"] for p in parts])
            st = {key: np.stack([p[2][key] for p in parts]) for key in ("min", "max", "sum", "count", "level_var")}
            # cells: the last row waits for the next slab's first slice (its upper border)
            clo, chi = (np.concatenate([p[2][key] for p in parts], axis=1) for key in ("cell_min", "cell_max"))
            if pending is not None:
                row, plo, phi = pending
                slo, shi = _slice_cells(slab[0], lay.cell_edge)
                _write_cells(cells, row, np.fmin(plo, slo), np.fmax(phi, shi))
            keep = clo.shape[0] - (1 if bz + 1 < gz else 0)
            _write_cells(cells, bz * cpb, clo[:keep], chi[:keep])
            pending = (bz * cpb + keep, clo[keep:], chi[keep:]) if keep < clo.shape[0] else None
            below = slab[-1].copy()
            level_std[bz] = np.sqrt(st["level_var"])
            stats["min"][bz], stats["max"][bz], stats["count"][bz] = st["min"], st["max"], st["count"]
            with np.errstate(invalid="ignore", divide="ignore"):
                stats["mean"][bz] = np.where(st["count"] > 0, st["sum"] / np.maximum(st["count"], 1), np.nan)
            if (st["count"] > 0).any():
                lo, hi = min(lo, float(np.nanmin(st["min"]))), max(hi, float(np.nanmax(st["max"])))
            nan_count += int(slab.size - st["count"].sum())
            bar.update(1)
            del slab, parts, rows  # before the next slab is read
        for w in writers + std_writers:
            w.flush()
            w.close()
        if lo > hi:
            raise SourceError("the volume holds no valid voxel (every value is NaN)")
        bins = Bins.for_range(lo, hi, integer=dtype.kind in "iu", max_bins=n_bins)
        seg = min(segments, bins.count)
        overall = np.zeros(bins.count)  # the volume's histogram (borders counted twice): the omero window
        hist_arr = blocks.create_array("hist", shape=lay.grid + (bins.count,), dtype=np.uint32,
                                       chunks=(1, gy, gx, bins.count), fill_value=0,
                                       compressors=BloscCodec(cname="zstd", clevel=1, shuffle=BloscShuffle.bitshuffle))
        # pass 2: level 0 again, in z order (from the source when that is cheap, else read back from the store).
        # Each piece is counted alone: into its own row of blocks, and a row's first and last slices also into the
        # borders of the rows below and above. A row is complete once the first piece of the next one is counted,
        # so only the piece being counted, the one being read (when pieces are small) and up to three rows of
        # counts are alive.
        level0 = group["0"]
        assert isinstance(level0, zarr.Array)  # created above as an array
        if src.rereads_cheaply:  # pieces of a few slices: a slab of wide slices is this pass's largest array
            read = lambda z0, z1: _read_slices(src, lay, z0, z1)  # noqa: E731
            step = _count_slices(lay, dtype)
        else:  # whole block-slabs: a thinner read of the store would decode each chunk several times
            read = lambda z0, z1: _read_banded(level0, z0, z1)  # noqa: E731
            step = lay.block_size
        pieces = _pieces(lay, step)
        ahead = step * lay.shape[1] * lay.shape[2] * dtype.itemsize <= READ_AHEAD_BYTES  # as in pass 1
        acc: dict[int, list[np.ndarray]] = {}
        for i, piece in enumerate(_read_ahead(lambda j: read(*pieces[j][1:]), len(pieces), reader if ahead else None)):
            bz, z0, z1 = pieces[i]
            below, above = _borders(lay, bz, z0, z1)
            for row, part in zip((bz, bz - 1, bz + 1), _piece_histograms(piece, lay, bins, below, above)):
                if part is not None:
                    _merge(acc, row, part)
            del piece  # without read-ahead, before the next one is read
            for row in ([bz - 1] if below else []) + ([bz] if i == len(pieces) - 1 else []):
                hist, stats["min_border"][row], stats["max_border"][row] = acc.pop(row)
                hist_arr[row] = hist
                overall += hist.reshape(-1, bins.count).sum(axis=0)
                bar.update(1)
        # the simplified histograms, once the volume's data is no longer in memory: the OpenCL device that finds
        # them holds memory of its own (PoCL's compiler and threads) from the moment it starts
        starts_arr = blocks.create_array("hist_starts", shape=lay.grid + (seg + 1,), dtype=np.uint16,
                                         chunks=(1, gy, gx, seg + 1), fill_value=0)
        heights_arr = blocks.create_array("hist_heights", shape=lay.grid + (seg,), dtype=np.float32,
                                          chunks=(1, gy, gx, seg), fill_value=0)
        device = _segmentation_device()
        for row in range(gz):
            starts, heights = simplify(np.asarray(hist_arr[row]).reshape(gy * gx, -1), seg, device=device)
            starts_arr[row], heights_arr[row] = starts.reshape(gy, gx, -1), heights.reshape(gy, gx, -1)
            bar.update(1)
    finally:
        for w in writers + std_writers:
            w.close()
        bar.close()
        reader.shutdown(wait=True, cancel_futures=True)
        pool.shutdown(wait=True, cancel_futures=True)
    attrs = _attributes(src, lay, dtype, (lo, hi), bins, seg, nan_count, root, source_label, std_max)
    attrs["ome"]["omero"] = omero(Path(source_label).name or "volume", overall, bins.edges, (lo, hi))
    attrs["lodcast"]["manifest"] = data_manifest(root)  # what open_store checks: files deleted or cut are noticed
    group.attrs.update({**attrs, **(carried or {})})
    seal(root, group, {w.shards.folder.relative_to(root).as_posix(): w.shards.written for w in writers + std_writers})


def seal(root: Path, group: zarr.Group, known: dict[str, dict[str, list[int]]] | None = None) -> None:
    """Format 4's checksums of everything written (store/checksum.py): the manifest of every data file and array
    zarr.json, and the digests of the root attributes as zarr wrote them, recorded under `lodcast.integrity`."""
    written = json.loads((root / "zarr.json").read_bytes())["attributes"]
    marker = dict(written["lodcast"])
    marker["integrity"] = {"algorithm": "crc32c", "manifest": MANIFEST, "crc32c": write_manifest(root, known),
                           "attributes": attribute_digests(written)}
    group.attrs["lodcast"] = marker


def _segmentation_device() -> Any:
    """An OpenCL device of this ingest's own for the histograms' segmentation (lodcast.opencl, below the store and
    the renderer), or False for NumPy where OpenCL is not installed."""
    try:
        from lodcast.opencl import Device
    except ImportError:
        return False
    return Device()


def _write_cells(cells: dict[str, Any], row: int, lo: np.ndarray, hi: np.ndarray) -> None:
    if lo.shape[0]:
        cells["cell_min"][row : row + lo.shape[0]], cells["cell_max"][row : row + lo.shape[0]] = _outward32(lo, hi)


def _merge(acc: dict[int, list[np.ndarray]], row: int, part: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    if row not in acc:
        acc[row] = [part[0].copy(), part[1].copy(), part[2].copy()]
        return
    acc[row][0] += part[0]
    acc[row][1] = np.fmin(acc[row][1], part[1])
    acc[row][2] = np.fmax(acc[row][2], part[2])


def _count_slices(lay: Layout, dtype: np.dtype) -> int:
    """Slices per piece of pass 2: up to COUNT_BYTES, at least one, at most a block-slab."""
    return max(1, min(lay.block_size, COUNT_BYTES // (lay.shape[1] * lay.shape[2] * np.dtype(dtype).itemsize)))


def _pieces(lay: Layout, step: int) -> list[tuple[int, int, int]]:
    """(row of blocks, z0, z1) of pass 2's pieces: every row cut into runs of `step` slices, in z order."""
    b, depth = lay.block_size, lay.shape[0]
    return [(bz, z0, min(z0 + step, (bz + 1) * b, depth))
            for bz in range(lay.grid[0]) for z0 in range(bz * b, min((bz + 1) * b, depth), step)]


def _borders(lay: Layout, bz: int, z0: int, z1: int) -> tuple[bool, bool]:
    """Whether a piece's first slice borders the row below and its last slice the row above."""
    b = lay.block_size
    return bz > 0 and z0 == bz * b, bz + 1 < lay.grid[0] and z1 == (bz + 1) * b


def _piece_histograms(piece: np.ndarray, lay: Layout, bins: Bins, below: bool, above: bool) -> tuple:
    """A piece's counts for its own row of blocks, and (when it starts or ends that row) those of its first and
    last slices, which are border voxels of the rows below and above (else None)."""
    return (_layer_histograms(piece, lay, bins), _layer_histograms(piece[:1], lay, bins) if below else None,
            _layer_histograms(piece[-1:], lay, bins) if above else None)


def _layer_histograms(layer: np.ndarray, lay: Layout, bins: Bins) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Histograms and min/max of every voxel of `layer` (any number of slices) that falls in each block of the
    row or in its one-voxel border across y and x, as (blocks_y, blocks_x, bins) uint32 and two (blocks_y,
    blocks_x) float64 arrays. The x borders, shared by two blocks, are counted by two extra bincounts over the
    border columns; the y borders come with each row's band."""
    b = lay.block_size
    _, ny, nx = layer.shape
    gy, gx = lay.grid[1:]
    nb = bins.count
    block_of_x = np.arange(nx) // b
    left = np.arange(1, gx) * b - 1  # column left of block 1.., bordering it
    right = np.arange(1, gx) * b  # column right of block ..gx-2, bordering it
    starts = np.arange(0, nx, b)
    hist = np.zeros((gy, gx, nb), np.uint32)
    mn = np.full((gy, gx), np.nan)
    mx = np.full((gy, gx), np.nan)
    for by in range(gy):
        region = layer[:, max(0, by * b - 1) : min(ny, (by + 1) * b + 1)]
        keys = bins.index(region).reshape(-1, nx)
        missing = keys < 0 if region.dtype.kind == "f" else None  # NaN voxels are counted nowhere
        keys += (block_of_x * nb).astype(keys.dtype)
        kl, kr = keys[:, left] + nb, keys[:, right] - nb  # border columns, counted again for their other block
        if missing is not None:
            keys, kl, kr = keys[~missing], kl[~missing[:, left]], kr[~missing[:, right]]
        counts = np.bincount(keys.ravel(), minlength=gx * nb)
        counts += np.bincount(kl.ravel(), minlength=gx * nb)
        counts += np.bincount(kr.ravel(), minlength=gx * nb)
        hist[by] = counts.reshape(gx, nb)
        flat = region.reshape(-1, nx)
        lo_f, hi_f = (np.fmin, np.fmax) if flat.dtype.kind == "f" else (np.minimum, np.maximum)
        cmin, cmax = lo_f.reduce(flat, axis=0), hi_f.reduce(flat, axis=0)
        bmin, bmax = lo_f.reduceat(cmin, starts).astype(np.float64), hi_f.reduceat(cmax, starts).astype(np.float64)
        bmin[1:], bmax[1:] = lo_f(bmin[1:], cmin[left]), hi_f(bmax[1:], cmax[left])
        bmin[:-1], bmax[:-1] = lo_f(bmin[:-1], cmin[right]), hi_f(bmax[:-1], cmax[right])
        mn[by], mx[by] = bmin, bmax
    return hist, mn, mx


def _read_banded(array: zarr.Array, z0: int, z1: int) -> np.ndarray:
    """array[z0:z1] read one band of shards across y at a time, so decoding temporaries stay a band's size."""
    z1 = min(z1, array.shape[0])
    out = np.empty((z1 - z0,) + tuple(array.shape[1:]), array.dtype)
    assert array.shards is not None  # level 0 is created sharded
    band = array.shards[1]
    for y0 in range(0, out.shape[1], band):
        out[:, y0 : y0 + band] = array[z0:z1, y0 : y0 + band]
    return out


def _read_slab(src: VolumeSource, lay: Layout, bz: int) -> np.ndarray:
    b = lay.block_size
    return _read_slices(src, lay, bz * b, min(lay.shape[0], (bz + 1) * b))


def _read_slices(src: VolumeSource, lay: Layout, z0: int, z1: int) -> np.ndarray:
    slab = np.asarray(src.read(z0, z1))
    expected = (z1 - z0,) + tuple(lay.shape[1:])
    if slab.shape != expected:
        raise SourceError(f"reader returned a slab of shape {slab.shape} for z {z0}:{z1}, expected {expected}")
    return slab


def _read_ahead(read: Callable[[int], np.ndarray], count: int,
                reader: ThreadPoolExecutor | None) -> Iterator[np.ndarray]:
    """read(0), read(1), … read(count − 1), each started on `reader` while the previous one is being used (without
    a reader, each when the previous one is done with)."""
    if reader is None:
        for i in range(count):
            yield read(i)
        return
    nxt = reader.submit(read, 0)
    for i in range(count):
        item = nxt.result()
        if i + 1 < count:
            nxt = reader.submit(read, i + 1)
        yield item


def _attributes(src: VolumeSource, lay: Layout, dtype: np.dtype, vrange: tuple[float, float], bins: Bins,
                seg: int, nan_count: int, root: Path, source_label: str, std_max: float) -> dict[str, Any]:
    import lodcast

    info = src.info
    name = (parse_temp_name(root.name) or (root.name,))[0].removesuffix(".zarr")
    return {
        # a new id per ingest: caches keyed by it notice a store rewritten at the same place (object storage has
        # no inode or mtime to tell)
        "lodcast": {"format_version": FORMAT_VERSION, "generation": uuid.uuid4().hex},
        "shape": list(lay.shape),
        "dtype": dtype.name,
        "spacing": list(info.spacing),
        "origin": list(info.origin),
        "units": info.units,
        "block_size": lay.block_size,
        "grid": list(lay.grid),
        "levels": [
            {"path": str(k), "shape": list(lay.level_shape(k)), "block_edge": lay.block_edge(k)} for k in range(lay.n_levels)
        ],
        "value_range": list(vrange),
        "nan_count": nan_count,
        "histogram": {"bins": bins.to_dict(), "segments": seg, "border": 1},
        "downsampling": "mean within each block; integers rounded half to even; edge-replicated padding",
        "distribution": {"kind": "gaussian", "std": "std/{level}", "dtype": std_dtype(dtype).name, "std_max": std_max,
                         "block_level_std": "blocks/level_std"},
        "source": {"path": source_label, "format": info.format, **info.provenance},
        **({} if info.direction is None else {"orientation": {
            "space": info.space, "axes": axis_codes(info.space, info.direction),
            "direction": [list(row) for row in info.direction]}}),
        "provenance": {
            "lodcast_version": lodcast.__version__,
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "zarr_version": zarr.__version__,
        },
        "ome": multiscales(name, lay.n_levels, info.spacing, info.origin, info.units),
    }


# --- sources ---------------------------------------------------------------------------------------------------

def _open(source: Any, options: dict[str, Any]) -> VolumeSource:
    if isinstance(source, VolumeSource):
        return source
    if isinstance(source, np.ndarray):
        unknown = set(options) - {"spacing", "origin", "units"}
        if unknown:
            raise SourceError(f"options {sorted(unknown)} do not apply to an in-memory array")
        return ArraySource(source, **{k: v for k, v in options.items() if v is not None})
    from lodcast.store.readers import open_source

    return open_source(source, **{k: v for k, v in options.items() if v is not None})


def _show_progress(progress: bool | None) -> bool:
    return sys.stderr.isatty() if progress is None else progress


def _progress(total: int, show: bool, desc: str) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="slab", disable=not show, file=sys.stderr, leave=False)
