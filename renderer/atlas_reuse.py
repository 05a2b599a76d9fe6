"""What a new selection keeps of the last atlas of the same store: bricks copied across, cells recomputed where
they can have changed.

The view-weighted selection (renderer/visibility.py) re-selects at every new view, and a move of a degree or two
changes the level of 5-20% of the loaded blocks (chest CT at 30:1: 400-1,500 of ~8,000). Packing every brick
again from the brick cache and bounding every octant of the atlas again (atlas_cells.cl) cost 45 + 44 ms of a
new view's 144 ms of host time on this 2-core machine, while most of it was already on the device. So
`device_atlas` builds a new atlas from the last one of the same store (the engine's `last_atlas`), TF-independent layout and buffers: a block
at the same level keeps its brick (one array copy per level: the bricks of a level lie together in C order of
the grid), only the others are read from the brick cache, and level 0's aprons are filled again as before (a
neighbour's level may have changed). The octants' bounds (`atlas_cells`) are copied for every block whose bounds
cannot have changed, and computed on the device for the others (`dirty_blocks`). The result is the same atlas,
index map and cells, element for element, as one packed from nothing (tests/test_atlas_reuse.py).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from lodcast.renderer import atlas as lod_atlas  # (which imports this module: its names are looked up at call time)

__all__ = ["copy_kept", "dirty_blocks"]


def copy_kept(dst: np.ndarray, src: np.ndarray, levels: np.ndarray, offsets: np.ndarray, old_levels: np.ndarray,
              old_offsets: np.ndarray, kept: np.ndarray, which: range, block_size: int) -> int:
    """Copy into buffer `dst` (the new atlas's elements at `offsets`) from `src` (the old one's at `old_offsets`)
    the bricks of the blocks `kept` (same level in both) whose level lies in `which` (the levels the buffer
    holds). Flat per-block arrays; a level's bricks lie together in C order of the grid in both buffers, so each
    level is one gather of whole bricks. Returns the number of bricks copied."""
    copied = 0
    for k in which:
        sel = kept & (levels == k)
        if not sel.any():
            continue
        size = int(lod_atlas.brick_elements(np.int64(k), block_size))
        new_at, old_at = offsets[levels == k], old_offsets[old_levels == k]
        n0, o0 = int(new_at.min()), int(old_at.min())
        dv = dst[n0:n0 + new_at.size * size].reshape(new_at.size, size)
        sv = src[o0:o0 + old_at.size * size].reshape(old_at.size, size)
        dv[(offsets[sel] - n0) // size] = sv[(old_offsets[sel] - o0) // size]
        copied += int(sel.sum())
    return copied


def dirty_blocks(old_levels: np.ndarray, levels: np.ndarray, interpolation: str) -> np.ndarray:
    """The blocks (grid-shaped bool) whose cells' bounds (atlas_cells.cl) a change of levels from `old_levels`
    to `levels` can change. Nearest block reads a block's own brick, and a level-0 brick's apron, which holds
    the neighbours' samples where they are at level 0 too: a block whose level changed, or a level-0 block next
    to (26-neighbourhood) one that became or stopped being level 0. Interblock reads the neighbourhood's bricks:
    every block next to one whose level changed."""
    old_levels, levels = np.asarray(old_levels), np.asarray(levels)
    changed = old_levels != levels
    if interpolation == "interblock":
        return lod_atlas.neighbourhood_max(changed.astype(np.int8)) > 0
    zero_changed = (old_levels == 0) != (levels == 0)
    return changed | ((levels == 0) & (lod_atlas.neighbourhood_max(zero_changed.astype(np.int8)) > 0))
