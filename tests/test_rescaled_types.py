"""The stored-type rule across the readers that rescale (DICOM series, multi-frame DICOM, NIfTI): whole rescaled
values are stored in the smallest integer type that holds the values present, whatever bit depth the file
declares; fractional ones in float32. Files written here by pydicom and nibabel."""
from __future__ import annotations

import tracemalloc
from pathlib import Path

import nibabel as nib
import numpy as np
from test_readers import check, dicom_slice, enhanced_ct

import lodcast
from lodcast.store.readers import open_source

RNG = np.random.default_rng(46)


def ct_pixels(shape: tuple[int, int, int], top: int = 4095) -> np.ndarray:
    """Unsigned pixels 0…top of a CT stored with intercept −1024: air around a body of soft tissue and bone,
    with both ends present."""
    z, y, x = np.indices(shape) - (np.array(shape)[:, None, None, None] - 1) / 2
    r = np.sqrt(z**2 + y**2 + x**2) / (min(shape) / 2)
    hu = np.where(r < 0.8, 40.0, -1000.0) + RNG.normal(0, 10, shape)
    hu[(r > 0.3) & (r < 0.4)] = 1200.0
    pixels = np.clip(np.rint(hu) + 1024, 0, top).astype(np.uint16)
    pixels.flat[0], pixels.flat[-1] = 0, top
    return pixels


def dicom_series(folder: Path, pixels: np.ndarray, intercepts: list[float], slope: float = 1.0) -> None:
    """Single-frame files of 16 stored bits (as many scanners write them, whatever range the pixels use)."""
    folder.mkdir()
    for k, plane in enumerate(pixels):
        dicom_slice(folder / f"IM{k}", plane, 2.0 * k, slope=slope, intercept=intercepts[k % len(intercepts)], bits=16)


def rescaled(pixels: np.ndarray, slope: float, intercepts: list[float]) -> np.ndarray:
    """The float64 rescale every stored value must equal exactly."""
    per_slice = np.array([intercepts[k % len(intercepts)] for k in range(len(pixels))])[:, None, None]
    return pixels.astype(np.float64) * slope + per_slice


def test_unsigned_16_bit_dicom_holding_a_12_bit_ct_is_int16(tmp_path: Path) -> None:
    pixels = ct_pixels((6, 20, 16))
    dicom_series(tmp_path / "ct", pixels, [-1024.0, -1000.0])  # one intercept per slice, as a series may have
    want = rescaled(pixels, 1.0, [-1024.0, -1000.0])
    with open_source(tmp_path / "ct") as src:
        assert src.info.provenance["dtype"] == "uint16"
        assert src.info.provenance["scaling"] == {"slope": [1.0], "intercept": [-1024.0, -1000.0]}
        check(src, want.astype(np.int16))
    assert np.array_equal(want.astype(np.int16).astype(np.float64), want)


def test_rescaled_dicom_values_past_int16_are_float32(tmp_path: Path) -> None:
    """Past int16 the stored-type rule's float32, which holds whole numbers up to 2^24 exactly."""
    pixels = ct_pixels((4, 12, 10), top=40000)  # −1024…38976: neither int16 nor uint16 holds them
    dicom_series(tmp_path / "ct", pixels, [-1024.0])
    want = rescaled(pixels, 1.0, [-1024.0])
    with open_source(tmp_path / "ct") as src:
        check(src, want.astype(np.float32))
    assert want.max() == 38976.0


def test_fractional_dicom_slope_is_float32(tmp_path: Path) -> None:
    pixels = ct_pixels((4, 12, 10))
    dicom_series(tmp_path / "pet", pixels, [-1024.0], slope=0.25)
    with open_source(tmp_path / "pet") as src:
        check(src, rescaled(pixels, 0.25, [-1024.0]).astype(np.float32))


def test_multiframe_dicom_of_16_stored_bits_is_int16(tmp_path: Path) -> None:
    frames = ct_pixels((5, 20, 16))
    enhanced_ct(tmp_path / "ct.dcm", frames, [0.0, 2.0, 4.0, 6.0, 8.0], bits=16)
    with open_source(tmp_path / "ct.dcm") as src:
        check(src, rescaled(frames, 1.0, [-1024.0]).astype(np.int16))


def nifti(path: Path, pixels: np.ndarray, slope: float, inter: float) -> np.ndarray:
    """`pixels` (z, y, x) written as NIfTI's stored values with scl_slope/scl_inter; returns nibabel's float64
    scaled values in (z, y, x)."""
    img = nib.Nifti1Image(pixels.transpose(2, 1, 0), np.eye(4))
    img.header.set_data_dtype(pixels.dtype)
    img.header.set_slope_inter(slope, inter)
    nib.save(img, path)
    back = nib.load(path)
    assert back.get_data_dtype() == pixels.dtype
    assert np.array_equal(back.dataobj.get_unscaled().transpose(2, 1, 0), pixels)  # stored as given, not rescaled
    scaled = np.asanyarray(back.dataobj).transpose(2, 1, 0)
    assert scaled.dtype == np.float64
    return scaled


def test_nifti_with_whole_scaling_takes_the_type_of_its_values(tmp_path: Path) -> None:
    """uint16 voxels 0…4095 with scl_inter −1024 are int16 (once float32); past int16, float32 (exact); a fractional slope
    stays float32. Every value equals nibabel's float64 scaling exactly."""
    pixels = ct_pixels((6, 14, 12))
    for name, slope, inter, top, want in [("hu", 1.0, -1024.0, 4095, np.int16), ("wide", 1.0, -1024.0, 60000, np.float32),
                                          ("twice", 2.0, -1024.0, 4095, np.int16), ("frac", 0.5, -1024.0, 4095, np.float32)]:
        stored = np.minimum(pixels, top)
        stored.flat[-1] = top
        expected = nifti(tmp_path / f"{name}.nii.gz", stored, slope, inter)
        with open_source(tmp_path / f"{name}.nii.gz", orient="source") as src:
            assert src.info.provenance["dtype"] == "uint16"
            check(src, expected.astype(want))
        if want != np.float32:
            assert np.array_equal(expected.astype(want).astype(np.float64), expected)


def test_ingested_unsigned_ct_is_int16_with_a_soft_tissue_window(tmp_path: Path) -> None:
    """Through ingest: the store of an unsigned 16-bit CT series is int16, its voxels the Hounsfield units, and its
    OME window the soft-tissue one (not −1024…3071, grey)."""
    pixels = ct_pixels((24, 32, 32))
    dicom_series(tmp_path / "ct", pixels, [-1024.0])
    st = lodcast.ingest(tmp_path / "ct", tmp_path / "ct.zarr", orient="source")
    assert st.dtype == np.int16
    assert np.array_equal(st.read_region(0, (slice(None),) * 3), rescaled(pixels, 1.0, [-1024.0]))
    win = st.attrs["ome"]["omero"]["channels"][0]["window"]
    assert (win["start"], win["end"]) == (-160.0, 240.0) and (win["min"], win["max"]) == (-1024.0, 3071.0), win


def opening_peak(path: Path) -> int:
    """tracemalloc's peak while a source is opened (where the scan of the values runs), after a first opening has
    brought in the imports and caches."""
    with open_source(path, orient="source"):
        pass
    tracemalloc.start()
    try:
        with open_source(path, orient="source") as src:
            assert src.info.dtype == np.int16
            return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_the_scan_of_the_values_holds_a_slice_or_a_few_not_the_volume(tmp_path: Path) -> None:
    """The pass over the pixels that settles the type reads them as slabs are read: a DICOM slice at a time (the
    series declared 16-bit, which is scanned, needs little more than the same series declared 12-bit, which is
    not), NIfTI in a few slices; neither grows with the depth."""
    slice_bytes = 128 * 128 * 2
    peaks: dict[str, list[int]] = {"dicom": [], "nifti": []}
    for depth in (32, 128):
        pixels = (np.arange(depth * 128 * 128) % 4096).astype(np.uint16).reshape(depth, 128, 128)
        declared = {}
        for bits in (12, 16):
            folder = tmp_path / f"ct{depth}_{bits}"
            folder.mkdir()
            for z in range(depth):
                dicom_slice(folder / f"{z}.dcm", pixels[z], float(z), bits=bits)
            declared[bits] = opening_peak(folder)
        assert declared[16] - declared[12] < 4 * slice_bytes, (depth, declared)
        peaks["dicom"].append(declared[16] - declared[12])
        nifti(tmp_path / f"n{depth}.nii.gz", pixels, 1.0, -1024.0)
        peaks["nifti"].append(opening_peak(tmp_path / f"n{depth}.nii.gz"))
    assert peaks["nifti"][-1] < 128 * 128 * 128 * 2 // 4, peaks  # nibabel's copies of a few slices, not the volume
    for kind, (shallow, deep) in peaks.items():
        assert deep < shallow + slice_bytes, (kind, peaks)
