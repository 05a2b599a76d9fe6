"""The OpenCL ray caster against analytic answers and the independent float64 reference (issue 4's
"Numerical cases").

Every render goes through the public path: a float32 .npy file → `lodcast.ingest` → `lodcast.open_store` →
`lodcast.render(store, scene)` with `"quality": "full", "format": "npy"`; the float32 premultiplied RGBA is
compared in float64.

Tolerances. The contract is max abs error ≤ 2e-3 on premultiplied RGBA against the float64 reference
(`TOL`). Constant regions are integrated exactly by the kernel's opacity correction at any step, so
constant-field cases are held to `TOL` at every step, even 10 voxels. For non-constant fields a fixed-step
sum differs from the integral by a step-dependent amount, so those cases compare against the *continuous*
reference at a small step (1/8 voxel or less; the kernel's error there is ~1e-4, second order in the step),
and the step-invariance test states its ΔE bound per step. Where a test needs a looser bound (NaN boundaries,
MIP, entering an opaque interval, early termination), the docstring derives it.

Unless a test is about early termination, scenes set `early_termination: 1.0` so that the integral is
compared unaltered (the default 0.99 may legitimately change a pixel by up to 0.01, see the ET test).
"""
from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from reference import analytic_slab_alpha, delta_e, orbit_to_lookat, reference_render
from scenes import aim_at, axis_camera, centroid, const_tf, predicted_pixel

import lodcast

TOL = 2e-3  # docs/design.md, issue 4: float32 kernel vs float64 reference, max abs error on premultiplied RGBA
STEPS = (0.125, 0.25, 0.5, 1.0, 2.0)  # "from 1/8 to 2 voxels"

RED, BLUE, GREEN = [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]


# ------------------------------------------------------------------------------------------------ helpers
@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Callable[..., Any]:
    """make(name, volume, spacing=None, origin=None, block_size=None) → opened store (cached per module)."""
    root = tmp_path_factory.mktemp("numerics")
    cache: dict[str, Any] = {}

    def make(name: str, vol: np.ndarray, spacing=None, origin=None, block_size: int | None = None) -> Any:
        if name not in cache:
            src = root / f"{name}.npy"
            np.save(src, np.ascontiguousarray(vol, dtype=np.float32))
            kw: dict[str, Any] = {}
            if spacing is not None:
                kw["spacing"] = tuple(spacing)
            if origin is not None:
                kw["origin"] = tuple(origin)
            if block_size is not None:
                kw["block_size"] = block_size
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                lodcast.ingest(str(src), str(root / f"{name}.zarr"), progress=False, **kw)
            st = lodcast.open_store(str(root / f"{name}.zarr"))
            if spacing is not None:
                assert tuple(st.spacing) == tuple(float(s) for s in spacing)
            cache[name] = st
        return cache[name]

    return make


def kernel(st: Any, scene: dict, step: float = 0.5, **sampling: Any) -> tuple[np.ndarray, dict]:
    """Render through lodcast.render; returns (float64 H×W×4 premultiplied RGBA, report)."""
    samp = {"step": step, "early_termination": 1.0, **sampling}
    full = {**scene, "quality": "full", "format": "npy", "sampling": samp}
    res = lodcast.render(st, full)
    img = np.asarray(res.rgba)
    assert img.dtype == np.float32 and img.shape == (scene["height"], scene["width"], 4)
    assert np.isfinite(img).all(), "NaN/inf in the image"
    assert img.min() >= -1e-6 and img.max() <= 1 + 1e-5
    return img.astype(np.float64), res.report


def blob(shape=(20, 24, 28), centre=(15.0, 11.0, 10.0), radii=(6.0, 5.0, 4.0)) -> np.ndarray:
    zz, yy, xx = np.mgrid[: shape[0], : shape[1], : shape[2]].astype(float)
    (cx, cy, cz), (rx, ry, rz) = centre, radii
    return np.exp(-(((xx - cx) / rx) ** 2 + ((yy - cy) / ry) ** 2 + ((zz - cz) / rz) ** 2)).astype(np.float32)


BLOB_TF = {"points": [{"value": 0.1, "color": [0.2, 0.4, 1.0], "opacity": 0.0}, {"value": 0.6, "color": [1.0, 0.3, 0.1], "opacity": 0.3},
                      {"value": 1.0, "color": [1.0, 0.9, 0.2], "opacity": 0.8}]}
BLOB_SCENE = {"camera": {"azimuth": 30, "elevation": 20, "distance": 2.0, "fov": 30}, "width": 32, "height": 24, "tf": BLOB_TF}


@pytest.fixture(scope="module")
def blob_ref() -> np.ndarray:
    return reference_render(blob(), BLOB_SCENE)


# ------------------------------------------------------------------------------------------ constant slab
@pytest.mark.parametrize("step", STEPS)
@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_constant_slab_any_step(store, axis: str, step: float) -> None:
    """docs/design.md: crossing L of constant value gives 1 − (1 − a)^(L/unit) whatever the step; rgb = c·A.
    13, 9 and 6 voxels are not multiples of 2 voxels, so a mishandled partial last step shows (at step 2
    it would be off by ≥ 0.02)."""
    shape = (6, 9, 13)
    st = store("slab", np.full(shape, 3.0))
    scene = {"camera": axis_camera(axis, shape), "width": 4, "height": 3, "tf": const_tf(0.3, unit=1.0, lo=-10.0, hi=10.0)}
    img, _ = kernel(st, scene, step)
    want = analytic_slab_alpha(0.3, {"x": 13, "y": 9, "z": 6}[axis], 1.0)
    assert np.abs(img[..., 3] - want).max() <= TOL
    assert np.abs(img[..., :3] - want * np.array([0.8, 0.5, 0.2])).max() <= TOL


@pytest.mark.parametrize("step", (*STEPS, 10.0))
def test_constant_volume_oblique_perspective(store, step: float) -> None:
    """A constant volume seen obliquely in perspective: every ray's chord differs, the reference (exact
    for constant fields) gives 1 − (1 − a)^(chord/unit); default unit (smallest spacing) with spacing
    (1, 1, 1), and a value outside the TF's control points (constant extrapolation)."""
    vol = np.full((10, 12, 14), 7.0)
    st = store("const", vol)
    tf = {"points": [{"value": 0.0, "color": RED, "opacity": 0.0}, {"value": 5.0, "color": [0.3, 0.6, 0.9], "opacity": 0.15}]}
    scene = {"camera": {"eye": [-12.0, -20.0, 18.0], "target": [6.5, 5.5, 4.5], "up": [0, 0, 1], "fov": 40.0}, "width": 24, "height": 18, "tf": tf}
    img, _ = kernel(st, scene, step)
    ref = reference_render(vol, scene)
    assert ref[..., 3].max() > 0.8 and (ref[..., 3] == 0).sum() > 20  # some rays miss, some cross a lot
    assert np.abs(img - ref).max() <= TOL


def test_constant_volume_transparent_tf_is_empty(store) -> None:
    """A TF with zero opacity at the volume's only value: nothing at all, and no brick is sampled."""
    st = store("const", np.full((10, 12, 14), 7.0))
    tf = {"points": [{"value": 6.0, "color": RED, "opacity": 0.0}, {"value": 8.0, "color": RED, "opacity": 0.0}, {"value": 9.0, "color": RED, "opacity": 0.5}]}
    img, rep = kernel(st, {"camera": {"azimuth": 20, "elevation": 10, "distance": 2.0}, "width": 12, "height": 10, "tf": tf}, 0.5,
                      empty_space_skipping=True)
    assert np.all(img == 0.0)


# -------------------------------------------------------------------------------------------- linear ramp
@pytest.mark.parametrize("view", ["axis", "oblique"])
def test_linear_ramp(store, view: str) -> None:
    """Values rising linearly along x with a TF linear in colour and opacity (the reference's closed form
    is checked in test_reference.py). Compared at step 1/8 voxel with the continuous reference: TOL."""
    n = 16
    vol = np.broadcast_to(np.linspace(100.0, 400.0, n), (6, 7, n)).astype(np.float32)
    st = store("ramp", vol)
    tf = {"points": [{"value": 100.0, "color": RED, "opacity": 0.02}, {"value": 400.0, "color": BLUE, "opacity": 0.6}], "unit_distance": 1.0}
    if view == "axis":
        scene = {"camera": axis_camera("x", vol.shape, view_height=2.0), "width": 4, "height": 4, "tf": tf}
    else:
        scene = {"camera": {"eye": [-10.0, -9.0, 8.0], "target": [7.5, 3.0, 2.5], "up": [0, 0, 1], "fov": 35.0}, "width": 20, "height": 16, "tf": tf}
    img, _ = kernel(st, scene, 0.125)
    ref = reference_render(vol, scene)
    assert ref[..., 3].max() > 0.5
    assert np.abs(img - ref).max() <= TOL


# ------------------------------------------------------------------------------------------------- sphere
def test_sphere(store) -> None:
    """Voxel values = distance to a centre (off the lattice), TF opaque inside radius 8 with a soft edge,
    perspective: the kernel at step 1/8 against the reference (whose chords test_reference.py checks
    analytically), TOL."""
    n = 24
    ctr = np.array([11.3, 11.6, 11.5])
    zz, yy, xx = np.mgrid[:n, :n, :n].astype(float)
    vol = np.sqrt((xx - ctr[0]) ** 2 + (yy - ctr[1]) ** 2 + (zz - ctr[2]) ** 2).astype(np.float32)
    st = store("sphere", vol)
    tf = {"points": [{"value": 7.0, "color": [0.3, 0.6, 0.9], "opacity": 0.12}, {"value": 9.0, "color": [0.9, 0.6, 0.3], "opacity": 0.0}], "unit_distance": 1.0}
    scene = {"camera": {"eye": [-20.0, -30.0, 25.0], "target": ctr.tolist(), "up": [0, 0, 1], "fov": 35.0}, "width": 24, "height": 24, "tf": tf}
    img, _ = kernel(st, scene, 0.125)
    ref = reference_render(vol, scene)
    assert ref[..., 3].max() > 0.8 and (ref[..., 3] == 0).sum() > 50
    assert np.abs(img - ref).max() <= TOL


# ------------------------------------------------------------------------------------------ step invariance
@pytest.mark.parametrize("step", STEPS)
def test_step_invariance_delta_e(store, blob_ref: np.ndarray, step: float) -> None:
    """The image of a smooth blob under steps 1/8 … 2 voxels against the converged integral (docs/design.md's
    scene reference is step ≤ ¼ voxel; ours is the limit). Stated bound: mean ΔE ≤ 0.4·step² + 0.02 and
    p95 ≤ 1.5·step² + 0.05 (the fixed-step sum is second order; at 2 voxels that is mean ≤ 1.6, about one
    just-noticeable difference), and at step ≤ ¼ voxel the RGBA is within TOL. An opacity that were not
    corrected for the step would be off by tens of ΔE at step 2 and 1/8."""
    st = store("blob", blob())
    img, _ = kernel(st, BLOB_SCENE, step)
    de = delta_e(img, blob_ref)
    assert de["footprint"] > 100
    assert de["mean"] <= 0.4 * step**2 + 0.02, de
    assert de["p95"] <= 1.5 * step**2 + 0.05, de
    if step <= 0.25:
        assert np.abs(img - blob_ref).max() <= TOL


def test_orbit_equals_lookat(store) -> None:
    """The orbit camera renders exactly like the look-at camera it stands for (float noise only)."""
    st = store("blob", blob())
    look = orbit_to_lookat(BLOB_SCENE["camera"], blob().shape)
    a, _ = kernel(st, BLOB_SCENE, 0.5)
    b, _ = kernel(st, {**BLOB_SCENE, "camera": look}, 0.5)
    assert a[..., 3].max() > 0.3
    assert np.abs(a - b).max() <= 1e-4


# --------------------------------------------------------------------------------------------- marker voxel
MARKER_TF = {"points": [{"value": 0.0, "color": [1, 1, 1], "opacity": 0.0}, {"value": 0.05, "color": [1, 1, 1], "opacity": 1.0},
                        {"value": 1.0, "color": [1, 1, 1], "opacity": 1.0}]}


@pytest.mark.parametrize("form", ["lookat", "orbit"])
@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
def test_marker_voxel_on_predicted_pixel(store, form: str, projection: str) -> None:
    """A single marker voxel, non-square image: the alpha-weighted centroid of its footprint lies within
    0.25 px of the pixel docs/design.md's camera formula predicts (the footprint is a few pixels wide; a flipped
    axis, a wrong aspect or a half-pixel shift would move it by ≥ 0.5 px)."""
    vol = np.zeros((16, 24, 32), np.float32)
    vol[5, 14, 20] = 1.0
    p = np.array([20.0, 14.0, 5.0])
    st = store("marker", vol)
    W, H = 64, 40
    if form == "orbit":
        cam: dict = {"azimuth": 25, "elevation": 15, "distance": 2.0, "fov": 30}
    else:
        cam = {"eye": [-30.0, -45.0, 25.0], "target": [15.5, 11.5, 7.5], "up": [0.0, 0.0, 1.0], "fov": 30.0}
    if projection == "orthographic":
        cam.update(projection="orthographic", view_height=24.0)
    look = orbit_to_lookat(cam, vol.shape) if form == "orbit" else cam
    img, _ = kernel(st, {"camera": cam, "width": W, "height": H, "tf": MARKER_TF}, 0.125)
    i, j = predicted_pixel(look, W, H, p)
    assert img[..., 3].max() > 0.5
    ci, cj = centroid(img[..., 3])
    assert abs(ci - i) < 0.25 and abs(cj - j) < 0.25, ((ci, cj), (i, j))


@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
def test_marker_exact_pixel_anisotropic_mip(store, projection: str) -> None:
    """Spacing (0.3, 1, 5), origin (1, 2, 3): voxel (13, 4, 5) is at world (28, 6, 4.9). A camera is built so
    that pixel (17, 61)'s ray passes exactly through it; MIP with opacity = value. That pixel must be the
    brightest and reach 1 − L·Δ (L = the field's largest slope along the ray per world unit ≤ 1/0.3 + 1 + 1/5,
    Δ = step/64·0.3 world: the largest sample misses the peak by at most Δ)."""
    spacing, origin = (0.3, 1.0, 5.0), (1.0, 2.0, 3.0)
    vol = np.zeros((20, 12, 8), np.float32)
    vol[13, 4, 5] = 1.0
    p = np.array([28.0, 6.0, 4.9])
    st = store("marker_aniso", vol, spacing, origin)
    W, H, pix = 96, 72, (17, 61)
    f0, up = (0.3, 1.0, -0.4), (0.0, 0.0, 1.0)
    cam = aim_at(p, pix, W, H, f0, up, 30.0, fov=35.0) if projection == "perspective" else aim_at(p, pix, W, H, f0, up, 30.0, view_height=20.0)
    tf = {"points": [{"value": 0.0, "color": [1, 1, 1], "opacity": 0.0}, {"value": 1.0, "color": [1, 1, 1], "opacity": 1.0}]}
    step = 1 / 64
    img, _ = kernel(st, {"camera": cam, "width": W, "height": H, "tf": tf, "mode": "mip"}, step)
    a = img[..., 3]
    slope = 1 / 0.3 + 1 / 1.0 + 1 / 5.0
    assert a[pix] >= 1 - slope * step * 0.3 - 1e-6, a[pix]
    assert np.unravel_index(np.argmax(a), a.shape) == pix


# ------------------------------------------------------------------------------------------- near-opaque
@pytest.mark.parametrize("step", (1e-3, 0.125, 1.0, 10.0))
@pytest.mark.parametrize("unit", [1.0, 4.0])
def test_near_opaque_thin_layer(store, step: float, unit: float) -> None:
    """a = 0.999999 through one voxel (a 1-voxel-thick volume seen face on): A = 1 − 1e-6^(1/unit) — with
    unit 4 that is 0.968377, far from saturation, so a naive pow(1 − a, Δ/unit) in float32 (1 − a rounds to
    1.0000000e-6 ± 6e-8 relative…) or a clamp would show. rgb = c·A."""
    vol = np.full((1, 6, 6), 1.0)
    st = store("thin", vol)
    scene = {"camera": axis_camera("z", vol.shape, view_height=2.0), "width": 3, "height": 3, "tf": const_tf(0.999999, (0.2, 0.4, 0.6), unit, lo=-10.0, hi=10.0)}
    img, _ = kernel(st, scene, step)
    want = 1 - (1 - 0.999999) ** (1 / unit)
    assert np.abs(img[..., 3] - want).max() <= TOL
    assert np.abs(img[..., :3] - want * np.array([0.2, 0.4, 0.6])).max() <= TOL


@pytest.mark.parametrize("a", [0.999999, 1.0])
@pytest.mark.parametrize("step", (1e-3, 0.125, 2.0))
def test_near_opaque_slab(store, a: float, step: float) -> None:
    """Through 13 voxels a = 0.999999 and a = 1 are opaque: A = 1 and rgb = c (within TOL), finite."""
    shape = (6, 9, 13)
    st = store("slab", np.full(shape, 3.0))
    img, _ = kernel(st, {"camera": axis_camera("x", shape), "width": 3, "height": 3, "tf": const_tf(a, (0.1, 0.7, 0.4), lo=-10.0, hi=10.0)}, step)
    assert np.abs(img[..., 3] - 1.0).max() <= TOL
    assert np.abs(img[..., :3] - np.array([0.1, 0.7, 0.4])).max() <= TOL


@pytest.mark.parametrize("step", (1 / 64, 0.125))
def test_opaque_interval_takes_colour_at_entry(store, step: float) -> None:
    """A ramp 0 … 1 over 11 voxels; TF a = 0.1 (red) up to 0.5, rising to a = 1 (green) at 0.5 + 1e-3 and
    staying opaque (→ blue). The reference takes the colour where a reaches 1 (green, A = 1). The kernel
    becomes opaque at its first sample past that point, up to Δ later, where the colour has moved towards
    blue by at most Δ·0.1/(0.5 − 1e-3) per voxel, and the clear part it composited may be off by Δ·σ:
    bound TOL + Δ·(0.2 + 0.11)."""
    n = 11
    vol = np.broadcast_to(np.linspace(0.0, 1.0, n), (3, 3, n)).astype(np.float32)
    st = store("ramp01", vol)
    tf = {"points": [{"value": 0.0, "color": RED, "opacity": 0.1}, {"value": 0.5, "color": RED, "opacity": 0.1},
                     {"value": 0.501, "color": GREEN, "opacity": 1.0}, {"value": 1.0, "color": BLUE, "opacity": 1.0}], "unit_distance": 1.0}
    scene = {"camera": axis_camera("x", vol.shape, view_height=1.5), "width": 2, "height": 2, "tf": tf}
    img, _ = kernel(st, scene, step)
    ref = reference_render(vol, scene)
    assert np.all(img[..., 3] >= 1 - 1e-6)
    assert np.abs(img - ref).max() <= TOL + step * 0.31, (img[0, 0], ref[0, 0])


# ------------------------------------------------------------------------------------------ tiny and huge
def test_tiny_step(store) -> None:
    """Step 1e-4 voxel (130 000 samples per ray) on a 2×2 image: the float32 accumulation over that many
    tiny opacities must still give the slab law, and the ramp must match the continuous reference."""
    shape = (6, 9, 13)
    st = store("slab", np.full(shape, 3.0))
    img, rep = kernel(st, {"camera": axis_camera("x", shape), "width": 2, "height": 2, "tf": const_tf(0.3, unit=1.0, lo=-10.0, hi=10.0)}, 1e-4)
    want = analytic_slab_alpha(0.3, 13, 1.0)
    assert np.abs(img[..., 3] - want).max() <= TOL
    assert rep["samples"] >= 4 * 13 / 1e-4 * 0.99
    n = 16
    vol = np.broadcast_to(np.linspace(100.0, 400.0, n), (6, 7, n)).astype(np.float32)
    tf = {"points": [{"value": 100.0, "color": RED, "opacity": 0.02}, {"value": 400.0, "color": BLUE, "opacity": 0.6}], "unit_distance": 1.0}
    scene = {"camera": axis_camera("x", vol.shape, view_height=2.0), "width": 2, "height": 2, "tf": tf}
    img, _ = kernel(store("ramp", vol), scene, 1e-4)
    assert np.abs(img - reference_render(vol, scene)).max() <= TOL


def test_huge_step(store) -> None:
    """Step 10 voxels: longer than the 6- and 9-voxel slabs and the 1-voxel layer. Constant regions are
    still exact (the partial step carries its own length), and a blob stays a bounded, finite image."""
    shape = (6, 9, 13)
    st = store("slab", np.full(shape, 3.0))
    for axis, L in (("x", 13), ("y", 9), ("z", 6)):
        img, _ = kernel(st, {"camera": axis_camera(axis, shape), "width": 3, "height": 2, "tf": const_tf(0.3, unit=1.0, lo=-10.0, hi=10.0)}, 10.0)
        assert np.abs(img[..., 3] - analytic_slab_alpha(0.3, L, 1.0)).max() <= TOL, axis
    img, _ = kernel(store("blob", blob()), BLOB_SCENE, 10.0)
    assert img[..., 3].max() > 0.05


# ------------------------------------------------------------------------------------------------- NaN
@pytest.mark.parametrize("nan_x,clear", [(6, 2.0), (19, 1.5), (18, 2.0), (0, 1.5)])
def test_nan_plane(store, nan_x: int, clear: float) -> None:
    """A plane of NaN voxels at x = k: every sample whose trilinear stencil reads it is transparent, i.e.
    x ∈ (k − 1, k + 1), plus the half-voxel rim when k is the edge voxel (a rim sample reads only the edge
    voxel, so k = n − 2 does not reach it). A = 1 − (1 − a)^((20 − clear)/unit). The kernel resolves the
    NaN boundaries only to its step: bound TOL + 2·Δ·σ with σ = −ln(1 − a)/unit."""
    n, a, step = 20, 0.1, 1 / 64
    vol = np.full((4, 4, n), 2.0)
    vol[:, :, nan_x] = np.nan
    st = store(f"nanplane{nan_x}", vol)
    img, _ = kernel(st, {"camera": axis_camera("x", vol.shape, view_height=2.0), "width": 3, "height": 3, "tf": const_tf(a, unit=1.0, lo=-10.0, hi=10.0)}, step)
    bound = TOL + 2 * step * -math.log1p(-a)
    assert np.abs(img[..., 3] - analytic_slab_alpha(a, n - clear, 1.0)).max() <= bound


def test_nan_voxels_in_blob(store) -> None:
    """A block of NaN voxels inside the blob: finite image, equal to the reference within TOL + 2·Δ·σ_max
    (each ray enters and leaves the convex NaN-touched region once; at step 1/128 the bound is 0.027, the
    kernel measured 2.5e-3 at step 1/32 and 0.014 at 1/8: the boundary error is first order)."""
    vol = blob()
    vol[8:11, 9:16, 10:20] = np.nan
    st = store("nanblob", vol)
    step = 1 / 128
    img, _ = kernel(st, BLOB_SCENE, step)
    ref = reference_render(vol, BLOB_SCENE)
    sigma_max = -math.log1p(-0.8)  # unit = 1 voxel
    assert np.abs(img - ref).max() <= TOL + 2 * step * sigma_max
    # the hole is visible: the NaN-free blob differs from this image by far more than the bound
    assert np.abs(ref - reference_render(blob(), BLOB_SCENE)).max() > 0.05


# ------------------------------------------------------------------------------------- 1-voxel-thick volume
@pytest.mark.parametrize("step", (0.125, 1.0, 10.0))
def test_one_voxel_thick_volume(store, step: float) -> None:
    """shape (1, 6, 6), spacing z = 2, unit 1: face on the chord is 2 (A = 1 − 0.6²); at 30° off z through
    the middle it is 2 / cos 30°. Step in voxels of the finest level = multiples of 1 (the smallest
    spacing)."""
    vol = np.full((1, 6, 6), 5.0)
    spacing = (2.0, 1.0, 1.0)
    st = store("thin2", vol, spacing)
    tf = const_tf(0.4, unit=1.0, lo=-10.0, hi=10.0)
    img, _ = kernel(st, {"camera": axis_camera("z", vol.shape, spacing, view_height=2.0), "width": 3, "height": 3, "tf": tf}, step)
    assert np.abs(img[..., 3] - analytic_slab_alpha(0.4, 2.0, 1.0)).max() <= TOL
    th = math.radians(30)
    c = np.array([2.5, 2.5, 0.0])
    cam = {"eye": (c + 10 * np.array([-math.sin(th), 0, math.cos(th)])).tolist(), "target": c.tolist(), "up": [1, 0, 0],
           "projection": "orthographic", "view_height": 0.5}
    img, _ = kernel(st, {"camera": cam, "width": 1, "height": 1, "tf": tf}, step)
    assert abs(img[0, 0, 3] - analytic_slab_alpha(0.4, 2.0 / math.cos(th), 1.0)) <= TOL


# ------------------------------------------------------------------------------------- anisotropic spacing
@pytest.mark.parametrize("step", (0.125, 1.0, 2.0))
@pytest.mark.parametrize("axis,length", [("x", 7 * 5.0), ("y", 9 * 1.0), ("z", 11 * 0.3)])
def test_anisotropic_slab(store, axis: str, length: float, step: float) -> None:
    """spacing (z, y, x) = (0.3, 1, 5): default unit = 0.3; A = 1 − (1 − a)^(L/0.3) along each axis."""
    shape, spacing, origin = (11, 9, 7), (0.3, 1.0, 5.0), (2.0, -4.0, 10.0)
    st = store("aniso_const", np.full(shape, 1.0), spacing, origin)
    img, _ = kernel(st, {"camera": axis_camera(axis, shape, spacing, origin, view_height=0.5), "width": 3, "height": 2,
                         "tf": const_tf(0.05, lo=-10.0, hi=10.0)}, step)
    assert np.abs(img[..., 3] - analytic_slab_alpha(0.05, length, 0.3)).max() <= TOL


def test_anisotropic_blob(store) -> None:
    """The blob with spacing (0.3, 1, 5) and an origin, orbit camera, step 1/8 (of 0.3): reference, TOL."""
    spacing, origin = (0.3, 1.0, 5.0), (-1.0, 4.0, 2.0)
    st = store("blob_aniso", blob(), spacing, origin)
    img, _ = kernel(st, BLOB_SCENE, 0.125)
    ref = reference_render(blob(), BLOB_SCENE, spacing, origin)
    assert ref[..., 3].max() > 0.5
    assert np.abs(img - ref).max() <= TOL


# ------------------------------------------------------------------------------------------ MIP, background
def test_mip_against_reference(store) -> None:
    """MIP takes the TF at the largest sample. A fixed step misses the continuous maximum by at most
    Δ·max|ds/dt| ≤ Δ·√3·max|Δv| (the trilinear gradient's components are bounded by the largest voxel
    difference per axis), which moves a by at most 1.25× that (opacity slope 1/0.8) and rgb·a by at most
    |c'|·a + |c|·|a'| ≤ 1 + 1.25 = 2.25× that: bound TOL + 2.25·√3·Δ·max|Δv|."""
    vol = blob()
    st = store("blob", vol)
    tf = {"points": [{"value": 0.2, "color": [0.2, 0.4, 1.0], "opacity": 0.0}, {"value": 1.0, "color": [1.0, 0.9, 0.2], "opacity": 1.0}]}
    scene = {**BLOB_SCENE, "tf": tf, "mode": "mip"}
    step = 1 / 64  # bound 0.0147; a distance-corrected or straight (not premultiplied) MIP is off by > 0.1
    img, _ = kernel(st, scene, step)
    ref = reference_render(vol, scene)
    dv = max(float(np.abs(np.diff(vol.astype(float), axis=k)).max()) for k in range(3))
    assert ref[..., 3].max() > 0.8
    assert np.abs(img - ref).max() <= TOL + 2.25 * math.sqrt(3) * step * dv


def test_background_composited_under(store, blob_ref: np.ndarray) -> None:
    """rgb = C + (1 − A)·bg_rgb·bg_α, α = A + (1 − A)·bg_α (premultiplied), against the reference."""
    bg = [0.2, 0.5, 0.3, 0.6]
    img, _ = kernel(store("blob", blob()), {**BLOB_SCENE, "background": bg}, 0.125)
    ref = reference_render(blob(), {**BLOB_SCENE, "background": bg})
    assert np.abs(img - ref).max() <= TOL
    assert np.abs(img[0, 0] - [0.2 * 0.6, 0.5 * 0.6, 0.3 * 0.6, 0.6]).max() <= 1e-6  # a corner ray misses the volume


# ------------------------------------------------------------------------------------ ESS and early termination
SPARSE_TF = {"points": [{"value": 0.3, "color": [0.2, 0.4, 1.0], "opacity": 0.0}, {"value": 1.0, "color": [1.0, 0.9, 0.2], "opacity": 0.9}]}
SPARSE_SCENE = {"camera": {"azimuth": 30, "elevation": 20, "distance": 2.0, "fov": 30}, "width": 32, "height": 32, "tf": SPARSE_TF}


def _sparse(store):
    return store("sparse", blob((40, 40, 40), (26.0, 16.0, 20.0), (5.0, 4.0, 6.0)), block_size=8)


@pytest.mark.parametrize("step", (0.25, 1.0))
def test_empty_space_skipping_changes_nothing(store, step: float) -> None:
    """Blocks whose TF opacity is zero over their border-inclusive [min, max] are skipped without sampling;
    the image must not change beyond float noise (1e-6) — skipping whole steps keeps the sample lattice —
    while the sample count drops and bricks are reported skipped."""
    st = _sparse(store)
    on, rep_on = kernel(st, SPARSE_SCENE, step, empty_space_skipping=True)
    off, rep_off = kernel(st, SPARSE_SCENE, step, empty_space_skipping=False)
    assert on[..., 3].max() > 0.5
    assert np.abs(on - off).max() <= 1e-6
    assert rep_on["bricks_skipped"] > 0 and rep_on["samples"] < 0.5 * rep_off["samples"]


@pytest.mark.parametrize("t", [0.5, 0.9, 0.99])
def test_early_termination_bound(store, t: float) -> None:
    """With threshold t the ray stops after the first sample at which A_k ≥ t and gives what is left of it,
    T_k = 1 − A_k ≤ 1 − t, that sample's colour c (renderer/kernel/lc_classify.h, LC_BLEND). The exact rest is
    T_k·(C_rest, A_rest) with 0 ≤ C_rest ≤ A_rest ≤ 1, so per pixel the terminated alpha is exactly 1,
    0 ≤ A_ET − A_full ≤ 1 − t and |Δrgb| ≤ T_k ≤ 1 − t; pixels whose full alpha stays below t do not change
    at all. Float noise allowance 1e-6. The sample count must drop. (t is the threshold the kernel takes:
    params.early_stop moves the scene's closer to 1 for a TF of widely differing colours.)"""
    from lodcast.renderer.kernel.params import early_stop
    from lodcast.renderer.scene.scene import Scene

    st = _sparse(store)
    full, rep_full = kernel(st, SPARSE_SCENE, 0.25, early_termination=1.0)
    et, rep_et = kernel(st, SPARSE_SCENE, 0.25, early_termination=t)
    t = early_stop(Scene.parse({**SPARSE_SCENE, "sampling": {"early_termination": t}}))
    dA = et[..., 3] - full[..., 3]
    drgb = full[..., :3] - et[..., :3]
    eps = 1e-6
    assert full[..., 3].max() > 0.995
    stopped = et[..., 3] >= t
    assert stopped.any() and np.all(np.abs(et[..., 3][stopped] - 1.0) <= eps)
    assert dA.min() >= -eps and dA.max() <= 1 - t + eps
    assert np.abs(drgb).max() <= 1 - t + eps
    below = full[..., 3] < t - 1e-4
    assert np.abs(full[below] - et[below]).max() <= eps
    assert rep_et["samples"] < rep_full["samples"]


def test_default_early_termination_within_its_bound(store, blob_ref: np.ndarray) -> None:
    """The default threshold 0.99 keeps the image within 0.01 + TOL of the integral (see the bound above)."""
    img, _ = kernel(store("blob", blob()), BLOB_SCENE, 0.125, early_termination=0.99)
    assert np.abs(img - blob_ref).max() <= 0.01 + TOL


# -------------------------------------------------------------------------------------------------- jitter
def test_jitter_reproducible_and_exact_on_constant_regions(store, blob_ref: np.ndarray) -> None:
    """A jittered ray start is seeded: the same seed gives the same image bit for bit, another seed a
    different one (so jitter acts). Shifting the sample lattice cannot change a constant region's integral
    (slab law within TOL at steps ½ and 2), and at step ¼ the jittered blob stays within TOL of the integral."""
    shape = (6, 9, 13)
    st = store("slab", np.full(shape, 3.0))
    for step in (0.5, 2.0):
        img, _ = kernel(st, {"camera": axis_camera("x", shape), "width": 4, "height": 3, "tf": const_tf(0.3, unit=1.0, lo=-10.0, hi=10.0)}, step, jitter=True, seed=7)
        assert np.abs(img[..., 3] - analytic_slab_alpha(0.3, 13, 1.0)).max() <= TOL
    sb = store("blob", blob())
    a, _ = kernel(sb, BLOB_SCENE, 0.25, jitter=True, seed=3)
    b, _ = kernel(sb, BLOB_SCENE, 0.25, jitter=True, seed=3)
    c, _ = kernel(sb, BLOB_SCENE, 0.25, jitter=True, seed=4)
    assert np.array_equal(a, b)
    assert np.abs(a - c).max() > 1e-6
    assert np.abs(a - blob_ref).max() <= TOL
