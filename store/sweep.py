"""Start-up sweeps of what killed ingests leave: `lodcast serve` and `lodcast worker` call `sweep` once, before
they take work. An ingest to object storage writes its store into a local folder named by host and pid
(``lodcast-ingest-HOST@PID-XXXXXXXX`` under ``LODCAST_TMP``, else the system's temporary folder); an ingest into a
store root writes a hidden ``.NAME.partial-HOST@PID-XXXXXXXX`` beside its destination (store/store.py: temp_path).
A folder whose owner on this host is gone is removed (a replaced store whose successor never arrived is put back,
store/atomic.py: remove_stale); another host's folders are left to that host, or to a day's age."""
from __future__ import annotations

import os
import re
import shutil
import tempfile
from pathlib import Path

from lodcast.environment import environment
from lodcast.store.atomic import remove_stale
from lodcast.store.store import host_tag, parse_temp_name

__all__ = ["LOCAL_COPY", "local_copy", "sweep", "sweep_local_copies", "sweep_partials"]

LOCAL_COPY = re.compile(r"^lodcast-ingest-(?P<host>[A-Za-z0-9_-]+)@(?P<pid>\d+)-")


def local_copy() -> Path:
    """A new folder for an ingest's local copy of a store bound for object storage, named by host and pid."""
    return Path(tempfile.mkdtemp(prefix=f"lodcast-ingest-{host_tag()}@{os.getpid()}-", dir=environment().tmp))


def sweep_local_copies(folder: Path | None = None) -> list[str]:
    """Remove the local copies of ingests to object storage whose process on this host is gone."""
    from lodcast.store.atomic import _alive

    base = Path(folder if folder is not None else (environment().tmp or tempfile.gettempdir()))
    gone = []
    for p in base.glob("lodcast-ingest-*") if base.is_dir() else ():
        m = LOCAL_COPY.match(p.name)
        if m and m["host"] == host_tag() and not _alive(int(m["pid"])):
            shutil.rmtree(p, ignore_errors=True)
            gone.append(p.name)
    return gone


def sweep_partials(root: Path) -> list[str]:
    """remove_stale for every destination under the store root `root` that has hidden ingest folders."""
    names = {parsed[0] for p in root.glob(".*") if (parsed := parse_temp_name(p.name)) is not None}
    before = {p.name for p in root.glob(".*")}
    for name in sorted(names):
        remove_stale(root / name)
    return sorted(before - {p.name for p in root.glob(".*")})


def sweep(root: Path | str) -> list[str]:
    """Both sweeps (a root URL has no hidden folders of its own: its ingests write local copies)."""
    gone = sweep_local_copies()
    if not isinstance(root, str) and Path(root).is_dir():
        gone += sweep_partials(Path(root))
    return gone
