"""Ingest jobs in a child process (service/queue.py). A cancelled job's ingest is killed wherever it is (in a reader
of a slow file, in a header that spins, between two slabs), so its worker takes the next job within a poll; what the
killed process left (a hidden partial store beside the destination, or the local copy of a store bound for object
storage) is removed as the start-up sweep removes it (store/sweep.py). An error of the child is raised here as
itself, with what lodcast.faults needs to tell a transient storage fault, since its causes do not cross processes."""
from __future__ import annotations

import contextlib
import ctypes
import multiprocessing
import os
import pickle
import signal
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from lodcast.errors import LodcastError
from lodcast.faults import storage_fault

__all__ = ["IngestFailed", "StorageFault", "run_ingest"]

#: prctl's option: the signal this process gets when the thread that started it ends
PR_SET_PDEATHSIG = 1


class IngestFailed(LodcastError):
    """An ingest child's error that could not be sent back as itself (its message kept), or a child that died."""


class StorageFault(ConnectionError):
    """What an ingest child's error is raised from here when it was a transient storage fault (lodcast.faults)."""


@dataclass(frozen=True)
class _Failure:
    error: bytes | None  # the pickled exception, when it pickles and unpickles
    text: str
    fault: str | None  # lodcast.faults' reason, judged in the child where the causes are


def _failure(exc: BaseException) -> _Failure:
    blob: bytes | None
    try:
        blob = pickle.dumps(exc)
        pickle.loads(blob)
    except Exception:  # noqa: BLE001 - an exception that does not round-trip is sent as its message
        blob = None
    return _Failure(blob, str(exc) or type(exc).__name__, storage_fault(exc))


def _die_with(parent: int) -> None:
    """The kernel kills this process when its worker dies, SIGKILL included (Linux; elsewhere nothing), so that a
    killed worker leaves no ingest behind, still writing the volume that the job's next owner writes again."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # the worker died before the line above
        os._exit(1)


def _child(conn: Connection, parent: int, source: str, dest: str, options: dict[str, Any],
           storage: dict[str, Any]) -> None:
    _die_with(parent)
    try:
        from lodcast.malloc import tame_malloc
        from lodcast.service.objectstorage import bound_object_storage
        from lodcast.store.ingest import ingest

        tame_malloc()
        bound_object_storage(**storage)
        ingest(source, dest, progress=False, **options)
        conn.send(None)
    except BaseException as exc:  # noqa: BLE001 - every way it ends is reported to the worker
        conn.send(_failure(exc))
    finally:
        conn.close()


def _sweep(dest: str) -> None:
    """What the killed child left, now that its process is gone."""
    from lodcast.store.remote import is_url

    if is_url(dest):
        from lodcast.store.sweep import sweep_local_copies

        sweep_local_copies()
    else:
        from lodcast.store.atomic import remove_stale

        remove_stale(Path(dest))


def run_ingest(source: str, dest: str | os.PathLike[str], options: dict[str, Any], *, storage: dict[str, Any],
               keep_going: Callable[[], bool], poll_s: float) -> bool:
    """`lodcast.ingest(source, dest, **options)` in a child process (`storage`: service/objectstorage.py's limits).
    `keep_going()` is asked every `poll_s` seconds; once it is false the child is killed, its leftovers removed and
    False returned. True when the ingest is done; its error, raised here, otherwise."""
    ctx = multiprocessing.get_context("spawn")  # not fork: the worker runs threads (heartbeats, huey, renders)
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(send, os.getpid(), source, os.fspath(dest), options, storage), name="lodcast-ingest")
    proc.start()
    send.close()  # the child holds the only writer: its end is an end of file here
    try:
        while not recv.poll(poll_s):
            if not keep_going():
                proc.kill()
                proc.join()
                _sweep(os.fspath(dest))
                return False
        try:
            outcome: _Failure | None = recv.recv()
        except EOFError:  # it died without a word (killed from outside, out of memory)
            proc.join()
            outcome = _Failure(None, f"the ingest process ended with exit code {proc.exitcode}", None)
    finally:
        recv.close()
        if proc.is_alive():  # the worker's own error while it waited: the child goes with it
            proc.kill()
            proc.join()
            _sweep(os.fspath(dest))
        proc.join()
    if outcome is None:
        return True
    err = pickle.loads(outcome.error) if outcome.error is not None else IngestFailed(outcome.text)
    if outcome.fault is not None and storage_fault(err) is None:
        raise err from StorageFault(outcome.fault)
    raise err
