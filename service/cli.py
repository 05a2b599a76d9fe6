"""The `lodcast` command. Each subcommand is a small function; bad input exits 2 with a one-line reason."""
from __future__ import annotations

import argparse
import json
import logging
import os
import re
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from lodcast.errors import LodcastError
from lodcast.faults import storage_fault
from lodcast.store.remote import is_url

__all__ = ["main", "UsageError"]


class UsageError(LodcastError, ValueError):
    """A command-line argument is wrong; the message names it."""


LOG_LEVELS = ("debug", "info", "warning", "error")


class _Help(argparse.RawDescriptionHelpFormatter):
    """Examples kept as written; every option's default said, where it has one and its help does not say it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (default in (None, False, argparse.SUPPRESS) or "default" in text or not action.option_strings
                or isinstance(action, (argparse._HelpAction, argparse._VersionAction))):
            return text
        return f"{text} (default {default})"


#: what `lodcast COMMAND --help` shows under its options
EXAMPLES = {
    "ingest": ("convert a volume file into a lodcast store: levels of detail, per-block histograms, OME-Zarr "
               "metadata; written atomically (nothing is left on failure)",
               "lodcast ingest ct_series/ chest.zarr                       # a DICOM folder\n"
               "lodcast ingest head.nii.gz head.zarr --block-size 32\n"
               "lodcast ingest scan.raw scan.zarr --shape 128,256,256 --dtype uint16 --spacing 1.5,0.7,0.7"),
    "info": ("print a store's attributes as JSON: shape, spacing, levels, blocks, shards, size on disk",
             "lodcast info chest.zarr"),
    "verify": ("read every file of a store and check its checksums (a scrub): exit 0 clean, 1 damage found (each "
               "damaged file listed on stdout), 2 not a store. A store written before checksums (format 3 or "
               "older) is read whole and said to carry none",
               "lodcast verify chest.zarr\n"
               "lodcast verify chest.zarr --workers 8"),
    "upgrade": ("rewrite a store written by an older lodcast in the current format (checksums, stored-type rule), "
                "in place and atomically, from its own level 0: the source file is not needed",
                "lodcast upgrade chest.zarr"),
    "render": ("render one image of a store on this machine's OpenCL device; the scene's fields (camera, tf, "
               "quality, sampling, shading, clip, mode, ...) are described in docs/reference.md. 8-bit images "
               "(png, jpg, webp, tif) are composited over opaque black unless the scene or --background gives a "
               "background; a .npy is the float32 premultiplied RGBA as the integral produced it",
               "lodcast render chest.zarr -o chest.png --tf ct-bone --azimuth 30 --elevation 15\n"
               "lodcast render chest.zarr -o bone.png --tf ct-bone --background transparent   # keeps the alpha\n"
               "lodcast render head.zarr -o head.jpg --tf '{\"points\": [{\"value\": 40, \"opacity\": 0}, "
               "{\"value\": 120, \"opacity\": 0.6}]}'\n"
               "lodcast render head.zarr -o lod.png --scene examples/head-lod.scene.json --report report.json   # 30:1, shading\n"
               "lodcast render chest.zarr -o chest.png --tf ct-bone --progressive   # chest-stage0.png, chest-stage1.png, then chest.png"),
    "kernels": ("build the kernel programs a store's usual scenes need (full resolution, lossless, 30:1 with "
                "nearest-block and interblock interpolation, unlit and lit; --scene adds others), so that no first "
                "picture waits for a compiler: builds stay on disk for every later process",
                "lodcast kernels chest.zarr\n"
                "lodcast kernels chest.zarr --scene examples/head-lod.scene.json"),
    "serve": ("serve the HTTP API (OpenAPI at /docs) over the stores under a root, with a job queue and a worker",
              "lodcast serve --root stores/ --port 8000\n"
              "LODCAST_TOKEN=secret lodcast serve --root stores/ --host 0.0.0.0 --queue redis://localhost:6379/0\n"
              "lodcast serve --root s3://bucket/volumes --queue redis://queue-host:6379/0   # AWS_* credentials"),
    "worker": ("run batch jobs from the queue: SIGTERM or Ctrl-C finishes the frame and hands the job back",
               "lodcast worker --root stores/ --queue redis://queue-host:6379/0 --threads 2"),
    "submit": ("submit a batch job (turntable, scenes, tf_sweep, volumes, ingest) to a server, or run it here "
               "without one", "lodcast submit examples/turntable.job.json --url http://127.0.0.1:8000 --wait\n"
               "lodcast submit examples/turntable.job.json --root stores/        # no server: runs here"),
    "jobs": ("list, show, cancel or wait for batch jobs, or fetch their results (frames, and a turntable's "
             "animation); they are looked up on the server at --url (or LODCAST_URL), else in the local queue "
             "under --root (or LODCAST_ROOT)",
             "lodcast jobs list --state running\nlodcast jobs wait JOB_ID --timeout 600\n"
             "lodcast jobs results JOB_ID -o frames/"),
    "report": ("measure the levels of detail of a store on this machine: time, reduction, predicted and measured ΔE, "
               "for a scene (--scene, or made with the flags as `lodcast render` takes them)",
               "lodcast report chest.zarr --tf ct-bone --width 256 --height 256 -o report/"),
    "demo": ("fetch a real MR head from a package registry, ingest it, render pictures and serve it",
             "lodcast demo\nlodcast demo --size 512 --no-serve"),
    "presets": ("the named transfer functions a scene may give as \"tf\": NAME", "lodcast presets\nlodcast presets --json"),
}


#: one or more numbers separated by commas (or x), the first negative
_NUMBERS = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?([,x][-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?)*$")


class _Parser(argparse.ArgumentParser):
    """Malformed arguments exit 2 with one line (argparse's own error prints the whole usage first); every
    (sub)command takes ``--log-level``, so that it may stand before or after the command's name."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        kwargs.setdefault("formatter_class", _Help)
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        # a value such as "-680.05,-59.2,-201.2" (an origin) is a value, not an option: argparse takes only a
        # lone negative number for one, and no option of ours starts with a digit
        self._negative_number_matcher = _NUMBERS
        self.add_argument("--log-level", choices=LOG_LEVELS, default=argparse.SUPPRESS,
                          help="what the log on stderr shows (default warning)")

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (see {self.prog} --help)\n")


def _triple(kind: type, name: str) -> Callable[[str], tuple]:
    def parse(text: str) -> tuple:
        parts = [p for p in text.replace("x", ",").split(",") if p.strip()]
        try:
            values = tuple(kind(p) for p in parts)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be three comma-separated numbers z,y,x, got {text!r}") from None
        if len(values) != 3:
            raise argparse.ArgumentTypeError(f"{name} must be three comma-separated numbers z,y,x, got {text!r}")
        return values

    return parse


# --- ingest / info -------------------------------------------------------------------------------------------

def _add_ingest(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("ingest", help="convert a volume file (npy, raw, NRRD, NIfTI, TIFF, DICOM folder, zarr) into a lodcast store")
    p.add_argument("src", help="source file, or a DICOM / TIFF series folder")
    p.add_argument("dest", help="store to write (a folder, conventionally NAME.zarr)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing store at DEST")
    p.add_argument("--format", help="source format when the extension does not tell (npy, raw, nrrd, nifti, tiff, dicom, zarr)")
    p.add_argument("--shape", type=_triple(int, "--shape"), help="raw only: z,y,x")
    p.add_argument("--dtype", help="raw only: numpy dtype name, e.g. uint16")
    p.add_argument("--byte-order", choices=("little", "big"), default="little", help="raw only (default little)")
    p.add_argument("--header-bytes", type=int, default=0, help="raw only: bytes to skip at the start")
    p.add_argument("--spacing", type=_triple(float, "--spacing"), help="voxel spacing z,y,x in world units (overrides the file's)")
    p.add_argument("--origin", type=_triple(float, "--origin"), help="world position z,y,x of voxel (0,0,0)'s centre")
    p.add_argument("--units", help="unit of the spacing (mm, um, nm, cm, m; overrides the file's)")
    p.add_argument("--index", type=int, help="which volume of a 4D series (time point or channel) to ingest")
    # store.readers.reorient.ORIENTS, spelled out so that `lodcast --help` does not import the readers
    p.add_argument("--orient", choices=("LPS", "source"), default="LPS",
                   help="LPS (default): turn DICOM, NIfTI or NRRD data with patient geometry so that x, y, z point to "
                        "the patient's left, posterior, superior (axes swapped and reversed, no resampling): every "
                        "format then shows the face at azimuth 0; source: keep the file's array axes. A source "
                        "without patient geometry keeps its axes either way")
    p.add_argument("--block-size", type=int, default=16, help="block edge B in voxels, a power of two (default 16)")
    p.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None, help="progress bar (default: when stderr is a terminal)")
    p.add_argument("--json", action="store_true", help="print the store's attributes as JSON (what `lodcast info` prints) "
                   "instead of a short summary")
    p.set_defaults(func=_cmd_ingest)


def _summary(dest: Any, info: dict[str, Any]) -> tuple[str, str]:
    """A store's summary in two parts: its volume (shape, type, spacing, values) and its layout (levels, blocks,
    size on disk), as ingest and the demo print them."""
    shape, spacing = "x".join(map(str, info["shape"])), " x ".join(f"{v:g}" for v in info["spacing"])
    lo, hi = info["value_range"]
    on_disk = "" if info["bytes_on_disk"] is None else f", {info['bytes_on_disk'] / 1e6:.1f} MB on disk"
    values = "no finite values" if lo is None or hi is None or lo != lo else f"values {lo:g} .. {hi:g}"
    return (f"{dest}: {shape} {info['dtype']} voxels (z, y, x) of {spacing} {info['units'] or 'units'}, {values}",
            f"{len(info['levels'])} levels, {info['blocks']} blocks of {info['block_size']}³{on_disk}")


def _cmd_ingest(args: argparse.Namespace) -> int:
    from lodcast.malloc import tame_malloc
    from lodcast.store.ingest import ingest

    tame_malloc()
    t0 = time.perf_counter()
    try:
        store = ingest(args.src, args.dest, overwrite=args.overwrite, format=args.format, shape=args.shape,
                       dtype=args.dtype, byte_order=args.byte_order, header_bytes=args.header_bytes,
                       spacing=args.spacing, origin=args.origin, index=args.index, block_size=args.block_size,
                       progress=args.progress, units=args.units, orient=args.orient)
    except OSError as exc:  # a full disk names no file of its own: say where it was writing
        if exc.filename is None and not isinstance(exc, LodcastError):
            exc.filename = args.dest
        raise
    info = store.summary()
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    volume, layout = _summary(args.dest, info)
    print(f"{volume}\n  {layout}, in {time.perf_counter() - t0:.1f} s (`lodcast info {args.dest}` for everything)")
    turned = (info.get("source") or {}).get("reoriented")
    if turned:
        print(f"  the file's axes point {', '.join(turned['source_axes'])}: turned to {', '.join(info['orientation'] or [])} "
              f"(x, y, z) by reversing and swapping axes, no resampling (--orient source keeps them)")
    kept = (info.get("source") or {}).get("orientation_kept")
    if kept:
        print(f"  {kept}")
    for warning in (info.get("source") or {}).get("warnings", []):
        print(f"  notice: {warning}")
    return 0


def _add_info(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="print a store's attributes, levels, blocks, shards and size on disk as JSON")
    p.add_argument("store", help="a lodcast store (a folder written by `lodcast ingest`)")
    p.set_defaults(func=_cmd_info)


def _cmd_info(args: argparse.Namespace) -> int:
    from lodcast.store.store import open_store

    print(json.dumps(open_store(args.store).summary(), indent=2))
    return 0


def _add_verify(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("verify", help="read every file of a store and check its checksums; list what is damaged")
    p.add_argument("store", help="a lodcast store (a local folder)")
    p.add_argument("--workers", type=int, default=None, help="threads reading files (default: 2 per CPU, at most 16)")
    p.set_defaults(func=_cmd_verify)


def _cmd_verify(args: argparse.Namespace) -> int:
    from lodcast.store.verify import verify

    show = sys.stderr.isatty()

    def progress(done: int, total: int) -> None:
        if show and (done == total or done % 64 == 0):
            print(f"\rlodcast verify: {done}/{total} files", end="\n" if done == total else "", file=sys.stderr)

    result = verify(args.store, workers=args.workers, progress=progress)
    for d in result.damage:
        print(f"{d.file or args.store}: {d.reason}")
    size = f"{result.files} data files, {result.bytes / 1e6:.1f} MB"
    if not result.checksums:
        print(f"{args.store}: format {result.format_version} carries no checksums (written before format 4): "
              f"{size} read and decoded; `lodcast upgrade {args.store}` adds them", file=sys.stderr)
    if result.damage:
        print(f"{args.store}: {len(result.damage)} damaged files; re-ingest the store", file=sys.stderr)
        return 1
    print(f"{args.store}: clean ({size})", file=sys.stderr)
    return 0


def _add_upgrade(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("upgrade", help="rewrite an older store in the current format, in place, without its source")
    p.add_argument("store", help="a lodcast store (a local folder)")
    p.set_defaults(func=_cmd_upgrade)


def _cmd_upgrade(args: argparse.Namespace) -> int:
    from lodcast.store.upgrade import upgrade

    done = upgrade(args.store, progress=sys.stderr.isatty())
    now = f"format {done.store.format_version} ({done.store.dtype.name})"
    if not done.rewritten:
        print(f"{args.store}: already {now}; nothing to do")
    else:
        print(f"{args.store}: format {done.from_format} ({done.from_dtype}) -> {now}")
    return 0


# --- service: serve / worker / submit / jobs (implemented in lodcast.service.commands) ----------------------

def _add_serve(sub: argparse._SubParsersAction) -> None:
    from lodcast.service.commands import add_serve

    add_serve(sub)


def _add_worker(sub: argparse._SubParsersAction) -> None:
    from lodcast.service.commands import add_worker

    add_worker(sub)


def _add_submit(sub: argparse._SubParsersAction) -> None:
    from lodcast.service.commands import add_submit

    add_submit(sub)


def _add_jobs(sub: argparse._SubParsersAction) -> None:
    from lodcast.service.commands import add_jobs

    add_jobs(sub)


# --- report -------------------------------------------------------------------------------------------------

def _add_report(sub: argparse._SubParsersAction) -> None:
    from lodcast.renderer.tools.cli_render import add_scene_options

    p = sub.add_parser("report", help="error against run time: one scene at every quality, interpolation and stepping, vs its reference")
    p.add_argument("store", help="a lodcast store (a folder written by `lodcast ingest`)")
    p.add_argument("--scene", help="scene JSON (its quality and sampling options are swept); the flags below "
                   "override its fields, or make one with --tf")
    p.add_argument("-o", "--out", default="report", help="folder for report.md, report.json and report.png (default ./report)")
    p.add_argument("--repeat", type=int, default=2, help="timed renders per configuration after a warm-up (default 2)")
    p.add_argument("--no-adaptive", action="store_true", help="leave out adaptive object-space sampling")
    p.add_argument("--no-naive", action="store_true", help="leave out naive adaptive stepping")
    p.add_argument("--no-steps", action="store_true",
                   help="leave out full resolution at steps 2, 1, 1/2, 1/4 with and without pre-integration")
    add_scene_options(p, sweep=True)
    p.set_defaults(func=_cmd_report)


def _cmd_report(args: argparse.Namespace) -> int:
    from lodcast.renderer.scene.scene import Scene
    from lodcast.renderer.tools.cli_render import scene_data
    from lodcast.renderer.tools.quality_report import default_variants, run_report, table, write_report
    from lodcast.store.store import open_store

    store = open_store(args.store)  # in the order a user fixes them: the store, the output, then the scene
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"-o {args.out}: not a folder")
    if args.repeat < 1:
        raise UsageError(f"--repeat must be at least 1, got {args.repeat}")
    scene = scene_data(args)
    dual = Scene.parse(scene).tf2 is not None  # a bad scene fails here, naming the field, before any rendering
    result = run_report(store, scene, default_variants(adaptive=not args.no_adaptive, naive=not args.no_naive,
                                                           steps=not args.no_steps, dual=dual), repeat=args.repeat)
    paths = write_report(result, out)
    print(table(result))
    print(f"wrote {paths['table']}, {paths['json']} and {paths['plot']}")
    return 0


# --- demo -----------------------------------------------------------------------------------------------------

def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="fetch a real MR head from a package registry, ingest it and show what lodcast does")
    p.add_argument("--out", default="demo-output", help="folder for the store and the pictures (default ./demo-output)")
    p.add_argument("--size", type=int, default=384, help="picture width and height in pixels (default 384)")
    p.add_argument("--serve", action=argparse.BooleanOptionalAction, default=True, help="end by serving the volume over HTTP (default on)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0: every interface)")
    p.add_argument("--port", type=int, default=8000, help="TCP port to listen on")
    p.set_defaults(func=_cmd_demo)


def _cmd_demo(args: argparse.Namespace) -> int:
    from lodcast.service.demo import fetch_demo_volume
    from lodcast.store.ingest import ingest
    from lodcast.store.store import open_store

    out = Path(args.out)
    vol = fetch_demo_volume()
    print(f"demo volume: {vol.description}\n  file: {vol.path}\n  licence: {vol.licence}")
    dest = out / f"{vol.name}.zarr"
    store = open_store(dest) if dest.exists() else ingest(vol.path, dest, progress=None)
    s = store.summary()
    volume, layout = _summary(dest, s)
    print(f"{volume}; {layout}")
    from lodcast.renderer.tools.demo import render_demo

    pictures = render_demo(store, out / "pictures", size=args.size)
    print(f"{len(pictures)} pictures in {out / 'pictures'} (each with its scene as JSON: lodcast render {dest} --scene FILE -o OUT.png)")
    if not args.serve:
        return 0
    from lodcast.service.commands import serve_forever

    return serve_forever(root=out, host=args.host, port=args.port)


# --- presets -------------------------------------------------------------------------------------------------

def _add_presets(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("presets", help="list the named transfer functions (a scene may give \"tf\": NAME)")
    p.add_argument("--json", action="store_true", help="print every preset's TF as JSON")
    p.set_defaults(func=_cmd_presets)


def _cmd_presets(args: argparse.Namespace) -> int:
    from lodcast.renderer.scene.presets import catalogue

    presets = catalogue()
    if args.json:
        print(json.dumps(presets, indent=2))
        return 0
    for name, tf in sorted(presets.items()):
        if "template" in tf:
            print(f"{name:14s} adaptive: {tf['description']}")
            continue
        pts = tf["points"]
        print(f"{name:14s} {len(pts)} points, values {pts[0]['value']:g} .. {pts[-1]['value']:g} (CT, Hounsfield units)")
    return 0


# --- entry point ---------------------------------------------------------------------------------------------

def _add_render(sub: argparse._SubParsersAction) -> None:
    from lodcast.renderer.tools.cli_render import add_parser

    add_parser(sub, _cmd_render)


def _cmd_render(args: argparse.Namespace) -> int:
    from lodcast.renderer.tools.cli_render import run

    return run(args)


def _add_kernels(sub: argparse._SubParsersAction) -> None:
    from lodcast.renderer.tools.cli_kernels import add_parser

    add_parser(sub, _cmd_kernels)


def _cmd_kernels(args: argparse.Namespace) -> int:
    from lodcast.renderer.tools.cli_kernels import run

    return run(args)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="lodcast", description="Render large scalar volumes with transfer-function-driven level of detail.")
    parser.add_argument("--version", action="version", version=f"lodcast {__import__('lodcast').__version__}")
    parser.set_defaults(log_level="warning")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in (_add_ingest, _add_info, _add_verify, _add_upgrade, _add_render, _add_kernels, _add_serve, _add_worker, _add_submit, _add_jobs, _add_report, _add_demo, _add_presets):
        add(sub)
    for name, command in sub.choices.items():
        command.description, examples = EXAMPLES[name]
        command.epilog = "examples:\n" + "\n".join("  " + line for line in examples.split("\n"))
    return parser




def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)  # exits 2 with one line on malformed arguments (_Parser.error)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    logging.getLogger("lodcast").setLevel(args.log_level.upper())  # the libraries below stay at warning
    _announce_slow_builds(args.command, args.log_level)
    try:
        return int(args.func(args) or 0)
    except BrokenPipeError:
        # the reader of our output went away (`lodcast info S | head`): nothing more to say, and nowhere to say it
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except Exception as exc:
        # User errors, the environment's (a full disk, a permission) and the storage's (object storage unreachable,
        # whichever library's error says so): one line, exit 2, no traceback (what was being written is gone: ingest
        # and frames write atomically). Anything else is a bug and keeps its traceback.
        if not isinstance(exc, (LodcastError, OSError, ValueError)) and storage_fault(exc) is None:
            raise
        print(f"lodcast {args.command}: error: {_one_line(exc, _store(args))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"lodcast {args.command}: interrupted", file=sys.stderr)
        return 130


class _Stderr(logging.StreamHandler):
    """Writes to sys.stderr as it is when a record comes (main() may run in a process that swaps it later)."""

    def emit(self, record: logging.LogRecord) -> None:
        self.stream = sys.stderr
        super().emit(record)


def _announce_slow_builds(command: str, log_level: str) -> None:
    """A first kernel build can take tens of seconds: the first one of this process that takes over a second says
    what it builds, once, at INFO on the logger lodcast.opencl.build (lodcast/opencl.py), which the command shows
    on stderr unless --log-level is error (libraries leave it quiet)."""
    build_log = logging.getLogger("lodcast.opencl.build")  # by name: no pyopencl import for commands that build nothing
    handler = _Stderr()
    handler.setFormatter(logging.Formatter(f"lodcast {command}: %(message)s"))
    build_log.handlers[:] = [handler]
    build_log.setLevel(logging.INFO if log_level != "error" else logging.ERROR)
    build_log.propagate = False  # said once, not again by the root handler at --log-level info


def _store(args: argparse.Namespace) -> str | None:
    """The store or store root a command works on, as the user named it."""
    named = (getattr(args, key, None) for key in ("dest", "store", "root"))
    return next((str(v) for v in named if isinstance(v, (str, Path))), None)


def _one_line(exc: BaseException, store: str | None = None) -> str:
    why = storage_fault(exc)
    if why is not None and store is not None and is_url(store) and not isinstance(exc, LodcastError):
        return " ".join(f"{store} is unavailable ({why})".split())  # the library's message names a request, not the store
    if isinstance(exc, OSError) and exc.strerror and not isinstance(exc, LodcastError):
        where = f" ({exc.filename})" if exc.filename else ""
        return " ".join(f"{exc.strerror}{where}".split())
    text = str(exc) or type(exc).__name__
    return " ".join(text.split())


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
