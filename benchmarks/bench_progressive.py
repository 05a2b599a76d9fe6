"""Issue 44 item 1: how soon a progressive render shows its first picture, against the plain render of the same scene.

    .venv/bin/python benchmarks/bench_progressive.py [--size 512] [--pairs 7] [--json benchmarks/results/progressive.json]

The chest CT (../shared/data/ct_chest_dicom, 275x512x512, ingested with 16³ blocks under benchmarks/results/),
ct-bone, azimuth 30, elevation 15, at quality "full" and 30:1. Two situations, each as interleaved pairs (plain,
then progressive) so that both see the same machine:
- "first view": a new Renderer per render (empty brick and device caches; the kernels come from the disk cache,
  built once before the pairs; the page cache is not dropped, so the store's files are read from memory);
- "new view": one Renderer that has rendered the scene at azimuth 30; each pair turns the camera 2° further.
Per pair: the plain render's wall ms, and each progressive stage's wall ms since the request. Prints a markdown
table of medians and writes the JSON with every pair. The machine is shared (two cores): compare within one run.
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import subprocess
import time
from pathlib import Path

from bench_consistent_lod import DATA, RESULTS, store_of

from lodcast.renderer.frame.render import Renderer


def scene(size: int, quality: object, azimuth: float) -> dict:
    return {"tf": "ct-bone", "width": size, "height": size, "quality": quality, "format": "npy",
            "camera": {"azimuth": azimuth, "elevation": 15}}


def pair(plain_eng: Renderer, prog_eng: Renderer, store: object, sc: dict) -> dict:
    t = time.perf_counter()
    plain = plain_eng.render(store, sc)
    plain_ms = (time.perf_counter() - t) * 1e3
    stages = [r.report for r in prog_eng.render_progressive(store, sc)]
    return {"plain_ms": plain_ms, "plain_samples": plain.report["samples"],
            "stages": [{k: r[k] for k in ("stage", "final", "wall_ms", "reduction", "predicted_delta_e", "samples",
                                          "image_scale", "bricks_read", "bricks_cached")} for r in stages]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--pairs", type=int, default=7)
    ap.add_argument("--json", type=Path, default=RESULTS / "progressive.json")
    a = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    store = store_of("ct_chest", DATA / "ct_chest_dicom")
    warm = Renderer()
    for q in ("full", {"reduction": 30}):  # build (or load) every stage's program once
        list(warm.render_progressive(store, scene(a.size, q, 30.0)))
    out: dict = {"date": time.strftime("%Y-%m-%d"), "machine": f"{platform.node()} {platform.processor()}",
                 "device": warm.device.info()["name"], "size": a.size,
                 "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                                          text=True).stdout.strip(), "runs": {}}
    for q in ("full", {"reduction": 30}):
        name = q if isinstance(q, str) else f"{q['reduction']:g}:1"
        first = [pair(Renderer(), Renderer(), store, scene(a.size, q, 30.0)) for _ in range(a.pairs)]
        turned = [pair(warm, warm, store, scene(a.size, q, 30.0 + 2.0 * (i + 1))) for i in range(a.pairs)]
        out["runs"][name] = {"first view": first, "new view": turned}
    a.json.write_text(json.dumps(out, indent=1))
    print(f"{out['date']}, {out['device']}, {a.size}², medians of {a.pairs} pairs\n")
    print("| quality | situation | plain ms | stage 0 ms | stages (reduction:1 @ ms since request) | final ms |")
    print("|---|---|---|---|---|---|")
    for name, runs in out["runs"].items():
        for where, pairs in runs.items():
            n = len(pairs[0]["stages"])
            med = [statistics.median(p["stages"][k]["wall_ms"] for p in pairs) for k in range(n)]
            desc = ", ".join(f"{pairs[0]['stages'][k]['reduction']:.3g} @ {med[k]:.0f}" for k in range(n))
            print(f"| {name} | {where} | {statistics.median(p['plain_ms'] for p in pairs):.0f} | {med[0]:.0f} | "
                  f"{desc} | {med[-1]:.0f} |")


if __name__ == "__main__":
    main()
