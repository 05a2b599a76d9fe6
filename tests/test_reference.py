"""The float64 reference (tests/reference.py) against closed forms.

Every expected value here is computed from docs/design.md's formulas directly (slab law, closed-form optical depth
of a linear opacity ramp, chord lengths, the camera formula written out again), never by calling the
reference's own quadrature, so these tests hold the reference to the contract before it is used to hold the
kernel. Tolerances are stated per test; the reference's quadrature converges to ~1e-12, so most are tight.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from reference import (
    analytic_slab_alpha,
    box_bounds,
    camera_rays,
    delta_e,
    orbit_to_lookat,
    project_point,
    reference_render,
    sample_field,
)
from scenes import aim_at, axis_camera, basis, centroid, const_tf, predicted_pixel
from scipy import integrate

RED, BLUE = [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]


def ortho_pixel_points(cam: dict, W: int, H: int) -> np.ndarray:
    """World point on the image plane of each pixel centre of an orthographic camera (H×W×3)."""
    eye, f, r, u = basis(cam)
    h = cam["view_height"] / 2
    px = (2 * (np.arange(W) + 0.5) / W - 1) * W / H
    py = 1 - 2 * (np.arange(H) + 0.5) / H
    return eye + h * (px[None, :, None] * r + py[:, None, None] * u)


# ------------------------------------------------------------------------------------------- constant slab
@pytest.mark.parametrize("axis", ["x", "y", "z"])
@pytest.mark.parametrize("a,unit", [(0.05, None), (0.3, 2.5), (0.9, 0.5)])
def test_constant_slab_along_each_axis(axis: str, a: float, unit: float | None) -> None:
    """A = 1 − (1 − a)^(L/unit) with L the box's extent along the ray, colour = c·A (premultiplied)."""
    shape = (6, 9, 13)
    vol = np.full(shape, 3.0)
    cam = axis_camera(axis, shape)
    img = reference_render(vol, {"camera": cam, "width": 4, "height": 3, "tf": const_tf(a, unit=unit)})
    L = {"x": 13, "y": 9, "z": 6}[axis]
    want = analytic_slab_alpha(a, L, unit or 1.0)
    assert np.abs(img[..., 3] - want).max() < 1e-11
    assert np.abs(img[..., :3] - want * np.array([0.8, 0.5, 0.2])).max() < 1e-11


def test_analytic_slab_law_itself() -> None:
    assert analytic_slab_alpha(0.1, 40, 1.0) == pytest.approx(1 - 0.9**40, abs=1e-15)
    assert analytic_slab_alpha(0.999999, 1, 4.0) == pytest.approx(1 - 1e-6**0.25, abs=1e-12)  # 0.999999 is inexact
    assert analytic_slab_alpha(1.0, 1e-9, 1.0) == 1.0


def test_rays_missing_the_box_and_eye_inside() -> None:
    vol = np.ones((4, 4, 10))
    # the eye inside the box at x = 2 looking along +x: only the part in front counts (t ≥ 0)
    cam = {"eye": [2.0, 1.5, 1.5], "target": [9.0, 1.5, 1.5], "up": [0, 0, 1], "projection": "orthographic", "view_height": 1.0}
    img = reference_render(vol, {"camera": cam, "width": 2, "height": 2, "tf": const_tf(0.2, unit=1.0)})
    assert np.abs(img[..., 3] - analytic_slab_alpha(0.2, 9.5 - 2.0, 1.0)).max() < 1e-11
    # looking away from the box: nothing at all
    cam_away = {**cam, "eye": [-1.0, 1.5, 1.5], "target": [-9.0, 1.5, 1.5]}
    assert np.all(reference_render(vol, {"camera": cam_away, "width": 2, "height": 2, "tf": const_tf(0.2)}) == 0)


# ------------------------------------------------------------------------------------------- linear ramp
def _ramp_tau(a0: float, a1: float, length: float, unit: float):
    """Closed-form optical depth τ(t) for opacity a(t) = a0 + (a1 − a0)·t/length over [0, length]:
    σ = −ln(1 − a)/unit; with u = 1 − a, ∫ −ln u dt = (1/q)[u ln u − u] (q = (a1 − a0)/length)."""
    q = (a1 - a0) / length
    F = lambda u: u * math.log(u) - u if u > 0 else 0.0  # noqa: E731  (u ln u → 0)
    return lambda t: (F(1 - a0 - q * t) - F(1 - a0)) / q / unit


def _ramp_expected(a0, a1, c0, c1, n, sx, unit):
    """Ray along +x through a volume whose values rise linearly from v0 to v1 over index 0 … n−1 with a TF
    that is linear from (v0, c0, a0) to (v1, c1, a1): a half-voxel rim at a0, the ramp, a rim at a1.
    A from the closed-form τ; C = ∫ c σ e^(−τ) dt by scipy.quad on the closed-form τ (independent of the
    reference's quadrature)."""
    Lr, rim = (n - 1) * sx, sx / 2
    c0, c1 = np.asarray(c0, float), np.asarray(c1, float)
    s_rim0 = -math.log1p(-a0) / unit
    tau_r = _ramp_tau(a0, a1, Lr, unit)
    T1 = math.exp(-s_rim0 * rim)
    C = c0 * (1 - T1)
    rgb = []
    for k in range(3):
        f = lambda t: (c0[k] + (c1[k] - c0[k]) * t / Lr) * (-math.log1p(-(a0 + (a1 - a0) * t / Lr)) / unit) * math.exp(-tau_r(t))  # noqa: E731
        val, err = integrate.quad(f, 0, Lr, epsabs=1e-13, epsrel=1e-12, limit=200)
        rgb.append(val)
    C = C + T1 * np.array(rgb)
    T2 = T1 * math.exp(-tau_r(Lr))
    if a1 >= 1.0:  # the back rim is opaque: it shows its colour through what is left
        return np.r_[C + T2 * c1, 1.0]
    s_rim1 = -math.log1p(-a1) / unit
    C = C + T2 * c1 * (1 - math.exp(-s_rim1 * rim))
    return np.r_[C, 1 - T2 * math.exp(-s_rim1 * rim)]


@pytest.mark.parametrize("a0,a1,sx,unit", [(0.02, 0.6, 1.0, 1.0), (0.3, 0.05, 5.0, 2.0), (0.0, 1.0, 1.0, 1.0), (0.2, 0.999999, 1.0, 0.7)])
def test_linear_ramp_with_linear_tf(a0: float, a1: float, sx: float, unit: float) -> None:
    n, v0, v1 = 12, 100.0, 400.0
    vol = np.broadcast_to(np.linspace(v0, v1, n), (3, 3, n)).copy()
    spacing = (1.0, 1.0, sx)
    tf = {"points": [{"value": v0, "color": RED, "opacity": a0}, {"value": v1, "color": BLUE, "opacity": a1}], "unit_distance": unit}
    cam = axis_camera("x", vol.shape, spacing, view_height=1.5)
    img = reference_render(vol, {"camera": cam, "width": 3, "height": 3, "tf": tf}, spacing)
    want = _ramp_expected(a0, a1, RED, BLUE, n, sx, unit)
    assert np.abs(img - want).max() < 1e-7, (img[1, 1], want)


def test_tf_peak_of_opacity_one_is_integrable_not_opaque() -> None:
    """A TF that touches a = 1 at a single value: σ = −ln|…| is integrable, so the ray is not opaque:
    τ = closed form over the two linear halves (0.2 → 1 then 1 → 0.2)."""
    n = 5
    vol = np.broadcast_to(np.linspace(0.0, 2.0, n), (3, 3, n)).copy()
    tf = {"points": [{"value": 0.0, "color": RED, "opacity": 0.2}, {"value": 1.0, "color": RED, "opacity": 1.0},
                     {"value": 2.0, "color": RED, "opacity": 0.2}], "unit_distance": 1.0}
    img = reference_render(vol, {"camera": axis_camera("x", vol.shape, view_height=1.5), "width": 3, "height": 3, "tf": tf})
    half = (n - 1) / 2
    tau = 2 * _ramp_tau(0.2, 1.0, half, 1.0)(half) + 2 * 0.5 * -math.log(0.8)
    want = 1 - math.exp(-tau)
    assert want < 0.999  # the point of the test: finite optical depth
    assert np.abs(img[..., 3] - want).max() < 1e-6
    assert np.abs(img[..., 0] - want).max() < 1e-6


# --------------------------------------------------------------------------------------------- sphere
def test_sphere_chords() -> None:
    """Voxel values = distance to a centre, TF opaque (a, constant colour) below R − δ, clear above R + δ.
    Trilinear interpolation of the convex r over-estimates r by at most 3/(8(R − 1)) voxels (Jensen plus
    the Hessian bound 1/r), so the opaque region lies between the spheres of radius R − δ − ε and R + δ:
    A is bounded by the slab law over those chords, A = 0 outside R + δ, and rgb = c·A exactly."""
    n, R, delta, a = 24, 9.0, 1e-3, 0.15
    ctr = np.array([11.3, 11.6, 11.5])  # (x, y, z), off the voxel lattice on purpose
    zz, yy, xx = np.mgrid[:n, :n, :n].astype(float)
    vol = np.sqrt((xx - ctr[0]) ** 2 + (yy - ctr[1]) ** 2 + (zz - ctr[2]) ** 2)
    col = [0.3, 0.6, 0.9]
    tf = {"points": [{"value": R - delta, "color": col, "opacity": a}, {"value": R + delta, "color": col, "opacity": 0.0}], "unit_distance": 1.0}
    cam = {"eye": [ctr[0], ctr[1], -20.0], "target": ctr.tolist(), "up": [0, 1, 0], "projection": "orthographic", "view_height": 22.0}
    W = H = 16
    img = reference_render(vol, {"camera": cam, "width": W, "height": H, "tf": tf})
    pts = ortho_pixel_points(cam, W, H)
    b = np.hypot(pts[..., 0] - ctr[0], pts[..., 1] - ctr[1])
    chord = lambda rad: 2 * np.sqrt(np.maximum(rad**2 - b**2, 0.0))  # noqa: E731
    eps = 3 / (8 * (R - 1))
    lo = 1 - (1 - a) ** chord(R - delta - eps)
    hi = 1 - (1 - a) ** chord(R + delta)
    A = img[..., 3]
    assert np.all(A >= lo - 1e-9) and np.all(A <= hi + 1e-9)
    inner = b < 0.8 * R
    assert inner.sum() > 60 and np.all((hi - lo)[inner] < 0.02)  # the bound is tight where it is tested
    assert np.all(A[b > R + delta] == 0.0)
    assert np.abs(img[..., :3] - A[..., None] * np.array(col)).max() < 1e-12


# --------------------------------------------------------------------------------------------- cameras
def test_orbit_to_lookat_formula() -> None:
    shape, spacing = (16, 32, 48), (1.0, 1.0, 1.0)
    centre, radius = np.array([23.5, 15.5, 7.5]), 0.5 * math.sqrt(48**2 + 32**2 + 16**2)
    c0 = orbit_to_lookat({"azimuth": 0, "elevation": 0, "distance": 2}, shape, spacing)
    assert np.allclose(c0["eye"], centre + [0, -2 * radius, 0]) and np.allclose(c0["target"], centre)
    c90 = orbit_to_lookat({"azimuth": 90, "elevation": 0, "distance": 2}, shape, spacing)
    assert np.allclose(c90["eye"], centre + [2 * radius, 0, 0])  # azimuth turns towards +x
    cel = orbit_to_lookat({"azimuth": 0, "elevation": 30, "distance": 1}, shape, spacing)
    assert np.allclose(cel["eye"], centre + radius * np.array([0, -math.cos(math.pi / 6), 0.5]))  # towards +z
    assert cel["up"] == [0.0, 0.0, 1.0]


def test_orbit_render_equals_lookat_render() -> None:
    rng = np.random.default_rng(1)
    vol = rng.random((8, 10, 12))
    spacing, origin = (2.0, 1.0, 0.5), (-3.0, 1.0, 4.0)
    tf = {"points": [{"value": 0.2, "color": RED, "opacity": 0.0}, {"value": 0.9, "color": BLUE, "opacity": 0.5}]}
    orbit = {"azimuth": 35, "elevation": -20, "distance": 3, "fov": 25}
    lo, hi = box_bounds(vol.shape, spacing, origin)
    c, rad = (lo + hi) / 2, np.linalg.norm(hi - lo) / 2
    az, el = math.radians(35), math.radians(-20)
    eye = c + 3 * rad * np.array([math.sin(az) * math.cos(el), -math.cos(az) * math.cos(el), math.sin(el)])
    look = {"eye": eye.tolist(), "target": c.tolist(), "up": [0, 0, 1], "fov": 25}
    base = {"width": 12, "height": 9, "tf": tf}
    i1 = reference_render(vol, {**base, "camera": orbit}, spacing, origin)
    i2 = reference_render(vol, {**base, "camera": look}, spacing, origin)
    assert i1[..., 3].max() > 0.1
    assert np.abs(i1 - i2).max() < 1e-12


def _marker_volume():
    vol = np.zeros((16, 24, 32))
    vol[5, 14, 20] = 1.0
    return vol, np.array([20.0, 14.0, 5.0])  # world (x, y, z) of voxel (z=5, y=14, x=20)


MARKER_TF = {"points": [{"value": 0.0, "color": [1, 1, 1], "opacity": 0.0}, {"value": 0.05, "color": [1, 1, 1], "opacity": 1.0},
                        {"value": 1.0, "color": [1, 1, 1], "opacity": 1.0}]}


@pytest.mark.parametrize("form", ["lookat", "orbit"])
@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
def test_marker_voxel_lands_on_predicted_pixel(form: str, projection: str) -> None:
    """The alpha-weighted centroid of a marker voxel's footprint lies within 0.25 px of the pixel the camera
    formula predicts, on a non-square image; the footprint is compact (a few pixels), so a flipped row or
    column, a swapped axis or a wrong aspect would move it by many pixels."""
    vol, p = _marker_volume()
    W, H = 64, 40
    if form == "orbit":
        cam: dict = {"azimuth": 25, "elevation": 15, "distance": 2.0, "fov": 30}
        if projection == "orthographic":
            cam.update(projection="orthographic", view_height=24.0)
        look = orbit_to_lookat(cam, vol.shape)
    else:
        cam = {"eye": [-30.0, -45.0, 25.0], "target": [15.5, 11.5, 7.5], "up": [0.0, 0.0, 1.0], "fov": 30.0}
        if projection == "orthographic":
            cam.update(projection="orthographic", view_height=24.0)
        look = cam
    img = reference_render(vol, {"camera": cam, "width": W, "height": H, "tf": MARKER_TF})
    a = img[..., 3]
    i, j = predicted_pixel(look, W, H, p)
    assert 3 < i < H - 3 and 3 < j < W - 3
    ci, cj = centroid(a)
    assert abs(ci - i) < 0.25 and abs(cj - j) < 0.25, ((ci, cj), (i, j))
    assert (a > 0.01).sum() < 40
    assert np.allclose(project_point(cam, W, H, p, vol.shape), (i, j), atol=1e-9)


def test_camera_rays_pixel_convention() -> None:
    """Row 0 is the top (+u), column 0 the left (−r); perspective directions are unit and the centre of an
    odd-sized image looks straight along f."""
    cam = {"eye": [0.0, -10.0, 0.0], "target": [0.0, 0.0, 0.0], "up": [0.0, 0.0, 1.0], "fov": 60.0}
    o, d = camera_rays(cam, 5, 3, (1, 1, 1))
    assert np.allclose(np.linalg.norm(d, axis=-1), 1.0)
    assert np.allclose(d[1, 2], [0, 1, 0])
    assert d[0, 2, 2] > 0 and d[2, 2, 2] < 0  # top row looks up (+z)
    assert d[1, 0, 0] < 0 and d[1, 4, 0] > 0  # f × up = +y × +z = +x: right is +x
    t = math.tan(math.radians(30))
    assert np.allclose(d[0, 2] / d[0, 2, 1], [0, 1, (1 - 1 / 3) * t])  # py = 1 − 2·(0.5)/3


# ------------------------------------------------------------------------------------------------ NaN
@pytest.mark.parametrize("nan_x,clear", [(6, 2.0), (19, 1.5), (18, 2.0), (0, 1.5)])
def test_nan_plane_blanks_its_stencil(nan_x: int, clear: float) -> None:
    """A plane of NaN voxels at x = k blanks every sample whose stencil reads it: x ∈ (k − 1, k + 1) inside,
    plus the half-voxel rim when k is the edge voxel (the rim reads only the edge voxel; so a NaN at
    n − 2 does not reach the rim). Expected A = 1 − (1 − a)^((L − clear)/unit)."""
    n = 20
    vol = np.full((4, 4, n), 2.0)
    vol[:, :, nan_x] = np.nan
    img = reference_render(vol, {"camera": axis_camera("x", vol.shape, view_height=2.0), "width": 3, "height": 3, "tf": const_tf(0.1, unit=1.0)})
    assert np.isfinite(img).all()
    assert np.abs(img[..., 3] - analytic_slab_alpha(0.1, n - clear, 1.0)).max() < 1e-11


def test_single_nan_voxel_and_mip_ignore_it() -> None:
    n = 12
    vol = np.full((5, 5, n), 2.0)
    vol[2, 2, 5] = np.nan
    # orthographic along x; view_height 5 on 5×5 pixels puts the rays at y, z = 0.5 … 4.5: between voxel
    # centres, so exactly the four rays at y, z ∈ {1.5, 2.5} pass through cells that read the NaN voxel
    cam = axis_camera("x", vol.shape, view_height=5.0)
    pts = ortho_pixel_points(cam, 5, 5)
    img = reference_render(vol, {"camera": cam, "width": 5, "height": 5, "tf": const_tf(0.1, unit=1.0)})
    touches = (np.abs(pts[..., 1] - 2) < 1) & (np.abs(pts[..., 2] - 2) < 1)
    assert touches.sum() == 4
    assert np.abs(img[..., 3][touches] - analytic_slab_alpha(0.1, n - 2, 1.0)).max() < 1e-11
    assert np.abs(img[..., 3][~touches] - analytic_slab_alpha(0.1, n, 1.0)).max() < 1e-11
    mip_tf = {"points": [{"value": 0.0, "color": RED, "opacity": 0.0}, {"value": 4.0, "color": RED, "opacity": 1.0}]}
    mip = reference_render(vol, {"camera": cam, "width": 5, "height": 5, "tf": mip_tf, "mode": "mip"})
    assert np.isfinite(mip).all() and np.abs(mip[..., 3] - 0.5).max() < 1e-12
    allnan = np.full((2, 2, 2), np.nan)
    out = reference_render(allnan, {"camera": axis_camera("x", allnan.shape), "width": 2, "height": 2, "tf": const_tf(0.5)})
    assert np.all(out == 0)


def test_sample_field_stencil_rule() -> None:
    vol = np.arange(8.0).reshape(1, 1, 8)
    vol[0, 0, 6] = np.nan
    x = np.array([0.0, 2.25, 5.0, 5.5, 6.5, 7.0, 7.4, -0.5])
    s = sample_field(vol, np.stack([x, np.zeros_like(x), np.zeros_like(x)], -1))
    assert s[0] == 0 and s[1] == 2.25 and s[2] == 5.0 and s[5] == 7.0 and s[6] == 7.0 and s[7] == 0.0
    assert np.isnan(s[3]) and np.isnan(s[4])


# ------------------------------------------------------------------------------------- anisotropic spacing
@pytest.mark.parametrize("axis,length", [("x", 7 * 5.0), ("y", 9 * 1.0), ("z", 11 * 0.3)])
def test_anisotropic_spacing_slab(axis: str, length: float) -> None:
    """spacing (z, y, x) = (0.3, 1, 5): the default unit is the smallest spacing, 0.3."""
    shape, spacing, origin = (11, 9, 7), (0.3, 1.0, 5.0), (2.0, -4.0, 10.0)
    vol = np.full(shape, 1.0)
    cam = axis_camera(axis, shape, spacing, origin, view_height=0.5)
    img = reference_render(vol, {"camera": cam, "width": 3, "height": 2, "tf": const_tf(0.05)}, spacing, origin)
    assert np.abs(img[..., 3] - analytic_slab_alpha(0.05, length, 0.3)).max() < 1e-11


@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
def test_anisotropic_marker_exact_pixel(projection: str) -> None:
    """spacing (0.3, 1, 5), origin (1, 2, 3): the voxel (13, 4, 5) sits at world (x, y, z) = (28, 6, 4.9).
    A camera is built so that pixel (17, 61)'s ray passes exactly through that point; with a MIP of a TF whose
    opacity equals the value, that pixel (and no other) shows the marker's full value 1."""
    spacing, origin = (0.3, 1.0, 5.0), (1.0, 2.0, 3.0)
    vol = np.zeros((20, 12, 8))
    vol[13, 4, 5] = 1.0
    p = np.array([3.0 + 5 * 5.0, 2.0 + 4 * 1.0, 1.0 + 13 * 0.3])
    W, H, pix = 96, 72, (17, 61)
    f0, up = (0.3, 1.0, -0.4), (0.0, 0.0, 1.0)
    cam = aim_at(p, pix, W, H, f0, up, 30.0, fov=35.0) if projection == "perspective" else aim_at(p, pix, W, H, f0, up, 30.0, view_height=20.0)
    tf = {"points": [{"value": 0.0, "color": [1, 1, 1], "opacity": 0.0}, {"value": 1.0, "color": [1, 1, 1], "opacity": 1.0}]}
    img = reference_render(vol, {"camera": cam, "width": W, "height": H, "tf": tf, "mode": "mip"}, spacing, origin)
    a = img[..., 3]
    assert abs(a[pix] - 1.0) < 1e-12
    others = a.copy()
    others[pix] = 0
    assert others.max() < 0.999
    assert np.allclose(predicted_pixel(cam, W, H, p), pix, atol=1e-9)


# --------------------------------------------------------------------------------------- thin volumes
def test_one_voxel_thick_volume() -> None:
    """shape (1, 6, 6), spacing z = 2: along z the chord is 2 (the box is one voxel thick, the value clamped);
    at 30° off z through the middle it is 2 / cos 30°."""
    vol = np.full((1, 6, 6), 5.0)
    spacing = (2.0, 1.0, 1.0)
    tf = const_tf(0.4, unit=1.0)
    img = reference_render(vol, {"camera": axis_camera("z", vol.shape, spacing, view_height=2.0), "width": 3, "height": 3, "tf": tf}, spacing)
    assert np.abs(img[..., 3] - analytic_slab_alpha(0.4, 2.0, 1.0)).max() < 1e-12
    th = math.radians(30)
    c = np.array([2.5, 2.5, 0.0])
    cam = {"eye": (c + 10 * np.array([-math.sin(th), 0, math.cos(th)])).tolist(), "target": c.tolist(), "up": [1, 0, 0],
           "projection": "orthographic", "view_height": 0.5}
    img = reference_render(vol, {"camera": cam, "width": 1, "height": 1, "tf": tf}, spacing)
    assert abs(img[0, 0, 3] - analytic_slab_alpha(0.4, 2.0 / math.cos(th), 1.0)) < 1e-12
    one = reference_render(np.ones((1, 1, 1)), {"camera": axis_camera("x", (1, 1, 1), view_height=0.5), "width": 1, "height": 1,
                                                "tf": const_tf(0.4, unit=1.0)})
    assert abs(one[0, 0, 3] - 0.4) < 1e-12


# ------------------------------------------------------------------------------------- near-opaque TFs
@pytest.mark.parametrize("unit", [1.0, 4.0, 0.25])
def test_near_opaque_a_0_999999(unit: float) -> None:
    vol = np.full((1, 3, 3), 1.0)
    img = reference_render(vol, {"camera": axis_camera("z", vol.shape, view_height=1.0), "width": 2, "height": 2,
                                 "tf": const_tf(0.999999, color=(0.2, 0.4, 0.6), unit=unit)})
    want = 1 - 1e-6 ** (1 / unit)
    assert np.abs(img[..., 3] - want).max() < 1e-12
    assert np.abs(img[..., :3] - want * np.array([0.2, 0.4, 0.6])).max() < 1e-12


def test_opaque_a_1_takes_the_colour_at_entry() -> None:
    """A ramp along x (0 … 1 over 11 voxels) and a TF that is clear-ish (a = 0.1, red) up to v = 0.5, rises
    to a = 1 (green) at v = 0.5 + ε and stays opaque (→ blue). The ray composites the clear part by the slab
    law, the short rise with the closed-form τ and scipy.quad for its colour, and then takes the colour where
    a reaches 1 (green) with A = 1 exactly."""
    n, eps = 11, 1e-3
    vol = np.broadcast_to(np.linspace(0.0, 1.0, n), (3, 3, n)).copy()
    GREEN = [0.0, 1.0, 0.0]
    tf = {"points": [{"value": 0.0, "color": RED, "opacity": 0.1}, {"value": 0.5, "color": RED, "opacity": 0.1},
                     {"value": 0.5 + eps, "color": GREEN, "opacity": 1.0}, {"value": 1.0, "color": BLUE, "opacity": 1.0}],
          "unit_distance": 1.0}
    img = reference_render(vol, {"camera": axis_camera("x", vol.shape, view_height=1.5), "width": 2, "height": 2, "tf": tf})
    T = 0.9**5.5  # the rim 0.5 + 5 voxels up to v = 0.5 at x = 5
    ell = eps / 0.1  # the field rises 0.1 per voxel
    tau_r = _ramp_tau(0.1, 1.0, ell, 1.0)
    sig = lambda t: -math.log1p(-(0.1 + 0.9 * t / ell))  # noqa: E731
    g, _ = integrate.quad(lambda t: (t / ell) * sig(t) * math.exp(-tau_r(t)), 0, ell, epsabs=1e-14, limit=200)
    r, _ = integrate.quad(lambda t: (1 - t / ell) * sig(t) * math.exp(-tau_r(t)), 0, ell, epsabs=1e-14, limit=200)
    Tr = math.exp(-tau_r(ell))
    want = np.array([1 - T + T * r, T * (g + Tr), 0.0, 1.0])
    assert T * (1 - Tr) > 5e-4  # the rise is resolved, not negligible
    assert np.abs(img - want).max() < 1e-7, (img[0, 0], want)
    const1 = reference_render(np.ones((3, 3, 4)), {"camera": axis_camera("x", (3, 3, 4), view_height=1.0), "width": 2, "height": 2,
                                                   "tf": const_tf(1.0, color=(0.1, 0.2, 0.3))})
    assert np.all(const1[..., 3] == 1.0) and np.allclose(const1[..., :3], [0.1, 0.2, 0.3], atol=1e-15)


# ------------------------------------------------------------------------------------------------- MIP
def test_mip_takes_tf_at_exact_maximum() -> None:
    """A single marker voxel; a ray along x at offsets (fy, fz) from it sees the trilinear field peak
    (1 − fy)(1 − fz) at the marker's x. MIP = (rgb·a, a) of the TF there, no distance correction."""
    vol = np.zeros((5, 5, 9))
    vol[2, 2, 4] = 1.0
    tf = {"points": [{"value": 0.0, "color": RED, "opacity": 0.0}, {"value": 1.0, "color": BLUE, "opacity": 0.8}], "unit_distance": 0.01}
    cam = axis_camera("x", vol.shape, view_height=5.0)
    W = H = 7
    img = reference_render(vol, {"camera": cam, "width": W, "height": H, "tf": tf, "mode": "mip"})
    pts = ortho_pixel_points(cam, W, H)
    fy, fz = np.abs(pts[..., 1] - 2), np.abs(pts[..., 2] - 2)
    peak = np.clip(1 - fy, 0, None) * np.clip(1 - fz, 0, None)
    a = 0.8 * peak
    assert peak.max() > 0.7
    assert np.abs(img[..., 3] - a).max() < 1e-12
    assert np.abs(img[..., 0] - (1 - peak) * a).max() < 1e-12 and np.abs(img[..., 2] - peak * a).max() < 1e-12


def test_mip_oblique_ray_through_cell_interior() -> None:
    """An oblique ray's peak (inside a cell or on a cell face) is found exactly: compare to a brute-force
    maximum over 200 001 points refined by 20 001 points around the best one."""
    rng = np.random.default_rng(3)
    vol = rng.random((4, 4, 4))
    tf = {"points": [{"value": 0.0, "color": RED, "opacity": 0.0}, {"value": 1.0, "color": RED, "opacity": 1.0}]}
    cam = {"eye": [-5.0, -3.0, -4.0], "target": [1.7, 1.4, 1.6], "up": [0, 0, 1], "fov": 20.0}
    img = reference_render(vol, {"camera": cam, "width": 3, "height": 3, "tf": tf, "mode": "mip"})
    o, d = camera_rays(cam, 3, 3, vol.shape)
    t = np.linspace(0, 20, 200_001)
    for i in range(3):
        for j in range(3):
            s = sample_field(vol, o[i, j] + t[:, None] * d[i, j])
            lo, hi = box_bounds(vol.shape)
            p = o[i, j] + t[:, None] * d[i, j]
            inside = np.all((p >= lo) & (p <= hi), axis=1)
            k = np.argmax(np.where(inside, s, -np.inf))
            tt = np.linspace(t[max(k - 1, 0)], t[k + 1], 20_001)
            p2 = o[i, j] + tt[:, None] * d[i, j]
            brute = np.where(np.all((p2 >= lo) & (p2 <= hi), axis=1), sample_field(vol, p2), -np.inf).max()
            assert brute - 1e-9 <= img[i, j, 3] <= brute + 1e-8


# ------------------------------------------------------------------------------------------ background
def test_background_composited_under() -> None:
    vol = np.full((3, 3, 10), 1.0)
    bg = [0.2, 0.4, 0.6, 0.5]
    img = reference_render(vol, {"camera": axis_camera("x", vol.shape, view_height=1.0), "width": 2, "height": 2,
                                 "tf": const_tf(0.1, color=(1, 0, 0), unit=1.0), "background": bg})
    A = analytic_slab_alpha(0.1, 10, 1.0)
    want = np.array([A + (1 - A) * 0.2 * 0.5, (1 - A) * 0.4 * 0.5, (1 - A) * 0.6 * 0.5, A + (1 - A) * 0.5])
    assert np.abs(img - want).max() < 1e-12


# ------------------------------------------------------------------------------------------ convergence
def test_quadrature_converged() -> None:
    """Refining the quadrature (order 8 → 12, panels ½ → ⅛ voxel, τ per panel 0.5 → 0.1) on a noisy blob
    with a three-point TF changes nothing beyond 1e-9: the defaults are converged far below 1e-5."""
    rng = np.random.default_rng(0)
    zz, yy, xx = np.mgrid[:14, :14, :14]
    vol = np.exp(-(((xx - 7) / 3.0) ** 2 + ((yy - 6) / 2.5) ** 2 + ((zz - 7) / 2.0) ** 2)) + 0.05 * rng.random((14, 14, 14))
    tf = {"points": [{"value": 0.1, "color": [0.2, 0.4, 1], "opacity": 0.0}, {"value": 0.5, "color": [1, 0.3, 0.1], "opacity": 0.4},
                     {"value": 1.0, "color": [1, 0.8, 0.2], "opacity": 0.95}]}
    scene = {"camera": {"azimuth": 30, "elevation": 20, "distance": 2.5}, "width": 12, "height": 12, "tf": tf}
    a = reference_render(vol, scene)
    b = reference_render(vol, scene, order=12, max_panel=0.125, tau_max=0.1)
    assert a[..., 3].max() > 0.5
    assert np.abs(a - b).max() < 1e-9


# ------------------------------------------------------------------------------------------------- ΔE
def test_delta_e_definition() -> None:
    black = np.zeros((2, 2, 4))
    white = np.ones((2, 2, 4))
    d = delta_e(black, white)
    assert d["footprint"] == 4 and d["mean"] == pytest.approx(100.0, abs=0.01) and d["max"] == pytest.approx(100.0, abs=0.01)
    assert delta_e(white, white)["max"] == 0.0
    faint = np.zeros((1, 2, 4))
    faint[0, 0] = [0.5 / 255, 0, 0, 0.5 / 255]  # below the footprint threshold in both images
    faint[0, 1] = [0.0, 0.0, 0.0, 1.0 / 255]
    assert delta_e(faint, np.zeros((1, 2, 4)))["footprint"] == 1
    # premultiplied rgb over black is the rgb: a mid grey of 50 % alpha vs itself straight is not equal
    grey = np.full((1, 1, 4), 0.5)
    assert delta_e(grey, np.array([[[1.0, 1.0, 1.0, 0.5]]]))["max"] > 20


def test_the_default_orbit_distance_agrees_with_the_reference_bisection() -> None:
    """Without a distance, lodcast's closed form (camera.fit_distance) and the reference's bisection put the eye at
    the same place."""
    from lodcast.renderer.scene.camera import box_world, frame
    from lodcast.renderer.scene.scene import OrbitCamera

    rng = np.random.default_rng(9)
    for _ in range(20):
        shape = tuple(int(s) for s in rng.integers(4, 200, 3))
        spacing = tuple(float(s) for s in rng.uniform(0.3, 3.0, 3))
        az, el, fov = float(rng.uniform(-180, 180)), float(rng.uniform(-80, 80)), float(rng.uniform(15, 60))
        w, h = int(rng.integers(32, 800)), int(rng.integers(32, 800))
        ref = orbit_to_lookat({"azimuth": az, "elevation": el, "fov": fov}, shape, spacing, aspect=w / h)
        lo, hi = box_world(shape, spacing, (0.0, 0.0, 0.0))
        fr = frame(OrbitCamera(azimuth=az, elevation=el, fov=fov), w, h, lo, hi)
        radius = 0.5 * float(np.linalg.norm(np.asarray(hi) - np.asarray(lo)))
        np.testing.assert_allclose(fr.eye, ref["eye"], atol=1e-6 * radius)
