"""lodcast.environment: the store's and renderer's variables are read when asked (not at import; a renderer reads
them once, when it is made), malformed values are refused naming the variable, and every one of them is in the
README's table."""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest

import lodcast
from lodcast.environment import VARIABLES, EnvironmentInvalid, environment
from lodcast.renderer.frame.render import Renderer

README = Path(__file__).resolve().parents[1] / "README.md"


def test_defaults_and_units(monkeypatch):
    for name, _, _ in VARIABLES:
        monkeypatch.delenv(name, raising=False)
    env = environment()
    assert env.brick_cache_bytes == env.device_cache_bytes == 1024 * 2**20  # MiB
    assert env.device_budget_bytes is None and env.max_voxels is None
    assert env.max_samples == 2_000_000_000 and env.read_threads is None and env.lossless_zeta == 0.5
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    eng = Renderer()
    assert eng.read_threads(remote=False) == max(1, cores - 1) and eng.read_threads(remote=True) == 8
    assert eng.read_threads(remote=False, caller_waits=True) == cores + 1  # readers that place what they read
    assert env.significance_numpy is False and env.tmp is None and env.open_stores == 32
    monkeypatch.setenv("LODCAST_DEVICE_BUDGET_MB", "64")  # docs/design.md, Limits: MB = 10⁶ bytes
    monkeypatch.setenv("LODCAST_MAX_SAMPLES", "2e7")
    monkeypatch.setenv("LODCAST_SIGNIFICANCE_NUMPY", "1")
    monkeypatch.setenv("LODCAST_READ_THREADS", "3")
    env = environment()
    assert env.device_budget_bytes == 64_000_000 and env.max_samples == 20_000_000 and env.significance_numpy
    assert eng.read_threads(remote=False) == max(1, cores - 1)  # made before: its settings are its own
    eng = Renderer()
    assert eng.read_threads(remote=False) == eng.read_threads(remote=True) == 3
    assert eng.settings.device_budget_bytes == 64_000_000 and eng.settings.max_samples == 20_000_000


@pytest.mark.parametrize("name, value", [("LODCAST_BRICK_CACHE_MB", "lots"), ("LODCAST_DEVICE_CACHE_MB", "-1"),
                                         ("LODCAST_DEVICE_BUDGET_MB", "0"), ("LODCAST_DEVICE_BUDGET_MB", "nan"),
                                         ("LODCAST_READ_THREADS", "1.5"), ("LODCAST_READ_THREADS", "0"),
                                         ("LODCAST_MAX_SAMPLES", "many"), ("LODCAST_MAX_VOXELS", "-5"),
                                         ("LODCAST_LOSSLESS_ZETA", "inf"), ("LODCAST_OPEN_STORES", "0"),
                                         ("LODCAST_OPEN_STORES", "2.5")])
def test_malformed_values_are_refused_naming_the_variable(monkeypatch, name, value):
    monkeypatch.setenv(name, value)
    with pytest.raises(EnvironmentInvalid, match=name) as err:
        environment()
    assert isinstance(err.value, ValueError) and repr(value) in str(err.value)


def test_read_when_a_renderer_is_made_not_at_import(monkeypatch, tmp_path):
    """LODCAST_LOSSLESS_ZETA used to be read once at import: a later change did nothing. Now a renderer made after
    the change selects coarser levels for a larger ζ, on the same store and TF; one made before keeps its own."""
    rng = np.random.default_rng(3)
    vol = rng.normal(500, 200, (64, 64, 64)).astype(np.float32)
    store = lodcast.ingest(vol, tmp_path / "v.zarr")
    scene = {"width": 48, "height": 48, "quality": "lossless",
             "tf": {"points": [{"value": 0, "color": [1, 1, 1], "opacity": 0}, {"value": 1000, "color": [1, 0.5, 0.2], "opacity": 0.3}]}}
    monkeypatch.setenv("LODCAST_LOSSLESS_ZETA", "0.5")
    before = Renderer()
    tight = before.render(store, scene).report
    monkeypatch.setenv("LODCAST_LOSSLESS_ZETA", "500")
    loose = Renderer().render(store, scene).report
    assert loose["reduction"] > 2 * tight["reduction"], (tight["reduction"], loose["reduction"])
    assert before.render(store, scene).report["reduction"] == tight["reduction"]


def test_every_variable_is_in_the_readme_table():
    rows = {m.group(1) for m in re.finditer(r"^\| `(LODCAST_[A-Z_]+)`", README.read_text(), re.M)}
    rows |= {m.group(2) for m in re.finditer(r"^\| `(LODCAST_[A-Z_]+)`, `(LODCAST_[A-Z_]+)`", README.read_text(), re.M)}
    missing = [name for name, _, _ in VARIABLES if name not in rows]
    assert not missing, f"README's table of environment variables lacks {missing}"
