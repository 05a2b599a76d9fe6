"""The ecosystem opens a lodcast store properly (issue 46, item 5): napari through lodcast's own npe2 reader plugin,
as one multiscale image with its world scale, translation and contrast window, headless; and xarray through
`Store.to_xarray(level)`, with z/y/x coordinates in world units (xarray.open_zarr cannot read OME-Zarr
multiscales)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import lodcast
from lodcast.store.napari import napari_get_reader


@pytest.fixture(scope="module")
def ct(tmp_path_factory: pytest.TempPathFactory) -> lodcast.store.store.Store:
    rng = np.random.default_rng(7)
    z, y, x = np.mgrid[:40, :48, :56] - np.array([20, 24, 28])[:, None, None, None]
    r = np.sqrt(z**2 + y**2 + x**2)
    vol = np.where(r < 18, 40.0, -1000.0) + rng.normal(0, 5, r.shape)
    vol[r < 6] = 1100.0
    return lodcast.ingest(np.rint(vol).astype(np.int16), tmp_path_factory.mktemp("interop") / "ct.zarr",
                          spacing=(2.0, 0.5, 0.75), origin=(-30.0, 10.0, 5.5), progress=False)


def test_the_napari_reader_gives_one_multiscale_image(ct, tmp_path: Path):
    assert napari_get_reader(str(tmp_path)) is None  # not a store: other readers are asked
    reader = napari_get_reader(ct.location)
    assert reader is not None
    [(levels, kw, kind)] = reader(ct.location)
    assert kind == "image" and kw["multiscale"] and len(levels) == ct.n_levels
    assert levels[0].shape == ct.shape and np.array_equal(np.asarray(levels[1][...]), ct.read_level(1))
    assert kw["scale"] == [2.0, 0.5, 0.75] and kw["translate"] == [-30.0, 10.0, 5.5]
    assert kw["contrast_limits"] == [-160.0, 240.0]  # a CT: the soft-tissue window of its omero metadata


def test_napari_finds_the_plugin_and_builds_the_layer(ct):
    """Through napari's plugin engine, as `napari.Viewer().open(path, plugin="lodcast")` reads it (headless: no
    viewer, the layer built from the reader's data)."""
    npe2 = pytest.importorskip("npe2")
    layers = pytest.importorskip("napari.layers")
    pm = npe2.PluginManager.instance()
    pm.discover()
    assert pm.get_manifest("lodcast").name == "lodcast"  # (KeyError: reinstall lodcast, pip install -e ., for its entry point)
    [(data, kw, kind)] = npe2.read([ct.location], stack=False, plugin_name="lodcast")
    layer = getattr(layers, kind.capitalize())(data, **{k: v for k, v in kw.items() if k != "units"})
    assert layer.multiscale and len(layer.data) == ct.n_levels
    np.testing.assert_allclose(layer.scale, [2.0, 0.5, 0.75])
    np.testing.assert_allclose(layer.translate, [-30.0, 10.0, 5.5])
    assert tuple(layer.contrast_limits) == (-160.0, 240.0)
    # the world position of a voxel centre: index × scale + translate, as lodcast's own convention
    np.testing.assert_allclose(layer.data_to_world([3, 4, 5]), [-30.0 + 6.0, 10.0 + 2.0, 5.5 + 3.75])


def test_to_xarray_has_world_coordinates(ct):
    pytest.importorskip("xarray")
    a0, a1 = ct.to_xarray(), ct.to_xarray(1)
    assert a0.dims == ("z", "y", "x") and a0.shape == ct.shape and a0.attrs["units"] == ct.units
    np.testing.assert_allclose(a0.z.values[:3], [-30.0, -28.0, -26.0])
    # level 1: voxels twice as wide, the first centre half a level-0 voxel further on
    np.testing.assert_allclose(a1.x.values[:2], [5.5 + 0.375, 5.5 + 0.375 + 1.5])
    np.testing.assert_array_equal(np.asarray(a1.values), ct.read_level(1))
    # selection by world position gives the voxel at that centre
    z, y, x = -30.0 + 2.0 * 20, 10.0 + 0.5 * 24, 5.5 + 0.75 * 28
    assert int(a0.sel(z=z, y=y, x=x)) == int(ct.read_level(0)[20, 24, 28])
