"""Batch jobs on huey (SqliteHuey embedded, RedisHuey shared) with a crash-safe job record beside the queue.

huey carries one message per job (the job id). Losing a message is what huey does when a worker dies mid-task, so
the truth is the record (``records.py``): a worker *claims* a queued job by compare-and-set, refreshes a heartbeat
while it runs, and checks before each frame that it still owns the job (a cancelled job stops within one frame). The
reaper (at start-up and every ``reap_every_s``) turns running jobs whose heartbeat went stale back to queued and
enqueues them again, and re-enqueues queued jobs whose message was lost; a duplicate message is harmless because only
one claim succeeds. A resumed job renders only frames whose file is missing, and only the owner can mark it done, so
it completes exactly once. The same code runs on both back ends.
"""
from __future__ import annotations

import builtins
import json
import logging
import os
import re
import signal
import socket
import threading
import time
import uuid
from pathlib import Path
from typing import Any

from lodcast.errors import LodcastError
from lodcast.faults import storage_fault
from lodcast.service.frames import FrameRenderer
from lodcast.service.ingestproc import run_ingest
from lodcast.service.jobs import IngestJob, TurntableJob, encode_animation, frame_ext, parse_job, plan_frames
from lodcast.service.objectstorage import s3_limits
from lodcast.service.records import ACTIVE, Records, open_records
from lodcast.service.rendering import RenderEngine
from lodcast.service.results import JobFiles, drop_upload, frame_name, parked_uploads
from lodcast.service.volumes import JOB_ID, volume_path
from lodcast.store.remote import is_url

__all__ = ["make_huey", "JobQueue", "Worker"]

log = logging.getLogger("lodcast.service.queue")


def make_huey(settings: Any) -> Any:
    """SqliteHuey under the store root by default; RedisHuey when the queue setting is a redis:// URL."""
    if settings.is_redis:
        from huey import RedisHuey

        return RedisHuey(name=settings.queue_name, url=settings.queue, results=False, blocking=True, read_timeout=1)
    from huey import SqliteHuey

    path = settings.sqlite_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    return SqliteHuey(name=settings.queue_name, filename=str(path), results=False, strict_fifo=True, timeout=30)


def _one_line(exc: BaseException) -> str:
    text = " ".join((str(exc) or type(exc).__name__).split())
    return text[:2000]


class JobQueue:
    """Submit, inspect, cancel and run jobs. One per process (HTTP app, worker, CLI)."""

    def __init__(self, settings: Any, records: Records | None = None, engine: RenderEngine | None = None) -> None:
        self.settings = settings
        self.engine = engine or RenderEngine(settings)  # the process's: the app hands its own over
        self.records = records or open_records(settings)
        self.huey = make_huey(settings)
        self._task = self.huey.task(name="lodcast_job", retries=0)(self._execute)
        self._help_task = self.huey.task(name="lodcast_help", retries=0)(self._help)
        self.stopping = threading.Event()
        self.owner_prefix = f"{socket.gethostname()}:{os.getpid()}"

    def check(self) -> None:
        """Raise ValueError naming the queue when its back end cannot be reached (for a one-line CLI error)."""
        try:
            if self.settings.is_redis:
                self.records.client.ping()  # type: ignore[attr-defined]
            self.huey.pending_count()
            self.records.list(limit=1)
        except Exception as exc:  # noqa: BLE001 - any failure to reach the queue is the same user error
            where = self.settings.queue if self.settings.is_redis else str(self.settings.sqlite_path())
            raise ValueError(f"queue: cannot use {where}: {' '.join(str(exc).split())}") from None

    # --- client side ----------------------------------------------------------------------------------------
    def job_dir(self, job_id: str) -> Path:
        """The local folder of a job's results (a root folder's; service/results.py)."""
        if not JOB_ID.match(job_id):
            raise ValueError(f"id: invalid job id {job_id[:40]!r}")
        return self.settings.jobs_dir / job_id

    def files(self, job_id: str) -> JobFiles:
        """A job's results, wherever they live (the state folder, or object storage under a root URL)."""
        if not JOB_ID.match(job_id):
            raise ValueError(f"id: invalid job id {job_id[:40]!r}")
        return JobFiles(self.settings.results, job_id)

    def submit(self, job: Any, *, upload: Path | str | None = None) -> dict[str, Any]:
        job_id = uuid.uuid4().hex
        spec = job.model_dump(mode="json")
        if upload is not None:
            spec["source"], spec["_upload"] = str(upload), True
        now = time.time()
        self.records.create({
            "id": job_id, "kind": job.kind, "spec": json.dumps(spec), "state": "queued",
            "total": len(plan_frames(job)) or 1, "created": now, "enqueued": now,
        })
        self._task(job_id)
        return self.records.get(job_id)  # type: ignore[return-value]

    def get(self, job_id: str) -> dict[str, Any] | None:
        return self.records.get(job_id) if JOB_ID.match(job_id or "") else None

    def list(self, limit: int = 100, states: tuple[str, ...] | None = None) -> list[dict[str, Any]]:
        return self.records.list(limit=limit, states=states)

    def cancel(self, job_id: str) -> dict[str, Any] | None:
        """Mark the job cancelled (a queued job never starts, a running one stops before its next frame). A queued
        upload's file goes at once: nothing will read it."""
        if self.records.update(job_id, {"state": "cancelled", "finished": time.time()}, expect={"state": ("queued",)}):
            spec = json.loads((self.get(job_id) or {}).get("spec") or "{}")
            if spec.get("_upload"):
                drop_upload(spec["source"])
        else:
            self.records.update(job_id, {"state": "cancelled", "finished": time.time()}, expect={"state": ACTIVE})
        return self.get(job_id)

    def sweep_uploads(self) -> builtins.list[str]:
        """Delete uploaded files that no queued or running job will read (a job cancelled while running, a crash
        between an upload's last byte and its job's record) once they are `upload_grace_s` old: an upload still
        arriving is younger, its file being written."""
        folder = self.settings.uploads_dir
        wanted = {json.loads(r["spec"] or "{}").get("source") for r in self.records.list(limit=100_000, states=ACTIVE)
                  if r["kind"] == "ingest"}
        cutoff, gone = time.time() - self.settings.upload_grace_s, []
        for p in (folder.iterdir() if folder.is_dir() else ()):
            try:
                if str(p) not in wanted and p.is_file() and p.stat().st_mtime < cutoff:
                    p.unlink()
                    gone.append(p.name)
            except FileNotFoundError:
                continue
        if self.settings.remote:  # uploads parked on object storage for a worker on another host
            for url, mtime in parked_uploads(f"{self.settings.root}/.uploads"):
                if url not in wanted and mtime < cutoff:
                    drop_upload(url)
                    gone.append(url.rsplit("/", 1)[-1])
        if gone:
            log.info("deleted %d uploaded files no job reads", len(gone))
        return gone

    def wait(self, job_id: str, timeout: float | None = None, poll: float = 0.2) -> dict[str, Any]:
        end = None if timeout is None else time.monotonic() + timeout
        while True:
            rec = self.get(job_id)
            if rec is None:
                raise KeyError(job_id)
            if rec["state"] not in ACTIVE or (end is not None and time.monotonic() > end):
                return rec
            time.sleep(poll)

    def _pending_ids(self) -> set[str]:
        try:
            return {str(t.args[0]) for t in self.huey.pending() if t.args and t.name == "lodcast_job"}
        except Exception:  # an unreadable message must not stop the reaper
            log.exception("could not list pending messages")
            return set()

    def reap(self) -> builtins.list[str]:
        """Re-enqueue running jobs whose heartbeat is stale and queued jobs whose message was lost."""
        now = time.time()
        stale = now - self.settings.stale_after_s
        out: list[str] = []
        pending: set[str] | None = None
        for rec in self.records.list(limit=100_000, states=ACTIVE):
            jid = rec["id"]
            if rec["state"] == "running" and (rec["heartbeat"] or 0.0) < stale:
                if self.records.update(
                    jid, {"state": "queued", "owner": None, "enqueued": now},
                    expect={"state": ("running",), "owner": (rec["owner"],), "heartbeat": (rec["heartbeat"],)},
                ):
                    log.warning("job %s: heartbeat stale (owner %s), re-enqueued", jid, rec["owner"])
                    self.records.drop_leases(jid, rec["owner"])  # its frame in flight is free at once
                    self._task(jid)
                    out.append(jid)
            elif rec["state"] == "queued" and (rec["enqueued"] or 0.0) < stale:
                if pending is None:
                    pending = self._pending_ids()
                if jid not in pending and self.records.update(jid, {"enqueued": now}, expect={"state": ("queued",)}):
                    log.warning("job %s: queued without a message, re-enqueued", jid)
                    self._task(jid)
                    out.append(jid)
        return out

    def expire(self) -> builtins.list[str]:
        """Delete jobs that ended more than `keep_jobs_s` ago: results first, then the record, so that a crash
        between the two leaves a record that the next call finds again (never results without a record)."""
        keep = self.settings.keep_jobs_s
        if not keep:
            return []
        gone = []
        for jid in self.records.finished_before(time.time() - keep):
            self.delete_results(jid)
            self.records.drop_leases(jid)
            if self.records.delete_final(jid):
                gone.append(jid)
        if gone:
            log.info("deleted %d jobs that ended more than %.0f s ago", len(gone), keep)
        return gone

    # --- worker side ----------------------------------------------------------------------------------------
    def _execute(self, job_id: str) -> None:
        rec = self.records.get(job_id)
        if rec is None or rec["state"] != "queued":
            return  # done, cancelled, or another worker's: a duplicate message
        if self.stopping.is_set():
            self._task(job_id)  # hand the message back for another worker
            return
        owner = f"{self.owner_prefix}:{uuid.uuid4().hex[:8]}"
        now = time.time()
        if not self.records.update(
            job_id,
            {"state": "running", "owner": owner, "heartbeat": now, "started": rec["started"] or now,
             "attempts": int(rec["attempts"] or 0) + 1},
            expect={"state": ("queued",)},
        ):
            return
        beat = threading.Event()
        hb = threading.Thread(target=self._heartbeat, args=(job_id, owner, beat), daemon=True, name=f"hb-{job_id[:8]}")
        hb.start()
        try:
            outcome = self._run_resuming(job_id, owner, rec)
            if outcome == "done":
                cur = self.records.get(job_id) or rec
                self.records.update(
                    job_id,
                    {"state": "done", "finished": time.time(), "done": cur["total"], "error": None,
                     "completions": int(cur["completions"] or 0) + 1},
                    expect={"state": ("running",), "owner": (owner,)},
                )
        except Exception as exc:  # the job's own failure, or a storage fault past its retries: recorded
            if isinstance(exc, LodcastError):  # a refusal whose message says it all (a hostile upload): no traceback
                log.warning("job %s failed: %s", job_id, _one_line(exc))
            else:
                log.exception("job %s failed", job_id)
            self.records.update(job_id, {"state": "failed", "error": self._unplaced(_one_line(exc)), "finished": time.time()},
                                expect={"state": ("running",), "owner": (owner,)})
        finally:
            beat.set()
            hb.join(timeout=5)
            self.records.drop_leases(job_id, owner)

    def _run_resuming(self, job_id: str, owner: str, rec: dict[str, Any]) -> str:
        """`_run`, resumed after a transient storage fault (lodcast.faults: object storage unreachable or
        throttling, a full disk) up to `storage_retries` times, waiting `storage_backoff_s`, doubled each time (at
        most 60 s), before each: a resumed job renders only the frames it has not written. The job stays running
        and its heartbeat beats meanwhile; its `error` says what it waits for."""
        attempt = 0
        while True:
            try:
                return self._run(job_id, owner, rec)
            except Exception as exc:
                why = storage_fault(exc)
                if why is None or attempt == self.settings.storage_retries:
                    raise
                wait = min(60.0, self.settings.storage_backoff_s * 2.0**attempt)
                log.warning("job %s: storage fault (%s); resumed in %.1f s", job_id, why, wait)
                self.records.update(job_id, {"error": self._unplaced(f"storage fault, retry {attempt + 1} of "
                                                                     f"{self.settings.storage_retries} in "
                                                                     f"{wait:g} s: {why}")},
                                    expect={"state": ("running",), "owner": (owner,)})
                if self.stopping.wait(wait):
                    self._release(job_id, owner)
                    return "released"
                if not self._mine(job_id, owner):
                    return "lost"
                attempt += 1

    def _unplaced(self, message: str) -> str:
        """A job's error as its client may read it: paths relative to the store root and the import roots (an
        upload's file is "the upload"), never where they lie on the server."""
        message = re.sub(r"\S*/\.uploads/[0-9a-f]{32}(?:\.\w+)+", "the upload", message)  # a local file or a parked object
        for base in (*self.settings.import_roots, self.settings.root):
            message = message.replace(str(base) + os.sep, "").replace(str(base), ".")
        return message

    def _heartbeat(self, job_id: str, owner: str, stop: threading.Event) -> None:
        while not stop.wait(self.settings.heartbeat_s):
            try:
                if not self.records.update(job_id, {"heartbeat": time.time()},
                                           expect={"state": ("running",), "owner": (owner,)}):
                    return
            except Exception:
                log.exception("heartbeat of job %s", job_id)

    def _mine(self, job_id: str, owner: str) -> bool:
        rec = self.records.get(job_id)
        if not rec:
            return False
        return rec["state"] == "running" and rec["owner"] == owner

    def _release(self, job_id: str, owner: str) -> None:
        """Graceful stop: put the job back in the queue for another worker, keeping its frames."""
        if self.records.update(job_id, {"state": "queued", "owner": None, "enqueued": time.time()},
                               expect={"state": ("running",), "owner": (owner,)}):
            self._task(job_id)

    def _run(self, job_id: str, owner: str, rec: dict[str, Any]) -> str:
        spec = json.loads(rec["spec"])
        upload = bool(spec.pop("_upload", False))
        job = parse_job(spec)
        if isinstance(job, IngestJob):
            return self._run_ingest(job_id, owner, job, rec, upload)
        plan = plan_frames(job)
        files = self.files(job_id)
        files.clear_partial()  # a frame half-written by a worker that died: never a result
        names = [frame_name(i, frame_ext(s)) for i, (_, s) in enumerate(plan)]
        there = files.names()
        self.records.update(job_id, {"total": len(plan), "done": len(there & set(names))}, expect={"owner": (owner,)})
        for _ in range(min(self.settings.job_helpers, len(plan) - 1)):
            self._help_task(job_id)  # idle workers, here or on other hosts, take frames of this job beside this one
        frames = FrameRenderer(self.settings, self.records, job_id, plan, files, names, self.engine)
        todo = [i for i in range(len(plan)) if names[i] not in there]  # frames written before a crash or a release
        while todo:
            took = False
            for n, i in enumerate(todo):
                if files.exists(names[i]):
                    continue  # a helper's
                if not self._mine(job_id, owner):
                    return "lost"  # cancelled, or re-assigned after a stall
                if self.stopping.is_set():
                    self._release(job_id, owner)
                    return "released"
                took |= frames.render(i, owner, todo[n + 1] if n + 1 < len(todo) else None)
            there = files.names()
            todo = [i for i in todo if names[i] not in there]
            if todo and not took:  # the rest are under helpers' leases: their frames come, or a dead one's lapses
                if not self._mine(job_id, owner):
                    return "lost"
                if self.stopping.wait(self.settings.poll_s):
                    self._release(job_id, owner)
                    return "released"
        files.clear_partial()  # what a helper killed mid-write left
        if isinstance(job, TurntableJob) and job.animation:
            out = f"turntable.{job.animation}"
            if not files.exists(out):
                if not self._mine(job_id, owner):
                    return "lost"
                files.write(out, encode_animation([(n, files.read(n)) for n in names], job.animation, job.fps))
        return "done" if self._mine(job_id, owner) else "lost"

    def _help(self, job_id: str) -> None:
        """A help message (enqueued by the job's owner): render frames of the running job that no one has leased,
        beside its owner, until none is left. Never marks the job done (its owner does, once every frame is
        there); a frame that fails here is left to the owner, which renders it and reports the error."""
        rec = self.records.get(job_id)
        if rec is None or rec["state"] != "running" or self.stopping.is_set():
            return
        spec = json.loads(rec["spec"])
        spec.pop("_upload", None)
        job = parse_job(spec)
        if isinstance(job, IngestJob):
            return
        plan = plan_frames(job)
        files = self.files(job_id)
        names = [frame_name(i, frame_ext(s)) for i, (_, s) in enumerate(plan)]
        helper = f"{self.owner_prefix}:{uuid.uuid4().hex[:8]}:helper"
        frames = FrameRenderer(self.settings, self.records, job_id, plan, files, names, self.engine)
        try:
            there = files.names()
            for i in range(len(plan)):
                cur = self.records.get(job_id)
                if self.stopping.is_set() or cur is None or cur["state"] != "running":
                    return
                if names[i] not in there:
                    frames.render(i, helper, i + 1 if i + 1 < len(plan) else None)
        except Exception:  # noqa: BLE001 - the owner meets the same error on that frame and records it
            log.exception("job %s: a helper's frame failed; left to the job's owner", job_id)
        finally:
            self.records.drop_leases(job_id, helper)

    def _run_ingest(self, job_id: str, owner: str, job: IngestJob, rec: dict[str, Any], upload: bool) -> str:
        from lodcast.errors import StoreExists

        dest = volume_path(self.settings.root, job.name, must_exist=False, field="name")
        source, fetched = job.source, None
        if upload and is_url(source):  # parked on object storage by the API host (it may be another host): fetch it
            import fsspec

            fetched = self.settings.uploads_dir / f"{job_id}-{source.rsplit('/', 1)[-1]}"
            fetched.parent.mkdir(parents=True, exist_ok=True)
            fs, path = fsspec.core.url_to_fs(source)
            fs.get(path, str(fetched))
            source = str(fetched)
        try:
            # an upload is one file: it may not name others (a detached NRRD header could read any server file)
            options = {"overwrite": job.overwrite, "max_voxels": self.settings.max_voxels,
                       "max_memory": int(self.settings.max_ingest_memory_mb * 1e6), **job.options,
                       **({"detached": False} if upload else {})}
            # in a child process, killed when the job is cancelled (or taken from this worker): the worker is free
            if not run_ingest(source, dest, options, storage=s3_limits(self.settings), poll_s=self.settings.poll_s,
                              keep_going=lambda: self._mine(job_id, owner)):
                return "lost"
        except StoreExists:
            if int(rec["attempts"] or 0) < 1:  # a retry after a crash that happened after the rename: it is done
                raise
        except Exception as exc:
            if upload and storage_fault(exc) is None:  # the job fails for good: the upload is of no further use
                drop_upload(job.source)
            raise
        finally:
            if fetched is not None:
                fetched.unlink(missing_ok=True)
        if upload:
            drop_upload(job.source)
        self.engine.forget(dest)
        self.records.update(job_id, {"done": 1}, expect={"owner": (owner,)})
        return "done" if self._mine(job_id, owner) else "lost"

    def delete_results(self, job_id: str) -> None:
        self.files(job_id).delete()


class Worker:
    """Threads that take messages from huey and run them, plus the reaper. Used in-process by `lodcast serve`
    and as the `lodcast worker` process."""

    def __init__(self, jobs: JobQueue, threads: int = 1, reap: bool = True) -> None:
        self.jobs = jobs
        self.n = threads
        self.reap = reap
        self._threads: list[threading.Thread] = []

    def start(self) -> "Worker":
        if self.reap:
            t = threading.Thread(target=self._reaper, daemon=True, name="lodcast-reaper")
            t.start()
            self._threads.append(t)
        for i in range(self.n):
            t = threading.Thread(target=self._loop, daemon=True, name=f"lodcast-worker-{i}")
            t.start()
            self._threads.append(t)
        return self

    def _loop(self) -> None:
        stopping = self.jobs.stopping
        while not stopping.is_set():
            try:
                task = self.jobs.huey.dequeue()
            except Exception:
                log.exception("dequeue failed; retrying")
                stopping.wait(1.0)
                continue
            if task is None:
                if not self.jobs.settings.is_redis:
                    stopping.wait(self.jobs.settings.poll_s)
                continue
            try:
                self.jobs.huey.execute(task)
            except Exception:
                log.exception("task %s", task)

    def _reaper(self) -> None:
        stopping = self.jobs.stopping
        expired_at = float("-inf")
        while True:
            try:
                self.jobs.reap()
                if time.monotonic() - expired_at >= self.jobs.settings.expire_every_s:
                    expired_at = time.monotonic()
                    self.jobs.expire()
                    self.jobs.sweep_uploads()
            except Exception:
                log.exception("reaper")
            if stopping.wait(self.jobs.settings.reap_every_s):
                return

    def stop(self, timeout: float = 30.0) -> None:
        """Graceful: running jobs stop before their next frame and go back to the queue."""
        self.jobs.stopping.set()
        end = time.monotonic() + timeout
        for t in self._threads:
            t.join(timeout=max(0.0, end - time.monotonic()))

    def run_forever(self) -> int:
        """The `lodcast worker` main loop: SIGTERM / SIGINT stop gracefully."""
        def handler(signum: int, frame: Any) -> None:
            self.jobs.stopping.set()

        signal.signal(signal.SIGTERM, handler)
        signal.signal(signal.SIGINT, handler)
        self.start()
        while not self.jobs.stopping.wait(0.5):
            pass
        self.stop()
        return 0
