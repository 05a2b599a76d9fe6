"""Clipping (scene `clip`: up to 6 planes and a crop box, world units): what the kernel and the LOD selection see.

The kept region — the volume's box ∩ the crop box ∩ every plane's half-space — is convex, so each ray keeps one
interval of its parameter: the crop box is intersected with the volume's box on the host (the kernel's box test
does the rest, no option needed), each plane becomes (n, w) with n·x + w >= 0 kept (LC_CLIP), and the ray's
sampling then cuts exactly that interval into steps, the last one shorter (raycast.cl): the clipped segment gets
the exact opacity of its length. Blocks entirely outside the kept region are neither loaded nor marched.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from lodcast.renderer.scene.scene import Clip

__all__ = ["clipped_box", "kernel_planes", "block_bounds", "block_mask", "MAX_PLANES"]

MAX_PLANES = 6


def clipped_box(box: tuple[np.ndarray, np.ndarray], clip: Clip | None) -> tuple[np.ndarray, np.ndarray]:
    """The volume's world box (x, y, z) intersected with the crop box (may come out empty: lo >= hi somewhere)."""
    lo, hi = np.asarray(box[0], np.float64), np.asarray(box[1], np.float64)
    if clip is None or clip.box is None:
        return lo, hi
    return np.maximum(lo, clip.box.min), np.minimum(hi, clip.box.max)


def kernel_planes(clip: Clip | None) -> np.ndarray:
    """(MAX_PLANES, 4) float32 rows (nx, ny, nz, w), n of unit length, w = -n·point: a point x is kept where
    n·x + w >= 0. Rows beyond the scene's planes are zero."""
    out = np.zeros((MAX_PLANES, 4), np.float32)
    for k, pl in enumerate([] if clip is None else clip.planes):
        n = np.asarray(pl.normal, np.float64)
        n /= np.linalg.norm(n)
        out[k, :3], out[k, 3] = n, -float(n @ np.asarray(pl.point, np.float64))
    return out


def block_bounds(grid: Sequence[int], shape: Sequence[int], spacing: Sequence[float], origin: Sequence[float],
                 block_size: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per array axis (z, y, x): the world lower and upper bounds of every block's box — its voxels' box (half a
    voxel beyond the outer centres) grown by one voxel each side, so that every interpolation stencil of a kept
    sample lies in a kept block."""
    lo, hi = [], []
    for ax in range(3):
        k = np.arange(grid[ax])
        sp, org = float(spacing[ax]), float(origin[ax])
        lo.append(org + (k * block_size - 1.5) * sp)
        hi.append(org + (np.minimum((k + 1) * block_size, shape[ax]) - 1 + 1.5) * sp)
    return lo, hi


def block_mask(grid: Sequence[int], shape: Sequence[int], spacing: Sequence[float], origin: Sequence[float],
               block_size: int, clip: Clip | None) -> np.ndarray | None:
    """Grid-shaped bool (z, y, x): False where a block's box (block_bounds) lies entirely outside the kept region
    (None: no clip)."""
    if clip is None or (clip.box is None and not clip.planes):
        return None
    lo_c, hi_c = block_bounds(grid, shape, spacing, origin, block_size)
    Z, Y, X = np.meshgrid(np.arange(grid[0]), np.arange(grid[1]), np.arange(grid[2]), indexing="ij")
    lo = np.stack([lo_c[2][X], lo_c[1][Y], lo_c[0][Z]], -1)  # world (x, y, z)
    hi = np.stack([hi_c[2][X], hi_c[1][Y], hi_c[0][Z]], -1)
    keep = np.ones(tuple(grid), bool)
    if clip.box is not None:
        keep &= np.all((hi > np.asarray(clip.box.min)) & (lo < np.asarray(clip.box.max)), axis=-1)
    for pl in kernel_planes(clip)[: len(clip.planes)].astype(np.float64):
        n, w = pl[:3], pl[3]
        # the block's corner furthest along n: if even it is outside, the whole block is
        far = np.where(n > 0, hi, lo)
        keep &= far @ n + w >= 0.0
    return keep
