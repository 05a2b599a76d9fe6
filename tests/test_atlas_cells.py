"""Empty-space skipping on the brick atlas walks half-block cells (issue 13 item 1: a fine grid for the atlas
too): each cell's bounds (atlas_cells.cl) hold every value and standard deviation the kernel's own sampler takes
in it, for random mixes of levels, nearest block and interblock; and renders with the cells are exactly the
block walk's images with fewer samples."""
from __future__ import annotations

import weakref

import numpy as np
import pyopencl as cl
import pytest

import lodcast
from lodcast.renderer.data import atlas as lod_atlas
from lodcast.renderer.data import atlas_cells, passes
from lodcast.renderer.data.volume import VolumeView, as_volume
from lodcast.renderer.frame.render import Renderer

BONE = {"points": [{"value": 300, "color": [1, 0.9, 0.8], "opacity": 0.0},
                   {"value": 900, "color": [1, 1, 1], "opacity": 0.7}]}


def _ribs(shape=(48, 64, 80)) -> np.ndarray:
    """Thin bright shells in noisy soft tissue, a NaN hole: coarse levels keep a wide distribution near the
    shells, most half-block cells see none of them."""
    z, y, x = np.mgrid[: shape[0], : shape[1], : shape[2]].astype(np.float64)
    r = np.sqrt((y - 32) ** 2 + (x - 40) ** 2)
    a = 50 + 5 * np.sin(z / 3.0) + np.random.default_rng(3).normal(0, 8, shape)
    for r0 in (9.0, 19.0, 29.0):
        a = np.where(np.abs(r - r0) < 1.0, 1000.0, a)
    a[2:6, 2:6, 2:6] = np.nan
    return a.astype(np.float32)


@pytest.fixture
def eng():
    """A renderer of the test's own: nothing kept from other tests."""
    r = Renderer()
    yield r
    r.close()


@pytest.fixture(scope="module")
def ribs(tmp_path_factory):
    return lodcast.ingest(_ribs(), tmp_path_factory.mktemp("cells") / "ribs.zarr")


def _probe(eng: Renderer, da: lod_atlas.DeviceAtlas, grid, B: int, interp: str, pts: np.ndarray) -> np.ndarray:
    ctx, queue = eng.device.context, eng.device.queue
    opts = ["-DLC_INTERP_II" if interp == "interblock" else "-DLC_INTERP_NB", "-DLC_DIST", *da.voxel]
    p4 = np.zeros((len(pts), 4), np.float32)
    p4[:, :3] = pts
    d_pts = cl.Buffer(ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=p4)
    out = np.zeros((len(pts), 2), np.float32)
    d_out = cl.Buffer(ctx, cl.mem_flags.WRITE_ONLY, out.nbytes)
    cl.Kernel(eng.device.program("atlas_probe.cl", opts).program, "lc_probe_atlas")(
        queue, (len(pts),), None, da.atlas, da.std, da.index, np.array([grid[2], grid[1], grid[0], B], np.int32),
        d_pts, d_out, np.int32(len(pts)))
    cl.enqueue_copy(queue, out, d_out)
    queue.finish()
    return out


@pytest.mark.parametrize("interp", ["interblock", "nearest_block"])
def test_the_cells_of_some_blocks_are_those_cells_of_the_whole_grid(eng, ribs, interp):
    """A pass of a render in several computes the cells of its own blocks only (the 8 GiB volume's lossless passes
    each made a whole grid's: 3 x 32 MB on the device and again on the host): the same values, bit for bit."""
    vol = as_volume(ribs)
    B, G = int(vol.block_size), vol.grid
    rng = np.random.default_rng(5)
    levels = rng.integers(-1, 5, size=G).astype(np.int8)
    da = lod_atlas.device_atlas(eng, vol, levels, with_std=True, keep=False)
    whole = atlas_cells.atlas_cells(eng, da, G, B, interp, vol.std_unit)
    for _ in range(6):
        a = [int(rng.integers(0, g)) for g in G]
        blocks = tuple(slice(s, int(rng.integers(s + 1, g + 1))) for s, g in zip(a, G))
        part = atlas_cells.atlas_cells(eng, da, G, B, interp, vol.std_unit, blocks)
        assert part.vmin.shape == tuple(2 * (b.stop - b.start) for b in blocks)
        for got, ref in ((part.vmin, whole.vmin), (part.vmax, whole.vmax), (part.std, whole.std)):
            np.testing.assert_array_equal(got, ref[part.at])


@pytest.mark.parametrize("interp", ["interblock", "nearest_block"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cell_bounds_hold_every_sample_of_the_field(eng, ribs, interp, seed):
    vol = as_volume(ribs)
    B, G = int(vol.block_size), vol.grid
    rng = np.random.default_rng(seed)
    levels = rng.integers(-1 if seed else 0, 5, size=G).astype(np.int8)  # seed 0: every block loaded
    da = lod_atlas.device_atlas(eng, vol, levels, with_std=True, keep=False)
    cells = atlas_cells.atlas_cells(eng, da, G, B, interp, vol.std_unit)
    assert cells.vmin.shape == tuple(2 * g for g in G)
    # random points, many of them within rounding of a cell face (where the walk may assign a sample either way)
    n = 200_000
    hi = np.array([G[2], G[1], G[0]]) * B - 0.5
    pts = rng.uniform(-0.5, hi, size=(n, 3))
    on_face = rng.random(n) < 0.3
    axis = rng.integers(0, 3, n)
    C = B / 2
    pts[on_face, axis[on_face]] = np.round((pts[on_face, axis[on_face]] + 0.5) / C) * C - 0.5 + rng.uniform(
        -1e-4, 1e-4, on_face.sum())
    pts = np.clip(pts, -0.5, hi - 1e-3)
    got = _probe(eng, da, G, B, interp, pts.astype(np.float32))
    h = np.clip(np.floor((pts.astype(np.float32) + 0.5) / C).astype(np.int64), 0, np.array([2 * G[2], 2 * G[1], 2 * G[0]]) - 1)
    cz, cy, cx = h[:, 2], h[:, 1], h[:, 0]
    lo, up, sd = cells.vmin[cz, cy, cx], cells.vmax[cz, cy, cx], cells.std[cz, cy, cx]
    v, s = got[:, 0], got[:, 1] * vol.std_unit
    finite = np.isfinite(v)
    assert finite.any() and (seed == 0 or (~finite).any())  # missing blocks are NaN
    assert np.all(np.isfinite(lo[finite])), "a cell that yields values has bounds"
    tol = 1e-5 * np.maximum(1.0, np.abs(v[finite]))
    assert np.all(v[finite] >= lo[finite] - tol) and np.all(v[finite] <= up[finite] + tol)
    assert np.all(s[finite] <= sd[finite] * (1 + 1e-5) + 1e-6)
    # not vacuous: many cells of blocks that hold a shell stay below the bone TF's first opaque value
    shell = np.repeat(np.repeat(np.repeat(vol.max_border > 300, 2, 0), 2, 1), 2, 2)
    assert np.mean(cells.vmax[shell] < 300) > 0.1


SCENES = {
    "interblock, adaptive, distribution": {"quality": {"reduction": 8}},
    "interblock, fixed steps": {"quality": {"reduction": 8}, "sampling": {"adaptive_object": False}},
    "nearest block, adaptive": {"quality": {"reduction": 8}, "sampling": {"interpolation": "nearest_block"}},
    "nearest block, mean": {"quality": {"reduction": 8},
                            "sampling": {"interpolation": "nearest_block", "classification": "mean"}},
    "lossless": {"quality": "lossless"},
    "mip": {"quality": {"reduction": 8}, "mode": "mip"},
    "shading, pre-integration": {"quality": {"reduction": 8}, "shading": {}, "sampling": {"preintegration": True}},
    "tf2": {"quality": {"reduction": 8},
            "tf2": {"points": [{"value": 950, "color": [1, 0.3, 0.2], "opacity": 0.0},
                               {"value": 1000, "color": [1, 0.3, 0.2], "opacity": 0.9}]}},
}


@pytest.mark.parametrize("name", list(SCENES))
def test_half_block_cells_change_nothing_but_the_samples(eng, ribs, monkeypatch, name):
    scene = {"tf": BONE, "width": 64, "height": 64, "camera": {"azimuth": 30, "elevation": 20}, **SCENES[name]}
    # the cells' skipping alone: the level-0 mask of coarse cells changes what a coarse level shows (tested below)
    monkeypatch.setattr(VolumeView, "has_cell_ranges", property(lambda self: False))
    fine = eng.render(ribs, scene)
    monkeypatch.setattr(passes, "_cells", lambda pr, da, *a: None)  # the walk over whole blocks, as before
    blocks = eng.render(ribs, scene)
    # interblock: a half-block cell knows its own interblock neighbourhood (lc_blk_cell), so samples that the block
    # walk sends through the blend sum with every other weight 0 take the own block's sample directly: equal up to
    # the rounding of w·v/w
    np.testing.assert_allclose(fine.rgba, blocks.rgba, rtol=0, atol=1e-6)
    assert fine.report["samples"] <= blocks.report["samples"]
    if "mode" not in SCENES[name]:  # composite: the thin shells leave many half-block cells of their blocks empty
        # (nearest block's adaptive walk keeps whole-block cells: it skips a block only when all its cells are
        # empty; tf2 sees a second band)
        bound = {"nearest block, adaptive": 1.0, "tf2": 0.95}.get(name, 0.9)
        assert fine.report["samples"] < bound * blocks.report["samples"], (fine.report["samples"],
                                                                            blocks.report["samples"])


def test_the_atlas_walk_is_kept_per_selection_and_visibility(eng, ribs, monkeypatch):
    """The atlas's walk info and the adaptive walk's steps and leaps are computed once per selection, TF zero
    pattern (distribution table included), mode and block info: a TF that only changes colours reuses them, a
    wider TF, another reduction or MIP computes them afresh, and every image equals one rendered with nothing
    kept."""
    from lodcast.renderer.walk import info as R

    cells, leaps = [], []
    orig_cells, orig_leaps = R.atlas_cell_info, R.step_leaps
    monkeypatch.setattr(R, "atlas_cell_info", lambda *a, **k: cells.append(1) or orig_cells(*a, **k))
    monkeypatch.setattr(R, "step_leaps", lambda *a, **k: leaps.append(1) or orig_leaps(*a, **k))
    base = {"width": 48, "height": 40, "camera": {"azimuth": 30, "elevation": 20}, "quality": {"reduction": 8},
            "sampling": {"lod_visibility": False}}  # (the selection must not follow the TF's colours either)
    recolour = {"points": [{"value": 300, "color": [0.2, 0.9, 0.8], "opacity": 0.0},
                           {"value": 900, "color": [1, 0.5, 1], "opacity": 0.7}]}
    wider = {"points": [{"value": 20, "color": [1, 0.9, 0.8], "opacity": 0.0},
                        {"value": 900, "color": [1, 1, 1], "opacity": 0.7}]}
    scenes = [{**base, "tf": BONE}, {**base, "tf": BONE}, {**base, "tf": recolour}, {**base, "tf": wider},
              {**base, "tf": BONE, "quality": {"reduction": 4}}, {**base, "tf": BONE},
              {**base, "tf": BONE, "mode": "mip"}]
    counts, images = [], []
    for sc in scenes:
        n0, m0 = len(cells), len(leaps)
        images.append(eng.render(ribs, sc).rgba)
        counts.append((len(cells) - n0, len(leaps) - m0))
    # MIP: its cells' maxima, no adaptive leaps (the adaptive walk leaps in composite renders only)
    assert counts == [(1, 1), (0, 0), (0, 0), (1, 1), (1, 1), (0, 0), (1, 0)], counts
    eng.walks.clear()
    eng.adaptive_walks.clear()
    for sc, img in zip(scenes, images):
        assert np.array_equal(eng.render(ribs, sc).rgba, img)


OCTANT_SCENES = {
    "nearest block, distribution": {},
    "interblock": {"sampling": {"interpolation": "interblock"}},
    "mean classification": {"sampling": {"classification": "mean"}},
    "jitter, shading": {"sampling": {"jitter": True}, "shading": {}},
    "lossless": {"quality": "lossless"},
}


@pytest.mark.parametrize("name", list(OCTANT_SCENES))
def test_octant_masks_change_nothing_but_the_samples(eng, ribs, monkeypatch, name):
    """The adaptive walk skips the samples of a sampled half-block cell that fall in octants (quarter-block cells)
    whose field bounds the TF shows nothing of (config.octants): the same image within float rounding (the
    kernels differ, and with them the compiler's contractions), fewer samples. A wrong bit order or a missed
    sample past a cell's face (a coarse cell's last step on the level-0 lattice) changes pixels by up to 1."""
    from lodcast.renderer.kernel import config

    scene = {"tf": BONE, "width": 64, "height": 64, "camera": {"azimuth": 30, "elevation": 20},
             "quality": {"reduction": 4}, **OCTANT_SCENES[name]}
    if name == "lossless":  # (at its default bounds lossless keeps every block of this phantom the TF shows at level 0)
        monkeypatch.setenv("LODCAST_LOSSLESS_ZETA", "500")
        eng = Renderer()
    with_octants = eng.render(ribs, scene)
    assert "-DLC_OCTANTS" in with_octants.report["build_options"]
    monkeypatch.setattr(config.KernelConfig, "octants", property(lambda self: False))
    without = eng.render(ribs, scene)
    assert "-DLC_OCTANTS" not in without.report["build_options"]
    np.testing.assert_allclose(with_octants.rgba, without.rgba, rtol=0, atol=1e-5)
    # (interblock's octants near a block face reach into the neighbours' bricks: wider bounds, fewer skipped)
    # (lossless, held to its 10:1 selection here, keeps more level-0 blocks, whose cells the octants do not split)
    bound = 0.97 if name == "interblock" else (0.95 if name == "lossless" else 0.9)
    assert with_octants.report["samples"] < bound * without.report["samples"], (with_octants.report["samples"],
                                                                                 without.report["samples"])


def test_no_octant_masks_beyond_fine_cells_octants(eng, ribs, monkeypatch):
    """The octants' bounds are kept for the whole grid (12 bytes each, on the host and the device): on a grid of
    more than sampler.FINE_CELLS octants (the 8 GiB volume's 64 million: 12.5 s a turntable frame, 5.3 GB of peak
    RSS) the walk takes every sample of its half-block cells, as full resolution walks 8³ cells there."""
    from lodcast.renderer.frame import plan

    scene = {"tf": BONE, "width": 48, "height": 40, "camera": {"azimuth": 30, "elevation": 20},
             "quality": {"reduction": 4}}
    vol = as_volume(ribs)
    assert "-DLC_OCTANTS" in eng.render(ribs, scene).report["build_options"]
    monkeypatch.setattr(plan, "FINE_CELLS", 64 * vol.n_blocks - 1)
    assert "-DLC_OCTANTS" not in eng.render(ribs, scene).report["build_options"]


def test_octants_of_every_half_block_cell_hold_its_bounds(eng, ribs):
    """atlas_cells at 4 cells per block edge: each half-block cell's bounds are the union of its eight octants'
    (both from the same brick samples, the octants' reach a subset), bit for bit, so that cells_and_octants
    reduces the half-block cells from the octants instead of running the kernel twice."""
    vol = as_volume(ribs)
    B, G = int(vol.block_size), vol.grid
    levels = np.random.default_rng(7).integers(-1, 4, size=G).astype(np.int8)
    da = lod_atlas.device_atlas(eng, vol, levels, with_std=True, keep=False)
    for interp in ("interblock", "nearest_block"):
        half = atlas_cells.atlas_cells(eng, da, G, B, interp, vol.std_unit)
        octs = atlas_cells.atlas_cells(eng, da, G, B, interp, vol.std_unit, cpb=4)
        assert octs.vmin.shape == tuple(4 * g for g in G) and octs.cpb == 4
        parts = [(octs.vmin[z::2, y::2, x::2], octs.vmax[z::2, y::2, x::2], octs.std[z::2, y::2, x::2])
                 for z in (0, 1) for y in (0, 1) for x in (0, 1)]
        lo = np.fmin.reduce([p[0] for p in parts])
        hi = np.fmax.reduce([p[1] for p in parts])
        sd = np.max([p[2] for p in parts], axis=0)
        f = np.isfinite(half.vmin)
        assert np.array_equal(f, np.isfinite(lo))
        assert np.all(half.vmin[f] <= lo[f]) and np.all(half.vmax[f] >= hi[f]) and np.all(half.std >= sd)
        tighter = [(p[0][f] > half.vmin[f]) | (p[1][f] < half.vmax[f]) for p in parts]
        assert np.mean(tighter) > 0.2  # what the octants are for
        derived, _ = atlas_cells.cells_and_octants(eng, da, G, B, interp, vol.std_unit)
        for got, ref in ((derived.vmin, half.vmin), (derived.vmax, half.vmax), (derived.std, half.std)):
            np.testing.assert_array_equal(got, ref)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_octant_masks_change_nothing_on_random_volumes_and_views(eng, tmp_path, monkeypatch, seed):
    """Property: random blobs and shells, 16³ or 32³ blocks, anisotropic spacing, random views (perspective or
    orthographic), clip planes and reductions: the image with octant masks is the one without, within float
    rounding, and never takes more samples."""
    from lodcast.renderer.kernel import config

    rng = np.random.default_rng(100 + seed)
    shape = tuple(int(n) for n in rng.integers(24, 72, 3))
    z, y, x = np.mgrid[: shape[0], : shape[1], : shape[2]].astype(np.float64)
    a = rng.normal(40, 10, shape)
    for _ in range(4):  # thin shells and small bright blobs
        c = [rng.uniform(0, n) for n in shape]
        r = np.sqrt((z - c[0]) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2)
        a = np.where(np.abs(r - rng.uniform(3, 15)) < rng.uniform(0.6, 2.0), rng.uniform(600, 1000), a)
    B = int(rng.choice([16, 32]))
    st = lodcast.ingest(a.astype(np.float32), tmp_path / "v.zarr", block_size=B,
                        spacing=tuple(float(s) for s in rng.uniform(0.5, 2.0, 3)), progress=False)
    cam = {"azimuth": float(rng.uniform(0, 360)), "elevation": float(rng.uniform(-70, 70))}
    if seed % 2:
        cam.update(projection="orthographic", view_height=float(max(shape)) * 1.5)
    scene = {"tf": BONE, "width": 48, "height": 40, "camera": cam,
             "quality": {"reduction": float(rng.choice([2, 4, 8, 16]))},
             "sampling": {"interpolation": str(rng.choice(["nearest_block", "interblock"])),
                          "jitter": bool(seed % 2)}}
    if seed >= 2:
        scene["clip"] = {"planes": [{"normal": [float(v) for v in rng.normal(size=3)],
                                     "point": [float(n) * 0.4 for n in shape[::-1]]}]}
    on = eng.render(st, scene)
    monkeypatch.setattr(config.KernelConfig, "octants", property(lambda self: False))
    off = eng.render(st, scene)
    assert "-DLC_OCTANTS" in on.report["build_options"] and "-DLC_OCTANTS" not in off.report["build_options"]
    assert on.rgba[..., 3].max() > 0.2  # something shows
    np.testing.assert_allclose(on.rgba, off.rgba, rtol=0, atol=1e-5)
    assert on.report["samples"] <= off.report["samples"]


@pytest.mark.parametrize("scene", [{}, {"sampling": {"classification": "mean"}},
                                   {"sampling": {"empty_space_skipping": False}},
                                   {"tf2": {"points": [{"value": 40, "color": [1, 0, 0], "opacity": 0.0},
                                                       {"value": 80, "color": [1, 0, 0], "opacity": 0.3}]}}])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("derived", [False, True])
def test_a_walk_info_from_the_last_one_is_the_one_computed_from_nothing(eng, ribs, monkeypatch, scene, seed, derived):
    """atlas_cell_info from the newest info of its scene (a new view's selection) classifies again only the cells
    whose bounds, block info or coarseness changed, and gives, bit for bit, the info computed from nothing: over
    random changes of levels (block info spread near coarse blocks, coarse cells against the level-0 ranges) and
    of some cells' bounds (NaN among them), with distribution classification and without, without empty-space
    skipping and with a second TF. `derived`: the cells say they were computed from the last ones and which
    were computed again (some of those unchanged), as an atlas built from the last one gives them; then no cell
    is compared."""
    from lodcast.renderer.frame.prepare import prepare
    from lodcast.renderer.walk import info as R

    classified = []
    orig = R._composite_cells
    monkeypatch.setattr(R, "_composite_cells", lambda pr, up, *a: classified.append(up.size) or orig(pr, up, *a))
    rng = np.random.default_rng(seed)
    vol = as_volume(ribs)
    g = vol.grid
    top = ribs.n_levels - 1
    sc = {"width": 32, "height": 32, "tf": BONE, **scene}
    last = ("test", seed)

    def cells_of(old: atlas_cells.AtlasCells | None, frac: float) -> atlas_cells.AtlasCells:
        shape = tuple(2 * n for n in g)
        new = [rng.uniform(0, 1200, shape).astype(np.float32) for _ in range(2)]
        lo, hi = np.minimum(*new), np.maximum(*new)
        lo[rng.random(shape) < 0.05] = np.nan
        sd = rng.uniform(0, 60, shape).astype(np.float32) * (rng.random(shape) < 0.5)
        if old is None:
            return atlas_cells.AtlasCells(lo, hi, sd)
        m = rng.random(shape) < frac
        arrays = [np.where(m, a, b) for a, b in ((lo, old.vmin), (hi, old.vmax), (sd, old.std))]
        if not derived:
            return atlas_cells.AtlasCells(*arrays)
        redone = np.flatnonzero(m | (rng.random(shape) < frac))
        return atlas_cells.AtlasCells(*arrays, base=weakref.ref(old), redone=redone)

    orig_differ, shape = R._bits_differ, tuple(2 * n for n in g)

    def forbid(a, b):
        raise AssertionError("derived cells compared")

    levels = rng.integers(-1, top + 1, size=g).astype(np.int8)
    cells = cells_of(None, 1.0)
    R.atlas_cell_info(prepare(eng, ribs, sc, levels=levels), cells, last)
    for frac in (0.02, 0.2):
        levels = levels.copy()
        m = rng.random(g) < frac
        levels[m] = rng.integers(-1, top + 1, size=int(m.sum()))
        cells = cells_of(cells, frac)
        pr = prepare(eng, ribs, sc, levels=levels)
        classified.clear()
        if derived:
            monkeypatch.setattr(R, "_bits_differ", lambda a, b: forbid(a, b) if a is not None and a.shape == shape
                                else orig_differ(a, b))
        got = R.atlas_cell_info(pr, cells, last)
        monkeypatch.setattr(R, "_bits_differ", orig_differ)
        assert 0 < sum(classified) < cells.vmin.size  # classified again in part
        np.testing.assert_array_equal(got, R.atlas_cell_info(pr, cells))
