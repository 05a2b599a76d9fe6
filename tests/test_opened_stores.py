"""Stores named by path are opened once per renderer (store/opened.py, each renderer's OpenStores): a series of renders of a path reads the
store's metadata and walks its data manifest once, and a store replaced or removed at that path is seen."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

import lodcast
from lodcast.errors import StoreNotFound
from lodcast.store import store as store_module
from lodcast.store.opened import OpenStores

TF = {"points": [{"value": 0.0, "color": [1, 1, 1], "opacity": 0.0}, {"value": 4.0, "color": [1, 1, 1], "opacity": 0.5}]}
SCENE = {"tf": TF, "width": 24, "height": 24, "format": "npy", "camera": {"azimuth": 20, "elevation": 10}}


def _volume(value: float) -> np.ndarray:
    v = np.zeros((16, 16, 16), np.float32)
    v[4:12, 4:12, 4:12] = value
    return v


@pytest.fixture
def counted_manifests(monkeypatch):
    """The number of data-manifest walks (one per open of a local store)."""
    calls = []
    real = store_module.data_manifest
    monkeypatch.setattr(store_module, "data_manifest", lambda root: calls.append(root) or real(root))
    return calls


def test_renders_of_a_path_open_the_store_once(eng, tmp_path, counted_manifests, monkeypatch):
    dest = tmp_path / "v.zarr"
    lodcast.ingest(_volume(3.0), dest, block_size=8)
    counted_manifests.clear()
    first = eng.render(str(dest), SCENE)
    assert len(counted_manifests) == 1
    for cam in (30, 40):  # new views, a relative path and a Path: the same opened store
        monkeypatch.chdir(tmp_path)
        again = eng.render("v.zarr", {**SCENE, "camera": {"azimuth": cam, "elevation": 10}})
        assert again.rgba[..., 3].max() > 0.1
    np.testing.assert_array_equal(eng.render(dest, SCENE).rgba, first.rgba)
    assert len(counted_manifests) == 1
    assert eng.stores.get(dest) is eng.stores.get(str(dest))


def test_a_store_replaced_or_removed_at_its_path_is_seen(eng, tmp_path, counted_manifests):
    dest = tmp_path / "v.zarr"
    lodcast.ingest(_volume(1.0), dest, block_size=8)
    dim = eng.render(dest, SCENE).rgba
    held = eng.stores.get(dest)
    lodcast.ingest(_volume(4.0), dest, block_size=8, overwrite=True)  # a new folder renamed into place
    bright = eng.render(dest, SCENE).rgba
    assert eng.stores.get(dest) is not held
    # the TF's opacity rises from 0 at value 0 to 0.5 at 4: the replaced volume is the more opaque
    assert bright[..., 3].max() > dim[..., 3].max() + 0.1
    shutil.rmtree(dest)
    with pytest.raises(StoreNotFound):
        eng.render(dest, SCENE)


def test_open_stores_keeps_the_most_recently_used(tmp_path):
    paths = [tmp_path / f"s{i}.zarr" for i in range(3)]
    for p in paths:
        lodcast.ingest(_volume(2.0), p, block_size=8)
    kept = OpenStores(max_open=2)
    a, b = kept.get(paths[0]), kept.get(paths[1])
    assert kept.get(paths[0]) is a  # used again: now the most recent
    kept.get(paths[2])  # drops b, the least recently used
    assert kept.get(paths[0]) is a and kept.get(paths[1]) is not b
    kept.forget(paths[0])
    assert kept.get(paths[0]) is not a
    with pytest.raises(ValueError, match="max_open"):
        OpenStores(max_open=0)
