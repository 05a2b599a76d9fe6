"""Camera per docs/design.md, in world (x, y, z) coordinates (x is the last array axis, z the first).

Pixel (row i, column j), row 0 at the top, casts its ray through its centre: f = normalize(target − eye),
r = normalize(f × up), u = r × f; perspective direction ∝ f + ((2(j+½)/W − 1)·tan(fov/2)·W/H)·r +
((1 − 2(i+½)/H)·tan(fov/2))·u. Orthographic: parallel rays along f from the image plane through the eye, of
height `view_height`. The orbit form puts the eye at azimuth/elevation around the box centre at `distance` times
the bounding-sphere radius.

`frame` refuses (SceneError naming the field) what the scene model alone cannot judge, since it depends on the
volume: an eye or target more than MAX_RADII bounding-sphere radii from the box centre, an orthographic view height
outside VIEW_HEIGHT_RADII radii, and any frame whose numbers are not finite in the kernel's single precision (an
eye that coincides with the target once rounded, a view height that underflows) — such a view is empty or noise,
never a picture of the volume.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from lodcast.renderer.scene.clip import clipped_box
from lodcast.renderer.scene.scene import MAX_RADII, VIEW_HEIGHT_RADII, LookAtCamera, OrbitCamera, Scene, SceneError

__all__ = ["Frame", "box_world", "fit_distance", "frame", "geometry", "look_at", "orbit_eye", "pixel_rays", "ray_box", "ray_octants",
           "rays_at", "resolve_view"]


def box_world(shape_zyx: ArrayLike, spacing_zyx: ArrayLike, origin_zyx: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """The volume's box (lo, hi) in world xyz: origin − spacing/2 to origin + (shape − ½)·spacing."""
    sh = np.asarray(shape_zyx, np.float64)[::-1]
    sp = np.asarray(spacing_zyx, np.float64)[::-1]
    org = np.asarray(origin_zyx, np.float64)[::-1]
    return org - sp / 2, org + (sh - 0.5) * sp


@dataclass(frozen=True)
class Frame:
    eye: np.ndarray  # xyz; orthographic: centre of the image plane
    f: np.ndarray
    r: np.ndarray
    u: np.ndarray
    half_w: float  # perspective: tan(fov/2)·W/H; orthographic: half the view width in world units
    half_h: float
    orthographic: bool


def _tame(v: np.ndarray) -> np.ndarray:
    """`v`, divided by its largest |component| where squaring it would overflow or underflow (a vector of 1e-300
    or 1e308 components has a direction too); as it is otherwise."""
    m = float(np.max(np.abs(v)))
    return v / m if (m < 1e-150 or m > 1e150) and 0.0 < m < np.inf else v


def _unit(v: np.ndarray) -> np.ndarray:
    v = _tame(v)
    return v / np.linalg.norm(v)


def orbit_eye(cam: OrbitCamera, center: np.ndarray, radius: float,
              distance: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(eye, up) of the orbit camera at `distance` radii (default the camera's). `up` is the elevation tangent,
    equal to +z's direction in the view plane, so the poles (elevation ±90°) stay well defined."""
    a, e = np.radians(cam.azimuth), np.radians(cam.elevation)
    d = np.array([np.sin(a) * np.cos(e), -np.cos(a) * np.cos(e), np.sin(e)])
    up = np.array([-np.sin(a) * np.sin(e), np.cos(a) * np.sin(e), np.cos(e)])
    dist = cam.distance if distance is None else distance
    assert dist is not None, "orbit_eye: the camera has no distance and none was given"
    return center + d * radius * dist, up


def fit_distance(box_lo: ArrayLike, box_hi: ArrayLike, azimuth: float, elevation: float, fov: float = 30.0,
                 aspect: float = 1.0, margin: float = 0.05) -> float:
    """The smallest orbit distance (in bounding-sphere radii) at which every corner of the box projects inside the
    perspective view with `margin` (a fraction of the half-width) to spare: the whole volume in the picture."""
    lo, hi = np.asarray(box_lo, np.float64), np.asarray(box_hi, np.float64)
    center, radius = (lo + hi) / 2, 0.5 * float(np.linalg.norm(hi - lo))
    eye, up = orbit_eye(OrbitCamera(azimuth=azimuth, elevation=elevation), center, radius, 1.0)
    fr = look_at(eye, center, up, fov, 1, 1)  # the view's basis does not depend on the distance
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]) - center
    t = float(np.tan(np.radians(fov) / 2)) * (1.0 - margin)
    # a corner at depth (c·f + d R) needs |c·r| <= t·aspect·depth and |c·u| <= t·depth
    need = np.maximum(np.abs(corners @ fr.r) / (t * aspect), np.abs(corners @ fr.u) / t) - corners @ fr.f
    return float(need.max() / radius)


def resolve_view(cam: OrbitCamera, codes: list[str] | None) -> OrbitCamera:
    """An orbit camera's named `view` as the azimuth and elevation that put the eye on that side of the patient,
    given the patient direction of world +x, +y, +z (store/orientation.py)."""
    if cam.view is None:
        return cam
    if codes is None:
        raise SceneError(f"camera.view: {cam.view!r} needs the patient orientation, which this volume's source did "
                         f"not give (DICOM, NIfTI and NRRD do); use azimuth/elevation")
    from lodcast.store.orientation import view_direction

    d = view_direction(cam.view, codes)
    elevation = float(np.degrees(np.arcsin(np.clip(d[2], -1.0, 1.0))))
    azimuth = float(np.degrees(np.arctan2(d[0], -d[1]))) if abs(d[2]) < 1.0 else 0.0
    return cam.model_copy(update={"azimuth": azimuth, "elevation": elevation, "view": None})


def look_at(eye: ArrayLike, target: ArrayLike, up: ArrayLike, fov: float, width: int, height: int,
            orthographic: bool = False, view_height: float | None = None) -> Frame:
    eye = np.asarray(eye, np.float64)
    f = _unit(np.asarray(target, np.float64) - eye)
    r = _unit(np.cross(f, _tame(np.asarray(up, np.float64))))
    u = np.cross(r, f)
    aspect = width / height
    if orthographic:
        assert view_height is not None  # the camera models require it with an orthographic projection
        hh = 0.5 * float(view_height)
        return Frame(eye, f, r, u, hh * aspect, hh, True)
    t = float(np.tan(np.radians(fov) / 2))
    return Frame(eye, f, r, u, t * aspect, t, False)


_F32_MAX = float(np.finfo(np.float32).max)


def _far(p: np.ndarray, center: np.ndarray, radius: float) -> float:
    """|p − center| in bounding-sphere radii (inf where it overflows)."""
    with np.errstate(over="ignore", invalid="ignore"):
        d = np.abs(np.asarray(p, np.float64) - center)
        m = float(np.max(d))
        far = m * float(np.linalg.norm(d / m)) / radius if 0.0 < m < np.inf else m / radius
    return far if np.isfinite(far) else float("inf")


def _check(fr: Frame, field: str, view_field: str) -> Frame:
    """The frame as the kernel takes it (float32): every number finite, the basis unit vectors, the image plane of
    non-zero size; otherwise SceneError naming `field` (the eye's place) or `view_field` (the image plane's size)."""
    basis = np.concatenate([fr.eye, fr.f, fr.r, fr.u])
    if not (np.all(np.isfinite(basis)) and float(np.max(np.abs(basis))) < _F32_MAX
            and all(abs(float(np.linalg.norm(v)) - 1.0) < 1e-6 for v in (fr.f, fr.r, fr.u))):
        raise SceneError(f"{field}: the view is degenerate for this volume (the eye coincides with the target or "
                         f"its position overflows single precision)")
    for half in (fr.half_w, fr.half_h):
        if not (np.isfinite(half) and 0.0 < half < _F32_MAX and np.float32(half) > 0):
            raise SceneError(f"{view_field}: the image's half extent ({half:.3g}) is not a positive number in "
                             f"single precision; the view is degenerate")
    return fr


def frame(cam: LookAtCamera | OrbitCamera, width: int, height: int, box_lo: np.ndarray, box_hi: np.ndarray) -> Frame:
    """The camera's frame for a `width` x `height` image of the volume whose world box is [box_lo, box_hi]; raises
    SceneError naming the camera's field where the view would be non-finite or degenerate for this volume."""
    ortho = cam.projection == "orthographic"
    box_lo, box_hi = np.asarray(box_lo, np.float64), np.asarray(box_hi, np.float64)
    center = (box_lo + box_hi) / 2
    radius = 0.5 * float(np.linalg.norm(box_hi - box_lo))
    if not (np.all(np.isfinite(center)) and np.isfinite(radius) and radius > 0.0):
        raise SceneError("camera: the volume's world box is not finite (its spacing or origin), no view of it can "
                         "be computed; re-ingest the volume")
    if ortho:
        assert cam.view_height is not None  # the camera models require it with an orthographic projection
        lo, hi = VIEW_HEIGHT_RADII
        if not lo * radius <= cam.view_height <= hi * radius:
            raise SceneError(f"camera.view_height: {cam.view_height:.6g} world units is outside {lo:g} to {hi:g} "
                             f"times this volume's bounding-sphere radius ({radius:.6g})")
    view_field = "camera.view_height" if ortho else "camera.fov"
    if isinstance(cam, OrbitCamera):
        distance = cam.distance
        if distance is None:  # the whole box in the picture (orthographic: any eye outside the box will do)
            distance = 2.0 if ortho else fit_distance(box_lo, box_hi, cam.azimuth, cam.elevation, cam.fov,
                                                      width / height)
        eye, up = orbit_eye(cam, center, radius, distance)
        fr = look_at(eye, center, up, cam.fov, width, height, ortho, cam.view_height)
        return _check(fr, "camera.distance" if cam.distance is not None else "camera.fov", view_field)
    for name, p in (("eye", cam.eye), ("target", cam.target)):
        far = _far(np.asarray(p, np.float64), center, radius)
        if far > MAX_RADII:
            raise SceneError(f"camera.{name}: {far:.3g} bounding-sphere radii from the volume's centre, more than "
                             f"{MAX_RADII:g} (radius {radius:.6g} world units): the image would be empty or noise")
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        fr = look_at(cam.eye, cam.target, cam.up, cam.fov, width, height, ortho, cam.view_height)
    return _check(fr, "camera.eye", view_field)


def rays_at(fr: Frame, x: ArrayLike, y: ArrayLike, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(origins, unit directions) (..., 3) float64 of the rays through image positions (x, y) in pixels from the
    top left corner (pixel (i, j)'s centre is x = j + 1/2, y = i + 1/2) — the host-side mirror of the kernel's ray
    setup (lc_pixel_ray)."""
    px = (2 * np.asarray(x, np.float64) / width - 1)[..., None] * fr.half_w
    py = (1 - 2 * np.asarray(y, np.float64) / height)[..., None] * fr.half_h
    if fr.orthographic:
        org = fr.eye + px * fr.r + py * fr.u
        return org, np.broadcast_to(fr.f, org.shape).copy()
    d = fr.f + px * fr.r + py * fr.u
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return np.broadcast_to(fr.eye, d.shape).copy(), d


def ray_octants(fr: Frame) -> tuple[int, ...]:
    """The octants of direction (o = (x > 0) | (y > 0) << 1 | (z > 0) << 2, world axes, which are the voxel axes)
    the rays through any image position can go in: the kernel's DDA reads the space-leaping plane of its ray's
    octant (renderer/walk/leap.py). A ray's direction f + px r + py u is linear in the image position, so each
    component's sign over the image is bounded by its values at the four corners; a component that may be zero
    or change sign there (within rounding of float32) gives both octants along that axis."""
    if fr.orthographic:
        d = fr.f[None, :]
    else:
        d = np.array([fr.f + sx * fr.half_w * fr.r + sy * fr.half_h * fr.u for sx in (-1, 1) for sy in (-1, 1)])
    tol = 1e-5 * float(np.abs(d).max())
    signs = [[s for s, ok in ((0, (d[:, a] <= tol).any()), (1, (d[:, a] >= -tol).any())) if ok] for a in range(3)]
    return tuple(sorted(x | y << 1 | z << 2 for x in signs[0] for y in signs[1] for z in signs[2]))


def pixel_rays(fr: Frame, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(origins, unit directions), each (H, W, 3) float64, through the pixel centres."""
    y, x = np.mgrid[:height, :width] + 0.5
    return rays_at(fr, x, y, width, height)


def ray_box(o: np.ndarray, d: np.ndarray, lo: ArrayLike, hi: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """(t0, t1) per ray (..., 3) of the part inside the box [lo, hi] (world), t0 >= 0 (rays start at the eye or the
    image plane); t1 <= t0 where a ray misses it."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # a direction of 1e-308 along an axis: ±inf
        ta, tb = (lo - o) / d, (hi - o) / d
    t0 = np.maximum(np.nanmax(np.minimum(ta, tb), axis=-1), 0.0)
    return t0, np.nanmin(np.maximum(ta, tb), axis=-1)


def geometry(vol: Any, scene: Scene) -> tuple[tuple, Frame, tuple, float]:
    """(the volume's world box, the camera frame, the box the rays integrate (crop box applied), the step in world
    units) of `scene` on `vol` (a VolumeView: its shape, spacing, origin and frame box)."""
    box = box_world(vol.shape, vol.spacing, vol.origin) if vol.frame_box is None else vol.frame_box
    fr = frame(scene.camera, scene.width, scene.height, *box)  # the camera frames the whole volume
    kbox = clipped_box(box, scene.clip)
    if np.any(kbox[0] >= kbox[1]):  # the crop box misses the volume: a degenerate box no ray enters
        kbox = (kbox[0], kbox[0].copy())
    return box, fr, kbox, scene.sampling.step * float(min(vol.spacing))
