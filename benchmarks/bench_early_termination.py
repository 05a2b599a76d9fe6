"""Early termination's error and cost (issue 45, item 6; docs/design.md: the default may move a composite image by
at most 0.1 mean ΔE against `early_termination: 1.0` at step ≤ ½).

The default threshold is tightened for TFs whose colours differ widely (renderer/kernel/params.py, early_stop: the
colour still to come differs from the ray's last colour by at most the TF's colour spread). Error: the chest CT at
full resolution, step ½, two views, opaque, translucent and lit TFs, against the same render with early termination
off (mean and 95th percentile ΔE over the footprint, and samples as a share of ET off): the default 0.99 as given
(the rule off), the default with the rule, and 0.999 as given. Cost: on the bone scenes (ct-bone at full
resolution and 30:1, unlit, and lit at full resolution), `--pairs` interleaved pairs of renders with the rule off
and on, in one process, the threshold each gives, and the median ratio (on ÷ off) of kernel and wall times with a
bootstrap 95 % interval.
Writes JSON with the date, machine and command.

    python benchmarks/bench_early_termination.py --size 512 --pairs 20 --json docs/measurements/early_termination.json
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_consistent_lod import BAND_OVER_BONE, chest_store  # noqa: E402

from lodcast.renderer.frame.render import Renderer
from lodcast.renderer.image.delta_e import delta_e_stats
from lodcast.renderer.kernel import params
from lodcast.renderer.scene.scene import Scene
from lodcast.renderer.scene.transfer_function import CT_PRESETS

TFS = {"ct-bone": CT_PRESETS["ct-bone"], "ct-skin": CT_PRESETS["ct-skin"], "ct-skin-bone": CT_PRESETS["ct-skin-bone"],
       "ct-body": CT_PRESETS["ct-body"], "band+bone": BAND_OVER_BONE}
VIEWS = ((30, 15), (200, -20))


LIT = {"ambient": 0.3, "diffuse": 0.7, "specular": 0.2, "shininess": 32, "light": "headlight"}


def _scene(tf: dict, view: tuple[int, int], size: int, et: float, quality: object = "full",
           shading: dict | None = None) -> dict:
    return {"camera": {"azimuth": view[0], "elevation": view[1], "distance": 1.9}, "width": size, "height": size,
            "tf": tf, "format": "npy", "quality": quality, "shading": shading,
            "sampling": {"step": 0.5, "early_termination": et}}


def _ci(ratios: np.ndarray, rng: np.random.Generator) -> tuple[float, float, float]:
    boot = np.median(rng.choice(ratios, (10000, ratios.size)), axis=1)
    return float(np.median(ratios)), float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--pairs", type=int, default=20)
    ap.add_argument("--store", type=Path, default=None, help="the chest CT's store (left out: ingested once under benchmarks/results/)")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    rule = params.ET_SPREAD
    errors, costs = [], []
    rng = np.random.default_rng(0)
    store = chest_store(a.store)
    eng = Renderer()
    for name, tf, sh in [(n, t, None) for n, t in TFS.items()] + [("ct-bone lit", TFS["ct-bone"], LIT)]:
        for view in VIEWS:
            off = eng.render(store, _scene(tf, view, a.size, 1.0, shading=sh))
            row: dict = {"tf": name, "view": list(view)}
            for label, t, spread in (("0.99 as given", 0.99, math.inf), ("0.99 default", 0.99, rule),
                                     ("0.999 as given", 0.999, math.inf)):
                params.ET_SPREAD = spread
                r = eng.render(store, _scene(tf, view, a.size, t, shading=sh))
                de = delta_e_stats(r.rgba, off.rgba)
                row[label] = {"mean": round(de["mean"], 4), "p95": round(de["p95"], 3),
                              "samples": round(r.report["samples"] / off.report["samples"], 4)}
            params.ET_SPREAD = rule
            print(json.dumps(row), flush=True)
            errors.append(row)
    for label, quality, sh in (("ct-bone full", "full", None), ("ct-bone 30:1", {"reduction": 30}, None),
                               ("ct-bone lit full", "full", LIT)):
        tf = TFS["ct-bone"]
        sc = _scene(tf, VIEWS[0], a.size, 0.99, quality, sh)

        def timed(spread: float) -> dict:
            params.ET_SPREAD = spread
            try:
                return eng.render(store, sc).report
            finally:
                params.ET_SPREAD = rule

        timed(math.inf), timed(rule)  # warm: kernels built, bricks read
        k, w = [], []
        for i in range(a.pairs):
            if i % 2 == 0:
                ro, rn = timed(math.inf), timed(rule)
            else:
                rn, ro = timed(rule), timed(math.inf)
            k.append(rn["kernel_ms"] / ro["kernel_ms"])
            w.append(rn["wall_ms"] / ro["wall_ms"])
        kc, wc = _ci(np.array(k), rng), _ci(np.array(w), rng)
        params.ET_SPREAD = math.inf
        as_given = params.early_stop(Scene.parse(sc))
        params.ET_SPREAD = rule
        row = {"scene": label, "pairs": a.pairs, "threshold": [as_given, params.early_stop(Scene.parse(sc))],
               "kernel_ratio": [round(v, 4) for v in kc], "wall_ratio": [round(v, 4) for v in wc]}
        print(json.dumps(row), flush=True)
        costs.append(row)
    eng.close()
    if a.json:
        out = {"date": datetime.date.today().isoformat(),
               "machine": f"{platform.node()} ({os.cpu_count()} CPUs, {platform.machine()})",
               "command": "benchmarks/bench_early_termination.py " + " ".join(sys.argv[1:]), "size": a.size,
               "et_spread": rule, "errors": errors,
               "costs (rule on / off: median, 95 % interval)": costs}
        a.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
