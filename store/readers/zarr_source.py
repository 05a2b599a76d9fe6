"""zarr sources: a plain 2D/3D/4D zarr array, or an OME-Zarr 0.4/0.5 image group (a lodcast store is one), of which
the first dataset is read, scaled and translated as its coordinate transformations say, with singleton t/c axes
dropped and at most one non-singleton t or c axis chosen by `index`. Only the store's own files are read (a file or
folder in it that links out of it is refused), and each chunk is decoded once: the last row of chunks read is kept
for the slabs it still holds, and counted as `held_bytes`.
"""
from __future__ import annotations

import math
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from zarr.abc.store import ByteRequest
from zarr.core.buffer import Buffer, BufferPrototype
from zarr.storage import LocalStore

from lodcast.errors import SourceError
from lodcast.store.readers.base import UNITS, Reader, pick_volume, shape_text, source_info

__all__ = ["ZarrReader"]

#: chunks may exceed a small array (a (64, 64, 64) chunk of a 10³ array is ordinary), but one that decodes to more
#: than this and more than the whole array is refused from the metadata: its declared size is all the decoder
#: would allocate
CHUNK_BYTES_LIMIT = 256 << 20


class _OwnFiles(LocalStore):
    """A read-only LocalStore that reads only files inside its root, symlinks resolved: a chunk or a metadata file
    that links out of the store is refused rather than read."""

    def _inside(self, key: str) -> None:
        real, root = os.path.realpath(self.root / key), os.path.realpath(self.root)
        if os.path.commonpath([real, root]) != root:
            raise SourceError(f"zarr source {self.root}: {key!r} links to {real}, outside the store; a source reads "
                              f"only its own files")

    def get_sync(self, key: str, *, prototype: BufferPrototype | None = None,
                 byte_range: ByteRequest | None = None) -> Buffer | None:
        self._inside(key)
        return super().get_sync(key, prototype=prototype, byte_range=byte_range)

    async def get(self, key: str, prototype: BufferPrototype | None = None,
                  byte_range: ByteRequest | None = None) -> Buffer | None:
        self._inside(key)
        return await super().get(key, prototype, byte_range)

    async def get_partial_values(self, prototype: BufferPrototype,
                                 key_ranges: Iterable[tuple[str, ByteRequest | None]]) -> list[Buffer | None]:
        key_ranges = list(key_ranges)
        for key, _ in key_ranges:
            self._inside(key)
        return await super().get_partial_values(prototype, key_ranges)


class ZarrReader(Reader):
    """A plain 2D/3D/4D zarr array, or an OME-Zarr 0.4/0.5 image group (a lodcast store is one): its first
    dataset, scaled and translated as its coordinate transformations say, singleton t/c axes dropped."""

    def __init__(self, path: Path, index: int | None) -> None:
        import zarr

        try:
            node = zarr.open(store=_OwnFiles(path, read_only=True), mode="r")
        except SourceError:
            raise
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
            name = str(dataset["path"])
            if name.startswith("/") or "\\" in name or ".." in name.split("/"):
                raise SourceError(f"OME-Zarr {path} names dataset path {name!r} (multiscales[0].datasets[0].path), "
                                  f"outside the store; expected a path inside it")
            try:
                array = node[name]
            except KeyError:
                raise SourceError(f"OME-Zarr {path} names dataset '{name}', which does not exist") from None
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
        self._rows: tuple[int, int, np.ndarray] | None = None  # the last row of chunks read: z0, z1, voxels
        self._chunk_depth, self.held_bytes = _chunk_rows(array, shape4[1:], path)
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
        # zarr decodes whole chunks: read a chunk row once and cut the slabs it holds from it, else a chunk deeper
        # than a slab is decoded again for every slab (a 1024³ chunk: 64 times)
        c, depth = self._chunk_depth, self.info.shape[0]
        parts = []
        for r in range(z0 // c, (z1 - 1) // c + 1):
            if self._rows is None or self._rows[0] != r * c:
                self._rows = None  # before the next row is decoded: one row held at a time
                r0, r1 = r * c, min(depth, (r + 1) * c)
                self._rows = (r0, r1, np.asarray(self._array[(*self._select, slice(r0, r1))]))
            r0, _, rows = self._rows
            parts.append(rows[max(z0, r0) - r0:min(z1, r0 + c) - r0])
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def close(self) -> None:
        self._rows = None


def _chunk_rows(array: Any, shape: tuple[int, ...], path: Path) -> tuple[int, int]:
    """(chunk depth along z, bytes held while reading: a decoded row of chunks across the volume, and the chunks
    zarr decodes at once). A chunk that decodes to more than CHUNK_BYTES_LIMIT and more than the whole array is
    refused from the metadata."""
    import zarr

    chunks = tuple(int(c) for c in array.chunks)  # the inner chunks of a sharded array: what is decoded
    item = np.dtype(array.dtype).itemsize
    chunk_bytes = math.prod(chunks) * item
    if chunk_bytes > max(CHUNK_BYTES_LIMIT, math.prod(int(s) for s in array.shape) * item):
        raise SourceError(f"zarr {path} has chunks of {'x'.join(map(str, chunks))} ({chunk_bytes / 1e6:.0f} MB "
                          f"decoded), larger than the array {'x'.join(str(int(s)) for s in array.shape)} itself; "
                          f"expected chunks within the array")
    c = chunks[-3] if len(chunks) >= 3 and shape[0] > 1 else 1  # a 2D image is read whole, one slice
    per_row = math.prod(math.ceil(s / n) for s, n in zip(array.shape[-2:], chunks[-2:]))
    at_once = min(per_row, int(zarr.config.get("async.concurrency") or 1))
    return c, min(c, shape[0]) * shape[1] * shape[2] * item + at_once * chunk_bytes


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
