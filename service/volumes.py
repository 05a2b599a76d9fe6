"""Volume ids and paths under the store root: validation, traversal and symlink safety, listing, deletion.

A volume is a store directly under the root; its id is the folder name. No request may name a path outside the
root: ids are matched against a strict pattern, resolved, and checked to stay inside the root (a symlink that leads
out of it is refused). Hidden folders (``.jobs``, ``.lodcast``) never match the pattern, so they are never volumes.

The root may also be an fsspec URL (``s3://bucket/prefix``, a `str`; a folder is a `Path`): a volume is then the
store at ``ROOT/ID`` (an id holds no "/", so it cannot leave the prefix), and it exists once its root
``zarr.json`` is there (ingest publishes that object last, store/remote.py); deletion takes that object away
first, so a store being deleted is never listed half there.
"""
from __future__ import annotations

import os
import re
import shutil
import uuid
from pathlib import Path
from typing import Any

from lodcast.errors import LodcastError, SourceError, StoreInvalid
from lodcast.store.remote import is_url, published

__all__ = [
    "VOLUME_ID",
    "JOB_ID",
    "BadId",
    "OutsideRoot",
    "StoreUnusable",
    "check_store_geometry",
    "VolumeNotFound",
    "check_volume_id",
    "volume_path",
    "volume_exists",
    "list_volumes",
    "volume_summary",
    "delete_volume",
    "safe_import_path",
]

VOLUME_ID = re.compile(r"\A[A-Za-z0-9][A-Za-z0-9._-]{0,127}\Z")  # \Z: "$" lets a trailing newline through
JOB_ID = re.compile(r"\A[0-9a-f]{32}\Z")
NAME_MAX, PATH_MAX = 255, 4096  # bytes of one path component, of a whole path (Linux's limits)


class BadId(LodcastError, ValueError):
    """An id does not match its pattern."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(message)
        self.field = field


class OutsideRoot(BadId):
    """A path resolves outside the folder it must stay in (traversal or symlink)."""


class VolumeNotFound(LodcastError, FileNotFoundError):
    def __init__(self, volume_id: str) -> None:
        super().__init__(f"volume: no volume {volume_id!r} under the store root")
        self.field = "volume"
        self.volume_id = volume_id


def check_volume_id(volume_id: Any, field: str = "volume") -> str:
    if not isinstance(volume_id, str) or not VOLUME_ID.match(volume_id) or volume_id in (".", ".."):
        raise BadId(field, f"{field}: invalid volume id {str(volume_id)[:140]!r} (expected {VOLUME_ID.pattern})")
    return volume_id


def _inside(path: Path, root: Path) -> bool:
    try:
        return path.resolve(strict=False).is_relative_to(root.resolve())
    except (OSError, RuntimeError):  # symlink loops
        return False


def _fs(url: str) -> tuple[Any, str]:
    """The fsspec filesystem of `url` and the path in it, with no listing cached (another process may have
    published or deleted a store since)."""
    import fsspec

    fs, path = fsspec.core.url_to_fs(url)
    fs.invalidate_cache()
    return fs, path.rstrip("/")


def volume_exists(root: Path | str, volume_id: Any, field: str = "volume") -> bool:
    """Whether something is at the volume's place: a folder (or file) under a root folder, a published store under a
    root URL."""
    path = volume_path(root, volume_id, must_exist=False, field=field)
    return published(path) if isinstance(path, str) else path.exists()


def volume_path(root: Path | str, volume_id: Any, *, must_exist: bool = True, field: str = "volume") -> Path | str:
    """The store of a volume (a folder, or a URL under a root URL), refusing bad ids and anything that resolves
    outside ``root``."""
    vid = check_volume_id(volume_id, field)
    if is_url(root):
        url = f"{str(root).rstrip('/')}/{vid}"
        if must_exist and not volume_exists(root, vid, field):
            raise VolumeNotFound(vid)
        return url
    root = Path(root).resolve()
    path = root / vid
    if not _inside(path, root):
        raise OutsideRoot(field, f"{field}: {vid!r} resolves outside the store root")
    if must_exist and not path.is_dir():
        raise VolumeNotFound(vid)
    return path


def list_volumes(root: Path | str) -> list[str]:
    """Ids of the folders directly under ``root`` that look like stores (a zarr group), sorted."""
    if is_url(root):
        fs, base = _fs(str(root))
        try:
            names = [str(e).rstrip("/").rsplit("/", 1)[-1] for e in fs.ls(base, detail=False)]
        except FileNotFoundError:
            return []
        return sorted(n for n in names if VOLUME_ID.match(n) and fs.exists(f"{base}/{n}/zarr.json"))
    root = Path(root).resolve()
    out: list[str] = []
    try:
        entries = list(os.scandir(root))
    except FileNotFoundError:
        return out
    for entry in entries:
        if not VOLUME_ID.match(entry.name) or not entry.is_dir():
            continue
        path = root / entry.name
        if not _inside(path, root):
            continue
        if (path / "zarr.json").is_file():
            out.append(entry.name)
    return sorted(out)


class StoreUnusable(StoreInvalid):
    """A complete store whose attributes no render can use: spacing and origin that give no finite world box (an
    older lodcast ingested them; ingest refuses them now). HTTP 409: re-ingest or delete it."""


def check_store_geometry(store: Any, volume_id: Any) -> None:
    """Raises StoreUnusable, naming the volume and the attribute, when the store's spacing and origin do not give
    the finite, non-degenerate world box that ingest requires of a source (store/source.py: check_world_box)."""
    from lodcast.store.source import SourceInfo, check_world_box

    try:
        shape = tuple(int(n) for n in store.shape)
        info = SourceInfo(shape=(shape[0], shape[1], shape[2]), dtype=store.dtype, spacing=tuple(store.spacing),
                          origin=tuple(store.origin), provenance={"path": f"volume {str(volume_id)!r}"})
        check_world_box(info)
    except SourceError as exc:
        raise StoreUnusable(f"{' '.join(str(exc).split())}; the store was written by an older lodcast: re-ingest "
                            f"or delete it") from None
    except (TypeError, ValueError, IndexError, OverflowError) as exc:
        raise StoreUnusable(f"volume {str(volume_id)!r}: the store's shape, spacing or origin is malformed "
                            f"({exc}): re-ingest or delete it") from None


def volume_summary(root: Path | str, volume_id: Any) -> dict[str, Any]:
    """The store's attributes (``Store.summary()``) plus its id; raises VolumeNotFound / StoreInvalid
    (StoreUnusable where its spacing and origin give no finite world box)."""
    from lodcast.errors import StoreNotFound

    path = volume_path(root, volume_id)
    from lodcast.store.store import open_store

    try:
        store = open_store(path)
        check_store_geometry(store, volume_id)
        summary = dict(store.summary())
    except StoreNotFound:
        raise VolumeNotFound(str(volume_id)) from None
    summary.pop("path", None)  # the server's own filesystem layout is not the client's business
    source = summary.get("source")
    if isinstance(source, dict) and source.get("path"):  # its file name only; an upload's is random: none
        path = str(source["path"]).replace("\\", "/").rstrip("/")
        summary["source"] = {**source, "path": None if "/.uploads/" in path else path.rsplit("/", 1)[-1]}
    return {"id": str(volume_id), **summary}


def delete_volume(root: Path | str, volume_id: Any) -> None:
    """Remove a volume's store: renamed aside first (atomic; under a root URL its root zarr.json goes first), then
    deleted, so it never looks half there."""
    path = volume_path(root, volume_id)
    if isinstance(path, str):
        fs, p = _fs(path)
        fs.rm(f"{p}/zarr.json")  # unpublished: no reader opens it from now on
        fs.rm(p, recursive=True)
        return
    if not (path / "zarr.json").is_file():  # only stores are volumes: never delete another folder under the root
        raise VolumeNotFound(str(volume_id))
    if path.is_symlink():
        path.unlink()  # a link inside the root pointing at a store elsewhere: remove the link, never the target
        return
    trash = Path(root).resolve() / f".trash-{uuid.uuid4().hex}"
    os.replace(path, trash)
    shutil.rmtree(trash, ignore_errors=True)


def _no_links_out(folder: Path, base: Path, source: str, field: str) -> None:
    """A folder source (a DICOM or TIFF series, a zarr store) may not hold a link to a file outside the import
    root: its bytes would be ingested and come back through a render."""
    for top, dirs, files in os.walk(folder):
        for name in (*dirs, *files):
            p = Path(top) / name
            if p.is_symlink() and not _inside(p.resolve(), base):
                raise OutsideRoot(field, f"{field}: {source!r} holds {str(p.relative_to(folder))!r}, a link to "
                                         f"outside the configured import roots")


def safe_import_path(source: Any, import_roots: list[Path], field: str = "source") -> Path:
    """A server-side source path for ingest; it must resolve inside one of the configured import roots."""
    if not isinstance(source, str) or not source or "\x00" in source:
        raise BadId(field, f"{field}: must be a non-empty path")
    if not import_roots:
        raise BadId(field, f"{field}: ingest from server-side paths is disabled (no import roots configured)")
    try:
        raw = os.fsencode(source)
    except UnicodeError:
        raise BadId(field, f"{field}: {source[:140]!r} holds characters no file name can have") from None
    longest = max(len(part) for part in raw.split(b"/"))
    if longest > NAME_MAX:  # ENAMETOOLONG from the filesystem, a 500 before
        raise BadId(field, f"{field}: a component of the path is {longest} bytes long, more than a file name may "
                           f"be ({NAME_MAX} bytes)")
    if len(raw) > PATH_MAX:
        raise BadId(field, f"{field}: the path is {len(raw)} bytes long, more than {PATH_MAX}")
    p = Path(source)
    try:
        for base in import_roots:
            cand = p if p.is_absolute() else base / p
            if _inside(cand, base):
                resolved = cand.resolve()
                if not resolved.exists():
                    raise BadId(field, f"{field}: {source!r} does not exist")
                if resolved.is_dir():
                    _no_links_out(resolved, base, source, field)
                return resolved
    except (OSError, RuntimeError) as exc:  # a name too long once resolved, a loop of links, a permission
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else type(exc).__name__
        raise BadId(field, f"{field}: {source[:140]!r} cannot be opened ({reason})") from None
    raise OutsideRoot(field, f"{field}: {source!r} is outside the configured import roots")
