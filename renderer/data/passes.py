"""Renders in several passes: volume data larger than the device budget (docs/design.md, Limits:
`LODCAST_DEVICE_BUDGET_MB`) or than one device allocation.

When the data a render samples — level 0 at quality "full", the brick atlas of a selection otherwise (with its
standard deviations under distribution classification) — exceeds the limit, the block grid is cut into a grid of
regions of whole blocks, halving the longest extent until every region's data fits. A pass uploads one region's
data: at full resolution the region's voxels plus a rim of `ghost_voxels` (the trilinear stencil, the gradient's
central differences and a pre-integrated segment's front end reach that far past a sample), on the atlas the
bricks of the region's blocks and of `ring_blocks` blocks around them (interblock interpolation reads the
neighbouring blocks, nearest block a level-0 brick's apron, and their neighbours where a gradient or a segment end
reaches into them). Each pass takes
the samples of the blocks it owns and carries every ray's state to the next (lc_integrator.h), in a front-to-back
visibility order of the regions, the same for every ray of the view (`visibility_order`): the image is the
single-pass image exactly. Regions whose blocks all are empty space for this scene are not uploaded at all.

`MB` here is 10⁶ bytes. `device_bytes` in the report is the volume data one pass holds on the device (the largest
over the passes); a render in several passes does not keep its data in the device cache, and with a budget set the
device cache itself is bounded by it.
"""
from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Sequence

import numpy as np
import pyopencl as cl

from lodcast.malloc import release_free_memory
from lodcast.opencl import DeviceError
from lodcast.renderer.data import atlas as lod_atlas
from lodcast.renderer.data import atlas_cells
from lodcast.renderer.data.bricks import BrickStats
from lodcast.renderer.data.sampler import ess_cell, level0_buffer, level0_cells, upload_level0
from lodcast.renderer.data.volume import VolumeView
from lodcast.renderer.engine import Engine
from lodcast.renderer.scene.camera import Frame

__all__ = ["Region", "PassPlan", "volume_limit", "ghost_voxels", "ring_blocks", "split_grid",
           "visibility_order", "plan", "own_mask", "pass_levels", "pass_steps", "PassStats", "PassData", "volume_data",
           "fill_pass"]


def volume_limit(eng: Engine) -> tuple[int, str]:
    """(the most bytes of volume data one pass may hold: `eng`'s device budget, and at most one allocation; what
    sets it, for errors)."""
    budget, max_alloc = eng.settings.device_budget_bytes, eng.device.max_alloc_bytes
    if budget is None or budget > max_alloc:
        return max_alloc, "the device's largest allocation (CL_DEVICE_MAX_MEM_ALLOC_SIZE)"
    return budget, "LODCAST_DEVICE_BUDGET_MB"


def ghost_voxels(step_voxels: float) -> int:
    """How far past an owned sample (voxels of level 0) a pass's data must reach: half a trilinear stencil plus a
    gradient's central difference (2), plus one step for a pre-integrated segment's front end or an isosurface's
    previous sample."""
    return int(math.ceil(step_voxels)) + 2


def ring_blocks(step_voxels: float, block_size: int, interpolation: str) -> int:
    """Blocks around a region whose bricks a pass on the atlas loads: those within the ghost reach of its samples,
    and further: interblock interpolation by half a block (a position's neighbourhood spans the block centres
    around it); nearest block by one voxel (a level-0 brick's apron, which a pass fills from the bricks it loads,
    holds its neighbours' samples half a voxel past its faces)."""
    extra = block_size / 2 if interpolation == "interblock" else 1
    return int(math.ceil((ghost_voxels(step_voxels) + extra) / block_size))


@dataclass(frozen=True)
class Region:
    blocks: tuple[slice, slice, slice]  # the blocks this pass owns (z, y, x)
    data: tuple[slice, slice, slice]  # full: the voxels it uploads; atlas: the blocks whose bricks it loads
    nbytes: int  # its volume data on the device


@dataclass(frozen=True)
class PassPlan:
    regions: tuple[Region, ...]  # in visibility order, the empty ones left out
    split: tuple[int, int, int]  # regions per axis (z, y, x) of the grid
    limit: int  # bytes one pass may hold
    single_bytes: int  # what one pass over everything would have needed


def _cuts(n: int, parts: int) -> np.ndarray:
    return np.unique(np.round(np.linspace(0, n, parts + 1)).astype(np.int64))


def split_grid(grid: tuple[int, int, int], nbytes: Callable[[Sequence[int], Sequence[int]], int], limit: int,
               extent: Sequence[float], what: str = "LODCAST_DEVICE_BUDGET_MB") -> tuple[list[np.ndarray], int]:
    """Cuts per axis (block indices, 0 ... grid) of the coarsest grid of regions whose every region's data,
    `nbytes(lo, hi)` for block ranges lo..hi (z, y, x), fits `limit`: the axis of largest region extent
    (`extent`: a block's size per axis) is halved until it does. When single blocks do not fit, raises ValueError
    if the limit is `what` = LODCAST_DEVICE_BUDGET_MB (a setting to change), else DeviceError."""
    parts = [1, 1, 1]
    while True:
        cuts = [_cuts(g, p) for g, p in zip(grid, parts)]
        worst = 0
        for z0, z1 in zip(cuts[0][:-1], cuts[0][1:]):
            for y0, y1 in zip(cuts[1][:-1], cuts[1][1:]):
                for x0, x1 in zip(cuts[2][:-1], cuts[2][1:]):
                    worst = max(worst, nbytes((z0, y0, x0), (z1, y1, x1)))
        if worst <= limit:
            return cuts, worst
        span = [(grid[a] / parts[a]) * extent[a] if parts[a] < grid[a] else -1.0 for a in range(3)]
        a = int(np.argmax(span))
        if span[a] < 0:
            msg = f"{what}: {limit / 1e6:.3g} MB cannot hold even one block's data ({worst / 1e6:.3g} MB needed)"
            raise ValueError(msg) if what == "LODCAST_DEVICE_BUDGET_MB" else DeviceError(msg)
        parts[a] = min(grid[a], parts[a] * 2)


def visibility_order(cuts: list[np.ndarray], fr: Frame, vol: VolumeView) -> np.ndarray:
    """A key per region (C order of the region grid) such that along every ray of the view the regions it
    crosses have strictly increasing keys: perspective, the Manhattan distance in region indices from the
    eye's (virtual, outside the grid: -1 or n) region — a ray from the eye moves every index away from the eye's;
    orthographic, the sum of the indices signed by the view direction."""
    idx = np.meshgrid(*[np.arange(len(c) - 1) for c in cuts], indexing="ij")
    B = float(vol.block_size)
    f = np.asarray(fr.f, np.float64)[::-1]  # z, y, x
    if fr.orthographic:
        return np.asarray(sum(np.sign(f[a]) * idx[a] for a in range(3)))
    q = (np.asarray(fr.eye, np.float64) - np.asarray(vol.origin[::-1], np.float64)) / np.asarray(vol.spacing[::-1])
    p = (q[::-1] + 0.5) / B  # block coordinates z, y, x
    eye = [int(np.searchsorted(c, p[a], side="right")) - 1 for a, c in enumerate(cuts)]
    eye = [-1 if p[a] < cuts[a][0] else (len(cuts[a]) - 1 if p[a] >= cuts[a][-1] else e) for a, e in enumerate(eye)]
    return np.asarray(sum(np.abs(idx[a] - eye[a]) for a in range(3)))


def _box_sum(per_block: np.ndarray) -> Callable[[Sequence[int], Sequence[int]], int]:
    """Sums of `per_block` over block boxes in O(1) each (a 3D prefix sum)."""
    c = np.zeros(tuple(s + 1 for s in per_block.shape), np.int64)
    c[1:, 1:, 1:] = per_block.astype(np.int64).cumsum(0).cumsum(1).cumsum(2)

    def total(lo: Sequence[int], hi: Sequence[int]) -> int:
        (z0, y0, x0), (z1, y1, x1) = lo, hi
        return int(c[z1, y1, x1] - c[z0, y1, x1] - c[z1, y0, x1] - c[z1, y1, x0]
                   + c[z0, y0, x1] + c[z0, y1, x0] + c[z1, y0, x0] - c[z0, y0, x0])
    return total


def plan(vol: VolumeView, fr: Frame, step_voxels: float, levels: np.ndarray | None, with_std: bool,
         unsampled: Callable[[], np.ndarray], limit: int, interpolation: str = "interblock",
         what: str = "LODCAST_DEVICE_BUDGET_MB") -> PassPlan | None:
    """The passes of a render, or None when its data fits `limit` in one. `levels`: the atlas selection (None: level
    0, full resolution); `unsampled()`: the blocks the kernel never samples in this scene (empty-space skipping, or
    adaptive cells all skipped): regions of only those are left out (asked only when there are passes: it is not
    free)."""
    G, B, shape = vol.grid, int(vol.block_size), vol.shape
    size = vol.voxel_dtype.itemsize  # bytes of a voxel on the device
    if levels is None:
        g = ghost_voxels(step_voxels)

        def data_box(lo: Sequence[int], hi: Sequence[int]) -> tuple[slice, slice, slice]:
            z, y, x = (slice(max(0, lo[a] * B - g), min(shape[a], hi[a] * B + g)) for a in range(3))
            return z, y, x

        def nbytes(lo: Sequence[int], hi: Sequence[int]) -> int:
            return size * math.prod(s.stop - s.start for s in data_box(lo, hi))

        single = size * vol.n_voxels
    else:
        lv = np.asarray(levels)
        sig = lod_atlas.deviation_bytes(vol.voxel_dtype) if with_std else 0  # deviations: coarse bricks only
        coarse = sig if sig == 4 else size + sig  # 4: the coarse values live beside their deviations alone
        # the total from the blocks per level first: the per-block sizes and their prefix sums below cost a good
        # part of a large volume's frame, and most renders fit in one pass (a comparison per level on the small
        # type: widening the grid for a bincount cost more than the rest of the plan)
        single = sum(int(np.count_nonzero(lv == k)) * int(lod_atlas.brick_elements(np.int64(k), B))
                     * (coarse if k >= 1 else size) for k in range(int(lv.max(initial=-1)) + 1))
        if single <= limit:
            return None
        lv = lv.astype(np.int64)
        per = lod_atlas.brick_elements(lv, B) * np.where(lv >= 1, coarse, size)
        total, r = _box_sum(per), ring_blocks(step_voxels, B, interpolation)

        def data_box(lo: Sequence[int], hi: Sequence[int]) -> tuple[slice, slice, slice]:
            z, y, x = (slice(max(0, lo[a] - r), min(G[a], hi[a] + r)) for a in range(3))
            return z, y, x

        def nbytes(lo: Sequence[int], hi: Sequence[int]) -> int:
            d = data_box(lo, hi)
            return total(tuple(s.start for s in d), tuple(s.stop for s in d))

    if single <= limit:
        return None
    extent = tuple(B * float(s) for s in vol.spacing)
    cuts, _ = split_grid(G, nbytes, limit, extent, what)
    not_sampled = unsampled()
    key = visibility_order(cuts, fr, vol).ravel()
    regions = []
    boxes = [(z0, y0, x0, z1, y1, x1) for z0, z1 in zip(cuts[0][:-1], cuts[0][1:])
             for y0, y1 in zip(cuts[1][:-1], cuts[1][1:]) for x0, x1 in zip(cuts[2][:-1], cuts[2][1:])]
    for i in np.argsort(key, kind="stable"):
        z0, y0, x0, z1, y1, x1 = (int(v) for v in boxes[i])
        own = (slice(z0, z1), slice(y0, y1), slice(x0, x1))
        if not_sampled[own].all():
            continue  # nothing here is sampled: no pass
        regions.append(Region(own, data_box((z0, y0, x0), (z1, y1, x1)), nbytes((z0, y0, x0), (z1, y1, x1))))
    return PassPlan(tuple(regions), tuple(len(c) - 1 for c in cuts), limit, single)  # type: ignore[arg-type]


def own_mask(grid: tuple[int, int, int], region: Region) -> np.ndarray:
    """One byte per block (C order): 1 where `region` owns the block."""
    m = np.zeros(grid, np.uint8)
    m[region.blocks] = 1
    return m


def pass_levels(levels: np.ndarray, region: Region) -> np.ndarray:
    """The part of a selection a pass on the atlas loads: its region's blocks and their ring, -1 elsewhere."""
    out = np.full(np.asarray(levels).shape, -1, np.int8)
    out[region.data] = np.asarray(levels, np.int8)[region.data]
    return out


def pass_steps(steps: np.ndarray, own: np.ndarray) -> np.ndarray:
    """Adaptive sampling's step levels (half-block cells) with every cell outside the pass's blocks skipped."""
    return lod_atlas.skipped(steps, lod_atlas.half_cells(own) == 0)


@dataclass
class PassStats:
    """What the passes of one render uploaded, for its report."""

    planned: int = 1
    passes: int = 0
    read: int = 0  # blocks (full) or bricks (atlas) read from the store
    cached: int = 0  # found on the device (one pass) or in the brick cache
    upload_ms: float = 0.0
    device_bytes: int = 0  # the most volume data on the device at once


@dataclass(frozen=True)
class PassData:
    region: Region | None  # None: the one pass of a render that fits
    vol: Any  # cl.Buffer: level 0 (or the pass's sub-volume), or the atlas
    index: Any  # the atlas's index map (full: a placeholder)
    std: Any  # the standard deviations beside the atlas (or a placeholder)
    steps: np.ndarray  # adaptive sampling's step levels (or a placeholder)
    own: np.ndarray  # LC_PASSES: the blocks the pass owns (or a placeholder)
    cell_min: np.ndarray | None = None  # full resolution: the border-inclusive extrema of the cells of
    cell_max: np.ndarray | None = None  # empty-space skipping (of the pass's own blocks; NaN elsewhere)
    cell: int = 0  # their edge in voxels
    cells: "atlas_cells.AtlasCells | None" = None  # the atlas: its half-block cells (with empty-space skipping)
    octants: "atlas_cells.AtlasCells | None" = None  # and their octants (the adaptive walk's masks: config.octants)
    owner: Any = None  # what holds `vol`'s buffers (an atlas): held until the pass's kernel has finished


def _empty_region(levels: np.ndarray | None) -> Region:
    """A pass that owns nothing: the image of a render whose every region is empty space (only its state
    initialisation and background run)."""
    none = (slice(0, 0),) * 3
    return Region(none, none if levels is not None else (slice(0, 1),) * 3, 4)


def volume_data(pr: Any, stats: PassStats) -> Iterator[PassData]:
    """The volume data of each pass of `pr` (renderer/frame/render.py's Prepared), uploaded when its pass comes and
    dropped after it, counting into `stats`."""
    eng: Engine = pr.engine
    ctx = eng.device.context
    mf = cl.mem_flags
    cfg, vol, lod = pr.config, pr.volume, pr.lod
    steps = lod.step_levels if lod is not None and lod.step_levels is not None else np.zeros(8, np.int8)
    placeholder = cl.Buffer(ctx, mf.READ_ONLY, size=8)
    if pr.passes is None:
        stats.passes = 1
        if lod is None:
            dv, hit = upload_level0(eng, vol)
            stats.read, stats.cached = (0, vol.n_blocks) if hit else (vol.n_blocks, 0)
            stats.upload_ms, stats.device_bytes = (0.0 if hit else dv.upload_ms), dv.nbytes
            yield PassData(None, dv.buffer, placeholder, placeholder, steps, np.ones(1, np.uint8), dv.cell_min,
                           dv.cell_max, dv.cell)
        else:
            da = lod_atlas.device_atlas(eng, vol, lod.levels, with_std=cfg.distribution)
            stats.read, stats.cached, stats.upload_ms, stats.device_bytes = da.read, da.cached, da.upload_ms, da.nbytes
            cells = _cells(pr, da)
            yield PassData(None, da.atlas, da.index, da.std if cfg.distribution else placeholder, steps,
                           np.ones(1, np.uint8), cells=cells,
                           octants=_cells_and_octants(pr, da)[1] if cfg.octants and cells is not None else None,
                           owner=da)
        return
    # a render beyond the budget has the device to itself, and the host what was kept beside the atlases it drops
    # (their cells and walks, which grow with the selection: on a large volume, a good part of its size)
    eng.clear_passes()
    release_free_memory()  # (freed, they would stay resident under the first pass's data)
    regions = pr.passes.regions or (_empty_region(None if lod is None else lod.levels),)
    stats.planned = len(regions)
    slices = lod_atlas.slice_max(lod.levels) if lod is not None else None
    for reg in regions:
        own = own_mask(vol.grid, reg)
        t = time.perf_counter()
        with contextlib.ExitStack() as held:
            if lod is None:
                shape = tuple(r.stop - r.start for r in reg.data)
                nbytes = math.prod(shape) * vol.voxel_dtype.itemsize
                if not vol.has_levels or vol.key is None:
                    # a CPU device's buffer is host memory: the brick pool gives way to it while the pass lasts (a
                    # store's pass voxels are in the pool already, and are the buffer on such a device)
                    held.enter_context(eng.holding(nbytes))
                    eng.bricks.trim()
                data, got = _level0_pass(eng, vol, reg, shape, own, steps, placeholder)
                stats.read += got.read
                stats.cached += got.cached
                stats.upload_ms += (time.perf_counter() - t) * 1e3
            else:
                da = lod_atlas.device_atlas(eng, vol, pass_levels(lod.levels, reg), with_std=cfg.distribution,
                                            slices=slices, keep=False)
                stats.read += da.read
                stats.cached += da.cached
                stats.upload_ms += da.upload_ms
                nbytes = da.nbytes
                data = PassData(reg, da.atlas, da.index, da.std if cfg.distribution else placeholder,
                                pass_steps(steps, own) if cfg.adaptive else steps, own,
                                cells=_cells(pr, da, reg.blocks), owner=da)
            stats.passes += 1
            stats.device_bytes = max(stats.device_bytes, nbytes)
            yield data
            del data
        release_free_memory()  # the pass's bricks or voxels, freed by many threads, leave the process


def _level0_pass(eng: Engine, vol: Any, reg: Region, shape: tuple[int, int, int], own: np.ndarray,
                 steps: np.ndarray, placeholder: cl.Buffer) -> tuple[PassData, BrickStats]:
    """A full-resolution pass's data: its voxels on the device, and the value ranges of its cells for empty-space
    skipping; with the counts of bricks read and found. A store's pass voxels are kept whole in the engine's brick
    pool (`_pass_voxels`): a second frame, or a pass over the same region, reads nothing and transposes nothing.
    A volume without a store's bricks (an array) is read straight into the buffer."""
    dev = eng.device
    st = BrickStats()
    if not vol.has_levels or vol.key is None:
        buf = level0_buffer(dev, vol, reg.data)
        st.read = int(own.sum())
    else:
        buf = dev.read_only(_pass_voxels(eng, vol, reg.data, shape, st))  # (a CPU device's: the pooled voxels)
    cmin, cmax = level0_cells(dev, buf, shape, tuple(s.start for s in reg.data), reg.blocks, vol)
    return PassData(reg, buf, placeholder, placeholder, steps, own, cmin, cmax, ess_cell(vol.shape, vol.block_size)), st


def _pass_voxels(eng: Engine, vol: Any, box: tuple[slice, slice, slice], shape: tuple[int, int, int],
                 st: BrickStats) -> np.ndarray:
    """Level 0's voxels `box` (z-y-x slices) of a store, kept whole in the engine's brick pool (renderer/pool.py
    says why): found there, else made from the pool's level-0 bricks where it holds all of them, else read from
    the store straight into place (not as bricks: the pool would hold the region twice)."""
    B = int(vol.block_size)
    lo = [s.start // B for s in box]
    hi = [-(-s.stop // B) for s in box]
    n = math.prod(h - low for h, low in zip(hi, lo))
    fam = ("voxels", vol.key, tuple((s.start, s.stop) for s in box))
    got = eng.bricks.held(fam)
    if got is not None:
        st.cached += n
        return got
    out = np.empty(shape, vol.voxel_dtype)
    blocks = np.asarray(np.ravel_multi_index(tuple(np.mgrid[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].reshape(3, -1)), vol.grid))
    if (eng.bricks.find(("bricks", vol.key, 0), vol.n_blocks, blocks) >= 0).all():
        _level0_voxels(eng, vol, box, out, st)
    else:
        vol.read_level0_region(box, out)
        st.read += n
    eng.bricks.hold(fam, out)
    return out


def _level0_voxels(eng: Engine, vol: Any, box: tuple[slice, slice, slice], out: np.ndarray, st: BrickStats) -> None:
    """Level 0's voxels `box` (z-y-x slices) into `out` from the level-0 bricks of the brick pool, one row of blocks
    across z at a time, each row's bricks transposed into voxels; a row whose bricks another thread evicted
    meanwhile is read from the store."""
    B = int(vol.block_size)
    lo = [s.start // B for s in box]
    hi = [-(-s.stop // B) for s in box]
    ny, nx = hi[1] - lo[1], hi[2] - lo[2]
    row = np.empty((B, ny * B, nx * B), vol.voxel_dtype)
    ys, xs = (slice(box[a].start - lo[a] * B, box[a].stop - lo[a] * B) for a in (1, 2))
    yx = np.mgrid[lo[1]:hi[1], lo[2]:hi[2]].reshape(2, -1)
    fam = ("bricks", vol.key, 0)
    for bz in range(lo[0], hi[0]):
        z0, z1 = max(box[0].start, bz * B), min(box[0].stop, (bz + 1) * B)
        dst = out[z0 - box[0].start:z1 - box[0].start]
        blocks = np.ravel_multi_index((np.full(yx.shape[1], bz), yx[0], yx[1]), vol.grid)
        held, bricks = eng.bricks.get(fam, vol.n_blocks, blocks)
        if bricks is None or not held.all():
            vol.read_level0_region((slice(z0, z1), box[1], box[2]), dst)
            st.read += blocks.size
            continue
        st.cached += blocks.size
        row.reshape(B, ny, B, nx, B)[...] = bricks.reshape(ny, nx, B, B, B).transpose(2, 0, 3, 1, 4)
        dst[...] = row[z0 - bz * B:z1 - bz * B, ys, xs]


def _cells(pr: Any, da: "lod_atlas.DeviceAtlas",
           blocks: tuple[slice, slice, slice] | None = None) -> "atlas_cells.AtlasCells | None":
    """The atlas's half-block cells, where the walk can skip on them (renderer/walk/info.py); a pass needs
    those of the blocks it owns (`blocks`) only."""
    cfg = pr.config
    if not cfg.ess or pr.volume.block_size % 2:  # (average and iso have no walk: cfg.ess is off for them)
        return None
    if cfg.octants and blocks is None:  # reduced from the octants the walk needs as well
        return _cells_and_octants(pr, da)[0]
    return atlas_cells.atlas_cells(pr.engine, da, pr.volume.grid, int(pr.volume.block_size), cfg.interpolation,
                                   pr.volume.std_unit if cfg.distribution else 1.0, blocks)


def _cells_and_octants(pr: Any,
                       da: "lod_atlas.DeviceAtlas") -> tuple["atlas_cells.AtlasCells", "atlas_cells.AtlasCells"]:
    """The whole atlas's half-block cells and their octants (config.octants), kept beside the atlas."""
    cfg = pr.config
    return atlas_cells.cells_and_octants(pr.engine, da, pr.volume.grid, int(pr.volume.block_size),
                                         cfg.interpolation, pr.volume.std_unit if cfg.distribution else 1.0)


def fill_pass(p: np.ndarray, region: Region | None, pr: Any, first: bool) -> None:
    """The pass fields of the parameter block: the world box of the samples the pass owns (one voxel wider, for
    rounding), its sub-volume's offset and extent (full resolution), whether it is the first."""
    if region is None:
        return
    vol = pr.volume
    B = int(vol.block_size)
    sp, org = np.asarray(vol.spacing[::-1], np.float64), np.asarray(vol.origin[::-1], np.float64)
    lo = np.array([region.blocks[a].start for a in (2, 1, 0)], np.float64) * B - 1.5
    hi = np.array([region.blocks[a].stop for a in (2, 1, 0)], np.float64) * B + 0.5
    q = p[0]
    q["pass_lo"] = (*(org + lo * sp), 0.0)
    q["pass_hi"] = (*(org + hi * sp), 0.0)
    if pr.lod is None:
        q["pass_off"] = (region.data[2].start, region.data[1].start, region.data[0].start, 0)
        q["pass_dims"] = tuple(max(1, region.data[a].stop - region.data[a].start) for a in (2, 1, 0)) + (0,)
    q["pass_first"] = 1 if first else 0
