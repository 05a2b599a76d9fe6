"""Opened stores, kept by whoever owns an OpenStores (each renderer has one: renderer/engine.py). Opening a store
reads its zarr.json files and block statistics and checks the data manifest (a walk over every shard file); a
render that names its store by path or URL opens it once, not per call, so that a series of renders (views, TFs) also keeps the renderer's caches
that hang on the opened store, such as the selection's per-TF tables. A store replaced at the same place (ingest
with --overwrite renames a new folder into place; on object storage a new root zarr.json is published) is opened
anew. While the storage under a kept store has a transient fault (object storage unreachable or throttling), the
check whether it was replaced cannot be made, and the kept store goes on serving what its caches hold: an outage
does not stop renders whose bricks are cached. `lodcast.open_store` itself always opens afresh.

How many stay opened is LODCAST_OPEN_STORES (a `lodcast serve` process has one renderer, so one such bound); the
least recently used goes first. What the engine's caches hold of a dropped store is keyed by its path and stamp,
not by the opened object, so its bricks and device buffers serve it again once it is reopened, until they age out
of their own byte bounds."""
from __future__ import annotations

import os
import threading
import time
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
    """Up to `max_open` opened stores by path or URL, least recently used dropped first (dropping one closes
    nothing that a render still holds; the next `get` opens it again). `check_s`: a store on object storage,
    once found and opened, is trusted this long before its root metadata is asked again (was it replaced or
    removed?); a local store's check is a stat, made every time."""

    def __init__(self, max_open: int = 32, check_s: float = 0.0) -> None:
        if max_open < 1:
            raise ValueError(f"max_open must be at least 1, got {max_open}")
        if not check_s >= 0:
            raise ValueError(f"check_s must be a non-negative number of seconds, got {check_s}")
        # key -> (stamp, store, when the stamp was last read: time.monotonic())
        self._stores: OrderedDict[Path | str, tuple[tuple, Any, float]] = OrderedDict()
        self._lock = threading.Lock()
        self._opening: dict[Path | str, list] = {}  # key -> [the lock of its open, the callers using that lock]
        self._max_open = max_open
        self._check_s = float(check_s)

    @property
    def max_open(self) -> int:
        return self._max_open

    def __len__(self) -> int:
        with self._lock:
            return len(self._stores)

    def _trusted(self, key: Path | str) -> Any:
        """The store kept for `key` when it is on object storage and was checked less than `check_s` ago, else
        None; a hit is the most recently used."""
        if not isinstance(key, str) or self._check_s <= 0:
            return None
        with self._lock:
            hit = self._stores.get(key)
            if hit is None or time.monotonic() - hit[2] >= self._check_s:
                return None
            self._stores.move_to_end(key)
            return hit[1]

    def recent(self, location: str | os.PathLike[str]) -> bool:
        """Whether the store at `location` is kept and trusted without asking the storage (see `check_s`)."""
        return self._trusted(_key(location)) is not None

    def get(self, location: str | os.PathLike[str]) -> Any:
        """The opened store at `location`, opened now if it is not kept or was replaced since."""
        from lodcast.store.store import open_store

        key = _key(location)
        trusted = self._trusted(key)
        if trusted is not None:
            return trusted
        try:
            st = stamp(key)
        except Exception as exc:
            with self._lock:
                kept = self._stores.get(key)
            if kept is not None and storage_fault(exc):
                return kept[1]  # whether it was replaced cannot be asked now: what is kept serves on
            raise
        now = time.monotonic()
        hit = self._hit(key, st, now)
        if hit is not None:
            return hit
        # one open per store at a time: renders of a volume that arrive together (viewers joining it, a render
        # and its cost check) share one opened store, so the caches keyed by it compute each table once
        with self._lock:
            opening = self._opening.setdefault(key, [threading.Lock(), 0])
            opening[1] += 1
        try:
            with opening[0]:
                hit = self._hit(key, st, now)
                if hit is not None:
                    return hit
                store = open_store(key)
                if st is not None:
                    with self._lock:
                        self._stores[key] = (st, store, now)
                        self._stores.move_to_end(key)
                        while len(self._stores) > self._max_open:
                            self._stores.popitem(last=False)
                return store
        finally:
            with self._lock:
                opening[1] -= 1
                if not opening[1]:
                    del self._opening[key]

    def _hit(self, key: Path | str, st: tuple | None, now: float) -> Any:
        """The store kept for `key` if it has stamp `st` (now the most recently used, checked at `now`), else None."""
        with self._lock:
            hit = self._stores.get(key)
            if hit is None or st is None or hit[0] != st:
                return None
            self._stores[key] = (st, hit[1], now)
            self._stores.move_to_end(key)
            return hit[1]

    def kept(self, location: str | os.PathLike[str]) -> bool:
        """Whether a store is kept open for `location`."""
        with self._lock:
            return _key(location) in self._stores

    def forget(self, location: str | os.PathLike[str]) -> None:
        """Drop the store at `location` (deleted, or about to be replaced)."""
        with self._lock:
            self._stores.pop(_key(location), None)
