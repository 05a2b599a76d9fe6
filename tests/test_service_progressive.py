"""Progressive renders over HTTP (service/progressive.py), through the clients, and from `lodcast render --progressive`:
NDJSON lines that parse, every image H×W, the last the plain render's bytes; a dropped connection and a newer
request of the same X-Lodcast-Session end a stream before its final stage."""
from __future__ import annotations

import asyncio
import base64
import io
import json
import warnings
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image
from recording import record_renders

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

import lodcast
from lodcast.errors import StoreCorrupt
from lodcast.service.app import create_app
from lodcast.service.cli import main
from lodcast.service.client import ServiceError
from lodcast.service.settings import Settings
from lodcast.service.testing import TINY_TF, make_volume

TOKEN = "prog-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
URL = "/volumes/v/render"
PROGRESSIVE = {"progressive": "true"}


def scene(**extra: object) -> dict:
    return {"camera": {"azimuth": 30, "elevation": 20}, "width": 96, "height": 64, "tf": TINY_TF, **extra}


@pytest.fixture(scope="module")
def root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("progsvc") / "root"
    root.mkdir()
    make_volume(root, "v", n=64, block_size=8)  # staged: 64³ voxels, blocks of 8
    return root


@pytest.fixture
def client(root):
    with TestClient(create_app(Settings(root=root, token=TOKEN, workers=0)), headers=AUTH) as c:
        yield c


def lines(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines() if line]


@pytest.mark.parametrize("fmt", ["png", "npy"])
def test_stages_stream_as_ndjson_and_end_with_the_plain_image(client, fmt):
    r = client.post(URL, params=PROGRESSIVE, json=scene(format=fmt))
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/x-ndjson")
    got = lines(r.text)
    assert [g["stage"] for g in got] == [0, 1, 2] and [g["final"] for g in got] == [False, False, True]
    assert all(set(g) == {"stage", "final", "report", "image"} and g["report"]["stage"] == g["stage"] for g in got)
    plain = client.post(URL, json=scene(format=fmt))
    images = [base64.b64decode(g["image"]) for g in got]
    if fmt == "npy":
        arrays = [np.load(io.BytesIO(b), allow_pickle=False) for b in images]
        assert images[-1] == plain.content  # the same bytes: the same float32 image
    else:  # a PNG carries its report (times differ): the same pixels
        arrays = [np.asarray(Image.open(io.BytesIO(b))) for b in images]
        np.testing.assert_array_equal(arrays[-1], np.asarray(Image.open(io.BytesIO(plain.content))))
    assert all(a.shape == (64, 96, 4) for a in arrays)
    reports = [g["report"] for g in got]
    assert [x["reduction"] for x in reports] == sorted((x["reduction"] for x in reports), reverse=True)
    assert [x["predicted_delta_e"] for x in reports] == sorted((x["predicted_delta_e"] for x in reports), reverse=True)
    assert [x["wall_ms"] for x in reports] == sorted(x["wall_ms"] for x in reports)
    assert reports[0]["samples"] < reports[-1]["samples"] == json.loads(plain.headers["x-lodcast-report"])["samples"]


def test_a_newer_request_of_the_session_cancels_the_older_ones_stages(client, monkeypatch):
    """The test client hands the app one line at a time as the test reads it: holding the first stream after its
    first line keeps it from starting its final stage, and the second request of the same session, read in full
    meanwhile, cancels what the first has to come."""
    seen = record_renders(monkeypatch, client.app.state.engine.renderer)  # type: ignore[attr-defined]
    session = {"X-Lodcast-Session": "viewer-1"}
    with client.stream("POST", URL, params=PROGRESSIVE, json=scene(format="npy"), headers=session) as first:
        it = first.iter_lines()
        assert json.loads(next(it))["stage"] == 0
        second = lines(client.post(URL, params=PROGRESSIVE, json=scene(format="npy"), headers=session).text)
        rest = [json.loads(line) for line in it if line]
    assert [g["stage"] for g in second] == [0, 1, 2] and second[-1]["final"]
    assert all(not g["final"] for g in rest) and [g["stage"] for g in rest] in ([], [1])
    finals = [s for s in seen if s["quality"] == "full"]
    assert len(finals) == 1, seen  # the second's: the first never rendered its final stage
    assert len(client.app.state.engine.sessions) == 0  # type: ignore[attr-defined]


def test_other_sessions_do_not_cancel(client):
    with client.stream("POST", URL, params=PROGRESSIVE, json=scene(format="npy"),
                       headers={"X-Lodcast-Session": "a"}) as first:
        it = first.iter_lines()
        assert json.loads(next(it))["stage"] == 0
        other = lines(client.post(URL, params=PROGRESSIVE, json=scene(format="npy"),
                                  headers={"X-Lodcast-Session": "b"}).text)
        rest = [json.loads(line) for line in it if line]
    assert other[-1]["final"] and [g["stage"] for g in rest] == [1, 2] and rest[-1]["final"]


def test_a_dropped_connection_cancels_its_stages(client, monkeypatch):
    seen = record_renders(monkeypatch, client.app.state.engine.renderer)  # type: ignore[attr-defined]
    with client.stream("POST", URL, params=PROGRESSIVE, json=scene(format="npy"),
                       headers={"X-Lodcast-Session": "gone"}) as r:
        assert json.loads(next(r.iter_lines()))["stage"] == 0
    # hung up after the first line: the stage after it may have rendered, the final did not
    assert 1 <= len(seen) <= 2 and all(s["quality"] != "full" for s in seen), seen
    assert len(client.app.state.engine.sessions) == 0  # type: ignore[attr-defined]


def test_stages_bounds_the_stream(client, monkeypatch):
    """?stages=k: the first k stages and no more rendered (a viewer's preview asks for 1)."""
    seen = record_renders(monkeypatch, client.app.state.engine.renderer)  # type: ignore[attr-defined]
    got = lines(client.post(URL, params={**PROGRESSIVE, "stages": 1}, json=scene(format="npy")).text)
    assert [g["stage"] for g in got] == [0] and not got[0]["final"] and len(seen) == 1, seen
    got = lines(client.post(URL, params={**PROGRESSIVE, "stages": 2}, json=scene(format="npy")).text)
    assert [g["stage"] for g in got] == [0, 1] and len(seen) == 3
    assert [g["stage"] for g in lines(client.post(URL, params={**PROGRESSIVE, "stages": 9}, json=scene()).text)] == [0, 1, 2]
    r = client.post(URL, params={**PROGRESSIVE, "stages": 0}, json=scene())
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "stages"]


def test_refusals_come_before_the_stream_and_failures_as_its_last_line(client, monkeypatch):
    assert client.post(URL, params=PROGRESSIVE, json=scene(), headers={"Authorization": ""}).status_code == 401
    r = client.post(URL, params=PROGRESSIVE, json=scene(), headers={"X-Lodcast-Session": "x" * 129})
    assert r.status_code == 422 and "x-lodcast-session" in r.text.lower()
    assert client.post("/volumes/none/render", params=PROGRESSIVE, json=scene()).status_code == 404
    eng = client.app.state.engine.renderer  # type: ignore[attr-defined]
    plain = eng.render

    def damaged_after_first(store, sc, **kw):  # type: ignore[no-untyped-def]
        if lodcast.Scene.parse(sc).width == 96:  # the stages after the first (at the scene's size)
            raise StoreCorrupt("shard 0/c/0/0/0 does not decode")
        return plain(store, sc, **kw)

    monkeypatch.setattr(eng, "render", damaged_after_first)
    got = lines(client.post(URL, params=PROGRESSIVE, json=scene()).text)
    assert got[0]["stage"] == 0 and got[-1]["error"]["status"] == 409 and "damaged" in got[-1]["error"]["detail"]


def test_the_clients_yield_render_results(client, root):
    local = lodcast.Renderer().render(root / "v", scene(format="npy"))
    with lodcast.Client("http://testserver", token=TOKEN, transport=client._transport) as c:
        stages = list(c.render_progressive("v", scene()))
        with pytest.raises(ServiceError) as e:
            list(c.render_progressive("none", scene()))
    assert e.value.status == 404
    assert [s.report["stage"] for s in stages] == [0, 1, 2] and stages[-1].report["final"]
    assert all(isinstance(s, lodcast.RenderResult) and s.rgba.shape == (64, 96, 4) for s in stages)
    np.testing.assert_array_equal(stages[-1].rgba, local.rgba)

    async def collect() -> list[lodcast.RenderResult]:
        transport = httpx.ASGITransport(app=client.app)
        async with lodcast.AsyncClient("http://testserver", token=TOKEN, transport=transport) as ac:
            return [s async for s in ac.render_progressive("v", scene())]

    again = asyncio.run(collect())
    assert [s.report["stage"] for s in again] == [0, 1, 2]
    np.testing.assert_array_equal(again[-1].rgba, local.rgba)


def test_the_cli_writes_each_stage(root, tmp_path, capsys):
    out = tmp_path / "v.png"
    assert main(["render", str(root / "v"), "-o", str(out), "--tf", json.dumps(TINY_TF), "--width", "96",
                 "--height", "64", "--progressive", "--report", str(tmp_path / "r.json")]) == 0
    err = capsys.readouterr().err.splitlines()
    assert [line.split(":")[0] for line in err[:3]] == ["stage 0", "stage 1", "stage 2 (final)"]
    assert len(err) == 4 and err[3].startswith(f"wrote {out}")
    assert "reduction 64" in err[0] and "predicted ΔE" in err[0] and " ms since the start" in err[0]
    for path in (tmp_path / "v-stage0.png", tmp_path / "v-stage1.png", out):
        assert Image.open(path).size == (96, 64)
    assert json.loads((tmp_path / "r.json").read_text())["final"] is True
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json", "v-stage0.png", "v-stage1.png", "v.png"]
