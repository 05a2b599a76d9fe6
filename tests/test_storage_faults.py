"""Storage faults heal (issue 49, items 2 and 5): real processes on loopback. moto's S3 server behind the test proxy
(lodcast.service.testing.s3_server), which can cut every connection or answer S3's throttling 503 SlowDown; a
redis-server that is killed. During an outage a render of a volume whose bricks are cached answers 200, anything
that needs the storage 503 with Retry-After naming the store, never a 500; a job across an outage resumes and ends
done once; /healthz and /readyz name the component that is down.

The S3 client is told to give up after one try here (fsspec's config for s3), so that each refused request takes a
moment instead of s3fs' and botocore's retries; what the service answers does not depend on it."""
from __future__ import annotations

import errno
import threading
import time
import warnings

import pytest

pytest.importorskip("s3fs")
pytest.importorskip("moto")

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from fastapi import FastAPI
    from fastapi.testclient import TestClient

import lodcast  # noqa: E402
from lodcast.errors import StoreInvalid  # noqa: E402
from lodcast.faults import storage_fault  # noqa: E402
from lodcast.service.app import create_app  # noqa: E402
from lodcast.service.faults import install  # noqa: E402
from lodcast.service.settings import Settings  # noqa: E402
from lodcast.service.testing import RedisServer, make_volume, redis_available, s3_server, tiny_scene  # noqa: E402

BUCKET = "lodcast-faults"
ROOT = f"s3://{BUCKET}/volumes"
QUICK_S3 = {"config_kwargs": {"retries": {"max_attempts": 1}, "connect_timeout": 2, "read_timeout": 5}}


@pytest.fixture(scope="module")
def outage(tmp_path_factory):
    import fsspec.config

    base = tmp_path_factory.mktemp("faults")
    local = base / "local"
    local.mkdir()
    make_volume(local, "tiny")
    for fault in ("cut", "slowdown"):  # a volume never rendered before its outage, one per kind of fault
        make_volume(local, fault, n=16)
    saved = fsspec.config.conf.get("s3")
    fsspec.config.conf["s3"] = QUICK_S3
    try:
        with s3_server() as srv:
            fs = fsspec.filesystem("s3", skip_instance_cache=True)
            fs.mkdir(BUCKET)
            for name in ("tiny", "cut", "slowdown"):
                lodcast.ingest(local / name, f"{ROOT}/{name}", block_size=8)
            settings = Settings(root=ROOT, state_root=base / "state", workers=1, poll_s=0.05, storage_backoff_s=0.5,
                                storage_retries=8, store_check_s=0.2, health_every_s=0.1)
            with TestClient(create_app(settings)) as client:
                yield client, srv
                srv.fault = None
    finally:
        if saved is None:
            fsspec.config.conf.pop("s3", None)
        else:
            fsspec.config.conf["s3"] = saved


def _unavailable(r, store: str) -> None:
    assert r.status_code == 503, (r.status_code, r.text)
    assert int(r.headers["Retry-After"]) > 0
    assert store in r.json()["detail"] and "unavailable" in r.json()["detail"], r.json()


@pytest.mark.parametrize("fault", ["cut", "slowdown"])
def test_an_outage_is_503_naming_the_store_and_cached_volumes_keep_rendering(outage, fault):
    client, srv = outage
    scene = {**tiny_scene(24), "format": "npy"}
    before = client.post("/volumes/tiny/render", json=scene)
    assert before.status_code == 200
    srv.fault = fault
    try:
        time.sleep(0.3)  # past store_check_s: the next render asks the storage again, and cannot
        for _ in range(3):
            r = client.post("/volumes/tiny/render", json=scene)
            assert r.status_code == 200, r.text  # its bricks are cached
            assert r.content == before.content
        _unavailable(client.post(f"/volumes/{fault}/render", json={**scene, "width": 20}), f"{ROOT}/{fault}")
        _unavailable(client.get("/volumes"), ROOT)
        _unavailable(client.get(f"/volumes/{fault}"), f"{ROOT}/{fault}")
    finally:
        srv.fault = None
    assert [v["id"] for v in client.get("/volumes").json()] == ["cut", "slowdown", "tiny"]  # healed at once
    assert client.post(f"/volumes/{fault}/render", json={**scene, "width": 20}).status_code == 200


def test_a_job_across_an_outage_resumes_and_ends_done_once(outage):
    client, srv = outage
    job = client.post("/jobs", json={"kind": "turntable", "volume": "tiny", "scene": tiny_scene(16), "frames": 6})
    assert job.status_code == 202
    jid = job.json()["id"]
    deadline = time.monotonic() + 60
    while client.get(f"/jobs/{jid}").json()["state"] != "running" and time.monotonic() < deadline:
        time.sleep(0.02)
    srv.fault = "cut"  # its results go to ROOT/.jobs on the same storage: their writes fail
    seen_retry = False
    try:
        end = time.monotonic() + 3.0
        while time.monotonic() < end:
            st = client.get(f"/jobs/{jid}").json()
            assert st["state"] in ("running", "done"), st
            seen_retry |= "storage fault" in (st["error"] or "")
            time.sleep(0.1)
    finally:
        srv.fault = None
    while (st := client.get(f"/jobs/{jid}").json())["state"] == "running" and time.monotonic() < deadline + 60:
        time.sleep(0.1)
    assert st["state"] == "done" and st["error"] is None, st
    assert st["progress"] == {"done": 6, "total": 6}
    assert seen_retry or st["state"] == "done"
    frames = [client.get(f"/jobs/{jid}/results/{n}") for n in range(6)]
    assert all(f.status_code == 200 and f.content[:4] == b"\x89PNG" for f in frames)


def test_health_names_the_store_root_when_object_storage_is_down(outage):
    client, srv = outage
    assert client.get("/readyz").status_code == 200 or _settle(client, "/readyz", 200)
    srv.fault = "cut"
    try:
        r = _settle(client, "/readyz", 503)
        assert r.json()["detail"].startswith("store_root: down"), r.json()
        h = client.get("/healthz").json()
        assert h["status"] == "degraded" and h["components"]["store_root"]["status"] == "down"
        assert h["components"]["queue"]["status"] == "ok"
    finally:
        srv.fault = None
    assert _settle(client, "/readyz", 200).json()["components"]["store_root"]["status"] == "ok"


def _settle(client, path: str, status: int, timeout: float = 30.0):
    end = time.monotonic() + timeout
    while True:
        r = client.get(path)
        if r.status_code == status or time.monotonic() > end:
            assert r.status_code == status, r.text
            return r
        time.sleep(0.05)


@pytest.mark.skipif(redis_available() is None, reason="redis-server not installed")
def test_a_redis_that_is_down_is_named_by_readyz_and_healthz(tmp_path):
    redis = RedisServer(tmp_path / "redis")
    try:
        make_volume(tmp_path / "root", "tiny")
        settings = Settings(root=tmp_path / "root", queue=redis.url, workers=0, health_every_s=0.1)
        with TestClient(create_app(settings)) as client:
            assert _settle(client, "/readyz", 200).json()["components"]["queue"]["status"] == "ok"
            redis.stop()
            r = _settle(client, "/readyz", 503)
            assert "queue: down" in r.json()["detail"] and r.headers["Retry-After"]
            h = client.get("/healthz")
            assert h.status_code == 200 and h.json()["status"] == "degraded"
            assert h.json()["components"]["queue"]["status"] == "down"
            assert h.json()["components"]["store_root"]["status"] == "ok"
            assert client.post("/volumes/tiny/render", json=tiny_scene(16)).status_code == 200  # renders go on
    finally:
        redis.stop()


def test_healthz_answers_while_renders_hold_every_render_thread(tmp_path):
    """/healthz is answered on the event loop from what the probe threads saw: renders in flight do not delay it
    (the figures under load: benchmarks/bench_faults.py)."""
    make_volume(tmp_path / "root", "tiny")
    settings = Settings(root=tmp_path / "root", workers=0, health_every_s=0.1)
    with TestClient(create_app(settings)) as client:
        _settle(client, "/readyz", 200)
        big = {**tiny_scene(512), "sampling": {"step": 0.05}}
        threads = [threading.Thread(target=client.post, args=("/volumes/tiny/render",), kwargs={"json": big})
                   for _ in range(3)]
        for t in threads:
            t.start()
        answers = [client.get("/healthz") for _ in range(5)]
        for t in threads:
            t.join()
    assert all(a.status_code == 200 and set(a.json()["components"]) == {"store_root", "queue", "device"}
               for a in answers)


def test_a_full_disk_anywhere_in_a_route_is_503_not_500():
    app = FastAPI()
    install(app, Settings(root="s3://b/p"))

    @app.get("/write")
    def write() -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    @app.get("/bug")
    def bug() -> None:
        raise OSError(errno.EINVAL, "a bug, not a fault")

    with TestClient(app, raise_server_exceptions=False) as c:
        r = c.get("/write")
        assert r.status_code == 503 and r.headers["Retry-After"] == "5"
        assert "s3://b/p" in r.json()["detail"] and "no space left" in r.json()["detail"]
        assert c.get("/bug").status_code == 500  # anything else keeps its meaning


def test_which_faults_pass():
    import botocore.exceptions

    closed = botocore.exceptions.ConnectionClosedError(endpoint_url="http://127.0.0.1:9")
    try:
        try:
            raise closed
        except botocore.exceptions.ConnectionClosedError as exc:
            raise StoreInvalid("s3://b/v.zarr is not a readable zarr v3 group") from exc
    except StoreInvalid as wrapped:
        assert storage_fault(wrapped) and "ConnectionClosedError" in storage_fault(wrapped)
    throttled = botocore.exceptions.ClientError({"Error": {"Code": "SlowDown", "Message": "reduce"}}, "GetObject")
    assert storage_fault(throttled) == "SlowDown: reduce"
    assert storage_fault(OSError(errno.ENOSPC, "No space left on device")) == "no space left on the device"
    assert storage_fault(ConnectionResetError()) and storage_fault(TimeoutError("read"))
    for permanent in (FileNotFoundError(errno.ENOENT, "x"), PermissionError(errno.EACCES, "x"), ValueError("x"),
                      botocore.exceptions.ClientError({"Error": {"Code": "NoSuchKey"}}, "GetObject"),
                      StoreInvalid("damaged")):
        assert storage_fault(permanent) is None, permanent
