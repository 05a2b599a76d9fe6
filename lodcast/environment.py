"""The store's and the renderer's environment variables, in one place (the service's own are `service.Settings`).

``environment()`` reads them when called, never at import time; a renderer (lodcast.Renderer) reads them once,
when it is made, and its keywords override them; a malformed value is an `EnvironmentInvalid` naming the variable and what it
expects, never a silent default. Every variable here is in the README's table (a test keeps the two together).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

from lodcast.errors import LodcastError

__all__ = ["Environment", "EnvironmentInvalid", "environment", "VARIABLES"]


class EnvironmentInvalid(LodcastError, ValueError):
    """An environment variable has a value lodcast cannot use; the message names it and what it expects."""


@dataclass(frozen=True)
class Environment:
    """What the variables say, in bytes and counts (None: unset, no limit)."""

    brick_cache_bytes: int  # LODCAST_BRICK_CACHE_MB (MiB)
    device_cache_bytes: int  # LODCAST_DEVICE_CACHE_MB (MiB)
    open_stores: int  # LODCAST_OPEN_STORES
    device_budget_bytes: int | None  # LODCAST_DEVICE_BUDGET_MB (MB = 10⁶ bytes, docs/design.md Limits)
    read_threads: int | None  # LODCAST_READ_THREADS; None: the engine decides (renderer/engine.py: read_threads)
    max_samples: int  # LODCAST_MAX_SAMPLES
    max_voxels: int | None  # LODCAST_MAX_VOXELS
    max_ingest_bytes: int | None  # LODCAST_MAX_INGEST_MEMORY_MB (MB = 10⁶ bytes)
    lossless_zeta: float  # LODCAST_LOSSLESS_ZETA
    significance_numpy: bool  # LODCAST_SIGNIFICANCE_NUMPY
    device: str  # LODCAST_DEVICE
    cache_dir: Path  # LODCAST_CACHE_DIR, else LODCAST_CACHE, else the user's cache folder
    tmp: str | None  # LODCAST_TMP


#: name, default as the README gives it, what it sets
VARIABLES: tuple[tuple[str, str, str], ...] = (
    ("LODCAST_BRICK_CACHE_MB", "1024", "host cache of bricks read from stores (MiB; on a CPU device, whose buffers "
     "are host memory, less what the device cache holds, down to an eighth)"),
    ("LODCAST_DEVICE_CACHE_MB", "1024", "device cache of level-0 volumes and atlases (MiB; also bounded by the budget)"),
    ("LODCAST_OPEN_STORES", "32", "stores a renderer (and so the service) keeps opened, least recently used closed "
     "first; one closed is opened again when next asked for, and the bricks cached from it serve on"),
    ("LODCAST_DEVICE_BUDGET_MB", "one allocation", "most device memory (10⁶ bytes) of one render's volume data"),
    ("LODCAST_READ_THREADS", "the CPU count less one (at least 1); 8 on object storage", "threads reading shards "
     "(local files: decoding is the work, the calling thread places what they read, and threads beyond the cores "
     "only contend; object storage: requests wait on the network)"),
    ("LODCAST_MAX_SAMPLES", "2·10⁹", "most samples one render may take, estimated before it starts"),
    ("LODCAST_MAX_VOXELS", "no limit", "largest volume ingest accepts (voxels of the whole blocks it would store), "
                                       "checked from the source's header"),
    ("LODCAST_MAX_INGEST_MEMORY_MB", "no limit", "most memory (10⁶ bytes) ingest may plan for, checked on the "
                                                 "source's declared shape"),
    ("LODCAST_LOSSLESS_ZETA", "0.5", "ΔE per block that `quality: \"lossless\"` allows"),
    ("LODCAST_SIGNIFICANCE_NUMPY", "off", "1: the LOD significance in NumPy rather than SciPy's sparse product"),
    ("LODCAST_DEVICE", "first GPU, else CPU", "`gpu`, `cpu` or part of an OpenCL device name"),
    ("LODCAST_CACHE_DIR", "user cache folder", "built kernels (`…/kernels`)"),
    ("LODCAST_TMP", "the system's", "where ingest to object storage writes the store before uploading it"),
)


def _number(name: str, default: float, *, positive: bool = True, optional: bool = False) -> float | None:
    raw = os.environ.get(name, "").strip()
    if not raw:
        return None if optional else default
    try:
        value = float(raw)
    except ValueError:
        raise EnvironmentInvalid(f"{name}: {raw!r} is not a number") from None
    if not math.isfinite(value) or (value <= 0 if positive else value < 0):
        raise EnvironmentInvalid(f"{name}: must be a {'positive' if positive else 'non-negative'} number, got {raw!r}")
    return value


def _count(name: str, default: float, optional: bool = False) -> int | None:
    value = _number(name, default, optional=optional)
    if value is None:
        return None
    if value < 1 or (value != int(value) and value < 1e6):  # "2e9" is a count; "1.5" threads is not
        raise EnvironmentInvalid(f"{name}: must be a whole number of at least 1, got {os.environ.get(name)!r}")
    return int(value)


def _cache_dir() -> Path:
    explicit = os.environ.get("LODCAST_CACHE_DIR") or os.environ.get("LODCAST_CACHE")
    if explicit:
        return Path(explicit).expanduser()
    import platformdirs

    return Path(platformdirs.user_cache_dir("lodcast"))


def environment() -> Environment:
    """The variables as they are now (cheap: a few dictionary lookups)."""
    budget = _number("LODCAST_DEVICE_BUDGET_MB", 0, optional=True)
    ingest_mb = _number("LODCAST_MAX_INGEST_MEMORY_MB", 0, optional=True)
    return Environment(
        brick_cache_bytes=int(_number("LODCAST_BRICK_CACHE_MB", 1024, positive=False) * 2**20),  # type: ignore[operator]
        device_cache_bytes=int(_number("LODCAST_DEVICE_CACHE_MB", 1024, positive=False) * 2**20),  # type: ignore[operator]
        open_stores=_count("LODCAST_OPEN_STORES", 32),  # type: ignore[arg-type]
        device_budget_bytes=None if budget is None else int(budget * 1e6),
        read_threads=_count("LODCAST_READ_THREADS", 0, optional=True),
        max_samples=_count("LODCAST_MAX_SAMPLES", 2e9),  # type: ignore[arg-type]
        max_voxels=_count("LODCAST_MAX_VOXELS", 0, optional=True),
        max_ingest_bytes=None if ingest_mb is None else int(ingest_mb * 1e6),
        lossless_zeta=float(_number("LODCAST_LOSSLESS_ZETA", 0.5, positive=False)),  # type: ignore[arg-type]
        significance_numpy=os.environ.get("LODCAST_SIGNIFICANCE_NUMPY", "").strip().lower() not in ("", "0", "false", "no"),
        device=os.environ.get("LODCAST_DEVICE", "").strip().lower(),
        cache_dir=_cache_dir(),
        tmp=os.environ.get("LODCAST_TMP") or None,
    )
