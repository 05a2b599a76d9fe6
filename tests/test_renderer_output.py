"""Image output (PNG straight alpha 8-bit, .npy float32 premultiplied) and the `lodcast render` command."""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from lodcast.renderer.image.output import ImageError, save_image, to_straight_rgba8

TF = {"points": [{"value": 0.1, "color": [1, 0.5, 0], "opacity": 0.0}, {"value": 1, "color": [1, 0.5, 0], "opacity": 0.5}]}


def test_png_is_straight_alpha_and_npy_premultiplied(tmp_path):
    rgba = np.zeros((2, 3, 4), np.float32)
    rgba[0, 0] = (0.25, 0.125, 0.0, 0.5)  # premultiplied: straight colour (0.5, 0.25, 0), alpha 0.5
    rgba[1, 2] = (1.0, 1.0, 1.0, 1.0)
    save_image(tmp_path / "a.png", rgba)
    save_image(tmp_path / "a.npy", rgba)
    png = np.asarray(Image.open(tmp_path / "a.png"))
    assert png.shape == (2, 3, 4) and png.dtype == np.uint8
    assert png[0, 0].tolist() == [128, 64, 0, 128]
    assert png[1, 2].tolist() == [255, 255, 255, 255] and png[0, 1].tolist() == [0, 0, 0, 0]
    back = np.load(tmp_path / "a.npy")
    assert back.dtype == np.float32 and np.array_equal(back, rgba)
    assert to_straight_rgba8(np.full((1, 1, 4), np.nan, np.float32)).tolist() == [[[0, 0, 0, 0]]]


SUFFIXES = ".png, .jpg (.jpeg), .webp, .tif (.tiff) or .npy"


def test_bad_output_names_are_refused(tmp_path):
    for name, got in (("a.gif", "got .gif"), ("a", "got no extension")):
        with pytest.raises(ImageError, match=re.escape(f"the name must end in {SUFFIXES}, {got}")):
            save_image(tmp_path / name, np.zeros((1, 1, 4), np.float32))
    with pytest.raises(ImageError, match="format must be one of jpg, npy, png, tif, webp, got 'bmp'"):
        save_image(tmp_path / "a.png", np.zeros((1, 1, 4), np.float32), format="bmp")
    with pytest.raises(ImageError, match="does not exist"):
        save_image(tmp_path / "no" / "a.png", np.zeros((1, 1, 4), np.float32))
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_jpeg_webp_and_tiff_are_written_as_such(tmp_path):
    """Issue 46, item 3: -o x.jpg / .webp / .tif write those formats (Pillow): WebP (lossless) and TIFF keep the
    straight alpha a PNG has; JPEG has none, so the image is composited over opaque black (its premultiplied
    colour)."""
    rgba = np.zeros((4, 6, 4), np.float32)
    rgba[0, 0] = (0.25, 0.125, 0.0, 0.5)  # premultiplied; straight (0.5, 0.25, 0), alpha 0.5
    rgba[1:, 2:] = (0.2, 0.6, 1.0, 1.0)
    straight = to_straight_rgba8(rgba)
    for name, fmt in (("a.webp", "WEBP"), ("a.tif", "TIFF"), ("a.tiff", "TIFF"), ("b.TIF", "TIFF")):
        path = save_image(tmp_path / name, rgba)
        im = Image.open(path)
        assert im.format == fmt and im.mode == "RGBA", (name, im.format, im.mode)
        np.testing.assert_array_equal(np.asarray(im), straight)
    for name in ("a.jpg", "a.jpeg", "c.JPG"):
        im = Image.open(save_image(tmp_path / name, rgba))
        assert im.format == "JPEG" and im.mode == "RGB"
        error = np.abs(np.asarray(im).astype(int) - np.round(rgba[..., :3] * 255))  # over black: the premultiplied
        assert error.mean() < 4 and error[0, 0].max() <= 6, (name, error.mean())  # JPEG is lossy, not that lossy
    assert not list(tmp_path.glob(".*"))  # written atomically: no temporary left


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    import lodcast

    d = tmp_path_factory.mktemp("cli")
    zz, yy, xx = np.mgrid[:16, :20, :24].astype(np.float32)
    np.save(d / "v.npy", np.exp(-(((xx - 12) / 5) ** 2 + ((yy - 10) / 4) ** 2 + ((zz - 8) / 3) ** 2)).astype(np.float32))
    lodcast.ingest(d / "v.npy", d / "v.zarr")
    return d / "v.zarr"


def lodcast_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lodcast.service.cli", *map(str, args)], capture_output=True,
                          text=True, timeout=120)


def test_cli_render_scene_file_flags_and_report(store, tmp_path):
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps({"tf": TF, "width": 24, "height": 16, "camera": {"azimuth": 10, "elevation": 5}}))
    tf = tmp_path / "tf.json"
    tf.write_text(json.dumps(TF))
    p = lodcast_cli("render", store, "-o", tmp_path / "o.npy", "--scene", scene, "--report", tmp_path / "r.json",
                    "--width", 20, "--step", 0.25)
    assert p.returncode == 0, p.stderr
    img = np.load(tmp_path / "o.npy")
    assert img.shape == (16, 20, 4) and img.dtype == np.float32 and img[..., 3].max() > 0.05
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["width"] == 20 and rep["step_world"] == 0.25 and "build_options" in rep
    p = lodcast_cli("render", store, "-o", tmp_path / "o.png", "--tf", tf, "--width", 12, "--height", 10,
                    "--azimuth", 90, "--elevation", 30, "--distance", 3, "--fov", 40, "--mode", "mip")
    assert p.returncode == 0, p.stderr
    assert np.asarray(Image.open(tmp_path / "o.png")).shape == (10, 12, 4)


def test_cli_quality_shortcut(store, tmp_path):
    """--quality takes full, lossless, a reduction as 4 or 4:1, or JSON, into the scene's quality (the report says
    what was asked and what the selection reached); anything else exits 2 naming the flag."""
    tf = tmp_path / "tf.json"
    tf.write_text(json.dumps(TF))
    for given, want in (("4:1", {"reduction": 4.0}), ("4", {"reduction": 4.0}), ("lossless", "lossless"),
                        ('{"budget_mb": 0.01}', {"budget_mb": 0.01})):
        p = lodcast_cli("render", store, "-o", tmp_path / "q.npy", "--tf", tf, "--width", 16, "--height", 12,
                        "--quality", given, "--report", tmp_path / "q.json")
        assert p.returncode == 0, (given, p.stderr)
        rep = json.loads((tmp_path / "q.json").read_text())
        assert rep["quality"] == want and "-DLC_SAMPLER_ATLAS" in rep["build_options"], (given, rep["quality"])
        if "reduction" in want:
            assert rep["reduction"] >= 4.0 - 1e-9
    p = lodcast_cli("render", store, "-o", tmp_path / "q.npy", "--tf", tf, "--quality", "lots")
    assert p.returncode == 2 and "--quality" in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr


def test_cli_tf_preset_renders_as_its_points(tmp_path):
    """`--tf ct-bone` is the preset's points: the same image as the same TF given as a file, and a volume in
    Hounsfield units shows bone (1000 HU) and hides soft tissue (40 HU)."""
    import lodcast
    from lodcast.renderer.scene.transfer_function import CT_PRESETS

    hu = np.full((12, 16, 16), 40, np.int16)
    hu[4:8, 5:11, 5:11] = 1000
    lodcast.ingest(hu, tmp_path / "hu.zarr", progress=False)
    tf = tmp_path / "bone.json"
    tf.write_text(json.dumps(CT_PRESETS["ct-bone"]))
    images = []
    for arg in ("ct-bone", tf):
        p = lodcast_cli("render", tmp_path / "hu.zarr", "-o", tmp_path / "o.npy", "--tf", arg, "--width", 16,
                        "--height", 16, "--azimuth", 0, "--elevation", 0)
        assert p.returncode == 0, p.stderr
        images.append(np.load(tmp_path / "o.npy"))
    np.testing.assert_array_equal(images[0], images[1])
    alpha = images[0][..., 3]
    assert alpha[8, 8] > 0.9 and alpha[0, 0] == 0.0


@pytest.mark.parametrize("args, needle", [
    (["--scene", "{missing}"], "--scene"),
    (["--tf", "{tf}", "--width", "0"], "width"),
    (["--tf", "{tf}", "--step", "-1"], "sampling.step"),
    (["--tf", "{tf}", "--fov", "200"], "camera.fov"),
    ([], "tf:"),
    (["--tf", "{tf}", "--out-of-range"], "unrecognized"),
    (["--tf", "{tf}", "--tf2", "ct-nope"], "--tf2 'ct-nope': no such file, inline JSON, nor a preset (presets: auto, ct-body,"),
    (["--tf", "{tf}", "--tf2", "ct-dense", "--mode", "mip"], "tf2: a second transfer function needs mode"),
])
def test_cli_render_bad_input_exits_2_with_one_line(store, tmp_path, args, needle):
    tf = tmp_path / "tf.json"
    tf.write_text(json.dumps(TF))
    args = [a.format(tf=tf, missing=tmp_path / "nope.json") for a in args]
    p = lodcast_cli("render", store, "-o", tmp_path / "o.png", *args)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert needle in lines[-1] and (len(lines) == 1 or "usage" in p.stderr)
    assert not (tmp_path / "o.png").exists()


def test_cli_render_bad_output_and_store(store, tmp_path):
    tf = tmp_path / "tf.json"
    tf.write_text(json.dumps(TF))
    p = lodcast_cli("render", store, "-o", tmp_path / "o.gif", "--tf", tf)
    assert p.returncode == 2 and SUFFIXES in p.stderr
    p = lodcast_cli("render", tmp_path / "nostore", "-o", tmp_path / "o.png", "--tf", tf)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1


def test_cli_render_reports_errors_in_the_order_a_user_fixes_them(store, tmp_path, capsys):
    """Issue 46, item 3: `lodcast render nosuch.zarr -o x.png` says the store is missing (exit 2, one line naming
    the path), not that a TF is required: the store first, then the output path and format, then the scene."""
    from lodcast.service.cli import main

    def error(*args: object) -> str:
        assert main(["render", *map(str, args)]) == 2
        (line,) = capsys.readouterr().err.strip().splitlines()
        assert line.startswith("lodcast render: error: "), line
        return line

    missing = tmp_path / "nosuch.zarr"
    for bad_rest in (["-o", tmp_path / "x.png"], ["-o", tmp_path / "x.gif"], ["-o", tmp_path / "no" / "x.png"],
                     ["-o", tmp_path / "x.png", "--tf", "ct-nope", "--width", "0"]):
        assert error(missing, *bad_rest) == f"lodcast render: error: no store at {missing}"
    (tmp_path / "empty").mkdir()
    assert "is not a lodcast store" in error(tmp_path / "empty", "-o", tmp_path / "x.gif")
    # a store: then the output
    assert SUFFIXES in error(store, "-o", tmp_path / "x.gif")
    assert "does not exist" in error(store, "-o", tmp_path / "no" / "x.png", "--tf", "ct-nope")
    assert "--report" in error(store, "-o", tmp_path / "x.png", "--report", tmp_path / "no" / "r.json")
    # a store and an output: then the scene
    assert "tf: a transfer function is required" in error(store, "-o", tmp_path / "x.png")
    assert "width" in error(store, "-o", tmp_path / "x.png", "--tf", "ct-bone", "--width", "0")
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]


def test_cli_8bit_images_are_over_opaque_black_unless_a_background_is_given(store, tmp_path, capsys):
    """Issue 46, item 3: the CLI's default background is opaque black for 8-bit outputs (as VTK's and ParaView's
    are); `--background transparent` keeps the straight alpha, a scene's own background is kept, and a .npy is the
    integral as produced."""
    tf = tmp_path / "tf.json"
    tf.write_text(json.dumps(TF))
    common = ["--tf", tf, "--width", 24, "--height", 16, "--azimuth", 10]

    from lodcast.service.cli import main

    def render(name: str, *extra: object) -> np.ndarray:
        assert main(["render", str(store), "-o", str(tmp_path / name), *map(str, common), *map(str, extra)]) == 0
        path = tmp_path / name
        return np.load(path) if path.suffix == ".npy" else np.asarray(Image.open(path))

    integral = render("o.npy")
    assert integral[..., 3].min() == 0.0 and integral[..., 3].max() > 0.05  # the volume does not fill the frame
    straight = to_straight_rgba8(integral)
    for name in ("o.png", "o.webp", "o.tif"):
        img = render(name)
        if img.shape[-1] == 4:  # WebP leaves out an alpha channel that is opaque everywhere
            assert (img[..., 3] == 255).all(), name
        np.testing.assert_allclose(img[..., :3], np.round(integral[..., :3] * 255), atol=1, err_msg=name)
    jpg = render("o.jpg").astype(int)
    assert np.abs(jpg - np.round(integral[..., :3] * 255)).mean() < 3
    np.testing.assert_array_equal(render("t.png", "--background", "transparent"), straight)
    np.testing.assert_array_equal(render("t.npy", "--background", "transparent"), integral)
    white = render("w.png", "--background", "1,1,1,1")
    assert white[0, 0].tolist() == [255, 255, 255, 255]
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps({"tf": TF, "background": [0, 0, 1, 1]}))
    assert render("s.png", "--scene", scene)[0, 0].tolist() == [0, 0, 255, 255]  # the scene's own
    with pytest.raises(SystemExit) as exit_:
        main(["render", str(store), "-o", str(tmp_path / "x.png"), "--tf", str(tf), "--background", "grey"])
    assert exit_.value.code == 2 and "transparent or 4 comma-separated numbers" in capsys.readouterr().err


SLOW_BUILDS = """
import sys, time
import pyopencl as cl

_build, builds = cl.Program.build, []


def slow(self, *args, **kwargs):  # the two compiles after the device's probe take over a second, as first builds do
    builds.append(1)
    if 2 <= len(builds) <= 3:
        time.sleep(1.1)
    return _build(self, *args, **kwargs)


cl.Program.build = slow
if sys.argv[1] == "cli":
    from lodcast.service.cli import main

    sys.exit(main(sys.argv[2:]))
import lodcast

lodcast.render(sys.argv[2], {"tf": "ct-bone", "width": 8, "height": 8})
"""


def test_a_slow_kernel_build_says_what_it_builds_once_on_the_cli_only(store, tmp_path):
    """Issue 46, item 3: a kernel build that takes over a second prints what it is building, once per process, on
    stderr, from the `lodcast` command only (a library call stays quiet). The kernel cache is empty, so that every
    program is compiled, and the first two compiles are made slow."""
    import os

    env = {**os.environ, "LODCAST_CACHE_DIR": str(tmp_path / "cache")}
    p = subprocess.run([sys.executable, "-c", SLOW_BUILDS, "cli", "render", str(store), "-o", str(tmp_path / "o.png"),
                        "--tf", "ct-bone", "--width", "8", "--height", "8"], capture_output=True, text=True, env=env,
                       timeout=300)
    assert p.returncode == 0, p.stderr
    said = [line for line in p.stderr.splitlines() if "building the OpenCL kernel" in line]
    assert len(said) == 1, p.stderr
    assert said[0].startswith("lodcast render: building the OpenCL kernel ") and "cached afterwards" in said[0]
    assert len(list((tmp_path / "cache" / "kernels").glob("*.bin"))) >= 2  # more than one build, one line
    assert p.stderr.splitlines()[-1].startswith("wrote ")
    env["LODCAST_CACHE_DIR"] = str(tmp_path / "cache2")
    p = subprocess.run([sys.executable, "-c", SLOW_BUILDS, "library", str(store)], capture_output=True, text=True,
                       env=env, timeout=300)
    assert p.returncode == 0, p.stderr
    assert "building" not in p.stderr and len(list((tmp_path / "cache2" / "kernels").glob("*.bin"))) >= 1


def test_demo_pictures_from_a_store(store, tmp_path):
    from lodcast.renderer.tools.demo import render_demo

    lines = []
    paths = render_demo(store, tmp_path / "demo", size=24, log=lines.append)
    assert len(paths) >= 4 and all(p.is_file() and p.suffix == ".png" for p in paths)
    assert all(p.with_name(p.stem + ".scene.json").is_file() for p in paths)
    assert str(tmp_path / "demo") in lines[-1]
    assert any(np.asarray(Image.open(p))[..., 3].max() > 0 for p in paths)


def test_pngs_carry_their_scene_report_and_srgb(tmp_path):
    """Issue 15, item 11: a saved or served PNG says how it was made (iTXt lodcast:scene / lodcast:report), is
    tagged sRGB, and a RenderResult shows itself in a notebook."""
    import json

    from PIL import Image

    import lodcast

    vol = np.random.default_rng(2).random((8, 8, 8)).astype(np.float32)
    r = lodcast.render(vol, {"tf": "ct-bone", "width": 12, "height": 10, "camera": {"azimuth": 15}})
    path = r.save(tmp_path / "p.png")
    im = Image.open(path)
    assert json.loads(im.text["lodcast:scene"])["camera"]["azimuth"] == 15
    assert json.loads(im.text["lodcast:report"])["kernel_ms"] == r.report["kernel_ms"]
    assert "srgb" in im.info
    assert r._repr_png_()[:8] == b"\x89PNG\r\n\x1a\n"
    np.testing.assert_array_equal(np.asarray(im), to_straight_rgba8(r.rgba))


def test_cli_render_takes_a_second_tf(store, tmp_path):
    tf = tmp_path / "tf.json"
    tf.write_text(json.dumps(TF))
    p = lodcast_cli("render", store, "-o", tmp_path / "o.npy", "--tf", tf, "--tf2", tf, "--width", "16",
                    "--height", "16", "--report", tmp_path / "r.json")
    assert p.returncode == 0, p.stderr
    rep = json.loads((tmp_path / "r.json").read_text())
    assert "-DLC_TF2" in rep["build_options"] and rep["tf2"] is True and rep["priority_map"] is not None
