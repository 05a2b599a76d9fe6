"""Space leaping: how far a ray may jump from an empty cell of the block walk without passing a cell it must sample.

The walk (raycast.cl's 3D DDA over empty-space skipping's cells) skips an empty cell in one DDA step, so a ray
through air still pays a step per cell, a large share of the kernel's time where the TF shows little. Empty-space
leaping with a distance map (Cohen and Sheffer, "Proximity clouds: an acceleration technique for 3D grid
traversal", 1994; Sramek and Kaufman's chessboard distance for ray casting, 2000) lets a ray in an empty cell
leave, in one step, a cube of cells that the map says is empty. A ray only moves forward, so only the cells ahead
of it matter: the map keeps one distance per octant of ray directions (direction-dependent distance maps, as in
Deakin and Knackstedt, "Efficient ray casting of volumetric images using distance maps for empty space skipping",
Computational Visual Media 2020): the edge r of the largest cube that starts at the cell and runs r cells forward
along each axis in that octant's directions with every cell in it empty. A ray going in that octant (an axis it
does not move along counts either way) stays in the cube until it leaves through one of its far faces, r - 1 cells
ahead along that axis, and it leaves in one step. A Chebyshev distance, the same in every direction, is held down
by the nearest non-empty cell anywhere — the wall a ray has just passed through, the floor beside it; the octant's
sees only what lies ahead, and left the walk the fewest steps (against Chebyshev distances, each 4³ cell's own or
its 8³ parent's). Cells outside the grid count as empty: past the grid the ray has left the volume's box, where
there is nothing to sample.

The map rides beside the walk's info (renderer/walk/info.py: walk_info, adaptive_walk) as planes of uint8 over its
cells (Leaps), one per octant o = (x forward) | (y forward) << 1 | (z forward) << 2, 0 in a cell that is not empty;
r = 1 is an ordinary skip. Only the planes of the octants a view's rays go in are computed and handed to the kernel
(camera.ray_octants: one to four; LcParams.leap_planes says which plane is whose).
A leap changes no sample: the cells it passes are empty, and the first sample after them is found where the leap
ends, as after a run of skipped cells (tests/test_leap.py).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np

from lodcast.renderer.data.atlas import half_cells, pair_reduce

__all__ = ["LEAP_MAX", "NO_PLANE", "OCTANTS", "Leaps", "cell_leaps", "children", "coarsen_ranges", "octant_radii",
           "step_leaps"]

#: the largest cube edge stored: leaps of 15 cells (60 voxels at full resolution's 4³ cells) are long enough that
#: the DDA steps left over are few, and the map's passes (one per cell of edge) stay cheap on large grids
LEAP_MAX = 16
#: the map's planes, one per octant of ray directions
OCTANTS = 8


def octant_radii(empty: np.ndarray, cap: int = LEAP_MAX) -> np.ndarray:
    """Per octant of directions and cell of the boolean grid `empty` (z, y, x): the largest r <= `cap` such that the
    r x r x r cells from the cell forward in the octant's directions are all empty (cells outside the grid count as
    empty); 0 where the cell is not empty. uint8 of shape (8, z, y, x), plane o = (x forward) | (y forward) << 1 |
    (z forward) << 2."""
    empty = _grid(empty)
    if not 1 <= cap <= 255:
        raise ValueError(f"cap must lie in 1..255, got {cap}")
    return np.stack([_octant(empty, o, cap) for o in range(OCTANTS)])


def _grid(empty: np.ndarray) -> np.ndarray:
    empty = np.ascontiguousarray(empty, dtype=bool)
    if empty.ndim != 3:
        raise ValueError(f"empty must be a 3-D grid of cells, got shape {empty.shape}")
    return empty


def _octant(empty: np.ndarray, o: int, cap: int) -> np.ndarray:
    """octant_radii's plane o. The cube of edge k + 1 at c is the union of the eight cubes of edge k at c + s, s in
    {0, 1}^3 forward in the octant's directions, so "holds a non-empty cell" grows from edge k to k + 1 by an OR
    with the next cell forward along each axis in turn; r counts the edges whose cube holds none. On bits, 64 cells
    of a row along x to a word (the words first, so that each axis's OR runs over whole planes of words): a pass
    over the grid moves an eighth of the bytes a pass over bools did. The count, a sum of nested sets (a cube
    without a non-empty cell of edge k has none at every smaller edge), is kept as its binary digits: digit j is
    the parity of how many multiples of 2^j are at most r."""
    Z, Y, X = empty.shape
    fwd = [bool(o >> bit & 1) for bit in (2, 1, 0)]  # z, y, x: axes 1, 2 of the words, then along the words
    W = (X + 63) // 64
    full = np.zeros((Z, Y, 64 * W), bool)  # cells past the grid count as empty
    np.logical_not(empty, out=full[..., :X])
    bits = np.ascontiguousarray(np.packbits(full, axis=2, bitorder="little").view("<u8").transpose(2, 0, 1))
    del full
    last = np.packbits(np.arange(64 * (W - 1), 64 * W) < X, bitorder="little").view("<u8")[0]  # the last word's cells
    digits = [np.zeros_like(bits) for _ in range(cap.bit_length())]
    free = ~bits
    free[-1] &= last
    digits[0] ^= free
    t = np.empty_like(bits)
    one, top = np.uint64(1), np.uint64(63)
    for k in range(2, cap + 1):
        if X > 1:  # bit b of word w takes bit b + 1 forward, b - 1 backward, across the words
            if fwd[2]:
                np.right_shift(bits, one, out=t)
                t[:-1] |= bits[1:] << top
            else:
                np.left_shift(bits, one, out=t)
                t[1:] |= bits[:-1] >> top
            bits |= t
        for ax, n in ((1, Z), (2, Y)):
            if n < 2:
                continue
            lo, hi = [slice(None)] * 3, [slice(None)] * 3
            lo[ax], hi[ax] = slice(0, n - 1), slice(1, n)
            if fwd[ax - 1]:
                bits[tuple(lo)] |= bits[tuple(hi)]
            else:
                bits[tuple(hi)] |= bits[tuple(lo)]
        np.invert(bits, out=free)
        free[-1] &= last
        if not free.any():
            break
        j = 0
        while k % (1 << j) == 0:
            digits[j] ^= free
            j += 1
    out = np.zeros((Z, Y, X), np.uint8)
    for j, d in enumerate(digits):
        u = np.unpackbits(np.ascontiguousarray(d.transpose(1, 2, 0)).view(np.uint8), axis=2,
                          bitorder="little")[..., :X]
        if j:
            u <<= np.uint8(j)
        out |= u
    return out


#: LcParams.leap_planes' code of an octant with no plane: its rays walk cell by cell
NO_PLANE = 15


@dataclass(eq=False)
class Leaps:
    """A walk's leaps, its empty cells' octant_radii, computed one octant at a time as views need them: a view's
    rays go in one to four octants (camera.ray_octants), and each octant costs a pass over the grid and a byte per
    cell."""

    empty: np.ndarray
    planes: dict[int, np.ndarray]
    #: the last buffer handed out and its octants: a view that repeats (or keeps its octants) reuses it
    last: tuple[tuple[int, ...], np.ndarray] | None = None

    @classmethod
    def of(cls, empty: np.ndarray) -> "Leaps":
        return cls(_grid(empty), {})

    @property
    def nbytes(self) -> int:
        """What it holds with the planes of a view or two and their buffer (a cache's account, taken when it is
        kept)."""
        return self.empty.nbytes * (1 + 2 * max(2, len(self.planes)))

    def for_octants(self, octants: Iterable[int]) -> tuple[np.ndarray, int]:
        """(the kernel's buffer: the planes of `octants` one after another, (k, z, y, x) uint8; LcParams.leap_planes:
        4 bits per octant o at bit 4 o, the index of its plane in the buffer, NO_PLANE for the others)."""
        octants = sorted(set(int(o) for o in octants))
        assert octants and all(0 <= o < OCTANTS for o in octants), octants
        for o in octants:
            if o not in self.planes:
                self.planes[o] = _octant(self.empty, o, LEAP_MAX)
        code = 0
        for o in range(OCTANTS):
            code |= (octants.index(o) if o in octants else NO_PLANE) << (4 * o)
        key = tuple(octants)
        if self.last is None or self.last[0] != key:
            self.last = key, np.stack([self.planes[o] for o in octants])
        return self.last[1], code


def cell_leaps(info: np.ndarray) -> Leaps:
    """The composite walk's leaps (its info float32, <= 0: an empty cell)."""
    return Leaps.of(np.asarray(info) <= 0.0)


def step_leaps(steps: np.ndarray) -> Leaps:
    """The adaptive walk's leaps (over its half-block cells, renderer/data/atlas.py: step_levels' codes), as Leaps of its
    skipped level-0 cells (code -1: empty blocks, unloaded ones, empty level-0 cells). Such a cell leaves the ray's
    next step where it is, so a cube of them is passed alike cell by cell or at once. (A skipped coarse cell moves
    the next step to its exit; cubes of them hardly occur in real selections, where skipped level-0 cells that leap
    are many.)"""
    return Leaps.of(np.asarray(steps) == -1)


def coarsen_ranges(cmin: np.ndarray, cmax: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The border-inclusive value ranges of cells of twice the edge from those of a grid of cells (z, y, x; NaN: no
    value): each the union of its up to eight children's, exact, since the children's border-inclusive voxels
    together are the parent's."""
    return pair_reduce(np.asarray(cmin, np.float32), np.fmin), pair_reduce(np.asarray(cmax, np.float32), np.fmax)


def children(parent: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """A per-cell array of a grid of cells of twice the edge over the finer grid of `shape` (each child takes its
    parent's value)."""
    return half_cells(np.asarray(parent))[: shape[0], : shape[1], : shape[2]]
