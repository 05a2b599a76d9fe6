"""Reading a lodcast store: a zarr v3 group of level arrays, per-block metadata arrays and attributes.

Layout of a store (all written by `lodcast.store.ingest`):

- attributes: `shape`, `dtype`, `spacing`, `origin` (z, y, x; world = index × spacing + origin at voxel centres),
  `units`, `block_size`, `grid`, `levels` (one entry per level array), `value_range` (NaN-free), `histogram`
  (bins and segment count), `nan_count`, `source` (what was read), `provenance` (who wrote it, when), and the
  OME-Zarr 0.5 block under `ome`;
- arrays `0` … `L`: level k, shape ceil(shape / 2^k), inner chunks of one block (or a cube of blocks once blocks
  are under 16 samples across), grouped into shards by the sharding codec;
- arrays `std/1` … `std/L`: the standard deviation of the level-0 values behind each voxel of level k;
- arrays under `blocks/`, indexed by block (z, y, x): `min`, `max`, `mean`, `count` over the block's own valid
  voxels, `min_border`, `max_border` and `hist` over the block grown by one voxel into its neighbours, and the
  simplified histogram `hist_starts` (bin index where each piece starts, plus the end) and `hist_heights`.

`std/` and `blocks/` have no group node (stores written before this layout have one there and read the same),
so that the level arrays are the root group's only members: what napari's built-in reader and other tools that
list a group's members take for the image.
"""
from __future__ import annotations

import json
import os
import re
import socket
import uuid
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from types import EllipsisType
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from lodcast.errors import StoreCorrupt, StoreInvalid, StoreNotFound
from lodcast.store.checksum import Manifest
from lodcast.store.histogram import Bins
from lodcast.store.integrity import array_problems, attribute_problems, load_manifest, value_range_problem
from lodcast.store.layout import Layout

if TYPE_CHECKING:  # pragma: no cover
    import zarr

__all__ = ["Store", "BlockStats", "open_store", "data_manifest", "check_metadata", "read_local", "FORMAT_VERSION",
           "READABLE_VERSIONS"]

#: 2: adds the distribution behind every coarse voxel (`std/{level}`, `blocks/level_std`). Stores of format 1
#: still open and render; they have no distributions, so coarse samples are classified at their mean.
#: 3: adds the level-0 value range of every cell of Layout.cell_edge³ voxels (`blocks/cell_min`, `cell_max`).
#: Stores of format 2 still open and render; coarse samples are then taken wherever their own field can show
#: something, as before (renderer/frame/render.py: `_cell_info`).
#: 4: checksums (store/checksum.py): zarr's `crc32c` codec after every chunk and shard index, a manifest binding
#: every data file and array zarr.json to its place, digests of the root attributes; LPS orientation and the
#: stored-type rule (smallest of uint8, int8, uint16, int16 that holds the values, else float32) come with it.
#: Stores of format 3 and older still open and render, without those checks (`lodcast upgrade` rewrites them).
FORMAT_VERSION = 4
READABLE_VERSIONS = (1, 2, 3, 4)


@dataclass(frozen=True)
class BlockStats:
    """Per-block statistics, each shaped like the block grid. NaN where a block has no valid voxel."""

    min: np.ndarray
    max: np.ndarray
    mean: np.ndarray
    count: np.ndarray
    min_border: np.ndarray
    max_border: np.ndarray


class Store:
    """An opened lodcast store. Cheap to create; arrays are read on demand. A local store opens from its
    zarr.json files alone (store/shardio.py reads the arrays): zarr-python is imported only when `group` or
    `level` is asked for, or for a read the readers leave to it."""

    def __init__(self, location: str, attrs: dict, group: zarr.Group | None = None,
                 checksums: Manifest | None = None):
        self.location = location
        #: what ingest wrote, file by file (format 4, local stores): the readers check every shard against it
        self.checksums = checksums
        if group is not None:
            self.__dict__["group"] = group
        a = dict(attrs)
        try:
            marker = a["lodcast"]
            self.format_version = marker.get("format_version")
            if self.format_version not in READABLE_VERSIONS:
                raise StoreInvalid(
                    f"{location}: store format version {self.format_version} is not one of {READABLE_VERSIONS}: "
                    "re-ingest it with this lodcast"
                )
            self.attrs = a
            self.shape: tuple[int, int, int] = tuple(int(v) for v in a["shape"])  # type: ignore[assignment]
            self.dtype = np.dtype(a["dtype"])
            self.spacing: tuple[float, float, float] = tuple(float(v) for v in a["spacing"])  # type: ignore[assignment]
            self.origin: tuple[float, float, float] = tuple(float(v) for v in a["origin"])  # type: ignore[assignment]
            self.units: str = a["units"]
            self.block_size: int = int(a["block_size"])
            self.value_range: tuple[float, float] = (float(a["value_range"][0]), float(a["value_range"][1]))
            self.bins = Bins(**a["histogram"]["bins"])
            self.segments = int(a["histogram"]["segments"])
        except KeyError as exc:
            raise StoreInvalid(f"{location} is not a complete lodcast store: attribute {exc} is missing") from None
        self.layout = Layout(self.shape, self.block_size)
        self._readers: dict[str, Any] = {}  # array path -> ShardedReader, or False: zarr-python reads it
        self._arrays: dict[str, Any] = {}  # array path -> zarr.Array, opened once

    @cached_property
    def group(self) -> zarr.Group:
        """The store's root group (zarr-python)."""
        import zarr

        return zarr.open_group(self.location, mode="r")

    # --- geometry -------------------------------------------------------------------------------------------
    @property
    def n_levels(self) -> int:
        return self.layout.n_levels

    @property
    def grid(self) -> tuple[int, int, int]:
        return self.layout.grid

    @property
    def name(self) -> str:
        return Path(self.location.rstrip("/")).name.removesuffix(".zarr")

    @property
    def box(self) -> tuple[np.ndarray, np.ndarray]:
        """World-space box (lower, upper) corners in (z, y, x): half a voxel beyond the outermost centres."""
        sp, org, shp = (np.asarray(v, np.float64) for v in (self.spacing, self.origin, self.shape))
        return org - sp / 2, org + (shp - 0.5) * sp

    def level_geometry(self, k: int) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """(spacing, origin) of level k, z-y-x in world units: its voxels are 2^k level-0 voxels across, the first
        one's centre (2^k - 1)/2 level-0 voxels past level 0's first centre (as the OME metadata says)."""
        self.layout._check_level(k)
        f = float(1 << k)
        sp = tuple(s * f for s in self.spacing)
        org = tuple(o + s * (f - 1.0) / 2.0 for o, s in zip(self.origin, self.spacing))
        return sp, org  # type: ignore[return-value]

    def to_xarray(self, level: int = 0) -> Any:
        """Level `level` as an `xarray.DataArray` (dims z, y, x; coordinates in world units at voxel centres,
        named with the store's units; attrs: units, orientation, value range). The data stay on disk (a lazy
        zarr array) until asked for. Needs xarray (`pip install "lodcast[interop]"`): `xarray.open_zarr` cannot
        read OME-Zarr multiscales, whose levels are arrays of one group."""
        try:
            import xarray as xr
        except ImportError:
            raise ImportError('Store.to_xarray needs xarray: pip install "lodcast[interop]" (or xarray)') from None
        sp, org = self.level_geometry(level)
        arr = self.level(level)
        coords = {ax: (ax, org[i] + sp[i] * np.arange(arr.shape[i]), {"units": self.units})
                  for i, ax in enumerate(("z", "y", "x"))}
        return xr.DataArray(arr, dims=("z", "y", "x"), coords=coords, name=self.name,
                            attrs={"units": self.units, "level": level, "value_range": list(self.value_range),
                                   "orientation": self.orientation, "source": self.location})

    # --- data -----------------------------------------------------------------------------------------------
    def level(self, k: int) -> zarr.Array:
        self.layout._check_level(k)
        return self._array(str(k))

    def _array(self, path: str) -> zarr.Array:
        """The array at `path`, opened once (on object storage each opening costs requests for its metadata)."""
        a = self._arrays.get(path)
        if a is None:
            a = self._arrays[path] = cast("zarr.Array", self.group[path])  # every path asked for names an array
        return a

    def read_region(self, k: int, region: tuple | EllipsisType = ..., dtype: Any = None,
                    out: np.ndarray | None = None) -> np.ndarray:
        """Samples `region` (a tuple of slices, or ... for all) of level k, in `dtype` when given (into `out`, an
        array of the region's shape, when given)."""
        return self._read(str(k), region, dtype, out)

    def _reader(self, path: str) -> Any:
        """The shard-level reader of the array at `path` (store/shardio.py), or False where zarr-python reads."""
        reader = self._readers.get(path)
        if reader is None:
            from lodcast.store.shardio import fast_reader

            complete = self.manifest is not None and not path.startswith("blocks")  # levels and std: every chunk
            digests = None if self.checksums is None else self.checksums.files.get(path, {})
            if "://" in self.location:
                reader = fast_reader(self._array(path), complete, self.location, digests=digests)
            else:
                reader = fast_reader(Path(self.location) / path, complete, digests=digests)
            reader = self._readers[path] = reader or False
        return reader

    def _read(self, path: str, region: tuple | EllipsisType, dtype: Any = None,
              out: np.ndarray | None = None) -> np.ndarray:
        """A region of the array at `path` through the shard-level reader (store/shardio.py: locally far less per
        chunk than zarr-python on 16³ and 8³ blocks; on object storage a few range requests per shard instead of
        one per chunk), else through zarr-python."""
        reader = self._reader(path)
        if reader is not False:
            return reader.read_region(region, dtype, out)
        import zarr

        # zarr decodes one inner chunk at a time unless batched: batching shortens reads of a whole level of small
        # blocks
        with zarr.config.set({"codec_pipeline.batch_size": 256}):
            a = np.asarray(self._array(path)[region], dtype=dtype)
        if out is None:
            return a
        out[...] = a
        return out

    def read_level(self, k: int) -> np.ndarray:
        return self.read_region(k)

    def read_chunks(self, k: int, chunks: Any, std: bool = False) -> np.ndarray:
        """The inner chunks of level k (std: of its standard deviations, `read_std_region`'s array) at chunk
        coordinates `chunks` (n, 3), all in one shard, as one (n, *chunk) array in the array's own type: each the
        level's region under it and, past the level's end, that region's last samples repeated (as a brick is
        padded). What a brick loader needs when the bricks it wants lie scattered over a shard, without the rest
        of their bounding box."""
        c = self.layout.chunk_shape(k)  # (checks k)
        shape = self.layout.level_shape(k)
        coords = np.asarray(chunks, np.int64).reshape(-1, 3)
        if std and (k == 0 or not self.has_distribution):
            return np.zeros((len(coords), *c), np.float32)
        path = f"std/{k}" if std else str(k)
        reader = self._reader(path)
        if reader is not False:
            box = reader.read_chunks(coords).astype(reader.dtype, copy=False)
        else:
            parts = [self._read(path, tuple(slice(a, min(a + n, s)) for a, n, s in zip(co, c, shape)))
                     for co in (coords * c).tolist()]
            box = np.empty((len(coords), *c), parts[0].dtype if parts else np.float32)
            for b, a in zip(box, parts):
                b[tuple(slice(0, n) for n in a.shape)] = a
        for i in np.flatnonzero(((coords + 1) * c > shape).any(axis=1)).tolist():  # a chunk the level ends inside
            e = [min(n, s - a * n) for a, n, s in zip(coords[i].tolist(), c, shape)]
            box[i] = np.pad(box[i][:e[0], :e[1], :e[2]], [(0, n - m) for n, m in zip(c, e)], mode="edge")
        return box

    @cached_property
    def generation(self) -> str | None:
        """A new id per ingest (None for stores written before it was recorded)."""
        return (self.attrs["lodcast"] or {}).get("generation")

    @cached_property
    def manifest(self) -> dict | None:
        """What ingest wrote (data_manifest), or None for stores written before it was recorded."""
        return (self.attrs["lodcast"] or {}).get("manifest")

    @property
    def has_distribution(self) -> bool:
        """Whether the store keeps the spread of the level-0 values behind every coarse voxel (format >= 2)."""
        return self.format_version >= 2

    @cached_property
    def cell_ranges(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(min, max) of the level-0 values of every cell of Layout.cell_edge³ voxels, over Layout.cell_grid,
        float32 rounded outwards, NaN where a cell holds no valid voxel (edge padding never counted); None for a
        store of format < 3."""
        if self.format_version < 3:
            return None
        return self._read("blocks/cell_min", ...), self._read("blocks/cell_max", ...)

    @property
    def std_max(self) -> float:
        """The largest stored standard deviation (0 for a format-1 store)."""
        return float(self.attrs.get("distribution", {}).get("std_max", 0.0)) if self.has_distribution else 0.0

    def read_std_region(self, k: int, region: tuple | EllipsisType = ...) -> np.ndarray:
        """Standard deviation of the level-0 values behind each sample of `region` of level k (NaN and edge
        padding left out; zeros at level 0 and for a format-1 store, which keeps no distributions)."""
        self.layout._check_level(k)
        if k == 0 or not self.has_distribution:
            full = self.layout.level_shape(k)
            sl = (slice(None),) * 3 if region is ... else region
            return np.zeros(tuple(len(range(*s.indices(n))) for s, n in zip(sl, full)), np.float32)
        return self._read(f"std/{k}", region)

    def read_brick(self, k: int, block: tuple[int, int, int]) -> np.ndarray:
        """Block `block` at level k as a full (B/2^k)³ brick; samples past the volume repeat the edge (the same
        padding ingest averaged into the coarser levels)."""
        region = self.layout.block_region(*block, level=k)
        data = self.read_region(k, region)
        e = self.layout.block_edge(k)
        pad = [(0, e - n) for n in data.shape]
        return np.pad(data, pad, mode="edge") if any(p for _, p in pad) else data

    @cached_property
    def stats(self) -> BlockStats:
        """The per-block statistics; StoreCorrupt when the root's value range is not theirs (an edited attribute
        would mis-place every histogram bin and transfer-function lookup)."""
        stats = BlockStats(**{f: self._read(f"blocks/{f}", ...)
                              for f in ("min", "max", "mean", "count", "min_border", "max_border")})
        problem = value_range_problem(self.location, self.value_range, stats.min, stats.max)
        if problem is not None:
            raise problem
        return stats

    @cached_property
    def level_std(self) -> np.ndarray | None:
        """Per block and level, grid + (levels,): the RMS over the block's coarse voxels of their standard
        deviation (level 0: 0). None for a format-1 store."""
        return self._read("blocks/level_std", ...) if self.has_distribution else None

    @cached_property
    def hist(self) -> np.ndarray:
        """Border-inclusive histograms, shape grid + (bins,), uint32."""
        return self._read("blocks/hist", ...)

    @property
    def hist_edges(self) -> np.ndarray:
        return self.bins.edges

    @cached_property
    def hist_simplified(self) -> tuple[np.ndarray, np.ndarray]:
        """(starts, heights): grid + (segments + 1,) bin indices and grid + (segments,) mean counts per bin."""
        return self._read("blocks/hist_starts", ...), self._read("blocks/hist_heights", ...)

    # --- reporting ------------------------------------------------------------------------------------------
    def bytes_on_disk(self) -> int | None:
        """Size of every file of the store; on object storage of every object (one listing); None where the
        filesystem cannot list (plain HTTP)."""
        if "://" in self.location:
            import fsspec

            try:
                fs, path = fsspec.core.url_to_fs(self.location)
                return int(fs.du(path.rstrip("/"), total=True))
            except (NotImplementedError, OSError, ValueError):
                return None
        root = Path(self.location)
        if not root.is_dir():
            return None
        return sum(f.stat().st_size for f in root.rglob("*") if f.is_file())

    @cached_property
    def orientation(self) -> list[str] | None:
        """The patient direction of world +x, +y, +z, e.g. ["L", "P", "S"] for an axial DICOM CT or any store
        ingested with the default orient="LPS", ["R", "A", "S"] for a NIfTI kept in its own axes (orient="source") (store/orientation.py); None
        when the source gave no patient geometry."""
        from lodcast.store.orientation import legacy_axis_codes

        if "orientation" in self.attrs:
            return self.attrs["orientation"]["axes"]
        return legacy_axis_codes(self.attrs.get("source") or {})

    @property
    def direction(self) -> list[list[float]] | None:
        """Unit vectors of world x, y, z in the source's space (LPS for patient data; near the identity, the tilt
        of an oblique acquisition); None when the source gave no geometry or the store predates it."""
        return (self.attrs.get("orientation") or {}).get("direction")

    def summary(self) -> dict[str, Any]:
        """What `lodcast info` prints."""
        lay = self.layout
        levels = [
            {
                "path": str(k),
                "shape": list(lay.level_shape(k)),
                "block_edge": lay.block_edge(k),
                "chunks": list(lay.chunk_shape(k)),
                "shards": list(lay.shard_shape(k)),
                "shard_count": lay.shard_count(k),
                "scale": [s * (1 << k) for s in self.spacing],
            }
            for k in range(lay.n_levels)
        ]
        return {
            "path": self.location,
            "shape": list(self.shape),
            "dtype": self.dtype.name,
            "spacing": list(self.spacing),
            "origin": list(self.origin),
            "units": self.units,
            "orientation": self.orientation,
            "direction": self.direction,
            "block_size": self.block_size,
            "levels": levels,
            "value_range": list(self.value_range),
            "nan_count": int(self.attrs.get("nan_count", 0)),
            "grid": list(lay.grid),
            "blocks": lay.n_blocks,
            "shards": sum(lvl["shard_count"] for lvl in levels),
            "bytes_on_disk": self.bytes_on_disk(),
            "histogram": self.attrs["histogram"],
            "format_version": self.format_version,
            "distribution": self.attrs.get("distribution"),  # None: format 1, coarse samples classified by the mean
            # the level-0 value range of every cell (blocks/cell_min, cell_max); None: format < 3
            "cells": {"edge": lay.cell_edge, "grid": list(lay.cell_grid)} if self.format_version >= 3 else None,
            "source": self.attrs.get("source", {}),
            "provenance": self.attrs.get("provenance", {}),
        }

    def __repr__(self) -> str:
        return f"Store({self.location!r}, shape={self.shape}, dtype={self.dtype.name}, block_size={self.block_size})"


# Ingest's hidden folders beside a destination DEST: `.DEST.partial-PID-HEX`, the store being written (renamed into
# place only after its last write), and `.DEST.replaced-PID-HEX`, the store an `--overwrite` moved aside.
_TEMP_NAME = re.compile(r"^\.(?P<dest>.+)\.(?P<kind>partial|replaced)-(?:(?P<host>[A-Za-z0-9_-]+)@)?(?P<pid>\d+)"
                        r"-[0-9a-f]{8}$")


def host_tag() -> str:
    """This host's name as ingest's hidden folders carry it (several hosts may share a store root)."""
    return re.sub(r"[^A-Za-z0-9_-]", "-", socket.gethostname())[:64] or "host"


def temp_path(dest: Path, kind: str) -> Path:
    """A new hidden folder of `kind` ("partial" or "replaced") for this process beside `dest`: unique across the
    hosts that share the folder (host, pid and a random part)."""
    assert kind in ("partial", "replaced")
    return dest.parent / f".{dest.name}.{kind}-{host_tag()}@{os.getpid()}-{uuid.uuid4().hex[:8]}"


def parse_temp_name(name: str) -> tuple[str, str, str | None, int] | None:
    """(destination name, kind, owner host (None: a name from before hosts were recorded), owner pid) of an
    ingest's hidden folder name; None for any other name."""
    m = _TEMP_NAME.match(name)
    return (m["dest"], m["kind"], m["host"], int(m["pid"])) if m else None


def data_manifest(root: Path) -> dict[str, list[int]]:
    """Per array of the store (its path in the group, e.g. "0", "std/1", "blocks/hist"): [number of chunk or shard
    files, their total bytes] — what ingest wrote, recorded in its attributes and checked by open_store."""
    root = Path(root)

    def scan(folder: str) -> tuple[str, int, int, list[str]]:
        n = size = 0
        folders = []
        with os.scandir(folder) as entries:
            for e in entries:
                if e.is_dir(follow_symlinks=False):
                    folders.append(e.path)
                elif not e.is_dir():  # (a link to a folder is neither followed nor counted, as os.walk does)
                    n, size = n + 1, size + e.stat().st_size
        return folder, n, size, folders

    out: dict[str, list[int]] = {}
    # folders on a thread pool: a large store has tens of thousands of files, whose stats from a cold disk one by
    # one took seconds of a first picture (waiting on the disk, not the CPU)
    with ThreadPoolExecutor(16, thread_name_prefix="lodcast-manifest") as pool:
        pending = [pool.submit(scan, str(root))]
        while pending:
            folder, n, size, folders = pending.pop().result()
            pending += [pool.submit(scan, f) for f in folders]
            parts = Path(folder).relative_to(root).parts
            if "c" not in parts or not n:
                continue
            entry = out.setdefault("/".join(parts[: parts.index("c")]), [0, 0])
            entry[0] += n
            entry[1] += size
    return out


def _check_manifest(location: str, recorded: dict) -> None:
    found = data_manifest(Path(location))
    for path in sorted(set(recorded) | set(found)):
        want, got = recorded.get(path, [0, 0]), found.get(path, [0, 0])
        if list(want) != list(got):
            raise StoreCorrupt(
                f"{location}: array {path!r} has {got[0]} data files ({got[1]} bytes) on disk, ingest wrote {want[0]} "
                f"({want[1]} bytes): the store is damaged or was changed, re-ingest it")


def open_store(path_or_url: str | os.PathLike[str]) -> Store:
    """Open a store written by `lodcast.ingest`: a local folder, or an fsspec URL (s3://…, https://…)."""
    location = os.fspath(path_or_url)
    is_url = "://" in location
    if not is_url:
        p = Path(location)
        if not p.exists():
            raise StoreNotFound(f"no store at {location}")
        if parse_temp_name(p.name) is not None:  # may look whole at a given instant, yet is not a store
            raise StoreInvalid(f"{location} is a temporary folder of an unfinished ingest, not a store")
        if not (p / "zarr.json").is_file():
            raise StoreInvalid(f"{location} is not a lodcast store (no zarr.json: not a zarr v3 group)")
    attrs: dict[str, Any]
    if is_url:
        import zarr

        try:
            group = zarr.open_group(location, mode="r")
        except FileNotFoundError:
            raise StoreNotFound(f"no store at {location}") from None
        except Exception as exc:  # zarr raises several types for foreign or corrupt metadata
            raise StoreInvalid(f"{location} is not a readable zarr v3 group: {exc}") from None
        attrs = dict(group.attrs)
    else:  # the root's zarr.json alone: what zarr-python's open_group checks of it
        group = None
        try:
            meta = json.loads((Path(location) / "zarr.json").read_bytes())
            if not isinstance(meta, dict) or meta.get("zarr_format") != 3 or meta.get("node_type") != "group":
                raise ValueError("its zarr.json does not describe a zarr v3 group")
            attrs = meta.get("attributes") or {}
            if not isinstance(attrs, dict):
                raise ValueError("its attributes are not an object")
        except (OSError, ValueError) as exc:
            raise StoreInvalid(f"{location} is not a readable zarr v3 group: {exc}") from None
    if "lodcast" not in attrs:
        raise StoreInvalid(f"{location} is a zarr group but not a lodcast store (no 'lodcast' attribute)")
    for problem in attribute_problems(location, attrs):  # before the attributes are used
        raise problem
    store = Store(location, attrs, group)
    if not is_url:  # (on object storage a listing of every file would cost a request per page of a large store)
        manifest = (attrs["lodcast"] or {}).get("manifest")
        if manifest is not None:
            _check_manifest(location, manifest)
    store.checksums = check_metadata(store, read_url(location) if is_url else read_local(location))
    return store


def read_local(location: str) -> Callable[[str], bytes]:
    """A reader of the files of the local store at `location` by relative path."""
    return lambda rel: (Path(location) / rel).read_bytes()


def read_url(location: str) -> Callable[[str], bytes]:
    """A reader of the objects of the store at URL `location` by relative path (fsspec; FileNotFoundError where
    one is missing, as a local reader)."""
    import fsspec

    fs, root = fsspec.core.url_to_fs(location)
    return lambda rel: fs.cat_file(f"{root.rstrip('/')}/{rel}")


def check_metadata(store: Store, read: Callable[[str], bytes]) -> Manifest | None:
    """What opening a store checks before any voxel is read, once its root attributes are (store/integrity.py): its
    manifest (format 4) and every array's zarr.json, read by `read`; raises the first StoreCorrupt. Returns the
    manifest (None for a store written before checksums): each shard is checked against it when its index is
    first read, locally and on object storage alike."""
    manifest = load_manifest(store.location, store.attrs, read)
    for problem in array_problems(store.location, store.attrs, store.layout, store.format_version, manifest, read):
        raise problem
    return manifest
