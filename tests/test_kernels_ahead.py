"""Kernels built ahead (renderer/frame/ahead.py, `lodcast kernels`): the programs built for the usual scenes are
the ones their renders use, worked out from the store's metadata alone."""
from __future__ import annotations

import pytest

from lodcast.renderer.frame.ahead import AHEAD
from lodcast.renderer.frame.render import Renderer
from lodcast.service.cli import main
from lodcast.service.testing import TINY_TF, make_volume

SHELL = {"points": [{"value": 400, "color": [1, 1, 1], "opacity": 0.0},
                   {"value": 600, "color": [1, 1, 1], "opacity": 0.8}]}


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return make_volume(tmp_path_factory.mktemp("ahead"), "v", n=48, block_size=8)


def test_the_programs_built_ahead_are_the_ones_the_usual_scenes_render_with(store):
    eng = Renderer()
    try:
        built = eng.build_ahead(store)
        options = {b.options for b in built}
        assert len(options) == len(built) == len(AHEAD) + 4  # full: with and without its walk; lossless: all level 0
        for scene in AHEAD:
            for tf in (TINY_TF, SHELL):  # something in every cell; empty cells to skip
                r = eng.render(store, {**scene, "tf": tf, "width": 16, "height": 16})
                assert tuple(r.report["build_options"]) in options, (scene, tf)
        # a second engine finds them all compiled already (on disk), reading no voxel to find out which
        again = Renderer()
        try:
            assert {b.source for b in again.build_ahead(store)} == {"disk"}
        finally:
            again.close()
    finally:
        eng.close()


def test_the_command_names_each_program_and_refuses_a_missing_store(store, tmp_path, capsys):
    assert main(["kernels", str(store)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == len(AHEAD) + 4 and all(line.startswith(f"{store}: ") for line in lines)
    assert all("-DLC_SAMPLER_" in line for line in lines)
    assert main(["kernels", str(tmp_path / "nothing.zarr")]) == 2
    assert "nothing.zarr" in capsys.readouterr().err
    assert main(["kernels", str(store), "--scene", str(tmp_path / "absent.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--scene" in err[0] and "absent.json" in err[0]
    (tmp_path / "bad.json").write_text('{"quality": "sharp"}')
    assert main(["kernels", str(store), "--scene", str(tmp_path / "bad.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "quality" in err[0]
