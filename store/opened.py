"""Opened stores, kept by whoever owns an OpenStores (each renderer has one: renderer/engine.py). Opening a store
reads its zarr.json files and block statistics and checks the data manifest (a walk over every shard file); a
render that names its store by path or URL opens it once, not per call, so that a series of renders (views, TFs) also keeps the renderer's caches
that hang on the opened store, such as the selection's per-TF tables. A store replaced at the same place (ingest
with --overwrite renames a new folder into place; on object storage a new root zarr.json is published) is opened
anew. While the storage under a kept store has a transient fault (object storage unreachable or throttling), the
check whether it was replaced cannot be made, and the kept store goes on serving what its caches hold: an outage
does not stop renders whose bricks are cached. `lodcast.open_store` itself always opens afresh."""
from __future__ import annotations

import os
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Any

from lodcast.faults import storage_fault

__all__ = ["OpenStores", "stamp"]


def _key(location: str | os.PathLike[str]) -> Path | str:
    """A URL as given, a local path made absolute (so that "ct.zarr" and "./ct.zarr" are one store)."""
    if isinstance(location, str) and "://" in location:
        return location
    return Path(os.path.abspath(os.fspath(location)))


def stamp(location: Path | str) -> tuple | None:
    """What changes when the store at `location` is replaced: its root zarr.json's inode and modification time,
    or on object storage that object's ETag, modification time and size. None where there is none to read (the
    open that follows says what is wrong); a transient storage fault (lodcast.faults) is raised."""
    if isinstance(location, str):
        import fsspec

        try:
            fs, p = fsspec.core.url_to_fs(location)
            info = fs.info(f"{p.rstrip('/')}/zarr.json", refresh=True)
        except (OSError, ValueError) as exc:  # FileNotFoundError included
            if storage_fault(exc):
                raise
            return None
        return info.get("ETag"), str(info.get("LastModified") or info.get("mtime") or ""), info.get("size")
    try:
        st = (location / "zarr.json").stat()
    except OSError as exc:
        if storage_fault(exc):
            raise
        return None
    return st.st_ino, st.st_mtime_ns


class OpenStores:
    """Up to `max_open` opened stores by path or URL, least recently used dropped first."""

    def __init__(self, max_open: int = 32) -> None:
        if max_open < 1:
            raise ValueError(f"max_open must be at least 1, got {max_open}")
        self._stores: OrderedDict[Path | str, tuple[tuple, Any]] = OrderedDict()  # key -> (stamp, store)
        self._lock = threading.Lock()
        self._max_open = max_open

    def get(self, location: str | os.PathLike[str]) -> Any:
        """The opened store at `location`, opened now if it is not kept or was replaced since."""
        from lodcast.store.store import open_store

        key = _key(location)
        try:
            st = stamp(key)
        except Exception as exc:
            with self._lock:
                kept = self._stores.get(key)
            if kept is not None and storage_fault(exc):
                return kept[1]  # whether it was replaced cannot be asked now: what is kept serves on
            raise
        with self._lock:
            hit = self._stores.get(key)
            if hit is not None and st is not None and hit[0] == st:
                self._stores.move_to_end(key)
                return hit[1]
        store = open_store(key)
        if st is not None:
            with self._lock:
                self._stores[key] = (st, store)
                self._stores.move_to_end(key)
                while len(self._stores) > self._max_open:
                    self._stores.popitem(last=False)
        return store

    def kept(self, location: str | os.PathLike[str]) -> bool:
        """Whether a store is kept open for `location`."""
        with self._lock:
            return _key(location) in self._stores

    def forget(self, location: str | os.PathLike[str]) -> None:
        """Drop the store at `location` (deleted, or about to be replaced)."""
        with self._lock:
            self._stores.pop(_key(location), None)

