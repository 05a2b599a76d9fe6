"""Small test data several test files write: a head phantom, a smooth sphere and a DICOM dataset's common header."""
from __future__ import annotations

from typing import Any

import numpy as np


def head(n: int) -> np.ndarray:
    """A uint8 head phantom, n³: an ellipsoid of 90 with a bright skull shell of 160 in background 4, noisy."""
    z, y, x = (np.mgrid[:n, :n, :n] - (n - 1) / 2) / (n / 2)
    r = np.sqrt((z / 0.8) ** 2 + (y / 0.9) ** 2 + (x / 0.75) ** 2)
    vol = np.where(r < 1.0, 90.0, 4.0) + np.random.default_rng(3).normal(0, 3, r.shape)
    vol[(r > 0.88) & (r < 1.0)] = 160.0
    return np.clip(vol, 0, 255).astype(np.uint8)


# the engine CT's metal as a faint band (α 0.01 per unit over most of its values) beside opaque plates: a block's
# error sits in the band while the plates set its opacity (tests/test_prediction.py, benchmarks/bench_prediction.py)
ENGINE_BAND = {"points": [{"value": 60, "color": [0.8, 0.85, 0.9], "opacity": 0.0},
                          {"value": 90, "color": [0.8, 0.85, 0.9], "opacity": 0.01},
                          {"value": 180, "color": [0.9, 0.8, 0.6], "opacity": 0.01},
                          {"value": 230, "color": [1.0, 0.6, 0.3], "opacity": 0.3}]}


#: a TF that shows sphere_ramp's surface as an opaque shell whose colour follows the values inside
# soft tissue as a faint band (α 0.006 per unit over 300 HU) over most of a CT's body, bone opaque behind it: the
# translucent case of the level of detail's lossless and predicted error (tests/test_lossless.py, test_prediction.py,
# and the benchmarks' BAND_OVER_BONE: benchmarks/bench_consistent_lod.py)
BAND_BONE = {"points": [
    {"value": -150, "color": [0.9, 0.5, 0.4], "opacity": 0.0},
    {"value": -100, "color": [0.9, 0.5, 0.4], "opacity": 0.006},
    {"value": 200, "color": [0.9, 0.55, 0.45], "opacity": 0.006},
    {"value": 250, "color": [1.0, 1.0, 0.9], "opacity": 0.0},
    {"value": 300, "color": [1.0, 1.0, 0.9], "opacity": 0.0},
    {"value": 700, "color": [1.0, 1.0, 0.95], "opacity": 0.6},
    {"value": 1500, "color": [1.0, 1.0, 1.0], "opacity": 0.9}]}

SPHERE_TF = {"points": [{"value": -100, "color": [0.9, 0.6, 0.4], "opacity": 0.0},
                        {"value": 100, "color": [0.9, 0.7, 0.5], "opacity": 0.9},
                        {"value": 1000, "color": [1.0, 1.0, 1.0], "opacity": 0.9}]}


def sphere_ramp(n: int = 128) -> np.ndarray:
    """A smooth float32 volume, n³: a sphere of radius 0.31 n as a radial ramp (25 per voxel, 0 on the surface,
    positive inside) plus a linear ramp along x (3 per voxel), off the block grid's centre so that its surface
    crosses block faces at every angle."""
    zz, yy, xx = np.mgrid[:n, :n, :n].astype(np.float32)
    r = np.sqrt((xx - 0.496 * n) ** 2 + (yy - 0.469 * n) ** 2 + (zz - 0.516 * n) ** 2)
    return ((0.3125 * n - r) * 25.0 + 3.0 * (xx - n / 2)).astype(np.float32)


def dicom_dataset(sop_class: str) -> Any:
    """A CT DICOM dataset of `sop_class` with its file meta (explicit VR little endian) and a fresh instance UID;
    the caller adds series, geometry and pixels."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = sop_class, generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID = sop_class, meta.MediaStorageSOPInstanceUID
    ds.Modality = "CT"
    return ds


def multiframe(path: Any, frames: int, syntax: str | None = None) -> None:
    """A multi-frame DICOM holding one 64x64 frame of pixel data whose header declares `frames` frames (`syntax`: a
    transfer syntax to compress that frame with, else native)."""
    from pydicom.uid import EnhancedCTImageStorage

    ds = dicom_dataset(EnhancedCTImageStorage)
    ds.NumberOfFrames, ds.Rows, ds.Columns = 1, 64, 64
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 0
    ds.PixelData = np.arange(64 * 64, dtype=np.uint16).tobytes()
    if syntax is not None:
        ds.compress(syntax)
    ds.NumberOfFrames = frames
    ds.save_as(path, enforce_file_format=True)
