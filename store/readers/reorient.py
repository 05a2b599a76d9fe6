"""A source's geometry in the store's world (store/orientation.py): by default (`orient` "LPS") a source with
patient geometry is turned by permutations and flips so that world +x, +y, +z are L, P, S; `orient` "source"
keeps the array as the file has it. A source without patient geometry is never turned."""
from __future__ import annotations

import dataclasses
import os
import tempfile

import numpy as np

from lodcast.errors import SourceError
from lodcast.store.orientation import FRAMES, OPPOSITE, PATIENT_SPACE, Turn, space_name, to_lps, turn_of
from lodcast.store.readers.base import Reader
from lodcast.store.source import SourceInfo, VolumeSource

__all__ = ["reorient", "ORIENTS"]


ORIENTS = ("LPS", "source")
#: formats that can carry a patient frame
PATIENT_FORMATS = ("dicom", "nifti", "nrrd")


def reorient(reader: Reader, orient: str = "LPS") -> Reader:
    """The source in the store's world (module docstring). "LPS" turns the array so that its axes are the patient's
    closest ones; "source" keeps the array's axes and writes the geometry as a rotation of the patient frame onto
    them. A source without patient geometry (no direction, or a space that is not a patient frame, such as NRRD's
    scanner-xyz) keeps its axes under either, and its provenance says why (`orientation_kept`). `reader` itself
    when nothing is turned."""
    if orient not in ORIENTS:
        raise SourceError(f"orient {orient!r}: expected one of {', '.join(ORIENTS)}")
    info = reader.info
    if info.direction is None:
        if orient == "LPS" and info.format in PATIENT_FORMATS:  # others never carry a patient frame: no news
            reader.info = dataclasses.replace(info, provenance={**info.provenance, "orientation_kept": (
                f"this {info.format or 'array'} source has no patient geometry (DICOM, NIfTI with a coded affine and "
                "NRRD with space directions have one): its axes are kept")})
        return reader
    space = space_name(info.space)
    d = np.asarray(info.direction, dtype=np.float64)
    origin_xyz = np.asarray(info.origin[::-1], dtype=np.float64)
    if space in FRAMES:
        d, origin_xyz = to_lps(space, d), to_lps(space, origin_xyz[None])[0]
        space = PATIENT_SPACE
    patient = space == PATIENT_SPACE
    turn = turn_of(d) if orient == "LPS" and patient else Turn((0, 1, 2), (False, False, False))
    shape_xyz, spacing_xyz = info.shape[::-1], info.spacing[::-1]
    # the source voxel that becomes index 0: the far end of every reversed axis
    first = [shape_xyz[turn.order[j]] - 1 if turn.flip[j] else 0 for j in range(3)]
    corner = origin_xyz + sum(first[j] * spacing_xyz[turn.order[j]] * d[turn.order[j]] for j in range(3))
    direction = np.array([d[turn.order[j]] * (-1.0 if turn.flip[j] else 1.0) for j in range(3)])
    prov = dict(info.provenance)
    if orient == "LPS" and not patient:
        prov["orientation_kept"] = (f"the source's space {info.space!r} is not a patient frame (LPS, RAS or LAS): "
                                    "its axes are kept")
    if not turn.identity:
        assert space is not None  # only a patient frame is turned
        codes = {turn.order[j]: OPPOSITE[FRAMES[space][j]] if turn.flip[j] else FRAMES[space][j] for j in range(3)}
        prov["reoriented"] = {"source_axes": [codes[i] for i in range(3)], "order": list(turn.order),
                              "flipped": list(turn.flip)}
    # the ignores: each tuple below has three items, but mypy types a tuple built from a generator as any length
    turned = dataclasses.replace(
        info, shape=tuple(shape_xyz[turn.order[j]] for j in (2, 1, 0)),  # type: ignore[arg-type]
        spacing=tuple(spacing_xyz[turn.order[j]] for j in (2, 1, 0)),  # type: ignore[arg-type]
        origin=tuple(_significant(v) for v in (direction @ corner)[::-1]), space=space,  # type: ignore[arg-type]
        direction=tuple(tuple(float(v) + 0.0 for v in row) for row in direction),  # type: ignore[misc]
        provenance=prov)
    if turn.identity:
        reader.info = turned
        return reader
    return _Reoriented(reader, turn, turned)



def _significant(v: float) -> float:
    """A world coordinate to 12 significant digits: what turning the axes adds in float64 arithmetic (3 × 0.7 =
    2.0999999999999996) is noise far below any header's precision, and would show in `lodcast info`."""
    return float(f"{float(v):.12g}") + 0.0

class _Reoriented(Reader):
    """A source turned by permutations and flips. While the source's slice axis stays the store's z, unreversed,
    each slab is turned as it is read (streaming as the source does); otherwise the source is first copied once,
    in its own order, to a temporary file (in TMPDIR; removed by `close`) from which the store's slabs are cut."""

    def __init__(self, inner: VolumeSource, turn: Turn, info: SourceInfo) -> None:
        self._inner, self._turn, self.info = inner, turn, info
        self._streams = turn.order[2] == 2 and not turn.flip[2]
        self.rereads_cheaply = inner.rereads_cheaply if self._streams else True
        self.held_bytes = inner.held_bytes
        self._spool: np.ndarray | None = None
        self._spool_path: str | None = None

    def _slab(self, z0: int, z1: int) -> np.ndarray:
        if self._streams:  # in pieces, so that a slab is held once and an eighth of it twice
            out = np.empty((z1 - z0, *self.info.shape[1:]), self._inner.info.dtype)
            step = max(1, (z1 - z0) // 8)
            for z in range(z0, z1, step):
                out[z - z0:z - z0 + step] = self._turn.apply(self._inner.read(z, min(z + step, z1)))
            return out
        if self._spool is None:
            self._copy()
        assert self._spool is not None  # set by _copy
        return self._turn.apply(self._spool)[z0:z1]

    def _copy(self) -> None:
        fd, self._spool_path = tempfile.mkstemp(prefix="lodcast-reorient-", suffix=".npy")
        os.close(fd)
        src = self._inner.info
        spool = np.lib.format.open_memmap(self._spool_path, mode="w+", dtype=src.dtype, shape=src.shape)
        for z in range(0, src.shape[0], 32):
            spool[z:z + 32] = self._inner.read(z, min(z + 32, src.shape[0]))
        spool.flush()
        del spool
        self._spool = np.load(self._spool_path, mmap_mode="r")

    def close(self) -> None:
        self._spool = None
        if self._spool_path is not None:
            os.unlink(self._spool_path)
            self._spool_path = None
        self._inner.close()
