"""What the multiresolution field sampled from an atlas can take in each of its half-block cells, or in their
octants (quarter-block cells): computed on the device where the atlas is (atlas_cells.cl), kept beside the atlas,
and, for an atlas built from the last one of its store (renderer/data/atlas.py: reuse), computed again only for the
blocks the change of levels can reach. Empty-space skipping on the atlas walks these cells and the adaptive walk
masks their octants (renderer/walk/info.py)."""
from __future__ import annotations

from dataclasses import dataclass

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


def _bounds(dev: Device, da: DeviceAtlas, interpolation: str, cpb: int, entry: str, size: tuple[int, int, int],
            grid: tuple[int, int, int], block_size: int, where: tuple, shape: tuple[int, ...],
            std_unit: float) -> list[np.ndarray]:
    """(min, max, largest deviation in the data's units) of the cells that atlas_cells.cl's `entry` bounds over the
    global size `size`, given `where` it works (its box or its list of blocks), as arrays of `shape`."""
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
            cl.enqueue_copy(queue, h, d)
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
    """atlas_cells of atlas `da` from `base`, the cells of the atlas it was built from: those of the blocks the
    change of levels can reach (atlas.dirty_blocks) computed on the device, the others copied."""
    assert da.base_levels is not None and da.levels is not None  # set on an atlas built from another (base_key)
    dirty = dirty_blocks(da.base_levels.reshape(grid), da.levels.reshape(grid), interpolation)
    out = [a.copy() for a in (base.vmin, base.vmax, base.std)]
    zyx = np.argwhere(dirty)
    if len(zyx):
        lst = np.zeros((len(zyx), 4), np.int32)
        lst[:, :3] = zyx[:, ::-1]
        d_list = cl.Buffer(dev.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=lst)
        got = _bounds(dev, da, interpolation, cpb, "lc_atlas_cells_of", (cpb, cpb, cpb * len(zyx)), grid, block_size,
                      (d_list,), (len(zyx), cpb, cpb, cpb), std_unit)
        for a, g in zip(out, got):  # (gz, c, gy, c, gx, c) -> (gz, gy, gx, c, c, c): a view, written through
            per_block = a.reshape(grid[0], cpb, grid[1], cpb, grid[2], cpb).transpose(0, 2, 4, 1, 3, 5)
            per_block[zyx[:, 0], zyx[:, 1], zyx[:, 2]] = g
    return AtlasCells(out[0], out[1], out[2], None, cpb)


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

