"""Ingest's atomic writes: a store is written under a hidden name beside its destination and renamed into place,
so a killed ingest never leaves anything at the destination that opens as a store, and a killed `--overwrite`
loses nothing (the store it had moved aside is put back by the next ingest)."""
from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

from lodcast.errors import StoreExists
from lodcast.store.store import host_tag, parse_temp_name, temp_path

__all__ = ["remove_stale", "move_into_place", "fsync_tree", "fsync_dir", "FOREIGN_STALE_S"]

#: another host's ingest folder is taken for a leftover of a dead ingest after this long untouched (its process
#: cannot be asked from here)
FOREIGN_STALE_S = 24 * 3600.0


def remove_stale(dest: Path) -> None:
    """Leftovers of ingests that were killed (their process is gone; on another host sharing the folder: untouched
    for FOREIGN_STALE_S): partial stores are removed; a replaced store whose successor never arrived is put back,
    so a kill during `--overwrite` loses nothing."""
    for p in dest.parent.glob(f".{dest.name}.*"):
        parsed = parse_temp_name(p.name)
        if parsed is None or parsed[0] != dest.name or _running(p, parsed[2], parsed[3]):
            continue
        if parsed[1] == "replaced" and not dest.exists():
            os.rename(p, dest)
        else:
            shutil.rmtree(p, ignore_errors=True)


def _running(p: Path, host: str | None, pid: int) -> bool:
    """Whether the ingest that owns folder `p` may still be running."""
    if host is None or host == host_tag():
        return _alive(pid)
    try:
        return time.time() - p.stat().st_mtime < FOREIGN_STALE_S
    except FileNotFoundError:
        return True  # gone meanwhile: nothing to do


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def move_into_place(tmp: Path, dest: Path, overwrite: bool) -> None:
    if not dest.exists():
        os.rename(tmp, dest)
        return
    if not overwrite:
        raise StoreExists(f"destination {dest} appeared while ingesting (use --overwrite to replace it)")
    # the old store goes to a hidden name first; a kill between the two renames leaves it there, and the next
    # ingest to this destination puts it back (see remove_stale)
    old = temp_path(dest, "replaced")
    os.rename(dest, old)
    os.rename(tmp, dest)
    shutil.rmtree(old, ignore_errors=True)


def fsync_tree(root: Path) -> None:
    """Flush every file and folder under `root` to disk: a rename that publishes `root` afterwards cannot outlive,
    after a power loss, the data it names."""
    for dirpath, _, names in os.walk(root):
        for name in names:
            fd = os.open(os.path.join(dirpath, name), os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        fsync_dir(Path(dirpath))


def fsync_dir(folder: Path) -> None:
    """Flush a folder's entries (a rename in it) to disk."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
