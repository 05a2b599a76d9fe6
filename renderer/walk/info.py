"""The walks: which cells a ray may skip, and how far it may leap (Open VKL's interval iterator, where
renderer/data/sampler.py and renderer/data/atlas.py are its sampler). Full resolution walks cells of 4³ or 8³ voxels over
their border-inclusive value ranges; the atlas walks half-block cells over the bounds of the field sampled in them
(atlas_cells.cl), and the adaptive walk reads the same cells' step levels, leaps and octant masks. What a walk
needs of a scene is computed on the host per volume or selection, TF and clip, and kept (renders that repeat a
scene, or change only what the walk does not depend on, reuse it)."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from lodcast.renderer.data import atlas as lod_atlas
from lodcast.renderer.data.volume import VolumeView
from lodcast.renderer.kernel.config import EXTREMUM_MODES, KernelConfig
from lodcast.renderer.lod import dual
from lodcast.renderer.lod.classification import DistTable
from lodcast.renderer.scene import clip as clipping
from lodcast.renderer.scene.transfer_function import Lut
from lodcast.renderer.walk.leap import Leaps, cell_leaps, children, coarsen_ranges, step_leaps
from lodcast.store.layout import cell_edge

if TYPE_CHECKING:  # pragma: no cover
    from lodcast.renderer.data import atlas_cells
    from lodcast.renderer.data import passes as multipass
    from lodcast.renderer.frame.plan import Prepared

__all__ = ["FINE_STEP", "adaptive_walk", "atlas_cell_info", "block_info", "octant_masks", "range_info",
           "walk_info", "walk_steps"]

def block_info(vol: VolumeView, lut: Lut, mode: str, lut2: Lut | None = None) -> tuple[np.ndarray, int]:
    """(per-block float32 array in kernel order (gz, gy, gx), number of empty blocks): `range_info` of the blocks'
    border-inclusive ranges."""
    return range_info(vol.min_border, vol.max_border, lut, mode, lut2)


def range_info(vmin: np.ndarray, vmax: np.ndarray, lut: Lut, mode: str,
               lut2: Lut | None = None) -> tuple[np.ndarray, int]:
    """What the block walk needs of cells with border-inclusive value ranges [vmin, vmax] (NaN: no value), and the
    number of empty cells. Composite: 1 where the TF is non-zero somewhere on the range (with a second TF's
    `lut2`: bit 1 for tf, bit 2 for tf2, renderer/lod/dual.py); MIP: the maximum; MinIP: minus the minimum (the kernel
    tracks the maximum of -v); average and iso (no block walk): zeros."""
    if mode in EXTREMUM_MODES:
        ext = vmax if mode == "mip" else -np.asarray(vmin, np.float64)
        mx = np.where(np.isfinite(ext), ext, -np.inf)
        return np.ascontiguousarray(mx, dtype=np.float32), 0
    if mode != "composite":
        return np.zeros(np.shape(vmin), np.float32), 0
    vis = lut.visible(vmin, vmax)
    if lut2 is not None:
        vis = dual.visibility_bits(vis, lut2.visible(vmin, vmax))
    return np.ascontiguousarray(vis, dtype=np.float32), int(vis.size - np.count_nonzero(vis))


_CELL_CHUNK = 1 << 20


def walk_info(pr: "Prepared", data: "multipass.PassData") -> tuple[np.ndarray, tuple[int, int, int, int],
                                                                   Leaps | None]:
    """(the block walk's info, its grid (x, y, z, cell edge), its leaps): at full resolution over the cells of
    empty-space skipping (`_level0_walk`), with the clip region's cells outside empty; on the atlas over its
    half-block cells (data.cells): the selection's block info where the cell's field can show something
    (`atlas_cell_info`), else the block info. With leaps (config.leap) the empty cells' leaps (renderer/walk/leap.py:
    cell_leaps, their planes computed as views need them), else None."""
    leap = pr.config.leap and not pr.config.adaptive  # (the adaptive walk's leaps: step_leaps)
    key = _walk_key(pr, data, leap)
    anchor = data.cell_min if data.cells is None else data.cells
    if key is not None:
        hit = pr.engine.walks.get(key)
        if hit is not None and hit[0] is anchor:  # (the reference held keeps the id from being reused)
            return hit[1], hit[2], hit[3]
    vol = pr.volume
    B = int(vol.block_size)
    if data.cells is not None:
        last = None if key is None else (vol.key, *key[3:])  # (what the cells' info depends on, less the cells)
        info, C = atlas_cell_info(pr, data.cells, last), B // 2
    elif data.cell_min is None or not pr.config.ess:
        info, C = pr.block_info, B
    else:
        info, C = _level0_walk(pr, data)
    g = info.shape
    info = np.ascontiguousarray(info, dtype=np.float32)
    out = info, (g[2], g[1], g[0], C), (cell_leaps(info) if leap else None)
    if key is not None:
        pr.engine.walks.put(key, (anchor, *out), info.nbytes + (0 if out[2] is None else out[2].nbytes))
    return out


def _walk_key(pr: "Prepared", data: "multipass.PassData", leap: bool) -> tuple | None:
    """What the walk info depends on, besides the cells' ranges, by identity: full resolution's (data.cell_min,
    which the device cache keeps per volume) or the atlas's half-block cells (data.cells, kept per selection beside
    the atlas); then the TFs' opacities (only where they are zero matters, but the tables are small), the mode, the
    clip planes, the leaps and which cells the step walks (FINE_STEP); on the atlas also the selection's block info,
    the distribution tables' visible spans and whether the store keeps its level-0 cell ranges (atlas_cell_info
    costs too much to run on every render of the same scene).
    Passes and volumes the device cache does not keep (arrays without a key): None (computed per render)."""
    if data.region is not None or not pr.config.ess or pr.volume.key is None:
        return None
    if data.cells is None and data.cell_min is None:
        return None
    digest = pr.engine.digest
    tfs = tuple((t.lut.lo, t.lut.scale, t.lut.n, digest(t.lut.opacity > 0),
                 None if t.dist is None else (t.dist.lo, t.dist.scale, t.dist.rows, t.dist.std_max,
                                              digest(t.dist.kernel_table[-1])))
                for t in [pr] + ([] if pr.second is None else [pr.second]))
    clip = None if pr.scene.clip is None else pr.scene.clip.model_dump_json()
    common = (pr.scene.mode, tfs, clip, leap, pr.scene.sampling.step > FINE_STEP)
    if data.cells is not None:
        return ("atlas", id(data.cells), digest(pr.block_info), pr.scene.sampling.empty_space_skipping,
                pr.volume.has_cell_ranges, *common)
    return id(data.cell_min), data.cell, *common


#: full resolution walks its finest cells (4³: sampler.ess_cell) while the step is at most this many voxels, and cells
#: of 8³ (their ranges from the finer ones') beyond: a long step takes few samples per fine cell, and each costs its
#: walk step (the finer cells won in kernel time up to a step of a voxel, about even at 1.5, lost at 2)
FINE_STEP = 1.0


def _level0_walk(pr: "Prepared", data: "multipass.PassData") -> tuple[np.ndarray, int]:
    """Full resolution's walk info over its cells (data.cell voxels, or twice that for steps beyond FINE_STEP) and
    their edge. Fine cells are classified only where their parent cell of twice the edge can show something (a
    child's range lies inside its parent's)."""
    vol, mode = pr.volume, pr.scene.mode
    B, C = int(vol.block_size), data.cell
    lut2 = None if pr.second is None else pr.second.lut
    empty = -np.inf if mode in EXTREMUM_MODES else 0.0
    cmin, cmax = data.cell_min, data.cell_max
    assert cmin is not None and cmax is not None  # walk_info asks only with the cells' ranges (set together)
    coarse_walk = pr.scene.sampling.step > FINE_STEP  # the parents are the walk's cells
    # cells of twice the edge still lie inside a block, and the walk is over them or classifies under them
    parents = (2 * C <= cell_edge(B) and B % (2 * C) == 0
               and (coarse_walk or (data.region is None and mode not in EXTREMUM_MODES)))
    if parents:
        hit = pr.engine.parents.get(id(cmin))
        if hit is None or hit[0] is not cmin:  # (the reference held keeps the id from being reused)
            hit = (cmin, *coarsen_ranges(cmin, cmax))
            pr.engine.parents.put(id(cmin), hit, hit[1].nbytes * 2)
        if coarse_walk:
            cmin, cmax, C, parents = hit[1], hit[2], 2 * C, False
    if data.region is not None:  # a pass: its own blocks' cells hold values, the rest NaN (every pass over all the
        # cells of a large volume took a good part of its full-resolution render)
        k = B // C
        box = tuple(slice(b.start * k, min(n, b.stop * k)) for b, n in zip(data.region.blocks, cmin.shape))
        info = np.full(cmin.shape, empty, np.float32)
        info[box], _ = range_info(cmin[box], cmax[box], pr.lut, mode, lut2)
        return _clipped(pr, info, C), C
    if not parents or mode in EXTREMUM_MODES:
        info, _ = range_info(cmin, cmax, pr.lut, mode, lut2)
        return _clipped(pr, info, C), C
    parent, _ = range_info(hit[1], hit[2], pr.lut, mode, lut2)
    parent = _clipped(pr, parent, 2 * C)
    info = np.zeros(cmin.shape, np.float32)  # composite: a child can show something only where its parent can
    seen = children(parent != 0.0, cmin.shape)
    info[seen], _ = range_info(cmin[seen], cmax[seen], pr.lut, mode, lut2)
    return _clipped(pr, info, C), C


def _clipped(pr: "Prepared", info: np.ndarray, C: int) -> np.ndarray:
    """The walk info with the cells (edge C) that lie outside the clip region empty."""
    vol = pr.volume
    keep = clipping.block_mask(info.shape, vol.shape, vol.spacing, vol.origin, C, pr.scene.clip)
    if keep is None:
        return info
    return np.where(keep, info, -np.inf if pr.scene.mode in EXTREMUM_MODES else 0.0).astype(np.float32)


def atlas_cell_info(pr: "Prepared", cells: "atlas_cells.AtlasCells", last: tuple | None = None) -> np.ndarray:
    """The walk's info over the atlas's half-block cells: the selection's block info (pr.block_info) where the
    field sampled in the cell can be visible, empty (0; MIP: its largest value, MinIP: minus its smallest) where
    it cannot: every value there is invisible under the point classification and, with distribution
    classification, under the TF's distribution table for deviations up to the cell's largest. Where the block
    info already says empty it stays so, so the image is the block walk's: only samples that add nothing are
    left out (tests/test_atlas_cells.py). Cells of a pass's blocks only (cells.blocks): the rest are empty, the
    pass samples nothing there. `last`: the key of what this depends on besides the cells' bounds, the block
    info and the levels (`_walk_key`'s): the newest info of that key is kept (`eng.cell_infos`), and the next one
    computed again only in the cells whose inputs changed (`_updated_cell_info`)."""
    mode = pr.scene.mode
    if cells.blocks is None and last is not None and mode == "composite":
        return _updated_cell_info(pr, cells, last)
    part = _cell_info(pr, cells, pr.block_info if cells.blocks is None else pr.block_info[cells.blocks])
    if cells.blocks is None:
        return part
    out = np.full(tuple(2 * g for g in pr.block_info.shape), -np.inf if mode in EXTREMUM_MODES else 0.0, np.float32)
    out[cells.at] = part
    return out


def _coarse_blocks(pr: "Prepared") -> np.ndarray | None:
    """The blocks (grid-shaped bool) whose coarse cells the level-0 ranges may leave out (`_composite_cells`), or
    None where the store keeps no level-0 cell ranges."""
    if pr.lod is None or pr.volume.half_cell_ranges(pr.engine.tables.half_cells) is None:
        return None
    return np.asarray(pr.lod.levels >= 1)


def _cell_info(pr: "Prepared", cells: "atlas_cells.AtlasCells", block_info: np.ndarray) -> np.ndarray:
    up = lod_atlas.half_cells(block_info)
    mode = pr.scene.mode
    if mode in EXTREMUM_MODES:
        ext = cells.vmax if mode == "mip" else -cells.vmin.astype(np.float64)
        ext = np.where(np.isfinite(ext), ext, -np.inf)
        return np.ascontiguousarray(np.minimum(up, ext), dtype=np.float32)
    coarse_blocks = _coarse_blocks(pr)
    coarse = lo0 = hi0 = None
    if coarse_blocks is not None:
        level0 = pr.volume.half_cell_ranges(pr.engine.tables.half_cells)
        assert level0 is not None  # (_coarse_blocks: the store keeps them)
        coarse = lod_atlas.half_cells(coarse_blocks)[cells.at].reshape(-1)
        lo0, hi0 = (a[cells.at].reshape(-1) for a in level0)
    return _composite_cells(pr, up.reshape(-1), cells.vmin.reshape(-1), cells.vmax.reshape(-1),
                            cells.std.reshape(-1), coarse, lo0, hi0).reshape(up.shape)


def _composite_cells(pr: "Prepared", up: np.ndarray, lo: np.ndarray, hi: np.ndarray, sd: np.ndarray,
                     coarse: np.ndarray | None, lo0: np.ndarray | None, hi0: np.ndarray | None) -> np.ndarray:
    """The composite walk info of cells given as flat arrays (each cell on its own: the info of any subset of
    cells is the same as theirs among all): `up` their blocks' info, [lo, hi] and `sd` their field's bounds,
    `coarse` whether their block is coarse and [lo0, hi0] their level-0 ranges (None: the store keeps none)."""
    # A coarse cell (its block at level >= 1) whose level-0 voxels, one-voxel border included, the TF shows nothing
    # of is not sampled (the store's cell ranges), however its coarse field classifies: full resolution skips that
    # cell too, and what the coarse field shows there is its blur of the neighbouring cells or a Gaussian's tail
    # (the haze that bimodal voxels, air against skin, give a bone TF). It leaves out samples and lowers the image
    # error (benchmarks/bench_lod_sweep.py). Without the border it saved more but clipped silhouettes that end at a
    # cell's face, which full resolution shows a voxel further.
    # Without empty-space skipping (the walk then runs for this alone, prepare()) every other cell is sampled.
    skip_empty = pr.scene.sampling.empty_space_skipping
    if not skip_empty:
        up = np.full(up.shape, 1.0 if pr.second is None else 3.0, np.float32)  # (tf2: both TFs' bits)

    def seen(lut: Lut, dist: DistTable | None) -> np.ndarray:
        # in pieces: the tests make float64 temporaries, ~60 bytes per cell (8M cells of a 1024 x 2048² volume)
        out = np.empty(lo.shape, bool)
        for i in range(0, out.size, _CELL_CHUNK):
            part = slice(i, i + _CELL_CHUNK)
            out[part] = _shows(lut, dist, lo[part], hi[part], sd[part]) if skip_empty else True
            if coarse is not None:  # only where a coarse cell is still visible (8M cells of the 8 GiB volume)
                assert lo0 is not None and hi0 is not None
                sub = out[part]
                idx = np.flatnonzero(sub & coarse[part])
                sub[idx] = lut.visible(lo0[part][idx], hi0[part][idx])
        return out

    vis = seen(pr.lut, pr.dist)
    if pr.second is not None:
        vis = dual.visibility_bits(vis, seen(pr.second.lut, pr.second.dist))
        return np.ascontiguousarray(np.bitwise_and(up.astype(np.int64), vis.astype(np.int64)), dtype=np.float32)
    return np.ascontiguousarray(np.where(vis, up, np.float32(0.0)), dtype=np.float32)


def _bits_differ(a: np.ndarray | None, b: np.ndarray | None) -> np.ndarray | bool:
    """Where two arrays of the same shape differ bit for bit (NaN equal to the same NaN); True where either is
    None and the other not."""
    if a is None or b is None:
        return (a is None) != (b is None)
    if a is b:
        return False
    return a.view(np.dtype(f"u{a.dtype.itemsize}")) != b.view(np.dtype(f"u{b.dtype.itemsize}"))


def _updated_cell_info(pr: "Prepared", cells: "atlas_cells.AtlasCells", last: tuple) -> np.ndarray:
    """atlas_cell_info of the whole composite atlas, from the newest one of `last` (the same TFs, mode, clip and
    store): a new view's selection changes the level of a few thousand blocks, and so the bounds of their cells
    and their neighbours', the block info near them and which blocks are coarse, while classifying every cell
    again was a good part of a new view's host time on a large volume. Cells whose block's info or coarseness or
    whose own bounds changed (bit for bit) are classified again, the others keep their info: each cell's info is a
    function of these alone (`_composite_cells`), so the result is the one computed from nothing. Cells computed
    from the last ones (AtlasCells.derived_from) can differ only where they were computed again: no comparison of
    every cell then."""
    eng = pr.engine
    info = np.ascontiguousarray(pr.block_info, dtype=np.float32)
    coarse = _coarse_blocks(pr)
    prev = eng.cell_infos.get(last)
    g = info.shape
    if prev is None or prev[0].vmin.shape != cells.vmin.shape or prev[1].shape != g:
        out = _cell_info(pr, cells, info)
    else:
        old_cells, old_info, old_coarse, old_out = prev
        per_block = _bits_differ(info, old_info) | _bits_differ(coarse, old_coarse)
        redone = cells.derived_from(old_cells)
        if redone is None:
            redo = lod_atlas.half_cells(np.broadcast_to(per_block, g))
            for a, b in ((cells.vmin, old_cells.vmin), (cells.vmax, old_cells.vmax), (cells.std, old_cells.std)):
                redo |= _bits_differ(a, b)
        else:  # the cells computed from the last ones: only those computed again can differ
            redo = np.zeros(cells.vmin.shape, bool)
            redo.reshape(-1)[redone] = True
            bz, by, bx = np.nonzero(np.broadcast_to(per_block, g))
            redo.reshape(g[0], 2, g[1], 2, g[2], 2)[bz, :, by, :, bx, :] = True
        at = np.flatnonzero(redo)
        out = old_out.copy()
        if at.size:
            z, y, x = np.unravel_index(at, redo.shape)
            block = np.ravel_multi_index((z >> 1, y >> 1, x >> 1), g)
            level0 = pr.volume.half_cell_ranges(eng.tables.half_cells) if coarse is not None else None
            lo0, hi0 = (None, None) if level0 is None else (level0[0].reshape(-1)[at], level0[1].reshape(-1)[at])
            out.reshape(-1)[at] = _composite_cells(
                pr, info.reshape(-1)[block], cells.vmin.reshape(-1)[at], cells.vmax.reshape(-1)[at],
                cells.std.reshape(-1)[at], None if coarse is None else coarse.reshape(-1)[block], lo0, hi0)
    out.flags.writeable = False
    # kept as they are where nothing writes them: the block info read-only, `coarse` made here
    kept = info if not info.flags.writeable else info.copy()
    eng.cell_infos.put(last, (cells, kept, coarse, out), out.nbytes + info.nbytes)
    return out


def _shows(lut: Lut, dist: DistTable | None, lo: np.ndarray, hi: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """Where a field whose values lie in [lo, hi] and deviations in [0, sd] can show something: under the point
    classification, or under the distribution table's."""
    vis = lut.visible(lo, hi)
    if dist is not None:
        vis |= dist.visible(lo, hi, sd)
    return vis


def adaptive_walk(pr: "Prepared", cfg: KernelConfig, data: "multipass.PassData", walk: np.ndarray,
                  leaps: Leaps | None) -> tuple[np.ndarray, np.ndarray, Leaps | None]:
    """(the adaptive walk's step levels, the walk info the kernel reads, the leaps): the adaptive walk reads its
    cells' skips in the steps, the octant masks of its sampled cells in the info (config.octants) and the leaps
    over its skipped level-0 cells (renderer/walk/leap.py: step_leaps); without adaptive steps, (data.steps, walk,
    leaps). Kept per (walk info, step levels), both by identity (each comes from a cache of its own when the scene
    repeats), so that a repeated scene does not pay for it again."""
    if not cfg.adaptive:
        return data.steps, walk, leaps
    key = (None if data.region is not None or pr.volume.key is None
           else (id(walk), id(data.steps), cfg.leap, cfg.octants))
    hit = pr.engine.adaptive_walks.get(key) if key is not None else None
    if hit is not None and hit[0] is walk and hit[1] is data.steps:
        return hit[2], hit[3], hit[4]
    steps = walk_steps(pr, data.steps, walk) if data.cells is not None else data.steps
    info = octant_masks(pr, data.octants, steps) if cfg.octants else walk
    out = steps, np.ascontiguousarray(info, dtype=np.float32), (step_leaps(steps) if cfg.leap else None)
    if key is not None:
        pr.engine.adaptive_walks.put(key, (walk, data.steps, *out), sum(a.nbytes for a in out if a is not None))
    return out


def octant_masks(pr: "Prepared", octants: "atlas_cells.AtlasCells | None", steps: np.ndarray) -> np.ndarray:
    """The adaptive walk's octant masks (config.octants; float32 over the half-block cells, 0-255): bit
    (z & 1) << 2 | (y & 1) << 1 | (x & 1) of a sampled cell's octant (quarter-block cell) where the field sampled
    there can show something under the point or the distribution classification (atlas_cells.cl's bounds), as
    `_cell_info` tests its cells; the kernel takes no sample in the others, whose samples add nothing. Only the
    octants of sampled cells are classified (a skipped cell's entry is 0). Without octants (no half-block
    cells to walk): every bit set. At lossless and 5:1 most of what the rays meet is level 0 in cells of 8³, where
    full resolution walks cells of 4³: without octant masks such renders took more samples than full resolution."""
    if octants is None:
        return np.full(steps.shape, 255.0, np.float32)
    want = lod_atlas.per_cell(steps >= 0, 2).reshape(-1)  # the octants of sampled cells
    idx = np.flatnonzero(want)
    vis = np.zeros(want.size, bool)
    vis[idx] = _shows(pr.lut, pr.dist, *(a.reshape(-1)[idx] for a in (octants.vmin, octants.vmax, octants.std)))
    g = steps.shape
    bits = vis.reshape(g[0], 2, g[1], 2, g[2], 2).astype(np.uint8)
    mask = sum(bits[:, oz, :, oy, :, ox] << np.uint8(oz << 2 | oy << 1 | ox)
               for oz in (0, 1) for oy in (0, 1) for ox in (0, 1))
    return np.asarray(mask).astype(np.float32)


def walk_steps(pr: "Prepared", steps: np.ndarray, walk: np.ndarray) -> np.ndarray:
    """Adaptive sampling's step levels with the half-block cells the walk's info marks empty skipped."""
    if pr.scene.mode != "composite":
        return steps
    return lod_atlas.skipped(steps, walk == 0.0)
