"""What reading the next frame's bricks during the current render buys (issue 14 item 2): a TF sweep on the chest
CT at 30:1, with and without prefetch, as the job worker runs it (service/queue.py's _Prefetch: one frame ahead,
one thread).

    .venv/bin/python benchmarks/bench_prefetch.py [--tfs 8] [--size 256] [--repeat 2] [--json benchmarks/results/prefetch.json]

Each run starts with empty brick and device caches; the sweep moves ct-bone's thresholds by 40 HU per frame, so
every frame's selection differs from the last. A turntable's selection does not change with the view (the LOD is
chosen from the TF), so after its first frame a prefetch finds everything cached: nothing to gain there. Per run:
total ms and per-frame ms; the better of `repeat` runs. The machine is shared (two cores: the prefetch's reads
and decoding compete with the kernel): compare within one run.
"""
from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from bench_consistent_lod import DATA, RESULTS, store_of

from lodcast.renderer.frame.render import Renderer


def _tf(shift: float) -> dict:
    return {"points": [{"value": 250 + shift, "color": [1.0, 0.95, 0.85], "opacity": 0.0},
                       {"value": 700 + shift, "color": [1.0, 0.95, 0.85], "opacity": 0.6},
                       {"value": 1500 + shift, "color": [1, 1, 1], "opacity": 0.9}]}


def sweep(eng: Renderer, store, scenes: list[dict], ahead: bool) -> list[float]:
    eng.bricks.clear()
    eng.device_cache.clear()
    pool = ThreadPoolExecutor(max_workers=1)
    ms = []
    for i, sc in enumerate(scenes):
        if ahead and i + 1 < len(scenes):
            pool.submit(eng.prefetch, store, scenes[i + 1])
        t = time.perf_counter()
        eng.render(store, sc)
        ms.append((time.perf_counter() - t) * 1e3)
    pool.shutdown(wait=True)
    return ms


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tfs", type=int, default=8)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--json", type=Path, default=RESULTS / "prefetch.json")
    a = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    store = store_of("ct_chest", DATA / "ct_chest_dicom")
    scenes = [{"tf": _tf(40.0 * i), "width": a.size, "height": a.size, "quality": {"reduction": 30},
               "camera": {"azimuth": 30, "elevation": 15}, "format": "npy"} for i in range(a.tfs)]
    eng = Renderer()
    eng.render(store, scenes[0])  # build the programs
    runs = {k: min((sweep(eng, store, scenes, k == "prefetch") for _ in range(a.repeat)), key=sum)
            for k in ("plain", "prefetch", "plain again")}
    table = "\n".join([f"TF sweep, chest CT, 30:1, {a.tfs} TFs, {a.size}², cold caches", "",
                       "| run | total ms | first frame ms | later frames ms (mean) |", "|---|---|---|---|"] + [
        f"| {k} | {sum(v):.0f} | {v[0]:.0f} | {sum(v[1:]) / max(1, len(v) - 1):.0f} |" for k, v in runs.items()])
    print(table)
    a.json.write_text(json.dumps({"runs": runs, "table": table}, indent=2))
    print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
