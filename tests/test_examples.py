"""Every file in examples/ works as written: each scene renders a picture that shows something, the TF file
renders a CT phantom, each job runs to its end on a local queue; the README there names every file."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

import lodcast

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _head(n: int = 64) -> np.ndarray:
    """MR-like: dark background, a bright scalp shell around softer tissue (arbitrary units, as MR is)."""
    rng = np.random.default_rng(7)
    z, y, x = (np.mgrid[:n, :n, :n] - (n - 1) / 2) / (n / 2)
    r = np.sqrt((z / 0.8) ** 2 + (y / 0.9) ** 2 + (x / 0.75) ** 2)
    vol = np.where(r < 1.0, 90.0, 4.0) + rng.normal(0, 3, r.shape)
    vol[(r > 0.88) & (r < 1.0)] = 160.0
    return np.clip(vol, 0, 255).astype(np.float32)


def _shows_something(rgba: np.ndarray, background: tuple = (0, 0, 0)) -> None:
    colour = rgba[..., :3] - np.asarray(background, np.float32) * (1 - rgba[..., 3:4])
    lit = (np.abs(colour).max(axis=-1) > 0.05).mean()
    assert 0.1 < lit < 0.95 and rgba[..., :3].std() > 0.05, (lit, rgba[..., :3].std())


@pytest.fixture(scope="module")
def root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("examples")
    lodcast.ingest(_head(), root / "ch2.zarr")
    return root


@pytest.mark.parametrize("name", sorted(p.name for p in EXAMPLES.glob("*.scene.json")))
def test_each_scene_renders_a_picture(root, name):
    scene = json.loads((EXAMPLES / name).read_text())
    result = lodcast.render(root / "ch2.zarr", str(EXAMPLES / name))  # a scene file's name, as the README says
    assert result.rgba.shape == (scene["height"], scene["width"], 4)
    assert result.rgba[..., 3].min() == pytest.approx(1.0)  # an opaque background: a picture for people
    _shows_something(result.rgba)


def test_the_tf_file_renders_a_ct_phantom(tmp_path):
    z, y, x = np.mgrid[:48, :48, :48] - 23.5
    r = np.sqrt(z**2 + y**2 + x**2) / 20
    ct = np.where(r < 1, 40.0, -1000.0)
    ct[(r > 0.5) & (r < 0.6)] = 800.0
    store = lodcast.ingest(ct.astype(np.float32), tmp_path / "ct.zarr")
    tf = json.loads((EXAMPLES / "ct-skin-bone.tf.json").read_text())
    result = lodcast.render(store, {"width": 96, "height": 96, "tf": tf, "shading": {}, "background": [0, 0, 0, 1]})
    _shows_something(result.rgba)


@pytest.mark.parametrize("name", sorted(p.name for p in EXAMPLES.glob("*.job.json")))
def test_each_job_runs_to_its_end(root, name):
    from lodcast.service.jobs import parse_job, plan_frames, validate_job
    from lodcast.service.queue import JobQueue, Worker
    from lodcast.service.settings import Settings

    jq = JobQueue(Settings(root=root, poll_s=0.05, token=None))
    job = validate_job(parse_job(json.loads((EXAMPLES / name).read_text())), jq.settings, jq.engine)
    rec = jq.submit(job)
    worker = Worker(jq, threads=1).start()
    try:
        t = time.monotonic()
        while jq.get(rec["id"])["state"] in ("queued", "running") and time.monotonic() - t < 300:
            time.sleep(0.1)
    finally:
        worker.stop()
    st = jq.get(rec["id"])
    assert st["state"] == "done", st
    frames = sorted(jq.job_dir(rec["id"]).glob("frame_*.png"))
    assert len(frames) == len(plan_frames(job)) >= 2
    from PIL import Image

    first = np.asarray(Image.open(frames[0]).convert("RGBA"), np.float32) / 255
    _shows_something(first)
    if getattr(job, "animation", None):
        assert any(jq.job_dir(rec["id"]).glob("*.gif"))


def test_the_examples_readme_names_every_file():
    text = (EXAMPLES / "README.md").read_text()
    files = sorted(p.name for p in EXAMPLES.iterdir() if p.name != "README.md")
    assert files and all(f"`{f}`" in text for f in files), [f for f in files if f"`{f}`" not in text]
