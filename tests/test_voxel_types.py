"""Integer voxels of up to 16 bits stay in their own type on the device (level 0 and the LOD atlas): half or a
quarter of float32's bytes, and the same image bit for bit, since the kernel converts them to float exactly."""
from __future__ import annotations

import numpy as np
import pytest

import lodcast
from lodcast.renderer.frame.render import render

SCENE = {"camera": {"azimuth": 35, "elevation": 20}, "width": 40, "height": 36, "format": "npy"}


@pytest.mark.parametrize("dtype,ctype", [(np.int16, "short"), (np.uint16, "ushort"), (np.uint8, "uchar"),
                                         (np.int8, "char")])
def test_integer_voxels_stay_narrow_and_render_as_float32(tmp_path, dtype, ctype):
    info = np.iinfo(dtype)
    rng = np.random.default_rng(11)
    z, y, x = np.mgrid[0:20, 0:24, 0:28].astype(np.float64)
    field = np.sin(x / 4) * np.cos(y / 5) + 0.6 * np.sin(z / 3) + 0.2 * rng.standard_normal(x.shape)
    lo, hi = max(info.min, -3000), min(info.max, 3000)
    vol = np.round(lo + (field - field.min()) / np.ptp(field) * (hi - lo)).astype(dtype)
    narrow = lodcast.ingest(vol, tmp_path / "i.zarr", block_size=8)
    wide = lodcast.ingest(vol.astype(np.float32), tmp_path / "f.zarr", block_size=8)
    span = float(hi) - float(lo)
    tf = {"points": [{"value": lo + 0.3 * span, "color": [0.9, 0.6, 0.4], "opacity": 0.0},
                     {"value": lo + 0.6 * span, "color": [1, 0.9, 0.8], "opacity": 0.3},
                     {"value": lo + 0.9 * span, "color": [1, 1, 1], "opacity": 0.8}]}
    scene = {**SCENE, "tf": tf}
    a, b = render(narrow, scene), render(wide, scene)
    assert f"-DLC_VOXEL={ctype}" in a.report["build_options"]
    assert not any(o.startswith("-DLC_VOXEL") for o in b.report["build_options"])
    assert a.report["device_bytes"] == vol.size * np.dtype(dtype).itemsize
    assert b.report["device_bytes"] == vol.size * 4
    assert a.rgba[..., 3].max() > 0.2 and np.array_equal(a.rgba, b.rgba)
    # the atlas: every visible block at level 0 through interblock sampling (trilinear there), same bits again
    levels = np.zeros(narrow.grid, np.int8)
    a, b = render(narrow, {**scene, "quality": "lossless"}, levels=levels), render(wide, {**scene, "quality": "lossless"},
                                                                                   levels=levels)
    assert "-DLC_SAMPLER_ATLAS" in a.report["build_options"] and f"-DLC_VOXEL={ctype}" in a.report["build_options"]
    assert a.report["device_bytes"] * 4 == b.report["device_bytes"] * np.dtype(dtype).itemsize
    assert np.array_equal(a.rgba, b.rgba)
