"""OpenCL device selection and the program cache, below both the store (its histogram segmentation kernel) and the
renderer, so that neither imports the other for it.

Programs are built from `.cl` files (the renderer's folder by default, or the caller's; our own `#include "..."` lines are resolved here, so
no include path reaches the OpenCL compiler) and the `-D` options of a KernelConfig, and cached by
sha256(source, options, platform, device, driver) — in memory for the process and on disk under the user cache
directory (see `cache_dir`) as device binaries,
so a second process skips the compiler. Every `get_program` says where the program came from and, when it was
built, how long that took.
"""
from __future__ import annotations

import functools
import hashlib
import os
import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import pyopencl as cl

from lodcast.environment import environment
from lodcast.errors import LodcastError

__all__ = ["DeviceError", "Built", "get_context", "get_program", "kernel", "kernel_source", "cache_dir",
           "device_info", "device_memory_is_host"]

@functools.cache
def _renderer_folder() -> Path:
    """Where the renderer's `.cl` files are (found without importing the renderer: this module lies below it)."""
    import importlib.util

    spec = importlib.util.find_spec("lodcast.renderer")
    assert spec is not None and spec.submodule_search_locations, "lodcast.renderer is part of the package"
    return Path(list(spec.submodule_search_locations)[0]).resolve()
_INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)"\s*$', re.M)
_LOCK = threading.RLock()
_CTX: tuple[cl.Context, cl.CommandQueue] | None = None
_MEMO: dict[str, cl.Program] = {}
# a render asks for its program every time: the expanded source per (file, folder), valid while every file it was
# read from keeps its modification time and size (re-reading and expanding it took ~1.7 ms a render), and its
# cache key per (source, options, device), which hashes ~100 kB
_SOURCES: dict[tuple[str, Path], tuple[tuple[tuple[Path, int, int], ...], str]] = {}
_KEYS: dict[tuple, tuple[str, str]] = {}
_THREAD = threading.local()


class DeviceError(LodcastError, RuntimeError):
    """No usable OpenCL device, or the volume does not fit on it."""


@dataclass(frozen=True)
class Built:
    program: cl.Program
    key: str
    source: str  # "memory" | "disk" | "built"
    build_ms: float  # compile (or binary load) time in this call; 0 for memory hits


def cache_dir() -> Path:
    """``$LODCAST_CACHE_DIR/kernels``, else ``$LODCAST_CACHE/kernels`` (the variable the demo's downloads use),
    else the platform's user cache directory for lodcast."""
    return environment().cache_dir / "kernels"


def get_context() -> tuple[cl.Context, cl.CommandQueue]:
    """The process's context and profiling queue. Device: ``$LODCAST_DEVICE`` ("gpu", "cpu" or a substring of the
    device name), else the first GPU, else the first CPU; a device whose compiler cannot build a trivial kernel
    is passed over for the next one (PoCL's LLVM 14, bundled with pyopencl's wheels, rejects CPUs it does not
    know, e.g. AMD Zen 5: "unknown target CPU 'generic'"; Debian's pocl-opencl-icd builds there).

    The OpenCL ICD loader bundled with pyopencl's wheels sees only its own PoCL unless OCL_ICD_VENDORS says
    otherwise: when unset, the system's vendor folder /etc/OpenCL/vendors is added, so GPU drivers and a system
    PoCL are found too."""
    global _CTX
    with _LOCK:
        if _CTX is None:
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
            want = environment().device

            def rank(pd):
                _, d = pd
                name = d.name.lower()
                if want in ("gpu", "cpu"):
                    match = bool(d.type & (cl.device_type.GPU if want == "gpu" else cl.device_type.CPU))
                else:
                    match = bool(want) and want in name
                return (not match, not (d.type & cl.device_type.GPU))

            failures = []
            for _, dev in sorted(devices, key=rank):
                ctx = cl.Context([dev])
                try:
                    cl.Program(ctx, "__kernel void lc_ok(__global int* a) { a[0] = 1; }").build()
                except cl.Error as exc:
                    failures.append(f"{dev.name.strip()} ({dev.platform.version.strip()}): {str(exc).splitlines()[-1] if str(exc) else exc}")
                    continue
                queue = cl.CommandQueue(ctx, properties=cl.command_queue_properties.PROFILING_ENABLE)
                _CTX = (ctx, queue)
                break
            else:
                raise DeviceError("no OpenCL device can build a kernel: " + "; ".join(failures)
                                  + " (on Debian/Ubuntu: apt-get install pocl-opencl-icd)")
        return _CTX


def device_info() -> dict:
    ctx, _ = get_context()
    d = ctx.devices[0]
    return {
        "name": d.name.strip(),
        "platform": d.platform.name.strip(),
        "driver": d.driver_version.strip(),
        "max_mem_alloc_size": int(d.max_mem_alloc_size),
        "global_mem_size": int(d.global_mem_size),
    }


@functools.cache
def device_memory_is_host() -> bool:
    """Whether the device's buffers live in the host's memory (a CPU device such as PoCL's, or an integrated GPU
    that says so): then they count in the process's resident memory beside the host caches."""
    d = get_context()[0].devices[0]
    try:
        unified = bool(d.host_unified_memory)
    except cl.Error:  # an OpenCL 3 driver may no longer answer the 1.x query
        unified = False
    return unified or bool(d.type & cl.device_type.CPU)


def kernel_source(name: str, folder: Path | None = None) -> str:
    """The text of `name` (a .cl file beside this module, or in `folder`) with our own quoted #includes inlined,
    once each; read again only when one of its files has changed."""
    base = folder or _renderer_folder()
    hit = _SOURCES.get((name, base))
    if hit is not None and all(_stamp(p) == (p, m, n) for p, m, n in hit[0]):
        return hit[1]
    seen: dict[Path, tuple[Path, int, int]] = {}

    def expand(fname: str) -> str:
        path = base / fname
        if path in seen:
            return ""
        seen[path] = _stamp(path)  # before reading: a change in between is seen next time
        return _INCLUDE.sub(lambda m: expand(m.group(1)), path.read_text())

    src = expand(name)
    _SOURCES[(name, base)] = (tuple(seen.values()), src)
    return src


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


def get_program(name: str, options: tuple[str, ...] | list[str] = (), folder: Path | None = None) -> Built:
    """Program `name` (e.g. "raycast.cl", beside this module or in `folder`) built with `options`, from memory,
    disk or the compiler."""
    options = tuple(options)
    ctx, _ = get_context()
    dev = ctx.devices[0]
    src = kernel_source(name, folder)
    memo = (name, folder, options, dev.int_ptr)
    hit = _KEYS.get(memo)
    if hit is not None and hit[0] is src:
        key = hit[1]
    else:
        key = _key(src, options, dev)
        _KEYS[memo] = (src, key)
    with _LOCK:
        prg = _MEMO.get(key)
        if prg is not None:
            return Built(prg, key, "memory", 0.0)
        t = time.perf_counter()
        path = cache_dir() / f"{key}.bin"
        prg = None
        if path.is_file():
            try:
                prg = cl.Program(ctx, [dev], [path.read_bytes()]).build(options=list(options))
                where = "disk"
            except (cl.Error, OSError):
                prg = None  # stale or corrupt binary: rebuild below
        if prg is None:
            try:
                prg = cl.Program(ctx, src).build(options=list(options))
            except cl.RuntimeError as exc:
                raise DeviceError(f"building {name} with {' '.join(options)} failed: {exc}") from None
            where = "built"
            try:
                binary = prg.get_info(cl.program_info.BINARIES)[0]
                if binary:
                    path.parent.mkdir(parents=True, exist_ok=True)
                    tmp = path.with_suffix(f".tmp{os.getpid()}")
                    tmp.write_bytes(binary)
                    os.replace(tmp, path)
            except (cl.Error, OSError):
                pass  # the disk cache is an optimisation only
        _MEMO[key] = prg
        return Built(prg, key, where, (time.perf_counter() - t) * 1e3)


def kernel(built: Built, name: str) -> cl.Kernel:
    """Kernel `name` of `built`, kept per thread (its arguments are its own state): making one took 0.1-0.6 ms a
    render, pyopencl looking its argument handler up in a disk cache. Its last arguments stay set until the next
    call's, so a caller whose buffers must go early makes its own."""
    cache = _THREAD.__dict__.setdefault("kernels", {})
    k = cache.get((built.key, name))
    if k is None:
        k = cache[(built.key, name)] = cl.Kernel(built.program, name)
    return k
