"""A job's files: where its results live, and where an upload waits for its ingest job.

Results:  ``<results>/<job id>/frame_NNNNN.<png|npy>`` (and ``turntable.<gif|mp4>``).

With a store root folder, ``<results>`` is the state folder's ``.jobs/`` (a shared filesystem when workers run on
several hosts). With a root URL (``s3://bucket/prefix``) it is ``ROOT/.jobs/`` on the same object storage, so that
every host sharing the queue reads what any worker wrote, with nothing shared but the queue and the bucket. Either
way a result is complete or absent: a local file is written to a temporary name and renamed, an object is one PUT.

Uploads: a file sent to `POST /volumes/{id}/upload` lands in the state folder's ``.uploads/``; with a root URL the
API host parks it under ``ROOT/.uploads/`` on the object storage, so that a worker on any host can ingest it.
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

from lodcast.service.jobs import write_atomic
from lodcast.store.atomic import fsync_dir
from lodcast.store.remote import is_url

__all__ = ["JobFiles", "frame_name", "park_upload", "drop_upload", "parked_uploads"]


def frame_name(n: int, ext: str) -> str:
    return f"frame_{n:05d}.{ext}"


class JobFiles:
    """The result files of one job under `base` (a folder, or a URL: a str)."""

    def __init__(self, base: Path | str, job_id: str) -> None:
        self.fs: Any = None
        if isinstance(base, str):
            import fsspec

            self.fs, path = fsspec.core.url_to_fs(base)
            self.dir: Path | str = f"{path.rstrip('/')}/{job_id}"
        else:
            self.dir = Path(base) / job_id

    def _at(self, name: str) -> Path | str:
        return f"{self.dir}/{name}" if self.fs is not None else Path(self.dir) / name

    def names(self) -> set[str]:
        """The complete results there now (one listing)."""
        if self.fs is not None:
            self.fs.invalidate_cache(self.dir)
            try:
                return {str(p).rstrip("/").rsplit("/", 1)[-1] for p in self.fs.ls(self.dir, detail=False)}
            except FileNotFoundError:
                return set()
        try:
            return {n for n in os.listdir(self.dir) if not n.startswith(".")}
        except FileNotFoundError:
            return set()

    def frames(self) -> list[str]:
        return sorted(n for n in self.names() if n.startswith("frame_"))

    def exists(self, name: str) -> bool:
        if self.fs is not None:
            self.fs.invalidate_cache(self.dir)
            return bool(self.fs.exists(self._at(name)))
        return Path(self._at(name)).is_file()

    def write(self, name: str, data: bytes) -> None:
        if self.fs is not None:
            self.fs.pipe(self._at(name), data)  # one PUT: the object is complete or absent
            return
        folder = Path(self.dir)
        if not folder.is_dir():
            folder.mkdir(parents=True, exist_ok=True)
            fsync_dir(folder.parent)  # the job's folder itself, before a result in it is published
        write_atomic(Path(self._at(name)), data)

    def read(self, name: str) -> bytes:
        if self.fs is not None:
            return bytes(self.fs.cat(self._at(name)))
        return Path(self._at(name)).read_bytes()

    def local(self, name: str) -> Path | None:
        """The file's path when the results are a local folder (to be served as a file), else None."""
        return None if self.fs is not None else Path(self._at(name))

    def clear_partial(self) -> None:
        """Temporary files of a worker that died mid-write: never results (objects have none)."""
        if self.fs is None and Path(self.dir).is_dir():
            for tmp in Path(self.dir).glob(".*.tmp"):
                tmp.unlink(missing_ok=True)

    def delete(self) -> None:
        if self.fs is not None:
            try:
                self.fs.rm(self.dir, recursive=True)
            except FileNotFoundError:
                pass
            return
        shutil.rmtree(self.dir, ignore_errors=True)


def park_upload(local: Path, url: str) -> None:
    """Upload a file to object storage (an upload for the workers of every host)."""
    import fsspec

    fs, path = fsspec.core.url_to_fs(url)
    fs.put_file(str(local), path)


def drop_upload(source: str) -> None:
    """Delete an uploaded file: in the local uploads folder, or parked under a root URL's .uploads/."""
    if not is_url(source):
        Path(source).unlink(missing_ok=True)
        return
    import fsspec

    fs, path = fsspec.core.url_to_fs(source)
    try:
        fs.rm(path)
    except FileNotFoundError:
        pass


def parked_uploads(url: str) -> list[tuple[str, float]]:
    """(URL, modification time) of the uploads parked under `url`."""
    import fsspec

    fs, base = fsspec.core.url_to_fs(url)
    fs.invalidate_cache(base)
    try:
        entries = fs.ls(base, detail=True)
    except FileNotFoundError:
        return []
    out = []
    for e in entries:
        t = e.get("LastModified") or e.get("mtime")
        stamp = t.timestamp() if hasattr(t, "timestamp") else float(t or 0.0)
        out.append((f"{url}/{str(e['name']).rstrip('/').rsplit('/', 1)[-1]}", stamp))
    return out
