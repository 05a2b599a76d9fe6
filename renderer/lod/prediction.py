"""The picture's error from a selection's per-block errors: how a block's error reaches the image along the rays
that cross it (selection._predicted with `rays`; docs/lod.md, "Predicted ΔE").

A block's table ζ(k) is the colour error of one unit slab (the TF's opacity unit: level_error.py); a ray shows the
sum over the slabs it crosses, each seen through the transmittance in front of it. Per block and level:

- the error a level-k voxel makes: its spread ς(k) (level_error.block_zetas): the colour change over one
  level-k deviation about each value (ζ_step · s_k / s_1: the structure within a level-k voxel, which neither
  classification keeps), and how far the classification's colour at the block's mean (a normal distribution of the level's
  spread; the TF at the mean) is from the colours of the values the block holds (what a model of the voxel's
  values gets wrong where it mixes materials: air and metal, with a translucent band between them that the normal
  distribution fills and the mean lands in), weighted by (s_k / s_top)², the share of
  level-k voxels that straddle such a boundary (a sharp boundary: the level-k spreads' RMS is the top spread
  times the root of that share; a smooth ramp's voxels, whose spreads grow as the level's size, count less).
  Under `classification: "mean"` the level's own ζ(k) is added (the TF at the mean is not the mean of the TF):
  e(k)² = ς(k)² + ζ(k)²;
- in which colours: the tables compare colours in the picture's CIELUV (level_error.picture_table: the
  premultiplied colour times CIELUV's Jacobian at the TF's own colour), not in each slab's. A ray composites
  premultiplied colour linearly, so a slab's error reaches the picture in those units and becomes a ΔE only at
  the picture's colour; a faint slab's own CIELUV (its lightness in the linear segment, its chroma scaled by that
  lightness) all but drops a change of hue, which on a translucent TF of changing colour is most of the error.
  The selection keeps its own ζ in each slab's CIELUV ("lossless" was set against it);
- how many unit slabs of it a ray takes: the error is spread over the block's visible voxels (the share of its
  values the TF shows, s, at least a one-voxel sheet: ζ's own normalisation), so a ray crossing the block meets
  λ_e = ℓ · max(s, 1/B) units of it (ℓ the block's length in units along the ray), and a slab at depth t is seen
  through (1 − a_e)^t of it, a_e the opacity of the values that carry the error (those of the step's colour
  change, weighted by it): n = Σ_t (1 − a_e)^t = (1 − (1 − a_e)^λ_e) / a_e unit slabs, λ_e for a faint band,
  1/a_e for an opaque surface. A block whose error sits in a faint band beside an opaque part (a band over bone,
  the engine's faint metal beside its plates) would, counted at the block's own opacity, show a few slabs of it.
  The errors of one block add along the ray (the structure a level hides runs across the block); those of
  different blocks are independent and add in quadrature;
- what is in front of it: the block's transmittance (1 − a)^λ multiplies along the ray (a = m₂/m₁, the
  opacity-weighted mean opacity, λ = ℓ · max(f, 1/B), f = m₁²/m₂ its visible share by the opacity moments: where
  the opaque part hides what is behind); where the selection was
  weighted by the camera's view (visibility.py), that weight (the largest transmittance with which a ray of the
  view enters the block) stands for it.

A pixel's error is then √(Σ_b (T_b · n_b · e_b)²) over the blocks b on its ray, and the image's mean ΔE the mean
over the pixels its footprint covers (accumulated opacity ≥ 1/255). A dual-TF composite shows two integrals, the
second over the first, and the second is not attenuated by what the first shows: each TF's errors go along the
rays through its own opacities, and a pixel's add in quadrature (one set of tables with the TFs' maxima counted
the second TF's blocks as hidden behind the first's). Without a view, the rays are the block grid's
columns along each axis, both ways; with the view's weight, along each axis (the weight is direction-free). The
result times RAY_GAIN is the prediction. RAY_GAIN is the one fitted constant (a ray's mean |error| is below its
RMS, and where an opaque surface only moves in depth an unlit picture does not show it): the geometric mean of
measured ÷ predicted over the chest CT's pairs of benchmarks/bench_prediction.py (five TFs, three views, 5:1 to
100:1, both classifications), validated on the engine and bonsai CTs (docs/measurements/prediction.md).
All of it is NumPy over the block grid, O(blocks).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["RAY_GAIN", "RayModel", "ray_delta_e"]

#: fitted on the chest CT alone (module doc); the engine and bonsai CTs validate it
RAY_GAIN = 0.196
_FOOTPRINT = 1.0 / 255.0  # docs/design.md: a pixel is in the footprint from alpha 1/255


@dataclass(frozen=True)
class RayModel:
    """What the ray model needs beside a selection's levels: the grid, each block's length along each axis in TF
    opacity units, and per block (flattened in C order) the spread table ς (N, L), the classification's own ζ (N, L)
    where it adds a bias ("mean"; None for "distribution"), both in the picture's CIELUV, the opacity moments (N, 4:
    level_error.block_zetas) and the view's weight (N,) or None."""

    grid: tuple[int, int, int]
    path: tuple[float, float, float]  # units per block along z, y, x
    spread: np.ndarray
    bias: np.ndarray | None
    opac: np.ndarray
    seen: np.ndarray | None = None


def ray_delta_e(model: RayModel | Sequence[RayModel], levels: np.ndarray, gain: float = RAY_GAIN) -> float:
    """The predicted mean ΔE of the image of a selection (`levels` (N,), −1 not loaded), module doc. A sequence of
    models: the integrals of a dual-TF composite, one per TF, each through its own opacities (the second TF's is
    not attenuated by what the first shows: that is what the composite is for); a pixel's errors from them add in
    quadrature, over the pixels either covers."""
    models = [model] if isinstance(model, RayModel) else list(model)
    lv = np.asarray(levels, np.int64).ravel()
    if not (lv >= 0).any() or not models:
        return 0.0
    parts = [_ray_columns(m, lv) for m in models]
    out = []
    for cols in zip(*parts):  # the same axes and ways in every model: one grid
        err2 = sum(e * e for e, _ in cols)
        footprint = np.logical_or.reduce([f for _, f in cols])
        if footprint.any():
            out.append(float(np.sqrt(err2[footprint]).mean()))
    return gain * float(np.mean(out)) if out else 0.0


def _ray_columns(model: RayModel, lv: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per axis and way along it (module doc), the error of each ray column of the grid (√Σ_b (T_b · n_b · e_b)²)
    and whether the column is in the footprint."""
    loaded = lv >= 0
    rows = np.flatnonzero(loaded)
    k = lv[rows]
    e2 = np.zeros(lv.size)
    e2[rows] = np.asarray(model.spread, np.float64)[rows, k] ** 2
    if model.bias is not None:
        e2[rows] += np.asarray(model.bias, np.float64)[rows, k] ** 2
    opac = np.asarray(model.opac, np.float64)
    m1 = np.where(loaded, opac[:, 0], 0.0)
    m2 = np.where(loaded, opac[:, 1], 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(m1 > 0, m2 / m1, 0.0)
        f = np.where(m2 > 0, m1 * m1 / m2, 0.0)
    a = np.minimum(a, 1.0 - 1e-6)
    block = 1 << max(int(np.asarray(model.spread).shape[1]) - 1, 0)  # B: the coarsest level holds one voxel
    # the error's own slabs: spread over the visible share (ζ's normalisation), at the opacity of the values that
    # carry it (a block's error may sit in its faint part while its opaque part sets its transmittance)
    share = np.where(loaded, opac[:, 2], 0.0)
    a_err = np.minimum(np.where(loaded & (opac[:, 3] > 0), opac[:, 3], a), 1.0 - 1e-6)
    grid = tuple(model.grid)
    seen = None if model.seen is None else np.clip(np.asarray(model.seen, np.float64), 0.0, 1.0).reshape(grid)
    # per unit of path: the block's log transmittance, and its error's slabs' (on the loaded blocks, which alone
    # have an error); each axis scales them by its path (the transcendental functions once, not once per axis)
    log_tau = np.where(a > 0, np.maximum(f, 1.0 / block) * np.log1p(-a), 0.0)
    ae, lam_e = a_err[rows], np.maximum(share[rows], 1.0 / block)
    log_e = lam_e * np.log1p(-ae)
    out = []
    for ax in range(3):
        p = model.path[ax]
        n_slabs = np.where(ae > 1e-12, -np.expm1(p * log_e) / np.maximum(ae, 1e-12), p * lam_e)
        flat = np.zeros(lv.size)
        flat[rows] = n_slabs * n_slabs * e2[rows]
        x2 = np.moveaxis(flat.reshape(grid), ax, 0)
        lt = np.moveaxis(log_tau.reshape(grid), ax, 0)
        footprint = -np.expm1(p * lt.sum(axis=0)) >= _FOOTPRINT
        if seen is not None:
            ways: tuple[tuple[np.ndarray, np.ndarray], ...] = ((np.moveaxis(seen, ax, 0), x2),)
        else:
            t = np.exp(p * lt)
            ways = ((_in_front(t), x2), (_in_front(t[::-1]), x2[::-1]))
        for front, xx in ways:
            out.append((np.sqrt((front * front * xx).sum(axis=0)), footprint))
    return out


def _in_front(tau: np.ndarray) -> np.ndarray:
    """The transmittance in front of each block along axis 0 (1 for the first)."""
    front = np.ones_like(tau)
    np.cumprod(tau[:-1], axis=0, out=front[1:])
    return front
