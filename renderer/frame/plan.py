"""What a frame will do, decided on the host before anything is launched: the kernel's configuration
(`kernel_config`: which pieces are compiled in), the level-of-detail plan (`LodPlan`) and everything a launch
needs (`Prepared`, with the engine that prepared it). Plain data: renderer/frame/prepare.py computes them, the walks,
passes and the frame's launch read them."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from lodcast.renderer.data.sampler import FINE_CELLS
from lodcast.renderer.data.volume import VolumeView
from lodcast.renderer.engine import Engine
from lodcast.renderer.kernel.config import PRECISE_SAMPLES, KernelConfig
from lodcast.renderer.kernel.preintegration import PreintTable
from lodcast.renderer.lod.classification import DistTable
from lodcast.renderer.scene.scene import Scene
from lodcast.renderer.scene.transfer_function import Lut

if TYPE_CHECKING:  # pragma: no cover
    from lodcast.renderer.data import passes as multipass
    from lodcast.renderer.frame import screen as screen_space
    from lodcast.renderer.frame.target import Choice
    from lodcast.renderer.lod import dual

__all__ = ["Prepared", "LodPlan", "kernel_config", "MAX_SAMPLES_PER_RAY"]

MAX_SAMPLES_PER_RAY = 2**30


def kernel_config(scene: Scene, max_samples: int, lod: bool = False,
                  distribution: bool = False, voxel: str = "float", block_size: int = 16,
                  n_blocks: int = 0) -> KernelConfig:
    """`distribution`: whether the volume keeps the distributions behind its coarse voxels (the scene decides
    whether to use them); `voxel`: the OpenCL C type of its voxels on the device; `block_size`, `n_blocks`: its
    blocks' edge and number. Octant masks need blocks of 16 or more, a multiple of 4 (half-block cells of 4³ are
    full resolution's own, and octants of 2³ skipped little more but slowed a first render), and a grid of at most
    sampler.FINE_CELLS octants, as full resolution's 4³ cells: the octants' bounds are kept for the whole grid, 12
    bytes each on the host and again on the device (beyond the bound, recomputed every frame, they cost a large
    volume's frames many times their time and memory)."""
    s = scene.sampling
    # default (None): on at every quality that samples the atlas. Level-0 cells step on full resolution's lattice
    # (raycast.cl), so "lossless" keeps its image (its error against full resolution is that of fixed steps) and
    # its coarse blocks, which lose nothing the TF shows, are stepped over faster
    adaptive = lod and (s.adaptive_object is not False or s.adaptive_naive)
    # "lossless" promises full resolution's image: its level 0 keeps full resolution's lattice after coarse cells
    # too (without it, close up, its error against full resolution grows past that of fixed steps); the budgeted
    # qualities leave it out (it costs them kernel time and they do not promise full resolution's image)
    lattice = adaptive and not s.adaptive_naive and scene.quality == "lossless"
    return KernelConfig(
        sampler="atlas" if lod else "full",
        interpolation=(s.interpolation or "nearest_block") if lod else "trilinear",
        adaptive=adaptive,
        adaptive_naive=lod and s.adaptive_naive,
        lattice=lattice,
        distribution=lod and distribution and s.classification == "distribution" and scene.mode == "composite",
        mode=scene.mode,
        ess=s.empty_space_skipping and scene.mode not in ("average", "iso"),  # these read every sample
        octant_cells=block_size >= 16 and block_size % 4 == 0 and 64 * n_blocks <= FINE_CELLS,
        precise=max_samples > PRECISE_SAMPLES,
        clip=scene.clip is not None and len(scene.clip.planes) > 0,
        shade=scene.shading is not None and scene.mode in ("composite", "iso"),
        preint=s.preintegration and scene.mode == "composite",
        gradient_opacity=any(getattr(t, "gradient_opacity", None) is not None for t in (scene.tf, scene.tf2)),
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
    estimated_samples: int = 0  # renderer/scene/cost.py: the full march's samples, checked against the limit
    second: "dual.SecondTf | None" = None  # tf2 (LC_TF2) only
    priority: "dual.PriorityMap | None" = None  # tf2 with sampling.priority_map only
    screen: "screen_space.ScreenPlan | None" = None  # sampling.adaptive_screen only
    passes: "multipass.PassPlan | None" = None  # volume data beyond the device budget only (LC_PASSES)
    step_delta_e: float = 0.0  # the step's predicted error (selection.step_delta_e), composite renders of a store
    octants: tuple[int, ...] = tuple(range(8))  # the octants of direction the rays go in (camera.ray_octants)
    chosen: "tuple[Scene, Choice] | None" = None  # a quality target: the scene as asked, and what it picked (`scene`)


@dataclass(frozen=True)
class LodPlan:
    levels: np.ndarray  # grid-shaped int8, store level per block, -1 = not loaded
    reduction: float | None
    predicted_delta_e: float | None
    step_levels: np.ndarray | None  # adaptive sampling: int8 per half-block cell (atlas.step_levels)
    selection: Any = None
    view_weighted: bool = False  # the selection weighed what the camera sees (visibility.py)
