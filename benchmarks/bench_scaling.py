"""Scaling with the volume's size (issue 44 item 5): volumes of 1, 8 and 32 GiB at one memory and device budget.

    .venv/bin/python benchmarks/bench_scaling.py [--sizes 1,8,32] [--frames 12] [--size 512] [--quality budget_mb=256]
        [--json docs/measurements/scaling.json] [--plot docs/images/scaling.png]

Each volume is uint16, made by benchmarks/bench_large_volume.py's `make` (the chest CT tiled and mirrored, each tile
shifted in intensity, with noise) and ingested as `lodcast ingest` does, in a process of its own: ingest MB/s and
peak RSS. Shapes (z, y, x): 1 GiB 512 x 1024 x 1024, 8 GiB 1024 x 2048 x 2048, 32 GiB 1024 x 4096 x 4096. They are
written to benchmarks/results/large/ (never committed; a rerun measures the renders only: delete them afterwards).

Then per volume, in a fresh process with the page cache dropped first (said so where it could not be), at a brick
pool of LODCAST_BRICK_CACHE_MB=1024 and a device budget of LODCAST_DEVICE_BUDGET_MB=512, ct-bone, the size² image,
at `--quality`: budget_mb=MB (the default, 256: the selection's data stays the same as the volume grows, so the
warm frame should stay nearly flat) or reduction=R (30: the data grows with the volume, and past the budgets every
frame reads and packs again):
- a progressive render: the first stage's wall time from the request, and the final image's (and its reduction);
- a turntable of `frames` frames 2° apart after it (the warm frame: nothing read, host work and kernel), median ms
  and the median share of it outside the kernel.
Prints a table, writes JSON and the table beside it (.md) and plots time against volume size (PNG).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from bench_large_volume import LARGE, drop_caches, make, peak_rss  # noqa: E402

SHAPES = {1: (512, 1024, 1024), 8: (1024, 2048, 2048), 32: (1024, 4096, 4096)}
ENV = {"LODCAST_BRICK_CACHE_MB": "1024", "LODCAST_DEVICE_BUDGET_MB": "512"}


def _store(gib: int) -> tuple[Path, Path]:
    name = "body_" + "x".join(map(str, SHAPES[gib]))
    return LARGE / f"{name}.npy", LARGE / f"{name}.zarr"


def ingest_step(raw: str, store: str) -> None:
    """Runs in the child: ingest as `lodcast ingest` does; its peak RSS as the last line."""
    from lodcast.service.cli import main

    rc = main(["ingest", raw, store, "--spacing", "1.0,0.78125,0.78125", "--no-progress"])
    print(json.dumps({"rc": rc, "peak_rss": peak_rss()}))


def ensure(gib: int) -> dict | None:
    """The volume of `gib` GiB made and ingested (once): its ingest figures, or None when it existed before them."""
    raw, store = _store(gib)
    meta = store.with_suffix(".ingest.json")
    if not store.exists():
        LARGE.mkdir(parents=True, exist_ok=True)
        if not raw.exists():
            make(raw, SHAPES[gib])
        t = time.perf_counter()
        p = subprocess.run([sys.executable, __file__, "--ingest-step", str(raw), str(store)], capture_output=True,
                           text=True)
        if p.returncode:
            raise SystemExit(p.stderr[-3000:])
        dt = time.perf_counter() - t
        got = json.loads(p.stdout.strip().splitlines()[-1])
        meta.write_text(json.dumps({"s": dt, "mb_per_s": raw.stat().st_size / 1e6 / dt,
                                    "peak_rss_mb": got["peak_rss"] / 1e6}))
        raw.unlink()  # the raw volume was needed for ingest only
    return json.loads(meta.read_text()) if meta.exists() else None


def _quality(text: str) -> dict:
    """budget_mb=256 or reduction=30 as the scene's quality."""
    name, _, value = text.partition("=")
    if name not in ("budget_mb", "reduction") or not value:
        raise argparse.ArgumentTypeError(f"{text!r}: expected budget_mb=MB or reduction=R")
    return {name: float(value)}


def render_step(store: str, frames: int, size: int, quality: dict) -> None:
    """Runs in the child, page cache dropped by the parent: one JSON line."""
    t0 = time.perf_counter()
    import lodcast

    eng = lodcast.Renderer()
    st = lodcast.open_store(store)
    scene = {"tf": "ct-bone", "width": size, "height": size, "format": "npy", "quality": quality,
             "camera": {"azimuth": 30, "elevation": 15}}
    stages = []
    for r in eng.render_progressive(st, scene):
        stages.append({"stage": r.report["stage"], "s": time.perf_counter() - t0, "reduction": r.report["reduction"],
                       "predicted_delta_e": r.report["predicted_delta_e"], "bricks_read": r.report["bricks_read"]})
    warm = []
    for i in range(frames):
        sc = {**scene, "camera": {"azimuth": 32 + 2 * i, "elevation": 15}}
        t = time.perf_counter()
        r = eng.render(st, sc)
        ms = (time.perf_counter() - t) * 1e3
        warm.append({"ms": ms, "kernel_ms": r.report["kernel_ms"], "bricks_read": r.report["bricks_read"]})
    print(json.dumps({"stages": stages, "warm": warm, "peak_rss_mb": peak_rss() / 1e6}))


def table(rows: list[dict]) -> str:
    lines = ["| volume | ingest MB/s | ingest peak RSS (MB) | first stage, cold (s) | final image, cold (s) | "
             "its reduction | warm frame (ms, median) | host share of a warm frame | bricks read, warm | "
             "renderer peak RSS (MB) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ing = r.get("ingest") or {}
        w = r["warm"]
        host = np.median([(f["ms"] - f["kernel_ms"]) / f["ms"] for f in w])
        lines.append(
            f"| {r['gib']} GiB {'x'.join(map(str, r['shape']))} | {ing.get('mb_per_s', float('nan')):.0f} | "
            f"{ing.get('peak_rss_mb', float('nan')):.0f} | {r['stages'][0]['s']:.1f} | {r['stages'][-1]['s']:.1f} | "
            f"{r['stages'][-1]['reduction']:.0f}:1 | {np.median([f['ms'] for f in w]):.0f} | {host:.0%} | {sum(f['bricks_read'] for f in w)} | "
            f"{r['peak_rss_mb']:.0f} |")
    return "\n".join(lines)


def plot(rows: list[dict], path: Path, quality: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    gib = [r["gib"] for r in rows]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.6))
    ax[0].plot(gib, [r["stages"][0]["s"] for r in rows], "o-", label="first progressive stage")
    ax[0].plot(gib, [r["stages"][-1]["s"] for r in rows], "s-", label="final image")
    ax[0].set(xscale="log", yscale="log", xlabel="volume (GiB)", ylabel="seconds from request, page cache dropped",
              title="cold")
    ax[1].plot(gib, [np.median([f["ms"] for f in r["warm"]]) for r in rows], "o-", label="frame")
    ax[1].plot(gib, [np.median([f["kernel_ms"] for f in r["warm"]]) for r in rows], "s--", label="kernel")
    what = ", ".join(f"{k} {v:g}" for k, v in quality.items())
    ax[1].set(xscale="log", xlabel="volume (GiB)", ylabel="ms", title=f"warm new view, {what}", ylim=(0, None))
    for a in ax:
        a.set_xticks(gib, [str(g) for g in gib])
        a.legend(fontsize=8)
        a.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1,8,32")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--quality", type=_quality, default={"budget_mb": 256.0})
    ap.add_argument("--make-only", action="store_true", help="make and ingest the volumes, render nothing")
    ap.add_argument("--json", type=Path, default=ROOT / "docs" / "measurements" / "scaling.json")
    ap.add_argument("--plot", type=Path, default=ROOT / "docs" / "images" / "scaling.png")
    ap.add_argument("--ingest-step", nargs=2, help=argparse.SUPPRESS)
    ap.add_argument("--render-step", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.ingest_step:
        return ingest_step(*a.ingest_step)
    if a.render_step:
        return render_step(a.render_step, a.frames, a.size, a.quality)
    sizes = [int(s) for s in a.sizes.split(",")]
    ingests = {g: ensure(g) for g in sizes}
    if a.make_only:
        return
    rows = []
    for g in sizes:
        dropped = drop_caches()
        q = ",".join(f"{k}={v:g}" for k, v in a.quality.items())
        p = subprocess.run([sys.executable, __file__, "--render-step", str(_store(g)[1]), "--frames", str(a.frames),
                            "--size", str(a.size), "--quality", q], capture_output=True, text=True,
                           env={**os.environ, **ENV})
        if p.returncode:
            raise SystemExit(p.stderr[-3000:])
        row = {"gib": g, "shape": SHAPES[g], "ingest": ingests[g], "page_cache_dropped": dropped,
               **json.loads(p.stdout.strip().splitlines()[-1])}
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "warm"}), flush=True)
    cpu = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                if ln.startswith("model name")), platform.processor())
    res = {"date": time.strftime("%Y-%m-%d"), "nproc": os.cpu_count(), "cpu": cpu, "command": " ".join(sys.argv),
           "env": ENV, "quality": a.quality, "rows": rows, "table": table(rows)}
    print(res["table"])
    a.json.parent.mkdir(parents=True, exist_ok=True)
    a.json.write_text(json.dumps(res, indent=2))
    a.json.with_suffix(".md").write_text(res["table"] + "\n")
    plot(rows, a.plot, a.quality)
    print(f"wrote {a.json} and {a.plot}")


if __name__ == "__main__":
    main()
