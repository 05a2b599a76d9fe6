"""Image error as DESIGN.md defines it: CIE76 ΔE in CIELUV (D65, sRGB input) per pixel, after compositing both
premultiplied RGBA images over opaque black; mean and 95th percentile over the footprint (pixels where either
image has alpha ≥ 1/255), and max. Colours are composited as given (no linearisation), so "over black" leaves
the premultiplied rgb, clipped to [0, 1]."""
from __future__ import annotations

import warnings

import numpy as np

__all__ = ["delta_e_image", "delta_e_stats", "srgb_to_luv"]


def srgb_to_luv(rgb: np.ndarray) -> np.ndarray:
    """CIE L*u*v* (D65) of sRGB colours in [0, 1], any leading shape."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # colour-science's optional-dependency notices
        import colour

        xyz = colour.sRGB_to_XYZ(np.clip(np.asarray(rgb, np.float64), 0.0, 1.0))
        return colour.XYZ_to_Luv(xyz, colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"])


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
