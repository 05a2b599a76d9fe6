"""Image error as docs/design.md defines it: CIE76 ΔE in CIELUV (D65, sRGB input) per pixel, after compositing both
premultiplied RGBA images over opaque black; mean and 95th percentile over the footprint (pixels where either
image has alpha ≥ 1/255), and max. Colours are composited as given (no linearisation), so "over black" leaves
the premultiplied rgb, clipped to [0, 1]."""
from __future__ import annotations

import numpy as np

__all__ = ["delta_e_image", "delta_e_stats", "srgb_to_luv"]

# IEC 61966-2-1's linear sRGB -> XYZ matrix (as published, rounded: colour-science uses it too) and the D65 white
# (CIE 1931 2° observer, xy = 0.3127, 0.3290)
_M = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
_WHITE_XYZ = np.array([0.3127 / 0.3290, 1.0, (1.0 - 0.3127 - 0.3290) / 0.3290])
_UV_WHITE = np.array([4.0, 9.0]) * _WHITE_XYZ[:2] / (_WHITE_XYZ @ np.array([1.0, 15.0, 3.0]))


def srgb_to_luv(rgb: np.ndarray) -> np.ndarray:
    """CIE L*u*v* (D65, 2° observer) of sRGB colours in [0, 1] (clipped), any leading shape, float64: the sRGB
    decoding, the standard's matrix and CIE 1976 L*u*v*, as colour-science's sRGB_to_XYZ and XYZ_to_Luv
    compute them (tests/test_renderer_tf.py checks the two agree), in NumPy: importing colour-science takes a
    second, which a first render should not pay."""
    c = np.clip(np.asarray(rgb, np.float64), 0.0, 1.0)
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    xyz = lin @ _M.T
    yr = xyz[..., 1] / _WHITE_XYZ[1]
    L = np.where(yr > (6.0 / 29.0) ** 3, 116.0 * np.cbrt(yr) - 16.0, (29.0 / 3.0) ** 3 * yr)
    den = xyz @ np.array([1.0, 15.0, 3.0])
    with np.errstate(invalid="ignore", divide="ignore"):
        uv = np.stack([4.0 * xyz[..., 0], 9.0 * xyz[..., 1]], axis=-1) / den[..., None]
    uv = np.where(den[..., None] > 0, uv, _UV_WHITE)  # black: u = v = 0
    return np.concatenate([L[..., None], 13.0 * L[..., None] * (uv - _UV_WHITE)], axis=-1)


def delta_e_image(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel ΔE between two premultiplied RGBA images (H×W×4) and the footprint mask."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape or a.ndim != 3 or a.shape[2] != 4:
        raise ValueError(f"images must both be H×W×4, got {a.shape} and {b.shape}")
    de = np.linalg.norm(srgb_to_luv(a[..., :3]) - srgb_to_luv(b[..., :3]), axis=-1)
    footprint = (a[..., 3] >= 1 / 255) | (b[..., 3] >= 1 / 255)
    return de, footprint


def delta_e_stats(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """{"mean", "p95", "max", "footprint"} of the ΔE between two premultiplied RGBA images."""
    de, footprint = delta_e_image(a, b)
    if not footprint.any():
        return {"mean": 0.0, "p95": 0.0, "max": 0.0, "footprint": 0}
    v = de[footprint]
    return {"mean": float(v.mean()), "p95": float(np.percentile(v, 95)), "max": float(v.max()), "footprint": int(v.size)}
