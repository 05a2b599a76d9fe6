"""`lodcast.Renderer`, the engine, and `lodcast.render(store, scene) -> RenderResult`: one frame through the OpenCL
ray caster.

A `Renderer` (an `Engine`, renderer/engine.py, with the verbs) owns the OpenCL device, the caches and the settings;
`lodcast.render` and the other module-level verbs use a default one, made on first use. Every function below the
verbs takes the engine it works for.

Quality 'full' reads level 0 as one buffer (LC_SAMPLER_FULL): bricks_read counts level-0 blocks uploaded by this
call, bricks_cached those already on the device, bricks_skipped the blocks empty-space skipping leaves out (TF
opacity zero over their border-inclusive value range), reduction is 1 and predicted_delta_e 0.

Any other quality ('lossless', {"budget_mb"}, {"reduction"}) selects a level per block (renderer/selection.py,
thesis §3.2), packs the selected bricks into the atlas (renderer/atlas.py: bricks_read / bricks_cached count the
bricks read from the store / found in the brick cache, bricks_skipped the blocks not loaded, level -1) and samples
it with nearest-block or interblock interpolation (LC_SAMPLER_ATLAS, lc_atlas.h), optionally with adaptive
object-space sampling (LC_ADAPTIVE). At quality 'full' adaptive sampling would change nothing (every block is
level 0: the step is the base step everywhere), so the full-resolution path renders and the report says
``"adaptive": false``.

Blocks the selection leaves out (level -1: zero significance, the TF is transparent over their border-inclusive
value range) are empty space: the block walk skips them, a sample inside one is NaN (transparent), and interblock
interpolation gives them weight 0 (lc_atlas.h), so nothing leaks into or out of them. Empty-space skipping on the
LOD path also skips loaded blocks whose border-inclusive range is invisible, as at full resolution.
"""
from __future__ import annotations

import hashlib
import json
import math
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pyopencl as cl

from lodcast.renderer.adaptive_tf import resolve_tfs
from lodcast.renderer import atlas as lod_atlas
from lodcast.renderer import bricks
from lodcast.renderer import camera as cam
from lodcast.renderer import clip as clipping
from lodcast.renderer import cost
from lodcast.renderer import dual
from lodcast.renderer import passes as multipass
from lodcast.renderer.params import ext_table, fill_params, fill_tf2, lut_table, tables
from lodcast.renderer import screen as screen_space
from lodcast.renderer import visibility
from lodcast.renderer.walk import adaptive_walk, block_info, walk_info
from lodcast.renderer.classification import DistTable, cached_dist_table
from lodcast.renderer.sampler import FINE_CELLS
from lodcast.renderer.config import EXTREMUM_MODES, PRECISE_SAMPLES, KernelConfig
from lodcast.renderer.preintegration import PreintTable, preintegrate
from lodcast.renderer.engine import Engine
from lodcast.renderer.scene import OrbitCamera, Scene, SceneError
from lodcast.renderer.structs import STATE_FLOATS
from lodcast.renderer.transfer_function import Lut, build_lut, unit_distance
from lodcast.renderer.volume import VOXEL_CTYPES, VolumeView, as_volume

__all__ = ["Renderer", "RenderResult", "Prepared", "default_renderer", "render", "prepare", "prefetch", "check_cost",
           "launch", "kernel_config", "LOCAL_SIZE", "MAX_SAMPLES_PER_RAY"]

LOCAL_SIZE = (8, 8)
BAND_SAMPLES = 20_000_000  # a launch band (render(stop=...)): about 0.2-0.5 s of kernel time on two CPU cores
MAX_SAMPLES_PER_RAY = 2**30


@dataclass(frozen=True)
class RenderResult:
    """`rgba`: float32 premultiplied RGBA, shape (H, W, 4), row 0 at the top; `report`: JSON-ready dict."""

    rgba: np.ndarray
    report: dict = field(default_factory=dict)
    scene: dict | None = None  # the scene as rendered (JSON), stored in the PNG beside the report

    def _text(self) -> dict:
        return {k: v for k, v in (("scene", self.scene), ("report", self.report)) if v}

    def save(self, path: str | Path, format: str | None = None) -> Path:
        from lodcast.renderer.image import save_image

        return save_image(path, self.rgba, format, self._text())

    def png_bytes(self) -> bytes:
        from lodcast.renderer.image import png_bytes

        return png_bytes(self.rgba, self._text())

    def _repr_png_(self) -> bytes:  # notebooks show the picture
        return self.png_bytes()


def kernel_config(scene: Scene, orthographic: bool, max_samples: int, lod: bool = False,
                  distribution: bool = False, voxel: str = "float", block_size: int = 16,
                  n_blocks: int = 0) -> KernelConfig:
    """`distribution`: whether the volume keeps the distributions behind its coarse voxels (the scene decides
    whether to use them); `voxel`: the OpenCL C type of its voxels on the device; `block_size`, `n_blocks`: its
    blocks' edge and number. Octant masks need blocks of 16 or more, a multiple of 4 (half-block cells of 4³ are
    full resolution's own, and octants of 2³ skipped little more and took 0.57 s more of an 8³ store's first
    render, chest CT, 2.96 s), and a grid of at most sampler.FINE_CELLS octants, as full resolution's 4³ cells:
    the octants' bounds are kept for the whole grid, 12 bytes each on the host and again on the device (on the
    8 GiB volume's 64 million octants a turntable frame at 30:1 took 12.5 s against 1.2 s, the renderer's peak
    RSS 5.3 GB against 2.1)."""
    s = scene.sampling
    # default (None): on at every quality that samples the atlas. Level-0 cells step on full resolution's lattice
    # (raycast.cl), so "lossless" keeps its image (chest CT, 512², three TFs: mean ΔE against full resolution
    # 0.13/0.08/0.35, with fixed steps 0.12/0.08/0.35) and its coarse blocks, which lose nothing the TF shows, are
    # stepped over faster
    adaptive = lod and (s.adaptive_object is not False or s.adaptive_naive)
    # "lossless" promises full resolution's image: its level 0 keeps full resolution's lattice after coarse cells
    # too (at 128², closer up, mean ΔE against full resolution 0.34 without, 0.17 with, as with fixed steps); the
    # budgeted qualities leave it out (it cost them about 5% of the kernel's time)
    lattice = adaptive and not s.adaptive_naive and scene.quality == "lossless"
    return KernelConfig(
        sampler="atlas" if lod else "full",
        interpolation=(s.interpolation or "nearest_block") if lod else "trilinear",
        adaptive=adaptive,
        adaptive_naive=lod and s.adaptive_naive,
        lattice=lattice,
        distribution=lod and distribution and s.classification == "distribution" and scene.mode == "composite",
        mode=scene.mode,
        orthographic=orthographic,
        ess=s.empty_space_skipping and scene.mode not in ("average", "iso"),  # these read every sample
        octant_cells=block_size >= 16 and block_size % 4 == 0 and 64 * n_blocks <= FINE_CELLS,
        jitter=s.jitter,
        precise=max_samples > PRECISE_SAMPLES,
        background=scene.background[3] > 0,
        clip=scene.clip is not None and len(scene.clip.planes) > 0,
        shade=scene.shading is not None and scene.mode in ("composite", "iso"),
        preint=s.preintegration and scene.mode == "composite",
        tf2=scene.tf2 is not None,
        screen=s.adaptive_screen,
        voxel=voxel,
    )


@dataclass(frozen=True)
class Prepared:
    """Everything a launch needs, computed on the host (also used by the benchmark's bare march), and the engine
    that computed it, whose device and caches the launch uses."""

    engine: Engine
    scene: Scene
    volume: VolumeView
    lut: Lut
    config: KernelConfig
    params: np.ndarray  # (1,) PARAMS_DTYPE
    block_info: np.ndarray
    n_empty: int
    step_world: float
    unit: float
    lod: "LodPlan | None" = None  # level-of-detail renders only
    dist: DistTable | None = None  # distribution classification (LC_DIST) only
    preint: PreintTable | None = None  # pre-integrated classification (LC_PREINT) only
    estimated_samples: int = 0  # renderer/cost.py: the full march's samples, checked against the limit
    second: "dual.SecondTf | None" = None  # tf2 (LC_TF2) only
    priority: "dual.PriorityMap | None" = None  # tf2 with sampling.priority_map only
    screen: "screen_space.ScreenPlan | None" = None  # sampling.adaptive_screen only
    passes: "multipass.PassPlan | None" = None  # volume data beyond the device budget only (LC_PASSES)
    step_delta_e: float = 0.0  # the step's predicted error (selection.step_delta_e), composite renders of a store
    octants: tuple[int, ...] = tuple(range(8))  # the octants of direction the rays go in (camera.ray_octants)


@dataclass(frozen=True)
class LodPlan:
    levels: np.ndarray  # grid-shaped int8, store level per block, -1 = not loaded
    reduction: float | None
    predicted_delta_e: float | None
    step_levels: np.ndarray | None  # adaptive sampling: int8 per half-block cell (atlas.step_levels)
    selection: Any = None
    view_weighted: bool = False  # the selection weighed what the camera sees (visibility.py)


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
    from lodcast.renderer.selection import step_delta_e
    from lodcast.renderer.significance import meta_of_store

    tfs, base = _tfs_and_key(vol, scene, keep)
    key = (*base, scene.sampling.step)
    hit = eng.step_errors.get(key)
    if hit is None:
        hit = step_delta_e(meta_of_store(vol.source, eng.tables), tfs, scene.sampling.step, keep, eng.tables)
        eng.step_errors.put(key, hit, 1)
    return hit  # type: ignore[no-any-return]


def _view_weighted(scene: Scene, vol: VolumeView) -> bool:
    """Whether the selection weighs what the camera sees (visibility.py): sampling.lod_visibility (null: on for
    volumes of at most visibility.AUTO_VOXELS), at the budgeted qualities ('lossless' promises the full-resolution
    image from any view, and selects once per TF), for a single TF composited (the projections and a second TF see
    through what one TF hides)."""
    on = scene.sampling.lod_visibility
    if on is None:
        on = vol.n_voxels <= visibility.AUTO_VOXELS
    return on and not isinstance(scene.quality, str) and scene.mode == "composite" and scene.tf2 is None


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
        lv = np.ascontiguousarray(levels, dtype=np.int8)
        if lv.shape != vol.grid:
            raise SceneError(f"levels: shape {lv.shape} is not the block grid {vol.grid}")
        return lv, None
    if not vol.has_levels:
        raise SceneError(f"quality: {scene.quality!r} needs a lodcast store (an array has only full resolution)")
    from lodcast.renderer.selection import select_lod

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
        if key is not None:
            eng.selections.put(key, sel, 1)
    return np.ascontiguousarray(sel.levels, dtype=np.int8), sel


def _lod_plan(eng: Engine, vol: VolumeView, scene: Scene, levels: np.ndarray | None, info: np.ndarray, cfg: KernelConfig,
              mode: str, keep: np.ndarray | None,
              view: tuple | None = None) -> tuple[LodPlan, np.ndarray, int, KernelConfig]:
    """The selection (blocks outside the clip region `keep` not loaded; weighted by what the camera sees when
    `view` is given, see _select), the block info with unloaded blocks marked empty, the number of empty blocks,
    and the kernel configuration (the default adaptive sampling is dropped when every block is at level 0)."""
    lv, sel = _select(eng, vol, scene, levels, keep, view)
    if cfg.adaptive and scene.sampling.adaptive_object is None and not scene.sampling.adaptive_naive and not (lv > 0).any():
        # the default: every block at level 0 leaves nothing to step over
        cfg = replace(cfg, adaptive=False, lattice=False)
    B = vol.block_size
    if sel is not None:
        reduction, pred = (float(sel.reduction) if math.isfinite(sel.reduction) else None), float(sel.predicted_delta_e)  # None: nothing loaded (JSON has no inf)
    else:
        chosen = int(np.where(lv >= 0, (B >> np.maximum(lv.astype(np.int64), 0)) ** 3, 0).sum())
        reduction, pred = (vol.n_blocks * B**3 / chosen if chosen else None), None
    info = info.copy()
    missing = lv < 0
    info[missing] = -np.inf if mode in EXTREMUM_MODES else 0.0
    # interblock interpolation reaches half a sample of a coarse block (2^(k-1) voxels) past its faces, further
    # than the one-voxel border of the block ranges: where a coarse block is near, a block may show what its
    # neighbours hold, so it takes its neighbourhood's info (empty-space skipping must not change the image)
    near_coarse = (lod_atlas.neighbourhood_max(lv) >= 1) & ~missing
    if near_coarse.any() and cfg.interpolation == "interblock":  # nearest block: half a level-0 voxel, at most
        spread = lod_atlas.neighbourhood_max(info) if scene.tf2 is None else dual.dilate_bits(info, lod_atlas.neighbourhood_max)
        info = np.where(near_coarse, spread, info).astype(np.float32)
    n_empty = int(np.count_nonzero(info == 0.0)) if mode == "composite" else int(missing.sum())
    steps = None
    if cfg.adaptive:
        skip = (info == 0.0) if (mode == "composite" and scene.sampling.empty_space_skipping) else None
        steps = _step_levels(eng, lv, int(B), skip)
    return LodPlan(lv, reduction, pred, steps, sel, view is not None), info, n_empty, cfg


def _step_levels(eng: Engine, lv: np.ndarray, block_size: int, skip: np.ndarray | None) -> np.ndarray:
    """atlas.step_levels, kept for the last few (levels, skip) pairs: a turntable asks for the same each frame, and
    on a grid of a million blocks it costs 0.6 s."""
    key = (block_size, hashlib.sha1(lv.tobytes()).hexdigest(), lv.shape,
           None if skip is None else hashlib.sha1(np.packbits(skip).tobytes()).hexdigest())
    hit = eng.steps.get(key)
    if hit is None:
        hit = lod_atlas.step_levels(lv, block_size, skip)
        eng.steps.put(key, hit, hit.nbytes)
    return hit  # type: ignore[no-any-return]


def geometry(vol: VolumeView, scene: Scene) -> tuple[tuple, cam.Frame, tuple, float]:
    """(the volume's world box, the camera frame, the box the rays integrate (crop box applied), the step in world
    units)."""
    box = cam.box_world(vol.shape, vol.spacing, vol.origin)
    fr = cam.frame(scene.camera, scene.width, scene.height, *box)  # the camera frames the whole volume
    kbox = clipping.clipped_box(box, scene.clip)
    if np.any(kbox[0] >= kbox[1]):  # the crop box misses the volume: a degenerate box no ray enters
        kbox = (kbox[0], kbox[0].copy())
    return box, fr, kbox, scene.sampling.step * float(min(vol.spacing))


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


def _check_cost(eng: Engine, store: Any, scene: Any, sample_limit: int | None = None) -> int:
    vol = as_volume(store, stores=eng.stores)
    scene = resolved(eng, Scene.parse(scene), vol)
    _, fr, kbox, step_world = geometry(vol, scene)
    return _cost(eng, scene, fr, kbox, step_world, sample_limit)


def _prepare(eng: Engine, store: Any, scene: Any, *, spacing: Any = None, origin: Any = None,
             levels: np.ndarray | None = None, sample_limit: int | None = None) -> Prepared:
    vol = as_volume(store, spacing=spacing, origin=origin, stores=eng.stores)
    scene = resolved(eng, Scene.parse(scene), vol)  # "tf": "auto" takes its control points from this volume
    box, fr, kbox, step_world = geometry(vol, scene)
    estimated = _cost(eng, scene, fr, kbox, step_world, sample_limit)
    unit = unit_distance(scene.tf, vol.spacing)
    diag = float(np.linalg.norm(box[1] - box[0]))
    max_samples = int(math.ceil(diag / step_world)) + 2
    if max_samples > MAX_SAMPLES_PER_RAY:
        raise SceneError(
            f"sampling.step: {scene.sampling.step} voxels is too small for this volume "
            f"({max_samples} samples per ray, at most {MAX_SAMPLES_PER_RAY})"
        )
    lut = build_lut(scene.tf, vol.value_range)
    second = None
    if scene.tf2 is not None:
        second = dual.SecondTf(scene.tf2, build_lut(scene.tf2, vol.value_range), unit_distance(scene.tf2, vol.spacing))
    info, n_empty = block_info(vol, lut, scene.mode, None if second is None else second.lut)
    keep = clipping.block_mask(vol.grid, vol.shape, vol.spacing, vol.origin, vol.block_size, scene.clip)
    if keep is not None:  # blocks outside the clip region are empty space
        info = np.where(keep, info, -np.inf if scene.mode in EXTREMUM_MODES else 0.0).astype(np.float32)
        n_empty = int(np.count_nonzero(info == 0.0)) if scene.mode == "composite" else 0
    lod = None
    use_lod = levels is not None or scene.quality != "full"
    cfg = kernel_config(scene, fr.orthographic, max_samples, lod=use_lod, distribution=vol.has_distribution,
                        voxel=VOXEL_CTYPES[vol.voxel_dtype], block_size=int(vol.block_size), n_blocks=vol.n_blocks)
    if use_lod:
        view = (fr, kbox, lut, unit) if levels is None and _view_weighted(scene, vol) else None
        lod, info, n_empty, cfg = _lod_plan(eng, vol, scene, levels, info, cfg, scene.mode, keep, view)
        if scene.mode == "composite" and vol.has_cell_ranges and (lod.levels >= 1).any():
            cfg = replace(cfg, ess=True)  # the walk leaves out coarse cells empty at level 0 (walk.py: _cell_info), always
        if cfg.distribution and not (lod.levels > 0).any():
            cfg = replace(cfg, distribution=False)  # all level 0: nothing to classify by distribution
    dist, pre = _classification_tables(eng, scene.tf, lut, unit, cfg, vol, step_world)
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
                  prio, plan, pp, _step_error(eng, vol, scene, keep), cam.ray_octants(fr))
    if second is not None:
        fill_tf2(params, pr)
    return pr


def _pass_plan(eng: Engine, vol: VolumeView, scene: Scene, fr: cam.Frame, cfg: KernelConfig, info: np.ndarray,
               lod: "LodPlan | None") -> "multipass.PassPlan | None":
    """The passes of a render whose volume data exceeds the device budget or one allocation (renderer/passes.py),
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


def _classification(pr: Prepared) -> str:
    """How coarse samples were classified, for the report."""
    if pr.config.distribution:
        return "distribution"
    if pr.lod is None or not (pr.lod.levels > 0).any():
        return "point (every sample at level 0)"
    if pr.scene.sampling.classification == "distribution" and pr.scene.mode == "composite" and not pr.volume.has_distribution:
        return "mean (this store keeps no distributions, format 1: re-ingest it for distribution classification)"
    return "mean"


def _coarse_cells(pr: Prepared) -> str | None:
    """What became of coarse cells whose level-0 voxels the TF shows nothing of (walk.py: _cell_info), for the report."""
    if pr.lod is None or not (pr.lod.levels > 0).any() or pr.scene.mode != "composite":
        return None
    if pr.volume.has_cell_ranges:
        return "skipped"
    return "sampled (this store keeps no level-0 cell ranges, format < 3: re-ingest it to skip them)"


def _screen_report(pr: Prepared, reconstruct_ms: float) -> dict | None:
    """Adaptive screen-space sampling: the rays cast against one per pixel, and the tiles per resolution."""
    sp = pr.screen
    if sp is None:
        return None
    n, k = np.unique(sp.res, return_counts=True)
    return {"statistic": pr.scene.sampling.screen_statistic, "tile": sp.tile, "rays": sp.rays,
            "rays_per_pixel": sp.rays / (pr.scene.width * pr.scene.height),
            "tiles": {f"{int(a)}x{int(a)}": int(b) for a, b in zip(n, k)}, "reconstruct_ms": reconstruct_ms}


def _priority_report(pr: Prepared, nsamp: np.ndarray) -> dict | None:
    """Dual TF with a priority map: its tile size, the share of pixels with priority (their rays integrate tf2),
    and the samples taken by the pixels with and without it."""
    if pr.priority is None:
        return None
    if pr.screen is None:
        m = pr.priority.pixels(pr.scene.width, pr.scene.height)
    else:  # per ray of the tiles: the map's tile under its image position
        xy = pr.screen.positions.astype(np.int64) // pr.priority.tile
        th, tw = pr.priority.tiles.shape
        m = pr.priority.tiles[np.minimum(xy[:, 1], th - 1), np.minimum(xy[:, 0], tw - 1)].astype(bool)
    return {"tile": pr.priority.tile, "priority_pixels": float(m.mean()),
            "samples_priority": int(nsamp[m].sum(dtype=np.int64)),
            "samples_other": int(nsamp[~m].sum(dtype=np.int64))}


def _prefetch(eng: Engine, store: Any, scene: Any) -> int:
    pr = _prepare(eng, store, scene)
    if pr.lod is None or pr.volume.key is None:
        return 0
    n = 0
    for what in ("mean", "std") if pr.config.distribution else ("mean",):
        st = bricks.BrickStats()
        for _ in bricks.iter_bricks(eng, pr.volume, pr.lod.levels, what=what, stats=st):
            pass  # into the brick cache only: holding them all here would cost the selection's size
        n += st.read
    return n


def launch(queue: cl.CommandQueue, kern: cl.Kernel, width: int, height: int, *, estimated_samples: int = 0,
           stop: Callable[[], None] | None = None) -> list[cl.Event]:
    """Enqueue the image as bands of rows of about BAND_SAMPLES estimated samples each (one band for most renders),
    calling `stop()` after each band but the last: it raises to end the render there (a client gone, a deadline),
    so that no render is beyond reach for longer than one band. The events of the bands launched."""
    lx, ly = LOCAL_SIZE
    gx = int(math.ceil(width / lx) * lx)
    bands = max(1, math.ceil(estimated_samples / BAND_SAMPLES)) if stop is not None else 1
    rows = int(math.ceil(math.ceil(height / bands) / ly) * ly)
    events: list[cl.Event] = []
    for y0 in range(0, height, rows):
        if events:
            events[-1].wait()
            stop()  # type: ignore[misc]
        h = int(math.ceil(min(rows, height - y0) / ly) * ly)
        events.append(cl.enqueue_nd_range_kernel(queue, kern, (gx, h), LOCAL_SIZE, global_work_offset=(0, y0)))
    return events


def _render(eng: Engine, store: Any, scene: Any, *, spacing: Any = None, origin: Any = None,
            levels: np.ndarray | None = None, sample_limit: int | None = None,
            stop: Callable[[], None] | None = None) -> RenderResult:
    t_start = time.perf_counter()
    pr = _prepare(eng, store, scene, spacing=spacing, origin=origin, levels=levels, sample_limit=sample_limit)
    scene, vol, lut, cfg = pr.scene, pr.volume, pr.lut, pr.config
    dev = eng.device
    ctx, queue = dev.context, dev.queue
    mf = cl.mem_flags
    W, H = scene.width, scene.height
    d_lut = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=lut_table(pr))
    d_ext = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=ext_table(pr))
    n_rays = W * H if pr.screen is None else max(pr.screen.rays, 1)
    d_out = cl.Buffer(ctx, mf.WRITE_ONLY, size=n_rays * 16)
    d_n = cl.Buffer(ctx, mf.WRITE_ONLY, size=n_rays * 4)
    spos = pr.screen.positions if pr.screen is not None and pr.screen.rays else np.zeros((1, 2), np.float32)
    d_spos = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=spos)
    d_dtab, d_ptab = (
        cl.Buffer(ctx, mf.READ_ONLY, size=16) if t is None else cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=t)
        for t in (tables(pr, "dist"), tables(pr, "preint"))
    )
    prio = pr.priority.tiles if pr.priority is not None else np.ones(16, np.uint8)
    d_prio = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=prio)
    d_state = cl.Buffer(ctx, mf.READ_WRITE, size=STATE_FLOATS * n_rays * 4 if pr.passes is not None else 4)
    rows = H if pr.screen is None else -(-n_rays // W)  # LC_SCREEN: the rays in rows of W
    evs: list[cl.Event] = []
    stats = multipass.PassStats()
    for k, data in enumerate(multipass.volume_data(pr, stats)):
        if k and stop is not None:
            stop()  # between passes as between bands
        p = pr.params.copy()
        multipass.fill_pass(p, data.region, pr, k == 0)
        walk, p[0]["ess_grid"], leaps = walk_info(pr, data)
        if k == 0:  # the program, once the walk's cells are known
            if pr.passes is None and cfg.sampler == "full" and cfg.ess and scene.mode == "composite" and (walk > 0).all():
                cfg = replace(cfg, ess=False)  # no cell can be skipped: compile the walk out
            options = cfg.build_options()
            built = dev.program("raycast.cl", options)
            # (a pass's buffers go as it ends: a kept kernel would hold the last one's)
            kern = cl.Kernel(built.program, "lc_render") if pr.passes is not None else dev.kernel(built, "lc_render")
        steps, walk, leaps = adaptive_walk(pr, cfg, data, walk, leaps)
        d_info = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=walk)
        planes, p[0]["leap_planes"] = ((np.zeros(1, np.uint8), 0xFFFFFFFF) if leaps is None or not cfg.leap
                                       else leaps.for_octants(pr.octants))
        d_leaps = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=planes)
        d_params = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=p)
        d_steps = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=steps)
        d_own = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=data.own)
        kern.set_args(d_params, data.vol, d_lut, d_ext, d_info, d_out, d_n, data.index, d_steps, data.std, d_dtab,
                      d_ptab, d_prio, d_spos, d_own, d_state, d_leaps)
        evs += launch(queue, kern, W, rows, estimated_samples=pr.estimated_samples // stats.planned, stop=stop)
        if pr.passes is not None:
            evs[-1].wait()  # this pass's data may go before the next is uploaded
        del data
    n_read, n_cached, upload_ms = stats.read, stats.cached, stats.upload_ms
    rgba = np.empty((H, W, 4) if pr.screen is None else (n_rays, 4), np.float32)
    nsamp = np.empty((H, W) if pr.screen is None else (n_rays,), np.uint32)
    cl.enqueue_copy(queue, rgba, d_out, wait_for=evs)
    cl.enqueue_copy(queue, nsamp, d_n, wait_for=evs)
    queue.finish()
    t_rec = time.perf_counter()
    if pr.screen is not None:  # the mosaic, reconstructed by intertile interpolation
        rgba = screen_space.reconstruct(pr.screen, rgba[: pr.screen.rays]).astype(np.float32)
    reconstruct_ms = (time.perf_counter() - t_rec) * 1e3
    kernel_ms = sum(ev.profile.end - ev.profile.start for ev in evs) * 1e-6
    n_blocks = vol.n_blocks
    if pr.lod is None:
        skipped = pr.n_empty if (scene.sampling.empty_space_skipping and scene.mode == "composite") else 0
        reduction, pred, quality = 1.0, pr.step_delta_e, "full"
    else:
        skipped = int(np.count_nonzero(pr.lod.levels < 0))
        reduction = pr.lod.reduction
        pred = None if pr.lod.predicted_delta_e is None else pr.lod.predicted_delta_e + pr.step_delta_e
        quality = scene.quality if isinstance(scene.quality, str) else scene.quality.model_dump()
    report = {
        "wall_ms": (time.perf_counter() - t_start) * 1e3,
        "kernel_ms": kernel_ms,
        "bricks_read": n_read,
        "bricks_cached": n_cached,
        "bricks_skipped": skipped,
        "reduction": reduction,
        "predicted_delta_e": pred,
        "samples": int(nsamp.sum(dtype=np.int64)),
        "estimated_samples": pr.estimated_samples,
        "launches": len(evs),
        "build_options": list(options),
        "program_cache": built.source,
        "build_ms": built.build_ms,
        "upload_ms": upload_ms,
        "quality": quality,
        "level": 0 if pr.lod is None else None,
        "interpolation": cfg.interpolation,
        "classification": _classification(pr),
        "coarse_cells": _coarse_cells(pr),
        "adaptive": "naive" if cfg.adaptive_naive else ("limited" if cfg.adaptive else False),
        "lod_visibility": pr.lod is not None and pr.lod.view_weighted,
        "blocks": n_blocks,
        "step_world": pr.step_world,
        "unit_distance": pr.unit,
        "lut_entries": lut.n,
        "lut_exact": lut.exact,
        "preintegration_ms": None if pr.preint is None else pr.preint.build_ms,
        "tf2": pr.second is not None,
        "priority_map": _priority_report(pr, nsamp),
        "adaptive_screen": _screen_report(pr, reconstruct_ms),
        "device_bytes": stats.device_bytes,
        "passes": stats.passes,
        "width": W,
        "height": H,
        "device": dev.info()["name"],
    }
    return RenderResult(rgba, report, scene.model_dump(mode="json"))


class Renderer(Engine):
    """The rendering engine: an OpenCL device (context and queue), the brick and device caches, the selection, walk,
    significance and step-error caches, the opened stores, and the settings read from the environment once, when
    it is made (each keyword overrides its ``LODCAST_*`` variable: `device` LODCAST_DEVICE, `device_budget_mb`
    LODCAST_DEVICE_BUDGET_MB (10⁶ bytes), `brick_cache_mb` LODCAST_BRICK_CACHE_MB and `device_cache_mb`
    LODCAST_DEVICE_CACHE_MB (MiB)). Its verbs are thread-safe; two renderers share nothing but the kernel
    binaries cached on disk. `lodcast.render` and the other module-level verbs use `default_renderer()`."""

    def __init__(self, *, device: str | None = None, device_budget_mb: float | None = None,
                 brick_cache_mb: float | None = None, device_cache_mb: float | None = None) -> None:
        super().__init__(device=device, device_budget_mb=device_budget_mb, brick_cache_mb=brick_cache_mb,
                         device_cache_mb=device_cache_mb)

    def render(self, store: Any, scene: Any, *, spacing: Any = None, origin: Any = None,
               levels: np.ndarray | None = None, sample_limit: int | None = None,
               stop: Callable[[], None] | None = None) -> RenderResult:
        """Render `scene` (a Scene, dict, JSON text or file) of `store` (a lodcast store, its path or URL, or a 3D
        array with optional `spacing`/`origin`, z-y-x). Raises SceneError (a ValueError) naming the field on bad
        input. `levels` (grid-shaped, store level per block, -1 = not loaded) replaces the LOD selection (tests,
        experiments): the atlas path renders it whatever the quality. `sample_limit`: see `prepare`. `stop`:
        called between launch bands (see `launch`); whatever it raises ends the render there."""
        return _render(self, store, scene, spacing=spacing, origin=origin, levels=levels,
                       sample_limit=sample_limit, stop=stop)

    def prepare(self, store: Any, scene: Any, *, spacing: Any = None, origin: Any = None,
                levels: np.ndarray | None = None, sample_limit: int | None = None) -> Prepared:
        """Everything a launch needs. `sample_limit`: the most samples the render may take (estimated before it
        starts: renderer/cost.py), default LODCAST_MAX_SAMPLES or 2·10⁹; above it CostError (a SceneError) names
        the field."""
        return _prepare(self, store, scene, spacing=spacing, origin=origin, levels=levels,
                        sample_limit=sample_limit)

    def prefetch(self, store: Any, scene: Any) -> int:
        """Read the bricks a render of `scene` will need (its level-of-detail selection, and the distributions
        behind coarse bricks) into the brick cache, without touching the device but for the small cast that weighs
        the selection by the view (visibility.py, on a queue of its own): a job calls it for its next frame while
        the current one renders. The bricks read from the store (0: all cached already, or a scene at quality
        "full", whose level 0 goes to the device whole)."""
        return _prefetch(self, store, scene)

    def check_cost(self, store: Any, scene: Any, sample_limit: int | None = None) -> int:
        """The samples `scene` of `store` would take (renderer/cost.py), before anything is loaded or built;
        raises CostError naming the field when that is above `sample_limit` (default LODCAST_MAX_SAMPLES)."""
        return _check_cost(self, store, scene, sample_limit)

    def visibility(self, store: Any, scene: Any) -> np.ndarray:
        """Per block, what the camera of `scene` sees of it (visibility.block_visibility), as a render computes it
        for its selection: to look at, or to select with outside a render (selection.select_lod's
        `visibility`)."""
        vol = as_volume(store, stores=self.stores)
        sc = resolved(self, Scene.parse(scene), vol)
        _, fr, kbox, _ = geometry(vol, sc)
        return visibility.block_visibility(self, vol, sc, fr, kbox, build_lut(sc.tf, vol.value_range),
                                           unit_distance(sc.tf, vol.spacing))


_DEFAULT: list[Renderer] = []  # the default renderer, made on first use (default_renderer)
_DEFAULT_LOCK = threading.Lock()


def default_renderer() -> Renderer:
    """The renderer `lodcast.render` and the other module-level verbs use, made on first use with the environment
    as it is then."""
    with _DEFAULT_LOCK:
        if not _DEFAULT:
            _DEFAULT.append(Renderer())
        return _DEFAULT[0]


def render(store: Any, scene: Any, *, spacing: Any = None, origin: Any = None, levels: np.ndarray | None = None,
           sample_limit: int | None = None, stop: Callable[[], None] | None = None) -> RenderResult:
    """`Renderer.render` on the default renderer."""
    return default_renderer().render(store, scene, spacing=spacing, origin=origin, levels=levels,
                                     sample_limit=sample_limit, stop=stop)


def prepare(store: Any, scene: Any, *, spacing: Any = None, origin: Any = None, levels: np.ndarray | None = None,
            sample_limit: int | None = None) -> Prepared:
    """`Renderer.prepare` on the default renderer."""
    return default_renderer().prepare(store, scene, spacing=spacing, origin=origin, levels=levels,
                                      sample_limit=sample_limit)


def prefetch(store: Any, scene: Any) -> int:
    """`Renderer.prefetch` on the default renderer."""
    return default_renderer().prefetch(store, scene)


def check_cost(store: Any, scene: Any, sample_limit: int | None = None) -> int:
    """`Renderer.check_cost` on the default renderer."""
    return default_renderer().check_cost(store, scene, sample_limit)
