"""NIfTI-1/2 (and Analyze .hdr/.img pairs) through nibabel. The data axes (i, j, k) are the store's (x, y, z) (the
store is `transpose(data, (2, 1, 0))`) unless ingest is asked to turn them to LPS; the coded sform (else qform)
affine, in RAS, is the patient geometry `store/readers/reorient.py` records or turns by; scaled data is stored in
the stored-type rule's type (base.rescaled_type: int16 for integer voxels scaled to Hounsfield units), 4D series give one volume chosen by `index` (vector-like intents are refused as non-scalar), and slabs
are read in pieces so that nibabel's temporaries stay small beside them.
"""
from __future__ import annotations

import dataclasses
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from lodcast.errors import SourceError
from lodcast.store.readers.base import (
    READ_CHUNK,
    UNITS,
    Reader,
    pick_volume,
    rescaled_type,
    shape_text,
    source_info,
)

__all__ = ["NiftiReader"]


_NIFTI_VECTOR_INTENTS = {"vector", "displacement vector", "rgb vector", "rgba vector", "quaternion",
                         "symmetric matrix", "general matrix", "pointset", "triangle", "fnirt disp field"}



def _decimal(x: Any) -> float:
    """A header's float32 number as the decimal it was written as (1.2, not 1.2000000476837158): the shortest
    decimal that rounds to the same float32."""
    return float(np.format_float_positional(np.float32(x), unique=True, trim="-"))

def _pair(path: Path) -> list[Path]:
    """What nibabel reads for an Analyze/NIfTI pair besides `path`: the .img of a .hdr, the .hdr of an .img, and
    SPM's .mat (same stem, same compression suffix)."""
    import nibabel as nib
    from nibabel.filename_parser import splitext_addext

    if splitext_addext(str(path))[1].lower() not in (".hdr", ".img"):
        return []
    return [Path(h.filename) for h in nib.Spm99AnalyzeImage.filespec_to_file_map(str(path)).values() if h.filename]


def _check_companions(path: Path, files: list[Path], detached: bool) -> None:
    """Each of `files` other than `path` that exists must be a file in `path`'s own folder, symlinks resolved;
    `detached=False` (uploads: one file) accepts none."""
    folder = path.parent.resolve()
    for f in files:
        if f == path or not (f.exists() or f.is_symlink()):
            continue
        if not detached:
            raise SourceError(f"NIfTI {path} keeps its data or header in another file ({f.name}); only a single-file "
                              f".nii or .nii.gz is accepted here")
        if f.resolve().parent != folder:
            raise SourceError(f"{f.name}, the companion of NIfTI {path}, links to a file outside its folder; "
                              f"expected a file beside it (copy it in)")
        if not f.is_file():
            raise SourceError(f"{f.name}, the companion of NIfTI {path}, is not a regular file")


class NiftiReader(Reader):
    """NIfTI-1/2 (and Analyze) through nibabel: slabs of `transpose(data, (2, 1, 0))`. The proxy keeps its file
    open so that a .gz reads forwards."""

    def __init__(self, path: Path, index: int | None, detached: bool = True) -> None:
        import nibabel as nib

        _check_companions(path, _pair(path), detached)  # before nibabel opens any of them
        try:
            img: Any = nib.load(str(path), keep_file_open=True)  # NIfTI-1, NIfTI-2 or Analyze, each its own API
            ondisk = img.get_data_dtype()
        except Exception as exc:  # nibabel raises many types for files it cannot parse
            raise SourceError(f"{path} is not a readable NIfTI file: {exc}") from None
        # and what nibabel took the file for (given format="nifti", any of its formats), before any voxel is read
        _check_companions(path, [Path(h.filename) for h in img.file_map.values() if h.filename], detached)
        shape = list(img.shape)
        while len(shape) > 3 and shape[-1] == 1:
            shape.pop()
        intent = img.header.get_intent()[0] if hasattr(img.header, "get_intent") else "none"
        if len(shape) > 4 or len(shape) < 2:
            raise SourceError(f"NIfTI file {path} has {len(shape)} dimensions (shape {shape_text(shape)}, intent {intent}); "
                              f"expected a scalar 3D volume, or 4D with an index")
        if len(shape) == 4 and intent in _NIFTI_VECTOR_INTENTS:
            raise SourceError(f"non-scalar data: NIfTI file {path} is 4D with intent '{intent}'; expected scalar data")
        # nibabel's order is (x, y, z, t); pick_volume wants t first
        shape4, t = pick_volume([shape[3], *shape[2::-1]] if len(shape) == 4 else shape[::-1], index, f"NIfTI file {path}")
        self._proxy = img.dataobj
        # a chosen t, then 0 for the trailing singleton axes dropped above
        self._tail = ((t,) if len(shape) == 4 else ()) + (0,) * (len(img.shape) - len(shape))
        self._flat = len(shape) == 2
        self._path = path
        slope, inter = float(getattr(self._proxy, "slope", 1.0)), float(getattr(self._proxy, "inter", 0.0))
        scaled = (slope, inter) != (1.0, 0.0)
        zooms = [_decimal(z) for z in img.header.get_zooms()[:3]] + [1.0] * (3 - min(3, len(shape)))
        affine = np.asarray(img.affine, dtype=float)
        # the scanner or standard-space affine (sform, else qform); neither coded: NIfTI says nothing of where
        # the patient is, and nibabel's fallback affine is only a guess
        coded = None
        if hasattr(img.header, "get_sform"):  # Analyze headers have neither
            coded = next((a for a, code in (img.header.get_sform(coded=True), img.header.get_qform(coded=True))
                          if code and a is not None), None)
        if coded is not None:
            coded = np.vectorize(_decimal, otypes=[np.float64])(np.asarray(coded))
        geometry: dict[str, Any] = {} if coded is None else {"space": "RAS", "direction": coded[:3, :3].T,
                                                              "origin": coded[:3, 3][::-1]}
        units = img.header.get_xyzt_units()[0] if hasattr(img.header, "get_xyzt_units") else "unknown"
        provenance: dict[str, Any] = {"affine": affine.tolist(), "intent": intent}
        if scaled:
            provenance["scaling"] = {"slope": slope, "intercept": inter}
        if index is not None:
            provenance["index"] = t
        self.info = source_info(shape4[1:], ondisk, "nifti", path, spacing=zooms[::-1],
                                units=UNITS.get(units, "millimeter"), **geometry, **provenance)
        if scaled:
            declared = (np.iinfo(ondisk).min, np.iinfo(ondisk).max) if ondisk.kind in "iu" else (0, 0)
            # nibabel's pieces come scaled (float64, exact for whole slopes and intercepts)
            self.info = dataclasses.replace(self.info, dtype=rescaled_type(
                np.dtype(ondisk), declared, [(slope, inter)],
                lambda: ((piece, (1.0, 0.0)) for piece in self._pieces(0, self.info.shape[0]))))

    def _slab(self, z0: int, z1: int) -> np.ndarray:
        out = np.empty((z1 - z0, *self.info.shape[1:]), self.info.dtype)
        z = z0
        for piece in self._pieces(z0, z1):
            out[z - z0:z - z0 + len(piece)] = piece
            z += len(piece)
        return out

    def _pieces(self, z0: int, z1: int) -> Iterator[np.ndarray]:
        """Voxels [z0, z1) as nibabel gives them (scaled), (z, y, x), a few slices at a time: nibabel holds a few
        copies of what it reads (compressed bytes, scaled float64), which then stay small beside a slab."""
        step = max(1, READ_CHUNK // (self.info.shape[1] * self.info.shape[2] * self.info.dtype.itemsize))
        try:
            if self._flat:
                yield np.asarray(self._proxy[:, :]).T[None]
                return
            for z in range(z0, z1, step):
                piece = self._proxy[(slice(None), slice(None), slice(z, min(z + step, z1))) + self._tail]
                yield np.asarray(piece).transpose(2, 1, 0)
        except (OSError, EOFError, ValueError, zlib.error) as exc:
            raise SourceError(f"NIfTI data of {self._path} is corrupt or truncated: {exc}") from None

    def close(self) -> None:
        self._proxy = None  # the proxy closes the file it kept open when it goes
