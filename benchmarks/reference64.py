"""A float64 fixed-step reference image for the benchmark: every renderer in `run.py` (lodcast and its peers) is
measured against it, with lodcast's ΔE, so that no renderer is judged by its own output.

It is written from lodcast's documented conventions (docs/reference.md) and shares no code with lodcast's kernel:
rays and the box come from tests/reference.py (the suite's independent reference, too slow for 512² images of a
72-million-voxel CT), the field is trilinear between voxel centres in float64 and clamped in the half-voxel rim,
and each ray's segment in the box is cut into equal parts no longer than `step` × the smallest spacing, each
classified at its midpoint and composited front to back with α = 1 − (1 − a)^(Δ/unit). Rays stop once their
transmittance is below 1e-7 (the image moves by less than that). run.py caches the images in its output folder
(reference/) by a hash of everything that determines them, so a second run of the benchmark costs nothing here.
"""
from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from reference import TransferFunction, box_bounds, camera_rays, ray_box  # noqa: E402

__all__ = ["reference_image"]

T_STOP = 1e-7
CHUNK = 1 << 16


def _march(vol: np.ndarray, o: np.ndarray, d: np.ndarray, t0: np.ndarray, t1: np.ndarray, tf: TransferFunction,
           spacing_xyz: np.ndarray, origin_xyz: np.ndarray, step: float) -> np.ndarray:
    """Premultiplied RGBA (N×4, float64) of N rays."""
    n = np.maximum(np.ceil((t1 - t0) / step), 0).astype(np.int64)
    dt = np.where(n > 0, (t1 - t0) / np.maximum(n, 1), 0.0)
    shape_xyz = np.array(vol.shape[::-1])
    flat = vol.reshape(-1)
    strides = np.array([1, vol.shape[2], vol.shape[1] * vol.shape[2]], np.int64)  # x, y, z in elements
    C = np.zeros((len(o), 3))
    T = np.ones(len(o))
    live = np.nonzero(n > 0)[0]
    k = 0
    while live.size:
        t = t0[live] + (k + 0.5) * dt[live]
        q = (o[live] + d[live] * t[:, None] - origin_xyz) / spacing_xyz
        q = np.clip(q, 0.0, shape_xyz - 1)
        lo = np.floor(q).astype(np.int64)
        fr = q - lo
        hi_step = np.where(lo < shape_xyz - 1, strides, 0)  # at the last voxel the upper neighbour is itself
        base = lo @ strides
        s = np.zeros(live.size)
        for cz in (0, 1):
            wz = fr[:, 2] if cz else 1 - fr[:, 2]
            for cy in (0, 1):
                wy = fr[:, 1] if cy else 1 - fr[:, 1]
                for cx in (0, 1):
                    wx = fr[:, 0] if cx else 1 - fr[:, 0]
                    idx = base + cx * hi_step[:, 0] + cy * hi_step[:, 1] + cz * hi_step[:, 2]
                    s += wz * wy * wx * flat[idx]
        a = tf.opacity(s)
        alpha = np.where(a >= 1.0, 1.0, 1.0 - np.power(np.clip(1.0 - a, 0.0, 1.0), dt[live] / tf.unit))
        w = T[live] * alpha
        C[live] += w[:, None] * tf.color(s)
        T[live] *= 1.0 - alpha
        k += 1
        live = live[(k < n[live]) & (T[live] >= T_STOP)]
    return np.concatenate([C, (1.0 - T)[:, None]], axis=1)


def _key(volume_id: str, scene: dict[str, Any], spacing, origin, step: float) -> str:
    text = json.dumps({"v": volume_id, "scene": scene, "spacing": list(spacing), "origin": list(origin),
                       "step": step, "t_stop": T_STOP, "rev": 1}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def reference_image(vol: np.ndarray, scene: dict[str, Any], spacing, origin, *, volume_id: str,
                    cache: Path | None = None, step: float = 0.25, log=None) -> np.ndarray:
    """H×W×4 premultiplied RGBA (float64, row 0 at the top) of `scene` (camera, width, height, tf; emission–
    absorption, transparent background) over `vol` (z, y, x) with `spacing` and `origin` in z, y, x order."""
    path = None
    if cache is not None:
        path = cache / f"{_key(volume_id, scene, spacing, origin, step)}.npy"
        if path.exists():
            return np.load(path)
    W, H = int(scene["width"]), int(scene["height"])
    o, d = camera_rays(scene["camera"], W, H, vol.shape, spacing, origin)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    lo, hi = box_bounds(vol.shape, spacing, origin)
    t0, t1 = ray_box(o, d, lo, hi)
    tf = TransferFunction(scene["tf"], spacing)
    sp, org = np.asarray(spacing, np.float64)[::-1], np.asarray(origin, np.float64)[::-1]
    dstep = step * float(min(spacing))
    out = np.empty((W * H, 4))
    for a in range(0, W * H, CHUNK):
        b = min(a + CHUNK, W * H)
        out[a:b] = _march(vol, o[a:b], d[a:b], t0[a:b], t1[a:b], tf, sp, org, dstep)
        if log:
            log(f"  reference: {b * 100 // (W * H)}% of {W}x{H} rays")
    img = out.reshape(H, W, 4)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, img)
    return img
