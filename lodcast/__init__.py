"""lodcast: volume rendering of large scalar volumes with transfer-function-driven level of detail.

The public verbs are imported lazily so that `import lodcast` stays cheap (no OpenCL, no FastAPI).
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from lodcast.errors import (
    LodcastError,
    SourceError,
    SourceNotFound,
    StoreCorrupt,
    StoreExists,
    StoreInvalid,
    StoreNotFound,
)

__version__ = "0.1.0"

__all__ = [
    "__version__",
    "ingest",
    "open_store",
    "render",
    "render_progressive",
    "Renderer",
    "Client",
    "AsyncClient",
    "JobStatus",
    "VolumeSummary",
    "RenderResult",
    "RenderReport",
    "Scene",
    "SceneLike",
    "StoreLike",
    "LodcastError",
    "SourceError",
    "SourceNotFound",
    "StoreExists",
    "StoreInvalid",
    "StoreNotFound",
    "StoreCorrupt",
    "SceneError",
    "CostError",
    "ImageError",
    "DeviceError",
    "EnvironmentInvalid",
    "ServiceError",
]

_LAZY = {
    "ingest": ("lodcast.store.ingest", "ingest"),
    "open_store": ("lodcast.store.store", "open_store"),
    "render": ("lodcast.renderer.frame.render", "render"),
    "render_progressive": ("lodcast.renderer.frame.render", "render_progressive"),
    "Renderer": ("lodcast.renderer.frame.render", "Renderer"),
    "SceneError": ("lodcast.renderer.scene.scene", "SceneError"),
    "CostError": ("lodcast.renderer.scene.cost", "CostError"),
    "ImageError": ("lodcast.renderer.image.output", "ImageError"),
    "DeviceError": ("lodcast.opencl", "DeviceError"),
    "EnvironmentInvalid": ("lodcast.environment", "EnvironmentInvalid"),
    "ServiceError": ("lodcast.service.client", "ServiceError"),
    "RenderResult": ("lodcast.renderer.image.output", "RenderResult"),
    "RenderReport": ("lodcast.renderer.image.report", "RenderReport"),
    "Scene": ("lodcast.renderer.scene.scene", "Scene"),
    "SceneLike": ("lodcast.renderer.scene.scene", "SceneLike"),
    "StoreLike": ("lodcast.renderer.data.volume", "StoreLike"),
    "Client": ("lodcast.service.client", "Client"),
    "AsyncClient": ("lodcast.service.client", "AsyncClient"),
    "JobStatus": ("lodcast.service.models", "JobStatus"),
    "VolumeSummary": ("lodcast.service.models", "VolumeSummary"),
}

if TYPE_CHECKING:  # pragma: no cover
    from lodcast.environment import EnvironmentInvalid
    from lodcast.opencl import DeviceError
    from lodcast.renderer.data.volume import StoreLike
    from lodcast.renderer.frame.render import Renderer, render, render_progressive
    from lodcast.renderer.image.output import ImageError, RenderResult
    from lodcast.renderer.image.report import RenderReport
    from lodcast.renderer.scene.cost import CostError
    from lodcast.renderer.scene.scene import Scene, SceneError, SceneLike
    from lodcast.service.client import AsyncClient, Client, ServiceError
    from lodcast.service.models import JobStatus, VolumeSummary
    from lodcast.store.ingest import ingest
    from lodcast.store.store import open_store


def __getattr__(name: str) -> Any:
    try:
        module, attr = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module 'lodcast' has no attribute {name!r}") from None
    return getattr(importlib.import_module(module), attr)
