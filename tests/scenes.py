"""Scene-building helpers for tests: transfer functions, cameras and the pixel a world point lands on.

Written from docs/design.md's camera and transfer-function conventions (f = normalize(target − eye),
r = normalize(f × up), u = r × f; pixel centres at (i + 0.5, j + 0.5); aspect W/H on the horizontal axis),
independently of the renderer's code, so that tests of the reference and of the kernel build their scenes
and predictions without trusting either. Only `box_bounds` is taken from tests/reference.py.
"""
from __future__ import annotations

import math

import numpy as np
from reference import box_bounds


def const_tf(a: float, color=(0.8, 0.5, 0.2), unit: float | None = None, lo: float = -1e3, hi: float = 1e3) -> dict:
    """A transfer function of constant colour and opacity `a` over the values [lo, hi]."""
    tf = {"points": [{"value": lo, "color": list(color), "opacity": a}, {"value": hi, "color": list(color), "opacity": a}]}
    if unit is not None:
        tf["unit_distance"] = unit
    return tf


def axis_camera(axis: str, shape, spacing=(1, 1, 1), origin=(0, 0, 0), view_height: float | None = None) -> dict:
    """Orthographic camera looking along +axis (world x, y or z) through the box centre."""
    lo, hi = box_bounds(shape, spacing, origin)
    c = (lo + hi) / 2
    k = "xyz".index(axis)
    eye = c.copy()
    eye[k] = lo[k] - 10.0
    up = [0.0, 0.0, 1.0] if axis != "z" else [0.0, 1.0, 0.0]
    # default: small enough that every pixel of an image up to 2:1 sees the box across its full extent
    vh = view_height if view_height is not None else 0.4 * float(np.delete(hi - lo, k).min())
    return {"eye": eye.tolist(), "target": c.tolist(), "up": up, "projection": "orthographic", "view_height": vh}


def basis(cam: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """docs/design.md: f = normalize(target − eye), r = normalize(f × up), u = r × f (written out again here)."""
    eye, tgt, up = (np.asarray(cam[k], float) for k in ("eye", "target", "up"))
    f = (tgt - eye) / np.linalg.norm(tgt - eye)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    return eye, f, r, np.cross(r, f)


def predicted_pixel(cam: dict, W: int, H: int, p: np.ndarray) -> tuple[float, float]:
    """docs/design.md's pixel formula inverted: the (row, col) whose ray passes through world point p (written out
    independently of reference.project_point)."""
    eye, f, r, u = basis(cam)
    d = p - eye
    if cam.get("projection") == "orthographic":
        xc, yc = d @ r / (cam["view_height"] / 2), d @ u / (cam["view_height"] / 2)
    else:
        t = math.tan(math.radians(cam["fov"]) / 2)
        xc, yc = d @ r / (d @ f) / t, d @ u / (d @ f) / t
    return (1 - yc) * H / 2 - 0.5, (xc * H / W + 1) * W / 2 - 0.5


def centroid(a: np.ndarray) -> tuple[float, float]:
    """(row, col) centroid of a non-negative 2-D weight image."""
    H, W = a.shape
    return (a * np.arange(H)[:, None]).sum() / a.sum(), (a * np.arange(W)[None, :]).sum() / a.sum()


def aim_at(p: np.ndarray, pixel: tuple[int, int], W: int, H: int, f0, up, dist: float, fov: float | None = None,
           view_height: float | None = None) -> dict:
    """A camera looking along f0 whose pixel (i, j) ray passes exactly through world point p, built from
    docs/design.md's pixel formula: the basis depends only on f0 and up, so the eye is placed on that ray.
    Perspective with `fov`, orthographic with `view_height`."""
    f = np.asarray(f0, float) / np.linalg.norm(f0)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    i, j = pixel
    px, py = (2 * (j + 0.5) / W - 1) * W / H, 1 - 2 * (i + 0.5) / H
    if view_height is None:
        t = math.tan(math.radians(fov) / 2)
        d = f + px * t * r + py * t * u
        eye = p - dist * d / np.linalg.norm(d)
        return {"eye": eye.tolist(), "target": (eye + dist * f).tolist(), "up": list(up), "fov": fov}
    eye = p - dist * f - view_height / 2 * (px * r + py * u)
    return {"eye": eye.tolist(), "target": (eye + dist * f).tolist(), "up": list(up), "projection": "orthographic", "view_height": view_height}
