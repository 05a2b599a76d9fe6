"""The web viewer's server side (service/viewer.py, service/histograms.py): the histogram route against an analytic
volume — a large background, a large tissue with a broad spread of values and a small coherent one whose peak the
plain histogram buries under the large tissue's tail and the α-histogram of thesis §3.3.2 (eq. 3.4) reveals — and
the page's shell, open with a token set and shipped as package data."""
from __future__ import annotations

import fnmatch
import tomllib
import warnings
from pathlib import Path

import numpy as np
import pytest

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

import lodcast
import lodcast.service.histograms as histograms
from lodcast.service.app import create_app
from lodcast.service.histograms import SUGGESTED_OPACITY, find_peaks
from lodcast.service.settings import Settings
from lodcast.service.viewer import STATIC
from lodcast.store.store import open_store

TOKEN = "viewer-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
N, B = 64, 8
BIG, SMALL = 400.0, 700.0  # the tissues' mean values; the background is 0


def analytic() -> np.ndarray:
    """Background N(0, 15) in 72 % of the voxels, a sphere of N(400, 120) in 22 %, and one block of N(700, 15):
    0.2 %, in the large tissue's tail (2.5 σ above its mean)."""
    rng = np.random.default_rng(7)
    z, y, x = np.mgrid[:N, :N, :N]
    v = rng.normal(0.0, 15.0, (N, N, N))
    big = (z - 32) ** 2 + (y - 32) ** 2 + (x - 28) ** 2 < 24**2
    v[big] = rng.normal(BIG, 120.0, int(big.sum()))
    small = (z >= 48) & (z < 56) & (y >= 8) & (y < 16) & (x >= 48) & (x < 56)  # exactly one block
    v[small] = rng.normal(SMALL, 15.0, int(small.sum()))
    return np.clip(v, -50, 1000).astype(np.float32)


@pytest.fixture(scope="module")
def root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("viewer") / "root"
    root.mkdir()
    lodcast.ingest(analytic(), root / "tissues", block_size=B)
    return root


@pytest.fixture(scope="module")
def client(root):
    with TestClient(create_app(Settings(root=root, token=TOKEN, workers=0)), headers=AUTH) as c:
        yield c


def bin_width(h: dict) -> float:
    return float(np.diff(h["edges"]).max())


def test_the_alpha_histogram_reveals_the_small_tissue_the_plain_one_hides(client):
    h = client.get("/volumes/tissues/histogram").json()
    w = bin_width(h)
    assert h["alpha"] == 4.0 and len(h["edges"]) == len(h["counts"]) + 1 == len(h["alpha_counts"]) + 1
    suggested = [p for p in h["peaks"] if not p["background"]]
    near = lambda peaks, v, tol: [p for p in peaks if abs(p["value"] - v) <= tol]  # noqa: E731
    # the small tissue is the α-histogram's most prominent peak, within a bin and a half of its mean
    assert abs(suggested[0]["value"] - SMALL) <= 1.5 * w, suggested
    assert near(suggested, BIG, 15.0), suggested  # the large tissue (the α-sum skews it a little towards the edges)
    bg = [p for p in h["peaks"] if p["background"]]
    assert len(bg) == 1 and abs(bg[0]["value"]) <= w and h["peaks"][-1] is not None and h["peaks"][-1]["background"]
    assert abs(h["background"]) <= w
    # its share of the voxels: one block of 512 (plus its border counted there) in 64³, within the peak's half-width
    small = suggested[0]
    assert 0.5 * 512 / N**3 <= small["weight"] <= 1.5 * 1000 / N**3, small
    # the plain histogram has no peak near it as prominent as the route asks of a peak (its tissues are found), and
    # the bump it has there, at any prominence, stands out less than a fifth as far as the α-histogram's peak
    centres = 0.5 * (np.asarray(h["edges"][1:]) + np.asarray(h["edges"][:-1]))
    plain = np.asarray(h["counts"])
    assert not near([vars(p) for p in find_peaks(plain, centres)], SMALL, 50.0)
    assert near([vars(p) for p in find_peaks(plain, centres)], BIG, 15.0)
    bump = near([vars(p) for p in find_peaks(plain, centres, min_prominence=0.0)], SMALL, 50.0)
    assert all(b["prominence"] < suggested[0]["prominence"] / 5 for b in bump), (bump, suggested[0])
    # its suggested TF shows the small tissue's values and hides the large one's mean and the background; a ray
    # across the tissue's typical extent ((share × voxels)^(1/3) voxels) keeps SUGGESTED_OPACITY of it
    pts = small["tf"]["points"]
    tf = lambda v: np.interp(v, [p["value"] for p in pts], [p["opacity"] for p in pts])  # noqa: E731
    assert tf(BIG) == 0.0 and tf(0.0) == 0.0 and tf(small["value"]) == pytest.approx(max(p["opacity"] for p in pts))
    extent = (small["weight"] * N**3) ** (1 / 3)
    assert 1 - (1 - tf(small["value"])) ** extent == pytest.approx(SUGGESTED_OPACITY, abs=1e-3)
    big = near(suggested, BIG, 15.0)[0]
    assert big["tf"]["points"][1]["opacity"] < tf(small["value"]) / 2  # the large tissue: seen into
    # the adaptive presets, placed on this volume
    assert set(h["adapted"]) == {"auto", "mr-soft"} and all(tf["points"] for tf in h["adapted"].values())


def test_counts_are_the_block_histograms_and_eq_3_4_in_float64(client, root, monkeypatch):
    """Plain: the block histograms summed (border-inclusive: between the voxel count and (1 + 2/B)³ times it).
    α: eq. 3.4 over each block's distribution, computed here directly in float64, the same after the route sums
    it in chunks of 7 blocks."""
    store = open_store(root / "tissues")
    hist = np.asarray(store.hist, np.float64).reshape(-1, store.hist.shape[-1])
    monkeypatch.setattr(histograms, "_CHUNK", 7)
    for alpha in (1.0, 2.5, 8.0):
        h = client.get("/volumes/tissues/histogram", params={"alpha": alpha}).json()
        counts = np.asarray(h["counts"])
        np.testing.assert_array_equal(counts, hist.sum(axis=0))
        assert N**3 <= counts.sum() <= (1 + 2 / B) ** 3 * N**3
        dist = hist[hist.sum(axis=1) > 0] / hist[hist.sum(axis=1) > 0].sum(axis=1, keepdims=True)
        want = (dist**alpha).sum(axis=0) ** (1 / alpha)
        want *= counts.sum() / want.sum()
        np.testing.assert_allclose(h["alpha_counts"], want, rtol=1e-9, atol=1e-9 * want.max())


def test_a_store_ingested_again_is_not_answered_from_the_cache(client, root):
    """The route keeps each store's answer; a store replaced under the same id (ingest --overwrite) is read anew."""
    make = lambda v: lodcast.ingest(np.full((16, 16, 16), v, np.float32), root / "again", block_size=B,  # noqa: E731
                                    overwrite=True)
    make(100.0)
    first = client.get("/volumes/again/histogram").json()
    assert client.get("/volumes/again/histogram").json() == first
    make(300.0)
    second = client.get("/volumes/again/histogram").json()
    assert first["value_range"] == [100.0, 100.0] and second["value_range"] == [300.0, 300.0]


def test_bad_requests_name_the_field(client):
    r = client.get("/volumes/tissues/histogram", params={"alpha": 0.5})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "alpha"]
    assert client.get("/volumes/tissues/histogram", params={"alpha": "nan"}).status_code == 422
    r = client.get("/volumes/none/histogram")
    assert r.status_code == 404 and "none" in r.json()["detail"]
    assert client.get("/volumes/tissues/histogram", headers={"Authorization": ""}).status_code == 401
    schema = client.get("/openapi.json").json()
    route = schema["paths"]["/volumes/{volume_id}/histogram"]["get"]
    assert "Histogram" in str(route["responses"]["200"]) and {p["name"] for p in route["parameters"]} >= {"alpha"}


def test_the_shell_is_open_and_names_no_volume(client):
    """With a token set, the page, its files and the volume list's page load without it (they carry no volume
    data); what they fetch does not."""
    bare = {"Authorization": ""}
    for url in ("/", "/volumes/tissues/view", "/viewer/viewer.js", "/viewer/api.js", "/viewer/viewer.css"):
        r = client.get(url, headers=bare)
        assert r.status_code == 200, url
        assert "tissues" not in r.text, url
    assert client.get("/volumes/tissues/view", headers=bare).headers["content-type"].startswith("text/html")
    assert "javascript" in client.get("/viewer/viewer.js", headers=bare).headers["content-type"]
    assert client.get("/volumes", headers=bare).status_code == 401
    assert client.get("/volumes/-bad/view", headers=bare).status_code == 400
    assert client.get("/viewer/nothing.js", headers=bare).status_code == 404


def test_the_static_files_are_package_data():
    """Every file the viewer serves is matched by the package-data globs, so that `pip install .` ships it."""
    cfg = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    assert cfg["tool"]["setuptools"]["package-dir"]["lodcast.service.static"] == "service/static"
    globs = cfg["tool"]["setuptools"]["package-data"]["lodcast.service.static"]
    files = [p.relative_to(STATIC).as_posix() for p in STATIC.rglob("*") if p.is_file()]
    assert {"index.html", "viewer.html", "viewer.js"} <= set(files)
    assert all(any(fnmatch.fnmatch(f, g) for g in globs) for f in files), (files, globs)
