"""What the multiresolution field sampled from an atlas can take in each of its half-block cells, or in their
octants (quarter-block cells): computed on the device where the atlas is (atlas_cells.cl), kept beside the atlas,
and, for an atlas built from the last one of its store (renderer/data/atlas.py: reuse), computed again only for the
cells the change of levels can reach. Empty-space skipping on the atlas walks these cells and the adaptive walk
masks their octants (renderer/walk/info.py)."""
from __future__ import annotations

import weakref
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import pyopencl as cl

from lodcast.opencl import Device
from lodcast.renderer.data.atlas import DeviceAtlas, dirty_blocks, pair_reduce
from lodcast.renderer.engine import Engine

__all__ = ["AtlasCells", "atlas_cells", "cells_and_octants"]


@dataclass(frozen=True)
class AtlasCells:
    """What the field sampled from an atlas can take in each half-block cell (grid 2G; `cpb` 4: in each of their
    octants, grid 4G; C order; atlas_cells.cl):
    the extrema of its values (NaN: nothing to see) and the largest standard deviation behind them (0 at level 0
    and without distributions), in the data's units; over the cells of the blocks `blocks` (z, y, x slices of the
    block grid; None: all), which a pass of a render in several needs alone."""

    vmin: np.ndarray
    vmax: np.ndarray
    std: np.ndarray
    blocks: tuple[slice, slice, slice] | None = None
    cpb: int = 2  # cells per block edge: 2, half-block cells; 4, their octants (quarter-block cells)
    #: computed from other cells (an atlas built from the last one): those (weakly: None once they are gone), and
    #: the flat indices of the cells computed again; every other cell is theirs, bit for bit
    base: "weakref.ref[AtlasCells] | None" = field(default=None, compare=False, repr=False)
    redone: np.ndarray | None = field(default=None, compare=False, repr=False)

    def derived_from(self, other: "AtlasCells") -> np.ndarray | None:
        """The flat indices of the cells that may differ from `other`'s where these were computed from `other`,
        else None."""
        if self.base is None or self.base() is not other:
            return None
        return self.redone

    @property
    def at(self) -> tuple[slice, ...]:
        """Where these cells lie in the whole grid of cells."""
        if self.blocks is None:
            return (slice(None),) * 3
        return tuple(slice(self.cpb * b.start, self.cpb * b.stop) for b in self.blocks)


def atlas_cells(eng: Engine, da: DeviceAtlas, grid: tuple[int, int, int], block_size: int, interpolation: str,
                std_unit: float = 1.0, blocks: tuple[slice, slice, slice] | None = None, cpb: int = 2) -> AtlasCells:
    """The half-block cells of atlas `da` (block grid `grid`, z-y-x), or those of `blocks` only, computed on the
    device and kept beside the atlas (host arrays, in `eng.cells`, keyed by the atlas's device-cache key):
    empty-space skipping on the atlas walks these cells (renderer/walk/info.py). `cpb` 4: their octants instead, the
    quarter-block cells (block size a multiple of 4)."""
    assert cpb in (2, 4) and block_size % cpb == 0, (cpb, block_size)
    key = None if da.key is None else ("cells", da.key, interpolation, None if blocks is None else str(blocks), cpb)
    hit = eng.cells.get(key) if key is not None else None
    if hit is not None:
        return hit
    base = None
    if blocks is None and da.base_key is not None:  # the atlas was built from another: only changed blocks
        base = eng.cells.get(("cells", da.base_key, interpolation, None, cpb))
    if base is not None:
        cells = _updated_cells(eng.device, da, base, grid, block_size, interpolation, std_unit, cpb)
    else:
        cells = _device_cells(eng.device, da, grid, block_size, interpolation, std_unit, blocks, cpb)
    if key is not None:
        eng.cells.put(key, cells, 3 * cells.vmin.nbytes)
    return cells


def _bounds(dev: Device, da: DeviceAtlas, interpolation: str, cpb: int, entry: str, size: tuple[int, ...],
            grid: tuple[int, int, int], block_size: int, where: tuple, shape: tuple[int, ...],
            std_unit: float, beside: Callable[[], object] | None = None) -> list[np.ndarray]:
    """(min, max, largest deviation in the data's units) of the cells that atlas_cells.cl's `entry` bounds over the
    global size `size`, given `where` it works (its box or its list of cells), as arrays of `shape`. `beside`:
    called while the device works."""
    ctx, queue = dev.context, dev.queue
    n = int(np.prod(shape))
    d_out = [cl.Buffer(ctx, cl.mem_flags.WRITE_ONLY, size=max(4, 4 * n)) for _ in range(3)]
    out = [np.empty(shape, np.float32) for _ in range(3)]
    if n:
        opts = ["-DLC_INTERP_II" if interpolation == "interblock" else "-DLC_INTERP_NB", f"-DLC_CPB={cpb}", *da.voxel]
        std = da.std
        if std is not None:
            opts.append("-DLC_DIST")
        else:
            std = cl.Buffer(ctx, cl.mem_flags.READ_ONLY, size=8)
        g4 = np.array([grid[2], grid[1], grid[0], block_size], np.int32)
        cl.Kernel(dev.program("atlas_cells.cl", opts).program, entry)(queue, size, None, da.atlas, std, da.index, g4,
                                                                     *where, *d_out)
        for h, d in zip(out, d_out):
            cl.enqueue_copy(queue, h, d, is_blocking=False)
    if beside is not None:
        beside()
    queue.finish()
    out[2] *= np.float32(std_unit)
    return out


def _device_cells(dev: Device, da: DeviceAtlas, grid: tuple[int, int, int], block_size: int, interpolation: str,
                  std_unit: float, blocks: tuple[slice, slice, slice] | None, cpb: int) -> AtlasCells:
    """atlas_cells computed on the device over the box of cells of `blocks` (None: all)."""
    lo = (0, 0, 0) if blocks is None else tuple(cpb * b.start for b in blocks)
    hi = tuple(cpb * g for g in grid) if blocks is None else tuple(cpb * b.stop for b in blocks)
    shape = tuple(h - a for a, h in zip(lo, hi))
    box = tuple(np.array([c[2], c[1], c[0], 0], np.int32) for c in (lo, hi))
    out = _bounds(dev, da, interpolation, cpb, "lc_atlas_cells", shape[::-1], grid, block_size, box, shape, std_unit)
    return AtlasCells(out[0], out[1], out[2], blocks, cpb)


def _updated_cells(dev: Device, da: DeviceAtlas, base: AtlasCells, grid: tuple[int, int, int], block_size: int,
                   interpolation: str, std_unit: float, cpb: int) -> AtlasCells:
    """atlas_cells of atlas `da` from `base`, the cells of the atlas it was built from: the cells the change of
    levels can reach computed on the device, the others copied. A dirty block (atlas.dirty_blocks) names the
    blocks through which its cells can change; a cell reads its own block and the blocks on its own sides only
    (`_reach`), so a level-0 block beside one that became or stopped being level 0 computes again only the cells
    along the face, edge or corner they share."""
    assert da.base_levels is not None and da.levels is not None  # set on an atlas built from another (base_key)
    dirty = dirty_blocks(da.base_levels.reshape(grid), da.levels.reshape(grid), interpolation).reshape(-1)
    out: list[np.ndarray] = []
    blocks = np.flatnonzero(dirty)
    b, c = np.nonzero((dirty[blocks, None] & _reach(cpb, interpolation)[None, :]) != 0)
    zyx = [np.asarray(bi, np.int64) * cpb + ci for bi, ci in zip(np.unravel_index(blocks[b], grid),
                                                                  np.unravel_index(c, (cpb,) * 3))]
    flat = np.ravel_multi_index(zyx, base.vmin.shape)
    lst = np.zeros((max(flat.size, 1), 4), np.int32)
    lst[:flat.size, 0], lst[:flat.size, 1], lst[:flat.size, 2] = zyx[2], zyx[1], zyx[0]
    d_list = cl.Buffer(dev.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=lst)
    size = (-(-flat.size // 64) * 64,)
    # the copies of the others (most of them first touches of new pages) while the device computes these
    got = _bounds(dev, da, interpolation, cpb, "lc_atlas_cells_at", size, grid, block_size,
                  (d_list, np.int32(flat.size)), (flat.size,), std_unit,
                  lambda: out.extend(a.copy() for a in (base.vmin, base.vmax, base.std)))
    for a, g in zip(out, got):
        a.reshape(-1)[flat] = g
    return AtlasCells(out[0], out[1], out[2], None, cpb, weakref.ref(base), flat)


def _reach(cpb: int, interpolation: str) -> np.ndarray:
    """Per cell of a block (C order, cpb³): dirty_blocks' bits of the blocks its bounds read (atlas_cells.cl), its
    own and those on its sides. Nearest block: a cell on a block's face reads the apron there, which holds the
    samples of the blocks across it (an inner cell, cpb 4, none along that axis). Interblock: a cell reads the
    neighbourhood of its half-block cell, the blocks on that half's side along each axis."""
    side = np.zeros(cpb, np.int64)
    if interpolation == "interblock":
        side[:] = np.where(np.arange(cpb) < cpb // 2, -1, 1)
    else:
        side[0], side[-1] = -1, 1
    out = np.zeros((cpb,) * 3, np.uint32)
    for c in np.ndindex(*out.shape):
        s = [int(side[i]) for i in c]
        for d in np.ndindex(*(2 if e else 1 for e in s)):  # per axis 0, or 0 and the side
            dz, dy, dx = (k * e for k, e in zip(d, s))
            out[c] |= np.uint32(1 << (9 * (dz + 1) + 3 * (dy + 1) + dx + 1))
    return out.reshape(-1)


def cells_and_octants(eng: Engine, da: DeviceAtlas, grid: tuple[int, int, int], block_size: int, interpolation: str,
                      std_unit: float = 1.0) -> tuple[AtlasCells, AtlasCells]:
    """(the half-block cells, their octants) of the whole atlas `da`: the octants from the device, the half-block
    cells reduced from them, each the union of its eight octants' bounds, which is what `atlas_cells` gives for
    them (the same brick samples reached: tests/test_atlas_cells.py) without a second kernel (the reduction on the
    host costs less than the kernel would), kept as `atlas_cells` keeps its."""
    octants = atlas_cells(eng, da, grid, block_size, interpolation, std_unit, cpb=4)
    key = None if da.key is None else ("cells", da.key, interpolation, None, 2)
    cells = eng.cells.get(key) if key is not None else None
    if cells is None:
        lo, hi, sd = (pair_reduce(a, f) for a, f in ((octants.vmin, np.fmin), (octants.vmax, np.fmax),
                                                       (octants.std, np.maximum)))
        cells = AtlasCells(lo, hi, sd)
        if key is not None:
            eng.cells.put(key, cells, 3 * lo.nbytes)
    return cells, octants

