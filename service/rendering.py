"""Scene validation against the service's caps, the service's render engine, image encoding.

Shared by the HTTP layer and the job workers, so that a scene is judged the same way wherever it comes from. A
`lodcast serve` process makes one RenderEngine and hands it to its job queue, so that every render of the process
goes through one renderer (one brick pool, one device cache, the same opened stores).
"""
from __future__ import annotations

import io
import math
import re
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from lodcast.errors import LodcastError
from lodcast.faults import storage_fault
from lodcast.renderer.scene.scene import branchless

__all__ = ["RequestInvalid", "parse_scene", "from_pydantic", "field_error", "scene_refused", "check_tf", "RenderEngine",
           "encode", "finite_json"]


class RequestInvalid(LodcastError, ValueError):
    """A request body is malformed; ``errors`` is in FastAPI's shape ({"loc", "msg", "type"}) and names the field."""

    def __init__(self, errors: list[dict[str, Any]]) -> None:
        self.errors = errors
        first = errors[0] if errors else {"loc": [], "msg": "invalid"}
        super().__init__(f"{'.'.join(str(p) for p in first['loc'] if p != 'body')}: {first['msg']}")

    @classmethod
    def one(cls, loc: tuple | list, msg: str, type_: str = "value_error") -> "RequestInvalid":
        field = ".".join(str(p) for p in loc if p != "body")
        return cls([{"loc": list(loc), "msg": f"{field}: {msg}" if field else msg, "type": type_}])


_NAMED = re.compile(r"([a-z_][a-z0-9_]*(?:\.[a-z0-9_]+)*): (.*)", re.S)
_PLACES = ("body", "query", "path", "header")


def field_error(loc: Sequence[Any], msg: str, type_: str = "value_error") -> dict[str, Any]:
    """One error in FastAPI's shape ({"loc", "msg", "type"}) whose `loc` is the field's path as the request has it
    (without the branch labels pydantic puts into union paths, such as 'orbit') and whose message starts with that
    dotted path. A message that names its field itself (a model validator's "camera.target: ...", its path from
    the scene's root) places the error there: under the last element of `loc` that the path starts with, else
    below `loc`."""
    where: list[Any] = branchless(loc)
    msg = " ".join(str(msg).removeprefix("Value error, ").split())
    named = _NAMED.fullmatch(msg)
    if named:
        path, msg = named.group(1).split("."), named.group(2)
        at = max((i for i, p in enumerate(where) if p == path[0]), default=None)
        where = [*where[:at], *path] if at is not None else [*where, *path]
    field = ".".join(str(p) for p in where if p not in _PLACES)
    return {"loc": where, "msg": f"{field}: {msg}" if field else msg, "type": type_}


def from_pydantic(exc: Any, loc: tuple, drop: int = 0) -> RequestInvalid:
    """FastAPI-shaped errors, each message starting with the field's dotted path (`drop` leading parts of
    pydantic's own path are replaced by `loc`)."""
    return RequestInvalid([field_error([*loc, *e.get("loc", ())[drop:]], str(e.get("msg", "invalid")),
                                       str(e.get("type", "value_error"))) for e in exc.errors(include_url=False)])


def scene_refused(exc: Exception, loc: tuple = ("body",)) -> RequestInvalid:
    """A scene the renderer refuses for the volume it is rendered on (SceneError: a camera whose view of this volume
    is degenerate, a step too small for it), as a 422 naming the field its message names (else the scene)."""
    named = _NAMED.fullmatch(" ".join(str(exc).split())) is not None
    return RequestInvalid([field_error(loc if named or loc != ("body",) else (*loc, "scene"), str(exc))])


def parse_scene(data: Any, settings: Any, loc: tuple = ("body",)) -> Any:
    """Validate a scene (dict or Scene) with the shared pydantic model, then the service's caps."""
    from pydantic import ValidationError

    from lodcast.renderer.scene.scene import Scene

    if not isinstance(data, (dict, Scene)):
        raise RequestInvalid.one(loc, "a scene must be a JSON object", "type_error")
    try:
        scene = data if isinstance(data, Scene) else Scene.model_validate(data)
    except ValidationError as exc:
        raise from_pydantic(exc, loc) from None
    except (ValueError, TypeError, LodcastError) as exc:
        raise RequestInvalid.one(loc, str(exc)) from None
    if scene.width > settings.max_width:
        raise RequestInvalid.one((*loc, "width"), f"{scene.width} exceeds the service's cap of {settings.max_width}")
    if scene.height > settings.max_height:
        raise RequestInvalid.one((*loc, "height"), f"{scene.height} exceeds the service's cap of {settings.max_height}")
    step = getattr(getattr(scene, "sampling", None), "step", None)
    if step is not None and step < settings.min_step:
        raise RequestInvalid.one((*loc, "sampling", "step"), f"{step} is below the service's minimum of {settings.min_step}")
    return scene


def check_tf(data: Any, loc: tuple) -> dict | str:
    """Validate one transfer function (JSON or a preset's name) by putting it in a minimal scene (the TF model
    lives in the scene module)."""
    from pydantic import ValidationError

    from lodcast.renderer.scene.scene import Scene

    if not isinstance(data, (dict, str)):
        raise RequestInvalid.one(loc, "a transfer function must be a JSON object or a preset's name", "type_error")
    try:
        Scene.model_validate({"tf": data})
    except ValidationError as exc:
        raise from_pydantic(exc, loc, drop=1) from None
    return data


def finite_json(obj: Any) -> Any:
    """`obj` as JSON takes it: a float that is not finite (a reduction of infinity, when nothing is loaded) as null,
    NumPy scalars as Python's, keys as strings."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): finite_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_json(v) for v in obj]
    if hasattr(obj, "item") and callable(obj.item):  # numpy scalars
        try:
            return finite_json(obj.item())
        except (TypeError, ValueError):
            return str(obj)
    return obj


class RenderEngine:
    """The service's renderer (lodcast.Renderer, made on first use with the settings' device budget, bound on
    opened stores and store check interval), addressed by store path. Its opened stores (store/opened.py) are the
    service's only ones: at most `open_stores`, least recently used closed first, and reopened when a store was
    replaced since (another process ingested it again with --overwrite: a new folder renamed into place, so its
    root zarr.json has a new inode; on object storage a new root zarr.json, asked at most once per
    `store_check_s`)."""

    def __init__(self, settings: Any = None) -> None:
        from lodcast.service.progressive import Sessions

        self._budget = None if settings is None else getattr(settings, "device_budget_mb", None)
        self._open_stores = None if settings is None else getattr(settings, "open_stores", None)
        self._check_s = 0.0 if settings is None else float(getattr(settings, "store_check_s", 0.0))
        self._renderer: Any = None
        self._lock = threading.Lock()
        self.sessions = Sessions()  # the progressive streams under way, by X-Lodcast-Session

    @property
    def renderer(self) -> Any:
        with self._lock:
            if self._renderer is None:
                from lodcast.renderer.frame.render import Renderer

                self._renderer = Renderer(device_budget_mb=self._budget, open_stores=self._open_stores,
                                          store_check_s=self._check_s)
            return self._renderer

    def locate(self, root: Path | str, volume_id: str) -> Path | str:
        """volume_path (VolumeNotFound where there is none); a volume whose store the renderer trusts without asking
        (opened less than `store_check_s` ago) is not looked for again, and while the storage has a transient fault
        a volume whose store is kept open is taken to be there still."""
        from lodcast.service.volumes import volume_path

        url = volume_path(root, volume_id, must_exist=False)
        if self.renderer.stores.recent(url):
            return url
        try:
            return volume_path(root, volume_id)
        except Exception as exc:
            if storage_fault(exc) and self.renderer.stores.kept(url):
                return url
            raise

    def store(self, path: Path | str) -> Any:
        """The opened store at `path` (a folder, or a URL: a str); StoreUnusable (service/volumes.py) where its
        spacing and origin give no finite world box (a store an older lodcast wrote): no render can use it."""
        from lodcast.service.volumes import check_store_geometry

        store = self.renderer.stores.get(path)
        check_store_geometry(store, str(path).rstrip("/").replace("\\", "/").rsplit("/", 1)[-1])
        return store

    def forget(self, path: Path | str) -> None:
        if self._renderer is not None:
            self._renderer.stores.forget(path)

    def render(self, path: Path | str, scene: Any, sample_limit: int | None = None, stop: Any = None) -> Any:
        return self.renderer.render(self.store(path), scene, sample_limit=sample_limit, stop=stop)

    def progressive(self, path: Path | str, scene: Any, started: float) -> Any:
        """The stages of a progressive render (renderer/frame/progressive.py: Progressive), planned, none rendered;
        wall ms counted from `started` (time.perf_counter() at the request)."""
        from lodcast.renderer.frame.progressive import Progressive

        return Progressive.plan(self.renderer, self.renderer.render, self.store(path), scene, started=started)

    def prefetch(self, path: Path | str, scene: Any) -> int:
        """The bricks a render of `scene` will need, read into the brick cache (Renderer.prefetch)."""
        return int(self.renderer.prefetch(self.store(path), scene))

    def check_cost(self, path: Path | str, scene: Any, sample_limit: int) -> int:
        """The render's estimated samples; CostError (naming the field) above `sample_limit`."""
        return int(self.renderer.check_cost(self.store(path), scene, sample_limit))


def scene_format(scene: Any) -> str:
    fmt = getattr(scene, "format", "png") or "png"
    return str(getattr(fmt, "value", fmt))


def encode(result: Any, scene: Any) -> tuple[bytes, str]:
    """The image bytes and media type: straight-alpha 8-bit PNG, or the float32 premultiplied RGBA as .npy
    (application/x-npy)."""
    import numpy as np

    rgba = np.asarray(result.rgba, dtype=np.float32)
    if scene_format(scene) == "npy":
        buf = io.BytesIO()
        np.save(buf, rgba, allow_pickle=False)
        return buf.getvalue(), "application/x-npy"
    return result.png_bytes(), "image/png"  # the renderer's own 8-bit image, with its scene and report
