"""Kernels built ahead: the programs the usual scenes of a store need, compiled before anyone asks for a picture.

A kernel is specialised by its scene (renderer/kernel/config.py) and compiled on its first use; a build from source
takes seconds on a CPU device (interblock interpolation the longest), and the built binaries stay on disk for
every later process (lodcast/opencl.py). `build_ahead` builds the programs of `AHEAD` (full resolution with and without its
empty-space walk, lossless with and without coarse blocks, 30:1 with nearest-block and interblock interpolation, unlit and lit: what the viewer,
the presets and the docs' examples ask for) on a store, working out each one's configuration from the store's metadata as `prepare` does
once a selection is made, without reading a voxel or selecting a level: `lodcast kernels STORE` after an ingest
or in a deployment's start-up leaves none of them to a user's first picture.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace

from lodcast.renderer.data.volume import StoreLike, as_volume
from lodcast.renderer.engine import Engine
from lodcast.renderer.frame.prepare import lod_config, samples_per_ray, volume_config
from lodcast.renderer.scene import camera as cam
from lodcast.renderer.scene.scene import Scene, SceneLike

__all__ = ["AHEAD", "AheadBuild", "build_ahead"]

_QUALITIES: tuple[dict, ...] = (
    {"quality": "full"},
    {"quality": "lossless"},
    {"quality": {"reduction": 30}},
    {"quality": {"reduction": 30}, "sampling": {"interpolation": "interblock"}},
)
#: the scenes whose programs are built ahead: each quality unlit and lit (the TF and camera change no option)
_LIGHTS: tuple[dict, ...] = ({}, {"shading": {}})
AHEAD: tuple[dict, ...] = tuple({**q, **light} for q in _QUALITIES for light in _LIGHTS)


@dataclass(frozen=True)
class AheadBuild:
    scene: dict  # as given (AHEAD's entry, or the caller's)
    options: tuple[str, ...]  # the -D flags of its program
    source: str  # where the program came from: "memory", "disk" or "built" (lodcast/opencl.py: Built)
    ms: float


def _options(eng: Engine, store: StoreLike, scene: SceneLike) -> list[tuple[str, ...]]:
    """The options of the programs `scene` may render with on `store`: at full resolution with its empty-space walk
    and without (where the TF shows something in every cell, render.py compiles the walk out); "lossless" with
    coarse blocks and with every block at level 0."""
    vol = as_volume(store, stores=eng.stores)
    sc = Scene.parse(scene)
    box, _, _, step_world = cam.geometry(vol, sc)
    lod = sc.quality != "full"
    cfg = volume_config(sc, vol, samples_per_ray(box, step_world), lod)
    if lod:  # a budget keeps coarse blocks; "lossless" under a TF that shows every value may keep none
        coarse = (True, False) if sc.quality == "lossless" else (True,)
        return [lod_config(cfg, sc, vol, c).build_options() for c in coarse]
    if cfg.ess and sc.mode == "composite":
        return [cfg.build_options(), replace(cfg, ess=False).build_options()]
    return [cfg.build_options()]


def build_ahead(eng: Engine, store: StoreLike, scenes: Iterable[SceneLike] = AHEAD,
                progress: Callable[[AheadBuild], None] | None = None) -> list[AheadBuild]:
    """Build the kernel programs `scenes` need on `store` (default AHEAD; a scene without a TF takes a plain ramp,
    which changes no option), each once; `progress` is told of each as it is done."""
    done: list[AheadBuild] = []
    seen: set[tuple[str, ...]] = set()
    for scene in scenes:
        given = scene if isinstance(scene, dict) else Scene.parse(scene).model_dump(mode="json")
        full = {"tf": {"points": [{"value": 0, "color": [1, 1, 1], "opacity": 0.0},
                                  {"value": 1, "color": [1, 1, 1], "opacity": 0.5}]}, **given}
        for options in _options(eng, store, full):
            if options in seen:
                continue
            seen.add(options)
            t = time.perf_counter()
            built = eng.device.program("raycast.cl", options)
            step = AheadBuild(given, options, built.source, (time.perf_counter() - t) * 1e3)
            done.append(step)
            if progress is not None:
                progress(step)
    return done
