"""`lodcast verify`: a scrub of one local store. Every file is read and every checksum checked (chunks and shard
indexes by zarr's `crc32c`, whole files and array metadata by the manifest, the root attributes by their digests),
on a pool of threads; each damaged file is listed once. A store written before checksums (format < 4) is still
read whole: every chunk must decode, though a flipped bit may then go unseen."""
from __future__ import annotations

import itertools
import json
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lodcast.errors import StoreCorrupt, StoreInvalid, StoreNotFound
from lodcast.store.checksum import Manifest, crc32c
from lodcast.store.integrity import CHECKSUMS_SINCE, array_problems, attribute_problems, load_manifest, required_arrays
from lodcast.store.shardio import ChunkReader, ShardedReader, fast_reader
from lodcast.store.store import READABLE_VERSIONS, Store, read_local

__all__ = ["Damage", "Verified", "verify"]


@dataclass(frozen=True)
class Damage:
    """One damaged file of a store: its path relative to the store, and why."""

    file: str
    reason: str


@dataclass(frozen=True)
class Verified:
    """What `verify` found: `checksums` is False for a store written before them (format < 4)."""

    location: str
    format_version: int
    checksums: bool
    files: int
    bytes: int
    damage: tuple[Damage, ...]

    @property
    def clean(self) -> bool:
        return not self.damage


def _root_attrs(location: str) -> dict[str, Any]:
    """The root attributes of a lodcast store; StoreNotFound / StoreInvalid when `location` is not one."""
    p = Path(location)
    if not p.is_dir():
        raise StoreNotFound(f"no store at {location}")
    try:
        meta = json.loads((p / "zarr.json").read_bytes())
        attrs = meta["attributes"]
        version = attrs["lodcast"]["format_version"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise StoreInvalid(f"{location} is not a lodcast store (its zarr.json: {' '.join(str(exc).split())})") from None
    if version not in READABLE_VERSIONS:
        raise StoreInvalid(f"{location}: store format version {version} is not one of {READABLE_VERSIONS}")
    return attrs


def _damage(location: str, exc: Exception) -> Damage:
    text = " ".join(str(exc).split())
    prefix = location.rstrip("/") + "/"
    file, _, reason = text.partition(": ")
    return Damage(file.removeprefix(prefix), reason) if file.startswith(prefix) else Damage("", text)


def verify(path: str | os.PathLike[str], *, workers: int | None = None,
           progress: Callable[[int, int], None] | None = None) -> Verified:
    """Read and check every file of the local store at `path`. Raises StoreNotFound / StoreInvalid when `path` is
    not a lodcast store; damage is returned, never raised. `progress(done, total)` is called as files are checked."""
    location = os.fspath(path)
    attrs = _root_attrs(location)
    version = int(attrs["lodcast"]["format_version"])
    read = read_local(location)
    found: list[Damage] = [_damage(location, e) for e in attribute_problems(location, attrs)]
    try:
        store = Store(location, attrs)
    except StoreInvalid as exc:
        return Verified(location, version, version >= CHECKSUMS_SINCE, 0, 0, (*found, _damage(location, exc)))
    manifest: Manifest | None = None
    try:
        manifest = load_manifest(location, attrs, read)
    except StoreCorrupt as exc:
        found.append(_damage(location, exc))
    bad_meta = {d.file for d in found}
    for problem in array_problems(location, attrs, store.layout, version, manifest, read):
        found.append(d := _damage(location, problem))
        bad_meta.add(d.file)
    arrays = [a for a in required_arrays(store.layout, version) if f"{a}/zarr.json" not in bad_meta]
    jobs: list[tuple[str, str]] = []  # (array, chunk key) of every data file there is or should be
    for array in arrays:
        on_disk = _data_files(Path(location) / array)
        wrote = set(manifest.files.get(array, {})) if manifest is not None else set()
        jobs += [(array, key) for key in sorted(on_disk | wrote)]
    readers = {a: fast_reader(Path(location) / a, store.manifest is not None and not a.startswith("blocks"),
                              digests=None if manifest is None else manifest.files.get(a, {})) for a in arrays}

    def check(job: tuple[str, str]) -> tuple[Damage | None, int]:
        array, key = job
        try:
            return None, _check_file(location, array, key, readers[array], manifest)
        except (StoreCorrupt, OSError, ValueError, RuntimeError) as exc:
            return _damage(location, exc if isinstance(exc, StoreCorrupt) else StoreCorrupt(
                f"{location}/{array}/{key}: damaged ({' '.join(str(exc).split())})")), 0

    total = 0
    with ThreadPoolExecutor(workers or min(16, (os.cpu_count() or 1) * 2), thread_name_prefix="verify") as pool:
        for i, (damage, size) in enumerate(pool.map(check, jobs)):
            total += size
            if damage is not None:
                found.append(damage)
            if progress is not None:
                progress(i + 1, len(jobs))
    if not any(d.file.startswith(("blocks/min/", "blocks/max/")) for d in found):
        try:
            store.stats  # noqa: B018 - reading them checks the root's value range against them
        except StoreCorrupt as exc:
            found.append(_damage(location, exc))
    return Verified(location, version, manifest is not None, len(jobs), total, tuple(dict.fromkeys(found)))


def _data_files(folder: Path) -> set[str]:
    """Chunk keys of the data files under an array's folder."""
    out = set()
    for dirpath, _, names in os.walk(folder / "c"):
        for name in names:
            out.add((Path(dirpath) / name).relative_to(folder).as_posix())
    return out


def _check_file(location: str, array: str, key: str, reader: Any, manifest: Manifest | None) -> int:
    """Reads one data file whole and checks it: its bytes against the manifest, then every chunk it holds through
    the store's reader (which checks chunk and index checksums); returns its size."""
    name = f"{location}/{array}/{key}"
    want = None if manifest is None else manifest.files.get(array, {}).get(key)
    try:
        raw = (Path(location) / array / key).read_bytes()
    except FileNotFoundError:
        raise StoreCorrupt(f"{name}: file missing (ingest wrote it)") from None
    if manifest is not None:
        if want is None:
            raise StoreCorrupt(f"{name}: a file ingest did not write")
        if want[:2] != [len(raw), crc32c(raw)]:
            raise StoreCorrupt(f"{name}: damaged (its checksum or size differs from the manifest's)")
    coords = tuple(int(c) for c in key.split("/")[1:])
    if isinstance(reader, ShardedReader):
        per = [s // c for s, c in zip(reader.shard, reader.chunk)]
        grid = [-(-n // c) for n, c in zip(reader.shape, reader.chunk)]
        ranges = [range(i * p, min((i + 1) * p, g)) for i, p, g in zip(coords, per, grid)]
        reader.read_chunks(np.array(list(itertools.product(*ranges)), np.int64))
    elif isinstance(reader, ChunkReader):
        reader.read_chunk(coords)
    return len(raw)
