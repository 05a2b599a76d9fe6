"""The predicted ΔE holds where the old model broke: translucent bands, whose blocks' errors add up along every
ray through them (issue 45, item 2; renderer/lod/prediction.py). DESIGN.md's reading: within 2× of the measured
mean ΔE (against full resolution at the same sampling) where that is ≥ 0.3, within 0.15 below it."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from phantoms import BAND_BONE, ENGINE_BAND

import lodcast
from lodcast.renderer.image.delta_e import delta_e_stats
from lodcast.renderer.lod.prediction import RAY_GAIN, RayModel, ray_delta_e
from lodcast.renderer.scene.transfer_function import CT_PRESETS

SCENE = {"camera": {"azimuth": 30, "elevation": 15}, "width": 128, "height": 128, "format": "npy"}


def _holds(pred: float, meas: float) -> bool:
    return meas / 2 <= pred <= 2 * meas if meas >= 0.3 else abs(pred - meas) <= 0.15


@pytest.fixture(scope="module")
def chest(tmp_path_factory: pytest.TempPathFactory, shared_data: Path):
    return lodcast.ingest(shared_data / "ct_chest_dicom", tmp_path_factory.mktemp("ct") / "ct.zarr", progress=False)


@pytest.fixture(scope="module")
def engine(tmp_path_factory: pytest.TempPathFactory, shared_data: Path):
    return lodcast.ingest(shared_data / "engine.nii.gz", tmp_path_factory.mktemp("engine") / "e.zarr", progress=False)


def _pair(eng, store, scene: dict, quality: dict, sampling: dict | None = None) -> tuple[float, float]:
    """(predicted, measured): the level of detail's predicted ΔE (the report's less the step's own, which the
    full-resolution render's report gives alone) and the mean ΔE against full resolution at the same sampling."""
    full = eng.render(store, scene)
    r = eng.render(store, {**scene, "quality": quality, "sampling": sampling or {}})
    return (r.report["predicted_delta_e"] - full.report["predicted_delta_e"],
            delta_e_stats(r.rgba, full.rgba)["mean"])


@pytest.mark.parametrize("reduction", [30, 100])
def test_the_prediction_holds_where_a_block_s_error_sits_in_a_faint_band_beside_opaque_plates(engine, renderer,
                                                                                              reduction):
    """The engine CT under a faint band with opaque plates (phantoms.ENGINE_BAND; validation, not fitted): a
    block's error sits in the band, its opacity in the plates. Counted at the block's own opacity and visible share
    (the opacity moments) the prediction was 0.39× and 0.28× of the measured error at 30:1 and 100:1 (128²); over
    the band's visible share at the opacity of the values carrying the error, 0.85× and 0.61×."""
    pred, meas = _pair(renderer, engine, {**SCENE, "tf": ENGINE_BAND}, {"reduction": reduction})
    assert meas > 0.3
    assert _holds(pred, meas), (pred, meas)


@pytest.mark.parametrize("reduction", [10, 30])
def test_the_prediction_holds_on_a_translucent_band_over_the_chest_ct(chest, renderer, reduction):
    """Before this (one image-wide mean opacity, as for a surface): predicted 0.50 against 1.60 measured at 10:1
    and 1.42 against 3.12 at 30:1 (256²), a factor 0.3–0.45."""
    pred, meas = _pair(renderer, chest, {**SCENE, "tf": BAND_BONE}, {"reduction": reduction})
    assert meas > 0.3  # there is an error to predict
    assert _holds(pred, meas), (pred, meas)


def test_the_prediction_orders_scenes_like_the_measured_error(chest, renderer):
    """Spearman ≥ 0.9 over an opaque and a translucent TF, 5:1 to 30:1, both classifications and adaptive
    screen-space sampling (12 pairs; before this 0.69: the translucent band and the mosaic's error were predicted
    far too low). With the narrow skin band as well (18 pairs) it is 0.88: the mosaic's error is one figure per
    pixel without its own ray, and skin's smooth picture loses less to it than bone's edges."""
    pairs = [_pair(renderer, chest, {**SCENE, "tf": tf}, {"reduction": r}, samp)
             for tf in (CT_PRESETS["ct-bone"], BAND_BONE)
             for r, samp in ((5, None), (10, None), (30, None), (10, {"classification": "mean"}),
                             (10, {"adaptive_screen": True}), (30, {"adaptive_screen": True}))]
    pred, meas = (np.array(x) for x in zip(*pairs))

    def ranks(x: np.ndarray) -> np.ndarray:
        return np.argsort(np.argsort(x)).astype(np.float64)

    rho = float(np.corrcoef(ranks(pred), ranks(meas))[0, 1])
    assert rho >= 0.9, (rho, pairs)


def test_adaptive_screen_sampling_adds_its_own_error_to_the_prediction(chest, renderer):
    """The mosaic's interpolation is in the prediction (renderer/frame/screen.py: SCREEN_DELTA_E = 2.2 per pixel
    without its own ray at 256², twice that at 128²); before this the prediction ignored it and missed by 8× on
    bone at 10:1 (0.96 predicted, 8.2 measured at 128²)."""
    scene = {**SCENE, "tf": CT_PRESETS["ct-bone"]}
    plain = renderer.render(chest, {**scene, "quality": {"reduction": 10}})
    pred, meas = _pair(renderer, chest, scene, {"reduction": 10}, {"adaptive_screen": True})
    rays = renderer.render(chest, {**scene, "quality": {"reduction": 10}, "sampling": {"adaptive_screen": True}})
    share = 1.0 - rays.report["adaptive_screen"]["rays_per_pixel"]
    assert rays.report["predicted_delta_e"] == pytest.approx(plain.report["predicted_delta_e"] + 2.2 * 2 * share)
    assert _holds(pred, meas), (pred, meas)


def test_the_ray_model_adds_a_column_of_faint_blocks_in_quadrature_behind_their_transmittance():
    """The model's arithmetic on a column of m equal blocks (grid (m, 1, 1)): along z a ray crosses all of them,
    block b behind τ^b, τ = (1 − a)^λ, each showing n = (1 − τ)/a unit slabs of its error e; along y and x each
    ray crosses one. The prediction is RAY_GAIN times the mean over the six ways."""
    m, a, e, block = 6, 0.01, 0.5, 16
    levels = np.ones(m, np.int64)
    spread = np.zeros((m, 5))
    spread[:, 1] = e
    opac = np.tile([a, a * a, 1.0, a], (m, 1))  # every voxel at opacity a: visible share m1²/m2 = 1
    model = RayModel((m, 1, 1), (16.0, 16.0, 16.0), spread, None, opac)
    tau = (1 - a) ** block
    n = (1 - tau) / a
    along_z = n * e * np.sqrt(np.sum(tau ** (2 * np.arange(m))))
    want = RAY_GAIN * (2 * along_z + 4 * n * e) / 6
    assert ray_delta_e(model, levels) == pytest.approx(want, rel=1e-9)
    # the mean classification's own ζ adds in quadrature to the spread; blocks not loaded add nothing
    bias = RayModel((m, 1, 1), (16.0, 16.0, 16.0), spread, spread * 0.75, opac)
    assert ray_delta_e(bias, levels) == pytest.approx(1.25 * want, rel=1e-9)
    assert ray_delta_e(model, np.full(m, -1)) == 0.0


def test_the_ray_model_counts_the_error_where_it_sits_not_where_the_opacity_is():
    """A block of faint band (opacity a_f over nine tenths of its values) with an opaque tenth (a_o) whose error
    sits in the band (opacity moments column 4: the opacity of the values carrying it, a_f): a ray takes
    (1 − (1 − a_f)^λ_e) / a_f unit slabs of it over λ_e = ℓ · (visible share) units, while the block's
    transmittance stays (1 − a)^λ with a = m₂/m₁ and λ = ℓ · m₁²/m₂ (the opaque tenth hides what is behind it).
    Counted at the opaque tenth's opacity, as before, the band's error over the whole block was ~7× too small."""
    a_f, a_o, e, block = 0.01, 0.6, 0.5, 16
    m1, m2 = 0.9 * a_f + 0.1 * a_o, 0.9 * a_f ** 2 + 0.1 * a_o ** 2
    spread = np.zeros((1, 5))
    spread[:, 1] = e
    model = RayModel((1, 1, 1), (16.0, 16.0, 16.0), spread, None, np.array([[m1, m2, 1.0, a_f]]))
    n = (1 - (1 - a_f) ** block) / a_f
    assert ray_delta_e(model, np.ones(1, np.int64)) == pytest.approx(RAY_GAIN * n * e, rel=1e-9)
    a, lam = m2 / m1, block * m1 * m1 / m2
    old = (1 - (1 - a) ** lam) / a  # the block's own opacity and visible share
    assert n / old > 5
