"""Issue 45, item 4's figures: seams at 30:1 with shading, nearest block (NB, the default) and interblock (II), the
kernel sources of a git revision ("before", default HEAD) against the working tree's ("after").

    .venv/bin/python benchmarks/bench_seams.py [--rev REV] [--size 256] [--pairs 5]
                                               [--json docs/measurements/seams.json] [--images docs/images]

Scenes: tests/phantoms.py's smooth sphere (128³, SPHERE_TF) and the chest CT (../shared/data/ct_chest_dicom,
preset ct-bone), both in 16³ blocks under benchmarks/results/, lit with the default shading, azimuth 30°,
elevation 20°, size², the default step ½. Each 30:1 image is compared with full resolution at the same step
(renderer/image/seams.py): mean, p99.9 and max ΔE, and the seam measure — mean ΔE on the pixels whose rays show
something within reach of a level change against the others, and the same over every face where a coarse block
meets another ("coarse faces": nearest block's clamp also parts two coarse blocks of one level). Kernel ms: pairs
of before/after renders interleaved round by round (this 2-core machine is shared; compare ratios within one
run), median ratio after/before. Build times: every kernel compiled from source (PoCL's own cache off, an empty
lodcast kernel cache), before and after alternating.
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

from bench_consistent_lod import RESULTS, chest_store  # noqa: E402
from kernel_gate import kernels_from, old_sources  # noqa: E402
from phantoms import SPHERE_TF, sphere_ramp  # noqa: E402

import lodcast  # noqa: E402
from lodcast.opencl import Device  # noqa: E402
from lodcast.renderer.frame.render import Renderer  # noqa: E402
from lodcast.renderer.image.delta_e import delta_e_image  # noqa: E402
from lodcast.renderer.image.seams import crossings_of, seam_stats  # noqa: E402
from lodcast.renderer.kernel.config import KernelConfig  # noqa: E402

INTERP = ("nearest_block", "interblock")


def sphere_store() -> Any:
    dest = RESULTS / "sphere_ramp_b16.zarr"
    if dest.exists():
        return lodcast.open_store(dest)
    return lodcast.ingest(sphere_ramp(128), dest, block_size=16, overwrite=True, progress=False)


def scenes(size: int, names: list[str]) -> dict[str, tuple[Any, dict]]:
    base = {"camera": {"azimuth": 30, "elevation": 20}, "width": size, "height": size, "shading": {}, "format": "npy"}
    out = {"sphere": lambda: (sphere_store(), {**base, "tf": SPHERE_TF}),
           "chest": lambda: (chest_store(), {**base, "tf": "ct-bone"})}
    return {n: out[n]() for n in names if n}


def lod(base: dict, interp: str) -> dict:
    return {**base, "quality": {"reduction": 30}, "sampling": {"interpolation": interp}}


def errors(eng: Renderer, store: Any, base: dict, full: np.ndarray, crossings: Any, interp: str) -> dict[str, Any]:
    sc = lod(base, interp)
    r = eng.render(store, sc)
    levels = eng.prepare(store, sc).lod.levels
    de, fp = delta_e_image(r.rgba, full)
    return {"reduction": r.report["reduction"], "mean": float(de[fp].mean()),
            "p99_9": float(np.percentile(de[fp], 99.9)), "max": float(de[fp].max()),
            "level_change": seam_stats(r.rgba, full, crossings.mask(levels)).as_dict(),
            "coarse_faces": seam_stats(r.rgba, full, crossings.mask(levels, "coarse")).as_dict(), "rgba": r.rgba}


def build_times(folders: dict[str, Path | None], rounds: int) -> dict[str, dict[str, float]]:
    """Median seconds of a from-source build of the lit 30:1 kernel per interpolation: wall and the process's
    CPU time (the compiler runs in this thread; on a loaded machine the wall time is mostly waiting)."""
    dev = Device(None, Path(tempfile.mkdtemp()))
    out: dict[str, dict[str, list[float]]] = {k: {f"{i}{w}": [] for i in INTERP for w in ("", "_cpu")}
                                              for k in folders}
    for rnd in range(rounds):
        for interp in INTERP:
            for which, folder in folders.items():
                opts = KernelConfig(sampler="atlas", interpolation=interp, shade=True, distribution=True,
                                    voxel="short").build_options() + (f"-DLC_BENCH_ROUND={rnd}",)
                t, c = time.perf_counter(), time.process_time()
                dev.program("raycast.cl", opts, folder)
                out[which][interp].append(time.perf_counter() - t)
                out[which][f"{interp}_cpu"].append(time.process_time() - c)
    return {k: {i: float(np.median(v)) for i, v in d.items()} for k, d in out.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rev", default="HEAD", help="the before kernel's revision (default HEAD; after a commit of the change, the commit before it)")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--pairs", type=int, default=5, help="interleaved before/after timing pairs per variant")
    ap.add_argument("--builds", type=int, default=2, help="rounds of from-source builds (median; 0: none)")
    ap.add_argument("--scenes", default="sphere,chest", help="comma-separated: sphere, chest (empty: builds only)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--images", type=Path, default=None, help="write the sphere's before/after picture there")
    args = ap.parse_args()
    old = old_sources(args.rev, Path(tempfile.mkdtemp()))
    folders: dict[str, Path | None] = {"before": old, "after": None}
    eng = Renderer()
    result: dict[str, Any] = {"date": datetime.date.today().isoformat(),
                              "machine": f"{platform.node()} ({os.cpu_count()} CPUs, {platform.machine()})",
                              "device": eng.device.info(), "command": " ".join(sys.argv), "rev": args.rev,
                              "size": args.size, "scenes": {}}
    pictures: dict[str, np.ndarray] = {}
    for name, (store, base) in scenes(args.size, args.scenes.split(",")).items():
        full = eng.render(store, {**base, "quality": "full"}).rgba
        cross = crossings_of(eng.prepare(store, lod(base, "nearest_block")))
        rows: dict[str, Any] = {}
        for which, folder in folders.items():
            with kernels_from(folder):
                for interp in INTERP:
                    e = errors(eng, store, base, full, cross, interp)
                    if name == "sphere":
                        pictures[f"{which}_{interp}"] = e["rgba"]
                    rows[f"{which}_{interp}"] = {k: v for k, v in e.items() if k != "rgba"}
                    lc, cf = e["level_change"], e["coarse_faces"]
                    print(f"{name} {which} {interp}: ΔE mean {e['mean']:.3f} p99.9 {e['p99_9']:.2f} max "
                          f"{e['max']:.1f}; level change {lc['seam_delta_e']} / {lc['rest_delta_e']} = "
                          f"{lc['seam_ratio']}; coarse faces {cf['seam_ratio']}", flush=True)
        ms: dict[str, list[float]] = {f"{w}_{v}": [] for w in folders for v in ("full",) + INTERP}
        for _ in range(args.pairs):
            for v in ("full",) + INTERP:
                sc = {**base, "quality": "full"} if v == "full" else lod(base, v)
                for which, folder in folders.items():
                    with kernels_from(folder):
                        eng.render(store, sc)
                        ms[f"{which}_{v}"].append(eng.render(store, sc).report["kernel_ms"])
        timing = {k: float(np.median(t)) for k, t in ms.items()}
        timing.update({f"ratio_{v}": float(np.median(np.array(ms[f"after_{v}"]) / np.array(ms[f"before_{v}"])))
                       for v in ("full",) + INTERP})
        print(name, json.dumps(timing), flush=True)
        result["scenes"][name] = {"errors": rows, "kernel_ms": timing}
    if args.builds:
        result["build_s"] = build_times(folders, args.builds)
        print("builds", json.dumps(result["build_s"]), flush=True)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    if args.images:
        from lodcast.renderer.image.output import save_image

        crop = slice(args.size // 4, 3 * args.size // 4)
        row = np.concatenate([pictures[k][crop, crop] for k in ("before_nearest_block", "after_nearest_block",
                                                                  "after_interblock")], axis=1).copy()
        row[..., 3] = 1.0  # over opaque black, as the CLI writes pictures
        save_image(args.images / "seams_sphere_30to1.png", row)
    return 0


if __name__ == "__main__":
    sys.exit(main())
