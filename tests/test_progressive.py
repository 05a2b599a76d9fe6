"""Progressive renders in Python (renderer/frame/progressive.py): coarse to fine, every stage H×W, the last equal to
the plain render bit for bit; the coarse stages cheaper, their bricks reused, and nothing rendered after the
generator is closed."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from recording import record_renders

import lodcast
from lodcast.renderer.frame.progressive import Ladder, upsample
from lodcast.service.testing import TINY_TF, make_volume


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """64³ voxels in blocks of 8: four levels, the smallest volume that is staged by default."""
    return make_volume(tmp_path_factory.mktemp("prog"), "v", n=64, block_size=8)


def scene(**extra: object) -> dict:
    return {"camera": {"azimuth": 30, "elevation": 20}, "width": 96, "height": 64, "tf": TINY_TF, "format": "npy",
            **extra}


@pytest.mark.parametrize("quality", ["full", {"reduction": 4}])
def test_stages_go_coarse_to_fine_and_end_with_the_plain_render(eng, store, quality):
    stages = list(eng.render_progressive(store, scene(quality=quality)))
    plain = lodcast.Renderer().render(store, scene(quality=quality))  # a fresh engine: nothing shared
    reports = [s.report for s in stages]
    assert len(stages) == 3
    assert [r["stage"] for r in reports] == [0, 1, 2] and [r["final"] for r in reports] == [False, False, True]
    assert all(s.rgba.shape == (64, 96, 4) and s.rgba.dtype == np.float32 for s in stages)
    np.testing.assert_array_equal(stages[-1].rgba, plain.rgba)
    red = [r["reduction"] for r in reports]
    pred = [r["predicted_delta_e"] for r in reports]
    wall = [r["wall_ms"] for r in reports]
    assert red == sorted(red, reverse=True) and red[0] >= 16 * red[-1], red
    assert pred == sorted(pred, reverse=True) and pred[0] > pred[-1], pred
    assert wall == sorted(wall) and wall[0] > 0 and wall[-1] >= reports[-1]["kernel_ms"]
    # the first stage is the cheapest to show: a smaller image at 64 times less data, sampled adaptively
    assert reports[0]["image_scale"] == 0.5 and reports[1]["image_scale"] == reports[2]["image_scale"] == 1.0
    assert reports[0]["samples"] * 4 < reports[-1]["samples"], [r["samples"] for r in reports]
    assert reports[-1]["samples"] == plain.report["samples"]
    timing = ("wall_ms", "kernel_ms", "build_ms", "upload_ms", "program_cache", "bricks_read", "bricks_cached", "stage")
    assert {k: v for k, v in reports[-1].items() if k not in timing} == \
        {k: v for k, v in plain.report.items() if k not in timing}


def test_later_stages_reuse_what_earlier_ones_read(eng, store):
    q = {"reduction": 4}
    stages = [s.report for s in eng.render_progressive(store, scene(quality=q))]
    alone = lodcast.Renderer().render(store, scene(quality=q)).report
    assert stages[0]["bricks_cached"] == 0 and all(r["bricks_cached"] > 0 for r in stages[1:]), stages
    assert stages[-1]["bricks_read"] < alone["bricks_read"], (stages[-1]["bricks_read"], alone["bricks_read"])


def test_closing_the_generator_renders_nothing_more(eng, store, monkeypatch):
    seen = record_renders(monkeypatch, eng)
    gen = eng.render_progressive(store, scene())
    first = next(gen)
    assert first.report["stage"] == 0 and not first.report["final"] and len(seen) == 1
    gen.close()
    assert len(seen) == 1
    assert seen[0]["quality"] == {"reduction": 64.0} and seen[0]["width"] == 48


def test_stop_ends_the_stages_between_them(eng, store, monkeypatch):
    """A caller's `stop` (a deadline, a superseded request) is asked before each stage after the first."""
    seen = record_renders(monkeypatch, eng)
    asked = []

    def stop() -> None:
        asked.append(len(seen))
        if len(seen) >= 1:
            raise TimeoutError("superseded")

    gen = eng.render_progressive(store, scene(), stop=stop)
    assert next(gen).report["stage"] == 0
    with pytest.raises(TimeoutError):
        next(gen)
    assert len(seen) == 1 and asked[-1] == 1


@pytest.mark.parametrize("case", ["small volume", "coarse final", "array", "nothing visible"])
def test_stages_that_would_not_be_cheaper_are_skipped(eng, store, tmp_path, case):
    """Only the final where a coarse stage could not be much cheaper: a volume under Ladder.min_voxels, a final
    whose reduction leaves no room below the store's coarsest level, an array (no levels), a lossless final that
    loads nothing."""
    src: object = store
    sc = scene()
    if case == "small volume":
        src = make_volume(tmp_path, "small", n=24, block_size=8)
    elif case == "coarse final":
        sc = scene(quality={"reduction": 200})  # 4 × 200 is beyond 8³ (every block at its coarsest level)
    elif case == "array":
        src = np.random.default_rng(0).random((64, 64, 64)).astype(np.float32)
        sc = scene(tf={"points": [{"value": 0.5, "opacity": 0.0}, {"value": 1.0, "opacity": 0.3}]})
    else:
        sc = scene(quality="lossless", tf={"points": [{"value": 5000, "opacity": 0.0}, {"value": 6000, "opacity": 1}]})
    stages = list(eng.render_progressive(src, sc))
    assert len(stages) == 1 and stages[0].report["stage"] == 0 and stages[0].report["final"] is True
    np.testing.assert_array_equal(stages[0].rgba, lodcast.Renderer().render(src, sc).rgba)


def test_a_lossless_final_is_staged_below_its_own_reduction(eng, store):
    """Lossless selects first (the final finds the selection made): the coarse stage holds less than it."""
    reports = [s.report for s in eng.render_progressive(store, scene(quality="lossless"))]
    assert len(reports) >= 2 and reports[-1]["quality"] == "lossless"
    assert reports[0]["reduction"] >= 4 * reports[-1]["reduction"]
    assert reports[0]["predicted_delta_e"] >= reports[-1]["predicted_delta_e"]


def test_the_module_verb_uses_the_default_renderer(store):
    stages = list(lodcast.render_progressive(store, scene(width=32, height=32)))
    assert stages[-1].report["final"] and all(s.rgba.shape == (32, 32, 4) for s in stages)
    # too small an image for a smaller first one: every stage at the scene's size
    assert all(s.report["image_scale"] == 1.0 for s in stages)


def test_a_ladder_of_one_factor(eng, store):
    reports = [s.report for s in eng.render_progressive(store, scene(), ladder=Ladder(factors=(16.0,), first_scale=1))]
    assert [r["quality"] for r in reports] == [{"reduction": 16.0}, "full"]
    with pytest.raises(ValueError, match="factors"):
        Ladder(factors=(8.0, 64.0))


def test_upsample_blends_between_pixel_centres():
    a = np.zeros((2, 2, 4), np.float32)
    a[:, 1] = 1.0  # left column empty, right column opaque white
    up = upsample(a, 4, 4)
    assert up.shape == (4, 4, 4) and up.dtype == np.float32
    np.testing.assert_allclose(up[0, :, 3], [0.0, 0.25, 0.75, 1.0])  # centres at 0.5 and 2.5 of 4, edges clamped
    np.testing.assert_array_equal(up[0], up[3])
    assert upsample(a, 2, 2) is a
    np.testing.assert_array_equal(upsample(np.full((1, 1, 4), 0.5, np.float32), 3, 5), np.full((3, 5, 4), 0.5))


def test_a_coarse_level_is_a_volume_in_the_store_world(tmp_path):
    """volume.level_view: a level-k voxel is the mean of the 2^k-cube of level-0 voxels from 2^k times its index,
    so on a linear ramp its value is the world position of its own centre (origin + index · spacing of the view),
    exactly, wherever the cube lies inside the volume; the view frames the store's own box."""
    from lodcast.renderer.data.volume import as_volume, level_view
    from lodcast.renderer.scene.camera import box_world

    z, y, x = np.mgrid[:40, :48, :64].astype(np.float32)
    spacing, origin = (2.0, 0.5, 0.75), (-10.0, 3.0, 7.5)
    ramp = (origin[2] + x * spacing[2]) + 1000.0 * (origin[0] + z * spacing[0])  # world x and z, apart in value
    st = lodcast.ingest(ramp, tmp_path / "ramp.zarr", spacing=spacing, origin=origin, block_size=8, progress=False)
    vol = as_volume(st)
    for k in (1, 2, 3):
        lv = level_view(vol, k)
        f = 1 << k
        assert lv.spacing == tuple(s * f for s in spacing)
        a = np.asarray(lv.source, np.float64)
        inside = a[: 40 // f, : 48 // f, : 64 // f]
        n = inside.shape
        cz = lv.origin[0] + np.arange(n[0])[:, None, None] * lv.spacing[0]
        cx = lv.origin[2] + np.arange(n[2])[None, None, :] * lv.spacing[2]
        np.testing.assert_allclose(inside, np.broadcast_to(cx + 1000.0 * cz, n), rtol=0, atol=1e-3)
        for got, want in zip(lv.frame_box, box_world(vol.shape, vol.spacing, vol.origin)):
            np.testing.assert_array_equal(got, want)


def test_a_large_store_is_first_shown_as_a_coarse_level(tmp_path):
    """Past Ladder.preview_voxels the first stage is a coarse level rendered as a volume: no selection (the TF's
    error tables are not computed), no brick read, nothing predicted, the level's reduction; framed as the store,
    so its picture lies where the final's does; then the selections' stages."""
    from lodcast.renderer.frame.render import Renderer

    a = np.zeros((64, 64, 64), np.float32)
    a[20:44, 12:30, 30:58] = 1.0  # an opaque box off centre
    st = lodcast.ingest(a, tmp_path / "box.zarr", block_size=8, progress=False)
    tf = {"points": [{"value": 0.0, "color": [1, 1, 1], "opacity": 0.0},
                     {"value": 0.5, "color": [1, 0.8, 0.6], "opacity": 0.9}]}
    eng = Renderer()
    ladder = Ladder(preview_voxels=32**3, preview_level_voxels=16**3)
    sc = scene(tf=tf, quality={"reduction": 2}, width=64, height=64)
    stages = eng.render_progressive(st, sc, ladder=ladder)
    first = next(stages)
    rep = first.report
    assert rep["stage"] == 0 and not rep["final"] and rep["level"] == 2 and rep["quality"] == {"level": 2}
    assert rep["predicted_delta_e"] is None and rep["reduction"] == 64.0 and rep["image_scale"] == 0.5
    assert eng.bricks.reads == 0 and len(eng.tables.tf) == 0  # no brick, no error table yet
    rest = list(stages)
    final = rest[-1]
    assert final.report["final"] and final.report["predicted_delta_e"] is not None
    np.testing.assert_array_equal(final.rgba, Renderer().render(st, sc).rgba)
    # where the box shows: the same place within a preview pixel (two of the final's)
    ya, yb = (np.nonzero(s.rgba[..., 3] > 0.5) for s in (first, final))
    for p, q in zip(ya, yb):
        assert abs(p.min() - q.min()) <= 2 and abs(p.max() - q.max()) <= 2 and abs(p.mean() - q.mean()) <= 1.0
    assert np.abs(first.rgba[..., 3] - final.rgba[..., 3]).mean() < 0.05
