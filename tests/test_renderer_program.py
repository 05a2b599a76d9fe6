"""Program cache: memory hits within a process, disk hits across processes, keyed by source, options, device."""
from __future__ import annotations

import json
import os
import subprocess
import sys

from lodcast.opencl import get_program, kernel_source

SNIPPET = r"""
import json, sys
from lodcast.opencl import get_program
b = get_program("raycast.cl", tuple(sys.argv[1:]))
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
    a = get_program("raycast.cl", ("-DLC_SAMPLER_FULL",))
    b = get_program("raycast.cl", ("-DLC_SAMPLER_FULL",))
    assert b.source == "memory" and b.program is a.program and b.build_ms == 0.0


def test_includes_are_inlined_once():
    src = kernel_source("raycast.cl")
    assert "#include" not in src
    assert src.count("typedef struct LcParams") == 1
