"""lc_types.h and its NumPy mirror agree: size, and every field read back by a probe kernel."""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from lodcast.opencl import Device
from lodcast.renderer.kernel.structs import PARAMS_DTYPE, new_params


def test_params_dtype_size_and_alignment():
    assert PARAMS_DTYPE.itemsize == 592
    assert PARAMS_DTYPE.itemsize % 16 == 0
    for name in ("eye", "cam_f", "box_lo", "background", "dims", "grid", "pass_lo", "pass_off", "pass_dims", "ess_grid"):
        assert PARAMS_DTYPE.fields[name][1] % 16 == 0, name  # float4/int4 are 16-byte aligned in OpenCL


def test_every_field_reads_back_through_the_kernel():
    dev = Device()
    ctx, queue = dev.context, dev.queue
    p = new_params()
    vec_f = ["eye", "cam_f", "cam_r", "cam_u", "box_lo", "box_hi", "origin", "inv_spacing", "background"]
    for k, name in enumerate(vec_f):
        p[name] = np.arange(4) + 10 * k + 0.5
    p["dims"], p["grid"] = (1, 2, 3, 4), (5, 6, 7, 8)
    scal_f = ["half_w", "half_h", "step", "inv_unit", "lut_lo", "lut_scale", "early_term"]
    for k, name in enumerate(scal_f):
        p[name] = 100.25 + k
    p["lut_n"], p["width"], p["height"], p["seed"], p["max_samples"] = 11, 12, 13, 14, 15
    p["lut_vis_lo"], p["lut_vis_hi"] = -3.5, 77.25
    p["dist_n"], p["dist_rows"] = 16, 17
    p["dist_lo"], p["dist_scale"], p["dist_sscale"] = -1024.5, 0.25, 3.75
    p["clip"] = (np.arange(24).reshape(6, 4) + 0.5)
    p["light"], p["shade"] = (1.5, 2.5, 3.5, 4.5), (5.5, 6.5, 7.5, 8.5)
    p["shade_gmin"], p["iso"] = 0.125, 3.625
    p["pre_knots"], p["tf2_pre_knots"] = 61, 62
    p["shade_gref"] = 9.5
    p["n_clip"], p["pre_n"] = 5, 9
    ints2 = ["tf2_lut_at", "tf2_ext_at", "tf2_dtab_at", "tf2_ptab_at", "tf2_lut_n", "tf2_dist_n", "tf2_pre_n",
             "prio_tile", "prio_w"]
    floats2 = ["tf2_lut_lo", "tf2_lut_scale", "tf2_vis_lo", "tf2_vis_hi", "tf2_inv_unit", "tf2_dist_lo",
               "tf2_dist_scale"]
    for k, name in enumerate(ints2):
        p[name] = 31 + k
    for k, name in enumerate(floats2):
        p[name] = -50.75 + 1.5 * k
    p["pass_lo"], p["pass_hi"] = (-1.5, -2.5, -3.5, 0.0), (4.25, 5.25, 6.25, 0.0)
    p["pass_off"], p["pass_dims"], p["pass_first"] = (41, 42, 43, 0), (44, 45, 46, 0), 1
    p["ess_grid"] = (51, 52, 53, 8)
    p["jitter"], p["ortho"] = 71, 72
    p["grad_op"], p["tf2_grad_op"] = 0.375, 2.625
    mf = cl.mem_flags
    d_p = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=p)
    f = np.zeros(104, np.float32)
    n = np.zeros(48, np.int32)
    d_f = cl.Buffer(ctx, mf.WRITE_ONLY, f.nbytes)
    d_n = cl.Buffer(ctx, mf.WRITE_ONLY, n.nbytes)
    prg = dev.program("probe.cl").program
    cl.Kernel(prg, "lc_probe")(queue, (1,), None, d_p, d_f, d_n)
    cl.enqueue_copy(queue, f, d_f)
    cl.enqueue_copy(queue, n, d_n)
    queue.finish()
    assert n[13] == PARAMS_DTYPE.itemsize  # sizeof(LcParams) on the device
    for k, name in enumerate(vec_f):
        assert np.array_equal(f[4 * k:4 * k + 4], p[name][0]), name
    for k, name in enumerate(scal_f):
        assert f[36 + k] == p[name][0], name
    assert n[:8].tolist() == [1, 2, 3, 4, 5, 6, 7, 8]
    assert n[8:13].tolist() == [11, 12, 13, 14, 15]
    assert f[43:45].tolist() == [-3.5, 77.25]
    assert n[14:16].tolist() == [16, 17]
    assert f[45:48].tolist() == [-1024.5, 0.25, 3.75]
    assert np.array_equal(f[48:72].reshape(6, 4), p["clip"][0])
    assert np.array_equal(f[72:76], p["light"][0]) and np.array_equal(f[76:80], p["shade"][0])
    assert f[80] == 0.125 and f[83:85].tolist() == [3.625, 9.5]
    assert n[16:18].tolist() == [5, 9]
    assert n[18:27].tolist() == [31 + k for k in range(len(ints2))]
    assert f[85:92].tolist() == [-50.75 + 1.5 * k for k in range(len(floats2))]
    assert f[96:104].tolist() == [-1.5, -2.5, -3.5, 0.0, 4.25, 5.25, 6.25, 0.0]
    assert n[28:37].tolist() == [41, 42, 43, 0, 44, 45, 46, 0, 1]
    assert n[40:44].tolist() == [51, 52, 53, 8]
    assert n[44:46].tolist() == [61, 62]
    assert n[46:48].tolist() == [71, 72]
    assert f[92:94].tolist() == [0.375, 2.625]
