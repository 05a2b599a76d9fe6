"""Warm new views of a large volume with the selection weighed by the view (issue 44): each view selects again, and
a move of 2° changes the level of a few thousand blocks, whose bricks are read and placed in a new atlas.

    .venv/bin/python benchmarks/bench_new_view.py [--store benchmarks/results/large/body_1024x2048x2048.zarr]
        [--views 6] [--size 512] [--reduction 30] [--profile new_view.prof] [--json results/new_view.json]
        [--against ../base-worktree --pairs 5]

One renderer in this process (its settings from the LODCAST_* environment): a first view at azimuth 30° (cold for
the process, not counted), then `views` new views 2° apart, elevation 20°, ct-bone, `{"reduction": R}`, `size`²,
`"sampling": {"lod_visibility": true}`. Per view: the wall time of `Renderer.render`, the process's CPU time over
it (every thread's, the device's included on a CPU device: on a busy machine steadier than the wall time) and
the report's own figures (wall, kernel, upload and build ms, bricks read and cached), and every view's image
(SHA-1 of its RGBA bytes, the first view's too). `--profile FILE`: the new views run under
cProfile, whose statistics go to FILE (and the top of them, by cumulative time, to stdout); the times printed
then include the profiler's overhead. Prints the medians and writes JSON.

`--against DIR` (a worktree of another commit, with its own .venv): A/B instead, `pairs` interleaved pairs of
processes, this checkout's and DIR's, the order alternating between pairs, each process this benchmark (this
file, run by the other's interpreter, imports the other's lodcast); per process the median new view (wall and
CPU), and the ratios this / other: their median and a bootstrap 95 % interval; whether every process rendered the
same images.
"""
from __future__ import annotations

import argparse
import cProfile
import hashlib
import json
import os
import pstats
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from record import bootstrap, provenance, write_result  # noqa: E402

import lodcast  # noqa: E402

AZ0, STEP, ELEVATION = 30.0, 2.0, 20.0
REPORTED = ("wall_ms", "kernel_ms", "upload_ms", "build_ms", "bricks_read", "bricks_cached")


def scene(azimuth: float, size: int, reduction: float) -> dict:
    return {"camera": {"azimuth": azimuth, "elevation": ELEVATION}, "width": size, "height": size,
            "tf": "ct-bone", "quality": {"reduction": reduction}, "sampling": {"lod_visibility": True}}


def new_views(store: Path, views: int, size: int, reduction: float, profile: Path | None) -> dict:
    """The first view's time and, per new view, the wall time and the report's figures."""
    eng = lodcast.Renderer()
    t0 = time.perf_counter()
    r = eng.render(str(store), scene(AZ0, size, reduction))
    first = (time.perf_counter() - t0) * 1e3
    hashes = [hashlib.sha1(r.rgba.tobytes()).hexdigest()]
    prof = cProfile.Profile() if profile is not None else None
    rows = []
    for i in range(1, views + 1):
        sc = scene(AZ0 + STEP * i, size, reduction)
        t0, c0 = time.perf_counter(), time.process_time()
        if prof is not None:
            prof.enable()
        r = eng.render(str(store), sc)
        if prof is not None:
            prof.disable()
        rows.append({"ms": (time.perf_counter() - t0) * 1e3, "cpu_ms": (time.process_time() - c0) * 1e3,
                     **{k: r.report[k] for k in REPORTED}})
        hashes.append(hashlib.sha1(r.rgba.tobytes()).hexdigest())
    eng.close()
    if prof is not None:
        assert profile is not None
        prof.dump_stats(str(profile))
        pstats.Stats(str(profile)).sort_stats("cumulative").print_stats(45)
    return {"first_ms": first, "views": rows, "rgba_sha1": hashes,
            "median_ms": float(np.median([r["ms"] for r in rows])),
            "median_cpu_ms": float(np.median([r["cpu_ms"] for r in rows])),
            "median_host_ms": float(np.median([r["wall_ms"] - r["kernel_ms"] for r in rows])),
            "median_kernel_ms": float(np.median([r["kernel_ms"] for r in rows])),
            "median_bricks_read": float(np.median([r["bricks_read"] for r in rows]))}


def one_process(python: Path, args: list[str]) -> dict:
    """This benchmark run once by `python` (its lodcast, that of the checkout whose .venv it is), its JSON."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run.json"
        subprocess.run([str(python), str(Path(__file__).resolve()), *args, "--json", str(out)], check=True,
                       stdout=subprocess.DEVNULL)
        return json.loads(out.read_text())


def ab(other: Path, pairs: int, args: list[str]) -> dict:
    """`pairs` interleaved pairs (this checkout, `other`), the order alternating; ratios this / other."""
    pythons = {"this": Path(sys.executable), "other": other / ".venv" / "bin" / "python"}
    runs: dict[str, list[dict]] = {"this": [], "other": []}
    for i in range(pairs):
        for who in (("other", "this") if i % 2 == 0 else ("this", "other")):
            r = one_process(pythons[who], args)
            runs[who].append({k: r[k] for k in ("median_ms", "median_cpu_ms", "median_kernel_ms", "load",
                                                "load_after", "first_ms", "rgba_sha1")})
            print(f"pair {i + 1} {who}: median {r['median_ms']:.0f} ms, CPU {r['median_cpu_ms']:.0f} ms "
                  f"(load {r['load'][0]:.2f})", flush=True)
    res: dict = {"runs": runs, "images_identical": len({tuple(r["rgba_sha1"]) for rs in runs.values() for r in rs}) == 1}
    for what in ("median_ms", "median_cpu_ms"):
        ratio = np.array([a[what] / b[what] for a, b in zip(runs["this"], runs["other"])])
        res[what] = {"this": float(np.median([r[what] for r in runs["this"]])),
                     "other": float(np.median([r[what] for r in runs["other"]])),
                     "ratio_median": float(np.median(ratio)), "ratio_ci95": bootstrap(ratio), "ratios": ratio.tolist()}
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--store", type=Path, default=HERE / "results" / "large" / "body_1024x2048x2048.zarr")
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--reduction", type=float, default=30.0)
    ap.add_argument("--profile", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=HERE / "results" / "new_view.json")
    ap.add_argument("--against", type=Path, default=None)
    ap.add_argument("--pairs", type=int, default=5)
    a = ap.parse_args(argv)
    if not a.store.is_dir():
        print(f"--store: {a.store} is not a store (make one with benchmarks/bench_large_volume.py)", file=sys.stderr)
        return 2
    if a.against is not None:
        args = ["--store", str(a.store.resolve()), "--views", str(a.views), "--size", str(a.size),
                "--reduction", str(a.reduction)]
        res = {**provenance("bench_new_view.py"), "load": os.getloadavg(), "against": str(a.against),
               "store": a.store.name, "views": a.views, "size": a.size, "reduction": a.reduction,
               **ab(a.against, a.pairs, args), "load_after": os.getloadavg()}
        for what in ("median_ms", "median_cpu_ms"):
            r = res[what]
            print(f"{what}: this {r['this']:.0f}, other {r['other']:.0f}, ratio {r['ratio_median']:.3f} "
                  f"[{r['ratio_ci95'][0]:.3f}, {r['ratio_ci95'][1]:.3f}]")
        print(f"images identical in every process: {res['images_identical']}")
        write_result(a.json, res, indent=1)
        return 0
    res = {**provenance("bench_new_view.py"), "load": os.getloadavg(), "store": a.store.name, "size": a.size,
           "reduction": a.reduction, "step_deg": STEP, "profiled": a.profile is not None,
           "env": {k: v for k, v in os.environ.items() if k.startswith("LODCAST_")}}
    res.update(new_views(a.store, a.views, a.size, a.reduction, a.profile))
    res["load_after"] = os.getloadavg()
    print(f"\n{a.store.name}, {a.size}², reduction {a.reduction:g}, lod_visibility on, {a.views} new views "
          f"{STEP:g}° apart (load {res['load'][0]:.2f} -> {res['load_after'][0]:.2f})\n")
    print("| view | ms | CPU ms | kernel ms | upload ms | bricks read | bricks cached |")
    print("|---|---|---|---|---|---|---|")
    for i, r in enumerate(res["views"], 1):
        print(f"| {i} | {r['ms']:.0f} | {r['cpu_ms']:.0f} | {r['kernel_ms']:.0f} | {r['upload_ms']:.0f} | "
              f"{r['bricks_read']} | {r['bricks_cached']} |")
    print(f"\nfirst view {res['first_ms']:.0f} ms; new view median {res['median_ms']:.0f} ms, CPU "
          f"{res['median_cpu_ms']:.0f} ms (host {res['median_host_ms']:.0f}, kernel {res['median_kernel_ms']:.0f})")
    write_result(a.json, res, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
