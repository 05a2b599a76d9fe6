"""Brick atlas, block index map and brick cache (thesis §3.4: IDX, LOAD, PACK).

A level selection (grid-shaped int8: the store level of every block, -1 = not loaded) becomes:

- the **atlas**: one buffer (of `volume.device_dtype`) holding the selected bricks one after another, the bricks
  of a level together, each the block's (B >> level)³ samples in C order (z, y, x), a level-0 brick inside a
  one-sample apron of its level-0 neighbours' samples (`aprons.py`: nearest block reads one brick and is still
  trilinear across faces between level-0 blocks; on PoCL trilinear sampling from a plain buffer is faster than
  from a 3D image). One allocation: it must fit CL_DEVICE_MAX_MEM_ALLOC_SIZE, else `DeviceError` says how
  much it needs and what the device allows;
- the **index map**: one uint64 per block (C order of the grid): 0 for a block that is not loaded, else
  ``(offset << 16) | ((sz + 1) << 12) | ((sy + 1) << 8) | ((sx + 1) << 4) | (level + 1)``, offset = the brick's
  first element in the atlas (element offset, up to 2^48), s_a = the coarsest level among the 3x3 blocks of the
  block's own slice across axis a (unloaded blocks count as 0): interblock sampling's fast path, see
  lc_atlas.h; read by lc_atlas.h;
- the **step-level grid** for adaptive object-space sampling (half-block cells, see raycast.cl).

Bricks come from the brick cache (renderer/data/bricks.py). The device buffers of the selections stay in the device
cache (the engine's `device_cache`: same store and levels, nothing is packed or uploaded again).
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import ctypes
import sys
import time
import weakref
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Any, Callable, cast

import numpy as np
import pyopencl as cl
from numpy.typing import ArrayLike

from lodcast.opencl import DeviceError
from lodcast.renderer.data import aprons
from lodcast.renderer.data.bricks import BrickStats, Sink, place_bricks
from lodcast.renderer.data.volume import voxel_options
from lodcast.renderer.engine import Engine
from lodcast.renderer.pool import BrickPool
from lodcast.store.layout import beside

__all__ = ["DeviceAtlas", "pack", "pack_index", "slice_max", "pack_std", "unplaced", "step_levels", "skipped", "NEAR_LEVEL0",
           "device_atlas", "half_cells", "brick_elements", "coarse_elements", "deviation_bytes",
           "neighbourhood_max", "pair_reduce", "per_cell", "copy_kept", "dirty_blocks", "step_levels_from"]

MISSING = 0


def neighbourhood_max(levels: np.ndarray) -> np.ndarray:
    """Per block: the largest value over its 3x3x3 neighbourhood (itself included). Levels: unloaded blocks
    (-1) count as 0; float arrays (block infos) are taken as they are."""
    levels = np.asarray(levels)
    if levels.dtype.kind in "iu":  # (in the levels' own type: a pass over int64 costs eight times the bytes)
        return _spread_max(np.maximum(levels, 0), (0, 1, 2)).astype(np.int64)
    return _spread_max(levels, (0, 1, 2))


def _spread_max(a: np.ndarray, axes: tuple[int, ...]) -> np.ndarray:
    """Per element: the largest value over its 3-neighbourhood along each of `axes` in turn, edges repeated (a
    3x3x3 or 3x3 neighbourhood's maximum as one pass per axis, the order of a maximum's terms being free)."""
    out = a
    for ax in axes:
        src, out = out, out.copy()
        lo, hi = ([slice(None)] * a.ndim for _ in range(2))
        lo[ax], hi[ax] = slice(0, -1), slice(1, None)
        np.maximum(out[tuple(hi)], src[tuple(lo)], out=out[tuple(hi)])
        np.maximum(out[tuple(lo)], src[tuple(hi)], out=out[tuple(lo)])
    return out


def slice_max(levels: np.ndarray) -> np.ndarray:
    """(grid + (3,)): per block and axis a (x, y, z), the largest level among the 3x3 blocks of its own slice
    across a (itself and the 8 neighbours that share its a-coordinate; unloaded blocks count as 0)."""
    lv = np.maximum(np.asarray(levels), 0)
    out = np.empty(lv.shape + (3,), np.int64)
    for a, ax in enumerate((2, 1, 0)):  # x, y, z: the slice keeps array axis ax fixed
        out[..., a] = _spread_max(lv, tuple(i for i in range(3) if i != ax))
    return out


def pack_index(offset: np.ndarray, level: np.ndarray, slices: np.ndarray | None = None) -> np.ndarray:
    """Index map entries: 0 where level < 0, else (offset << 16) | ((sz + 1) << 12) | ((sy + 1) << 8) |
    ((sx + 1) << 4) | (level + 1), as uint64; slices (..., 3) = slice_max per axis (default: the level itself)."""
    level = np.asarray(level, np.int64)
    sl = np.repeat(level[..., None], 3, axis=-1) if slices is None else np.asarray(slices, np.int64)
    if max(level.max(initial=-1), sl.max(initial=-1)) > 14:
        raise ValueError("levels above 14 do not fit the index map's 4-bit level fields")
    offset = np.asarray(offset, np.uint64)
    if offset.size and int(offset.max()) >= 2**48:
        raise ValueError("atlas offsets of 2^48 elements and more do not fit the index map")
    ent = (offset << np.uint64(16)) | (level + 1).astype(np.uint64)
    for a in range(3):
        ent |= (sl[..., a] + 1).astype(np.uint64) << np.uint64(4 + 4 * a)
    return np.where(level >= 0, ent, np.uint64(MISSING)).astype(np.uint64)


def brick_elements(levels: ArrayLike, block_size: int) -> np.ndarray:
    """Atlas elements of every block's brick (grid-shaped int64, 0 for unloaded blocks): (B >> level) samples per
    edge, plus the one-sample apron on every face at level 0."""
    lv = np.asarray(levels).astype(np.int64)
    n = block_size >> np.maximum(lv, 0)
    return np.where(lv >= 0, (n + 2 * (lv == 0)) ** 3, 0)


def _levels_in(flat: np.ndarray) -> list[int]:
    """The levels a flat selection loads, ascending (counted, not np.unique's sort of the grid)."""
    return np.flatnonzero(np.bincount(flat[flat >= 0].astype(np.int64))).tolist()


def _offsets(levels: np.ndarray, block_size: int) -> tuple[np.ndarray, np.ndarray]:
    """(sizes, offsets) of every block's brick in the atlas, C order of the grid (0 for unloaded blocks). The
    bricks of one level lie together, in C order of the grid within it, the coarsest level first and level 0 last:
    the host's reference fills level 0's aprons as one array (`aprons.fill_aprons`), and the deviations beside the
    atlas need a buffer as long as the coarse bricks only (`coarse_elements`)."""
    lv = np.asarray(levels).ravel()
    sizes = brick_elements(lv, block_size)
    offsets = np.zeros(sizes.size, np.int64)
    start = 0
    for k in reversed(_levels_in(lv)):
        mine = np.flatnonzero(lv == k)  # (C order: each level's rank among its own, no sort of the grid)
        size = int(brick_elements(np.int64(k), block_size))
        offsets[mine] = start + size * np.arange(mine.size, dtype=np.int64)
        start += size * mine.size
    if start and (lv < 0).any():  # unloaded blocks take the end, as they would sort last
        offsets[lv < 0] = start
    return sizes, offsets


def _checked_offsets(levels: np.ndarray, block_size: int, max_bytes: int | None,
                     itemsize: int = 4) -> tuple[np.ndarray, int]:
    """(offsets, total elements) of the atlas of `levels` (voxels of `itemsize` bytes); DeviceError when it would
    exceed `max_bytes` (None: no limit)."""
    sizes, offsets = _offsets(levels, block_size)
    total = int(sizes.sum())
    _check_alloc(total * itemsize, max_bytes, "brick atlas")
    return offsets, total


def _check_alloc(nbytes: int, max_bytes: int | None, what: str) -> None:
    """DeviceError when a buffer of `nbytes` would exceed `max_bytes` (None: no limit)."""
    if max_bytes is None:
        return
    limit = int(max_bytes)
    if nbytes > limit:
        raise DeviceError(
            f"the level-of-detail selection needs a {nbytes / 2**20:.1f} MiB {what}, more than the device's "
            f"largest allocation ({limit / 2**20:.1f} MiB, CL_DEVICE_MAX_MEM_ALLOC_SIZE); choose a smaller "
            "budget_mb or a larger reduction"
        )


def _place(out: np.ndarray, grid: tuple, offsets: np.ndarray, items: Any) -> None:
    """Write each ((level, bz, by, bx), brick) of `items` at its block's offset in `out` (cast to out's type): a
    level-0 brick inside its apron, which `aprons.py` fills."""
    for (k, z, y, x), a in items:
        o = int(offsets[(z * grid[1] + y) * grid[2] + x])
        if k == 0:
            m = a.shape[0] + 2
            out[o:o + m**3].reshape(m, m, m)[1:-1, 1:-1, 1:-1] = a
        else:
            out[o:o + a.size] = a.ravel()


class _Placer:
    """Writes (level, blocks, bricks) batches (bricks.brick_batches) at their blocks' offsets in `out` (cast to
    out's type), as `_place` does brick by brick: the bricks of a level lie together in C order of the grid, each
    the same size, so a batch is one assignment into the level's run of bricks. Safe to call from several threads
    at once with batches of different blocks (they write different elements); `bits`: coarse bricks go in as their
    16 bits (the low halves of the deviations' buffer, lc_sig: two's complement for signed types, 8-bit types
    widened as the kernel narrows them back, lc_common.h: LC_SIG_VALUE)."""

    def __init__(self, out: np.ndarray, offsets: np.ndarray, runs: dict[int, tuple[int, int, int]],
                 bits: bool = False) -> None:
        self.out, self.offsets, self.runs, self.bits = out, offsets.ravel(), runs, bits

    @staticmethod
    def runs_of(levels: np.ndarray, offsets: np.ndarray, block_size: int) -> dict[int, tuple[int, int, int]]:
        """Per level: (its run's first element, its bricks, their edge with the apron), the same for every buffer
        of an atlas (its placers share them)."""
        flat, at = np.asarray(levels).ravel(), offsets.ravel()
        runs = {}
        for k in _levels_in(flat):
            mine = at[flat == k]
            runs[k] = int(mine.min()), mine.size, (block_size >> k) + 2 * (k == 0)
        return runs

    def __call__(self, k: int, blocks: np.ndarray, bricks: np.ndarray) -> None:
        if self.bits:
            bricks = (bricks if bricks.dtype.itemsize == 2 else bricks.astype(np.int16)).view(np.uint16)
        o0, n, m = self.runs[k]
        run = self.out[o0:o0 + n * m**3].reshape(n, m, m, m)
        rows = (self.offsets[blocks] - o0) // m**3
        if k == 0:
            run[rows, 1:-1, 1:-1, 1:-1] = bricks
        else:
            run[rows] = bricks


def pack(levels: np.ndarray, bricks: dict, block_size: int, max_bytes: int | None = None,
         slices: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(atlas float32 1D, index map uint64 grid-shaped), on the host (tests, references; renders use
    device_atlas). Bricks are packed in C order of the grid. Raises
    DeviceError when the atlas would exceed `max_bytes` (None: no limit). `slices`: the
    index map's slice maxima (default slice_max(levels); a pass of a render in several packs part of a selection
    with the whole selection's)."""
    levels = np.asarray(levels)
    offsets, total = _checked_offsets(levels, block_size, max_bytes)
    atlas = np.empty(max(total, 1), np.float32)
    _place(atlas, levels.shape, offsets, bricks.items())
    aprons.fill_aprons(atlas, levels, offsets, block_size)
    return atlas, _index(levels, offsets, slices)


def _index(levels: np.ndarray, offsets: np.ndarray, slices: np.ndarray | None) -> np.ndarray:
    sl = slice_max(levels) if slices is None else slices
    return pack_index(offsets, np.asarray(levels).astype(np.int64).ravel(), sl.reshape(-1, 3)).reshape(levels.shape)


def coarse_elements(levels: np.ndarray, block_size: int) -> int:
    """Atlas elements of the coarse bricks (level >= 1), which lie before the level-0 ones (`_offsets`): the length
    of the deviations' buffer beside the atlas (level 0 has none, and the kernel reads them for coarse bricks
    only)."""
    lv = np.asarray(levels).astype(np.int64)
    return int(brick_elements(np.where(lv >= 1, lv, -1), block_size).sum())


def deviation_bytes(voxel_dtype: Any) -> int:
    """Bytes per element of the deviations' buffer beside an atlas of `voxel_dtype` (lc_common.h: lc_sig): 4 for
    integer voxels (the coarse values' bits packed below the deviation), 2 beside float32."""
    return 4 if np.dtype(voxel_dtype).kind in "iu" else 2


def pack_std(levels: np.ndarray, std_bricks: dict, block_size: int) -> np.ndarray:
    """The standard deviations beside the atlas (uint16 in units of vol.std_unit, same offsets as `pack`, the
    coarse bricks' only) from `std_bricks` ((level, bz, by, bx) -> brick)."""
    _, offsets = _offsets(levels, block_size)
    out = np.zeros(max(coarse_elements(levels, block_size), 1), np.uint16)
    _place(out, np.asarray(levels).shape, offsets, std_bricks.items())
    return out


def step_levels(levels: np.ndarray, block_size: int, skip: np.ndarray | None = None) -> np.ndarray:
    """Adaptive sampling's step level per cell (C order, int8): the kernel steps step * 2^s in a cell of step level
    s, and restarts its steps at the faces of coarse cells (limited: a coarse step never runs into a finer block),
    while runs of level-0 cells keep full resolution's lattice (raycast.cl). A coarse cell with a level-0 cell
    across a face holds s | NEAR_LEVEL0. A skipped cell holds -(code + 1) (`skipped`): the march passes it as it
    would pass it sampled, without its samples, so that what it skips changes no other sample. The cells are the
    half-block cells (grid 2G, cell h in block h >> 1) for both interpolations: nearest block's step level is
    constant over a block, but the walk also leaves out the coarse half-cells that level 0 leaves empty
    (walk._cell_info), which on whole blocks it could do only where all eight are: half-block cells take fewer
    samples for no more image error (benchmarks/bench_lod_sweep.py). A cell takes its own block's level k; cells of
    skipped blocks (`skip`) and of unloaded ones (level -1, stepped as level 0) are skipped.

    s = k at level 0, s = k + 1 at coarse levels (capped at log2 B, the longest step the kernel has a table for;
    a step never runs past its cell anyway): the base step over-samples level 0 (default 1/2 voxel: a sharp TF
    edge crossed inside a voxel), while a level-k field is a smooth average, classified by a distribution that
    blurs the TF by the spread behind it, and needs no more than about one sample per coarse voxel (2^k voxels
    at the default step). Against step * 2^k over the same selections it takes fewer samples for about the same
    image error.

    With interblock interpolation a coarse half-cell next to a finer block keeps its own step too (thesis §3.6.1
    limits it by the finest of the eight blocks around): inside the coarse block the blend towards the finer
    neighbour spans 2^(k-1) voxels and mixes in that neighbour's samples clamped to its face, which are constant
    along the face's normal: along the normal the field there holds no finer detail than the coarse field (at
    most twice as steep); what a coarse step can miss is the neighbour's detail across the face, met by oblique
    rays. The finest-of-eight rule took more samples for the same image error (benchmarks/bench_lod_sweep.py)."""
    lv = np.asarray(levels)
    off = lv < 0 if skip is None else (lv < 0) | np.asarray(skip, bool)
    code = _step_code(lv, block_size)
    # NEAR_LEVEL0: a coarse cell with a level-0 cell across a face, where the kernel looks at the cell the ray
    # enters next (its last step ends on full resolution's lattice there); elsewhere it need not read it. A cell's
    # neighbour across a face inside its block has its own code, so only the blocks across its outer faces count:
    # each of the eight cells of every block (octant o) at once, from the blocks' codes, rather than over the
    # cells' grid with eight times the work
    fine = np.pad(code == 0, 1)
    G = code.shape
    out = np.empty((G[0], 2, G[1], 2, G[2], 2), np.int8)
    inner = tuple(slice(1, 1 + n) for n in G)
    for o in np.ndindex(2, 2, 2):
        near = np.zeros(G, bool)
        for ax in range(3):  # the block before along ax for the lower cell, the one after for the upper
            near |= fine[tuple(slice(2 * o[a], 2 * o[a] + n) if a == ax else inner[a] for a, n in enumerate(G))]
        out[:, o[0], :, o[1], :, o[2]] = _cell_code(code, near, off)
    return out.reshape(2 * G[0], 2 * G[1], 2 * G[2])


def step_levels_from(last: tuple | None, levels: np.ndarray, block_size: int,
                     skip: np.ndarray | None = None) -> np.ndarray:
    """step_levels of (levels, skip) from `last`, the (levels, skip, step levels) of another selection of the same
    grid: a block's eight cells depend on its own level and skip and on whether its six face neighbours are at
    level 0 (or unloaded, stepped as level 0), so only the blocks where one of these changed are computed again
    (tests/test_lod_adaptive.py holds the two equal). A change of most blocks, or none to start from: step_levels
    over the grid."""
    lv = np.asarray(levels)
    if last is None:
        return step_levels(lv, block_size, skip)
    old_lv, old_skip, old_steps = last
    changed = old_lv != lv
    if skip is not None:
        changed |= old_skip != np.asarray(skip, bool)
    fine = (old_lv <= 0) != (lv <= 0)  # a neighbour's NEAR_LEVEL0 follows its level-0 status
    for ax in range(3):
        lo, hi = [slice(None)] * 3, [slice(None)] * 3
        lo[ax], hi[ax] = slice(0, -1), slice(1, None)
        changed[tuple(lo)] |= fine[tuple(hi)]
        changed[tuple(hi)] |= fine[tuple(lo)]
    at = np.flatnonzero(changed)
    if 8 * at.size > lv.size:  # most of the grid: the whole-grid passes cost less than the gathers
        return step_levels(lv, block_size, skip)
    G = lv.shape
    flat = lv.reshape(-1)
    own = flat[at]
    code = _step_code(own, block_size)
    off = own < 0
    if skip is not None:
        off |= np.asarray(skip, bool).reshape(-1)[at]
    pos = np.unravel_index(at, G)
    fine_at = {}  # (axis, side): the face neighbour there is in the grid and at level 0 or unloaded
    for ax in range(3):
        for side in (-1, 1):
            rows, nb = beside(at, pos, G, tuple(side if a == ax else 0 for a in range(3)))
            fine_at[ax, side] = np.zeros(at.size, bool)
            fine_at[ax, side][rows] = flat[nb] <= 0
    cells = np.empty((at.size, 2, 2, 2), np.int8)
    for o in np.ndindex(2, 2, 2):  # the lower cell along an axis looks at the block before, the upper after
        near = fine_at[0, 2 * o[0] - 1] | fine_at[1, 2 * o[1] - 1] | fine_at[2, 2 * o[2] - 1]
        cells[:, o[0], o[1], o[2]] = _cell_code(code, near, off)
    out = old_steps.copy()
    out.reshape(G[0], 2, G[1], 2, G[2], 2)[pos[0], :, pos[1], :, pos[2], :] = cells
    return out


def _step_code(levels: np.ndarray, block_size: int) -> np.ndarray:
    """step_levels' s of each block's level (unloaded: 0), int8 (levels fit 4 bits: pack_index)."""
    code = np.maximum(np.asarray(levels).astype(np.int8), 0)
    np.add(code, 1, out=code, where=code >= 1)
    np.minimum(code, int(block_size).bit_length() - 1, out=code)
    return code


def _cell_code(code: np.ndarray, near: np.ndarray, off: np.ndarray) -> np.ndarray:
    """A cell's step level from its block's s, whether a level-0 cell lies across its outer faces, and whether it
    is skipped (step_levels)."""
    c = np.where((code > 0) & near, code | np.int8(NEAR_LEVEL0), code)
    return np.where(off, -c - np.int8(1), c)


#: step_levels' flag of a coarse cell next to a level-0 one (the step level is the code's low three bits)
NEAR_LEVEL0 = 8


def skipped(steps: np.ndarray, where: np.ndarray) -> np.ndarray:
    """Step levels (`step_levels`) with the cells `where` marks skipped: -(s + 1) (cells skipped already stay)."""
    st = np.asarray(steps, np.int8)  # (in int8 throughout: int64 temporaries, eight bytes a half-block cell,
    out = st.copy()  # add up to a good part of each pass's peak memory on a large volume)
    m = np.asarray(where, bool) & (st >= 0)
    out[m] = -st[m] - 1
    return np.ascontiguousarray(out)


def half_cells(a: np.ndarray) -> np.ndarray:
    """A per-block array over the half-block cells (grid 2G): cell h takes block h >> 1's value."""
    return per_cell(a, 2)


def pair_reduce(a: np.ndarray, f: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> np.ndarray:
    """A grid of cells (z, y, x) reduced to cells of twice the edge by `f` (np.fmin, np.fmax, np.maximum) over each
    one's up to eight children; an odd axis is padded with NaN."""
    for ax in range(3):  # pairs along one axis at a time (a reduction over a 6-D view is much slower)
        if a.shape[ax] % 2:
            pad = [(0, 0)] * 3
            pad[ax] = (0, 1)
            a = np.pad(a, pad, constant_values=np.nan)
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[ax], hi[ax] = slice(0, None, 2), slice(1, None, 2)
        a = f(a[tuple(lo)], a[tuple(hi)])
    return a


def per_cell(a: np.ndarray, k: int) -> np.ndarray:
    """A per-cell array over the grid of cells k times finer per axis: each takes its parent's value."""
    for ax in range(3):
        a = np.repeat(a, k, axis=ax)
    return a


@dataclass(frozen=True)
class DeviceAtlas:
    atlas: cl.Buffer
    std: cl.Buffer | None  # the deviations beside the atlas (uint16, vol.std_unit), for distribution classification
    index: cl.Buffer
    index_host: np.ndarray
    nbytes: int  # atlas bytes
    selected: int  # bricks in the atlas
    read: int
    cached: int
    skipped: int
    read_ms: float
    upload_ms: float
    reused: bool  # the device buffers of a recent render with the same store and levels were reused
    key: tuple | None = None  # its device-cache key (None: not kept)
    voxel: tuple[str, ...] = ()  # the -D option of its voxel type (volume.voxel_options)
    levels: np.ndarray | None = None  # the selection (flat int64), with a kept atlas
    offsets: np.ndarray | None = None  # every brick's first element in its buffer (flat int64, the index's)
    base_key: tuple | None = None  # the device-cache key of the atlas this one was built from (reuse, below)
    base_levels: np.ndarray | None = None  # that atlas's selection (flat int64)
    lease: Any = None  # its buffers' `_Lease`: while any copy of this atlas lives, they are nobody's spares


def _family(vol: Any, levels: np.ndarray, with_std: bool) -> tuple | None:
    """The atlases a new one of `levels` may take bricks from (store key, grid, with deviations, voxel type)."""
    return None if vol.key is None else (vol.key, levels.shape, with_std, str(vol.voxel_dtype))


def _last(eng: Engine, family: tuple | None, levels: np.ndarray) -> tuple[Any, np.ndarray | None]:
    """The newest atlas of `family` and which of `levels`' bricks it holds at the same level (flat), or None."""
    base = None if family is None else eng.last_atlas(family)
    if base is None:
        return None, None
    flat = levels.ravel()
    return base, (base.levels == flat) & (flat >= 0)


def _unkept(levels: np.ndarray, kept: np.ndarray | None) -> np.ndarray:
    return levels if kept is None else np.where(kept.reshape(levels.shape), -1, levels).astype(np.int8)


def unplaced(eng: Engine, vol: Any, levels: np.ndarray, with_std: bool) -> np.ndarray:
    """`levels` less the bricks the next device_atlas of them copies from the newest atlas (-1 there): what it
    would take from the brick pool or the store. A read ahead asks for these only (the pool need not hold what
    the atlas on the device already has)."""
    levels = np.ascontiguousarray(levels, dtype=np.int8)
    return _unkept(levels, _last(eng, _family(vol, levels, with_std), levels)[1])


def device_atlas(eng: Engine, vol: Any, levels: np.ndarray, *, with_std: bool = False, max_bytes: int | None = None,
                 cache: BrickPool | None = None, slices: np.ndarray | None = None,
                 keep: bool = True) -> DeviceAtlas:
    """The atlas and index map of `levels` on `eng`'s device (kept in its device cache: reused when a recent render
    had the same store and levels, else loaded through the brick cache, packed and uploaded); `with_std`: also the
    standard deviations of the coarse bricks, for distribution classification. A pass of a render in several
    gives its part of the selection with the whole one's `slices` (see `pack`) and `keep=False` (its atlas is
    not kept on the device after the pass)."""
    levels = np.ascontiguousarray(levels, dtype=np.int8)
    key = (("atlas", vol.key, levels.shape, eng.digest(levels), with_std)
           if vol.key is not None and keep else None)
    n_sel = int(np.count_nonzero(levels >= 0))
    hit = eng.device_cache.get(key) if key is not None else None
    family = None if key is None else _family(vol, levels, with_std)
    if hit is not None:
        assert family is not None  # a hit needs a key, which comes with a family
        eng.remember_atlas(family, hit)  # the next selection starts from the latest one shown
        return replace(hit, read=0, cached=n_sel, read_ms=0.0, upload_ms=0.0, reused=True)
    t_read = time.perf_counter()
    cache = eng.bricks if cache is None else cache
    dtype = vol.voxel_dtype
    B = int(vol.block_size)
    max_bytes = eng.device.max_alloc_bytes if max_bytes is None else max_bytes
    offsets, total = _checked_offsets(levels, B, max_bytes, dtype.itemsize)
    n_coarse = coarse_elements(levels, B)
    sig_type = np.dtype(f"u{deviation_bytes(dtype)}")  # lc_common.h: lc_sig
    packed = with_std and sig_type.itemsize == 4
    if packed:  # the coarse bricks live in the deviations' buffer alone; level 0's offsets start the atlas
        offsets = np.where(levels.ravel() == 0, offsets - n_coarse, offsets)
        total -= n_coarse
        _check_alloc(n_coarse * sig_type.itemsize, max_bytes, "coarse bricks' buffer")
    index = _index(levels, offsets, slices)
    base, kept = _last(eng, family, levels)
    flat = levels.ravel().astype(np.int64)
    ctx, queue = eng.device.context, eng.device.queue
    st = BrickStats()
    n_std = max(n_coarse, 1)
    nbytes = max(total, 1) * dtype.itemsize + (sig_type.itemsize * n_std if with_std else 0)
    # bricks go straight into the mapped device buffers as they are read, by the reader threads that read them:
    # no packed copy on the host, no brick beyond what the brick cache keeps (a CPU device's buffers are host
    # memory already), and no placing left to this thread; a brick of the last atlas of this store at the same
    # level is copied from there (reuse, below)
    todo = _unkept(levels, kept)
    L = int(flat.max(initial=0)) + 1
    if key is not None:  # what putting this atlas would evict goes now: its buffers are the spares it takes
        eng.device_cache.make_room(nbytes + index.nbytes)
    with eng.holding(nbytes), _reading(queue, base, dtype, sig_type) as old:
        d_std, sig = _mapped(eng, n_std, sig_type, max_bytes) if with_std else (None, None)
        try:
            d_atlas, host = _mapped(eng, max(total, 1), dtype, max_bytes)
            try:
                dirty = None
                # the kept bricks are copied beside the reads, on a thread of their own: they are other blocks'
                # bricks, and the copy (most of it first touches of the new buffer's pages) runs without the
                # interpreter lock, which the readers spend most of their time holding
                with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="lodcast-kept") as beside:
                    copied = None
                    if old is not None:  # kept compares with base, which old maps
                        assert base is not None and kept is not None
                        copied = beside.submit(_copy_kept_all, host, sig, old, flat, offsets, base, kept, L, B,
                                               packed)
                        # a kept level-0 brick's apron came with it, and still holds unless a neighbour's level-0
                        # status changed: the blocks whose cells can change under nearest block are the ones to fill
                        dirty = dirty_blocks(base.levels.reshape(levels.shape), levels, "nearest_block")
                    place_bricks(eng, vol, todo, _sinks(host, sig, levels, offsets, B, packed), cache, st)
                    if copied is not None:
                        copied.result()
            finally:
                cast(cl.MemoryMap, host.base).release(queue)  # a mapped array's base is its mapping
            aprons.device_aprons(eng.device, d_atlas, dtype, levels, offsets, B, dirty)
        finally:
            if sig is not None:
                cast(cl.MemoryMap, sig.base).release(queue)
    if kept is not None:
        st.cached += int(kept.sum())
        st.skipped = int(np.count_nonzero(levels < 0))
    t = time.perf_counter()
    d_index = cl.Buffer(ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=index)
    queue.finish()
    da = DeviceAtlas(d_atlas, d_std, d_index, index, nbytes, n_sel, st.read, st.cached, st.skipped,
                     (t - t_read) * 1e3, (time.perf_counter() - t) * 1e3, False, key, voxel_options(dtype),
                     flat if family is not None else None, offsets.ravel() if family is not None else None,
                     None if base is None else base.key, None if base is None else base.levels,
                     _lease(eng, d_atlas, d_std) if key is not None else None)
    if key is not None:
        assert family is not None
        eng.device_cache.put(key, da, d_atlas.size + (0 if d_std is None else d_std.size) + index.nbytes)
        eng.spares.trim()
        eng.remember_atlas(family, da)
    cache.trim()  # its bound may follow the device cache's bytes
    return da


@contextlib.contextmanager
def _reading(queue: Any, da: "DeviceAtlas | None", dtype: Any,
             sig_type: Any) -> Iterator[tuple[np.ndarray, np.ndarray | None] | None]:
    """Host mappings (atlas of `dtype`, deviations' buffer of `sig_type`) of atlas `da` for reading, while in this
    context (None: no atlas)."""
    if da is None:
        yield None
        return
    maps = [cl.enqueue_map_buffer(queue, b, cl.map_flags.READ, 0, (b.size // np.dtype(t).itemsize,), t)[0]
            if b is not None else None
            for b, t in ((da.atlas, dtype), (da.std, sig_type))]
    assert maps[0] is not None  # an atlas always has its buffer
    try:
        yield maps[0], maps[1]
    finally:
        for m in maps:
            if m is not None:
                m.base.release(queue)


def _mapped(eng: Engine, n: int, dtype: Any, max_bytes: int) -> tuple[cl.Buffer, np.ndarray]:
    """A device buffer of at least n elements and its host mapping of n for writing (the caller releases it): one of
    the engine's spares that fits (renderer/cache.py: Spares; its pages are resident already), else a new one, a
    little larger than asked (within `max_bytes`) so that the next atlas of about this size fits it too, advised
    into huge pages (`_huge_pages`)."""
    nbytes = n * np.dtype(dtype).itemsize
    buf = eng.spares.take(nbytes)
    if buf is None:
        room = min(-(-(nbytes + nbytes // 32) // 64) * 64, max(nbytes, max_bytes))
        buf = cl.Buffer(eng.device.context, cl.mem_flags.READ_ONLY, size=room)
    host, _ = cl.enqueue_map_buffer(eng.device.queue, buf, cl.map_flags.WRITE_INVALIDATE_REGION, 0, (n,), dtype)
    _huge_pages(host)
    return buf, host


class _Lease:
    """A kept atlas's buffers, held for as long as any DeviceAtlas of them lives (copies share it: a device-cache
    hit is one) or a render's pass data (renderer/data/passes.py keeps it until the image is read back); then they
    become the engine's spares, for the next atlas of about their size (`_mapped`). The atlases of a render in
    passes have none: theirs go as they did, since a spare beside the next pass's buffers would be device memory
    beyond the budget."""

    __slots__ = ("__weakref__",)


def _lease(eng: Engine, *bufs: cl.Buffer | None) -> _Lease:
    lease = _Lease()
    f = weakref.finalize(lease, _spare, weakref.ref(eng.spares), [b for b in bufs if b is not None])
    f.atexit = False
    return lease


def _spare(spares: "weakref.ref[Any]", bufs: list) -> None:
    held = spares()
    if held is not None:  # (an engine closed since keeps none)
        for b in bufs:
            held.give(b, b.size)


def _huge_pages(host: np.ndarray) -> None:
    """Ask Linux for transparent huge pages under `host` before it is first written: a cold atlas is hundreds of
    MB written once, and faulting it in 4 KiB pages took a large part of the time spent placing its bricks. The
    whole 2 MiB pages inside it only; elsewhere, or where it is refused, nothing changes."""
    if not sys.platform.startswith("linux"):
        return
    huge = 2 << 20
    lo = -(-host.ctypes.data // huge) * huge
    hi = (host.ctypes.data + host.nbytes) // huge * huge
    if hi > lo:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.madvise(ctypes.c_void_p(lo), ctypes.c_size_t(hi - lo), ctypes.c_int(14))  # MADV_HUGEPAGE


def _sinks(host: np.ndarray, sig: np.ndarray | None, levels: np.ndarray, offsets: np.ndarray, block_size: int,
           packed: bool) -> dict[str, Sink]:
    """bricks.place_bricks' sinks of an atlas (`host`) and, where it has them, the deviations beside it (`sig`):
    packed (integer voxels), the coarse values' 16 bits go below each deviation and level 0 into the atlas."""
    runs = _Placer.runs_of(levels, offsets, block_size)
    if sig is None:
        return {"mean": _Placer(host, offsets, runs)}
    if not packed:
        return {"mean": _Placer(host, offsets, runs), "std": _Placer(sig, offsets, runs)}
    assert np.little_endian, "lc_sig packs the value into the low half: a little-endian host"
    halves = sig.view(np.uint16)
    level0, coarse = _Placer(host, offsets, runs), _Placer(halves[0::2], offsets, runs, bits=True)

    def values(k: int, blocks: np.ndarray, bricks: np.ndarray) -> None:
        (coarse if k >= 1 else level0)(k, blocks, bricks)

    return {"mean": values, "std": _Placer(halves[1::2], offsets, runs)}


# --- reuse: a new selection's atlas from the last one ------------------------------------------------------------
# What a new selection keeps of the last atlas of the same store: bricks copied across, cells recomputed where
# they can have changed. The view-weighted selection (renderer/lod/visibility.py) selects again at every new view, and
# a move of a degree or two changes the level of only a small share of the loaded blocks, while packing every
# brick and bounding every octant again was most of a new view's host time. So `device_atlas` builds a new atlas
# from the engine's `last_atlas` of the same store, TF-independent layout and buffers: a block at the same level
# keeps its brick (one array copy per level: the bricks of a level lie together in C order of the grid), only the
# others are read from the brick cache, and level 0's aprons are filled again towards a neighbour whose level-0
# status changed. The cells' bounds (atlas_cells.py) are copied for every cell that reads no changed block and
# computed on the device for the others (`dirty_blocks` names, per block, the directions a change reaches it
# from). Its buffers are those of the atlas it evicts from the device cache, where no render holds that one any
# more (`_mapped`, `_Lease`). The result is the same atlas, index map and cells,
# element for element, as one packed from nothing (tests/test_atlas_reuse.py).


def copy_kept(dst: np.ndarray, src: np.ndarray, levels: np.ndarray, offsets: np.ndarray, old_levels: np.ndarray,
              old_offsets: np.ndarray, kept: np.ndarray, which: range, block_size: int) -> int:
    """Copy into buffer `dst` (the new atlas's elements at `offsets`) from `src` (the old one's at `old_offsets`)
    the bricks of the blocks `kept` (same level in both) whose level lies in `which` (the levels the buffer
    holds). Flat per-block arrays; a level's bricks lie together in C order of the grid in both buffers, so the
    kept bricks of a level run in the same order in both, and each stretch of them with no brick added or dropped
    between is one slice copy (a small change of levels leaves a few thousand such runs over hundreds of MB,
    where a gather of every brick went through a temporary as large as the atlas). Returns the number of bricks
    copied."""
    copied = 0
    for k in which:
        sel = kept & (levels == k)
        if not sel.any():
            continue
        size = int(brick_elements(np.int64(k), block_size))
        new_at, old_at = offsets[levels == k], old_offsets[old_levels == k]
        n0, o0 = int(new_at.min()), int(old_at.min())
        dv = dst[n0:n0 + new_at.size * size].reshape(new_at.size, size)
        sv = src[o0:o0 + old_at.size * size].reshape(old_at.size, size)
        rows, old_rows = (offsets[sel] - n0) // size, (old_offsets[sel] - o0) // size
        cut = np.flatnonzero((np.diff(rows) != 1) | (np.diff(old_rows) != 1)) + 1
        starts, ends = np.r_[0, cut], np.r_[cut, rows.size]
        for a, n, o in zip(rows[starts].tolist(), (ends - starts).tolist(), old_rows[starts].tolist()):
            dv[a:a + n] = sv[o:o + n]
        copied += rows.size
    return copied


def _copy_kept_all(host: np.ndarray, sig: np.ndarray | None, old: tuple, levels: np.ndarray, offsets: np.ndarray,
                   base: "DeviceAtlas", kept: np.ndarray, n_levels: int, block_size: int, packed: bool) -> None:
    """copy_kept of every buffer of a new atlas (`host`, and `sig` with deviations) from the mappings `old` of
    `base`'s: the deviations' buffer holds the coarse levels (packed: the coarse values ride along with their
    deviations), the atlas level 0 and, unpacked, the coarse values too."""
    assert base.levels is not None and base.offsets is not None  # an atlas built from holds its selection
    if sig is not None:
        assert old[1] is not None  # with_std is part of base's family
        copy_kept(sig, old[1], levels, offsets, base.levels, base.offsets, kept, range(1, n_levels), block_size)
    copy_kept(host, old[0], levels, offsets, base.levels, base.offsets, kept, range(0, 1 if packed else n_levels),
              block_size)


def dirty_blocks(old_levels: np.ndarray, levels: np.ndarray, interpolation: str) -> np.ndarray:
    """The blocks whose cells' bounds (atlas_cells.cl) a change of levels from `old_levels` to `levels` can
    change, and through which blocks: a grid of uint32, 0 where nothing can change, else bit
    9 (dz + 1) + 3 (dy + 1) + (dx + 1) set for each block (own + d) whose change reaches it, bit 13 (d = 0) where
    the block's own level changed. Nearest block reads a block's own brick, and a level-0 brick's apron, which
    holds the neighbours' samples where they are at level 0 too: a block whose level changed, and a level-0 block
    next to (26-neighbourhood) one that became or stopped being level 0, through that one (only its cells and
    apron samples towards it can change). Interblock reads the neighbourhood's bricks: every block next to one
    whose level changed, through each such one. Nonzero is the set of blocks whose cells are computed again."""
    old_levels, levels = np.asarray(old_levels), np.asarray(levels)
    changed = (old_levels != levels).ravel()
    nearest = interpolation != "interblock"
    source = (((old_levels == 0) != (levels == 0)).ravel()) if nearest else changed
    out = np.zeros(levels.size, np.uint32)
    at = np.flatnonzero(source)
    pos = np.unravel_index(at, levels.shape)
    zero = levels.ravel() == 0 if nearest else None
    for bit, d in enumerate(np.ndindex(3, 3, 3)):
        b = beside(at, pos, levels.shape, tuple(1 - e for e in d))[1]  # the block at source - d reaches it
        if zero is not None:
            b = b[zero[b]]  # only level-0 bricks have aprons
        out[b] |= np.uint32(1 << bit)  # (a block at most once per direction: no index repeats)
    if nearest:
        out[np.flatnonzero(changed)] |= np.uint32(1 << 13)
    return out.reshape(levels.shape)
