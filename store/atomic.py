"""Ingest's atomic writes: a store is written under a hidden name beside its destination and renamed into place,
so a killed ingest never leaves anything at the destination that opens as a store, and a killed `--overwrite`
loses nothing (the store it had moved aside is put back by the next ingest)."""
from __future__ import annotations

import os
import shutil
from pathlib import Path

from lodcast.errors import StoreExists
from lodcast.store.store import parse_temp_name, temp_path

__all__ = ["remove_stale", "move_into_place"]


def remove_stale(dest: Path) -> None:
    """Leftovers of ingests that were killed (their process is gone): partial stores are removed; a replaced
    store whose successor never arrived is put back, so a kill during `--overwrite` loses nothing."""
    for p in dest.parent.glob(f".{dest.name}.*"):
        parsed = parse_temp_name(p.name)
        if parsed is None or parsed[0] != dest.name or _alive(parsed[2]):
            continue
        if parsed[1] == "replaced" and not dest.exists():
            os.rename(p, dest)
        else:
            shutil.rmtree(p, ignore_errors=True)


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
