"""Hostile numbers and requests against the service and the scene (issue 49, item 3, the service's side; item 4's
`.nii.gz`): nothing gives a 500, every refusal names its field.

- Finite extreme cameras (`"distance": 1e308`, `"fov": 1e-300`, an eye at ±1e308, a view height of 1e-300, ...)
  are refused alike by HTTP (422), jobs (422 at submission), Python (`SceneError`) and the CLI (exit 2), each
  naming the camera's field; well-defined extreme vectors (`"up": [0, 0, 1e-300]`) render as their direction says.
- `GET /volumes` lists the good volumes and reports a store it cannot read with an `error`, never a 500.
- A path component over 255 bytes in `POST /volumes` is 422 naming `source`.
- `.nii.gz` uploads are ingested (gzip told by its magic bytes).
- A job's summed cost is capped at submission (`LODCAST_MAX_JOB_SAMPLES`, 422 naming `frames` or `scenes`).
- With a token, a request without it is 401 before its body is parsed; the OpenAPI schema states the id rules.
- A seeded fuzz of render bodies with extreme numbers in the camera, sampling, TF, shading and clip fields: no 5xx,
  every 4xx names a field.
"""
from __future__ import annotations

import copy
import gzip
import io
import json
import os
import random
import re
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

import lodcast
from lodcast.renderer.frame.render import check_cost
from lodcast.renderer.scene.scene import SceneError
from lodcast.service.app import create_app
from lodcast.service.settings import Settings
from lodcast.service.testing import TINY_TF, free_port, make_volume, service_folders, start_serve, tiny_scene, wait_job

TOKEN = "hostile-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
JSON = {"content-type": "application/json"}
#: a message that starts with the field's dotted path ("camera.eye: ...", "body: ...")
NAMED = re.compile(r"^[a-z_][a-z0-9_]*(\.[a-z0-9_]+)*: \S")


@pytest.fixture(scope="module")
def env(tmp_path_factory: pytest.TempPathFactory):
    base = tmp_path_factory.mktemp("hostile")
    root, imports = service_folders(base, "blob.npy", np.zeros((8, 8, 8), np.float32))
    settings = Settings(root=root, token=TOKEN, import_roots=[imports], max_width=64, max_height=64, max_frames=50,
                        min_step=0.25, workers=1, poll_s=0.05)
    with TestClient(create_app(settings), headers=AUTH) as client:
        yield client, root, imports, base


def messages(resp) -> list[str]:
    detail = resp.json()["detail"]
    return [d["msg"] for d in detail] if isinstance(detail, list) else [detail]


# --- 1. cameras whose numbers make the view non-finite or degenerate -----------------------------------------------

LOOK = {"eye": [11.5, -60.0, 11.5], "target": [11.5, 11.5, 11.5]}
CAMERAS = [
    ({"azimuth": 10, "distance": 1e308}, "camera.distance"),
    ({"azimuth": 10, "distance": 1e-308}, "camera.distance"),
    ({"azimuth": 10, "fov": 1e-300}, "camera.fov"),
    ({"azimuth": 10, "fov": 180.5}, "camera.fov"),
    ({**LOOK, "fov": 1e-300}, "camera.fov"),
    ({"eye": [1e308, 0, 0], "target": [0, 0, 0]}, "camera.eye"),
    ({"eye": [0, -1e308, 0], "target": [11.5, 11.5, 11.5]}, "camera.eye"),
    ({"eye": [-1e308, 0, 0], "target": [1e308, 0, 0]}, "camera.target"),
    ({"eye": [11.5, -60.0, 11.5], "target": [11.5, 1e308, 11.5]}, "camera.target"),
    ({"eye": [1, 2, 3], "target": [1, 2, 3]}, "camera.target"),
    ({**LOOK, "up": [0, 1, 0]}, "camera.up"),
    ({**LOOK, "projection": "orthographic", "view_height": 1e-300}, "camera.view_height"),
    ({**LOOK, "projection": "orthographic", "view_height": 1e308}, "camera.view_height"),
    ({"azimuth": 10, "projection": "orthographic", "view_height": 1e308}, "camera.view_height"),
]


@pytest.mark.parametrize("camera, field", CAMERAS, ids=[f"{f}={json.dumps(c)}" for c, f in CAMERAS])
def test_extreme_cameras_are_refused_naming_the_field(env, camera, field):
    """HTTP 422 naming the field (it was a 200 of an empty image, or a 500 and a dropped connection), and the same
    refusal from Python (SceneError) and inside a job (422 at submission, naming the scene's place)."""
    client, root = env[0], env[1]
    scene = {**tiny_scene(), "camera": camera}
    r = client.post("/volumes/tiny/render", json=scene)
    assert r.status_code == 422, (r.status_code, r.text[:300])
    err = r.json()["detail"][0]
    assert err["loc"] == ["body", *field.split(".")] and err["msg"].startswith(f"{field}: "), err
    with pytest.raises(SceneError, match=rf"^{re.escape(field)}: "):
        lodcast.render(root / "tiny", scene)
    r = client.post("/jobs", json={"kind": "turntable", "volume": "tiny", "scene": scene, "frames": 2})
    assert r.status_code == 422, (r.status_code, r.text[:300])
    err = r.json()["detail"][0]
    assert err["loc"] == ["body", "scene", *field.split(".")] and err["msg"].startswith(f"scene.{field}: "), err


def test_the_cli_refuses_extreme_cameras_with_exit_2(env, tmp_path):
    root = env[1]
    for camera, field in (CAMERAS[0], CAMERAS[5], CAMERAS[11]):
        scene = tmp_path / "scene.json"
        scene.write_text(json.dumps({**tiny_scene(), "camera": camera}))
        out = tmp_path / "out.png"
        proc = subprocess.run([sys.executable, "-m", "lodcast", "render", str(root / "tiny"), "-o", str(out),
                               "--scene", str(scene)], capture_output=True, text=True, timeout=300)
        assert proc.returncode == 2, (camera, proc.returncode, proc.stderr[-2000:])
        assert field in proc.stderr and "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
        assert not out.exists()


def test_well_defined_extreme_vectors_render_as_their_direction_says(env):
    """An up of 1e-300 or 1e308 and an eye 1e-300 from its target overflowed or underflowed when normalised: refused
    as "the zero vector" or "parallel", or a blank image. Scaled first, they give the picture their direction
    gives."""
    client = env[0]

    def npy(camera: dict) -> np.ndarray:
        r = client.post("/volumes/tiny/render", json={**tiny_scene(), "camera": camera, "format": "npy"})
        assert r.status_code == 200, r.text[:300]
        return np.load(io.BytesIO(r.content))

    plain = npy(LOOK)
    assert plain[..., 3].max() > 0.05
    for up in ([0, 0, 1e-300], [0, 0, 1e308], [0, 0, 5e-324]):
        assert np.array_equal(npy({**LOOK, "up": up}), plain), up
    near = npy({"eye": [11.5, -1e-300, 11.5], "target": [11.5, 0.0, 11.5]})  # from the front face, along +y
    same = npy({"eye": [11.5, -1e-9, 11.5], "target": [11.5, 0.0, 11.5]})
    assert near[..., 3].max() > 0.05 and np.allclose(near, same, atol=1e-4)


# --- 2. GET /volumes never fails as a whole -------------------------------------------------------------------------

def _bad_stores(root: Path) -> dict[str, str]:
    """Copies of the tiny store, damaged as an older lodcast or a disk might leave them: name -> what the error
    names."""
    def edit(name: str, key: str, value: object) -> None:
        p = root / name / "zarr.json"
        doc = json.loads(p.read_text())
        doc["attributes"][key] = value
        p.write_text(json.dumps(doc))

    for name in ("huge", "subnormal", "faraway", "garbled"):
        shutil.copytree(root / "tiny", root / name)
    edit("huge", "spacing", [1e308, 1e308, 1e308])  # ingested by lodcast before the world box was checked
    edit("subnormal", "spacing", [1e-320, 1.0, 1.0])
    edit("faraway", "origin", [1e308, -1e308, 0.0])
    (root / "garbled" / "zarr.json").write_text('{"zarr_format": 3, "node_type": "gr')
    return {"huge": "spacing", "subnormal": "spacing", "faraway": "origin", "garbled": "zarr"}


def test_one_bad_store_never_fails_the_listing(tmp_path):
    """Spacing 1e308 made GET /volumes a 500 for every client until the volume was deleted (and GET /volumes/{id}
    and its renders 500 too). Now the good volumes are listed, each bad one as {"id", "error"} naming what is wrong,
    and the bad ones answer 409 (404: not a readable store) naming it; through a real `lodcast serve` and the typed
    client."""
    root = tmp_path / "root"
    root.mkdir()
    make_volume(root, "tiny")
    bad = _bad_stores(root)
    port = free_port()
    log = tmp_path / "serve.log"
    proc = start_serve(root, port, env={"LODCAST_TOKEN": TOKEN}, log=log)
    try:
        url = f"http://127.0.0.1:{port}"
        import httpx

        r = httpx.get(f"{url}/volumes", headers=AUTH, timeout=60)
        assert r.status_code == 200, r.text[:500]
        listed = {v["id"]: v for v in r.json()}
        assert set(listed) == {"tiny", *bad}
        assert "error" not in listed["tiny"] and listed["tiny"]["shape"] == [24, 24, 24]
        for name, what in bad.items():
            assert set(listed[name]) == {"id", "error"} and what in listed[name]["error"], listed[name]
            r = httpx.get(f"{url}/volumes/{name}", headers=AUTH, timeout=60)
            assert r.status_code == (404 if name == "garbled" else 409) and what in r.json()["detail"], r.text
            r = httpx.post(f"{url}/volumes/{name}/render", json=tiny_scene(), headers=AUTH, timeout=60)
            assert r.status_code == (404 if name == "garbled" else 409) and what in r.json()["detail"], r.text
        assert httpx.post(f"{url}/volumes/tiny/render", json=tiny_scene(), headers=AUTH, timeout=60).status_code == 200
        with lodcast.Client(url, token=TOKEN) as client:
            vols = {v.id: v for v in client.volumes()}
        from lodcast.service.models import VolumeSummary, VolumeUnreadable

        assert isinstance(vols["tiny"], VolumeSummary) and vols["tiny"].shape == [24, 24, 24]
        assert all(isinstance(vols[n], VolumeUnreadable) and vols[n].error for n in bad)
    finally:
        proc.stop()
    assert "Traceback" not in log.read_text(), log.read_text()[-3000:]


# --- 3. long path components ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("source", ["a" * 256, "sub/" + "é" * 128 + "/x.npy", "blob.npy/" + "b" * 300, "x" * 4000,
                                    "/" + "c" * 300])
def test_a_path_component_over_255_bytes_is_422_naming_source(env, source):
    """ENAMETOOLONG from the filesystem was a 500."""
    client = env[0]
    for path, body in (("/volumes", {"name": "longname", "source": source}),
                       ("/jobs", {"kind": "ingest", "name": "longname", "source": source})):
        r = client.post(path, json=body)
        assert r.status_code == 422, (path, r.status_code, r.text[:300])
        assert r.json()["detail"][0]["loc"] == ["body", "source"] and "255 bytes" in messages(r)[0], r.text[:300]
    r = client.post("/volumes", content=b'{"name": "longname", "source": "x\\ud800y"}', headers={**AUTH, **JSON})
    assert r.status_code == 422 and "source" in messages(r)[0]


# --- 4. .nii.gz uploads ---------------------------------------------------------------------------------------------

def test_nifti_uploads_gzipped_or_not(env, tmp_path):
    """Every NIfTI upload was stored as .nii, so a .nii.gz (gzip: 1f 8b) could never be read by nibabel."""
    nib = pytest.importorskip("nibabel")
    client, root = env[0], env[1]
    data = np.arange(6 * 7 * 8, dtype=np.int16).reshape(8, 7, 6)
    nib.save(nib.Nifti1Image(data, np.diag([1.0, 2.0, 3.0, 1.0])), tmp_path / "v.nii")
    for name, body in (("gz", gzip.compress((tmp_path / "v.nii").read_bytes())),
                       ("plain", (tmp_path / "v.nii").read_bytes())):
        r = client.post(f"/volumes/nii{name}/upload?format=nifti", content=body)
        assert r.status_code == 202, r.text
        st = wait_job(client, r.json()["id"])
        assert st["state"] == "done", st
        info = client.get(f"/volumes/nii{name}").json()
        assert info["shape"] == [6, 7, 8] and info["value_range"] == [0, 6 * 7 * 8 - 1], info
    assert not list((root / ".uploads").glob("*")), "an ingested upload leaves nothing behind"


def test_a_refused_upload_is_one_log_line_not_a_traceback(env, caplog):
    """Every hostile upload's refusal was logged with a full traceback (the 28 refused files of
    benchmarks/bench_hostile_inputs.py left 28 in the server's log); a refusal of lodcast's own (a LodcastError)
    is one line naming the job and the reason."""
    import logging

    client = env[0]
    body = b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 4 4 2\nencoding: raw\nline skip: 1000000000000\n\n" + bytes(600)
    with caplog.at_level(logging.INFO, logger="lodcast.service.queue"):
        r = client.post("/volumes/skips/upload?format=nrrd", content=body)
        assert r.status_code == 202, r.text
        st = wait_job(client, r.json()["id"])
    assert st["state"] == "failed" and "line skip" in st["error"], st
    mine = [rec for rec in caplog.records if r.json()["id"] in rec.getMessage()]
    assert len(mine) == 1 and mine[0].levelno == logging.WARNING and mine[0].exc_info is None, mine
    assert "line skip" in mine[0].getMessage()


# --- 5. a job's summed cost -----------------------------------------------------------------------------------------

def test_a_job_s_summed_cost_is_capped_at_submission(tmp_path, monkeypatch):
    """1,000 frames each near the render limit (14 hours) were accepted. Now the frames' estimates are summed (a
    turntable: frames x the first frame's) and a job above LODCAST_MAX_JOB_SAMPLES is 422 naming frames or scenes."""
    monkeypatch.delenv("LODCAST_MAX_JOB_SAMPLES", raising=False)
    assert Settings(root=tmp_path).max_job_samples == 10**12  # docs/design.md, Limits
    monkeypatch.setenv("LODCAST_MAX_JOB_SAMPLES", "2.5e5")
    assert Settings(root=tmp_path).max_job_samples == 250_000
    make_volume(tmp_path, "tiny")
    scene = tiny_scene(32)
    one = check_cost(tmp_path / "tiny", scene, 10**15)
    frames = 250_000 // one  # the most that fit
    assert 2 <= frames < 50, one
    settings = Settings(root=tmp_path, token=None, workers=0, max_job_samples=frames * one)
    with TestClient(create_app(settings)) as client:
        ok = client.post("/jobs", json={"kind": "turntable", "volume": "tiny", "scene": scene, "frames": frames})
        assert ok.status_code == 202, ok.text
        r = client.post("/jobs", json={"kind": "turntable", "volume": "tiny", "scene": scene, "frames": frames + 1})
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "frames"], r.text
        assert messages(r)[0].startswith("frames: ") and "LODCAST_MAX_JOB_SAMPLES" in messages(r)[0]
        scenes = [scene] * (frames + 1)
        r = client.post("/jobs", json={"kind": "scenes", "volume": "tiny", "scenes": scenes})
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "scenes"], r.text
        assert client.post("/jobs", json={"kind": "scenes", "volume": "tiny", "scenes": scenes[1:]}).status_code == 202
        r = client.post("/jobs", json={"kind": "tf_sweep", "volume": "tiny", "scene": scene,
                                       "tfs": [TINY_TF] * (frames + 1)})
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "tfs"], r.text


# --- 6. the token before the body; the id rules in the schema -------------------------------------------------------

def test_the_token_is_checked_before_the_body_is_parsed(env):
    """A request without the token but with bad JSON got 422 (the body was validated first), telling a client
    without the token what the route expects. Now 401, whatever the body; with the token the body is judged."""
    client = env[0]
    bad = b'{"camera": '
    for method, path in (("POST", "/volumes/tiny/render"), ("POST", "/jobs"), ("POST", "/volumes"),
                         ("POST", "/volumes/tiny/render?progressive=true"), ("GET", "/volumes"),
                         ("POST", "/volumes/x/upload?format=nifti&overwrite=maybe")):
        for auth in ("", "Bearer wrong", "Basic " + TOKEN):
            r = client.request(method, path, content=bad, headers={**JSON, "Authorization": auth})
            assert r.status_code == 401, (method, path, auth, r.status_code, r.text[:200])
            assert r.headers["WWW-Authenticate"] == "Bearer" and "Authorization" in r.json()["detail"]
    r = client.post("/volumes/tiny/render", content=bad, headers=JSON)
    assert r.status_code == 422 and messages(r) == [messages(r)[0]] and messages(r)[0].startswith("body: not valid JSON")
    for path in ("/healthz", "/docs", "/openapi.json"):  # open, as docs/design.md's LODCAST_TOKEN line says
        assert client.get(path, headers={"Authorization": ""}).status_code == 200, path


def test_the_openapi_schema_states_the_id_rules(env):
    """schemathesis generated volume ids the server must reject (10 valid-looking requests refused): the pattern and
    length are in the schema now, and they are the server's own rules."""
    from lodcast.service.volumes import VOLUME_ID

    spec = env[0].get("/openapi.json").json()
    for path, ops in spec["paths"].items():
        for op in ops.values():
            for p in op.get("parameters", []):
                if p["name"] == "volume_id":
                    s = p["schema"]
                    assert s["maxLength"] == 128 and s["minLength"] == 1, (path, s)
                    rule = re.compile(s["pattern"])
                elif p["name"] == "job_id":
                    assert p["schema"]["pattern"] == "^[0-9a-f]{32}$", path
    for vid in ("tiny", "a", "ch2.zarr", "A-b_c.9", "a" * 128, "a" * 129, ".hidden", "-x", "..", "a/b", "a\n", "é"):
        assert bool(rule.fullmatch(vid)) == bool(VOLUME_ID.match(vid)), vid


# --- the fuzz -------------------------------------------------------------------------------------------------------

EXTREMES = [0.0, -0.0, 1e308, -1e308, 1.7976931348623157e308, 1e-308, -1e-308, 5e-324, 1e-300, 1e300, 3.5e38,
            -3.5e38, 1e38, 1e-38, 1e-45, 2.0**53, -(2.0**63), 2.0**64, 1e15, 1e-15, 1e7, 1e-7, 1e6, 1e-6, 1.0, -1.0,
            0.5, 90.0, -90.0, 179.0, 179.999, 180.0, 360.0]
#: fields the fuzz puts an extreme number into (a path into the scene; skipped where the base scene has no such part)
FIELDS = [("camera", "eye", 0), ("camera", "eye", 1), ("camera", "target", 2), ("camera", "up", 0), ("camera", "up", 2),
          ("camera", "fov"), ("camera", "view_height"), ("camera", "azimuth"), ("camera", "elevation"),
          ("camera", "distance"), ("sampling", "step"), ("sampling", "early_termination"), ("sampling", "seed"),
          ("tf", "points", 0, "value"), ("tf", "points", 1, "value"), ("tf", "points", 1, "opacity"),
          ("tf", "points", 0, "color", 1), ("tf", "unit_distance"), ("tf2", "points", 0, "value"),
          ("tf2", "unit_distance"), ("quality", "reduction"), ("quality", "budget_mb"), ("shading", "shininess"),
          ("shading", "light", 1), ("shading", "min_gradient"), ("shading", "gradient_weighting"),
          ("clip", "planes", 0, "point", 0), ("clip", "planes", 0, "normal", 1), ("clip", "box", "min", 0),
          ("clip", "box", "max", 2), ("isovalue",), ("background", 3), ("width",), ("height",)]
OPTIONAL = {"fov", "distance", "view_height", "unit_distance", "early_termination", "seed"}
FUZZ_CASES = int(os.environ.get("LODCAST_FUZZ_CASES", "300"))


def _base_scene(rng: random.Random) -> dict:
    """A valid scene of the tiny volume, with a random camera and some of the optional parts."""
    if rng.random() < 0.5:
        cam: dict = {"eye": [rng.uniform(-60, 60), -50.0, rng.uniform(-20, 40)], "target": [11.5, 11.5, 11.5],
                     "up": [0.0, 0.0, 1.0]}
    else:
        cam = {"azimuth": rng.uniform(-180, 180), "elevation": rng.uniform(-80, 80), "distance": rng.uniform(0.5, 4)}
    if rng.random() < 0.25:
        cam.update(projection="orthographic", view_height=rng.uniform(5, 60))
    sc = {"camera": cam, "width": rng.choice([1, 7, 16]), "height": rng.choice([1, 5, 16]),
          "tf": {**copy.deepcopy(TINY_TF), "unit_distance": 1.0}, "sampling": {"step": rng.choice([0.5, 1.0, 2.0])}}
    if rng.random() < 0.15:
        sc["tf2"] = {"points": [{"value": 100, "color": [1, 0, 0], "opacity": 0},
                                {"value": 900, "color": [0, 1, 0], "opacity": 0.5}], "unit_distance": 1.0}
    if rng.random() < 0.2:
        sc["quality"] = rng.choice([{"reduction": 4.0}, {"budget_mb": 1.0}])
    if rng.random() < 0.2:
        sc["shading"] = {"shininess": 32.0, "light": [1.0, 1.0, 1.0], "min_gradient": 1.0, "gradient_weighting": 1.0}
    if rng.random() < 0.2:
        sc["clip"] = {"planes": [{"point": [11.5, 11.5, 11.5], "normal": [1.0, 0.0, 0.0]}],
                      "box": {"min": [0.0, 0.0, 0.0], "max": [20.0, 20.0, 20.0]}}
    if rng.random() < 0.1 and "tf2" not in sc:
        sc.update(mode="iso", isovalue=500.0)
    if rng.random() < 0.1:
        sc["background"] = [0.0, 0.0, 0.0, 1.0]
    return sc


def _put(scene: dict, path: tuple, value: float) -> bool:
    """Put `value` at `path` in the scene where that part exists (an optional leaf may be added); False if not."""
    cur: object = scene
    for key in path[:-1]:
        if isinstance(cur, dict) and key in cur:
            cur = cur[key]
        elif isinstance(cur, list) and isinstance(key, int) and key < len(cur):
            cur = cur[key]
        else:
            return False
    leaf = path[-1]
    if isinstance(cur, list):
        if leaf >= len(cur):
            return False
        cur[leaf] = value
        return True
    assert isinstance(cur, dict)
    orbit = "azimuth" in cur or "distance" in cur
    if leaf not in cur and (leaf not in OPTIONAL or (leaf == "distance" and not orbit)):
        return False
    cur[leaf] = int(value) if leaf in ("seed", "width", "height") and abs(value) < 2**63 else value
    return True


def test_fuzzed_render_bodies_never_make_a_5xx_and_every_4xx_names_a_field(env):
    """A few hundred render bodies (seeded: the same every run), each a valid scene with one or two fields set to
    an extreme number (±1e308, 5e-324, 3.5e38, 2^64, ...): no 5xx, every 4xx's JSON names the field at fault (each
    message starts with its dotted path), and a 200 is an image."""
    client = env[0]
    rng = random.Random(49)
    seen: dict[int, int] = {}
    failures = []
    for _ in range(FUZZ_CASES):
        scene = _base_scene(rng)
        for _ in range(rng.choice([1, 1, 2])):
            for _ in range(50):
                if _put(scene, rng.choice(FIELDS), rng.choice(EXTREMES) * rng.choice([1.0, 1.0, 1.0000001])):
                    break
        body = json.dumps(scene)  # 1e308 as 1e+308; a product that overflowed as Infinity, which the server parses
        r = client.post("/volumes/tiny/render", content=body, headers=JSON)
        seen[r.status_code] = seen.get(r.status_code, 0) + 1
        if r.status_code >= 500:
            failures.append(f"{r.status_code} {r.text[:200]} for {body[:400]}")
        elif r.status_code >= 400:
            bad = [m for m in messages(r) if not NAMED.match(m)]
            if bad:
                failures.append(f"{r.status_code} names no field: {bad[0][:200]} for {body[:400]}")
        elif r.status_code != 200 or not r.content.startswith(b"\x89PNG"):
            failures.append(f"{r.status_code} {r.headers.get('content-type')} for {body[:400]}")
    assert not failures, f"{len(failures)} of {FUZZ_CASES}: " + "\n".join(failures[:5])
    assert seen.get(200, 0) >= FUZZ_CASES // 10 and seen.get(422, 0) >= FUZZ_CASES // 10, seen  # both sides covered
