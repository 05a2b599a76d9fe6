"""The atlas's level-0 aprons on the device (aprons.cl, renderer/data/aprons.py) against the host's reference
(aprons.fill_aprons), element for element: random selections with blocks at level 0 beside coarse and unloaded
ones and at the grid's faces, for every voxel size, whole and for a subset of the bricks."""
from __future__ import annotations

import numpy as np
import pyopencl as cl
import pytest

from lodcast.renderer.data import aprons
from lodcast.renderer.data.atlas import _offsets
from lodcast.renderer.frame.render import Renderer


@pytest.fixture(scope="module")
def eng():
    r = Renderer()
    yield r
    r.close()


def _atlas(levels: np.ndarray, B: int, dtype, rng) -> tuple[np.ndarray, np.ndarray]:
    sizes, offsets = _offsets(levels, B)
    info = np.iinfo(dtype) if np.dtype(dtype).kind in "iu" else None
    lo, hi = (info.min, info.max) if info else (-1e6, 1e6)
    a = rng.uniform(lo, hi, int(sizes.sum())).astype(dtype)
    return a, offsets


def _on_device(eng, host: np.ndarray, levels, offsets, B, only=None) -> np.ndarray:
    ctx, queue = eng.device.context, eng.device.queue
    buf = cl.Buffer(ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=host)
    aprons.device_aprons(eng.device, buf, host.dtype, levels, offsets, B, only)
    out = np.empty_like(host)
    cl.enqueue_copy(queue, out, buf)
    return out


@pytest.mark.parametrize("dtype", [np.float32, np.int16, np.uint16, np.uint8])
@pytest.mark.parametrize("seed", [0, 1])
def test_device_aprons_are_the_hosts(eng, dtype, seed):
    rng = np.random.default_rng(seed)
    B = 4
    levels = rng.choice([-1, 0, 0, 0, 1, 2], size=(5, 6, 7)).astype(np.int8)
    atlas, offsets = _atlas(levels, B, dtype, rng)
    want = atlas.copy()
    aprons.fill_aprons(want, levels, offsets, B)
    np.testing.assert_array_equal(_on_device(eng, atlas, levels, offsets, B), want)
    # a subset: the other bricks' aprons are right already (copied with their bricks), these are garbage
    only = rng.random(levels.shape) < 0.3
    start = want.copy()
    own, _, _ = aprons.neighbours(levels, offsets, only)
    m = B + 2
    for o in own:
        brick = start[o:o + m**3].reshape(m, m, m)
        inner = brick[1:-1, 1:-1, 1:-1].copy()
        brick[...] = atlas[o:o + m**3].reshape(m, m, m)  # whatever was there
        brick[1:-1, 1:-1, 1:-1] = inner
    assert len(own) and not np.array_equal(start, want)
    np.testing.assert_array_equal(_on_device(eng, start, levels, offsets, B, only), want)


def test_a_single_block_and_a_grid_without_level_0(eng):
    rng = np.random.default_rng(3)
    for levels in (np.zeros((1, 1, 1), np.int8), np.ones((2, 2, 2), np.int8)):
        atlas, offsets = _atlas(levels, 4, np.float32, rng)
        want = atlas.copy()
        aprons.fill_aprons(want, levels, offsets, 4)
        np.testing.assert_array_equal(_on_device(eng, atlas, levels, offsets, 4), want)
