"""Job kinds (docs/design.md: turntable, scenes, tf_sweep, volumes, ingest), their validation and their frames.

A job is a list of frames, each one (volume, scene); frame n is written to ``ROOT/.jobs/<id>/frame_<n>.<fmt>``
atomically (temporary name, then rename), so a frame file exists only when it is complete, and a resumed job
renders only the frames whose file is missing.
"""
from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path
from typing import Annotated, Any, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, GetJsonSchemaHandler
from pydantic.json_schema import JsonSchemaValue
from pydantic_core import CoreSchema

from lodcast.renderer.scene.scene import Scene, SceneError, TransferFunction
from lodcast.service.rendering import RequestInvalid, check_tf, parse_scene, scene_format, scene_refused
from lodcast.service.volumes import BadId, VolumeNotFound, check_volume_id, safe_import_path, volume_exists, volume_path
from lodcast.store.atomic import fsync_dir

__all__ = [
    "Job",
    "TurntableJob",
    "ScenesJob",
    "TfSweepJob",
    "VolumesJob",
    "IngestJob",
    "parse_job",
    "validate_job",
    "plan_frames",
    "write_atomic",
]

#: a scene as a job carries it: its JSON (see SceneSchema)
SceneDict = dict[str, Any]


class SceneSchema:
    """A job's scene in the OpenAPI schema: the Scene model's schema (a reference to it), while the field is
    validated as a plain JSON object, so that each scene is checked by validate_job (parse_scene: against the
    service's caps, each error naming the scene's place in the job). `tf_required=False`: the Scene with `tf`
    optional (a TF sweep replaces it)."""

    model = Scene  # what docs/generate.py shows as the field's type

    def __init__(self, *, tf_required: bool = True) -> None:
        self.tf_required = tf_required

    def __get_pydantic_json_schema__(self, core: CoreSchema, handler: GetJsonSchemaHandler) -> JsonSchemaValue:
        ref = handler(Scene.__pydantic_core_schema__)
        if self.tf_required:
            return ref
        schema = dict(handler.resolve_ref_schema(ref))
        required = [k for k in schema.pop("required", []) if k != "tf"]
        if required:
            schema["required"] = required
        schema["title"] = "Scene (tf optional)"
        return schema


#: a job's scene: a JSON object validated by validate_job, typed in OpenAPI as the Scene it must be
JobScene = Annotated[SceneDict, SceneSchema()]


class TfSchema:
    """A TF sweep's transfer function in the OpenAPI schema: the TransferFunction model's schema, while the field
    is validated as a plain JSON object by validate_job (check_tf, each error naming the TF's place)."""

    model = TransferFunction  # what docs/generate.py shows as the field's type

    def __get_pydantic_json_schema__(self, core: CoreSchema, handler: GetJsonSchemaHandler) -> JsonSchemaValue:
        return handler(TransferFunction.__pydantic_core_schema__)


#: a sweep's TF: JSON typed as a TransferFunction, or a preset name
JobTf = Union[Annotated[dict[str, Any], TfSchema()], str]

#: keyword options of lodcast.ingest an ingest job may pass (reader options and the block size)
INGEST_OPTIONS = frozenset({"format", "shape", "dtype", "byte_order", "header_bytes", "spacing", "origin", "index",
                            "block_size", "units", "orient"})


class _Job(BaseModel):
    model_config = ConfigDict(extra="forbid")


class TurntableJob(_Job):
    """`frames` images of `volume` around its vertical axis: the scene's orbit camera with azimuths from
    `start_azimuth` in steps of 360° / frames; optionally encoded to an animation."""

    kind: Literal["turntable"]
    volume: str = Field(max_length=128)
    scene: JobScene
    frames: int = Field(36, ge=1)
    start_azimuth: float = Field(0.0, ge=-360, le=360, description="degrees, azimuth of frame 0")
    animation: Literal["gif", "mp4"] | None = Field(None, description="also encode the frames to an animated GIF or MP4")
    fps: float = Field(12.0, gt=0, le=120)


class ScenesJob(_Job):
    """One image of `volume` per scene, in order."""

    kind: Literal["scenes"]
    volume: str = Field(max_length=128)
    scenes: list[JobScene] = Field(min_length=1)


class TfSweepJob(_Job):
    """One image of `volume` per transfer function, each in the same `scene`."""

    kind: Literal["tf_sweep"]
    volume: str = Field(max_length=128)
    scene: Annotated[SceneDict, SceneSchema(tf_required=False)] = Field(
        default_factory=dict, description="the scene each TF is rendered in (its own tf is replaced)")
    tfs: list[JobTf] = Field(min_length=1, description="transfer functions (JSON or preset names)")


class VolumesJob(_Job):
    """The same `scene` rendered on each of `volumes`."""

    kind: Literal["volumes"]
    volumes: list[str] = Field(min_length=1)
    scene: JobScene


class IngestJob(_Job):
    """Ingest a server-side file (under an import root) as the new volume `name` (`POST /volumes` submits one)."""

    kind: Literal["ingest"]
    source: str = Field(min_length=1, max_length=4096, description="server-side path under a configured import root")
    name: str = Field(max_length=128, description="volume id of the new store")
    overwrite: bool = False
    options: dict[str, Any] = Field(default_factory=dict, description=(
        "ingest options, as `lodcast ingest` takes them: format, shape, dtype, byte_order, header_bytes, spacing, "
        "origin, units, index, block_size, orient (`LPS`, the default, or `source`)"))


Job = Annotated[Union[TurntableJob, ScenesJob, TfSweepJob, VolumesJob, IngestJob], Field(discriminator="kind")]


def parse_job(data: Any) -> Any:
    from pydantic import TypeAdapter, ValidationError

    from lodcast.service.rendering import from_pydantic

    try:
        return TypeAdapter(Job).validate_python(data)
    except ValidationError as exc:
        raise from_pydantic(exc, ("body",)) from None


def validate_job(job: Any, settings: Any, engine: Any, *, upload: Path | None = None) -> Any:
    """Check a parsed job against the store root and the caps (its frames' cost estimated by `engine`, a
    service.rendering.RenderEngine); raises RequestInvalid / VolumeNotFound naming the field."""
    def vol(v: str, loc: tuple) -> None:
        try:
            volume_path(settings.root, v, field=".".join(loc))
        except (BadId, VolumeNotFound) as exc:
            raise RequestInvalid.one(("body", *loc), str(exc).split(": ", 1)[-1]) from None

    if isinstance(job, IngestJob):
        try:
            check_volume_id(job.name, "name")
            volume_path(settings.root, job.name, must_exist=False, field="name")
            source = str(upload) if upload is not None else str(safe_import_path(job.source, settings.import_roots, "source"))
        except BadId as exc:
            raise RequestInvalid.one(("body", exc.field), str(exc).split(": ", 1)[-1]) from None
        for key in job.options:
            if key not in INGEST_OPTIONS:
                raise RequestInvalid.one(("body", "options", key), f"unknown ingest option (known: {', '.join(sorted(INGEST_OPTIONS))})")
        from lodcast.store.readers.reorient import ORIENTS

        if job.options.get("orient", "LPS") not in ORIENTS:
            raise RequestInvalid.one(("body", "options", "orient"), f"{job.options['orient']!r} is not one of "
                                     f"{', '.join(ORIENTS)}")
        if not job.overwrite and volume_exists(settings.root, job.name, "name"):
            raise RequestInvalid.one(("body", "name"), f"volume {job.name!r} exists (set overwrite)")
        return job.model_copy(update={"source": source})
    if isinstance(job, TurntableJob):
        vol(job.volume, ("volume",))
        if job.frames > settings.max_frames:
            raise RequestInvalid.one(("body", "frames"), f"{job.frames} exceeds the service's cap of {settings.max_frames}")
        one = _affordable(engine, job.volume, parse_scene(job.scene, settings, ("body", "scene")), settings, ("body", "scene"))
        _within_job_limit(settings, "frames", one * job.frames, f"{job.frames} frames of about {one:.3g} samples each")
    elif isinstance(job, ScenesJob):
        vol(job.volume, ("volume",))
        _cap(len(job.scenes), settings, "scenes")
        total = 0
        for i, s in enumerate(job.scenes):
            total += _affordable(engine, job.volume, parse_scene(s, settings, ("body", "scenes", i)), settings,
                                 ("body", "scenes", i))
        _within_job_limit(settings, "scenes", total, f"{len(job.scenes)} scenes")
    elif isinstance(job, TfSweepJob):
        vol(job.volume, ("volume",))
        _cap(len(job.tfs), settings, "tfs")
        for i, tf in enumerate(job.tfs):
            check_tf(tf, ("body", "tfs", i))
        sc = parse_scene({**job.scene, "tf": job.tfs[0]}, settings, ("body", "scene"))
        one = _affordable(engine, job.volume, sc, settings, ("body", "scene"))  # the TF does not change the estimate
        _within_job_limit(settings, "tfs", one * len(job.tfs), f"{len(job.tfs)} frames of about {one:.3g} samples each")
    elif isinstance(job, VolumesJob):
        _cap(len(job.volumes), settings, "volumes")
        for i, v in enumerate(job.volumes):
            vol(v, ("volumes", str(i)))
        sc = parse_scene(job.scene, settings, ("body", "scene"))
        total = sum(_affordable(engine, v, sc, settings, ("body", "scene")) for v in job.volumes)
        _within_job_limit(settings, "volumes", total, f"the scene on {len(job.volumes)} volumes")
    return job


def _affordable(engine: Any, volume: str, scene: Any, settings: Any, loc: tuple) -> int:
    """A job's frame must fit LODCAST_MAX_SAMPLES (estimated on the volume's geometry, renderer/scene/cost.py): refused
    at submission (422 naming the field), not after it has queued; its estimated samples. A store that cannot be
    opened is left to the job, which fails with the store's own message (0 samples)."""
    from lodcast.errors import StoreInvalid, StoreNotFound
    from lodcast.renderer.scene.cost import CostError

    try:
        return int(engine.check_cost(volume_path(settings.root, volume), scene, settings.max_samples))
    except CostError as exc:
        raise RequestInvalid.one((*loc, *exc.field.split(".")), " ".join(str(exc).split(": ", 1)[-1].split())) from None
    except SceneError as exc:  # a view of this volume that is degenerate (renderer/scene/camera.py: frame)
        raise scene_refused(exc, loc) from None
    except (StoreNotFound, StoreInvalid):
        return 0


def _within_job_limit(settings: Any, field: str, total: int, what: str) -> None:
    """A job's frames' estimated samples, summed, must fit LODCAST_MAX_JOB_SAMPLES (docs/design.md, Limits):
    refused at submission with a 422 naming `field`."""
    limit = settings.max_job_samples
    if total > limit:
        raise RequestInvalid.one(("body", field), f"{what} would take about {total:.3g} samples in all, more than "
                                 f"the limit of {limit:.3g} per job (LODCAST_MAX_JOB_SAMPLES); use fewer {field}, "
                                 f"fewer pixels or a larger sampling.step")


def _cap(n: int, settings: Any, field: str) -> None:
    if n > settings.max_scenes:
        raise RequestInvalid.one(("body", field), f"{n} items exceed the service's cap of {settings.max_scenes}")


# --- frames ----------------------------------------------------------------------------------------------------

def _turn(scene: SceneDict, azimuth: float) -> SceneDict:
    """The scene seen from ``azimuth`` degrees: the convenience camera gets its azimuth replaced; a look-at camera
    has its eye turned about the vertical axis (world z) through the target. The level of detail is selected by
    the TF alone unless the scene says otherwise (sampling.lod_visibility): one selection for the whole animation,
    nothing changes from frame to frame but the view."""
    out = dict(scene)
    out["sampling"] = {"lod_visibility": False, **(out.get("sampling") or {})}
    cam = dict(out.get("camera") or {})
    if "eye" in cam and "target" in cam:
        ex, ey, ez = (float(v) for v in cam["eye"])
        tx, ty, tz = (float(v) for v in cam["target"])
        a = math.radians(azimuth)
        dx, dy = ex - tx, ey - ty
        # counter-clockwise about +z, as the orbit camera's azimuth turns (from -y towards +x)
        cam["eye"] = [tx + dx * math.cos(a) - dy * math.sin(a), ty + dx * math.sin(a) + dy * math.cos(a), ez]
    else:
        cam["azimuth"] = float(cam.get("azimuth", 0.0)) + azimuth
    out["camera"] = cam
    return out


def plan_frames(job: Any) -> list[tuple[str, SceneDict]]:
    """(volume id, scene dict) for every frame, in result order."""
    if isinstance(job, TurntableJob):
        return [(job.volume, _turn(job.scene, job.start_azimuth + 360.0 * i / job.frames)) for i in range(job.frames)]
    if isinstance(job, ScenesJob):
        return [(job.volume, s) for s in job.scenes]
    if isinstance(job, TfSweepJob):
        return [(job.volume, {**job.scene, "tf": tf}) for tf in job.tfs]
    if isinstance(job, VolumesJob):
        return [(v, job.scene) for v in job.volumes]
    return []


def frame_ext(scene: Any) -> str:
    if isinstance(scene, dict):
        return "npy" if scene.get("format") == "npy" else "png"
    return scene_format(scene)


def write_atomic(path: Path, data: bytes) -> None:
    """Write to a temporary file in the same folder, fsync, then rename, and fsync the folder: the file is complete
    or absent, also after a power loss."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        fsync_dir(path.parent)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def encode_animation(frames: list[tuple[str, bytes]], fmt: str, fps: float) -> bytes:
    """Frames (name, PNG or .npy bytes) to an animated GIF (Pillow) or an H.264/MPEG-4 MP4 (PyAV), over opaque
    black."""
    import io

    import numpy as np
    from PIL import Image

    images = []
    for name, data in frames:
        if name.endswith(".npy"):
            rgba = np.load(io.BytesIO(data), allow_pickle=False)
            rgb = np.clip(rgba[..., :3], 0, 1)  # premultiplied: over black is the colour itself
            images.append(Image.fromarray(np.round(rgb * 255).astype(np.uint8), "RGB"))
        else:
            im = Image.open(io.BytesIO(data)).convert("RGBA")
            bg = Image.new("RGBA", im.size, (0, 0, 0, 255))
            images.append(Image.alpha_composite(bg, im).convert("RGB"))
    buf = io.BytesIO()
    if fmt == "gif":
        images[0].save(buf, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
        return buf.getvalue()
    import av

    w, h = images[0].size
    w2, h2 = w + (w % 2), h + (h % 2)  # yuv420p needs even sizes
    with av.open(buf, mode="w", format="mp4") as out:
        try:
            stream = out.add_stream("libx264", rate=round(fps))
        except Exception:  # a PyAV build without x264
            stream = out.add_stream("mpeg4", rate=round(fps))
        stream.width, stream.height, stream.pix_fmt = w2, h2, "yuv420p"
        for im in images:
            if (w2, h2) != (w, h):
                canvas = Image.new("RGB", (w2, h2))
                canvas.paste(im)
                im = canvas
            for packet in stream.encode(av.VideoFrame.from_image(im)):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    return buf.getvalue()

