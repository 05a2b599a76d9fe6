"""Error against run time: what each speed-up costs in image error (`lodcast report`).

One scene is rendered at every quality (full resolution, virtually lossless, reductions 5…100:1), with
nearest-block and interblock sampling, with and without adaptive object-space sampling (and its naive variant),
and at full resolution at the steps 2, 1, ½, ¼ with and without pre-integration,
and each image is compared with the scene's reference — its full-resolution render with a step of at most ¼ of
the smallest spacing and no LOD or adaptive sampling (docs/design.md) — by ΔE (mean, p95, max over the footprint).
Each configuration is rendered once to warm the brick cache and the program cache, then timed `repeat` times
(the fastest run counts: the machine is shared). Output: a Markdown table, JSON, and a PNG plot of ΔE against
milliseconds with the report's predicted ΔE (level of detail plus step) beside the measured one. Each level-of-detail
row also has the seam measure (renderer/image/seams.py): mean ΔE on the pixels whose rays cross a level change
against the rest, and the same over every face where a coarse block meets another (DESIGN.md's "no block grid":
≤ 1.5×), in the seam table below the main one.
"""
from __future__ import annotations

import json
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from lodcast.renderer.image.delta_e import delta_e_stats
from lodcast.renderer.image.seams import Crossings, crossings_of, seam_stats

__all__ = ["Variant", "default_variants", "run_report", "write_report", "target_front"]

REDUCTIONS = (5, 10, 20, 30, 60, 100)
STEPS = (2.0, 1.0, 0.5, 0.25)


@dataclass(frozen=True)
class Variant:
    quality: Any  # "full" | "lossless" | {"reduction": r} | {"budget_mb": m}
    interpolation: str = "interblock"
    adaptive: str = "off"  # "off" | "limited" | "naive"
    classification: str = "distribution"  # of coarse samples: "distribution" | "mean"
    step: float | None = None  # None: the scene's step
    preintegration: bool = False
    priority_map: bool = True  # dual-TF scenes: False renders without the priority map (what it buys)
    screen: str | None = None  # adaptive screen-space sampling with this statistic ("max" | "average" | "rms")

    @property
    def label(self) -> str:
        return (self._label() + ("" if self.priority_map else ", no priority map")
                + ("" if self.screen is None else f", adaptive screen ({self.screen})"))

    def _label(self) -> str:
        q = self.quality if isinstance(self.quality, str) else ", ".join(f"{k} {v}" for k, v in self.quality.items())
        if self.quality == "full":
            return ("full resolution" + ("" if self.step is None else f", step {self.step:g}")
                    + (", pre-integrated" if self.preintegration else "")
                    + ("" if self.adaptive == "off" else f", adaptive {self.adaptive}"))
        return (f"{q}, {self.interpolation.replace('_', ' ')}" + ("" if self.adaptive == "off" else f", adaptive {self.adaptive}")
                + ("" if self.classification == "distribution" else f", by {self.classification}"))

    def apply(self, scene: dict) -> dict:
        sampling = dict(scene.get("sampling") or {})
        if self.quality != "full":
            sampling["interpolation"] = self.interpolation
            sampling["classification"] = self.classification
        sampling["adaptive_object"] = self.adaptive != "off"
        if self.step is not None:
            sampling["step"] = self.step
        if self.preintegration:
            sampling["preintegration"] = True
        if not self.priority_map:
            sampling["priority_map"] = False
        if self.screen is not None:
            sampling["adaptive_screen"], sampling["screen_statistic"] = True, self.screen
        if self.adaptive == "naive":
            sampling["adaptive_naive"] = True
        else:
            sampling.pop("adaptive_naive", None)
        return {**scene, "quality": self.quality, "sampling": sampling, "format": "npy"}


def default_variants(adaptive: bool = True, naive: bool = True, steps: bool = True, dual: bool = False) -> list[Variant]:
    """The sweep: qualities × interpolation × adaptive stepping, and interblock classified by the mean beside the
    default classification by distribution; `steps`: full resolution at the steps STEPS with and without
    pre-integration (what the step costs, and what pre-integration buys back); `dual` (a scene with tf2): full
    resolution and 30:1 also without the priority map (its speed-up). 30:1 with adaptive screen-space sampling by
    each statistic (rays cast, speed-up, error)."""
    qualities: list[Any] = ["lossless"] + [{"reduction": r} for r in REDUCTIONS]
    out = [Variant("full")]
    if dual:
        out += [Variant("full", priority_map=False), Variant({"reduction": 30}, priority_map=False)]
    out += [Variant({"reduction": 30}, screen=stat) for stat in ("max", "average", "rms")]
    if steps:
        out += [Variant("full", step=st, preintegration=pre) for st in STEPS for pre in (False, True)]
    for q in qualities:
        out.append(Variant(q, "interblock", classification="mean"))
        for interp in ("nearest_block", "interblock"):
            out.append(Variant(q, interp))
            if adaptive:
                out.append(Variant(q, interp, "limited"))
                if naive:
                    out.append(Variant(q, interp, "naive"))
    return out


def reference_scene(scene: dict, store: Any) -> dict:
    """The scene's reference: full resolution, step ≤ ¼ of the smallest spacing, no LOD, no adaptive sampling."""
    sampling = dict(scene.get("sampling") or {})
    sampling["step"] = min(0.25, float(sampling.get("step", 0.5)))
    for key in ("adaptive_object", "adaptive_screen", "adaptive_naive", "jitter"):
        sampling.pop(key, None)
    return {**scene, "quality": "full", "sampling": sampling, "format": "npy"}


def run_report(store: Any, scene: dict, variants: Iterable[Variant] | None = None, repeat: int = 2,
               log: Callable[[str], Any] | None = None, reference: Any = None,
               renderer: Any = None) -> dict[str, Any]:
    """Render every variant (and the reference, unless `reference`, the RenderResult of `reference_scene`, is
    given) on `renderer` (default: lodcast.render's); return rows of error and time."""
    from lodcast.renderer.frame.render import default_renderer

    eng = renderer or default_renderer()
    render = eng.render

    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    variants = list(variants if variants is not None else default_variants())
    ref_scene = reference_scene(scene, store)
    t = time.perf_counter()
    ref = reference if reference is not None else render(store, ref_scene)
    log(f"reference: step {ref_scene['sampling']['step']} voxel, {ref.report['wall_ms']:.0f} ms")
    rows = []
    crossings: Crossings | None = None
    for i, v in enumerate(variants, 1):
        vs = v.apply(scene)
        first = render(store, vs)  # warms the program and brick caches
        best = first
        for _ in range(max(1, repeat)):
            r = render(store, vs)
            if r.report["wall_ms"] < best.report["wall_ms"]:
                best = r
        de = delta_e_stats(best.rgba, ref.rgba)
        rep = best.report
        rows.append({
            "label": v.label, "quality": v.quality, "interpolation": v.interpolation, "adaptive": v.adaptive,
            "classification": v.classification, "step": v.step, "preintegration": v.preintegration,
            "priority_map": v.priority_map, "priority_pixels": (rep.get("priority_map") or {}).get("priority_pixels"),
            "screen": v.screen, "rays": (rep.get("adaptive_screen") or {}).get("rays", rep["width"] * rep["height"]),
            "reduction": rep.get("reduction"), "predicted_delta_e": rep.get("predicted_delta_e"),
            "delta_e_mean": de["mean"], "delta_e_p95": de["p95"], "delta_e_max": de["max"], "footprint": de["footprint"],
            "wall_ms": rep["wall_ms"], "kernel_ms": rep["kernel_ms"], "samples": rep.get("samples"),
            "bricks_read_first": first.report.get("bricks_read"), "bricks_skipped": rep.get("bricks_skipped"),
        })
        lod = None if v.quality == "full" else eng.prepare(store, vs).lod
        if lod is not None:
            if crossings is None:  # the march depends on the camera, level 0 and the TF only: once per report
                crossings = crossings_of(eng.prepare(store, vs))
            rows[-1].update(seam_stats(best.rgba, ref.rgba, crossings.mask(lod.levels)).as_dict())
            rows[-1]["coarse_face_ratio"] = seam_stats(best.rgba, ref.rgba,
                                                       crossings.mask(lod.levels, "coarse")).ratio
        log(f"[{i}/{len(variants)}] {v.label}: ΔE mean {de['mean']:.2f} p95 {de['p95']:.2f}, "
            f"{rep['kernel_ms']:.0f} ms kernel, reduction {_fmt(rep.get('reduction'))}")
    full = next((r for r in rows if r["quality"] == "full" and r["adaptive"] == "off" and r["step"] is None
                 and not r["preintegration"] and r["priority_map"]), None)
    for r in rows:
        r["speedup_vs_full"] = (full["kernel_ms"] / r["kernel_ms"]) if full and r["kernel_ms"] else None
    front = target_front(renderer or default_renderer(), store, scene, rows)
    return {"store": str(getattr(store, "location", store)), "scene": scene, "reference_scene": ref_scene,
            "reference_ms": ref.report["wall_ms"], "report_s": time.perf_counter() - t, "rows": rows,
            "device": ref.report.get("device"), "front": front}


def target_front(eng: Any, store: Any, scene: dict, rows: list[dict]) -> list[dict] | None:
    """The Pareto front of predicted ΔE against predicted ms that quality targets choose from
    (renderer/frame/target.py), fastest first, each with the row of the same setting (None where the sweep has
    none); None where the scene can take no target (an array). Marks each row's `on_front`."""
    from lodcast.renderer.data.volume import as_volume
    from lodcast.renderer.frame import target
    from lodcast.renderer.frame.prepare import resolved
    from lodcast.renderer.scene.scene import Scene, SceneError

    vol = as_volume(store, stores=eng.stores)
    try:
        cands = target.candidates(eng, vol, resolved(eng, Scene.parse({**scene, "quality": {"max_ms": 1.0}}), vol))
    except SceneError:
        return None
    step = float((scene.get("sampling") or {}).get("step", 0.5))

    def same(r: dict, c: Any) -> bool:
        lod = r["quality"] != "full"
        return (r["quality"] == c.quality and (r["step"] or step) == c.step and r["adaptive"] == ("limited" if lod else "off")
                and (r["interpolation"] if lod else None) == c.interpolation and (r["screen"] is not None) == c.adaptive_screen
                and r["screen"] in (None, "rms") and r["classification"] == "distribution" and not r["preintegration"]
                and r["priority_map"])

    front = []
    for c in target.pareto(cands):
        at = next((i for i, r in enumerate(rows) if same(r, c)), None)
        front.append({"label": c.label(), **c.setting(), "row": at})
        if at is not None:
            rows[at]["on_front"] = True
    return front


def _fmt(x: Any, nd: int = 1) -> str:
    if x is None:
        return "–"
    if isinstance(x, float) and not np.isfinite(x):
        return "∞"
    return f"{x:.{nd}f}" if isinstance(x, float) else str(x)


def table(result: dict[str, Any]) -> str:
    head = ("| configuration | reduction | predicted ΔE | mean ΔE | p95 ΔE | max ΔE | rays | kernel ms | wall ms | speed-up |\n"
            "|---|---|---|---|---|---|---|---|---|---|\n")
    lines = [
        f"| {r['label']} | {_fmt(r['reduction'])} | {_fmt(r['predicted_delta_e'], 2)} | {r['delta_e_mean']:.2f} | "
        f"{r['delta_e_p95']:.2f} | {r['delta_e_max']:.1f} | {_fmt(r.get('rays'))} | {r['kernel_ms']:.0f} | {r['wall_ms']:.0f} | "
        f"{_fmt(r['speedup_vs_full'], 2)}x |"
        for r in result["rows"]
    ]
    out = head + "\n".join(lines) + "\n" + seams_table(result)
    if result.get("front"):  # what quality targets choose from ({"max_delta_e"}, {"max_ms"}: docs/lod.md)
        out += ("\nThe Pareto front quality targets choose from (predicted ΔE / predicted ms on this device; ◆ a row "
                "above):\n\n" + "\n".join(
                    f"- {'◆ ' if f['row'] is not None else ''}{f['label']}: {f['predicted_delta_e']:.2f} / "
                    f"{f['predicted_ms']:.0f} ms" for f in result["front"]) + "\n")
    return out


def seams_table(result: dict[str, Any]) -> str:
    """The level-of-detail rows' seam measure (renderer/image/seams.py), below the main table."""
    rows = [r for r in result["rows"] if r.get("seam_pixels") is not None]
    if not rows:
        return ""
    head = ("\n| configuration | ΔE crossing a level change | ΔE elsewhere | ratio | pixels crossing | coarse faces ratio |\n"
            "|---|---|---|---|---|---|\n")
    return head + "\n".join(
        f"| {r['label']} | {_fmt(r['seam_delta_e'], 2)} | {_fmt(r['rest_delta_e'], 2)} | {_fmt(r['seam_ratio'], 2)} | "
        f"{r['seam_pixels']} | {_fmt(r['coarse_face_ratio'], 2)} |" for r in rows) + "\n"


def plot(result: dict[str, Any], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 6), dpi=110)
    markers = {("nearest_block", "off"): "s", ("interblock", "off"): "o", ("nearest_block", "limited"): "D",
               ("interblock", "limited"): "^", ("nearest_block", "naive"): "x", ("interblock", "naive"): "+"}
    for key, marker in markers.items():
        rows = [r for r in result["rows"] if (r["interpolation"], r["adaptive"]) == key and r["quality"] != "full"
                and r.get("classification", "distribution") == "distribution"]
        if rows:
            ax.scatter([r["kernel_ms"] for r in rows], [r["delta_e_mean"] for r in rows], marker=marker,
                       label=f"{key[0].replace('_', ' ')}, adaptive {key[1]} (measured mean)")
            pred = [(r["kernel_ms"], r["predicted_delta_e"]) for r in rows if r["predicted_delta_e"] is not None]
            if pred and key[1] == "off":
                ax.scatter(*zip(*pred), marker=marker, facecolors="none", edgecolors="grey", alpha=0.7,
                           label=f"{key[0].replace('_', ' ')}: predicted")
            for r in rows:
                if r["adaptive"] == "off":
                    q = r["quality"]
                    ax.annotate("lossless" if q == "lossless" else f"{q.get('reduction', '')}:1", (r["kernel_ms"], r["delta_e_mean"]),
                                fontsize=7, xytext=(3, 3), textcoords="offset points")
    by_mean = [r for r in result["rows"] if r.get("classification") == "mean"]
    if by_mean:
        ax.scatter([r["kernel_ms"] for r in by_mean], [r["delta_e_mean"] for r in by_mean], marker="v", color="grey",
                   label="interblock, classified by the mean")
    for pre, style in ((False, "k--"), (True, "k-")):  # full resolution at several steps
        pts = sorted((r["kernel_ms"], r["delta_e_mean"], r["step"]) for r in result["rows"]
                     if r["quality"] == "full" and r.get("step") is not None and r.get("preintegration") == pre)
        if pts:
            ax.plot([p[0] for p in pts], [p[1] for p in pts], style, marker=".", alpha=0.6,
                    label="full resolution, steps " + ", ".join(f"{p[2]:g}" for p in pts)
                    + (", pre-integrated" if pre else ""))
    for r in result["rows"]:
        if r["quality"] == "full" and r.get("step") is None and not r.get("preintegration"):
            ax.scatter([r["kernel_ms"]], [r["delta_e_mean"]], marker="*", s=140, color="black",
                       label=r["label"] + " (vs step-¼ reference)")
    ax.set_xlabel("kernel time per frame (ms)")
    ax.set_ylabel("ΔE (CIELUV, mean over footprint) against the reference")
    ax.set_title(f"Error against run time — {Path(result['store']).name}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def write_report(result: dict[str, Any], out_dir: str | Path) -> dict[str, Path]:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "report.json", "table": out / "report.md", "plot": out / "report.png"}
    paths["json"].write_text(json.dumps(result, indent=2, default=float))
    paths["table"].write_text(table(result))
    plot(result, paths["plot"])
    return paths
