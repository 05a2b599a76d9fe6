"""The level-1 bound as users get it (issue 45, item 5): `"quality": {"level": 1}`, `{"reduction": 30}` and the
budget at the level-1 image's own reduction on the chest CT against the step-¼ reference (default settings
otherwise), and 30:1 ÷ the bound and same reduction ÷ the bound per scene, with each one's predicted ΔE and
reduction. Writes JSON with the date, machine and command.

    python benchmarks/bench_level_bound.py --size 512 --json docs/measurements/level_bound.json
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_consistent_lod import BAND_OVER_BONE, chest_store  # noqa: E402
from record import provenance  # noqa: E402

from lodcast.renderer.frame.render import Renderer
from lodcast.renderer.image.delta_e import delta_e_stats
from lodcast.renderer.scene.transfer_function import CT_PRESETS

TFS = {"ct-bone": CT_PRESETS["ct-bone"], "ct-skin": CT_PRESETS["ct-skin"], "ct-skin-bone": CT_PRESETS["ct-skin-bone"],
       "band+bone": BAND_OVER_BONE}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--store", type=Path, default=None, help="the chest CT's store (left out: ingested once under benchmarks/results/)")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    rows = []
    store = chest_store(a.store)
    eng = Renderer()
    for name, tf in TFS.items():
        sc = {"camera": {"azimuth": 30, "elevation": 15, "distance": 1.9}, "width": a.size, "height": a.size,
              "tf": tf, "format": "npy"}
        ref = eng.render(store, {**sc, "sampling": {"step": 0.25}})
        row: dict = {"tf": name}
        for label, q in (("level1", {"level": 1}), ("30:1", {"reduction": 30}), ("same", None)):
            # "same": the budget at the level-1 image's own reduction, so the greedy is compared with one level
            # everywhere at equal data (where level 1 is far from 30:1, 30:1 ÷ the bound compares unequal budgets)
            q = q or {"reduction": row["level1"]["reduction_exact"]}
            r = eng.render(store, {**sc, "quality": q})
            row[label] = {"reduction": round(r.report["reduction"], 2), "reduction_exact": r.report["reduction"],
                          "predicted": round(r.report["predicted_delta_e"], 3),
                          "measured": round(delta_e_stats(r.rgba, ref.rgba)["mean"], 3)}
        row["30:1 / bound"] = round(row["30:1"]["measured"] / row["level1"]["measured"], 3)
        row["same reduction / bound"] = round(row["same"]["measured"] / row["level1"]["measured"], 3)
        print(json.dumps(row), flush=True)
        rows.append(row)
    eng.close()
    if a.json:
        out = {**provenance("bench_level_bound.py"), "size": a.size, "rows": rows}
        a.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
