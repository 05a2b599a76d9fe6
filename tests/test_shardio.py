"""lodcast.store.shardio: the shard-level reader returns exactly what zarr-python returns for the arrays ingest writes."""
from __future__ import annotations

import os

import numpy as np
import pytest
import zarr
from zarr.codecs import BloscCodec, BloscShuffle, BytesCodec

from lodcast.store import shardio
from lodcast.store.shardio import ShardedReader, fast_reader

BITSHUFFLE = BloscCodec(cname="zstd", clevel=1, shuffle=BloscShuffle.bitshuffle)
SHUFFLE = BloscCodec(cname="zstd", clevel=1, shuffle=BloscShuffle.shuffle)


def _data(shape: tuple[int, ...], dtype: str, seed: int = 0) -> np.ndarray:
    """Smooth-ish values with noise, in the dtype's range (floats carry a few NaN)."""
    rng = np.random.default_rng(seed)
    z, y, x = np.meshgrid(*(np.linspace(0, 3, n) for n in shape), indexing="ij")
    v = np.sin(z * 2 + y) * np.cos(x * 3 - y) + 0.1 * rng.standard_normal(shape)
    dt = np.dtype(dtype)
    if dt.kind in "iu":
        info = np.iinfo(dt)
        lo, hi = max(info.min, -30000), min(info.max, 60000)
        return np.clip((v + 1.3) / 2.6 * (hi - lo) + lo, lo, hi).astype(dt)
    out = v.astype(dt)
    out.flat[rng.choice(out.size, 5, replace=False)] = np.nan
    return out


def _array(root, name, shape, dtype, chunks, shards, compressors=BITSHUFFLE, data=True, **kw) -> zarr.Array:
    group = zarr.open_group(root, mode="a")
    fill = np.nan if np.dtype(dtype).kind == "f" else 0
    arr = group.create_array(name, shape=shape, dtype=dtype, chunks=chunks, shards=shards, compressors=compressors,
                             fill_value=kw.pop("fill_value", fill), dimension_names=("z", "y", "x"), **kw)
    if data:
        arr[...] = _data(shape, dtype)
    return zarr.open_group(root, mode="r")[name]  # read back as the store does: a read-only LocalStore


def _same(reader: ShardedReader, arr: zarr.Array, region: tuple[slice, ...]) -> None:
    got, want = reader.read_region(region), np.asarray(arr[region])
    assert got.dtype == want.dtype and got.shape == want.shape, (region, got.dtype, want.dtype, got.shape, want.shape)
    assert np.array_equal(got, want, equal_nan=want.dtype.kind == "f"), region


def _random_regions(shape: tuple[int, ...], n: int, seed: int) -> list[tuple[slice, ...]]:
    rng = np.random.default_rng(seed)
    regions = []
    for _ in range(n):
        bounds = [np.sort(rng.integers(0, s + 1, 2)) for s in shape]
        regions.append(tuple(slice(int(a), int(b) if b > a else int(a) + 1) for a, b in bounds))
    return regions


CASES = [  # shape, dtype, chunks, shards, compressors
    ((37, 50, 29), "uint16", (8, 8, 8), (16, 16, 16), BITSHUFFLE),
    ((33, 70, 65), "uint8", (16, 16, 16), (16, 32, 32), SHUFFLE),
    ((20, 30, 45), "int16", (4, 4, 4), (8, 16, 16), SHUFFLE),
    ((25, 19, 40), "float16", (8, 8, 8), (8, 16, 24), BITSHUFFLE),
    ((17, 40, 33), "float32", (8, 8, 8), (16, 16, 16), BITSHUFFLE),
    ((9, 12, 30), "float64", (4, 4, 4), (8, 8, 8), SHUFFLE),
    ((48, 64, 64), "uint16", (16, 16, 16), (16, 64, 64), BITSHUFFLE),  # multiples of chunks and shards
    ((21, 22, 23), "uint16", (4, 4, 4), (8, 8, 8), None),  # bytes only, no compressor
]


@pytest.mark.parametrize("shape,dtype,chunks,shards,compressors", CASES, ids=[f"{c[1]}-{c[0]}" for c in CASES])
def test_regions_match_zarr(tmp_path, shape, dtype, chunks, shards, compressors):
    arr = _array(tmp_path, "a", shape, dtype, chunks, shards, compressors)
    reader = fast_reader(arr)
    assert reader is not None
    full = tuple(slice(None) for _ in shape)
    _same(reader, arr, full)
    _same(reader, arr, tuple(slice(0, c) for c in chunks))  # one chunk
    last = tuple(slice((s - 1) // c * c, s) for s, c in zip(shape, chunks))  # the partial corner chunk
    _same(reader, arr, last)
    across = tuple(slice(max(0, sh - 3), min(s, sh + 3)) for s, sh in zip(shape, shards))  # crosses shard faces
    _same(reader, arr, across)
    _same(reader, arr, (slice(-5, None), slice(2, -2), slice(None, 7)))  # negative and open bounds
    for region in _random_regions(shape, 60, seed=len(shape) * 7 + sum(shape)):
        _same(reader, arr, region)


def test_never_written_chunks_and_shards_read_as_fill(tmp_path):
    for dtype, fill in (("uint16", 7), ("float32", np.nan), ("int16", -3)):
        name = f"sparse_{dtype}"
        group = zarr.open_group(tmp_path, mode="a")
        arr = group.create_array(name, shape=(40, 50, 60), dtype=dtype, chunks=(8, 8, 8), shards=(16, 16, 16),
                                 compressors=BITSHUFFLE, fill_value=fill)
        arr[3:11, 20:37, 5:30] = _data((8, 17, 25), dtype, seed=1)  # part of a few shards; most shards absent
        arr[16:24, 16:24, 16:24] = fill  # a chunk equal to the fill value: zarr does not store it
        arr = zarr.open_group(tmp_path, mode="r")[name]
        assert len(os.listdir(tmp_path / name / "c")) < 3  # shards that were never written have no file
        reader = fast_reader(arr)
        _same(reader, arr, (slice(None),) * 3)
        for region in _random_regions(arr.shape, 40, seed=3):
            _same(reader, arr, region)
        assert np.array_equal(reader.read_region((slice(30, 40), slice(40, 50), slice(50, 60))),
                              np.full((10, 10, 10), fill, dtype), equal_nan=True)


def test_all_empty_array(tmp_path):
    arr = _array(tmp_path, "empty", (10, 20, 30), "float32", (4, 4, 4), (8, 8, 8), data=False)
    out = fast_reader(arr).read_region((slice(None),) * 3)
    assert out.shape == (10, 20, 30) and np.isnan(out).all()


def test_big_endian_serializer_and_dtype(tmp_path):
    group = zarr.open_group(tmp_path, mode="a")
    for name, dtype in (("be_bytes", "uint16"), ("be_dtype", ">i2")):
        arr = group.create_array(name, shape=(18, 20, 22), dtype=dtype, chunks=(4, 4, 4), shards=(8, 8, 8),
                                 serializer=BytesCodec(endian="big"), compressors=SHUFFLE, fill_value=0)
        arr[...] = _data((18, 20, 22), dtype)
        arr = zarr.open_group(tmp_path, mode="r")[name]
        reader = fast_reader(arr)
        for region in [(slice(None),) * 3] + _random_regions(arr.shape, 20, seed=5):
            _same(reader, arr, region)


def test_index_at_start(tmp_path):
    arr = _array(tmp_path, "start", (20, 21, 22), "uint16", (4, 4, 4), {"shape": (8, 8, 8), "index_location": "start"})
    assert arr.metadata.to_dict()["codecs"][0]["configuration"]["index_location"] == "start"
    reader = fast_reader(arr)
    for region in [(slice(None),) * 3] + _random_regions(arr.shape, 20, seed=6):
        _same(reader, arr, region)


def test_layout_shaped_level(tmp_path):
    """A level array as ingest lays it out (block 16: chunks 16³, shards (16, 128, 128)), shape not a multiple."""
    arr = _array(tmp_path, "0", (40, 150, 140), "uint16", (16, 16, 16), (16, 128, 128))
    reader = fast_reader(arr)
    _same(reader, arr, (slice(16, 32), slice(0, 128), slice(0, 128)))  # exactly one shard
    _same(reader, arr, (slice(None),) * 3)
    for region in _random_regions(arr.shape, 30, seed=7):
        _same(reader, arr, region)


def test_rewritten_shard_is_reread(tmp_path):
    arr = _array(tmp_path, "w", (16, 16, 16), "uint16", (8, 8, 8), (16, 16, 16))
    reader = fast_reader(arr)
    before = reader.read_region((slice(None),) * 3)
    writable = zarr.open_group(tmp_path, mode="a")["w"]
    writable[0:8, 0:8, 0:8] = 1  # shard rewritten with a different layout; index cache keyed by mtime and size
    new = zarr.open_group(tmp_path, mode="r")["w"]
    _same(reader, new, (slice(None),) * 3)
    assert not np.array_equal(before, reader.read_region((slice(None),) * 3))


def test_non_unit_step_falls_back_to_zarr(tmp_path):
    arr = _array(tmp_path, "s", (20, 20, 20), "uint8", (4, 4, 4), (8, 8, 8))
    _same(fast_reader(arr), arr, (slice(0, 20, 2), slice(None), slice(1, 19, 3)))


def test_bad_region_is_refused(tmp_path):
    arr = _array(tmp_path, "r", (8, 8, 8), "uint8", (4, 4, 4), (8, 8, 8))
    with pytest.raises(TypeError):
        fast_reader(arr).read_region((slice(None), slice(None)))
    with pytest.raises(TypeError):
        fast_reader(arr).read_region((0, slice(None), slice(None)))


def test_corrupt_index_is_detected(tmp_path):
    arr = _array(tmp_path, "c", (8, 8, 8), "uint16", (4, 4, 4), (8, 8, 8))
    shard = tmp_path / "c" / "c" / "0" / "0" / "0"
    raw = bytearray(shard.read_bytes())
    raw[-10] ^= 0xFF  # inside the index, before the checksum
    shard.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="checksum"):
        fast_reader(arr).read_region((slice(None),) * 3)


def test_unsupported_arrays_return_none(tmp_path):
    group = zarr.open_group(tmp_path, mode="a")
    zstd_inner = group.create_array("zstd", shape=(10, 10, 10), dtype="uint16", chunks=(4, 4, 4), shards=(8, 8, 8))
    assert fast_reader(zstd_inner) is None  # zarr's default compressor (zstd codec) is not handled
    transposed = group.create_array("t", shape=(10, 10, 10), dtype="uint16", chunks=(4, 4, 4), shards=(8, 8, 8),
                                    filters=[zarr.codecs.TransposeCodec(order=(2, 1, 0))], compressors=BITSHUFFLE)
    assert fast_reader(transposed) is None
    memory = zarr.open_group(zarr.storage.MemoryStore(), mode="w")
    in_memory = memory.create_array("m", shape=(10, 10, 10), dtype="uint16", chunks=(4, 4, 4), shards=(8, 8, 8),
                                    compressors=BITSHUFFLE)
    assert fast_reader(in_memory) is None
    v2 = zarr.open_array(tmp_path / "v2", mode="w", shape=(10, 10, 10), chunks=(4, 4, 4), dtype="uint16", zarr_format=2)
    assert fast_reader(v2) is None
    assert fast_reader(np.zeros((4, 4, 4))) is None
    assert fast_reader(tmp_path / "nothing_here") is None
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "zarr.json").write_text("{not json")
    assert fast_reader(tmp_path / "bad") is None
    assert fast_reader(tmp_path) is None  # a group's folder: not an array
    assert fast_reader(tmp_path / "t") is None  # the transposed array, opened from its folder alone


UNSHARDED = [  # shape, dtype, chunks, compressors: what ingest writes for the per-block arrays, and more
    ((35, 64, 64), "float64", (1, 64, 64), "zstd"),
    ((35, 64, 64, 13), "uint16", (1, 64, 64, 13), "zstd"),
    ((9, 10, 11, 256), "uint32", (1, 10, 11, 256), BITSHUFFLE),
    ((17, 23, 30), "float32", (4, 8, 16), SHUFFLE),  # partial chunks on every axis
    ((17, 23, 30), "int16", (5, 6, 7), None),  # bytes only
    ((40,), "float16", (16,), "zstd"),
]


@pytest.mark.parametrize("shape,dtype,chunks,compressors", UNSHARDED, ids=[f"{c[1]}-{c[0]}" for c in UNSHARDED])
def test_unsharded_arrays_match_zarr(tmp_path, shape, dtype, chunks, compressors):
    """An unsharded array (ingest's per-block metadata) read by ChunkReader, opened from the array object and from
    its folder alone: zarr-python's values for the whole array, random regions, chunks never written (fill) and a
    region with steps (which zarr-python reads)."""
    group = zarr.open_group(tmp_path, mode="a")
    fill = np.nan if np.dtype(dtype).kind == "f" else 3
    kw = {} if compressors == "zstd" else {"compressors": compressors}
    arr = group.create_array("u", shape=shape, dtype=dtype, chunks=chunks, fill_value=fill, **kw)
    rng = np.random.default_rng(len(shape))
    data = (rng.normal(0, 1000, shape) if np.dtype(dtype).kind == "f" else rng.integers(0, 3000, shape)).astype(dtype)
    data.flat[:: max(1, data.size // 7)] = data.flat[0]
    arr[...] = data
    arr[tuple(slice(0, c) for c in chunks)] = fill  # a chunk equal to the fill value: zarr does not store it
    arr = zarr.open_group(tmp_path, mode="r")["u"]
    for reader in (fast_reader(arr), fast_reader(tmp_path / "u")):
        assert type(reader).__name__ == "ChunkReader"
        _same(reader, arr, (slice(None),) * len(shape))
        assert np.array_equal(reader.read_region(...), np.asarray(arr[...]), equal_nan=True)
        for region in _random_regions(shape, 30, seed=sum(shape)):
            _same(reader, arr, region)
        stepped = tuple(slice(1, None, 2) for _ in shape)
        _same(reader, arr, stepped)


def test_damaged_unsharded_chunk_is_store_corrupt(tmp_path):
    from lodcast.errors import StoreCorrupt

    group = zarr.open_group(tmp_path, mode="a")
    arr = group.create_array("m", shape=(4, 8, 8), dtype="float64", chunks=(1, 8, 8), fill_value=0.0)
    arr[...] = np.arange(256.0).reshape(4, 8, 8)
    reader = fast_reader(tmp_path / "m")
    assert np.array_equal(reader.read_region(...), np.arange(256.0).reshape(4, 8, 8))
    (tmp_path / "m" / "c" / "2" / "0" / "0").write_bytes(b"\x28\xb5\x2f\xfd garbage")
    with pytest.raises(StoreCorrupt, match="re-ingest"):
        fast_reader(tmp_path / "m").read_region(...)


def test_rendering_a_local_store_does_not_import_zarr(tmp_path):
    """Opening a local store and rendering it reads the arrays' zarr.json and chunks itself: zarr-python (0.2-0.4 s
    to import, a fifth of a first render) is not imported; asking for the group imports it."""
    import subprocess
    import sys

    import lodcast

    vol = np.random.default_rng(1).normal(100, 30, (20, 24, 28)).astype(np.float32)
    lodcast.ingest(vol, tmp_path / "s.zarr", block_size=8, progress=False)
    code = ("import sys, lodcast; st = lodcast.open_store(sys.argv[1]); "
            "r = lodcast.render(st, {'width': 16, 'height': 16, 'quality': 'lossless', "
            "'tf': {'points': [{'value': 0, 'opacity': 0}, {'value': 200, 'opacity': 0.5}]}}); "
            "print('zarr' in sys.modules, st.stats.mean.shape == st.grid); st.group; print('zarr' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "s.zarr")], capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == ["False", "True", "True"], out


def test_work_units_tile_the_region_once(tmp_path):
    """The pieces a region is split into cover each of its chunks exactly once and never straddle a shard."""
    arr = _array(tmp_path, "u", (70, 300, 260), "uint8", (8, 8, 8), (16, 64, 64), data=False)
    reader = fast_reader(arr)
    for region in _random_regions(arr.shape, 30, seed=9) + [(slice(None),) * 3]:
        lo = tuple(s.indices(n)[0] for s, n in zip(region, arr.shape))
        hi = tuple(s.indices(n)[1] for s, n in zip(region, arr.shape))
        hits = np.zeros([-(-n // 8) for n in arr.shape], np.int32)
        for c0, c1 in reader._units(lo, hi):
            assert all(a < b for a, b in zip(c0, c1))
            assert all(a // p == (b - 1) // p for a, b, p in zip(c0, c1, (2, 8, 8)))
            hits[tuple(slice(a, b) for a, b in zip(c0, c1))] += 1
        want = np.zeros_like(hits)
        want[tuple(slice(a // 8, -(-b // 8)) for a, b in zip(lo, hi))] = 1
        assert np.array_equal(hits, want)


def test_a_region_read_in_another_dtype_is_the_cast_of_the_region(tmp_path):
    """`read_region(..., dtype)` casts as it places each chunk: the same values as reading, then converting."""
    import lodcast

    rng = np.random.default_rng(8)
    vol = rng.integers(-1024, 3000, (37, 50, 45)).astype(np.int16)
    st = lodcast.ingest(vol, tmp_path / "v.zarr")
    for region in (..., (slice(3, 30), slice(0, 50), slice(7, 41)), (slice(0, 1), slice(5, 6), slice(0, 45))):
        want = vol[region if region is not ... else ()].astype(np.float32)
        got = st.read_region(0, region, np.float32)
        assert got.dtype == np.float32 and np.array_equal(got, want)
    assert st.read_region(1, ..., np.float64).dtype == np.float64


@pytest.mark.parametrize("shape,dtype,chunks,shards,compressors", CASES, ids=[f"{c[1]}-{c[0]}" for c in CASES])
def test_scattered_chunks_match_zarr(tmp_path, shape, dtype, chunks, shards, compressors):
    """read_chunks of random scattered chunks of each shard (edge chunks included) returns each whole chunk, and
    its part inside the array is zarr-python's region of that chunk."""
    arr = _array(tmp_path, "a", shape, dtype, chunks, shards, compressors)
    reader = fast_reader(arr)
    rng = np.random.default_rng(sum(shape))
    per = [s // c for s, c in zip(shards, chunks)]
    n_chunks = [-(-s // c) for s, c in zip(shape, chunks)]
    for shard in np.ndindex(*[-(-n // p) for n, p in zip(n_chunks, per)]):
        inside = [(sh * p, min((sh + 1) * p, n)) for sh, p, n in zip(shard, per, n_chunks)]
        every = np.array(list(np.ndindex(*[b - a for a, b in inside]))) + np.array([a for a, _ in inside])
        pick = every[rng.choice(len(every), size=max(1, len(every) // 3), replace=False)]
        box = reader.read_chunks(pick)
        assert box.shape == (len(pick), *chunks)
        for got, co in zip(box, pick):
            region = tuple(slice(int(c) * k, min((int(c) + 1) * k, s)) for c, k, s in zip(co, chunks, shape))
            want = np.asarray(arr[region])
            part = got[tuple(slice(0, r.stop - r.start) for r in region)].astype(want.dtype)
            assert np.array_equal(part, want, equal_nan=want.dtype.kind == "f"), co


def test_scattered_chunks_read_no_other_chunk(tmp_path):
    """Two chunks at opposite corners of a shard whose middle chunk is damaged: read_chunks decodes only the two
    (a region spanning them would take the damaged one and fail)."""
    arr = _array(tmp_path, "d", (8, 16, 16), "uint16", (4, 4, 4), (8, 16, 16))
    reader = fast_reader(arr)
    key = arr.metadata.encode_chunk_key((0, 0, 0))
    index = reader._index(reader._files.open(key), "d", key)
    middle = np.ravel_multi_index((0, 1, 1), (2, 4, 4))
    off, size = (int(v) for v in index[middle])
    shard = tmp_path / "d" / "c" / "0" / "0" / "0"
    raw = bytearray(shard.read_bytes())
    raw[off:off + size] = b"\xff" * size
    shard.write_bytes(bytes(raw))
    box = reader.read_chunks(np.array([[0, 0, 0], [1, 3, 3]]))
    want = _data((8, 16, 16), "uint16")
    assert np.array_equal(box[0], want[:4, :4, :4]) and np.array_equal(box[1], want[4:, 12:, 12:])
    with pytest.raises(shardio.StoreCorrupt):
        reader.read_region((slice(0, 8), slice(0, 16), slice(0, 16)))
    with pytest.raises(AssertionError, match="more than one shard"):
        _array(tmp_path, "e", (8, 16, 16), "uint16", (4, 4, 4), (8, 8, 8))
        fast_reader(zarr.open_group(tmp_path, mode="r")["e"]).read_chunks(np.array([[0, 0, 0], [0, 3, 3]]))


def test_a_shard_mostly_wanted_is_read_in_one_request(tmp_path, monkeypatch):
    """Half a shard's chunks or more: the file is read whole, once (its index from its tail), and the chunks are
    those read with the index and the chunks' span as two requests; fewer: no whole read."""
    arr = _array(tmp_path, "w", (16, 16, 16), "uint16", (4, 4, 4), (8, 16, 16))
    every = np.array(list(np.ndindex(2, 4, 4)))
    for wanted, requests in ((every, 1), (every[::2], 1), (every[:5], 2)):
        reads = []
        reader = fast_reader(arr)  # (a fresh reader: no index cached)
        pread = reader._files.pread
        monkeypatch.setattr(reader._files, "pread", lambda fd, n, off: reads.append(n) or pread(fd, n, off))
        got = reader.read_chunks(wanted)
        assert len(reads) == requests
        monkeypatch.setattr(shardio, "WHOLE_SHARD_BYTES", 0)
        apart = fast_reader(arr).read_chunks(wanted)
        monkeypatch.undo()
        assert np.array_equal(got, apart)
        want = _data((16, 16, 16), "uint16")
        for g, co in zip(got, wanted):
            assert np.array_equal(g, want[tuple(slice(c * 4, c * 4 + 4) for c in co)])
