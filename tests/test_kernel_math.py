"""The kernels' own elementary functions against float64: lc_alpha_of_depth (1 - e^-x without a library call,
lc_common.h), which the distribution classification composites with."""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from lodcast.opencl import get_context, kernel_source

KERNEL = """
__kernel void alpha_of_depth(__global const float* x, __global float* out) {
    const int i = get_global_id(0);
    out[i] = lc_alpha_of_depth(x[i]);
}
"""


def _run(x: np.ndarray) -> np.ndarray:
    ctx, queue = get_context()
    prg = cl.Program(ctx, kernel_source("lc_common.h") + KERNEL).build()
    mf = cl.mem_flags
    d_x = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=x)
    d_out = cl.Buffer(ctx, mf.WRITE_ONLY, x.nbytes)
    prg.alpha_of_depth(queue, (x.size,), None, d_x, d_out)
    out = np.empty_like(x)
    cl.enqueue_copy(queue, out, d_out)
    return out


def test_alpha_of_depth_matches_float64_over_every_scale():
    rng = np.random.default_rng(7)
    x = np.concatenate([
        np.array([0.0, 1e-30, 1e-8, 0.25, np.nextafter(np.float32(0.25), np.float32(0)), 0.6931472, 1.0, 2.0, 86.9, 87.0,
                  87.5, 100.0, 1e30]),
        10.0 ** rng.uniform(-9, 2.2, 200_000),  # optical depths of a segment: tiny (thin media) to opaque
        rng.uniform(0.2, 0.3, 20_000),  # both sides of the series' switch
    ]).astype(np.float32)
    got = _run(x).astype(np.float64)
    want = -np.expm1(-x.astype(np.float64))
    assert np.all((got >= 0) & (got <= 1))
    rel = np.abs(got - want) / want.clip(min=1e-300)
    assert rel[x > 0].max() < 4e-7, (x[np.argmax(rel)], rel.max())
    assert got[x == 0].tolist() == [0.0]
    # monotone, as an opacity of a longer segment must be (up to one float32 ulp of wobble)
    order = np.argsort(x, kind="stable")
    assert np.all(np.diff(got[order]) >= -np.spacing(got[order][1:]))
