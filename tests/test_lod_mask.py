"""Level-0 cell ranges (store format 3) and what the renderer does with them: a cell of a coarse block whose level-0
voxels (with a one-voxel border) the TF shows nothing of is not sampled (renderer/walk/info.py: _cell_info).

The ranges are checked against a float64 reference computed here from the volume (each cell grown by one voxel,
NaN left out, edge padding never counted, float32 rounded outwards), with block sizes whose slabs hold one, two and
four rows of cells (the border across slabs is the delicate part); the half-block cells the atlas walk uses
against the same reference over those cells; the mask by renders against full resolution's: it only takes opacity
away, the image comes closer to full resolution's, the walk takes far fewer samples, and a store of format 2
renders as before and says so in the report.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr

import lodcast
from lodcast.renderer.data.volume import VolumeView, as_volume
from lodcast.renderer.frame.render import render
from lodcast.renderer.image.delta_e import delta_e_stats
from lodcast.store.layout import cell_edge


def _volume(name: str, shape: tuple[int, int, int], dtype) -> np.ndarray:
    rng = np.random.default_rng(abs(hash(name)) % 2**32)
    if np.dtype(dtype).kind == "f":
        vol = (rng.normal(0, 50, shape) + (1e5 if name == "f64_far" else 0.0)).astype(dtype)
        if name == "f64_far":  # values float32 cannot hold: the ranges must round outwards
            vol += rng.uniform(0, 1e-3, shape)
        vol.flat[rng.integers(0, vol.size, max(2, vol.size // 30))] = np.nan
        vol[:10, :10, :10] = np.nan  # a cell without a valid voxel, border included
        return vol
    info = np.iinfo(dtype)
    return rng.integers(max(info.min, -3000), min(info.max, 4000), shape).astype(dtype)


def _reference(vol: np.ndarray, c: int) -> tuple[np.ndarray, np.ndarray]:
    grid = tuple(-(-n // c) for n in vol.shape)
    lo, hi = np.full(grid, np.nan), np.full(grid, np.nan)
    v = vol.astype(np.float64)
    for z, y, x in np.ndindex(grid):
        # the cell grown by one voxel (what trilinear interpolation reads there), within the true extent: no padding
        cell = v[tuple(slice(max(0, i * c - 1), (i + 1) * c + 1) for i in (z, y, x))]
        if np.isfinite(cell).any():
            lo[z, y, x], hi[z, y, x] = np.nanmin(cell), np.nanmax(cell)
    return lo, hi


CASES = [
    ("i16", (37, 21, 45), np.int16, 16),
    ("u8_b4", (10, 13, 9), np.uint8, 4),
    ("f32_b32", (40, 35, 33), np.float32, 32),
    ("thin_f32", (1, 19, 30), np.float32, 8),
    ("i32", (9, 17, 12), np.int32, 8),
    ("f64_far", (12, 20, 11), np.float64, 16),
]


@pytest.mark.parametrize("name,shape,dtype,block", CASES, ids=[c[0] for c in CASES])
def test_cell_ranges_equal_a_float64_reference(tmp_path: Path, name, shape, dtype, block):
    vol = _volume(name, shape, dtype)
    lodcast.ingest(vol, tmp_path / "s.zarr", block_size=block, progress=False)
    st = lodcast.open_store(tmp_path / "s.zarr")
    c = cell_edge(block)
    assert st.format_version == 4 and c == min(8, block)
    assert st.summary()["cells"] == {"edge": c, "grid": [-(-n // c) for n in shape]}
    lo, hi = st.cell_ranges
    want_lo, want_hi = _reference(vol, c)
    assert lo.dtype == hi.dtype == np.float32 and lo.shape == want_lo.shape
    np.testing.assert_array_equal(np.isnan(lo), np.isnan(want_lo))
    np.testing.assert_array_equal(np.isnan(hi), np.isnan(want_hi))
    ok = ~np.isnan(want_lo)
    assert ok.any()
    # outwards: the float32 range holds the float64 one, and is the nearest float32 that does
    assert (lo[ok] <= want_lo[ok]).all() and (hi[ok] >= want_hi[ok]).all()
    assert (np.nextafter(lo[ok], np.float32(np.inf)) > want_lo[ok]).all()
    assert (np.nextafter(hi[ok], np.float32(-np.inf)) < want_hi[ok]).all()
    if np.dtype(dtype).kind == "f":
        assert np.isnan(lo).any()  # the all-NaN cell
    if name == "f64_far":
        assert (lo[ok] < want_lo[ok]).any()  # rounding did happen, outwards


@pytest.mark.parametrize("block", [4, 8, 16, 32])
def test_half_block_cells_take_the_range_of_the_level_0_voxels_they_cover(tmp_path: Path, block):
    """VolumeView.half_cell_ranges: the range over each half-block cell (the atlas walk's, grid 2G), from the
    store's cells: several cells per half-cell at B = 32, the containing cell (the block) below B = 16."""
    vol = _volume(f"half{block}", (45, 30, 51), np.float32)
    st = lodcast.ingest(vol, tmp_path / "s.zarr", block_size=block, progress=False)
    lo, hi = as_volume(st).half_cell_ranges()
    g2 = tuple(2 * g for g in st.grid)
    assert lo.shape == hi.shape == g2
    span = max(block // 2, cell_edge(block))  # what a half-cell's range covers: itself, or its whole cell
    for h in {(0, 0, 0), tuple(g - 1 for g in g2), tuple(min(i, g - 1) for i, g in zip((3, 1, 5), g2)),
              tuple(g // 2 for g in g2)}:
        start = [(i * (block // 2)) // span * span for i in h]
        cell = vol[tuple(slice(max(0, a - 1), a + span + 1) for a in start)].astype(np.float64)  # grown by a voxel
        if not np.isfinite(cell).any():
            assert np.isnan(lo[h]) and np.isnan(hi[h])
            continue
        assert lo[h] == np.float32(np.nanmin(cell)) and hi[h] == np.float32(np.nanmax(cell)), h


@pytest.fixture(scope="module")
def tissue(tmp_path_factory):
    """Fat and muscle (-100 and 50 HU, alternating voxel by voxel) around a bone ball: every coarse voxel of the
    soft tissue has mean -25 and spread 75, whose Gaussian tail reaches ct-bone's range (250 HU and up)."""
    rng = np.random.default_rng(4)
    z, y, x = np.indices((48, 48, 48))
    vol = (np.where((z + y + x) % 2, 50.0, -100.0) + rng.normal(0, 5, z.shape)).astype(np.float32)
    vol[(z - 24) ** 2 + (y - 24) ** 2 + (x - 24) ** 2 < 8 ** 2] = 1200.0
    return lodcast.ingest(vol, tmp_path_factory.mktemp("tissue") / "t.zarr", block_size=8, progress=False)


SCENE = {"tf": "ct-bone", "width": 48, "height": 48, "camera": {"azimuth": 20, "elevation": 10}, "format": "npy"}


@pytest.fixture(scope="module")
def tissue_reference(tissue):
    return render(tissue, {**SCENE, "sampling": {"step": 0.25}}).rgba


@pytest.mark.parametrize("sampling", [{"adaptive_object": False}, {"adaptive_object": True},
                                      {"adaptive_object": False, "empty_space_skipping": False}],
                         ids=["fixed", "adaptive", "no-ess"])
def test_coarse_cells_empty_at_level_0_are_skipped(tissue, tissue_reference, monkeypatch, sampling):
    """Level 1 everywhere, interblock: the coarse field of the ball spreads a voxel or two past it (nearest block
    keeps it in the ball's own blocks, where the atlas's own cell ranges already bound it), and the spread of the
    tissue's coarse voxels (mean -25, spread 75, and up to 600 where they hold some bone) reaches ct-bone's range
    (250 HU and up), in cells whose level-0 voxels and their borders hold no bone. Those cells are skipped, with or
    without empty-space skipping: at most 3/4 of the samples (measured 0.62), nothing is added anywhere (alpha
    only falls), and the image comes closer to full resolution's (mean ΔE 9.0 against 9.9, measured)."""
    scene = {**SCENE, "quality": {"reduction": 2}, "sampling": {"interpolation": "interblock", **sampling}}
    levels = np.ones(tissue.grid, np.int8)
    masked = render(tissue, scene, levels=levels)
    with monkeypatch.context() as m:
        m.setattr(VolumeView, "has_cell_ranges", property(lambda self: False))
        every = render(tissue, scene, levels=levels)
    assert masked.report["coarse_cells"] == "skipped" and every.report["coarse_cells"].startswith("sampled")
    n_masked, n_every = masked.report["samples"], every.report["samples"]
    assert n_masked < 0.75 * n_every, (n_masked, n_every)
    assert (masked.rgba[..., 3] <= every.rgba[..., 3] + 1e-6).all()
    assert np.abs(masked.rgba - every.rgba).max() > 0.05  # the spread was visible
    e_masked, e_every = (delta_e_stats(r.rgba, tissue_reference)["mean"] for r in (masked, every))
    assert e_masked < e_every, (e_masked, e_every)
    assert masked.rgba[..., 3].max() > 0.5  # the ball shows


def test_level_0_cells_are_never_masked(tissue):
    """At level 0 the cells' skipping is exact as at full resolution (the mask is for coarse cells only): all
    blocks at level 0 render the full-resolution image, and the report has nothing to say about coarse cells."""
    full = render(tissue, SCENE)
    lod = render(tissue, {**SCENE, "quality": "lossless"}, levels=np.zeros(tissue.grid, np.int8))
    np.testing.assert_allclose(lod.rgba, full.rgba, rtol=0, atol=1e-5)
    assert lod.report["coarse_cells"] is None and full.report["coarse_cells"] is None


def to_format_2(path: Path) -> None:
    """What a store written before the cell ranges looks like: no blocks/cell_min, cell_max, format 2."""
    g = zarr.open_group(str(path), mode="a")
    for name in ("cell_min", "cell_max"):
        shutil.rmtree(path / "blocks" / name)
    attrs = dict(g.attrs)
    attrs["lodcast"] = {k: v for k, v in attrs["lodcast"].items() if k not in ("manifest", "integrity")} | {"format_version": 2}
    g.attrs.put(attrs)


def test_format_2_store_samples_every_coarse_cell_and_says_so(tissue, tmp_path, monkeypatch):
    p2 = tmp_path / "v2.zarr"
    shutil.copytree(Path(tissue.location), p2)
    to_format_2(p2)
    st2 = lodcast.open_store(p2)
    assert st2.format_version == 2 and st2.cell_ranges is None and st2.summary()["cells"] is None
    scene = {**SCENE, "quality": {"reduction": 4}}
    old = render(st2, scene)
    assert old.report["coarse_cells"].startswith("sampled (this store keeps no level-0 cell ranges")
    monkeypatch.setattr(VolumeView, "has_cell_ranges", property(lambda self: False))
    np.testing.assert_array_equal(old.rgba, render(tissue, scene).rgba)  # format 3 without its ranges: the same
