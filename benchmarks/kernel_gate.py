"""The kernel gate (issue 43, item 2): the kernel sources of a git revision ("old", default HEAD) against the
working tree's ("new"), on the same stores, over scenes that cover every pair of values of the kernel's options
(a greedy pairwise covering array over the scene settings that select them), plus a few scenes per family for
timing. For each scene: the largest difference of the two images in alpha and in colour (premultiplied RGBA
float32; 0.0 where the arithmetic order is unchanged) and whether both kernels took the same samples; for each
family (dense, bone, soft, 30:1, dual TF, pre-integrated, passes): interleaved A/B pairs of kernel ms, the median
ratio new/old and a bootstrap 95 % interval (docs/design.md, "How targets are measured": not worse means the
interval's upper end <= 1.03).

    .venv/bin/python benchmarks/kernel_gate.py                      # HEAD's kernel against the working tree's
    .venv/bin/python benchmarks/kernel_gate.py --rev 6972ac4 --pairs 20 --json docs/measurements/kernel_gate.json

Only the .cl/.h sources differ between the two renderers (both use this checkout's Python); the old sources are
taken with `git show REV:renderer/kernel/FILE` into a temporary folder.
"""
from __future__ import annotations

import argparse
import itertools
import json
import platform
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

import lodcast  # noqa: E402
from lodcast import opencl  # noqa: E402
from lodcast.renderer.frame.render import Renderer  # noqa: E402

#: scene settings that select kernel options, each with the values a covering set takes
FACTORS: dict[str, list[Any]] = {
    "quality": ["full", {"reduction": 8}, "lossless"],
    "interpolation": ["nearest_block", "interblock"],
    "adaptive_object": [None, False, "naive"],
    "classification": ["distribution", "mean"],
    "mode": ["composite", "mip", "minip", "average", "iso"],
    "projection": ["perspective", "orthographic"],
    "empty_space_skipping": [True, False],
    "jitter": [False, True],
    "step": [0.5, 0.04],  # 0.04 on the volume below: more than 4,096 samples a ray, the compensated sums
    "background": [False, True],
    "clip": [False, True],
    "shading": [False, True],
    "preintegration": [False, True],
    "tf2": [False, True],
    "adaptive_screen": [False, True],
    "budget": [None, 0.4],  # a share of level 0's bytes as the device budget: the volume data in passes
    "voxel": ["float32", "int16", "uint8"],
}
TF = {"points": [{"value": 0.35, "color": [1.0, 0.6, 0.4], "opacity": 0.0},
                 {"value": 0.6, "color": [1.0, 0.9, 0.8], "opacity": 0.15},
                 {"value": 1.0, "color": [1.0, 1.0, 1.0], "opacity": 0.8}]}
TF2 = {"points": [{"value": 0.85, "color": [0.3, 0.6, 1.0], "opacity": 0.0},
                  {"value": 0.95, "color": [0.3, 0.6, 1.0], "opacity": 0.9}]}


def valid(row: dict[str, Any]) -> bool:
    """What the renderer allows: a second TF in composite mode only; naive adaptive steps not in passes."""
    return not (row["tf2"] and row["mode"] != "composite") and not (row["adaptive_object"] == "naive"
                                                                   and row["budget"] is not None)


def pairwise(factors: dict[str, list[Any]], seed: int = 0) -> list[dict[str, Any]]:
    """A greedy covering array: valid rows until every pair of values of every two factors that some valid row can
    hold appears in one."""
    names = list(factors)

    def possible(a: int, i: int, b: int, j: int) -> bool:
        probe = {n: factors[n][0] for n in names}
        probe.update({names[a]: factors[names[a]][i], names[b]: factors[names[b]][j]})
        if not valid(probe) and names[a] != "mode" and names[b] != "mode":
            probe["mode"] = "composite"
        if not valid(probe) and names[a] != "tf2" and names[b] != "tf2":
            probe["tf2"] = False
        return valid(probe)

    todo = {(a, i, b, j) for a, b in itertools.combinations(range(len(names)), 2)
            for i in range(len(factors[names[a]])) for j in range(len(factors[names[b]])) if possible(a, i, b, j)}
    rng = np.random.default_rng(seed)
    rows = []
    while todo:
        best, gain = None, -1
        for _ in range(60):
            row = [int(rng.integers(len(factors[n]))) for n in names]
            a, i, b, j = next(iter(todo))  # make sure the candidate covers at least one missing pair
            row[a], row[b] = i, j
            if not valid({n: factors[n][k] for n, k in zip(names, row)}):
                continue
            g = sum((x, row[x], y, row[y]) in todo for x, y in itertools.combinations(range(len(names)), 2))
            if g > gain:
                best, gain = row, g
        assert best is not None
        todo -= {(x, best[x], y, best[y]) for x, y in itertools.combinations(range(len(names)), 2)}
        rows.append({n: factors[n][k] for n, k in zip(names, best)})
    return rows


def scene_of(row: dict[str, Any], size: int) -> tuple[dict[str, Any], float | None, str]:
    """The scene a row asks for, its device budget and its voxel type."""
    cam: dict[str, Any] = {"azimuth": 35, "elevation": 20}
    if row["projection"] == "orthographic":
        cam = {"azimuth": 35, "elevation": 20, "projection": "orthographic", "view_height": 180.0}
    scene: dict[str, Any] = {
        "tf": TF, "width": size, "height": size, "camera": cam, "format": "npy", "quality": row["quality"],
        "mode": row["mode"],
        "sampling": {"interpolation": row["interpolation"], "classification": row["classification"],
                     "empty_space_skipping": row["empty_space_skipping"], "jitter": row["jitter"],
                     "step": row["step"], "preintegration": row["preintegration"],
                     "adaptive_screen": row["adaptive_screen"]},
    }
    if row["adaptive_object"] == "naive":
        scene["sampling"]["adaptive_naive"] = True
    elif row["adaptive_object"] is not None:
        scene["sampling"]["adaptive_object"] = row["adaptive_object"]
    if row["mode"] == "iso":
        scene["isovalue"] = 0.6
    if row["background"]:
        scene["background"] = [0.1, 0.1, 0.2, 1.0]
    if row["clip"]:
        scene["clip"] = {"planes": [{"point": [64, 56, 48], "normal": [1, 0.3, 0]}]}
    if row["shading"]:
        scene["shading"] = {}
    if row["tf2"]:
        scene["tf2"] = TF2
    return scene, row["budget"], row["voxel"]


def volume(dtype: str) -> np.ndarray:
    """Shells and blobs in [0, 1] (scaled to the integer types), 96 x 112 x 128: empty space, thin surfaces, a
    translucent band, values for both TFs."""
    rng = np.random.default_rng(1)
    z, y, x = np.mgrid[:96, :112, :128].astype(np.float64)
    r = np.sqrt((z - 48) ** 2 + (y - 56) ** 2 + (x - 64) ** 2) * (32 / 48)
    a = 0.3 * np.exp(-((r - 26) / 5) ** 2) + 0.7 * (np.abs(r - 14) < 1.5) + 0.25 * rng.random(r.shape) * (r < 30)
    a += 0.95 * (((z - 30) ** 2 + (y - 45) ** 2 + (x - 80) ** 2) < 64)
    a = np.clip(a, 0.0, 1.0)
    if dtype == "uint8":
        return np.rint(a * 255).astype(np.uint8)
    if dtype == "int16":
        return np.rint(a * 4000 - 1000).astype(np.int16)
    return a.astype(np.float32)


def tf_for(scene: dict[str, Any], dtype: str) -> dict[str, Any]:
    """The scene with its TFs (and isovalue) moved onto the integer types' value scale."""
    scale, shift = {"uint8": (255.0, 0.0), "int16": (4000.0, -1000.0)}.get(dtype, (1.0, 0.0))

    def move(tf: dict[str, Any]) -> dict[str, Any]:
        return {"points": [{**p, "value": p["value"] * scale + shift} for p in tf["points"]]}

    out = {**scene, "tf": move(scene["tf"])}
    if scene.get("tf2"):
        out["tf2"] = move(scene["tf2"])
    if "isovalue" in scene:
        out["isovalue"] = scene["isovalue"] * scale + shift
    return out


@contextmanager
def kernels_from(folder: Path | None) -> Iterator[None]:
    """Renders in this context build their programs from `folder`'s sources (None: this checkout's)."""
    real = opencl.renderer_folder
    if folder is not None:
        opencl.renderer_folder = lambda: folder  # type: ignore[assignment]
    try:
        yield
    finally:
        opencl.renderer_folder = real  # type: ignore[assignment]


def old_sources(rev: str, dest: Path) -> Path:
    names = subprocess.run(["git", "ls-tree", "--name-only", f"{rev}:renderer/kernel"], cwd=REPO, check=True,
                           capture_output=True, text=True).stdout.split()
    for n in names:
        if n.endswith((".cl", ".h")):
            blob = subprocess.run(["git", "show", f"{rev}:renderer/kernel/{n}"], cwd=REPO, check=True,
                                  capture_output=True).stdout
            (dest / n).write_bytes(blob)
    return dest


def bootstrap(ratios: np.ndarray, n: int = 2000, seed: int = 0) -> tuple[float, float]:
    rng = np.random.default_rng(seed)
    meds = np.median(rng.choice(ratios, (n, ratios.size), replace=True), axis=1)
    return float(np.quantile(meds, 0.025)), float(np.quantile(meds, 0.975))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rev", default="HEAD", help="the old kernel's revision (default HEAD)")
    ap.add_argument("--size", type=int, default=48, help="image edge of the covering scenes (default 48)")
    ap.add_argument("--pairs", type=int, default=20,
                    help="interleaved A/B pairs per timing family (default 20; 0: images only)")
    ap.add_argument("--timing-size", type=int, default=256)
    ap.add_argument("--families", default=None, help="comma-separated timing families (default: all)")
    ap.add_argument("--images", action=argparse.BooleanOptionalAction, default=True,
                    help="compare the covering set's images (--no-images: timing only, for an old kernel that takes "
                         "options this checkout no longer passes)")
    ap.add_argument("--json", type=Path, default=None, help="write the results there too")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="lodcast-gate-"))
    (work / "old").mkdir()
    old = old_sources(args.rev, work / "old")
    stores = {dt: lodcast.ingest(volume(dt), work / f"{dt}.zarr", block_size=16, progress=False)
              for dt in FACTORS["voxel"]}
    rows = pairwise(FACTORS) if args.images else []
    print(f"{len(rows)} scenes cover every pair of {len(FACTORS)} settings; old kernel: {args.rev}", flush=True)
    results, refused = [], 0
    worst_a = worst_c = 0.0
    for k, row in enumerate(rows):
        scene, share, dtype = scene_of(row, args.size)
        scene = tf_for(scene, dtype)
        budget = None if share is None else share * stores[dtype].layout.n_voxels * np.dtype(dtype).itemsize / 1e6
        out = []
        for folder in (old, None):
            with kernels_from(folder):
                try:
                    out.append(Renderer(device_budget_mb=budget).render(stores[dtype], scene))
                except ValueError as exc:  # a combination the renderer refuses (e.g. naive steps in passes)
                    out.append(exc)
        if isinstance(out[0], Exception) or isinstance(out[1], Exception):
            same = type(out[0]) is type(out[1]) and str(out[0]) == str(out[1])
            refused += 1
            results.append({"row": k, "refused": str(out[0]), "same_refusal": same})
            continue
        a, b = out[0].rgba, out[1].rgba
        da, dc = float(np.abs(a[..., 3] - b[..., 3]).max()), float(np.abs(a[..., :3] - b[..., :3]).max())
        worst_a, worst_c = max(worst_a, da), max(worst_c, dc)
        results.append({"row": k, "options": out[1].report["build_options"], "alpha": da, "colour": dc,
                        "identical": bool(np.array_equal(a, b)),
                        "samples": [out[0].report["samples"], out[1].report["samples"]]})
    identical = sum(1 for r in results if r.get("identical"))
    same_samples = sum(1 for r in results if "samples" in r and r["samples"][0] == r["samples"][1])
    print(f"images: {identical} of {len(results) - refused} bit for bit the same; largest difference alpha "
          f"{worst_a:.3g}, colour {worst_c:.3g}; the same samples taken in {same_samples}; {refused} combinations "
          "refused alike by both", flush=True)
    families = {
        "dense": ({"tf": TF, "quality": "full"}, None),
        "bone": ({"tf": {"points": [{"value": 0.55, "color": [1, 0.9, 0.8], "opacity": 0.0},
                                    {"value": 0.75, "color": [1, 1, 1], "opacity": 0.9}]}, "quality": "full"}, None),
        "soft": ({"tf": {"points": [{"value": 0.05, "color": [1, 0.7, 0.5], "opacity": 0.0},
                                    {"value": 0.4, "color": [1, 0.8, 0.7], "opacity": 0.03}]}, "quality": "full"}, None),
        "30:1": ({"tf": TF, "quality": {"reduction": 30}}, None),
        "dual TF": ({"tf": TF, "tf2": TF2, "quality": "full"}, None),
        "pre-integrated": ({"tf": TF, "quality": "full", "sampling": {"preintegration": True}}, None),
        "passes": ({"tf": TF, "quality": "full"}, 0.4 * volume("float32").nbytes / 1e6),
    }
    if args.families:
        families = {k: v for k, v in families.items() if k in args.families.split(",")}
    timing = {}
    for name, (extra, budget) in families.items() if args.pairs > 0 else ():
        scene = {"width": args.timing_size, "height": args.timing_size, "format": "npy",
                 "camera": {"azimuth": 35, "elevation": 20}, **extra}
        engines = []
        for folder in (old, None):
            with kernels_from(folder):
                eng = Renderer(device_budget_mb=budget)
                eng.render(stores["float32"], scene)  # built and warm
            engines.append((folder, eng))
        ratios = []
        for _ in range(args.pairs):
            ms = []
            for folder, eng in engines:
                with kernels_from(folder):
                    ms.append(eng.render(stores["float32"], scene).report["kernel_ms"])
            ratios.append(ms[1] / ms[0])
        r = np.array(ratios)
        lo, hi = bootstrap(r)
        timing[name] = {"median_ratio": float(np.median(r)), "ci95": [lo, hi], "pairs": len(r)}
        print(f"  {name:15s} new/old kernel ms: median {np.median(r):.3f} (95 % {lo:.3f}-{hi:.3f})", flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        dev = Renderer().device.info()
        args.json.write_text(json.dumps({
            "date": time.strftime("%Y-%m-%d"), "machine": f"{platform.node()}: {dev['name']} ({dev['platform']})",
            "command": " ".join(sys.argv), "old": args.rev, "scenes": len(rows), "identical": identical, "same_samples": same_samples,
            "largest_alpha": worst_a, "largest_colour": worst_c, "refused": refused, "rows": results,
            "timing": timing}, indent=1))
    return 0 if worst_a <= 1e-5 and worst_c <= 1e-5 and same_samples == len(results) - refused else 1


if __name__ == "__main__":
    sys.exit(main())
