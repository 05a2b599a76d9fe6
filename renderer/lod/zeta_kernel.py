"""level_error.block_zetas on the engine's OpenCL device (renderer/kernel/zeta.cl).

The selection's first sight of a TF evaluates every visible block's error at every level: O(K · L) table lookups
per block over up to millions of blocks (a large volume's first image, and every TF change after it). As NumPy
array work that made most of a large volume's first selection; one work-item per block, with the sums over the
quadrature kept in registers, does the same arithmetic without the arrays between its steps. level_error.py's
NumPy path stays the reference (tests/test_level_error.py holds the two together).
"""
from __future__ import annotations

from typing import Any

import numpy as np
import pyopencl as cl

from lodcast.opencl import Device

__all__ = ["device_zetas"]


def device_zetas(device: Device, meta: Any, tf: Any, rows: np.ndarray, starts: np.ndarray, t: Any, luv: np.ndarray,
                 classification: str, worst_values: bool, level_errors: bool = True) -> tuple[np.ndarray, ...]:
    """(ζ(k) (m, L), ζ_step (m,), opacity moments (m, 4: level_error.block_zetas), the worst value's ζ(k) (m, L), zeros unless
    `worst_values`, the spread ς(k) (m, L); ζ(k) zeros unless `level_errors`) of the blocks `rows` of `meta`,
    float32, as level_error.block_zetas computes them: `tf` a TransferFunction, `starts` the effective starts (N, K + 1), `t` and `luv` the distribution
    table and its CIELUV colours (level_error.luv_table)."""
    m, n_lv = rows.size, int(meta.n_levels)
    k_pieces = int(starts.shape[1]) - 1
    assert meta.level_std is not None
    st = np.ascontiguousarray(starts[rows], np.int32)
    heights = np.ascontiguousarray(np.asarray(meta.heights)[rows], np.float32)
    level_std = np.ascontiguousarray(np.asarray(meta.level_std)[rows], np.float32)
    half_range = 0.5 * (np.asarray(meta.max_border)[rows] - np.asarray(meta.min_border)[rows])
    # values go to the device relative to the table's first entry, in float64 until then: float32 keeps the
    # position within the value range whatever its offset (data in [1e9, 1e9 + 1000] included)
    lo = float(t.lo)
    mean_hr = np.ascontiguousarray(np.stack([np.asarray(meta.mean)[rows] - lo, np.nan_to_num(half_range)], axis=1),
                                   np.float32)
    big = float(np.finfo(np.float32).max)
    pts = np.array([(min(max(p.value - lo, -big), big), p.opacity) for p in tf.points], np.float32)
    edges = np.asarray(meta.bins.edges, np.float64) - lo
    table = np.ascontiguousarray(luv, np.float32).ravel()
    ax = np.array([0.0, t.scale, t.std_scale, 1.0 / (1 << (n_lv - 1))], np.float32)
    sz = np.array([t.n, t.rows, len(pts), m], np.int32)
    opts = [f"-DLC_K={k_pieces}", f"-DLC_L={n_lv}"]
    opts += ["-DLC_MEAN"] if classification == "mean" else []
    opts += ["-DLC_WORST"] if worst_values else []
    opts += [] if level_errors else ["-DLC_NO_LEVEL_ERRORS"]
    ctx = device.context
    queue = cl.CommandQueue(ctx)  # its own: a selection may run beside a render on the engine's queue
    mf = cl.mem_flags

    def src(a: np.ndarray) -> cl.Buffer:
        return cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)

    out = np.empty((m, n_lv), np.float32)
    worst = np.zeros((m, n_lv), np.float32)
    step = np.empty((m, 5), np.float32)
    spreads = np.empty((m, n_lv), np.float32)
    d_out, d_worst = cl.Buffer(ctx, mf.WRITE_ONLY, out.nbytes), cl.Buffer(ctx, mf.WRITE_ONLY, max(worst.nbytes, 4))
    d_step, d_spread = cl.Buffer(ctx, mf.WRITE_ONLY, step.nbytes), cl.Buffer(ctx, mf.WRITE_ONLY, spreads.nbytes)
    kern = cl.Kernel(device.program("zeta.cl", opts).program, "lc_zeta")
    kern(queue, (m,), None, ax, sz, src(table), src(pts), src(st), src(edges.astype(np.float32)),
         src(heights), src(level_std), src(mean_hr), d_out, d_worst, d_step, d_spread)
    cl.enqueue_copy(queue, out, d_out)
    cl.enqueue_copy(queue, step, d_step)
    cl.enqueue_copy(queue, spreads, d_spread)
    if worst_values:
        cl.enqueue_copy(queue, worst, d_worst)
    queue.finish()
    return out, step[:, 0], step[:, 1:], worst, spreads
