"""Source readers: every format against files written here with the format's own library, every refusal, streaming
memory, and the real volumes in ../shared/data."""
from __future__ import annotations

import json
import random
import tracemalloc
from pathlib import Path
from typing import Any

import nibabel as nib
import nrrd
import numpy as np
import pydicom
import pytest
import tifffile
import zarr
from phantoms import dicom_dataset
from pydicom.dataset import Dataset
from pydicom.uid import CTImageStorage, generate_uid

from lodcast.errors import SourceError, SourceNotFound
from lodcast.store.readers import open_source

RNG = np.random.default_rng(7)


def volume(shape: tuple[int, ...], dtype: str = "uint16") -> np.ndarray:
    """Distinct-enough values that any axis mix-up shows."""
    dt = np.dtype(dtype)
    if dt.kind == "f":
        return RNG.normal(100, 50, shape).astype(dt)
    hi = min(int(np.iinfo(dt).max), 60000)
    return RNG.integers(max(int(np.iinfo(dt).min), -30000), hi, shape, endpoint=True).astype(dt)


def read_all(src, cuts: list[int] | None = None) -> np.ndarray:
    """The whole volume from slabs cut at `cuts` (default: 32-thick, as ingest does)."""
    depth = src.info.shape[0]
    cuts = cuts if cuts is not None else list(range(0, depth, 32))
    edges = sorted(set([0, *cuts, depth]))
    slabs = [src.read(a, b) for a, b in zip(edges[:-1], edges[1:])]
    for (a, b), s in zip(zip(edges[:-1], edges[1:]), slabs):
        assert s.shape == (b - a, *src.info.shape[1:])
        assert s.dtype == src.info.dtype
    return np.concatenate(slabs)


def check(src, expected: np.ndarray) -> None:
    """Exact voxels, in whole-volume reads and in odd slab cuts, including a step back (streams restart)."""
    assert src.info.shape == expected.shape
    assert src.info.dtype == expected.dtype
    np.testing.assert_array_equal(read_all(src), expected)
    depth = expected.shape[0]
    cuts = sorted(random.Random(depth).sample(range(1, depth), min(3, depth - 1))) if depth > 1 else []
    np.testing.assert_array_equal(read_all(src, cuts), expected)
    np.testing.assert_array_equal(src.read(depth - 1, depth), expected[-1:])
    np.testing.assert_array_equal(src.read(0, 1), expected[:1])
    assert src.read(depth, depth).shape == (0, *expected.shape[1:])


def refused(match: str, path, **kw) -> None:
    with pytest.raises(SourceError, match=match):
        open_source(path, **kw).close()


# --- npy, raw ----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("order", ["C", "F"])
def test_npy_values_in_both_orders(tmp_path: Path, order: str) -> None:
    a = np.asarray(volume((37, 9, 11), "int16"), order=order)
    np.save(tmp_path / "v.npy", a)
    with open_source(tmp_path / "v.npy") as src:
        assert src.info.format == "npy" and src.info.spacing == (1.0, 1.0, 1.0) and src.info.origin == (0.0, 0.0, 0.0)
        check(src, np.ascontiguousarray(a))


def test_npy_fortran_windows_smaller_than_the_volume(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import lodcast.store.readers as readers

    monkeypatch.setattr(readers, "WINDOW_BYTES", 5 * 6 * 7 * 4)  # one x-plane at a time
    a = np.asfortranarray(volume((5, 6, 7), "float32"))
    a[2, 3, 4] = np.nan  # NaN is data and is kept
    np.save(tmp_path / "f.npy", a)
    with open_source(tmp_path / "f.npy") as src:
        assert src.info.provenance["order"] == "F"
        got = read_all(src, [1, 3])
        np.testing.assert_array_equal(got, a)
        assert np.isnan(got[2, 3, 4])


def test_npy_2d_is_one_slice_and_4d_needs_index(tmp_path: Path) -> None:
    flat = volume((6, 8), "uint8")
    np.save(tmp_path / "flat.npy", flat)
    with open_source(tmp_path / "flat.npy") as src:
        check(src, flat[None])
    series = volume((3, 4, 5, 6), "uint16")
    np.save(tmp_path / "t.npy", series)
    with open_source(tmp_path / "t.npy", index=2) as src:
        check(src, series[2])
        assert src.info.provenance["index"] == 2
    refused(r"4D .* 3 volumes .* index=0\.\.2", tmp_path / "t.npy")
    refused(r"index 3 is out of range: .* 3 volumes", tmp_path / "t.npy", index=3)
    refused(r"index 1 given but .* not a 4D series", tmp_path / "flat.npy", index=1)
    np.save(tmp_path / "single.npy", series[:1])  # a 4th axis of length 1 is squeezed
    with open_source(tmp_path / "single.npy") as src:
        check(src, series[0])
    np.save(tmp_path / "line.npy", np.zeros(5))
    refused(r"1 dimensions .* expected 3 \(z, y, x\)", tmp_path / "line.npy")


def test_npy_dtypes_converted_only_when_exact(tmp_path: Path) -> None:
    cases = {
        "int64": (np.arange(-60, 60, dtype=np.int64).reshape(2, 6, 10) * 1000, np.int32),
        "uint64": (np.arange(120, dtype=np.uint64).reshape(2, 6, 10) * 2**25, np.uint32),
        "uint64_big": (np.arange(120, dtype=np.uint64).reshape(2, 6, 10) * 2**30, np.float64),
        "int64_big": (np.arange(120, dtype=np.int64).reshape(2, 6, 10) * 2**40, np.float64),
        "float16": (volume((2, 6, 10), "float16"), np.float32),
        "big_endian": (volume((2, 6, 10), "int16").astype(">i2"), np.int16),
    }
    for name, (a, stored) in cases.items():
        np.save(tmp_path / f"{name}.npy", a)
        with open_source(tmp_path / f"{name}.npy") as src:
            assert src.info.dtype == np.dtype(stored), name
            got = read_all(src, [1])
            assert got.dtype == np.dtype(stored)
            np.testing.assert_array_equal(got, a)  # exactly the same numbers
            assert src.info.provenance["dtype"] == str(a.dtype)
    np.save(tmp_path / "huge.npy", np.array([[[2**62, 1]]], dtype=np.int64))
    refused(r"int64 values from 1 to 4611686018427387904, which neither int32 nor float64", tmp_path / "huge.npy")


@pytest.mark.parametrize("array, match", [
    (np.zeros((2, 3, 4), np.complex64), "unsupported dtype complex64"),
    (np.zeros((2, 3, 4), bool), "unsupported dtype bool"),
    (np.full((2, 3, 4), "ab"), "unsupported dtype <U2"),
    (np.zeros((2, 3, 4), object), "unsupported dtype object"),
    (np.zeros((2, 3, 4), [("r", "u1"), ("g", "u1"), ("b", "u1")]), "non-scalar data: .* fields r, g, b"),
    (np.zeros((0, 3, 4), np.uint8), "empty: shape 0x3x4 has an axis of length 0"),
    (np.zeros((3, 3, 0), np.float32), "empty: shape 3x3x0"),
])
def test_npy_refusals(tmp_path: Path, array: np.ndarray, match: str) -> None:
    np.save(tmp_path / "bad.npy", array, allow_pickle=True)
    refused(match, tmp_path / "bad.npy")


@pytest.mark.parametrize("order", ["little", "big"])
def test_raw_byte_order_header_and_overrides(tmp_path: Path, order: str) -> None:
    a = volume((13, 7, 5), "uint16")
    (tmp_path / "v.raw").write_bytes(b"H" * 24 + a.astype("<u2" if order == "little" else ">u2").tobytes())
    with open_source(tmp_path / "v.raw", shape=(13, 7, 5), dtype="uint16", byte_order=order, header_bytes=24,
                     spacing=(2.5, 0.5, 0.25), origin=(-1, 2, 3)) as src:
        assert src.info.spacing == (2.5, 0.5, 0.25) and src.info.origin == (-1.0, 2.0, 3.0)
        assert src.info.dtype == np.uint16 and src.info.dtype.isnative
        check(src, a)


def test_raw_refusals(tmp_path: Path) -> None:
    (tmp_path / "v.raw").write_bytes(bytes(1000))
    refused(r"^raw file is 1000 bytes but shape 10x10x11 of uint8 needs 1100 bytes$", tmp_path / "v.raw",
            shape=(10, 10, 11), dtype="uint8")
    refused(r"raw file is 1000 bytes but shape 10x10x10 of uint8 needs 1016 bytes \(16-byte header",
            tmp_path / "v.raw", shape=(10, 10, 10), dtype="uint8", header_bytes=16)
    refused(r"needs its shape \(z, y, x\) and dtype", tmp_path / "v.raw")
    refused(r"needs its shape", tmp_path / "v.raw", dtype="uint8")
    refused(r"byte_order must be 'little' or 'big', got 'middle'", tmp_path / "v.raw", shape=(10, 10, 10),
            dtype="uint8", byte_order="middle")
    refused("unsupported dtype complex64", tmp_path / "v.raw", shape=(5, 5, 5), dtype="complex64")
    refused("spacing must be three positive numbers", tmp_path / "v.raw", shape=(10, 10, 10), dtype="uint8",
            spacing=(1, 0, 1))
    refused("origin must be three finite numbers", tmp_path / "v.raw", shape=(10, 10, 10), dtype="uint8",
            origin=(1, 2))
    refused("shape, dtype and header_bytes describe raw files only", tmp_path / "v.raw", format="npy", shape=(1, 1, 1))
    (tmp_path / "slice.bin").write_bytes(np.arange(12, dtype="<i4").tobytes())
    with open_source(tmp_path / "slice.bin", shape=(3, 4), dtype="int32") as src:  # one 2D image
        check(src, np.arange(12, dtype=np.int32).reshape(1, 3, 4))
    (tmp_path / "weird.dat").write_bytes(bytes(8))
    with open_source(tmp_path / "weird.dat", shape=(2, 2, 2), dtype="uint8") as src:  # raw options say raw
        assert src.info.format == "raw"


# --- NRRD --------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("encoding", ["gzip", "raw", "bzip2"])
def test_nrrd_encodings_spacing_origin(tmp_path: Path, encoding: str) -> None:
    a = volume((40, 9, 6), "int16")  # (z, y, x)
    header = {"encoding": encoding, "space": "left-posterior-superior",
              "space directions": np.diag([0.5, 0.75, 2.0]), "space origin": np.array([10.0, 20.0, 30.0])}
    nrrd.write(str(tmp_path / "v.nrrd"), a.transpose(2, 1, 0), header)  # pynrrd takes (x, y, z)
    with open_source(tmp_path / "v.nrrd") as src:
        assert src.info.spacing == (2.0, 0.75, 0.5)
        assert src.info.origin == (30.0, 20.0, 10.0)
        assert src.info.provenance["encoding"] == encoding
        check(src, a)


def test_nrrd_detached_spacings_oblique_and_4d(tmp_path: Path) -> None:
    a = volume((5, 4, 3), "float32")
    nrrd.write(str(tmp_path / "d.nhdr"), a.transpose(2, 1, 0), {"encoding": "raw", "spacings": [0.1, 0.2, 0.3]},
               detached_header=True)
    with open_source(tmp_path / "d.nhdr", orient="source") as src:
        assert src.info.spacing == pytest.approx((0.3, 0.2, 0.1))
        check(src, a)
    oblique = np.array([[0.0, 2.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 3.0]])
    nrrd.write(str(tmp_path / "o.nrrd"), a.transpose(2, 1, 0),
               {"space": "RAS", "space directions": oblique, "space origin": np.array([1.0, 2.0, 3.0])})
    with open_source(tmp_path / "o.nrrd", orient="source") as src:
        # the file's axes kept; the origin is the space origin (1, 2, 3) seen along them (rows (0, 1, 0), (-1, 0, 0)…)
        assert src.info.spacing == (3.0, 1.0, 2.0) and src.info.origin == (3.0, -1.0, 2.0)
        assert src.info.provenance["space_directions"] == oblique.tolist()
        check(src, a)
    image = volume((4, 6), "uint16")  # a 2D NRRD is one slice
    nrrd.write(str(tmp_path / "flat.nrrd"), image.T, {"encoding": "gzip", "spacings": [0.5, 0.25]})
    with open_source(tmp_path / "flat.nrrd") as src:
        assert src.info.spacing == (1.0, 0.25, 0.5)
        check(src, image[None])
    series = volume((3, 5, 4, 6), "uint8")  # (t, z, y, x)
    nrrd.write(str(tmp_path / "t.nrrd"), series.transpose(3, 2, 1, 0),
               {"kinds": ["domain", "domain", "domain", "time"], "encoding": "gzip"})
    with open_source(tmp_path / "t.nrrd", index=1, orient="source") as src:
        check(src, series[1])
    refused(r"4D .* 3 volumes .* index=0\.\.2", tmp_path / "t.nrrd")
    rgb = volume((3, 4, 5, 6), "uint8")
    nrrd.write(str(tmp_path / "rgb.nrrd"), rgb, {"kinds": ["RGB-color", "domain", "domain", "domain"]})
    refused(r"non-scalar data: NRRD axis 0 .* 'rgb-color' of size 3", tmp_path / "rgb.nrrd")
    gradients = volume((2, 5, 4, 6), "int16")  # a list axis last: volumes one after another (diffusion MR)
    nrrd.write(str(tmp_path / "dwi.nrrd"), gradients.transpose(3, 2, 1, 0),
               {"kinds": ["space", "space", "space", "list"], "encoding": "raw"})
    with open_source(tmp_path / "dwi.nrrd", index=1, orient="source") as src:
        check(src, gradients[1])


def test_nrrd_truncated_gzip_is_refused_on_read(tmp_path: Path) -> None:
    nrrd.write(str(tmp_path / "v.nrrd"), volume((6, 6, 6), "uint16"), {"encoding": "gzip"})
    data = (tmp_path / "v.nrrd").read_bytes()
    (tmp_path / "v.nrrd").write_bytes(data[: len(data) - 200])
    with open_source(tmp_path / "v.nrrd") as src, pytest.raises(SourceError, match="v.nrrd"):
        src.read(0, 6)


# --- NIfTI -------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["v.nii", "v.nii.gz"])
def test_nifti_axes_spacing_origin(tmp_path: Path, name: str) -> None:
    data = volume((7, 9, 40), "int16")  # (i, j, k)
    affine = np.diag([0.5, 0.75, 2.0, 1.0])
    affine[:3, 3] = [-10, 20, 30]
    nib.save(nib.Nifti1Image(data, affine), tmp_path / name)
    with open_source(tmp_path / name, orient="source") as src:
        assert src.info.spacing == (2.0, 0.75, 0.5)
        assert src.info.origin == (30.0, 20.0, -10.0)
        check(src, data.transpose(2, 1, 0))


def test_nifti_header_numbers_are_the_decimals_written(tmp_path: Path) -> None:
    """A NIfTI header holds float32: 1.2 mm is 1.2000000476837158 as a double. Spacing and origin come out as the
    decimals written (what `lodcast info` prints), turned to LPS or not; a value that is not such a decimal keeps
    float32's precision."""
    affine = np.diag([1.2, 0.7, 0.3, 1.0])
    affine[:3, 3] = [-680.05, -59.2, 1 / 3]
    nib.save(nib.Nifti1Image(volume((5, 6, 7), "uint8"), affine), tmp_path / "d.nii")
    with open_source(tmp_path / "d.nii", orient="source") as src:
        assert src.info.spacing == (0.3, 0.7, 1.2)
        assert src.info.origin == (0.33333334, -59.2, -680.05)  # 0.33333334: the shortest decimal of float32(1/3)
    with open_source(tmp_path / "d.nii") as src:  # LPS: x and y reversed, the origin at their far ends
        assert src.info.spacing == (0.3, 0.7, 1.2)
        assert src.info.origin[0] == 0.33333334
        assert src.info.origin[1:] == (55.7, 675.25)  # exact decimals, no float64 residue of the turn


def test_nifti_scaled_is_float32_of_nibabels_values(tmp_path: Path) -> None:
    data = volume((6, 5, 4), "uint8")
    img = nib.Nifti1Image(data, np.eye(4))
    img.header.set_slope_inter(2.5, -10.0)
    nib.save(img, tmp_path / "s.nii.gz")
    expected = np.asanyarray(nib.load(tmp_path / "s.nii.gz").dataobj).transpose(2, 1, 0).astype(np.float32)
    np.testing.assert_array_equal(expected, (data.transpose(2, 1, 0) * 2.5 - 10).astype(np.float32))
    with open_source(tmp_path / "s.nii.gz", orient="source") as src:
        assert src.info.provenance["scaling"] == {"slope": 2.5, "intercept": -10.0}
        assert src.info.provenance["dtype"] == "uint8"
        check(src, expected)


def test_nifti_oblique_4d_and_refusals(tmp_path: Path) -> None:
    data = volume((4, 5, 6), "float32")
    rotated = np.array([[0, -1, 0, 5], [1, 0, 0, 6], [0, 0, 1, 7], [0, 0, 0, 1]], float)
    nib.save(nib.Nifti1Image(data, rotated), tmp_path / "o.nii")
    with open_source(tmp_path / "o.nii", orient="source") as src:
        assert src.info.origin == (7.0, -5.0, 6.0)  # (5, 6, 7) seen along i = (0, 1, 0), j = (-1, 0, 0), k
        assert src.info.provenance["affine"] == rotated.tolist()
        check(src, data.transpose(2, 1, 0))
    series = volume((4, 5, 6, 3), "uint16")
    nib.save(nib.Nifti1Image(series, np.eye(4)), tmp_path / "t.nii.gz")
    with open_source(tmp_path / "t.nii.gz", index=2, orient="source") as src:
        check(src, series[..., 2].transpose(2, 1, 0))
    refused(r"4D .* 3 volumes .* index=0\.\.2", tmp_path / "t.nii.gz")
    refused(r"index 5 is out of range", tmp_path / "t.nii.gz", index=5)
    nib.save(nib.Nifti1Image(series[..., :1], np.eye(4)), tmp_path / "one.nii")  # 4th axis of length 1
    with open_source(tmp_path / "one.nii", orient="source") as src:
        check(src, series[..., 0].transpose(2, 1, 0))
    flat = volume((6, 5), "int16")
    nib.save(nib.Nifti1Image(flat, np.eye(4)), tmp_path / "flat.nii")
    with open_source(tmp_path / "flat.nii", orient="source") as src:
        check(src, flat.T[None])
    displacement = nib.Nifti1Image(volume((4, 5, 6, 3), "float32"), np.eye(4))
    displacement.header.set_intent("vector")
    nib.save(displacement, tmp_path / "disp.nii")
    refused(r"non-scalar data: .* 4D with intent 'vector'", tmp_path / "disp.nii", index=0)
    vectors = nib.Nifti1Image(volume((4, 5, 6, 1, 3), "float32"), np.eye(4))
    vectors.header.set_intent("vector")
    nib.save(vectors, tmp_path / "vec.nii")
    refused(r"5 dimensions .* intent vector.*expected a scalar 3D volume", tmp_path / "vec.nii")
    nib.save(nib.Nifti1Image(np.zeros((2, 3, 4), np.complex64), np.eye(4)), tmp_path / "c.nii")
    refused("unsupported dtype complex64", tmp_path / "c.nii")
    (tmp_path / "junk.nii").write_bytes(b"not a nifti file at all" * 20)
    refused("not a readable NIfTI file", tmp_path / "junk.nii")


# --- TIFF --------------------------------------------------------------------------------------------------------

def test_a_tiff_folder_of_two_series_or_of_links_says_so(tmp_path: Path) -> None:
    """Two name patterns in one folder (a reconstruction beside its projections, say) are refused naming both,
    not stacked into one volume; TIFFs that are symbolic links to files elsewhere are skipped, and the error or
    the warning says so and why."""
    import tifffile

    two = tmp_path / "two"
    two.mkdir()
    for z in range(3):
        tifffile.imwrite(two / f"recon_{z:03d}.tif", np.full((4, 5), z, np.uint8))
        tifffile.imwrite(two / f"proj{z}.tif", np.full((4, 5), z, np.uint8))
    tifffile.imwrite(two / "recon_003.tif", np.zeros((4, 5), np.uint8))
    refused(r"2 name patterns, 'recon_#\.tif' \(4 files, e\.g\. recon_000\.tif\), 'proj#\.tif' \(3 files", two)
    elsewhere, links = tmp_path / "elsewhere", tmp_path / "links"
    elsewhere.mkdir()
    links.mkdir()
    for z in range(3):
        tifffile.imwrite(elsewhere / f"s{z}.tif", np.full((4, 5), z, np.uint8))
        (links / f"s{z}.tif").symlink_to(elsewhere / f"s{z}.tif")
    refused(r"no \.tif/\.tiff files in folder .*links; 3 \.tif/\.tiff files are symbolic links to files outside", links)
    tifffile.imwrite(links / "s3.tif", np.full((4, 5), 3, np.uint8))  # one of its own
    with open_source(links) as src:
        assert src.info.shape == (1, 4, 5)
        assert any("3 .tif/.tiff files are symbolic links" in w for w in src.info.provenance["warnings"])


def test_tiff_multipage_imagej_and_folder(tmp_path: Path) -> None:
    a = volume((9, 6, 7), "uint16")
    tifffile.imwrite(tmp_path / "plain.tif", a)
    with open_source(tmp_path / "plain.tif") as src:
        assert src.info.spacing == (1.0, 1.0, 1.0)
        check(src, a)
    tifffile.imwrite(tmp_path / "ij.tif", a, imagej=True, resolution=(1 / 0.5, 1 / 0.25),
                     metadata={"spacing": 2.0, "unit": "um", "axes": "ZYX"})
    with open_source(tmp_path / "ij.tif") as src:
        assert src.info.spacing == (2.0, 0.25, 0.5) and src.info.units == "micrometer"
        check(src, a)
    folder = tmp_path / "stack"
    folder.mkdir()
    for z in random.Random(1).sample(range(9), 9):  # written out of order; natural order puts s2 before s10
        tifffile.imwrite(folder / f"s{z + 1}.tif", a[z])
    with open_source(folder) as src:
        assert src.info.format == "tiff"
        check(src, a)


def test_ome_tiff_physical_sizes_and_units(tmp_path: Path) -> None:
    """OME-TIFF's PhysicalSize{X,Y,Z} (µm unless said) become the spacing: an OME-TIFF at 0.2/0.2/1.5 µm used
    to ingest as 1/1/1 mm. A TIFF without any size says so, and --spacing/--units override."""
    import tifffile

    data = volume((6, 8, 10))
    tifffile.imwrite(tmp_path / "cells.ome.tif", data, ome=True,
                     metadata={"axes": "ZYX", "PhysicalSizeX": 0.2, "PhysicalSizeY": 0.2, "PhysicalSizeZ": 1.5})
    with open_source(tmp_path / "cells.ome.tif") as src:
        assert src.info.spacing == pytest.approx((1.5, 0.2, 0.2)) and src.info.units == "micrometer"
        assert "warnings" not in src.info.provenance
        check(src, data)
    tifffile.imwrite(tmp_path / "nm.ome.tif", data, ome=True,
                     metadata={"axes": "ZYX", "PhysicalSizeX": 50, "PhysicalSizeXUnit": "nm", "PhysicalSizeY": 50,
                               "PhysicalSizeYUnit": "nm"})
    with open_source(tmp_path / "nm.ome.tif") as src:
        assert src.info.spacing == pytest.approx((1.0, 50.0, 50.0)) and src.info.units == "nanometer"
        assert any("no PhysicalSize for z" in w for w in src.info.provenance["warnings"])
    tifffile.imwrite(tmp_path / "plain.tif", data, photometric="minisblack")
    with open_source(tmp_path / "plain.tif") as src:
        assert src.info.spacing == (1.0, 1.0, 1.0) and any("no voxel size" in w for w in src.info.provenance["warnings"])
    with open_source(tmp_path / "plain.tif", spacing=(2, 0.5, 0.5), units="um") as src:
        assert src.info.spacing == (2.0, 0.5, 0.5) and src.info.units == "micrometer"
        assert "warnings" not in src.info.provenance  # the user said what the file did not
    refused("units 'parsec'", tmp_path / "plain.tif", units="parsec")


def test_tiff_hyperstack_and_refusals(tmp_path: Path) -> None:
    tzyx = volume((3, 5, 6, 7), "uint8")
    tifffile.imwrite(tmp_path / "h.tif", tzyx, imagej=True, metadata={"axes": "TZYX"})
    with open_source(tmp_path / "h.tif", index=1) as src:
        check(src, tzyx[1])
    refused(r"4D .* 3 volumes", tmp_path / "h.tif")
    tifffile.imwrite(tmp_path / "rgb.tif", np.zeros((4, 6, 7, 3), np.uint8), photometric="rgb")
    refused(r"non-scalar data: .*rgb.tif is RGB with 3 samples per pixel", tmp_path / "rgb.tif")
    truncated = volume((3, 5, 6, 7), "uint16")  # ImageJ files may index only their first page
    tifffile.imwrite(tmp_path / "tr.tif", truncated, imagej=True, truncate=True, metadata={"axes": "TZYX"})
    with tifffile.TiffFile(tmp_path / "tr.tif") as tif:
        assert len(tif.pages) == 1
    with open_source(tmp_path / "tr.tif", index=2) as src:
        check(src, truncated[2])
    zcyx = volume((5, 2, 6, 7), "int16")  # channels inside z: index picks the channel
    tifffile.imwrite(tmp_path / "zc.tif", zcyx, imagej=True, metadata={"axes": "ZCYX"})
    with open_source(tmp_path / "zc.tif", index=1) as src:
        check(src, zcyx[:, 1])
    single = volume((6, 7), "float32")
    tifffile.imwrite(tmp_path / "single.tif", single)
    with open_source(tmp_path / "single.tif") as src:
        check(src, single[None])
    folder = tmp_path / "mixed"
    folder.mkdir()
    tifffile.imwrite(folder / "a1.tif", np.zeros((6, 7), np.uint16))
    tifffile.imwrite(folder / "a2.tif", np.zeros((6, 8), np.uint16))
    refused(r"inconsistent images: a1.tif is 6x7 uint16 but a2.tif is 6x8 uint16", folder)


# --- DICOM -------------------------------------------------------------------------------------------------------

#: JPEG lossless transfer syntaxes (process 14) and the predictor each is written with: SV1 (first-order
#: prediction, the one most scanners write) and the general one with another predictor
JPEG_LOSSLESS = {"1.2.840.10008.1.2.4.70": 1, "1.2.840.10008.1.2.4.57": 6}


def dicom_slice(path: Path, pixels: np.ndarray, z: float, series: str = "1.2.826.0.1.1", slope: float = 1.0,
                intercept: float = -1024.0, samples: int = 1, syntax: str | None = None,
                orientation=(1, 0, 0, 0, 1, 0), position=None, bits: int = 12) -> None:
    ds = dicom_dataset(CTImageStorage)
    ds.SeriesInstanceUID, ds.StudyInstanceUID = series, "1.2.826.0.1.2"
    ds.Rows, ds.Columns = pixels.shape[:2]
    ds.SamplesPerPixel = samples
    ds.PhotometricInterpretation = "MONOCHROME2" if samples == 1 else "RGB"
    if samples > 1:
        ds.PlanarConfiguration = 0
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, bits, bits - 1, 0
    ds.PixelSpacing, ds.SliceThickness = [0.5, 0.25], 2.0
    ds.ImagePositionPatient = list(position) if position is not None else [-10.0, -20.0, z]
    ds.ImageOrientationPatient = list(orientation)
    ds.RescaleSlope, ds.RescaleIntercept = slope, intercept
    ds.PixelData = pixels.astype(np.uint16).tobytes()
    if syntax in JPEG_LOSSLESS:  # pydicom has no JPEG lossless encoder: libjpeg-turbo's, through imagecodecs
        import imagecodecs
        from pydicom.encaps import encapsulate

        frame = imagecodecs.jpeg8_encode(pixels.astype(np.uint16), lossless=True, predictor=JPEG_LOSSLESS[syntax],
                                         bitspersample=12)
        assert frame.find(b"\xff\xc3") > 0  # SOF3: the lossless process, not a DCT one
        ds.PixelData = encapsulate([frame])
        ds["PixelData"].VR = "OB"
        ds.file_meta.TransferSyntaxUID = syntax
    elif syntax is not None:  # compressed by pydicom's own encoders and its plugins (pyjpegls, pylibjpeg-openjpeg)
        ds.compress(syntax)
    ds.save_as(path, enforce_file_format=True)


def ct_series(folder: Path, depth: int = 6, *, slope: float = 1.0, intercept: float = -1024.0, step: float = 2.0,
              series: str = "1.2.826.0.1.1", prefix: str = "IM") -> np.ndarray:
    """Slices at descending positions under shuffled names; returns the stored pixels in ascending position."""
    folder.mkdir(exist_ok=True)
    stored = RNG.integers(0, 4096, (depth, 16, 12)).astype(np.uint16)
    names = random.Random(depth).sample(range(100, 100 + depth), depth)
    for k in range(depth):
        dicom_slice(folder / f"{prefix}{names[k]}", stored[k], 50.0 - step * (depth - 1 - k), series,
                    slope, intercept)
    return stored


def test_dicom_series_sorted_and_rescaled_to_int16(tmp_path: Path) -> None:
    stored = ct_series(tmp_path / "ct", 7)
    (tmp_path / "ct" / "README.txt").write_text("not DICOM, ignored")
    with open_source(tmp_path / "ct") as src:
        assert src.info.format == "dicom"
        assert src.info.dtype == np.int16
        assert src.info.spacing == pytest.approx((2.0, 0.5, 0.25))
        assert src.info.origin == pytest.approx((50.0 - 2.0 * 6, -20.0, -10.0))
        assert src.info.provenance["scaling"] == {"slope": [1.0], "intercept": [-1024.0]}
        assert any("not DICOM and were skipped (e.g. README.txt)" in w for w in src.info.provenance["warnings"])
        check(src, stored.astype(np.int16) - 1024)


@pytest.mark.parametrize("syntax", ["1.2.840.10008.1.2.5", "1.2.840.10008.1.2.4.80", "1.2.840.10008.1.2.4.90",
                                    *JPEG_LOSSLESS],
                         ids=["rle", "jpeg-ls", "jpeg2000", "jpeg-lossless-sv1", "jpeg-lossless-p6"])
def test_compressed_dicom_series(tmp_path: Path, syntax: str) -> None:
    """RLE, JPEG-LS and JPEG 2000 (lossless) series written by pydicom with its encoders, and JPEG lossless ones
    (process 14) by libjpeg-turbo, read back exactly."""
    stored = RNG.integers(0, 4096, (5, 64, 48)).astype(np.uint16)  # openjpeg needs more than 16 x 12 pixels
    (tmp_path / "ct").mkdir()
    for k in range(5):
        dicom_slice(tmp_path / "ct" / f"IM{k}", stored[k], 2.0 * k, syntax=syntax)
    with open_source(tmp_path / "ct") as src:
        assert src.info.dtype == np.int16
        check(src, stored.astype(np.int16) - 1024)


def enhanced_ct(path: Path, frames: np.ndarray, z: list[float], syntax: str | None = None, bits: int = 12) -> None:
    """An Enhanced CT Image Storage file: the frames' positions in per-frame functional groups, spacing,
    orientation and rescaling in the shared group."""
    from pydicom.sequence import Sequence
    from pydicom.uid import EnhancedCTImageStorage

    ds = dicom_dataset(EnhancedCTImageStorage)
    ds.SeriesInstanceUID, ds.StudyInstanceUID = generate_uid(), generate_uid()
    ds.NumberOfFrames, (ds.Rows, ds.Columns) = len(frames), frames.shape[1:]
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, bits, bits - 1, 0

    def item(**kw: Any) -> Dataset:
        d = Dataset()
        for k, v in kw.items():
            setattr(d, k, v)
        return d

    shared = item(PixelMeasuresSequence=Sequence([item(PixelSpacing=[0.5, 0.25], SliceThickness=2.0)]),
                  PlaneOrientationSequence=Sequence([item(ImageOrientationPatient=[1, 0, 0, 0, 1, 0])]),
                  PixelValueTransformationSequence=Sequence([item(RescaleSlope=1, RescaleIntercept=-1024,
                                                                  RescaleType="HU")]))
    ds.SharedFunctionalGroupsSequence = Sequence([shared])
    ds.PerFrameFunctionalGroupsSequence = Sequence(
        [item(PlanePositionSequence=Sequence([item(ImagePositionPatient=[-10.0, -20.0, zk])])) for zk in z])
    ds.PixelData = frames.astype(np.uint16).tobytes()
    if syntax is not None:
        ds.compress(syntax)
    ds.save_as(path, enforce_file_format=True)


@pytest.mark.parametrize("syntax", [None, "1.2.840.10008.1.2.5"], ids=["native", "rle"])
def test_enhanced_multiframe_dicom(tmp_path: Path, syntax: str | None) -> None:
    """One multi-frame file whose frames lie in shuffled positions: sorted along the normal, spacing and origin
    from the functional groups, rescaled to Hounsfield units; alone in a folder it reads the same."""
    frames = RNG.integers(0, 4096, (6, 20, 16)).astype(np.uint16)
    z = [8.0, 0.0, 4.0, 2.0, 10.0, 6.0]
    (tmp_path / "mf").mkdir()
    enhanced_ct(tmp_path / "mf" / "ct.dcm", frames, z, syntax)
    want = frames[np.argsort(z)].astype(np.int16) - 1024
    for where in (tmp_path / "mf" / "ct.dcm", tmp_path / "mf"):
        with open_source(where) as src:
            assert src.info.format == "dicom" and src.info.dtype == np.int16 and src.info.shape == (6, 20, 16)
            assert src.info.spacing == pytest.approx((2.0, 0.5, 0.25))
            assert src.info.origin == pytest.approx((0.0, -20.0, -10.0))
            assert src.info.provenance["frames"] == 6
            check(src, want)


def test_dicom_float_rescale_several_series_and_uneven_spacing(tmp_path: Path) -> None:
    stored = ct_series(tmp_path / "pet", 4, slope=0.5, intercept=1.25)
    ct_series(tmp_path / "pet", 2, series="1.2.826.0.1.9", prefix="other")  # a smaller second series in the same folder
    with open_source(tmp_path / "pet") as src:
        assert src.info.dtype == np.float32
        assert src.info.provenance["series_uid"] == "1.2.826.0.1.1"
        assert src.info.provenance["other_series"] == {"1.2.826.0.1.9": 2}
        check(src, (stored * 0.5 + 1.25).astype(np.float32))
    uneven = tmp_path / "uneven"
    uneven.mkdir()
    for k, z in enumerate([0.0, 1.0, 2.0, 4.0]):
        dicom_slice(uneven / f"{k}.dcm", np.full((4, 4), k), z)
    with open_source(uneven) as src:
        assert src.info.spacing[0] == 2.0  # SliceThickness, with a warning
        assert "not evenly spaced" in src.info.provenance["warnings"][0]
        np.testing.assert_array_equal(read_all(src)[:, 0, 0], [-1024, -1023, -1022, -1021])


@pytest.mark.parametrize("signed", [False, True])
@pytest.mark.parametrize("syntax", ["1.2.840.10008.1.2", "1.2.840.10008.1.2.1"])
def test_dicom_pixels_read_directly_match_pydicom(tmp_path: Path, signed: bool, syntax: str) -> None:
    """Uncompressed pixels are read from the file at their offset: with junk in the unused high bits, 12-bit
    signed and unsigned data must come out exactly as pydicom decodes them (masked, sign from bit 11), with
    rescaling off so that nothing hides a difference."""
    raw = RNG.integers(0, 65536, (3, 70, 9)).astype(np.uint16)  # 630 pixels: above and below the defer size
    for k in range(3):
        path = tmp_path / f"{k}.dcm"
        dicom_slice(path, raw[k], float(k), intercept=0.0)
        ds = pydicom.dcmread(path)
        ds.PixelRepresentation = int(signed)
        ds.file_meta.TransferSyntaxUID = syntax
        ds.save_as(path, implicit_vr=syntax == "1.2.840.10008.1.2", little_endian=True)
    expected = np.stack([pydicom.dcmread(tmp_path / f"{k}.dcm").pixel_array for k in range(3)])
    assert expected.dtype == (np.int16 if signed else np.uint16)
    assert (expected.astype(np.int64) != raw.astype(np.int64)).any()  # the high bits did change something
    with open_source(tmp_path) as src:
        assert all(layout is not None for layout in src._native_layout)  # the direct path is the one tested
        check(src, expected)


@pytest.mark.filterwarnings("ignore:Invalid value for VR UI")
def test_dicom_refusals(tmp_path: Path) -> None:
    def pair(name: str, first: tuple, second: tuple) -> Path:
        folder = tmp_path / name
        folder.mkdir()
        dicom_slice(folder / "a.dcm", *first)
        dicom_slice(folder / "b.dcm", *second)
        return folder

    sizes = pair("sizes", (np.zeros((8, 8)), 0.0), (np.zeros((8, 6)), 1.0))
    refused(r"inconsistent images: a.dcm is 8x8 of 16 bits but b.dcm is 8x6", sizes)
    corrupt = tmp_path / "corrupt"
    corrupt.mkdir()
    dicom_slice(corrupt / "a.dcm", np.zeros((8, 8)), 0.0)
    (corrupt / "b.dcm").write_bytes(bytes(128) + b"DICM" + b"\x02\x00\x10\x00UI\xff\x7fgarbage")
    refused(r"unreadable DICOM file .*b.dcm", corrupt, format="dicom")
    truncated = tmp_path / "truncated"
    truncated.mkdir()
    dicom_slice(truncated / "a.dcm", np.zeros((64, 64)), 0.0)
    data = (truncated / "a.dcm").read_bytes()
    (truncated / "a.dcm").write_bytes(data[: len(data) // 2])
    refused(r"DICOM file .*a.dcm is truncated: \d+ bytes, but its 64x64 pixels of 16 bits need 8192", truncated)
    (truncated / "a.dcm").write_bytes(data[:-100])  # passes the size check, fails when decoded
    with open_source(truncated) as src, pytest.raises(SourceError, match=r"cannot decode the pixels of DICOM file"):
        src.read(0, 1)
    rgb = tmp_path / "rgb"
    rgb.mkdir()
    dicom_slice(rgb / "a.dcm", np.zeros((4, 4, 3)), 0.0, samples=3)
    refused(r"non-scalar data: DICOM file .* RGB with 3 samples per pixel", rgb)
    twins = pair("twins", (np.zeros((4, 4)), 3.0), (np.zeros((4, 4)), 3.0))
    refused(r"two slices at position 3 mm \(a.dcm, b.dcm\)", twins)
    single = tmp_path / "one.dcm"
    dicom_slice(single, np.arange(20).reshape(4, 5), 7.0, intercept=0.0)
    with open_source(single) as src:  # one file is a one-slice series
        assert src.info.spacing == (2.0, 0.5, 0.25) and src.info.origin == (7.0, -20.0, -10.0)
        check(src, np.arange(20, dtype=np.uint16).reshape(1, 4, 5))
    none = tmp_path / "none"
    none.mkdir()
    (none / "x.dcm").write_text("hello")
    refused(r"no DICOM files \(with a DICM preamble\)", none, format="dicom")


# --- zarr --------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("zarr_format", [2, 3])
def test_zarr_plain_array(tmp_path: Path, zarr_format: int) -> None:
    a = volume((33, 6, 5), "float32")
    z = zarr.create_array(tmp_path / "a.zarr", shape=a.shape, dtype=a.dtype, chunks=(8, 6, 5), zarr_format=zarr_format)
    z[:] = a
    with open_source(tmp_path / "a.zarr") as src:
        assert src.info.format == "zarr"
        check(src, a)


def ome_group(path: Path, version: str, data: np.ndarray, axes: str) -> None:
    zarr_format = 2 if version == "0.4" else 3
    g = zarr.open_group(path, mode="w", zarr_format=zarr_format)
    g.create_array("s0", shape=data.shape, dtype=data.dtype, chunks=data.shape)[:] = data
    g.create_array("s1", shape=(1,) * data.ndim, dtype=data.dtype)  # a coarser level, never read
    n = len(axes)
    spatial_scale, spatial_shift = [4.0, 0.5, 0.25], [-1.0, 2.0, 3.0]
    multiscales = [{
        "axes": [{"name": a, "type": {"t": "time", "c": "channel"}.get(a, "space"),
                  **({"unit": "micrometer"} if a in "zyx" else {})} for a in axes],
        "datasets": [{"path": "s0", "coordinateTransformations": [
            {"type": "scale", "scale": [1.0] * (n - 3) + spatial_scale},
            {"type": "translation", "translation": [0.0] * (n - 3) + spatial_shift}]},
            {"path": "s1", "coordinateTransformations": [{"type": "scale", "scale": [1.0] * n}]}],
    }]
    if version == "0.4":
        multiscales[0]["version"] = "0.4"
        g.attrs["multiscales"] = multiscales
    else:
        g.attrs["ome"] = {"version": "0.5", "multiscales": multiscales}


@pytest.mark.parametrize("version", ["0.4", "0.5"])
def test_ome_zarr_scale_translation_and_singletons(tmp_path: Path, version: str) -> None:
    a = volume((1, 1, 10, 6, 5), "uint16")
    ome_group(tmp_path / "i.zarr", version, a, "tczyx")
    with open_source(tmp_path / "i.zarr") as src:
        assert src.info.spacing == (4.0, 0.5, 0.25) and src.info.origin == (-1.0, 2.0, 3.0)
        assert src.info.units == "micrometer"
        check(src, a[0, 0])
    channels = volume((2, 10, 6, 5), "int8")
    ome_group(tmp_path / "c.zarr", version, channels, "czyx")
    with open_source(tmp_path / "c.zarr", index=1) as src:
        check(src, channels[1])
    refused(r"4D .* 2 volumes .* index=0\.\.1", tmp_path / "c.zarr")
    ome_group(tmp_path / "tc.zarr", version, volume((2, 2, 3, 4, 5), "uint8"), "tczyx")
    refused(r"at most one non-singleton t or c axis", tmp_path / "tc.zarr")


def test_zarr_refusals_and_2d(tmp_path: Path) -> None:
    zarr.open_group(tmp_path / "g.zarr", mode="w")
    refused(r"no OME-Zarr 'multiscales' metadata", tmp_path / "g.zarr")
    zarr.create_array(tmp_path / "s.zarr", shape=(2, 3, 4), dtype=str)
    refused(r"unsupported dtype StringDType\(\) in .*s.zarr; expected one of uint8", tmp_path / "s.zarr")
    zarr.create_array(tmp_path / "five.zarr", shape=(1, 2, 3, 4, 5), dtype="uint8")
    refused(r"5 dimensions \(shape 1x2x3x4x5\); expected 3", tmp_path / "five.zarr")
    flat = volume((6, 5), "uint16")
    zarr.create_array(tmp_path / "flat.zarr", shape=flat.shape, dtype=flat.dtype)[:] = flat
    with open_source(tmp_path / "flat.zarr") as src:
        check(src, flat[None])


def test_lodcast_store_reads_back(tmp_path: Path) -> None:
    from lodcast.store.ingest import ingest

    a = volume((35, 20, 9), "int16")
    ingest(a, tmp_path / "s.zarr", spacing=(2.0, 1.0, 0.5), origin=(1.0, 2.0, 3.0), progress=False)
    with open_source(tmp_path / "s.zarr") as src:
        assert src.info.spacing == (2.0, 1.0, 0.5) and src.info.origin == (1.0, 2.0, 3.0)
        check(src, a)


# --- format guessing, missing files ----------------------------------------------------------------------------

def test_format_guessing_by_extension_and_content(tmp_path: Path) -> None:
    a = volume((3, 4, 5), "uint8")
    np.save(tmp_path / "v.npy", a)
    (tmp_path / "v.npy").rename(tmp_path / "v.data")  # no known extension: the magic says npy
    nrrd.write(str(tmp_path / "v.nhdr"), a.T, {"encoding": "raw"}, detached_header=True)
    nib.save(nib.Nifti1Image(a.T, np.eye(4)), tmp_path / "v.nii")
    tifffile.imwrite(tmp_path / "v.tiff", a, photometric="minisblack")
    tifffile.imwrite(tmp_path / "tiff.blob", a, photometric="minisblack")
    dicom_slice(tmp_path / "slice.ima", np.zeros((4, 5)), 0.0)
    for name, fmt in [("v.data", "npy"), ("v.nhdr", "nrrd"), ("v.nii", "nifti"), ("v.tiff", "tiff"), ("tiff.blob", "tiff"),
                      ("slice.ima", "dicom")]:
        with open_source(tmp_path / name) as src:
            assert src.info.format == fmt, name
            assert src.info.shape == ((1, 4, 5) if fmt == "dicom" else (3, 4, 5))
    (tmp_path / "mystery.xyz").write_bytes(bytes(64))
    refused(r"unknown format of .*mystery.xyz: expected \.npy", tmp_path / "mystery.xyz")
    refused(r"unknown format 'vtk'; expected one of npy, raw, nrrd, nifti, tiff, dicom, zarr", tmp_path / "v.tiff",
            format="vtk")
    empty = tmp_path / "empty"
    empty.mkdir()
    refused(r"cannot tell the format of folder", empty)
    refused(r"a nifti source must be a file", empty, format="nifti")
    with pytest.raises(SourceNotFound, match=r"source not found: .*nope.nii"):
        open_source(tmp_path / "nope.nii")


def test_reads_outside_the_volume_are_refused(tmp_path: Path) -> None:
    np.save(tmp_path / "v.npy", np.zeros((4, 2, 2), np.uint8))
    with open_source(tmp_path / "v.npy") as src:
        with pytest.raises(SourceError, match=r"slab z 3:5 is outside the volume's z range 0:4"):
            src.read(3, 5)
        with pytest.raises(SourceError, match=r"slab z 2:1 is outside"):
            src.read(2, 1)


def test_zero_spacing_in_a_header_becomes_one(tmp_path: Path) -> None:
    nrrd.write(str(tmp_path / "z.nrrd"), volume((5, 4, 3), "uint8"), {"spacings": [0.0, 2.0, 3.0]})
    with open_source(tmp_path / "z.nrrd") as src:
        assert src.info.spacing == (3.0, 2.0, 1.0)
        assert "not positive" in src.info.provenance["warnings"][0]
    with open_source(tmp_path / "z.nrrd", spacing=(1, 1, 0.5)) as src:  # the user's spacing wins, silently
        assert src.info.spacing == (1.0, 1.0, 0.5) and "warnings" not in src.info.provenance


def test_provenance_is_json(tmp_path: Path) -> None:
    ct_series(tmp_path / "ct", 3, slope=2.0, intercept=-1000.0)
    nib.save(nib.Nifti1Image(volume((3, 4, 5), "uint8"), np.eye(4)), tmp_path / "v.nii.gz")
    for path in (tmp_path / "ct", tmp_path / "v.nii.gz"):
        with open_source(path) as src:
            assert json.loads(json.dumps(src.info.provenance)) == src.info.provenance


# --- memory ------------------------------------------------------------------------------------------------------

def write_tall(kind: str, path: Path, a: np.ndarray) -> dict:
    if kind == "npy":
        np.save(path, a)
    elif kind == "raw":
        a.tofile(path)
        return {"shape": a.shape, "dtype": a.dtype.name}
    elif kind == "nii.gz":
        nib.save(nib.Nifti1Image(a.transpose(2, 1, 0), np.eye(4)), path)
    elif kind == "nrrd-gzip":
        nrrd.write(str(path), a.transpose(2, 1, 0), {"encoding": "gzip", "space directions": np.eye(3)})
    elif kind == "dicom":
        path.mkdir()
        for z in range(a.shape[0]):
            dicom_slice(path / f"{z}.dcm", a[z], float(z), intercept=0.0)
    return {}


def peak_reading(path: Path, options: dict) -> tuple[int, int, int]:
    """tracemalloc's peak while reading the volume in 32-slice slabs, as ingest does; a checksum; a slab's bytes."""
    with open_source(path, **options) as src:
        depth, total = src.info.shape[0], 0
        src.read(0, 32)  # imports and caches that a first read brings are not the reader's working set
        tracemalloc.start()
        try:
            for z in range(0, depth, 32):
                total += int(src.read(z, min(z + 32, depth)).sum(dtype=np.int64))
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        return peak, total, 32 * src.info.shape[1] * src.info.shape[2] * src.info.dtype.itemsize


@pytest.mark.parametrize("kind, suffix, depths", [("npy", ".npy", (128, 512)), ("raw", ".raw", (128, 512)),
                                                  ("nii.gz", ".nii.gz", (128, 512)), ("nrrd-gzip", ".nrrd", (128, 512)),
                                                  ("dicom", "", (64, 256))])  # one file per slice: fewer
def test_streaming_memory_does_not_grow_with_depth(tmp_path: Path, kind: str, suffix: str, depths: tuple) -> None:
    peaks = []
    for depth in depths:
        a = (np.arange(depth * 128 * 128, dtype=np.uint32) % 251).astype(np.uint8).reshape(depth, 128, 128)
        path = tmp_path / f"tall{depth}{suffix}"
        peak, total, slab = peak_reading(path, write_tall(kind, path, a))
        assert total == int(a.sum(dtype=np.int64))
        assert peak < 2 * slab, f"{kind}: peak {peak} bytes for slabs of {slab} (volume {a.nbytes})"
        peaks.append(peak)
    assert peaks[1] < peaks[0] + slab // 4, f"{kind}: peak grew from {peaks[0]} to {peaks[1]} bytes with depth"


# --- real volumes ----------------------------------------------------------------------------------------------

@pytest.mark.shared_data
def test_real_engine_nifti_is_the_transposed_data(shared_data: Path) -> None:
    p = shared_data / "engine.nii.gz"
    with open_source(p, orient="source") as src:
        assert src.info.shape == (128, 256, 256) and src.info.dtype == np.uint8
        np.testing.assert_array_equal(read_all(src), np.transpose(np.asanyarray(nib.load(p).dataobj), (2, 1, 0)))
    img = nib.load(p)  # by default turned to LPS, as nibabel turns it
    ornt = nib.orientations.ornt_transform(nib.orientations.io_orientation(img.affine),
                                           nib.orientations.axcodes2ornt(("L", "P", "S")))
    with open_source(p) as src:
        np.testing.assert_array_equal(read_all(src), np.transpose(
            nib.orientations.apply_orientation(np.asanyarray(img.dataobj), ornt), (2, 1, 0)))


@pytest.mark.shared_data
def test_real_mr_head_nifti_is_scaled_float(shared_data: Path) -> None:
    p = shared_data / "mr_head.nii.gz"
    with open_source(p, orient="source") as src:
        assert src.info.shape == (160, 232, 160) and src.info.dtype == np.float32
        assert src.info.spacing == pytest.approx((0.898437, 0.898437, 1.0), rel=1e-5)
        assert src.info.provenance["scaling"]["slope"] == pytest.approx(2.007843, rel=1e-6)
        expected = np.transpose(np.asanyarray(nib.load(p).dataobj), (2, 1, 0)).astype(np.float32)
        np.testing.assert_array_equal(read_all(src), expected)


@pytest.mark.shared_data
def test_real_flair_nrrd_oblique(shared_data: Path) -> None:
    p = shared_data / "flair.nrrd"
    data, header = nrrd.read(str(p))
    with open_source(p, orient="source") as src:
        assert src.info.shape == (140, 160, 124) and src.info.dtype == np.uint8
        assert src.info.spacing == (1.0, 1.0, 1.0)  # norms of the direction vectors, rounding noise removed
        unit = header["space directions"] / np.linalg.norm(header["space directions"], axis=1)[:, None]
        np.testing.assert_allclose(src.info.origin, (unit @ header["space origin"])[::-1], atol=1e-9)
        np.testing.assert_allclose(src.info.direction, unit, atol=1e-12)
        np.testing.assert_allclose(src.info.provenance["space_directions"], header["space directions"])
        np.testing.assert_array_equal(read_all(src), data.transpose(2, 1, 0))


@pytest.mark.shared_data
def test_real_ct_chest_dicom(shared_data: Path) -> None:
    folder = shared_data / "ct_chest_dicom"
    headers = {f: pydicom.dcmread(f, stop_before_pixels=True) for f in folder.glob("*.dcm")}
    by_z = sorted(headers, key=lambda f: float(headers[f].ImagePositionPatient[2]))
    assert by_z != sorted(headers)  # file names are not in slice order
    with open_source(folder) as src:
        info = src.info
        assert info.shape == (275, 512, 512) and info.dtype == np.int16
        assert info.spacing == (1.0, 0.78125, 0.78125)
        assert info.origin == pytest.approx((float(headers[by_z[0]].ImagePositionPatient[2]), -59.0, -201.0))
        lo, hi = np.inf, -np.inf
        for z in range(0, 275, 32):
            slab = src.read(z, min(z + 32, 275))
            lo, hi = min(lo, slab.min()), max(hi, slab.max())
        assert -1024 <= lo <= -1000 + 1 and 1000 < hi < 4000  # air and bone, in Hounsfield units
        for k in (0, 137, 274):
            ds = pydicom.dcmread(by_z[k])
            hu = ds.pixel_array * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
            np.testing.assert_array_equal(src.read(k, k + 1)[0], hu)
            np.testing.assert_array_equal(src.read(k, k + 1)[0], pydicom.pixels.apply_rescale(ds.pixel_array, ds))


@pytest.mark.shared_data
def test_real_mr_3slice_dicom_descending_positions(shared_data: Path) -> None:
    folder = shared_data / "mr_3slice_dicom"
    files = sorted(folder.glob("*.dcm"))
    z = [float(pydicom.dcmread(f, stop_before_pixels=True).ImagePositionPatient[2]) for f in files]
    assert z == sorted(z, reverse=True)
    with open_source(folder) as src:
        assert src.info.shape == (3, 512, 512) and src.info.dtype == np.uint16
        assert src.info.spacing == pytest.approx((12.0, 0.9765625, 0.9765625))
        assert src.info.origin[0] == min(z)
        got = read_all(src)
        for k, f in enumerate(reversed(files)):
            np.testing.assert_array_equal(got[k], pydicom.dcmread(f).pixel_array)


@pytest.mark.shared_data
def test_real_raw_mr_head_small(shared_data: Path) -> None:
    p = shared_data / "mr_head_small.raw"
    with open_source(p, shape=(42, 62, 48), dtype="uint8", spacing=(4, 4, 4)) as src:
        assert src.info.spacing == (4.0, 4.0, 4.0)
        check(src, np.fromfile(p, np.uint8).reshape(42, 62, 48))
    refused(r"raw file is 124992 bytes but shape 42x62x49 of uint8 needs 127596 bytes", p, shape=(42, 62, 49),
            dtype="uint8")


def test_detached_nrrd_data_must_lie_beside_the_header(tmp_path):
    """Issue 10, item 1: `data file:` may not leave the header's folder — not by '..', not by an absolute path,
    not through a symlink — and open_source(detached=False) refuses detached headers altogether."""
    import nrrd

    hdir, out = tmp_path / "h", tmp_path / "outside"
    hdir.mkdir(), out.mkdir()
    (out / "secret.raw").write_bytes(bytes(range(256)) * 4)
    (hdir / "link.raw").symlink_to(out / "secret.raw")
    for name in ("../outside/secret.raw", str(out / "secret.raw"), "link.raw"):
        (hdir / "v.nhdr").write_text(f"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 8 8 16\nencoding: raw\n"
                                     f"data file: {name}\n\n")
        with pytest.raises(SourceError, match="outside the header's folder"):
            open_source(hdir / "v.nhdr")
    a = np.arange(4 * 5 * 6, dtype=np.uint8).reshape(4, 5, 6)
    nrrd.write(str(hdir / "ok.nhdr"), a.T, {"encoding": "raw"}, detached_header=True)
    with open_source(hdir / "ok.nhdr") as src:  # beside the header: fine
        assert np.array_equal(src.read(0, 4), a)
    with pytest.raises(SourceError, match="data in another file"):
        open_source(hdir / "ok.nhdr", detached=False)


def test_source_folders_skip_files_that_link_outside(tmp_path):
    import tifffile

    d, out = tmp_path / "stack", tmp_path / "outside"
    d.mkdir(), out.mkdir()
    for k in range(3):
        tifffile.imwrite(d / f"s{k}.tif", np.full((4, 5), k, np.uint8))
    tifffile.imwrite(out / "s3.tif", np.full((4, 5), 99, np.uint8))
    (d / "s3.tif").symlink_to(out / "s3.tif")
    with open_source(d) as src:
        assert src.info.shape == (3, 4, 5) and src.read(0, 3).max() == 2
