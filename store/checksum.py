"""Format 4's checksums: CRC-32C as zarr's `crc32c` codec computes it, the manifest that binds every data file and
array metadata file of a store to its place, and the digests of the root attributes.

The manifest (`manifest.json` at the store's root) records, per array path and chunk key: the file's size and the
CRC-32C of its bytes, plus, for a shard, its index's own checksum (the index's last four bytes). A reader checks a
shard's size and index checksum when it first reads the index (store/shardio.py), so a shard moved to another place
in the store, or replaced by a shard of another store, is damage even though its own checksums hold; `verify`
(store/verify.py) checks every file's whole-file checksum as well. The root attributes record the manifest's own
checksum and one per top-level attribute, so an edited `value_range` or `dtype` is damage that names the attribute.
Chunk checksums inside the shards are zarr's (`crc32c` after `blosc` in the sharding codec's codecs, and in its
index codecs), so zarr-python and other zarr v3 readers open the same store and check the same bytes.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import google_crc32c
import numpy as np

from lodcast.errors import StoreCorrupt

__all__ = ["crc32c", "MANIFEST", "Manifest", "write_manifest", "read_manifest", "attribute_digests",
           "UNSIGNED_ATTRIBUTES"]

#: the manifest's file name, at the store's root
MANIFEST = "manifest.json"
#: root attributes without a digest: `lodcast` holds the digests themselves; `ome` is OME-Zarr's, which viewers may
#: rewrite (a contrast window) without changing what lodcast reads
UNSIGNED_ATTRIBUTES = frozenset({"lodcast", "ome"})


def crc32c(data: Any) -> int:
    """CRC-32C (Castagnoli) of a bytes-like object, as zarr's `crc32c` codec computes it (hardware-accelerated
    where the CPU has the instruction)."""
    return int(google_crc32c.value(data if isinstance(data, bytes) else np.frombuffer(data, np.uint8)))


def _canonical(value: Any) -> bytes:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=True).encode()


def attribute_digests(attrs: dict[str, Any]) -> dict[str, int]:
    """CRC-32C of every top-level root attribute but UNSIGNED_ATTRIBUTES, of its canonical JSON."""
    return {k: crc32c(_canonical(v)) for k, v in sorted(attrs.items()) if k not in UNSIGNED_ATTRIBUTES}


@dataclass(frozen=True)
class Manifest:
    """What ingest wrote: `files[array path][chunk key]` = [size, crc32c of the file] (+ [index checksum] for a
    shard), `metadata[relative path of a zarr.json]` = its crc32c."""

    files: dict[str, dict[str, list[int]]]
    metadata: dict[str, int]


def _is_sharded(meta: dict[str, Any]) -> bool:
    codecs = meta.get("codecs") or []
    return bool(codecs) and codecs[0].get("name") == "sharding_indexed"


def write_manifest(root: Path, known: Mapping[str, Mapping[str, list[int]]] | None = None) -> int:
    """Write the manifest of the store at `root` (every array's zarr.json and data files as they are now) and return
    the CRC-32C of the manifest file, which the root attributes record. `known[array path][file key]`: entries of
    files the caller wrote itself (store/shardwrite.py), taken instead of reading those files back."""
    files: dict[str, dict[str, list[int]]] = {}
    metadata: dict[str, int] = {}
    for dirpath, dirnames, names in os.walk(root):
        dirnames.sort()
        rel = Path(dirpath).relative_to(root)
        if "zarr.json" not in names or rel == Path("."):
            continue
        meta_bytes = (Path(dirpath) / "zarr.json").read_bytes()
        metadata[(rel / "zarr.json").as_posix()] = crc32c(meta_bytes)
        sharded = _is_sharded(json.loads(meta_bytes))
        entries = files.setdefault(rel.as_posix(), {})
        have = (known or {}).get(rel.as_posix(), {})
        for sub, _, chunk_files in os.walk(Path(dirpath) / "c"):
            for name in chunk_files:
                path = Path(sub) / name
                key = path.relative_to(dirpath).as_posix()
                entry = have.get(key)
                if entry is None:
                    data = path.read_bytes()
                    entry = [len(data), crc32c(data)]
                    if sharded:
                        entry.append(int.from_bytes(data[-4:], "little"))
                entries[key] = list(entry)
    raw = _canonical({"algorithm": "crc32c", "files": files, "metadata": metadata})
    (root / MANIFEST).write_bytes(raw)
    return crc32c(raw)


def read_manifest(raw: bytes, expected: int, name: str) -> Manifest:
    """The manifest from the bytes of its file `name`, StoreCorrupt unless they are the ones ingest wrote."""
    if crc32c(raw) != expected:
        raise StoreCorrupt(f"{name}: damaged manifest (its checksum differs from the one the root zarr.json "
                           f"records): re-ingest the store")
    doc = json.loads(raw)
    return Manifest(doc["files"], doc["metadata"])
