"""`lodcast render STORE -o OUT.png|.jpg|.webp|.tif|.npy [--scene scene.json] [--report out.json] [--progressive] [shortcuts]`.

The scene file is the JSON scene of docs/design.md; flag shortcuts override it (or build one from nothing, with
--tf): --width --height --azimuth --elevation --distance --fov --tf TF.json --tf2 TF.json --step --mode --isovalue
--jitter --seed --background. --azimuth/--elevation/--distance make the camera the orbit form; --fov applies to either form.
The output format follows OUT's extension; an 8-bit image is composited over opaque black unless the scene or
--background gives a background (docs/design.md), a .npy is the integral as produced. Bad input raises
SceneError/ImageError/StoreNotFound (LodcastError), which the CLI turns into exit code 2 and one line, in the order a
user fixes them: the store, then the output (and --report) path and format, then the scene.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from lodcast.renderer.kernel.config import MODES
from lodcast.renderer.scene.presets import preset_names
from lodcast.renderer.scene.scene import SceneError

if TYPE_CHECKING:
    from lodcast.renderer.scene.scene import Scene

__all__ = ["add_parser", "add_scene_options", "run", "scene_data", "scene_from_args"]


def _floats(name: str, n: int) -> Callable[[str], tuple[float, ...]]:
    def parse(text: str) -> tuple[float, ...]:
        try:
            vals = tuple(float(p) for p in text.split(",") if p.strip())
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be {n} comma-separated numbers, got {text!r}") from None
        if len(vals) != n:
            raise argparse.ArgumentTypeError(f"{name} must be {n} comma-separated numbers, got {text!r}")
        return vals

    return parse


def _quality(text: str) -> Any:
    """--quality: "full" | "lossless" | "30" or "30:1" (a reduction) | "level1" (every visible block at level 1) |
    JSON; the scene validates the value."""
    t = text.strip()
    if t in ("full", "lossless"):
        return t
    if t.startswith("level") and t[5:].isdigit():
        return {"level": int(t[5:])}
    if t.startswith("{"):
        try:
            return json.loads(t)
        except json.JSONDecodeError as exc:
            raise argparse.ArgumentTypeError(f"not valid JSON ({exc.msg} at character {exc.pos})") from None
    try:
        return {"reduction": float(t[:-2] if t.endswith(":1") else t)}
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected full, lossless, a reduction such as 30 or 30:1, a level "
                                         "such as level1, or JSON "
                                         "such as {\"budget_mb\": 64}") from None


def _background(text: str) -> tuple[float, ...]:
    """--background: "transparent" or r,g,b,a in [0, 1]."""
    if text.strip().lower() == "transparent":
        return (0.0, 0.0, 0.0, 0.0)
    try:
        return _floats("--background", 4)(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"--background must be transparent or 4 comma-separated numbers r,g,b,a, "
                                         f"got {text!r}") from None


#: the 8-bit image formats, which the CLI composites over opaque black unless a background is given
OPAQUE_BY_DEFAULT = ("png", "jpg", "webp", "tif")


def add_parser(sub: argparse._SubParsersAction, func: Callable[[argparse.Namespace], int]) -> argparse.ArgumentParser:
    p = sub.add_parser("render", help="render a store locally to an image (PNG, JPEG, WebP, TIFF) or .npy "
                       "(float32 premultiplied RGBA)")
    p.add_argument("store", help="a lodcast store (folder written by `lodcast ingest`)")
    p.add_argument("-o", "--output", required=True, help="image to write: OUT.png, OUT.jpg, OUT.webp, OUT.tif (8-bit "
                   "sRGB; JPEG has no alpha) or OUT.npy (float32 premultiplied RGBA, the integral as produced)")
    p.add_argument("--scene", help="scene JSON file (camera, width, height, tf, quality, sampling, shading, clip, mode, ...: docs/reference.md); the flags below override its fields")
    p.add_argument("--report", help="write the render report (JSON) here")
    p.add_argument("--progressive", action="store_true",
                   help="render coarse to fine: each stage before the last is written as OUT-stage0.png, "
                        "OUT-stage1.png, ... (OUT's suffix), the last, at the scene's quality, as OUT; one line per "
                        "stage on stderr")
    add_scene_options(p)
    p.set_defaults(func=func)
    return p


def add_scene_options(p: argparse.ArgumentParser, *, sweep: bool = False) -> None:
    """The flag shortcuts of a scene (what `scene_data` reads); `sweep` (lodcast report, which sweeps quality and
    sampling) leaves out --quality, --step, --jitter and --seed."""
    names = ", ".join(preset_names())
    p.add_argument("--tf", help="transfer function: a JSON file or inline JSON ({\"points\": [...], \"unit_distance\": d}) "
                   f"or a preset: {names}")
    p.add_argument("--tf2", help="a second transfer function (file or preset), composited over the first: what it "
                   "shows stays visible inside what --tf hides (e.g. --tf ct-body --tf2 ct-dense)")
    p.add_argument("--width", type=int, help="image width in pixels (default 512)")
    p.add_argument("--height", type=int, help="image height in pixels (default 512)")
    p.add_argument("--azimuth", type=float, help="orbit camera: degrees, 0 looks from -y, turning towards +x")
    p.add_argument("--elevation", type=float, help="orbit camera: degrees towards +z")
    p.add_argument("--distance", type=float, help="orbit camera: multiples of the box's bounding-sphere radius")
    p.add_argument("--fov", type=float, help="vertical field of view in degrees")
    if not sweep:
        target = p.add_mutually_exclusive_group()
        target.add_argument("--quality", type=_quality, help="full, lossless, a data reduction (30 or 30:1: "
                            "{\"reduction\": 30}), every visible block at one store level (level1: {\"level\": 1}) or a "
                            "quality as JSON ({\"budget_mb\": 64})")
        target.add_argument("--max-delta-e", type=float, metavar="X", help="a quality target: the fastest setting "
                            "(step, full resolution or a reduction, interpolation, adaptive screen sampling) whose "
                            "predicted ΔE is at most X ({\"max_delta_e\": X}; the report's chosen says what it "
                            "picked)")
        target.add_argument("--max-ms", type=float, metavar="T", help="a quality target: the best predicted quality "
                            "predicted to render within T milliseconds on this device ({\"max_ms\": T})")
        p.add_argument("--step", type=float, help="sampling step in voxels of the finest level")
    p.add_argument("--mode", choices=MODES, help="composite (default), mip, minip, average or iso (with --isovalue)")
    p.add_argument("--isovalue", type=float, help="mode iso: the data value of the surface")
    p.add_argument("--shading", action=argparse.BooleanOptionalAction, default=None,
                   help="local illumination (Blinn-Phong, a headlight); --no-shading turns a scene's off")
    if not sweep:
        p.add_argument("--jitter", action=argparse.BooleanOptionalAction, default=None, help="jittered ray start")
        p.add_argument("--seed", type=int, help="jitter seed")
    p.add_argument("--background", type=_background,
                   help="r,g,b,a in [0,1] (straight colour and opacity), or transparent; " + (
                       "default the scene's, else transparent" if sweep else
                       "when neither this nor the scene gives one, 8-bit images (png, jpg, webp, tif) are composited "
                       "over opaque black (0,0,0,1) and a .npy is the integral as produced"))


def _load_json(path: str, what: str) -> Any:
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise SceneError(f"{what} {path!r}: no such file") from None
    except OSError as exc:
        raise SceneError(f"{what} {path!r}: {exc.strerror or exc}") from None
    except json.JSONDecodeError as exc:
        raise SceneError(f"{what} {path!r}: not valid JSON ({exc})") from None


def scene_from_args(args: argparse.Namespace) -> Scene:
    """The Scene the flags describe (validated; SceneError naming the field otherwise)."""
    from lodcast.renderer.scene.scene import Scene

    return Scene.parse(scene_data(args))


def scene_data(args: argparse.Namespace) -> dict[str, Any]:
    """The scene the flags describe, as JSON data (--scene's file with the shortcuts applied), not yet validated;
    SceneError for a file or TF that cannot be read, or no TF at all."""
    data: dict[str, Any] = {}
    if args.scene:
        data = _load_json(args.scene, "--scene")
        if not isinstance(data, dict):
            raise SceneError(f"--scene {args.scene!r}: a scene must be a JSON object")
    for key in ("tf", "tf2"):
        v = getattr(args, key)
        if v in preset_names():
            data[key] = v
        elif v and v.lstrip().startswith("{"):  # the TF itself, inline
            try:
                data[key] = json.loads(v)
            except json.JSONDecodeError as exc:
                raise SceneError(f"--{key}: not valid JSON ({exc.msg} at character {exc.pos})") from None
        elif v and not Path(v).exists():
            raise SceneError(f"--{key} {v!r}: no such file, inline JSON, nor a preset (presets: {', '.join(preset_names())})")
        elif v:
            data[key] = _load_json(v, f"--{key}")
    if "tf" not in data:
        raise SceneError("tf: a transfer function is required (in --scene or with --tf)")
    for key in ("width", "height", "mode", "isovalue", "quality"):
        if getattr(args, key, None) is not None:
            data[key] = getattr(args, key)
    for key in ("max_delta_e", "max_ms"):  # (argparse keeps them and --quality apart)
        if getattr(args, key, None) is not None:
            data["quality"] = {key: getattr(args, key)}
    if args.shading is not None:
        data["shading"] = (data.get("shading") or {}) if args.shading else None
    if args.background is not None:
        data["background"] = list(args.background)
    cam = dict(data.get("camera") or {})
    orbit = {k: getattr(args, k) for k in ("azimuth", "elevation", "distance") if getattr(args, k) is not None}
    if orbit:
        if "eye" in cam or "target" in cam:
            cam = {k: v for k, v in cam.items() if k in ("fov", "projection", "view_height")}
        cam.update(orbit)
    if args.fov is not None:
        cam["fov"] = args.fov
    if cam:
        data["camera"] = cam
    sampling = dict(data.get("sampling") or {})
    for key in ("step", "jitter", "seed"):
        if getattr(args, key, None) is not None:
            sampling[key] = getattr(args, key)
    if sampling:
        data["sampling"] = sampling
    return data


def stage_path(out: Path, k: int) -> Path:
    """Where `lodcast render --progressive -o OUT` writes stage `k` before the last: OUT-stage{k} with OUT's suffix."""
    return out.with_name(f"{out.stem}-stage{k}{out.suffix}")


def _progressive(store: Any, scene: Scene, out: Path, fmt: str) -> Any:
    """The stages of `scene`, each before the last written beside `out` (stage_path) as it arrives, one line each on
    stderr; the last stage's result (its caller writes it to `out`)."""
    from lodcast.renderer.frame.render import render_progressive

    for result in render_progressive(store, scene):
        r = result.report
        pred = r["predicted_delta_e"]
        where = out if r["final"] else result.save(stage_path(out, r["stage"]), fmt)
        print(f"stage {r['stage']}{' (final)' if r['final'] else ''}: reduction "
              f"{'-' if r['reduction'] is None else format(r['reduction'], '.3g')}:1, predicted ΔE "
              f"{'-' if pred is None else format(pred, '.2f')}, {r['wall_ms']:.0f} ms since the start -> {where}",
              file=sys.stderr)
    return result


def run(args: argparse.Namespace) -> int:
    """`lodcast render`. Errors come in the order a user fixes them: the store, then the output (and --report)
    path and format, then the scene."""
    from lodcast.renderer.frame.render import render
    from lodcast.renderer.image.output import format_for
    from lodcast.renderer.scene.scene import Scene
    from lodcast.store.store import open_store

    store = open_store(args.store)  # StoreNotFound / StoreInvalid / StoreCorrupt name the path
    fmt = format_for(args.output)
    out = Path(args.output)
    if not out.parent.is_dir():
        raise SceneError(f"-o {args.output!r}: folder {str(out.parent)!r} does not exist")
    if args.report and not Path(args.report).parent.is_dir():
        raise SceneError(f"--report {args.report!r}: folder does not exist")
    data = scene_data(args)
    if "background" not in data and fmt in OPAQUE_BY_DEFAULT:
        data["background"] = [0.0, 0.0, 0.0, 1.0]  # as VTK and ParaView show a volume; --background transparent keeps alpha
    scene = Scene.parse(data)
    result = _progressive(store, scene, out, fmt) if args.progressive else render(store, scene)
    result.save(out, fmt)
    if args.report:
        rp = Path(args.report)
        tmp = rp.with_name(f".{rp.name}.tmp{os.getpid()}")
        tmp.write_text(json.dumps(result.report, indent=2))
        os.replace(tmp, rp)
    r = result.report
    print(f"wrote {out} ({scene.width}x{scene.height}, {fmt}) in {r['wall_ms']:.0f} ms "
          f"(kernel {r['kernel_ms']:.1f} ms, {r['samples']} samples)", file=sys.stderr)
    return 0
