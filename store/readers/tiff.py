"""TIFF sources: a multi-page file (pages are z; ImageJ hyperstacks take z from their Z axis and one other
non-singleton axis from `index`), read through tifffile's zarr view, or a folder of single-image TIFFs, one slice
each in natural name order, of which only the slab's files are opened. ImageJ metadata gives spacing and units.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from lodcast.errors import SourceError
from lodcast.store.readers.base import UNITS, Reader, files_in, pick_volume, shape_text, source_info

__all__ = ["open_tiff"]


def open_tiff(path: Path, index: int | None, detached: bool = True) -> Reader:
    """`detached=False` refuses a multi-file OME-TIFF (uploads: only the uploaded file may be read); otherwise the
    files its OME-XML names must lie in its own folder. A folder's slices are read page by page: no slice reads
    another file."""
    return _TiffFolderReader(path, index) if path.is_dir() else _TiffFileReader(path, index, detached)


_MICROMETERS = {"nanometer": 1e-3, "micrometer": 1.0, "millimeter": 1e3, "centimeter": 1e4, "meter": 1e6}


def _ome_geometry(xml: str) -> dict[str, Any]:
    """Spacing and units from OME-XML's Pixels element (PhysicalSize{X,Y,Z} and their units, µm by the OME
    schema's default); a size it does not give is 1, and said."""
    import xml.etree.ElementTree as ET

    try:
        root = ET.fromstring(xml)
    except ET.ParseError:
        return {"warnings": ["OME-XML metadata does not parse; spacing 1 used"]}
    pixels = next((el for el in root.iter() if el.tag.rsplit("}", 1)[-1] == "Pixels"), None)
    if pixels is None:
        return {}
    sizes, units, missing = [], [], []
    for axis in "ZYX":
        value = pixels.get(f"PhysicalSize{axis}")
        sizes.append(float(value) if value else 1.0)
        units.append(UNITS.get(pixels.get(f"PhysicalSize{axis}Unit", "µm"), "micrometer") if value else None)
        if not value:
            missing.append(axis.lower())
    given = {u for u in units if u is not None}
    if not given:
        return {"warnings": ["the OME-XML gives no physical sizes; spacing 1 used"]}
    unit = given.pop() if len(given) == 1 else "micrometer"
    if unit == "micrometer" and len({u for u in units if u}) > 1:  # axes in different units: all in µm
        sizes = [v * _MICROMETERS[u] if u else v for v, u in zip(sizes, units)]
    out: dict[str, Any] = {"spacing": tuple(sizes), "units": unit}
    if missing:
        out["warnings"] = [f"OME-XML gives no PhysicalSize for {', '.join(missing)}; 1 {unit} used there"]
    return out


def _tiff_geometry(tif: Any) -> dict[str, Any]:
    """Spacing and units from OME-XML, else ImageJ metadata (z `spacing`, y/x from the resolution tags); without
    either, spacing 1 and a warning in the provenance (which `lodcast ingest` prints)."""
    if tif.is_ome and tif.ome_metadata:
        return _ome_geometry(tif.ome_metadata)
    meta = tif.imagej_metadata if tif.is_imagej else None
    if not meta:
        return {"warnings": ["the TIFF gives no voxel size (neither OME-XML nor ImageJ metadata); spacing 1 used "
                             "(set it with --spacing z,y,x)"]}
    xres, yres = tif.pages[0].resolution
    spacing = (float(meta.get("spacing", 1.0)), 1.0 / yres if yres > 0 else 1.0, 1.0 / xres if xres > 0 else 1.0)
    return {"spacing": spacing, "units": UNITS.get(str(meta.get("unit", "")), "millimeter")}


def _open_tiff(path: Path, companions: bool = False) -> Any:
    """tifffile's view of one file, with its series that read other files turned off: NDTiff and Micro-Manager
    series (which take file names from an index file or a glob) always, OME series naming other files unless
    `companions` (checked by `_check_companions` first)."""
    import tifffile

    try:
        return tifffile.TiffFile(path, _multifile=companions, is_ndtiff=False, is_mmstack=False)
    except Exception as exc:  # tifffile raises many types for files it cannot parse
        raise SourceError(f"{path} is not a readable TIFF file: {exc}") from None


def _ome_files(tif: Any, path: Path) -> list[str]:
    """The FileName of every OME-XML `<TiffData><UUID>` that tifffile opens as a file of its own (a UUID other than
    the OME element's): a multi-file OME-TIFF's other files, or `path` itself named under another UUID."""
    import xml.etree.ElementTree as ET

    if not tif.is_ome or not tif.ome_metadata:
        return []
    try:
        root = ET.fromstring(tif.ome_metadata)
    except ET.ParseError:
        return []  # tifffile cannot parse it either: it falls back to the file's own pages
    own = root.get("UUID")
    names = []
    for data in root.iter():
        if data.tag.endswith("TiffData"):
            names += [uuid.get("FileName", "") for uuid in data
                      if uuid.tag.endswith("UUID") and not (own and uuid.text == own)]
    # as tifffile tells its own file when the OME element has no UUID: by name, in any case
    return [n for n in names if not (own is None and n.lower() == path.name.lower())]


def _check_companions(tif: Any, path: Path, detached: bool) -> bool:
    """Whether `path` is a multi-file OME-TIFF whose files may be read: each other file must be a file in `path`'s
    own folder (symlinks resolved), and `detached=False` (uploads) accepts none. Raises SourceError otherwise,
    naming the field."""
    names = _ome_files(tif, path)
    for name in names:
        if name == path.name:
            continue  # itself
        field = f"OME-XML <TiffData><UUID FileName={name!r}>"
        if not detached:
            raise SourceError(f"OME-TIFF {path} names another file in its {field}; only a single-file OME-TIFF is "
                              f"accepted here")
        if not name:
            raise SourceError(f"OME-TIFF {path} names another file by UUID alone in its OME-XML <TiffData><UUID>; "
                              f"expected a FileName beside it")
        other = path.parent / name
        if Path(name).is_absolute() or other.resolve().parent != path.resolve().parent:
            raise SourceError(f"{field} of OME-TIFF {path} names a file outside the TIFF's folder; expected a file "
                              f"beside it")
        if not other.is_file():
            raise SourceError(f"{field} of OME-TIFF {path} names a file that does not exist")
    return bool(names)


class _TiffFileReader(Reader):
    """A multi-page TIFF: pages are z. ImageJ hyperstacks (TZYX, ZCYX…) take z from the Z axis and the other
    non-singleton axis from `index`. Read through tifffile's zarr view, which also serves ImageJ files whose
    pages after the first are not indexed."""

    def __init__(self, path: Path, index: int | None, detached: bool = True) -> None:
        import zarr

        self._tif = _open_tiff(path)
        try:
            if _check_companions(self._tif, path, detached):
                self._tif.close()
                self._tif = _open_tiff(path, companions=True)
            try:
                series, page = self._tif.series[0], self._tif.pages[0]
            except Exception as exc:  # tifffile raises many types for series it cannot make sense of
                raise SourceError(f"{path} is not a readable TIFF file: {exc}") from None
            axes, shape = series.axes, series.shape
            if "S" in axes or page.samplesperpixel > 1:
                raise SourceError(f"non-scalar data: {path} is {page.photometric.name} with {page.samplesperpixel} "
                                  f"samples per pixel; expected one (grayscale)")
            lead = [a for a in range(len(shape) - 2) if shape[a] > 1]
            if len(lead) > 2:
                raise SourceError(f"{path} has axes {axes} of sizes {shape_text(shape)}; expected z plus at most one "
                                  f"time or channel axis")
            z_axis = next((a for a in lead if axes[a] == "Z"), lead[-1] if lead else None)
            stack = [a for a in lead if a != z_axis]
            shape4, t = pick_volume([shape[a] for a in stack] + [shape[z_axis] if lead else 1, *shape[-2:]], index, str(path))
            self._select: list[Any] = [t if a in stack else 0 for a in range(len(shape) - 2)]
            self._z_axis = z_axis
            self._array: Any = zarr.open(self._tif.aszarr(series=0), mode="r")  # zarr types it an array or a group
            self.info = source_info(shape4[1:], series.dtype, "tiff", path, axes=axes, **_tiff_geometry(self._tif))
        except BaseException:
            self._tif.close()
            raise

    def _slab(self, z0: int, z1: int) -> np.ndarray:
        select = list(self._select)
        if self._z_axis is not None:
            select[self._z_axis] = slice(z0, z1)
        return np.asarray(self._array[tuple(select)]).reshape((z1 - z0,) + self.info.shape[1:])

    def close(self) -> None:
        self._tif.close()


def _natural(p: Path) -> list[Any]:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", p.name)]


def _single_image(f: Path, folder: Path) -> tuple[tuple[int, ...], np.dtype, dict[str, Any]]:
    with _open_tiff(f) as tif:
        page = tif.pages[0]
        if page.samplesperpixel > 1:
            raise SourceError(f"non-scalar data: {f} has {page.samplesperpixel} samples per pixel; "
                              f"expected one (grayscale)")
        if len(tif.pages) > 1:
            raise SourceError(f"TIFF folder {folder} holds {f.name} with {len(tif.pages)} pages; "
                              f"expected one image per file")
        return tuple(page.shape), np.dtype(page.dtype), _tiff_geometry(tif)


class _TiffFolderReader(Reader):
    """A folder of single-image TIFFs, one slice each, in natural name order (img2 before img10)."""

    def __init__(self, path: Path, index: int | None) -> None:
        is_tiff = lambda f: f.suffix.lower() in (".tif", ".tiff")  # noqa: E731
        self._files = sorted(files_in(path, is_tiff), key=_natural)
        linked = len([f for f in path.iterdir() if f.is_file() and is_tiff(f)]) - len(self._files)
        why = (f"{linked} .tif/.tiff {'files are symbolic links' if linked > 1 else 'file is a symbolic link'} to "
               f"files outside {path}, skipped: a source folder reads only its own files (copy them in)"
               ) if linked else None
        if not self._files:
            raise SourceError(f"no .tif/.tiff files in folder {path}" + (f"; {why}" if why else ""))
        series: dict[str, list[Path]] = {}
        for f in self._files:
            series.setdefault(re.sub(r"\d+", "#", f.name.lower()), []).append(f)
        if len(series) > 1:
            named = sorted(series.items(), key=lambda kv: -len(kv[1]))
            raise SourceError(f"TIFF folder {path} holds files of {len(series)} name patterns, "
                              + ", ".join(f"{pat!r} ({len(fs)} files, e.g. {fs[0].name})" for pat, fs in named[:3])
                              + ": which are the slices of one volume is unclear; move each series to a folder "
                              "of its own")
        if index is not None:
            raise SourceError(f"index {index} given but TIFF folder {path} is a single 3D volume")
        shape, dtype, geometry = _single_image(self._files[0], path)
        for f in self._files[1:]:
            other = _single_image(f, path)
            if other[:2] != (shape, dtype):
                raise SourceError(f"TIFF folder {path} has inconsistent images: {self._files[0].name} is "
                                  f"{shape_text(shape)} {dtype} but {f.name} is {shape_text(other[0])} {other[1]}")
        if why:
            geometry["warnings"] = [*geometry.get("warnings", []), why]
        self.info = source_info((len(self._files), *shape), dtype, "tiff", path, files=len(self._files), **geometry)

    def _slab(self, z0: int, z1: int) -> np.ndarray:
        return np.stack([_first_page(f).reshape(self.info.shape[1:]) for f in self._files[z0:z1]])


def _first_page(f: Path) -> np.ndarray:
    """The one image of a folder's slice, its page read directly (a series would follow OME-XML to other files)."""
    with _open_tiff(f) as tif:
        try:
            return np.asarray(tif.pages[0].asarray())
        except Exception as exc:  # decoding errors come from tifffile and imagecodecs
            raise SourceError(f"cannot decode TIFF slice {f}: {exc}") from None
