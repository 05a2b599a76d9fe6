"""The ray caster's machinery: build options per scene, empty-space skipping and early termination (what they
skip, that they change nothing beyond their bound), jitter, MIP, background, NaN, device limits, addressing, the
report. Numerical accuracy against the float64 reference lives in test_kernel_numerics.py."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from lodcast.opencl import DeviceError, kernel_source
from lodcast.renderer.data.sampler import upload_level0, voxel_offset
from lodcast.renderer.data.volume import VolumeView, block_minmax_border
from lodcast.renderer.frame.render import render
from lodcast.renderer.kernel.config import KernelConfig
from lodcast.renderer.scene.scene import TransferFunction
from lodcast.renderer.scene.transfer_function import evaluate

REPORT_KEYS = {"wall_ms", "kernel_ms", "bricks_read", "bricks_cached", "bricks_skipped", "reduction",
               "predicted_delta_e", "samples", "build_options"}


def blob_volume(shape=(40, 48, 64)) -> np.ndarray:
    """A Gaussian blob in one corner of a zero volume: most 8³ blocks are empty."""
    zz, yy, xx = np.mgrid[: shape[0], : shape[1], : shape[2]].astype(np.float32)
    return np.exp(-(((xx - 45) / 6) ** 2 + ((yy - 30) / 5) ** 2 + ((zz - 25) / 4) ** 2)).astype(np.float32)


TF_SPARSE = {"points": [{"value": 0.2, "color": [0.2, 0.4, 1.0], "opacity": 0.0},
                        {"value": 1.0, "color": [1.0, 0.8, 0.2], "opacity": 0.6}]}
CAM = {"azimuth": 30, "elevation": 20, "distance": 2.5, "fov": 30}


def scene(**kw) -> dict:
    base = {"camera": CAM, "width": 40, "height": 32, "tf": TF_SPARSE, "format": "npy"}
    sampling = kw.pop("sampling", {})
    base.update(kw)
    base["sampling"] = {"step": 0.5, **sampling}
    return base


@pytest.fixture(scope="module")
def blob() -> np.ndarray:
    return blob_volume()


def test_report_has_the_contract_keys(blob):
    r = render(blob, scene())
    assert REPORT_KEYS <= set(r.report)
    assert r.rgba.shape == (32, 40, 4) and r.rgba.dtype == np.float32
    assert r.report["reduction"] == 1.0 and r.report["predicted_delta_e"] == 0.0
    assert r.report["samples"] > 0 and r.report["kernel_ms"] > 0
    assert r.rgba[..., 3].max() > 0.1


def test_build_options_follow_the_scene():
    assert KernelConfig().build_options() == ("-DLC_SAMPLER_FULL", "-DLC_ESS", "-DLC_LEAP")
    # leaping needs a skip that only the cells decide: not MIP's, a second TF's or a pass's
    for kw in ({"mode": "mip"}, {"tf2": True}, {"passes": True}, {"ess": False}):
        assert "-DLC_LEAP" not in KernelConfig(**kw).build_options(), kw
    opts = KernelConfig(mode="mip", ess=False, precise=True).build_options()
    assert set(opts) == {"-DLC_SAMPLER_FULL", "-DLC_MODE_MIP"}  # compensated sums belong to compositing
    assert "-DLC_PRECISE" in KernelConfig(precise=True).build_options()
    with pytest.raises(ValueError):
        KernelConfig(sampler="atlas")


def test_render_reports_the_options_it_built_with():
    vol = np.zeros((4, 4, 40), np.float32)
    vol[..., :20] = 1.0  # two 32³ blocks along x; the second one is empty under TF_SPARSE
    cases = [
        ({}, {"-DLC_SAMPLER_FULL", "-DLC_ESS", "-DLC_LEAP"}),
        ({"mode": "mip"}, {"-DLC_SAMPLER_FULL", "-DLC_ESS", "-DLC_MODE_MIP"}),
        # the projection, jitter and the background are parameters of one program, not options
        ({"camera": {"eye": [-9, 1.5, 1.5], "target": [0, 1.5, 1.5], "projection": "orthographic", "view_height": 3}},
         {"-DLC_SAMPLER_FULL", "-DLC_ESS", "-DLC_LEAP"}),
        ({"sampling": {"jitter": True, "empty_space_skipping": False}}, {"-DLC_SAMPLER_FULL"}),
        ({"background": [0, 0, 0, 1]}, {"-DLC_SAMPLER_FULL", "-DLC_ESS", "-DLC_LEAP"}),
        ({"sampling": {"step": 0.001}}, {"-DLC_SAMPLER_FULL", "-DLC_ESS", "-DLC_LEAP", "-DLC_PRECISE"}),
    ]
    for kw, want in cases:
        r = render(vol, scene(width=4, height=4, **kw))
        assert set(r.report["build_options"]) == want, kw
    # nothing to skip: the block walk is compiled out
    full = render(np.ones((4, 4, 4), np.float32), scene(width=4, height=4))
    assert full.report["build_options"] == ["-DLC_SAMPLER_FULL"] and full.report["bricks_skipped"] == 0


@pytest.mark.parametrize("seed", range(12))
def test_block_border_ranges_of_an_array_equal_a_block_by_block_scan(seed):
    """What empty-space skipping decides from, for arrays rendered without a store: random shapes (ragged last
    blocks, 1-voxel axes), float with NaN (some blocks all NaN) and integer types, against a loop over blocks."""
    rng = np.random.default_rng(seed)
    B = int(rng.choice([2, 4, 8]))
    shape = tuple(int(rng.integers(1, 3 * B + 2)) for _ in range(3))
    if seed % 3 == 2:
        a = rng.integers(-500, 500, shape).astype(np.int16)
    else:
        a = rng.normal(0, 1, shape).astype(np.float32)
        a[rng.random(shape) < 0.3] = np.nan
        if seed % 3 == 1:
            a[: min(shape[0], B + 2)] = np.nan  # whole blocks and their borders without a finite value
    mn, mx = block_minmax_border(a, B)
    grid = tuple(-(-s // B) for s in shape)
    assert mn.shape == mx.shape == grid and mn.dtype == np.float64
    v = a.astype(np.float64)
    for b in np.ndindex(grid):
        win = v[tuple(slice(max(0, i * B - 1), (i + 1) * B + 1) for i in b)]
        if np.isnan(win).all():
            assert np.isnan(mn[b]) and np.isnan(mx[b]), b
        else:
            assert (mn[b], mx[b]) == (np.nanmin(win), np.nanmax(win)), b


def test_empty_space_skipping_skips_blocks_and_changes_nothing(blob):
    from lodcast.renderer.data.volume import _from_array  # 8³ blocks instead of 32³: many of them

    v = _from_array(blob, block_size=8)
    on = render(v, scene())
    off = render(v, scene(sampling={"empty_space_skipping": False}))
    assert on.report["bricks_skipped"] > v.n_blocks // 2  # the blob fills a corner
    assert off.report["bricks_skipped"] == 0
    assert on.report["samples"] < 0.6 * off.report["samples"]
    # every skipped sample would have contributed exactly zero: identical images
    assert np.array_equal(on.rgba, off.rgba)


def test_skipping_respects_a_tf_that_is_zero_at_both_ends_of_a_block_range():
    ramp = np.broadcast_to(np.linspace(0, 10, 32, dtype=np.float32)[None, None, :], (16, 16, 32)).copy()
    peak = {"points": [{"value": 4, "opacity": 0}, {"value": 5, "opacity": 0.9}, {"value": 6, "opacity": 0}]}
    from lodcast.renderer.data.volume import _from_array

    v = _from_array(ramp, block_size=8)
    on = render(v, scene(tf=peak, width=16, height=16))
    off = render(v, scene(tf=peak, width=16, height=16, sampling={"empty_space_skipping": False}))
    assert on.rgba[..., 3].max() > 0.2
    assert np.array_equal(on.rgba, off.rgba)
    assert 0 < on.report["bricks_skipped"] < v.n_blocks


def test_early_termination_stops_rays_within_its_bound():
    vol = np.full((24, 24, 24), 1.0, np.float32)
    tf = {"points": [{"value": 0, "color": [1, 0.5, 0.25], "opacity": 0.5}, {"value": 2, "color": [0.2, 1, 0.5], "opacity": 0.5}]}
    cam = {"eye": [-40, 11.5, 11.5], "target": [11.5, 11.5, 11.5], "projection": "orthographic", "view_height": 20}
    et = render(vol, scene(tf=tf, camera=cam, width=8, height=8, sampling={"early_termination": 0.99}))
    full = render(vol, scene(tf=tf, camera=cam, width=8, height=8, sampling={"early_termination": 1.0}))
    assert et.report["samples"] < 0.5 * full.report["samples"]
    assert (et.rgba[..., 3] >= 0.99).all()
    # what is left out is at most the transmittance remaining at termination
    assert np.abs(et.rgba - full.rgba).max() <= 1 - 0.99 + 1e-6


def test_jitter_is_reproducible_by_seed(blob):
    a = render(blob, scene(sampling={"jitter": True, "seed": 7, "step": 2.0}))
    b = render(blob, scene(sampling={"jitter": True, "seed": 7, "step": 2.0}))
    c = render(blob, scene(sampling={"jitter": True, "seed": 8, "step": 2.0}))
    plain = render(blob, scene(sampling={"step": 2.0}))
    assert np.array_equal(a.rgba, b.rgba)
    assert not np.array_equal(a.rgba, c.rgba)
    assert not np.array_equal(a.rgba, plain.rgba)
    # jitter trades banding for noise: on average it agrees with the unjittered image
    assert abs(float(a.rgba[..., 3].mean() - plain.rgba[..., 3].mean())) < 0.01


def test_mip_takes_the_tf_at_the_largest_sample():
    z, y = np.mgrid[:16, :16].astype(np.float32)
    vol = np.repeat(((z + y) / 30.0)[:, :, None], 8, axis=2)  # constant along x: the ray's max is the value there
    vol[:, :, 3] -= 0.5  # lower inside: must not matter
    tf = {"points": [{"value": 0, "color": [0, 0, 1], "opacity": 0.1}, {"value": 1, "color": [1, 0, 0], "opacity": 0.9}]}
    cam = {"eye": [-30, 7.5, 7.5], "target": [3.5, 7.5, 7.5], "projection": "orthographic", "view_height": 16}
    for ess in (True, False):
        r = render(vol, scene(tf=tf, camera=cam, width=16, height=16, mode="mip", sampling={"empty_space_skipping": ess}))
        # pixel (i, j) looks along +x at world y = j - 0.25 .. (right = -y for a camera looking along +x), z = 15 - i
        zc = 15.0 - np.arange(16)[:, None]
        yc = 15.0 - np.arange(16)[None, :]
        rgb, a = evaluate(TransferFunction.model_validate(tf), (zc + yc) / 30.0)
        assert np.allclose(r.rgba[..., 3], a, atol=1e-4)
        assert np.allclose(r.rgba[..., :3], rgb * a[..., None], atol=1e-4)


def test_background_is_composited_under_the_integral(blob):
    bg = (0.2, 0.4, 0.6, 0.5)
    plain = render(blob, scene())
    withbg = render(blob, scene(background=list(bg)))
    A = plain.rgba[..., 3:4]
    want_rgb = plain.rgba[..., :3] + (1 - A) * np.array(bg[:3]) * bg[3]
    want_a = A + (1 - A) * bg[3]
    assert np.allclose(withbg.rgba[..., :3], want_rgb, atol=1e-6)
    assert np.allclose(withbg.rgba[..., 3:], want_a, atol=1e-6)


def test_nan_voxels_are_transparent(blob):
    v = blob.copy()
    v[20:30, 25:35, 40:50] = np.nan
    r = render(v, scene())
    assert np.isfinite(r.rgba).all()
    allnan = render(np.full((8, 8, 8), np.nan, np.float32), scene(width=8, height=8))
    assert np.array_equal(allnan.rgba, np.zeros_like(allnan.rgba))
    assert allnan.report["bricks_skipped"] == 1


def test_level0_larger_than_one_device_allocation_is_refused(eng):
    """Sized from the device: one z-slab of blocks more than CL_DEVICE_MAX_MEM_ALLOC_SIZE holds in float32 (16 GiB
    was not enough on an H200, whose largest allocation is 35 GiB)."""
    limit = eng.device.max_alloc_bytes
    nz = 32 * (limit // (2048 * 2048 * 4 * 32) + 1)
    huge = VolumeView(shape=(nz, 2048, 2048), spacing=(1, 1, 1), origin=(0, 0, 0), block_size=32,
                      value_range=(0, 1), min_border=np.zeros((nz // 32, 64, 64)), max_border=np.ones((nz // 32, 64, 64)),
                      key=None, _read0=lambda: pytest.fail("must not read a volume that cannot fit"))
    with pytest.raises(DeviceError, match="CL_DEVICE_MAX_MEM_ALLOC_SIZE"):
        upload_level0(eng, huge)


def test_voxel_addressing_is_64_bit():
    shape = (2048, 2048, 1024)  # 2^32 voxels
    z, y, x = np.array([2047, 1024, 3]), np.array([2047, 5, 1]), np.array([1023, 7, 2])
    got = voxel_offset(z, y, x, shape)
    want = [(int(a) * shape[1] + int(b)) * shape[2] + int(c) for a, b, c in zip(z, y, x)]
    assert got.dtype == np.uint64 and got.tolist() == want
    assert int(got[0]) == 2**32 - 1
    # the kernel computes offsets through the ulong macro only
    src = kernel_source("raycast.cl")
    assert re.search(r"#define LC_OFFSET\(x, y, z, nx, ny\) \(\(\(ulong\)\(z\) \* \(ulong\)\(ny\)", src)
    assert "ulong b = LC_OFFSET(" in src and "int idx" not in src


def test_step_too_small_for_the_volume_is_a_scene_error():
    from lodcast.renderer.scene.scene import SceneError

    with pytest.raises(SceneError, match=r"^sampling\.step"):
        render(np.zeros((4, 4, 4), np.float32), scene(width=2, height=2, sampling={"step": 1e-9}))


def test_store_render_reads_then_caches(tmp_path: Path, blob):
    import lodcast

    src = tmp_path / "blob.npy"
    np.save(src, blob)
    store = lodcast.ingest(src, tmp_path / "blob.zarr")
    r1 = render(tmp_path / "blob.zarr", scene())
    r2 = render(store, scene())
    assert r1.report["bricks_read"] == int(np.prod(store.grid)) and r1.report["bricks_cached"] == 0
    assert r2.report["bricks_read"] == 0 and r2.report["bricks_cached"] == int(np.prod(store.grid))
    direct = render(blob, scene())
    assert np.allclose(r1.rgba, direct.rgba, atol=1e-6)


@pytest.mark.parametrize("step", [0.3, 1.0, 2.0, 3.0, 10.0])
@pytest.mark.parametrize("a, unit", [(0.3, 1.0), (0.999999, 4.0)])
def test_last_shorter_segment_is_exact(step, a, unit):
    """13 voxels do not divide into steps of 2, 3 or 10: the ray's last segment is shorter and must take its own
    opacity (from the extinction, not the step's alpha, which rounds to 1 in float32 for a = 0.999999)."""
    vol = np.full((6, 9, 13), 3.0, np.float32)
    tf = {"points": [{"value": 0, "color": [0.2, 0.4, 0.6], "opacity": a}], "unit_distance": unit}
    cam = {"eye": [-20, 4, 2.5], "target": [6, 4, 2.5], "projection": "orthographic", "view_height": 3}
    r = render(vol, scene(tf=tf, camera=cam, width=2, height=2, sampling={"step": step, "early_termination": 1.0}))
    want = 1 - (1 - a) ** (13 / unit)
    assert np.abs(r.rgba[..., 3] - want).max() <= 1e-6
    assert np.allclose(r.rgba[..., :3], np.array([0.2, 0.4, 0.6]) * r.rgba[..., 3:], atol=1e-6)
