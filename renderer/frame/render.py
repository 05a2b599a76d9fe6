"""`lodcast.Renderer`, the engine, and `lodcast.render(store, scene) -> RenderResult`: one frame through the OpenCL
ray caster.

A `Renderer` (an `Engine`, renderer/engine.py, with the verbs) owns the OpenCL device, the caches and the settings;
`lodcast.render` and the other module-level verbs use a default one, made on first use. Every function below the
verbs takes the engine it works for.

Quality 'full' reads level 0 as one buffer (LC_SAMPLER_FULL): bricks_read counts level-0 blocks uploaded by this
call, bricks_cached those already on the device, bricks_skipped the blocks empty-space skipping leaves out (TF
opacity zero over their border-inclusive value range), reduction is 1 and predicted_delta_e 0.

Any other quality ('lossless', {"budget_mb"}, {"reduction"}) selects a level per block (renderer/lod/selection.py,
thesis §3.2), packs the selected bricks into the atlas (renderer/data/atlas.py: bricks_read / bricks_cached count the
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

import contextlib
import math
import threading
import time
from dataclasses import replace
from typing import Any, Callable, Iterator, Literal

import numpy as np
import pyopencl as cl

from lodcast.renderer.data import passes as multipass
from lodcast.renderer.data.volume import StoreLike, as_volume
from lodcast.renderer.engine import Engine
from lodcast.renderer.frame import prepare as preparing
from lodcast.renderer.frame import screen as screen_space
from lodcast.renderer.frame import target
from lodcast.renderer.frame.plan import Prepared
from lodcast.renderer.frame.progressive import Ladder, Progressive
from lodcast.renderer.image.output import RenderResult
from lodcast.renderer.image.report import PriorityMapReport, RenderReport, ScreenReport
from lodcast.renderer.kernel.params import ext_table, lut_table, tables
from lodcast.renderer.kernel.structs import STATE_FLOATS
from lodcast.renderer.lod import visibility
from lodcast.renderer.scene import camera as cam
from lodcast.renderer.scene.scene import QualityLevel, Scene, SceneLike, TransferFunction
from lodcast.renderer.scene.transfer_function import build_lut, unit_distance
from lodcast.renderer.walk.info import adaptive_walk, walk_info

__all__ = ["Renderer", "RenderResult", "RenderReport", "StoreLike", "SceneLike", "default_renderer", "render",
           "render_progressive", "Ladder", "prepare", "prefetch", "check_cost", "launch", "LOCAL_SIZE"]

LOCAL_SIZE = (8, 8)
BAND_SAMPLES = 10_000_000  # a launch band: a stop, and a small render (Turns), wait for the bands on the device


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


def _screen_report(pr: Prepared, reconstruct_ms: float) -> ScreenReport | None:
    """Adaptive screen-space sampling: the rays cast against one per pixel, and the tiles per resolution."""
    sp = pr.screen
    if sp is None:
        return None
    n, k = np.unique(sp.res, return_counts=True)
    return {"statistic": pr.scene.sampling.screen_statistic, "tile": sp.tile, "rays": sp.rays,
            "rays_per_pixel": sp.rays / (pr.scene.width * pr.scene.height),
            "tiles": {f"{int(a)}x{int(a)}": int(b) for a, b in zip(n, k)}, "reconstruct_ms": reconstruct_ms}


def _priority_report(pr: Prepared, nsamp: np.ndarray) -> PriorityMapReport | None:
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


class Turns:
    """Who may launch next on one device. A render of one band (a small one) launches at once, and while one is
    under way no band of a bigger render starts; the bands of bigger renders take turns, at most `slots` of them on
    the device at once (one running, the next queued behind it, so that the device is not left idle while the next
    one's thread wakes). A CPU device such as PoCL's runs the commands of all queues one after another in the order
    they came, so without turns a small render's kernel, and then its read-back, would wait behind a band of every
    big render in flight; with them it waits for the bands already on the device when it came. A band waits for
    small renders at most `yield_s` seconds, so that a stream of small ones cannot stop a big one for good."""

    def __init__(self, yield_s: float = 2.0, slots: int = 2) -> None:
        self.yield_s, self.slots = yield_s, slots
        self._cv = threading.Condition()
        self._small = 0
        self._bands = 0

    @contextlib.contextmanager
    def small(self) -> Iterator[None]:
        """Held by a small render from its kernel to its read-back."""
        with self._cv:
            self._small += 1
        try:
            yield
        finally:
            with self._cv:
                self._small -= 1
                self._cv.notify_all()

    @contextlib.contextmanager
    def band(self) -> Iterator[None]:
        """Held while one band of a big render is on the device (enqueued and waited for)."""
        with self._cv:
            deadline = time.monotonic() + self.yield_s
            while True:
                if self._bands >= self.slots:
                    self._cv.wait()
                    continue
                left = deadline - time.monotonic()
                if not self._small or left <= 0:
                    break
                self._cv.wait(left)
            self._bands += 1
        try:
            yield
        finally:
            with self._cv:
                self._bands -= 1
                self._cv.notify_all()


def bands(estimated_samples: int) -> int:
    """How many bands a launch of `estimated_samples` samples is cut into."""
    return max(1, math.ceil(estimated_samples / BAND_SAMPLES))


def launch(queue: cl.CommandQueue, kern: cl.Kernel, width: int, height: int, *, estimated_samples: int = 0,
           stop: Callable[[], None] | None = None, turns: Turns | None = None) -> list[cl.Event]:
    """Enqueue the image as bands of rows of about BAND_SAMPLES estimated samples each (one band for most renders),
    each band after the one before has finished, calling `stop()` (if given) between them: it raises to end the
    render there (a client gone, a deadline), so that no render is beyond reach for longer than one band. With
    `turns` (the device's, see Turns; none for a small render) each band runs in its turn and has finished on
    return.
    The events of the bands launched."""
    lx, ly = LOCAL_SIZE
    gx = int(math.ceil(width / lx) * lx)
    n = bands(estimated_samples)
    rows = int(math.ceil(math.ceil(height / n) / ly) * ly)
    events: list[cl.Event] = []
    for y0 in range(0, height, rows):
        if events:
            events[-1].wait()
            if stop is not None:
                stop()
        h = int(math.ceil(min(rows, height - y0) / ly) * ly)
        # the offset (0, y0) positionally: pyopencl's binding calls it global_work_offset, its stub global_offset
        if turns is None:
            events.append(cl.enqueue_nd_range_kernel(queue, kern, (gx, h), LOCAL_SIZE, (0, y0)))
            continue
        with turns.band():
            events.append(cl.enqueue_nd_range_kernel(queue, kern, (gx, h), LOCAL_SIZE, (0, y0)))
            events[-1].wait()
    return events


def _render(eng: Renderer, store: StoreLike, scene: SceneLike, *, spacing: Any = None, origin: Any = None,
            levels: np.ndarray | None = None, sample_limit: int | None = None,
            stop: Callable[[], None] | None = None) -> RenderResult:
    t_start = time.perf_counter()
    pr = preparing.prepare(eng, store, scene, spacing=spacing, origin=origin, levels=levels,
                          sample_limit=sample_limit)
    scene, vol, lut, cfg = pr.scene, pr.volume, pr.lut, pr.config
    dev = eng.device
    ctx, queue = dev.context, dev.queue
    mf = cl.mem_flags
    W, H = scene.width, scene.height
    dev_turns = eng.turns
    small = pr.passes is None and bands(pr.estimated_samples) == 1
    with contextlib.ExitStack() as held:
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
        owners: list[Any] = []
        stats = multipass.PassStats()
        for k, data in enumerate(multipass.volume_data(pr, stats)):
            if k and stop is not None:
                stop()  # between passes as between bands
            p = pr.params.copy()
            multipass.fill_pass(p, data.region, pr, k == 0)
            walk, p[0]["ess_grid"], leaps = walk_info(pr, data)
            if k == 0 and small:
                # first on the device from its kernel to its read-back (Turns), but not while its bricks are
                # read: a slow store would hold the big renders back for nothing
                held.enter_context(dev_turns.small())
            if k == 0:  # the program, once the walk's cells are known
                if pr.passes is None and cfg.sampler == "full" and cfg.ess and scene.mode == "composite" and (walk > 0).all():
                    cfg = replace(cfg, ess=False)  # no cell can be skipped: compile the walk out
                options = cfg.build_options()
                built = dev.program("raycast.cl", options)
                # (a pass's buffers go as it ends: a kept kernel would hold the last one's)
                kern = cl.Kernel(built.program, "lc_render") if pr.passes is not None else dev.kernel(built, "lc_render")
            steps, walk, leaps = adaptive_walk(pr, cfg, data, walk, leaps)
            d_info = dev.read_only(walk)  # (walk, steps and leaps are kept: see walk/info.py)
            planes, p[0]["leap_planes"] = ((np.zeros(1, np.uint8), 0xFFFFFFFF) if leaps is None or not cfg.leap
                                           else leaps.for_octants(pr.octants))
            d_leaps = dev.read_only(planes)
            d_params = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=p)
            d_steps = dev.read_only(steps)
            d_own = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=data.own)
            kern.set_args(d_params, data.vol, d_lut, d_ext, d_info, d_out, d_n, data.index, d_steps, data.std, d_dtab,
                          d_ptab, d_prio, d_spos, d_own, d_state, d_leaps)
            evs += launch(queue, kern, W, rows, estimated_samples=pr.estimated_samples // stats.planned, stop=stop,
                          turns=None if small else dev_turns)
            if pr.passes is not None:
                evs[-1].wait()  # this pass's data may go before the next is uploaded
            else:  # its atlas's buffers must stay its own until the image is read back (atlas.py: _Lease)
                owners.append(data.owner)
            del data
        n_read, n_cached, upload_ms = stats.read, stats.cached, stats.upload_ms
        rgba = np.empty((H, W, 4) if pr.screen is None else (n_rays, 4), np.float32)
        nsamp = np.empty((H, W) if pr.screen is None else (n_rays,), np.uint32)
        cl.enqueue_copy(queue, rgba, d_out, wait_for=evs)
        cl.enqueue_copy(queue, nsamp, d_n, wait_for=evs)
        queue.finish()
        owners.clear()
    t_rec = time.perf_counter()
    if pr.screen is not None:  # the mosaic, reconstructed by intertile interpolation
        rgba = screen_space.reconstruct(pr.screen, rgba[: pr.screen.rays]).astype(np.float32)
    reconstruct_ms = (time.perf_counter() - t_rec) * 1e3
    kernel_ms = sum(ev.profile.end - ev.profile.start for ev in evs) * 1e-6
    n_blocks = vol.n_blocks
    reduction: float | None
    pred: float | None
    quality: Literal["full", "lossless"] | dict[str, Any]
    if pr.lod is None:
        skipped = pr.n_empty if (scene.sampling.empty_space_skipping and scene.mode == "composite") else 0
        reduction, pred, quality = 1.0, pr.step_delta_e, "full"
    else:
        skipped = int(np.count_nonzero(pr.lod.levels < 0))
        reduction = pr.lod.reduction
        pred = None if pr.lod.predicted_delta_e is None else pr.lod.predicted_delta_e + pr.step_delta_e
        if pred is not None and pr.screen is not None:
            pred += screen_space.predicted_delta_e(pr.screen)
        quality = scene.quality if isinstance(scene.quality, str) else scene.quality.model_dump()
    asked = scene if pr.chosen is None else pr.chosen[0]
    if pr.chosen is not None:
        quality = asked.quality if isinstance(asked.quality, str) else asked.quality.model_dump()
    report: RenderReport = {
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
        "level": 0 if pr.lod is None else (scene.quality.level if isinstance(scene.quality, QualityLevel) else None),
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
        "stage": 0,
        "final": True,
        "image_scale": 1.0,
        "chosen": None if pr.chosen is None else pr.chosen[1].report(asked.quality),
    }
    if pr.chosen is not None:
        choice = pr.chosen[1]
        target.observe(eng, vol, scene, choice.chosen, report["wall_ms"] - choice.choose_ms)
    return RenderResult(rgba, report, asked.model_dump(mode="json"))


class Renderer(Engine):
    """The rendering engine: an OpenCL device (context and queue), the brick and device caches, the selection, walk,
    significance and step-error caches, the opened stores, and the settings read from the environment once, when
    it is made (each keyword overrides its ``LODCAST_*`` variable: `device` LODCAST_DEVICE, `device_budget_mb`
    LODCAST_DEVICE_BUDGET_MB (10⁶ bytes), `brick_cache_mb` LODCAST_BRICK_CACHE_MB and `device_cache_mb`
    LODCAST_DEVICE_CACHE_MB (MiB), `open_stores` LODCAST_OPEN_STORES; `store_check_s`: how long a store on object
    storage is trusted to exist between checks, 0 by default). Its verbs are thread-safe; two renderers share nothing but the kernel
    binaries cached on disk. `lodcast.render` and the other module-level verbs use `default_renderer()`. `turns`
    (Turns): who launches next on its device, shared by the threads that render with it."""

    def __init__(self, *, device: str | None = None, device_budget_mb: float | None = None,
                 brick_cache_mb: float | None = None, device_cache_mb: float | None = None,
                 open_stores: int | None = None, store_check_s: float = 0.0) -> None:
        super().__init__(device=device, device_budget_mb=device_budget_mb, brick_cache_mb=brick_cache_mb,
                         device_cache_mb=device_cache_mb, open_stores=open_stores, store_check_s=store_check_s)
        self.turns = Turns()

    def render(self, store: StoreLike, scene: SceneLike, *, spacing: Any = None, origin: Any = None,
               levels: np.ndarray | None = None, sample_limit: int | None = None,
               stop: Callable[[], None] | None = None) -> RenderResult:
        """Render `scene` (a Scene, dict, JSON text or file) of `store` (a lodcast store, its path or URL, or a 3D
        array with optional `spacing`/`origin`, z-y-x). Raises SceneError (a ValueError) naming the field on bad
        input. `levels` (grid-shaped, store level per block, -1 = not loaded) replaces the LOD selection (tests,
        experiments): the atlas path renders it whatever the quality. `sample_limit`: see `prepare`. `stop`:
        called between launch bands (see `launch`); whatever it raises ends the render there."""
        return _render(self, store, scene, spacing=spacing, origin=origin, levels=levels,
                       sample_limit=sample_limit, stop=stop)

    def render_progressive(self, store: StoreLike, scene: SceneLike, *, ladder: Ladder | None = None,
                           sample_limit: int | None = None,
                           stop: Callable[[], None] | None = None) -> Iterator[RenderResult]:
        """`scene` of `store` coarse to fine (renderer/frame/progressive.py): RenderResults of the scene's size,
        the last at its quality and equal to `render(store, scene)`; each report's `stage`, `final` and wall_ms
        since the first stage was asked for. Each stage renders when the next result is asked for: closing the
        generator ends the work. `ladder` (progressive.Ladder) changes the staging; `sample_limit` and `stop` as
        `render`'s, for every stage."""
        prog = Progressive.plan(self, self.render, store, scene, ladder or Ladder())
        for k in range(len(prog.stages)):
            yield prog.render(k, sample_limit, stop)

    def prepare(self, store: StoreLike, scene: SceneLike, *, spacing: Any = None, origin: Any = None,
                levels: np.ndarray | None = None, sample_limit: int | None = None) -> Prepared:
        """Everything a launch needs. `sample_limit`: the most samples the render may take (estimated before it
        starts: renderer/scene/cost.py), default LODCAST_MAX_SAMPLES or 2·10⁹; above it CostError (a SceneError) names
        the field."""
        return preparing.prepare(self, store, scene, spacing=spacing, origin=origin, levels=levels,
                                 sample_limit=sample_limit)

    def prefetch(self, store: StoreLike, scene: SceneLike) -> int:
        """Read the bricks a render of `scene` will need (its level-of-detail selection, and the distributions
        behind coarse bricks) into the brick cache, without touching the device but for the small cast that weighs
        the selection by the view (visibility.py, on a queue of its own): a job calls it for its next frame while
        the current one renders. Bricks the newest atlas of the store already holds at their level are left out:
        the render copies those on the device. The bricks read from the store (0: all cached or on the device
        already, or a scene at quality "full", whose level 0 goes to the device whole)."""
        return preparing.prefetch(self, store, scene)

    def build_ahead(self, store: StoreLike, scenes: Any = None, progress: Any = None) -> list:
        """Build the kernel programs `scenes` (default ahead.AHEAD: full resolution, lossless and 30:1 with either
        interpolation, unlit and lit) need on `store`, without reading a voxel: renders that follow find them
        compiled, and later processes on disk. A list of ahead.AheadBuild (scene, options, where the program came
        from, ms); `progress` is called with each."""
        from lodcast.renderer.frame import ahead

        return ahead.build_ahead(self, store, ahead.AHEAD if scenes is None else scenes, progress)

    def check_cost(self, store: StoreLike, scene: SceneLike, sample_limit: int | None = None) -> int:
        """The samples `scene` of `store` would take (renderer/scene/cost.py), before anything is loaded or built;
        raises CostError naming the field when that is above `sample_limit` (default LODCAST_MAX_SAMPLES)."""
        return preparing.check_cost(self, store, scene, sample_limit)

    def visibility(self, store: StoreLike, scene: SceneLike) -> np.ndarray:
        """Per block, what the camera of `scene` sees of it (visibility.block_visibility), as a render computes it
        for its selection: to look at, or to select with outside a render (selection.select_lod's
        `visibility`)."""
        vol = as_volume(store, stores=self.stores)
        sc = preparing.resolved(self, Scene.parse(scene), vol)
        _, fr, kbox, _ = cam.geometry(vol, sc)
        assert isinstance(sc.tf, TransferFunction)  # resolved() put an adaptive TF's control points in its place
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


def render(store: StoreLike, scene: SceneLike, *, spacing: Any = None, origin: Any = None, levels: np.ndarray | None = None,
           sample_limit: int | None = None, stop: Callable[[], None] | None = None) -> RenderResult:
    """`Renderer.render` on the default renderer."""
    return default_renderer().render(store, scene, spacing=spacing, origin=origin, levels=levels,
                                     sample_limit=sample_limit, stop=stop)


def render_progressive(store: StoreLike, scene: SceneLike, *, ladder: Ladder | None = None,
                       sample_limit: int | None = None,
                       stop: Callable[[], None] | None = None) -> Iterator[RenderResult]:
    """`Renderer.render_progressive` on the default renderer."""
    return default_renderer().render_progressive(store, scene, ladder=ladder, sample_limit=sample_limit, stop=stop)


def prepare(store: StoreLike, scene: SceneLike, *, spacing: Any = None, origin: Any = None, levels: np.ndarray | None = None,
            sample_limit: int | None = None) -> Prepared:
    """`Renderer.prepare` on the default renderer."""
    return default_renderer().prepare(store, scene, spacing=spacing, origin=origin, levels=levels,
                                      sample_limit=sample_limit)


def prefetch(store: StoreLike, scene: SceneLike) -> int:
    """`Renderer.prefetch` on the default renderer."""
    return default_renderer().prefetch(store, scene)


def check_cost(store: StoreLike, scene: SceneLike, sample_limit: int | None = None) -> int:
    """`Renderer.check_cost` on the default renderer."""
    return default_renderer().check_cost(store, scene, sample_limit)
