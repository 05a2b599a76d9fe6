"""The web viewer: ``GET /`` (the volumes, each linked to its viewer), ``GET /volumes/{id}/view`` (orbit, transfer
function editor, progressive refinement) and their static files under ``/viewer/`` (plain HTML, JavaScript modules
and CSS in service/static, shipped as package data: no build step, nothing from a CDN), plus the data route the
editor draws on, ``GET /volumes/{id}/histogram`` (service/histograms.py).

The page and its files carry no volume names or data, so they are open with LODCAST_TOKEN set (docs/design.md,
Limits); everything the page fetches (the volume list, presets, histogram, renders) is a protected route, and the
page asks for the token on a 401 and sends it as `Authorization: Bearer` from then on.
"""
from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

from fastapi import FastAPI, Query
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, ConfigDict, Field

from lodcast.renderer.cache import ByteLru
from lodcast.service.histograms import ALPHA, MIN_PROMINENCE, volume_histogram
from lodcast.service.models import errors
from lodcast.service.params import VolumeId
from lodcast.service.volumes import check_volume_id

__all__ = ["STATIC", "Histogram", "HistogramPeak", "add_viewer"]

#: the viewer's files (package data: pyproject.toml's [tool.setuptools.package-data])
STATIC = Path(__file__).parent / "static"


class _Out(BaseModel):
    model_config = ConfigDict(extra="ignore")


class HistogramPeak(_Out):
    value: float = Field(description="the peak's data value (bin centre)")
    lo: float = Field(description="where the peak has fallen by half its prominence below its value, or a valley")
    hi: float = Field(description="the same above its value")
    prominence: float = Field(description="decades the smoothed α-histogram falls around the peak before higher "
                                          "ground")
    weight: float = Field(description="share of the voxels (plain histogram) between lo and hi")
    background: bool = Field(description="the peak of the most common value (air around a body): what a TF hides")
    tf: dict[str, Any] | None = Field(description="a transfer function showing this peak's range alone (null for the "
                                                  "background): the viewer's one-click suggestion")


class Histogram(_Out):
    """A volume's histograms from its per-block histograms (no voxel read; service/histograms.py)."""

    volume: str
    value_range: list[float]
    edges: list[float] = Field(description="bin edges, one more than bins")
    counts: list[float] = Field(description="the plain histogram: the block histograms summed (each block's one-voxel "
                                            "border is counted in its neighbours too)")
    alpha: float
    alpha_counts: list[float] = Field(description="the α-histogram (thesis §3.3.2, eq. 3.4) scaled to the plain "
                                                  "histogram's total")
    background: float = Field(description="the most common value")
    peaks: list[HistogramPeak] = Field(description="the α-histogram's peaks, the most prominent first, the "
                                                   "background's last")
    adapted: dict[str, dict[str, Any]] = Field(description="each adaptive preset (GET /presets) as placed on this "
                                                           "volume's α-histogram peaks")


class _Static(StaticFiles):
    """The viewer's files, revalidated on every load (as its pages)."""

    async def get_response(self, path: str, scope: Any) -> Any:
        response = await super().get_response(path, scope)
        response.headers["Cache-Control"] = "no-cache"
        return response


def _page(name: str) -> FileResponse:
    # revalidated on every load: a server upgraded under an open browser serves the new page, not a cached one
    return FileResponse(STATIC / name, media_type="text/html", headers={"Cache-Control": "no-cache"})


def add_viewer(app: FastAPI, *, auth: list[Any], opened: Callable[[str], Any], renderer: Callable[[], Any]) -> None:
    """The viewer's routes on `app`: `auth` marks the histogram route as protected, `opened(volume_id)` is the
    volume's opened store (raising the HTTP errors of one that cannot be used), `renderer()` the service's engine
    (whose cache keeps each store's tissue peaks)."""

    app.mount("/viewer", _Static(directory=STATIC), name="viewer")
    # per store (its identity changes when it is ingested again), α and prominence: a page load of a large store
    # reads its block histograms once, not once per tab
    kept = ByteLru(16 << 20)

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return _page("index.html")

    @app.get("/volumes/{volume_id}/view", include_in_schema=False)
    def view(volume_id: str) -> FileResponse:
        check_volume_id(volume_id, "volume")  # the shell names no volume; a malformed id is refused all the same
        return _page("viewer.html")

    @app.get("/volumes/{volume_id}/histogram", tags=["volumes"], dependencies=auth, response_model=Histogram,
             summary="The volume's plain and α-histograms and their peaks, from its block histograms",
             responses=errors(400, 401, 404, 409, 422, 503))
    def histogram(volume_id: VolumeId,
                  alpha: Annotated[float, Query(ge=1.0, le=64.0, description="the α of eq. 3.4: 1 is the plain "
                                                "histogram's shape; larger lifts tissues that fill a few blocks, "
                                                "and the noise")] = ALPHA,
                  min_prominence: Annotated[float, Query(ge=0.0, le=10.0, description="decades a peak must stand "
                                                         "out")] = MIN_PROMINENCE) -> dict[str, Any]:
        """Bins over the volume's value range (store/histogram.py); the α-histogram of thesis §3.3.2 (eq. 3.4);
        its peaks with a suggested TF each; the adaptive presets placed on this volume."""
        from lodcast.renderer.data.volume import as_volume
        from lodcast.renderer.scene.adaptive_tf import adaptive_tf
        from lodcast.renderer.scene.presets import ADAPTIVE

        check_volume_id(volume_id, "volume")
        store = opened(volume_id)
        vol = as_volume(store)
        key = None if vol.key is None else (vol.key, alpha, min_prominence)
        out = None if key is None else kept.get(key)
        if out is None:
            out = volume_histogram(store, alpha, min_prominence)
            out["adapted"] = {name: adaptive_tf(name, vol, None, renderer().tables.peaks) for name in ADAPTIVE}
            if key is not None:
                kept.put(key, out, len(json.dumps(out)))
        return {"volume": volume_id, **out}
