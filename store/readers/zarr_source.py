"""zarr sources: a plain 2D/3D/4D zarr array, or an OME-Zarr 0.4/0.5 image group (a lodcast store is one), of which
the first dataset is read, scaled and translated as its coordinate transformations say, with singleton t/c axes
dropped and at most one non-singleton t or c axis chosen by `index`.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from lodcast.errors import SourceError
from lodcast.store.readers.base import UNITS, Reader, pick_volume, shape_text, source_info

__all__ = ["ZarrReader"]


class ZarrReader(Reader):
    """A plain 2D/3D/4D zarr array, or an OME-Zarr 0.4/0.5 image group (a lodcast store is one): its first
    dataset, scaled and translated as its coordinate transformations say, singleton t/c axes dropped."""

    def __init__(self, path: Path, index: int | None) -> None:
        import zarr

        try:
            node = zarr.open(store=str(path), mode="r")
        except Exception as exc:  # zarr raises several types for folders that are not stores
            raise SourceError(f"{path} is not a readable zarr store: {exc}") from None
        provenance: dict[str, Any] = {}
        array: Any  # zarr types a node read by path as an array or a group
        if isinstance(node, zarr.Array):
            array, image, dataset = node, None, None
            names = {2: "yx", 3: "zyx", 4: "tzyx"}.get(array.ndim) or pick_volume(array.shape, index, f"zarr array {path}")
            axes: list[dict[str, Any]] = [{"name": n} for n in names]
        else:
            ome: Any = dict(node.attrs)  # JSON as the writer made it: checked as it is read
            ome = ome.get("ome", ome)  # 0.5 nests its metadata under "ome", 0.4 does not
            multiscales = ome.get("multiscales") if isinstance(ome, dict) else None
            if not multiscales:
                raise SourceError(f"zarr group {path} has no OME-Zarr 'multiscales' metadata; expected a zarr array "
                                  f"or an OME-Zarr image")
            image, dataset = multiscales[0], multiscales[0]["datasets"][0]
            try:
                array = node[dataset["path"]]
            except KeyError:
                raise SourceError(f"OME-Zarr {path} names dataset '{dataset['path']}', which does not exist") from None
            axes = [a if isinstance(a, dict) else {"name": a} for a in image.get("axes", [])] or \
                [{"name": n} for n in "tczyx"[-array.ndim:]]
            provenance.update(ome_version=str(ome.get("version", image.get("version", ""))),
                              dataset=str(dataset["path"]))
        spatial = [k for k, a in enumerate(axes) if a.get("type") == "space" or a["name"] in ("z", "y", "x")]
        lead = array.ndim - len(spatial)
        if len(axes) != array.ndim or len(spatial) not in (2, 3) or spatial != list(range(lead, array.ndim)):
            raise SourceError(f"zarr {path} has axes {[a['name'] for a in axes]} for shape {shape_text(array.shape)}; "
                              f"expected z, y, x (or y, x) after at most a t and a c axis")
        stacks = [k for k in range(lead) if array.shape[k] > 1]
        if len(stacks) > 1:
            raise SourceError(f"zarr {path} has axes {[a['name'] for a in axes]} of sizes {shape_text(array.shape)}; "
                              f"expected at most one non-singleton t or c axis (chosen by index)")
        shape4, t = pick_volume([array.shape[k] for k in stacks] + list(array.shape[lead:]), index, f"zarr {path}")
        self._array, self._select, self._flat = array, [t if k in stacks else 0 for k in range(lead)], len(spatial) == 2
        spacing, origin, units = [1.0] * 3, [0.0] * 3, "millimeter"
        if image is not None:
            assert dataset is not None  # read with `image`
            scale, translation = _ome_transform(dataset, image, array.ndim)
            pad = 3 - len(spatial)  # a 2D image is one slice of unit thickness
            spacing, origin = [1.0] * pad + [scale[k] for k in spatial], [0.0] * pad + [translation[k] for k in spatial]
            unit = axes[spatial[-1]].get("unit")
            units = UNITS.get(str(unit), str(unit)) if unit else units
        if index is not None:
            provenance["index"] = t
        self.info = source_info(shape4[1:], array.dtype, "zarr", path, spacing=spacing, origin=origin, units=units,
                          **provenance)

    def _slab(self, z0: int, z1: int) -> np.ndarray:
        if self._flat:
            return np.asarray(self._array[tuple(self._select)])[None]
        return np.asarray(self._array[(*self._select, slice(z0, z1))])


def _ome_transform(dataset: dict[str, Any], image: dict[str, Any], ndim: int) -> tuple[list[float], list[float]]:
    """Scale and translation per axis of a dataset, followed by the image-wide transformations when present."""
    scale, translation = [1.0] * ndim, [0.0] * ndim
    for transforms in (dataset.get("coordinateTransformations", []), image.get("coordinateTransformations", [])):
        for tr in transforms:
            if tr.get("type") == "scale":
                s = [float(v) for v in tr["scale"]]
                scale, translation = [a * b for a, b in zip(scale, s)], [a * b for a, b in zip(translation, s)]
            elif tr.get("type") == "translation":
                translation = [a + float(b) for a, b in zip(translation, tr["translation"])]
    return scale, translation
