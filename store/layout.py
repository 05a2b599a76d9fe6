"""Geometry of the flat multiresolution blocking (thesis §3.1): block grid, level shapes, chunks, shards, addresses.

Every block covers B³ voxels of the finest level whatever its resolution; level k stores each block at (B/2^k)³
cell-centred samples, so a level-k voxel is the average of a 2^k-cube of level-0 voxels. A volume whose shape is
not a multiple of B is padded by edge replication to the block grid; only the true shape is stored at level 0 and
ceil(shape / 2^k) at level k.

Addresses are Python ints (or int64 arrays), never int32: volumes beyond 2^31 voxels are ordinary here.
"""
from __future__ import annotations

from dataclasses import dataclass
from math import ceil, log2

import numpy as np

__all__ = ["Layout", "MIN_CHUNK_EDGE", "SHARD_BLOCKS_YX", "beside", "cell_edge"]

#: Below this many voxels per edge, a level's inner chunk holds a group of blocks rather than one: tiny chunks
#: multiply read requests, which dominate I/O cost (thesis §3.4, group-of-blocks).
MIN_CHUNK_EDGE = 16
#: Blocks per shard along y and x at level 0; coarser levels keep the same voxel extent, so hold more blocks.
SHARD_BLOCKS_YX = 8


def cell_edge(block_size: int) -> int:
    """Edge (voxels) of the cells finer than the blocks that empty-space skipping walks, and whose level-0 value
    ranges the store keeps: 8, or the block itself when it is not a multiple of 8 (cells of 8³ leave clearly less
    of a CT to sample under a bone TF at full resolution than cells of 16³)."""
    return 8 if block_size % 8 == 0 else block_size


def beside(at: np.ndarray, pos: tuple[np.ndarray, ...], shape: tuple[int, ...],
           d: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Of the blocks at flat indices `at` (C order of a grid of `shape`; `pos` = np.unravel_index(at, shape)), those
    whose neighbour offset by `d` (one step per axis, -1, 0 or 1) lies in the grid: (their places in `at`, the
    neighbours' flat indices). By index, not over the grid: a change of levels touches a few thousand of a
    million blocks."""
    inside = np.ones(len(at), bool)
    for p, e, n in zip(pos, d, shape):
        inside &= (p + e >= 0) & (p + e < n)
    rows = np.flatnonzero(inside)
    step = int(np.dot(d, np.cumprod((1, *shape[:0:-1]))[::-1]))
    return rows, np.asarray(at)[rows] + step


@dataclass(frozen=True)
class Layout:
    shape: tuple[int, int, int]
    block_size: int = 16

    def __post_init__(self) -> None:
        b = self.block_size
        if b < 1 or b & (b - 1):
            raise ValueError(f"block size must be a power of two >= 1, got {b}")
        if len(self.shape) != 3 or min(self.shape) < 1:
            raise ValueError(f"shape must be three positive lengths (z, y, x), got {self.shape}")

    # --- block grid -----------------------------------------------------------------------------------------
    @property
    def grid(self) -> tuple[int, int, int]:
        """Blocks per axis (z, y, x)."""
        return tuple(ceil(s / self.block_size) for s in self.shape)  # type: ignore[return-value]

    @property
    def n_blocks(self) -> int:
        gz, gy, gx = self.grid
        return gz * gy * gx

    @property
    def padded_shape(self) -> tuple[int, int, int]:
        return tuple(g * self.block_size for g in self.grid)  # type: ignore[return-value]

    @property
    def n_voxels(self) -> int:
        z, y, x = self.shape
        return z * y * x

    # --- cells ----------------------------------------------------------------------------------------------
    @property
    def cell_edge(self) -> int:
        return cell_edge(self.block_size)

    @property
    def cell_grid(self) -> tuple[int, int, int]:
        """Cells per axis (z, y, x)."""
        c = self.cell_edge
        return tuple(ceil(s / c) for s in self.shape)  # type: ignore[return-value]

    # --- levels ---------------------------------------------------------------------------------------------
    @property
    def n_levels(self) -> int:
        """Levels 0 (full resolution) … log2(B) (one sample per block)."""
        return int(log2(self.block_size)) + 1

    def block_edge(self, level: int) -> int:
        """Samples per block edge at `level`."""
        self._check_level(level)
        return self.block_size >> level

    def level_shape(self, level: int) -> tuple[int, int, int]:
        """Shape of the level array: the true shape at 1/2^level, rounded up (its last sample may average padding)."""
        self._check_level(level)
        f = 1 << level
        return tuple(-(-s // f) for s in self.shape)  # type: ignore[return-value]

    def chunk_shape(self, level: int) -> tuple[int, int, int]:
        """Inner chunk: one block, or a cube of blocks once blocks are smaller than MIN_CHUNK_EDGE."""
        edge = max(self.block_edge(level), min(MIN_CHUNK_EDGE, self.block_size))
        return (edge, edge, edge)

    def shard_shape(self, level: int) -> tuple[int, int, int]:
        """Shard (group of blocks): 4^k block-slabs deep at level k, whose buffer holds B·Y·X/2^k samples, so
        ingest writes every shard whole from a bounded buffer (no read-modify-write of shards); SHARD_BLOCKS_YX·B
        samples across at every level, so a level-k shard groups 16^k times more blocks than a level-0 one."""
        c = self.chunk_shape(level)[0]
        z = max(c, self.block_size << level)
        yx = max(c, SHARD_BLOCKS_YX * self.block_size)
        # no larger than the level (rounded up to whole chunks): a shard's index has an entry per chunk it could
        # hold, so an unclipped level-4 shard of a small MR was 18 kB of index for 400 bytes of data
        return tuple(min(s, ceil(n / c) * c) for s, n in zip((z, yx, yx), self.level_shape(level)))  # type: ignore[return-value]

    def shard_count(self, level: int) -> int:
        return int(np.prod([ceil(s / d) for s, d in zip(self.level_shape(level), self.shard_shape(level))]))

    def chunk_count(self, level: int) -> int:
        return int(np.prod([ceil(s / d) for s, d in zip(self.level_shape(level), self.chunk_shape(level))]))

    def level_samples(self, level: int) -> int:
        """Samples of one block at `level` (padding included): the unit of LOD cost."""
        return self.block_edge(level) ** 3

    # --- addressing -----------------------------------------------------------------------------------------
    def block_index(self, bz: int | np.ndarray, by: int | np.ndarray, bx: int | np.ndarray) -> int | np.ndarray:
        """Linear block number in C order of the grid."""
        _, gy, gx = self.grid
        return (np.asarray(bz, np.int64) * gy + by) * gx + bx if isinstance(bz, np.ndarray) else (bz * gy + by) * gx + bx

    def block_coords(self, index: int | np.ndarray) -> tuple:
        _, gy, gx = self.grid
        index = np.asarray(index, np.int64) if isinstance(index, np.ndarray) else int(index)
        return index // (gy * gx), (index // gx) % gy, index % gx

    def block_of_voxel(self, z: int, y: int, x: int) -> tuple[int, int, int]:
        b = self.block_size
        return z // b, y // b, x // b

    def voxel_offset(self, z: int | np.ndarray, y: int | np.ndarray, x: int | np.ndarray, level: int = 0) -> int | np.ndarray:
        """Linear C-order offset of a voxel in the level array, in 64-bit arithmetic."""
        _, ly, lx = self.level_shape(level)
        if isinstance(z, np.ndarray) or isinstance(y, np.ndarray) or isinstance(x, np.ndarray):
            z, y, x = (np.asarray(v, np.int64) for v in (z, y, x))
            return (z * np.int64(ly) + y) * np.int64(lx) + x
        return (int(z) * ly + int(y)) * lx + int(x)

    def voxel_of_offset(self, offset: int, level: int = 0) -> tuple[int, int, int]:
        _, ly, lx = self.level_shape(level)
        offset = int(offset)
        return offset // (ly * lx), (offset // lx) % ly, offset % lx

    def block_region(self, bz: int, by: int, bx: int, level: int = 0, border: int = 0) -> tuple[slice, slice, slice]:
        """Slices of the level array covered by a block, grown by `border` samples and clipped to the level."""
        e = self.block_edge(level)
        return tuple(
            slice(max(0, i * e - border), min(n, (i + 1) * e + border))
            for i, n in zip((bz, by, bx), self.level_shape(level))
        )  # type: ignore[return-value]

    def _check_level(self, level: int) -> None:
        if not 0 <= level < self.n_levels:
            raise ValueError(f"level must be in 0..{self.n_levels - 1} for block size {self.block_size}, got {level}")
