"""Small pieces of the service: volume-id and path safety, job records' compare-and-set, turntable cameras, settings."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from lodcast.service.jobs import _turn, parse_job, plan_frames
from lodcast.service.records import SqliteRecords, status_json
from lodcast.service.rendering import RequestInvalid
from lodcast.service.settings import Settings
from lodcast.service.volumes import BadId, OutsideRoot, VolumeNotFound, check_volume_id, safe_import_path, volume_path


@pytest.mark.parametrize("vid", ["engine", "a", "CT_2024-01.v2", "x" * 128, "0"])
def test_good_volume_ids(vid):
    assert check_volume_id(vid) == vid


@pytest.mark.parametrize("vid", ["", ".", "..", ".hidden", "-x", "_x", "a/b", "a\\b", "x" * 129, "a\x00b", "é", "a b", None, 3])
def test_bad_volume_ids(vid):
    with pytest.raises(BadId):
        check_volume_id(vid)


def test_symlink_out_of_root_refused(tmp_path: Path):
    root, outside = tmp_path / "root", tmp_path / "outside"
    (outside / "v").mkdir(parents=True)
    root.mkdir()
    (root / "inside").mkdir()
    (root / "out").symlink_to(outside / "v")
    (root / "alias").symlink_to(root / "inside")  # a link that stays inside the root is fine
    assert volume_path(root, "inside") == root / "inside"
    assert volume_path(root, "alias") == root / "alias"
    with pytest.raises(OutsideRoot):
        volume_path(root, "out")
    with pytest.raises(VolumeNotFound):
        volume_path(root, "missing")


def test_import_roots(tmp_path: Path):
    imp = tmp_path / "imports"
    imp.mkdir()
    (imp / "a.npy").write_bytes(b"x")
    (imp / "link.npy").symlink_to(tmp_path / "elsewhere.npy")
    assert safe_import_path("a.npy", [imp]) == imp / "a.npy"
    assert safe_import_path(str(imp / "a.npy"), [imp]) == imp / "a.npy"
    for bad in ("../x.npy", "/etc/passwd", "link.npy", ""):
        with pytest.raises(BadId):
            safe_import_path(bad, [imp])
    with pytest.raises(BadId):
        safe_import_path("a.npy", [])


@pytest.fixture(params=["sqlite", "redis"])
def records(request, tmp_path: Path):
    if request.param == "sqlite":
        yield SqliteRecords(tmp_path / "jobs.db")
        return
    from lodcast.service.records import RedisRecords
    from lodcast.service.testing import RedisServer, in_ci, redis_available

    if redis_available() is None:
        msg = "redis-server not installed (Debian package redis-server)"
        if in_ci():
            pytest.fail(msg)
        pytest.skip(msg)
    server = RedisServer(tmp_path / "redis")
    try:
        yield RedisRecords(server.url, prefix="unit")
    finally:
        server.stop()


def test_records_compare_and_set(records):
    rec = records
    now = time.time()
    rec.create({"id": "a" * 32, "kind": "turntable", "spec": "{}", "state": "queued", "total": 3, "created": now})
    assert rec.update("a" * 32, {"state": "running", "owner": "w1"}, expect={"state": ("queued",)})
    assert not rec.update("a" * 32, {"state": "running", "owner": "w2"}, expect={"state": ("queued",)})  # one claim wins
    assert not rec.update("a" * 32, {"done": 1}, expect={"owner": ("w2",)})
    assert rec.update("a" * 32, {"done": 1}, expect={"owner": ("w1",), "state": ("running",)})
    assert rec.update("a" * 32, {"owner": None}, expect={"owner": ("w1",)})
    assert rec.update("a" * 32, {"state": "queued"}, expect={"owner": (None,)})
    got = rec.get("a" * 32)
    assert got["done"] == 1 and got["state"] == "queued" and got["owner"] is None
    st = status_json(got)
    assert list(st) == ["id", "kind", "state", "progress", "error", "created", "started", "finished"]
    assert st["progress"] == {"done": 1, "total": 3} and st["created"].endswith("Z") and st["started"] is None
    assert [r["id"] for r in rec.list(states=("queued",))] == ["a" * 32] and rec.list(states=("done",)) == []
    rec.create({"id": "b" * 32, "kind": "scenes", "spec": "{}", "state": "queued", "total": 1, "created": now + 1})
    assert [r["id"] for r in rec.list(states=("queued", "running"))] == ["b" * 32, "a" * 32]  # newest first
    assert rec.update("a" * 32, {"state": "done", "finished": now + 2}, expect={"state": ("queued", "running")})
    assert [r["id"] for r in rec.list(states=("queued", "running"))] == ["b" * 32]
    assert [r["id"] for r in rec.list(states=("done",))] == ["a" * 32]
    assert [r["id"] for r in rec.list()] == ["b" * 32, "a" * 32]
    assert rec.get("c" * 32) is None and not rec.update("c" * 32, {"state": "queued"})


def test_turntable_lookat_turns_like_the_orbit_camera():
    from lodcast.renderer.scene.camera import orbit_eye
    from lodcast.renderer.scene.scene import OrbitCamera

    centre = np.zeros(3)
    eye0, _ = orbit_eye(OrbitCamera(azimuth=0, elevation=0, distance=1), centre, 5.0)
    for az in (30, 90, 200):
        want, _ = orbit_eye(OrbitCamera(azimuth=az, elevation=0, distance=1), centre, 5.0)
        got = _turn({"camera": {"eye": list(eye0), "target": [0, 0, 0]}}, az)["camera"]["eye"]
        np.testing.assert_allclose(got, want, atol=1e-9)
    assert _turn({"camera": {"azimuth": 10, "elevation": 5}}, 90)["camera"] == {"azimuth": 100.0, "elevation": 5}
    assert _turn({}, 45)["camera"] == {"azimuth": 45.0}


def test_plan_frames_per_kind():
    scene = {"tf": {"points": [{"value": 0}]}}
    job = parse_job({"kind": "turntable", "volume": "v", "scene": scene, "frames": 4, "start_azimuth": 10})
    assert [s["camera"]["azimuth"] for _, s in plan_frames(job)] == [10, 100, 190, 280]
    job = parse_job({"kind": "tf_sweep", "volume": "v", "scene": scene, "tfs": [{"points": [{"value": 1}]}] * 3})
    assert len(plan_frames(job)) == 3
    job = parse_job({"kind": "volumes", "volumes": ["a", "b"], "scene": scene})
    assert [v for v, _ in plan_frames(job)] == ["a", "b"]
    with pytest.raises(RequestInvalid) as e:
        parse_job({"kind": "turntable", "volume": "v", "scene": scene, "frames": "many"})
    assert "frames" in str(e.value)


def test_settings_from_environment(monkeypatch, tmp_path: Path):
    monkeypatch.setenv("LODCAST_ROOT", str(tmp_path))
    monkeypatch.setenv("LODCAST_TOKEN", "t")
    monkeypatch.setenv("LODCAST_MAX_WIDTH", "99")
    s = Settings()
    assert s.root == tmp_path.resolve() and s.token == "t" and s.max_width == 99 and not s.is_redis
    assert s.sqlite_path() == tmp_path.resolve() / ".lodcast" / "queue.db"
    assert Settings(queue="sqlite:///tmp/q.db").sqlite_path() == Path("/tmp/q.db")
    assert Settings(queue="redis://127.0.0.1:6379/0").is_redis


def test_unreachable_queue_is_503_naming_it(tmp_path: Path):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from fastapi.testclient import TestClient

    from lodcast.service.app import create_app
    from lodcast.service.testing import make_volume, tiny_scene

    make_volume(tmp_path, "v")
    app = create_app(Settings(root=tmp_path, queue="redis://127.0.0.1:1/0", workers=0, token=None))
    with TestClient(app) as client:
        r = client.get("/jobs")
        assert r.status_code == 503 and "queue" in r.json()["detail"]
        r = client.post("/jobs", json={"kind": "turntable", "volume": "v", "scene": tiny_scene(), "frames": 2})
        assert r.status_code == 503
        assert client.get("/volumes/v").status_code == 200  # the rest of the API is unaffected
