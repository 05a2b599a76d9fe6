"""The kernel's parameter block (lc_types.h's LcParams) and its tables (LUT, extinction and per-level alpha rows,
distribution and pre-integration tables, tf2's after tf's) from a prepared scene (render.Prepared)."""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from lodcast.renderer.data.volume import VolumeView
from lodcast.renderer.kernel.preintegration import PreintTable
from lodcast.renderer.kernel.structs import new_params
from lodcast.renderer.lod.classification import DistTable
from lodcast.renderer.scene import camera as cam
from lodcast.renderer.scene import clip as clipping
from lodcast.renderer.scene.scene import Scene, TransferFunction
from lodcast.renderer.scene.transfer_function import Lut

if TYPE_CHECKING:
    from lodcast.renderer.frame.plan import Prepared

__all__ = ["fill_params", "fill_tf2", "lut_table", "ext_table", "tables", "early_stop", "colour_spread"]

#: the colour spread (per channel) up to which a TF keeps `sampling.early_termination` as given (early_stop)
ET_SPREAD = 0.25


def colour_spread(tf: TransferFunction) -> float:
    """The largest difference, over the channels, between two colours the TF can show (the colours of its points
    that bound a stretch of non-zero opacity)."""
    ops = [pt.opacity for pt in tf.points]
    n = len(ops)
    shown = [tf.points[i].color for i in range(n)
             if ops[i] > 0 or (i > 0 and ops[i - 1] > 0) or (i + 1 < n and ops[i + 1] > 0)]
    if not shown:
        return 0.0
    c = np.asarray(shown, np.float64)
    return float((c.max(axis=0) - c.min(axis=0)).max())


def early_stop(scene: Scene) -> float:
    """The accumulated opacity at which a ray ends: `sampling.early_termination`, tightened for TFs whose colours
    differ widely. An ended ray fills what is left of it with its last sample's colour (lc_classify.h, lc_blend);
    what lay behind differs from that by at most the TF's colour spread D per channel, so ending at transmittance
    T moves the pixel by at most T·D. Holding that to (1 − early_termination)·ET_SPREAD keeps the threshold of a TF
    of one hue (the bone presets: D ≤ ET_SPREAD, their cost unchanged) and ends a ray through skin in front of
    bone later, where the given threshold moved translucent images by more than docs/design.md's 0.1 ΔE. Lighting
    is left out of D: rays end deep inside material, where gradients are weak and samples nearly unlit (lc_shade.h
    weighs the lighting by gradient magnitude), and counting the darkest lit colour would tighten every lit TF for
    an error that stays within the bound (docs/rendering.md, Early termination)."""
    et = float(scene.sampling.early_termination)
    if et >= 1.0 or scene.mode != "composite":
        return et
    tfs = [t for t in (scene.tf, scene.tf2) if isinstance(t, TransferFunction)]
    d = max((colour_spread(t) for t in tfs), default=0.0)
    return et if d <= ET_SPREAD else 1.0 - (1.0 - et) * ET_SPREAD / d


def fill_params(vol: VolumeView, scene: Scene, fr: cam.Frame, box: tuple, lut: Lut, step_world: float,
                 unit: float, max_samples: int, dist: DistTable | None, pre: PreintTable | None) -> np.ndarray:
    p = new_params()[0]
    xyz = lambda v: (*[float(c) for c in v], 0.0)  # noqa: E731
    p["eye"], p["cam_f"], p["cam_r"], p["cam_u"] = xyz(fr.eye), xyz(fr.f), xyz(fr.r), xyz(fr.u)
    p["box_lo"], p["box_hi"] = xyz(box[0]), xyz(box[1])
    p["origin"] = xyz(vol.origin[::-1])
    p["inv_spacing"] = xyz(1.0 / np.asarray(vol.spacing[::-1], np.float64))
    r, g, b, a = scene.background
    p["background"] = (r * a, g * a, b * a, a)
    p["dims"] = (vol.shape[2], vol.shape[1], vol.shape[0], 0)
    p["grid"] = (vol.grid[2], vol.grid[1], vol.grid[0], vol.block_size)
    p["half_w"], p["half_h"] = fr.half_w, fr.half_h
    p["step"], p["inv_unit"] = step_world, 1.0 / unit
    p["lut_lo"], p["lut_scale"], p["lut_n"] = lut.lo, lut.scale, lut.n
    p["early_term"] = early_stop(scene)
    p["iso"] = scene.isovalue if scene.isovalue is not None else 0.0
    p["width"], p["height"] = scene.width, scene.height
    p["seed"], p["jitter"] = scene.sampling.seed, int(scene.sampling.jitter)
    p["ortho"] = int(fr.orthographic)
    p["max_samples"] = max_samples
    p["lut_vis_lo"], p["lut_vis_hi"] = lut.visible_span()
    p["grad_op"] = _inverse_gradient_opacity(scene.tf)
    if pre is not None:
        p["pre_n"], p["pre_knots"] = pre.n, len(pre.warp)
    p["clip"] = clipping.kernel_planes(scene.clip)
    p["n_clip"] = 0 if scene.clip is None else len(scene.clip.planes)
    sh = scene.shading
    if sh is not None:
        p["shade"] = (sh.ambient, sh.diffuse, sh.specular, sh.shininess)
        if sh.light == "headlight":
            p["light"] = (0.0, 0.0, 0.0, 1.0)
        else:
            v = np.asarray(sh.light, np.float64)
            if sh.light_space == "view":  # x right, y up, z towards the viewer
                v = v[0] * fr.r + v[1] * fr.u - v[2] * fr.f
            p["light"] = xyz(v / np.linalg.norm(v))
        span = float(vol.value_range[1]) - float(vol.value_range[0])
        p["shade_gmin"] = sh.min_gradient if sh.min_gradient is not None else 1e-3 * span / float(min(vol.spacing))
        p["shade_gref"] = sh.gradient_weighting or 0.0
    if dist is not None:
        p["dist_n"], p["dist_rows"] = dist.n, dist.rows
        # the atlas holds standard deviations in units of vol.std_unit; the kernel only takes their square root
        p["dist_lo"], p["dist_scale"] = dist.lo, dist.scale
        p["dist_sscale"] = dist.std_scale * math.sqrt(vol.std_unit)
    return p.reshape(1)


def _inverse_gradient_opacity(tf: object) -> float:
    """LcParams.grad_op of a TF: 1 / its gradient_opacity, 0 for none (LC_GRADIENT_OPACITY)."""
    g = getattr(tf, "gradient_opacity", None)
    return 0.0 if g is None else 1.0 / float(g)


def _tfs(pr: "Prepared") -> list[tuple[Lut, float]]:
    """(LUT, unit distance) of each TF the kernel integrates: tf, and tf2 after it (LC_TF2)."""
    return [(pr.lut, pr.unit)] + ([(pr.second.lut, pr.second.unit)] if pr.second is not None else [])


def lut_table(pr: "Prepared") -> np.ndarray:
    """The LUT as the kernel built for this scene reads it (see raycast.cl); with tf2 its LUT follows at
    params.tf2_lut_at."""
    if pr.config.mode != "composite":  # the projections and iso take the TF's opacity as given
        return pr.lut.kernel_table("opacity")
    kind = "depth" if pr.config.precise else "alpha"
    return np.concatenate([lut.kernel_table(kind, pr.step_world / unit) for lut, unit in _tfs(pr)])


def _ext_rows(lut: Lut, unit: float, pr: "Prepared") -> list[np.ndarray]:
    rows = [lut.kernel_table("extinction")[:, 3]]
    if pr.config.adaptive and pr.config.mode == "composite" and not pr.config.precise:
        ratio = pr.step_world / unit
        rows += [lut.kernel_table("alpha", ratio * 2**k)[:, 3] for k in range(1, int(pr.volume.block_size).bit_length())]
    return rows


def ext_table(pr: "Prepared") -> np.ndarray:
    """lut_ext: the extinction per LUT entry; with adaptive sampling (composite, not LC_PRECISE) followed by one
    row per level k >= 1 holding the alpha of a whole step of step * 2^k (exact, float64 on the host); with tf2
    its rows follow at params.tf2_ext_at."""
    rows = [r for lut, unit in _tfs(pr) for r in _ext_rows(lut, unit, pr)]
    return np.ascontiguousarray(np.concatenate(rows), dtype=np.float32)


def tables(pr: "Prepared", kind: str) -> np.ndarray | None:
    """The distribution ("dist") or pre-integration ("preint") tables of tf (and tf2 after it), float4 rows."""
    own = getattr(pr, kind)  # Prepared and SecondTf name them alike
    if own is None:
        return None
    tabs = [t.kernel_table for t in (own, getattr(pr.second, kind, None)) if t is not None]
    return np.ascontiguousarray(np.concatenate([np.asarray(t, np.float32).reshape(-1, 4) for t in tabs]))


def fill_tf2(p: np.ndarray, pr: "Prepared") -> None:
    """The second TF's fields of the parameter block (LC_TF2), the offsets matching lut_table, ext_table and
    _tables."""
    sec, q = pr.second, p[0]
    assert sec is not None
    q["tf2_lut_at"] = pr.lut.n + 1
    q["tf2_ext_at"] = sum(r.size for r in _ext_rows(pr.lut, pr.unit, pr))
    q["tf2_lut_lo"], q["tf2_lut_scale"], q["tf2_lut_n"] = sec.lut.lo, sec.lut.scale, sec.lut.n
    q["tf2_vis_lo"], q["tf2_vis_hi"] = sec.lut.visible_span()
    q["tf2_inv_unit"] = 1.0 / sec.unit
    q["tf2_grad_op"] = _inverse_gradient_opacity(sec.tf)
    if sec.dist is not None:
        assert pr.dist is not None  # tf2 has a table only where tf has one: one kernel config builds both
        q["tf2_dtab_at"] = np.asarray(pr.dist.kernel_table).reshape(-1, 4).shape[0]
        q["tf2_dist_n"], q["tf2_dist_lo"], q["tf2_dist_scale"] = sec.dist.n, sec.dist.lo, sec.dist.scale
    if sec.preint is not None:
        assert pr.preint is not None
        q["tf2_ptab_at"] = pr.preint.kernel_table.shape[0]
        q["tf2_pre_n"], q["tf2_pre_knots"] = sec.preint.n, len(sec.preint.warp)
    if pr.priority is not None:
        q["prio_tile"], q["prio_w"] = pr.priority.tile, pr.priority.tiles.shape[1]
