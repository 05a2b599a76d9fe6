"""Classification by distribution (format-2 stores): the per-voxel standard deviations ingest stores against a
float64 reference, the Gaussian table (renderer/lod/classification.py) against float64 quadrature and its bilinear
lookup against the exact expectation, the atlas sampler's interpolated std, and renders whose answer is known:
a constant volume, a volume of uniform (mean, std) at every coarse level, a one-voxel opaque slab whose optical
depth the distribution keeps and the mean loses, and format-1 stores, which render by mean and say so.

Everything "exact" here is computed from the definitions, independently of the implementation: the expectation
of a piecewise-linear function under a Gaussian by dense Gauss-Legendre quadrature, or in closed form as a sum of
ramps (E[(v - x)_+] = s phi((m - x)/s) + (m - x) Phi((m - x)/s)), the two cross-checked below.
"""
from __future__ import annotations

import itertools
import math
import shutil
import warnings
import zlib
from pathlib import Path

import lod_reference as ref
import numpy as np
import pytest
import zarr
from scenes import axis_camera
from scipy.special import ndtr

import lodcast
from lodcast.renderer.data.volume import VolumeView
from lodcast.renderer.frame.render import Renderer, render
from lodcast.renderer.lod import classification
from lodcast.renderer.lod.classification import EXT_CAP, dist_table
from lodcast.renderer.lod.significance import srgb_to_luv
from lodcast.renderer.scene.scene import TransferFunction
from lodcast.renderer.scene.transfer_function import CT_PRESETS, Lut, build_lut
from lodcast.store.store import FORMAT_VERSION


# ------------------------------------------------------------------------------------------- float64 helpers
def point_channels(lut) -> np.ndarray:
    """(4, n): sigma_t = min(-log(1 - a), EXT_CAP) at the LUT entries and sigma_t * rgb, written from the definition
    (a = 1 has infinite extinction, capped)."""
    a = np.asarray(lut.opacity, np.float64)
    with np.errstate(divide="ignore"):
        sig = np.minimum(-np.log1p(-np.minimum(a, 1.0)), EXT_CAP)
    return np.vstack([sig, sig * np.asarray(lut.rgb, np.float64).T])


_GL_X, _GL_W = np.polynomial.legendre.leggauss(16)

#: the table zeroes expected extinctions below EXT_ZERO (FFT rounding), and in its rows of std > 0 below EXT_ZERO_REL
#: of the TF's largest extinction (a tail from values the TF shows nothing at), colour included
EXT_ZERO = float(getattr(classification, "EXT_ZERO", 0.0))
EXT_ZERO_REL = float(getattr(classification, "EXT_ZERO_REL", 0.0))


def zeroed_below(j: int, largest: float) -> float:
    """What row j of a TF's table zeroes: expected extinctions below this."""
    return max(EXT_ZERO, EXT_ZERO_REL * largest) if j > 0 else EXT_ZERO


def quad_expectation(xs: np.ndarray, f: np.ndarray, m: float, s: float) -> np.ndarray:
    """E[f(v)], v ~ N(m, s^2), f (C, n) piecewise linear through the points xs, constant beyond the ends, by dense
    quadrature: panels cut at every entry within 12 s of m and every s/4, 16-point Gauss-Legendre on each (the
    integrand is a linear function times a Gaussian on each panel); the mass beyond 12 s (1e-32) is dropped and the
    rest normalised by the quadrature of the density itself."""
    w_ = 12.0 * s
    inner = xs[(xs > m - w_) & (xs < m + w_)]
    bp = np.unique(np.concatenate([inner, m + s * np.linspace(-12.0, 12.0, 97)]))
    a, b = bp[:-1], bp[1:]
    h = (b - a) / 2
    t = (a + b)[:, None] / 2 + h[:, None] * _GL_X[None]
    w = h[:, None] * _GL_W[None] * np.exp(-0.5 * ((t - m) / s) ** 2)
    vals = np.stack([np.interp(t, xs, fc) for fc in f])
    return (vals * w).sum(axis=(1, 2)) / w.sum()


def closed_expectation(xs: np.ndarray, f: np.ndarray, m: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The same expectation in closed form at many (m, s) (N,) -> (N, C): f = f_0 + sum_k (slope change at x_k) *
    (v - x_k)_+, and E[(v - x)_+] = s phi((m - x)/s) + (m - x) Phi((m - x)/s)."""
    f = np.atleast_2d(np.asarray(f, np.float64))
    slopes = np.diff(f, axis=1) / np.diff(xs)
    z0 = np.zeros((f.shape[0], 1))
    dsl = np.diff(np.concatenate([z0, slopes, z0], axis=1), axis=1)
    m, s = np.atleast_1d(np.asarray(m, np.float64)), np.atleast_1d(np.asarray(s, np.float64))
    out = np.empty((m.size, f.shape[0]))
    for c in range(0, m.size, 512):
        mm, ss = m[c:c + 512, None], np.maximum(s[c:c + 512, None], 1e-300)
        x = mm - xs[None]
        with np.errstate(over="ignore"):  # s = 0: z overflows, and the point value is taken below
            z = x / ss
            r = ss * np.exp(-0.5 * z * z) / math.sqrt(2 * math.pi) + x * ndtr(z)
        r = np.where(s[c:c + 512, None] > 0, r, np.maximum(x, 0.0))
        out[c:c + 512] = f[:, 0][None] + r @ dsl.T
    return out


def lut_of(tf: dict, value_range) -> Lut:
    """The LUT the renderer builds for `tf` over a store's value range."""
    return build_lut(TransferFunction.model_validate(tf), value_range)


def tf_points(values, colors, opacities) -> dict:
    return {"points": [{"value": float(v), "color": [float(c) for c in col], "opacity": float(a)}
                       for v, col, a in zip(values, colors, opacities)]}


# ------------------------------------------------------------------------------- 1. the table, to 1e-9
TABLE_CASES = {
    "ct-bone": (CT_PRESETS["ct-bone"], (-1024.0, 3071.0), 1500.0),
    "ct-skin": (CT_PRESETS["ct-skin"], (-1024.0, 3071.0), 1500.0),
    # a narrow near-opaque peak (sigma_t = 13.8) with a colour change across it
    "near-opaque": (tf_points([0, 100, 180], [[1, 0.5, 0], [0.2, 0.4, 1], [0, 1, 0]], [0, 0.999999, 0.2]), (-50.0, 400.0), 120.0),
    # a = 1 on an interval: infinite extinction, capped at EXT_CAP in the table
    "opaque-1": (tf_points([0, 40, 60, 100], [[1, 0, 0], [1, 1, 1], [0, 0, 1], [0, 1, 0]], [0, 1, 1, 0.3]), (0.0, 200.0), 60.0),
}


@pytest.mark.parametrize("name", list(TABLE_CASES))
def test_dist_table_equals_float64_quadrature(name):
    """ext[j, i] = E[sigma_t(v)] and emission[j, i] = E[(sigma_t rgb)(v)] under N(m_i, s_j^2), sigma_t and sigma_t*rgb
    piecewise linear between the LUT entries (constant beyond), against 16-point Gauss-Legendre quadrature on panels
    of s/4: |table - quad| <= 1e-9 |quad| + 1e-12 max(sigma_t) (measured: <= 6e-11 relative, <= 2.2e-13 of the
    largest extinction absolute), except where the exact extinction is below what the table zeroes (zeroed_below:
    in coarse rows 10^-4 of the TF's largest extinction). The axes are m_i = lo + i/scale and
    s_j = std_max (j/(rows-1))^2."""
    tf, vr, smax = TABLE_CASES[name]
    lut = lut_of(tf, vr)
    assert lut.n <= 4096  # the table keeps every LUT entry (no subsampling) for these TFs
    tab = dist_table(lut, smax, rows=64)
    f = point_channels(lut)
    xs = lut.values
    assert tab.ext.shape == (64, lut.n) and tab.emission.shape == (64, lut.n, 3)
    np.testing.assert_allclose(tab.stds, smax * (np.arange(64) / 63.0) ** 2, rtol=1e-15)
    np.testing.assert_allclose(tab.lo + np.arange(tab.n) / tab.scale, xs, rtol=0, atol=1e-9 * (vr[1] - vr[0]))
    smax_sig = float(f[0].max())
    if name == "opaque-1":
        assert smax_sig == EXT_CAP and tab.ext.max() == pytest.approx(EXT_CAP, rel=1e-12)
    # row 0 (s = 0) is the point classification exactly
    np.testing.assert_array_equal(tab.ext[0], f[0])
    np.testing.assert_allclose(tab.emission[0], f[1:].T, rtol=1e-15, atol=0)
    rng = np.random.default_rng(len(name))
    cols = np.unique(np.r_[0, 1, tab.n - 1, rng.integers(0, tab.n, 14),
                           # entries at and beside the TF's control points (the kinks)
                           [int(round((p["value"] - tab.lo) * tab.scale)) + d for p in tf["points"] for d in (-1, 0, 1)
                            if 0 <= round((p["value"] - tab.lo) * tab.scale) + d < tab.n]])
    worst_rel, n_checked, n_zeroed = 0.0, 0, 0
    for j in (1, 2, 3, 7, 20, 41, 63):
        s = float(tab.stds[j])
        for i in cols:
            want = quad_expectation(xs, f, float(xs[i]), s)
            got = np.r_[tab.ext[j, i], tab.emission[j, i]]
            if want[0] < zeroed_below(j, smax_sig) * (1 + 1e-6) and not got.any():
                n_zeroed += 1
                continue  # a tail below the table's floor, zeroed on purpose
            err = np.abs(got - want)
            assert (err <= 1e-9 * np.abs(want) + 1e-12 * smax_sig).all(), (j, i, got, want)
            n_checked += 1
            big = np.abs(want) > 1e-3 * smax_sig
            worst_rel = max(worst_rel, float((err[big] / np.abs(want[big])).max(initial=0.0)))
    assert worst_rel <= 1e-9 and n_checked >= 40
    # the closed form used by the other tests is the same expectation (cross-check of the two float64 references)
    ms = xs[cols]
    for j in (1, 20, 63):
        s = float(tab.stds[j])
        q = np.array([quad_expectation(xs, f, m, s) for m in ms])
        np.testing.assert_allclose(closed_expectation(xs, f, ms, np.full(ms.size, s)), q, rtol=1e-9, atol=1e-12 * smax_sig)


@pytest.mark.parametrize("name", ["ct-bone", "near-opaque", "opaque-1"])
def test_dist_table_with_tiny_std_is_the_point_classification(name):
    """A table whose largest std is 1e-9 of an entry spacing: every row equals the LUT's sigma_t and sigma_t*rgb.
    The Gaussian is a delta on this scale, except at a kink, where the expectation moves by s phi(0) |slope change|
    (exactly: measured 3.3e-11 = 2.8e-10 * 0.399 * 0.29 at opaque-1's colour kink): atol = 0.4e-9 * the largest
    slope change per entry, rtol 1e-9."""
    tf, vr, _ = TABLE_CASES[name]
    lut = lut_of(tf, vr)
    f = point_channels(lut)
    tab = dist_table(lut, 1e-9 / lut.scale, rows=16)
    kink = 0.4e-9 * np.abs(np.diff(f, 2, axis=1)).max(axis=1)  # per channel
    assert kink.max() > 0
    for j in range(tab.rows):
        kept = f[0] >= zeroed_below(j, float(f[0].max()))  # coarse rows zero what is below their floor
        np.testing.assert_allclose(tab.ext[j][kept], f[0][kept], rtol=1e-9, atol=kink[0])
        np.testing.assert_allclose(tab.emission[j][kept], f[1:].T[kept], rtol=1e-9, atol=kink[1:].max())
        assert (tab.ext[j][~kept] <= zeroed_below(j, float(f[0].max())) * (1 + 1e-6)).all()
    # colour (emission / extinction) at a visible entry is the TF colour, and lookup at std 0 reads row 0
    col, ext = tab.lookup(lut.values, np.zeros(lut.n))
    vis = f[0] > 1e-3
    np.testing.assert_allclose(ext, f[0], rtol=1e-6)  # the kernel table is float32
    np.testing.assert_allclose(col[vis], lut.rgb[vis], atol=1e-6)


# ------------------------------------------------------------------------------- 2. table resolution in ΔE
@pytest.mark.parametrize("preset", ["ct-bone", "ct-skin", "ct-skin-bone"])
def test_table_lookup_off_the_grid_within_a_tenth_delta_e(preset):
    """The kernel's bilinear lookup (in mean and sqrt(std)) at random (mean, std) over the CT range, against the
    exact expectation there, as the colour of a unit slab over black (alpha = 1 - exp(-ext), alpha * colour) in
    CIELUV: mean ΔE <= 0.1 (measured: 0.0013 ct-bone, 0.0003 ct-skin, 0.0020 ct-skin-bone; p95 <= 0.009, max
    <= 0.03; asserted p95 <= 0.5, max <= 2). Half the stds are uniform in
    [0, std_max], half uniform in the row coordinate sqrt(std) (dense near 0, where the table changes fastest)."""
    vr, smax = (-1024.0, 3071.0), 1500.0
    lut = lut_of(CT_PRESETS[preset], vr)
    tab = dist_table(lut, smax)
    f = point_channels(lut)
    rng = np.random.default_rng(5)
    n = 3000
    m = rng.uniform(*vr, n)
    s = np.where(np.arange(n) % 2 == 0, rng.uniform(0, smax, n), smax * rng.uniform(0, 1, n) ** 2)
    e = closed_expectation(lut.values, f, m, s)
    ext = e[:, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        col = np.where(ext[:, None] > 0, e[:, 1:] / ext[:, None], 0.0)
    want = -np.expm1(-ext)[:, None] * col
    gcol, gext = tab.lookup(m, s)
    got = -np.expm1(-gext)[:, None] * gcol
    de = np.linalg.norm(srgb_to_luv(got) - srgb_to_luv(want), axis=-1)
    assert (want.max(axis=-1) > 1 / 255).sum() > n // 3  # the sample is mostly visible, not empty space
    assert de.mean() <= 0.1, (de.mean(), np.percentile(de, 95), de.max())
    assert np.percentile(de, 95) <= 0.5 and de.max() <= 2.0, (np.percentile(de, 95), de.max())


# ------------------------------------------------------------------------------- 3. the stored deviations
def reference_std(vol: np.ndarray, k: int) -> np.ndarray:
    """Std of the real, non-NaN level-0 voxels of every 2^k cube, in float64 (cut to ceil(shape / 2^k); the cube at
    an edge holds only the voxels that exist; a cube without any valid voxel: 0)."""
    v = vol.astype(np.float64)
    f = 1 << k
    shp = [-(-n // f) for n in v.shape]
    p = np.pad(v, [(0, s * f - n) for s, n in zip(shp, v.shape)], constant_values=np.nan)
    cubes = p.reshape(shp[0], f, shp[1], f, shp[2], f)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sd = np.nanstd(cubes, axis=(1, 3, 5))
    return np.where(np.isnan(sd), 0.0, sd)


def reference_mean(vol: np.ndarray, block: int, k: int) -> np.ndarray:
    """Level k's mean, which still averages the edge-replicated padding (to a multiple of the block), NaN ignored."""
    v = vol.astype(np.float64)
    p = np.pad(v, [(0, (-n) % block) for n in v.shape], mode="edge")
    f = 1 << k
    shp = [n // f for n in p.shape]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(p.reshape(shp[0], f, shp[1], f, shp[2], f), axis=(1, 3, 5))
    return mean[tuple(slice(0, -(-n // f)) for n in vol.shape)]


def _std_volume(name, shape, dtype):
    rng = np.random.default_rng(zlib.crc32(name.encode()))  # str hash() differs between processes
    dtype = np.dtype(dtype)
    if dtype.kind == "f":
        base = {"f32_offset": 1000.0, "f64_far": 1e5}.get(name, 0.0)
        scale = {"f32_offset": 0.5, "f64_far": 0.01}.get(name, 100.0)
        vol = (base + rng.standard_normal(shape) * scale).astype(dtype)
        if name not in ("f32_offset", "f64_far"):
            vol.flat[rng.integers(0, vol.size, max(3, vol.size // 40))] = np.nan
        if name == "f32_nan":
            vol[0:4, 4:8, 8:12] = np.nan  # a whole level-2 cube (and its eight level-1 cubes) without a valid voxel
            vol[4:6, 0:2, 0:2] = 7.5  # a constant level-1 cube: std exactly 0
    else:
        info = np.iinfo(dtype)
        vol = rng.integers(max(info.min, -2000), min(info.max, 3000) if dtype.itemsize <= 2 else 2_000_000, shape).astype(dtype)
        vol[..., :1] = vol[..., :1] // 2  # an edge that differs from its neighbours: padding by replication would show
    return vol


STD_CASES = [
    ("odd_u16", (33, 17, 5), np.uint16, 8),
    ("thin_i16", (1, 19, 23), np.int16, 8),
    ("u8", (10, 12, 14), np.uint8, 8),
    ("f32_nan", (11, 20, 14), np.float32, 4),  # edge cubes with 3 and 2 real layers of 4: padding would show
    ("thin_f32", (6, 1, 9), np.float32, 4),
    ("f32_offset", (12, 12, 12), np.float32, 4),
    ("i32", (7, 9, 11), np.int32, 4),
    ("f64", (5, 6, 7), np.float64, 4),
    ("f64_far", (9, 10, 11), np.float64, 4),  # 1e5 ± 0.01: sums of squares about zero lost 7 % of the spread
]


@pytest.mark.parametrize("name,shape,dtype,block", STD_CASES, ids=[c[0] for c in STD_CASES])
def test_stored_std_equals_float64_reference(tmp_path: Path, name, shape, dtype, block):
    """std/k is the std of the real non-NaN level-0 voxels of each 2^k cube (edge padding and NaN never counted, an
    all-NaN cube 0): float16 for integers of <= 16 bits (relative 2^-11, the format's rounding), float32 otherwise
    (1e-6 relative); level_std is sqrt(mean over the block's coarse voxels of std^2) in float64 (1e-9); std_max the
    largest std; the mean levels still average the edge-replicated padding."""
    vol = _std_volume(name, shape, dtype)
    st = lodcast.ingest(vol, tmp_path / f"{name}.zarr", block_size=block, progress=False)
    st = lodcast.open_store(tmp_path / f"{name}.zarr")
    assert st.has_distribution and st.format_version == FORMAT_VERSION
    small_int = np.dtype(dtype).kind in "iu" and np.dtype(dtype).itemsize <= 2
    want_dtype = np.float16 if small_int else np.float32
    scale = float(np.nanmax(np.abs(vol.astype(np.float64))))
    refs = {0: np.zeros(st.layout.level_shape(0))}
    for k in range(1, st.n_levels):
        want = reference_std(vol, k)
        refs[k] = want
        got = st.read_std_region(k)
        assert got.dtype == want_dtype and got.shape == want.shape == st.layout.level_shape(k)
        if small_int:
            np.testing.assert_allclose(got.astype(np.float64), want, rtol=2.0**-11, atol=1e-6)
        else:
            np.testing.assert_allclose(got.astype(np.float64), want, rtol=1e-6, atol=1e-9 * scale)
        # a region reads the same values
        reg = tuple(slice(n // 3, max(n // 3 + 1, n - 1)) for n in want.shape)
        np.testing.assert_array_equal(st.read_std_region(k, region=reg), got[reg])
        # the mean levels: edge padding averaged in (unchanged by the distribution)
        mref = reference_mean(vol, block, k)
        mref = np.rint(mref) if np.dtype(dtype).kind in "iu" else mref
        np.testing.assert_allclose(st.read_level(k).astype(np.float64), mref, rtol=1e-6 if dtype == np.float32 else 1e-12,
                                   atol=0, equal_nan=True)
    assert not st.read_std_region(0).any() and st.read_std_region(0).shape == shape
    if name == "f32_nan":
        assert (st.read_std_region(1)[0:2, 2:4, 4:6] == 0).all() and st.read_std_region(2)[0, 1, 2] == 0
        assert st.read_std_region(1)[2, 0, 0] == 0
    # the edge cubes count only real voxels: a thin volume's level-k std is the std of a 1-voxel-thick patch
    if name == "thin_i16":
        np.testing.assert_allclose(st.read_std_region(1)[0, 0, 0], np.std(vol[0, 0:2, 0:2].astype(np.float64)), rtol=2.0**-11)
    assert st.std_max == pytest.approx(max(float(r.max()) for r in refs.values()), rel=1e-9)
    # level_std: grid + (levels,), the RMS of the coarse voxels' std over each block's true extent
    ls = st.level_std
    assert ls.shape == st.grid + (st.n_levels,)
    want_ls = np.zeros(ls.shape)
    for b in itertools.product(*(range(g) for g in st.grid)):
        for k in range(1, st.n_levels):
            e = block >> k
            cube = refs[k][tuple(slice(i * e, (i + 1) * e) for i in b)]
            want_ls[b + (k,)] = math.sqrt(float(np.mean(cube ** 2)))
    np.testing.assert_allclose(ls, want_ls, rtol=1e-9, atol=1e-12 * scale)
    assert (ls[..., 0] == 0).all() and ls[..., 1:].max() > 0


# ------------------------------------------------------------------------------- 4. constant volumes
@pytest.mark.parametrize("adaptive", [True, False], ids=["adaptive", "fixed_step"])
def test_constant_volume_renders_identically_at_every_level(tmp_path, adaptive):
    """A constant volume: every forced level (levels = k everywhere) renders the full-resolution image, with
    distribution classification (its std is 0 everywhere, so coarse samples are classified exactly as at level 0)
    and with mean classification; within 1e-5 on premultiplied RGBA (measured: 0 with a fixed step, <= 5e-7 with
    adaptive steps; the TF keeps alpha below the early-termination threshold, whose overshoot grows
    with the step)."""
    shape = (20, 28, 36)  # not multiples of the block: edge blocks and the rim included
    st = lodcast.ingest(np.full(shape, 500, np.uint16), tmp_path / "c.zarr", block_size=8, progress=False)
    assert st.std_max == 0.0 and not st.read_std_region(st.n_levels - 1).any()
    tf = tf_points([0, 1000], [[0.1, 0.2, 0.9], [0.9, 0.6, 0.1]], [0.0, 0.1])
    samp = {"adaptive_object": adaptive}
    for cam in ({"azimuth": 30, "elevation": 20, "distance": 2.2}, axis_camera("z", shape)):
        sc = {"tf": tf, "width": 40, "height": 32, "camera": cam, "format": "npy"}
        full = render(st, sc)
        assert 0.5 < full.rgba[..., 3].max() < 0.95
        for k in range(st.n_levels):
            for cls in ("distribution", "mean"):
                r = render(st, {**sc, "sampling": {"classification": cls, **samp}}, levels=np.full(st.grid, k, np.int8))
                np.testing.assert_allclose(r.rgba, full.rgba, rtol=0, atol=1e-5, err_msg=f"level {k} {cls}")
                rep = r.report
                if k == 0:
                    assert rep["classification"] == "point (every sample at level 0)"
                    assert "-DLC_DIST" not in rep["build_options"]
                else:
                    assert rep["classification"] == cls
                    assert ("-DLC_DIST" in rep["build_options"]) == (cls == "distribution")


def test_uniform_distribution_volume_renders_the_gaussian_expectation(tmp_path):
    """A 3-D checkerboard of 400 and 600: at every level k >= 1 every coarse voxel has mean 500 and std 100. With
    the TF's opacity only above 520 the mean is transparent, while the distribution classification takes
    ext = E[sigma_t(v)], v ~ N(500, 100^2): along a ray of L units through the box alpha = 1 - exp(-ext L) and the
    colour is E[sigma_t rgb]/ext, the same at levels 1, 2 and 3 (within 1e-5 of each other) and equal to the float64
    expectation within 5e-4 (measured 2e-7: (500, 100) is a node of the table, the last row as std_max = 100, so only
    float32 remains). Mean classification renders nothing."""
    shape = (16, 24, 32)
    z, y, x = np.indices(shape)
    vol = np.where((x + y + z) % 2 == 0, 400, 600).astype(np.uint16)
    st = lodcast.ingest(vol, tmp_path / "cb.zarr", block_size=8, progress=False)
    for k in range(1, st.n_levels):
        assert (st.read_level(k) == 500).all()
        np.testing.assert_array_equal(st.read_std_region(k), np.full(st.layout.level_shape(k), 100.0, np.float16))
    tf = tf_points([520, 600, 680], [[1, 0.2, 0.1], [0.9, 0.8, 0.3], [0.1, 0.3, 1]], [0.0, 0.3, 0.0])
    cam = axis_camera("z", shape)
    L = shape[0]  # the box along z, in units (spacing 1)
    sc = {"tf": tf, "width": 24, "height": 16, "camera": cam, "format": "npy", "sampling": {"step": 0.5}}
    # the exact expectation with the TF's own sigma_t (fine grid: the LUT's entries fall on the control points)
    lut = lut_of(tf, st.value_range)
    f = point_channels(lut)
    e = closed_expectation(lut.values, f, np.array([500.0]), np.array([100.0]))[0]
    alpha = -math.expm1(-e[0] * L)
    want = np.r_[alpha * e[1:] / e[0], alpha]
    assert 0.3 < alpha < 0.95
    imgs = []
    for k in range(1, st.n_levels):
        r = render(st, sc, levels=np.full(st.grid, k, np.int8))
        assert r.report["classification"] == "distribution"
        imgs.append(r.rgba)
        np.testing.assert_allclose(r.rgba.reshape(-1, 4), np.broadcast_to(want, (r.rgba[..., 0].size, 4)), rtol=0, atol=5e-4)
        m = render(st, {**sc, "sampling": {"step": 0.5, "classification": "mean"}}, levels=np.full(st.grid, k, np.int8))
        assert m.report["classification"] == "mean" and m.rgba.max() == 0.0
    for img in imgs[1:]:
        np.testing.assert_allclose(img, imgs[0], rtol=0, atol=1e-5)


# ------------------------------------------------------------------------------- 5. a one-voxel opaque slab
SLAB_RGB = np.array([1.0, 0.9, 0.8])


def slab_tf(a: float) -> dict:
    """Opacity 0 up to 450, then extinction rising linearly to sigma_a = -ln(1 - a) at 550 (21 control points with
    opacity 1 - (1 - a)^(i/20)), a above. Symmetric about 500: the integral of sigma_t over [0, 1000] is 500 sigma_a,
    so the trilinear tent of a one-voxel slab of 1000 has optical depth sigma_a, the analytic value of a one-unit
    slab of opacity a, while its level-1 mean (500 at the peak) is nearly transparent and level 2's (250) entirely."""
    i = np.arange(21)
    vals = np.r_[0, 450 + 5 * i, 1000]
    ops = np.r_[0, 1 - (1 - a) ** (i / 20), a]
    return {**tf_points(vals, [SLAB_RGB] * len(vals), ops), "unit_distance": 1.0}


def slab_model(a: float, k: int, z_max: float = math.inf) -> tuple[float, float, float]:
    """(level-0 optical depth, distribution depth at level k, mean depth at level k) along the slab's normal, in
    float64 from the TF itself: the level-k voxel holding the slab has mean 1000 p and std 1000 sqrt(p (1 - p)),
    p = 2^-k, its neighbours 0 and 0; between voxel centres (2^k apart) the field is their linear interpolation;
    depth = integral over z of E[sigma_t(v)], v ~ N(m(z), s(z)^2) (distribution), of sigma_t(m(z)) (mean), over z
    up to z_max from the voxel's centre (the renderer leaves out coarse cells whose level-0 voxels are all empty)."""
    tf = slab_tf(a)
    cv = np.array([p["value"] for p in tf["points"]])
    co = np.array([p["opacity"] for p in tf["points"]])
    xs = np.unique(np.r_[np.linspace(0, 1000, 4001), cv])
    sig = -np.log1p(-np.interp(xs, cv, co))
    u = np.linspace(-1.0, 1.0, 400001)
    tau0 = np.trapezoid(np.interp(1000 * (1 - np.abs(u)), xs, sig), u)
    p, L = 2.0**-k, 2.0**k
    z = np.linspace(-L, min(L, z_max), 8001)
    lam = 1 - np.abs(z) / L
    m, s = 1000 * p * lam, 1000 * math.sqrt(p * (1 - p)) * lam
    tau_d = np.trapezoid(closed_expectation(xs, sig, m, s)[:, 0], z)
    tau_m = np.trapezoid(np.interp(m, xs, sig), z)
    return float(tau0), float(tau_d), float(tau_m)


@pytest.fixture(scope="module")
def slab_store(tmp_path_factory):
    vol = np.zeros((32, 32, 32), np.uint16)
    vol[13] = 1000  # one z-slice: in block 0 of 16, in the level-1 voxel [12, 13] and the level-2 voxel [12, 15]
    return lodcast.ingest(vol, tmp_path_factory.mktemp("slab") / "s.zarr", block_size=16, progress=False)


def _slab_alpha(st, a, levels=None, **sampling) -> tuple[float, dict, np.ndarray]:
    """Centre-pixel alpha (every pixel sees the same slab: asserted), the report, the image."""
    sc = {"tf": slab_tf(a), "width": 8, "height": 8, "camera": axis_camera("z", st.shape), "format": "npy",
          "sampling": {"early_termination": 1.0, **sampling}}
    r = render(st, sc, levels=levels)
    al = r.rgba[..., 3]
    assert np.ptp(al) <= 1e-5
    np.testing.assert_allclose(r.rgba[..., :3], al[..., None] * SLAB_RGB, atol=1e-5)  # the TF's one colour
    return float(al[4, 4]), r.report, r.rgba


def _depth(alpha: float) -> float:
    return -math.log1p(-min(alpha, 1 - 1e-7))


@pytest.mark.parametrize("a", [0.9, 0.999999])
def test_thin_opaque_slab_keeps_its_optical_depth(slab_store, a):
    """A one-voxel slab of opacity a per unit seen along its normal (orthographic, all pixels alike).
    * Full resolution: alpha = 1 - (1 - a)^1 within 1e-3 (the TF makes the trilinear tent's depth sigma_a; step 0.25
      integrates it exactly, the tent's two transitions being one voxel apart).
    * The float64 model of levels 1 and 2 (slab_model) keeps 77 % and 69 % of sigma_a with the distribution:
      exact for the slab's two-point distribution (share p = 2^-k of a voxel 2^k long: depth sigma_a), the
      Gaussian stand-in N(1000 p, 1000^2 p (1 - p)) puts less mass above the TF's window at 500. The mean keeps
      10 % (level 1) and 0 (level 2). The kernel, with a fixed step of 0.05 and no empty-space skipping, is that
      model within 1e-3 in alpha (measured <= 4e-4).
    * As rendered at the budgeted qualities (adaptive steps, empty-space skipping, step 0.25): the distribution keeps >= 60 % of
      the depth (alpha >= 1 - (1 - a)^0.6), the mean <= 12 % (measured: 0 - the thin remnant falls between the
      coarse steps)."""
    st = slab_store
    sig_a = -math.log1p(-a)
    tau0, _, _ = slab_model(a, 1)
    assert tau0 == pytest.approx(sig_a, rel=1e-3)  # the TF's tent depth is the one-unit slab's
    a0, rep, _ = _slab_alpha(st, a, step=0.25)
    assert rep["classification"] == "point (every sample at level 0)"
    assert abs(a0 - a) <= 1e-3, a0
    for k in (1, 2):
        lv = np.full(st.grid, k, np.int8)
        # the slab's 8³ cell ends at z = 15.5 (cells cover [8h - 1/2, 8h + 15/2)): the level-2 field's tail past it
        # lies in cells whose level-0 voxels are all empty, which the renderer leaves out (a 3 % loss of depth)
        _, tau_d, tau_m = slab_model(a, k, z_max=15.5 - ((13 >> k) + 0.5) * 2**k + 0.5)
        assert 0.6 * sig_a <= tau_d <= sig_a and tau_m <= 0.12 * sig_a  # the derivation, in float64
        # the model is trilinear interpolation of the level: interblock's on one level everywhere (nearest block
        # clamps inside every coarse block)
        exact = {"step": 0.05, "adaptive_object": False, "empty_space_skipping": False, "interpolation": "interblock"}
        ad, rd, _ = _slab_alpha(st, a, lv, **exact)
        am, rm, _ = _slab_alpha(st, a, lv, classification="mean", **exact)
        assert rd["classification"] == "distribution" and "-DLC_DIST" in rd["build_options"]
        assert rm["classification"] == "mean" and "-DLC_DIST" not in rm["build_options"]
        assert abs(ad + math.expm1(-tau_d)) <= 1e-3, (k, ad, -math.expm1(-tau_d))
        assert abs(am + math.expm1(-tau_m)) <= 1e-3, (k, am, -math.expm1(-tau_m))
        # as rendered at the budgeted qualities: adaptive steps (2^k x 0.25 here) and empty-space skipping
        ad, rd, _ = _slab_alpha(st, a, lv, step=0.25, adaptive_object=True)
        am, rm, _ = _slab_alpha(st, a, lv, step=0.25, adaptive_object=True, classification="mean")
        assert rd["adaptive"] == "limited" and rd["classification"] == "distribution"
        assert _depth(ad) >= 0.6 * sig_a, (k, ad)
        assert _depth(am) <= 0.12 * sig_a, (k, am)
        assert ad - am >= 0.6  # "far lower"


def test_empty_space_skipping_does_not_change_a_coarse_level_image(slab_store):
    """docs/design.md, scene: empty-space skipping never changes the image. At level 2 the slab's coarse voxel (centre
    z = 13.5) interpolates into block 1 (z >= 15.5) up to the next centre (17.5); block 1's level-0 values (border
    included) are all 0, so a skip test on them alone dropped that part of the distribution's depth (alpha 0.7892
    instead of 0.7950): near coarse blocks the block info is the neighbourhood's."""
    lv = np.full(slab_store.grid, 2, np.int8)
    on, _, _ = _slab_alpha(slab_store, 0.9, lv, step=0.05, adaptive_object=False)
    off, _, _ = _slab_alpha(slab_store, 0.9, lv, step=0.05, adaptive_object=False, empty_space_skipping=False)
    assert abs(on - off) <= 1e-4, (on, off)



@pytest.mark.parametrize("scale", [1e-3, 1e-6, 1e-7, 1e3, 1e5])
def test_distribution_image_does_not_depend_on_the_data_unit(tmp_path, scale):
    """Scaling a float32 volume and its TF's control values by the same factor changes nothing physical: the image
    must stay the same (1e-3 in alpha). With the deviations on the device as float16 in data units the slab at
    level 1 fell from 0.831 to the mean's 0.205 at 1e-7 (std 5e-5 flushed to 0) and to 0.369 at 1e3 (std 5e5
    overflowed); they are held as uint16 multiples of std_max / 65535 now."""
    out = []
    for sc_ in (1.0, scale):
        vol = np.zeros((32, 32, 32), np.float32)
        vol[13] = 1000 * sc_
        st = lodcast.ingest(vol, tmp_path / f"s{sc_}.zarr", block_size=16, progress=False)
        tf = slab_tf(0.9)
        for p in tf["points"]:
            p["value"] *= sc_
        sc = {"tf": tf, "width": 4, "height": 4, "camera": axis_camera("z", st.shape), "format": "npy",
              "sampling": {"early_termination": 1.0, "step": 0.25}}
        out.append(float(render(st, sc, levels=np.full(st.grid, 1, np.int8)).rgba[2, 2, 3]))
    assert out[0] > 0.8 and abs(out[1] - out[0]) <= 1e-3, out


# ------------------------------------------------------------------------------- 6. format-1 stores
def _field(shape):
    z, y, x = np.mgrid[0:shape[0], 0:shape[1], 0:shape[2]].astype(np.float64)
    return (np.sin(x / 3.0) + np.cos(y / 4.0) + 1.5 * z / shape[0] + 0.4 * np.sin((x + y + z) / 1.7)).astype(np.float32)


def to_format_1(path: Path) -> None:
    """What a store written before distributions looks like: no std/ group, no blocks/level_std, format 1 (and no
    manifest or checksums, which came later still)."""
    shutil.rmtree(path / "std")  # a prefix without a group node (store/store.py): not a member to delete
    g = zarr.open_group(str(path), mode="a")
    del g["blocks/level_std"]
    attrs = dict(g.attrs)
    attrs.pop("distribution", None)
    attrs["lodcast"] = {k: v for k, v in attrs["lodcast"].items() if k not in ("manifest", "integrity")} | {"format_version": 1}
    g.attrs.put(attrs)


TF6 = {"points": [{"value": -1.0, "color": [1, 0, 0], "opacity": 0.0}, {"value": 1.0, "color": [0, 1, 0], "opacity": 0.15},
                  {"value": 2.5, "color": [0.2, 0.3, 1], "opacity": 0.5}]}


def test_format_1_store_renders_by_mean_and_says_so(tmp_path):
    """A store of format 1 (no std/, no blocks/level_std) opens and renders at forced levels and at a LOD quality;
    coarse samples are classified by their mean and the report says why; the image is exactly the format-2 store's
    with "classification": "mean" (measured: identical), which differs from its default distribution image."""
    p2, p1 = tmp_path / "v2.zarr", tmp_path / "v1.zarr"
    st2 = lodcast.ingest(_field((30, 33, 40)), p2, block_size=8, progress=False)
    shutil.copytree(p2, p1)
    to_format_1(p1)
    st1 = lodcast.open_store(p1)
    assert st1.format_version == 1 and not st1.has_distribution and st1.std_max == 0.0 and st1.level_std is None
    assert "std" not in zarr.open_group(str(p1), mode="r")
    assert not st1.read_std_region(1).any()
    np.testing.assert_array_equal(st1.read_level(1), st2.read_level(1))
    rng = np.random.default_rng(4)
    lv = rng.integers(0, st2.n_levels, st2.grid).astype(np.int8)
    lv[0, 0, 0], lv[-1, -1, -1] = -1, 2
    sc = {"tf": TF6, "width": 48, "height": 40, "camera": {"azimuth": 35, "elevation": 25, "distance": 2.2}, "format": "npy"}
    old = render(st1, sc, levels=lv)
    assert old.report["classification"].startswith("mean (this store keeps no distributions")
    assert "-DLC_DIST" not in old.report["build_options"]
    new_mean = render(st2, {**sc, "sampling": {"classification": "mean"}}, levels=lv)
    assert new_mean.report["classification"] == "mean"
    np.testing.assert_allclose(old.rgba, new_mean.rgba, rtol=0, atol=1e-6)
    new_dist = render(st2, sc, levels=lv)
    assert new_dist.report["classification"] == "distribution"
    assert np.abs(new_dist.rgba - new_mean.rgba).max() > 1e-3  # the format-2 default does differ: it was not used
    assert old.rgba[..., 3].max() > 0.2
    # a LOD quality goes through the selection and renders by mean too
    q = render(st1, {**sc, "quality": {"reduction": 4}})
    assert q.report["classification"].startswith("mean (this store keeps no distributions")
    assert q.report["reduction"] > 1 and np.isfinite(q.rgba).all() and q.rgba[..., 3].max() > 0.1
    # asking for the mean explicitly is just "mean"; all level 0 is the point classification
    assert render(st1, {**sc, "sampling": {"classification": "mean"}}, levels=lv).report["classification"] == "mean"
    z = render(st1, sc, levels=np.zeros(st1.grid, np.int8))
    assert z.report["classification"] == "point (every sample at level 0)"


# ------------------------------------------------------------------------------- 7. the sampler's std
B7, NL7 = 8, 4


def std_pyramid(v0: np.ndarray, n_levels: int) -> list[np.ndarray]:
    """Level k: the std of the 2^k cube of level-0 values behind each voxel (level 0: zeros)."""
    out = [np.zeros_like(v0, dtype=np.float64)]
    for k in range(1, n_levels):
        f = 1 << k
        z, y, x = (n // f for n in v0.shape)
        out.append(v0.reshape(z, f, y, f, x, f).std(axis=(1, 3, 5)))
    return out


@pytest.mark.parametrize("interp", ["interblock", "nearest_block"])
def test_sampler_interpolates_the_std_like_the_values(interp):
    """probe with std bricks returns (value, std): the value as without them, and the std by the very formula the
    values follow (trilinear in a brick, eq. 3.5 / 3.6 across blocks) applied to the std bricks, level-0 blocks
    contributing 0 (they have none). The std travels as uint16 multiples of a unit (std_max / 65535, as the renderer
    holds it): the reference uses the rounded bricks, so only float32 arithmetic remains (atol 2e-6)."""
    rng = np.random.default_rng(12)
    G = (3, 3, 4)
    v0 = rng.random(tuple(g * B7 for g in G)) * (1 + rng.random(tuple(g * B7 for g in G)) ** 4 * 3)
    pyr, spyr = ref.pyramid(v0, NL7), std_pyramid(v0, NL7)
    levels = rng.integers(-1, NL7, G).astype(np.int8)
    levels[1, 1, 1], levels[0, 0, 0], levels[2, 2, 3] = 0, 3, 1
    br = ref.bricks_of(levels, pyr, B7)
    unit = max(float(p.max()) for p in spyr) / 65535
    sbr_all = {key: ref.quantized_std(a, unit) for key, a in ref.bricks_of(levels, spyr, B7).items()}
    sbr = {key: a for key, a in sbr_all.items() if key[0] >= 1}
    pts = rng.uniform(-0.5, np.array([G[2], G[1], G[0]]) * B7 - 0.5, (3000, 3))
    got = ref.probe(levels, br, B7, pts, interp, std_bricks=sbr, std_unit=unit).astype(np.float64)
    assert got.shape == (3000, 2)
    vals = ref.probe(levels, br, B7, pts, interp).astype(np.float64)
    want_v = np.array([ref.sample(levels, br, B7, q, interp) for q in pts])
    want_s = np.array([ref.sample(levels, sbr_all, B7, q, interp) for q in pts])
    ok = ~np.isnan(want_v)
    assert ok.sum() > 1000 and np.array_equal(np.isnan(got[:, 0]), ~ok)
    np.testing.assert_array_equal(got[ok, 0], vals[ok])
    np.testing.assert_allclose(got[ok, 0], want_v[ok], atol=2e-6)
    np.testing.assert_allclose(got[ok, 1], want_s[ok], atol=2e-6)
    assert want_s[ok].max() > 0.3 and (want_s[ok] == 0).any()  # coarse samples carry a spread, pure level 0 none
    # all blocks at one coarse level, interblock: trilinear interpolation of that level's std
    if interp == "interblock":
        lk = np.full(G, 2, np.int8)
        sb = {key: ref.quantized_std(a, unit) for key, a in ref.bricks_of(lk, spyr, B7).items()}
        g2 = ref.probe(lk, ref.bricks_of(lk, pyr, B7), B7, pts, interp, std_bricks=sb, std_unit=unit).astype(np.float64)
        s16 = [ref.quantized_std(p, unit) for p in spyr]
        np.testing.assert_allclose(g2[:, 1], [ref.trilinear_level(s16, 2, B7, q) for q in pts], atol=2e-6)


def test_coarse_cells_reached_only_by_a_weak_tail_are_skipped(tmp_path, monkeypatch):
    """Fat and muscle (-100 and 50 HU, alternating voxel by voxel) around a bone ball, rendered from level 1 under
    ct-bone: each coarse voxel of the soft tissue has mean -25 and spread 75, so its Gaussian reaches the TF's
    range (250 HU and up) only 3.7 spreads out, an expected extinction of ~3e-6 per unit, far below 10^-4 of
    the TF's strongest, which the table zeroes, so the march skips those cells. Without the floor it takes every
    one of them; the image is the same to 1/255 of opacity or colour. (The floor alone: the level-0 cell ranges,
    which skip these cells too, are left out; tests/test_lod_mask.py.) Interblock: every cell of the ball's
    interblock neighbourhoods reaches its values (measured 6,338 samples against 44,116 without the floor);
    nearest block's cells beside the ball reach them through the aprons (3,952 against 5,953)."""
    monkeypatch.setattr(VolumeView, "has_cell_ranges", property(lambda self: False))
    rng = np.random.default_rng(4)
    z, y, x = np.indices((48, 48, 48))
    vol = (np.where((z + y + x) % 2, 50.0, -100.0) + rng.normal(0, 5, z.shape)).astype(np.float32)
    vol[(z - 24) ** 2 + (y - 24) ** 2 + (x - 24) ** 2 < 8 ** 2] = 1200.0
    st = lodcast.ingest(vol, tmp_path / "tail.zarr", block_size=8, progress=False)
    scene = {"tf": "ct-bone", "width": 48, "height": 48, "camera": {"azimuth": 20, "elevation": 10},
             "quality": {"reduction": 2}, "sampling": {"adaptive_object": False, "interpolation": "interblock"},
             "format": "npy"}
    levels = np.ones(st.grid, np.int8)
    kept = Renderer().render(st, scene, levels=levels)
    monkeypatch.setattr(classification, "EXT_ZERO_REL", 0.0)
    every = Renderer().render(st, scene, levels=levels)  # a renderer of its own: its tables are built anew
    assert kept.report["samples"] < 0.5 * every.report["samples"], (kept.report["samples"], every.report["samples"])
    assert np.abs(kept.rgba - every.rgba).max() < 1 / 255
    assert kept.rgba[..., 3].max() > 0.5  # the ball shows
