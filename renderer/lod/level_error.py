"""Significance per level under the classification the kernel will actually use (eq. 3.1 generalised).

The thesis' ζ(0) compares the TF colour at a block's mean with the colours of its histogram, and spreads it
linearly over the levels. With classification by distribution (classification.py) a coarse block no longer shows
T*(mean): its level-k voxels show the Gaussian-classified colour of their own means and spreads. What a block
loses at level k is modelled from its histogram h and the store's per-block, per-level spread s_k (the RMS over
the block's level-k voxels of the standard deviation of the level-0 values behind each):

    ζ(k)² = (1/n_vis) Σ_v h(v) |T*(v) − T̃(v, s_k)|²,        n_vis = max(visible voxels, n / B)

T* is the unit-slab colour in CIELUV (significance.py), T̃(m, s) the unit-slab colour of the distribution
classification (1 − e^−σ̄)·ε̄/σ̄ at mean m and spread s: every value is seen through the spread of the level-k voxel
that holds it, so a block whose colours change within s_k of its values loses them, and one whose TF is flat
there keeps them ("mean" classification: T̃ = T*(m) at the coarse mean, the value shrunk towards the block mean
by √(1 − s_k²/s_top²), the law of total variance's share of the level-k means). Level 0 (s = 0) gives ζ = 0.

Normalising by the visible voxels rather than all of them is what the image needs: a thin visible structure (skin,
a vessel wall, a rib's cortex) is a small share of its block's voxels but covers the block's whole projection, so
its error is not diluted by the transparent rest; the floor n / B is a one-voxel sheet across the block.
Measured as the thesis' fig. 3.4 does, this ranked blocks better than comparing with the colour at the coarse
mean.

The sum runs over the simplified histogram's pieces (restricted to the block's border-inclusive value range) with
three Gauss–Legendre nodes per piece; T* and T̃ are bilinear lookups in one CIELUV table per TF over the
distribution table's (mean, √spread) grid, so the per-block work is O(K) table lookups per level.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from lodcast.renderer.engine import Tables
from lodcast.renderer.lod.classification import DistTable, cached_dist_table
from lodcast.renderer.lod.significance import BlockMeta, as_tf, srgb_to_luv
from lodcast.renderer.lod.zeta_kernel import device_zetas

__all__ = ["block_zetas", "level_zeta", "luv_table", "picture_table", "step_zeta"]

_NODES = np.array([-np.sqrt(3 / 5), 0.0, np.sqrt(3 / 5)])
_WEIGHTS = np.array([5 / 9, 8 / 9, 5 / 9]) / 2.0  # on [−1, 1], normalised to the piece width
_CHUNK = 8192


def _luv(table: DistTable) -> np.ndarray:
    """CIELUV of the unit-slab colour (rows, n, 3) of a distribution table, float32 (block_zetas says why)."""
    alpha = -np.expm1(-table.ext)
    return srgb_to_luv(alpha[..., None] * table.colour()).astype(np.float32)


def _picture(table: DistTable) -> np.ndarray:
    """The unit-slab colour (rows, n, 3) of a distribution table as the picture's CIELUV sees it, float32: the
    premultiplied colour times the Jacobian of CIELUV at the TF's own colour (the mean of its colours weighted by
    their opacities), so that differences are ΔE at the colour the picture shows rather than at the faint colour
    of one slab.

    Why: a ray composites premultiplied colour linearly, so a slab's colour error reaches the picture unchanged
    in those units (times the transmittance in front) and only then becomes a ΔE, at the picture's colour. A
    slab of opacity a has a colour about a times as bright, where CIELUV's lightness is in its linear segment and
    its chroma (u*, v* ∝ L*) nearly vanishes: a difference there (`_luv`) weighs a change of hue by the slab's
    L*, not the picture's. On a translucent TF whose colours change hue (leaves over a trunk) that is most of the
    error (docs/measurements/prediction.md)."""
    alpha = -np.expm1(-table.ext)
    a0 = alpha[0]
    c0 = (a0[:, None] * table.rgb).sum(axis=0) / max(float(a0.sum()), 1e-300)
    h = 1e-4
    c0 = np.clip(c0, h, 1.0 - h)  # (the differences stay within the gamut)
    jac = np.stack([(srgb_to_luv(c0 + d) - srgb_to_luv(c0 - d)) / (2 * h) for d in np.eye(3) * h], axis=1)
    return ((alpha[..., None] * table.colour()) @ jac.T).astype(np.float32)


def luv_table(tf: Any, value_range: tuple[float, float], std_max: float,
              tables: Tables | None = None) -> tuple[DistTable, np.ndarray]:
    """The distribution table of `tf` and its unit-slab colours in CIELUV (kept in `tables` when given)."""
    return _colour_table(tf, value_range, std_max, tables, _luv)


def picture_table(tf: Any, value_range: tuple[float, float], std_max: float,
                  tables: Tables | None = None) -> tuple[DistTable, np.ndarray]:
    """The distribution table of `tf` and its unit-slab colours in the picture's CIELUV (`_picture`; kept in
    `tables` when given)."""
    return _colour_table(tf, value_range, std_max, tables, _picture)


def _colour_table(tf: Any, value_range: tuple[float, float], std_max: float, tables: Tables | None,
                  colours: Any) -> tuple[DistTable, np.ndarray]:
    t = cached_dist_table(as_tf(tf), value_range, std_max, None if tables is None else tables.dist)
    key = (colours.__name__, id(t))
    hit = None if tables is None else tables.luv.get(key)
    if hit is None or hit[0] is not t:
        hit = (t, colours(t))
        if tables is not None:
            tables.luv.put(key, hit, 1)  # (the table held beside it keeps its id from being reused)
    return t, hit[1]


def _pieces(meta: BlockMeta, starts: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The quadrature of the blocks `rows`: values x (m, K, 3), three Gauss–Legendre nodes on each piece of the
    simplified histogram (`starts`: effective_starts, restricted to the block's border-inclusive range), and
    weights wq summing to 1 per block."""
    edges = meta.bins.edges
    st = starts[rows]
    lo, hi = edges[st[:, :-1]], edges[st[:, 1:]]  # (m, K) value interval of each piece
    w = (st[:, 1:] - st[:, :-1]) * meta.heights[rows].astype(np.float64)  # voxels in each piece
    total = w.sum(axis=1)
    x = 0.5 * (lo + hi)[..., None] + 0.5 * (hi - lo)[..., None] * _NODES
    return x, (w[..., None] * _WEIGHTS) / np.maximum(total, 1e-300)[:, None, None]


def _evaluated(meta: BlockMeta, visible: np.ndarray) -> np.ndarray:
    """The blocks worth evaluating: visible, not constant, with a value."""
    return np.flatnonzero(visible & (meta.max_border > meta.min_border) & np.isfinite(meta.mean))


def _opacity_moments(tf: Any, x: np.ndarray,
                     wq: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per block the mean TF opacity and mean squared TF opacity over its values and its visible share; the TF
    opacity at each value."""
    from lodcast.renderer.scene.transfer_function import evaluate

    a = evaluate(tf, x)[1]
    return (wq * a).sum(axis=(1, 2)), (wq * a * a).sum(axis=(1, 2)), (wq * (a > 0)).sum(axis=(1, 2)), a


def block_zetas(meta: BlockMeta, tf: Any, visible: np.ndarray, value_range: tuple[float, float], std_max: float,
                classification: str = "distribution", tables: Tables | None = None,
                worst_values: bool = False, picture: bool = False,
                level_errors: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(ζ(k) per block and level (N, L), ζ_step per block (N,), opacity moments (N, 4: the mean TF opacity over
    the block's values, the mean squared opacity, the visible share, and the opacity of the values that carry the
    step's error, weighted by it: what prediction.py takes), the worst value's ζ(k) per
    block and level (N, L): the largest |T* − T̃| over the values the block holds, where ζ is their RMS; computed
    where `worst_values` asks, else zeros: it costs half as much again, and only "lossless" needs it; the spread
    ς(k) per block and level (N, L), prediction.py's, per visible voxel as ζ: ζ_step · s_k / s_1, the colour change
    over a level-k deviation (what a level-k voxel hides whatever the classification) and, beside it, how far the
    classification's colour at the block's mean (a normal distribution of spread s_k; the TF at the mean) is from
    the mean colour of the values the block holds, weighted by (s_k / s_top)²), float64,
    0 for invisible and constant blocks (and at level 0): `level_zeta` and `step_zeta` in one pass over the blocks' quadrature, which
    they share with the TF's opacities there and the values' table positions (apart, the two repeated that work, a
    good part of a first render). The table lookups run in float32: ζ is a colour difference in CIELUV
    units (0-100) that the selection compares with 0.5. `picture`: the colours differ in the picture's CIELUV
    (`_picture`: what prediction.py takes) instead of each slab's own. `level_errors` False: ζ(k) (and the worst
    values) stay zeros, the rest as with it: what the prediction takes under distribution classification, where
    ζ(k)'s lookups, one per level and value, would be most of the pass. With `tables` of an engine (its `device` set) the blocks
    are evaluated there (zeta_kernel.py: the same arithmetic, a work-item per block); this NumPy path is the
    reference it is tested against."""
    assert classification in ("distribution", "mean") and (level_errors or not worst_values)
    n_lv = meta.n_levels
    out, step, worst = np.zeros((meta.n, n_lv)), np.zeros(meta.n), np.zeros((meta.n, n_lv))
    spread = np.zeros((meta.n, n_lv))
    opac = np.zeros((meta.n, 4))
    todo = _evaluated(meta, visible)
    if todo.size == 0:
        return out, step, opac, worst, spread
    assert meta.level_std is not None, "block_zetas needs a store with per-level spreads (format >= 2)"
    tf = as_tf(tf)
    t, luv = (picture_table if picture else luv_table)(tf, value_range, std_max, tables)
    starts = meta.effective
    if tables is not None and tables.device is not None:
        got = device_zetas(tables.device, meta, tf, todo, starts, t, luv, classification, worst_values,
                           level_errors)
        for a, b in zip((out, step, opac, worst, spread), got):
            a[todo] = b
        return out, step, opac, worst, spread
    row0 = t.std_axis(0.0)
    level_std = meta.level_std
    half_range = np.nan_to_num(0.5 * (meta.max_border - meta.min_border))

    def chunk(rows: np.ndarray) -> None:
        x, wq = _pieces(meta, starts, rows)
        opac[rows, 0], opac[rows, 1], vis_frac, alpha = _opacity_moments(tf, x, wq)
        opac[rows, 2] = vis_frac
        wq = wq.astype(np.float32)
        sheet = np.maximum(vis_frac, 1.0 / (1 << (n_lv - 1)))  # n_vis / n, at least a one-voxel sheet
        if n_lv == 1:
            return
        s = np.asarray(level_std[rows], np.float64)  # (m, L)
        # the step: the colour change over the level-1 spread (½ |T*(v + s_1) − T*(v − s_1)|)
        s1 = s[:, 1][:, None, None]
        d = t.lerp(luv, _f32(t.mean_axis(x + s1)), row0) - t.lerp(luv, _f32(t.mean_axis(x - s1)), row0)
        d2s = wq * (0.25 * (d * d).sum(axis=-1))
        step2 = d2s.sum(axis=(1, 2))
        step[rows] = np.sqrt(np.maximum(step2, 0.0) / sheet)
        # the opacity of the values that carry the step's error (prediction.py: how many of its slabs a ray sees)
        opac[rows, 3] = np.where(step2 > 0, (d2s * alpha).sum(axis=(1, 2)) / np.where(step2 > 0, step2, 1.0), 0.0)
        at_x = _f32(t.mean_axis(x))  # the same values at every level: their table position once
        tstar = t.lerp(luv, at_x, row0)
        mbar = meta.mean[rows][:, None, None]
        s_top = np.maximum(s[:, -1], 1e-300)
        # the block's colours as its histogram holds them, against which the classification's colour at the block's
        # mean (and a level's spread) is a model: far off where the block mixes materials the TF shows apart (air
        # and metal, with a translucent band between them that a normal distribution, or the mean, lands in)
        held = (wq[..., None] * tstar).sum(axis=(1, 2))
        at_mean = _f32(t.mean_axis(meta.mean[rows]))
        for k in range(1, n_lv):
            # what the level's spread hides: the colour change over a deviation s_k about each value, the step's
            # over s_1 scaled by s_k / s_1 (the structure within a level-k voxel, which neither classification keeps;
            # against the values s_k either side, looked up, it predicted no better and doubled this function's cost)
            hidden = step[rows] * np.where(s[:, 1] > 0, s[:, k] / np.maximum(s[:, 1], 1e-300), 0.0)
            modelled = t.lerp(luv, at_mean, _f32(t.std_axis(s[:, k])) if classification == "distribution" else row0)
            model = ((held - modelled) ** 2).sum(axis=-1) * (s[:, k] / s_top) ** 2
            spread[rows, k] = np.sqrt(hidden * hidden + model / sheet)
            if not level_errors:
                continue
            if classification == "distribution":
                shown = t.lerp(luv, at_x, _f32(t.std_axis(s[:, k][:, None, None])))  # one deviation per block
            else:
                rho = np.sqrt(np.clip(1.0 - (s[:, k] / s_top) ** 2, 0.0, 1.0))[:, None, None]
                shown = t.lerp(luv, _f32(t.mean_axis(mbar + rho * (x - mbar))), row0)
            d2 = ((tstar - shown) ** 2).sum(axis=-1)
            out[rows, k] = np.sqrt(np.maximum((wq * d2).sum(axis=(1, 2)), 0.0) / sheet)
            if not worst_values:
                continue
            # the worst value: seen through the largest spread one level-k voxel of the block can have (the
            # spreads' RMS is s_k over its n_k voxels, and no set of values in its border-inclusive range spreads
            # wider than half that range), and in a voxel whose mean lies that far from it: ζ's one spread per
            # block, centred on each value, averages away the few voxels where a thin structure meets its
            # surroundings and misses a smooth gradient flattened into one coarse sample
            sw = np.minimum(s[:, k] * np.sqrt(float((1 << (n_lv - 1 - k)) ** 3)), half_range[rows])[:, None, None]
            row_w = _f32(t.std_axis(sw))
            dw = d2
            for shift in (-sw, 0.0, sw):
                seen_w = t.lerp(luv, _f32(t.mean_axis(x + shift)), row_w)
                dw = np.maximum(dw, ((tstar - seen_w) ** 2).sum(axis=-1))
            worst[rows, k] = np.sqrt(np.where(wq > 0, dw, 0.0).max(axis=(1, 2)))

    # the chunks write disjoint rows, and NumPy lets go of the GIL in their array work: on a million blocks (a
    # large volume's first selection) the cores share it
    chunks = [todo[c0:c0 + _CHUNK] for c0 in range(0, todo.size, _CHUNK)]
    workers = min(len(chunks), os.cpu_count() or 1)
    if workers > 1:
        with ThreadPoolExecutor(workers, thread_name_prefix="lodcast-zeta") as pool:
            list(pool.map(chunk, chunks))
    else:
        for rows in chunks:
            chunk(rows)
    return out, step, opac, worst, spread


def _f32(axis: tuple[np.ndarray, np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A table axis position (entry, next entry, weight) with its weight in float32, so that lookups in a float32
    table stay float32."""
    return axis[0], axis[1], axis[2].astype(np.float32)


def level_zeta(meta: BlockMeta, tf: Any, visible: np.ndarray, value_range: tuple[float, float], std_max: float,
               classification: str = "distribution") -> tuple[np.ndarray, np.ndarray]:
    """(ζ(k) per block and level (N, L) float64: 0 at level 0, 0 for invisible and constant blocks; per block the
    mean TF opacity and the mean squared TF opacity over its values (N, 2), 0 for blocks not evaluated)."""
    z, _, opac, _, _ = block_zetas(meta, tf, visible, value_range, std_max, classification)
    return z, opac[:, :2]


def step_zeta(meta: BlockMeta, tf: Any, visible: np.ndarray, value_range: tuple[float, float],
              std_max: float) -> tuple[np.ndarray, np.ndarray]:
    """(ζ_step per block (N,), opacity moments (N, 2) as level_zeta's): the RMS change of the unit-slab colour
    over one voxel along a ray, per visible voxel, from the block's histogram and its level-1 spread s_1 (the
    spread of the values within 2³ voxels: a ray crossing one voxel sees values change by about that much),
    ½ |T*(v + s_1) − T*(v − s_1)| at every value v of the block. What a ray marcher misses between samples h
    voxels apart grows as h² times this (selection.step_delta_e). 0 for invisible and constant blocks."""
    assert meta.level_std is not None and meta.n_levels > 1, "step_zeta needs per-level spreads (format >= 2)"
    _, z, opac, _, _ = block_zetas(meta, tf, visible, value_range, std_max)
    return z, opac[:, :2]
