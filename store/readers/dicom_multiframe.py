"""Enhanced (multi-frame) DICOM: one file whose frames are the slices (Enhanced CT / MR Image Storage and other
multi-frame grayscale objects). Geometry and rescaling come from the functional groups: the shared group, else
each frame's own (PlanePositionSequence, PlaneOrientationSequence, PixelMeasuresSequence,
PixelValueTransformationSequence), else the top-level attributes. Frames are sorted along the slice normal and
decoded one at a time (pydicom's `pixel_array(..., index=i)`), so memory holds a slab, never the whole file.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, cast

import numpy as np

from lodcast.errors import SourceError
from lodcast.store.readers.base import Reader, rescaled_type, shape_text, source_info

__all__ = ["MultiFrameDicomReader", "frame_count"]

def frame_count(f: Path) -> int:
    """NumberOfFrames of a DICOM file (1 for single-frame files and unreadable ones)."""
    import pydicom

    try:
        ds = pydicom.dcmread(f, stop_before_pixels=True, specific_tags=["NumberOfFrames"])
        return int(ds.get("NumberOfFrames", 1) or 1)
    except Exception:  # pydicom raises many types on corrupt files: the series reader reports them
        return 1


def _check_frames(ds: Any, path: Path, n: int, bits: int) -> None:
    """NumberOfFrames against what the file holds, from the header: uncompressed frames are Rows x Columns pixels
    each, all in the file; compressed ones (encapsulated) are at least one fragment each, whose item header alone
    is 8 bytes. (What compressed frames decode to is bounded by ingest's voxel and memory limits.)"""
    if n < 1:
        raise SourceError(f"DICOM file {path} declares NumberOfFrames = {n}; expected 1 or more")
    if "PixelData" not in ds:
        raise SourceError(f"DICOM file {path} has no PixelData")
    item: Any = ds.get_item("PixelData")  # a raw element when small, a deferred DataElement when large
    offset = int(item.value_tell if hasattr(item, "value_tell") else item.file_tell)
    held = path.stat().st_size - offset
    syntax = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
    rows, cols = int(ds.get("Rows", 0) or 0), int(ds.get("Columns", 0) or 0)
    if syntax is None or syntax.is_compressed:
        need, what = 8 * n, "an 8-byte fragment header each at least"
    else:
        need, what = n * rows * cols * (bits // 8), f"{rows}x{cols} pixels of {bits} bits each"
        if syntax.is_deflated:  # the whole dataset is one deflate stream: at most 1032 bytes out per byte in
            held = 1032 * path.stat().st_size
    if need > held:
        raise SourceError(f"DICOM file {path} declares NumberOfFrames = {n} ({what}: {need} bytes), but holds "
                          f"{max(held, 0)} bytes of pixel data")


def _group(ds: Any, k: int, sequence: str) -> Any:
    """The first item of functional group `sequence` for frame k: per frame, else shared, else None."""
    for groups, i in (("PerFrameFunctionalGroupsSequence", k), ("SharedFunctionalGroupsSequence", 0)):
        seq = ds.get(groups)
        inner = seq[i].get(sequence) if seq is not None and len(seq) > i else None
        if inner:
            return inner[0]
    return None


class MultiFrameDicomReader(Reader):
    """The frames of one multi-frame DICOM file as a volume; RescaleSlope/Intercept applied into the stored-type
    rule's type (base.rescaled_type)."""

    def __init__(self, path: Path, index: int | None) -> None:
        import pydicom

        from lodcast.store.readers.dicom import PIXEL_DTYPES, coincident, patient_geometry, stored_range, z_spacing

        if index is not None:
            raise SourceError(f"index {index} given but DICOM file {path} is a single 3D volume")
        try:
            ds = pydicom.dcmread(path, defer_size=4096)
        except Exception as exc:
            raise SourceError(f"unreadable DICOM file {path}: {exc}") from None
        self._path, n = path, int(ds.get("NumberOfFrames", 1) or 1)
        if int(ds.get("SamplesPerPixel", 1)) != 1:
            raise SourceError(f"non-scalar data: DICOM file {path} has {ds.SamplesPerPixel} samples per pixel; "
                              f"expected one (grayscale)")
        bits, signed = int(ds.get("BitsAllocated", 16)), int(ds.get("PixelRepresentation", 0))
        if (bits, signed) not in PIXEL_DTYPES:
            raise SourceError(f"DICOM file {path} has {bits}-bit pixels; expected 8, 16 or 32")
        pixel_dtype = np.dtype(PIXEL_DTYPES[bits, signed])
        _check_frames(ds, path, n, bits)  # before anything is done per frame
        provenance: dict[str, Any] = {"frames": n, "warnings": []}
        positions, orientations, rescale = [], [], []
        for k in range(n):
            pos = _group(ds, k, "PlanePositionSequence")
            ori = _group(ds, k, "PlaneOrientationSequence")
            trans = _group(ds, k, "PixelValueTransformationSequence")
            positions.append(None if pos is None or "ImagePositionPatient" not in pos else
                             [float(v) for v in pos.ImagePositionPatient])
            orientations.append([float(v) for v in (ori.ImageOrientationPatient if ori is not None and
                                                    "ImageOrientationPatient" in ori else
                                                    ds.get("ImageOrientationPatient", [1, 0, 0, 0, 1, 0]))])
            src = trans if trans is not None else ds
            rescale.append((float(src.get("RescaleSlope", 1) or 1), float(src.get("RescaleIntercept", 0) or 0)))
        measures = _group(ds, 0, "PixelMeasuresSequence")
        pixel_spacing = measures.get("PixelSpacing") if measures is not None else ds.get("PixelSpacing")
        thickness = float((measures.get("SpacingBetweenSlices") or measures.get("SliceThickness") or 1.0)
                          if measures is not None else ds.get("SliceThickness", 1.0) or 1.0)
        if pixel_spacing is None:
            provenance["warnings"].append("no PixelSpacing; y and x spacing taken as 1")
            pixel_spacing = (1.0, 1.0)
        orientation = np.array(orientations[0])
        if any(not np.allclose(o, orientation, atol=1e-4) for o in orientations):
            raise SourceError(f"DICOM file {path} mixes frame orientations; expected one volume")
        geometry: dict[str, Any] = {}
        if None in positions:
            provenance["warnings"].append(f"frames lack PlanePositionSequence; in file order, z spacing {thickness}")
            order, dz = list(range(n)), thickness
        else:
            known = cast("list[list[float]]", positions)  # None is not among them
            normal = np.cross(orientation[:3], orientation[3:])
            depth = np.array([np.dot(p, normal) for p in known])
            order = [int(i) for i in np.argsort(depth, kind="stable")]
            where = coincident(depth[order])
            if where is not None:
                raise SourceError(f"DICOM file {path} has two frames at one position ({depth[order][where]:g} mm); "
                                  f"expected one frame per slice (a 4D series is not supported)")
            dz = z_spacing(depth[order], thickness, provenance, "frame")
            geometry = patient_geometry(orientation, known[order[0]], provenance)
        self._order, self._rescale, self._pixel_dtype = order, [rescale[i] for i in order], pixel_dtype
        if any(r != (1.0, 0.0) for r in rescale):
            provenance["scaling"] = {"slope": sorted({s for s, _ in rescale}),
                                     "intercept": sorted({i for _, i in rescale})}
        for key in ("Modality", "SeriesDescription"):
            if key in ds:
                provenance[key.lower()] = str(ds.get(key))
        if not provenance["warnings"]:
            del provenance["warnings"]
        self.info = source_info((n, int(ds.Rows), int(ds.Columns)), pixel_dtype, "dicom", path,
                                spacing=(dz, *map(float, pixel_spacing)), **geometry, **provenance)
        dtype = rescaled_type(pixel_dtype, stored_range(pixel_dtype, int(ds.get("BitsStored", bits))), self._rescale,
                              lambda: ((self._pixels(k), self._rescale[k]) for k in range(n)))
        self.info = dataclasses.replace(self.info, dtype=dtype)

    def _slab(self, z0: int, z1: int) -> np.ndarray:
        out = np.empty((z1 - z0, *self.info.shape[1:]), self.info.dtype)
        for k in range(z0, z1):
            pixels = self._pixels(k)
            slope, intercept = self._rescale[k]
            out[k - z0] = pixels if (slope, intercept) == (1.0, 0.0) else pixels * slope + intercept
        return out

    def _pixels(self, k: int) -> np.ndarray:
        """Slice k's stored pixels (frame `_order[k]`), not rescaled."""
        from pydicom.pixels import pixel_array

        try:
            pixels = pixel_array(self._path, index=self._order[k])
        except Exception as exc:  # decoding errors come from pydicom and its image plugins
            raise SourceError(f"cannot decode frame {self._order[k]} of DICOM file {self._path}: {exc}") from None
        if pixels.shape != self.info.shape[1:]:
            raise SourceError(f"frame {self._order[k]} of {self._path} is {shape_text(pixels.shape)}; expected "
                              f"{shape_text(self.info.shape[1:])}")
        return pixels
