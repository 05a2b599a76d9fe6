"""Progressive renders: a scene rendered coarse to fine, each stage a whole H×W picture, the last the scene itself.

`stage_plan` decides the stages before anything is loaded: the scene's quality last, and before it coarser
level-of-detail selections holding 1/64 and 1/8 of the final's data (`Ladder.factors`), the first of them on a
smaller image scaled up to H×W. A coarse stage is dropped where it would not be much cheaper than the one after it
(a volume that is small already, a final that is coarse already, a store whose coarsest level is reached), so a
scene may have the final stage alone.

A large store (more than `Ladder.preview_voxels` at level 0) is first shown as one of its coarse levels rendered as
a volume of its own (volume.level_view: the finest level of at most `Ladder.preview_level_voxels`), on the smaller
image: one read of a small array, where a selection's first stage needs the TF's error tables over every block and
a brick per visible block (on a million blocks, many seconds before anything shows). That stage has no selection,
so its report predicts no ΔE (null) and gives the level's reduction; the selections' stages follow. The stages run on one engine, one after the other, so what an early stage
reads stays in its brick cache for the later ones (the coarse levels a selection keeps, the metadata and tables of
the TF), and a stage is only rendered when the caller asks for it: a generator closed early renders nothing more.

`Progressive` is a plan under way (its stages and the clock started at the request), for callers that run the
stages themselves (the HTTP stream runs each on a worker thread); `Renderer.render_progressive` iterates it.
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from lodcast.renderer.data.volume import StoreLike, VolumeView, as_volume, level_view
from lodcast.renderer.engine import Engine
from lodcast.renderer.frame import prepare as preparing
from lodcast.renderer.image.output import RenderResult
from lodcast.renderer.image.report import RenderReport
from lodcast.renderer.scene.scene import (
    QualityLevel,
    QualityMaxDeltaE,
    QualityMaxMs,
    QualityReduction,
    Scene,
    SceneLike,
)

#: an engine's render (renderer/frame/render.py: Renderer.render), handed in so that this module does not import
#: the one that imports it
RenderFn = Callable[..., RenderResult]

__all__ = ["Ladder", "Stage", "Progressive", "stage_plan", "upsample", "final_reduction"]


@dataclass(frozen=True)
class Ladder:
    """How a progressive render is staged. `factors`: each coarse stage's data reduction as a multiple of the
    final's, coarsest first; `min_gain`: a coarse stage is kept when it holds at most 1/min_gain of the data of the
    stage after it; `first_scale`: the first stage's image edge against the scene's (its rays are what a coarse
    level's time goes to), used where both edges stay at least `min_edge` pixels; `min_voxels`: a volume with fewer
    voxels renders its final stage alone (its full resolution is quick already); `preview_voxels`: a store with
    more voxels is shown first as its finest level of at most `preview_level_voxels` (module doc)."""

    factors: tuple[float, ...] = (64.0, 8.0)
    min_gain: float = 4.0
    first_scale: float = 0.5
    min_edge: int = 32
    min_voxels: int = 64**3
    preview_voxels: int = 1 << 27
    preview_level_voxels: int = 1 << 24

    def __post_init__(self) -> None:
        if any(not f > 1.0 for f in self.factors) or list(self.factors) != sorted(self.factors, reverse=True):
            raise ValueError(f"factors: each above 1, largest first, got {self.factors}")
        if not self.min_gain >= 1.0 or not 0.0 < self.first_scale <= 1.0 or self.min_edge < 1:
            raise ValueError("min_gain: at least 1; first_scale: in (0, 1]; min_edge: at least 1")


@dataclass(frozen=True)
class Stage:
    """One stage: the scene it renders (the final's, or a coarser quality and perhaps a smaller image) and the
    size its picture is scaled up to."""

    scene: Scene
    width: int
    height: int
    final: bool
    level: int | None = None  # a store's coarse level rendered as a volume of its own (module doc), else None

    @property
    def image_scale(self) -> float:
        """Rays per pixel edge: 1, or less where a smaller image is scaled up."""
        return self.scene.width / self.width


def final_reduction(engine: Engine, scene: Scene, vol: VolumeView) -> float:
    """The data reduction of the scene's quality, as far as it is known before rendering: 1 at "full", the asked
    reduction, a budget's share of the whole volume (at most the visible blocks' share: coarse stages then hold
    less, never more), or at "lossless" and a level its selection's (made here once, the final stage finds it made; infinite
    when nothing is visible)."""
    q = scene.quality
    if isinstance(q, (QualityMaxDeltaE, QualityMaxMs)):
        return 1.0  # a target picks its setting when the final stage renders: the ladder starts from full
    if isinstance(q, QualityReduction):
        return float(q.reduction)
    if q == "lossless" or isinstance(q, QualityLevel):
        return float(preparing.selection(engine, vol, scene).reduction)
    if isinstance(q, str):
        return 1.0
    return max(1.0, vol.n_voxels * vol.voxel_dtype.itemsize / (q.budget_mb * 1e6))


def _coarse_reductions(engine: Engine, scene: Scene, vol: VolumeView, ladder: Ladder) -> list[float]:
    """The coarse stages' reductions, coarsest first: each a factor of the final's, within what the store's
    coarsest level gives, and each at least min_gain times the next."""
    if not vol.has_levels or vol.n_voxels < ladder.min_voxels:
        return []
    final = final_reduction(engine, scene, vol)
    if not math.isfinite(final):
        return []
    most = float(8 ** (vol.n_levels - 1))  # every block at the coarsest level
    kept, finer = [], final
    for r in sorted({min(f * final, most) for f in ladder.factors}):  # finest first: it wins a tie at the cap
        if r >= ladder.min_gain * finer:
            kept.append(r)
            finer = r
    return kept[::-1]


def _preview_level(vol: VolumeView, ladder: Ladder) -> int | None:
    """The coarse level a large store is first shown as (module doc), or None."""
    if not vol.has_levels or vol.n_voxels <= ladder.preview_voxels:
        return None
    for k in range(1, vol.n_levels):
        if int(np.prod(vol.level_shape(k), dtype=np.int64)) <= ladder.preview_level_voxels:
            return k
    return vol.n_levels - 1 if vol.n_levels > 1 else None


def _preview_scene(scene: Scene, vol: VolumeView, w: int, h: int) -> Scene:
    """The scene of a preview stage: at quality "full" of the level's volume, with the store's opacity unit (a TF
    without its own would take the level's coarser spacing as its unit and show more transparent)."""
    unit = float(min(vol.spacing))
    update: dict = {"quality": "full", "width": w, "height": h}
    for name in ("tf", "tf2"):
        tf = getattr(scene, name)
        if tf is not None and tf.unit_distance is None:
            update[name] = tf.model_copy(update={"unit_distance": unit})
    return scene.model_copy(update=update)


def stage_plan(engine: Engine, scene: Scene, vol: VolumeView, ladder: Ladder = Ladder()) -> list[Stage]:
    """The stages of a progressive render of `scene` on `vol`, the final (the scene itself) last."""
    W, H = scene.width, scene.height
    small = round(min(W, H) * ladder.first_scale) >= ladder.min_edge
    stages = []
    reductions = _coarse_reductions(engine, scene, vol, ladder)
    level = _preview_level(vol, ladder)
    if level is not None:
        # resolved on the store: an adaptive TF or a named view taken on the level's volume would differ
        resolved = preparing.resolved(engine, scene, vol)
        w, h = (max(1, round(W * ladder.first_scale)), max(1, round(H * ladder.first_scale))) if small else (W, H)
        stages.append(Stage(_preview_scene(resolved, vol, w, h), W, H, False, level))
        preview = vol.n_voxels / float(np.prod(vol.level_shape(level), dtype=np.int64))
        reductions = [r for r in reductions if ladder.min_gain * r <= preview]
    for i, r in enumerate(reductions):
        w, h = W, H
        if i == 0 and level is None and small:
            w, h = max(1, round(W * ladder.first_scale)), max(1, round(H * ladder.first_scale))
        # a preview samples adaptively whatever the scene says (coarse blocks hold nothing a finer step could find),
        # and selects by the TF alone: its selection and atlas then serve every view, so a new view's first stage
        # costs its kernel, not a visibility cast, a selection and a packing
        sampling = scene.sampling.model_copy(update={"adaptive_object": None, "adaptive_naive": False,
                                                     "lod_visibility": False})
        coarse = scene.model_copy(update={"quality": QualityReduction(reduction=r), "width": w, "height": h,
                                          "sampling": sampling})
        stages.append(Stage(coarse, W, H, False))
    return [*stages, Stage(scene, W, H, True)]


def upsample(rgba: np.ndarray, height: int, width: int) -> np.ndarray:
    """Premultiplied RGBA scaled to height × width by bilinear interpolation between pixel centres (the edges
    clamped): premultiplied colours blend without dark fringes."""
    h, w = rgba.shape[:2]
    if (h, w) == (height, width):
        return rgba

    def axis(n_out: int, n_in: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = np.clip((np.arange(n_out) + 0.5) * (n_in / n_out) - 0.5, 0.0, n_in - 1)
        i0 = np.floor(x).astype(np.int64)
        return i0, np.minimum(i0 + 1, n_in - 1), (x - i0).astype(np.float32)

    y0, y1, fy = axis(height, h)
    x0, x1, fx = axis(width, w)
    rows = rgba[y0] * (1 - fy)[:, None, None] + rgba[y1] * fy[:, None, None]
    out = rows[:, x0] * (1 - fx)[None, :, None] + rows[:, x1] * fx[None, :, None]
    return out.astype(np.float32)


@dataclass(frozen=True)
class Progressive:
    """A progressive render under way: `stages` (stage_plan) of `scene` on `store`, rendered by `renders` (the
    render of `engine`, whose tables keep a preview's level) when `render(k)` asks, each report's wall_ms counted from `started` (time.perf_counter() at the
    request)."""

    renders: RenderFn
    store: StoreLike
    scene: Scene
    stages: list[Stage]
    engine: Engine
    started: float = field(default_factory=time.perf_counter)

    def _level(self, k: int) -> VolumeView:
        """Level k of the store as a volume (kept in the engine's tables: the next request of a turntable shows it
        again)."""
        vol = as_volume(self.store)
        key = None if vol.key is None else (vol.key, k)
        hit = self.engine.tables.levels.get(key) if key is not None else None
        if hit is None:
            hit = level_view(vol, k)
            if key is not None:
                self.engine.tables.levels.put(key, hit, hit.n_voxels * hit.voxel_dtype.itemsize)
        return hit

    @classmethod
    def plan(cls, engine: Engine, renders: RenderFn, store: StoreLike, scene: SceneLike, ladder: Ladder = Ladder(),
             started: float | None = None) -> "Progressive":
        """Parse the scene (SceneError naming the field), open the store and plan the stages."""
        t = time.perf_counter() if started is None else started
        sc = Scene.parse(scene)
        vol = as_volume(store, stores=engine.stores)
        return cls(renders, vol, sc, stage_plan(engine, sc, vol, ladder), engine, t)

    def render(self, k: int, sample_limit: int | None = None,
               stop: Callable[[], None] | None = None) -> RenderResult:
        """Stage `k`: its render (`stop` as Renderer.render's), scaled up to the scene's size, with the report's
        `stage`, `final`, `image_scale` and wall_ms since the request. A stage after the first calls `stop`
        before it starts."""
        if k and stop is not None:
            stop()
        st = self.stages[k]
        store = self.store if st.level is None else self._level(st.level)
        res = self.renders(store, st.scene, sample_limit=sample_limit, stop=stop)
        report: RenderReport = {**res.report, "wall_ms": (time.perf_counter() - self.started) * 1e3,
                                "width": st.width, "height": st.height, "stage": k, "final": st.final,
                                "image_scale": st.image_scale}
        if st.level is not None:  # what the level is of the store, not of itself; no selection: nothing predicted
            vol = as_volume(self.store)
            report.update({"reduction": vol.n_voxels / float(np.prod(vol.level_shape(st.level), dtype=np.int64)),
                           "predicted_delta_e": None, "level": st.level, "quality": {"level": st.level},
                           "blocks": vol.n_blocks})
        scene = res.scene if st.final else {**(res.scene or {}), "width": st.width, "height": st.height}
        return RenderResult(upsample(res.rgba, st.height, st.width), report, scene)
