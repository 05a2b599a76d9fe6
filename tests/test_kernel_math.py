"""The kernels' own elementary functions against float64: lc_alpha_of_depth (1 - e^-x without a library call,
lc_common.h), which every composite march takes its opacities from, lc_exp_neg (e^-x: the compensated march's
transmittance), lc_depth_of_alpha (-ln(1 - a): pre-integration's segments of other lengths) and lc_pow01 (x^e on (0, 1], the highlight of
the shading)."""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from lodcast.opencl import Device, kernel_source

KERNEL = """
__kernel void alpha_of_depth(__global const float* x, __global float* out) {
    const int i = get_global_id(0);
    out[i] = lc_alpha_of_depth(x[i]);
}
__kernel void exp_neg(__global const float* x, __global float* out) {
    const int i = get_global_id(0);
    out[i] = lc_exp_neg(x[i]);
}
__kernel void depth_of_alpha(__global const float* x, __global float* out) {
    const int i = get_global_id(0);
    out[i] = lc_depth_of_alpha(x[i]);
}
__kernel void pow01(__global const float* x, __global const float* e, __global float* out) {
    const int i = get_global_id(0);
    out[i] = lc_pow01(x[i], e[i]);
}
"""


def _run(x: np.ndarray, *more: np.ndarray, name: str = "alpha_of_depth") -> np.ndarray:
    dev = Device()
    ctx, queue = dev.context, dev.queue
    prg = cl.Program(ctx, kernel_source("lc_common.h") + KERNEL).build()
    mf = cl.mem_flags
    bufs = [cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a) for a in (x, *more)]
    d_out = cl.Buffer(ctx, mf.WRITE_ONLY, x.nbytes)
    getattr(prg, name)(queue, (x.size,), None, *bufs, d_out)
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


def test_pow01_matches_float64_on_the_unit_interval():
    rng = np.random.default_rng(8)
    x = np.concatenate([np.array([1.0, np.nextafter(np.float32(1), np.float32(0)), 0.5, 0.70710677, 0.7071068, 1e-3,
                                  1e-20, 1.1754944e-38, 1e-40, 0.0]),
                        10.0 ** rng.uniform(-8, 0, 100_000), rng.uniform(0.9, 1.0, 50_000)]).astype(np.float32)
    e = np.concatenate([np.array([20.0, 20.0, 1.0, 64.0, 64.0, 0.5, 1.0, 2.0, 2.0, 3.0]),
                        rng.choice([0.0, 0.5, 1.0, 8.0, 20.0, 128.0], 150_000)]).astype(np.float32)
    got = _run(x, e, name="pow01").astype(np.float64)
    with np.errstate(divide="ignore"):
        want = np.power(x.astype(np.float64), e.astype(np.float64))
    assert np.all((got >= 0) & (got <= 1))
    err = np.abs(got - want)
    assert err.max() < 1e-6, (x[np.argmax(err)], e[np.argmax(err)], err.max())
    assert got[e == 0].min() == 1.0 and got[x == 1].min() == 1.0


def test_exp_neg_matches_float64_up_to_the_smallest_normal_number():
    rng = np.random.default_rng(9)
    x = np.concatenate([np.array([0.0, 1e-30, 1e-8, 0.25, np.nextafter(np.float32(0.25), np.float32(0)), 1.0, 86.9,
                                  87.0, 87.5, 1e30, np.inf]),
                        10.0 ** rng.uniform(-9, 1.94, 200_000), rng.uniform(0.2, 0.3, 20_000)]).astype(np.float32)
    got = _run(x, name="exp_neg").astype(np.float64)
    want = np.exp(-x.astype(np.float64))
    normal = x <= 87.0
    assert (np.abs(got - want)[normal] / want[normal]).max() < 4e-7
    assert (got[~normal] == 0).all() and got[x == 0].tolist() == [1.0]
    order = np.argsort(x, kind="stable")  # monotone: a longer path lets less through
    assert np.all(np.diff(got[order]) <= np.spacing(got[order][:-1]))


def test_depth_of_alpha_matches_float64_over_the_unit_interval():
    rng = np.random.default_rng(10)
    a = np.concatenate([np.array([0.0, 1e-30, 1e-8, 0.25, np.nextafter(np.float32(0.25), np.float32(0)), 0.5, 0.999999,
                                  np.nextafter(np.float32(1), np.float32(0)), 1.0]),
                        10.0 ** rng.uniform(-9, 0, 200_000), 1 - 10.0 ** rng.uniform(-7, -0.5, 50_000)]).astype(np.float32)
    a = np.clip(a, 0, 1)
    got = _run(a, name="depth_of_alpha").astype(np.float64)
    with np.errstate(divide="ignore"):
        want = -np.log1p(-a.astype(np.float64))
    inner = (a > 0) & (a < 1)
    assert (np.abs(got[inner] - want[inner]) / want[inner]).max() < 4e-7
    assert got[a == 0].tolist() == [0.0] and np.isinf(got[a == 1]).all()
