"""Publishing a store to object storage (an fsspec URL such as s3://bucket/prefix/ct.zarr), atomically for readers.

Ingest writes the store locally first (under the system's temporary folder, or ``LODCAST_TMP``), then uploads it
here: every object but the root ``zarr.json``, then the root ``zarr.json`` last. A reader opens a store by that
object, so until the upload is complete there is no store at the URL (``open_store`` says so), and a killed
upload leaves none either. Replacing (``overwrite``) first takes the old root ``zarr.json`` away and deletes the
old objects, so no reader opens a half-replaced store (one that opened the old store before keeps reading objects
that are being replaced: re-open after an overwrite). Objects left by a killed upload (no root ``zarr.json``) are
deleted by the next ingest to that URL. Credentials: the filesystem's own (for S3, the usual AWS variables).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from lodcast.errors import StoreExists

__all__ = ["is_url", "published", "publish", "ingest_to_url"]


def is_url(dest: Any) -> bool:
    return "://" in os.fspath(dest)


def published(url: str) -> bool:
    """Whether a store is published at `url` now (its root zarr.json exists; no cached listing is trusted, another
    process may have published or deleted it since)."""
    import fsspec

    fs, root = fsspec.core.url_to_fs(url)
    fs.invalidate_cache(root.rstrip("/"))
    return bool(fs.exists(f"{root.rstrip('/')}/zarr.json"))


def ingest_to_url(source: Any, url: str, *, overwrite: bool, **kw: Any) -> Any:
    """`lodcast.ingest` to a URL: into a local folder named by host and pid (store/sweep.py), then `publish`; the
    store opened there. The local copy goes however the ingest ends; one a killed ingest left is removed by the
    next ingest to object storage on this host, or by `serve`/`worker` start-up."""
    import shutil

    from lodcast.store.ingest import ingest
    from lodcast.store.store import open_store
    from lodcast.store.sweep import local_copy, sweep_local_copies

    if not overwrite and published(url):  # before the work, as for a local destination
        raise StoreExists(f"destination {url} exists (use --overwrite to replace it)")
    sweep_local_copies()
    tmp = local_copy()
    try:
        local = tmp / (url.rstrip("/").rsplit("/", 1)[-1] or "store.zarr")
        ingest(source, local, **kw)
        publish(local, url, overwrite)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return open_store(url)


def _put(fs: Any, local: list[str], remote: list[str]) -> None:
    """Upload files (one batched call: the filesystem runs the requests concurrently)."""
    if local:
        fs.put(local, remote)


def publish(local: Path, url: str, overwrite: bool) -> None:
    """Upload the store folder `local` to `url`, the root zarr.json last; StoreExists if a store is there and
    `overwrite` is false."""
    import fsspec

    fs, root = fsspec.core.url_to_fs(url)
    root = root.rstrip("/")
    head = f"{root}/zarr.json"
    if fs.exists(head):
        if not overwrite:
            raise StoreExists(f"destination {url} exists (use --overwrite to replace it)")
        fs.rm(head)  # unpublished first: from here on no reader opens it
    if fs.exists(root):
        fs.rm(root, recursive=True)  # the old store's objects, or a killed upload's
    files = sorted(p for p in Path(local).rglob("*") if p.is_file())
    body = [p for p in files if p != Path(local) / "zarr.json"]
    _put(fs, [str(p) for p in body], [f"{root}/{p.relative_to(local).as_posix()}" for p in body])
    _put(fs, [str(Path(local) / "zarr.json")], [head])
