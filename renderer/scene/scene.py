"""The Scene: one pydantic model shared by `lodcast.render`, the CLI, the HTTP API, jobs and the client.

Field names and defaults follow docs/design.md's scene JSON. Every validation error names its field
(``SceneError: sampling.step: Input should be greater than 0``).
"""
from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal, TypeAlias, Union

from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    ValidationError,
    field_validator,
    model_validator,
)

from lodcast.errors import LodcastError
from lodcast.renderer.scene.presets import ADAPTIVE, preset

__all__ = [
    "SceneError",
    "Scene",
    "SceneLike",
    "TransferFunction",
    "AdaptiveTF",
    "TFPoint",
    "LookAtCamera",
    "OrbitCamera",
    "Sampling",
    "Shading",
    "Clip",
    "ClipPlane",
    "ClipBox",
    "parse_scene",
]

class SceneError(LodcastError, ValueError):
    """A scene (or one of its parts) is invalid; the message names the field."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


Unit = Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False)]
#: world units per opacity unit: its reciprocal must be finite and non-zero in the kernel's single precision
UnitDistance = Annotated[float, Field(ge=1e-30, le=1e30, allow_inf_nan=False)]
Finite = Annotated[float, Field(allow_inf_nan=False)]
GradientOpacity = Annotated[float, Field(gt=0.0, le=1e30, allow_inf_nan=False, description=(
    "composite: the gradient magnitude (data units per world unit) from which the TF's opacity applies in full; "
    "where the field's gradient is weaker the TF's extinction is scaled by |gradient| / gradient_opacity, so "
    "boundaries show and homogeneous regions fade (None: opacity by value alone)"))]
Vec3 = tuple[Finite, Finite, Finite]


class TFPoint(_Model):
    """A control point: at data `value`, straight (not premultiplied) sRGB `color` and `opacity`."""

    value: Finite
    color: tuple[Unit, Unit, Unit] = (1.0, 1.0, 1.0)
    opacity: Unit = 1.0


class TransferFunction(_Model):
    """Piecewise linear over data values, constant outside; opacity per `unit_distance` world units
    (None: the volume's smallest spacing)."""

    points: list[TFPoint] = Field(min_length=1, max_length=4096)
    unit_distance: UnitDistance | None = None
    gradient_opacity: GradientOpacity | None = None

    @field_validator("points")
    @classmethod
    def _sorted(cls, pts: list[TFPoint]) -> list[TFPoint]:
        for k in range(1, len(pts)):
            if pts[k].value < pts[k - 1].value:
                raise ValueError(
                    f"control point values must be non-decreasing: point {k} has value {pts[k].value} "
                    f"after {pts[k - 1].value}"
                )
        return pts


#: the camera's limits (docs/design.md, Camera): a vertical field of view outside FOV_RANGE degrees, an orbit
#: distance outside DISTANCE_RANGE bounding-sphere radii, or (renderer/scene/camera.py: frame, which knows the
#: volume) an eye or target farther than MAX_RADII radii from the volume's centre or a view height outside
#: VIEW_HEIGHT_RADII radii makes the view degenerate or its numbers overflow in the kernel's single precision
FOV_RANGE = (0.1, 179.0)
DISTANCE_RANGE = (1e-6, 1e6)
MAX_RADII = 1e6
VIEW_HEIGHT_RADII = (1e-6, 1e6)

Fov = Annotated[float, Field(ge=FOV_RANGE[0], le=FOV_RANGE[1], allow_inf_nan=False,
                             description=f"vertical field of view, degrees ({FOV_RANGE[0]:g} to {FOV_RANGE[1]:g})")]
ViewHeight = Annotated[float, Field(gt=0.0, allow_inf_nan=False, description="orthographic: the image's height in "
                                    "world units (within 10^-6 to 10^6 times the volume's bounding-sphere radius)")]


def _scaled(v: tuple[float, ...]) -> tuple[tuple[float, ...], float]:
    """`v` divided by its largest |component| (so that squaring cannot overflow or underflow), and that scale."""
    m = max(abs(c) for c in v)
    return (tuple(c / m for c in v) if m > 0.0 else tuple(v)), m


def _norm(v: tuple[float, ...]) -> float:
    return math.sqrt(sum(c * c for c in v))


class LookAtCamera(_Model):
    """The eye at `eye`, looking at `target` (world units, x, y, z), `up` towards the image's top; `fov` is the
    vertical field of view in degrees; `orthographic` projection needs `view_height` (world units). The eye and
    the target must lie within 10^6 bounding-sphere radii of the volume's centre."""

    eye: Vec3
    target: Vec3
    up: Vec3 = (0.0, 0.0, 1.0)
    fov: Fov = 30.0
    projection: Literal["perspective", "orthographic"] = "perspective"
    view_height: ViewHeight | None = None

    @model_validator(mode="after")
    def _geometry(self) -> "LookAtCamera":
        d = tuple(t - e for t, e in zip(self.target, self.eye))
        if not all(math.isfinite(c) for c in d):
            raise ValueError("camera.target: too far from camera.eye (target - eye overflows)")
        f, nf = _scaled(d)  # unit-free: no overflow for 1e308, no underflow for 1e-308
        if nf == 0.0:
            raise ValueError("camera.target: equals camera.eye, there is no view direction")
        up, nu = _scaled(self.up)
        if nu == 0.0:
            raise ValueError("camera.up: must not be the zero vector")
        cross = (
            f[1] * up[2] - f[2] * up[1],
            f[2] * up[0] - f[0] * up[2],
            f[0] * up[1] - f[1] * up[0],
        )
        if _norm(cross) <= 1e-9 * _norm(f) * _norm(up):
            raise ValueError("camera.up: parallel to the view direction (target - eye)")
        if self.projection == "orthographic" and self.view_height is None:
            raise ValueError("camera.view_height: required with projection 'orthographic'")
        return self


class OrbitCamera(_Model):
    """Around the box centre: azimuth 0, elevation 0 looks from -y towards +y with +z up; azimuth turns towards
    +x, elevation towards +z; distance in multiples of the box's bounding-sphere radius, 10^-6 to 10^6 (null, the
    default: the nearest at which the whole box is in the picture from this view, with 5 % to spare)."""

    azimuth: Finite = 0.0
    elevation: Annotated[float, Field(ge=-90.0, le=90.0)] = 0.0
    distance: Annotated[float, Field(ge=DISTANCE_RANGE[0], le=DISTANCE_RANGE[1], allow_inf_nan=False)] | None = None
    view: Literal["anterior", "posterior", "left", "right", "superior", "inferior"] | None = Field(
        default=None,
        description="an anatomical view instead of azimuth/elevation: the eye on that side of the patient, "
                    "whichever way the file stored the volume (needs a DICOM, NIfTI or NRRD source)")
    fov: Fov = 30.0
    projection: Literal["perspective", "orthographic"] = "perspective"
    view_height: ViewHeight | None = None

    @model_validator(mode="after")
    def _ortho(self) -> "OrbitCamera":
        if self.view is not None and {"azimuth", "elevation"} & self.model_fields_set:
            raise ValueError("camera.view: give either a view or azimuth/elevation, not both")
        if self.projection == "orthographic" and self.view_height is None:
            raise ValueError("camera.view_height: required with projection 'orthographic'")
        return self


def _camera_kind(v: Any) -> str:
    if isinstance(v, dict):
        return "lookat" if ("eye" in v or "target" in v) else "orbit"
    return "lookat" if isinstance(v, LookAtCamera) else "orbit"


Camera = Annotated[
    Union[Annotated[LookAtCamera, Tag("lookat")], Annotated[OrbitCamera, Tag("orbit")]],
    Discriminator(_camera_kind),
]


class QualityReduction(_Model):
    """Level of detail at a data reduction of `reduction`:1 (bytes of the visible blocks at level 0 / bytes
    used), the blocks chosen by their significance to the image under the TF (thesis eq. 3.1)."""

    reduction: Annotated[float, Field(ge=1.0, allow_inf_nan=False)]


class QualityBudget(_Model):
    """Level of detail within `budget_mb` megabytes (10⁶ bytes) of brick data (thesis eq. 3.2)."""

    budget_mb: Annotated[float, Field(gt=0.0, allow_inf_nan=False)]


class QualityLevel(_Model):
    """Every visible block at store level `level` (0 = full resolution, each level halves the resolution along
    each axis), with its predicted ΔE: the bound any selection of about that reduction starts from
    (docs/lod.md: What 30:1 can reach). A level the store does not have is refused when it renders."""

    level: Annotated[int, Field(ge=0, le=15, strict=True)]


class QualityMaxDeltaE(_Model):
    """A target: the fastest setting (step, full resolution or a reduction, interpolation, adaptive screen-space
    sampling) whose predicted ΔE against the reference is at most `max_delta_e`, by the engine's cost model of its
    device (renderer/frame/target.py); the report's `chosen` says what it picked and why."""

    max_delta_e: Annotated[float, Field(gt=0.0, allow_inf_nan=False)]


class QualityMaxMs(_Model):
    """A target: the setting of the smallest predicted ΔE whose predicted time on this engine's device is at most
    `max_ms` milliseconds (renderer/frame/target.py); the report's `chosen` says what it picked and why."""

    max_ms: Annotated[float, Field(gt=0.0, allow_inf_nan=False)]


Quality = Union[Literal["full", "lossless"], QualityReduction, QualityBudget, QualityLevel, QualityMaxDeltaE,
                QualityMaxMs]


class Sampling(_Model):
    """`step` is in voxels of the finest level: multiples of the smallest spacing. `interpolation` chooses how
    the brick atlas is sampled across blocks of different levels (thesis §3.5): "nearest_block" (the default, when
    left out) samples a position's own block, clamped half a sample inside it (eq. 3.5), except across faces
    between level-0 blocks, whose bricks carry a one-sample apron of their neighbours' samples: trilinear there
    (thin seams where a ray grazes a face of a coarse block); "interblock" blends the blocks around every block
    face, continuous everywhere, but slower, for about the same mean ΔE (docs/lod.md: When it pays). At quality
    'full' the field is trilinear interpolation of level 0 whatever it says. `priority_map` belongs to the dual-TF
    mode (tf2).
    `empty_space_skipping` (default on) may be turned off for comparison; it never changes the image. (With coarse
    levels from a store of format 3 the walk over cells runs anyway: it also leaves out the coarse cells whose
    level-0 voxels the TF shows nothing of, which is part of what a coarse level shows.)
    `classification`: how a coarse sample (level >= 1) is classified: "distribution" (default) by the expected
    extinction and colour under the distribution of the level-0 values it stands for (kept by the store), "mean"
    by the TF at its mean value; at level 0 both are the same.
    `adaptive_object`: adaptive object-space sampling at LOD qualities (thesis §3.6.1: the step grows with the
    block's level, limited at block boundaries: `step` in level-0 blocks, step·2^(k+1) — about one sample per
    coarse voxel — in level-k blocks, up to step·B; the steps in a run of level-0 cells lie on full
    resolution's lattice); left out (null), it is on at every level-of-detail quality — a coarse level holds no
    detail a finer step could find, and without it a reduction saves memory but no time — and off at 'full' and
    wherever every block is at level 0, where it would change nothing. `adaptive_naive` (for benchmarking only):
    the naive variant whose steps are not limited at block boundaries (implies adaptive sampling; it undersamples finer blocks).
    `lod_visibility`: at the budgeted qualities the level-of-detail selection weighs each block's significance by
    how much of it the camera sees (a low-resolution cast of the view through a coarse level,
    renderer/lod/visibility.py), so that what lies behind opaque material stays coarse and the budget goes to what the
    picture shows; the selection then follows the view, and each new view selects and packs its atlas again. Left
    out (null) it is on for volumes of at most 2^27 voxels (a 512³ CT: a new view's selection costs little beside
    its render) and off above (where each new view's selection and atlas cost many times the render), and a
    turntable job's frames take it off (one selection for the whole animation: nothing changes from frame to
    frame but the view). Off: the selection depends on the TFs alone. Composite with one TF only (the projections
    and a second TF see what one TF hides).
    `adaptive_screen`: adaptive screen-space sampling (thesis §3.6.3): tiles of `screen_tile`² pixels rendered at
    2×2 up to full resolution, chosen by `screen_statistic` ("max", "average" or "rms") of the block scales along
    their rays, and reconstructed by intertile interpolation; at level 0 everywhere every tile is at full
    resolution and the image equals the plain render.
    `early_termination`: a ray ends once its opacity reaches it, and what is left of it takes its last colour; for
    a TF whose colours spread by more than 0.25 in a channel the threshold moves closer to 1 (what is left is
    (1 − t) · 0.25 / spread), since what the ray leaves unseen may differ from its last colour by that spread."""

    step: Annotated[float, Field(gt=0.0, le=1000.0, allow_inf_nan=False)] = 0.5
    interpolation: Literal["nearest_block", "interblock"] | None = None
    classification: Literal["distribution", "mean"] = "distribution"
    adaptive_object: bool | None = None
    adaptive_naive: bool = False
    adaptive_screen: bool = False
    preintegration: bool = False
    jitter: bool = False
    seed: Annotated[int, Field(ge=0, lt=2**32)] = 0
    early_termination: Annotated[float, Field(gt=0.0, le=1.0)] = 0.99
    empty_space_skipping: bool = True
    priority_map: bool = True
    lod_visibility: bool | None = None
    screen_statistic: Literal["max", "average", "rms"] = "rms"
    screen_tile: Annotated[int, Field(ge=2, le=64)] = 16



NonNeg = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]


def _nonzero(v: Vec3) -> Vec3:
    """A direction: not the zero vector; scaled to a largest |component| of 1 where squaring its components would
    overflow or underflow (a normal of [0, 1e308, 0] is +y, which the renderer's normalisation made 0)."""
    if not any(v):
        raise ValueError("must not be the zero vector")
    scaled, m = _scaled(v)
    return (scaled[0], scaled[1], scaled[2]) if m > 1e150 or m < 1e-150 else v


class Shading(_Model):
    """Local illumination (Blinn-Phong, two-sided) with the gradient of the sampled field as the normal.
    `light`: "headlight" (from the eye: every pixel lit along its own ray) or a direction towards the light, in
    world coordinates (`light_space` "world") or in the camera's frame (`light_space` "view": x right, y up,
    z towards the viewer). `min_gradient` (data units per world unit): below it a sample has no defined normal
    and is lit as a surface facing the light without a highlight; null: 1/1000 of the volume's value range per
    smallest voxel spacing. `gradient_weighting` (data units per world unit, optional): shading weighted by
    gradient magnitude — below it the lit colour blends linearly towards the unlit one, so that noise in
    homogeneous tissue is not lit. Shading is for composite and iso modes; the projections ignore it."""

    ambient: NonNeg = 0.3
    diffuse: NonNeg = 0.7
    specular: NonNeg = 0.2
    shininess: Annotated[float, Field(gt=0.0, le=1000.0, allow_inf_nan=False)] = 32.0
    light: Literal["headlight"] | Vec3 = "headlight"
    light_space: Literal["world", "view"] = "world"
    min_gradient: NonNeg | None = None
    gradient_weighting: Annotated[float, Field(gt=0.0, allow_inf_nan=False)] | None = None

    @field_validator("light")
    @classmethod
    def _light(cls, v: Any) -> Any:
        return v if isinstance(v, str) else _nonzero(v)


class ClipPlane(_Model):
    """Keeps the half-space the normal points into: points x with normal . (x - point) >= 0 (world units)."""

    point: Vec3
    normal: Vec3

    @field_validator("normal")
    @classmethod
    def _normal(cls, v: Vec3) -> Vec3:
        return _nonzero(v)


class ClipBox(_Model):
    """A crop box in world units (x, y, z); rays integrate only its inside, and blocks outside are not loaded."""

    min: Vec3
    max: Vec3

    @model_validator(mode="after")
    def _order(self) -> "ClipBox":
        for a, lo, hi in zip("xyz", self.min, self.max):
            if not lo < hi:
                raise ValueError(f"clip.box: min {a} = {lo} must be below max {a} = {hi}")
        return self


class Clip(_Model):
    """Up to 6 clip planes and a crop box (world units); the image is the integral over what all of them keep."""

    planes: list[ClipPlane] = Field(default_factory=list, max_length=6)
    box: ClipBox | None = None


class AdaptiveTF(_Model):
    """A TF template placed on the volume's α-histogram peaks when the renderer knows the volume
    (renderer/scene/adaptive_tf.py); given as `"tf": "auto"` (or another adaptive preset's name)."""

    template: Literal[tuple(ADAPTIVE)]  # type: ignore[valid-type]
    unit_distance: UnitDistance | None = None


def _named_tf(v: Any) -> Any:
    """A preset name stands for its TF (renderer/scene/presets.py); an adaptive one for its template."""
    if isinstance(v, str):
        try:
            return preset(v)
        except KeyError as exc:
            raise ValueError(exc.args[0]) from None
    return v


class Scene(_Model):
    """What to render: the camera, the image size, the transfer function(s), the quality (`"full"` resolution,
    `"lossless"` level of detail, `{"reduction": r}`, `{"budget_mb": m}` or `{"level": k}`, or a target:
    `{"max_delta_e": x}` or `{"max_ms": t}`), sampling, shading, clipping, the
    blend `mode` (`iso` needs `isovalue`), the `background` composited under the image (premultiplied RGBA; a
    transparent one keeps the image's alpha) and the output `format`."""

    camera: Camera = Field(default_factory=OrbitCamera)
    width: Annotated[int, Field(ge=1, le=16384)] = 512
    height: Annotated[int, Field(ge=1, le=16384)] = 512
    tf: TransferFunction | AdaptiveTF
    tf2: TransferFunction | AdaptiveTF | None = None
    quality: Quality = "full"
    sampling: Sampling = Field(default_factory=Sampling)
    shading: Shading | None = None
    clip: Clip | None = None
    mode: Literal["composite", "mip", "minip", "average", "iso"] = "composite"
    isovalue: Finite | None = None
    background: tuple[Unit, Unit, Unit, Unit] = (0.0, 0.0, 0.0, 0.0)
    format: Literal["png", "npy"] = "png"

    @model_validator(mode="after")
    def _iso(self) -> "Scene":
        if self.mode == "iso" and self.isovalue is None:
            raise ValueError("isovalue: required with mode 'iso' (the data value of the surface)")
        if self.tf2 is not None and self.mode != "composite":
            raise ValueError(f"tf2: a second transfer function needs mode 'composite', not {self.mode!r}")
        for name in ("tf", "tf2"):
            if getattr(getattr(self, name), "gradient_opacity", None) is not None and self.mode != "composite":
                raise ValueError(f"{name}.gradient_opacity: gradient opacity needs mode 'composite', not {self.mode!r}")
        return self

    @field_validator("tf", "tf2", mode="before")
    @classmethod
    def _preset(cls, v: Any) -> Any:
        return _named_tf(v)

    # -- construction with one-line errors ---------------------------------------------------------------
    @classmethod
    def parse(cls, data: SceneLike | bytes) -> Scene:
        """A Scene from a Scene, a dict (any mapping), JSON text or a JSON file's path; raises SceneError naming
        the field."""
        if isinstance(data, Scene):
            return data
        if isinstance(data, str) and not data.lstrip().startswith("{") and Path(data).is_file():
            data = Path(data)  # a file's name, not JSON text
        if isinstance(data, os.PathLike):
            path = Path(data)
            try:
                data = path.read_text()
            except OSError as exc:
                raise SceneError(f"scene file {str(path)!r}: {exc.strerror or exc}") from None
        if isinstance(data, (str, bytes)):
            try:
                data = json.loads(data)
            except json.JSONDecodeError as exc:
                raise SceneError(f"scene is not valid JSON: {exc}") from None
        if isinstance(data, Mapping) and not isinstance(data, dict):
            data = dict(data)
        if not isinstance(data, dict):
            raise SceneError(f"a scene must be a JSON object, got {type(data).__name__}")
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise SceneError(validation_message(exc)) from None


#: What the verbs take as a scene (`lodcast.render`, `Renderer.render`, ...): a Scene, a dict or other mapping of
#: the scene's JSON, JSON text, or a JSON file's path (Scene.parse reads each)
SceneLike: TypeAlias = Scene | Mapping[str, Any] | str | os.PathLike[str]


def parse_scene(data: Any) -> Scene:
    return Scene.parse(data)


def branchless(loc: Any) -> list[str | int]:
    """A pydantic error location without the branch labels pydantic inserts into union paths ('lookat', 'orbit',
    "literal['full','lossless']", 'tuple[float, float, float]', 'QualityReduction', 'function-after[...]'): the
    field's path as the JSON has it."""
    return [p for p in loc if not isinstance(p, str) or (
        p not in ("lookat", "orbit") and "[" not in p and not (p.startswith("function-") or p[:1].isupper()))]


def validation_message(exc: ValidationError, prefix: str = "") -> str:
    """One line naming the (first) bad field as a dotted path, e.g. ``sampling.step: Input should be ...``."""
    errs = exc.errors(include_url=False)
    if not errs:
        return str(exc)
    # inside a union pydantic reports every branch; the most specific one (deepest, not a mere tag mismatch) wins
    weak = {"literal_error", "missing", "extra_forbidden", "model_type", "dict_type"}
    e = min(errs, key=lambda x: (len(errs) > 1 and x.get("type") in weak, -len(x.get("loc", ()))))
    loc = [str(p) for p in branchless(e.get("loc", ()))]
    msg = str(e.get("msg", "invalid"))
    if msg.startswith("Value error, "):
        msg = msg[len("Value error, "):]
    where = "" if re.match(r"^[a-z_][a-z0-9_.]*: ", msg) else ".".join(loc)  # a validator may name it itself
    text = f"{prefix}{where}: {msg}" if where else f"{prefix}{msg}"
    others = {x.get("loc", ("",))[:1] for x in errs} - {e.get("loc", ("",))[:1]}  # other fields, not other branches
    if others:
        text += f" (and {len(others)} more field{'s' if len(others) > 1 else ''} invalid)"
    return " ".join(text.split())
