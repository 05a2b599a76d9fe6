"""The service fails fast on object storage (issue 49, item 3): with its own limits on the S3 client (settings
s3_connect_timeout_s, s3_read_timeout_s, s3_retries; service/objectstorage.py) and nothing else configured, the
first request of an outage, a render of a volume not opened before, answers 503 naming the store, instead of
waiting out s3fs' and botocore's retries. moto's S3 on loopback behind the test proxy, cut."""
from __future__ import annotations

import time
import warnings

import pytest

pytest.importorskip("s3fs")
pytest.importorskip("moto")

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

import lodcast  # noqa: E402
from lodcast.service.app import create_app  # noqa: E402
from lodcast.service.settings import Settings  # noqa: E402
from lodcast.service.testing import make_volume, s3_server, tiny_scene  # noqa: E402

BUCKET = "lodcast-fail-fast"
ROOT = f"s3://{BUCKET}/volumes"


def test_the_first_render_of_an_outage_answers_503_within_seconds(tmp_path, monkeypatch):
    import fsspec
    import fsspec.config
    import s3fs

    # the limits the app sets are the process's: put back whatever this test process had before
    monkeypatch.setitem(fsspec.config.conf, "s3", {})
    monkeypatch.setattr(s3fs.S3FileSystem, "retries", s3fs.S3FileSystem.retries)
    make_volume(tmp_path, "cold", n=16)
    with s3_server() as srv:
        fsspec.filesystem("s3", skip_instance_cache=True).mkdir(BUCKET)
        lodcast.ingest(tmp_path / "cold", f"{ROOT}/cold", block_size=8)
        settings = Settings(root=ROOT, state_root=tmp_path / "state", workers=1, token=None)
        with TestClient(create_app(settings)) as client:
            srv.fault = "cut"  # every connection dropped without an answer, from before the volume was ever opened
            try:
                t0 = time.monotonic()
                r = client.post("/volumes/cold/render", json={**tiny_scene(16), "format": "npy"})
                took = time.monotonic() - t0
            finally:
                srv.fault = None
            assert r.status_code == 503, (r.status_code, r.text)
            assert int(r.headers["Retry-After"]) > 0 and f"{ROOT}/cold" in r.json()["detail"], r.json()
            assert took < 20, took  # generous: the point is an answer, not the libraries' half minute of retries
            assert client.post("/volumes/cold/render", json={**tiny_scene(16), "format": "npy"}).status_code == 200
