"""Stores named by path are opened once per renderer (store/opened.py, each renderer's OpenStores): a series of renders of a path reads the
store's metadata and walks its data manifest once, and a store replaced or removed at that path is seen. How many
stay opened is a setting (LODCAST_OPEN_STORES, or the renderer's and the service's `open_stores`): the (N+1)-th
store closes the least recently used one, which reopens when asked for again, its cached bricks serving on; the
caches' bytes stay within their bounds whatever the number of volumes."""
from __future__ import annotations

import shutil
import threading

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


def _stores(tmp_path, n: int) -> list:
    paths = []
    for i in range(n):
        v = np.random.default_rng(i).normal(2.0, 1.0, (32, 32, 32)).astype(np.float32)
        v[8:24, 8:24, 8:24] += 1 + i  # each volume its own picture
        lodcast.ingest(v, tmp_path / f"s{i}.zarr", block_size=8)
        paths.append(tmp_path / f"s{i}.zarr")
    return paths


REDUCED = {**SCENE, "quality": {"reduction": 2}}  # an atlas of bricks from the brick pool


def test_the_bound_on_opened_stores_is_a_setting(monkeypatch, tmp_path):
    from lodcast.environment import EnvironmentInvalid
    from lodcast.renderer.frame.render import Renderer

    monkeypatch.setenv("LODCAST_OPEN_STORES", "3")
    assert Renderer().stores.max_open == 3
    assert Renderer(open_stores=1).stores.max_open == 1  # the keyword overrides the variable
    monkeypatch.delenv("LODCAST_OPEN_STORES")
    assert Renderer().stores.max_open == 32
    for bad in (0, 2.5, True):
        with pytest.raises(EnvironmentInvalid, match="open_stores"):
            Renderer(open_stores=bad)


def test_the_next_volume_closes_the_least_recently_used_store_which_reopens_transparently(tmp_path, counted_manifests):
    from lodcast.renderer.frame.render import Renderer

    paths = _stores(tmp_path, 3)
    eng = Renderer(open_stores=2)
    counted_manifests.clear()
    first = [eng.render(p, REDUCED) for p in paths[:2]]
    eng.render(paths[0], REDUCED)  # s0 is now the more recently used of the two
    eng.render(paths[2], REDUCED)  # the third store: s1 goes
    assert [eng.stores.kept(p) for p in paths] == [True, False, True] and len(eng.stores) == 2
    assert len(counted_manifests) == 3
    again = eng.render(paths[1], REDUCED)  # opened anew (s0 goes now), the same picture from the cached bricks
    assert len(counted_manifests) == 4 and eng.stores.kept(paths[1]) and not eng.stores.kept(paths[0])
    np.testing.assert_array_equal(again.rgba, first[1].rgba)
    assert again.report["bricks_read"] == 0 and again.report["bricks_cached"] > 0
    assert not np.array_equal(first[0].rgba, first[1].rgba)  # (the volumes differ: no store stood in for another)


def test_cache_bytes_stay_within_their_bounds_across_volumes(tmp_path):
    from lodcast.renderer.frame.render import Renderer

    paths = _stores(tmp_path, 4)
    eng = Renderer(open_stores=2, brick_cache_mb=0.4, device_cache_mb=0.25)  # (the pool: room for two volumes)
    s = eng.settings
    for p in [*paths, *paths]:
        report = eng.render(p, REDUCED).report
        assert report["bricks_read"] + report["bricks_cached"] > 0
        assert 0 < eng.bricks.nbytes <= s.brick_cache_bytes
        assert eng.device_cache.nbytes <= s.device_cache_bound or len(eng.device_cache) == 1  # the newest stays
        assert len(eng.stores) <= 2
    # one pool across volumes: the last three volumes' bricks pushed the first one's out
    assert eng.render(paths[0], REDUCED).report["bricks_read"] > 0


def test_a_store_on_object_storage_is_trusted_for_check_s(tmp_path):
    """What the service's `store_check_s` sets: a store named by URL (here file://, read through fsspec as s3://
    is) is not asked again whether it was replaced until check_s has passed; with 0 it is asked every time."""
    lodcast.ingest(_volume(1.0), tmp_path / "v.zarr", block_size=8)
    url = f"file://{tmp_path / 'v.zarr'}"
    trusting, asking = OpenStores(check_s=3600), OpenStores()
    a, b = trusting.get(url), asking.get(url)
    assert trusting.recent(url) and not asking.recent(url)
    lodcast.ingest(_volume(4.0), tmp_path / "v.zarr", block_size=8, overwrite=True)
    assert trusting.get(url) is a and asking.get(url) is not b
    assert not trusting.recent(tmp_path / "v.zarr")  # a local path is a stat away: always asked
    with pytest.raises(ValueError, match="check_s"):
        OpenStores(check_s=-1)


def test_the_service_keeps_its_opened_stores_in_its_renderer_under_the_same_bound(tmp_path):
    from fastapi.testclient import TestClient

    from lodcast.service.app import create_app
    from lodcast.service.settings import Settings
    from lodcast.service.testing import make_volume, tiny_scene

    for name in ("a", "b", "c"):
        make_volume(tmp_path, name)
    app = create_app(Settings(root=tmp_path, workers=0, token=None, open_stores=2))
    stores = app.state.engine.renderer.stores
    assert stores.max_open == 2
    scene = {**tiny_scene(16), "format": "npy"}
    with TestClient(app) as client:
        first = client.post("/volumes/a/render", json=scene)
        for name in ("b", "c"):
            assert client.post(f"/volumes/{name}/render", json=scene).status_code == 200
        assert [stores.kept(tmp_path / n) for n in "abc"] == [False, True, True]
        again = client.post("/volumes/a/render", json=scene)
        assert again.status_code == 200 and again.content == first.content
        assert [stores.kept(tmp_path / n) for n in "abc"] == [True, False, True]


def test_callers_that_ask_for_a_store_together_share_one_open(tmp_path, monkeypatch):
    """Two renders of a volume arriving together (two viewers joining it): the second waits for the first's open
    and gets the same store, so that what the renderer keys by the store (its per-TF tables) is computed once."""
    from lodcast.store import opened

    dest = tmp_path / "v.zarr"
    lodcast.ingest(_volume(1.0), dest, block_size=8)
    opens, inside, release, second = [], threading.Event(), threading.Event(), threading.Event()
    real_open, real_stamp = store_module.open_store, opened.stamp

    def slow_open(location):
        opens.append(location)
        inside.set()
        release.wait(60)
        return real_open(location)

    def stamp(key):
        if inside.is_set():
            second.set()  # the second caller is past its check: next it opens the store, or waits for the first
        return real_stamp(key)

    monkeypatch.setattr(store_module, "open_store", slow_open)
    monkeypatch.setattr(opened, "stamp", stamp)
    kept, got = OpenStores(), [None, None]
    first = threading.Thread(target=lambda: got.__setitem__(0, kept.get(dest)))
    first.start()
    assert inside.wait(60)
    other = threading.Thread(target=lambda: got.__setitem__(1, kept.get(dest)))
    other.start()
    assert second.wait(60)
    release.set()
    first.join(60)
    other.join(60)
    assert len(opens) == 1 and got[0] is not None and got[0] is got[1]
