"""Bricks of a level selection, read from the store through the brick pool (thesis §3.4: LOAD).

The **brick pool** is shared by every render of an engine (`Engine.bricks`, renderer/pool.py: LRU by bytes, size
``LODCAST_BRICK_CACHE_MB``, default 1024, less what a CPU device's buffers hold): only missing bricks are read, in
parallel (a thread pool, one task per shard: the bricks of one shard are read together, from the chunks that hold
them, since the number of requests dominates I/O), so a camera change reads nothing and a TF change reads only the
bricks whose level changed. renderer/data/atlas.py packs them: the readers themselves place what they read into the
atlas (`place_bricks`), so that a cold atlas's placing and pool books run on every core beside the decoding, rather
than on the calling thread while the readers wait for it.
"""
from __future__ import annotations

import concurrent.futures
import itertools
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Mapping

import numpy as np

from lodcast.renderer.data.volume import device_dtype
from lodcast.renderer.engine import Engine
from lodcast.renderer.pool import BrickPool
from lodcast.store.layout import Layout

__all__ = ["AtlasLoad", "BrickStats", "Sink", "brick_batches", "load_bricks", "place_bricks", "std_table"]

#: the brick pool's arena kind of each `what`
_KIND = {"mean": "bricks", "std": "std"}


@dataclass(frozen=True)
class AtlasLoad:
    bricks: dict  # (level, bz, by, bx) -> brick
    read: int  # bricks read from the store by this call
    cached: int  # bricks found in the cache
    skipped: int  # blocks not loaded (level -1)
    shards: int  # shard read requests issued
    read_ms: float


#: bricks handed on at once from the pool (bounded, so that a caller placing them keeps no more than this beside)
BATCH_BYTES = 32 << 20


def std_table(vol: Any) -> np.ndarray:
    """For float16 standard deviations: the uint16 in units of vol.std_unit of every float16 bit pattern, as
    `_read_group` converts them (a gather where the conversion took several passes in float64 over every brick)."""
    every = np.arange(1 << 16, dtype=np.uint32).astype(np.uint16).view(np.float16)
    with np.errstate(over="ignore"):  # (the infinities among them, which clip to 65535 as they do in a brick)
        return _std_units(every, vol)


def _std_units(a: np.ndarray, vol: Any) -> np.ndarray:
    unit = np.float64(vol.std_unit)  # whole units of vol.std_unit (volume.py says why)
    return np.clip(np.rint(np.nan_to_num(a.astype(np.float64), nan=0.0) / unit), 0, 65535).astype(np.uint16)


def _read_group(vol: Any, lay: Layout, level: int, blocks: np.ndarray, what: str = "mean",
                table: np.ndarray | None = None) -> np.ndarray:
    """The bricks of `blocks` ((n, 3) z, y, x, all in one shard of `level`), (n, e, e, e), cut from the inner
    chunks that hold them and no others (a brick lies in one chunk: chunks are whole blocks or cubes of them) and
    edge-padded where the level ends inside them: the values ("mean") or the standard deviations behind them
    ("std", uint16 in units of vol.std_unit; `table`: std_table(vol), used for float16 ones). Whole-array
    operations: the bricks of a chunk are a view of it."""
    e = lay.block_edge(level)
    c = lay.chunk_shape(level)[0]
    start = np.asarray(blocks, np.int64).reshape(-1, 3) * e  # the bricks' first samples in the level
    where = start // c
    q = c // e
    if q == 1:  # a chunk per brick: the blocks' own chunks, in their order (a shard's blocks are distinct)
        sub = vol.read_chunks(level, where, std=what != "mean")
    else:  # a cube of q³ bricks per chunk: (m, q, e, q, e, q, e), each brick picked by its place in the chunk
        # chunks by their flat index in the level's chunk grid (np.unique along an axis sorts rows as records, slowly)
        shape = np.array(lay.level_shape(level))
        flat = np.ravel_multi_index(tuple(where.T), tuple(-(-shape // c)))
        first, which = np.unique(flat, return_index=True, return_inverse=True)[1:]
        box = vol.read_chunks(level, where[first], std=what != "mean")
        at = (start - where * c) // e
        sub = box.reshape(-1, q, e, q, e, q, e)[which.ravel(), at[:, 0], :, at[:, 1], :, at[:, 2], :]
    if what == "mean":  # the type the atlas holds (volume.device_dtype): the store's own up to 16-bit integers
        return np.ascontiguousarray(sub, dtype=device_dtype(sub.dtype))
    if table is not None and sub.dtype == np.float16:
        return table[sub.view(np.uint16)]
    return _std_units(sub, vol)


@dataclass
class BrickStats:
    read: int = 0  # bricks read from the store
    cached: int = 0  # bricks found in the cache
    skipped: int = 0  # blocks not loaded (level -1)
    shards: int = 0  # shard read requests issued
    read_ms: float = 0.0


def _checked(vol: Any, levels: np.ndarray) -> tuple[Layout, np.ndarray]:
    lay = Layout(tuple(vol.shape), int(vol.block_size))
    levels = np.asarray(levels)
    if levels.shape != lay.grid:
        raise ValueError(f"level grid has shape {levels.shape}, the volume's block grid is {lay.grid}")
    return lay, levels.ravel()


def _cached(cache: BrickPool, vol: Any, lay: Layout, flat: np.ndarray, what: str, stats: BrickStats,
            missing: list) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """The batches of `flat`'s bricks that the pool holds; appends (level, blocks) of the others to `missing`."""
    n_blocks = flat.size
    for k in np.unique(flat[flat >= (0 if what == "mean" else 1)]).tolist():
        blocks = np.flatnonzero(flat == k)
        if vol.key is None:
            missing.append((k, blocks))
            continue
        fam = (_KIND[what], vol.key, k)
        held = cache.find(fam, n_blocks, blocks) >= 0
        hit, lost = blocks[held], [blocks[~held]]
        step = max(1, BATCH_BYTES // ((lay.block_edge(k) ** 3) * 4))
        for i in range(0, hit.size, step):
            part = hit[i:i + step]
            ok, got = cache.get(fam, n_blocks, part)  # (evicted since find by another thread: read below)
            stats.cached += int(ok.sum())
            if got is not None and ok.any():
                yield k, part[ok], got
            lost.append(part[~ok])
        missing.append((k, np.sort(np.concatenate(lost))))  # C order, as the shards are read


def _by_shard(lay: Layout, missing: list) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """The missing bricks ((level, blocks) pairs) by shard: (level, blocks, their (z, y, x)), (level, shard)
    sorted, each shard's blocks in C order."""
    groups = []
    for k, blocks in missing:
        if not blocks.size:
            continue
        e, sh = lay.block_edge(k), np.array(lay.shard_shape(k))
        zyx = np.stack(np.unravel_index(blocks, lay.grid), axis=1)
        shard = zyx * e // sh
        key = np.ravel_multi_index(tuple(shard.T), tuple(int(v) + 1 for v in shard.max(axis=0)))
        order = np.argsort(key, kind="stable")
        cuts = np.flatnonzero(np.diff(key[order])) + 1
        groups += [(k, part, where) for part, where in zip(np.split(blocks[order], cuts), np.split(zyx[order], cuts))]
    return groups


def _remote(vol: Any) -> bool:
    return "://" in str(getattr(vol.source, "location", ""))


def brick_batches(eng: Engine, vol: Any, levels: np.ndarray, cache: BrickPool | None = None, what: str = "mean",
                  stats: BrickStats | None = None) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """(level, blocks, bricks) for every brick `levels` selects, in batches: `blocks` the flat indices (C order of
    the grid) of the blocks whose bricks `bricks` (n, e, e, e) holds, from `cache` (default: `eng`'s pool) or read
    from the store (missing ones only, grouped by shard, shards read in parallel, a few at a time so that bricks
    stream through rather than pile up: a caller that places each batch keeps none); read bricks enter the pool.
    Values keep the store's type up to 16-bit integers, else float32. what="std": the standard deviations of the
    coarse bricks (level >= 1; level 0 has none), uint16 in units of vol.std_unit, instead of the values. `stats`
    is filled in."""
    cache = eng.bricks if cache is None else cache
    stats = BrickStats() if stats is None else stats
    t = time.perf_counter()
    lay, flat = _checked(vol, levels)
    stats.skipped = int(np.count_nonzero(flat < 0))
    missing: list = []
    yield from _cached(cache, vol, lay, flat, what, stats, missing)
    groups = _by_shard(lay, missing)
    stats.shards = len(groups)
    threads = eng.read_threads(_remote(vol))
    table = std_table(vol) if what == "std" else None
    window = 2 * threads
    futs: deque = deque()

    def take() -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        k, blocks, fut = futs.popleft()
        got = fut.result()
        stats.read += len(got)
        if vol.key is not None:
            cache.put((_KIND[what], vol.key, k), flat.size, blocks, got)
        yield k, blocks, got

    for k, blocks, zyx in groups:
        futs.append((k, blocks, eng.read_pool(threads).submit(_read_group, vol, lay, k, zyx, what, table)))
        if len(futs) > window:
            yield from take()
    while futs:
        yield from take()
    if what == "mean":
        cache.reads += stats.read
    stats.read_ms = (time.perf_counter() - t) * 1e3


#: a sink of place_bricks: takes (level, blocks, bricks) batches as brick_batches yields them, from any thread
Sink = Callable[[int, np.ndarray, np.ndarray], None]


def place_bricks(eng: Engine, vol: Any, levels: np.ndarray, sinks: Mapping[str, Sink],
                 cache: BrickPool | None = None, stats: BrickStats | None = None) -> None:
    """Every brick `levels` selects, of each kind in `sinks` ("mean" and/or "std", as brick_batches' `what`),
    handed to that kind's sink in batches: the ones `cache` (default: `eng`'s pool) holds from the calling
    thread, the others from the reader threads, each shard's batch as soon as it is read (and put into the pool
    there). The shards of both kinds are read in one queue, a shard's values beside its deviations, on a reader
    per CPU: the calling thread only waits, and no batch is handed from thread to thread. A sink is called from
    several threads at once with batches of different blocks. `stats` (the values') is filled in; when a read
    fails no sink is called any more by the time the error is raised."""
    cache = eng.bricks if cache is None else cache
    stats = BrickStats() if stats is None else stats
    t = time.perf_counter()
    lay, flat = _checked(vol, levels)
    stats.skipped = int(np.count_nonzero(flat < 0))
    queues = []
    for what, sink in sinks.items():
        missing: list = []
        for k, blocks, got in _cached(cache, vol, lay, flat, what, stats if what == "mean" else BrickStats(),
                                      missing):
            sink(k, blocks, got)
        groups = _by_shard(lay, missing)
        if what == "mean":
            stats.shards = len(groups)
        queues.append([(what, *g) for g in groups])
    jobs = [j for row in itertools.zip_longest(*queues) for j in row if j is not None]
    remote = _remote(vol)
    threads = eng.read_threads(remote, caller_waits=True)
    table = std_table(vol) if "std" in sinks else None
    pool = eng.read_pool(threads)
    futs: deque = deque()

    def done() -> None:
        what, fut = futs.popleft()
        n = fut.result()
        stats.read += n if what == "mean" else 0

    try:
        for what, k, blocks, zyx in jobs:  # a few shards ahead: the readers are shared with other renders
            futs.append((what, pool.submit(_read_into, vol, lay, k, blocks, zyx, what, table, cache, flat.size,
                                           sinks[what])))
            while len(futs) > 2 * threads:
                done()
        while futs:
            done()
    finally:  # (after an error: the shards still queued are dropped, and those being read finish first)
        for _, fut in futs:
            fut.cancel()
        concurrent.futures.wait([f for _, f in futs])
    cache.reads += stats.read
    stats.read_ms = (time.perf_counter() - t) * 1e3


def _read_into(vol: Any, lay: Layout, k: int, blocks: np.ndarray, zyx: np.ndarray, what: str,
               table: np.ndarray | None, cache: BrickPool, n_blocks: int, sink: Sink) -> int:
    """Runs in a reader thread: one shard's bricks read, put into the pool and handed to `sink`; their count."""
    got = _read_group(vol, lay, k, zyx, what, table)
    if vol.key is not None:
        cache.put((_KIND[what], vol.key, k), n_blocks, blocks, got)
    sink(k, blocks, got)
    return len(got)


def load_bricks(eng: Engine, vol: Any, levels: np.ndarray, cache: BrickPool | None = None,
                what: str = "mean") -> AtlasLoad:
    """brick_batches as a dict (level, bz, by, bx) -> brick, with its counts (references and tests: a dict of
    bricks is what a per-brick reference packs)."""
    st = BrickStats()
    bricks = {}
    grid = np.asarray(levels).shape
    for k, blocks, got in brick_batches(eng, vol, levels, cache, what, st):
        for b, a in zip(np.stack(np.unravel_index(blocks, grid), axis=1).tolist(), got):
            bricks[(k, *b)] = a
    return AtlasLoad(bricks, st.read, st.cached, st.skipped, st.shards, st.read_ms)
