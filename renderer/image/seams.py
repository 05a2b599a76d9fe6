"""The seam measure: does a level-of-detail image differ more from full resolution along level changes than
elsewhere (DESIGN.md's "no block grid": mean ΔE on the pixels whose rays cross a level change ≤ 1.5 × that on the
other pixels).

A pixel's ray crosses a level change where a sample of its march that shows something (non-zero opacity while
the ray is still open: transmittance above 1 − early termination) lies within `reach` of a face between loaded
blocks of different levels, on its own side: there the sample, or its shading gradient, depends on how the two
blocks are joined.
Faces behind an opaque surface, or in empty space, cannot show. Which faces each ray comes near depends on the
camera, the volume's level 0 and the TF only, not on the selection, so `crossings` marches once on the host
(NumPy, nearest voxel, one voxel a step) and `Crossings.mask(levels)` answers for any selection. The march is
independent of the kernel under test: the kernel does not measure its own seams, and no build option exists only
to measure them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from lodcast.renderer.image.delta_e import delta_e_image
from lodcast.renderer.scene import camera as cam
from lodcast.renderer.scene.transfer_function import Lut, opacity_for_step

__all__ = ["Crossings", "SeamStats", "crossings", "crossings_of", "reach", "seam_stats"]

#: samples a chunk of the march holds at once (rays × steps), to bound its memory
_CHUNK_SAMPLES = 1 << 20


def reach(level: np.ndarray) -> np.ndarray:
    """How far (level-0 voxels) from its block's face a sample of a block at `level` depends on how the block is
    joined to the next: half a sample of its own block (nearest block's clamp zone, eq. 3.5; interblock's blend
    zone on this side, eq. 3.6) plus the shading gradient's one-voxel stencil."""
    return 0.5 * np.exp2(level) + 1.0


@dataclass(frozen=True)
class Crossings:
    """The block faces the rays integrate near: entry k is a sample of the ray of flat pixel index pixel[k]
    (row-major in an image of `size` = (H, W)) in block a[k] (flat index, C order of the block grid), dist[k]
    level-0 voxels from its face with block b[k] (the least over the ray's samples that show something)."""

    pixel: np.ndarray
    a: np.ndarray
    b: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]

    def mask(self, levels: np.ndarray, faces: str = "level_change") -> np.ndarray:
        """(H, W) bool: the pixels whose rays show something within `reach` of a face of the selection `levels`
        (grid-shaped, −1 = not loaded) between loaded blocks of different levels (`faces` "level_change":
        DESIGN.md's crossing of a level change), or between loaded blocks at least one of which is coarser than
        level 0 ("coarse": every face where the sampling is not level 0's trilinear interpolation)."""
        lv = np.asarray(levels).ravel().astype(np.int64)
        la, lb = lv[self.a], lv[self.b]
        joined = (la != lb) if faces == "level_change" else (np.maximum(la, lb) > 0)
        hit = (la >= 0) & (lb >= 0) & joined & (self.dist < reach(la))
        out = np.zeros(self.size[0] * self.size[1], bool)
        out[self.pixel[hit]] = True
        return out.reshape(self.size)


@dataclass(frozen=True)
class SeamStats:
    seam_mean: float | None  # mean ΔE over footprint pixels whose rays cross a level change (None: there are none)
    rest_mean: float | None  # over the other footprint pixels
    ratio: float | None  # seam_mean ÷ rest_mean (None where either is missing or rest_mean is 0)
    seam_pixels: int
    rest_pixels: int

    def as_dict(self) -> dict[str, Any]:
        return {"seam_delta_e": self.seam_mean, "rest_delta_e": self.rest_mean, "seam_ratio": self.ratio,
                "seam_pixels": self.seam_pixels, "rest_pixels": self.rest_pixels}


def seam_stats(rgba: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> SeamStats:
    """ΔE (docs/design.md's, over the footprint of the two images) of `rgba` against `ref` on the pixels of
    `mask` and on the others."""
    de, footprint = delta_e_image(rgba, ref)
    seam, rest = footprint & mask, footprint & ~mask
    sm = float(de[seam].mean()) if seam.any() else None
    rm = float(de[rest].mean()) if rest.any() else None
    ratio = sm / rm if sm is not None and rm else None
    return SeamStats(sm, rm, ratio, int(seam.sum()), int(rest.sum()))


def _nearest_first(pixel: np.ndarray, a: np.ndarray, b: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, ...]:
    """One entry per (pixel, a, b), the least dist."""
    if pixel.size == 0:
        return pixel, a, b, dist
    o = np.lexsort((dist, b, a, pixel))
    pixel, a, b, dist = pixel[o], a[o], b[o], dist[o]
    first = np.ones(pixel.size, bool)
    first[1:] = (pixel[1:] != pixel[:-1]) | (a[1:] != a[:-1]) | (b[1:] != b[:-1])
    return pixel[first], a[first], b[first], dist[first]


def crossings(level0: np.ndarray, spacing: Any, origin: Any, block_size: int, lut: Lut, unit: float,
              frame: cam.Frame, box: tuple[np.ndarray, np.ndarray], width: int, height: int, *,
              early_termination: float = 0.99, levels: int = 1) -> Crossings:
    """The block faces near which the rays of a `width` × `height` image through `frame` show something, in the
    world box `box` (lo, hi, xyz) of the volume `level0` (z, y, x; spacing and origin z, y, x) cut into blocks of
    `block_size`, classified by `lut` (opacity per `unit` world units); faces farther than the reach of the
    coarsest of `levels` levels are left out."""
    vol = np.asarray(level0)
    sp = np.asarray(spacing, np.float64)[::-1]
    org = np.asarray(origin, np.float64)[::-1]
    shape_xyz = np.array(vol.shape[::-1])
    grid_xyz = -(-shape_xyz // block_size)
    stride = np.array([1, grid_xyz[0], grid_xyz[0] * grid_xyz[1]])
    far = float(reach(np.array(levels - 1)))
    step = float(sp.min())
    a_step = opacity_for_step(lut.opacity, step / unit)
    open_t = 1.0 - early_termination
    o, d = cam.pixel_rays(frame, width, height)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    t0, t1 = cam.ray_box(o, d, *box)
    hit = np.flatnonzero(t1 > t0)
    n = np.ceil((t1[hit] - t0[hit]) / step).astype(np.int64)
    order = hit[np.argsort(-n)]  # rays of similar length share a chunk
    parts: list[tuple[np.ndarray, ...]] = []
    i = 0
    while i < order.size:
        steps = int(math.ceil((t1[order[i]] - t0[order[i]]) / step))
        rays = order[i:i + max(1, _CHUNK_SAMPLES // max(steps, 1))]
        i += rays.size
        t = t0[rays, None] + (np.arange(steps) + 0.5) * step
        inside = t < t1[rays, None]
        q = (o[rays, None, :] + t[..., None] * d[rays, None, :] - org) / sp  # voxel coordinates x, y, z
        v = np.clip(np.rint(q).astype(np.int64), 0, shape_xyz - 1)
        val = vol[v[..., 2], v[..., 1], v[..., 0]].astype(np.float64)
        f = np.nan_to_num(np.clip(np.rint((val - lut.lo) * lut.scale), 0, lut.n - 1)).astype(np.int64)
        alpha = np.where(inside & np.isfinite(val), a_step[f], 0.0)
        before = np.cumprod(np.concatenate([np.ones((rays.size, 1)), 1.0 - alpha[:, :-1]], axis=1), axis=1)
        r, k = np.nonzero((alpha > 0.0) & (before > open_t))  # the samples that show something
        qs = np.clip(q[r, k] + 0.5, 0.0, shape_xyz - 1e-3)  # from the volume's box face: blocks start at 0
        blk = np.minimum((qs // block_size).astype(np.int64), grid_xyz - 1)
        own = blk @ stride
        off = qs - blk * block_size
        for ax in range(3):
            for side, dist in ((-1, off[:, ax]), (1, block_size - off[:, ax])):
                nb = blk[:, ax] + side
                ok = (dist < far) & (nb >= 0) & (nb < grid_xyz[ax])
                parts.append(_nearest_first(rays[r[ok]], own[ok], own[ok] + side * stride[ax], dist[ok]))
    cat = [np.concatenate([p[j] for p in parts]) if parts else np.zeros(0) for j in range(4)]
    pixel, a, b, dist = _nearest_first(cat[0].astype(np.int64), cat[1].astype(np.int64), cat[2].astype(np.int64),
                                       cat[3].astype(np.float64))
    return Crossings(pixel, a, b, dist, (height, width))


def crossings_of(prepared: Any) -> Crossings:
    """`crossings` for a render as prepared (renderer.prepare(store, scene)): its volume, first TF, camera and
    the box its rays integrate."""
    vol, scene = prepared.volume, prepared.scene
    _, fr, kbox, _ = cam.geometry(vol, scene)
    levels = int(math.log2(vol.block_size)) + 1
    return crossings(vol.read_level0(), vol.spacing, vol.origin, vol.block_size, prepared.lut, prepared.unit, fr,
                     kbox, scene.width, scene.height, early_termination=scene.sampling.early_termination,
                     levels=levels)
