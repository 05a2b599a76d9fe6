"""docs/design.md's image error and the error-against-run-time report."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from reference import delta_e as reference_delta_e

import lodcast
from lodcast.renderer.image.delta_e import delta_e_stats
from lodcast.renderer.tools.quality_report import Variant, reference_scene, run_report, write_report


def test_delta_e_matches_the_independent_reference_and_closed_forms():
    rng = np.random.default_rng(2)
    a = rng.random((16, 12, 4))
    b = rng.random((16, 12, 4))
    a[..., :3] *= a[..., 3:]  # premultiplied
    b[..., :3] *= b[..., 3:]
    ours, theirs = delta_e_stats(a, b), reference_delta_e(a, b)
    for k in ("mean", "p95", "max"):
        assert ours[k] == pytest.approx(theirs[k], rel=1e-12)
    white = np.ones((2, 2, 4))
    black = np.zeros((2, 2, 4))
    black[..., 3] = 1.0
    # white over black is L* = 100, u* = v* = 0 against L* = 0: ΔE = 100 exactly (D65 white point)
    assert delta_e_stats(white, black)["mean"] == pytest.approx(100.0, abs=1e-4)  # sRGB matrix rounding
    assert delta_e_stats(white, white) == {"mean": 0.0, "p95": 0.0, "max": 0.0, "footprint": 4}
    assert delta_e_stats(np.zeros((3, 3, 4)), np.zeros((3, 3, 4)))["footprint"] == 0


def test_report_measures_error_against_the_step_quarter_reference(tmp_path: Path):
    zz, yy, xx = np.mgrid[:24, :28, :32]
    vol = np.exp(-(((xx - 16) / 7.0) ** 2 + ((yy - 14) / 6.0) ** 2 + ((zz - 12) / 5.0) ** 2)).astype(np.float32)
    store = lodcast.ingest(vol, tmp_path / "blob.zarr", block_size=8)
    scene = {"camera": {"azimuth": 30, "elevation": 20, "distance": 2.5}, "width": 48, "height": 40,
             "tf": {"points": [{"value": 0.1, "color": [0.2, 0.4, 1.0], "opacity": 0.0},
                               {"value": 1.0, "color": [1.0, 0.8, 0.2], "opacity": 0.3}]},
             "sampling": {"step": 2.0}}
    assert reference_scene(scene, store)["sampling"]["step"] == 0.25
    result = run_report(store, scene, [Variant("full")], repeat=1, log=lambda m: None)
    (row,) = result["rows"]
    # step 2 against step 1/4 on a smooth blob: visible but bounded error (second-order in the step)
    assert 0.05 < row["delta_e_mean"] < 3.0 and row["footprint"] > 200
    assert row["kernel_ms"] > 0 and row["speedup_vs_full"] == pytest.approx(1.0)
    # a reference rendered by the caller is used as given: an empty image makes every pixel of the variant error
    given = lodcast.render(store, reference_scene(scene, store))
    given.rgba[:] = 0.0
    (other,) = run_report(store, scene, [Variant("full")], repeat=1, log=lambda m: None, reference=given)["rows"]
    assert other["delta_e_mean"] > 10 * row["delta_e_mean"]
    paths = write_report(result, tmp_path / "rep")
    assert json.loads(paths["json"].read_text())["rows"][0]["label"] == "full resolution"
    assert "| full resolution |" in paths["table"].read_text()
    assert paths["plot"].stat().st_size > 10_000


def test_report_rows_for_steps_with_and_without_preintegration(tmp_path: Path):
    """default_variants' full-resolution rows: the step's error falls as the step does, the step-¼ row equals the
    reference, and pre-integration's rows say so and reach the table and the plot."""
    from lodcast.renderer.tools.quality_report import STEPS, default_variants

    zz, yy, xx = np.mgrid[:24, :28, :32]
    vol = np.exp(-(((xx - 16) / 7.0) ** 2 + ((yy - 14) / 6.0) ** 2 + ((zz - 12) / 5.0) ** 2)).astype(np.float32)
    store = lodcast.ingest(vol, tmp_path / "blob.zarr", block_size=8)
    scene = {"camera": {"azimuth": 30, "elevation": 20, "distance": 2.5}, "width": 40, "height": 32,
             "tf": {"points": [{"value": 0.4, "color": [1, 0.5, 0.2], "opacity": 0.0},
                               {"value": 0.45, "color": [1, 0.6, 0.3], "opacity": 0.9},
                               {"value": 0.5, "color": [1, 0.7, 0.4], "opacity": 0.0}]}}
    variants = [v for v in default_variants() if v.quality == "full"]
    assert len(variants) == 1 + 2 * len(STEPS)
    result = run_report(store, scene, variants, repeat=1, log=lambda m: None)
    rows = result["rows"]
    point = {r["step"]: r["delta_e_mean"] for r in rows if r["step"] is not None and not r["preintegration"]}
    pre = {r["step"]: r["delta_e_mean"] for r in rows if r["preintegration"]}
    assert point[0.25] == 0.0  # the reference itself
    assert point[2.0] > point[1.0] > point[0.5] > 0.0
    assert pre[2.0] < 0.5 * point[2.0]  # a thin TF band: pre-integration pays at long steps
    assert any(r["label"] == "full resolution, step 2, pre-integrated" for r in rows)
    paths = write_report(result, tmp_path / "rep")
    assert "| full resolution, step 1, pre-integrated |" in paths["table"].read_text()
