"""An ingest job's worker is free as soon as the job is cancelled (issue 49, item 3): the ingest runs in a child
process that the worker kills, so a reader deep in a slow source cannot hold the worker, and nothing of the killed
ingest is left beside the store root's volumes."""
from __future__ import annotations

import gzip
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from lodcast.service.jobs import IngestJob
from lodcast.service.queue import JobQueue, Worker
from lodcast.service.settings import Settings
from lodcast.service.testing import start_worker
from lodcast.store.store import parse_temp_name


def _slow_nrrd(path: Path, n: int = 256) -> None:
    """A gzip NRRD of n³ voxels whose ingest takes seconds here (varied values: every block has work to do)."""
    voxels = ((np.arange(n**3, dtype=np.uint64) * 2654435761) >> 24).astype(np.uint8)
    with open(path, "wb") as f:
        f.write(f"NRRD0004\ntype: uint8\ndimension: 3\nsizes: {n} {n} {n}\nencoding: gzip\n\n".encode())
        f.write(gzip.compress(voxels.tobytes(), 1))


def _wait(pred, timeout: float = 120.0, what: str = "condition"):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if value := pred():
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def test_a_cancelled_ingest_frees_its_worker_for_the_next_job_and_leaves_nothing(tmp_path: Path):
    src = tmp_path / "sources"
    src.mkdir()
    _slow_nrrd(src / "big.nrrd")
    np.save(src / "small.npy", np.arange(8 * 8 * 8, dtype=np.uint16).reshape(8, 8, 8))
    root = tmp_path / "root"
    root.mkdir()
    jq = JobQueue(Settings(root=root, token=None, poll_s=0.05, heartbeat_s=0.2))
    big = jq.submit(IngestJob(kind="ingest", source=str(src / "big.nrrd"), name="big"))["id"]
    small = jq.submit(IngestJob(kind="ingest", source=str(src / "small.npy"), name="small"))["id"]
    worker = Worker(jq, threads=1, reap=False).start()  # one thread: the small job waits for the big one's end
    try:
        # the big ingest is writing its hidden partial store: it is mid-ingest, in its reading and writing loops
        _wait(lambda: any(p.name.startswith(".big.") for p in root.iterdir()), what="the big ingest's partial store")
        assert jq.get(big)["state"] == "running" and jq.get(small)["state"] == "queued"
        jq.cancel(big)
        _wait(lambda: jq.get(small)["state"] in ("done", "failed"), what="the next job")
    finally:
        worker.stop()
    assert jq.get(small)["state"] == "done", jq.get(small)["error"]
    assert jq.get(big)["state"] == "cancelled"
    # the big ingest was stopped, not finished behind the small one: no store of it, and no partial one
    assert sorted(p.name for p in root.iterdir() if not p.name.startswith(".lodcast")) == ["small"], \
        sorted(p.name for p in root.iterdir())


def _alive(pid: int) -> bool:
    """Whether process `pid` runs (a zombie whose parent is gone does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


def test_an_ingest_dies_with_its_killed_worker(tmp_path: Path):
    """A worker SIGKILLed mid-ingest leaves no ingest process behind (the job's next owner ingests it again)."""
    if not Path("/proc/self/stat").exists():
        pytest.skip("needs Linux's /proc (and prctl)")
    _slow_nrrd(tmp_path / "big.nrrd")
    root = tmp_path / "root"
    root.mkdir()
    jq = JobQueue(Settings(root=root, token=None))
    jq.submit(IngestJob(kind="ingest", source=str(tmp_path / "big.nrrd"), name="big"))
    worker = start_worker(root, env={"LODCAST_POLL_S": "0.05", "LODCAST_TOKEN": ""})
    try:
        partial = _wait(lambda: next((p for p in root.iterdir() if p.name.startswith(".big.")), None),
                        what="the big ingest's partial store")
        owner = parse_temp_name(partial.name)
        assert owner is not None and owner[3] != worker.pid  # written by the worker's ingest process
        os.kill(worker.pid, signal.SIGKILL)  # the worker alone, not its process group
        _wait(lambda: not _alive(owner[3]), timeout=30, what="the ingest process to die with its worker")
    finally:
        worker.stop()
    assert not (root / "big").exists()
