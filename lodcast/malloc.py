"""The C allocator of the process (glibc's malloc, where there is one): what a Python process that moves
gigabytes of arrays through many threads needs from it. Elsewhere both functions do nothing."""
from __future__ import annotations

import ctypes

__all__ = ["tame_malloc", "release_free_memory"]


def _libc() -> "ctypes.CDLL | None":
    """glibc, where there is one (dlopen hands out the same loaded library each time)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return None
    return libc if hasattr(libc, "malloc_trim") and hasattr(libc, "mallopt") else None  # glibc only


def tame_malloc() -> None:
    """For processes that ingest (the CLI, the service's workers; `ingest()` leaves the host process's allocator
    alone): ingest allocates and frees slab-sized arrays on several threads. glibc then grows per-thread arenas and
    raises its mmap threshold, so freed slabs stay resident far beyond the live arrays. A fixed threshold returns
    every large array to the OS; at 16 MiB rather than 1 MiB, row-of-blocks temporaries stay on the heap, which
    costs system time less for about the same peak (docs/measurements/code-notes.md)."""
    libc = _libc()
    if libc is not None:
        libc.mallopt(-3, 16 << 20)  # M_MMAP_THRESHOLD (fixing it also turns off the dynamic adjustment)
        libc.mallopt(-8, 2)  # M_ARENA_MAX


def release_free_memory() -> None:
    """Return the free pages inside the allocator's heaps to the OS (malloc_trim). Bricks are small arrays made
    and dropped by many reading threads, each with its heap: freed, they stay resident until trimmed. Called
    after each pass of a render in several (renderer/data/passes.py), whose data is the size of the device budget:
    on the 8 GiB volume the process kept 2.0 GB resident after a full-resolution render of 32 passes."""
    libc = _libc()
    if libc is not None:
        libc.malloc_trim(0)
