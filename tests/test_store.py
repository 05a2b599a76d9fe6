"""The brick store: levels against an independent float64 reference, statistics and histograms against brute
force, optimal simplified histograms, addressing beyond 2^31 voxels, OME metadata, atomic writes."""
from __future__ import annotations

import itertools
import json
import os
from pathlib import Path

import numpy as np
import pytest
import zarr

import lodcast
from lodcast.errors import SourceError, StoreExists, StoreInvalid, StoreNotFound
from lodcast.store import ingest as ingest_module
from lodcast.store.histogram import Bins, segmentation_sse, simplify
from lodcast.store.layout import Layout
from lodcast.store.source import ArraySource


def reference_level(volume: np.ndarray, block: int, k: int) -> np.ndarray:
    """Level k the slow way: pad each axis to a multiple of the block by repeating the edge, average every
    2^k-cube in float64 ignoring NaN, cut to ceil(shape / 2^k)."""
    v = volume.astype(np.float64)
    pad = [(0, (-s) % block) for s in v.shape]
    v = np.pad(v, pad, mode="edge")
    f = 1 << k
    out_shape = [s // f for s in v.shape]
    out = np.empty(out_shape)
    for idx in itertools.product(*(range(n) for n in out_shape)):
        cube = v[idx[0] * f : (idx[0] + 1) * f, idx[1] * f : (idx[1] + 1) * f, idx[2] * f : (idx[2] + 1) * f]
        out[idx] = np.nanmean(cube) if not np.isnan(cube).all() else np.nan
    return out[tuple(slice(0, -(-s // f)) for s in volume.shape)]


def brute_border_hist(volume: np.ndarray, block: int, edges: np.ndarray) -> np.ndarray:
    grid = [-(-s // block) for s in volume.shape]
    out = np.zeros(grid + [len(edges) - 1], np.int64)
    for b in itertools.product(*(range(g) for g in grid)):
        region = volume[tuple(slice(max(0, i * block - 1), min(n, (i + 1) * block + 1)) for i, n in zip(b, volume.shape))]
        vals = region[~np.isnan(region.astype(np.float64))].astype(np.float64)
        out[b] = np.histogram(vals, bins=edges)[0]
    return out


def rounded(ref: np.ndarray, dtype: np.dtype) -> np.ndarray:
    return np.rint(ref) if np.dtype(dtype).kind in "iu" else ref


CASES = [
    ("odd", (33, 17, 5), np.uint16, 8),
    ("thin", (1, 19, 23), np.int16, 8),
    ("one_block", (16, 16, 16), np.uint8, 16),
    ("float", (9, 20, 13), np.float32, 4),
    ("float64", (5, 6, 7), np.float64, 4),
]


@pytest.mark.parametrize("reread", ["source", "pieces", "store"], ids=["pass2_source", "pass2_pieces", "pass2_store"])
@pytest.mark.parametrize("name,shape,dtype,block", CASES, ids=[c[0] for c in CASES])
def test_levels_stats_and_histograms_match_brute_force(tmp_path: Path, monkeypatch, name, shape, dtype, block, reread):
    rng = np.random.default_rng(abs(hash(name)) % 2**32)
    if np.dtype(dtype).kind == "f":
        vol = (rng.standard_normal(shape) * 100).astype(dtype)
        vol.flat[rng.integers(0, vol.size, 3)] = np.nan
    else:
        info = np.iinfo(dtype)
        vol = rng.integers(max(info.min, -2000), min(info.max, 3000), shape).astype(dtype)
    # the histogram pass reads the source again, or level 0 back from the store when the source is slow to read
    src = ArraySource(vol, spacing=(0.3, 1.0, 5.0))
    src.rereads_cheaply = reread != "store"
    if reread == "pieces":  # the source read again three slices at a time: pieces that cut rows of blocks
        monkeypatch.setattr(ingest_module, "COUNT_BYTES", 3 * shape[1] * shape[2] * np.dtype(dtype).itemsize)
    st = lodcast.ingest(src, tmp_path / f"{name}.zarr", block_size=block)
    assert st.spacing == (0.3, 1.0, 5.0) and st.shape == shape and st.dtype == np.dtype(dtype)
    # level 0 bit-exact (NaN where NaN)
    np.testing.assert_array_equal(st.read_level(0), vol)
    # every level against the float64 reference; integers rounded half to even, floats to their precision
    for k in range(1, st.n_levels):
        ref = rounded(reference_level(vol, block, k), dtype)
        got = st.read_level(k).astype(np.float64)
        assert got.shape == ref.shape
        np.testing.assert_allclose(got, ref, rtol=1e-6 if dtype == np.float32 else 1e-12, atol=0, equal_nan=True)
    # interior statistics: padding and NaN excluded
    v64 = vol.astype(np.float64)
    for b in itertools.product(*(range(g) for g in st.grid)):
        cube = v64[tuple(slice(i * block, (i + 1) * block) for i in b)]
        assert st.stats.count[b] == np.count_nonzero(~np.isnan(cube))
        assert st.stats.min[b] == np.nanmin(cube) and st.stats.max[b] == np.nanmax(cube)
        assert st.stats.mean[b] == pytest.approx(np.nanmean(cube), rel=1e-12)
        border = v64[tuple(slice(max(0, i * block - 1), (i + 1) * block + 1) for i in b)]
        assert st.stats.min_border[b] == np.nanmin(border) and st.stats.max_border[b] == np.nanmax(border)
    # border-inclusive histograms equal a brute-force count with the stored edges
    np.testing.assert_array_equal(st.hist, brute_border_hist(vol, block, st.hist_edges))
    assert st.hist.sum() > 0
    # value range is NaN-free
    assert st.value_range == (float(np.nanmin(v64)), float(np.nanmax(v64)))


def test_integer_levels_round_half_to_even(tmp_path: Path):
    vol = np.zeros((2, 2, 4), np.uint8)
    vol[:, :, :2] = [[[2, 3], [2, 3]], [[2, 3], [2, 3]]]  # mean 2.5 -> 2
    vol[:, :, 2:] = [[[3, 4], [3, 4]], [[3, 4], [3, 4]]]  # mean 3.5 -> 4
    st = lodcast.ingest(vol, tmp_path / "r.zarr", block_size=2)
    np.testing.assert_array_equal(st.read_level(1)[0, 0], [2, 4])


def test_constant_and_nan_volumes(tmp_path: Path):
    st = lodcast.ingest(np.full((5, 6, 7), 42, np.int16), tmp_path / "c.zarr", block_size=4)
    assert st.value_range == (42.0, 42.0) and st.bins.count == 1
    assert (st.hist[..., 0] > 0).all()
    with pytest.raises(SourceError, match="no valid voxel"):
        lodcast.ingest(np.full((4, 4, 4), np.nan, np.float32), tmp_path / "n.zarr")
    assert not (tmp_path / "n.zarr").exists() and not list(tmp_path.glob(".n.zarr*"))


@pytest.mark.parametrize("device", [True, False], ids=["opencl", "numpy"])
def test_simplified_histograms_are_optimal_against_brute_force(device: bool):
    rng = np.random.default_rng(7)

    def brute(h: np.ndarray, k: int) -> float:
        best = np.inf
        for m in range(1, min(k, len(h)) + 1):
            for cuts in itertools.combinations(range(1, len(h)), m - 1):
                b = (0, *cuts, len(h))
                best = min(best, sum(((h[b[i] : b[i + 1]] - h[b[i] : b[i + 1]].mean()) ** 2).sum() for i in range(m)))
        return best

    hists = []
    for _ in range(150):
        n = int(rng.integers(1, 12))
        hists.append((rng.integers(0, 5, n) * (rng.random(n) < 0.6)).astype(np.float64))
    for k in (1, 2, 3, 4):
        for h in hists:
            starts, heights = simplify(h[None], k, device=device)
            assert starts[0, 0] == 0 and starts[0, -1] == len(h) and (np.diff(starts[0].astype(int)) >= 0).all()
            assert segmentation_sse(h[None], starts, heights)[0] == pytest.approx(brute(h, k), abs=1e-9)


def test_simplified_histograms_opencl_and_numpy_agree_on_large_noisy_batches():
    rng = np.random.default_rng(5)
    h = rng.poisson(40, (300, 256)) * (rng.random((300, 256)) < 0.8)
    on_device, in_numpy = simplify(h, 12, device=True), simplify(h, 12, device=False)
    np.testing.assert_allclose(segmentation_sse(h, *on_device), segmentation_sse(h, *in_numpy), rtol=1e-12)


def test_simplified_histograms_batch_equals_single_and_have_12_pieces():
    rng = np.random.default_rng(3)
    x = np.arange(256)
    centres, widths = rng.uniform(20, 230, (40, 2, 1)), rng.uniform(3, 25, (40, 2, 1))
    h = np.rint((1000 * np.exp(-0.5 * ((x - centres) / widths) ** 2)).sum(axis=1))  # block histograms: a few peaks
    s_all, h_all = simplify(h, 12)
    assert s_all.shape == (40, 13) and h_all.shape == (40, 12)
    for i in (0, 17, 39):
        s1, h1 = simplify(h[i : i + 1], 12)
        np.testing.assert_array_equal(s1[0], s_all[i])
        # more pieces never increase the error, and twelve pieces capture a few peaks far better than one
        assert segmentation_sse(h[i : i + 1], s1, h1)[0] <= segmentation_sse(h[i : i + 1], *simplify(h[i : i + 1], 11))[0] + 1e-9
    assert (segmentation_sse(h, s_all, h_all) < 0.1 * segmentation_sse(h, *simplify(h, 1))).all()


def test_addressing_beyond_2_31_voxels():
    lay = Layout((2048, 2048, 1024), 32)
    assert lay.n_voxels == 2**32
    last = lay.voxel_offset(2047, 2047, 1023)
    assert last == 2**32 - 1 and isinstance(last, int)
    assert lay.voxel_of_offset(last) == (2047, 2047, 1023)
    z = np.array([0, 1024, 2047])
    off = lay.voxel_offset(z, np.array([5, 2047, 2047]), np.array([7, 1023, 1023]))
    assert off.dtype == np.int64 and off.tolist() == [5 * 1024 + 7, (1024 * 2048 + 2047) * 1024 + 1023, 2**32 - 1]
    assert lay.grid == (64, 64, 32) and lay.n_blocks == 131072
    bi = lay.block_index(np.array([63]), np.array([63]), np.array([31]))
    assert bi.tolist() == [131071] and [c.tolist() for c in lay.block_coords(bi)] == [[63], [63], [31]]
    assert lay.level_shape(5) == (64, 64, 32) and lay.voxel_offset(63, 63, 31, level=5) == 131071
    # sub-ranges of the last block at level 0 are clipped correctly
    assert lay.block_region(63, 63, 31, border=1) == (slice(2015, 2048), slice(2015, 2048), slice(991, 1024))


def test_other_readers_see_the_image_alone(tmp_path: Path):
    """The level arrays are the root group's only members (std/ and blocks/ have no group node): napari's
    built-in reader, which opens a group's first subgroup if it has one, opens the levels in order; ome-zarr-py
    reads the levels with their scale, translation and the omero window."""
    rng = np.random.default_rng(3)
    vol = rng.normal(100.0, 20.0, (40, 50, 36)).astype(np.float32)
    vol[10:30, 10:40, 8:28] += 400.0
    st = lodcast.ingest(vol, tmp_path / "v.zarr", spacing=(2.0, 0.5, 0.25), origin=(10.0, -5.0, 1.0), block_size=8)
    g = zarr.open_group(str(tmp_path / "v.zarr"), mode="r")
    with pytest.warns(UserWarning, match="not recognized as a component"):  # std/, blocks/: prefixes, not nodes
        members = dict(g.members())
    assert sorted(members, key=int) == [str(k) for k in range(st.n_levels)] and not list(g.group_keys())
    assert all(isinstance(a, zarr.Array) for a in members.values())
    assert np.array_equal(st.read_std_region(1), np.asarray(g["std/1"][...]))  # lodcast's own arrays, by path
    assert g["blocks/hist"].shape[:3] == st.grid

    try:  # the `interop` extra, which test.sh installs
        from napari_builtins.io import _read as napari_read
        from ome_zarr.io import parse_url
        from ome_zarr.reader import Reader
    except ImportError as e:
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            raise
        pytest.skip(f"napari or ome-zarr is not installed ({e}): pip install -e '.[interop]'")
    layers = napari_read.napari_get_reader(str(tmp_path / "v.zarr"))(str(tmp_path / "v.zarr"))
    levels = layers[0][0]
    assert [lv.shape for lv in levels] == [st.level(k).shape for k in range(st.n_levels)]
    assert np.array_equal(np.asarray(levels[0]), vol) and np.array_equal(np.asarray(levels[2]), st.read_level(2))

    (node,) = list(Reader(parse_url(str(tmp_path / "v.zarr")))())[:1]
    assert [d.shape for d in node.data] == [st.level(k).shape for k in range(st.n_levels)]
    assert np.array_equal(np.asarray(node.data[1]), st.read_level(1))
    ct = node.metadata["coordinateTransformations"]
    assert ct[1][0]["scale"] == [4.0, 1.0, 0.5] and ct[0][1]["translation"] == [10.0, -5.0, 1.0]
    lo, hi = node.metadata["contrast_limits"][0]
    assert float(vol.min()) <= lo < 150.0 < 450.0 < hi <= float(vol.max())  # the omero window spans both tissues


def test_chunks_shards_and_ome_metadata(tmp_path: Path):
    from ome_zarr_models.v05.image import Image

    vol = np.random.default_rng(0).integers(0, 255, (70, 300, 40)).astype(np.uint8)
    st = lodcast.ingest(vol, tmp_path / "v.zarr", spacing=(2.0, 0.5, 0.25), origin=(10.0, -5.0, 1.0), block_size=32)
    for k in range(st.n_levels):
        arr = st.level(k)
        assert arr.shards == st.layout.shard_shape(k) and arr.chunks == st.layout.chunk_shape(k)
        assert arr.chunks[0] == max(32 >> k, 16)
        if k:  # the spread behind each coarse voxel: the same chunks and shards as its level
            sd = st.group[f"std/{k}"]
            assert sd.shards == arr.shards and sd.chunks == arr.chunks and sd.shape == arr.shape
    # coarser levels group more blocks per shard; level 0 here is 3 slabs x 2 shards across y
    assert st.layout.shard_count(0) == 3 * 2 * 1 and st.layout.shard_count(st.n_levels - 1) == 1
    shard_files = [p for p in (tmp_path / "v.zarr" / "0" / "c").rglob("*") if p.is_file()]
    assert len(shard_files) == st.layout.shard_count(0)
    image = Image.from_zarr(zarr.open_group(str(tmp_path / "v.zarr"), mode="r"))
    ds = image.ome_attributes.multiscales[0].datasets
    assert [d.path for d in ds] == [str(k) for k in range(st.n_levels)]
    for k, d in enumerate(ds):
        scale, trans = d.coordinateTransformations[0].scale, d.coordinateTransformations[1].translation
        assert list(scale) == [2.0 * 2**k, 0.5 * 2**k, 0.25 * 2**k]
        # the first level-k sample is the mean of level-0 samples 0 .. 2^k - 1: its centre is their centre
        assert list(trans) == pytest.approx([o + s * (2**k - 1) / 2 for o, s in zip((10.0, -5.0, 1.0), (2.0, 0.5, 0.25))])


def test_atomic_destination_and_errors(tmp_path: Path):
    dest = tmp_path / "a.zarr"
    first = lodcast.ingest(np.zeros((3, 4, 5), np.uint8), dest)
    with pytest.raises(StoreExists):
        lodcast.ingest(np.ones((3, 4, 5), np.uint8), dest)
    assert (lodcast.open_store(dest).read_level(0) == 0).all()
    lodcast.ingest(np.ones((3, 4, 5), np.uint8), dest, overwrite=True)
    assert (lodcast.open_store(dest).read_level(0) == 1).all() and first.shape == (3, 4, 5)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.zarr"]  # no temporary or replaced store left
    with pytest.raises(SourceError, match="unsupported voxel type complex64"):
        lodcast.ingest(np.zeros((2, 2, 2), np.complex64), tmp_path / "c.zarr")
    with pytest.raises(SourceError, match="shape"):
        lodcast.ingest(np.zeros((0, 2, 2), np.uint8), tmp_path / "e.zarr")
    with pytest.raises(ValueError, match="power of two"):
        lodcast.ingest(np.zeros((2, 2, 2), np.uint8), tmp_path / "b.zarr", block_size=24)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.zarr"]
    with pytest.raises(StoreNotFound):
        lodcast.open_store(tmp_path / "missing.zarr")
    zarr.open_group(str(tmp_path / "plain.zarr"), mode="w", zarr_format=3)
    with pytest.raises(StoreInvalid, match="not a lodcast store"):
        lodcast.open_store(tmp_path / "plain.zarr")


def test_read_brick_pads_with_edge(tmp_path: Path):
    vol = np.arange(5 * 6 * 7, dtype=np.uint16).reshape(5, 6, 7)
    st = lodcast.ingest(vol, tmp_path / "b.zarr", block_size=4)
    brick = st.read_brick(0, (1, 1, 1))
    np.testing.assert_array_equal(brick, np.pad(vol[4:, 4:, 4:], ((0, 3), (0, 2), (0, 1)), mode="edge"))
    assert st.read_brick(2, (0, 0, 0)).shape == (1, 1, 1)


def test_summary_has_the_info_keys(tmp_path: Path):
    st = lodcast.ingest(np.zeros((40, 8, 8), np.int16), tmp_path / "s.zarr")
    assert st.block_size == 16  # docs/design.md's default, the thesis' choice
    info = json.loads(json.dumps(st.summary()))
    for key in ("shape", "dtype", "spacing", "origin", "block_size", "levels", "value_range", "blocks", "shards", "bytes_on_disk"):
        assert key in info
    assert info["blocks"] == 3 and info["bytes_on_disk"] > 0 and len(info["levels"]) == 5
    assert info["format_version"] == 4 and info["distribution"]["std"] == "std/{level}"
    assert info["cells"] == {"edge": 8, "grid": [5, 1, 1]}
    assert info["shards"] == sum(lvl["shard_count"] for lvl in info["levels"])


def test_bins_map_values_to_the_stored_edges():
    b = Bins.for_range(-1.5, 2.5, integer=False, max_bins=8)
    v = np.array([-1.5, -1.0, 0.0, 2.4999, 2.5, np.nan])
    idx = b.index(v)
    assert idx.tolist() == [0, 1, 3, 7, 7, -1]
    edges = b.edges
    for val, i in zip(v[:-1], idx[:-1]):
        assert edges[i] <= val <= edges[i + 1]
    bi = Bins.for_range(-3, 4, integer=True)
    assert bi.count == 8 and bi.index(np.array([-3, 0, 4])).tolist() == [0, 3, 7]


def test_a_damaged_store_is_refused_never_rendered_wrong(tmp_path):
    """Issue 10, item 5: ingest records what it wrote (attrs lodcast.manifest) and writes every level chunk; a
    deleted or cut shard file is noticed when the store opens, one deleted or overwritten after it was opened
    when it is read — StoreCorrupt naming the file, never the fill value in the image."""
    import glob
    import os

    from lodcast.errors import StoreCorrupt

    v = np.zeros((40, 40, 40), np.float32)
    v[10:20] = 5.0  # zeros elsewhere: chunks equal to the fill value are written too
    dest = tmp_path / "m.zarr"
    st = lodcast.ingest(v, dest, block_size=8)
    assert st.manifest["0"][0] == len(glob.glob(str(dest / "0" / "c" / "*" / "*" / "*")))
    shard = sorted(glob.glob(str(dest / "0" / "c" / "*" / "*" / "*")))[0]
    data = open(shard, "rb").read()

    os.remove(shard)
    with pytest.raises(StoreCorrupt, match=r"array '0' has 4 data files .* ingest wrote 5"):
        lodcast.open_store(dest)
    open(shard, "wb").write(data[:-10])  # cut short
    with pytest.raises(StoreCorrupt, match="array '0'"):
        lodcast.open_store(dest)
    open(shard, "wb").write(data)
    st = lodcast.open_store(dest)
    np.testing.assert_array_equal(st.read_level(0), v)
    open(shard, "wb").write(bytes(len(data)))  # same size, other bytes: seen when read
    with pytest.raises(StoreCorrupt, match="damaged shard"):
        lodcast.open_store(dest).read_level(0)
    open(shard, "wb").write(data)
    st = lodcast.open_store(dest)
    os.remove(std := sorted(glob.glob(str(dest / "std" / "1" / "c" / "*" / "*" / "*")))[0])  # after opening
    with pytest.raises(StoreCorrupt, match="shard file missing"):
        st.read_std_region(1, (slice(None),) * 3)
    assert std


def test_stores_without_a_manifest_still_open(tmp_path):
    dest = tmp_path / "old.zarr"
    lodcast.ingest(np.ones((16, 16, 16), np.float32), dest, block_size=8)
    g = zarr.open_group(str(dest), mode="r+")
    meta = dict(g.attrs["lodcast"])
    meta.pop("manifest")
    g.attrs["lodcast"] = meta
    st = lodcast.open_store(dest)
    assert st.manifest is None and st.read_level(0).sum() == 16**3


def test_shards_are_no_larger_than_their_level():
    """A shard's index has an entry per chunk it could hold: a coarse level's shard is cut to the level's extent
    (in whole chunks), so its files stay the size of its data, not of an index for 512 x 128 x 128 voxels."""
    from math import ceil

    from lodcast.store.layout import Layout

    for shape, b in (((91, 109, 91), 16), ((300, 40, 1000), 16), ((7, 7, 7), 8), ((2000, 512, 512), 32)):
        lay = Layout(shape, b)
        for k in range(lay.n_levels):
            c = lay.chunk_shape(k)[0]
            sh, lv = lay.shard_shape(k), lay.level_shape(k)
            assert all(s % c == 0 and s <= ceil(n / c) * c for s, n in zip(sh, lv)), (shape, k, sh, lv)
            assert sh[0] == min(max(c, b << k), ceil(lv[0] / c) * c)  # the ingest buffer's depth where it fits


def test_the_omero_window_spans_the_bulk_of_the_values(tmp_path: Path):
    """OME viewers start from `omero`'s window: the 0.5th to 99.5th percentile of the volume's values, so a few
    outliers (metal in a CT, hot pixels) do not leave the picture black."""
    from ome_zarr_models.v05.image import Image

    rng = np.random.default_rng(2)
    vol = rng.uniform(100, 200, (40, 40, 40))
    vol.flat[rng.choice(vol.size, 50, replace=False)] = rng.choice([0.0, 4000.0], 50)
    st = lodcast.ingest(vol.astype(np.float32), tmp_path / "w.zarr")
    Image.from_zarr(zarr.open_group(str(tmp_path / "w.zarr"), mode="r"))  # still valid OME-Zarr 0.5
    win = st.attrs["ome"]["omero"]["channels"][0]["window"]
    assert (win["min"], win["max"]) == (0.0, 4000.0)
    width = (4000.0 - 0.0) / st.bins.count
    assert 100 - 2 * width <= win["start"] <= 100 + 2 * width and 200 - 2 * width <= win["end"] <= 200 + 2 * width, win


@pytest.mark.parametrize("reader", ["shard-level", "zarr-python"])
def test_read_chunks_are_the_level_regions_of_those_chunks(tmp_path, monkeypatch, reader):
    """Store.read_chunks, of levels and of their standard deviations, on a volume that is no multiple of the
    block: each chunk is the level's region under it and, past the level's edge, that region's last samples
    repeated, for random subsets of each shard's chunks; through the shard-level reader and through zarr-python
    (where that reader declines)."""
    vol = np.random.default_rng(11).normal(400, 150, (37, 45, 29)).astype(np.float32)
    st = lodcast.ingest(vol, tmp_path / "r.zarr", block_size=8, progress=False)
    if reader == "zarr-python":
        from lodcast.store import shardio

        monkeypatch.setattr(shardio, "fast_reader", lambda *a, **k: None)
        st = lodcast.open_store(tmp_path / "r.zarr")
    lay = st.layout
    rng = np.random.default_rng(2)
    for k in range(lay.n_levels):
        c, sh, shape = np.array(lay.chunk_shape(k)), np.array(lay.shard_shape(k)), np.array(lay.level_shape(k))
        every = np.array(list(np.ndindex(*(-(-shape // c)))))
        for shard in np.unique(every // (sh // c), axis=0):
            own = every[(every // (sh // c) == shard).all(axis=1)]
            pick = own[rng.choice(len(own), size=max(1, len(own) // 2), replace=False)]
            for std in (False, True):
                got = st.read_chunks(k, pick, std=std)
                assert got.shape == (len(pick), *c.tolist())
                for a, co in zip(got, pick):
                    region = tuple(slice(int(x) * int(n), min((int(x) + 1) * int(n), int(s))) for x, n, s in zip(co, c, shape))
                    want = st.read_std_region(k, region) if std else st.read_region(k, region)
                    want = np.pad(want, [(0, int(n) - m) for n, m in zip(c, want.shape)], mode="edge")
                    assert np.array_equal(a, want, equal_nan=True), (k, co, std)


def test_a_ct_opens_in_the_soft_tissue_window(tmp_path: Path, shared_data: Path):
    """A CT in Hounsfield units (air near -1000, tissue and bone above) gets the soft-tissue window (level 40, width
    400) as its OME `omero` window, as a radiology viewer opens it, rather than its full range (air to bone, grey);
    a volume that merely spans negative values, or an MR, keeps the percentile window."""
    rng = np.random.default_rng(5)
    z, y, x = np.mgrid[:48, :48, :48] - 23.5
    r = np.sqrt(z**2 + y**2 + x**2)
    ct = np.where(r < 20, 40.0, -1000.0) + rng.normal(0, 10, r.shape)
    ct[(r > 8) & (r < 11)] = 1200.0  # bone
    st = lodcast.ingest(np.rint(ct).astype(np.int16), tmp_path / "ct.zarr")
    win = st.attrs["ome"]["omero"]["channels"][0]["window"]
    assert (win["start"], win["end"]) == (-160.0, 240.0) and win["min"] < -950 and win["max"] > 1150, win
    signal = rng.normal(0, 300, (32, 32, 32)).astype(np.float32)  # symmetric about 0: no air peak
    win = lodcast.ingest(signal, tmp_path / "s.zarr").attrs["ome"]["omero"]["channels"][0]["window"]
    assert win["start"] < -500 and win["end"] > 500, win
    real = lodcast.ingest(shared_data / "ct_chest_dicom", tmp_path / "chest.zarr")
    assert real.attrs["ome"]["omero"]["channels"][0]["window"]["start"] == -160.0
    mr = lodcast.ingest(shared_data / "mr_head.nii.gz", tmp_path / "mr.zarr")
    win = mr.attrs["ome"]["omero"]["channels"][0]["window"]
    assert win["start"] >= 0.0 and (win["start"], win["end"]) != (-160.0, 240.0), win
