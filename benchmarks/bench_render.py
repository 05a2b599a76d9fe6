"""Ray caster throughput at full resolution on the largest real volume (chest CT, 275×512×512), against a bare
trilinear march (same rays, same sampler, no TF, no compositing) measured in the same run; plus the speed-ups
of empty-space skipping and early ray termination on a sparse (bone) transfer function.

    .venv/bin/python benchmarks/bench_render.py [--sizes 512 1024] [--repeat 3] [--json benchmarks/results/render.json]

The CT is ingested once into benchmarks/results/ct_chest.zarr. Times are kernel times from OpenCL profiling
events: every case runs --repeat times, round robin, after a small warm-up; the table shows the best run (the
machine may be shared) and the JSON every run. samples/s counts the samples the kernel actually took.
Goal (issue 4): the renderer reaches >= 50% of the bare march's samples/s.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import pyopencl as cl

HERE = Path(__file__).resolve().parent
DATA = Path(os.environ.get("LODCAST_SHARED_DATA", HERE.parents[1] / "shared" / "data"))
RESULTS = HERE / "results"

CAMERA = {"azimuth": 30, "elevation": 15, "distance": 1.9, "fov": 30}
# Soft tissue faint, bone stronger: every sample inside the body does TF work; rays mostly run to the far side.
TF_DENSE = {"points": [
    {"value": -1000, "color": [0.0, 0.0, 0.0], "opacity": 0.0},
    {"value": -600, "color": [0.6, 0.3, 0.2], "opacity": 0.004},
    {"value": 0, "color": [0.9, 0.5, 0.4], "opacity": 0.01},
    {"value": 300, "color": [1.0, 0.9, 0.8], "opacity": 0.05},
    {"value": 1500, "color": [1.0, 1.0, 1.0], "opacity": 0.5},
]}
# Bone only: air, lung and soft tissue are transparent (most blocks empty), bone nearly opaque.
TF_SPARSE = {"points": [
    {"value": 250, "color": [1.0, 0.9, 0.8], "opacity": 0.0},
    {"value": 500, "color": [1.0, 0.95, 0.9], "opacity": 0.9},
    {"value": 1500, "color": [1.0, 1.0, 1.0], "opacity": 1.0},
]}


def ensure_store() -> Path:
    import lodcast

    dest = RESULTS / "ct_chest.zarr"
    if not dest.exists():
        RESULTS.mkdir(parents=True, exist_ok=True)
        print(f"ingesting {DATA / 'ct_chest_dicom'} -> {dest} (once)", file=sys.stderr)
        lodcast.ingest(DATA / "ct_chest_dicom", dest)
    return dest


def run_render(eng, store, scene: dict) -> dict:
    r = eng.render(store, scene)
    return {"kernel_ms": r.report["kernel_ms"], "wall_ms": r.report["wall_ms"], "samples": r.report["samples"],
            "bricks_skipped": r.report["bricks_skipped"], "blocks": r.report["blocks"],
            "build_options": r.report["build_options"], "alpha_mean": float(r.rgba[..., 3].mean())}


def run_bare(eng, store, scene: dict) -> dict:
    """The bare march on the same rays (same Prepared parameters, same volume buffer: `eng`'s device cache)."""
    from lodcast.renderer.data.sampler import upload_level0
    from lodcast.renderer.data.volume import voxel_options
    from lodcast.renderer.frame.render import launch

    ctx, queue = eng.device.context, eng.device.queue
    pr = eng.prepare(store, scene)
    W, H = pr.scene.width, pr.scene.height
    opts = ("-DLC_SAMPLER_FULL",) + voxel_options(pr.volume.voxel_dtype)
    prg = eng.device.program("march_bare.cl", opts).program
    dvol, _ = upload_level0(eng, pr.volume)
    mf = cl.mem_flags
    d_p = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=pr.params)
    d_out = cl.Buffer(ctx, mf.WRITE_ONLY, W * H * 4)
    d_n = cl.Buffer(ctx, mf.WRITE_ONLY, W * H * 4)
    kern = cl.Kernel(prg, "lc_march_bare")
    kern.set_args(d_p, dvol.buffer, d_out, d_n)
    (ev,) = launch(queue, kern, W, H)
    n = np.empty(W * H, np.uint32)
    cl.enqueue_copy(queue, n, d_n, wait_for=[ev])
    queue.finish()
    return {"kernel_ms": (ev.profile.end - ev.profile.start) * 1e-6, "samples": int(n.sum(dtype=np.int64))}


CASES = [
    ("bare trilinear march", "bare", TF_DENSE, {}),
    ("render, dense TF (ESS+ET on)", "render", TF_DENSE, {}),
    ("render, sparse TF (ESS+ET on)", "render", TF_SPARSE, {}),
    ("render, sparse TF, ESS off", "render", TF_SPARSE, {"empty_space_skipping": False}),
    ("render, sparse TF, ET off", "render", TF_SPARSE, {"early_termination": 1.0}),
    ("render, sparse TF, ESS+ET off", "render", TF_SPARSE, {"empty_space_skipping": False, "early_termination": 1.0}),
]


def measure(eng, store, size: int, step: float, repeat: int) -> list[dict]:
    """Every case `repeat` times, interleaved (round robin), so that load from other processes on a shared
    machine hits all cases alike; the best (minimum) kernel time of each case is its figure, the median beside."""
    runs: dict[str, list[dict]] = {name: [] for name, *_ in CASES}
    for _ in range(repeat):
        for name, kind, tf, sampling in CASES:
            scene = {"camera": CAMERA, "width": size, "height": size, "format": "npy", "tf": tf,
                     "sampling": {"step": step, **sampling}}
            runs[name].append((run_bare if kind == "bare" else run_render)(eng, store, scene))
    rows = []
    for name, kind, *_ in CASES:
        rs = runs[name]
        best = min(rs, key=lambda r: r["kernel_ms"])
        row = {"case": name, "size": size, **best, "kernel_ms_median": statistics.median(r["kernel_ms"] for r in rs),
               "kernel_ms_all": [r["kernel_ms"] for r in rs]}
        row["samples_per_s"] = row["samples"] / (row["kernel_ms"] * 1e-3)
        rows.append(row)
    bare = rows[0]["samples_per_s"]
    for row in rows[1:]:
        row["vs_bare_samples_per_s"] = row["samples_per_s"] / bare
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[512, 1024])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--step", type=float, default=0.5, help="sampling step in voxels (default 0.5)")
    ap.add_argument("--json", type=Path, default=RESULTS / "render.json")
    args = ap.parse_args(argv)

    import lodcast

    eng = lodcast.Renderer()  # one engine for every case: the warm-up's programs and volume buffer are its own
    store = lodcast.open_store(ensure_store())
    dev = eng.device.info()
    print(f"device: {dev['name']} ({dev['platform']}); volume {store.shape} {store.dtype}, step {args.step} voxel")
    out = {"device": dev, "host": platform.node(), "volume": {"shape": list(store.shape), "dtype": str(store.dtype)},
           "camera": CAMERA, "step": args.step, "rows": [], "speedups": []}
    for name, kind, tf, sampling in CASES:  # warm-up: build every program variant, upload the volume
        scene = {"camera": CAMERA, "width": 64, "height": 64, "tf": tf, "sampling": {"step": args.step, **sampling}}
        (run_bare if kind == "bare" else run_render)(eng, store, scene)
    rows = []
    for size in args.sizes:
        rows += measure(eng, store, size, args.step, args.repeat)
        by = {r["case"]: r for r in rows if r["size"] == size}
        on = by["render, sparse TF (ESS+ET on)"]["kernel_ms"]
        out["speedups"].append({
            "size": size,
            "ess": by["render, sparse TF, ESS off"]["kernel_ms"] / on,
            "et": by["render, sparse TF, ET off"]["kernel_ms"] / on,
            "both": by["render, sparse TF, ESS+ET off"]["kernel_ms"] / on,
        })
    out["rows"] = rows

    hdr = f"{'case':34s} {'size':>5s} {'ms/frame':>9s} {'Msamples':>9s} {'Msamples/s':>11s} {'vs bare':>8s} {'skipped':>8s}"
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        vs = f"{100 * r['vs_bare_samples_per_s']:.0f}%" if "vs_bare_samples_per_s" in r else "-"
        sk = f"{r['bricks_skipped']}/{r['blocks']}" if "blocks" in r else "-"
        print(f"{r['case']:34s} {r['size']:5d} {r['kernel_ms']:9.1f} {r['samples'] / 1e6:9.1f} "
              f"{r['samples_per_s'] / 1e6:11.1f} {vs:>8s} {sk:>8s}")
    for s in out["speedups"]:
        print(f"sparse TF at {s['size']}²: empty-space skipping ×{s['ess']:.2f} (with ET on), early termination "
              f"×{s['et']:.2f} (with ESS on), both ×{s['both']:.2f} (against neither)")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    out["finished"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    args.json.write_text(json.dumps(out, indent=2))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
