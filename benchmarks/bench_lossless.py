"""`"quality": "lossless"` against full resolution at the same sampling (issue 45, item 1).

The chest CT under an opaque bone TF, a wide soft-tissue TF, a faint soft-tissue band (α 0.006 per unit) over bone,
skin with bone, and skin alone, from two views: lossless and 10:1 against full resolution (step ½, default
settings otherwise), mean ΔE over the footprint, its 99.9th percentile and max, reduction and predicted ΔE. Writes
JSON with the date, machine and command; run it on the commit before a change for "before".

    python benchmarks/bench_lossless.py --size 256 --json docs/measurements/lossless.json
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_consistent_lod import BAND_OVER_BONE, chest_store  # noqa: E402
from record import provenance  # noqa: E402

from lodcast.renderer.frame.render import Renderer
from lodcast.renderer.image.delta_e import delta_e_image
from lodcast.renderer.scene.transfer_function import CT_PRESETS

TFS = {"bone": CT_PRESETS["ct-bone"], "soft": CT_PRESETS["ct-body"], "band+bone": BAND_OVER_BONE,
       "skin+bone": CT_PRESETS["ct-skin-bone"], "skin": CT_PRESETS["ct-skin"]}
VIEWS = ((30, 15), (200, -20))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--store", type=Path, default=None, help="the chest CT's store (left out: ingested once under benchmarks/results/)")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    store = chest_store(a.store)
    eng = Renderer()
    rows = []
    for az, el in VIEWS:
        for name, tf in TFS.items():
            sc = {"camera": {"azimuth": az, "elevation": el, "distance": 1.9}, "width": a.size, "height": a.size,
                  "tf": tf, "format": "npy", "sampling": {"step": 0.5}}
            full = eng.render(store, sc)
            for q in ("lossless", {"reduction": 10}):
                r = eng.render(store, {**sc, "quality": q})
                de, fp = delta_e_image(r.rgba, full.rgba)
                v = de[fp]
                row = {"tf": name, "view": [az, el], "quality": q if isinstance(q, str) else "10:1",
                       "reduction": round(r.report["reduction"], 2),
                       "predicted": round(r.report["predicted_delta_e"], 3),
                       "mean": round(float(v.mean()), 3), "p99.9": round(float(np.percentile(v, 99.9)), 2),
                       "max": round(float(v.max()), 2)}
                print(json.dumps(row), flush=True)
                rows.append(row)
    eng.close()
    if a.json:
        out = {**provenance("bench_lossless.py"), "size": a.size, "rows": rows}
        a.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
