"""Source readers for ingest: `open_source(path)` turns a file or folder into a `VolumeSource`.

Formats: NumPy .npy, raw, NRRD, NIfTI, TIFF (multi-page or a folder of slices), a DICOM series folder and
zarr / OME-Zarr. Every reader reads one z-slab per call and keeps nothing else: uncompressed files are read with
plain file reads (a long-lived memmap would leave every page it touched resident), gzip/bzip2 streams are read
forwards and restarted only when a caller goes back, DICOM and TIFF folders open only the slab's files.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lodcast.errors import SourceError, SourceNotFound
from lodcast.store.source import VolumeSource

__all__ = ["open_source", "FORMATS"]

FORMATS = ("npy", "raw", "nrrd", "nifti", "tiff", "dicom", "zarr")
_ALIASES = {"nii": "nifti", "nhdr": "nrrd", "tif": "tiff", "dcm": "dicom", "ome-zarr": "zarr"}
WINDOW_BYTES = 16 << 20  # read window for Fortran-ordered files, whose z-slabs are scattered over the whole file

# the format modules come after the names above: binary reads WINDOW_BYTES from this package when it reads
from lodcast.store.readers.base import Reader, finish  # noqa: E402
from lodcast.store.readers.binary import open_npy, open_nrrd, open_raw  # noqa: E402
from lodcast.store.readers.dicom import is_dicom, open_dicom  # noqa: E402
from lodcast.store.readers.nifti import NiftiReader  # noqa: E402
from lodcast.store.readers.reorient import reorient  # noqa: E402
from lodcast.store.readers.tiff import open_tiff  # noqa: E402
from lodcast.store.readers.zarr_source import ZarrReader  # noqa: E402


def open_source(path: str | Path, *, format: str | None = None, shape: Sequence[int] | None = None,
                dtype: Any = None, byte_order: str = "little", header_bytes: int = 0,
                spacing: Sequence[float] | None = None, origin: Sequence[float] | None = None,
                index: int | None = None, detached: bool = True, units: str | None = None,
                orient: str = "LPS") -> VolumeSource:
    """Open a volume for ingest. `format` is guessed from the extension or folder content when None; `shape`
    (z, y, x), `dtype`, `byte_order` ('little' or 'big') and `header_bytes` describe raw files; `spacing` and
    `origin` (z, y, x) and `units` (e.g. "mm", "µm") override the file's, in the store's axes; `orient` "LPS"
    (the default) turns a source with patient geometry so that x, y, z point left, posterior, superior, by axis
    permutations and flips only, and "source" keeps the file's array axes (store/orientation.py); a source without
    patient geometry is never turned; `index` picks one volume of a 4D series (time or channel axis);
    `detached=False` refuses sources that name other files (a detached NRRD header, a NIfTI .hdr/.img pair, a
    multi-file OME-TIFF), for uploads. Every reader reads only the source itself or files beside it in its own
    folder (symlinks resolved), never by absolute path or `..`.
    Raises SourceNotFound for a missing path and SourceError for anything that cannot be ingested."""
    p = Path(path)
    if not p.exists():
        raise SourceNotFound(f"source not found: {p}")
    fmt = _format_name(format) if format is not None else _guess_format(p, shape is not None or dtype is not None)
    if fmt != "raw" and (shape is not None or dtype is not None or header_bytes):
        raise SourceError(f"shape, dtype and header_bytes describe raw files only, but {p} is read as {fmt}")
    if fmt in ("npy", "raw", "nrrd", "nifti") and p.is_dir():
        raise SourceError(f"a {fmt} source must be a file, but {p} is a folder")
    if fmt == "zarr" and not p.is_dir():
        raise SourceError(f"a zarr source must be a folder (a .zarr store), but {p} is a file")
    if index is not None and (isinstance(index, bool) or not isinstance(index, (int, np.integer))):
        raise SourceError(f"index must be a whole number, got {index!r}")
    if fmt == "raw":
        reader: Reader = open_raw(p, shape, dtype, byte_order, header_bytes, index)
    elif fmt == "nrrd":
        reader = open_nrrd(p, index, detached)
    elif fmt == "tiff":
        reader = open_tiff(p, index, detached)
    elif fmt == "nifti":
        reader = NiftiReader(p, index, detached)
    else:
        reader = {"npy": open_npy, "dicom": open_dicom, "zarr": ZarrReader}[fmt](p, index)
    try:
        return finish(reorient(reader, orient), spacing, origin, units)
    except BaseException:
        reader.close()
        raise


# --- which format -----------------------------------------------------------------------------------------------

def _format_name(name: str) -> str:
    fmt = _ALIASES.get(str(name).lower(), str(name).lower())
    if fmt not in FORMATS:
        raise SourceError(f"unknown format '{name}'; expected one of {', '.join(FORMATS)}")
    return fmt


def _guess_format(p: Path, raw_options: bool) -> str:
    name = p.name.lower()
    if p.is_dir():
        if name.endswith(".zarr") or any((p / m).is_file() for m in ("zarr.json", ".zarray", ".zgroup")):
            return "zarr"
        files = [f for f in p.iterdir() if f.is_file()]
        if any(is_dicom(f) for f in files):
            return "dicom"
        if any(f.suffix.lower() in (".tif", ".tiff") for f in files):
            return "tiff"
        raise SourceError(f"cannot tell the format of folder {p}: it holds no DICOM files, no .tif files and no "
                          f"zarr metadata")
    by_suffix = [(".nii.gz", "nifti"), (".nii", "nifti"), (".hdr", "nifti"), (".nrrd", "nrrd"), (".nhdr", "nrrd"),
                 (".npy", "npy"), (".raw", "raw"), (".bin", "raw"), (".tif", "tiff"), (".tiff", "tiff"),
                 (".dcm", "dicom")]
    for suffix, fmt in by_suffix:
        if name.endswith(suffix):
            return fmt
    if name.endswith(".img"):  # Analyze/NIfTI pairs an .img with an .hdr; otherwise it is headerless raw
        return "nifti" if p.with_suffix(".hdr").is_file() else "raw"
    with open(p, "rb") as f:
        head = f.read(132)
    for magic, fmt in ((b"\x93NUMPY", "npy"), (b"NRRD", "nrrd"), (b"II*\0", "tiff"), (b"MM\0*", "tiff"),
                       (b"II+\0", "tiff"), (b"MM\0+", "tiff")):
        if head.startswith(magic):
            return fmt
    if head[128:132] == b"DICM":
        return "dicom"
    if raw_options:
        return "raw"
    raise SourceError(f"unknown format of {p}: expected .npy, .raw/.bin/.img (with shape and dtype), .nrrd/.nhdr, "
                      f".nii/.nii.gz, .tif/.tiff, a DICOM or TIFF folder or a .zarr store, or pass format=")
