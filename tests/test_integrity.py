"""Issue 49, items 1 and 5: a damaged store is never an image. Format 4 carries zarr's crc32c after every chunk and
shard index, a manifest binding every file to its place and digests of the root attributes; bit flips, swapped
shards and edited metadata are StoreCorrupt naming the file (HTTP 409, CLI exit 2), `lodcast verify` lists the
damage, `lodcast upgrade` rewrites an older store in place. Real files, real zarr-python."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr

import lodcast
from lodcast.errors import StoreCorrupt
from lodcast.service.cli import main
from lodcast.store.store import data_manifest

BLOCK = 8


def volume(dtype: str = "uint16") -> np.ndarray:
    """A smooth field with noise (every chunk compresses to another size), 0..3000."""
    rng = np.random.default_rng(49)
    z, y, x = np.mgrid[0:24, 0:40, 0:40].astype(np.float64)
    f = 1500 + 1000 * np.sin(x / 5) * np.cos(y / 7) + 400 * np.sin(z / 4) + 60 * rng.standard_normal(x.shape)
    return np.clip(np.round(f), 0, 3000).astype(dtype)


@pytest.fixture
def store(tmp_path: Path) -> Path:
    lodcast.ingest(volume(), tmp_path / "v.zarr", block_size=BLOCK)
    return tmp_path / "v.zarr"


def shards(root: Path, array: str = "0") -> list[Path]:
    return sorted(p for p in (root / array / "c").rglob("*") if p.is_file())


def format3(root: Path, dtype: str | None = None) -> None:
    """Rewrite a format-4 store as format 3 wrote it: the same arrays without the crc32c codec after each chunk
    (zarr's default crc32c stays in the shard index codecs, as it was), no manifest file, no integrity record;
    `dtype`: the level arrays in another (wider) type, as an older ingest could store them."""
    for meta_path in sorted(root.rglob("zarr.json")):
        if meta_path.parent == root:
            continue
        folder = meta_path.parent
        old = zarr.open_array(folder, mode="r")
        data = old[...]
        meta = old.metadata
        sharded = meta.codecs[0].__class__.__name__ == "ShardingCodec"
        inner = meta.codecs[0].codecs if sharded else meta.codecs
        compressors = [c for c in inner[1:] if type(c).__name__ != "Crc32cCodec"]
        level = folder.name.isdigit() and folder.parent == root
        kind = np.dtype(dtype) if dtype is not None and level else data.dtype
        shutil.rmtree(folder)
        new = zarr.create_array(store=str(folder), shape=data.shape, dtype=kind, fill_value=meta.fill_value,
                                chunks=meta.codecs[0].chunk_shape if sharded else meta.chunks,
                                shards=meta.chunks if sharded else None, compressors=compressors,
                                config={"write_empty_chunks": sharded},
                                dimension_names=meta.dimension_names, zarr_format=3)
        new[...] = data.astype(kind)
    doc = json.loads((root / "zarr.json").read_text())
    attrs = doc["attributes"]
    attrs["lodcast"] = {"format_version": 3, "generation": attrs["lodcast"]["generation"],
                        "manifest": data_manifest(root)}
    if dtype is not None:
        attrs["dtype"] = dtype
    (root / "manifest.json").unlink()
    (root / "zarr.json").write_text(json.dumps(doc))


def read_all(root: Path) -> list[np.ndarray]:
    st = lodcast.open_store(root)
    return [st.read_level(k) for k in range(st.n_levels)]


# --- readers of the format -----------------------------------------------------------------------------------

def test_zarr_python_reads_a_format_4_store_and_checks_its_crc32c(store: Path):
    st = lodcast.open_store(store)
    assert st.format_version == 4 and st.checksums is not None
    group = zarr.open_group(store, mode="r")
    for k in range(st.n_levels):
        codecs = group[str(k)].metadata.to_dict()["codecs"][0]["configuration"]
        assert [c["name"] for c in codecs["codecs"]] == ["bytes", "blosc", "crc32c"]
        assert [c["name"] for c in codecs["index_codecs"]] == ["bytes", "crc32c"]
        np.testing.assert_array_equal(group[str(k)][...], st.read_level(k))
    np.testing.assert_array_equal(group["0"][...], volume())
    blocks_min = zarr.open_array(store / "blocks" / "min", mode="r")
    assert blocks_min.metadata.to_dict()["codecs"][-1]["name"] == "crc32c"
    np.testing.assert_array_equal(blocks_min[...], st.stats.min)
    # zarr-python checks the same checksum: a flipped bit in a chunk is an error there too, not other voxels
    shard = shards(store)[0]
    raw = bytearray(shard.read_bytes())
    raw[40] ^= 0x10
    shard.write_bytes(bytes(raw))
    with pytest.raises(Exception, match="(?i)checksum|crc"):
        zarr.open_array(store / "0", mode="r")[...]


# --- the corruption suite ----------------------------------------------------------------------------------

def test_the_manifest_ingest_writes_is_the_one_read_back_from_disk(store: Path, tmp_path: Path):
    """Ingest takes the entries of the shards it wrote instead of reading them back: the manifest must be the one a
    fresh reading of every file gives."""
    from lodcast.store.checksum import MANIFEST, write_manifest

    written = json.loads((store / MANIFEST).read_bytes())
    copy = tmp_path / "copy.zarr"
    shutil.copytree(store, copy)
    write_manifest(copy)
    assert json.loads((copy / MANIFEST).read_bytes()) == written
    assert len(written["files"]["0"]) >= 2  # shards of level 0 are among them


def test_bit_flips_in_shard_data_and_index_are_never_silent(store: Path):
    """40 single-bit flips at random positions of level-0 shards (data and index alike): each one is StoreCorrupt
    naming the shard, or harmless (the voxels read are the ingested ones); none gives other voxels. A shard holds
    no unused bytes, so every flip is caught."""
    want = volume()
    rng = np.random.default_rng(4940)
    files = shards(store)
    caught = harmless = silent = 0
    in_index = 0
    index_bytes = 16 * _chunks_per_shard(store) + 4
    for _ in range(40):
        shard = files[int(rng.integers(len(files)))]
        good = shard.read_bytes()
        raw = bytearray(good)
        pos = int(rng.integers(len(raw)))
        raw[pos] ^= 1 << int(rng.integers(8))
        in_index += pos >= len(raw) - index_bytes
        shard.write_bytes(bytes(raw))
        try:
            got = lodcast.open_store(store).read_level(0)
        except StoreCorrupt as exc:
            assert str(shard.relative_to(store)) in str(exc), exc
            caught += 1
        else:
            if np.array_equal(got, want):
                harmless += 1
            else:
                silent += 1
        shard.write_bytes(good)
    assert (caught, harmless, silent) == (40, 0, 0)
    assert 0 < in_index < 40  # both kinds of position were hit
    np.testing.assert_array_equal(lodcast.open_store(store).read_level(0), want)


def _chunks_per_shard(root: Path) -> int:
    cfg = json.loads((root / "0" / "zarr.json").read_text())
    shard = cfg["chunk_grid"]["configuration"]["chunk_shape"]
    chunk = cfg["codecs"][0]["configuration"]["chunk_shape"]
    return int(np.prod([s // c for s, c in zip(shard, chunk)]))


def test_a_flip_in_per_block_metadata_is_caught(store: Path):
    chunk = sorted(p for p in (store / "blocks" / "max" / "c").rglob("*") if p.is_file())[0]
    raw = bytearray(chunk.read_bytes())
    raw[len(raw) // 2] ^= 0x04
    chunk.write_bytes(bytes(raw))
    with pytest.raises(StoreCorrupt, match="blocks/max/c/"):
        lodcast.open_store(store).stats  # noqa: B018


def test_swapped_shards_are_caught(store: Path):
    a, b = shards(store)[:2]
    da, db = a.read_bytes(), b.read_bytes()
    assert len(da) != len(db) or da != db
    a.write_bytes(db)
    b.write_bytes(da)
    with pytest.raises(StoreCorrupt, match=r"not the shard ingest wrote at this place"):
        lodcast.open_store(store).read_level(0)
    # verify compares each file's whole bytes with the manifest: both shards are listed
    result = _verify(store)
    assert {d.file for d in result.damage} == {str(a.relative_to(store)), str(b.relative_to(store))}


def test_edited_level_data_type_is_caught_naming_the_file(store: Path):
    p = store / "0" / "zarr.json"
    p.write_text(p.read_text().replace('"uint16"', '"int16"'))
    with pytest.raises(StoreCorrupt, match=r"0/zarr.json: array metadata changed since ingest"):
        lodcast.open_store(store)


def test_edited_value_range_is_caught_naming_the_attribute(store: Path):
    p = store / "zarr.json"
    doc = json.loads(p.read_text())
    doc["attributes"]["value_range"] = [0.0, 1500.0]
    p.write_text(json.dumps(doc))
    with pytest.raises(StoreCorrupt, match=r"zarr.json: attribute 'value_range' changed"):
        lodcast.open_store(store)


def test_older_stores_have_their_metadata_checked_against_the_root(store: Path):
    format3(store)
    st = lodcast.open_store(store)
    assert st.format_version == 3 and st.checksums is None
    np.testing.assert_array_equal(st.read_level(0), volume())
    p = store / "zarr.json"
    doc = json.loads(p.read_text())
    doc["attributes"]["value_range"] = [0.0, 1500.0]
    p.write_text(json.dumps(doc))
    with pytest.raises(StoreCorrupt, match=r"attribute 'value_range' \[0.0, 1500.0\] is not the range"):
        lodcast.open_store(store).stats  # noqa: B018
    doc["attributes"]["value_range"] = [float(volume().min()), float(volume().max())]
    p.write_text(json.dumps(doc))
    level = store / "0" / "zarr.json"
    level.write_text(level.read_text().replace('"uint16"', '"int16"'))
    with pytest.raises(StoreCorrupt, match=r"0/zarr.json: array metadata disagrees with the root zarr.json "
                                           r"\(data_type int16 where the root attributes give uint16\)"):
        lodcast.open_store(store)


@pytest.mark.parametrize("damage", ["garbled level 0", "deleted level 0", "garbled blocks/mean"])
def test_damaged_array_metadata_is_409_over_http_and_exit_2_on_the_cli(tmp_path: Path, capsys, damage: str):
    from fastapi.testclient import TestClient

    from lodcast.service.app import create_app
    from lodcast.service.settings import Settings
    from lodcast.service.testing import make_volume, tiny_scene

    make_volume(tmp_path, "good")
    bad = make_volume(tmp_path, "bad")
    rel = "blocks/mean/zarr.json" if "blocks" in damage else "0/zarr.json"
    if damage.startswith("deleted"):
        (bad / rel).unlink()
    else:
        (bad / rel).write_text('{"shape": [24, 24, 2')
    with TestClient(create_app(Settings(root=tmp_path, token=None, workers=0))) as client:
        for r in (client.post("/volumes/bad/render", json=tiny_scene()), client.get("/volumes/bad")):
            assert r.status_code == 409, r.text
            assert r.headers["content-type"] == "application/json" and rel in r.json()["detail"], r.json()
        assert client.post("/volumes/good/render", json=tiny_scene()).status_code == 200
        listed = {v["id"]: v for v in client.get("/volumes").json()}
        assert rel in listed["bad"]["error"] and "error" not in listed["good"]
    capsys.readouterr()
    assert main(["info", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{bad}/{rel}" in err[0], err
    assert main(["render", str(bad), "-o", str(tmp_path / "x.png"), "--tf", "ct-bone"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{bad}/{rel}" in err[0], err
    assert not (tmp_path / "x.png").exists()


def test_a_flipped_bit_is_409_naming_the_shard_and_chunk(tmp_path: Path):
    from fastapi.testclient import TestClient

    from lodcast.service.app import create_app
    from lodcast.service.settings import Settings
    from lodcast.service.testing import make_volume, tiny_scene

    bad = make_volume(tmp_path, "bad")
    for shard in shards(bad):  # every level-0 shard: whatever the render reads first is damaged
        raw = bytearray(shard.read_bytes())
        raw[20] ^= 0x01
        shard.write_bytes(bytes(raw))
    with TestClient(create_app(Settings(root=tmp_path, token=None, workers=0))) as client:
        r = client.post("/volumes/bad/render", json=tiny_scene(quality="full"))
    assert r.status_code == 409, r.text
    detail = r.json()["detail"]
    assert "0/c/" in detail and "chunk (" in detail and "fails its checksum" in detail, detail
    assert str(tmp_path) not in detail


# --- verify and upgrade --------------------------------------------------------------------------------------

def _verify(root: Path):  # type: ignore[no-untyped-def]
    from lodcast.store.verify import verify

    return verify(root, workers=2)


def test_verify_exit_codes_and_listing(store: Path, tmp_path: Path, capsys):
    assert main(["verify", str(store)]) == 0
    out = capsys.readouterr()
    assert out.out == "" and "clean" in out.err
    victim = shards(store)[1]
    raw = bytearray(victim.read_bytes())
    raw[7] ^= 0x80
    victim.write_bytes(bytes(raw))
    std = shards(store, "std/1")[0]
    std.write_bytes(std.read_bytes()[:-3])
    assert main(["verify", str(store)]) == 1
    out = capsys.readouterr()
    listed = [line.split(":")[0] for line in out.out.splitlines()]
    assert listed == sorted([str(victim.relative_to(store)), str(std.relative_to(store))], key=listed.index), out.out
    assert len(listed) == 2 and "2 damaged files" in out.err
    (tmp_path / "plain").mkdir()
    assert main(["verify", str(tmp_path / "plain")]) == 2
    assert main(["verify", str(tmp_path / "nothing")]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 2


def test_verify_says_a_format_3_store_carries_no_checksums(store: Path, capsys):
    format3(store)
    assert main(["verify", str(store)]) == 0
    assert "carries no checksums" in capsys.readouterr().err


def test_upgrade_of_a_format_3_store_is_verified_clean_and_renders_the_same(store: Path, capsys):
    format3(store, dtype="int32")  # an older ingest's wider type: the rule stores these values as uint16
    before = lodcast.open_store(store)
    assert before.format_version == 3 and before.dtype == np.int32
    levels = [before.read_level(k) for k in range(before.n_levels)]
    scene = {"camera": {"azimuth": 30, "elevation": 20}, "width": 24, "height": 24, "format": "npy",
             "tf": {"points": [{"value": 1000, "color": [1, 0.8, 0.6], "opacity": 0.0},
                               {"value": 2500, "color": [1, 1, 1], "opacity": 0.7}]}}
    image = lodcast.render(before, scene).rgba
    source = before.attrs["source"]
    assert main(["upgrade", str(store)]) == 0
    assert "format 3 (int32) -> format 4 (uint16)" in capsys.readouterr().out
    after = lodcast.open_store(store)
    assert after.format_version == 4 and after.dtype == np.uint16 and after.attrs["source"] == source
    assert after.attrs["provenance"]["upgraded"]["from_format"] == 3
    for k, want in enumerate(levels):
        np.testing.assert_array_equal(after.read_level(k), want)
    assert np.array_equal(lodcast.render(after, scene).rgba, image)
    assert _verify(store).clean and _verify(store).checksums
    assert not any(p.name.startswith(".") for p in store.parent.iterdir())  # nothing left beside it
    assert main(["upgrade", str(store)]) == 0
    assert "nothing to do" in capsys.readouterr().out


def test_upgrade_refuses_a_damaged_store(store: Path):
    format3(store)
    victim = shards(store)[0]
    victim.write_bytes(bytes(len(victim.read_bytes())))
    with pytest.raises(StoreCorrupt):
        from lodcast.store.upgrade import upgrade

        upgrade(store)
    assert json.loads((store / "zarr.json").read_text())["attributes"]["lodcast"]["format_version"] == 3
    assert os.path.exists(victim)


# --- the stored-type rule ------------------------------------------------------------------------------------

@pytest.mark.parametrize("pixel,bits,rescale,present,want", [
    ("uint16", 12, [(1.0, -1024.0)], (0, 4095), "int16"),  # a CT: 0..4095 stored, −1024..3071 HU
    ("uint16", 16, [(1.0, -1024.0)], (0, 4095), "int16"),  # the same pixels declared 16-bit: the values decide
    ("uint16", 16, [(1.0, -1024.0)], (0, 40000), "float32"),  # −1024..38976: no 16-bit type; float32 is exact
    ("uint16", 8, [(1.0, 10.0)], (0, 255), "uint16"),  # 10..265
    ("uint8", 8, [(1.0, -100.0)], (0, 255), "int16"),  # −100..155
    ("uint8", 8, [(1.0, -64.0)], (0, 127), "int8"),  # −64..63, from the values present
    ("uint8", 6, [(2.0, 100.0)], (0, 63), "uint8"),  # 100..226
    ("int16", 16, [(1.0, 0.0)], (-5, 5), "int16"),  # nothing rescaled: the pixels' own type
    ("int16", 16, [(1000.0, 0.0)], (-32768, 32767), "int32"),  # whole values past float32's exact integers
    ("int16", 16, [(-1.0, 0.0)], (-32768, 0), "uint16"),  # a negative slope turns the range round: 0..32768
    ("uint32", 32, [(2.0, 0.0)], (0, 2**32 - 1), "float64"),  # whole, past int32: float64 holds them exactly
    ("uint16", 12, [(0.5, -1024.0)], (0, 4095), "float32"),  # not whole
])
def test_rescaled_values_take_the_smallest_type_that_holds_them(pixel, bits, rescale, present, want):
    from lodcast.store.readers.base import rescaled_type
    from lodcast.store.readers.dicom import stored_range

    values = np.array(present, dtype=pixel)
    assert rescaled_type(np.dtype(pixel), stored_range(np.dtype(pixel), bits), rescale,
                         lambda: [(values, r) for r in rescale]) == np.dtype(want)


def test_declared_range_that_decides_reads_no_pixels():
    """12 stored bits with intercept −1024 give int16 from the header alone: the pixels are not read twice."""
    from lodcast.store.readers.base import rescaled_type

    def never():
        raise AssertionError("the pixels were scanned")

    assert rescaled_type(np.dtype("uint16"), (0, 4095), [(1.0, -1024.0)], never) == np.int16
