"""The cost model of a device (`CostModel`): what a render costs per frame, ray and sample on the engine's OpenCL
device, measured once (`calibrate`: probe renders of a small synthetic store) and kept on the engine
(`cost_model`) and on disk under the cache folder, by the device's name. Quality targets (target.py) scale its
figures to each store by small renders of the scene."""
from __future__ import annotations

import contextlib
import json
import math
import re
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

import numpy as np
import pyopencl as cl

from lodcast.renderer.engine import Engine
from lodcast.renderer.scene.scene import Scene

__all__ = ["COST_VERSION", "CostModel", "cost_model", "calibrate", "renders"]

COST_VERSION = 3  # a cost model on disk of another version is measured again


@dataclass(frozen=True)
class CostModel:
    """What a render costs on one device: `frame_ms` per render whatever it draws (host work, launch, read-back),
    `ray_ns` per ray, `sample_ns` per sample by sampler ("full": trilinear level 0; "nearest_block" and
    "interblock": the atlas), times `shade_factor` with shading; adaptive screen-space sampling's `pixel_ns` per
    pixel reconstructed (its pre-pass is timed where it is predicted: target.py `_screen_rays`); `byte_ns` per byte of
    volume data uploaded. `per_store`: the ray and sample costs and the host time are those small renders of each
    store measure, the samplers in the model's ratios (a measured model); off, the figures stand as given (a model
    given explicitly, e.g. a test's)."""

    device: str
    frame_ms: float
    ray_ns: float
    sample_ns: Mapping[str, float]
    shade_factor: float
    pixel_ns: float
    byte_ns: float
    per_store: bool = True


def cost_model(eng: Engine) -> CostModel:
    """The engine's cost model of its device: the one set on it (`eng.cost_model`), else the one kept on disk for
    this device, else measured now (`calibrate`) and kept in both places."""
    if eng.cost_model is not None:
        return eng.cost_model
    with eng.target_lock:
        if eng.cost_model is None:
            name = str(eng.device.info()["name"])
            path = eng.cost_dir / f"{re.sub(r'[^A-Za-z0-9._-]+', '_', name)[:100]}-v{COST_VERSION}.json"
            model = None
            with contextlib.suppress(OSError, ValueError, TypeError, KeyError):
                model = CostModel(**json.loads(path.read_text()))
            if model is None or model.device != name:
                model = calibrate(eng)
                with contextlib.suppress(OSError):
                    path.parent.mkdir(parents=True, exist_ok=True)
                    tmp = path.with_suffix(".tmp")
                    tmp.write_text(json.dumps(asdict(model) | {"sample_ns": dict(model.sample_ns)}))
                    tmp.replace(path)
            eng.cost_model = model
        return eng.cost_model


def _probe_volume(n: int = 96) -> np.ndarray:
    """A ball with a ramp and a shell inside, empty corners: every sampler's work, some space to skip."""
    z, y, x = np.mgrid[0:n, 0:n, 0:n].astype(np.float32)
    r = np.sqrt((x - n / 2) ** 2 + (y - n / 2) ** 2 + (z - n / 2) ** 2) / (n / 2)
    return np.where(r < 0.85, 0.2 + 0.5 * x / n + 0.3 * (np.abs(r - 0.6) < 0.05), 0.0).astype(np.float32)


@contextlib.contextmanager
def _probe_store() -> Iterator[Any]:
    from lodcast.store.ingest import ingest

    with tempfile.TemporaryDirectory(prefix="lodcast-cost-") as d:
        yield ingest(_probe_volume(), Path(d) / "probe.zarr", block_size=16, progress=False)


def calibrate(eng: Engine, repeat: int = 3) -> CostModel:
    """Measure `eng`'s device: probe renders of a small synthetic store (a second or a few, plus the kernels'
    first builds), each the fastest of `repeat` after a warm-up."""
    render = renders(eng)
    tf = {"points": [{"value": 0.15, "color": [0.9, 0.6, 0.5], "opacity": 0.0},
                     {"value": 0.5, "color": [1.0, 0.9, 0.8], "opacity": 0.05},
                     {"value": 0.9, "color": [1.0, 1.0, 1.0], "opacity": 0.3}]}
    n = 96
    base = {"camera": {"azimuth": 30, "elevation": 20}, "width": n, "height": n, "tf": tf, "format": "npy"}

    def run(extra: dict[str, Any]) -> Any:
        sc = Scene.parse({**base, **extra})
        render(store, sc)
        return min((render(store, sc).report for _ in range(repeat)), key=lambda r: r["kernel_ms"])

    with _probe_store() as store:
        fine, coarse = run({"sampling": {"step": 0.25}}), run({"sampling": {"step": 1.0}})
        rays = float(n * n)
        ds = fine["samples"] - coarse["samples"]
        full_ns = max((fine["kernel_ms"] - coarse["kernel_ms"]) * 1e6 / ds, 1e-3) if ds > 0 else \
            fine["kernel_ms"] * 1e6 / max(fine["samples"], 1)
        ray_ns = max((fine["kernel_ms"] * 1e6 - full_ns * fine["samples"]) / rays, 0.0)

        def per_sample(rep: Any) -> float:
            return max((rep["kernel_ms"] * 1e6 - ray_ns * rays) / max(rep["samples"], 1), 1e-3)

        fixed: dict[str, Any] = {"step": 0.25, "adaptive_object": False}
        nb = run({"quality": {"level": 1}, "sampling": fixed})
        ib = run({"quality": {"level": 1}, "sampling": {**fixed, "interpolation": "interblock"}})
        shaded = run({"sampling": {"step": 0.25}, "shading": {}})
        screen = run({"quality": {"level": 2}, "sampling": {"adaptive_screen": True}})
        tiny = [render(store, Scene.parse({**base, "width": 8, "height": 8})).report for _ in range(repeat + 1)]
        frame_ms = float(np.median([r["wall_ms"] - r["kernel_ms"] for r in tiny[1:]]))
        scr = screen["adaptive_screen"]
        pixel_ns = scr["reconstruct_ms"] * 1e6 / rays if scr else 0.0
    return CostModel(
        device=str(eng.device.info()["name"]), frame_ms=max(frame_ms, 0.0), ray_ns=ray_ns,
        sample_ns={"full": full_ns, "nearest_block": per_sample(nb), "interblock": per_sample(ib)},
        shade_factor=max(per_sample(shaded) / full_ns, 1.0), pixel_ns=pixel_ns, byte_ns=_byte_ns(eng))


def renders(eng: Engine) -> Callable[[Any, Scene], Any]:
    """`eng`'s render: the engines that choose are the Renderers that render (renderer/frame/render.py, which
    imports this module through prepare and target, so it is not imported here)."""
    render = getattr(eng, "render", None)
    if render is None:
        raise TypeError(f"{type(eng).__name__} cannot render: quality targets need a lodcast.Renderer")
    return render


def _byte_ns(eng: Engine, nbytes: int = 32 << 20) -> float:
    """Nanoseconds per byte of a host-to-device copy on `eng`'s device (the fastest of three)."""
    ctx = eng.device.context
    queue = cl.CommandQueue(ctx)
    host = np.ones(nbytes, np.uint8)
    buf = cl.Buffer(ctx, cl.mem_flags.READ_ONLY, size=nbytes)
    best = math.inf
    for _ in range(3):
        t = time.perf_counter()
        cl.enqueue_copy(queue, buf, host)
        queue.finish()
        best = min(best, time.perf_counter() - t)
    return best * 1e9 / nbytes

