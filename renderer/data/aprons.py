"""The one-sample aprons of the atlas's level-0 bricks (renderer/data/atlas.py lays the bricks out; lc_atlas.h reads
them): `fill_aprons` on the host, the reference (atlas.pack, tests), and `device_aprons` on the device where the
atlas is (aprons.cl), which a render's atlas takes: whole-array operations on the host moved every apron sample of
tens of thousands of bricks through NumPy's fancy indexing at every new selection."""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from lodcast.opencl import Device
from lodcast.store.layout import beside

__all__ = ["fill_aprons", "device_aprons", "neighbours"]

_ELEM = {1: "uchar", 2: "ushort", 4: "uint"}


def fill_aprons(out: np.ndarray, levels: np.ndarray, offsets: np.ndarray, block_size: int,
                 only: np.ndarray | None = None) -> None:
    """The aprons of the level-0 bricks in `out` (placed by atlas.py). The apron sample beyond a face,
    edge or corner of a brick lies towards the neighbouring block in direction d; along an axis where that leaves the grid,
    d is 0 there and the sample repeats the brick's edge (the volume's clamp to edge). It is the sample of block
    own + d when that block is at level 0 too, else the brick's own nearest sample (clamp to edge). Inside a region
    of level-0 blocks trilinear interpolation within a padded brick is then trilinear interpolation of level 0
    across the blocks' faces, clamped at the volume's faces as full resolution is (lc_atlas.h). Coarse bricks have
    no apron: theirs would take 1.95x (8³ of a 16³ block) to 27x (1³) their samples, and at high reductions, where
    most bricks are coarse, the atlas would grow by about as much as the apron-less one holds. `only` (grid-shaped
    bool): fill the aprons of these blocks' bricks alone (an atlas built from the last one copies the others'
    aprons with their bricks); an apron reads its neighbours' interiors only, so the rest may be filled already."""
    lv = np.asarray(levels).astype(np.int64)
    G = np.array(lv.shape)
    flat_off = offsets.reshape(lv.shape)
    where = lv == 0
    cnt = int(where.sum())
    if not cnt:
        return
    n = block_size
    m = n + 2
    start = int(flat_off[where].min())
    A = out[start:start + cnt * m**3].reshape(cnt, m, m, m)
    assert int(flat_off[where].max()) == start + (cnt - 1) * m**3, "bricks of a level lie together"
    rank = np.full(lv.shape, -1, np.int64)  # a brick's place in A; -1: not at level 0
    rank[where] = np.arange(cnt)
    fill = where if only is None else where & np.asarray(only, bool).reshape(lv.shape)
    pos = np.stack(np.nonzero(fill), axis=1)  # (k, 3) z, y, x in C order
    ranks = rank[fill]  # their places in A
    if not ranks.size:
        return
    # clamp to edge: x faces, then y (whole rows, x apron included), then z
    if only is None:  # (in place: a gather and a scatter of every brick would double the traffic)
        A[:, 1:-1, 1:-1, 0], A[:, 1:-1, 1:-1, -1] = A[:, 1:-1, 1:-1, 1], A[:, 1:-1, 1:-1, -2]
        A[:, 1:-1, 0, :], A[:, 1:-1, -1, :] = A[:, 1:-1, 1, :], A[:, 1:-1, -2, :]
        A[:, 0], A[:, -1] = A[:, 1], A[:, -2]
    else:
        B = A[ranks]
        B[:, 1:-1, 1:-1, 0], B[:, 1:-1, 1:-1, -1] = B[:, 1:-1, 1:-1, 1], B[:, 1:-1, 1:-1, -2]
        B[:, 1:-1, 0, :], B[:, 1:-1, -1, :] = B[:, 1:-1, 1, :], B[:, 1:-1, -2, :]
        B[:, 0], B[:, -1] = B[:, 1], B[:, -2]
        A[ranks] = B
    for d0 in np.ndindex(3, 3, 3):
        d = np.array(d0) - 1
        if not d.any():
            continue
        to = pos + d
        folded = (to < 0) | (to >= G)  # (k, 3): off the grid along that axis
        dd = np.where(folded, 0, d)  # the direction that stays on the grid
        moved = dd.any(axis=1)
        nb = np.full(len(pos), -1, np.int64)
        t = pos[moved] + dd[moved]
        nb[moved] = rank[t[:, 0], t[:, 1], t[:, 2]]
        fold_code = folded @ np.array([4, 2, 1])  # which axes fold, per brick: they take different source slices
        for code in np.unique(fold_code[nb >= 0]):
            fold = [(int(code) >> (2 - a)) & 1 for a in range(3)]
            own = np.nonzero((nb >= 0) & (fold_code == code))[0]
            dst = tuple(slice(1, n + 1) if e == 0 else (0 if e < 0 else n + 1) for e in d)
            # along a folded axis the neighbour's edge sample on the own side (it shares the own coordinate)
            src = tuple(slice(1, n + 1) if e == 0 else ((1 if e < 0 else n) if f else (n if e < 0 else 1))
                        for e, f in zip(d, fold))
            A[(ranks[own],) + dst] = A[(nb[own],) + src]


def neighbours(levels: np.ndarray, offsets: np.ndarray, only: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """The level-0 bricks whose aprons to fill (all, or those of the blocks `only`): their atlas offsets (k,), the
    offsets of their 27 neighbours' bricks (k, 27; z, y, x of the direction in C order, -1 where that block is off
    the grid or not at level 0) and their block positions (k, 4) int32 x, y, z, 0 (aprons.cl)."""
    lv = np.asarray(levels)
    G = lv.shape
    zero = (lv == 0).reshape(-1)
    # by flat index: a few thousand bricks of a million blocks, each pass over the grid a good part of the cost
    fill = np.flatnonzero(zero if only is None else zero & (np.asarray(only).reshape(-1) != 0))
    at = np.asarray(offsets, np.int64).reshape(-1)
    pos = np.unravel_index(fill, G)  # z, y, x
    nbr = np.full((fill.size, 27), -1, np.int64)
    for i, d in enumerate(np.ndindex(3, 3, 3)):
        rows, t = beside(fill, pos, G, tuple(e - 1 for e in d))
        there = zero[t]
        nbr[rows[there], i] = at[t[there]]
    xyz = np.zeros((fill.size, 4), np.int32)
    xyz[:, 0], xyz[:, 1], xyz[:, 2] = pos[2], pos[1], pos[0]
    return at[fill], nbr, xyz


def device_aprons(dev: Device, atlas: cl.Buffer, dtype: np.dtype, levels: np.ndarray, offsets: np.ndarray,
                  block_size: int, only: np.ndarray | None = None) -> None:
    """fill_aprons on the device, in the atlas buffer `atlas` (voxels of `dtype`, bricks at `offsets`), waited for.
    `only` of an unsigned integer type (atlas.dirty_blocks): of these bricks only the apron samples towards the
    blocks whose bits it holds, all of them with bit 13 (the others hold already: aprons.cl)."""
    own, nbr, pos = neighbours(levels, offsets, only)
    if not len(own):
        return
    if only is not None and np.asarray(only).dtype.kind == "u":
        dirs = np.asarray(only, np.uint32)[pos[:, 2], pos[:, 1], pos[:, 0]]
    else:
        dirs = np.full(len(own), 1 << 13, np.uint32)
    ctx, queue = dev.context, dev.queue
    mf = cl.mem_flags
    bufs = [cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(a))
            for a in (own, nbr, pos, dirs)]
    grid = np.array([*np.asarray(levels).shape[::-1], 0], np.int32)
    m = block_size + 2
    prg = dev.program("aprons.cl", (f"-DLC_ELEM={_ELEM[np.dtype(dtype).itemsize]}",)).program
    cl.Kernel(prg, "lc_aprons")(queue, (m * m, len(own)), None, atlas, *bufs, grid, np.int32(block_size),
                                np.int32(len(own)))
    queue.finish()
