"""Dual-TF compositing (thesis §3.6.2, item 3): the host's half — the second TF's tables, the per-block
visibility bits the block walk reads, and the priority map.

The kernel (LC_TF2, lc_classify.h) integrates `tf` and `tf2` concurrently along each ray and composites the second
integral over the first: rgba = I₂ + (1 − α₂)·I₁ (premultiplied), so that what tf2 shows (metal, contrast) stays
visible inside what tf hides ("X-ray vision", §3.8). Early ray termination then needs both integrals saturated,
which most rays never are; the priority map restores it: a low-resolution raster of the blocks where tf2 is
visible marks the tiles of pixels whose rays can meet one, and a zero-priority pixel ends on the first integral
alone (its second integral is zero: no block on its ray can show tf2).

The map is conservative, never a sampled guess: each tf2-visible block's box (grown by the interpolation stencil's
reach, clip.block_bounds) is projected corner by corner and its screen bounding rectangle marks every tile it
touches — the projection of a convex box in front of the eye lies inside the rectangle of its corners' projections;
a box reaching behind the eye plane marks the whole image. So the priority-map image equals the plain dual-TF
image up to float rounding.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from lodcast.renderer.kernel.preintegration import PreintTable
from lodcast.renderer.lod.classification import DistTable
from lodcast.renderer.scene import camera as cam
from lodcast.renderer.scene.clip import block_bounds
from lodcast.renderer.scene.scene import TransferFunction
from lodcast.renderer.scene.transfer_function import Lut

__all__ = ["PRIORITY_TILE", "SecondTf", "visibility_bits", "dilate_bits", "PriorityMap", "priority_map"]

#: pixels per priority-map tile edge: a 512² image has a 128² map (finer than a block's footprint in a whole view)
PRIORITY_TILE = 4
_CHUNK = 65536  # blocks projected at a time (bounds the host's memory for very large grids)


@dataclass(frozen=True)
class SecondTf:
    """tf2 and what the kernel needs of it, built as the first TF's are."""

    tf: TransferFunction
    lut: Lut
    unit: float  # its opacity unit distance (world)
    dist: DistTable | None = None
    preint: PreintTable | None = None


def visibility_bits(vis1: np.ndarray, vis2: np.ndarray) -> np.ndarray:
    """The block walk's info under LC_TF2: bit 1 where tf is visible, bit 2 where tf2 is (float32, 0..3)."""
    return (np.asarray(vis1, bool) * 1 + np.asarray(vis2, bool) * 2).astype(np.float32)


def dilate_bits(info: np.ndarray, spread: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """`spread` (a grid-shaped max filter) applied to each visibility bit on its own: the max of the flags would
    drop bit 1 where a neighbour has bit 2."""
    bits = np.asarray(info).astype(np.int64)
    out = sum(spread(((bits >> k) & 1).astype(np.float32)).astype(np.int64) << k for k in (0, 1))
    return np.asarray(out, np.float32)


@dataclass(frozen=True)
class PriorityMap:
    tiles: np.ndarray  # (th, tw) uint8, 1 where a ray of the tile may meet a tf2-visible block
    tile: int  # pixels per tile edge

    @property
    def fraction(self) -> float:
        return float(self.tiles.mean()) if self.tiles.size else 0.0

    def pixels(self, width: int, height: int) -> np.ndarray:
        """(height, width) bool: the map at full resolution."""
        t = self.tile
        return np.repeat(np.repeat(self.tiles.astype(bool), t, 0), t, 1)[:height, :width]


def priority_map(fr: cam.Frame, mask: np.ndarray, shape: Sequence[int], spacing: Sequence[float],
                 origin: Sequence[float], block_size: int, width: int, height: int,
                 tile: int = PRIORITY_TILE) -> PriorityMap:
    """The tiles whose pixels' rays may meet a block of `mask` (grid-shaped bool: tf2 visible and loaded)."""
    assert tile >= 1
    th, tw = -(-height // tile), -(-width // tile)
    diff = np.zeros((th + 1, tw + 1), np.int64)
    idx = np.argwhere(mask)
    lo_c, hi_c = block_bounds(mask.shape, shape, spacing, origin, block_size)
    corners = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)])  # (8, 3): hi or lo per x, y, z
    whole = False
    for s in range(0, len(idx), _CHUNK):
        b = idx[s : s + _CHUNK]
        lo = np.stack([lo_c[2][b[:, 2]], lo_c[1][b[:, 1]], lo_c[0][b[:, 0]]], -1)  # world x, y, z
        hi = np.stack([hi_c[2][b[:, 2]], hi_c[1][b[:, 1]], hi_c[0][b[:, 0]]], -1)
        pts = np.where(corners[None] == 1, hi[:, None, :], lo[:, None, :]) - fr.eye  # (n, 8, 3)
        x, y, z = pts @ fr.r, pts @ fr.u, pts @ fr.f
        if fr.orthographic:
            px, py = x / fr.half_w, y / fr.half_h
        else:
            behind = (z <= 1e-9 * (np.abs(x) + np.abs(y) + 1.0)).any(axis=1)
            if behind.any():
                whole = True
                break
            px, py = x / (z * fr.half_w), y / (z * fr.half_h)
        # pixel centres: column j + 1/2 = (px + 1) W / 2, row i + 1/2 = (1 - py) H / 2; the rectangle of centres
        # covered, widened by a pixel each side so that rounding never drops a ray at its edge
        j0 = np.floor((px.min(axis=1) + 1) * 0.5 * width - 0.5) - 1
        j1 = np.ceil((px.max(axis=1) + 1) * 0.5 * width - 0.5) + 1
        i0 = np.floor((1 - py.max(axis=1)) * 0.5 * height - 0.5) - 1
        i1 = np.ceil((1 - py.min(axis=1)) * 0.5 * height - 0.5) + 1
        on = (j1 >= 0) & (j0 <= width - 1) & (i1 >= 0) & (i0 <= height - 1)
        c0 = (np.clip(j0[on], 0, width - 1) // tile).astype(np.int64)
        c1 = (np.clip(j1[on], 0, width - 1) // tile).astype(np.int64)
        r0 = (np.clip(i0[on], 0, height - 1) // tile).astype(np.int64)
        r1 = (np.clip(i1[on], 0, height - 1) // tile).astype(np.int64)
        np.add.at(diff, (r0, c0), 1)
        np.add.at(diff, (r0, c1 + 1), -1)
        np.add.at(diff, (r1 + 1, c0), -1)
        np.add.at(diff, (r1 + 1, c1 + 1), 1)
    if whole:
        tiles = np.ones((th, tw), np.uint8)
    else:
        tiles = (diff.cumsum(0).cumsum(1)[:th, :tw] > 0).astype(np.uint8)
    return PriorityMap(np.ascontiguousarray(tiles), tile)
