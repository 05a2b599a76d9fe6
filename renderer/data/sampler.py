"""Device-side voxels kept between renders: level 0 as one buffer for quality "full" (the store's integer type up
to 16 bits, else float32: volume.device_dtype; on PoCL trilinear
sampling from a plain buffer is faster than from a 3D image), and the device cache that keeps those buffers and
the LOD atlases (`atlas.device_atlas`) resident: the engine's `device_cache` (renderer/engine.py), LRU by bytes
(``LODCAST_DEVICE_CACHE_MB``, default 1024, and never more than the device budget): a service
alternating between a few volumes or selections uploads nothing. The newest entry stays even when it alone exceeds
the budget (the next render of the same volume is the likeliest); a render holds its own reference to the buffers
it uses, so evicting an entry in use is safe."""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pyopencl as cl
from numpy.typing import ArrayLike

from lodcast.opencl import Device, DeviceError
from lodcast.renderer.data.volume import VolumeView, voxel_options
from lodcast.renderer.engine import Engine
from lodcast.store.layout import cell_edge

__all__ = ["DeviceVolume", "upload_level0", "level0_buffer", "voxel_offset", "ess_cell", "level0_cells"]


#: full resolution keeps the ranges of cells of 4³ voxels while their grid has at most this many cells, else the
#: store's 8³: the finer cells leave fewer samples, but the host classifies those under a visible 8³ parent for each
#: new TF (walk._level0_walk), in time that grows with their number
FINE_CELLS = 1 << 22


def ess_cell(shape: tuple[int, ...], block_size: int) -> int:
    """The edge (voxels) of the cells of empty-space skipping at full resolution: 4 on volumes whose grid of 4³
    cells stays within FINE_CELLS, else the store's cells (store.layout.cell_edge: 8, or the block when that is not
    a multiple of 8). Runs of cells to sample cost the walk a step per cell (raycast.cl), so finer cells pay where
    they leave out more samples than the walk's extra steps cost: at steps up to a voxel (walk.FINE_STEP; beyond,
    the walk takes their 8³ parents)."""
    c = cell_edge(block_size)
    if c % 4 == 0 and c > 4 and int(np.prod([-(-int(n) // 4) for n in shape])) <= FINE_CELLS:
        return 4
    return c


def level0_cells(dev: Device, buf: cl.Buffer, sub_shape: tuple[int, int, int], start: tuple[int, int, int],
                 blocks: tuple[slice, slice, slice], vol: VolumeView) -> tuple[np.ndarray, np.ndarray]:
    """The border-inclusive (min, max) of the ess_cell cells of `blocks`, from level-0 voxels on the device (`buf`:
    `sub_shape` voxels from voxel `start`, z-y-x, holding those cells and their borders), in float32 arrays over
    the volume's whole cell grid (NaN elsewhere: no value, nothing to see). Taken from the store where it keeps
    the ranges of these very cells (format >= 3, cells of store.layout.cell_edge: the same voxels, rounded
    outwards), else computed on the device (cells.cl)."""
    ctx, queue = dev.context, dev.queue
    C, B = ess_cell(vol.shape, vol.block_size), int(vol.block_size)
    k = B // C
    grid = tuple(-(-s // C) for s in vol.shape)
    cells = tuple(slice(b.start * k, min(grid[a], b.stop * k)) for a, b in enumerate(blocks))
    n = tuple(max(0, c.stop - c.start) for c in cells)
    full = [np.full(grid, np.nan, np.float32) for _ in range(2)]
    if 0 in n:
        return full[0], full[1]
    if vol.has_cell_ranges and C == cell_edge(B):
        for f, r in zip(full, vol.source.cell_ranges):
            f[cells] = r[cells]
        return full[0], full[1]
    parts = [np.empty(n, np.float32) for _ in range(2)]
    d_out = [cl.Buffer(ctx, cl.mem_flags.WRITE_ONLY, size=p.nbytes) for p in parts]
    xyz = lambda v: np.array([v[2], v[1], v[0], 0], np.int32)  # noqa: E731
    kern = cl.Kernel(dev.program("cells.cl", voxel_options(vol.voxel_dtype)).program, "lc_cell_range")
    kern(queue, (n[2], n[1], n[0]), None, buf, xyz(sub_shape), xyz(start), xyz(vol.shape), np.int32(C),
         xyz([c.start for c in cells]), xyz(n), *d_out)
    for p, d in zip(parts, d_out):
        cl.enqueue_copy(queue, p, d)
    queue.finish()
    for f, p in zip(full, parts):
        f[cells] = p
    return full[0], full[1]


@dataclass(frozen=True)
class DeviceVolume:
    buffer: cl.Buffer
    dims_xyz: tuple[int, int, int]
    nbytes: int
    upload_ms: float
    cell_min: np.ndarray  # border-inclusive extrema of the cells of empty-space skipping
    cell_max: np.ndarray
    cell: int  # their edge in voxels (ess_cell)


def voxel_offset(z: ArrayLike, y: ArrayLike, x: ArrayLike, shape_zyx: Sequence[int]) -> np.ndarray:
    """Host mirror of the kernel's LC_OFFSET: ((z·ny + y)·nx + x) in 64-bit unsigned arithmetic."""
    nz, ny, nx = (np.uint64(s) for s in shape_zyx)
    z, y, x = (np.asarray(v).astype(np.uint64) for v in (z, y, x))
    return (z * ny + y) * nx + x


def level0_buffer(dev: Device, vol: VolumeView, region: tuple[slice, slice, slice]) -> cl.Buffer:
    """A device buffer of level 0's voxels `region` (z-y-x slices), read straight into its host mapping: no host
    array beside it (one, read and then copied, touches level 0's bytes twice and slows a first full-resolution
    render)."""
    ctx, queue = dev.context, dev.queue
    shape = tuple(s.stop - s.start for s in region)
    buf = cl.Buffer(ctx, cl.mem_flags.READ_ONLY, size=max(4, int(np.prod(shape)) * vol.voxel_dtype.itemsize))
    host, _ = cl.enqueue_map_buffer(queue, buf, cl.map_flags.WRITE_INVALIDATE_REGION, 0, shape, vol.voxel_dtype)
    try:
        vol.read_level0_region(region, host)
    finally:
        host.base.release(queue)
    queue.finish()
    return buf


def upload_level0(eng: Engine, vol: VolumeView) -> tuple[DeviceVolume, bool]:
    """(device volume, whether it came from `eng`'s device cache). Raises DeviceError when level 0 exceeds the
    device's largest allocation (CL_DEVICE_MAX_MEM_ALLOC_SIZE)."""
    dtype = vol.voxel_dtype
    nbytes = vol.n_voxels * dtype.itemsize
    limit = eng.device.max_alloc_bytes
    if nbytes > limit:
        raise DeviceError(
            f"level 0 of this volume needs {nbytes / 2**30:.2f} GiB as {dtype.name}, more than the device's largest "
            f"allocation ({limit / 2**30:.2f} GiB, CL_DEVICE_MAX_MEM_ALLOC_SIZE); quality 'full' cannot render it "
            "on this device"
        )
    key = ("level0", vol.key)
    hit = eng.device_cache.get(key) if vol.key is not None else None
    if hit is not None:
        return hit, True
    t = time.perf_counter()
    (nz, ny, nx), (gz, gy, gx) = vol.shape, vol.grid
    buf = level0_buffer(eng.device, vol, (slice(0, nz), slice(0, ny), slice(0, nx)))
    cmin, cmax = level0_cells(eng.device, buf, vol.shape, (0, 0, 0), (slice(0, gz), slice(0, gy), slice(0, gx)), vol)
    dv = DeviceVolume(buf, (vol.shape[2], vol.shape[1], vol.shape[0]), nbytes, (time.perf_counter() - t) * 1e3,
                      cmin, cmax, ess_cell(vol.shape, vol.block_size))
    if vol.key is not None:
        eng.device_cache.put(key, dv, dv.nbytes)
    return dv, False
