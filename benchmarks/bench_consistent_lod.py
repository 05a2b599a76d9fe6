"""Issue 9's figures: consistent level of detail on real CTs (distribution classification, per-level significance,
predicted ΔE, LOD that pays for itself, first-render times).

    .venv/bin/python benchmarks/bench_consistent_lod.py [--sizes 256 512] [--repeat 3]
                                                        [--json benchmarks/results/consistent_lod.json]

Volumes: the chest CT (../shared/data/ct_chest_dicom, 275x512x512 HU, presets ct-bone, ct-skin, ct-skin-bone) and
the engine CT (engine.nii.gz, 128x256x256, an opaque metal TF), ingested with the default 16³ blocks (and 8³ for
the first-render times) under benchmarks/results/. Every image is compared with its reference (full resolution,
step ¼, docs/design.md's ΔE over the footprint) and with full resolution at the same step (what the predicted ΔE
predicts: the level of detail's own error). A quality's kernel ms and its speed relative to full resolution are
medians of `repeat` rounds after a warm-up, each round rendering full resolution and that quality one after the
other (the fixed-step and interblock columns: the fastest of `repeat`), on the first OpenCL device; the machine is
shared, so compare ratios within one run. Prints markdown tables and writes JSON.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np

HERE = Path(__file__).resolve().parent
DATA = Path(os.environ.get("LODCAST_SHARED_DATA", HERE.parents[1] / "shared" / "data"))
RESULTS = HERE / "results"

import lodcast  # noqa: E402
from lodcast.renderer.image.delta_e import delta_e_stats  # noqa: E402
from lodcast.renderer.kernel.config import KernelConfig  # noqa: E402
from lodcast.renderer.lod.selection import select_lod  # noqa: E402
from lodcast.renderer.scene.transfer_function import CT_PRESETS  # noqa: E402
from lodcast.store.store import FORMAT_VERSION  # noqa: E402

sys.path.insert(0, str(HERE.parent / "tests"))
from phantoms import BAND_BONE  # noqa: E402

ENGINE_TF = {"points": [{"value": 150, "color": [1.0, 0.8, 0.5], "opacity": 0.0},
                        {"value": 200, "color": [1.0, 0.9, 0.7], "opacity": 0.8},
                        {"value": 255, "color": [1.0, 1.0, 1.0], "opacity": 0.9}]}
#: the translucent TF of issue 45's lossless, level-bound and early-termination benchmarks: the tests' band over bone
BAND_OVER_BONE = BAND_BONE
QUALITIES = ["lossless", {"reduction": 5}, {"reduction": 10}, {"reduction": 30}, {"reduction": 100}]


def store_of(name: str, source: Path, block: int = 16):
    dest = RESULTS / f"{name}_b{block}.zarr"
    if dest.exists():
        st = lodcast.open_store(dest)
        if st.block_size == block and st.format_version == FORMAT_VERSION:  # else re-ingested in today's format
            return st
    return lodcast.ingest(source, dest, block_size=block, overwrite=True)


def chest_store(path: Path | None = None):
    """The chest CT's store: the one at `path` when given, else ingested once under benchmarks/results/."""
    return lodcast.open_store(path) if path else store_of("ct_chest", DATA / "ct_chest_dicom")


def best(eng, store, scene: dict, repeat: int, levels=None):
    eng.render(store, scene, levels=levels)
    runs = [eng.render(store, scene, levels=levels) for _ in range(repeat)]
    return min(runs, key=lambda r: r.report["kernel_ms"])


def paired(eng, store, full_scene: dict, scene: dict, repeat: int):
    """(the render of `scene`, its median kernel ms and full resolution's over the same rounds, the same two of
    wall ms: the whole `render` call, which on a GPU is mostly the host's): the two interleaved, round by round, so
    that the machine's drift (this shared 2-core machine moved the same kernel by 20-30% within minutes) falls on
    both alike."""
    eng.render(store, scene)
    t, t_full, runs = [], [], []
    for _ in range(repeat):
        full = eng.render(store, full_scene).report
        t_full.append((full["kernel_ms"], full["wall_ms"]))
        runs.append(eng.render(store, scene))
        t.append((runs[-1].report["kernel_ms"], runs[-1].report["wall_ms"]))
    q, f = np.median(t, axis=0), np.median(t_full, axis=0)
    return min(runs, key=lambda r: r.report["kernel_ms"]), float(q[0]), float(f[0]), float(q[1]), float(f[1])


def qlabel(q) -> str:
    return q if isinstance(q, str) else f"{q['reduction']:g}:1"


def sweep(eng, store, scene: dict, repeat: int) -> dict:
    """Default settings at every quality against full resolution; uniform levels by mean and by distribution;
    TF selection against L2 and uniform; adaptive sampling on and off."""
    ref = eng.render(store, {**scene, "sampling": {"step": 0.25}})
    full = best(eng, store, scene, repeat)
    out = {"full_ms": full.report["kernel_ms"], "full_wall_ms": full.report["wall_ms"], "full_samples": full.report["samples"],
           "full_delta_e": delta_e_stats(full.rgba, ref.rgba)["mean"], "full_predicted": full.report["predicted_delta_e"],
           "rows": [], "uniform": [], "fig34": []}
    for q in QUALITIES:
        r, q_ms, full_ms, q_wall, full_wall = paired(eng, store, scene, {**scene, "quality": q}, repeat)
        d = delta_e_stats(r.rgba, ref.rgba)
        row = {"quality": qlabel(q), "reduction": r.report["reduction"], "delta_e": d["mean"], "p95": d["p95"],
               "delta_e_vs_full": delta_e_stats(r.rgba, full.rgba)["mean"],
               "predicted": r.report["predicted_delta_e"], "kernel_ms": q_ms,
               "speed_vs_full": full_ms / q_ms, "wall_ms": q_wall, "wall_speed_vs_full": full_wall / q_wall,
               "samples_vs_full": r.report["samples"] / out["full_samples"]}
        # adaptive sampling's share: the same selection at fixed steps; and the adaptive steps alone, without the
        # octant masks that only the adaptive walk has (config.octants)
        fixed = best(eng, store, {**scene, "quality": q, "sampling": {"adaptive_object": False}}, repeat)
        with mock.patch.object(KernelConfig, "octants", property(lambda self: False)):
            steps_alone = eng.render(store, {**scene, "quality": q})
        row.update(fixed_ms=fixed.report["kernel_ms"], fixed_delta_e=delta_e_stats(fixed.rgba, ref.rgba)["mean"],
                   adaptive_gain=fixed.report["samples"] / r.report["samples"],  # issue 9: >= the cube root
                   steps_gain=fixed.report["samples"] / steps_alone.report["samples"])
        if q != "lossless":  # interblock; the selection without the view's weight (visibility.py)
            ii = best(eng, store, {**scene, "quality": q, "sampling": {"interpolation": "interblock"}}, repeat)
            blind = eng.render(store, {**scene, "quality": q, "sampling": {"lod_visibility": False}})
            row.update(ii_ms=ii.report["kernel_ms"], ii_delta_e=delta_e_stats(ii.rgba, ref.rgba)["mean"],
                       blind_delta_e=delta_e_stats(blind.rgba, ref.rgba)["mean"], blind_predicted=blind.report["predicted_delta_e"])
        out["rows"].append(row)
    # the engine's lossless ζ and tables, as its renders select
    vis = select_lod(store, [scene["tf"]], "lossless", lossless_zeta=eng.settings.lossless_zeta,
                     tables=eng.tables).levels >= 0
    for k in (1, 2):  # every visible block at one level: the data bound of each classification
        lv = np.where(vis, k, -1).astype(np.int8)
        red = float(np.prod(store.shape)) / (int(vis.sum()) * (store.block_size >> k) ** 3)
        e = {cls: delta_e_stats(eng.render(store, {**scene, "quality": {"reduction": 2},
                                                   "sampling": {"classification": cls, "adaptive_object": False}},
                                           levels=lv).rgba, ref.rgba)["mean"] for cls in ("mean", "distribution")}
        out["uniform"].append({"level": k, "reduction": red, **e})
    for red in (10, 30, 64):  # thesis fig. 3.4 and issue 9: TF selection (with the view's weight, the default, and
        # without) against L2 and uniform
        view = eng.render(store, {**scene, "quality": {"reduction": red}})
        e = {"tf_view": delta_e_stats(view.rgba, ref.rgba)["mean"], "tf_view_reduction": view.report["reduction"]}
        for method in ("tf", "l2", "uniform"):
            sel = select_lod(store, [scene["tf"]], {"reduction": red}, method=method, tables=eng.tables)
            img = eng.render(store, {**scene, "quality": {"reduction": red}}, levels=sel.levels)
            e[method], e[f"{method}_reduction"] = delta_e_stats(img.rgba, ref.rgba)["mean"], sel.reduction
        out["fig34"].append({"reduction": red, **e})
    return out


def new_views(eng, store, scene: dict, step: float, frames: int = 8, quality=None) -> dict:
    """Wall ms per frame of `frames` new views `step` degrees apart (azimuth from 40°, where the sweep above has not
    been) at 30:1 with the selection weighed by each view (the default), its atlas built from the last one
    (renderer/data/atlas.py: reuse) and, on the same views, packed from nothing; and full resolution's. Bricks are
    warmed by one pass first; `eng`'s selections, atlases and cells are dropped before each timed pass, whose first
    frame (nothing to build from) is left out of the medians."""
    quality = {"reduction": 30} if quality is None else quality
    views = [{**scene, "quality": quality, "camera": {**scene["camera"], "azimuth": 40 + i * step}}
             for i in range(frames)]

    def forget():
        eng.device_cache.clear()
        eng.cells.clear()
        eng.selections.clear()
        eng.forget_atlases()

    def timed(scenes):
        forget()
        out = []
        for s in scenes:
            t = time.perf_counter()
            r = eng.render(store, s)
            out.append(((time.perf_counter() - t) * 1e3, r.report["kernel_ms"]))
        return np.median(out[1:], axis=0)

    for s in views:
        eng.render(store, s)
    with mock.patch.object(eng, "last_atlas", lambda family: None):
        fresh = timed(views)
    reused = timed(views)
    full = timed([{**s, "quality": "full"} for s in views])
    return {"step": step, "frames": frames, "wall_ms": float(reused[0]), "kernel_ms": float(reused[1]),
            "fresh_wall_ms": float(fresh[0]), "fresh_kernel_ms": float(fresh[1]),
            "full_wall_ms": float(full[0]), "full_kernel_ms": float(full[1])}


def first_render(path: Path, scene: dict, runs: int = 3) -> float:
    """Wall ms of the first lossless render of a store in a fresh process (empty brick cache, lodcast's modules
    imported by the call; kernels from the disk cache after a warm-up in another process): the median of `runs`
    processes, one after another."""
    code = ("import json, sys, time, lodcast; t = time.perf_counter(); "
            "r = lodcast.render(sys.argv[1], json.loads(sys.argv[2])); print((time.perf_counter() - t) * 1e3)")
    args = [sys.executable, "-c", code, str(path), json.dumps({**scene, "quality": "lossless"})]
    subprocess.run(args, check=True, capture_output=True)  # builds the kernels into the disk cache
    return float(np.median([float(subprocess.run(args, check=True, capture_output=True, text=True).stdout.split()[-1])
                            for _ in range(runs)]))


def spearman(a, b) -> float:
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    return float(np.corrcoef(ra, rb)[0, 1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", type=Path, default=RESULTS / "consistent_lod.json")
    a = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    chest = store_of("ct_chest", DATA / "ct_chest_dicom")
    engine = store_of("engine", DATA / "engine.nii.gz")
    cases = [("chest CT", chest, name, CT_PRESETS[name]) for name in ("ct-bone", "ct-skin", "ct-skin-bone")]
    cases.append(("engine CT", engine, "engine-metal", ENGINE_TF))
    eng = lodcast.Renderer()  # every in-process render; first_render's fresh processes use their own default
    result = {"device": None, "cases": []}
    for size in a.sizes:
        for vol, store, tfname, tf in cases:
            scene = {"camera": {"azimuth": 30, "elevation": 15}, "width": size, "height": size, "tf": tf, "format": "npy"}
            res = sweep(eng, store, scene, a.repeat)
            res.update(volume=vol, tf=tfname, size=size, new_views=[new_views(eng, store, scene, d) for d in (2, 10)])
            result["cases"].append(res)
            print(f"{vol} {tfname} {size}²: done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    result["device"] = eng.render(chest, {"tf": CT_PRESETS["ct-bone"], "width": 8, "height": 8}).report["device"]
    scene = {"camera": {"azimuth": 30, "elevation": 15}, "width": 256, "height": 256, "tf": CT_PRESETS["ct-bone"]}
    result["first_render_ms"] = {f"{b}^3": first_render(store_of("ct_chest", DATA / "ct_chest_dicom", b).location, scene)
                                 for b in (16, 8)}
    # the report's prediction is of the error against the reference (step ¼): the level of detail's own plus the
    # step's; every quality's row and full resolution's
    pairs = [(c["volume"], r["delta_e"], r["predicted"], r["reduction"]) for c in result["cases"] for r in c["rows"]]
    pairs += [(c["volume"], c["full_delta_e"], c["full_predicted"], 1.0) for c in result["cases"]]
    factor = lambda sel: max(max(m / p, p / m) for _, m, p, red in sel if red >= 4.99 and m > 0 and p > 0)  # noqa: E731
    result["prediction"] = {
        "spearman": spearman([p[1] for p in pairs], [p[2] for p in pairs]),
        "worst_factor_at_5_or_more_chest": factor([p for p in pairs if p[0] == "chest CT"]),
        "worst_factor_at_5_or_more": factor(pairs),
    }
    a.json.write_text(json.dumps(result, indent=2, default=float))
    print(report(result))
    print(f"\nJSON: {a.json}  ({time.perf_counter() - t0:.0f} s)")


def _ms(ms: float) -> str:
    """Milliseconds to three figures (a GPU's kernels take well under one)."""
    return f"{ms:.0f}" if ms >= 100 else f"{ms:.3g}"


def budget_split(uniform: list[dict], reduction: float) -> str:
    """What a reduction leaves of the visible blocks, from the reduction of every visible block at level 1 (R1,
    so R1 / 8 at level 0): the share of their voxels it can keep at level 0 with the rest at level 1
    (g + (1 - g) / 8 = R1 / 8 / reduction), or, below R1, the share it must put at level 2 with the rest at level 1
    ((1 - h) / 8 + h / 64 = R1 / 8 / reduction). The greedy may mix more levels; this is the budget's arithmetic."""
    u1 = next(u for u in uniform if u["level"] == 1)
    x = u1["reduction"] / 8 / reduction  # the budget as a share of every visible block at level 0
    if x >= 1 / 8:
        split = f"at most {100 * (x - 1 / 8) / (7 / 8):.1f}% of the visible voxels at level 0, the rest at level 1"
    else:
        split = f"at least {100 * (1 / 8 - x) / (1 / 8 - 1 / 64):.0f}% of the visible voxels at level 2, the rest at level 1"
    return (f"{reduction:g}:1 holds {u1['reduction'] / reduction:.2f}× the samples of every visible block at level 1 "
            f"(mean ΔE {u1['distribution']:.2f} by distribution): {split}")


def report(res: dict) -> str:
    lines = [f"device: {res['device']}", ""]
    for c in res["cases"]:
        lines += [f"### {c['volume']}, {c['tf']}, {c['size']}² — full resolution {_ms(c['full_ms'])} ms of kernel, "
                  f"{_ms(c['full_wall_ms'])} ms a render, mean ΔE {c['full_delta_e']:.2f} (step ½ against step ¼), "
                  f"predicted {c['full_predicted']:.2f}", "",
                  "| quality | reduction | mean ΔE | p95 | ΔE vs full | predicted | kernel ms | × full speed | wall ms "
                  "(× full) | samples ÷ full | fixed-step ms · ΔE | fixed-step ÷ adaptive samples (∛reduction) |"
                  " interblock ms · ΔE | no view weight: ΔE · predicted |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in c["rows"]:
            extra = (f"{_ms(r['fixed_ms'])} · {r['fixed_delta_e']:.2f} | {r['adaptive_gain']:.2f} "
                     f"({r['reduction'] ** (1 / 3):.2f}; steps alone {r['steps_gain']:.2f}) | ") + (
                f"{_ms(r['ii_ms'])} · {r['ii_delta_e']:.2f} | {r['blind_delta_e']:.2f} · {r['blind_predicted']:.2f}"
                if "ii_ms" in r else "– | –")
            lines.append(f"| {r['quality']} | {r['reduction']:.1f} | {r['delta_e']:.2f} | {r['p95']:.1f} | "
                         f"{r['delta_e_vs_full']:.2f} | {r['predicted']:.2f} | {_ms(r['kernel_ms'])} | "
                         f"{r['speed_vs_full']:.2f} | {_ms(r['wall_ms'])} ({r['wall_speed_vs_full']:.2f}) | "
                         f"{r['samples_vs_full']:.2f} | {extra} |")
        lines += ["", "| every visible block at | reduction | mean ΔE by mean | by distribution |", "|---|---|---|---|"]
        lines += [f"| level {u['level']} | {u['reduction']:.1f} | {u['mean']:.2f} | {u['distribution']:.2f} |"
                  for u in c["uniform"]]
        lines += ["", budget_split(c["uniform"], 30)]
        lines += ["", "| 30:1, new views | wall ms/frame (kernel) | atlas packed from nothing | full resolution |",
                  "|---|---|---|---|"]
        lines += [f"| {v['frames']} views {v['step']:g}° apart | {_ms(v['wall_ms'])} ({_ms(v['kernel_ms'])}) | "
                  f"{_ms(v['fresh_wall_ms'])} ({_ms(v['fresh_kernel_ms'])}) | {_ms(v['full_wall_ms'])} "
                  f"({_ms(v['full_kernel_ms'])}) |" for v in c.get("new_views", [])]
        lines += ["", "| reduction | TF selection (default: weighed by the view) | TF alone | L2 | uniform |",
                  "|---|---|---|---|---|"]
        lines += [f"| {f['reduction']}:1 | {f['tf_view']:.2f} | {f['tf']:.2f} | {f['l2']:.2f} | {f['uniform']:.2f} "
                  f"({f['uniform_reduction']:.0f}:1) |" for f in c["fig34"]]
        lines.append("")
    p = res["prediction"]
    lines.append(f"predicted vs measured ΔE (against the step-¼ reference) over every row and full resolution: Spearman "
                 f"{p['spearman']:.3f}; worst factor at ≥ 5:1: {p['worst_factor_at_5_or_more_chest']:.2f} on the chest "
                 f"CT, {p['worst_factor_at_5_or_more']:.2f} on both CTs")
    lines.append("first uncached lossless render (fresh process, ct-bone 256²): "
                 + ", ".join(f"{k} {v:.0f} ms" for k, v in res["first_render_ms"].items()))
    return "\n".join(lines)


if __name__ == "__main__":
    main()
