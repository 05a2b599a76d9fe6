"""What opening a store checks of its metadata, and what `verify` lists: each array's zarr.json against the root
attributes (every format), and in format 4 the root attributes against their digests and every zarr.json against
the manifest (store/checksum.py). Each check yields StoreCorrupt naming the file; opening raises the first one,
`verify` lists them all."""
from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from lodcast.errors import StoreCorrupt
from lodcast.store.checksum import MANIFEST, Manifest, attribute_digests, crc32c, read_manifest
from lodcast.store.layout import Layout

__all__ = ["CHECKSUMS_SINCE", "required_arrays", "load_manifest", "attribute_problems", "array_problems",
           "value_range_problem"]

#: the first store format whose chunks, shard indexes, metadata and attributes carry checksums
CHECKSUMS_SINCE = 4
#: per-block arrays every format has (the Store reads them whatever the format)
_BLOCK_ARRAYS = ("min", "max", "mean", "count", "min_border", "max_border", "hist", "hist_starts", "hist_heights")

Read = Callable[[str], bytes]  # a file's bytes by its path relative to the store's root (FileNotFoundError if none)


def required_arrays(layout: Layout, format_version: int) -> list[str]:
    """The arrays (paths in the group) a store of `format_version` holds: what opening it checks."""
    levels = range(layout.n_levels)
    out = [str(k) for k in levels]
    out += [f"blocks/{name}" for name in _BLOCK_ARRAYS]
    if format_version >= 2:
        out += [f"std/{k}" for k in levels if k] + ["blocks/level_std"]
    if format_version >= 3:
        out += ["blocks/cell_min", "blocks/cell_max"]
    return out


def load_manifest(location: str, attrs: dict[str, Any], read: Read) -> Manifest | None:
    """The manifest of a format-4 store (None for an older one); StoreCorrupt when it is missing or damaged."""
    integrity = (attrs.get("lodcast") or {}).get("integrity")
    if integrity is None:
        return None
    name = f"{location}/{MANIFEST}"
    try:
        raw = read(MANIFEST)
    except FileNotFoundError:
        raise StoreCorrupt(f"{name}: manifest missing (ingest wrote it): re-ingest the store") from None
    return read_manifest(raw, int(integrity["crc32c"]), name)


def attribute_problems(location: str, attrs: dict[str, Any]) -> Iterator[StoreCorrupt]:
    """Root attributes that differ from what ingest wrote (format 4), one error each naming the attribute."""
    recorded = ((attrs.get("lodcast") or {}).get("integrity") or {}).get("attributes")
    if recorded is None:
        return
    found = attribute_digests(attrs)
    for key in sorted(set(recorded) | set(found)):
        if recorded.get(key) != found.get(key):
            change = "missing" if key not in found else "added" if key not in recorded else "changed"
            yield StoreCorrupt(f"{location}/zarr.json: attribute {key!r} {change} since ingest wrote it: the "
                               f"store is damaged or was edited, re-ingest it")


def _expected(path: str, layout: Layout, attrs: dict[str, Any], format_version: int) -> dict[str, Any]:
    """What an array's zarr.json must say: shape and data type of every array; chunk and shard shapes of the
    level and std arrays from format 4 on (older stores were cut with other shard shapes)."""
    top, _, rest = path.partition("/")
    if top == "blocks":
        return {"shape_prefix": list(layout.grid) if rest not in ("cell_min", "cell_max") else list(layout.cell_grid)}
    k = int(rest or top)
    out: dict[str, Any] = {"shape": list(layout.level_shape(k))}
    if top != "std":
        out["data_type"] = attrs["dtype"]
    elif "dtype" in (attrs.get("distribution") or {}):
        out["data_type"] = attrs["distribution"]["dtype"]
    if format_version >= CHECKSUMS_SINCE:
        out["shards"], out["chunks"] = list(layout.shard_shape(k)), list(layout.chunk_shape(k))
    return out


def _differences(meta: dict[str, Any], want: dict[str, Any]) -> list[str]:
    got: dict[str, Any] = {"shape": meta.get("shape"), "data_type": meta.get("data_type"),
                           "shards": (meta.get("chunk_grid") or {}).get("configuration", {}).get("chunk_shape")}
    codecs = meta.get("codecs") or [{}]
    got["chunks"] = (codecs[0].get("configuration") or {}).get("chunk_shape")
    out = [f"{key} {got[key]} where the root attributes give {value}" for key, value in want.items()
           if key in got and got[key] != value]
    prefix = want.get("shape_prefix")
    if prefix is not None and list(meta.get("shape") or [])[:3] != prefix:
        out.append(f"shape {meta.get('shape')} where the block grid is {prefix}")
    return out


def array_problems(location: str, attrs: dict[str, Any], layout: Layout, format_version: int,
                   manifest: Manifest | None, read: Read) -> Iterator[StoreCorrupt]:
    """Every array's zarr.json: there, the bytes ingest wrote (format 4), valid JSON, and its shape, data type and
    (format 4) chunk grid those of the root attributes."""
    for path in required_arrays(layout, format_version):
        rel = f"{path}/zarr.json"
        name = f"{location}/{rel}"
        try:
            raw = read(rel)
        except FileNotFoundError:
            yield StoreCorrupt(f"{name}: array metadata missing (ingest wrote it): the store is damaged, re-ingest it")
            continue
        if manifest is not None and manifest.metadata.get(rel) != crc32c(raw):
            yield StoreCorrupt(f"{name}: array metadata changed since ingest wrote it (its checksum differs from the "
                               f"manifest's): the store is damaged or was edited, re-ingest it")
            continue
        try:
            meta = json.loads(raw)
            if not isinstance(meta, dict):
                raise ValueError("not a JSON object")
        except ValueError as exc:
            yield StoreCorrupt(f"{name}: damaged array metadata ({' '.join(str(exc).split())}): re-ingest the store")
            continue
        wrong = _differences(meta, _expected(path, layout, attrs, format_version))
        if wrong:
            yield StoreCorrupt(f"{name}: array metadata disagrees with the root zarr.json ({'; '.join(wrong)}): the "
                               f"store is damaged or was edited, re-ingest it")


def value_range_problem(location: str, value_range: tuple[float, float], mins: np.ndarray,
                        maxs: np.ndarray) -> StoreCorrupt | None:
    """The root's `value_range` must be the range of the per-block minima and maxima ingest stored beside it."""
    lo, hi = (float(np.nanmin(mins)), float(np.nanmax(maxs))) if np.isfinite(mins).any() else (np.nan, np.nan)
    if (lo, hi) == tuple(value_range):
        return None
    return StoreCorrupt(f"{location}/zarr.json: attribute 'value_range' {list(value_range)} is not the range of the "
                        f"stored blocks ({lo:g}, {hi:g}): the store is damaged or was edited, re-ingest it")
