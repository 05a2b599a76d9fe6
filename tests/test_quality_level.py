"""`"quality": {"level": k}`: every visible block at store level k, with its predicted ΔE (issue 45, item 5): the
bound a selection of about that reduction starts from."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import lodcast
from lodcast.renderer.image.delta_e import delta_e_stats
from lodcast.renderer.lod.selection import select_lod
from lodcast.renderer.scene.scene import QualityLevel, Scene, SceneError
from lodcast.renderer.scene.transfer_function import CT_PRESETS
from lodcast.renderer.tools.cli_render import _quality

TF = {"points": [{"value": 0.2, "color": [1.0, 0.8, 0.6], "opacity": 0.0},
                 {"value": 0.8, "color": [1.0, 1.0, 1.0], "opacity": 0.6}]}


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory):
    return lodcast.ingest(_ball(), tmp_path_factory.mktemp("lv") / "ball.zarr", block_size=8, progress=False)


SCENE = {"camera": {"azimuth": 30, "elevation": 20}, "width": 64, "height": 64, "tf": TF, "format": "npy"}


@pytest.mark.parametrize("k", [0, 1, 2, 3])
def test_every_visible_block_at_the_level(eng, store, k):
    r = eng.render(store, {**SCENE, "quality": {"level": k}})
    t = Scene.parse(SCENE).tf
    lossless = select_lod(store, [t], "lossless")
    visible = lossless.levels >= 0
    sel = select_lod(store, [t], {"level": k})
    assert np.array_equal(sel.levels >= 0, visible) and (sel.levels[visible] == k).all()
    assert visible.sum() < visible.size  # the empty corners are left out
    rep = r.report
    assert rep["quality"] == {"level": k} and rep["level"] == k
    assert rep["reduction"] == pytest.approx(store.layout.n_blocks / visible.sum() * 8 ** k, rel=1e-6)
    # the same image as those levels given explicitly
    explicit = eng.render(store, {**SCENE, "quality": {"level": k}}, levels=sel.levels)
    assert np.array_equal(r.rgba, explicit.rgba)
    full = eng.render(store, SCENE)
    de = delta_e_stats(r.rgba, full.rgba)
    if k == 0:  # level 0 is full resolution: predicted and measured the same, to float rounding
        assert sel.predicted_delta_e == 0.0
        assert de["max"] <= 0.05, de
    else:  # each level loses more, and says so
        coarser = select_lod(store, [t], {"level": k - 1})
        assert sel.predicted_delta_e > coarser.predicted_delta_e
        assert de["mean"] > 0.0


def test_level_predicts_what_level_1_measures_on_the_chest_ct(eng, shared_data: Path, tmp_path: Path):
    """The level-1 bound on the chest CT under ct-bone, against the step-¼ reference (what a report's predicted ΔE
    predicts): docs/design.md's "within 2×" where the measured mean is at least 0.3."""
    ct = lodcast.ingest(shared_data / "ct_chest_dicom", tmp_path / "ct.zarr", progress=False)
    sc = {"camera": {"azimuth": 30, "elevation": 15, "distance": 1.9}, "width": 128, "height": 128,
          "tf": CT_PRESETS["ct-bone"], "format": "npy"}
    ref = eng.render(ct, {**sc, "sampling": {"step": 0.25}})
    r = eng.render(ct, {**sc, "quality": {"level": 1}})
    measured, predicted = delta_e_stats(r.rgba, ref.rgba)["mean"], r.report["predicted_delta_e"]
    assert measured >= 0.3 and 0.5 <= predicted / measured <= 2.0, (predicted, measured)
    assert r.report["reduction"] > 25.0  # every visible block at level 1: 34:1 (docs/lod.md)


def test_a_level_the_store_does_not_have_is_refused(eng, store):
    with pytest.raises(SceneError, match=r"^quality\.level: 4 is past the store's coarsest level, 3"):
        eng.render(store, {**SCENE, "quality": {"level": 4}})
    for bad in (-1, 1.5, "1", True, 16):
        with pytest.raises(SceneError, match="level"):
            Scene.parse({**SCENE, "quality": {"level": bad}})
    assert Scene.parse({**SCENE, "quality": {"level": 2}}).quality == QualityLevel(level=2)


def test_cli_and_http_take_it(tmp_path: Path):
    assert _quality("level2") == {"level": 2} and _quality('{"level": 1}') == {"level": 1}
    from fastapi.testclient import TestClient

    from lodcast.service.app import create_app
    from lodcast.service.settings import Settings

    root = tmp_path / "root"
    root.mkdir()
    lodcast.ingest(_ball(), root / "ball", block_size=8, progress=False)
    with TestClient(create_app(Settings(root=root, workers=0))) as c:
        scene = {**SCENE, "quality": {"level": 1}}
        r = c.post("/volumes/ball/render", json=scene)
        assert r.status_code == 200, r.text
        rep = json.loads(r.headers["X-Lodcast-Report"])
        assert rep["quality"] == {"level": 1} and rep["level"] == 1 and rep["predicted_delta_e"] > 0
        r = c.post("/volumes/ball/render", json={**scene, "quality": {"level": 9}})
        assert r.status_code == 422 and "quality.level" in r.text, r.text
        r = c.post("/volumes/ball/render", json={**scene, "quality": {"level": -1}})
        assert r.status_code == 422 and "level" in r.text, r.text


def _ball() -> np.ndarray:
    """A ball with a ramp inside and empty corners (blocks the TF does not show), 64³: in 8³ blocks, 4 levels."""
    n = 64
    z, y, x = np.mgrid[0:n, 0:n, 0:n].astype(np.float32)
    r = np.sqrt((x - 31.5) ** 2 + (y - 31.5) ** 2 + (z - 31.5) ** 2)
    return np.where(r < 26, 0.3 + 0.6 * x / n, 0.0).astype(np.float32)


def test_progressive_ends_at_the_level(eng, store):
    stages = list(eng.render_progressive(store, {**SCENE, "quality": {"level": 1}}))
    plain = eng.render(store, {**SCENE, "quality": {"level": 1}})
    assert stages[-1].report["final"] and np.array_equal(stages[-1].rgba, plain.rgba)
