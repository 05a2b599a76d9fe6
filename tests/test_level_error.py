"""Per-level significance under the kernel's classification (renderer/lod/level_error.py) and the predicted ΔE it
drives: properties on constructed volumes, and the prediction's ranking against measured image error."""
from __future__ import annotations

import numpy as np
import pytest
from test_lod_render import TF, _field

import lodcast
from lodcast.renderer.image.delta_e import delta_e_stats, srgb_to_luv
from lodcast.renderer.lod.level_error import level_zeta, step_zeta
from lodcast.renderer.lod.selection import step_delta_e
from lodcast.renderer.lod.significance import as_tf, meta_of_store, tf_visible
from lodcast.renderer.scene.transfer_function import evaluate

B = 8
OPAQUE_SHEET_TF = {"points": [{"value": 400, "color": [1, 1, 1], "opacity": 0.0},
                              {"value": 1000, "color": [1, 0.9, 0.8], "opacity": 0.9}]}


def _zeta(store, tf, classification):
    meta = meta_of_store(store)
    vis = tf_visible(tf, meta.min_border, meta.max_border)
    z, _ = level_zeta(meta, tf, vis, meta.value_range, meta.std_max, classification)
    return z.reshape(tuple(store.grid) + (store.n_levels,)), vis.reshape(store.grid)


@pytest.fixture(scope="module")
def sheets(tmp_path_factory):
    """Background 0 with one-voxel sheets of 1000 (every 8th z-slice, off the block faces): thin opaque structures
    that classifying the coarse mean loses (the level-1 mean of a sheet voxel is 500, level 2 250)."""
    vol = np.zeros((32, 24, 24), np.int16)
    vol[3::8] = 1000
    return lodcast.ingest(vol, tmp_path_factory.mktemp("sheets") / "s.zarr", block_size=B, progress=False)


def test_level_zero_is_exact_and_invisible_blocks_cost_nothing(sheets):
    for cls in ("distribution", "mean"):
        z, vis = _zeta(sheets, OPAQUE_SHEET_TF, cls)
        assert np.all(z[..., 0] == 0)  # full resolution shows the level-0 colours exactly
        assert np.all(z[~vis] == 0) and vis.any()


def test_the_mean_loses_a_thin_sheet_and_the_distribution_keeps_most_of_it(sheets):
    """Every block holds one sheet: under mean classification level 1 shows T*(500), a value the TF makes almost
    transparent, so the per-level ζ is large and grows with the level; under distribution classification every
    value is seen through its level's spread (≈ 433 at level 1), which keeps much of the sheet's colour."""
    z_mean, vis = _zeta(sheets, OPAQUE_SHEET_TF, "mean")
    z_dist, _ = _zeta(sheets, OPAQUE_SHEET_TF, "distribution")
    zm, zd = z_mean[vis], z_dist[vis]
    assert np.all(np.diff(zm, axis=1) >= -1e-9)  # coarser never looks better under the mean
    assert zm[:, 1].min() > 0 and np.all(zd[:, 1] < 0.9 * zm[:, 1])


def test_a_tf_flat_over_the_data_costs_nothing(tmp_path):
    """Where the TF is one colour and opacity over every value a block holds, every level shows the same colour:
    ζ = 0 at every level, under both classifications, however varied the data."""
    vol = np.random.default_rng(5).integers(100, 900, (16, 16, 16)).astype(np.int16)
    st = lodcast.ingest(vol, tmp_path / "f.zarr", block_size=B, progress=False)
    flat = {"points": [{"value": 0, "color": [0.5, 0.7, 0.2], "opacity": 0.4}]}
    for cls in ("distribution", "mean"):
        z, vis = _zeta(st, flat, cls)
        assert vis.all() and np.abs(z).max() < 1e-9


def test_predicted_delta_e_ranks_like_the_measured_error(tmp_path):
    """On a smooth translucent field the prediction orders the reductions exactly as the images do (Spearman 1 over
    2 … 64:1). Its scale was fitted on the chest CT (renderer/lod/prediction.py); on this synthetic field (a TF
    whose hue turns from red through green to blue, which the picture's CIELUV weighs fully) it is within 2.5× of
    the measured error from 4:1 on and 5.4× above it at 2:1, where both are small (against the step-¼ reference,
    the step's own error included: 0.49 predicted, 0.09 measured; 4:1: 1.63 and 0.66; 64:1: 5.8 and 6.05), so
    the bound is a factor 6, not the CT's 2."""
    st = lodcast.ingest(_field((64, 64, 64)), tmp_path / "v.zarr", block_size=B, progress=False)
    scene = {"tf": TF, "width": 64, "height": 64, "camera": {"azimuth": 30, "elevation": 20}, "format": "npy"}
    ref = lodcast.render(st, {**scene, "sampling": {"step": 0.25}})
    measured, predicted = [], []
    for r in (2, 4, 8, 16, 32, 64):
        img = lodcast.render(st, {**scene, "quality": {"reduction": r}})
        measured.append(delta_e_stats(img.rgba, ref.rgba)["mean"])
        predicted.append(img.report["predicted_delta_e"])
    rank = lambda v: np.argsort(np.argsort(v))  # noqa: E731
    assert np.corrcoef(rank(measured), rank(predicted))[0, 1] >= 0.9, (measured, predicted)
    ratio = np.asarray(measured) / np.asarray(predicted)
    assert np.all((ratio > 1 / 6) & (ratio < 6.0)), (measured, predicted)


def test_step_zeta_is_the_colour_change_over_the_level_1_spread(tmp_path):
    """ζ_step of every visible block against a float64 evaluation from the block's own voxels: the RMS over its
    visible voxels of ½ |T*(v + s₁) − T*(v − s₁)| (T* the unit-slab colour in CIELUV, s₁ the block's level-1
    spread). The store's simplified histogram stands for the voxels, hence the tolerance: each block within 20%, all
    within 6% RMS (measured 16% and 4.8%)."""
    rng = np.random.default_rng(3)
    vol = (rng.normal(0, 1, (24, 24, 24)).cumsum(axis=0) * 60 + 300).astype(np.float32)
    st = lodcast.ingest(vol, tmp_path / "w.zarr", block_size=B, progress=False)
    meta = meta_of_store(st)
    vis = tf_visible(TF, meta.min_border, meta.max_border)
    z, opac = step_zeta(meta, TF, vis, meta.value_range, meta.std_max)

    tf = as_tf(TF)

    def unit_slab_luv(v):
        rgb, a = evaluate(tf, v)
        return srgb_to_luv(a[..., None] * rgb)

    g = tuple(st.grid)
    want = np.zeros(meta.n)
    for i in np.flatnonzero(vis):
        bz, by, bx = np.unravel_index(i, g)
        lo = [max(c * B - 1, 0) for c in (bz, by, bx)]  # the histograms count a one-voxel border
        v = vol[lo[0]:(bz + 1) * B + 1, lo[1]:(by + 1) * B + 1, lo[2]:(bx + 1) * B + 1].astype(np.float64).ravel()
        s1 = meta.level_std[i, 1]
        d2 = (0.25 * (unit_slab_luv(v + s1) - unit_slab_luv(v - s1)) ** 2).sum(axis=-1)
        seen = max(np.mean(evaluate(tf, v)[1] > 0), 1.0 / (1 << (meta.n_levels - 1)))
        want[i] = np.sqrt(d2.mean() / seen)
    assert vis.sum() >= 8 and want.max() > 1.0
    rel = np.abs(z - want)[vis] / want[vis]
    assert rel.max() < 0.2 and np.sqrt(np.mean((z - want)[vis] ** 2)) < 0.06 * np.sqrt(np.mean(want[vis] ** 2)), rel
    assert np.all(z[~vis] == 0) and np.all(opac[vis, 0] > 0)


def test_the_predicted_step_error_grows_as_the_square_of_the_step(tmp_path):
    """selection.step_delta_e is h² times one figure per scene, and 0 for a constant volume (nothing changes
    along a ray)."""
    st = lodcast.ingest(_field((32, 32, 32)), tmp_path / "v.zarr", block_size=B, progress=False)
    meta = meta_of_store(st)
    e = [step_delta_e(meta, [TF], h) for h in (0.25, 0.5, 1.0, 2.0)]
    assert e[0] > 0 and np.allclose(np.asarray(e) / e[0], [1, 4, 16, 64], rtol=1e-12)
    flat = lodcast.ingest(np.full((16, 16, 16), 500, np.int16), tmp_path / "c.zarr", block_size=B, progress=False)
    assert step_delta_e(meta_of_store(flat), [TF], 1.0) == 0.0


def test_a_full_resolution_report_predicts_its_step_error(tmp_path):
    """At full resolution the report's prediction is the step's error against the step-¼ reference: on a smooth
    translucent field it orders the steps as the images do, and it is within a factor 5 of each: the scale was
    fitted on CT, and this field is smoother than any CT (measured 0.02 … 0.39 mean ΔE against 0.10 … 1.6
    predicted). Without the step term it would be 0 at every step."""
    st = lodcast.ingest(_field((64, 64, 64)), tmp_path / "v.zarr", block_size=B, progress=False)
    scene = {"tf": TF, "width": 64, "height": 64, "camera": {"azimuth": 30, "elevation": 20}, "format": "npy"}
    ref = lodcast.render(st, {**scene, "sampling": {"step": 0.25}})
    measured, predicted = [], []
    for h in (0.5, 1.0, 1.5, 2.0):
        img = lodcast.render(st, {**scene, "sampling": {"step": h}})
        measured.append(delta_e_stats(img.rgba, ref.rgba)["mean"])
        predicted.append(img.report["predicted_delta_e"])
    assert np.all(np.diff(measured) > 0) and np.all(np.diff(predicted) > 0), (measured, predicted)
    ratio = np.asarray(measured) / np.asarray(predicted)
    assert np.all((ratio > 1 / 6) & (ratio < 6.0)), (measured, predicted)


BAND_TF = {"points": [{"value": 40, "color": [0.9, 0.5, 0.4], "opacity": 0.0},
                      {"value": 60, "color": [0.9, 0.5, 0.4], "opacity": 0.008},
                      {"value": 140, "color": [1.0, 0.8, 0.6], "opacity": 0.008},
                      {"value": 160, "color": [1, 1, 1], "opacity": 0.9},
                      {"value": 160, "color": [1, 1, 1], "opacity": 0.9}]}
RAMP_TF = {"points": [{"value": 80, "color": [1, 0.9, 0.8], "opacity": 0.0},
                      {"value": 200, "color": [1, 1, 1], "opacity": 0.9}]}


@pytest.mark.parametrize("classification", ["distribution", "mean"])
def test_the_device_computes_the_block_errors_as_numpy_does(eng, shared_data, tmp_path, classification):
    """level_error.block_zetas on the engine's device (zeta.cl) against its NumPy path on a real volume (the engine
    CT), under a translucent band over an opaque step (a repeated point: a jump) and an opaque ramp, with the
    worst values too: every block's every output within 1e-3 ΔE units (float32 table lookups both; the selection
    compares them with 0.5) and 1e-3 relative where it is above 0.1, the mean opacities and the visible share to
    1e-5, and the opacity of the values carrying the step's error (a ratio of two float32 sums) to 1e-4."""
    from lodcast.renderer.engine import Tables
    from lodcast.renderer.lod.level_error import block_zetas, luv_table
    from lodcast.renderer.lod.significance import effective_starts
    from lodcast.renderer.lod.zeta_kernel import device_zetas

    store = lodcast.ingest(shared_data / "engine.nii.gz", tmp_path / "engine.zarr", progress=False)
    meta = meta_of_store(store)
    assert meta.effective is meta.effective  # computed once per metadata object
    np.testing.assert_array_equal(meta.effective, effective_starts(meta))
    for tf in (BAND_TF, RAMP_TF):
        vis = tf_visible(tf, meta.min_border, meta.max_border)
        assert vis.sum() > 100
        args = (meta, tf, vis, meta.value_range, meta.std_max, classification)
        ref = block_zetas(*args, Tables(None), worst_values=True)
        rows = np.flatnonzero(vis & (meta.max_border > meta.min_border))
        t, luv = luv_table(tf, meta.value_range, meta.std_max)
        on_device = device_zetas(eng.device, meta, as_tf(tf), rows, effective_starts(meta), t, luv, classification,
                                 True)
        got = block_zetas(*args, Tables(eng.device), worst_values=True)  # the engine's way: on its device
        for r, d, g in zip(ref, on_device, got):
            assert np.array_equal(g[rows], d) and not np.delete(g, rows, axis=0).any()
        for name, r, g in zip(("zeta", "step", "opacity", "worst", "spread"), ref, got):
            assert r.shape == g.shape
            assert np.abs(r).max() > 0, name  # (the comparison below compares something)
            tol = np.array([1e-5, 1e-5, 1e-5, 1e-4]) if name == "opacity" else 1e-3
            assert np.all(np.abs(g - r).max(axis=0) <= tol), (name, np.abs(g - r).max(axis=0))
            big = np.abs(r) > 0.1
            assert (np.abs(g - r)[big] / np.abs(r)[big]).max() <= 1e-3, name
        # without the worst values the same errors, and no worst values
        z, _, _, w, _ = block_zetas(*args, Tables(eng.device))
        assert np.abs(z - ref[0]).max() <= 1e-3 and not w.any()
        # without the level errors (the prediction's pass under distribution classification): no ζ(k), and the
        # same step, opacities and spread as the whole pass, on the device (the same float32 sums) and in NumPy
        for tables, whole in ((Tables(eng.device), got), (Tables(None), ref)):
            z, st, op, w, sp = block_zetas(*args, tables, level_errors=False)
            assert not z.any() and not w.any()
            for a, b in ((st, whole[1]), (op, whole[2]), (sp, whole[4])):
                np.testing.assert_array_equal(a, b)


def test_the_device_keeps_the_block_errors_of_values_far_from_zero(eng, tmp_path):
    """Values a billion away from zero (int32 in the store): the device takes them relative to the table's first
    entry, so float32 keeps their place in the value range, and its errors match the NumPy path's as on CT."""
    from lodcast.renderer.engine import Tables
    from lodcast.renderer.lod.level_error import block_zetas

    z, y, x = np.mgrid[0:32, 0:32, 0:32]
    field = 500 + 400 * np.sin(x / 5.0) * np.cos(y / 7.0) + 10 * z
    store = lodcast.ingest((1_000_000_000 + np.rint(field)).astype(np.int32), tmp_path / "far.zarr", block_size=B,
                           progress=False)
    meta = meta_of_store(store)
    tf = {"points": [{"value": 1_000_000_300, "color": [1, 0.6, 0.4], "opacity": 0.0},
                     {"value": 1_000_000_500, "color": [1, 1, 1], "opacity": 0.6},
                     {"value": 1e300, "color": [1, 1, 1], "opacity": 0.6}]}  # (a point beyond float32)
    vis = tf_visible(tf, meta.min_border, meta.max_border)
    args = (meta, tf, vis, meta.value_range, meta.std_max)
    ref = block_zetas(*args, tables=Tables(None), worst_values=True)
    got = block_zetas(*args, tables=Tables(eng.device), worst_values=True)
    assert ref[0].max() > 1.0  # (level 1 of this field loses colour: the comparison compares something)
    for r, g in zip(ref, got):
        assert np.abs(g - r).max() <= 1e-3 * max(1.0, float(np.abs(r).max()))


def test_picture_colours_weigh_a_faint_slab_s_change_of_hue_as_the_picture_shows_it():
    """The prediction's tables compare colours in the picture's CIELUV (level_error.picture_table): a faint TF's
    change of hue between two values, times the unit slabs a ray composites, is the ΔE between the two pictures
    (float64: a thick slab of each colour composited front to back, srgb_to_luv), within 10%. In each slab's own
    CIELUV (luv_table, what the tables took before) the same change is a small fraction of it: the slab's
    lightness is in CIELUV's linear segment and its chroma scales with that lightness."""
    from lodcast.renderer.lod.level_error import luv_table, picture_table

    a, depth = 0.01, 2000
    tf = {"points": [{"value": 0.0, "color": [0.4, 0.6, 0.3], "opacity": a},
                     {"value": 1.0, "color": [0.55, 0.45, 0.3], "opacity": a}]}
    v1, v2 = 0.45, 0.55
    rgb = np.array([evaluate(as_tf(tf), v)[0] for v in (v1, v2)])
    shown = (1 - (1 - a) ** depth) * rgb  # the composited pictures (premultiplied over black)
    want = float(np.linalg.norm(srgb_to_luv(shown[0]) - srgb_to_luv(shown[1])))
    slabs = (1 - (1 - a) ** depth) / a

    def change(table) -> float:
        t, colours = table(tf, (0.0, 1.0), 0.5)
        at = [t.lerp(colours, t.mean_axis(np.array([v])), t.std_axis(0.0))[0] for v in (v1, v2)]
        return slabs * float(np.linalg.norm(at[0] - at[1]))

    assert change(picture_table) == pytest.approx(want, rel=0.1)
    assert change(luv_table) < 0.5 * want
