"""Pictures for `lodcast demo`: a few views and transfer functions of any store, chosen from its own values.

    from lodcast.renderer.tools.demo import render_demo
    paths = render_demo(store, "demo-output")   # prints one line per picture and returns their paths

The TFs are derived from the volume's value distribution (percentiles of a coarse level, so this works for CT in
Hounsfield units as well as for MR in arbitrary units): a translucent "soft" TF over the upper body of the
distribution, an opaque "dense" TF for the brightest structures (lit by a headlight), and a MIP.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

__all__ = ["demo_tfs", "demo_scenes", "render_demo", "SHADING"]

#: the Shading model's defaults (a headlight), spelled out so that the saved scene files show them
SHADING = {"ambient": 0.3, "diffuse": 0.7, "specular": 0.2, "shininess": 32, "light": "headlight"}


def _coarse_values(store: Any) -> np.ndarray:
    level = max(0, min(int(getattr(store, "n_levels", 1)) - 1, 2))
    a = np.asarray(store.read_level(level), dtype=np.float64)
    a = a[np.isfinite(a)]
    return a if a.size else np.zeros(1)


def demo_tfs(store: Any) -> dict[str, dict]:
    """TFs from the volume's percentiles (background, usually the most common value, stays transparent):
    "soft" and "dense" for compositing, "mip" a grey ramp for maximum intensity projection."""
    v = _coarse_values(store)
    lo, hi = float(v.min()), float(v.max())
    p = {q: float(np.percentile(v, q)) for q in (50, 70, 85, 95, 99.5)}
    if hi <= lo:
        hi = lo + 1.0

    def mono(x: float) -> float:  # strictly increasing control points even on flat distributions
        return min(max(x, lo), hi)

    eps = (hi - lo) * 1e-3
    s0 = mono(max(p[50], lo + 0.05 * (hi - lo)))
    s1 = mono(max(p[70], s0 + eps))
    s2 = mono(max(p[95], s1 + eps))
    soft = {"points": [
        {"value": s0, "color": [0.9, 0.55, 0.4], "opacity": 0.0},
        {"value": s1, "color": [0.95, 0.7, 0.55], "opacity": 0.004},
        {"value": s2, "color": [1.0, 0.95, 0.85], "opacity": 0.08},
    ]}
    d0 = mono(max(p[85], lo + 0.3 * (hi - lo)))
    d1 = mono(max(p[99.5], d0 + eps))
    dense = {"points": [
        {"value": d0, "color": [0.8, 0.75, 0.7], "opacity": 0.0},
        {"value": d1, "color": [1.0, 1.0, 0.95], "opacity": 0.9},
    ]}
    grey = {"points": [{"value": s0, "color": [0, 0, 0], "opacity": 1.0},
                       {"value": hi, "color": [1, 1, 1], "opacity": 1.0}]}
    return {"soft": soft, "dense": dense, "mip": grey}


def demo_scenes(store: Any, size: int = 384) -> dict[str, dict]:
    tfs = demo_tfs(store)

    def orbit(az: float, el: float) -> dict:  # no distance: the whole volume in the picture, from each side
        return {"azimuth": az, "elevation": el}

    base = {"width": size, "height": size, "background": [0, 0, 0, 1]}
    scenes = {}
    for az in (0, 90, 210):
        scenes[f"soft_az{az}"] = {**base, "tf": tfs["soft"], "camera": orbit(az, 15)}
    for az in (30, 120):
        scenes[f"dense_az{az}"] = {**base, "tf": tfs["dense"], "camera": orbit(az, 25),
                                   "shading": SHADING}  # an opaque surface reads as a shape only when lit
    scenes["mip_az0"] = {**base, "tf": tfs["mip"],
                         "mode": "mip", "camera": orbit(0, 0)}
    return scenes


def render_demo(store: Any, out_dir: str | Path, size: int = 384,
                log: Callable[[str], Any] | None = None) -> list[Path]:
    """Render the demo pictures of `store` (a Store or its path) into `out_dir` as PNG, each with its scene beside
    it (render_NAME.scene.json: `lodcast render STORE --scene` reproduces it). Returns the PNG paths."""
    import lodcast
    from lodcast.renderer.frame.render import render

    log = log or (lambda msg: print(msg, file=sys.stderr))
    if isinstance(store, (str, Path)):
        store = lodcast.open_store(store)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scenes = demo_scenes(store, size)
    paths = []
    t = time.perf_counter()
    for name, scene in scenes.items():
        res = render(store, scene)
        path = res.save(out / f"render_{name}.png")
        (out / f"render_{name}.scene.json").write_text(json.dumps(scene, indent=2))
        paths.append(path)
        r = res.report
        log(f"  {path}  ({r['kernel_ms']:.0f} ms kernel, {r['samples'] / 1e6:.1f} M samples, "
            f"{r['bricks_skipped']} of {r['blocks']} blocks skipped)")
    log(f"rendered {len(paths)} pictures in {time.perf_counter() - t:.1f} s into {out}/ (each with its .scene.json)")
    return paths
