"""Quality asked for as a target (docs/design.md): `{"max_delta_e": x}` renders the fastest setting whose predicted ΔE
is at most x, `{"max_ms": t}` the setting of the smallest predicted ΔE predicted to take at most t milliseconds.

The candidates: every step of TARGET_STEPS, at full resolution and at every data setting the store offers
("lossless" and the reductions of TARGET_REDUCTIONS), the level-of-detail ones with nearest-block and interblock
interpolation, with adaptive screen-space sampling and without. Each one's predicted ΔE against the reference is
what a render's report predicts (the selection's own, selection.py, plus the step's, step_delta_e), plus what
adaptive screen-space sampling adds: SCREEN_GAIN × the share of the pixels of the tiles that meet loaded blocks
whose rays it leaves out (fitted on the chest CT, docs/measurements/quality_target.md). The selections are the
view-independent ones (the chosen scene renders with `lod_visibility` off unless the scene set it): a new view
then selects nothing again. Interpolation moves no prediction (interblock is continuous across block faces for
about the same mean ΔE): it is chosen only where it would be faster.

Each one's time: the host's milliseconds, plus its rays times a ray's cost (the walk over the volume's cells;
where rays end early most of what they cost, whatever the step), plus its samples times a sample's cost of its
path (full resolution, or the atlas with nearest-block or interblock interpolation), plus adaptive screen
sampling's pre-pass (timed where its rays are predicted) and reconstruction, plus the volume data uploaded every
frame where it exceeds the device budget (renders in passes). The samples are the full march's over the view
(cost.estimate_samples) times the share the scene's rays really take (empty space skipped, rays ended early)
times adaptive object sampling's share at the selection's levels. The costs are the device's (`CostModel`,
device_cost.py: measured once per device) scaled to this store by small renders of the scene on each path at
two steps (`_live`), and by what the renders of targets on this store and TFs then took (`observe`). The
selections, step errors and probes are kept per store and TFs in the engine (`targets`): a new view costs a few
array operations per data setting and the screen pre-pass, a new TF its selections and probes.

The candidates none of whose rivals is both faster and better form the Pareto front (`Choice.front`, which
`lodcast report` marks); a target's pick is always on it.
"""
from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from lodcast.renderer.data import passes as multipass
from lodcast.renderer.data.volume import VolumeView
from lodcast.renderer.engine import Engine
from lodcast.renderer.frame import screen as screen_space
from lodcast.renderer.frame.device_cost import CostModel, cost_model, renders
from lodcast.renderer.image.report import ChosenReport, ChosenSetting
from lodcast.renderer.scene import camera as cam
from lodcast.renderer.scene import clip as clipping
from lodcast.renderer.scene import cost
from lodcast.renderer.scene.scene import QualityMaxDeltaE, QualityMaxMs, Scene, SceneError

__all__ = ["TARGET_STEPS", "TARGET_REDUCTIONS", "SCREEN_GAIN", "OBSERVED_RANGE", "CostModel", "Candidate", "Choice",
           "is_target", "choose", "candidates", "pareto", "observe", "cost_model"]

TARGET_STEPS = (0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0)
TARGET_REDUCTIONS = (5.0, 10.0, 20.0, 30.0, 60.0)
#: the mean ΔE adaptive screen-space sampling adds per unit share of the pixels it leaves out in the tiles whose rays
#: meet loaded blocks (fitted on the chest CT under bone, soft tissue and a translucent band, 90 pairs with and
#: without it: docs/measurements/quality_target.md)
SCREEN_GAIN = 2.0
SCREEN_PROBE_TILES = 16  # the screen-space pre-pass a candidate's rays are predicted from: at most this many tiles
PROBE_RAYS = 64  # the scene's own probe (the share of the full march its rays take): rays along the longer side
OBSERVED_RANGE = (0.25, 4.0)  # the most a target's observed renders scale its predicted times


@dataclass(frozen=True)
class Candidate:
    """One setting: `quality` (full, lossless or a reduction), `step`, `interpolation` (None at full),
    `adaptive_screen`; its data `reduction` and its predictions."""

    quality: Any
    step: float
    interpolation: str | None
    adaptive_screen: bool
    reduction: float
    predicted_delta_e: float
    predicted_ms: float

    def setting(self) -> ChosenSetting:
        return {"quality": self.quality, "step": self.step, "interpolation": self.interpolation,
                "adaptive_screen": self.adaptive_screen, "reduction": self.reduction,
                "predicted_delta_e": self.predicted_delta_e, "predicted_ms": self.predicted_ms}

    def label(self) -> str:
        q = self.quality if isinstance(self.quality, str) else f"{self.quality['reduction']:g}:1"
        extra = "" if self.interpolation is None else f" {self.interpolation}"
        return f"{q} step {self.step:g}{extra}{' adaptive-screen' if self.adaptive_screen else ''}"


@dataclass(frozen=True)
class Choice:
    """What a target picked: the scene to render (`scene`, the target replaced by the chosen setting), the
    chosen candidate, the runner-up, why, every candidate and the Pareto front."""

    scene: Scene
    chosen: Candidate
    runner_up: Candidate | None
    why: str
    candidates: tuple[Candidate, ...]
    front: tuple[Candidate, ...]
    choose_ms: float

    def report(self, target: Any) -> ChosenReport:
        return {"target": target.model_dump(), "setting": self.chosen.setting(),
                "runner_up": None if self.runner_up is None else self.runner_up.setting(), "why": self.why,
                "candidates": len(self.candidates), "front": len(self.front), "choose_ms": self.choose_ms}


def is_target(quality: Any) -> bool:
    return isinstance(quality, (QualityMaxDeltaE, QualityMaxMs))


# ------------------------------------------------------------------------------------------------- data settings
@dataclass(frozen=True)
class _Data:
    """A data setting of one store under one set of TFs: its quality, reduction, predicted ΔE (the selection's
    own), adaptive object sampling's share of a fixed-step march's samples, bytes on the device and levels."""

    quality: Any
    reduction: float
    delta_e: float
    sample_share: float
    device_bytes: int
    levels: np.ndarray | None


@dataclass(frozen=True)
class _Table:
    data: tuple[_Data, ...]
    step_delta_e: Mapping[float, float]


def _key(vol: VolumeView, scene: Scene, keep: np.ndarray | None, *extra: Any) -> tuple:
    tfs = [scene.tf] + ([scene.tf2] if scene.tf2 is not None else [])
    return (vol.key, json.dumps([t.model_dump(mode="json") for t in tfs], sort_keys=True), scene.mode,
            scene.sampling.classification, None if keep is None else hashlib.sha1(np.packbits(keep).tobytes()).hexdigest(),
            *extra)


def _table(eng: Engine, vol: VolumeView, scene: Scene, keep: np.ndarray | None) -> _Table:
    """The data settings and step errors of `scene`'s store and TFs (kept in the engine: a new view needs none
    of them again)."""
    key = _key(vol, scene, keep, eng.settings.lossless_zeta)
    hit = eng.targets.get(key)
    if hit is not None:
        return hit
    from lodcast.renderer.lod.selection import select_lod, step_delta_e
    from lodcast.renderer.lod.significance import meta_of_store

    tfs = [scene.tf] + ([scene.tf2] if scene.tf2 is not None else [])
    meta = meta_of_store(vol.source, eng.tables)
    count = np.nan_to_num(meta.count.astype(np.float64))
    B = int(vol.block_size)
    classification = scene.sampling.classification if scene.mode == "composite" else "mean"
    per_voxel = 8 if classification == "distribution" and vol.has_distribution and scene.mode == "composite" else 4
    data = [_Data("full", 1.0, 0.0, 1.0, vol.n_voxels * vol.voxel_dtype.itemsize, None)]
    for q in ["lossless", *({"reduction": r} for r in TARGET_REDUCTIONS)]:
        try:
            sel = select_lod(vol.source, tfs, q, crop=keep, classification=classification,
                             lossless_zeta=eng.settings.lossless_zeta, tables=eng.tables)
        except SceneError:
            continue  # a budget below what every visible block needs at its coarsest level
        lv = sel.levels.ravel().astype(np.int64)
        loaded = lv >= 0
        if not loaded.any() or not math.isfinite(sel.reduction):
            continue
        # adaptive steps: step · 2^(k+1) in a level-k block, k ≥ 1 (atlas.step_levels), at most step · B
        s = np.minimum(np.where(lv > 0, lv + 1, 0), B.bit_length() - 1)[loaded]
        w = count[loaded]
        share = float((w * 0.5 ** s).sum() / max(w.sum(), 1.0))
        data.append(_Data(q, float(sel.reduction), float(sel.predicted_delta_e), share,
                          sel.bytes * per_voxel // 4, sel.levels))
    steps = {h: (step_delta_e(meta, tfs, h, keep, eng.tables) if scene.mode == "composite" else 0.0)
             for h in TARGET_STEPS}
    table = _Table(tuple(data), steps)
    eng.targets.put(key, table, 1)
    return table


@dataclass(frozen=True)
class _Live:
    """What small renders of the scene measured on this store, per path ("full": level 0 as one volume; "atlas":
    a selection, adaptive steps, nearest block): the share of a full march's samples the rays take (empty space
    skipped, rays ended early; on the atlas path against adaptive sampling's share at the probed selection's
    levels: it also skips coarse cells empty at level 0 and octants), the host milliseconds (selection, walks,
    launch, read-back), and the nanoseconds per ray (the walk over the volume's cells: where rays end early, most
    of a ray's cost whatever the step) and per sample, parted by two steps."""

    share: Mapping[str, float]
    host_ms: Mapping[str, float]
    ray_ns: Mapping[str, float]
    sample_ns: Mapping[str, float]


def _live(eng: Engine, vol: VolumeView, scene: Scene, keep: np.ndarray | None, table: _Table, fits: bool,
          model: CostModel) -> _Live:
    """What renders of the scene PROBE_RAYS rays across measure (`_Live`; each the fastest of three, warm) at
    steps 0.5 and 2: at full resolution where that fits the device, and at the finest selection of at least 8:1;
    a path not probed takes the other's figures in the device model's ratios. Kept per store and TFs."""
    key = _key(vol, scene, keep, "live", fits, scene.sampling.early_termination,
               scene.sampling.empty_space_skipping, scene.shading is None)
    hit = eng.targets.get(key)
    if hit is not None:
        return hit
    render = renders(eng)
    n = PROBE_RAYS
    w, h = (n, max(1, round(n * scene.height / scene.width))) if scene.width >= scene.height else \
        (max(1, round(n * scene.width / scene.height)), n)
    rays = float(w * h)
    march1 = float(cost.estimate_samples(*_geometry(vol, scene, w, h), w, h, float(min(vol.spacing))))

    def probe(quality: Any, step: float) -> Any:
        sampling = scene.sampling.model_copy(update={"step": step, "adaptive_screen": False, "adaptive_object": None,
                                                     "interpolation": None, "lod_visibility": False})
        sc = Scene.model_validate({**scene.model_dump(), "quality": quality, "width": w, "height": h,
                                   "sampling": sampling.model_dump(), "format": "npy"})
        render(vol, sc)
        return min((render(vol, sc).report for _ in range(3)), key=lambda r: r["kernel_ms"])

    def parted(quality: Any, sample_share: float, sampler: str) -> tuple[float, float, float, float]:
        """(share, host ms, ns per ray, ns per sample) of one path."""
        fine, coarse = probe(quality, 0.5), probe(quality, 2.0)
        ds = fine["samples"] - coarse["samples"]
        per_sample = (fine["kernel_ms"] - coarse["kernel_ms"]) * 1e6 / ds if ds > 0 else 0.0
        if per_sample <= 0.0:  # too noisy to part: as the device's model parts it
            part = model.sample_ns[sampler] * fine["samples"]
            part /= max(part + model.ray_ns * rays, 1e-9)
            per_sample = fine["kernel_ms"] * 1e6 * part / max(fine["samples"], 1)
        per_ray = max((fine["kernel_ms"] * 1e6 - per_sample * fine["samples"]) / rays, 0.0)
        return (min(1.0, fine["samples"] / max(2.0 * march1 * sample_share, 1.0)),
                max(fine["wall_ms"] - fine["kernel_ms"], 0.0), per_ray, per_sample)

    lods = [d for d in table.data if d.levels is not None]
    lod = next((d for d in lods if d.reduction >= 8.0), lods[-1] if lods else None)
    got = {}
    if fits or lod is None:
        got["full"] = parted("full", 1.0, "full")
    if lod is not None:
        got["atlas"] = parted(lod.quality, lod.sample_share, "nearest_block")
    ratio = model.sample_ns["nearest_block"] / model.sample_ns["full"]
    if "full" not in got:
        sh, host, ray, smp = got["atlas"]
        got["full"] = (sh, host, ray, smp / ratio)
    if "atlas" not in got:
        sh, host, ray, smp = got["full"]
        got["atlas"] = (sh, host, ray, smp * ratio)
    out = _Live(*({k: v[i] for k, v in got.items()} for i in range(4)))
    eng.targets.put(key, out, 1)
    return out


def _geometry(vol: VolumeView, scene: Scene, width: int, height: int) -> tuple[Any, Any]:
    """(the camera frame at `width` × `height`, the box the rays integrate) of `scene` on `vol`."""
    _, fr, kbox, _ = cam.geometry(vol, scene.model_copy(update={"width": width, "height": height}))
    return fr, kbox


# ------------------------------------------------------------------------------------------------- choosing
def candidates(eng: Engine, vol: VolumeView, scene: Scene, sample_limit: int | None = None) -> list[Candidate]:
    """Every candidate setting of `scene` (resolved on `vol`: renderer/frame/prepare.py `resolved`) with its
    predictions on `eng`'s device."""
    if not vol.has_levels:
        raise SceneError(f"quality: a target ({scene.quality!r}) needs a lodcast store (an array has "
                         "no error tables to predict from)")
    model = cost_model(eng)
    W, H = scene.width, scene.height
    fr, kbox = _geometry(vol, scene, W, H)
    keep = clipping.block_mask(vol.grid, vol.shape, vol.spacing, vol.origin, vol.block_size, scene.clip)
    table = _table(eng, vol, scene, keep)
    limit_bytes, _ = multipass.volume_limit(eng)
    live = _live(eng, vol, scene, keep, table, table.data[0].device_bytes <= limit_bytes, model)
    shaded = scene.shading is not None and scene.mode in ("composite", "iso")
    shade = model.shade_factor if shaded else 1.0
    if model.per_store:  # this store's costs (interblock in the device's ratio to nearest block)
        ray_ns, host_ms = live.ray_ns, live.host_ms
        sample_ns = {"full": live.sample_ns["full"], "nearest_block": live.sample_ns["atlas"],
                     "interblock": live.sample_ns["atlas"] * model.sample_ns["interblock"] / model.sample_ns["nearest_block"]}
    else:  # the model's figures as given
        ray_ns, host_ms = {"full": model.ray_ns, "atlas": model.ray_ns}, {"full": 0.0, "atlas": 0.0}
        sample_ns = {k: v * shade for k, v in model.sample_ns.items()}
    seen = eng.targets.get(_key(vol, scene, keep, "seen")) if model.per_store else None
    factor = 1.0 if seen is None else float(seen)  # what renders of these targets took against their predictions
    march1 = cost.estimate_samples(fr, kbox, W, H, float(min(vol.spacing)))  # the full march at step 1
    max_samples = eng.settings.max_samples if sample_limit is None else sample_limit
    out: list[Candidate] = []
    for d in table.data:
        path = "full" if d.levels is None else "atlas"
        upload = d.device_bytes if d.device_bytes > limit_bytes else 0  # in passes: uploaded every frame
        screens: list[tuple[bool, float, float, float]] = [(False, float(W * H), 0.0, 0.0)]
        if d.levels is not None and scene.tf2 is None:  # at full every tile is at full resolution
            screens.append((True, *_screen_rays(fr, vol, d.levels, scene)))
        for step in TARGET_STEPS:
            if march1 / step > max_samples:
                continue
            samples = march1 / step * live.share[path] * d.sample_share
            for interp in (None,) if d.levels is None else ("nearest_block", "interblock"):
                for screen, rays, left_out, prepass_ms in screens:
                    de = d.delta_e + table.step_delta_e[step] + SCREEN_GAIN * left_out
                    share = rays / (W * H)
                    ms = max(model.frame_ms, host_ms[path]) + (prepass_ms if model.per_store else 0.0) + 1e-6 * (
                        rays * ray_ns[path] + samples * share * sample_ns[interp or "full"] + upload * model.byte_ns
                        + (W * H * model.pixel_ns if screen else 0.0))
                    out.append(Candidate(d.quality, step, interp, screen, d.reduction, de, ms * factor))
    return out


def _screen_rays(fr: Any, vol: VolumeView, levels: np.ndarray, scene: Scene) -> tuple[float, float, float]:
    """(the rays adaptive screen-space sampling would cast at `levels`, the share of the pixels of the tiles whose
    rays meet loaded blocks that it leaves out, its pre-pass's milliseconds): its pre-pass (screen.tile_priorities)
    on tiles grown by a power of two to at most SCREEN_PROBE_TILES of them, each grown tile's resolution standing
    for the tiles it covers; its time, per tile, times the render's tiles. (Tiles that meet nothing are cast at
    2×2 and lose nothing.)"""
    s = scene.sampling
    W, H = scene.width, scene.height
    grow = 1
    while -(-W // (s.screen_tile * grow)) * -(-H // (s.screen_tile * grow)) > SCREEN_PROBE_TILES:
        grow *= 2
    t = time.perf_counter()
    pri = screen_space.tile_priorities(fr, levels, levels >= 0, vol.shape, vol.spacing, vol.origin, vol.block_size,
                                       W, H, s.screen_tile * grow, s.screen_statistic)
    prepass_ms = (time.perf_counter() - t) * 1e3 * (-(-W // s.screen_tile) * -(-H // s.screen_tile)) / pri.size
    kept = (screen_space.resolutions(pri, s.screen_tile).astype(np.float64) / s.screen_tile) ** 2
    covered = pri > 0
    left_out = float(1.0 - kept[covered].mean()) if covered.any() else 0.0
    return float(min(kept.mean(), 1.0) * W * H), left_out, prepass_ms


def observe(eng: Engine, vol: VolumeView, scene: Scene, chosen: Candidate, measured_ms: float) -> None:
    """Keep what the render of a target's pick took (`measured_ms`, choosing left out) against its prediction: the
    next predictions for this store and TFs are scaled by the running ratio (half the last ratio's logarithm, half
    the one before; within OBSERVED_RANGE), so that a machine busier or quieter than the probes found, or a view
    dearer than the probe's, moves what `max_ms` promises. Not for a model given explicitly."""
    if not cost_model(eng).per_store or chosen.predicted_ms <= 0.0 or measured_ms <= 0.0:
        return
    keep = clipping.block_mask(vol.grid, vol.shape, vol.spacing, vol.origin, vol.block_size, scene.clip)
    key = _key(vol, scene, keep, "seen")
    old = eng.targets.get(key)
    before = 1.0 if old is None else float(old)
    ratio = measured_ms / (chosen.predicted_ms / before)
    lo, hi = OBSERVED_RANGE
    eng.targets.put(key, float(np.clip(math.sqrt(before * ratio), lo, hi)), 1)


def pareto(cands: list[Candidate]) -> list[Candidate]:
    """The candidates no other is both at least as fast and at least as good as, and better in one, fastest
    first."""
    front: list[Candidate] = []
    best = math.inf
    for c in sorted(cands, key=lambda c: (c.predicted_ms, c.predicted_delta_e)):
        if c.predicted_delta_e < best:
            front.append(c)
            best = c.predicted_delta_e
    return front


def choose(eng: Engine, vol: VolumeView, scene: Scene, sample_limit: int | None = None) -> Choice:
    """The setting `scene`'s target (its quality, a QualityMaxDeltaE or QualityMaxMs) picks on `vol` (scene
    resolved on it), and the scene with the target replaced by it."""
    t0 = time.perf_counter()
    q = scene.quality
    cands = candidates(eng, vol, scene, sample_limit)
    if not cands:
        raise SceneError("quality: no candidate setting fits the sample limit (LODCAST_MAX_SAMPLES) at this image "
                         "size; use fewer pixels (width x height)")
    if isinstance(q, QualityMaxDeltaE):
        ok = sorted((c for c in cands if c.predicted_delta_e <= q.max_delta_e),
                    key=lambda c: (c.predicted_ms, c.predicted_delta_e))
        if ok:
            why = (f"the fastest of the {len(ok)} of {len(cands)} candidates predicted within ΔE "
                   f"{q.max_delta_e:g}")
        else:
            ok = sorted(cands, key=lambda c: (c.predicted_delta_e, c.predicted_ms))
            why = (f"no candidate is predicted within ΔE {q.max_delta_e:g}: the one of the smallest predicted ΔE "
                   f"of {len(cands)}")
    else:
        assert isinstance(q, QualityMaxMs)
        # choosing is part of the frame's time (a model given explicitly stands as given: nothing measured)
        left = q.max_ms - ((time.perf_counter() - t0) * 1e3 if cost_model(eng).per_store else 0.0)
        ok = sorted((c for c in cands if c.predicted_ms <= left), key=lambda c: (c.predicted_delta_e, c.predicted_ms))
        if ok:
            why = (f"the smallest predicted ΔE of the {len(ok)} of {len(cands)} candidates predicted within the "
                   f"{left:.3g} of {q.max_ms:g} ms left after choosing")
        else:
            ok = sorted(cands, key=lambda c: (c.predicted_ms, c.predicted_delta_e))
            why = f"no candidate is predicted within {q.max_ms:g} ms: the fastest of {len(cands)}"
    chosen, runner = ok[0], (ok[1] if len(ok) > 1 else None)
    if runner is not None:
        why += (f"; the runner-up, {runner.label()}, is predicted at ΔE {runner.predicted_delta_e:.3g} in "
                f"{runner.predicted_ms:.3g} ms against ΔE {chosen.predicted_delta_e:.3g} in "
                f"{chosen.predicted_ms:.3g} ms")
    sampling = scene.sampling.model_copy(update={
        "step": chosen.step, "interpolation": chosen.interpolation, "adaptive_screen": chosen.adaptive_screen,
        # the selections were predicted without the view's weight; a view-weighted one would select again each view
        "lod_visibility": scene.sampling.lod_visibility if scene.sampling.lod_visibility is not None else False})
    picked = Scene.model_validate({**scene.model_dump(), "quality": chosen.quality,
                                   "sampling": sampling.model_dump()})
    return Choice(picked, chosen, runner, why, tuple(cands), tuple(pareto(cands)),
                  (time.perf_counter() - t0) * 1e3)
