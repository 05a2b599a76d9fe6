"""`lodcast upgrade`: an older store rewritten as the current format, in place, without its source.

The store's level 0 is the source: ingest runs again on it (the same downsampling, statistics and histograms, so
every level holds the voxels it held, and format 4 adds the checksums), under a hidden name beside the store;
the new store is flushed to disk and renamed over the old one (store/atomic.py), so a killed upgrade leaves the
old store as it was (or moved aside for an instant: the next upgrade or ingest of that path puts it back). Integer voxels wider than the stored-type rule's (store/source.py: narrowest_integer over the
store's value range) are stored in the rule's type: the same values in fewer bytes. The root attributes that
describe the original source (its path, format, orientation, provenance) are carried over."""
from __future__ import annotations

import datetime as _dt
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lodcast.errors import StoreInvalid
from lodcast.store.atomic import fsync_dir, fsync_tree, move_into_place, remove_stale
from lodcast.store.histogram import DEFAULT_BINS
from lodcast.store.layout import Layout
from lodcast.store.source import SourceInfo, VolumeSource, narrowest_integer
from lodcast.store.store import FORMAT_VERSION, Store, open_store, temp_path

__all__ = ["upgrade", "upgraded_dtype", "Upgraded"]


def upgraded_dtype(store: Store) -> np.dtype:
    """The type an upgrade stores: the rule's for integer voxels (lo and hi of the value range are whole), else
    the stored type (float voxels keep their type: their coarse levels hold unrounded means)."""
    if store.dtype.kind in "iu":
        return narrowest_integer(*store.value_range) or store.dtype
    return store.dtype


class _LevelZero(VolumeSource):
    """An opened store's level 0 as a source, in `dtype` (which holds every value: checked by the caller)."""

    rereads_cheaply = False

    def __init__(self, store: Store, dtype: np.dtype) -> None:
        self._store = store
        source = store.attrs.get("source") or {}
        self.info = SourceInfo(shape=store.shape, dtype=dtype, spacing=store.spacing, origin=store.origin,
                               units=store.units, format=str(source.get("format", "lodcast")))

    def read(self, z0: int, z1: int) -> np.ndarray:
        return self._store.read_region(0, (slice(z0, z1), slice(None), slice(None)), self.info.dtype)


@dataclass(frozen=True)
class Upgraded:
    """What `upgrade` did: the store as it is now, and the format and type it had (the same: nothing to do)."""

    store: Store
    from_format: int
    from_dtype: str

    @property
    def rewritten(self) -> bool:
        return (self.from_format, self.from_dtype) != (self.store.format_version, self.store.dtype.name)


def upgrade(path: str | os.PathLike[str], *, progress: bool = False, workers: int | None = None) -> Upgraded:
    """Rewrite the local store at `path` in the current format (and stored type) in place. A store already current
    is left alone. Raises StoreNotFound / StoreInvalid /
    StoreCorrupt for what is not a readable store (a damaged store is not rewritten: its damage would be sealed)."""
    from lodcast.store.ingest import _write

    location = os.fspath(path)
    if "://" in location:
        raise StoreInvalid(f"{location}: upgrade rewrites local stores (download it, upgrade it, upload it)")
    remove_stale(Path(location))  # first: it puts back a store that a killed upgrade had moved aside
    old = open_store(location)
    dtype = upgraded_dtype(old)
    if old.format_version == FORMAT_VERSION and dtype == old.dtype:
        return Upgraded(old, old.format_version, old.dtype.name)
    dest = Path(location)
    keep: dict[str, Any] = {k: old.attrs[k] for k in ("source", "orientation") if k in old.attrs}
    stamp = {"from_format": old.format_version, "from_dtype": old.dtype.name,
             "at": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")}
    keep["provenance"] = {**(old.attrs.get("provenance") or {}), "upgraded": stamp}
    bins = int(old.attrs["histogram"]["bins"].get("count", DEFAULT_BINS))
    tmp = temp_path(dest, "partial")
    try:
        _write(_LevelZero(old, dtype), tmp, Layout(old.shape, old.block_size), max(bins, DEFAULT_BINS),
               old.segments, workers, progress, str((old.attrs.get("source") or {}).get("path", dest.name)), keep)
        fsync_tree(tmp)
        move_into_place(tmp, dest, overwrite=True)
        fsync_dir(dest.parent)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return Upgraded(open_store(dest), old.format_version, old.dtype.name)
