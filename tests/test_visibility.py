"""View-dependent visibility of the blocks (renderer/lod/visibility.py) and the selection it weighs: what the camera
sees through a coarse level, against a float64 host cast and analytic cases; occluded blocks stay coarse and the
budget goes to what the picture shows."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

import lodcast
from lodcast.renderer.data.volume import as_volume
from lodcast.renderer.frame.prepare import resolved
from lodcast.renderer.image.delta_e import delta_e_stats
from lodcast.renderer.lod import visibility
from lodcast.renderer.lod.selection import select_lod
from lodcast.renderer.scene import camera as cam
from lodcast.renderer.scene.camera import geometry
from lodcast.renderer.scene.scene import Scene
from lodcast.renderer.scene.transfer_function import evaluate, unit_distance

B = 16
WALL = {"points": [{"value": 0.4, "color": [1, 1, 1], "opacity": 0.0}, {"value": 0.6, "color": [1, 1, 1], "opacity": 1.0}]}


def _ortho(shape, f, height=None):
    """An orthographic camera looking along world direction f at the volume's centre, its view covering it."""
    c = (np.array(shape[::-1], float) - 1) / 2
    f = np.asarray(f, float) / np.linalg.norm(f)
    up = [0.0, 0.0, 1.0] if abs(f[2]) < 0.9 else [0.0, 1.0, 0.0]
    return {"eye": (c - 500 * f).tolist(), "target": c.tolist(), "up": up, "projection": "orthographic",
            "view_height": height or 1.5 * max(shape)}


def _host_visibility(eng, store, scene, entry=True):
    """The float64 host mirror of visibility.cl: the same rays (camera.rays_at at the cast's pixel centres), steps
    and coarse level, trilinear by scipy, the TF by transfer_function.evaluate; with `entry`, transmittance 1 where
    the image's own rays enter the box (lc_visibility_entry)."""
    vol = as_volume(store)
    sc = resolved(eng, Scene.parse(scene), vol)
    box, fr, kbox, _ = geometry(vol, sc)
    k = visibility.visibility_level(vol)
    coarse = store.read_region(k).astype(np.float64)
    n = visibility.cast_rays(vol.grid, sc.width, sc.height)
    w, h = (n, max(1, round(n * sc.height / sc.width))) if sc.width >= sc.height else (max(1, round(n * sc.width / sc.height)), n)
    y, x = np.mgrid[:h, :w] + 0.5
    o, d = cam.rays_at(fr, x, y, w, h)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    t0, t1 = cam.ray_box(o, d, *kbox)
    sp, org = np.array(vol.spacing[::-1], float), np.array(vol.origin[::-1], float)
    dt = 2.0**k * min(vol.spacing)
    unit = unit_distance(sc.tf, vol.spacing)
    G = np.array(vol.grid)
    vis = np.zeros(G, np.float64)
    for r in np.flatnonzero(t1 > t0):
        m = np.arange(int(np.ceil((t1[r] - t0[r]) / dt)))
        q = ((o[r] + d[r] * (t0[r] + (m[:, None] + 0.5) * dt)) - org) / sp  # voxel xyz
        qk = (np.clip(q, 0, np.array(vol.shape[::-1]) - 1) + 0.5) / 2**k - 0.5
        v = map_coordinates(coarse, qk[:, ::-1].T, order=1, mode="nearest")
        a = evaluate(sc.tf, v)[1]
        alpha = 1 - (1 - np.minimum(a, 1.0)) ** (dt / unit)
        T = np.concatenate([[1.0], np.cumprod(1 - alpha)])[:-1]
        T_back = np.concatenate([[1.0], T[:-1]])
        b = np.clip(((q[:, ::-1] + 0.5) // vol.block_size).astype(int), 0, G - 1)
        for (bz, by, bx), tb in zip(b, T_back):
            vis[bz, by, bx] = max(vis[bz, by, bx], tb)
    if entry:
        vis[_entry_blocks(vol, sc, fr, kbox)] = 1.0
    return vis


def _entry_blocks(vol, sc, fr, kbox):
    """Where the image's own rays enter the box (float64): the blocks of those points, a hundredth of the way in."""
    y, x = np.mgrid[:sc.height, :sc.width] + 0.5
    o, d = cam.rays_at(fr, x, y, sc.width, sc.height)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    t0, t1 = cam.ray_box(o, d, *kbox)
    hit = t1 > np.maximum(t0, 0.0)
    t0 = np.maximum(t0, 0.0)
    sp, org = np.array(vol.spacing[::-1], float), np.array(vol.origin[::-1], float)
    q = (o[hit] + d[hit] * (t0[hit] + 0.01 * (t1[hit] - t0[hit]))[:, None] - org) / sp
    b = np.clip(((q[:, ::-1] + 0.5) // vol.block_size).astype(int), 0, np.array(vol.grid) - 1)
    return tuple(b.T)


@pytest.fixture(scope="module")
def wall(tmp_path_factory):
    """Three blocks of soft noise, an opaque wall filling block column 3 along x, three more blocks behind."""
    rng = np.random.default_rng(5)
    v = (0.3 * rng.random((B, B, 7 * B))).astype(np.float32)
    v[:, :, 3 * B:4 * B] = 1.0
    return lodcast.ingest(v, tmp_path_factory.mktemp("vis") / "wall.zarr", block_size=B, progress=False)


def test_every_block_of_a_wide_grid_is_entered_by_some_ray(eng, tmp_path):
    """A grid of more blocks across than VIS_RAYS: a transparent volume is still seen whole (a cast of VIS_RAYS
    rays leaves every other block column without a ray, weighing nothing in the selection)."""
    st = lodcast.ingest(np.zeros((B, 128 * 4, 128 * 4), np.float32), tmp_path / "w.zarr", block_size=4,
                        progress=False)
    assert visibility.cast_rays(as_volume(st).grid, 512, 512) > 2 * visibility.VIS_RAYS
    vis = eng.visibility(st, {"tf": WALL, "width": 512, "height": 512, "camera": _ortho(st.shape, (0.05, 0.05, 1))})
    np.testing.assert_array_equal(vis, 1.0)


def test_a_transparent_volume_is_seen_whole(eng, tmp_path):
    st = lodcast.ingest(np.zeros((2 * B, 2 * B, 3 * B), np.float32), tmp_path / "z.zarr", block_size=B, progress=False)
    vis = eng.visibility(st, {"tf": WALL, "width": 64, "height": 64, "camera": _ortho(st.shape, (1, 0.3, 0.2))})
    np.testing.assert_array_equal(vis, 1.0)


@pytest.mark.parametrize("f, seen, hidden", [((1, 0, 0), [0, 1, 2, 3], [4, 5, 6]), ((-1, 0, 0), [6, 5, 4, 3], [2, 1, 0])])
def test_an_opaque_wall_hides_what_lies_behind_it(eng, wall, f, seen, hidden):
    """The wall's own block is seen (its face is what the picture shows), every block behind it is not."""
    vis = eng.visibility(wall, {"tf": WALL, "width": 48, "height": 48, "camera": _ortho(wall.shape, f)})
    assert vis.shape == (1, 1, 7)
    np.testing.assert_array_equal(vis[0, 0, seen], 1.0)
    np.testing.assert_array_equal(vis[0, 0, hidden], 0.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_visibility_matches_a_float64_host_cast(eng, tmp_path, seed):
    """Random smooth volumes, a translucent TF and a perspective view: the device's fixed-point float32 cast against
    the float64 mirror. A sample within rounding of a block face may fall in the other block, which moves that
    block's value by one step's attenuation at most (below 4% here); almost every block agrees to 1e-4."""
    rng = np.random.default_rng(seed)
    from scipy.ndimage import gaussian_filter

    v = gaussian_filter(rng.random((3 * B, 4 * B, 4 * B)), 3).astype(np.float32)
    v = (v - v.min()) / (v.max() - v.min())
    st = lodcast.ingest(v, tmp_path / "r.zarr", block_size=B, progress=False)
    tf = {"points": [{"value": 0.3, "color": [1, 1, 1], "opacity": 0.0}, {"value": 1.0, "color": [1, 1, 1], "opacity": 0.04}]}
    scene = {"tf": tf, "width": 80, "height": 60, "camera": {"azimuth": 40 + 70 * seed, "elevation": 25, "distance": 2.5}}
    got, ref = eng.visibility(st, scene), _host_visibility(eng, st, scene)
    assert 0.05 < ref[ref > 0].min() < 0.9  # the field attenuates: the test compares more than ones
    assert np.abs(got - ref).max() < 0.04
    assert np.mean(np.abs(got - ref) < 1e-4) > 0.9


def test_a_thin_last_layer_seen_at_a_grazing_angle_is_seen_where_the_image_enters_it(eng, tmp_path):
    """A volume whose last layer of blocks is 1 voxel thick (a CT's slices rarely fill the last block), seen from
    just above its top face: a ray of the cast crosses the layer along a path as long as the layer is thick over the
    sine of the angle, and its neighbour enters the face its spacing over that sine further on, so where the layer
    is thinner than the cast's ray spacing the cast leaves blocks between them unseen, and the selection put them
    (cut bone on a CT's top slice) at the coarsest level.
    Every block where a ray of the image enters the box is seen with transmittance 1, as a float64 host
    computation of the entry points gives them; elsewhere the cast's own figure stands."""
    v = np.full((3 * 4 + 1, 160, 160), 0.3, np.float32)  # a faint haze: the cast records every block it samples
    st = lodcast.ingest(v, tmp_path / "thin.zarr", block_size=4, progress=False)
    haze = {"points": [{"value": 0.0, "color": [1, 1, 1], "opacity": 0.0}, {"value": 1.0, "color": [1, 1, 1], "opacity": 0.002}]}
    scene = {"tf": haze, "width": 512, "height": 512, "camera": _ortho(st.shape, (1, 0.3, -0.1))}
    vol = as_volume(st)
    sc = resolved(eng, Scene.parse(scene), vol)
    _, fr, kbox, _ = geometry(vol, sc)
    entry = np.zeros(vol.grid, bool)
    entry[_entry_blocks(vol, sc, fr, kbox)] = True
    top = entry[-1]
    cast_only = _host_visibility(eng, st, scene, entry=False)
    assert top.sum() >= 100 and (cast_only[-1][top] == 0).sum() >= top.sum() // 4  # the cast alone misses many
    got = eng.visibility(st, scene)
    np.testing.assert_array_equal(got[entry], 1.0)
    np.testing.assert_allclose(got[~entry], cast_only[~entry], atol=0.04)


@pytest.mark.parametrize("f", [(1, 0.4, 0.3), (-1, 0.2, -0.5)])
def test_quiet_blocks_change_nothing(eng, tmp_path, monkeypatch, f):
    """Blocks whose neighbourhood the TF shows nothing of are passed without sampling (visibility.quiet_blocks): the
    cast's result is the one that samples every step, bit for bit. The wall starts two voxels inside its block
    column, so the block before it holds nothing visible, one-voxel border included, while the level-2 cast's
    samples near their shared face reach the wall's values: only its neighbours' ranges say so (oblique rays: along
    an axis the lattice of coarse steps may miss the face's few voxels). Through a level
    coarser than the block no block may be quiet."""
    v = (0.3 * np.random.default_rng(2).random((2 * B, 2 * B, 6 * B))).astype(np.float32)
    v[:, :, 3 * B + 1:3 * B + 6] = 1.0
    st = lodcast.ingest(v, tmp_path / "q.zarr", block_size=B, progress=False)
    veil = {"points": [{"value": 0.4, "color": [1, 1, 1], "opacity": 0.0},
                       {"value": 0.6, "color": [1, 1, 1], "opacity": 0.1}]}  # the blocks behind it stay seen
    scene = {"tf": veil, "width": 64, "height": 48, "camera": _ortho(st.shape, f)}
    vol = as_volume(st)
    monkeypatch.setattr(visibility, "VIS_VOXELS", int(np.prod(vol.level_shape(2))))  # a level 4 voxels wide
    assert visibility.visibility_level(vol) == 2
    from lodcast.renderer.scene.transfer_function import build_lut

    lut = build_lut(resolved(eng, Scene.parse(scene), vol).tf, vol.value_range)
    quiet = visibility.quiet_blocks(vol, lut, 2).reshape(vol.grid)
    assert quiet[..., :2].all() and not quiet[..., 2:5].any() and quiet[..., 5:].all()
    assert not visibility.quiet_blocks(vol, lut, 5).any()  # 2^5 > B: none
    got = eng.visibility(st, scene)
    assert ((got > 0.0) & (got < 1.0)).any()  # attenuated but seen: a missed sample would show
    monkeypatch.setattr(visibility, "quiet_blocks", lambda vol, lut, k: np.zeros(vol.n_blocks, np.uint8))
    np.testing.assert_array_equal(got, eng.visibility(st, scene))


def test_clip_planes_open_the_view(eng, wall):
    """A plane that keeps only x >= 4B removes the wall: the blocks behind it are seen."""
    scene = {"tf": WALL, "width": 48, "height": 48, "camera": _ortho(wall.shape, (1, 0, 0)),
             "clip": {"planes": [{"point": [4 * B - 0.5, 0, 0], "normal": [1, 0, 0]}]}}
    vis = eng.visibility(wall, scene)
    np.testing.assert_array_equal(vis[0, 0, 4:], 1.0)


def test_the_selection_spends_the_budget_on_what_the_camera_sees(eng, tmp_path):
    """Translucent detail in front of an opaque wall and behind it. Weighted by visibility the selection keeps the front at
    finer levels and lets the hidden part go coarse, so the picture is closer to full resolution at the same
    budget; the report says so, and lod_visibility: false gives the view-independent selection."""
    rng = np.random.default_rng(2)
    from scipy.ndimage import gaussian_filter

    v = gaussian_filter(rng.random((2 * B, 2 * B, 8 * B)), 1.5).astype(np.float32)
    v = (v - v.min()) / (v.max() - v.min())
    v[:, :, 4 * B:5 * B] = 2.0  # the wall: blocks 4, behind it 5-7
    st = lodcast.ingest(v, tmp_path / "w.zarr", block_size=B, progress=False)
    tf = {"points": [{"value": 0.45, "color": [1, 0.6, 0.3], "opacity": 0.0}, {"value": 0.7, "color": [0.3, 0.6, 1], "opacity": 0.05},
                     {"value": 1.5, "color": [1, 1, 1], "opacity": 0.05}, {"value": 2.0, "color": [1, 1, 1], "opacity": 1.0}]}
    scene = {"tf": tf, "width": 96, "height": 48, "format": "npy", "quality": {"reduction": 12},
             "camera": _ortho(st.shape, (1, 0, 0), height=2 * B + 4)}
    ref = eng.render(st, {**scene, "quality": "full", "sampling": {"step": 0.25}}).rgba
    on = eng.render(st, scene)
    off = eng.render(st, {**scene, "sampling": {"lod_visibility": False}})
    assert on.report["lod_visibility"] is True and off.report["lod_visibility"] is False
    lv_on = select_lod(st, [tf], {"reduction": 12}, visibility=eng.visibility(st, scene)).levels
    lv_off = select_lod(st, [tf], {"reduction": 12}).levels
    front, behind = (slice(None), slice(None), slice(0, 4)), (slice(None), slice(None), slice(5, 8))
    assert lv_on[behind].min() == st.layout.n_levels - 1  # hidden: the coarsest level
    assert lv_on[front].mean() < lv_off[front].mean()  # the front is finer
    e_on, e_off = delta_e_stats(on.rgba, ref)["mean"], delta_e_stats(off.rgba, ref)["mean"]
    assert e_on < 0.85 * e_off, (e_on, e_off)  # measured 3.0 against 3.9


def test_left_out_it_is_on_for_volumes_up_to_the_auto_size(eng, wall, monkeypatch):
    """sampling.lod_visibility null: on for volumes of at most visibility.AUTO_VOXELS, off above (where a new
    view's selection and atlas cost more than the picture); an explicit value wins; lossless never weighs the view."""
    scene = {"tf": WALL, "width": 32, "height": 32, "format": "npy", "quality": {"reduction": 8},
             "camera": _ortho(wall.shape, (1, 0, 0))}
    assert eng.render(wall, scene).report["lod_visibility"] is True
    assert eng.render(wall, {**scene, "quality": "lossless"}).report["lod_visibility"] is False
    monkeypatch.setattr(visibility, "AUTO_VOXELS", int(np.prod(wall.shape)) - 1)
    assert eng.render(wall, scene).report["lod_visibility"] is False
    assert eng.render(wall, {**scene, "sampling": {"lod_visibility": True}}).report["lod_visibility"] is True


def test_a_turntable_job_selects_once_unless_its_scene_says_otherwise(eng):
    """Every frame of a turntable job takes the selection by the TF alone (one selection for the animation, no level
    changing between frames), unless the job's scene sets lod_visibility."""
    from lodcast.service.jobs import parse_job, plan_frames

    base = {"kind": "turntable", "volume": "v", "frames": 4, "scene": {"tf": WALL, "quality": {"reduction": 8}}}
    frames = plan_frames(parse_job(base))
    assert len(frames) == 4 and all(s["sampling"]["lod_visibility"] is False for _, s in frames)
    asked = parse_job({**base, "scene": {**base["scene"], "sampling": {"lod_visibility": True, "step": 0.7}}})
    assert all(s["sampling"] == {"lod_visibility": True, "step": 0.7} for _, s in plan_frames(asked))
