"""Stores on object storage (issue 14 item 3): a real S3-compatible server (moto's server mode on loopback, behind a
counting proxy: tests/s3server.py) holds an ingested store; rendering it through fsspec (s3fs) gives the image of
the local store, bit for bit, with few requests: the shard-level reader fetches a shard's index with one suffix
range request and its needed chunks in spans, where zarr-python would ask once per chunk."""
from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("s3fs")
pytest.importorskip("moto")

import lodcast  # noqa: E402
from lodcast.errors import StoreCorrupt, StoreNotFound  # noqa: E402
from lodcast.service.testing import s3_server  # noqa: E402

TF = {"points": [{"value": -50, "color": [0.2, 0.4, 0.9], "opacity": 0.0},
                 {"value": 60, "color": [0.9, 0.6, 0.3], "opacity": 0.05},
                 {"value": 150, "color": [1, 1, 1], "opacity": 0.6}]}


def _field(shape=(70, 64, 80)) -> np.ndarray:
    z, y, x = np.mgrid[: shape[0], : shape[1], : shape[2]]
    return ((np.sin(x / 5.0) * np.cos(y / 7.0) + np.sin(z / 6.0)) * 100).astype(np.float32)


@pytest.fixture(scope="module")
def s3(tmp_path_factory):
    import fsspec

    local = lodcast.ingest(_field(), tmp_path_factory.mktemp("s3") / "v.zarr", progress=False)
    with s3_server() as srv:
        fs = fsspec.filesystem("s3", skip_instance_cache=True)
        fs.mkdir("lodcast-test")
        fs.put(str(local.location), "lodcast-test/v.zarr", recursive=True)
        yield srv, local, fs


def _fresh(eng):
    eng.bricks.clear()
    eng.device_cache.clear()


def _opened(eng):
    """The store on S3, opened, its per-block statistics and histograms read (what every first render of a store
    reads once, through zarr-python), and no bricks cached."""
    remote = lodcast.open_store("s3://lodcast-test/v.zarr")
    eng.selections.clear()  # so that this render reads the histograms the selection needs
    eng.walks.clear()  # and the cell ranges its walk needs (an earlier store object's walk would do)
    eng.render(remote, {"tf": TF, "width": 8, "height": 8, "quality": {"reduction": 8}})
    _fresh(eng)
    return remote


@pytest.mark.parametrize("quality", ["full", "lossless", {"reduction": 8}])
def test_a_store_on_s3_renders_the_local_image(eng, s3, quality):
    srv, local, _ = s3
    # the view-independent selection (lod_visibility off), so that a camera change below selects the same bricks
    scene = {"tf": TF, "width": 64, "height": 56, "quality": quality, "sampling": {"lod_visibility": False}}
    _fresh(eng)
    ref = eng.render(local, scene)
    remote = _opened(eng)
    assert remote.shape == local.shape and remote.block_size == local.block_size
    srv.reset()
    got = eng.render(remote, scene)
    n, nbytes = srv.counts()
    assert np.array_equal(got.rgba, ref.rgba)
    bricks = got.report["bricks_read"]
    ranged = [p for m, p, r, _ in srv.requests if r]
    assert bricks > 0 and 0 < n < bricks, (n, bricks)  # per-chunk reads would take at least `bricks`
    assert len(ranged) <= 2 * len(set(ranged))  # per shard object: its index and one span
    # byte ranges only, but for the metadata of arrays this store object had not opened yet
    assert all((m == "GET" and r) or p.endswith("zarr.json") for m, p, r, _ in srv.requests), srv.requests
    on_s3 = sum(f["size"] for f in s3[2].find("lodcast-test/v.zarr", detail=True).values())
    assert nbytes < on_s3  # only what the selection needs (full resolution: level 0, not the other levels)
    srv.reset()
    again = eng.render(remote, {**scene, "camera": {"azimuth": 70}})
    assert srv.counts() == (0, 0) and again.report["bricks_read"] == 0  # a camera change reads nothing
    if not isinstance(quality, str):  # the selection weighed by the view reads its coarse level from S3 as well
        seen = {**scene, "sampling": {}, "camera": {"azimuth": 150}}
        np.testing.assert_array_equal(eng.render(remote, seen).rgba, eng.render(local, seen).rgba)


def test_lod_reads_whole_shards_in_few_requests(eng, s3):
    srv, local, _ = s3
    remote = _opened(eng)
    srv.reset()
    eng.render(remote, {"tf": TF, "width": 32, "height": 32, "quality": {"reduction": 8}})
    ranged = [p for m, p, r, _ in srv.requests if m == "GET" and r]
    assert ranged and max(Counter(ranged).values()) <= 2  # per shard object: its index (once), then one span


def test_damaged_and_missing_stores_on_s3_say_so(eng, s3):
    srv, local, fs = s3
    with pytest.raises(StoreNotFound):
        lodcast.open_store("s3://lodcast-test/nothing-here.zarr")
    fs.copy("lodcast-test/v.zarr", "lodcast-test/broken.zarr", recursive=True)
    shard = sorted(p for p in fs.find("lodcast-test/broken.zarr/0") if "/c/" in p)[0]
    fs.rm(shard)
    _fresh(eng)
    broken = lodcast.open_store("s3://lodcast-test/broken.zarr")
    with pytest.raises(StoreCorrupt, match="shard file missing"):
        eng.render(broken, {"tf": TF, "width": 16, "height": 16})


def test_the_cli_renders_and_describes_a_store_on_s3(eng, s3, tmp_path):
    import json
    import subprocess
    import sys

    tf = tmp_path / "tf.json"
    tf.write_text(json.dumps(TF))
    out = tmp_path / "v.png"
    run = subprocess.run([sys.executable, "-m", "lodcast.service.cli", "render", "s3://lodcast-test/v.zarr", "-o",
                          str(out), "--tf", str(tf), "--width", "32", "--height", "32"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert out.stat().st_size > 100
    info = subprocess.run([sys.executable, "-m", "lodcast.service.cli", "info", "s3://lodcast-test/v.zarr"],
                          capture_output=True, text=True)
    assert info.returncode == 0, info.stderr
    assert json.loads(info.stdout)["shape"] == list(_field().shape)
    missing = subprocess.run([sys.executable, "-m", "lodcast.service.cli", "info", "s3://lodcast-test/none.zarr"],
                             capture_output=True, text=True)
    assert missing.returncode == 2 and "no store at s3://lodcast-test/none.zarr" in missing.stderr
    src = tmp_path / "v.npy"
    np.save(src, _field((12, 16, 20)))
    ing = subprocess.run([sys.executable, "-m", "lodcast.service.cli", "ingest", str(src), "s3://lodcast-test/cli.zarr"],
                         capture_output=True, text=True)
    assert ing.returncode == 0, ing.stderr
    assert "s3://lodcast-test/cli.zarr: 12x16x20 float32" in ing.stdout, ing.stdout
    again = subprocess.run([sys.executable, "-m", "lodcast.service.cli", "ingest", str(src),
                            "s3://lodcast-test/cli.zarr"], capture_output=True, text=True)
    assert again.returncode == 2 and "--overwrite" in again.stderr


def test_ingest_publishes_to_s3_with_the_root_metadata_last(eng, s3, monkeypatch):
    """`lodcast.ingest(..., "s3://...")`: written locally, then uploaded with the root zarr.json last, so a reader
    never finds half a store; a killed upload leaves none, and the next ingest cleans up after it."""
    from lodcast.errors import StoreExists
    from lodcast.store import remote

    srv, local, fs = s3
    url = "s3://lodcast-test/ingested.zarr"
    a = _field((20, 24, 28))
    st = lodcast.ingest(a, url, progress=False)
    assert st.location == url and np.array_equal(st.read_level(0), a)
    scene = {"tf": TF, "width": 24, "height": 24, "quality": {"reduction": 4}}
    eng.render(st, scene)  # fills the caches with this version
    with pytest.raises(StoreExists):
        lodcast.ingest(a, url, progress=False)
    # a failure after part of the upload (what a kill leaves): there is no store at the URL
    calls = []

    def failing(fs_, lp, rp):
        calls.append(len(lp))
        if len(calls) == 1:
            fs_.put(lp[: len(lp) // 2], rp[: len(rp) // 2])
            raise OSError("connection lost")
        raise AssertionError("the root metadata must not be uploaded after a failure")

    monkeypatch.setattr(remote, "_put", failing)
    with pytest.raises(OSError, match="connection lost"):
        lodcast.ingest(a + 1, url, overwrite=True, progress=False)
    assert not fs.exists("lodcast-test/ingested.zarr/zarr.json")
    assert fs.find("lodcast-test/ingested.zarr")  # half an upload's objects, but no store
    with pytest.raises(StoreNotFound):
        lodcast.open_store(url)
    monkeypatch.undo()
    st = lodcast.ingest(a + 2, url, progress=False)  # no store there: no --overwrite needed, leftovers removed
    assert np.array_equal(st.read_level(0), a + 2)
    ref = lodcast.ingest(a + 2, Path(s3[1].location).parent / "same.zarr", progress=False)
    got = sorted(p.removeprefix("lodcast-test/ingested.zarr/") for p in fs.find("lodcast-test/ingested.zarr"))
    want = sorted(p.relative_to(ref.location).as_posix() for p in Path(ref.location).rglob("*") if p.is_file())
    assert got == want  # the same objects as the local store, nothing left of the failed upload
    # the rewritten store renders its own data: no cache keeps the old version (keys carry the ingest's id)
    assert np.array_equal(eng.render(lodcast.open_store(url), scene).rgba, eng.render(ref, scene).rgba)


def test_swapped_shards_and_edited_metadata_on_s3_are_caught(eng, s3):
    """On object storage as locally: opening checks the manifest and every array's zarr.json (one small request
    each), and each shard's index against the manifest when it is first read, so two level-0 shards swapped (each
    passing its own checksums) or a level's zarr.json edited never render."""
    srv, local, fs = s3
    fs.copy("lodcast-test/v.zarr", "lodcast-test/swapped.zarr", recursive=True)
    a, b = sorted(p for p in fs.find("lodcast-test/swapped.zarr/0") if "/c/" in p)[:2]
    da, db = fs.cat_file(a), fs.cat_file(b)
    assert da != db
    fs.pipe_file(a, db)
    fs.pipe_file(b, da)
    _fresh(eng)
    swapped = lodcast.open_store("s3://lodcast-test/swapped.zarr")
    with pytest.raises(StoreCorrupt, match="swapped or replaced"):
        eng.render(swapped, {"tf": TF, "width": 16, "height": 16})
    fs.copy("lodcast-test/v.zarr", "lodcast-test/edited.zarr", recursive=True)
    meta = json.loads(fs.cat_file("lodcast-test/edited.zarr/0/zarr.json"))
    meta["attributes"] = {"edited": True}  # valid metadata of the same array, not the bytes ingest wrote
    fs.pipe_file("lodcast-test/edited.zarr/0/zarr.json", json.dumps(meta).encode())
    with pytest.raises(StoreCorrupt, match="zarr.json"):
        lodcast.open_store("s3://lodcast-test/edited.zarr")
    intact = lodcast.open_store("s3://lodcast-test/v.zarr")
    np.testing.assert_array_equal(eng.render(intact, {"tf": TF, "width": 16, "height": 16, "format": "npy"}).rgba,
                                  eng.render(local, {"tf": TF, "width": 16, "height": 16, "format": "npy"}).rgba)
