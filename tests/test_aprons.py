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


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_only_the_apron_samples_towards_the_named_blocks_are_filled(eng, seed):
    """`only` as dirty_blocks gives it, bits of directions per block: of each named level-0 brick exactly the apron
    samples whose direction, folded at the grid's faces, has its bit (all of them with bit 13) are filled; every
    other sample keeps what it held."""
    rng = np.random.default_rng(seed)
    B, m = 4, 6
    levels = rng.choice([-1, 0, 0, 0, 1], size=(4, 5, 6)).astype(np.int8)
    atlas, offsets = _atlas(levels, B, np.float32, rng)
    want = atlas.copy()
    aprons.fill_aprons(want, levels, offsets, B)
    bits = rng.random((*levels.shape, 27)) < rng.choice([0.05, 0.3])
    bits[rng.random(levels.shape) < 0.1, 13] = True
    bits[rng.random(levels.shape) < 0.2] = False
    only = (bits.astype(np.uint32) << np.arange(27, dtype=np.uint32)).sum(axis=-1).astype(np.uint32)
    got = _on_device(eng, atlas, levels, offsets, B, only)
    expect = atlas.copy()
    G = levels.shape
    for b in zip(*np.nonzero((levels == 0) & (only != 0))):
        o = int(offsets.reshape(G)[b])
        for s in np.ndindex(m, m, m):
            e = [(-1 if c == 0 else 1 if c == m - 1 else 0) for c in s]
            if not any(e):
                continue
            f = [0 if not 0 <= p + d < g else d for p, d, g in zip(b, e, G)]  # folded at the grid's faces
            if bits[b][13] or bits[b][9 * (f[0] + 1) + 3 * (f[1] + 1) + f[2] + 1]:
                i = o + (s[0] * m + s[1]) * m + s[2]
                expect[i] = want[i]
    assert not np.array_equal(expect, atlas) and not np.array_equal(expect, want)
    np.testing.assert_array_equal(got, expect)
