"""Space leaping (renderer/walk/leap.py, LC_LEAP): the walk's octant distance maps against a brute-force search of the
forward cubes, and images with leaps against the same images walked cell by cell, at full resolution, on the block
walk of the atlas and on the adaptive walk, over random volumes, views and steps."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

import lodcast
from lodcast.renderer.data.atlas import NEAR_LEVEL0
from lodcast.renderer.walk import info as R
from lodcast.renderer.walk.leap import (
    LEAP_MAX,
    NO_PLANE,
    OCTANTS,
    Leaps,
    cell_leaps,
    coarsen_ranges,
    octant_radii,
    step_leaps,
)


def _forward_cube(empty: np.ndarray, c, o: int, cap: int) -> int:
    """Brute force: the largest r <= cap whose cube of r cells from c forward in octant o's directions holds no
    non-empty cell of the grid (cells past it count as empty); 0 if c is not empty."""
    sign = [1 if o >> bit & 1 else -1 for bit in (2, 1, 0)]  # (z, y, x)
    r = 0
    while r < cap:
        for d in itertools.product(range(r + 1), repeat=3):
            if max(d) < r:
                continue  # (the cube of edge r was checked before)
            p = tuple(int(c[i]) + sign[i] * d[i] for i in range(3))
            if all(0 <= p[i] < empty.shape[i] for i in range(3)) and not empty[p]:
                return r
        r += 1
    return r


@pytest.mark.parametrize("seed", range(8))
def test_octant_radii_are_the_largest_empty_forward_cubes(eng, seed):
    rng = np.random.default_rng(seed)
    shape = tuple(int(n) for n in rng.integers(1, 11, 3))
    empty = rng.random(shape) > rng.choice([0.01, 0.05, 0.3, 0.8])
    cap = int(rng.choice([1, 2, 3, LEAP_MAX]))
    got = octant_radii(empty, cap)
    assert got.dtype == np.uint8 and got.shape == (OCTANTS, *shape)
    for o in range(OCTANTS):
        cells = np.argwhere(np.ones(shape, bool))
        want = np.array([_forward_cube(empty, c, o, cap) for c in cells]).reshape(shape)
        np.testing.assert_array_equal(got[o], want, err_msg=f"octant {o}")


@pytest.mark.parametrize("seed", range(3))
def test_octant_radii_across_words_of_cells(eng, seed):
    """Rows longer than a word of cells (64 along x, the map's bits): the radii at cells beside the words' bounds
    and at random ones are the brute force's, for every octant, with empty runs that cross the bounds."""
    rng = np.random.default_rng(seed)
    shape = (int(rng.integers(2, 9)), int(rng.integers(2, 9)), int(rng.choice([65, 128, 150, 193])))
    empty = rng.random(shape) > rng.choice([0.02, 0.1, 0.4])
    empty[:, :, 50:80] = True  # a run across the first bound
    if shape[2] >= 135:  # and across the second, with a few cells in the way
        empty[:, :, 120:135] = rng.random((shape[0], shape[1], 15)) > 0.03
    got = octant_radii(empty)
    xs = [x for x in (0, 62, 63, 64, 65, 126, 127, 128, 129, shape[2] - 1) if x < shape[2]]
    cells = [(int(rng.integers(shape[0])), int(rng.integers(shape[1])), x) for x in xs for _ in range(3)]
    cells += [tuple(int(rng.integers(n)) for n in shape) for _ in range(20)]
    for o in range(OCTANTS):
        for c in cells:
            assert got[o][c] == _forward_cube(empty, c, o, LEAP_MAX), (o, c)


def test_octant_radii_look_only_ahead(eng):
    """A wall behind the ray does not hold it back: beside a full plane every octant facing away from it leaps as
    far as the cap allows, those facing it only up to the wall."""
    empty = np.ones((20, 3, 3), bool)
    empty[4] = False
    r = octant_radii(empty)
    away, towards = r[4:].reshape(2, 2, *r.shape[1:])[1], r[:4].reshape(2, 2, *r.shape[1:])[1]  # z forward / back
    assert (away[:, 5] == LEAP_MAX).all() and (towards[:, 5] == 1).all()
    assert (r[:4, 9] == 5).all()  # z backward from cell 9: cells 9..5 are empty, 4 is not
    assert (r[:, 4] == 0).all()


def test_radii_of_grids_all_empty_and_all_full(eng):
    np.testing.assert_array_equal(octant_radii(np.ones((3, 4, 5), bool)), np.full((8, 3, 4, 5), LEAP_MAX))
    np.testing.assert_array_equal(octant_radii(np.zeros((3, 4, 5), bool)), np.zeros((8, 3, 4, 5)))
    with pytest.raises(ValueError, match="3-D grid"):
        octant_radii(np.ones((4, 4), bool))
    with pytest.raises(ValueError, match="cap"):
        octant_radii(np.ones((2, 2, 2), bool), 0)


def test_cell_leaps_are_the_radii_of_the_empty_cells_computed_per_octant_on_demand(eng):
    info = np.zeros((5, 6, 7), np.float32)
    info[2, 3, 3] = 1.0
    info[0, 0, 0] = -np.inf  # (MIP's empty)
    lp = cell_leaps(info)
    want = octant_radii(info <= 0)
    assert not lp.planes
    buf, code = lp.for_octants((6, 3))
    assert buf.shape == (2, *info.shape) and sorted(lp.planes) == [3, 6]
    np.testing.assert_array_equal(buf, want[[3, 6]])
    assert lp.for_octants([3, 6])[0] is buf  # the same view's buffer again, not a new copy
    assert [code >> (4 * o) & 15 for o in range(OCTANTS)] == [NO_PLANE] * 3 + [0] + [NO_PLANE] * 2 + [1, NO_PLANE]
    buf, code = lp.for_octants([5])
    np.testing.assert_array_equal(buf[0], want[5])
    assert code >> 20 & 15 == 0 and all(code >> (4 * o) & 15 == NO_PLANE for o in range(OCTANTS) if o != 5)
    buf, code = lp.for_octants(range(OCTANTS))
    np.testing.assert_array_equal(buf, want)
    assert code == 0x76543210
    assert (want[:, 2, 3, 3] == 0).all() and (want[:, 0, 0, 0] > 0).all()
    with pytest.raises(ValueError, match="3-D grid"):
        Leaps.of(np.ones((4, 4), bool))


@pytest.mark.parametrize("seed", range(4))
def test_step_leaps_cover_cubes_of_skipped_level_0_cells(eng, seed):
    """Every cell of the forward cube a leap vouches for is a skipped level-0 cell (code -1); nothing else leaps."""
    rng = np.random.default_rng(seed)
    codes = rng.choice(np.array([-1, -2, -3, -(NEAR_LEVEL0 | 1) - 1, 0, 2], np.int8), size=(9, 10, 11),
                       p=[0.45, 0.3, 0.1, 0.05, 0.05, 0.05])
    codes[:4, :5, :6] = -1
    out, _ = step_leaps(codes).for_octants(range(OCTANTS))
    assert out.dtype == np.uint8 and (out >= 2).any()
    assert (out[:, codes != -1] == 0).all()
    for o, *c in np.argwhere(out >= 2)[::7]:
        k = int(out[(o, *c)])
        sign = [1 if o >> bit & 1 else -1 for bit in (2, 1, 0)]
        box = tuple(slice(a, a + k) if s > 0 else slice(max(0, a - k + 1), a + 1) for a, s in zip(c, sign))
        assert (codes[box] == -1).all(), (o, c, k)


# ------------------------------------------------------------------------------------------------ images
def _volume(seed: int) -> np.ndarray:
    """A few blobs and a thin plate in empty space: long empty runs and cells near the material."""
    rng = np.random.default_rng(seed)
    shape = (40, 56, 64)
    z, y, x = np.indices(shape, dtype=np.float32)
    v = np.zeros(shape, np.float32)
    for _ in range(4):
        c = rng.uniform([6, 8, 8], [34, 48, 56])
        r = rng.uniform(3, 7)
        v = np.maximum(v, np.clip(1.2 - np.sqrt(((z - c[0]) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2)) / r, 0, 1))
    v[:, int(rng.integers(10, 46)), 20:44] = 0.9
    return v


TF = {"points": [{"value": 0.2, "color": [1.0, 0.6, 0.3], "opacity": 0.0},
                 {"value": 0.6, "color": [0.9, 0.9, 1.0], "opacity": 0.4},
                 {"value": 1.0, "color": [1.0, 1.0, 1.0], "opacity": 0.9}]}
VARIANTS = {
    "full": {},
    "10:1 adaptive": {"quality": {"reduction": 10}},
    "lossless adaptive": {"quality": "lossless"},
    "4:1 block walk": {"quality": {"reduction": 4}, "sampling": {"adaptive_object": False,
                                                              "interpolation": "interblock"}},
    "full, jitter and a clip plane": {"sampling": {"jitter": True},
                                      "clip": {"planes": [{"point": [30, 28, 20], "normal": [1, 0.3, -0.2]}]}},
    "10:1 shaded, clipped": {"quality": {"reduction": 10}, "shading": {},
                             "clip": {"planes": [{"point": [30, 28, 20], "normal": [-1, 0.2, 0.4]}]}},
}


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    d = tmp_path_factory.mktemp("leap")
    return [lodcast.ingest(_volume(s), d / f"v{s}.zarr", block_size=8, progress=False) for s in range(2)]


def _fixed(empty: np.ndarray, r: int) -> Leaps:
    """Leaps of r cells from every cell of `empty` in every octant (0: none), whatever lies ahead."""
    plane = np.where(empty, r, 0).astype(np.uint8)
    return Leaps(np.asarray(empty, bool), {o: plane for o in range(OCTANTS)})


def _no_leaps(monkeypatch):
    monkeypatch.setattr(R, "cell_leaps", lambda info: _fixed(info <= 0, 0))
    monkeypatch.setattr(R, "step_leaps", lambda steps: _fixed(steps == -1, 0))


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("seed", range(3))
def test_leaps_change_no_image(eng, stores, variant, seed, monkeypatch):
    """With leaps the image is the cell-by-cell walk's, bit for bit up to float noise (1e-6), and so are the
    adaptive walk's sample counts; at full resolution only samples past the grid's last cell that rounding left
    to the march may go (each adds nothing). The maps used do leap (radii >= 2 were handed to the kernel)."""
    rng = np.random.default_rng(100 + seed)
    st = stores[seed % 2]
    scene = {"tf": TF, "width": 40, "height": 36, "format": "npy",
             "camera": {"azimuth": float(rng.uniform(0, 360)), "elevation": float(rng.uniform(-60, 60)),
                        "distance": float(rng.uniform(1.4, 2.5)),
                        "projection": str(rng.choice(["perspective", "orthographic"]))},
             **VARIANTS[variant]}
    scene["sampling"] = {**scene.get("sampling", {}), "step": float(rng.uniform(0.3, 1.3))}
    used = []
    wl, sl = R.cell_leaps, R.step_leaps
    monkeypatch.setattr(R, "cell_leaps", lambda info: used.append(wl(info)) or used[-1])
    monkeypatch.setattr(R, "step_leaps", lambda steps: used.append(sl(steps)) or used[-1])
    on = eng.render(st, scene)
    assert len(used) == 1 and 1 <= len(used[0].planes) <= 4
    assert any((plane >= 2).any() for plane in used[0].planes.values())
    _no_leaps(monkeypatch)
    eng.walks.clear()
    off = eng.render(st, scene)
    assert on.rgba[..., 3].max() > 0.3
    assert np.abs(on.rgba - off.rgba).max() <= 1e-6
    if variant.startswith("full"):
        assert 0 <= off.report["samples"] - on.report["samples"] <= 0.002 * off.report["samples"] + 2
    else:
        assert on.report["samples"] == off.report["samples"]


@pytest.mark.parametrize("variant", ["full", "10:1 adaptive"])
def test_the_kernel_follows_the_map(eng, stores, variant, monkeypatch):
    """A map that claims more empty space than there is makes rays leap over material: the kernel reads it."""
    scene = {"tf": TF, "width": 32, "height": 32, "format": "npy", "camera": {"azimuth": 30, "elevation": 20},
             **VARIANTS[variant]}
    right = eng.render(stores[0], scene)
    eng.walks.clear()
    monkeypatch.setattr(R, "cell_leaps", lambda info: _fixed(np.ones(info.shape, bool), LEAP_MAX))
    monkeypatch.setattr(R, "step_leaps", lambda steps: _fixed(steps == -1, LEAP_MAX))
    wrong = eng.render(stores[0], scene)
    assert wrong.rgba[..., 3].sum() < 0.8 * right.rgba[..., 3].sum()


@pytest.mark.parametrize("seed", range(4))
def test_coarser_ranges_are_the_union_of_the_finer(eng, seed):
    """8³ cells' border-inclusive ranges from 4³ cells' equal those computed from the voxels (NaN left out)."""
    from lodcast.renderer.data.volume import block_minmax_border

    rng = np.random.default_rng(seed)
    a = rng.normal(size=tuple(int(n) for n in rng.integers(3, 40, 3))).astype(np.float32)
    a[a > 1.5] = np.nan
    mn4, mx4 = block_minmax_border(a, 4)
    mn8, mx8 = block_minmax_border(a, 8)
    got = coarsen_ranges(mn4, mx4)
    assert np.array_equal(got[0], mn8, equal_nan=True) and np.array_equal(got[1], mx8, equal_nan=True)


@pytest.mark.parametrize("seed", range(12))
def test_ray_octants_hold_every_ray_of_the_image(eng, seed):
    """camera.ray_octants: the octant of every pixel's ray (and of rays through the image's corners) is among them,
    and a view of a field of view up to 90° needs at most four of the eight planes."""
    from lodcast.renderer.scene import camera as cam
    from lodcast.renderer.scene.scene import Scene

    rng = np.random.default_rng(seed)
    W, H = int(rng.integers(8, 64)), int(rng.integers(8, 64))
    c = {"azimuth": float(rng.choice([0, 90, 180, rng.uniform(0, 360)])),
         "elevation": float(rng.choice([0, 45, rng.uniform(-89, 89)])), "fov": float(rng.uniform(5, 90)),
         "projection": str(rng.choice(["perspective", "orthographic"]))}
    if c["projection"] == "orthographic":
        c["view_height"] = 40.0
    scene = Scene.parse({"camera": c, "width": W, "height": H, "tf": TF})
    fr = cam.frame(scene.camera, W, H, np.zeros(3), np.array([30.0, 20.0, 10.0]))
    octs = cam.ray_octants(fr)
    y, x = np.mgrid[0:H + 1:0.5, 0:W + 1:0.5]
    _, d = cam.rays_at(fr, x, y, W, H)
    d = d.astype(np.float32)
    got = set(((d[..., 0] > 0) | (d[..., 1] > 0) << 1 | (d[..., 2] > 0) << 2).ravel().tolist())
    assert got <= set(octs), (c, got, octs)
    assert 1 <= len(octs) <= 4
