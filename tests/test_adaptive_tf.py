"""Adaptive transfer functions (thesis §3.3.2): the α-histogram of eq. 3.4 against a float64 loop, the minor
coherent feature of fig. 3.6 found where the plain histogram hides it, and `"tf": "auto"` placed on a volume's
peaks, rendered exactly as its explicit control points, from Python and over HTTP."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

import lodcast
from lodcast.renderer.data.volume import as_volume
from lodcast.renderer.scene.adaptive_tf import alpha_histogram, tissue_peaks, volume_peaks
from lodcast.renderer.scene.presets import ADAPTIVE


@pytest.mark.parametrize("alpha", [1.0, 2.0, 4.0, 8.0])
def test_alpha_histogram_is_eq_3_4(alpha):
    rng = np.random.default_rng(int(alpha))
    hist = rng.integers(0, 50, (3, 4, 5, 32)).astype(np.uint32)
    hist[0, 0, 0] = 0  # an empty block is left out, not divided by zero
    ref = np.zeros(32)
    for h in hist.reshape(-1, 32).astype(np.float64):
        if h.sum():
            ref += (h / h.sum()) ** alpha
    np.testing.assert_allclose(alpha_histogram(hist, alpha), ref ** (1 / alpha), rtol=1e-12)


def _fig_3_6(n: int = 64, seed: int = 0) -> np.ndarray:
    """A dominant gamma-distributed background (mean 30, sd 10·√3) hiding a spatially coherent minor feature
    (a tube, Gaussian mean 100, sd 20), as in the thesis' figure 3.6."""
    rng = np.random.default_rng(seed)
    vol = rng.gamma(3.0, 10.0, (n, n, n))
    z, y, x = np.mgrid[:n, :n, :n]
    tube = (y - n / 2) ** 2 + (x - n / 2 - 12 * np.sin(z / 10)) ** 2 < 4.0**2
    vol[tube] = rng.normal(100, 20, int(tube.sum()))
    assert 0.005 < tube.mean() < 0.05
    return np.clip(vol, 0, 255).astype(np.float32)


def test_the_alpha_histogram_reveals_the_minor_coherent_feature(tmp_path):
    store = lodcast.ingest(_fig_3_6(), tmp_path / "fig36.zarr")
    edges = store.hist_edges
    centres = 0.5 * (edges[1:] + edges[:-1])
    near = np.abs(centres - 100) < 15
    ratios = [alpha_histogram(store.hist, a)[near].max() / alpha_histogram(store.hist, a).max() for a in (1, 2, 4, 8)]
    assert all(b > a for a, b in zip(ratios, ratios[1:])) and ratios[2] > 1.5 * ratios[0], ratios  # emphasised by α
    bg, tissue = tissue_peaks(store.hist, centres)
    # gamma(3, 10) peaks at 20; the tube's peak sits on the gamma's falling tail, which pulls it below 100
    assert abs(bg - 20) < 12 and 70 < tissue < 115, (bg, tissue)


def _phantom() -> np.ndarray:
    """CT-like: air at -1000 around a soft-tissue ellipsoid (40 HU) with a bone shell (700 HU)."""
    rng = np.random.default_rng(1)
    z, y, x = np.mgrid[:48, :48, :48] - 23.5
    r = np.sqrt((z / 20) ** 2 + (y / 18) ** 2 + (x / 16) ** 2)
    vol = np.where(r < 1.0, 40.0, -1000.0) + rng.normal(0, 8, r.shape)
    vol[(r > 0.55) & (r < 0.62)] = 700.0
    return vol.astype(np.float32)


def test_auto_is_placed_on_the_peaks_and_renders_as_its_control_points(tmp_path):
    store = lodcast.ingest(_phantom(), tmp_path / "ph.zarr")
    bg, tissue = volume_peaks(as_volume(store))
    assert abs(bg + 1000) < 30 and abs(tissue - 40) < 30, (bg, tissue)
    scene = {"width": 48, "height": 48, "tf": "auto", "shading": {}, "camera": {"azimuth": 20, "elevation": 10}}
    auto = lodcast.render(store, scene)
    tf = auto.scene["tf"]
    values = [p["value"] for p in tf["points"]]
    u = [(v - bg) / (tissue - bg) for v in values]
    np.testing.assert_allclose(u[:2], [p[0] for p in ADAPTIVE["auto"]["points"][:2]], atol=1e-4)
    explicit = lodcast.render(store, {**scene, "tf": tf})
    np.testing.assert_array_equal(auto.rgba, explicit.rgba)
    assert auto.rgba[..., 3].mean() > 0.1  # the ellipsoid's surface covers the middle of the picture
    # arrays have no stored histograms: computed from the voxels, the same peaks within a bin or two
    bg2, tissue2 = volume_peaks(as_volume(_phantom()))
    assert abs(bg2 - bg) < 30 and abs(tissue2 - tissue) < 30


def test_adaptive_presets_are_listed_and_render_over_http(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from fastapi.testclient import TestClient
    from lodcast.service.app import create_app
    from lodcast.service.settings import Settings

    lodcast.ingest(_phantom(), tmp_path / "ph")
    with TestClient(create_app(Settings(root=tmp_path, workers=0, token=None))) as client:
        listed = client.get("/presets").json()
        assert listed["auto"]["template"] == "auto" and "ct-bone" in listed and "mr-soft" in listed
        r = client.post("/volumes/ph/render", json={"width": 32, "height": 32, "tf": "mr-soft", "format": "npy"})
        assert r.status_code == 200, r.text
        bad = client.post("/volumes/ph/render", json={"width": 32, "height": 32, "tf": "mr-nope"})
        assert bad.status_code == 422 and "mr-nope" in bad.text and "auto" in bad.text
