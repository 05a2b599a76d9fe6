"""Device-side voxels for the kernel's sampler. Full resolution for now: level 0 as one float32 buffer (on
PoCL trilinear from a plain buffer measured ~2x faster than from a 3D image), kept on the device between renders
of the same store. The brick atlas of the LOD issue replaces this module's upload, not the kernel interface."""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from lodcast.renderer.program import DeviceError, get_context
from lodcast.renderer.volume import VolumeView

__all__ = ["DeviceVolume", "upload_level0", "voxel_offset", "clear_cache"]

_LOCK = threading.Lock()
_CACHE: dict = {}  # key -> DeviceVolume; one entry (the last store rendered)


@dataclass(frozen=True)
class DeviceVolume:
    buffer: cl.Buffer
    dims_xyz: tuple[int, int, int]
    nbytes: int
    upload_ms: float


def voxel_offset(z, y, x, shape_zyx) -> np.ndarray:
    """Host mirror of the kernel's LC_OFFSET: ((z·ny + y)·nx + x) in 64-bit unsigned arithmetic."""
    nz, ny, nx = (np.uint64(s) for s in shape_zyx)
    z, y, x = (np.asarray(v).astype(np.uint64) for v in (z, y, x))
    return (z * ny + y) * nx + x


def clear_cache() -> None:
    with _LOCK:
        _CACHE.clear()


def upload_level0(vol: VolumeView) -> tuple[DeviceVolume, bool]:
    """(device volume, whether it came from the cache). Raises DeviceError when level 0 exceeds the device's
    largest allocation (CL_DEVICE_MAX_MEM_ALLOC_SIZE)."""
    ctx, queue = get_context()
    nbytes = vol.n_voxels * 4
    limit = int(ctx.devices[0].max_mem_alloc_size)
    if nbytes > limit:
        raise DeviceError(
            f"level 0 of this volume needs {nbytes / 2**30:.2f} GiB as float32, more than the device's largest "
            f"allocation ({limit / 2**30:.2f} GiB, CL_DEVICE_MAX_MEM_ALLOC_SIZE); quality 'full' cannot render it "
            "on this device"
        )
    with _LOCK:
        if vol.key is not None and vol.key in _CACHE:
            return _CACHE[vol.key], True
    t = time.perf_counter()
    data = np.ascontiguousarray(vol.read_level0(), dtype=np.float32)
    if tuple(data.shape) != tuple(vol.shape):
        raise DeviceError(f"level 0 has shape {data.shape}, the store says {vol.shape}")
    buf = cl.Buffer(ctx, cl.mem_flags.READ_ONLY, size=max(4, data.nbytes))
    cl.enqueue_copy(queue, buf, data)
    queue.finish()
    dv = DeviceVolume(buf, (vol.shape[2], vol.shape[1], vol.shape[0]), data.nbytes, (time.perf_counter() - t) * 1e3)
    if vol.key is not None:
        with _LOCK:
            _CACHE.clear()
            _CACHE[vol.key] = dv
    return dv, False
