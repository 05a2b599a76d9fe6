"""Write docs/reference.md from the code itself: the pydantic models (scene, TF, jobs, responses, settings), the
presets, the report's fields, the HTTP routes (the OpenAPI schema) and the environment variables, so that the
reference cannot drift from what lodcast accepts (tests/test_docs.py regenerates it and compares).

    python docs/generate.py            # rewrite docs/reference.md (and docs/images/camera.png if missing)
"""
from __future__ import annotations

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
        return " \\| ".join(f'`"{a}"`' if isinstance(a, str) else f"`{a}`" for a in args)
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
        return "`{}`" if value == {} else "`[]`" if value == [] else f"its fields' defaults"
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
    from lodcast.renderer.scene import scene as sc
    from lodcast.renderer.scene.presets import catalogue
    from lodcast.renderer.tools.report_fields import REPORT_FIELDS
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
    for cls in (sc.OrbitCamera, sc.LookAtCamera, sc.QualityReduction, sc.QualityBudget, sc.Sampling, sc.Shading,
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
            "`lodcast render --report FILE`).", "", "| key | meaning |", "|---|---|"]
    out += [f"| `{k}` | {v} |" for k, v in REPORT_FIELDS.items()]
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
    out += ["", _model(models.VolumeSummary), _model(models.Level), _model(models.Health), _model(models.ErrorBody),
            "## Environment variables", "", "The store's and renderer's (read at each use):", "",
            "| variable | default | what |", "|---|---|---|"]
    out += [f"| `{name}` | {default} | {what} |" for name, default, what in VARIABLES]
    out += ["", "The service's (`lodcast serve`, `lodcast worker`; each also a keyword of "
            "`lodcast.service.settings.Settings`):", "", "| variable | default | what |", "|---|---|---|"]
    for name, f in Settings.model_fields.items():
        out.append(f"| `LODCAST_{name.upper()}` | {_default(f)} | {' '.join((f.description or '').split())} |")
    return "\n".join(out).rstrip() + "\n"


def main() -> int:
    sys.path.insert(0, str(DOCS.parent))
    (DOCS / "reference.md").write_text(reference())
    if not (DOCS / "images" / "camera.png").exists() or "--images" in sys.argv:
        camera_picture(DOCS / "images" / "camera.png")
    print(f"wrote {DOCS / 'reference.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
