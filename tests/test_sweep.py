"""Start-up sweeps (issue 49, item 2): what a SIGKILLed ingest leaves (a local copy of a store bound for object
storage, a hidden partial folder beside a destination) is removed once its process is gone, never while it runs."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

from lodcast.store.store import host_tag
from lodcast.store.sweep import sweep, sweep_local_copies

MAKE_COPY = ("import sys, time; from lodcast.store.sweep import local_copy; p = local_copy(); "
             "(p / 'part.bin').write_bytes(b'x' * 1000); print(p, flush=True); time.sleep(600)")


def _owner(tmp: Path) -> tuple[subprocess.Popen, Path]:
    """A process that made a local copy under `tmp` (LODCAST_TMP) and holds it."""
    proc = subprocess.Popen([sys.executable, "-c", MAKE_COPY], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "LODCAST_TMP": str(tmp)})
    assert proc.stdout is not None
    return proc, Path(proc.stdout.readline().strip())


def test_a_killed_ingests_local_copy_is_swept_and_a_running_ones_kept(tmp_path):
    killed, left = _owner(tmp_path)
    running, held = _owner(tmp_path)
    try:
        assert left.name.startswith(f"lodcast-ingest-{host_tag()}@{killed.pid}-") and left.is_dir()
        killed.send_signal(signal.SIGKILL)
        killed.wait(10)
        assert left.is_dir()  # SIGKILL ran no clean-up
        assert sweep_local_copies(tmp_path) == [left.name]
        assert not left.exists() and held.is_dir()
        other = tmp_path / f"lodcast-ingest-otherhost@{killed.pid}-abcdefgh"
        other.mkdir()  # another host's: its pid means nothing here
        assert sweep_local_copies(tmp_path) == [] and other.is_dir()
    finally:
        running.kill()
        running.wait(10)


def test_hidden_partial_folders_of_dead_ingests_are_swept_from_the_root(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait(10)
    root = tmp_path / "root"
    root.mkdir()
    gone = root / f".ct.zarr.partial-{host_tag()}@{dead.pid}-0badc0de"
    live = root / f".mr.zarr.partial-{host_tag()}@{os.getpid()}-0badc0de"
    for p in (gone, live):
        p.mkdir()
        (p / "zarr.json").write_text("{}")
    (root / ".lodcast").mkdir()  # the queue's folder: no ingest's
    assert sweep(root) == [gone.name]
    assert not gone.exists() and live.is_dir() and (root / ".lodcast").is_dir()
