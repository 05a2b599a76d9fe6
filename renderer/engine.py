"""The engine's state: one object owns the OpenCL device, every cache a render keeps and the settings it reads.

`Engine` is what the stages below the frame take (the public `lodcast.Renderer`, renderer/frame/render.py, is one with
the verbs added). Nothing a render keeps between calls lives at module level: two engines in one process share no
buffer, brick, table or opened store, and dropping one frees what it held. The environment (`LODCAST_*`) is read
once, when the engine is made; its keywords override the variables.
"""
from __future__ import annotations

import contextlib
import hashlib
import os
import threading
import weakref
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Iterator

import numpy as np

from lodcast.environment import Environment, EnvironmentInvalid, environment
from lodcast.opencl import Device
from lodcast.renderer.cache import ByteLru, Spares
from lodcast.renderer.pool import BrickPool
from lodcast.store.opened import OpenStores

__all__ = ["Engine", "Settings", "Tables"]


@dataclass(frozen=True)
class Settings:
    """What an engine reads of its environment, once (lodcast/environment.py documents each variable)."""

    device: str  # LODCAST_DEVICE: "gpu", "cpu", part of a device name, or "" for the first GPU, else CPU
    device_budget_bytes: int | None  # LODCAST_DEVICE_BUDGET_MB; None: one allocation
    brick_cache_bytes: int  # LODCAST_BRICK_CACHE_MB
    device_cache_bytes: int  # LODCAST_DEVICE_CACHE_MB
    open_stores: int  # LODCAST_OPEN_STORES
    store_check_s: float  # not a variable: the service's setting (service/settings.py); 0 elsewhere
    max_samples: int  # LODCAST_MAX_SAMPLES
    lossless_zeta: float  # LODCAST_LOSSLESS_ZETA
    significance_numpy: bool  # LODCAST_SIGNIFICANCE_NUMPY
    read_threads: int | None  # LODCAST_READ_THREADS; None: by the CPU count (local) or 8 (object storage)

    @classmethod
    def of(cls, env: Environment, *, device: str | None = None, device_budget_mb: float | None = None,
           brick_cache_mb: float | None = None, device_cache_mb: float | None = None,
           open_stores: int | None = None, store_check_s: float = 0.0) -> "Settings":
        """`env` with the keywords that are given in its place (MB = 10⁶ bytes for the budget, MiB for the
        caches, as the variables)."""
        return cls(
            device=env.device if device is None else str(device).strip().lower(),
            device_budget_bytes=env.device_budget_bytes if device_budget_mb is None
            else int(_positive("device_budget_mb", device_budget_mb) * 1e6),
            brick_cache_bytes=env.brick_cache_bytes if brick_cache_mb is None
            else int(_positive("brick_cache_mb", brick_cache_mb, zero=True) * 2**20),
            device_cache_bytes=env.device_cache_bytes if device_cache_mb is None
            else int(_positive("device_cache_mb", device_cache_mb, zero=True) * 2**20),
            open_stores=env.open_stores if open_stores is None else _at_least_one("open_stores", open_stores),
            store_check_s=_positive("store_check_s", store_check_s, zero=True, unit="seconds"),
            max_samples=env.max_samples,
            lossless_zeta=env.lossless_zeta,
            significance_numpy=env.significance_numpy,
            read_threads=env.read_threads,
        )

    @property
    def device_cache_bound(self) -> int:
        """The device cache's bound: its own size, and never more than the budget."""
        b = self.device_budget_bytes
        return self.device_cache_bytes if b is None else min(self.device_cache_bytes, b)


def _positive(name: str, value: float, zero: bool = False, unit: str = "megabytes") -> float:
    v = float(value)
    if not (v == v and v != float("inf") and (v >= 0 if zero else v > 0)):
        raise EnvironmentInvalid(f"{name}: must be a {'non-negative' if zero else 'positive'} number of {unit}, "
                                 f"got {value!r}")
    return v


def _at_least_one(name: str, value: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise EnvironmentInvalid(f"{name}: must be a whole number of at least 1, got {value!r}")
    return value


class Tables:
    """What is computed from a store and transfer functions alone, not from the view, kept for the recent ones: a
    turntable or a camera sweep computes each once. Stores are held weakly (an entry goes with its store).
    `device`: where the per-block TF errors are computed (level_error.block_zetas; None: with NumPy on the host)."""

    def __init__(self, device: Device | None = None) -> None:
        self.device = device
        self.meta: weakref.WeakKeyDictionary[Any, Any] = weakref.WeakKeyDictionary()  # store -> BlockMeta
        self.pre: weakref.WeakKeyDictionary[Any, Any] = weakref.WeakKeyDictionary()  # BlockMeta -> its TF-free part
        self.half_cells: weakref.WeakKeyDictionary[Any, Any] = weakref.WeakKeyDictionary()  # store -> 8³ ranges
        self.tf = ByteLru(256 << 20)  # (store metadata, TF, classification) -> per-block ζ tables
        self.dist = ByteLru(32)  # (TF, value range, std_max) -> distribution table, one unit each
        self.luv = ByteLru(32)  # distribution table -> its unit-slab colours in CIELUV
        self.preint = ByteLru(16)  # (TF, value range, step ratio, n) -> pre-integration table
        self.peaks = ByteLru(64)  # store key -> the adaptive TFs' tissue peaks
        self.levels = ByteLru(256 << 20)  # (store key, level) -> that level as a volume (progressive previews)


class Engine:
    """The OpenCL device, the caches and the settings of one renderer (module docstring).

    Caches, each an LRU bounded by bytes or entries:
    - `bricks`: the pool of bricks read from stores, of every level and quality (renderer/pool.py); on a device whose buffers are host memory it gives
      way to what the device cache and the buffers being filled hold, down to an eighth of its size;
    - `device_cache`: level-0 volumes, atlases and coarse levels on the device; `spares`: in the room it leaves,
      the buffers of atlases no render holds any more, which the next atlas of about their size takes instead of
      new memory (renderer/data/atlas.py);
    - `targets`, `cost_model`: what quality targets choose by (renderer/frame/target.py);
    - `selections`, `step_errors`, `steps`, `block_infos`, `lod_plans`: level-of-detail selections, predicted step
      errors, adaptive step levels, the blocks' walk info of recent scenes and, per selection, that info with its
      unloaded blocks marked; `digests`: the digests of read-only grids (`digest`); `walks`, `adaptive_walks`,
      `parents`, `cells`, `cell_infos`: what the walks need (walk.py, atlas_cells.py); `last_atlas`: per atlas family
      the newest atlas, held weakly (atlas.py reuses its bricks);
    - `tables`: what is derived from a store and TFs (`Tables`); `stores`: stores named by path or URL, opened once,
      at most `open_stores` of them (LODCAST_OPEN_STORES), least recently used closed first. `store_check_s`: how
      long a store on object storage is trusted, once opened, before it is asked whether it was replaced (the
      service's setting; 0, every time, elsewhere).
    """

    def __init__(self, *, device: str | None = None, device_budget_mb: float | None = None,
                 brick_cache_mb: float | None = None, device_cache_mb: float | None = None,
                 open_stores: int | None = None, store_check_s: float = 0.0) -> None:
        env = environment()
        self.settings = Settings.of(env, device=device, device_budget_mb=device_budget_mb,
                                    brick_cache_mb=brick_cache_mb, device_cache_mb=device_cache_mb,
                                    open_stores=open_stores, store_check_s=store_check_s)
        self.device = Device(self.settings.device, env.cache_dir / "kernels")
        self.device_cache = ByteLru(self.settings.device_cache_bound, keep_last=True)
        self.spares = Spares(lambda: max(0, self.settings.device_cache_bound - self.device_cache.nbytes))
        self.bricks = BrickPool(self._brick_bound)
        self.selections = ByteLru(4)  # one unit each: (store, TFs, quality, classification, crop, view)
        self.step_errors = ByteLru(8)  # one unit each: (store, TFs, step, crop)
        self.block_infos = ByteLru(64 << 20, keep_last=True)  # (store, TFs, mode) -> the blocks' walk info
        # the newest walk stays whatever its size: a large volume's walk alone may pass the bound, and computing
        # it again every frame of a turntable costs several times the kernel
        self.steps = ByteLru(64 << 20, keep_last=True)
        self.lod_plans = ByteLru(64 << 20, keep_last=True)
        self.digests = ByteLru(16)  # one unit each: id of a read-only array -> (the array, its digest)
        self.walks = ByteLru(64 << 20, keep_last=True)
        self.adaptive_walks = ByteLru(32 << 20, keep_last=True)
        self.parents = ByteLru(64 << 20, keep_last=True)
        self.cells = ByteLru(256 << 20, keep_last=True)
        # per scene family the newest atlas walk info, whose cells the next selection's classifies again only where
        # they changed (walk/info.py: atlas_cell_info)
        self.cell_infos = ByteLru(64 << 20, keep_last=True)
        self.tables = Tables(self.device)
        # quality targets (renderer/frame/target.py): per store and TFs the data settings' predictions and the share
        # of a march the rays take; the device's cost model, measured on first use (kept on disk in `cost_dir`)
        self.targets = ByteLru(16)
        self.cost_model: Any = None  # renderer/frame/device_cost.CostModel (imported there: no import loop)
        self.cost_dir = env.cache_dir / "cost"
        self.target_lock = threading.Lock()
        self.stores = OpenStores(self.settings.open_stores, self.settings.store_check_s)
        self._last_atlas: dict[tuple, weakref.ref[Any]] = {}
        self._lock = threading.Lock()
        self._filling = 0  # bytes of device buffers being filled or used outside the device cache right now
        self._pools: dict[int, ThreadPoolExecutor] = {}

    def __repr__(self) -> str:
        s = self.settings
        return (f"{type(self).__name__}(device={s.device or 'default'!r}, device_budget_mb="
                f"{None if s.device_budget_bytes is None else s.device_budget_bytes / 1e6}, "
                f"brick_cache_mb={s.brick_cache_bytes / 2**20:g}, device_cache_mb={s.device_cache_bytes / 2**20:g})")

    def digest(self, a: np.ndarray) -> bytes:
        """A digest of `a`'s bytes for cache keys, kept per array while `a` is read-only: a turntable keys its
        walk, step levels and atlas on the same grids every frame, and hashing a large volume's grids again each
        time was a good part of its frames' host work. (The entry holds `a`, so its id stays its own.)"""
        if a.flags.writeable:
            return _digest(a)
        hit = self.digests.get(id(a))
        if hit is not None and hit[0] is a:
            return hit[1]
        d = _digest(a)
        self.digests.put(id(a), (a, d), 1)
        return d

    def _brick_bound(self) -> int:
        cap = self.settings.brick_cache_bytes
        if not self.device.memory_is_host:
            return cap
        return max(cap // 8, cap - self.device_cache.nbytes - self.spares.nbytes - self._filling)

    @contextlib.contextmanager
    def holding(self, nbytes: int) -> Iterator[None]:
        """While in this context, `nbytes` of device buffers outside the device cache are alive (an atlas being
        filled, a pass's volume data): on a device whose buffers are host memory the brick cache gives way."""
        with self._lock:
            self._filling += nbytes
        try:
            yield
        finally:
            with self._lock:
                self._filling -= nbytes

    def read_threads(self, remote: bool, caller_waits: bool = False) -> int:
        """Threads reading shards: LODCAST_READ_THREADS, else one less than the CPU count for local files (at
        least one: the calling thread places what they read), one more than the CPU count where the readers place
        what they read themselves and the caller only waits (`caller_waits`: a reader waiting on the disk leaves its
        core to the spare one), and 8 for object storage (requests wait on the network)."""
        n = self.settings.read_threads
        if n is not None:
            return n
        if remote:
            return 8
        cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        return cpus + 1 if caller_waits else max(1, cpus - 1)

    def read_pool(self, threads: int) -> ThreadPoolExecutor:
        """The engine's pool of `threads` shard readers (made on first use)."""
        with self._lock:
            pool = self._pools.get(threads)
            if pool is None:
                pool = self._pools[threads] = ThreadPoolExecutor(threads, thread_name_prefix="lodcast-bricks")
            return pool

    def remember_atlas(self, family: tuple, atlas: Any) -> None:
        """Make `atlas` the one the next selection of `family` (store key, grid, with deviations, voxel type)
        starts from. Held weakly: it lives as long as the device cache (or a caller) holds it, so reuse never
        keeps device memory alive by itself."""
        with self._lock:
            self._last_atlas[family] = weakref.ref(atlas)

    def last_atlas(self, family: tuple) -> Any:
        """The newest atlas of `family` still alive, or None."""
        with self._lock:
            ref = self._last_atlas.get(family)
        return None if ref is None else ref()

    def forget_atlases(self) -> None:
        """Build the next atlas of every family from nothing (atlas.py reuses the last one's bricks otherwise)."""
        with self._lock:
            self._last_atlas.clear()

    def clear_passes(self) -> None:
        """Drop what a render in passes cannot keep: the device cache's buffers and what was kept beside them
        (the walks and cells of their selections)."""
        self.device_cache.clear()
        self.spares.clear()
        self.walks.clear()
        self.adaptive_walks.clear()
        self.cells.clear()
        self.cell_infos.clear()

    def close(self) -> None:
        """Let the reader threads go and drop every cache (the engine stays usable: they fill again)."""
        with self._lock:
            pools, self._pools = self._pools, {}
        for pool in pools.values():
            pool.shutdown(wait=False)
        for c in (self.device_cache, self.spares, self.bricks, self.selections, self.step_errors, self.block_infos, self.steps,
                  self.lod_plans, self.digests, self.walks, self.adaptive_walks, self.parents, self.cells,
                  self.cell_infos, self.targets):
            c.clear()
        self.tables = Tables(self.device)
        self.forget_atlases()


def _digest(a: np.ndarray) -> bytes:
    return hashlib.blake2b(np.ascontiguousarray(a).tobytes(), digest_size=16).digest()
