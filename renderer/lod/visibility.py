"""How much of each block the camera can see: the view-dependent weight of the level-of-detail selection.

The TF significance (level_error.py) says what a block loses at each level, wherever it is. An image shows a
block only as far as what lies in front of it lets it through: a rib behind the sternum, bone under opaque skin,
the far wall of a skull contribute nothing to the picture, and the budget they take is better spent on what the
camera sees. Combining a data or TF error with view-dependent measures is the literature's standard step
(Ljung's thesis §2.3.1: distance to viewer and projected size, used to weight a data error measure); the measure
here is occlusion.

`block_visibility` casts a low-resolution set of the scene's own rays (`cast_rays` along the image's longer side, the
same camera, box and clip planes) front to back through a coarse level of the store (the finest with at most
VIS_VOXELS voxels: level 1 of a 512²×275 CT, level 3 of a 1024×2048² body), each sample classified by the TF at
its value, and records per block the largest transmittance with which any ray of the cast enters it
(visibility.cl); the blocks where the image's own rays enter the box (or the clip region) get 1, which a cast
sparser than the image misses where a face is seen at a grazing angle. Classifying coarse means thins small opaque structures rather than thickening them, so the
estimate errs towards calling a block visible. Blocks no ray reaches (outside the picture, or behind what the
cast saw as opaque) get 0. Where a block and its neighbours hold nothing the TF shows (`quiet_blocks`) the cast
takes no sample, only the block's entry: the same result in less time.

Why a coarse level, and which: docs/lod.md ("What the camera sees") compares the selection's error weighted by
this estimate from levels 0, 1 and 2 and unweighted.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from lodcast.opencl import Device
from lodcast.renderer.data.atlas import neighbourhood_max
from lodcast.renderer.data.volume import VolumeView
from lodcast.renderer.engine import Engine
from lodcast.renderer.kernel.params import fill_params
from lodcast.renderer.scene import camera as cam
from lodcast.renderer.scene.scene import Scene
from lodcast.renderer.scene.transfer_function import Lut

__all__ = ["AUTO_VOXELS", "RAYS_PER_BLOCK", "VIS_RAYS", "VIS_VOXELS", "block_visibility", "cast_rays",
           "quiet_blocks", "visibility_level"]

VIS_RAYS = 96  # rays along the longer side of the image, at least
#: and at least this many per block along the grid's longest extent (up to the image's own rays): a block that no
#: ray of the cast enters weighs nothing in the selection, so rays sparser than the blocks drop surface blocks from
#: the picture's budget by chance, and a new view a degree away drops others
RAYS_PER_BLOCK = 3
#: sampling.lod_visibility left out is on for volumes of at most this many voxels: beyond, a new view's selection
#: and atlas cost many times the picture (even with its atlas built from the last one's)
AUTO_VOXELS = 1 << 27
VIS_VOXELS = 1 << 24  # the coarse level cast through has at most this many voxels
_ONE = float(1 << 24)  # visibility.cl's fixed point


def visibility_level(vol: VolumeView) -> int:
    """The finest level of `vol` with at most VIS_VOXELS voxels (the coarsest if none has)."""
    for k in range(vol.n_levels):
        if int(np.prod(vol.level_shape(k), dtype=np.int64)) <= VIS_VOXELS:
            return k
    return vol.n_levels - 1


def _coarse(eng: Engine, vol: VolumeView, k: int) -> tuple[cl.Buffer, tuple[int, int, int]]:
    """Level k of `vol` as float32 on the device (kept in the device cache: a turntable casts every frame)."""
    key = None if vol.key is None else ("visibility", vol.key, k)
    hit = eng.device_cache.get(key) if key is not None else None
    if hit is not None:
        return hit
    a = np.ascontiguousarray(vol.read_level(k, np.float32))
    buf = cl.Buffer(eng.device.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=a)
    out = (buf, (a.shape[2], a.shape[1], a.shape[0]))
    if key is not None:
        eng.device_cache.put(key, out, a.nbytes)
    return out


def block_visibility(eng: Engine, vol: VolumeView, scene: Scene, fr: cam.Frame, kbox: tuple, lut: Lut,
                     unit: float) -> np.ndarray:
    """Per block (grid-shaped float32 in [0, 1]) the largest transmittance with which a ray of the scene's view
    enters it, through the scene's TF `lut` (unit distance `unit`) applied to a coarse level of `vol` (see the
    module doc). `kbox`: the box the rays integrate (crop box applied); the scene's clip planes cut the rays."""
    k = visibility_level(vol)
    buf, kdims = _coarse(eng, vol, k)
    n_long = cast_rays(vol.grid, scene.width, scene.height)
    w, h = (n_long, max(1, round(n_long * scene.height / scene.width))) if scene.width >= scene.height else \
        (max(1, round(n_long * scene.width / scene.height)), n_long)
    step_world = float(1 << k) * float(min(vol.spacing))
    p = fill_params(vol, scene, fr, kbox, lut, step_world, unit, 0, None, None)
    p[0]["width"], p[0]["height"] = w, h
    alpha = np.ascontiguousarray(lut.kernel_table("alpha", step_world / unit)[:, 3], dtype=np.float32)
    quiet = quiet_blocks(vol, lut, k)
    opts = ["-DLC_CLIP"] if scene.clip is not None and scene.clip.planes else []
    dev: Device = eng.device
    ctx = dev.context
    queue = cl.CommandQueue(ctx)  # its own: a job's prefetch casts the next frame while the current one renders
    mf = cl.mem_flags
    d_p = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=p)
    d_a = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=alpha)
    d_q = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=quiet)
    vis = np.zeros(vol.grid, np.uint32)
    d_v = cl.Buffer(ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=vis)
    prog = dev.program("visibility.cl", opts).program
    cl.Kernel(prog, "lc_visibility")(queue, (w, h), None, d_p, buf, np.array([*kdims, 0], np.int32), np.int32(k),
                                     d_a, d_q, d_v)
    cl.Kernel(prog, "lc_visibility_entry")(queue, (scene.width, scene.height), None, d_p,
                                           np.array([scene.width, scene.height], np.int32), d_v)
    cl.enqueue_copy(queue, vis, d_v)
    queue.finish()
    return (vis.astype(np.float64) / _ONE).astype(np.float32)


def cast_rays(grid: tuple[int, ...], width: int, height: int) -> int:
    """Rays of the cast along the image's longer side: VIS_RAYS, or RAYS_PER_BLOCK per block along the grid's
    longest extent where that is more, but not more than the image has."""
    return max(VIS_RAYS, min(RAYS_PER_BLOCK * max(grid), max(width, height)))


def quiet_blocks(vol: VolumeView, lut: Lut, k: int) -> np.ndarray:
    """Per block (uint8, C order): 1 where the cast through level k need not sample, since the TF's interpolant is
    zero on every value there: a level-k sample interpolates level-k voxels within 2^k level-0 voxels of it, each
    the mean of level-0 values there, so where 2^k is at most the block size its values lie in the border-inclusive
    ranges of the block and its 26 neighbours, and `lut.visible` (conservative by an entry) says none of them can
    be seen. Beyond that reach (a level coarser than the block): no block is quiet."""
    shows = lut.visible(vol.min_border, vol.max_border)
    if (1 << k) > int(vol.block_size):
        return np.zeros(shows.size, np.uint8)
    return np.ascontiguousarray(neighbourhood_max(shows.astype(np.int8)).ravel() == 0, dtype=np.uint8)

