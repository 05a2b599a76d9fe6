"""OpenCL devices and the programs built on them, below both the store (its histogram segmentation kernel) and the
renderer, so that neither imports the other for it.

A `Device` is a context on one OpenCL device, opened on first use, with an in-order profiling queue per thread and
the programs built on it: a render waits (clFinish) only for its own commands, never for another render's kernels
queued before them, so a small render is not served behind big ones on the device. Programs are built from `.cl` files (the renderer's folder by default, or the caller's; our own
`#include "..."` lines are resolved here, so no include path reaches the OpenCL compiler) and the `-D` options of
a KernelConfig, and cached by sha256(source, options, platform, device, driver): in the Device for its lifetime
and on disk under the user cache directory (see `cache_dir`) as device binaries, so that a second process skips
the compiler. Every `program` says where the program came from and, when it was built, how long that took.
Nothing here is shared between Devices but the disk cache, whose files are written atomically.
"""
from __future__ import annotations

import functools
import hashlib
import importlib.util
import logging
import os
import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyopencl as cl

from lodcast.environment import environment
from lodcast.errors import LodcastError

__all__ = ["Device", "DeviceError", "Built", "kernel_source", "cache_dir", "renderer_folder", "BUILD_LOG",
           "SLOW_BUILD_S"]

_INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)"\s*$', re.M)
_PROBE = "__kernel void lc_ok(__global int* a) { a[0] = 1; }"


#: a compile that runs longer than this (seconds) says what it builds, once per Device, at INFO on BUILD_LOG
SLOW_BUILD_S = 1.0
#: where it says so: quiet unless INFO is shown (the `lodcast` command shows it on stderr; libraries stay quiet)
BUILD_LOG = logging.getLogger("lodcast.opencl.build")


def _announce_after(name: str, options: tuple[str, ...], device: str,
                    announced: threading.Event) -> threading.Timer | None:
    """Say what is being built once SLOW_BUILD_S have passed (at once when it is 0 or less), unless `announced`
    (the Device's) says it was said already or no one would see it; the timer to cancel when the build ends."""
    if announced.is_set() or not BUILD_LOG.isEnabledFor(logging.INFO):
        return None
    flags = " for this scene's options" if options else ""
    what = f"building the OpenCL kernel {name}{flags} on {device} (first use; cached afterwards)…"

    def say() -> None:
        if announced.is_set():
            return
        announced.set()
        BUILD_LOG.info(what)

    if SLOW_BUILD_S <= 0:
        say()
        return None
    timer = threading.Timer(SLOW_BUILD_S, say)
    timer.daemon = True
    timer.start()
    return timer


class DeviceError(LodcastError, RuntimeError):
    """No usable OpenCL device, or the volume does not fit on it."""


@dataclass(frozen=True)
class Built:
    program: cl.Program
    key: str
    source: str  # "memory" | "disk" | "built"
    build_ms: float  # compile (or binary load) time in this call; 0 for memory hits


def renderer_folder() -> Path:
    """Where the renderer's `.cl` files are (renderer/kernel/, found without importing the renderer: this module
    lies below it)."""
    spec = importlib.util.find_spec("lodcast.renderer.kernel")
    assert spec is not None and spec.submodule_search_locations, "lodcast.renderer.kernel is part of the package"
    return Path(list(spec.submodule_search_locations)[0]).resolve()


def cache_dir() -> Path:
    """``$LODCAST_CACHE_DIR/kernels``, else ``$LODCAST_CACHE/kernels`` (the variable the demo's downloads use),
    else the platform's user cache directory for lodcast."""
    return environment().cache_dir / "kernels"


def kernel_source(name: str, folder: Path | None = None) -> str:
    """The text of `name` (a .cl file of the renderer, or in `folder`) with our own quoted #includes inlined, once
    each."""
    return _expand(name, folder or renderer_folder())[1]


def _expand(name: str, base: Path) -> tuple[tuple[tuple[Path, int, int], ...], str]:
    """The files read, with their stamps taken before reading (a change in between is seen next time), and the
    expanded text."""
    seen: dict[Path, tuple[Path, int, int]] = {}

    def expand(fname: str) -> str:
        path = base / fname
        if path in seen:
            return ""
        seen[path] = _stamp(path)
        return _INCLUDE.sub(lambda m: expand(m.group(1)), path.read_text())

    src = expand(name)
    return tuple(seen.values()), src


def _stamp(path: Path) -> tuple[Path, int, int]:
    try:
        st = path.stat()
    except OSError:
        return path, -1, -1
    return path, st.st_mtime_ns, st.st_size


def _key(src: str, options: tuple[str, ...], dev: cl.Device) -> str:
    h = hashlib.sha256()
    for part in (src, "\0".join(options), dev.platform.name, dev.platform.version, dev.name, dev.driver_version,
                 dev.version, cl.VERSION_TEXT):
        h.update(part.encode())
        h.update(b"\x01")
    return h.hexdigest()


class Device:
    """One OpenCL context, opened on first use, a profiling queue per thread, and the programs built on it.

    `want`: "gpu", "cpu" or a substring of the device name (default ``$LODCAST_DEVICE`` as it is when the Device
    is made), else the first GPU, else the first CPU; a device whose compiler cannot build a trivial kernel is
    passed over for the next one (PoCL's LLVM 14, bundled with pyopencl's wheels, rejects CPUs it does not know,
    e.g. AMD Zen 5: "unknown target CPU 'generic'"; Debian's pocl-opencl-icd builds there). `kernels`: the folder
    of built binaries (default `cache_dir()`).

    The OpenCL ICD loader bundled with pyopencl's wheels sees only its own PoCL unless OCL_ICD_VENDORS says
    otherwise: when unset, the system's vendor folder /etc/OpenCL/vendors is added, so GPU drivers and a system
    PoCL are found too."""

    def __init__(self, want: str | None = None, kernels: Path | None = None) -> None:
        self.want = (environment().device if want is None else want).strip().lower()
        self.kernels = cache_dir() if kernels is None else Path(kernels)
        self._lock = threading.RLock()
        self._opened: cl.Context | None = None
        self._programs: dict[str, cl.Program] = {}
        # a render asks for its program every time: the expanded source per (file, folder), valid while every
        # file it was read from keeps its modification time and size, and its cache key per (source, options),
        # which hashes the whole expanded source
        self._sources: dict[tuple[str, Path], tuple[tuple[tuple[Path, int, int], ...], str]] = {}
        self._keys: dict[tuple, tuple[str, str]] = {}
        self._thread = threading.local()
        self._announced = threading.Event()  # a slow build was announced (once per Device: a CLI process has one)

    def __repr__(self) -> str:
        return f"Device({self.want or 'default'!r}, {'open' if self._opened else 'not opened'})"

    @property
    def context(self) -> cl.Context:
        return self._open()

    @property
    def queue(self) -> cl.CommandQueue:
        """The calling thread's queue. Every render runs on one thread and finishes its own commands before it hands
        a buffer to others (an atlas in the device cache), so queues need no events between them."""
        q = self._thread.__dict__.get("queue")
        if q is None:
            q = self._thread.queue = cl.CommandQueue(self._open(),
                                                     properties=cl.command_queue_properties.PROFILING_ENABLE)
        return q

    @property
    def cl_device(self) -> cl.Device:
        return self._open().devices[0]

    def _open(self) -> cl.Context:
        opened = self._opened
        if opened is not None:
            return opened
        with self._lock:
            if self._opened is None:
                self._opened = self._choose()
            return self._opened

    def _choose(self) -> cl.Context:
        if "OCL_ICD_VENDORS" not in os.environ and os.path.isdir("/etc/OpenCL/vendors"):
            os.environ["OCL_ICD_VENDORS"] = "/etc/OpenCL/vendors"
        devices = []
        try:
            for p in cl.get_platforms():
                devices += [(p, d) for d in p.get_devices()]
        except cl.Error as exc:
            raise DeviceError(f"no OpenCL platform available: {exc}") from None
        if not devices:
            raise DeviceError("no OpenCL device available (install pocl-binary-distribution for the CPU)")
        want = self.want

        def rank(pd: tuple[Any, cl.Device]) -> tuple[bool, bool]:
            _, d = pd
            if want in ("gpu", "cpu"):
                match = bool(d.type & (cl.device_type.GPU if want == "gpu" else cl.device_type.CPU))
            else:
                match = bool(want) and want in d.name.lower()
            return (not match, not (d.type & cl.device_type.GPU))

        failures = []
        for _, dev in sorted(devices, key=rank):
            ctx = cl.Context([dev])
            try:
                cl.Program(ctx, _PROBE).build()
            except cl.Error as exc:
                failures.append(f"{dev.name.strip()} ({dev.platform.version.strip()}): "
                                f"{str(exc).splitlines()[-1] if str(exc) else exc}")
                continue
            return ctx
        raise DeviceError("no OpenCL device can build a kernel: " + "; ".join(failures)
                          + " (on Debian/Ubuntu: apt-get install pocl-opencl-icd)")

    def info(self) -> dict[str, Any]:
        d = self.cl_device
        return {
            "name": d.name.strip(),
            "platform": d.platform.name.strip(),
            "driver": d.driver_version.strip(),
            "max_mem_alloc_size": int(d.max_mem_alloc_size),
            "global_mem_size": int(d.global_mem_size),
        }

    @property
    def max_alloc_bytes(self) -> int:
        return int(self.cl_device.max_mem_alloc_size)

    @functools.cached_property
    def memory_is_host(self) -> bool:
        """Whether the device's buffers live in the host's memory (a CPU device such as PoCL's, or an integrated
        GPU that says so): then they count in the process's resident memory beside the host caches. Asked once:
        the brick cache's bound asks at every insertion, a million times in a large volume's first image."""
        d = self.cl_device
        try:
            unified = bool(d.host_unified_memory)
        except cl.Error:  # an OpenCL 3 driver may no longer answer the 1.x query
            unified = False
        return unified or bool(d.type & cl.device_type.CPU)

    def read_only(self, host: np.ndarray) -> cl.Buffer:
        """A read-only buffer of `host`, which the caller keeps unchanged while the buffer lives: on a device whose
        buffers are host memory the array itself (a large walk's tables, kept between frames, are not copied each
        frame), else a copy."""
        mf = cl.mem_flags
        where = mf.USE_HOST_PTR if self.memory_is_host and host.flags.c_contiguous else mf.COPY_HOST_PTR
        return cl.Buffer(self.context, mf.READ_ONLY | where, hostbuf=host)

    def source(self, name: str, folder: Path | None = None) -> str:
        """kernel_source, read again only when one of its files has changed."""
        base = folder or renderer_folder()
        hit = self._sources.get((name, base))
        if hit is not None and all(_stamp(p) == (p, m, n) for p, m, n in hit[0]):
            return hit[1]
        stamps, src = _expand(name, base)
        self._sources[(name, base)] = (stamps, src)
        return src

    def program(self, name: str, options: tuple[str, ...] | list[str] = (), folder: Path | None = None) -> Built:
        """Program `name` (e.g. "raycast.cl", the renderer's or in `folder`) built with `options`, from memory, disk
        or the compiler."""
        options = tuple(options)
        ctx = self.context
        dev = ctx.devices[0]
        src = self.source(name, folder)
        memo = (name, folder, options)
        hit = self._keys.get(memo)
        if hit is not None and hit[0] is src:
            key = hit[1]
        else:
            key = _key(src, options, dev)
            self._keys[memo] = (src, key)
        with self._lock:
            prg = self._programs.get(key)
            if prg is not None:
                return Built(prg, key, "memory", 0.0)
            t = time.perf_counter()
            prg, where = self._load_or_build(name, src, options, key)
            self._programs[key] = prg
            return Built(prg, key, where, (time.perf_counter() - t) * 1e3)

    def _load_or_build(self, name: str, src: str, options: tuple[str, ...], key: str) -> tuple[cl.Program, str]:
        ctx = self.context
        dev = ctx.devices[0]
        path = self.kernels / f"{key}.bin"
        if path.is_file():
            try:
                return cl.Program(ctx, [dev], [path.read_bytes()]).build(options=list(options)), "disk"
            except (cl.Error, OSError):
                pass  # stale or corrupt binary: rebuilt below
        notice = _announce_after(name, options, dev.name.strip(), self._announced)
        try:
            prg = cl.Program(ctx, src).build(options=list(options))
        except cl.RuntimeError as exc:
            raise DeviceError(f"building {name} with {' '.join(options)} failed: {exc}") from None
        finally:
            if notice is not None:
                notice.cancel()
        try:
            binary = prg.get_info(cl.program_info.BINARIES)[0]
            if binary:
                path.parent.mkdir(parents=True, exist_ok=True)
                tmp = path.with_suffix(f".tmp{os.getpid()}.{threading.get_ident()}")
                tmp.write_bytes(binary)
                os.replace(tmp, path)
        except (cl.Error, OSError):
            pass  # the disk cache is an optimisation only
        return prg, "built"

    def kernel(self, built: Built, name: str) -> cl.Kernel:
        """Kernel `name` of `built`, kept per thread (its arguments are its own state): making one costs pyopencl
        a lookup of its argument handler in a disk cache at every render. Its last arguments stay set until the
        next call's, so a caller whose buffers must go early makes its own."""
        cache = self._thread.__dict__.setdefault("kernels", {})
        k = cache.get((built.key, name))
        if k is None:
            k = cache[(built.key, name)] = cl.Kernel(built.program, name)
        return k
