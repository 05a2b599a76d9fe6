"""Every HTTP endpoint, happy and bad paths, in process (FastAPI TestClient, embedded SQLite queue, in-process worker)."""
from __future__ import annotations

import io
import json
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

import lodcast
from lodcast.service.app import create_app
from lodcast.service.settings import Settings
from lodcast.service.testing import TINY_TF, make_volume, tiny_scene, wait_job

TOKEN = "s3cret-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
NOAUTH = {"Authorization": ""}  # overrides the client's default header: a request without a token


@pytest.fixture(scope="module")
def env(tmp_path_factory: pytest.TempPathFactory):
    base = tmp_path_factory.mktemp("svc")
    root, imports, outside = base / "root", base / "imports", base / "outside"
    for d in (root, imports, outside):
        d.mkdir()
    make_volume(root, "tiny")
    make_volume(outside, "secret")
    np.save(imports / "blob.npy", np.random.default_rng(0).random((12, 12, 12), dtype=np.float32))
    (root / "escape").symlink_to(outside / "secret")  # a link leading out of the root
    (root / "notastore").mkdir()  # a folder that is not a store
    (root / "afile").write_text("x")
    settings = Settings(root=root, token=TOKEN, import_roots=[imports], max_width=64, max_height=64, max_frames=50,
                        min_step=0.25, max_upload_bytes=64 * 1024, workers=1, poll_s=0.05)
    with TestClient(create_app(settings), headers=AUTH) as client:  # reads need the token too
        yield client, root, imports, outside


def names_field(resp, field: str) -> bool:
    return field in json.dumps(resp.json()["detail"])


# --- health / volumes ------------------------------------------------------------------------------------------

def test_healthz_and_docs(env):
    client = env[0]
    assert client.get("/healthz").json()["status"] == "ok"
    page = client.get("/docs", headers=NOAUTH)
    assert page.status_code == 200
    # offline: every script and style the page loads is served here, none from a CDN
    import re

    urls = re.findall(r'(?:src|href)="([^"]+)"', page.text)
    assert urls and all(u.startswith("/docs/assets/") for u in urls), urls
    for u in urls:
        assert client.get(u, headers=NOAUTH).status_code == 200, u
    assert "/volumes/{volume_id}/render" in client.get("/openapi.json").json()["paths"]


def test_openapi_is_typed(env):
    """The render body is the Scene model, every operation has a summary, a typed response and its error codes,
    and the report header is declared."""
    spec = env[0].get("/openapi.json").json()
    render = spec["paths"]["/volumes/{volume_id}/render"]["post"]
    body = render["requestBody"]["content"]["application/json"]["schema"]
    assert body.get("$ref", "").endswith("/Scene") and "camera" in spec["components"]["schemas"]["Scene"]["properties"]
    assert "X-Lodcast-Report" in render["responses"]["200"]["headers"]
    assert {"400", "401", "404", "409", "413", "422", "503"} <= set(render["responses"])
    for path, ops in spec["paths"].items():
        for method, op in ops.items():
            assert op.get("summary"), (method, path)
            ok = op["responses"][next(c for c in op["responses"] if c.startswith("2"))]
            content = ok.get("content", {})
            assert content and all(v.get("schema") for v in content.values()), (method, path, ok)
            if path not in ("/healthz", "/readyz"):
                assert "401" in op["responses"], (method, path)
    status = spec["components"]["schemas"]["JobStatus"]["properties"]
    assert set(status) == {"id", "kind", "state", "progress", "error", "created", "started", "finished"}
    assert spec["components"]["securitySchemes"]["HTTPBearer"]["scheme"] == "bearer"


def test_wrong_method_names_every_allowed_one(env):
    client = env[0]
    for method, path, allowed in (("PUT", "/volumes", "GET, POST"), ("PATCH", "/jobs/" + "0" * 32, "DELETE, GET"),
                                  ("GET", "/volumes/tiny/render", "POST"), ("POST", "/healthz", "GET")):
        r = client.request(method, path)
        assert r.status_code == 405 and r.headers["Allow"] == allowed, (method, path, r.headers, r.text)
        assert method in r.json()["detail"] and allowed in r.json()["detail"]


def test_list_and_show_volumes(env):
    client = env[0]
    listed = client.get("/volumes").json()
    assert [v["id"] for v in listed] == ["tiny"]  # the symlink out of the root is not a volume
    info = client.get("/volumes/tiny").json()
    for key in ("shape", "dtype", "spacing", "origin", "block_size", "levels", "value_range", "blocks", "shards", "bytes_on_disk"):
        assert key in info
    assert info["shape"] == [24, 24, 24] and "path" not in info


@pytest.mark.parametrize("vid", ["..", ".jobs", ".lodcast", "-x", "a" * 129, "escape", "a%2F..%2F..", "%2E%2E", "nope",
                                 "notastore", "afile"])
def test_bad_volume_ids_refused(env, vid):
    client = env[0]
    r = client.get(f"/volumes/{vid}")
    if r.url.path == "/":  # the client resolved "/volumes/.." to "/": the viewer's list page, which names no volume
        assert r.headers["content-type"].startswith("text/html") and "secret" not in r.text
    else:
        assert 400 <= r.status_code < 500, (vid, r.status_code, r.text)
    r = client.post(f"/volumes/{vid}/render", json=tiny_scene())
    assert 400 <= r.status_code < 500
    if r.status_code != 404 or r.json().get("detail") != "Not Found":  # the router's own 404 names no field
        assert "volume" in r.text
    r = client.delete(f"/volumes/{vid}", headers=AUTH)
    assert 400 <= r.status_code < 500
    assert (env[3] / "secret" / "zarr.json").is_file()  # nothing outside the root was touched


# --- render ----------------------------------------------------------------------------------------------------

def test_render_png_and_report(env):
    client = env[0]
    r = client.post("/volumes/tiny/render", json=tiny_scene(24))
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/png" and r.content[:8] == b"\x89PNG\r\n\x1a\n"
    report = json.loads(r.headers["x-lodcast-report"])
    for key in ("wall_ms", "kernel_ms", "bricks_read", "bricks_cached", "bricks_skipped", "reduction",
                "predicted_delta_e", "samples", "build_options"):
        assert key in report


def test_render_npy_is_float_rgba(env):
    client = env[0]
    r = client.post("/volumes/tiny/render", json=tiny_scene(20, format="npy"))
    assert r.status_code == 200, r.text
    a = np.load(io.BytesIO(r.content))
    assert a.shape == (20, 20, 4) and a.dtype == np.float32 and a[..., 3].max() > 0


@pytest.mark.parametrize(
    "patch, field",
    [
        ({"width": 65}, "width"),
        ({"height": 1000}, "height"),
        ({"sampling": {"step": 0.1}}, "step"),
        ({"tf": {"points": [{"value": 0, "colour": [1, 1, 1]}]}}, "colour"),
        ({"tf": {"points": []}}, "points"),
        ({"tf": None}, "tf"),
        ({"camera": {"fov": 500}}, "fov"),
        ({"quality": "best"}, "quality"),
        ({"format": "jpg"}, "format"),
        ({"bogus": 1}, "bogus"),
    ],
)
def test_render_bad_scene_names_field(env, patch, field):
    client = env[0]
    r = client.post("/volumes/tiny/render", json={**tiny_scene(), **patch})
    assert r.status_code == 422, r.text
    assert names_field(r, field)


def test_render_malformed_bodies(env):
    client = env[0]
    r = client.post("/volumes/tiny/render", content=b"{not json", headers={"content-type": "application/json"})
    assert r.status_code == 422
    assert client.post("/volumes/tiny/render", json=[1, 2]).status_code == 422
    r = client.post("/volumes/tiny/render", json={"width": 8})
    assert r.status_code == 422 and names_field(r, "tf")
    r = client.post("/volumes/nope/render", json=tiny_scene())
    assert r.status_code == 404 and "volume" in r.json()["detail"]


# --- ingest / upload / delete ----------------------------------------------------------------------------------

def test_ingest_from_import_root_then_delete(env):
    client, root, imports, _ = env
    body = {"name": "blob", "source": "blob.npy"}
    assert client.post("/volumes", json=body, headers=NOAUTH).status_code == 401  # token required
    r = client.post("/volumes", json=body, headers=AUTH)
    assert r.status_code == 202, r.text
    st = wait_job(client, r.json()["id"])
    assert st["state"] == "done" and st["kind"] == "ingest", st
    assert "blob" in [v["id"] for v in client.get("/volumes").json()]
    # the server's folders are not the client's business: the source is named by its file name only
    info = client.get("/volumes/blob").json()
    assert info["source"]["path"] == "blob.npy" and str(imports.parent) not in client.get("/volumes").text
    r = client.post("/volumes", json=body, headers=AUTH)  # exists
    assert r.status_code == 422 and names_field(r, "name")
    assert client.delete("/volumes/blob", headers=NOAUTH).status_code == 401
    assert client.delete("/volumes/blob", headers=AUTH).status_code == 200
    assert client.get("/volumes/blob").status_code == 404 and not (root / "blob").exists()


def test_an_ingest_job_turns_a_nifti_to_lps_by_default(env):
    """The job option `orient`: by default a RAS NIfTI is turned (the volume's summary says L, P, S and level 0 is
    the array reversed along x and y), as with an explicit "LPS"; with "source" it keeps its axes (+x right); a value that is not an orientation is refused at
    submission, naming the option."""
    import nibabel as nib

    client, root, imports, _ = env
    vol = np.arange(4 * 6 * 8, dtype=np.uint16).reshape(4, 6, 8)  # (z, y, x)
    nib.save(nib.Nifti1Image(vol.transpose(2, 1, 0), np.eye(4)), str(imports / "ras.nii"))
    for name, options, axes in (("kept", {"orient": "source"}, ["R", "A", "S"]), ("turned", {}, ["L", "P", "S"]),
                                ("asked", {"orient": "LPS"}, ["L", "P", "S"])):
        r = client.post("/volumes", json={"name": name, "source": "ras.nii", "options": options}, headers=AUTH)
        assert r.status_code == 202, r.text
        assert wait_job(client, r.json()["id"])["state"] == "done"
        info = client.get(f"/volumes/{name}").json()
        assert info["orientation"] == axes and info["direction"] is not None
    np.testing.assert_array_equal(lodcast.open_store(root / "turned").level(0)[...], vol[:, ::-1, ::-1])
    np.testing.assert_array_equal(lodcast.open_store(root / "asked").level(0)[...], vol[:, ::-1, ::-1])
    np.testing.assert_array_equal(lodcast.open_store(root / "kept").level(0)[...], vol)
    r = client.post("/volumes", json={"name": "bad", "source": "ras.nii", "options": {"orient": "RAS"}}, headers=AUTH)
    assert r.status_code == 422 and names_field(r, "orient") and "not one of LPS, source" in r.text, r.text
    for name in ("kept", "turned", "asked"):
        assert client.delete(f"/volumes/{name}", headers=AUTH).status_code == 200


@pytest.mark.parametrize(
    "body, field",
    [
        ({"name": "x1", "source": "../outside/secret"}, "source"),
        ({"name": "x1", "source": "/etc/passwd"}, "source"),
        ({"name": "x1", "source": "missing.npy"}, "source"),
        ({"name": "../x", "source": "blob.npy"}, "name"),
        ({"name": ".jobs", "source": "blob.npy"}, "name"),
        ({"name": "x1"}, "source"),
        ({"name": "x1", "source": "blob.npy", "extra": 1}, "extra"),
        ({"name": "x1", "source": "blob.npy", "options": {"rm_rf": True}}, "rm_rf"),
    ],
)
def test_ingest_bad_requests(env, body, field):
    client = env[0]
    r = client.post("/volumes", json=body, headers=AUTH)
    assert r.status_code == 422, r.text
    assert names_field(r, field)


def test_a_folder_source_with_a_link_out_of_the_import_root_is_refused(env):
    """A zarr store (or DICOM / TIFF folder) under an import root holding a symlink to a file outside it: refused
    at submission, naming the link, with nothing ingested; the same store without the link ingests."""
    import shutil

    client, root, imports, outside = env
    lodcast.ingest(np.arange(16**3, dtype=np.uint16).reshape(16, 16, 16), outside / "plain.zarr")
    src = imports / "linked.zarr"
    shutil.copytree(outside / "plain.zarr", src)
    (src / "0" / "c").mkdir(exist_ok=True)
    (outside / "secret.txt").write_text("top secret")
    (src / "0" / "c" / "evil").symlink_to(outside / "secret.txt")
    r = client.post("/volumes", json={"name": "linked", "source": "linked.zarr", "options": {"format": "zarr"}})
    assert r.status_code == 422 and names_field(r, "source") and "evil" in r.text, r.text
    (src / "0" / "c" / "evil").unlink()
    r = client.post("/volumes", json={"name": "linked", "source": "linked.zarr", "options": {"format": "zarr"}})
    assert r.status_code == 202, r.text
    assert wait_job(client, r.json()["id"])["state"] == "done"
    assert client.delete("/volumes/linked").status_code == 200


def test_upload(env):
    client, root, imports, _ = env
    buf = io.BytesIO()
    np.save(buf, np.ones((10, 10, 10), np.float32))
    r = client.post("/volumes/up1/upload?format=npy", content=buf.getvalue(), headers=AUTH)
    assert r.status_code == 202, r.text
    assert wait_job(client, r.json()["id"])["state"] == "done"
    assert client.get("/volumes/up1").json()["shape"] == [10, 10, 10]
    big = b"\0" * (65 * 1024)
    r = client.post("/volumes/up2/upload?format=npy", content=big, headers=AUTH)
    assert r.status_code == 413 and "body" in r.json()["detail"]
    r = client.post("/volumes/up2/upload?format=npy", content=b"", headers=AUTH)
    assert r.status_code == 422
    r = client.post("/volumes/up2/upload?format=raw&dtype=uint8", content=b"\0" * 8, headers=AUTH)
    assert r.status_code == 422 and names_field(r, "shape")
    assert client.post("/volumes/up2/upload", content=b"x", headers=NOAUTH).status_code == 401
    r = client.post("/volumes/up3/upload?format=npy", content=b"not an npy file", headers=AUTH)
    assert r.status_code == 202  # accepted, then the ingest job fails with the reader's message
    st = wait_job(client, r.json()["id"])
    assert st["state"] == "failed" and st["error"], st
    assert client.get("/volumes/up3").status_code == 404
    assert not list((root / ".uploads").glob("*")), "rejected or failed uploads leave nothing behind"
    client.delete("/volumes/up1", headers=AUTH)


# --- jobs ------------------------------------------------------------------------------------------------------

def test_turntable_job_with_gif(env):
    client = env[0]
    job = {"kind": "turntable", "volume": "tiny", "scene": tiny_scene(16), "frames": 4, "animation": "gif"}
    assert client.post("/jobs", json=job, headers=NOAUTH).status_code == 401
    r = client.post("/jobs", json=job, headers=AUTH)
    assert r.status_code == 202, r.text
    st = r.json()
    assert set(st) == {"id", "kind", "state", "progress", "error", "created", "started", "finished"}
    assert st["progress"] == {"done": 0, "total": 4}
    st = wait_job(client, st["id"])
    assert st["state"] == "done" and st["progress"] == {"done": 4, "total": 4} and st["error"] is None, st
    assert st["started"] and st["finished"]
    frames = [client.get(f"/jobs/{st['id']}/results/{n}") for n in range(4)]
    assert all(f.status_code == 200 and f.content[:4] == b"\x89PNG" for f in frames)
    assert len({f.content for f in frames}) > 1  # the camera turns
    gif = client.get(f"/jobs/{st['id']}/animation")
    assert gif.status_code == 200 and gif.content[:3] == b"GIF"
    r = client.get(f"/jobs/{st['id']}/results/4")
    assert r.status_code == 404 and "n" in r.json()["detail"]
    assert st["id"] in [j["id"] for j in client.get("/jobs").json()]
    assert all(j["state"] == "done" for j in client.get("/jobs?state=done").json())


@pytest.mark.parametrize("kind", ["scenes", "tf_sweep", "volumes"])
def test_other_job_kinds(env, kind):
    client = env[0]
    tf2 = {"points": [{"value": 200, "color": [1, 0, 0], "opacity": 0.0}, {"value": 900, "color": [1, 0, 0], "opacity": 0.9}]}
    job = {
        "scenes": {"kind": "scenes", "volume": "tiny", "scenes": [tiny_scene(8), tiny_scene(12, format="npy")]},
        "tf_sweep": {"kind": "tf_sweep", "volume": "tiny", "scene": {k: v for k, v in tiny_scene(8).items() if k != "tf"},
                     "tfs": [TINY_TF, tf2]},
        "volumes": {"kind": "volumes", "volumes": ["tiny", "tiny"], "scene": tiny_scene(8)},
    }[kind]
    r = client.post("/jobs", json=job, headers=AUTH)
    assert r.status_code == 202, r.text
    st = wait_job(client, r.json()["id"])
    assert st["state"] == "done" and st["progress"] == {"done": 2, "total": 2}, st
    last = client.get(f"/jobs/{st['id']}/results/1")
    if kind == "scenes":
        assert np.load(io.BytesIO(last.content)).shape == (12, 12, 4)
    else:
        assert last.content[:4] == b"\x89PNG"


@pytest.mark.parametrize(
    "job, field",
    [
        ({"kind": "turntable", "volume": "nope", "scene": tiny_scene()}, "volume"),
        ({"kind": "turntable", "volume": "../x", "scene": tiny_scene()}, "volume"),
        ({"kind": "turntable", "volume": "tiny", "scene": tiny_scene(), "frames": 51}, "frames"),
        ({"kind": "turntable", "volume": "tiny", "scene": tiny_scene(), "frames": 0}, "frames"),
        ({"kind": "turntable", "volume": "tiny", "scene": {**tiny_scene(), "width": 100}}, "width"),
        ({"kind": "turntable", "volume": "tiny"}, "scene"),
        ({"kind": "spin", "volume": "tiny"}, "kind"),
        ({"volume": "tiny"}, "kind"),
        ({"kind": "scenes", "volume": "tiny", "scenes": []}, "scenes"),
        ({"kind": "scenes", "volume": "tiny", "scenes": [tiny_scene(), {"tf": {"points": [{"value": "a"}]}}]}, "value"),
        ({"kind": "tf_sweep", "volume": "tiny", "scene": tiny_scene(), "tfs": [{"points": [{"value": 1, "opacity": 2}]}]}, "opacity"),
        ({"kind": "tf_sweep", "volume": "tiny", "scene": tiny_scene(), "tfs": [{"pts": []}]}, "pts"),
        ({"kind": "tf_sweep", "volume": "tiny", "scene": {"width": 999}, "tfs": [TINY_TF]}, "width"),
        ({"kind": "volumes", "volumes": ["tiny", "escape"], "scene": tiny_scene()}, "volumes"),
        ({"kind": "ingest", "source": "blob.npy", "name": "tiny"}, "name"),
    ],
)
def test_bad_jobs_name_field(env, job, field):
    client = env[0]
    r = client.post("/jobs", json=job, headers=AUTH)
    assert r.status_code == 422, r.text
    assert names_field(r, field), r.text


def test_unknown_and_malformed_job_ids(env):
    client = env[0]
    for jid in ("0" * 32, "nope", "../../etc"):
        r = client.get(f"/jobs/{jid}")
        assert r.status_code == 404
        assert client.get(f"/jobs/{jid}/results/0").status_code == 404
        assert client.delete(f"/jobs/{jid}", headers=AUTH).status_code == 404
    assert client.get("/jobs/" + "0" * 32 + "/results/-1").status_code == 422
    assert client.get("/jobs?limit=0").status_code == 422
    assert client.get("/jobs?state=lost").status_code == 422


def test_cancel_queued_job(env):
    client = env[0]
    # a job whose frames are slow enough to cancel while the worker is on it or it is still queued
    job = {"kind": "turntable", "volume": "tiny", "scene": tiny_scene(64), "frames": 50}
    st = client.post("/jobs", json=job, headers=AUTH).json()
    assert client.delete(f"/jobs/{st['id']}", headers=NOAUTH).status_code == 401
    r = client.delete(f"/jobs/{st['id']}", headers=AUTH)
    assert r.status_code == 200 and r.json()["state"] == "cancelled"
    time.sleep(0.5)
    st = client.get(f"/jobs/{st['id']}").json()
    assert st["state"] == "cancelled" and st["progress"]["done"] < 50
    # cancelling again is harmless and keeps the state
    assert client.delete(f"/jobs/{st['id']}", headers=AUTH).json()["state"] == "cancelled"


def test_no_token_configured_means_open(tmp_path: Path):
    make_volume(tmp_path, "v")
    with TestClient(create_app(Settings(root=tmp_path, token=None, workers=0))) as client:
        r = client.post("/jobs", json={"kind": "turntable", "volume": "v", "scene": tiny_scene(), "frames": 2})
        assert r.status_code == 202
        assert client.delete(f"/jobs/{r.json()['id']}").json()["state"] == "cancelled"


def test_upload_of_a_detached_nrrd_header_reads_nothing_outside(env):
    """A header naming another file (here: a secret beside the store root, and another upload) is refused: an
    upload is one file, so its ingest may read that file only (issue 10, item 1)."""
    client, root, imports, outside = env
    secret = outside / "secret.raw"
    secret.write_bytes(bytes(range(256)) * 4)
    for name in (str(secret), "../../outside/secret.raw", "other-upload.raw"):
        (root / ".uploads").mkdir(exist_ok=True)
        (root / ".uploads" / "other-upload.raw").write_bytes(b"\1" * 1024)
        hdr = (f"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 8 8 16\nencoding: raw\ndata file: {name}\n"
               f"byte skip: -1\n\n").encode()
        r = client.post("/volumes/leak/upload?format=nrrd", content=hdr, headers=AUTH)
        assert r.status_code == 202, r.text
        st = wait_job(client, r.json()["id"])
        assert st["state"] == "failed" and "data in another file" in st["error"], st
        assert client.get("/volumes/leak", headers=AUTH).status_code == 404
        (root / ".uploads" / "other-upload.raw").unlink()


def test_a_decompression_bomb_upload_is_refused_from_its_header(env):
    """A 600-byte gzip NRRD declaring 4096 x 4096 x 4096 voxels (6.9e10, above the service's max_voxels) fails its
    job naming LODCAST_MAX_VOXELS, before a voxel is read; the uploaded file is removed."""
    import gzip

    client, root, _, _ = env
    hdr = b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 4096 4096 4096\nencoding: gzip\n\n"
    r = client.post("/volumes/bomb/upload?format=nrrd", content=hdr + gzip.compress(b"\0" * 100_000), headers=AUTH)
    assert r.status_code == 202, r.text
    st = wait_job(client, r.json()["id"])
    assert st["state"] == "failed" and "LODCAST_MAX_VOXELS" in st["error"] and "4096x4096x4096" in st["error"], st
    assert client.get("/volumes/bomb").status_code == 404 and not list((root / ".uploads").glob("*.nrrd"))


def test_failed_jobs_do_not_name_server_paths(env):
    """A truncated upload and a broken server-side file fail their jobs with messages about the file, not where
    the server keeps it (the store root, the import roots)."""
    client, root, imports, _ = env
    hdr = b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 8 8 8\nencoding: raw\n\n"
    r = client.post("/volumes/short/upload?format=nrrd", content=hdr + b"\0" * 100)
    st = wait_job(client, r.json()["id"])
    assert st["state"] == "failed" and "the upload" in st["error"] and str(root) not in st["error"], st
    (imports / "short.npy").write_bytes((imports / "blob.npy").read_bytes()[:300])
    r = client.post("/volumes", json={"name": "short", "source": "short.npy"})
    st = wait_job(client, r.json()["id"])
    assert st["state"] == "failed" and "short.npy" in st["error"] and str(imports) not in st["error"], st


def test_every_route_but_healthz_and_docs_needs_the_token(env):
    """docs/design.md, Limits: with LODCAST_TOKEN set every route but /healthz needs the bearer token, reads included
    (issue 10, item 3); the scheme is declared in OpenAPI."""
    client = env[0]
    from fastapi.routing import APIRoute

    open_paths = {"/healthz", "/readyz"}
    checked = 0
    for route in client.app.routes:
        if not isinstance(route, APIRoute) or route.path in open_paths or not route.include_in_schema:  # docs: open
            continue
        path = route.path.replace("{volume_id}", "tiny").replace("{job_id}", "0" * 32).replace("{n}", "0")
        for method in route.methods:
            for headers in (NOAUTH, {"Authorization": "Bearer wrong"}):
                r = client.request(method, path, headers=headers, json={})
                assert r.status_code == 401, (method, path, r.status_code)
                assert r.headers["www-authenticate"] == "Bearer"
            checked += 1
    assert checked >= 12
    assert client.get("/healthz", headers=NOAUTH).status_code == 200
    assert client.get("/volumes").status_code == 200  # with the token
    spec = client.get("/openapi.json", headers=NOAUTH).json()
    assert spec["components"]["securitySchemes"]["HTTPBearer"]["scheme"] == "bearer"


def test_ids_with_a_trailing_newline_or_too_long_are_refused(env):
    client, root, _, _ = env
    buf = io.BytesIO()
    np.save(buf, np.ones((4, 4, 4), np.float32))
    for vid in ("x%0A", "a" * 129):  # "$" let "x\n" through; 129 characters was a 500
        r = client.post(f"/volumes/{vid}/upload?format=npy", content=buf.getvalue())
        assert r.status_code == 400 and "invalid volume id" in r.json()["detail"], r.text
        assert client.get(f"/volumes/{vid}").status_code == 400
    assert not [p for p in root.iterdir() if "\n" in p.name]
    assert client.get("/jobs/" + "0" * 32 + "%0A").status_code == 404


def test_bodies_are_neither_echoed_nor_unbounded(tmp_path):
    settings = Settings(root=tmp_path, workers=0, max_body_bytes=4096)
    with TestClient(create_app(settings)) as c:
        r = c.post("/volumes/x/render", content=b"my secret text", headers={"content-type": "text/plain"})
        assert r.status_code == 422 and "my secret" not in r.text
        big = b'{"kind": "turntable", "volume": "x", "scene": {}, "pad": "' + b"x" * 10_000 + b'"}'
        r = c.post("/jobs", content=big, headers={"content-type": "application/json"})
        assert r.status_code == 413 and "body" in r.json()["detail"]

        def chunks():  # no Content-Length: counted as it arrives
            for _ in range(10):
                yield b" " * 1000

        r = c.post("/jobs", content=chunks(), headers={"content-type": "application/json"})
        assert r.status_code == 413 and "LODCAST_MAX_BODY_BYTES" in r.json()["detail"]
        assert c.get("/healthz").status_code == 200


def test_a_deleted_shard_file_is_a_clear_409(tmp_path):
    import glob
    import os

    make_volume(tmp_path, "v")
    with TestClient(create_app(Settings(root=tmp_path, workers=0))) as c:
        scene = {"tf": {"points": [{"value": 0, "opacity": 0.01}, {"value": 1000, "opacity": 0.5}]}, "width": 8,
                 "height": 8}
        assert c.post("/volumes/v/render", json=scene).status_code == 200
        for f in glob.glob(str(tmp_path / "v" / "[0-9]" / "c" / "*" / "*" / "*")):  # every level's shards
            os.remove(f)
        c.app.state.engine.renderer.close()  # nothing of this volume left in memory: it must be read
        r = c.post("/volumes/v/render", json={**scene, "quality": "lossless"})
        assert r.status_code == 409, r.text
        detail = r.json()["detail"]
        assert detail.startswith("volume 'v': the store is damaged") and str(tmp_path) not in detail


def test_a_volume_replaced_on_disk_is_rendered_from_its_new_data(tmp_path):
    """Another process re-ingests a volume under the same id, with another shape (--overwrite: a new folder renamed
    into place): the next render and summary read the new store, not the one opened before (issue 10, item 5;
    the caches are keyed by the folder's inode and mtime, renderer/data/volume.py)."""
    v = np.zeros((16, 16, 16), np.float32)
    lodcast.ingest(v, tmp_path / "v", block_size=8)
    scene = {"tf": {"points": [{"value": 0, "color": [1, 0, 0], "opacity": 0.0},
                               {"value": 1, "color": [1, 0, 0], "opacity": 0.5}]}, "width": 8, "height": 8,
             "format": "npy"}
    with TestClient(create_app(Settings(root=tmp_path, workers=0))) as c:
        a = np.load(io.BytesIO(c.post("/volumes/v/render", json=scene).content))
        assert a[..., 3].max() == 0.0
        lodcast.ingest(np.ones((24, 20, 16), np.float32), tmp_path / "v", block_size=8, overwrite=True)  # new shape
        r = c.post("/volumes/v/render", json=scene)
        assert r.status_code == 200, r.text
        assert np.load(io.BytesIO(r.content))[..., 3].max() > 0.5
        assert c.get("/volumes/v").json()["shape"] == [24, 20, 16]


def test_uploads_have_a_quota_and_files_no_job_reads_are_swept(tmp_path):
    """ROOT/.uploads holds at most max_uploads_bytes (503 with Retry-After beyond, the refused file removed); a
    cancelled queued upload's file goes at once; the sweep deletes old files no queued or running job reads."""
    import os

    root = tmp_path / "root"
    settings = Settings(root=root, workers=0, max_uploads_bytes=10_000, upload_grace_s=60)
    blob = io.BytesIO()
    np.save(blob, np.zeros((12, 12, 12), np.float32))  # 7 kB
    app = create_app(settings)
    with TestClient(app) as client:
        first = client.post("/volumes/a/upload?format=npy", content=blob.getvalue())
        assert first.status_code == 202 and first.json()["state"] == "queued"  # no worker: it waits
        over = client.post("/volumes/b/upload?format=npy", content=blob.getvalue())
        assert over.status_code == 503 and "LODCAST_MAX_UPLOADS_BYTES" in over.json()["detail"], over.text
        assert over.headers["Retry-After"] == "30" and len(list((root / ".uploads").iterdir())) == 1
        assert client.delete(f"/jobs/{first.json()['id']}").json()["state"] == "cancelled"
        assert not list((root / ".uploads").iterdir())  # nothing will read it: gone at once
        kept = client.post("/volumes/c/upload?format=npy", content=blob.getvalue())
        assert kept.status_code == 202
        jq = app.state.jobs()
        orphan = root / ".uploads" / "0123456789abcdef0123456789abcdef.npy"  # e.g. its job cancelled mid-ingest
        orphan.write_bytes(b"x" * 100)
        young = root / ".uploads" / "fedcba9876543210fedcba9876543210.npy"  # an upload still arriving
        young.write_bytes(b"y")
        old = time.time() - 120
        for p in (root / ".uploads").iterdir():
            if p != young:
                os.utime(p, (old, old))
        assert jq.sweep_uploads() == [orphan.name]
        assert young.exists() and len(list((root / ".uploads").iterdir())) == 2  # the queued job's file stays
