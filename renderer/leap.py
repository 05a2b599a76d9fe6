"""Space leaping: how far a ray may jump from an empty cell of the block walk without passing a cell it must sample.

The walk (raycast.cl's 3D DDA over empty-space skipping's cells) skips an empty cell in one DDA step, so a ray
through air still pays a step per cell: on the chest CT at 512², an image whose TF shows almost nothing took 52 ms
of such steps at full resolution (cells of 8³), 40% of a bone image's kernel time. Empty-space leaping with a
distance map (Cohen and Sheffer, "Proximity clouds: an acceleration technique for 3D grid traversal", 1994; Sramek
and Kaufman's chessboard distance for ray casting, 2000) lets a ray in an empty cell leave, in one step, the cube
of cells around it that the map says is empty: with r the Chebyshev distance (in cells) from the cell to the
nearest cell that is not empty, every cell within r - 1 of it is empty, and the ray leaves that cube of
(2r - 1)³ cells through one of its faces. Cells outside the grid count as empty: past the grid the ray has left
the volume's box, where there is nothing to sample.

The map rides in the walk's info (renderer/walk.py: walk_info): a cell that must be sampled keeps its positive info, an empty one
holds -r (r >= 1; r = 1 is an ordinary skip). A leap changes no sample: the cells it passes are empty, and the
first sample after them is found where the leap ends, as after a run of skipped cells (tests/test_leap.py).
"""
from __future__ import annotations

import numpy as np

from lodcast.renderer.atlas import half_cells, pair_reduce

__all__ = ["LEAP_MAX", "child_leaps", "children", "coarsen_ranges", "leap_radii", "step_leaps", "with_leaps"]

#: the largest radius stored: leaps of at least 15 cells (120 voxels at full resolution's 8³ cells) are long
#: enough that the DDA steps left over are few, and the map's passes stay cheap on large grids
LEAP_MAX = 16


def leap_radii(empty: np.ndarray, cap: int = LEAP_MAX) -> np.ndarray:
    """Per cell of the boolean grid `empty`: 0 where the cell is not empty, else its Chebyshev distance in cells
    to the nearest non-empty cell, capped at `cap` (cells outside the grid count as empty), as uint8."""
    empty = np.asarray(empty, bool)
    if empty.ndim != 3:
        raise ValueError(f"empty must be a 3-D grid of cells, got shape {empty.shape}")
    if not 1 <= cap <= 255:
        raise ValueError(f"cap must lie in 1..255, got {cap}")
    out = np.where(empty, cap, 0).astype(np.uint8)
    reached = ~empty  # within distance k - 1 of a non-empty cell
    for k in range(1, cap):
        if reached.all():
            break
        grown = reached  # (each axis below grows a copy)
        for ax in range(3):  # the 3 x 3 x 3 neighbourhood, one axis at a time (Chebyshev balls are cubes)
            n = grown.shape[ax]
            if n < 2:
                continue
            lo = [slice(None)] * 3
            hi = [slice(None)] * 3
            lo[ax], hi[ax] = slice(0, n - 1), slice(1, n)
            step = grown.copy()
            step[tuple(lo)] |= grown[tuple(hi)]
            step[tuple(hi)] |= grown[tuple(lo)]
            grown = step
        out[grown & ~reached] = k
        reached = grown
    return out


def with_leaps(info: np.ndarray) -> np.ndarray:
    """The composite walk's info (float32, 0: empty) with every empty cell holding -r (leap_radii)."""
    info = np.asarray(info, np.float32)
    r = leap_radii(info <= 0.0)
    return np.ascontiguousarray(np.where(r > 0, -r.astype(np.float32), info), dtype=np.float32)


def step_leaps(steps: np.ndarray) -> np.ndarray:
    """The adaptive walk's leaps (float32 over its half-block cells, renderer/atlas.py: step_levels' codes): the
    radius r >= 2 of the cubes of skipped level-0 cells (code -1: empty blocks, unloaded ones, empty level-0 cells),
    0 elsewhere. Such a cell leaves the ray's next step where it is, so a cube of them is passed alike cell by cell
    or at once. (A skipped coarse cell moves the next step to its exit; cubes of them hardly occur: none of radius
    2 in 9 chest and engine CT selections from 10:1 to 100:1, against 8,600-93,000 level-0 cells that leap.)"""
    r = leap_radii(np.asarray(steps) == -1)
    return np.ascontiguousarray(np.where(r >= 2, r, 0).astype(np.float32))


def coarsen_ranges(cmin: np.ndarray, cmax: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The border-inclusive value ranges of cells of twice the edge from those of a grid of cells (z, y, x; NaN: no
    value): each the union of its up to eight children's, exact, since the children's border-inclusive voxels
    together are the parent's."""
    return pair_reduce(np.asarray(cmin, np.float32), np.fmin), pair_reduce(np.asarray(cmax, np.float32), np.fmax)


def children(parent: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """A per-cell array of a grid of cells of twice the edge over the finer grid of `shape` (each child takes its
    parent's value)."""
    return half_cells(np.asarray(parent))[: shape[0], : shape[1], : shape[2]]


def child_leaps(parent: np.ndarray, info: np.ndarray) -> np.ndarray:
    """The leaps of a grid of cells (`info`, 0: empty) from those of its parents of twice the edge (`parent`, from
    with_leaps: -R in an empty parent): every parent within R - 1 of an empty parent is empty, so every child
    within 2R - 2 of its child is, and an empty child holds -(2R - 1) under an empty parent, -1 (a plain skip)
    under one that is not. Each such radius is at most the child's own distance to a non-empty child
    (tests/test_leap.py), and costs the parents' map alone (an eighth of the cells) instead of the children's."""
    r = children(np.where(parent < 0.0, -2.0 * parent - 1.0, 1.0), info.shape).astype(np.float32)
    info = np.asarray(info, np.float32)
    return np.ascontiguousarray(np.where(info <= 0.0, -r, info), dtype=np.float32)
