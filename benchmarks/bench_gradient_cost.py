"""Issue 45, item 4's remainder: what lit nearest-block (NB, the default) level-of-detail images pay for shading
normals from the interblock field (eq. 3.6), the kernel sources of a git revision ("old", default HEAD) against the
working tree's ("new"), and against the kernel before those normals ("pre", --pre: NB gradients from six NB
samples, the cost the issue measures against).

    .venv/bin/python benchmarks/bench_gradient_cost.py [--rev HEAD] [--pre be12259] [--pairs 20] [--builds 3]
                                                       [--json docs/measurements/gradient_cost.json]

Scenes as benchmarks/bench_seams.py's: the smooth sphere (tests/phantoms.py, 128³, SPHERE_TF, 256²) and the chest CT
(benchmarks/results/ct_chest_b16.zarr, ct-bone, 512²), lit with the default shading, azimuth 30°, elevation 20°,
16³ blocks. Per variant (lit NB 30:1, unlit NB 30:1, lit interblock 30:1, lit full resolution) interleaved pairs of
kernel ms, old and new alternating which goes first, all in this process (only the .cl/.h sources differ); the
median ratio new/old and its bootstrap 95 % interval (docs/design.md: "not worse" is an upper end <= 1.03). Lit NB
also new against pre. Build seconds: the lit NB 30:1 kernel of the last scene (the chest's: int16 voxels) compiled
from source (PoCL's cache off, an empty lodcast kernel cache), pre, old and new in turn, the median of --builds rounds, wall and this
process's CPU time.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

os.environ["POCL_KERNEL_CACHE"] = "0"  # build times: the compiler every time (read when PoCL starts)

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))

from bench_seams import lod, scenes  # noqa: E402
from kernel_gate import bootstrap, kernels_from, old_sources  # noqa: E402

from lodcast.opencl import Device  # noqa: E402
from lodcast.renderer.frame.render import Renderer  # noqa: E402

SIZES = {"sphere": 256, "chest": 512}


def variants(base: dict) -> dict[str, dict]:
    unlit = {k: v for k, v in base.items() if k != "shading"}
    return {"lit NB 30:1": lod(base, "nearest_block"), "unlit NB 30:1": lod(unlit, "nearest_block"),
            "lit II 30:1": lod(base, "interblock"), "lit full": {**base, "quality": "full"}}


def pairs(eng: Renderer, store: Any, scene: dict, a: Path | None, b: Path | None, n: int) -> dict[str, Any]:
    """n interleaved pairs of kernel ms, kernels from a and b (None: this checkout's), alternating which goes first:
    the median ms of each, the median ratio b/a and its bootstrap 95 % interval."""
    for f in (a, b):
        with kernels_from(f):
            eng.render(store, scene)  # built and warm
    ms: dict[str, list[float]] = {"a": [], "b": []}
    for i in range(n):
        for key, f in (("a", a), ("b", b)) if i % 2 == 0 else (("b", b), ("a", a)):
            with kernels_from(f):
                ms[key].append(eng.render(store, scene).report["kernel_ms"])
    r = np.array(ms["b"]) / np.array(ms["a"])
    lo, hi = bootstrap(r)
    return {"ms": [float(np.median(ms["a"])), float(np.median(ms["b"]))], "median_ratio": float(np.median(r)),
            "ci95": [lo, hi], "pairs": n}


def build_times(folders: dict[str, Path | None], opts: tuple[str, ...], rounds: int) -> dict[str, dict[str, float]]:
    """Median seconds of a from-source build of the kernel with build options opts: wall and this process's CPU
    time."""
    dev = Device(None, Path(tempfile.mkdtemp()))
    out: dict[str, dict[str, list[float]]] = {k: {"wall": [], "cpu": []} for k in folders}
    for rnd in range(rounds):
        for which, folder in folders.items():
            t, c = time.perf_counter(), time.process_time()
            dev.program("raycast.cl", opts + (f"-DLC_BENCH_ROUND={rnd}",), folder)
            out[which]["wall"].append(time.perf_counter() - t)
            out[which]["cpu"].append(time.process_time() - c)
    return {k: {m: float(np.median(v)) for m, v in d.items()} for k, d in out.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rev", default="HEAD", help="the old kernel's revision (default HEAD)")
    ap.add_argument("--pre", default="be12259", help="the kernel before interblock normals (default be12259)")
    ap.add_argument("--pairs", type=int, default=20)
    ap.add_argument("--builds", type=int, default=3, help="rounds of from-source builds (median; 0: none)")
    ap.add_argument("--scenes", default="sphere,chest")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    old = old_sources(args.rev, Path(tempfile.mkdtemp()))
    pre = old_sources(args.pre, Path(tempfile.mkdtemp()))
    eng = Renderer()
    result: dict[str, Any] = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="minutes"),
                              "machine": f"{platform.node()} ({os.cpu_count()} CPUs, {platform.processor() or platform.machine()})",
                              "device": eng.device.info(), "command": " ".join(sys.argv), "rev": args.rev,
                              "pre": args.pre, "load_before": os.getloadavg(), "scenes": {}}
    opts: tuple[str, ...] = ()
    for name, (store, base) in scenes(256, args.scenes.split(",")).items():
        base = {**base, "width": SIZES[name], "height": SIZES[name]}
        opts = tuple(eng.render(store, lod(base, "nearest_block")).report["build_options"])
        rows: dict[str, Any] = {}
        for v, sc in variants(base).items():
            rows[f"{v}: new/old"] = pairs(eng, store, sc, old, None, args.pairs)
            print(name, v, "new/old", json.dumps(rows[f"{v}: new/old"]), flush=True)
        sc = lod(base, "nearest_block")
        for key, a, b in (("new/pre", pre, None), ("old/pre", pre, old)):
            rows[f"lit NB 30:1: {key}"] = pairs(eng, store, sc, a, b, args.pairs)
            print(name, "lit NB 30:1", key, json.dumps(rows[f"lit NB 30:1: {key}"]), flush=True)
        result["scenes"][name] = rows
    if args.builds:
        result["build_options"] = list(opts)
        result["build_s"] = build_times({"pre": pre, "old": old, "new": None}, opts, args.builds)
        print("builds", json.dumps(result["build_s"]), flush=True)
    result["load_after"] = os.getloadavg()
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
