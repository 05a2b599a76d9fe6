"""Bricks of a level selection, read from the store through a brick cache (thesis §3.4: LOAD).

A **brick cache** is shared by every render of an engine (`Engine.bricks`, renderer/engine.py: LRU by bytes, size
``LODCAST_BRICK_CACHE_MB``, default 1024, less what a CPU device's buffers hold): only missing bricks are read, in
parallel (a thread pool, one task per shard: the bricks of one shard are read together, from the chunks that hold
them, since the number of requests dominates I/O), so a camera change reads nothing and a TF change reads only the
bricks whose level changed. renderer/data/atlas.py packs them.
"""
from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Iterator

import numpy as np

from lodcast.renderer.data.volume import device_dtype
from lodcast.renderer.engine import BrickCache, Engine
from lodcast.store.layout import Layout

__all__ = ["AtlasLoad", "BrickStats", "iter_bricks", "load_bricks"]


@dataclass(frozen=True)
class AtlasLoad:
    bricks: dict  # (level, bz, by, bx) -> brick (iter_bricks)
    read: int  # bricks read from the store by this call
    cached: int  # bricks found in the cache
    skipped: int  # blocks not loaded (level -1)
    shards: int  # shard read requests issued
    read_ms: float


def _read_group(vol: Any, lay: Layout, level: int, blocks: list[tuple[int, int, int]], what: str = "mean") -> dict:
    """The bricks `blocks` (all in one shard of `level`), cut into edge-padded bricks from the inner chunks that
    hold them and no others (a brick lies in one chunk: chunks are whole blocks or cubes of them): the values
    ("mean") or the standard deviations behind them ("std", uint16 in units of vol.std_unit)."""
    e = lay.block_edge(level)
    c = np.array(lay.chunk_shape(level))
    start = np.array(blocks, np.int64).reshape(-1, 3) * e  # the bricks' first samples in the level
    stop = np.minimum(start + e, np.array(lay.level_shape(level)))
    where = start // c
    # chunks by their flat index in the level's chunk grid (np.unique along an axis sorts rows as records, slowly:
    # at small blocks, a good part of a first render's reading)
    flat = np.ravel_multi_index(tuple(where.T), tuple(-(-np.array(lay.level_shape(level)) // c)))
    first, which = np.unique(flat, return_index=True, return_inverse=True)[1:]
    need = where[first]
    chunks = vol.read_chunks(level, need, std=what != "mean")
    lo, hi = start - where * c, stop - where * c  # within the chunk
    if what == "mean":  # the type the atlas holds (volume.device_dtype): the store's own up to 16-bit integers
        dtype, unit = device_dtype(chunks[0].dtype), None
    else:  # whole units of vol.std_unit (volume.py says why)
        dtype, unit = np.dtype(np.uint16), np.float64(vol.std_unit)
    out = {}
    for b, i, a, z in zip(blocks, which.ravel().tolist(), lo.tolist(), hi.tolist()):
        sub = chunks[i][a[0]:z[0], a[1]:z[1], a[2]:z[2]]
        if unit is not None:
            sub = np.clip(np.rint(np.nan_to_num(sub.astype(np.float64), nan=0.0) / unit), 0, 65535)
        if sub.shape != (e, e, e):
            sub = np.pad(sub, [(0, e - n) for n in sub.shape], mode="edge")
        out[(level, *b)] = np.ascontiguousarray(sub, dtype=dtype)
    return out


@dataclass
class BrickStats:
    read: int = 0  # bricks read from the store
    cached: int = 0  # bricks found in the cache
    skipped: int = 0  # blocks not loaded (level -1)
    shards: int = 0  # shard read requests issued
    read_ms: float = 0.0


def iter_bricks(eng: Engine, vol: Any, levels: np.ndarray, cache: BrickCache | None = None, what: str = "mean",
                stats: BrickStats | None = None) -> Iterator[tuple[tuple[int, int, int, int], np.ndarray]]:
    """((level, bz, by, bx), brick) for every brick `levels` selects, from `cache` (default: `eng`'s) or
    read from the store (missing ones only, grouped by shard, shards read in parallel, a few at a time so that
    bricks stream through rather than pile up: a caller that places each one keeps none); read bricks enter the
    cache. Values keep the store's type up to 16-bit integers, else float32. what="std": the standard deviations
    of the coarse bricks (level >= 1; level 0 has none), uint16 in units of vol.std_unit, instead of the values.
    `stats` is filled in."""
    cache = eng.bricks if cache is None else cache
    stats = BrickStats() if stats is None else stats
    t = time.perf_counter()
    lay = Layout(tuple(vol.shape), int(vol.block_size))
    levels = np.asarray(levels)
    if levels.shape != lay.grid:
        raise ValueError(f"level grid has shape {levels.shape}, the volume's block grid is {lay.grid}")
    bz, by, bx = np.nonzero(levels >= (0 if what == "mean" else 1))
    lv = levels[bz, by, bx].astype(np.int64)
    base = ("bricks" if what == "mean" else "std", vol.key)
    groups: dict[tuple, list] = {}
    stats.skipped = int(np.count_nonzero(levels < 0))
    # per level once, not per brick (the layout arithmetic, repeated per brick, adds up over a million of them)
    geom = {k: (lay.block_edge(k), lay.shard_shape(k)) for k in range(lay.n_levels)}
    for k, z, y, x in zip(lv.tolist(), bz.tolist(), by.tolist(), bx.tolist()):
        a = cache.get((base, k, z, y, x)) if vol.key is not None else None
        if a is not None:
            stats.cached += 1
            yield (k, z, y, x), a
            continue
        e, sh = geom[k]
        groups.setdefault((k, z * e // sh[0], y * e // sh[1], x * e // sh[2]), []).append((z, y, x))
    todo = sorted(groups.items())
    stats.shards = len(todo)
    threads = eng.read_threads("://" in str(getattr(vol.source, "location", "")))
    window = 2 * threads
    futs: deque = deque()

    def take() -> Iterator[tuple[tuple[int, int, int, int], np.ndarray]]:
        got = futs.popleft().result()
        stats.read += len(got)
        for key, a in got.items():
            if vol.key is not None:
                cache.put((base, *key), a)
            yield key, a

    for g, blks in todo:
        futs.append(eng.read_pool(threads).submit(_read_group, vol, lay, g[0], blks, what))
        if len(futs) > window:
            yield from take()
    while futs:
        yield from take()
    if what == "mean":
        cache.reads += stats.read
    stats.read_ms = (time.perf_counter() - t) * 1e3


def load_bricks(eng: Engine, vol: Any, levels: np.ndarray, cache: BrickCache | None = None,
                what: str = "mean") -> AtlasLoad:
    """iter_bricks as a dict, with its counts."""
    st = BrickStats()
    bricks = dict(iter_bricks(eng, vol, levels, cache, what, st))
    return AtlasLoad(bricks, st.read, st.cached, st.skipped, st.shards, st.read_ms)
