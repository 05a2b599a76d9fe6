"""Writer of whole shards of the sharded level and `std` arrays that ingest creates, bypassing zarr-python's codec
pipeline: the bytes are those zarr writes for the array's own zarr.json (any zarr v3 reader decodes them, and
store/shardio.py reads them back).

Why: zarr-python spends tens of microseconds of Python per inner chunk and per codec, so each codec of a level of
thousands of 16³ blocks costs a noticeable part of an ingest, checksums included. Here each chunk is blosc-compressed
by numcodecs, its CRC-32C appended as zarr's `crc32c` codec does (little endian, after the bytes it covers), and
each shard is written once: its chunks in C order, then the index of little-endian uint64 (offset, nbytes) per
chunk ((2⁶⁴−1, 2⁶⁴−1) for a chunk outside the array) followed by its own CRC-32C. Only what ingest creates is
handled: a regular grid, `sharding_indexed` with codecs `bytes` (little endian), `blosc`, optional `crc32c`,
index codecs `bytes` (little endian), optional `crc32c`, index at the end.
"""
from __future__ import annotations

import itertools
import json
from math import prod
from pathlib import Path

import numpy as np
from numcodecs import blosc

from lodcast.store.checksum import crc32c

__all__ = ["ShardWriter"]

_EMPTY = 2**64 - 1
_SHUFFLES = {"noshuffle": 0, "shuffle": 1, "bitshuffle": 2}


class ShardWriter:
    """Writes whole shards of the array whose folder is `folder` (created by zarr-python: its zarr.json says how)."""

    def __init__(self, folder: Path) -> None:
        meta = json.loads((folder / "zarr.json").read_bytes())
        (sharding,) = meta["codecs"]
        cfg = sharding["configuration"]
        inner, index = [c["name"] for c in cfg["codecs"]], [c["name"] for c in cfg["index_codecs"]]
        little = all((c.get("configuration") or {}).get("endian", "little") == "little"
                     for c in cfg["codecs"][:1] + cfg["index_codecs"][:1])
        if (sharding["name"] != "sharding_indexed" or inner not in (["bytes", "blosc"], ["bytes", "blosc", "crc32c"])
                or index not in (["bytes"], ["bytes", "crc32c"]) or not little
                or cfg.get("index_location", "end") != "end" or meta["chunk_grid"]["name"] != "regular"):
            raise ValueError(f"{folder}: not a sharded array as ingest creates it ({inner}, index {index})")
        b = cfg["codecs"][1]["configuration"]
        self._blosc = (b["cname"].encode(), int(b["clevel"]), _SHUFFLES[b["shuffle"]], int(b.get("blocksize", 0)))
        self._chunk_crc, self._index_crc = inner[-1] == "crc32c", index[-1] == "crc32c"
        self.folder = folder
        self.shape = tuple(int(n) for n in meta["shape"])
        self.dtype = np.dtype(meta["data_type"]).newbyteorder("<")
        fill = meta["fill_value"]
        self.fill = {"NaN": np.nan, "Infinity": np.inf, "-Infinity": -np.inf}.get(fill, fill) if isinstance(fill, str) \
            else fill
        self.chunk = tuple(int(n) for n in cfg["chunk_shape"])
        self.shard = tuple(int(n) for n in meta["chunk_grid"]["configuration"]["chunk_shape"])
        sep = ((meta.get("chunk_key_encoding") or {}).get("configuration") or {}).get("separator", "/")
        self._key = lambda coords: sep.join(["c", *map(str, coords)])
        #: the manifest's entry of each shard written, by its key (store/checksum.py: write_manifest takes them
        #: instead of reading the files back)
        self.written: dict[str, list[int]] = {}

    def write(self, start: tuple[int, ...], data: np.ndarray) -> None:
        """The shards that `data` covers, `data` starting at voxel `start`, a corner of a shard: it must reach the
        far side of every shard it touches, or the array's edge."""
        for s, n, d, shape in zip(start, data.shape, self.shard, self.shape):
            if s % d or (n % d and s + n != shape):
                raise ValueError(f"{self.folder}: region at {start} of {data.shape} is not whole shards of {self.shard}")
        first = [s // d for s, d in zip(start, self.shard)]
        counts = [-(-n // d) for n, d in zip(data.shape, self.shard)]
        for rel in itertools.product(*(range(c) for c in counts)):
            lo = [r * d for r, d in zip(rel, self.shard)]
            part = data[tuple(slice(a, a + d) for a, d in zip(lo, self.shard))]
            self._write_shard(tuple(f + r for f, r in zip(first, rel)), part)

    def _write_shard(self, coords: tuple[int, ...], part: np.ndarray) -> None:
        per = [d // c for d, c in zip(self.shard, self.chunk)]
        origin = [i * d for i, d in zip(coords, self.shard)]
        index = np.full((prod(per), 2), _EMPTY, np.dtype("<u8"))
        pieces, offset = [], 0
        cname, clevel, shuffle, blocksize = self._blosc
        for n, rel in enumerate(itertools.product(*(range(p) for p in per))):
            lo = [r * c for r, c in zip(rel, self.chunk)]
            if any(o + a >= s for o, a, s in zip(origin, lo, self.shape)):
                continue  # outside the array: zarr leaves it out too
            block = part[tuple(slice(a, a + c) for a, c in zip(lo, self.chunk))]
            if block.shape != self.chunk:  # at the array's edge: the rest is the fill value, as zarr pads it
                full = np.full(self.chunk, self.fill, self.dtype)
                full[tuple(slice(0, m) for m in block.shape)] = block
                block = full
            raw = blosc.compress(np.ascontiguousarray(block, self.dtype), cname, clevel, shuffle, blocksize,
                                 self.dtype.itemsize)
            if self._chunk_crc:
                raw += crc32c(raw).to_bytes(4, "little")
            pieces.append(raw)
            index[n] = offset, len(raw)
            offset += len(raw)
        table = index.tobytes()
        pieces.append(table + (crc32c(table).to_bytes(4, "little") if self._index_crc else b""))
        key = self._key(coords)
        path = self.folder / key
        path.parent.mkdir(parents=True, exist_ok=True)
        blob = b"".join(pieces)
        with open(path, "wb") as f:
            f.write(blob)
        self.written[path.relative_to(self.folder).as_posix()] = [len(blob), crc32c(blob),
                                                                 int.from_bytes(blob[-4:], "little")]
