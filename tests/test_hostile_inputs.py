"""Hostile input costs nothing (issue 49, item 3, readers and ingest): every reader reads only the file it is given
(and, where the format defines companions, files in that file's own folder), every declared quantity is bounded
from the header before anything is read or allocated, and spacing and origin must give a finite world box. Each
hostile file is written here with the format's own library; a refusal is a SourceError naming the file and the
field, the CLI exits 2 with one line, and nothing is left at the destination."""
from __future__ import annotations

import gzip
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import nibabel as nib
import nrrd
import numpy as np
import pytest
import tifffile
import zarr
from phantoms import multiframe

from lodcast.errors import SourceError
from lodcast.store.ingest import FILES_FLOOR, ingest, store_files
from lodcast.store.layout import Layout
from lodcast.store.readers import open_source
from lodcast.store.readers.zarr_source import _OwnFiles

#: the CLI, then its peak RSS in kB (VmHWM: ru_maxrss would keep the forking pytest worker's peak)
PEAK_RSS_KB = ("import sys; from lodcast.service.cli import main; rc = main(sys.argv[1:]); "
               "print(next(l.split()[1] for l in open('/proc/self/status') if l.startswith('VmHWM'))); sys.exit(rc)")


def cli_ingest(src: Path, dest: Path, *args: str, timeout: float = 60, **env: str) -> tuple[subprocess.CompletedProcess,
                                                                                             float, int]:
    """`lodcast ingest` in a child process: (result, seconds, peak RSS in kB). A hostile file that the CLI does not
    refuse from its header runs into `timeout` (subprocess.TimeoutExpired: the test fails)."""
    t0 = time.monotonic()
    out = subprocess.run([sys.executable, "-c", PEAK_RSS_KB, "ingest", "--no-progress", str(src), str(dest), *args],
                         capture_output=True, text=True, timeout=timeout, env={**os.environ, **env})
    rss = int(out.stdout.split()[-1]) if out.stdout.split() else 0
    return out, time.monotonic() - t0, rss


def refused_in_one_line(out: subprocess.CompletedProcess, *words: str) -> None:
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1, out.stderr
    for w in words:
        assert w in lines[0], lines[0]


def nothing_at(dest: Path) -> None:
    """Neither the store nor a hidden partial one beside it."""
    assert not dest.exists()
    assert not [p.name for p in dest.parent.iterdir() if p.name.startswith(f".{dest.name}")]


# --- readers open only their own files ------------------------------------------------------------------------

OME = "http://www.openmicroscopy.org/Schemas/OME/2016-06"


def ome_xml(depth: int, own: str, other: str | None, uuid: str | None = "urn:uuid:0000-own") -> str:
    """OME-XML of a (depth, 8, 8) uint8 image whose first two planes are the file's own pages and, when `other` is
    given, the rest the pages of the file named `other` (a multi-file OME-TIFF)."""
    root_uuid = f' UUID="{uuid}"' if uuid else ""
    own_data = f'<TiffData FirstZ="0" IFD="0" PlaneCount="2"><UUID FileName="{own}">{uuid or "urn:uuid:0000-own"}' \
               f'</UUID></TiffData>'
    other_data = (f'<TiffData FirstZ="2" IFD="0" PlaneCount="{depth - 2}"><UUID FileName="{other}">'
                  f'urn:uuid:0000-other</UUID></TiffData>') if other is not None else ""
    return (f'<?xml version="1.0" encoding="UTF-8"?><OME xmlns="{OME}"{root_uuid}><Image ID="Image:0">'
            f'<Pixels ID="Pixels:0" DimensionOrder="XYZCT" Type="uint8" SizeX="8" SizeY="8" SizeZ="{depth}" '
            f'SizeC="1" SizeT="1"><Channel ID="Channel:0:0" SamplesPerPixel="1"/>{own_data}{other_data}'
            f'</Pixels></Image></OME>')


@pytest.fixture
def secret(tmp_path: Path) -> Path:
    """A TIFF outside the source's folder that no source may read: its pixels are 200."""
    (tmp_path / "private").mkdir()
    tifffile.imwrite(tmp_path / "private" / "secret.tif", np.full((2, 8, 8), 200, np.uint8))
    return tmp_path / "private" / "secret.tif"


@pytest.mark.parametrize("how", ["absolute", "dotdot", "link"])
def test_ome_tiff_never_reads_a_file_outside_its_folder(tmp_path: Path, secret: Path, how: str) -> None:
    """The OME-XML of an uploaded OME-TIFF names another file in <TiffData><UUID FileName=…>: by absolute path, by
    `../`, or by a name beside it that links out. tifffile read those pages into the volume (a render showed the
    other file's pixels); now the file is refused naming the field, for uploads and imports alike."""
    up = tmp_path / "up"
    up.mkdir()
    if how == "link":
        (up / "other.tif").symlink_to(secret)
    name = {"absolute": str(secret), "dotdot": "../private/secret.tif", "link": "other.tif"}[how]
    tifffile.imwrite(up / "up.ome.tif", np.zeros((2, 8, 8), np.uint8), description=ome_xml(4, "up.ome.tif", name),
                     metadata=None)
    with pytest.raises(SourceError, match=r"FileName=.*outside the TIFF's folder"):
        open_source(up / "up.ome.tif")
    with pytest.raises(SourceError, match=r"names another file in its OME-XML <TiffData><UUID FileName="):
        open_source(up / "up.ome.tif", detached=False)


def test_multi_file_ome_tiff_reads_companions_beside_it_unless_uploaded(tmp_path: Path) -> None:
    """A multi-file OME-TIFF whose companion lies beside it is read whole (the format defines companions); an
    upload (detached=False) is a single file and refuses it; a companion that does not exist is named rather than
    read as zeros."""
    d = tmp_path / "set"
    d.mkdir()
    tifffile.imwrite(d / "b.ome.tif", np.full((2, 8, 8), 7, np.uint8))
    tifffile.imwrite(d / "a.ome.tif", np.full((2, 8, 8), 3, np.uint8), description=ome_xml(4, "a.ome.tif", "b.ome.tif"),
                     metadata=None)
    with open_source(d / "a.ome.tif") as src:
        assert src.info.shape == (4, 8, 8)
        assert src.read(0, 4)[:, 0, 0].tolist() == [3, 3, 7, 7]
    with pytest.raises(SourceError, match="only a single-file OME-TIFF"):
        open_source(d / "a.ome.tif", detached=False)
    (d / "b.ome.tif").unlink()
    with pytest.raises(SourceError, match="does not exist"):
        open_source(d / "a.ome.tif")
    tifffile.imwrite(d / "c.ome.tif", np.full((2, 8, 8), 5, np.uint8), description=ome_xml(2, "c.ome.tif", None),
                     metadata=None)
    with open_source(d / "c.ome.tif", detached=False) as src:  # a single-file OME-TIFF naming itself: fine
        assert src.info.shape == (2, 8, 8) and src.read(0, 2).max() == 5
    tifffile.imwrite(d / "s.ome.tif", np.full((2, 8, 8), 9, np.uint8), metadata=None,
                     description=ome_xml(4, "s.ome.tif", "s.ome.tif"))  # itself again, under another UUID
    with open_source(d / "s.ome.tif", detached=False) as src:
        assert src.info.shape == (4, 8, 8) and src.read(0, 4)[:, 0, 0].tolist() == [9, 9, 9, 9]


def test_tiff_folder_slices_read_their_own_page_only(tmp_path: Path, secret: Path) -> None:
    """A slice of a TIFF folder whose OME-XML names a file elsewhere as its one plane: tifffile's series (imread)
    gave that file's pixels; the folder reader reads each slice's own page."""
    d = tmp_path / "stack"
    d.mkdir()
    for k in range(3):
        xml = (f'<?xml version="1.0" encoding="UTF-8"?><OME xmlns="{OME}"><Image ID="Image:0"><Pixels ID="Pixels:0" '
               f'DimensionOrder="XYZCT" Type="uint8" SizeX="8" SizeY="8" SizeZ="1" SizeC="1" SizeT="1">'
               f'<Channel ID="Channel:0:0" SamplesPerPixel="1"/><TiffData IFD="0" PlaneCount="1">'
               f'<UUID FileName="{secret}">urn:uuid:elsewhere</UUID></TiffData></Pixels></Image></OME>')
        tifffile.imwrite(d / f"s{k}.tif", np.full((8, 8), k, np.uint8), description=xml, metadata=None)
    with open_source(d) as src:
        assert src.read(0, 3)[:, 0, 0].tolist() == [0, 1, 2]


def analyze_pair(folder: Path, value: int) -> Path:
    folder.mkdir(exist_ok=True)
    nib.save(nib.Nifti1Pair(np.full((4, 4, 4), value, np.uint8), np.eye(4)), folder / "v.hdr")
    return folder / "v.hdr"


@pytest.mark.parametrize("given, linked", [("v.hdr", "v.img"), ("v.img", "v.hdr")])
def test_nifti_pair_never_reads_a_companion_linked_out_of_its_folder(tmp_path: Path, given: str, linked: str) -> None:
    """A .hdr/.img pair whose other half is a link to a file elsewhere: nibabel read the outside file's bytes as
    the voxels (or its header); now refused before nibabel opens it. A real pair beside each other reads; an
    upload (detached=False) takes single files only."""
    outside = analyze_pair(tmp_path / "outside", 99)
    hdr = analyze_pair(tmp_path / "in", 1)
    with open_source(hdr) as src:
        assert src.read(0, 4).max() == 1
    with pytest.raises(SourceError, match="single-file .nii"):
        open_source(hdr, detached=False)
    (tmp_path / "in" / linked).unlink()
    (tmp_path / "in" / linked).symlink_to(outside.parent / linked)
    with pytest.raises(SourceError, match=f"{linked}, the companion of NIfTI .* outside its folder"):
        open_source(tmp_path / "in" / given)


def test_a_dicom_folder_reads_none_of_its_links_out(tmp_path: Path) -> None:
    """A series folder holding a link to a slice elsewhere (same series, next position): the slice is not part of
    the volume."""
    from test_readers import dicom_slice

    (tmp_path / "ct").mkdir()
    (tmp_path / "elsewhere").mkdir()
    for k in range(3):
        dicom_slice(tmp_path / "ct" / f"IM{k}", np.full((16, 12), 100 + k), 2.0 * k)
    dicom_slice(tmp_path / "elsewhere" / "IM3", np.full((16, 12), 4000), 6.0)
    (tmp_path / "ct" / "IM3").symlink_to(tmp_path / "elsewhere" / "IM3")
    with open_source(tmp_path / "ct") as src:
        assert src.info.shape == (3, 16, 12) and src.read(0, 3).max() == 102 - 1024


def test_zarr_source_reads_only_its_own_files(tmp_path: Path) -> None:
    """An OME-Zarr naming its dataset `../…` is refused naming the field (zarr raised a bare ValueError); a chunk
    file or an array folder that links out of the store is refused rather than read (an uncompressed chunk linked
    to another file gave that file's bytes as voxels)."""
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret.bin").write_bytes(bytes([77]) * 64)
    other = zarr.create_array(str(outside / "other.zarr"), shape=(4, 4, 4), chunks=(4, 4, 4), dtype="uint8",
                              fill_value=0, zarr_format=3)
    other[:] = 66
    src = tmp_path / "img.zarr"
    g = zarr.open_group(str(src), mode="w", zarr_format=3)
    a = g.create_array("0", shape=(4, 4, 4), chunks=(4, 4, 4), dtype="uint8", fill_value=0, compressors=None)
    a[:] = 1

    def name(path: str) -> None:
        g.attrs["ome"] = {"version": "0.5", "multiscales": [{
            "axes": [{"name": n, "type": "space"} for n in "zyx"],
            "datasets": [{"path": path, "coordinateTransformations": [{"type": "scale", "scale": [1, 1, 1]}]}]}]}

    name("0")
    with open_source(src) as s:
        assert s.read(0, 4).max() == 1
    name("../outside/other.zarr")
    with pytest.raises(SourceError, match=r"datasets\[0\]\.path"):
        open_source(src)
    name("0")
    chunk = src / "0" / "c" / "0" / "0" / "0"
    chunk.unlink()
    chunk.symlink_to(outside / "secret.bin")
    with pytest.raises(SourceError, match="outside the store"):
        open_source(src).read(0, 4)
    (tmp_path / "plain.zarr").symlink_to(outside / "other.zarr", target_is_directory=True)
    (tmp_path / "wrap.zarr").mkdir()
    (tmp_path / "wrap.zarr" / "zarr.json").write_bytes((src / "zarr.json").read_bytes())
    (tmp_path / "wrap.zarr" / "0").symlink_to(outside / "other.zarr", target_is_directory=True)
    with pytest.raises(SourceError, match="outside the store"):
        open_source(tmp_path / "wrap.zarr")


# --- declared quantities bounded from the header ----------------------------------------------------------------

@pytest.mark.parametrize("syntax", [None, "1.2.840.10008.1.2.5"], ids=["native", "rle"])
def test_dicom_declaring_2_31_frames_is_refused_from_its_header(tmp_path: Path, syntax: str | None) -> None:
    """NumberOfFrames = 2^31 - 1 in a file of one frame: the reader looped over every declared frame and grew
    without bound (7.4 GB after 12 minutes); now the frames' declared bytes (uncompressed: Rows x Columns each;
    compressed: an 8-byte fragment header each at least) are compared with the file's size first."""
    multiframe(tmp_path / "f.dcm", 2**31 - 1, syntax)
    out, seconds, rss = cli_ingest(tmp_path / "f.dcm", tmp_path / "f.zarr")
    refused_in_one_line(out, "NumberOfFrames = 2147483647", "f.dcm")
    assert seconds < 30 and rss < 250_000, (seconds, rss)
    nothing_at(tmp_path / "f.zarr")
    multiframe(tmp_path / "ok.dcm", 1, syntax)  # what it does hold reads
    with open_source(tmp_path / "ok.dcm") as src:
        assert src.read(0, 1).ravel().tolist() == list(range(64 * 64))


def nrrd_bytes(fields: str, data: bytes) -> bytes:
    return f"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 4 4 2\n{fields}\n".encode() + data


def test_nrrd_skips_beyond_the_file_are_refused_from_the_header(tmp_path: Path) -> None:
    """`line skip: 10^12` in a 600-byte file spun a worker for days (a readline per line, past the end); `byte
    skip` beyond the data file was refused only as a size mismatch. Skips the file can hold still read."""
    voxels = np.arange(32, dtype=np.uint8)
    cases = {"lines.nrrd": ("encoding: raw\nline skip: 1000000000000\n", bytes(600), "line skip 1000000000000"),
             "bytes.nrrd": ("encoding: raw\nbyte skip: 100000\n", bytes(600), "byte skip 100000"),
             "gzbytes.nrrd": ("encoding: gzip\nbyte skip: 1000000000000\n", gzip.compress(bytes(600)),
                              "byte skip 1000000000000")}
    for name, (fields, data, words) in cases.items():
        (tmp_path / name).write_bytes(nrrd_bytes(fields, data))
        out, seconds, _ = cli_ingest(tmp_path / name, tmp_path / "v.zarr")
        refused_in_one_line(out, words, name)
        assert seconds < 30
        nothing_at(tmp_path / "v.zarr")
    skipped = b"junk line\nanother\n"
    (tmp_path / "ok.nrrd").write_bytes(nrrd_bytes("encoding: raw\nline skip: 2\nbyte skip: 3\n",
                                                  skipped + b"abc" + voxels.tobytes()))
    (tmp_path / "okgz.nrrd").write_bytes(nrrd_bytes("encoding: gzip\nline skip: 2\nbyte skip: 3\n",
                                                    skipped + gzip.compress(b"abc" + voxels.tobytes())))
    for name in ("ok.nrrd", "okgz.nrrd"):
        with open_source(tmp_path / name) as src:
            assert np.array_equal(src.read(0, 2).ravel(), voxels)


def test_a_long_line_before_the_data_is_skipped_in_pieces(tmp_path: Path) -> None:
    """One line skip over a data file of 8 MB without a newline: refused once its end is reached, without reading
    the line into memory whole."""
    (tmp_path / "v.raw").write_bytes(b"x" * (8 << 20))
    (tmp_path / "v.nhdr").write_text("NRRD0004\ntype: uint8\ndimension: 3\nsizes: 4 4 2\nencoding: raw\n"
                                     "line skip: 1\ndata file: v.raw\n\n")
    with pytest.raises(SourceError, match="ends 1 lines short of its line skip"):
        open_source(tmp_path / "v.nhdr")


def test_a_thin_volume_is_refused_from_its_header(tmp_path: Path) -> None:
    """A 121-byte gzip NRRD declaring 1 x 1 x 20000 voxels became a 201 MB store of 15,856 files after a minute
    of work; now its store's files are counted from the header (FILES_FLOOR plus one per VOXELS_PER_FILE voxels)."""
    body = gzip.compress(bytes(20000))
    src = tmp_path / "thin.nrrd"
    src.write_bytes(b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 1 1 20000\nencoding: gzip\n\n" + body)
    assert src.stat().st_size == 121
    out, seconds, rss = cli_ingest(src, tmp_path / "thin.zarr")
    refused_in_one_line(out, "20000x1x1", "files", "nothing was read")
    assert seconds < 30 and rss < 250_000
    nothing_at(tmp_path / "thin.zarr")


def test_store_files_is_an_upper_bound_and_ordinary_shapes_pass(tmp_path: Path) -> None:
    """The estimate holds the files a real ingest writes, and ordinary shapes (a cube, a wide slab, a narrow but
    real stack) stay inside the bound; the padded blocks count against max_voxels."""
    for shape in [(40, 3, 5), (70, 20, 1)]:
        ingest(np.ones(shape, np.uint8), tmp_path / f"{shape[0]}.zarr", progress=False)
        files = sum(1 for p in (tmp_path / f"{shape[0]}.zarr").rglob("*") if p.is_file())
        assert files <= store_files(Layout(shape, 16)), (shape, files)
    for shape in [(512, 512, 512), (2, 8192, 8192), (1000, 16, 16), (2000, 8, 8), (1, 1, 1)]:
        assert store_files(Layout(shape, 16)) <= FILES_FLOOR + math.prod(shape) // 64, shape
    with pytest.raises(SourceError, match=r"in blocks of 16³ \(padded to 2.867e\+04 voxels\).*LODCAST_MAX_VOXELS"):
        ingest(np.ones((100, 1, 1), np.uint8), tmp_path / "p.zarr", max_voxels=10_000)
    nothing_at(tmp_path / "p.zarr")


def one_chunk_zarr(path: Path, shape: tuple[int, int, int], chunks: tuple[int, int, int]) -> None:
    a = zarr.create_array(str(path), shape=shape, chunks=chunks, dtype="uint8", fill_value=0, zarr_format=3)
    a[:] = np.arange(shape[0], dtype=np.uint8)[:, None, None]


def test_a_zarr_chunk_deeper_than_a_slab_is_decoded_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A zarr source in one chunk: every 16-slice slab decoded the whole chunk again (a 1024³ chunk of 56 kB:
    5.5 min, 1.2 GB); now the row of chunks is decoded once and kept while its slabs are read, and what it holds
    counts against the ingest memory limit."""
    one_chunk_zarr(tmp_path / "c.zarr", (64, 32, 32), (64, 32, 32))
    reads: list[str] = []
    get = _OwnFiles.get

    async def counted(self: Any, key: str, *args: Any, **kw: Any) -> Any:
        reads.append(key)
        return await get(self, key, *args, **kw)

    monkeypatch.setattr(_OwnFiles, "get", counted)
    with open_source(tmp_path / "c.zarr") as src:
        assert src.held_bytes >= 64 * 32 * 32
        reads.clear()
        slabs = [src.read(z, z + 16) for z in range(0, 64, 16)]
        assert np.array_equal(np.concatenate(slabs)[:, 0, 0], np.arange(64))
        assert [k for k in reads if "/c/" in k or k.startswith("c/")] == ["c/0/0/0"], reads
    monkeypatch.undo()
    one_chunk_zarr(tmp_path / "big.zarr", (256, 256, 256), (256, 256, 256))
    with pytest.raises(SourceError, match="34 MB of it the reader's: a decoded row of chunks"):
        ingest(tmp_path / "big.zarr", tmp_path / "big.store", max_memory=320_000_000, progress=False)
    nothing_at(tmp_path / "big.store")


def test_a_zarr_chunk_larger_than_its_array_is_refused_from_the_metadata(tmp_path: Path) -> None:
    """An 8³ array in chunks of 4096³ (metadata only, no chunk written): decoding one would allocate 64 GiB."""
    zarr.create_array(str(tmp_path / "c.zarr"), shape=(8, 8, 8), chunks=(4096, 4096, 4096), dtype="uint8",
                      fill_value=0, zarr_format=3)
    with pytest.raises(SourceError, match=r"chunks of 4096x4096x4096 .* larger than the array 8x8x8"):
        open_source(tmp_path / "c.zarr")


# --- a finite world box ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("field, value", [("spacing", (1e308, 1, 1)), ("spacing", (1, 1e-320, 1)),
                                          ("spacing", (1, 1, float("nan"))), ("origin", (1e308, 0, 0)),
                                          ("origin", (0, -1e308, 0)), ("origin", (0, 0, float("nan"))),
                                          ("origin", (1e9, 0, 0))])
def test_spacing_and_origin_must_give_a_finite_world_box(tmp_path: Path, field: str, value: tuple) -> None:
    """Spacing 1e308 or 1e-320, origin ±1e308 or NaN were ingested, and then every `GET /volumes` and render of the
    volume was a 500; now ingest refuses them naming the field, for arrays and files alike. A box a millionth as
    thick as its distance from 0 (origin 1e9, spacing 1e-6) is degenerate in float32 and refused too."""
    a = np.ones((4, 4, 4), np.uint8)
    options: dict[str, Any] = {field: value}
    if value == (1e9, 0, 0):
        options["spacing"] = (1e-6, 1, 1)
    match = "world box along z" if value == (1e9, 0, 0) else field
    with pytest.raises(SourceError, match=match):
        ingest(a, tmp_path / "a.zarr", progress=False, **options)
    nothing_at(tmp_path / "a.zarr")
    spacing = value if field == "spacing" else (1, 1, 1)
    origin = value if field == "origin" else (0, 0, 0)
    header = {"space": "left-posterior-superior", "space directions": np.diag(spacing[::-1]).tolist(),
              "space origin": list(origin[::-1])}
    if value == (1e9, 0, 0):
        header["space directions"] = np.diag([1, 1, 1e-6]).tolist()
    nrrd.write(str(tmp_path / "v.nrrd"), a, header)
    with pytest.raises(SourceError, match=rf"v.nrrd: .*({field}|world box)"):
        ingest(tmp_path / "v.nrrd", tmp_path / "v.zarr", progress=False, orient="source")
    nothing_at(tmp_path / "v.zarr")


def test_spacing_overrides_on_the_command_line_are_bounded(tmp_path: Path) -> None:
    np.save(tmp_path / "v.npy", np.ones((4, 4, 4), np.uint8))
    for args, word in [(["--spacing", "1e-320,1,1"], "spacing"), (["--spacing", "1e308,1,1"], "spacing"),
                       (["--origin", "1e308,0,0"], "origin")]:
        out, _, _ = cli_ingest(tmp_path / "v.npy", tmp_path / "v.zarr", *args)
        refused_in_one_line(out, word, "v.npy")
        nothing_at(tmp_path / "v.zarr")
    out, _, _ = cli_ingest(tmp_path / "v.npy", tmp_path / "v.zarr", "--spacing", "1e-6,2e-6,2e-6", "--units", "m")
    assert out.returncode == 0, out.stderr  # a micrometre voxel in metres is ordinary
