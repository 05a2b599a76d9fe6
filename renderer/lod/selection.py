"""Level-of-detail selection under a memory budget (thesis §3.2.2, eq. 3.2) and the fig. 3.4 baselines.

Levels are the store's: level 0 = full resolution (B³ samples per block), level L−1 = one sample per block,
level −1 = not loaded. n(k) = (B >> k)³ samples; the atlas holds float32, 4 bytes per sample.

The thesis' greedy: every block with non-zero significance starts at the coarsest level; a priority queue holds
every transition γ → γ* from a block's current level to any finer allowed level, with priority

    χ = (ζ(γ) − ζ(γ*)) / (n_γ* − n_γ)                                                         (eq. 3.2)

the best transition is taken while the budget allows (here: the selection stops at the first best transition
that does not fit), defunct transitions of that block are removed and its new ones inserted. Blocks of zero
significance are never inserted. Ties are broken by block index (C order), then by the nearer target.

Fast and exact equivalent (what `greedy` runs): from a block's current level the best transition goes to the
vertex reached by the steepest chord (the lower convex hull of the block's (n, ζ) points); the chain of such
steepest chords has non-increasing slopes (if the next chord were steeper, the chord skipping the middle vertex
would have been steeper than the one taken). So the queue pops, across blocks, chords in the order of their
slopes, each block's chords in chain order: sorting all chain chords by slope (stable, block-major, chain-minor
for ties) and taking them until the first that does not fit gives the same levels as the queue. The cut-off is
found by a sample-guided weighted selection (O(M) over the M chords; only a few thousand around the cut are
sorted), not a full sort. A float rounding that would make a
chain slope rise by an ulp is clamped to the previous slope, which is exactly when the queue would take that chord
next. `tests/test_selection.py` checks this against a literal heapq implementation.

Which blocks are loaded: a block is *TF-empty* (ζ = 0 and nothing visible: see significance.py) → −1, never
read; a block outside the crop box → −1; a visible block of zero significance (constant value) is loaded at the
coarsest level, which represents it exactly, and never refined. (The thesis says zero-significance blocks are
not loaded; read literally that would punch holes where a block is visible but uniform in the TF's colour — a
constant block, or one whose values all lie where the TF is constant. Such a block costs one sample.)

Quality: "full" = every block in the crop at level 0 (the reference; nothing skipped); "lossless" (virtually
lossless) = unlimited budget: every block of non-zero significance at its finest allowed level; {"budget_mb": x}
(MiB, 2^20 bytes) or {"reduction": r} (budget = full-resolution bytes of the whole volume at 4 bytes per voxel
÷ r). A budget below what every visible block needs at its coarsest level raises SceneError naming `quality`.
Bytes count whole bricks (B >> k)³, padding included, so "full" on a volume that is not a multiple of B reports a
reduction slightly below 1. Crop: a block is dropped when its box grown by one voxel misses the crop box;
`max_level` (grid-shaped) limits the finest level per block (e.g. for blocks cut by the crop).

Significance per level: with a store of format 2 (per-block, per-level spreads) the "tf" method takes ζ(k) from
level_error.py, what level k shows under the classification the kernel will use, and the greedy runs on those
tables (any shape, not the thesis' linear profile); format-1 stores keep eq. 3.1 spread linearly over the levels.

Predicted ΔE of a selection (a store with per-level spreads): renderer/lod/prediction.py, what each block's
error shows along the rays that cross it (the unit slabs of it a ray takes, the transmittance in front of it,
errors of different blocks in quadrature; the view's weight where the selection took it). It is the level of
detail's own error, against full resolution at the same step. A render's report adds the step's own error
(step_delta_e: against the step-¼ reference, STEP_GAIN · h² · RMS(ζ_step) / ā, fitted on two CTs and seven TFs),
so that it predicts what docs/design.md measures, and adaptive screen-space sampling's (renderer/frame/screen.py).
A format-1 store (eq. 3.1 spread linearly over the levels, no spreads) keeps the older image-wide model: the
count-weighted RMS over loaded blocks of ζ at the chosen level, times IMAGE_GAIN / ā ("lossless") or BUDGET_GAIN /
ā (the budgeted qualities), ā the opacity-weighted mean opacity of the loaded voxels (docs/measurements/code-notes.md).
Both are estimates of docs/design.md's measured ΔE, not bounds.

What the camera sees (`visibility`, renderer/lod/visibility.py; a render passes it at the budgeted qualities where
`sampling.lod_visibility` says so, by default for volumes of up to 2^27 voxels): per block the largest
transmittance with which a ray of a low-resolution cast of the view enters it. It multiplies ζ where the greedy
weighs it, and the prediction takes it for the transmittance in front of the block (an occluded block's error
does not reach the picture), so a block behind opaque material stays coarse and the budget goes to what the image
shows. 'lossless' does not take it (it promises the full-resolution image from any view); the "l2"
and "uniform" baselines ignore it.

What the greedy weighs: per block and level √(ζ(k) · s_k) (times the view's weight), s_k the store's per-block,
per-level spread (the RMS over the block's level-k voxels of the standard deviation of the level-0 values behind
each), where ζ alone would be the thesis' choice. ζ models what each value loses through the level's blur of the
TF, not where the level moves structure: a block whose colours survive the blur but whose voxels spread widely
loses its shapes (a translucent skin's folds, trabecular bone), which s_k measures and ζ does not; the geometric
mean ranks first the blocks where both are large, and a block of either zero stays coarse. Over two CTs, four
TFs, two views and 5:1 to 100:1 this lowered the summed mean ΔE against the step-¼ reference, with the view's
weight and without, for every TF, and moved no single image noticeably. ζ stays the prediction's and
'lossless''s measure (a ΔE); the product only orders the greedy. What such a greedy leaves coarse loses less in
the picture than its ζ says, so its prediction takes its own gain, BUDGET_GAIN (0.44, fitted as IMAGE_GAIN was,
on the budgeted qualities; with IMAGE_GAIN their error was predicted too high).

TF-empty blocks are excluded from the prediction (they show nothing either way), as are blocks outside the crop.
"lossless" promises no visible difference from full resolution at the same sampling. It keeps each block at the
coarsest level where (a) its ζ, (b) its worst value's error (each value seen through the largest spread one of the
block's level-k voxels can have, from a mean that far off: level_error.block_zetas) and (c) what its faces show of
values only its neighbours hold (full resolution interpolates across a face, a coarse block cuts it off) stay
within LODCAST_LOSSLESS_ZETA (a) and LOSSLESS_WORST_RATIO times that (b, c), each accumulated along a ray as far as the block's own
opacity lets it (IMAGE_GAIN / a, a the block's opacity-weighted mean opacity: a translucent band's small per-slab
errors add up along every ray through it, which one image-wide ā hid). No block is coarser than the 10:1 selection
keeps it. Where the TF shows a wide band, this leaves little to drop, and the report's reduction says so.
"""
from __future__ import annotations

import json
import weakref
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from lodcast.renderer.engine import Tables
from lodcast.renderer.image.delta_e import srgb_to_luv
from lodcast.renderer.lod.level_error import block_zetas
from lodcast.renderer.lod.prediction import RayModel, ray_delta_e
from lodcast.renderer.lod.significance import (
    BlockMeta,
    as_tf,
    block_significance,
    level_profile,
    meta_of_store,
    tf_visible,
)
from lodcast.renderer.scene.clip import block_bounds
from lodcast.renderer.scene.transfer_function import evaluate, unit_distance

__all__ = ["LOSSLESS_ZETA", "LodSelection", "select_lod", "select_from_meta", "greedy", "parse_quality", "crop_mask", "step_delta_e",
           "BYTES_PER_SAMPLE", "MB"]

BYTES_PER_SAMPLE = 4
MB = 1 << 20  # budget_mb counts MiB, as GPU memory is counted

METHODS = ("tf", "tf_full_hist", "l2", "uniform")
#: the ΔE per block that "lossless" allows by default (LODCAST_LOSSLESS_ZETA overrides it in an engine)
LOSSLESS_ZETA = 0.5
#: the worst value a block holds (its largest |T* − T̃| rather than the RMS over its values) may lose this many
#: times as much: at the default, 1 ΔE
LOSSLESS_WORST_RATIO = 2.0
#: image-space calibration of the predicted ΔE (see module doc), fitted so that the geometric mean of measured /
#: predicted is 1 over a set of CT renders (docs/measurements/code-notes.md): mean ΔE ≈
#: IMAGE_GAIN · RMS(ζ) / ā, ā the opacity-weighted mean opacity of the loaded voxels (translucent structures add
#: colour errors up over ~1/ā unit slabs along a ray; opaque ones show about one)
IMAGE_GAIN = 0.72
#: the same for the budgeted qualities, whose greedy orders by √(ζ · s_k) and the view's weight (module doc: what
#: it leaves coarse loses less in the picture than ζ says): geometric mean of measured / predicted = 1 over
#: bench_consistent_lod.py's budgeted rows (docs/measurements/code-notes.md)
BUDGET_GAIN = 0.44
#: the step's own error (step_delta_e): mean ΔE against the step-¼ reference ≈ STEP_GAIN · h² · RMS(ζ_step) / ā,
#: fitted on renders of two CTs under seven TFs at steps ½ and 1: geometric mean of measured / predicted = 1 over
#: all of them but one outlying view (docs/measurements/code-notes.md)
STEP_GAIN = 0.052
MIN_OPACITY = 0.05


@dataclass(frozen=True)
class LodSelection:
    levels: np.ndarray  # grid-shaped int8: store level per block (0 = full), -1 = not loaded
    zeta: np.ndarray  # grid + (n_levels,) float32: ΔE significance per block per level (0 at level 0)
    predicted_delta_e: float
    bytes: int  # atlas bytes of the selection (4 bytes per sample)
    reduction: float  # full-resolution bytes / selection bytes (inf when nothing is loaded)
    blocks_skipped: int  # blocks not loaded (zero significance or outside the crop)
    # what the prediction took beside the levels (prediction.ray_delta_e(rays, other_levels) predicts another
    # selection of the same store, TFs and view); None for a format-1 store
    rays: tuple[RayModel, ...] | None = None  # one per TF (a dual-TF composite's two integrals)


# --------------------------------------------------------------------------------------------- quality
def parse_quality(quality: Any, full_bytes: int) -> tuple[str, float | None]:
    """("full" | "lossless" | "budget" | "level", budget in bytes or the level, or None). Accepts the scene's
    strings, dicts and pydantic quality objects."""
    if hasattr(quality, "model_dump"):
        quality = quality.model_dump()
    if isinstance(quality, str):
        if quality in ("full", "lossless"):
            return quality, None
        raise ValueError(f"quality: unknown quality {quality!r} (full, lossless, budget_mb or reduction)")
    if isinstance(quality, dict):
        if "budget_mb" in quality:
            mb = float(quality["budget_mb"])
            if not mb > 0:
                raise ValueError("quality.budget_mb must be > 0")
            return "budget", mb * MB
        if "reduction" in quality:
            r = float(quality["reduction"])
            if not r >= 1.0:
                raise ValueError("quality.reduction must be >= 1")
            return "budget", full_bytes / r
        if "level" in quality:
            k = quality["level"]
            if not isinstance(k, (int, np.integer)) or isinstance(k, bool) or k < 0:
                raise ValueError("quality.level must be a whole number >= 0")
            return "level", float(k)
    raise ValueError(f"quality: cannot read {quality!r} (full, lossless, {{budget_mb: x}}, {{reduction: r}} or "
                     "{level: k})")


# --------------------------------------------------------------------------------------------- crop
def crop_mask(grid: Sequence[int], shape: Sequence[int], spacing: Sequence[float], origin: Sequence[float],
              block_size: int, crop: Any) -> np.ndarray:
    """Grid-shaped bool: True where a block meets the crop box. `crop` = (lower, upper) in world (z, y, x) or
    {"lower": …, "upper": …}. A block's box is its voxels' box (half a voxel beyond the outer centres) grown by one
    voxel each side, so that every interpolation stencil of a sample inside the crop box is loaded."""
    if isinstance(crop, dict):
        lo, hi = crop.get("lower", crop.get("min")), crop.get("upper", crop.get("max"))
    else:
        lo, hi = crop
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    b_lo, b_hi = block_bounds(grid, shape, spacing, origin, block_size)
    inside = [(b_hi[ax] > lo[ax]) & (b_lo[ax] < hi[ax]) for ax in range(3)]
    return inside[0][:, None, None] & inside[1][None, :, None] & inside[2][None, None, :]


# --------------------------------------------------------------------------------------------- greedy
def _mark(taken: np.ndarray, cand: np.ndarray | None, mask: np.ndarray) -> None:
    if cand is None:
        taken |= mask
    else:
        taken[cand[mask]] = True


def _take_prefix(keys: np.ndarray, costs: np.ndarray, budget: int) -> np.ndarray:
    """Boolean mask of the longest prefix, in the order (keys descending, index ascending), whose costs fit in
    `budget` (stops at the first item that does not fit).

    A weighted selection in O(M): each round estimates the cut from a strided sample and splits the candidates
    into keys above a band around it (taken whole if they fit), the band, and keys below; it then continues in
    the one part that holds the cut. Only the last few thousand candidates are sorted (stably)."""
    m = keys.size
    kc = np.asarray(keys, np.float64)
    cc = np.asarray(costs, np.int64)
    remaining = int(budget)
    taken = np.zeros(m, bool)
    cand = None  # None: every item (masks on the full arrays, no index arrays), else ascending indices
    while kc.size > 4096:
        step = kc.size // 8192 + 1
        sample_k = kc[::step]
        so = np.argsort(-sample_k, kind="stable")
        sk = sample_k[so]
        scum = np.cumsum(cc[::step][so]) * step
        pos = int(np.searchsorted(scum, remaining, side="right"))
        w = 32 + int(4 * np.sqrt(sk.size))
        p_hi = sk[max(pos - w, 0)]
        p_lo = sk[min(pos + w, sk.size - 1)]
        hi = kc > p_hi
        c_hi = int(np.dot(hi.view(np.uint8).astype(np.int64), cc))
        if c_hi > remaining:
            part = hi
        else:
            band = (kc >= p_lo) & ~hi
            c_band = int(np.dot(band.view(np.uint8).astype(np.int64), cc))
            if c_band > remaining - c_hi:
                if c_hi == 0 and c_band == int(cc.sum()):  # no progress (everything in the band): sort it
                    break
                _mark(taken, cand, hi)
                remaining -= c_hi
                part = band
            else:
                sel = hi | band
                _mark(taken, cand, sel)
                remaining -= c_hi + c_band
                part = ~sel
        idx = np.flatnonzero(part)
        cand = idx if cand is None else cand[idx]
        kc, cc = kc[idx], cc[idx]
    if cand is None:
        cand = np.arange(m)
    order = np.argsort(-kc, kind="stable")
    cs = np.cumsum(cc[order])
    k = int(np.searchsorted(cs, remaining, side="right"))
    taken[cand[order[:k]]] = True
    return taken


def _chains_general(z: np.ndarray, maxlev: np.ndarray, nsamp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Steepest-chord chains for arbitrary ζ tables: (slopes (N, L−1) with −inf past the chain end, targets)."""
    n, L = z.shape
    rows = np.arange(n)
    cur = np.full(n, L - 1, np.int64)
    slopes = np.full((n, L - 1), -np.inf)
    targets = np.full((n, L - 1), -1, np.int64)
    for step in range(L - 1):
        zc = z[rows, cur]
        nc = nsamp[cur]
        best = np.full(n, -np.inf)
        best_to = cur.copy()
        for d in range(1, L):
            to = cur - d
            ok = to >= maxlev
            if not ok.any():
                break
            toc = np.maximum(to, 0)
            with np.errstate(invalid="ignore"):
                chi = (zc - z[rows, toc]) / (nsamp[toc] - nc)
            better = ok & ((chi > best) | ((best == -np.inf) & (best_to == cur)))
            best = np.where(better, chi, best)
            best_to = np.where(better, to, best_to)
        moved = best_to < cur
        slopes[:, step] = np.where(moved, best, -np.inf)
        targets[:, step] = np.where(moved, best_to, -1)
        cur = best_to
        if not moved.any():
            break
    return slopes, targets


def _profile_chain(w: np.ndarray, nsamp: np.ndarray, m: int) -> list[int] | None:
    """Steepest-chord chain of a shared profile w (ζ = ζ0·w) down to level m, if it is unambiguous (every
    choice wins by a relative margin, so that any ζ0 > 0 gives the same chain in floating point); else None."""
    L = w.size
    cur, chain = L - 1, []
    while cur > m:
        chis = [((w[cur] - w[t]) / (nsamp[t] - nsamp[cur]), t) for t in range(cur - 1, m - 1, -1)]
        best = max(c for c, _ in chis)
        if not best > 0:
            return None
        close = [t for c, t in chis if c >= best * (1 - 1e-9)]
        if len(close) != 1:
            return None
        cur = close[0]
        chain.append(cur)
    return chain


def greedy(
    zeta: np.ndarray,
    maxlev: np.ndarray,
    nsamp: np.ndarray,
    budget_samples: float,
    profile: np.ndarray | None = None,
) -> np.ndarray:
    """Levels (N,) int64 of the eq. 3.2 greedy for blocks that all start at the coarsest level L−1.

    zeta (N, L): significance per level (store numbering); maxlev (N,): finest level each block may take;
    nsamp (L,): samples per block per level; budget_samples: samples that may be added beyond the start.
    profile: if every row is ζ0·profile, the chains are computed once per max level (faster)."""
    z = np.asarray(zeta, np.float64)
    n, L = z.shape
    maxlev = np.asarray(maxlev, np.int64)
    nsamp = np.asarray(nsamp, np.int64)
    levels = np.full(n, L - 1, np.int64)
    if n == 0 or L == 1:
        return levels
    slopes = targets = costs = None
    if profile is not None:
        classes = np.flatnonzero(np.bincount(np.clip(maxlev, 0, L - 1), minlength=L))
        chains = {int(m): _profile_chain(np.asarray(profile, np.float64), nsamp, int(m)) for m in classes}
        if all(c is not None for c in chains.values()):
            zt = np.ascontiguousarray(z.T)  # (L, N): contiguous columns
            slopes = np.full((n, L - 1), -np.inf)
            targets = np.full((n, L - 1), -1, np.int64)
            costs = np.zeros((n, L - 1), np.int64)
            for m, chain in chains.items():
                assert chain is not None
                rows = np.flatnonzero(maxlev == m) if len(chains) > 1 else slice(None)
                prev = L - 1
                for step, to in enumerate(chain):
                    dn = int(nsamp[to] - nsamp[prev])
                    if len(chains) > 1:
                        slopes[rows, step] = (zt[prev, rows] - zt[to, rows]) / float(dn)
                    else:
                        np.divide(zt[prev] - zt[to], float(dn), out=slopes[:, step])
                    targets[rows, step] = to
                    costs[rows, step] = dn
                    prev = to
    if slopes is None:
        slopes, targets = _chains_general(z, maxlev, nsamp)
    assert targets is not None  # set with slopes, above
    for j in range(1, L - 1):  # clamp an ulp's rise (see module doc); column-wise, -inf past a chain's end stays
        np.minimum(slopes[:, j], slopes[:, j - 1], out=slopes[:, j])
    valid = targets >= 0
    if costs is None:
        costs = np.zeros((n, L - 1), np.int64)
        prev = np.full(n, L - 1, np.int64)
        for j in range(L - 1):
            tj = targets[:, j]
            vj = tj >= 0
            costs[:, j] = np.where(vj, nsamp[np.maximum(tj, 0)] - nsamp[prev], 0)
            prev = np.where(vj, tj, prev)
    total = int(costs.sum())
    if budget_samples >= total:
        cnt = valid.sum(axis=1)
    else:
        # invalid items (past a chain's end) have key -inf: they sort after every valid item, and the cut falls
        # before them because the valid items alone exceed the budget
        t = _take_prefix(slopes.ravel(), np.maximum(costs, 1).ravel(), int(max(budget_samples, 0))).reshape(n, L - 1)
        cnt = np.zeros(n, np.int64)
        for j in range(L - 1):
            cnt += t[:, j]
    pick = np.maximum(cnt - 1, 0)
    return np.where(cnt > 0, np.take_along_axis(targets, pick[:, None], axis=1)[:, 0], L - 1)


# --------------------------------------------------------------------------------------------- entry
def _predicted(zeta_tab: np.ndarray, levels: np.ndarray, count: np.ndarray, opac: np.ndarray | None = None,
               gain: float = IMAGE_GAIN, rays: Sequence[RayModel] | None = None) -> float:
    """The selection's predicted image ΔE (see module doc). With `rays` (a store with per-level spreads): what
    the blocks' errors show along the rays that cross them (prediction.ray_delta_e; `gain` unused). Without (a
    format-1 store): the count-weighted RMS of ζ at the chosen levels; with the blocks' opacity moments (N, 2)
    known, times gain / ā, ā the opacity-weighted mean opacity of every loaded voxel."""
    if rays is not None:
        return ray_delta_e(rays, levels)
    loaded = levels >= 0
    if not loaded.any():
        return 0.0
    z = zeta_tab[np.flatnonzero(loaded), levels[loaded]].astype(np.float64)
    w = np.nan_to_num(count[loaded].astype(np.float64))
    if w.sum() <= 0:
        return 0.0
    rms = float(np.sqrt((w * z * z).sum() / w.sum()))
    return rms if opac is None else rms * _image_gain(opac, count, loaded, gain)


def _image_gain(opac: np.ndarray, count: np.ndarray, loaded: np.ndarray, gain: float = IMAGE_GAIN) -> float:
    """gain / ā, ā the opacity-weighted mean TF opacity over the voxels of the `loaded` blocks (from the
    blocks' opacity moments (N, 2))."""
    w = np.nan_to_num(count[loaded].astype(np.float64))
    m1, m2 = (w[:, None] * opac[loaded][:, :2]).sum(axis=0)
    return gain / max(m2 / m1 if m1 > 0 else 1.0, MIN_OPACITY)


def step_delta_e(meta: BlockMeta, tfs: Sequence[Any], step: float, in_crop: np.ndarray | None = None,
                 tables: Tables | None = None) -> float:
    """The predicted mean ΔE that sampling every `step` voxels adds against the reference (step ¼, docs/design.md):
    STEP_GAIN · step² · RMS / ā. RMS: of ζ_step (level_error.step_zeta: the colour change over one voxel along a
    ray) over the visible blocks in the crop, weighted by their voxels; ā as for the level of detail (ζ_step is a
    unit slab's; a ray shows ~1/ā of them). A ray marcher's error at step h against a finer one grows as h²
    (as measured on every scene of the fit). 0 for a store without per-level spreads
    (format 1) or with one level. The unshaded point-sampled integral: lighting and pre-integration change it."""
    if meta.level_std is None or meta.n_levels < 2:
        return 0.0
    _, z, opac, visible, _ = _max_tables(meta, tfs, "distribution", tables)  # ζ_step: the same under either classification
    loaded = visible if in_crop is None else visible & np.asarray(in_crop, bool).ravel()
    w = np.nan_to_num(meta.count[loaded].astype(np.float64))
    if not loaded.any() or w.sum() <= 0:
        return 0.0
    rms = float(np.sqrt((w * z[loaded] ** 2).sum() / w.sum()))
    return rms * float(step) ** 2 * _image_gain(opac, meta.count, loaded, STEP_GAIN)


def select_from_meta(
    meta: BlockMeta,
    tfs: Sequence[Any] | Any,
    quality: Any,
    *,
    n_voxels: int,
    block_size: int,
    in_crop: np.ndarray | None = None,
    max_level: np.ndarray | None = None,
    method: str = "tf",
    classification: str = "distribution",
    visibility: np.ndarray | None = None,
    lossless_zeta: float = LOSSLESS_ZETA,
    tables: Tables | None = None,
    path: Sequence[float] | None = None,
) -> LodSelection:
    """select_lod on flattened block metadata (what the benchmarks and tests drive directly). path: a block's
    length along z, y, x in the TFs' opacity units (select_lod: from the store's spacing); None: one unit per
    voxel."""
    if method not in METHODS:
        raise ValueError(f"unknown LOD method {method!r} (one of {', '.join(METHODS)})")
    L = meta.n_levels
    n = meta.n
    nsamp = np.array([(block_size >> k) ** 3 for k in range(L)], np.int64)
    full_bytes = int(n_voxels) * BYTES_PER_SAMPLE
    kind, budget = parse_quality(quality, full_bytes)
    crop = np.ones(n, bool) if in_crop is None else np.asarray(in_crop, bool).ravel()
    maxlev = np.zeros(n, np.int64) if max_level is None else np.clip(np.asarray(max_level, np.int64).ravel(), 0, L - 1)
    prof = level_profile(L)
    per_level = meta.level_std is not None and method == "tf"
    opac = None
    tf_list = [tfs] if isinstance(tfs, dict) or hasattr(tfs, "points") else list(tfs)
    if per_level and kind == "lossless" and tables is not None:  # (its tables, with the worst values, serve the drive's below)
        _max_tables(meta, tf_list, classification, tables, worst=True)
    if per_level:  # what each level will show under the kernel's classification (level_error.py); eq. 3.1 unused
        zeta_tab, opac, visible, drive_base, drive_max, picture = _drive_tables(meta, tf_list, classification, tables)
    else:
        z0, visible = block_significance(meta, tfs, "tf_full_hist" if method == "tf_full_hist" else "tf")
        zeta_tab = (z0[:, None] * prof[None, :]).astype(np.float32)
    # what the selection weighs: ζ, times what the camera sees of the block (visibility.py) when that is given;
    # the greedy takes it with the level's spread (module doc: "What the greedy weighs")
    seen = None if visibility is None or method not in ("tf", "tf_full_hist") else \
        np.clip(np.asarray(visibility, np.float64).ravel(), 0.0, 1.0)
    weight = meta.count if seen is None else meta.count * seen
    if per_level:  # (the view's weight scales whole rows: its maximum is the TF's maximum times the weight)
        z0 = drive_max if seen is None else drive_max * seen  # a block is refined if some level loses anything
    elif seen is not None:
        z0 = z0 * seen
    if kind == "full":
        levels = np.where(crop, maxlev, -1)
    else:
        loaded = visible & crop
        levels = np.where(loaded, L - 1, -1).astype(np.int64)
        if method == "l2":
            drive = zeta0_l2_cached(meta, visible)
        else:
            drive = z0
        refine = loaded & (drive > 0) & (maxlev < L - 1)
        base_samples = int(loaded.sum()) * int(nsamp[L - 1])
        if kind == "lossless" and per_level:
            # (every loaded block: one of no significance of its own may still border what the TF shows)
            some = loaded & (maxlev < L - 1)
            levels[some] = _lossless_levels(meta, tf_list, classification, tables, maxlev, lossless_zeta,
                                            LOSSLESS_WORST_RATIO * lossless_zeta, block_size)[some]
            # what 10:1 keeps finer, lossless keeps too (a bound on what the model above can miss)
            ten = select_from_meta(meta, tf_list, {"reduction": 10.0}, n_voxels=n_voxels, block_size=block_size,
                                   in_crop=in_crop, max_level=max_level, classification=classification,
                                   tables=tables, path=path).levels.ravel().astype(np.int64)
            levels = np.where(loaded & (ten >= 0), np.minimum(levels, np.where(ten >= 0, ten, L - 1)), levels)
        elif kind == "lossless":
            levels[refine] = maxlev[refine]
        elif kind == "level":
            assert budget is not None  # parse_quality gives the level with kind "level"
            if int(budget) > L - 1:
                from lodcast.renderer.scene.scene import SceneError

                raise SceneError(f"quality.level: {int(budget)} is past the store's coarsest level, {L - 1}")
            # every visible block at the level, even one the TF shows as constant (what the level shows, and what
            # its prediction counts); a block whose finest allowed level is coarser takes that one
            levels[loaded] = np.maximum(int(budget), maxlev)[loaded]
        else:
            assert budget is not None  # parse_quality gives one with kind "budget"
            budget_samples = int(budget // BYTES_PER_SAMPLE)
            if budget_samples < base_samples:
                from lodcast.renderer.scene.scene import SceneError

                raise SceneError(
                    f"quality: the budget ({budget / MB:.4g} MB) is below the {base_samples * BYTES_PER_SAMPLE / MB:.4g} MB "
                    "that every visible block at its coarsest level needs"
                )
            if method == "uniform":
                for k in range(L):
                    lv = np.maximum(k, maxlev[loaded])
                    if int(nsamp[lv].sum()) <= budget_samples:
                        levels[loaded] = lv
                        break
            elif per_level:
                rows = np.flatnonzero(refine)
                drive_rows = drive_base[rows]  # (a copy: fancy indexing)
                if seen is not None:
                    drive_rows *= seen[rows, None]
                levels[rows] = greedy(drive_rows, maxlev[rows], nsamp, budget_samples - base_samples)
            else:
                rows = np.flatnonzero(refine)
                ztab = drive[rows, None] * prof[None, :]
                levels[rows] = greedy(ztab, maxlev[rows], nsamp, budget_samples - base_samples, profile=prof)
    loaded = levels >= 0
    samples = int(nsamp[levels[loaded]].sum())
    nbytes = samples * BYTES_PER_SAMPLE
    rays = None
    if per_level and opac is not None:
        block_path = tuple(float(x) for x in (path or (block_size,) * 3))
        rays = tuple(RayModel(tuple(meta.grid), block_path, spread_t, zeta_t if classification == "mean" else None,  # type: ignore[arg-type]
                              opac_t, seen) for zeta_t, spread_t, opac_t in picture)
    return LodSelection(
        levels=levels.astype(np.int8).reshape(meta.grid),
        zeta=zeta_tab.reshape(tuple(meta.grid) + (L,)),
        # (a level asked for takes the budgeted qualities' gain: their selections at 10–30:1, from which it was
        # fitted, are mostly made of level-1 and level-2 blocks)
        predicted_delta_e=0.0 if kind == "full" else _predicted(zeta_tab, levels, weight, opac,
                                                                IMAGE_GAIN if kind == "lossless" else BUDGET_GAIN,
                                                                rays),
        bytes=nbytes,
        reduction=(full_bytes / nbytes) if nbytes else float("inf"),
        blocks_skipped=int((~loaded).sum()),
        rays=rays,
    )


def _lossless_levels(meta: BlockMeta, tfs: Sequence[Any], classification: str, tables: Tables | None,
                     maxlev: np.ndarray, mean_bound: float, worst_bound: float, block_size: int) -> np.ndarray:
    """Per block the coarsest level (not finer than `maxlev`) at which the block's error, accumulated along a ray
    as far as the block's own opacity lets it, stays within `mean_bound` for the RMS over its values (ζ) and within
    `worst_bound` for its worst value. A translucent block's error adds up over the ~1/a unit slabs a ray crosses
    before its own material hides what follows (a its opacity-weighted mean opacity, at most the volume's
    diagonal): measured against one image-wide ā, as before, a band at α ≈ 0.006 beside bone passed blocks whose
    small per-slab errors summed to several ΔE along every ray through the band."""
    zeta, _, opac, _, worst = _max_tables(meta, tfs, classification, tables, worst=True)
    n_lv = zeta.shape[1]
    m1, m2 = opac[:, 0], opac[:, 1]
    a = np.where(m1 > 0, m2 / np.maximum(m1, 1e-300), 1.0)
    depth = block_size * float(np.linalg.norm(np.asarray(meta.grid, np.float64)))
    acc = (IMAGE_GAIN / np.maximum(a, 1.0 / depth))[:, None]
    # (levels finer than a block's max level count as fine: they are not allowed anyway)
    ok = ((zeta * acc <= mean_bound) & (worst * acc <= worst_bound)) | (np.arange(n_lv)[None, :] < maxlev[:, None])
    first_bad = np.where(ok.all(axis=1), n_lv, ok.argmin(axis=1))
    lv = np.maximum(first_bad - 1, maxlev)
    if meta.own_min is not None and meta.own_max is not None:
        # full resolution interpolates across a block's faces, so within half a voxel of them it shows what only
        # the neighbours hold; a coarse block (and its level-0 neighbour, whose apron then stops at the face)
        # cuts that off, which ζ, over the block's own spreads, does not see: a surface there moves at the face
        face = np.zeros(meta.n, np.float64)
        for t in tfs:
            face = np.maximum(face, _face_error(t, meta.min_border, meta.own_min, meta.own_min, meta.own_max))
            face = np.maximum(face, _face_error(t, meta.own_max, meta.max_border, meta.own_min, meta.own_max))
        lv = np.where(face * acc[:, 0] > worst_bound, maxlev, lv)
    return lv


def _face_error(tf: Any, lo: np.ndarray, hi: np.ndarray, own_lo: np.ndarray, own_hi: np.ndarray) -> np.ndarray:
    """Per block the largest unit-slab ΔE between the TF anywhere on [lo, hi] (values only its neighbours hold) and
    at either end of its own range [own_lo, own_hi]; 0 where lo ≥ hi or nothing there is visible."""
    out = np.zeros(lo.shape, np.float64)
    rows = np.flatnonzero((lo < hi) & np.isfinite(lo) & np.isfinite(hi) & tf_visible(tf, lo, hi))
    if rows.size == 0:
        return out
    t = as_tf(tf)
    a, b = lo[rows, None], hi[rows, None]
    knots = np.array([p.value for p in t.points], np.float64)[None, :]
    x = np.concatenate([a + (b - a) * np.linspace(0.0, 1.0, 9)[None, :], np.clip(knots, a, b)], axis=1)

    def slab(v: np.ndarray) -> np.ndarray:
        rgb, op = evaluate(t, v)
        return srgb_to_luv(op[..., None] * rgb)

    there = slab(x)
    for own in (own_lo[rows], own_hi[rows]):
        out[rows] = np.maximum(out[rows], np.linalg.norm(there - slab(own)[:, None, :], axis=-1).max(axis=1))
    return out


def _tf_tables(meta: BlockMeta, tf: Any, classification: str, tables: Tables | None,
               worst: bool = False) -> tuple[np.ndarray, ...]:
    """(ζ(k) per block and level (N, L) float32, ζ_step (N,), opacity moments (N, 4), TF-visible blocks (N,), the
    worst value's ζ(k) (N, L) float32, zeros unless `worst` asks for it) of one TF (level_error.block_zetas). They
    depend on the store and the TF, not on the view or the budget, and cost a noticeable part of a first render:
    kept for the last few in `tables` (keyed by the metadata object, which `tables` keeps per store; tables with
    the worst values serve those without)."""
    key = (id(meta), json.dumps(as_tf(tf).model_dump(mode="json"), sort_keys=True), classification)
    for k in ((key + ("worst",),) if worst else (key + ("worst",), key)):
        hit = None if tables is None else tables.tf.get(k)
        if hit is not None and hit[0]() is meta:
            return hit[1]
    visible = tf_visible(tf, meta.min_border, meta.max_border)
    assert meta.value_range is not None  # a store's metadata has it (meta_of_store), and only a store's has spreads
    zeta, step, opac, w, _ = block_zetas(meta, tf, visible, meta.value_range, meta.std_max, classification, tables,
                                         worst_values=worst)
    out = (zeta.astype(np.float32), step, opac, visible, w.astype(np.float32))
    for a in out:
        a.setflags(write=False)
    if tables is not None:
        tables.tf.put(key + ("worst",) if worst else key, (weakref.ref(meta), out), sum(a.nbytes for a in out))
    return out


def _max_tables(meta: BlockMeta, tfs: Sequence[Any], classification: str,
                tables: Tables | None = None, worst: bool = False) -> tuple[np.ndarray, ...]:
    """(ζ(k) (N, L) float32, ζ_step (N,), opacity moments (N, 4), TF-visible blocks (N,), the worst value's ζ(k)
    (N, L) float32, zeros unless `worst` asks for it): the elementwise maxima over the TFs of their tables (zeros
    where no TF gives more)."""
    zeta, step = np.zeros((meta.n, meta.n_levels), np.float32), np.zeros(meta.n)
    opac, visible = np.zeros((meta.n, 4)), np.zeros(meta.n, bool)
    worst_z = np.zeros((meta.n, meta.n_levels), np.float32)
    for t in tfs:
        z_t, s_t, o_t, vis_t, w_t = _tf_tables(meta, t, classification, tables, worst)
        zeta, step = np.maximum(zeta, z_t), np.maximum(step, s_t)
        opac, visible, worst_z = np.maximum(opac, o_t), visible | vis_t, np.maximum(worst_z, w_t)
    return zeta, step, opac, visible, worst_z


def _picture_tables(meta: BlockMeta, tfs: Sequence[Any], classification: str,
                    tables: Tables | None = None) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], ...]:
    """Per TF, (ζ(k), the spread ς(k)) (N, L) float32 with colours compared in the picture's CIELUV
    (level_error.block_zetas with `picture`) and the opacity moments (N, 4) that go with them: what the
    prediction takes (prediction.py: a dual-TF composite's two integrals each through their own opacities). ζ(k)
    only under "mean" classification (the prediction's bias; zeros else): the level errors are most of the pass.
    The selection's own ζ stays in each slab's CIELUV, as "lossless" was set against it."""
    out = []
    for tf in tfs:
        visible = tf_visible(tf, meta.min_border, meta.max_border)
        assert meta.value_range is not None  # (as in _tf_tables)
        z, _, o, _, sp = block_zetas(meta, tf, visible, meta.value_range, meta.std_max, classification, tables,
                                     picture=True, level_errors=classification == "mean")
        out.append((z.astype(np.float32), sp.astype(np.float32), o))
    return tuple(out)


def _drive_tables(meta: BlockMeta, tfs: Sequence[Any], classification: str,
                  tables: Tables | None = None) -> tuple[Any, ...]:
    """(ζ(k) (N, L) float32, opacity moments (N, 2), TF-visible blocks (N,), what drives the greedy
    √(ζ(k) · spread(k)) (N, L) float64 (module doc: "What the greedy weighs"; level 0 drives nothing), its maximum
    per block (N,), per TF the ζ(k) and spread ς(k) (N, L) float32 in the picture's CIELUV and their opacity
    moments (N, 4), which the prediction takes (_picture_tables)): `_max_tables` and what follows
    from them and the store alone, kept in `tables` beside them (a new view of a large volume selects again, and
    these are most of the arithmetic over a million blocks)."""
    key = ("drive", id(meta), json.dumps([as_tf(t).model_dump(mode="json") for t in tfs], sort_keys=True),
           classification)
    hit = None if tables is None else tables.tf.get(key)
    if hit is not None and hit[0]() is meta:
        return hit[1]
    zeta, _, opac, visible, _ = _max_tables(meta, tfs, classification, tables)
    spread = np.nan_to_num(np.asarray(meta.level_std, np.float64))
    spread[:, 0] = 0.0
    drive = np.sqrt(zeta * spread)  # (float64, as the greedy takes it: the selection does not depend on keeping it)
    picture = _picture_tables(meta, tfs, classification, tables)
    arrays = [zeta, opac, visible, drive, drive.max(axis=1), *(a for t in picture for a in t)]
    for a in arrays:
        a.setflags(write=False)
    out = (*arrays[:5], picture)
    if tables is not None:
        tables.tf.put(key, (weakref.ref(meta), out), sum(a.nbytes for a in arrays))
    return out


def zeta0_l2_cached(meta: BlockMeta, visible: np.ndarray) -> np.ndarray:
    from lodcast.renderer.lod.significance import zeta0_l2

    return zeta0_l2(meta, visible)


def select_lod(store: Any, tfs: Any, quality: Any, crop: Any = None, method: str = "tf",
               max_level: np.ndarray | None = None, classification: str = "distribution",
               visibility: np.ndarray | None = None, lossless_zeta: float = LOSSLESS_ZETA,
               tables: Tables | None = None) -> LodSelection:
    """Select a level per block for `tfs` (one TF, or a list: ζ is the max over them) under `quality`
    ("full" | "lossless" | {"budget_mb": x} | {"reduction": r}, or the scene's quality objects).

    crop: world box (lower, upper) in (z, y, x), or a grid-shaped bool mask; blocks outside it are not loaded. max_level: optional grid-shaped
    finest level per block (0 = full allowed). method: "tf" (eq. 3.1 on simplified histograms), "tf_full_hist",
    "l2" (data-error significance, same greedy) or "uniform" (one level for every loaded block, the finest that
    fits). `zeta` and `predicted_delta_e` are always the ΔE significance (simplified, or full for tf_full_hist).
    visibility: optional grid-shaped weight per block in [0, 1], what the camera sees of it (visibility.py): the TF
    methods weigh ζ by it and the prediction counts each block's voxels times it (module doc).
    lossless_zeta: the ΔE per block that "lossless" allows (an engine passes LODCAST_LOSSLESS_ZETA). tables: what
    was computed for this store and these TFs before (an engine's), kept there; None: computed afresh."""
    meta = meta_of_store(store, tables)
    in_crop = None
    if isinstance(crop, np.ndarray) and crop.dtype == bool:
        in_crop = crop  # a block mask already (renderer/scene/clip.py: the scene's clip region)
    elif crop is not None:
        in_crop = crop_mask(store.grid, store.shape, store.spacing, store.origin, store.block_size, crop)
    if isinstance(tfs, dict) or hasattr(tfs, "points"):
        tfs = [tfs]
    # a block's length along each axis in opacity units (the finest TF's, where two differ)
    unit = min(unit_distance(as_tf(t), store.spacing) for t in tfs)
    path = tuple(store.block_size * float(sp) / unit for sp in store.spacing)
    return select_from_meta(
        meta,
        tfs,
        quality,
        n_voxels=int(np.prod(store.shape, dtype=np.int64)),
        block_size=store.block_size,
        in_crop=in_crop,
        max_level=max_level,
        method=method,
        classification=classification,
        visibility=visibility,
        lossless_zeta=lossless_zeta,
        tables=tables,
        path=path,
    )
