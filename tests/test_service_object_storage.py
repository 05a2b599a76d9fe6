"""The service over a store root on object storage (issue 14 item 3): `lodcast serve --root s3://bucket/prefix`
lists, describes, renders, ingests and deletes the volumes there, against a real S3-compatible server (moto's
server mode on loopback, lodcast.service.testing.s3_server). Images are those of the same store on local disk, bit
for bit; an ingest job publishes its store atomically (the root zarr.json last, so a listing never shows a half
store); job results go to ROOT/.jobs on the same storage, while the queue and uploads stay in the local state
folder."""
from __future__ import annotations

import io
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("s3fs")
pytest.importorskip("moto")

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

import lodcast  # noqa: E402
from lodcast.service.app import create_app  # noqa: E402
from lodcast.service.settings import Settings  # noqa: E402
from lodcast.service.testing import Proc, free_port, make_volume, running, s3_server, start_serve, tiny_scene, wait_job  # noqa: E402

BUCKET = "lodcast-svc"
ROOT = f"s3://{BUCKET}/volumes"


def _objects(fs, prefix: str) -> list[str]:
    fs.invalidate_cache()
    try:
        return sorted(fs.find(prefix))
    except FileNotFoundError:
        return []


@pytest.fixture(scope="module")
def svc(tmp_path_factory):
    import fsspec

    base = tmp_path_factory.mktemp("s3svc")
    local, imports, state = base / "local", base / "imports", base / "state"
    for d in (local, imports):
        d.mkdir()
    make_volume(local, "tiny")
    np.save(imports / "blob.npy", np.random.default_rng(3).random((20, 18, 22), dtype=np.float32) * 1000)
    with s3_server() as srv:
        fs = fsspec.filesystem("s3", skip_instance_cache=True)
        fs.mkdir(BUCKET)
        lodcast.ingest(local / "tiny", f"{ROOT}/tiny", block_size=8)  # a zarr source, published to S3
        settings = Settings(root=ROOT, state_root=state, import_roots=[imports], workers=1, poll_s=0.05)
        with TestClient(create_app(settings)) as client:
            yield client, fs, local, imports, state, srv


def test_a_root_url_is_kept_and_its_state_lives_locally(tmp_path):
    s = Settings(root="s3://bucket/prefix/")
    assert s.remote and s.root == "s3://bucket/prefix"
    assert s.local_root.is_relative_to(Path.home() / ".lodcast" / "state")
    assert Settings(root="s3://bucket/prefix").local_root == s.local_root  # the same root finds its jobs again
    assert Settings(root="s3://bucket/other").local_root != s.local_root
    t = Settings(root="s3://bucket/prefix", state_root=tmp_path)
    assert t.jobs_dir == tmp_path / ".jobs" and t.sqlite_path() == tmp_path / ".lodcast" / "queue.db"
    local = Settings(root=tmp_path)
    assert not local.remote and local.local_root == tmp_path.resolve()  # a folder root keeps its state as before
    assert Settings(root=f"file://{tmp_path}").root == tmp_path.resolve()


def test_volumes_on_s3_are_listed_and_described(svc):
    client, fs, *_ = svc
    assert [v["id"] for v in client.get("/volumes").json()] == ["tiny"]
    info = client.get("/volumes/tiny").json()
    assert info["shape"] == [24, 24, 24] and info["block_size"] == 8
    missing = client.get("/volumes/nope")
    assert missing.status_code == 404 and "nope" in missing.json()["detail"]
    bad = client.get("/volumes/..%2Fetc")
    assert bad.status_code in (400, 404, 422)


def test_a_render_from_s3_is_the_local_render_bit_for_bit(svc):
    client, fs, local, *_ = svc
    for quality in ("full", "lossless", {"reduction": 4}):
        scene = tiny_scene(24, quality=quality, format="npy")
        resp = client.post("/volumes/tiny/render", json=scene)
        assert resp.status_code == 200, resp.text
        got = np.load(io.BytesIO(resp.content))
        want = lodcast.render(local / "tiny", scene).rgba
        assert got.shape == want.shape and np.array_equal(got, want), (quality, float(np.abs(got - want).max()))
        assert want[..., 3].max() > 0.1  # not vacuous: the blobs show


def test_ingest_job_publishes_to_s3_and_delete_removes_it(svc):
    client, fs, local, imports, state, srv = svc
    resp = client.post("/volumes", json={"name": "blob", "source": "blob.npy", "options": {"block_size": 8}})
    assert resp.status_code == 202, resp.text
    st = wait_job(client, resp.json()["id"])
    assert st["state"] == "done", st
    assert [v["id"] for v in client.get("/volumes").json()] == ["blob", "tiny"]
    # the store is where the root says, readable by anyone with the URL, and equal to the source
    store = lodcast.open_store(f"{ROOT}/blob")
    assert store.shape == (20, 18, 22)
    want = np.load(imports / "blob.npy")
    img = client.post("/volumes/blob/render", json=tiny_scene(16, format="npy"))
    assert img.status_code == 200
    np.testing.assert_array_equal(np.asarray(store.level(0)[...]), want)
    # the queue, the records and uploads are in the state folder, not in the bucket
    assert not [o for o in _objects(fs, BUCKET) if "/.lodcast" in o or "/.uploads" in o], _objects(fs, BUCKET)
    assert (state / ".lodcast" / "queue.db").is_file()
    # a second ingest under the same name is refused at submission, naming the field
    again = client.post("/volumes", json={"name": "blob", "source": "blob.npy"})
    assert again.status_code == 422 and "name" in again.text
    # delete: the listing loses it and no object of it is left
    assert client.delete("/volumes/blob").json() == {"deleted": "blob"}
    assert [v["id"] for v in client.get("/volumes").json()] == ["tiny"]
    assert _objects(fs, f"{BUCKET}/volumes/blob") == []
    assert client.get("/volumes/blob").status_code == 404


def test_an_upload_is_parked_in_the_bucket_for_whichever_worker_ingests_it(svc):
    """With a root URL the worker that ingests an upload may run on another host: the API host parks the file
    under ROOT/.uploads/ and the job's source is that object; once ingested it is gone from both places."""
    client, fs, local, imports, state, srv = svc
    vol = np.random.default_rng(5).random((14, 16, 18), dtype=np.float32)
    buf = io.BytesIO()
    np.save(buf, vol)
    resp = client.post("/volumes/up/upload?format=npy", content=buf.getvalue(),
                       headers={"Content-Type": "application/octet-stream"})
    assert resp.status_code == 202, resp.text
    jq = client.app.state.jobs()
    spec = jq.get(resp.json()["id"])["spec"]
    assert f'"source": "{ROOT}/.uploads/' in spec, spec
    st = wait_job(client, resp.json()["id"])
    assert st["state"] == "done", st
    np.testing.assert_array_equal(np.asarray(lodcast.open_store(f"{ROOT}/up").level(0)[...]), vol)
    assert _objects(fs, f"{BUCKET}/volumes/.uploads") == []
    assert not list((state / ".uploads").glob("*")) if (state / ".uploads").is_dir() else True
    assert client.delete("/volumes/up").status_code == 200


def test_a_store_without_its_root_metadata_is_not_a_volume(svc):
    """What a listing sees while an ingest is uploading (or after a killed upload): objects but no root zarr.json."""
    client, fs, *_ = svc
    fs.pipe(f"{BUCKET}/volumes/half/levels/0/c/0/0/0", b"x" * 100)
    try:
        assert [v["id"] for v in client.get("/volumes").json()] == ["tiny"]
        assert client.get("/volumes/half").status_code == 404
        assert client.post("/volumes/half/render", json=tiny_scene(8)).status_code == 404
    finally:
        fs.rm(f"{BUCKET}/volumes/half", recursive=True)


def test_turntable_results_go_to_the_bucket(svc):
    """Results under ROOT/.jobs on the object storage, where every host sharing the queue reads them; not in the
    state folder, and never listed as a volume."""
    client, fs, local, imports, state, srv = svc
    job = {"kind": "turntable", "volume": "tiny", "scene": tiny_scene(16, quality={"reduction": 4}), "frames": 3,
           "animation": "gif"}
    st = wait_job(client, client.post("/jobs", json=job).json()["id"])
    assert st["state"] == "done" and st["progress"] == {"done": 3, "total": 3}, st
    prefix = f"{BUCKET}/volumes/.jobs/{st['id']}"
    names = [o.rsplit("/", 1)[-1] for o in _objects(fs, prefix)]
    assert names == ["frame_00000.png", "frame_00001.png", "frame_00002.png", "turntable.gif"], names
    got = client.get(f"/jobs/{st['id']}/results/2")
    assert got.status_code == 200 and got.headers["content-type"] == "image/png"
    assert got.content == fs.cat(f"{prefix}/frame_00002.png")
    assert client.get(f"/jobs/{st['id']}/animation").content[:3] == b"GIF"
    assert client.get(f"/jobs/{st['id']}/results/3").status_code == 404
    assert not (state / ".jobs" / st["id"]).exists()
    assert [v["id"] for v in client.get("/volumes").json()] == ["tiny"]


def test_lodcast_serve_with_a_root_url(svc, tmp_path):
    """The command as a user runs it: the banner names the volume on S3, which lists and renders over HTTP; a
    missing bucket is one line and exit 2 before any banner."""
    import httpx

    srv = svc[-1]
    port = free_port()
    log = tmp_path / "serve.log"
    proc = start_serve(ROOT, port, extra=["--state-root", str(tmp_path / "state")], log=log)
    with running(proc):
        url = f"http://127.0.0.1:{port}"
        assert [v["id"] for v in httpx.get(f"{url}/volumes", timeout=30).json()] == ["tiny"]
        r = httpx.post(f"{url}/volumes/tiny/render", json=tiny_scene(16), timeout=60)
        assert r.status_code == 200 and r.content[:8] == b"\x89PNG\r\n\x1a\n"
    assert f"serving 1 volume(s) from {ROOT}" in log.read_text()
    p = subprocess.run([sys.executable, "-m", "lodcast.service.cli", "serve", "--root", "s3://no-such-bucket/x",
                        "--state-root", str(tmp_path), "--port", str(free_port())], capture_output=True, text=True,
                       env={**os.environ, "AWS_ENDPOINT_URL": srv.endpoint}, timeout=120)
    assert p.returncode == 2, p.stderr
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "--root" in lines[0] and "no-such-bucket" in lines[0], p.stderr


def test_two_workers_on_redis_and_s3_split_a_turntable_each_frame_once(svc, tmp_path):
    """Issue 14 item 4: two `lodcast worker` processes (as on two hosts: each with a state folder of its own,
    sharing only the loopback Redis queue and the S3 bucket) split a 36-frame turntable between them; every frame
    is rendered exactly once (each worker logs the frames it renders) and all 36 are in the bucket."""
    import re

    from lodcast.service.jobs import TurntableJob
    from lodcast.service.queue import JobQueue
    from lodcast.service.testing import RedisServer, in_ci, redis_available

    if redis_available() is None:
        if in_ci():
            pytest.fail("redis-server missing under CI (Debian package redis-server)")
        pytest.skip("redis-server not installed (Debian package redis-server)")
    fs, srv = svc[1], svc[-1]
    redis = RedisServer(tmp_path / "redis")
    env = {"AWS_ENDPOINT_URL": srv.endpoint, "LODCAST_FRAME_DELAY_S": "0.05", "LODCAST_HEARTBEAT_S": "0.5",
           "LODCAST_REAP_EVERY_S": "1"}
    logs = [tmp_path / f"worker{k}.log" for k in (1, 2)]
    workers = [Proc([sys.executable, "-m", "lodcast.service.cli", "--log-level", "info", "worker", "--root", ROOT,
                     "--queue", redis.url, "--state-root", str(tmp_path / f"host{k}")], env=env, log=logs[k - 1])
               for k in (1, 2)]
    try:
        with running(*workers):
            jq = JobQueue(Settings(root=ROOT, queue=redis.url, state_root=tmp_path / "client"))
            scene = tiny_scene(48, quality={"reduction": 4})
            rec = jq.submit(TurntableJob(kind="turntable", volume="tiny", scene=scene, frames=36))
            st = jq.wait(rec["id"], timeout=240)
            assert st["state"] == "done" and st["done"] == 36, (st, [p.read_text()[-2000:] for p in logs])
    finally:
        redis.stop()
    rendered = [re.findall(rf"job {rec['id']}: frame (\d+) rendered by", p.read_text()) for p in logs]
    counts = [len(r) for r in rendered]
    frames = sorted(int(i) for r in rendered for i in r)
    assert frames == list(range(36)), (counts, frames)  # each frame once, by one of the two
    assert min(counts) >= 1, counts  # split between them, not one worker doing it all
    print(f"frames per worker: {counts}")
    objects = [o.rsplit("/", 1)[-1] for o in _objects(fs, f"{BUCKET}/volumes/.jobs/{rec['id']}")]
    assert objects == [f"frame_{i:05d}.png" for i in range(36)]
    first, last = (fs.cat(f"{BUCKET}/volumes/.jobs/{rec['id']}/frame_{i:05d}.png") for i in (0, 9))
    assert first != last  # the camera turned
