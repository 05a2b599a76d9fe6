"""Space leaping (renderer/leap.py, LC_LEAP): the walk's distance map against a brute-force Chebyshev distance, and
images with leaps against the same images walked cell by cell, at full resolution, on the block walk of the atlas
and on the adaptive walk, over random volumes, views and steps."""
from __future__ import annotations

import numpy as np
import pytest

import lodcast
from lodcast.renderer import walk as R
from lodcast.renderer.atlas import NEAR_LEVEL0
from lodcast.renderer.leap import LEAP_MAX, child_leaps, coarsen_ranges, leap_radii, step_leaps, with_leaps


def _chebyshev(empty: np.ndarray, cap: int) -> np.ndarray:
    """Brute force: per empty cell the largest axis offset to the nearest non-empty cell, capped; 0 elsewhere."""
    full = np.argwhere(~empty)
    cells = np.argwhere(np.ones(empty.shape, bool))
    if len(full) == 0:
        d = np.full(len(cells), cap)
    else:
        d = np.array([np.abs(full - c).max(axis=1).min() for c in cells])
    return np.where(empty.ravel(), np.minimum(d, cap), 0).reshape(empty.shape)


@pytest.mark.parametrize("seed", range(8))
def test_radii_are_capped_chebyshev_distances_to_the_nearest_full_cell(seed):
    rng = np.random.default_rng(seed)
    shape = tuple(int(n) for n in rng.integers(1, 13, 3))
    empty = rng.random(shape) > rng.choice([0.01, 0.05, 0.3, 0.8])
    cap = int(rng.choice([1, 2, 3, LEAP_MAX]))
    got = leap_radii(empty, cap)
    assert got.dtype == np.uint8
    np.testing.assert_array_equal(got, _chebyshev(empty, cap))


def test_radii_of_grids_all_empty_and_all_full():
    np.testing.assert_array_equal(leap_radii(np.ones((3, 4, 5), bool)), np.full((3, 4, 5), LEAP_MAX))
    np.testing.assert_array_equal(leap_radii(np.zeros((3, 4, 5), bool)), np.zeros((3, 4, 5)))
    with pytest.raises(ValueError, match="3-D grid"):
        leap_radii(np.ones((4, 4), bool))
    with pytest.raises(ValueError, match="cap"):
        leap_radii(np.ones((2, 2, 2), bool), 0)


def test_with_leaps_keeps_full_cells_and_marks_empty_ones():
    info = np.zeros((5, 6, 7), np.float32)
    info[2, 3, 3] = 1.0
    out = with_leaps(info)
    assert out[2, 3, 3] == 1.0 and out.dtype == np.float32
    np.testing.assert_array_equal(-out[info == 0], _chebyshev(info == 0, LEAP_MAX)[info == 0])


@pytest.mark.parametrize("seed", range(4))
def test_step_leaps_cover_cubes_of_skipped_level_0_cells(seed):
    """r >= 2: every cell within r - 1 is a skipped level-0 cell (code -1); nothing else leaps."""
    rng = np.random.default_rng(seed)
    codes = rng.choice(np.array([-1, -2, -3, -(NEAR_LEVEL0 | 1) - 1, 0, 2], np.int8), size=(9, 10, 11),
                       p=[0.45, 0.3, 0.1, 0.05, 0.05, 0.05])
    codes[:4, :5, :6] = -1
    out = step_leaps(codes)
    assert out.dtype == np.float32 and (out >= 2).any() and set(np.unique(out)) <= set(range(LEAP_MAX + 1))
    for c in np.argwhere(out > 0):
        k = int(out[tuple(c)]) - 1
        assert k >= 1 and (codes[tuple(slice(max(0, a - k), a + k + 1) for a in c)] == -1).all(), (c, k)
    np.testing.assert_array_equal(out >= 2, _chebyshev(codes == -1, LEAP_MAX) >= 2)


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


@pytest.fixture(autouse=True)
def fresh_walks():
    """Full resolution keeps its walk info per volume and TF (walk._WALKS): each test computes its own."""
    R._WALKS.clear()
    yield
    R._WALKS.clear()


def _no_leaps(monkeypatch):
    monkeypatch.setattr(R, "with_leaps", lambda info: info)
    monkeypatch.setattr(R, "step_leaps", lambda steps: np.zeros(steps.shape, np.float32))


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("seed", range(3))
def test_leaps_change_no_image(stores, variant, seed, monkeypatch):
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
    wl, sl = R.with_leaps, R.step_leaps
    monkeypatch.setattr(R, "with_leaps", lambda info: used.append(wl(info)) or used[-1])
    monkeypatch.setattr(R, "step_leaps", lambda steps: used.append(sl(steps)) or used[-1])
    on = lodcast.render(st, scene)
    assert len(used) == 1 and (np.abs(used[0]) >= 2).any()
    _no_leaps(monkeypatch)
    R._WALKS.clear()
    off = lodcast.render(st, scene)
    assert on.rgba[..., 3].max() > 0.3
    assert np.abs(on.rgba - off.rgba).max() <= 1e-6
    if variant.startswith("full"):
        assert 0 <= off.report["samples"] - on.report["samples"] <= 0.002 * off.report["samples"] + 2
    else:
        assert on.report["samples"] == off.report["samples"]


@pytest.mark.parametrize("variant", ["full", "10:1 adaptive"])
def test_the_kernel_follows_the_map(stores, variant, monkeypatch):
    """A map that claims more empty space than there is makes rays leap over material: the kernel reads it."""
    scene = {"tf": TF, "width": 32, "height": 32, "format": "npy", "camera": {"azimuth": 30, "elevation": 20},
             **VARIANTS[variant]}
    right = lodcast.render(stores[0], scene)
    R._WALKS.clear()
    monkeypatch.setattr(R, "with_leaps", lambda info: np.where(info <= 0, -float(LEAP_MAX), info).astype(np.float32))
    monkeypatch.setattr(R, "step_leaps", lambda steps: np.where(steps == -1, float(LEAP_MAX), 0.0).astype(np.float32))
    wrong = lodcast.render(stores[0], scene)
    assert wrong.rgba[..., 3].sum() < 0.8 * right.rgba[..., 3].sum()


@pytest.mark.parametrize("seed", range(4))
def test_coarser_ranges_are_the_union_of_the_finer(seed):
    """8³ cells' border-inclusive ranges from 4³ cells' equal those computed from the voxels (NaN left out)."""
    from lodcast.renderer.volume import block_minmax_border

    rng = np.random.default_rng(seed)
    a = rng.normal(size=tuple(int(n) for n in rng.integers(3, 40, 3))).astype(np.float32)
    a[a > 1.5] = np.nan
    mn4, mx4 = block_minmax_border(a, 4)
    mn8, mx8 = block_minmax_border(a, 8)
    got = coarsen_ranges(mn4, mx4)
    assert np.array_equal(got[0], mn8, equal_nan=True) and np.array_equal(got[1], mx8, equal_nan=True)


@pytest.mark.parametrize("seed", range(6))
def test_child_leaps_stay_inside_empty_space(seed):
    """A child's radius from its parent's never claims a cube holding a non-empty child, and under an empty parent
    it is at least one."""
    rng = np.random.default_rng(seed)
    shape = tuple(int(n) for n in rng.integers(2, 15, 3))
    info = (rng.random(shape) < rng.choice([0.01, 0.05, 0.2])).astype(np.float32)
    pshape = tuple(-(-n // 2) for n in shape)
    parent = np.zeros(pshape, np.float32)
    np.maximum.at(parent, tuple(np.argwhere(info > 0).T // 2), 1.0)  # a parent sees what any child sees
    out = child_leaps(with_leaps(parent), info)
    np.testing.assert_array_equal(out[info > 0], info[info > 0])
    r = -out[info <= 0]
    assert (r >= 1).all()
    exact = _chebyshev(info <= 0, 64)
    assert (r <= exact[info <= 0]).all()
    assert (out[info <= 0] < 0).all()
