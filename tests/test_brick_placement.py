"""The reader threads place the bricks they read (renderer/data/bricks.py: place_bricks): every brick of a selection,
values and deviations, lands where a serial, brick-by-brick placement of bricks cut from the store's whole levels
puts it, bit for bit (NaN included), whether it was read by a reader thread or found in the brick pool; and a
failed read stops the placing before the error reaches the caller."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

import lodcast
from lodcast.renderer.data import atlas as lod_atlas
from lodcast.renderer.data import bricks
from lodcast.renderer.data.volume import as_volume
from lodcast.renderer.frame.render import Renderer
from lodcast.renderer.pool import BrickPool
from lodcast.store.layout import Layout

B = 8


@pytest.fixture(scope="module", params=["int16", "float32"])
def store(request, tmp_path_factory):
    shape = (37, 45, 51)  # partial blocks at the far faces: bricks there are edge-padded
    rng = np.random.default_rng(3)
    a = rng.normal(200, 150, shape)
    a[10:20, 12:30, 5:40] += 900
    if request.param == "float32":
        a = a.astype(np.float32)
        a[1:4, 1:4, 1:4] = np.nan
    else:
        a = np.rint(a).astype(np.int16)
    return lodcast.ingest(a, tmp_path_factory.mktemp("place") / f"{request.param}.zarr", block_size=B)


def _reference(store, vol, levels: np.ndarray, what: str) -> dict:
    """(level, z, y, x) -> brick, cut from the store's whole level (values, or deviations in units of
    vol.std_unit computed in float64), edge-padded where the level ends inside it."""
    lay = Layout(tuple(vol.shape), B)
    out = {}
    for k in np.unique(levels[levels >= (0 if what == "mean" else 1)]).tolist():
        whole = store.read_level(k) if what == "mean" else store.read_std_region(k)
        e = lay.block_edge(k)
        grid = np.array(levels.shape)
        whole = np.pad(whole, [(0, int(g * e - n)) for g, n in zip(grid, whole.shape)], mode="edge")
        for z, y, x in zip(*np.nonzero(levels == k)):
            b = whole[z * e:(z + 1) * e, y * e:(y + 1) * e, x * e:(x + 1) * e]
            if what == "std":
                b = np.clip(np.rint(np.nan_to_num(b.astype(np.float64), nan=0.0) / float(vol.std_unit)), 0, 65535)
                b = b.astype(np.uint16)
            out[(k, int(z), int(y), int(x))] = b
    return out


def _buffers(vol, levels):
    offsets = lod_atlas._offsets(levels, B)[1]
    n = int(lod_atlas.brick_elements(levels, B).sum())
    return offsets, {"mean": np.zeros(n, vol.voxel_dtype), "std": np.zeros(n, np.uint16)}


@pytest.mark.parametrize("seed", [0, 1])
def test_bricks_placed_by_the_readers_equal_the_serial_placement(store, monkeypatch, seed):
    monkeypatch.setenv("LODCAST_READ_THREADS", "3")
    eng = Renderer()
    try:
        vol = as_volume(store)
        levels = np.random.default_rng(seed).integers(-1, store.n_levels, size=vol.grid).astype(np.int8)
        pool = BrickPool(1 << 30)
        for round_ in ("read", "pooled"):
            offsets, out = _buffers(vol, levels)
            callers: set[int] = set()

            def sink(what):
                place = lod_atlas._Placer(out[what], offsets, lod_atlas._Placer.runs_of(levels, offsets, B))

                def f(k, blocks, got):
                    callers.add(threading.get_ident())
                    place(k, blocks, got)
                return f

            st = bricks.BrickStats()
            bricks.place_bricks(eng, vol, levels, {w: sink(w) for w in out}, cache=pool, stats=st)
            n = int((levels >= 0).sum())
            if round_ == "read":  # every brick read, and placed by the readers only
                assert (st.read, st.cached) == (n, 0)
                assert callers and threading.get_ident() not in callers
            else:  # every brick from the pool, placed by the calling thread
                assert (st.read, st.cached) == (0, n) and callers == {threading.get_ident()}
            for what in ("mean", "std"):
                ref = np.zeros_like(out[what])
                lod_atlas._place(ref, levels.shape, offsets, _reference(store, vol, levels, what).items())
                np.testing.assert_array_equal(out[what].view(np.uint8), ref.view(np.uint8))
            assert np.count_nonzero(out["mean"]) > 0 and np.count_nonzero(out["std"]) > 0
    finally:
        eng.close()


def test_a_failed_read_stops_the_placing_before_it_raises(store, monkeypatch):
    monkeypatch.setenv("LODCAST_READ_THREADS", "2")
    eng = Renderer()
    try:
        vol = as_volume(store)
        levels = np.zeros(vol.grid, np.int8)
        levels[::2] = 1
        read = bricks._read_group
        calls = []

        def failing(vol, lay, k, zyx, what, table=None):
            if k == 1 and what == "std":
                raise OSError("disk gone")
            time.sleep(0.01)
            return read(vol, lay, k, zyx, what, table)

        monkeypatch.setattr(bricks, "_read_group", failing)
        offsets, out = _buffers(vol, levels)
        placers = {w: lod_atlas._Placer(out[w], offsets, lod_atlas._Placer.runs_of(levels, offsets, B)) for w in out}
        sinks = {w: (lambda k, b, g, w=w: (calls.append(w), placers[w](k, b, g))) for w in out}
        with pytest.raises(OSError, match="disk gone"):
            bricks.place_bricks(eng, vol, levels, sinks, cache=BrickPool(1 << 30))
        n = len(calls)
        time.sleep(0.1)
        assert len(calls) == n  # nothing still placing into buffers the caller is about to let go
    finally:
        eng.close()
