"""The renderer's view of a volume: geometry, block statistics and level-0 voxels — from a lodcast store, a path
to one, or a NumPy array (tests, quick looks). All store access of the renderer goes through this module."""
from __future__ import annotations

import math
import os
import warnings
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeAlias

import numpy as np

from lodcast.renderer.kernel.config import voxel_define
from lodcast.store.layout import cell_edge
from lodcast.store.store import Store

__all__ = ["VolumeView", "StoreLike", "as_volume", "level_view", "block_minmax_border", "device_dtype", "voxel_options", "VOXEL_CTYPES"]

#: OpenCL C names of the voxel types the device keeps as they are (renderer/kernel/lc_common.h's LC_VOXEL)
VOXEL_CTYPES = {np.dtype(np.int8): "char", np.dtype(np.uint8): "uchar", np.dtype(np.int16): "short",
                np.dtype(np.uint16): "ushort", np.dtype(np.float32): "float"}


def device_dtype(dtype: Any) -> np.dtype:
    """The type voxels of `dtype` have on the device (level 0 and the atlas): integers of up to 16 bits as they
    are (the kernel converts them to float exactly), anything else float32."""
    d = np.dtype(dtype)
    return d if d.kind in "iu" and d.itemsize <= 2 else np.dtype(np.float32)


def voxel_options(dtype: Any) -> tuple[str, ...]:
    """The -D option that makes a kernel read voxels of `dtype` (none for float32)."""
    return voxel_define(VOXEL_CTYPES[device_dtype(dtype)])


@dataclass
class VolumeView:
    shape: tuple[int, int, int]  # z, y, x
    spacing: tuple[float, float, float]
    origin: tuple[float, float, float]
    block_size: int
    value_range: tuple[float, float]
    min_border: np.ndarray  # grid-shaped (gz, gy, gx) float64, block plus a one-voxel border; NaN = no finite voxel
    max_border: np.ndarray
    key: Any  # hashable identity for device-side caching; None: do not cache
    _read0: Any = field(repr=False, default=None)
    source: Any = field(repr=False, default=None)
    #: the world box (lo, hi, xyz) the camera frames and the rays integrate, where it is not this volume's own: a
    #: coarse level shown in place of its store (`level_view`), whose last samples may reach past the store's box
    frame_box: tuple[np.ndarray, np.ndarray] | None = field(repr=False, default=None)

    @property
    def grid(self) -> tuple[int, int, int]:
        return tuple(int(g) for g in self.min_border.shape)  # type: ignore[return-value]

    @property
    def n_blocks(self) -> int:
        return int(np.prod(self.grid))

    @property
    def voxel_dtype(self) -> np.dtype:
        """The type of this volume's voxels on the device (`device_dtype` of the source's)."""
        return device_dtype(getattr(self.source, "dtype", np.float32))

    @property
    def n_voxels(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))

    def read_level0(self, dtype: Any = None) -> np.ndarray:
        """Level 0, in `dtype` when given (a store converts while it decodes, in its reading threads)."""
        a = self._read0(dtype)
        return a if dtype is None else np.asarray(a, dtype=dtype)

    def read_level0_region(self, region: tuple, out: np.ndarray) -> np.ndarray:
        """Voxels `region` (slices, z-y-x) of level 0 into `out` (of the region's shape, in its dtype): a pass of a
        render in several reads only its part, straight into its mapped device buffer."""
        if self.has_levels:
            return self.source.read_region(0, region, out.dtype, out)
        out[...] = np.asarray(self.source)[region]
        return out

    def read_level(self, level: int, dtype: Any = None) -> np.ndarray:
        """The whole of a store's level `level` (its level_shape), in `dtype` when given."""
        assert self.has_levels, "only a lodcast store has coarse levels"
        return self.source.read_region(level, ..., dtype)

    def level_shape(self, level: int) -> tuple[int, int, int]:
        return tuple(self.source.layout.level_shape(level))

    @property
    def n_levels(self) -> int:
        return int(self.source.layout.n_levels) if self.has_levels else 1

    @property
    def has_levels(self) -> bool:
        """Whether the coarser levels exist (a lodcast store), which level-of-detail rendering needs."""
        return hasattr(self.source, "level") and hasattr(self.source, "layout")

    @property
    def has_distribution(self) -> bool:
        """Whether the store keeps the standard deviation behind its coarse voxels (format >= 2)."""
        return self.has_levels and bool(getattr(self.source, "has_distribution", False))

    @property
    def std_max(self) -> float:
        return float(getattr(self.source, "std_max", 0.0)) if self.has_distribution else 0.0

    @property
    def has_cell_ranges(self) -> bool:
        """Whether the store keeps the level-0 value range of every cell (format >= 3)."""
        return self.has_levels and getattr(self.source, "format_version", 0) >= 3

    def half_cell_ranges(self, kept: "weakref.WeakKeyDictionary[Any, Any] | None" = None
                         ) -> tuple[np.ndarray, np.ndarray] | None:
        """(min, max) of the level-0 values of every half-block cell (grid 2G, C order, the atlas walk's cells),
        from the store's cell ranges (store.layout.cell_edge); NaN where a cell holds no valid voxel. None when the
        store keeps none (format < 3) or blocks have no halves (B = 1). `kept`: per store, what was computed
        before (an engine's `tables.half_cells`: a turntable asks each frame)."""
        if not self.has_cell_ranges or self.block_size < 2:
            return None
        hit = None if kept is None else kept.get(self.source)
        if hit is not None:
            return hit
        ranges = self.source.cell_ranges
        half, c = self.block_size // 2, cell_edge(self.block_size)
        g2 = tuple(2 * g for g in self.grid)
        out = []
        for a, reduce in ((ranges[0], np.fmin.reduce), (ranges[1], np.fmax.reduce)):
            if half >= c:  # several cells per half-cell (B = 32: 2³)
                f = half // c
                a = np.pad(a, [(0, g * f - n) for g, n in zip(g2, a.shape)], constant_values=np.nan)
                a = reduce(a.reshape(g2[0], f, g2[1], f, g2[2], f), axis=(1, 3, 5))
            else:  # a cell per block (B < 8): each half-cell takes its block's
                for ax in range(3):
                    a = np.repeat(a, c // half, axis=ax)
                a = np.pad(a, [(0, max(0, g - n)) for g, n in zip(g2, a.shape)], constant_values=np.nan)[
                    : g2[0], : g2[1], : g2[2]]
            out.append(np.ascontiguousarray(a, np.float32))
        if kept is not None:
            kept[self.source] = (out[0], out[1])
        return out[0], out[1]

    @property
    def std_unit(self) -> float:
        """The unit in which the device holds standard deviations, as uint16: std_max / 65535. Linear, so that the
        kernel interpolates the integers and scales once (decoding eight float16 per coarse sample took a good part
        of an interblock sample's time); the absolute step std_max / 65535 is 16 times finer than the first
        row of the classification table above zero (std_max / 63²), whatever the data's unit."""
        return self.std_max / 65535.0 if self.std_max > 0 else 1.0

    def read_chunks(self, level: int, chunks: Any, std: bool = False) -> np.ndarray:
        """The store's inner chunks `chunks` (n, 3) of level `level`, all in one shard, as one (n, *chunk) array
        padded past the level's end as a brick is (std: the standard deviations behind them): the brick loader's
        only read."""
        if not self.has_levels:
            raise ValueError("level-of-detail rendering needs a lodcast store (an array has no coarser levels)")
        return self.source.read_chunks(level, chunks, std)


def block_minmax_border(a: np.ndarray, B: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-block (min, max) over each B³ block plus a one-voxel border from its neighbours, ignoring NaN
    (NaN where a block and its border hold no finite value). A box's extremum is separable, so it is taken one
    axis at a time, each reduction shrinking the array B-fold: no copy of the volume, no loop over blocks."""
    grid = tuple(max(1, math.ceil(s / B)) for s in a.shape)
    if a.size == 0:
        return np.full(grid, np.nan), np.full(grid, np.nan)
    out = []
    for fn in (np.fmin, np.fmax):
        r = a
        for axis in (2, 1, 0):
            r = _axis_window(r, B, axis, fn)
        out.append(r.astype(np.float64))
    return out[0], out[1]


def _axis_window(a: np.ndarray, B: int, axis: int, fn: np.ufunc) -> np.ndarray:
    """fn (np.fmin / np.fmax) along `axis` over each block's window [b·B − 1, (b + 1)·B + 1)."""
    a = np.moveaxis(a, axis, -1)
    n = a.shape[-1]
    g, full = math.ceil(n / B), n // B
    parts = []
    if full:
        parts.append(fn.reduce(a[..., : full * B].reshape(*a.shape[:-1], full, B), axis=-1))
    if full < g:
        parts.append(fn.reduce(a[..., full * B :], axis=-1)[..., None])
    r = np.concatenate(parts, axis=-1) if len(parts) > 1 else parts[0]
    if g > 1:
        r[..., 1:] = fn(r[..., 1:], a[..., B - 1 : (g - 1) * B : B])  # the previous block's last voxel
        r[..., :-1] = fn(r[..., :-1], a[..., B : g * B : B])  # the next block's first voxel
    return np.moveaxis(r, -1, axis)


def _from_array(a: np.ndarray, spacing: Any = None, origin: Any = None, block_size: int = 16) -> VolumeView:
    a = np.asarray(a)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3:
        raise ValueError(f"a volume must be a 3D array (z, y, x), got shape {a.shape}")
    mn, mx = block_minmax_border(a, block_size)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        lo, hi = float(np.nanmin(a)) if a.size else 0.0, float(np.nanmax(a)) if a.size else 0.0
    if not (math.isfinite(lo) and math.isfinite(hi)):
        lo, hi = 0.0, 0.0
    return VolumeView(
        shape=tuple(int(s) for s in a.shape),  # type: ignore[arg-type]
        spacing=tuple(float(s) for s in (spacing or (1.0, 1.0, 1.0))),  # type: ignore[arg-type]
        origin=tuple(float(s) for s in (origin or (0.0, 0.0, 0.0))),  # type: ignore[arg-type]
        block_size=block_size,
        value_range=(lo, hi),
        min_border=mn,
        max_border=mx,
        key=None,
        _read0=lambda dtype=None: a,
        source=a,
    )


def level_view(vol: VolumeView, k: int) -> VolumeView:
    """Level k of a store's volume as a volume of its own, in the store's world: a level-k voxel is the mean of the
    2^k × 2^k × 2^k level-0 voxels from 2^k times its index, so its centre lies (2^k − 1)/2 level-0 voxels past
    theirs, and it spans 2^k of them; framed and integrated within the store's own box (`frame_box`). A progressive
    render's first look at a large store (renderer/frame/progressive.py): one read of a small array, no selection
    and no bricks."""
    assert vol.has_levels, "only a lodcast store has coarse levels"
    from lodcast.renderer.scene.camera import box_world

    f = float(1 << k)
    spacing = tuple(s * f for s in vol.spacing)
    origin = tuple(o + (f - 1.0) / 2.0 * s for o, s in zip(vol.origin, vol.spacing))
    out = _from_array(vol.read_level(k), spacing, origin, int(vol.block_size))
    out.key = None if vol.key is None else ("level", vol.key, k)
    out.frame_box = box_world(vol.shape, vol.spacing, vol.origin)
    return out


def _from_store(s: Any) -> VolumeView:
    st = s.stats
    path = getattr(s, "location", None) or getattr(s, "path", None)
    return VolumeView(
        shape=tuple(int(v) for v in s.shape),  # type: ignore[arg-type]
        spacing=tuple(float(v) for v in s.spacing),  # type: ignore[arg-type]
        origin=tuple(float(v) for v in s.origin),  # type: ignore[arg-type]
        block_size=int(s.block_size),
        value_range=(float(s.value_range[0]), float(s.value_range[1])),
        min_border=np.asarray(st.min_border, dtype=np.float64),
        max_border=np.asarray(st.max_border, dtype=np.float64),
        key=("store", str(path), _stamp(path), getattr(s, "generation", None)) if path is not None else None,
        _read0=lambda dtype=None: s.read_region(0, ..., dtype),
        source=s,
    )


def _stamp(path: Any) -> Any:
    """Changes when a store is replaced at the same path (ingest writes a new folder and renames it)."""
    try:
        st = Path(str(path)).stat()
        return (st.st_ino, st.st_mtime_ns)
    except OSError:
        return None


#: What the verbs take as a volume (`lodcast.render`, `Renderer.render`, ...): an opened lodcast store, a store's
#: path or URL, a 3D NumPy array (z, y, x; with optional spacing and origin), or a VolumeView
StoreLike: TypeAlias = Store | str | os.PathLike[str] | np.ndarray | VolumeView


def as_volume(obj: StoreLike, *, spacing: Any = None, origin: Any = None, stores: Any = None) -> VolumeView:
    """A VolumeView of a store, a store path or URL, a VolumeView or a 3D NumPy array (spacing/origin for arrays).
    A path is opened through `stores` (an OpenStores, e.g. an engine's: opened once for a series of renders), else
    afresh."""
    if isinstance(obj, VolumeView):
        return obj
    if isinstance(obj, np.ndarray):
        return _from_array(obj, spacing, origin)
    if isinstance(obj, (str, os.PathLike)):
        from lodcast.store.store import open_store

        return _from_store(open_store(obj) if stores is None else stores.get(obj))
    if hasattr(obj, "read_level") and hasattr(obj, "stats"):
        return _from_store(obj)
    raise TypeError(f"cannot render a {type(obj).__name__}: pass a lodcast store, a store path or a 3D array")
