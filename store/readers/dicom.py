"""DICOM series: a folder of single-frame grayscale files (or one file; one multi-frame file: dicom_multiframe.py). Headers are read once, keeping only the few
fields a series needs; the largest series is kept when several share a folder, slices are sorted along the normal of
their orientation, RescaleSlope/Intercept are applied into the smallest type that holds every value
(base.rescaled_type), and pixels are decoded only for the slab asked for.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from lodcast.errors import SourceError
from lodcast.store.readers.base import Reader, files_in, rescaled_type, shape_text, source_info, tidy

__all__ = ["DicomReader", "open_dicom", "is_dicom", "stored_range", "coincident", "z_spacing", "patient_geometry",
           "PIXEL_DTYPES"]


def open_dicom(path: Path, index: int | None) -> Reader:
    """A series of single-frame files (a folder, or one file), or one multi-frame (enhanced) file."""
    from lodcast.store.readers.dicom_multiframe import MultiFrameDicomReader, frame_count

    files = [path] if path.is_file() else files_in(path, is_dicom)
    if files and is_dicom(files[0]) and frame_count(files[0]) > 1:
        if len(files) > 1:
            raise SourceError(f"{path} holds {len(files)} DICOM files and {files[0].name} has several frames; "
                              f"ingest one multi-frame file at a time")
        return MultiFrameDicomReader(files[0], index)
    return DicomReader(path, index)


def coincident(depth: Any) -> int | None:
    """The index of the first of two slices at one position along the normal (`depth` ascending), or None."""
    steps = np.diff(depth)
    if len(steps) and steps.min() <= 1e-6 * max(1.0, abs(steps.max())):
        return int(np.argmin(steps))
    return None


def z_spacing(depth: Any, thickness: float, provenance: dict[str, Any], what: str) -> float:
    """The mean step between the (ascending) slice positions; the header's `thickness`, with a warning, when the
    steps differ by more than 1 %."""
    steps = np.diff(depth)
    dz = tidy(float(steps.mean())) if len(steps) else thickness
    if len(steps) and np.abs(steps - dz).max() > 0.01 * dz:
        provenance["warnings"].append(f"{what} positions are not evenly spaced ({steps.min():g} to "
                                      f"{steps.max():g} mm); z spacing {thickness} taken from the header")
        dz = thickness
    return dz


def patient_geometry(orientation: Any, first: list[float], provenance: dict[str, Any]) -> dict[str, Any]:
    """`source_info`'s geometry of a series sorted along its slice normal: LPS, the direction of rows, columns and
    the normal, and the first slice's position as the origin (z, y, x). Both also go into `provenance`."""
    orientation = np.asarray(orientation, dtype=np.float64)
    provenance["orientation"], provenance["first_position"] = orientation.tolist(), list(first)
    return {"space": "LPS", "direction": [orientation[:3], orientation[3:], np.cross(orientation[:3], orientation[3:])],
            "origin": (first[2], first[1], first[0])}


def stored_range(pixel: np.dtype, bits_stored: int) -> tuple[int, int]:
    """The values `bits_stored` bits of a `pixel` can hold (two's complement when it is signed)."""
    bits = min(max(bits_stored, 1), pixel.itemsize * 8)
    return (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) if pixel.kind == "i" else (0, 2**bits - 1)


def is_dicom(p: Path) -> bool:
    try:
        with open(p, "rb") as f:
            return f.read(132)[128:] == b"DICM"
    except OSError:
        return False


PIXEL_DTYPES = {(8, 0): np.uint8, (8, 1): np.int8, (16, 0): np.uint16, (16, 1): np.int16,
                 (32, 0): np.uint32, (32, 1): np.int32}


_DICOM_KEYWORDS = ("SeriesInstanceUID", "Rows", "Columns", "SamplesPerPixel", "PhotometricInterpretation",
                   "NumberOfFrames", "BitsAllocated", "BitsStored", "PixelRepresentation", "PixelSpacing",
                   "SliceThickness", "SpacingBetweenSlices", "ImagePositionPatient", "ImageOrientationPatient",
                   "InstanceNumber", "RescaleSlope", "RescaleIntercept", "Modality", "SeriesDescription", "HighBit")


# uncompressed little-endian syntaxes, whose pixels lie as plain bytes at a known offset
_NATIVE_SYNTAXES = ("1.2.840.10008.1.2", "1.2.840.10008.1.2.1")


def _dicom_header(f: Path) -> dict[str, Any]:
    """The few header fields a series needs (a whole pydicom header is tens of kB, times thousands of slices),
    and where the pixel data start when they are stored uncompressed."""
    import pydicom

    try:
        # deferring large values skips the pixel data but still records their file offset
        ds = pydicom.dcmread(f, defer_size=4096)
        header = {k: ds.get(k) for k in _DICOM_KEYWORDS if ds.get(k) is not None}
        syntax = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
        header["compressed"] = syntax is None or syntax.is_compressed
        if syntax in _NATIVE_SYNTAXES and "PixelData" in ds:
            item: Any = ds.get_item("PixelData")  # a raw element when small, a deferred DataElement when large
            header["pixel_offset"] = int(item.value_tell if hasattr(item, "value_tell") else item.file_tell)
    except Exception as exc:  # pydicom raises many types on corrupt files
        raise SourceError(f"unreadable DICOM file {f}: {exc}") from None
    return header


def _dicom_image(f: Path, ds: dict[str, Any]) -> tuple[int, int, int, int]:
    """(rows, columns, bits allocated, pixel representation) of one grayscale single-frame file."""
    if "Rows" not in ds or "Columns" not in ds:
        raise SourceError(f"unreadable DICOM file {f}: no Rows/Columns (corrupt, or not an image)")
    samples = int(ds.get("SamplesPerPixel", 1))
    if samples != 1:
        raise SourceError(f"non-scalar data: DICOM file {f} is {ds.get('PhotometricInterpretation', '?')} with "
                          f"{samples} samples per pixel; expected one (grayscale)")
    if int(ds.get("NumberOfFrames", 1) or 1) > 1:
        raise SourceError(f"DICOM file {f} holds {ds['NumberOfFrames']} frames; expected one slice per file")
    rows, cols, bits = int(ds["Rows"]), int(ds["Columns"]), int(ds.get("BitsAllocated", 16))
    need = rows * cols * bits // 8
    if not ds["compressed"] and f.stat().st_size < need:
        raise SourceError(f"DICOM file {f} is truncated: {f.stat().st_size} bytes, but its {rows}x{cols} pixels "
                          f"of {bits} bits need {need}")
    return rows, cols, bits, int(ds.get("PixelRepresentation", 0))


class DicomReader(Reader):
    """One DICOM series: a folder of single-frame files (or one file) with its slices sorted along the slice
    normal. Headers are read once; pixels only for the slab asked for. RescaleSlope/Intercept are applied."""

    def __init__(self, path: Path, index: int | None) -> None:
        if index is not None:
            raise SourceError(f"index {index} given but DICOM series {path} is a single 3D volume")
        files = [path] if path.is_file() else files_in(path, is_dicom)
        if not files or not is_dicom(files[0]):
            raise SourceError(f"no DICOM files (with a DICM preamble) in {path}")
        by_series: dict[str, list[tuple[Path, dict[str, Any]]]] = {}
        for f in files:
            header = _dicom_header(f)
            by_series.setdefault(str(header.get("SeriesInstanceUID", "")), []).append((f, header))
        uid = max(sorted(by_series), key=lambda u: len(by_series[u]))
        slices = by_series[uid]
        provenance: dict[str, Any] = {"series_uid": uid, "warnings": []}
        if path.is_dir():
            others = [f.name for f in files_in(path, lambda f: True) if f not in set(files)]
            if others:
                provenance["warnings"].append(f"{len(others)} file(s) in {path.name} are not DICOM and were skipped "
                                              f"(e.g. {', '.join(sorted(others)[:3])})")
        if len(by_series) > 1:
            provenance["other_series"] = {u: len(v) for u, v in by_series.items() if u != uid}
            provenance["warnings"].append(f"{len(by_series)} series in {path}; "
                                          f"kept the largest, {uid} ({len(slices)} files)")
        ny, nx, pixel_dtype = self._check_images(slices)
        slices, dz, geometry = self._sort(slices, provenance)
        self._files = [f for f, _ in slices]
        self._pixel_dtype = pixel_dtype
        self._native_layout = [self._native_of(ds, pixel_dtype) for _, ds in slices]
        self.rereads_cheaply = all(layout is not None for layout in self._native_layout)
        self._rescale = [(float(ds.get("RescaleSlope", 1) or 1), float(ds.get("RescaleIntercept", 0) or 0))
                         for _, ds in slices]
        if any(r != (1.0, 0.0) for r in self._rescale):
            provenance["scaling"] = {"slope": sorted({s for s, _ in self._rescale}),
                                     "intercept": sorted({i for _, i in self._rescale})}
        first = slices[0][1]
        pixel_spacing = first.get("PixelSpacing")
        if pixel_spacing is None:
            provenance["warnings"].append("no PixelSpacing; y and x spacing taken as 1")
            pixel_spacing = (1.0, 1.0)
        for key in ("Modality", "SeriesDescription"):
            if key in first:
                provenance[key.lower()] = str(first.get(key))
        if not provenance["warnings"]:
            del provenance["warnings"]
        # PixelSpacing is (between rows, between columns) = (y, x)
        self.info = source_info((len(slices), ny, nx), pixel_dtype, "dicom", path,
                                spacing=(dz, *map(float, pixel_spacing)), **geometry, **provenance)
        bits = max(int(ds.get("BitsStored", pixel_dtype.itemsize * 8)) for _, ds in slices)
        declared = stored_range(pixel_dtype, bits)
        dtype = rescaled_type(pixel_dtype, declared, self._rescale,
                              lambda: ((self._pixels(k), self._rescale[k]) for k in range(len(self._files))))
        self.info = dataclasses.replace(self.info, dtype=dtype)

    @staticmethod
    def _native_of(ds: dict[str, Any], pixel_dtype: np.dtype) -> tuple[int, int] | None:
        """(pixel offset, bits stored) when the pixels can be read straight from the file, else None."""
        stored = int(ds.get("BitsStored", pixel_dtype.itemsize * 8))
        high = int(ds.get("HighBit", stored - 1))
        if "pixel_offset" not in ds or high != stored - 1 or not 0 < stored <= pixel_dtype.itemsize * 8:
            return None  # unusual bit layouts are left to pydicom
        return ds["pixel_offset"], stored

    @staticmethod
    def _check_images(slices: list[tuple[Path, dict[str, Any]]]) -> tuple[int, int, np.dtype]:
        """Rows, columns and pixel type, the same in every file of the series."""
        first = _dicom_image(*slices[0])
        for f, ds in slices[1:]:
            image = _dicom_image(f, ds)
            if image != first:
                raise SourceError(f"DICOM series has inconsistent images: {slices[0][0].name} is {first[0]}x{first[1]} "
                                  f"of {first[2]} bits but {f.name} is {image[0]}x{image[1]} of {image[2]} bits")
        if (first[2], first[3]) not in PIXEL_DTYPES:
            raise SourceError(f"DICOM file {slices[0][0]} has {first[2]}-bit pixels; expected 8, 16 or 32")
        return first[0], first[1], np.dtype(PIXEL_DTYPES[first[2], first[3]])

    @staticmethod
    def _sort(slices: list[tuple[Path, dict[str, Any]]], provenance: dict[str, Any]
              ) -> tuple[list[tuple[Path, dict[str, Any]]], float, dict[str, Any]]:
        """Slices in order along the normal of their orientation, z spacing and geometry (patient_geometry)."""
        first = slices[0][1]
        thickness = float(first.get("SpacingBetweenSlices", first.get("SliceThickness", 1.0)) or 1.0)
        if not all("ImagePositionPatient" in ds and "ImageOrientationPatient" in ds for _, ds in slices):
            provenance["warnings"].append("slices lack ImagePositionPatient/ImageOrientationPatient; "
                                          f"sorted by InstanceNumber, z spacing {thickness} from the header")
            return sorted(slices, key=lambda s: int(s[1].get("InstanceNumber", 0) or 0)), thickness, {}
        orientation = np.array([float(v) for v in first["ImageOrientationPatient"]])
        for f, ds in slices:
            if not np.allclose([float(v) for v in ds["ImageOrientationPatient"]], orientation, atol=1e-4):
                raise SourceError(f"DICOM series mixes slice orientations: {f.name} differs from {slices[0][0].name}")
        normal = np.cross(orientation[:3], orientation[3:])
        placed = sorted(((float(np.dot([float(v) for v in ds["ImagePositionPatient"]], normal)), f.name, f, ds)
                         for f, ds in slices), key=lambda s: s[:2])
        slices = [(f, ds) for _, _, f, ds in placed]
        depth = [d for d, *_ in placed]
        where = coincident(depth)
        if where is not None:
            raise SourceError(f"DICOM series has two slices at position {depth[where]:g} mm ({slices[where][0].name}, "
                              f"{slices[where + 1][0].name}); expected one slice per position")
        dz = z_spacing(depth, thickness, provenance, "slice")
        ipp = [float(v) for v in slices[0][1]["ImagePositionPatient"]]
        return slices, dz, patient_geometry(orientation, ipp, provenance)

    def _slab(self, z0: int, z1: int) -> np.ndarray:
        out = np.empty((z1 - z0, *self.info.shape[1:]), self.info.dtype)
        for k in range(z0, z1):
            pixels = self._pixels(k)
            slope, intercept = self._rescale[k]
            out[k - z0] = pixels if (slope, intercept) == (1.0, 0.0) else pixels * slope + intercept
        return out

    def _pixels(self, k: int) -> np.ndarray:
        """Slice k's stored pixels, not rescaled."""
        return self._native(k) if self._native_layout[k] is not None else self._decoded(self._files[k])

    def _decoded(self, f: Path) -> np.ndarray:
        import pydicom

        try:
            pixels = pydicom.dcmread(f).pixel_array
        except Exception as exc:  # decoding errors come from pydicom and its image plugins
            raise SourceError(f"cannot decode the pixels of DICOM file {f}: {exc}") from None
        if pixels.shape != self.info.shape[1:]:
            raise SourceError(f"DICOM file {f} has pixels of shape {shape_text(pixels.shape)}; "
                              f"expected {shape_text(self.info.shape[1:])}")
        return pixels

    def _native(self, k: int) -> np.ndarray:
        """Uncompressed pixels read straight from the file (several times faster than parsing it again with
        pydicom), with pydicom's handling of unused high bits: masked off, and the sign taken from bit
        BitsStored - 1 for signed data."""
        f = self._files[k]
        layout = self._native_layout[k]
        assert layout is not None  # _slab reads natively only the files that have a layout
        offset, stored = layout
        dtype = np.dtype(self._pixel_dtype).newbyteorder("<")
        count = int(np.prod(self.info.shape[1:]))
        pixels = np.fromfile(f, dtype, count=count, offset=offset)
        if pixels.size != count:
            raise SourceError(f"cannot decode the pixels of DICOM file {f}: it ends after {pixels.size} of its "
                              f"{count} pixels")
        pixels = pixels.reshape(self.info.shape[1:]).astype(self._pixel_dtype, copy=False)
        unused = dtype.itemsize * 8 - stored
        if unused > 0:
            if dtype.kind == "i":
                pixels = (pixels << unused) >> unused  # arithmetic shift: sign-extends from the stored sign bit
            else:
                pixels &= (1 << stored) - 1
        return pixels
