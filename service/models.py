"""The HTTP API's response bodies and documented errors, as pydantic models, so that the OpenAPI schema says what
each route returns and others can generate clients from it. Request bodies are the renderer's `Scene` and the
job models (service/jobs.py)."""
from __future__ import annotations

from typing import Annotated, Any, Literal, Union

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["Health", "Progress", "JobStatus", "Level", "VolumeSummary", "VolumeUnreadable", "VolumeListing", "Deleted",
           "ErrorBody", "FieldError", "errors", "REPORT_HEADER",
           "SESSION_HEADER", "NDJSON"]

JOB_STATES = Literal["queued", "running", "done", "failed", "cancelled"]
JOB_KINDS = Literal["turntable", "scenes", "tf_sweep", "volumes", "ingest"]


class _Out(BaseModel):
    # a client reading a newer server's answer keeps working: fields it does not know are left out
    model_config = ConfigDict(extra="ignore")


class ComponentHealth(_Out):
    status: Literal["ok", "down", "starting"] = Field(description="what its last probe found (starting: none yet)")
    detail: str
    checked: float | None = Field(description="when it was last probed (seconds since the epoch)")


class Health(_Out):
    status: Literal["ok", "degraded"] = Field(description="degraded: a component is down")
    version: str
    queue: Literal["sqlite", "redis"]
    components: dict[str, ComponentHealth] = Field(default_factory=dict, description="store_root, queue, device")


class Progress(_Out):
    done: int = Field(ge=0, description="frames written (ingest: 1 when the store is in place)")
    total: int = Field(ge=0)


class JobStatus(_Out):
    """A job's status; times are ISO 8601 UTC, or null."""

    id: str = Field(pattern=r"^[0-9a-f]{32}$")
    kind: JOB_KINDS
    state: JOB_STATES
    progress: Progress
    error: str | None = Field(description="one line, when the job failed")
    created: str | None
    started: str | None
    finished: str | None


class Level(_Out):
    path: str = Field(description="the level's array in the store: '0' is full resolution")
    shape: list[int]
    block_edge: int = Field(description="voxels per block edge at this level (B / 2^k)")
    chunks: list[int]
    shards: list[int]
    shard_count: int
    scale: list[float] = Field(description="voxel spacing z, y, x at this level, world units")


class VolumeSummary(_Out):
    """A store's attributes (what `lodcast info` prints), without server paths."""

    id: str
    shape: list[int] = Field(description="z, y, x voxels")
    dtype: str
    spacing: list[float] = Field(description="z, y, x, world units per voxel")
    origin: list[float] = Field(description="world position z, y, x of voxel (0, 0, 0)'s centre")
    units: str | None
    orientation: list[str] | None = Field(None, description='the patient direction of world +x, +y, +z, e.g. '
                                                           '["L", "P", "S"] (always so when ingested with orient '
                                                           'LPS); null when the source gave none')
    direction: list[list[float]] | None = Field(None, description="unit vectors of world x, y, z in patient "
                                                "coordinates (LPS): near the identity, up to an oblique "
                                                "acquisition's tilt, when ingested with orient LPS; null without "
                                                "geometry")
    block_size: int
    levels: list[Level]
    value_range: list[float | None] = Field(description="min, max of the finite voxels (null when none is)")
    nan_count: int
    grid: list[int] = Field(description="blocks along z, y, x")
    blocks: int
    shards: int
    bytes_on_disk: int
    histogram: dict[str, Any] = Field(description="the bins of the per-block histograms")
    format_version: int
    distribution: dict[str, Any] | None = Field(description="how coarse levels keep the distribution behind each "
                                                            "voxel (null: format 1, classified by the mean)")
    source: dict[str, Any] = Field(description="format and header facts of the ingested file; its file name only")
    provenance: dict[str, Any]


class VolumeUnreadable(_Out):
    """A store under the root that `GET /volumes` cannot describe: its id and why, so that one damaged store never
    hides the others (`GET /volumes/{id}` answers 409 or 404 with the same reason)."""

    id: str
    error: str = Field(description="one line: what is wrong with the store (a zarr.json that is not valid JSON, "
                                   "attributes an older lodcast wrote that give no finite world box); re-ingest or "
                                   "delete it")


#: one entry of `GET /volumes`: a volume's attributes, or, for a store that cannot be read, its id and the error
VolumeListing = Annotated[Union[VolumeSummary, VolumeUnreadable], Field(union_mode="left_to_right")]


class Deleted(_Out):
    deleted: str


class FieldError(BaseModel):
    loc: list[str | int] = Field(description="where: 'body', 'query' or 'path', then the field's path")
    msg: str = Field(description="starts with the field's dotted path")
    type: str


class ErrorBody(BaseModel):
    detail: str | list[FieldError] = Field(description="one line naming the field or thing at fault, or, for a "
                                                       "malformed request, one entry per field")


_WHY = {
    400: "the request names something malformed (an id, a scene the renderer refuses)",
    401: "LODCAST_TOKEN is set and the bearer token is missing or wrong",
    404: "no such volume, job or result",
    409: "the volume's store is damaged or not a complete store (re-ingest it)",
    413: "too large: the body (LODCAST_MAX_BODY_BYTES, uploads max_upload_bytes) or the render's estimated cost "
         "(LODCAST_MAX_SAMPLES; the message names sampling.step or width)",
    422: "the body, query or path does not validate; every entry names its field",
    503: "the queue or the render device is unavailable, the render took longer than LODCAST_RENDER_TIMEOUT_S, or "
         "the space for uploads is full (Retry-After)",
}


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """The `responses=` of a route: each code with the error body and why it happens."""
    return {code: {"model": ErrorBody, "description": _WHY[code]} for code in codes}


#: the header naming a client's session: its newer progressive render cancels the stages still to come of the older
SESSION_HEADER = "X-Lodcast-Session"
#: the media type of a progressive render's stream: one JSON object per line
NDJSON = "application/x-ndjson"

REPORT_HEADER = {
    "X-Lodcast-Report": {
        "description": "the render report as compact JSON: wall_ms, kernel_ms, samples, reduction, "
                       "predicted_delta_e, bricks_read, device_bytes, passes, …",
        "schema": {"type": "string"},
    }
}
