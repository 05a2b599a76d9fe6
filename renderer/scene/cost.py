"""What a render will cost, estimated before it starts (docs/design.md, Limits: `LODCAST_MAX_SAMPLES`).

The estimate is rays × samples per ray: the scene's rays on a grid of at most 64 × 64 pixels across the same view
are intersected with the (clipped) box, and the mean length of their paths over the step, times every pixel of
the image, is the number of samples a march without empty-space skipping, early termination or adaptive steps
takes. That bounds what the kernel does (those only take samples away), to within the sub-grid's sampling of the
image, and costs next to nothing beside the render.
"""
from __future__ import annotations

import numpy as np

from lodcast.renderer.scene.camera import Frame, pixel_rays, ray_box
from lodcast.renderer.scene.scene import SceneError

__all__ = ["CostError", "DEFAULT_MAX_SAMPLES", "estimate_samples", "refuse_over_limit"]

DEFAULT_MAX_SAMPLES = 2_000_000_000  # far beyond an interactive render: only a runaway scene reaches it


class CostError(SceneError):
    """A render would take more samples than the limit; `field` names what to change."""

    def __init__(self, message: str, field: str, samples: int, limit: int):
        super().__init__(message)
        self.field, self.samples, self.limit = field, samples, limit


def estimate_samples(fr: Frame, box: tuple[np.ndarray, np.ndarray], width: int, height: int, step: float) -> int:
    """Samples of a full march of every ray through `box` (world x, y, z) at `step` (world units)."""
    lo, hi = np.asarray(box[0], np.float64), np.asarray(box[1], np.float64)
    if np.any(lo >= hi):
        return 0
    w, h = min(width, 64), min(height, 64)
    t0, t1 = ray_box(*pixel_rays(fr, w, h), lo, hi)
    n = np.where(t1 > t0, np.ceil((t1 - t0) / step), 0.0)
    return int(np.ceil(n.mean() * width * height))


def refuse_over_limit(samples: int, limit: int, width: int, height: int, step_voxels: float) -> None:
    """Raise CostError, naming sampling.step (or the image size, when even the step that takes one sample per
    voxel would not fit), if `samples` exceeds `limit`."""
    if samples <= limit:
        return
    per_ray = samples / (width * height)
    step_fit = step_voxels * samples / limit
    field = "sampling.step" if step_fit <= 1.0 else "width"  # steps above a voxel miss structure: fewer pixels
    raise CostError(
        f"{field}: this render would take about {samples:.3g} samples ({width}x{height} rays x {per_ray:.0f} per ray), "
        f"more than the limit of {limit:.3g} (LODCAST_MAX_SAMPLES); use a sampling.step of at least {step_fit:.3g} "
        f"voxels or fewer pixels (width x height)", field, samples, limit)
