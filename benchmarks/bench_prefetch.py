"""What reading the next frame's bricks during the current render buys (issue 14 item 2): a TF sweep on the chest
CT at 30:1, with and without reading ahead, through the job worker's own FrameRenderer (service/frames.py: one
frame ahead, on one thread, the first frame rendered alone, a read ahead asking only for what the newest atlas
lacks).

    .venv/bin/python benchmarks/bench_prefetch.py [--tfs 8] [--size 256] [--repeat 2] [--json benchmarks/results/prefetch.json]

Each run starts with empty brick and device caches; the sweep moves ct-bone's thresholds by 40 HU per frame, so
every frame's selection differs from the last. A turntable's selection does not change with the view (the LOD is
chosen from the TF), so after its first frame a read ahead finds everything on the device: nothing to gain there
(benchmarks/bench_paths.py measures that case). Per run: total ms and per-frame ms (the frame's render, PNG and
file as the worker writes them); the better of `repeat` runs. The machine is shared (two cores: the reads and
decoding compete with the kernel): compare within one run.
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from bench_consistent_lod import DATA, RESULTS, store_of

from lodcast.service.frames import FrameRenderer
from lodcast.service.jobs import parse_job, plan_frames
from lodcast.service.queue import JobQueue
from lodcast.service.rendering import RenderEngine
from lodcast.service.settings import Settings


def _tf(shift: float) -> dict:
    return {"points": [{"value": 250 + shift, "color": [1.0, 0.95, 0.85], "opacity": 0.0},
                       {"value": 700 + shift, "color": [1.0, 0.95, 0.85], "opacity": 0.6},
                       {"value": 1500 + shift, "color": [1, 1, 1], "opacity": 0.9}]}


def sweep(eng: RenderEngine, jq: JobQueue, job, ahead: bool) -> list[float]:
    """One run of the job's frames through FrameRenderer, the caches emptied first; ms per frame."""
    eng.renderer.close()  # nothing kept: no bricks, no atlas to build from
    jid = jq.submit(job)["id"]
    plan = plan_frames(job)
    names = [f"frame_{i:05d}.png" for i in range(len(plan))]
    frames = FrameRenderer(jq.settings, jq.records, jid, plan, jq.files(jid), names, eng)
    ms = []
    for i in range(len(plan)):
        t = time.perf_counter()
        frames.render(i, "bench", i + 1 if ahead and i + 1 < len(plan) else None)
        ms.append((time.perf_counter() - t) * 1e3)
    frames.ahead.wait()  # (its last read ahead, if any, before the next run empties the caches)
    jq.cancel(jid)
    return ms


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tfs", type=int, default=8)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--json", type=Path, default=RESULTS / "prefetch.json")
    a = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    store = Path(store_of("ct_chest", DATA / "ct_chest_dicom").location)
    scene = {"width": a.size, "height": a.size, "quality": {"reduction": 30},
             "camera": {"azimuth": 30, "elevation": 15}}
    with tempfile.TemporaryDirectory(prefix="lodcast-prefetch-") as state:
        settings = Settings(root=store.parent, state_root=Path(state), token=None)
        eng = RenderEngine(settings)
        jq = JobQueue(settings, engine=eng)
        job = parse_job({"kind": "tf_sweep", "volume": store.name, "scene": scene,
                         "tfs": [_tf(40.0 * i) for i in range(a.tfs)]})
        eng.render(store, plan_frames(job)[0][1])  # build the programs
        runs = {k: min((sweep(eng, jq, job, k == "prefetch") for _ in range(a.repeat)), key=sum)
                for k in ("plain", "prefetch", "plain again")}
    table = "\n".join([f"TF sweep, chest CT, 30:1, {a.tfs} TFs, {a.size}², cold caches", "",
                       "| run | total ms | first frame ms | later frames ms (mean) |", "|---|---|---|---|"] + [
        f"| {k} | {sum(v):.0f} | {v[0]:.0f} | {sum(v[1:]) / max(1, len(v) - 1):.0f} |" for k, v in runs.items()])
    print(table)
    a.json.write_text(json.dumps({"runs": runs, "table": table}, indent=2))
    print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
