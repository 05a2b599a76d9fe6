"""Preparing a frame on the host (renderer/frame/plan.py says what comes out): the scene resolved on the volume, the
camera and the box the rays integrate, the cost checked against the limit, the level-of-detail selection
(weighted by what the camera sees where that applies), the block infos, the classification tables, the passes
beyond the device budget and the screen-space plan. Everything kept between frames is kept in the engine.
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import replace
from typing import Any

import numpy as np

from lodcast.renderer.data import atlas as lod_atlas
from lodcast.renderer.data import bricks
from lodcast.renderer.data import passes as multipass
from lodcast.renderer.data.volume import VOXEL_CTYPES, StoreLike, VolumeView, as_volume
from lodcast.renderer.engine import Engine
from lodcast.renderer.frame import screen as screen_space
from lodcast.renderer.frame.plan import MAX_SAMPLES_PER_RAY, LodPlan, Prepared, kernel_config
from lodcast.renderer.kernel.config import EXTREMUM_MODES, KernelConfig
from lodcast.renderer.kernel.params import fill_params, fill_tf2
from lodcast.renderer.kernel.preintegration import PreintTable, preintegrate
from lodcast.renderer.lod import dual, visibility
from lodcast.renderer.lod.classification import DistTable, cached_dist_table
from lodcast.renderer.scene import camera as cam
from lodcast.renderer.scene import clip as clipping
from lodcast.renderer.scene import cost
from lodcast.renderer.scene.adaptive_tf import resolve_tfs
from lodcast.renderer.scene.scene import (
    AdaptiveTF,
    OrbitCamera,
    QualityBudget,
    QualityReduction,
    Scene,
    SceneError,
    SceneLike,
    TransferFunction,
)
from lodcast.renderer.scene.transfer_function import Lut, build_lut, unit_distance
from lodcast.renderer.walk.info import block_info

__all__ = ["prepare", "check_cost", "prefetch", "resolved", "selection", "lod_config", "samples_per_ray", "volume_config"]


def _tfs_and_key(vol: VolumeView, scene: Scene, keep: np.ndarray | None) -> tuple[list, tuple]:
    """The scene's TFs (tf, and tf2 when given), and the key of what is computed from them alone, not from the
    view (the selection, the step's error): the volume, the TFs and the clip region's blocks."""
    tfs = [scene.tf] + ([scene.tf2] if scene.tf2 is not None else [])
    return tfs, (vol.key, json.dumps([t.model_dump(mode="json") for t in tfs], sort_keys=True),
                 None if keep is None else hashlib.sha1(np.packbits(keep).tobytes()).hexdigest())


def _step_error(eng: Engine, vol: VolumeView, scene: Scene, keep: np.ndarray | None) -> float:
    """selection.step_delta_e for the scene's TFs, step and clip region (kept for the last few: a turntable asks
    for the same each frame); 0 where it does not apply (an array, a projection mode)."""
    if scene.mode != "composite" or not vol.has_levels or vol.key is None:
        return 0.0
    from lodcast.renderer.lod.selection import step_delta_e
    from lodcast.renderer.lod.significance import meta_of_store

    tfs, base = _tfs_and_key(vol, scene, keep)
    key = (*base, scene.sampling.step)
    hit = eng.step_errors.get(key)
    if hit is None:
        hit = step_delta_e(meta_of_store(vol.source, eng.tables), tfs, scene.sampling.step, keep, eng.tables)
        eng.step_errors.put(key, hit, 1)
    return hit


def _view_weighted(scene: Scene, vol: VolumeView) -> bool:
    """Whether the selection weighs what the camera sees (visibility.py): sampling.lod_visibility (null: on for
    volumes of at most visibility.AUTO_VOXELS), at the budgeted qualities ('lossless' promises the full-resolution
    image from any view, and selects once per TF), for a single TF composited (the projections and a second TF see
    through what one TF hides)."""
    on = scene.sampling.lod_visibility
    if on is None:
        on = vol.n_voxels <= visibility.AUTO_VOXELS
    # (a level asked for selects by the TF alone: the view would move only its prediction)
    return on and isinstance(scene.quality, (QualityReduction, QualityBudget)) and scene.mode == "composite" \
        and scene.tf2 is None


def _view_key(scene: Scene, fr: cam.Frame, kbox: tuple) -> str:
    """What the visibility of the blocks depends on besides the TF: the camera, the image's aspect, the box the rays
    integrate and the clip planes."""
    nums = np.concatenate([fr.eye, fr.f, fr.r, fr.u, [fr.half_w, fr.half_h, float(fr.orthographic)],
                           np.ravel(kbox)]).astype(np.float64)
    clip = None if scene.clip is None else scene.clip.model_dump(mode="json")
    return hashlib.sha1(np.round(nums, 9).tobytes() + json.dumps(clip, sort_keys=True).encode()).hexdigest()


def _select(eng: Engine, vol: VolumeView, scene: Scene, levels: np.ndarray | None, keep: np.ndarray | None,
            view: tuple | None = None) -> tuple[np.ndarray, Any]:
    """The level per block: `levels` as given, or the selection for the scene's TFs and quality, weighted by the
    blocks' visibility from the camera when `view` = (frame, ray box, LUT, unit distance) is given."""
    if levels is not None:
        lv = np.array(levels, dtype=np.int8, order="C")  # a copy: the caller's array may change between renders
        if lv.shape != vol.grid:
            raise SceneError(f"levels: shape {lv.shape} is not the block grid {vol.grid}")
        return lv, None
    if not vol.has_levels:
        raise SceneError(f"quality: {scene.quality!r} needs a lodcast store (an array has only full resolution)")
    from lodcast.renderer.lod.selection import select_lod

    tfs, base = _tfs_and_key(vol, scene, keep)
    quality = scene.quality if isinstance(scene.quality, str) else scene.quality.model_dump()
    classification = scene.sampling.classification if scene.mode == "composite" else "mean"
    # without the view's weight the selection does not depend on the view: a turntable selects once
    key = None if vol.key is None else (*base, json.dumps(quality, sort_keys=True), classification,
                                        eng.settings.lossless_zeta,
                                        None if view is None else _view_key(scene, view[0], view[1]))
    sel = eng.selections.get(key) if key is not None else None
    if sel is None:
        seen = None if view is None else visibility.block_visibility(eng, vol, scene, *view)
        sel = select_lod(vol.source, tfs, quality, crop=keep, classification=classification, visibility=seen,
                         lossless_zeta=eng.settings.lossless_zeta, tables=eng.tables)
        sel.levels.flags.writeable = False  # kept: what is derived from it is kept by its identity (_lod_plan)
        if key is not None:
            eng.selections.put(key, sel, 1)
    return np.ascontiguousarray(sel.levels, dtype=np.int8), sel


def samples_per_ray(box: tuple, step_world: float) -> int:
    """The most samples a ray through the world box `box` takes at `step_world`."""
    return int(math.ceil(float(np.linalg.norm(box[1] - box[0])) / step_world)) + 2


def volume_config(scene: Scene, vol: VolumeView, max_samples: int, lod: bool) -> KernelConfig:
    """plan.kernel_config of `scene` on `vol` (its voxel type, blocks and distributions), before any selection."""
    return kernel_config(scene, max_samples, lod=lod, distribution=vol.has_distribution,
                         voxel=VOXEL_CTYPES[vol.voxel_dtype], block_size=int(vol.block_size), n_blocks=vol.n_blocks)


def lod_config(cfg: KernelConfig, scene: Scene, vol: VolumeView, coarse: bool) -> KernelConfig:
    """The kernel configuration of a level-of-detail render once its selection is known: `coarse`, whether any
    block is coarser than level 0."""
    if not coarse:
        if cfg.adaptive and scene.sampling.adaptive_object is None and not scene.sampling.adaptive_naive:
            cfg = replace(cfg, adaptive=False, lattice=False)  # the default: all level 0 leaves nothing to step over
        return replace(cfg, distribution=False)  # nothing to classify by distribution either
    if scene.mode == "composite" and vol.has_cell_ranges:
        cfg = replace(cfg, ess=True)  # the walk leaves out coarse cells empty at level 0 (walk.py: _cell_info), always
    return cfg


def _lod_plan(eng: Engine, vol: VolumeView, scene: Scene, levels: np.ndarray | None, info: np.ndarray, cfg: KernelConfig,
              mode: str, keep: np.ndarray | None,
              view: tuple | None = None) -> tuple[LodPlan, np.ndarray, int, KernelConfig]:
    """The selection (blocks outside the clip region `keep` not loaded; weighted by what the camera sees when
    `view` is given, see _select), the block info with unloaded blocks marked empty, the number of empty blocks,
    and the kernel configuration (`lod_config`)."""
    lv, sel = _select(eng, vol, scene, levels, keep, view)
    cfg = lod_config(cfg, scene, vol, bool((lv > 0).any()))
    B = vol.block_size
    if sel is not None:
        reduction, pred = (float(sel.reduction) if math.isfinite(sel.reduction) else None), float(sel.predicted_delta_e)  # None: nothing loaded (JSON has no inf)
    else:
        chosen = int(np.where(lv >= 0, (B >> np.maximum(lv.astype(np.int64), 0)) ** 3, 0).sum())
        reduction, pred = (vol.n_blocks * B**3 / chosen if chosen else None), None
    skip = cfg.adaptive and mode == "composite" and scene.sampling.empty_space_skipping
    # a kept selection's grid is read-only and comes back as the same array: a turntable derives the same each frame
    key = (id(lv), id(info), mode, cfg.interpolation, scene.tf2 is None, cfg.adaptive, skip, int(B))
    hit = None if lv.flags.writeable else eng.lod_plans.get(key)
    if hit is not None and hit[0] is lv and hit[1] is info:
        marked, n_empty, steps = hit[2:]
    else:
        marked, n_empty, steps = _marked_info(eng, scene, lv, info, cfg, mode, skip, int(B))
        if not lv.flags.writeable:
            eng.lod_plans.put(key, (lv, info, marked, n_empty, steps), marked.nbytes + (0 if steps is None else steps.nbytes))
    return LodPlan(lv, reduction, pred, steps, sel, view is not None), marked, n_empty, cfg


def _marked_info(eng: Engine, scene: Scene, lv: np.ndarray, info: np.ndarray, cfg: KernelConfig, mode: str,
                 skip: bool, B: int) -> tuple[np.ndarray, int, np.ndarray | None]:
    """(the block info of the selection `lv` with its unloaded blocks marked empty, read-only; the number of empty
    blocks; the adaptive walk's step levels, or None)."""
    info = info.copy()
    missing = lv < 0
    info[missing] = -np.inf if mode in EXTREMUM_MODES else 0.0
    # interblock interpolation reaches half a sample of a coarse block (2^(k-1) voxels) past its faces, further
    # than the one-voxel border of the block ranges: where a coarse block is near, a block may show what its
    # neighbours hold, so it takes its neighbourhood's info (empty-space skipping must not change the image)
    near_coarse = (lod_atlas.neighbourhood_max(lv) >= 1) & ~missing if cfg.interpolation == "interblock" else None
    if near_coarse is not None and near_coarse.any():  # nearest block: half a level-0 voxel, at most
        spread = lod_atlas.neighbourhood_max(info) if scene.tf2 is None else dual.dilate_bits(info, lod_atlas.neighbourhood_max)
        info = np.where(near_coarse, spread, info).astype(np.float32)
    info.flags.writeable = False
    n_empty = int(np.count_nonzero(info == 0.0)) if mode == "composite" else int(missing.sum())
    steps = _step_levels(eng, lv, B, (info == 0.0) if skip else None) if cfg.adaptive else None
    return info, n_empty, steps


def _step_levels(eng: Engine, lv: np.ndarray, block_size: int, skip: np.ndarray | None) -> np.ndarray:
    """atlas.step_levels, kept for the last few (levels, skip) pairs: a turntable asks for the same each frame, and
    on a large grid it costs a good part of a frame. A new pair (a new view's selection) starts from the newest
    one of the same grid (atlas.step_levels_from)."""
    key = (block_size, eng.digest(lv), lv.shape, None if skip is None else eng.digest(np.packbits(skip)))
    hit = eng.steps.get(key)
    if hit is None:
        newest = ("newest", block_size, lv.shape, skip is None)
        last = eng.steps.get(newest)
        hit = lod_atlas.step_levels_from(last, lv, block_size, skip)
        eng.steps.put(key, hit, hit.nbytes)
        own = (lv.copy(), None if skip is None else np.array(skip, bool), hit)
        eng.steps.put(newest, own, own[0].nbytes + hit.nbytes + (0 if skip is None else lv.size))
    return hit


def _block_info(eng: Engine, vol: VolumeView, scene: Scene, lut: Lut, lut2: Lut | None) -> tuple[np.ndarray, int]:
    """walk.info.block_info, kept for the last few (store, TFs, mode): a turntable asks for the same each frame, and
    on a million blocks it is a good part of a frame's host time. Read-only: callers derive, never write."""
    key = None if vol.key is None else (*_tfs_and_key(vol, scene, None)[1][:2], scene.mode)
    hit = eng.block_infos.get(key) if key is not None else None
    if hit is None:
        hit = block_info(vol, lut, scene.mode, lut2)
        hit[0].flags.writeable = False
        if key is not None:
            eng.block_infos.put(key, hit, hit[0].nbytes)
    return hit


def _cost(eng: Engine, scene: Scene, fr: cam.Frame, kbox: tuple, step_world: float,
          sample_limit: int | None) -> int:
    estimated = cost.estimate_samples(fr, kbox, scene.width, scene.height, step_world)
    limit = eng.settings.max_samples if sample_limit is None else sample_limit
    cost.refuse_over_limit(estimated, limit, scene.width, scene.height, scene.sampling.step)
    return estimated


def resolved(eng: Engine, scene: Scene, vol: VolumeView) -> Scene:
    """`scene` as it renders on `vol`: adaptive TFs as the control points they take on it, an orbit camera's
    named view as its azimuth and elevation."""
    update = resolve_tfs(scene, vol, eng.tables.peaks)
    if isinstance(scene.camera, OrbitCamera) and scene.camera.view is not None:
        update["camera"] = cam.resolve_view(scene.camera, getattr(vol.source, "orientation", None))
    return scene.model_copy(update=update) if update else scene


def _target(eng: Engine, vol: VolumeView, scene: Scene, sample_limit: int | None) -> tuple[Scene, Scene, Any]:
    """(the scene as asked, the scene to render, the Choice of a quality target or None): a target
    (renderer/frame/target.py) is replaced by the setting it picks."""
    from lodcast.renderer.frame import target

    if not target.is_target(scene.quality):
        return scene, scene, None
    choice = target.choose(eng, vol, scene, sample_limit)
    return scene, choice.scene, choice


def check_cost(eng: Engine, store: StoreLike, scene: SceneLike, sample_limit: int | None = None) -> int:
    """Renderer.check_cost (of the setting a quality target picks)."""
    vol = as_volume(store, stores=eng.stores)
    scene = _target(eng, vol, resolved(eng, Scene.parse(scene), vol), sample_limit)[1]
    _, fr, kbox, step_world = cam.geometry(vol, scene)
    return _cost(eng, scene, fr, kbox, step_world, sample_limit)


def prepare(eng: Engine, store: StoreLike, scene: SceneLike, *, spacing: Any = None, origin: Any = None,
            levels: np.ndarray | None = None, sample_limit: int | None = None) -> Prepared:
    """Renderer.prepare."""
    vol = as_volume(store, spacing=spacing, origin=origin, stores=eng.stores)
    scene = resolved(eng, Scene.parse(scene), vol)  # "tf": "auto" takes its control points from this volume
    asked, scene, choice = _target(eng, vol, scene, sample_limit)
    tf, tf2 = scene.tf, scene.tf2
    assert isinstance(tf, TransferFunction) and not isinstance(tf2, AdaptiveTF)  # resolved() placed adaptive TFs
    box, fr, kbox, step_world = cam.geometry(vol, scene)
    estimated = _cost(eng, scene, fr, kbox, step_world, sample_limit)
    unit = unit_distance(tf, vol.spacing)
    max_samples = samples_per_ray(box, step_world)
    if max_samples > MAX_SAMPLES_PER_RAY:
        raise SceneError(
            f"sampling.step: {scene.sampling.step} voxels is too small for this volume "
            f"({max_samples} samples per ray, at most {MAX_SAMPLES_PER_RAY})"
        )
    lut = build_lut(tf, vol.value_range)
    second = None
    if tf2 is not None:
        second = dual.SecondTf(tf2, build_lut(tf2, vol.value_range), unit_distance(tf2, vol.spacing))
    info, n_empty = _block_info(eng, vol, scene, lut, None if second is None else second.lut)
    keep = clipping.block_mask(vol.grid, vol.shape, vol.spacing, vol.origin, vol.block_size, scene.clip)
    if keep is not None:  # blocks outside the clip region are empty space
        info = np.where(keep, info, -np.inf if scene.mode in EXTREMUM_MODES else 0.0).astype(np.float32)
        n_empty = int(np.count_nonzero(info == 0.0)) if scene.mode == "composite" else 0
    # before the selection: on a large volume the selection's tables push the TF's own out of their cache, and
    # the step's error would compute them again
    step_error = _step_error(eng, vol, scene, keep)
    lod = None
    use_lod = levels is not None or scene.quality != "full"
    cfg = volume_config(scene, vol, max_samples, use_lod)
    if use_lod:
        view = (fr, kbox, lut, unit) if levels is None and _view_weighted(scene, vol) else None
        lod, info, n_empty, cfg = _lod_plan(eng, vol, scene, levels, info, cfg, scene.mode, keep, view)
    dist, pre = _classification_tables(eng, tf, lut, unit, cfg, vol, step_world)
    params = fill_params(vol, scene, fr, kbox, lut, step_world, unit, max_samples, dist, pre)
    prio = None
    if second is not None:
        dist2, pre2 = _classification_tables(eng, second.tf, second.lut, second.unit, cfg, vol, step_world)
        second = replace(second, dist=dist2, preint=pre2)
        if scene.sampling.priority_map:
            prio = dual.priority_map(fr, (info.astype(np.int64) & 2) > 0, vol.shape, vol.spacing, vol.origin,
                                     vol.block_size, scene.width, scene.height)
    plan = _screen_plan(vol, scene, fr, info, lod) if cfg.screen else None
    if plan is not None:
        params[0]["screen_n"] = plan.rays
    pp = _pass_plan(eng, vol, scene, fr, cfg, info, lod)
    if pp is not None:
        cfg = replace(cfg, passes=True)
    pr = Prepared(eng, scene, vol, lut, cfg, params, info, n_empty, step_world, unit, lod, dist, pre, estimated, second,
                  prio, plan, pp, step_error, cam.ray_octants(fr),
                  None if choice is None else (asked, choice))
    if second is not None:
        fill_tf2(params, pr)
    return pr


def _pass_plan(eng: Engine, vol: VolumeView, scene: Scene, fr: cam.Frame, cfg: KernelConfig, info: np.ndarray,
               lod: "LodPlan | None") -> "multipass.PassPlan | None":
    """The passes of a render whose volume data exceeds the device budget or one allocation (renderer/data/passes.py),
    None for one pass."""
    limit, what = multipass.volume_limit(eng)

    def unsampled() -> np.ndarray:
        if cfg.adaptive and lod is not None and lod.step_levels is not None:  # cells of level -1 are never sampled
            st = lod.step_levels
            return st.reshape(st.shape[0] // 2, 2, st.shape[1] // 2, 2, st.shape[2] // 2, 2).max(axis=(1, 3, 5)) < 0
        if cfg.ess and scene.sampling.empty_space_skipping:  # blocks the walk skips whatever the ray did before
            # (without skipping the walk may still run, for the coarse cells' mask: it skips no block then)
            return info == (-np.inf if scene.mode in EXTREMUM_MODES else 0.0)
        return np.zeros(vol.grid, bool)

    reach = scene.sampling.step
    if cfg.adaptive and lod is not None:
        reach *= 2.0 ** max(0, int(lod.levels.max(initial=0)))  # an adaptive segment's front end
    pp = multipass.plan(vol, fr, reach, None if lod is None else lod.levels, cfg.distribution, unsampled, limit,
                        cfg.interpolation, what)
    if pp is not None and cfg.adaptive_naive:
        raise SceneError("sampling.adaptive_naive: naive adaptive steps run across blocks and cannot be split into "
                         "passes, which this volume needs on this device (LODCAST_DEVICE_BUDGET_MB)")
    return pp


def _classification_tables(eng: Engine, tf: Any, lut: Lut, unit: float, cfg: KernelConfig, vol: VolumeView,
                           step_world: float) -> tuple[DistTable | None, PreintTable | None]:
    """One TF's distribution table (LC_DIST) and pre-integration table (LC_PREINT: over its LUT's value range,
    for segments of the base step), where the kernel uses them."""
    dist = cached_dist_table(tf, vol.value_range, vol.std_max, eng.tables.dist) if cfg.distribution else None
    pre = (preintegrate(tf, lut.lo, lut.lo + (lut.n - 1) / lut.scale, step_world / unit, kept=eng.tables.preint)
           if cfg.preint else None)
    return dist, pre


def _screen_plan(vol: VolumeView, scene: Scene, fr: cam.Frame, info: np.ndarray,
                 lod: "LodPlan | None") -> "screen_space.ScreenPlan":
    """Adaptive screen-space sampling's pre-pass: each tile's resolution from the block scales along its rays."""
    s = scene.sampling
    levels = lod.levels if lod is not None else np.zeros(vol.grid, np.int8)
    visible = info != 0 if scene.mode == "composite" else np.ones(vol.grid, bool)
    pri = screen_space.tile_priorities(fr, levels, visible, vol.shape, vol.spacing, vol.origin, vol.block_size,
                                       scene.width, scene.height, s.screen_tile, s.screen_statistic)
    return screen_space.plan(screen_space.resolutions(pri, s.screen_tile), scene.width, scene.height, s.screen_tile)


def selection(eng: Engine, vol: VolumeView, scene: Scene) -> Any:
    """The level-of-detail selection (selection.Selection) `prepare` makes for `scene` (not at quality "full"),
    kept where prepare finds it: asking first costs a render of the scene nothing."""
    scene = resolved(eng, scene, vol)
    assert isinstance(scene.tf, TransferFunction)  # resolved() put an adaptive TF's control points in its place
    _, fr, kbox, _ = cam.geometry(vol, scene)
    keep = clipping.block_mask(vol.grid, vol.shape, vol.spacing, vol.origin, vol.block_size, scene.clip)
    view = None
    if _view_weighted(scene, vol):
        view = (fr, kbox, build_lut(scene.tf, vol.value_range), unit_distance(scene.tf, vol.spacing))
    return _select(eng, vol, scene, None, keep, view)[1]


def prefetch(eng: Engine, store: StoreLike, scene: SceneLike) -> int:
    """Renderer.prefetch."""
    pr = prepare(eng, store, scene)
    if pr.lod is None or pr.volume.key is None:
        return 0
    n = 0
    todo = lod_atlas.unplaced(eng, pr.volume, pr.lod.levels, pr.config.distribution)
    for what in ("mean", "std") if pr.config.distribution else ("mean",):
        st = bricks.BrickStats()
        for _ in bricks.brick_batches(eng, pr.volume, todo, what=what, stats=st):
            pass  # into the brick pool only: holding them all here would cost the selection's size
        n += st.read
    return n
