"""Program cache: memory hits within a Device, disk hits across processes, keyed by source, options, device."""
from __future__ import annotations

import json
import os
import subprocess
import sys

from lodcast.opencl import Device, kernel_source

SNIPPET = r"""
import json, sys
from lodcast.opencl import Device
b = Device().program("raycast.cl", tuple(sys.argv[1:]))
print(json.dumps({"source": b.source, "build_ms": b.build_ms, "key": b.key}))
"""


def _build_in_new_process(cache, options):
    env = {**os.environ, "LODCAST_CACHE_DIR": str(cache)}
    out = subprocess.run([sys.executable, "-c", SNIPPET, *options], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_program_cache_hits_across_processes(tmp_path):
    opts = ["-DLC_SAMPLER_FULL", "-DLC_MODE_MIP", "-DLC_JITTER"]
    first = _build_in_new_process(tmp_path, opts)
    second = _build_in_new_process(tmp_path, opts)
    assert first["source"] == "built" and first["build_ms"] > 0
    assert second["source"] == "disk" and second["key"] == first["key"]
    assert list((tmp_path / "kernels").glob("*.bin"))
    other = _build_in_new_process(tmp_path, opts[:2])  # other options: another program
    assert other["source"] == "built" and other["key"] != first["key"]


def test_program_cache_hits_in_memory():
    dev = Device()
    a = dev.program("raycast.cl", ("-DLC_SAMPLER_FULL",))
    b = dev.program("raycast.cl", ("-DLC_SAMPLER_FULL",))
    assert b.source == "memory" and b.program is a.program and b.build_ms == 0.0
    other = Device().program("raycast.cl", ("-DLC_SAMPLER_FULL",))  # another device object: its own programs
    assert other.source == "disk" and other.key == a.key and other.program is not a.program


def test_includes_are_inlined_once():
    src = kernel_source("raycast.cl")
    assert "#include" not in src
    assert src.count("typedef struct LcParams") == 1


def test_a_changed_kernel_file_is_read_again(tmp_path):
    """Sources are kept per file and folder while none of their files changes: the same text object until an
    included file's size or modification time moves, then the new text, and a program built from it."""
    (tmp_path / "k.cl").write_text('#include "inc.h"\n__kernel void k(__global int* a) { a[0] = LC_V; }\n')
    (tmp_path / "inc.h").write_text("#define LC_V 1\n")
    dev = Device()
    first = dev.source("k.cl", tmp_path)
    assert dev.source("k.cl", tmp_path) is first and "LC_V 1" in first and kernel_source("k.cl", tmp_path) == first
    a = dev.program("k.cl", (), folder=tmp_path)
    (tmp_path / "inc.h").write_text("#define LC_V 22\n")  # another size
    second = dev.source("k.cl", tmp_path)
    assert "LC_V 22" in second and "LC_V 1\n" not in second
    b = dev.program("k.cl", (), folder=tmp_path)
    assert b.key != a.key and b.source != "memory"
    st = (tmp_path / "inc.h").stat()
    (tmp_path / "inc.h").write_text("#define LC_V 33\n")  # the same size: the modification time tells
    os.utime(tmp_path / "inc.h", ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
    assert "LC_V 33" in dev.source("k.cl", tmp_path)
    assert dev.program("k.cl", (), folder=tmp_path).key not in (a.key, b.key)


def test_kernels_are_kept_per_thread():
    """A kernel's arguments are its own state: one thread's kernel is kept for it and never handed to another."""
    import threading

    dev = Device()
    kernel = dev.kernel
    built = dev.program("raycast.cl", ("-DLC_SAMPLER_FULL",))
    mine = kernel(built, "lc_render")
    assert kernel(built, "lc_render") is mine
    other = []
    t = threading.Thread(target=lambda: other.append(kernel(built, "lc_render")))
    t.start()
    t.join()
    assert other[0] is not mine and other[0].function_name == "lc_render"
