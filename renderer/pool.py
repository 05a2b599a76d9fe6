"""The engine's host brick pool: every brick an engine has read, of every store, level and quality, in one pool
bounded by bytes (`Engine.bricks`).

A million small coarse bricks as a million arrays in a dict cost a Python object, a key tuple and an LRU entry each,
and looking them up, placing them and evicting them one at a time was most of a large volume's host time. Here the
bricks of one (kind, store key, level) — an *arena* — lie in slabs of equal-shaped rows, and a block finds its row
through a grid-sized slot table: lookup, gather, insertion and eviction take index arrays and run as NumPy
operations, whatever the number of bricks. Recency is a stamp per row (the pool's operation count when the brick
was last asked for or stored); eviction takes the least recent rows of all arenas together, so one quality's
bricks give way to another's only by age, never by belonging to another selection.

Beside the arenas the pool holds *whole arrays*: a full-resolution pass's voxels, laid out as the kernel reads them
(renderer/data/passes.py). Turning bricks into a sub-volume of voxels is a transposing copy that costs several
times a plain one, so a render beyond the device budget keeps each pass's voxels rather than the bricks they came
from; they age and go by the same stamps as the bricks.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from lodcast.renderer.cache import ByteBound

__all__ = ["BrickPool", "ROW_BYTES", "SLAB_BYTES"]

#: what a pooled brick costs beyond its samples: its row's owner and stamp (int64 each)
ROW_BYTES = 16
#: bytes of one slab of an arena's rows: memory is taken and given back a slab at a time
SLAB_BYTES = 4 << 20
#: eviction frees down to this share of the bound, so that a cold render that fills the pool sorts the pool's
#: stamps once every few slabs rather than at every insertion
EVICT_TO = 0.875


@dataclass
class _Arena:
    shape: tuple[int, ...]  # one brick's
    dtype: np.dtype
    per: int  # rows per slab
    slot: np.ndarray  # per block (flat grid index): its row, -1 when absent
    slabs: list = field(default_factory=list)  # (per, *shape) arrays, None where given back
    owner: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # per row: its block, -1 free
    stamp: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # per row: last use
    free_rows: bool = False  # whether a live slab may hold a free row (none while the arena only fills)
    #: the free rows of the live slabs, ascending, where known (None: look for them): what the last `rows` left
    spare: np.ndarray | None = None

    @property
    def brick_bytes(self) -> int:
        return int(np.prod(self.shape)) * self.dtype.itemsize

    def rows(self, n: int) -> np.ndarray:
        """n free rows, the lowest first (rows fill slabs in order: a slab empties when its bricks age together),
        adding slabs as needed."""
        live = np.array([s is not None for s in self.slabs], bool)
        # (a pool filling up has no free row in its live slabs: looking for them among all rows at every insertion
        # made a large volume's first image quadratic in its bricks; a full pool's, after each eviction, kept
        # from one insertion to the next, costs a new view's reads as much)
        free = np.zeros(0, np.int64)
        if self.free_rows and self.spare is not None:
            free = self.spare
        elif self.free_rows:
            free = np.flatnonzero(self.owner[:live.size * self.per] < 0)
            free = free[live[free // self.per]]
        if free.size >= n:
            self.free_rows, self.spare = free.size > n, free[n:]
            return free[:n]
        more = -(-(n - free.size) // self.per)
        empty = [i for i, s in enumerate(self.slabs) if s is None]
        new: list[int] = []
        for _ in range(more):
            i = empty.pop(0) if empty else len(self.slabs)
            if i == len(self.slabs):
                self.slabs.append(None)
            new.append(i)
        if self.owner.size < len(self.slabs) * self.per:  # the books grow by half at a time, not a slab at a time
            grow = max(len(self.slabs) * self.per, self.owner.size * 3 // 2) - self.owner.size
            self.owner = np.concatenate([self.owner, np.full(grow, -1, np.int64)])
            self.stamp = np.concatenate([self.stamp, np.zeros(grow, np.int64)])
        for i in new:
            self.slabs[i] = np.empty((self.per, *self.shape), self.dtype)
        extra = np.concatenate([np.arange(i * self.per, (i + 1) * self.per) for i in new])
        rows = np.concatenate([free, extra])
        self.free_rows, self.spare = rows.size > n, np.sort(rows[n:])
        return rows[:n]

    def gather(self, rows: np.ndarray) -> np.ndarray:
        """The bricks of `rows`, (n, *shape): one gather per slab they lie in."""
        out = np.empty((rows.size, *self.shape), self.dtype)
        slab = rows // self.per
        order = np.argsort(slab, kind="stable")
        bounds = np.flatnonzero(np.diff(slab[order])) + 1
        for part in np.split(order, bounds) if rows.size else []:
            out[part] = self.slabs[int(slab[part[0]])][rows[part] % self.per]
        return out

    def scatter(self, rows: np.ndarray, bricks: np.ndarray) -> None:
        if rows.size and int(rows[-1]) - int(rows[0]) == rows.size - 1 and rows[0] // self.per == rows[-1] // self.per:
            # (rows in one run of one slab, as a filling arena hands them out: a plain copy)
            lo = int(rows[0]) % self.per
            self.slabs[int(rows[0]) // self.per][lo:lo + rows.size] = bricks
            return
        slab = rows // self.per
        order = np.argsort(slab, kind="stable")
        bounds = np.flatnonzero(np.diff(slab[order])) + 1
        for part in np.split(order, bounds) if rows.size else []:
            self.slabs[int(slab[part[0]])][rows[part] % self.per] = bricks[part]

    def give_back(self) -> None:
        """Drop the slabs that no longer hold a brick."""
        used = np.bincount(np.flatnonzero(self.owner >= 0) // self.per, minlength=len(self.slabs)) > 0
        for i in np.flatnonzero(~used).tolist():
            self.slabs[i] = None
        self.spare = None


def _least_recent(stamps: np.ndarray, costs: np.ndarray, nbytes: int) -> np.ndarray:
    """The places (in no order) of the entries a stable sort by `stamps` puts first, as few as make their `costs`
    reach `nbytes` (all of them when the total falls short): the entries older than the stamp where the running
    total reaches it, and the first ones of that stamp in place order. Counted per stamp rather than sorted: a
    pool holds a million bricks, and a new view's reads pass its bound several times."""
    if not stamps.size:
        return np.zeros(0, np.int64)
    lo = int(stamps.min())
    span = int(stamps.max()) - lo + 1
    if span > 4 * stamps.size + (1 << 20):  # (stamps too sparse to count per stamp)
        order = np.argsort(stamps, kind="stable")
        return order[:int(np.searchsorted(np.cumsum(costs[order]), nbytes)) + 1]
    total = np.cumsum(np.bincount(stamps - lo, weights=costs, minlength=span))  # (exact: bytes below 2^53)
    t = int(np.searchsorted(total, nbytes))
    if t >= span:
        return np.arange(stamps.size)
    tie = np.flatnonzero(stamps == lo + t)
    before = float(total[t - 1]) if t else 0.0
    m = int(np.searchsorted(np.cumsum(costs[tie]), nbytes - before)) + 1
    return np.concatenate([np.flatnonzero(stamps < lo + t), tie[:m]])


class BrickPool(ByteBound):
    """Bricks keyed by (kind, store key, level) and the block's flat index in the block grid; bounded by the bytes
    of the bricks it holds (each brick's samples plus ROW_BYTES; `max_bytes` a number, or a function asked at every
    insertion). Thread-safe. `reads` counts the bricks of values read from stores (the loader adds to it)."""

    def __init__(self, max_bytes: "int | Callable[[], int]"):
        super().__init__(max_bytes)
        self._arenas: dict[tuple, _Arena] = {}
        self._whole: dict[tuple, tuple[np.ndarray, int]] = {}  # family -> (array, stamp)
        self._count = 0
        self._tick = 0
        self.reads = 0

    def __len__(self) -> int:
        return self._count

    def find(self, family: tuple, n_blocks: int, blocks: np.ndarray) -> np.ndarray:
        """The rows of `blocks` (flat block indices) in `family`'s arena, -1 for those not held; the held ones
        count as used now."""
        blocks = np.asarray(blocks, np.int64)
        with self._lock:
            a = self._arenas.get(family)
            if a is None or a.slot.size != n_blocks:
                return np.full(blocks.size, -1, np.int64)
            rows = a.slot[blocks].astype(np.int64)
            self._tick += 1
            a.stamp[rows[rows >= 0]] = self._tick
            return rows

    def get(self, family: tuple, n_blocks: int, blocks: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Which of `blocks` are held (a mask) and their bricks (n held, *brick shape; None when the arena does not
        exist), looked up and gathered under one lock: rows that `find` gave may be evicted and reused by another
        thread's `put` before they are read. The held count as used now."""
        blocks = np.asarray(blocks, np.int64)
        with self._lock:
            a = self._arenas.get(family)
            if a is None or a.slot.size != n_blocks:
                return np.zeros(blocks.size, bool), None
            rows = a.slot[blocks].astype(np.int64)
            held = rows >= 0
            self._tick += 1
            a.stamp[rows[held]] = self._tick
            return held, a.gather(rows[held])

    def put(self, family: tuple, n_blocks: int, blocks: np.ndarray, bricks: np.ndarray) -> None:
        """Hold `bricks` (n, *shape) of `blocks` (flat indices) in `family`'s arena, evicting the least recently used
        bricks of the pool beyond its bound; what does not fit the bound at all is not kept, and blocks already held
        (another thread read them too) keep their row."""
        blocks = np.asarray(blocks, np.int64)
        with self._lock:
            a = self._arenas.get(family)
            if a is None or a.slot.size != n_blocks or a.shape != bricks.shape[1:] or a.dtype != bricks.dtype:
                if a is not None:
                    self._drop(family)
                per = max(1, SLAB_BYTES // max(1, int(np.prod(bricks.shape[1:])) * bricks.dtype.itemsize))
                a = self._arenas[family] = _Arena(bricks.shape[1:], bricks.dtype, per, np.full(n_blocks, -1, np.int32))
            new = a.slot[blocks] < 0
            if not new.all():  # (a batch's bricks are copied once more only where some are held already)
                blocks, bricks = blocks[new], bricks[new]
            cost = a.brick_bytes + ROW_BYTES
            bound = self.max_bytes
            keep = min(blocks.size, bound // cost)
            blocks, bricks = blocks[:keep], bricks[:keep]
            if self._bytes + keep * cost > bound:
                self._evict(self._bytes + keep * cost - int(bound * EVICT_TO))
                self._arenas[family] = a  # (an arena the eviction emptied is dropped: this one is about to fill)
            if not keep:
                return
            rows = a.rows(keep)
            a.scatter(rows, bricks)
            self._tick += 1
            a.owner[rows], a.stamp[rows], a.slot[blocks] = blocks, self._tick, rows
            self._bytes += keep * cost
            self._count += keep

    def held(self, family: tuple) -> np.ndarray | None:
        """The whole array held for `family` (`hold`), or None; it counts as used now. The array is the pool's
        own (read it, do not write it): eviction only lets go of it, so a caller holding it keeps it intact."""
        with self._lock:
            hit = self._whole.get(family)
            if hit is None:
                return None
            self._tick += 1
            self._whole[family] = (hit[0], self._tick)
            return hit[0]

    def hold(self, family: tuple, array: np.ndarray) -> bool:
        """Keep `array` itself (no copy; the caller no longer writes it) as `family`'s whole array, evicting the
        least recently used bricks and arrays beyond the bound; False where it alone exceeds the bound (not kept)."""
        cost = int(array.nbytes) + ROW_BYTES
        with self._lock:
            if family in self._whole:
                self._forget(family)
            bound = self.max_bytes
            if cost > bound:
                return False
            if self._bytes + cost > bound:
                self._evict(self._bytes + cost - int(bound * EVICT_TO))
            self._tick += 1
            self._whole[family] = (array, self._tick)
            self._bytes += cost
            self._count += 1
            return True

    def _forget(self, family: tuple) -> None:
        array, _ = self._whole.pop(family)
        self._bytes -= int(array.nbytes) + ROW_BYTES
        self._count -= 1

    def trim(self) -> None:
        """Evict down to the bound now (a bound that is a function may have shrunk since the last insertion)."""
        with self._lock:
            bound = self.max_bytes
            if self._bytes > bound:
                self._evict(self._bytes - bound)

    def clear(self) -> None:
        with self._lock:
            self._arenas.clear()
            self._whole.clear()
            self._bytes = self._count = 0

    def _drop(self, family: tuple) -> None:
        a = self._arenas.pop(family)
        n = int(np.count_nonzero(a.owner >= 0))
        self._bytes -= n * (a.brick_bytes + ROW_BYTES)
        self._count -= n

    def _evict(self, nbytes: int) -> None:
        """Free at least `nbytes` (or everything), the least recently used bricks and whole arrays of all arenas
        first."""
        fams = list(self._arenas)
        held = [np.flatnonzero(self._arenas[f].owner >= 0) for f in fams]
        wholes = list(self._whole)
        none = np.zeros(0, np.int64)
        stamps = np.concatenate([self._arenas[f].stamp[h] for f, h in zip(fams, held)]
                                + [np.array([self._whole[w][1] for w in wholes], np.int64)])
        # a whole array is arena -1 - its place in `wholes`
        which = np.concatenate([np.full(h.size, i, np.int64) for i, h in enumerate(held)]
                               + [-1 - np.arange(len(wholes), dtype=np.int64)])
        rows = np.concatenate(held + [np.zeros(len(wholes), np.int64)]) if held or wholes else none
        costs = np.concatenate([np.full(h.size, self._arenas[f].brick_bytes + ROW_BYTES, np.int64)
                                for f, h in zip(fams, held)]
                               + [np.array([self._whole[w][0].nbytes + ROW_BYTES for w in wholes], np.int64)])
        gone = _least_recent(stamps, costs, nbytes)
        for i in (-1 - which[gone[which[gone] < 0]]).tolist():
            self._forget(wholes[i])
        gone = gone[which[gone] >= 0]
        for i, f in enumerate(fams):
            a = self._arenas[f]
            r = rows[gone[which[gone] == i]]
            if not r.size:
                continue
            a.slot[a.owner[r]] = -1
            a.owner[r] = -1
            a.free_rows, a.spare = True, None
            a.give_back()
            if not (a.owner >= 0).any():  # its block table is as large as the grid: not kept for nothing
                del self._arenas[f]
        self._bytes -= int(costs[gone].sum())
        self._count -= int(gone.size)
