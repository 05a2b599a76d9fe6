"""Write the generated pages of docs/ from the code itself, so that they cannot drift from what lodcast accepts
(tests/test_docs.py regenerates each and compares):

- reference.md: the pydantic models (scene, TF, jobs, responses, settings), the presets, the report's fields, the
  HTTP routes (the OpenAPI schema) and the environment variables;
- cli.md: every `lodcast` command from its argparse parser (help, arguments, options, examples);
- python.md: the public API (`lodcast.__all__`) from its signatures and docstrings.

    python docs/generate.py            # rewrite them (and docs/images/camera.png if missing)
"""
from __future__ import annotations

import argparse
import inspect
import re
import sys
import typing
from pathlib import Path
from typing import Any

DOCS = Path(__file__).resolve().parent
SKIP = {"SceneError"}


def _type(annotation: Any) -> str:
    """A field's type as a reader wants it: int, float in [0, 1], "a" | "b", list of X, ..."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Annotated:
        base, *meta = args
        shown = next((m for m in meta if isinstance(getattr(m, "model", None), type)), None)
        if shown is not None:  # a field validated as `base`, typed in the schema as a model (a job's scene)
            text = _type(shown.model) + ("" if getattr(shown, "tf_required", True) else ", `tf` optional")
            meta = [m for m in meta if m is not shown]
        else:
            text = _type(base)
        bounds = []
        for m in meta:  # a constraint itself, or a FieldInfo holding them
            for c in (m, *(getattr(m, "metadata", None) or ())):
                for attr, sym in (("ge", "≥"), ("gt", ">"), ("le", "≤"), ("lt", "<")):
                    v = getattr(c, attr, None)
                    if v is not None:
                        bounds.append(f"{sym} {v:g}" if isinstance(v, (int, float)) else f"{sym} {v}")
        return f"{text} ({', '.join(bounds)})" if bounds else text
    if origin is typing.Literal:
        return " \\| ".join(f'`"{a}"`' if isinstance(a, str) else f"`{str(a).lower()}`" if isinstance(a, bool)
                             else f"`{a}`" for a in args)
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        parts = [_type(a) for a in args if a is not type(None)]
        return " or ".join(parts) + (" or null" if type(None) in args else "")
    if origin in (list, tuple):
        if origin is tuple and args and all(a == args[0] for a in args):
            return f"[{_type(args[0])}] × {len(args)}"
        return f"list of {_type(args[0])}" if args else "list"
    if origin is dict:
        return "object"
    if isinstance(annotation, type):
        return {"str": "string", "int": "integer", "float": "number", "bool": "boolean", "Path": "path"}.get(
            annotation.__name__, f"[{annotation.__name__}](#{annotation.__name__.lower()})")
    return str(annotation).replace("typing.", "")


def _default(field: Any) -> str:
    from pydantic_core import PydanticUndefined

    if field.default_factory is not None:
        try:
            value = field.default_factory()
        except TypeError:
            return "(computed)"
        return "`{}`" if value == {} else "`[]`" if value == [] else "its fields' defaults"
    if field.default is PydanticUndefined:
        return "**required**"
    import json

    return f"`{json.dumps(field.default, default=str)}`"


def _model(cls: Any, level: str = "###") -> str:
    doc = " ".join((cls.__doc__ or "").split())
    rows = ["| field | type | default | |", "|---|---|---|---|"]
    for name, f in cls.model_fields.items():
        rows.append(f"| `{f.alias or name}` | {_type(f.annotation if not f.metadata else typing.Annotated[(f.annotation, *f.metadata)])} "
                    f"| {_default(f)} | {' '.join((f.description or '').split())} |")
    return f"{level} {cls.__name__}\n\n{doc}\n\n" + "\n".join(rows) + "\n"


def _typed_dict(cls: Any, level: str = "###") -> str:
    """A TypedDict's keys and their types, as a table (what each means is its caller's to add)."""
    doc = " ".join((cls.__doc__ or "").split())
    rows = ["| key | type |", "|---|---|"]
    rows += [f"| `{k}` | {_type(t)} |" for k, t in typing.get_type_hints(cls).items()]
    return f"{level} {cls.__name__}\n\n{doc}\n\n" + "\n".join(rows)


def camera_picture(path: Path) -> None:
    """The orbit camera's angles drawn on a volume's box."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig = plt.figure(figsize=(6, 5), dpi=100)
    ax = fig.add_subplot(projection="3d")
    r = np.array([-1, 1])
    for a in r:
        for b in r:
            ax.plot(r, [a, a], [b, b], color="0.6")
            ax.plot([a, a], r, [b, b], color="0.6")
            ax.plot([a, a], [b, b], r, color="0.6")
    for vec, name in (((2.2, 0, 0), "+x"), ((0, 2.2, 0), "+y"), ((0, 0, 2.2), "+z (up)")):
        ax.quiver(0, 0, 0, *vec, color="k", arrow_length_ratio=0.08)
        ax.text(*(1.08 * np.array(vec)), name)
    eye = np.array([0, -3.2, 0])
    ax.scatter(*eye, color="tab:red", s=40)
    ax.text(*(eye + (-2.6, 0, -1.1)), "eye at azimuth 0, elevation 0\n(looks towards +y)", color="tab:red")
    t = np.linspace(0, np.pi / 3, 30)
    ax.plot(3.2 * np.sin(t), -3.2 * np.cos(t), 0 * t, color="tab:blue")
    ax.text(2.0, -2.6, -0.3, "azimuth +: towards +x", color="tab:blue")
    ax.plot(0 * t, -3.2 * np.cos(t), 3.2 * np.sin(t), color="tab:green")
    ax.text(0, -1.6, 2.9, "elevation +: towards +z", color="tab:green")
    ax.set_box_aspect((1, 1, 1))
    ax.set_axis_off()
    ax.view_init(elev=22, azim=-60)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def reference() -> str:
    import warnings

    from lodcast.environment import VARIABLES
    from lodcast.renderer.image import report as rp
    from lodcast.renderer.scene import scene as sc
    from lodcast.renderer.scene.presets import catalogue
    from lodcast.service import jobs, models
    from lodcast.service.app import create_app
    from lodcast.service.settings import Settings

    out = ["# lodcast reference", "",
           "Generated from the code by `python docs/generate.py`: every field lodcast accepts, with its type, bounds "
           "and default. Units: data values are the volume's own (Hounsfield units for CT); lengths on the volume are "
           "world units (the store's spacing: millimetres for medical scans); `sampling.step` is in voxels of the "
           "finest level; angles are degrees; opacity is per `unit_distance` world units (default: the smallest "
           "spacing); images are premultiplied RGBA (`npy`) or straight-alpha 8-bit sRGB (`png`).", "",
           "## Scene", "",
           "A scene is one JSON object (Python: a dict, a `lodcast.Scene`, or a JSON file's name). Only `tf` is "
           "required.", "", _model(sc.Scene)]
    for cls in (sc.OrbitCamera, sc.LookAtCamera, sc.QualityReduction, sc.QualityBudget, sc.QualityLevel,
                sc.QualityMaxDeltaE, sc.QualityMaxMs, sc.Sampling, sc.Shading,
                sc.Clip, sc.ClipPlane, sc.ClipBox):
        out.append(_model(cls))
    out += ["## Camera conventions", "",
            "World coordinates are the store's: voxel (z, y, x) sits at origin + index × spacing, and the world's "
            "x, y, z axes run along the volume's x, y, z. For a source with patient geometry (DICOM, NIfTI, NRRD) "
            "`lodcast info` gives `orientation`, the patient direction (LPS letters) of world +x, +y, +z, and "
            "`direction`; `lodcast ingest --orient LPS` turns the array (axes swapped and reversed, no resampling) "
            "so that +x, +y, +z point left, posterior, superior. The orbit camera circles the box's centre: "
            "azimuth 0, elevation 0 looks from −y towards +y with +z up (in LPS: at the face); a positive azimuth "
            "turns the eye towards +x, a positive elevation lifts it towards +z; `distance` is in multiples of the "
            "box's bounding-sphere radius; `view` names a side of the patient instead. Images have row 0 at the "
            "top.", "",
            "![the orbit camera](images/camera.png)", "",
            "## Transfer functions", "",
            "`tf` (and `tf2`) is a piecewise-linear function of the data value, constant beyond its first and last "
            "points; or a preset's name (below); or an adaptive preset, placed on each volume's histogram.", "",
            _model(sc.TransferFunction), _model(sc.TFPoint), _model(sc.AdaptiveTF),
            "### Presets", "", "| name | what |", "|---|---|"]
    for name, tf in sorted(catalogue().items()):
        if "template" in tf:
            out.append(f"| `{name}` | adaptive: {tf['description']} |")
        else:
            pts = ", ".join(f"{p['value']:g} → {p['opacity']:g}" for p in tf["points"])
            out.append(f"| `{name}` | CT (HU), value → opacity: {pts} |")
    out += ["", "## Jobs", "", "`POST /jobs`, `lodcast submit`: one JSON object whose `kind` says which. Scenes in "
            "jobs are scenes as above.", ""]
    for cls in (jobs.TurntableJob, jobs.ScenesJob, jobs.TfSweepJob, jobs.VolumesJob, jobs.IngestJob):
        out.append(_model(cls))
    out += ["A job's status (`GET /jobs/{id}`, what `lodcast submit` and `lodcast jobs` print):", "",
            _model(models.JobStatus), _model(models.Progress),
            "## Render report", "", "Every render returns one (`RenderResult.report`, the `X-Lodcast-Report` header, "
            "`lodcast render --report FILE`): a JSON object, in Python a plain dict typed `lodcast.RenderReport` (a "
            "TypedDict).", "", "| key | type | meaning |", "|---|---|---|"]
    hints = typing.get_type_hints(rp.RenderReport)
    out += [f"| `{k}` | {_type(hints[k])} | {v} |" for k, v in rp.REPORT_FIELDS.items()]
    out += ["", _typed_dict(rp.PriorityMapReport), "", _typed_dict(rp.ScreenReport), "", _typed_dict(rp.ChosenReport),
            "", _typed_dict(rp.ChosenSetting)]
    out += ["", "## HTTP routes", "", "OpenAPI (with every body and answer typed) at `/openapi.json`; Swagger UI at "
            "`/docs`. With `LODCAST_TOKEN` set, every route but `/healthz` and the docs needs "
            "`Authorization: Bearer TOKEN`. Errors are JSON `{\"detail\": ...}` naming the field.", "",
            "| method | path | what | answers |", "|---|---|---|---|"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        spec = create_app(Settings(root=DOCS / ".unused", token=None, workers=0)).openapi()
    for path, ops in spec["paths"].items():
        for method, op in ops.items():
            out.append(f"| {method.upper()} | `{path}` | {op.get('summary', '')} | {', '.join(sorted(op['responses']))} |")
    out += ["", _model(models.VolumeSummary), _model(models.VolumeUnreadable), _model(models.Level), _model(models.Health), _model(models.ErrorBody),
            _model(models.FieldError),
            "## Environment variables", "", "The store's and renderer's (read at each use):", "",
            "| variable | default | what |", "|---|---|---|"]
    out += [f"| `{name}` | {default} | {what} |" for name, default, what in VARIABLES]
    out += ["", "The service's (`lodcast serve`, `lodcast worker`; each also a keyword of "
            "`lodcast.service.settings.Settings`):", "", "| variable | default | what |", "|---|---|---|"]
    for name, f in Settings.model_fields.items():
        out.append(f"| `LODCAST_{name.upper()}` | {_default(f)} | {' '.join((f.description or '').split())} |")
    return "\n".join(out).rstrip() + "\n"


def _cell(text: str) -> str:
    """Text fit for one cell of a Markdown table: one line, pipes escaped."""
    return " ".join(text.split()).replace("|", "\\|")


def cli() -> str:
    """docs/cli.md: every command of `lodcast` as its argparse parser defines it."""
    from lodcast.service.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    summaries = {a.dest: a.help or "" for a in sub._choices_actions}
    out = ["# lodcast command line", "",
           "Generated by `python docs/generate.py` from the command's own parsers: what `lodcast COMMAND --help` "
           "prints, as one page. Every command exits 0 on success and 2 with one line naming the problem on bad "
           "input; `python -m lodcast` is the same command. Every field of a scene, a transfer function and a job "
           "is in [reference.md](reference.md).", "",
           f"{parser.description}", "",
           "| command | what |", "|---|---|"]
    out += [f"| [`{name}`](#lodcast-{name}) | {_cell(summaries.get(name, ''))} |" for name in sub.choices]
    out += ["", "Options every command takes: `--log-level {debug,info,warning,error}` (what the log on stderr "
            "shows, default warning; before or after the command's name), `-h`/`--help`; and `lodcast --version`.", ""]
    for name, cmd in sub.choices.items():
        fmt = cmd.formatter_class(prog=cmd.prog, width=100)
        fmt.add_usage(cmd.usage, cmd._actions, cmd._mutually_exclusive_groups, prefix="")
        usage = fmt.format_help().strip()
        out += [f"## lodcast {name}", "", _cell(cmd.description or summaries.get(name, "")), "",
                "```", usage, "```", ""]
        rows = []
        for action in cmd._actions:
            if isinstance(action, argparse._HelpAction) or action.dest == "log_level":
                continue
            invocation = fmt._format_action_invocation(action)
            what = fmt._expand_help(action) if action.help else ""
            if action.required and action.option_strings:
                what = f"**required**; {what}"
            rows.append(f"| `{_cell(invocation)}` | {_cell(what)} |")
        if rows:
            out += ["| argument | what |", "|---|---|", *rows, ""]
        examples = (cmd.epilog or "").split("\n")[1:]
        if examples:
            out += ["Examples:", "", "```bash", *(line[2:] if line.startswith("  ") else line for line in examples),
                    "```", ""]
    return "\n".join(out).rstrip() + "\n"


#: the methods of these classes that docs/python.md lists (the others, all their public methods)
_METHODS = {"Renderer": ("render", "prepare", "prefetch", "check_cost", "visibility", "close")}
#: pydantic models: fields are in docs/reference.md under these headings
_MODELS = {"Scene": "scene", "JobStatus": "jobstatus", "VolumeSummary": "volumesummary"}
#: TypedDicts: keys are in docs/reference.md under these headings
_TYPED = {"RenderReport": "render-report"}


def _annotation(annotation: Any) -> str:
    """An annotation as its source wrote it: no quotes, no module paths inside lodcast, None for NoneType."""
    text = annotation if isinstance(annotation, str) else inspect.formatannotation(annotation)
    text = re.sub(r"\blodcast(?:\.\w+)*\.(?=[A-Z_])", "", text.replace('"', "").replace("'", ""))
    text = text.replace("typing.", "").replace("collections.abc.", "").replace("numpy.", "np.")
    return text.replace("NoneType", "None")


def _signature(name: str, obj: Any, prefix: str = "def ", returns: bool = True) -> str:
    """`def name(a: int, *, b: str = 'x') -> T`, one parameter a line when it is long."""
    try:
        sig = inspect.signature(obj)
    except (TypeError, ValueError):
        return f"{prefix}{name}(...)"
    shown: list[str] = []
    star = False
    for p in sig.parameters.values():
        if p.name == "self":
            continue
        if p.kind is inspect.Parameter.KEYWORD_ONLY and not star:
            shown.append("*")
        if p.kind in (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.VAR_POSITIONAL):
            star = True
        text = {inspect.Parameter.VAR_POSITIONAL: "*", inspect.Parameter.VAR_KEYWORD: "**"}.get(p.kind, "") + p.name
        if p.annotation is not p.empty:
            text += f": {_annotation(p.annotation)}"
        if p.default is not p.empty:
            default = "<factory>" if "factory" in repr(p.default) else repr(p.default)
            text += f" = {default}" if p.annotation is not p.empty else f"={default}"
        shown.append(text)
    ret = sig.return_annotation
    tail = "" if ret is sig.empty or not returns else f" -> {_annotation(ret)}"
    one = f"{prefix}{name}({', '.join(shown)}){tail}"
    if len(one) <= 110:
        return one
    return f"{prefix}{name}(\n" + "".join(f"    {t},\n" for t in shown) + f"){tail}"


def _doc(obj: Any) -> str:
    doc = inspect.getdoc(obj) or ""
    return doc.strip()


def _is_alias(obj: Any) -> bool:
    """A type alias (`StoreLike = Store | str | ...`), not a class or function."""
    return typing.get_origin(obj) in (typing.Union, getattr(__import__("types"), "UnionType", None))


def _alias_doc(name: str) -> str:
    """The `#:` comment above `NAME: TypeAlias = ...` in the module lodcast takes NAME from."""
    import importlib

    import lodcast

    lines = inspect.getsource(importlib.import_module(lodcast._LAZY[name][0])).splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith(f"{name}: TypeAlias"))
    doc: list[str] = []
    while at > 0 and lines[at - 1].startswith("#:"):
        at -= 1
        doc.insert(0, lines[at][2:].strip())
    return " ".join(doc)


def _what(name: str, obj: Any) -> str:
    return _alias_doc(name) if _is_alias(obj) else _doc(obj)


def _public_methods(cls: type) -> list[str]:
    names: list[str] = []
    for klass in cls.__mro__:
        if klass is object or klass.__module__.split(".")[0] in ("pydantic", "builtins"):
            continue
        for n, v in vars(klass).items():
            if not n.startswith("_") and n not in names and (inspect.isfunction(v) or isinstance(v, classmethod)):
                names.append(n)
    return names


def python_api() -> str:
    """docs/python.md: `lodcast.__all__`, each with its signature and docstring."""
    import lodcast

    names = [n for n in lodcast.__all__ if n != "__version__"]
    errors = [n for n in names if isinstance(getattr(lodcast, n), type) and issubclass(getattr(lodcast, n), Exception)]
    out = ["# lodcast Python API", "",
           "Generated by `python docs/generate.py` from the signatures and docstrings of what `import lodcast` "
           "exports (`lodcast.__all__`). `import lodcast` is cheap: each name is imported when first used. Scenes, "
           "transfer functions, jobs and reports, field by field, are in [reference.md](reference.md); the "
           "conventions (axes, camera, opacity, ΔE) in [design.md](design.md).", "",
           "| name | what |", "|---|---|"]
    for n in names:
        first = _what(n, getattr(lodcast, n)).split("\n\n")[0]
        out.append(f"| [`{n}`](#{'errors' if n in errors else n.lower()}) | {_cell(first)} |")
    out.append("")
    for n in names:
        if n in errors:
            continue
        obj = getattr(lodcast, n)
        out += [f"## {n}", ""]
        if inspect.isfunction(obj):
            out += ["```python", _signature(f"lodcast.{n}", obj), "```", "", _doc(obj), ""]
            continue
        if _is_alias(obj):
            out += ["```python", f"lodcast.{n} = {_annotation(obj)}", "```", "", _alias_doc(n), ""]
            continue
        if typing.is_typeddict(obj):
            out += ["```python", f"class lodcast.{n}(TypedDict)", "```", "", _doc(obj), "",
                    f"Its keys, each with its type and meaning, are in [reference.md](reference.md#{_TYPED[n]}).", ""]
            continue
        if n in _MODELS:
            fields = ", ".join(f"`{f.alias or k}`" for k, f in obj.model_fields.items())
            out += ["```python", f"class lodcast.{n}(pydantic.BaseModel)", "```", "", _doc(obj), "",
                    f"Fields: {fields}; each with its type, default and meaning in "
                    f"[reference.md](reference.md#{_MODELS[n]}).", ""]
        else:
            out += ["```python", _signature(f"lodcast.{n}", obj, prefix="class ", returns=False), "```", "", _doc(obj), ""]
        if n == "AsyncClient":  # the same methods as Client's, each awaited: their signatures in one block
            out += ["Its methods, each `Client`'s of the same name awaited (`close` is `aclose`):", "", "```python",
                    *(_signature(m, getattr(obj, m), prefix="async def ") for m in _public_methods(obj)), "```", ""]
            continue
        for m in _METHODS.get(n, _public_methods(obj)):
            if n in _MODELS and m not in vars(obj):
                continue
            meth = getattr(obj, m)
            prefix = "@classmethod\ndef " if isinstance(inspect.getattr_static(obj, m), classmethod) else "def "
            out += [f"### {n}.{m}", "", "```python", _signature(m, meth, prefix=prefix), "```", ""]
            doc = _doc(meth)
            if doc:
                out += [doc, ""]
    out += ["## Errors", "",
            "Every error lodcast raises on purpose derives from `LodcastError`, and also from the built-in error it "
            "is a kind of, so `except FileNotFoundError` or `except ValueError` catch them too. The command line "
            "prints them as one line and exits 2; the service answers them with a 4xx status and a JSON `detail` "
            "naming the field or the file ([design.md](design.md#errors)).", "",
            "| error | derives from | when |", "|---|---|---|"]
    for n in errors:
        cls = getattr(lodcast, n)
        bases = ", ".join(f"`{b.__name__}`" for b in cls.__bases__)
        out.append(f"| `{n}` | {bases} | {_cell(_doc(cls))} |")
    return "\n".join(out).rstrip() + "\n"


#: every generated page and what makes it
PAGES = {"reference.md": reference, "cli.md": cli, "python.md": python_api}


def main() -> int:
    sys.path.insert(0, str(DOCS.parent))
    for name, make in PAGES.items():
        (DOCS / name).write_text(make())
        print(f"wrote {DOCS / name}")
    if not (DOCS / "images" / "camera.png").exists() or "--images" in sys.argv:
        camera_picture(DOCS / "images" / "camera.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
