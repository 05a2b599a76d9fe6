"""The pictures of `run.py`: error against time of every renderer, a gallery of LOD qualities with ΔE and ms under
each image, and `lodcast report`'s own plot; `publish` copies them to docs/images/ for the README and docs/benchmarks.md."""
from __future__ import annotations

import shutil
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["error_vs_time", "gallery", "demo_row", "report_plot", "publish"]

PUBLISHED = {"error_vs_time.png": "benchmark_error_vs_time.png", "gallery.png": "gallery.png",
             "report.png": "report_chest_bone.png"}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def error_vs_time(rows: list[dict], path: Path) -> Path:
    """One panel per volume and TF: mean ΔE against ms; full-resolution steps joined by a line per renderer."""
    plt = _plt()
    keys = list(dict.fromkeys((r["volume"], r["tf"]) for r in rows))
    fig, axes = plt.subplots(1, len(keys), figsize=(4.2 * len(keys), 3.8), dpi=110, squeeze=False)
    for ax, key in zip(axes[0], keys):
        rs = [r for r in rows if (r["volume"], r["tf"]) == key]
        peers = sorted({r["renderer"] for r in rs} - {"lodcast", "VTK FixedPoint"})
        styles = [("lodcast", "C0o-"), ("VTK FixedPoint", "C3s--")] + [(p, f"C{4 + i}D:") for i, p in enumerate(peers)]
        for renderer, style in styles:
            pts = sorted((r["ms"], r["delta_e"], r["step"]) for r in rs
                         if r["renderer"] == renderer and r["quality"] == "full")
            if pts:
                ax.plot([p[0] for p in pts], [p[1] for p in pts], style, label=f"{renderer}, full resolution")
                for ms, de, st in pts:
                    ax.annotate(f"step {st:g}", (ms, de), fontsize=7, xytext=(3, 3), textcoords="offset points")
        lod = [r for r in rs if r["renderer"] == "lodcast" and r["quality"] != "full"]
        ax.plot([r["ms"] for r in lod], [r["delta_e"] for r in lod], "C2^", label="lodcast LOD (default sampling)")
        for r in lod:
            ax.annotate(r["quality"], (r["ms"], r["delta_e"]), fontsize=7, xytext=(3, -9), textcoords="offset points")
        ax.set_xscale("log")
        # plain numbers, minor ticks labelled at 2 and 5 only (matplotlib's default crowds 3×10², 4×10², ...)
        ax.xaxis.set_major_formatter(plt.FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(plt.FuncFormatter(
            lambda v, _: f"{v:g}" if v > 0 and round(v / 10 ** np.floor(np.log10(v))) in (2, 5) else ""))
        ax.set_xlabel("ms per image (median)")
        ax.set_ylabel("mean ΔE against the float64 reference")
        ax.set_title(f"{key[0]}, {key[1]}", fontsize=10)
        ax.grid(alpha=0.3, which="both")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def gallery(rows_by_volume: dict[str, list[dict]], path: Path) -> Path:
    """A row per volume: its images on black, each captioned with quality, mean ΔE and ms."""
    plt = _plt()
    n = max(len(v) for v in rows_by_volume.values())
    fig, axes = plt.subplots(len(rows_by_volume), n, figsize=(3.0 * n, 3.3 * len(rows_by_volume)), dpi=110,
                             squeeze=False)
    for row_axes, (name, rows) in zip(axes, rows_by_volume.items()):
        for ax in row_axes:
            ax.axis("off")
        for ax, r in zip(row_axes, rows):
            img = r["image"]
            rgb = np.clip(img[..., :3], 0, 1)  # premultiplied: over black this is the picture
            ax.imshow(rgb)
            q = "full resolution" if r["quality"] == "full" else r["quality"]
            ax.set_title(f"{name}: {q}", fontsize=8)
            ax.text(0.5, -0.04, f"ΔE {r['delta_e']:.2f} · {r['ms']:,.0f} ms", transform=ax.transAxes,
                    ha="center", va="top", fontsize=8)
    fig.tight_layout(h_pad=2.5)
    fig.savefig(path, facecolor="white")
    plt.close(fig)
    return path


def demo_row(eng, size: int, camera: dict, out: Path, log) -> list[dict] | None:
    """The demo MR head (`lodcast demo`'s volume) with the demo's translucent TF at full resolution (step ½),
    lossless, 30:1 and 100:1, against the float64 reference, rendered on `eng` (run.py's Renderer); None (and a
    line saying why) where it cannot be fetched."""
    from reference64 import reference_image

    import lodcast
    from lodcast.errors import LodcastError
    from lodcast.renderer.image.delta_e import delta_e_stats
    from lodcast.renderer.tools.demo import demo_tfs
    from lodcast.service.demo import fetch_demo_volume

    try:
        demo = fetch_demo_volume()
    except (LodcastError, OSError) as e:
        log(f"gallery: the demo volume could not be fetched ({e}); its row is left out")
        return None
    dest = out / "stores" / "demo.zarr"
    store = lodcast.open_store(dest) if dest.exists() else lodcast.ingest(demo.path, dest)
    scene = {"camera": camera, "width": size, "height": size, "tf": demo_tfs(store)["soft"]}
    level0 = np.asarray(store.read_level(0))
    log(f"gallery: float64 reference of {demo.name}")
    ref = reference_image(level0, scene, store.spacing, store.origin, volume_id=f"demo:{store.generation}",
                          cache=out / "reference", log=log)
    rows = []
    for quality, extra in (("full", {"sampling": {"step": 0.5}}), ("lossless", {"quality": "lossless"}),
                           ("30:1", {"quality": {"reduction": 30}}), ("100:1", {"quality": {"reduction": 100}})):
        eng.render(store, {**scene, **extra})
        ms = []
        for _ in range(3):
            t = time.perf_counter()
            r = eng.render(store, {**scene, **extra})
            ms.append(1e3 * (time.perf_counter() - t))
        rows.append({"quality": quality, "image": r.rgba, "ms": statistics.median(ms),
                     "delta_e": delta_e_stats(r.rgba, ref)["mean"]})
    return rows


def report_plot(eng: Any, store: Any, size: int, camera: dict, out: Path) -> Path:
    """`lodcast report`'s sweep and plot for the chest CT with the bone preset (its own step-¼ reference)."""
    from lodcast.renderer.tools.quality_report import run_report, write_report

    scene = {"camera": camera, "width": min(size, 256), "height": min(size, 256), "tf": "ct-bone"}
    result = run_report(store, scene, repeat=1, log=lambda msg: None, renderer=eng)
    return write_report(result, out / "report")["plot"]


def publish(paths: list[Path], docs: Path) -> list[Path]:
    docs.mkdir(parents=True, exist_ok=True)
    done = []
    for p in paths:
        dest = docs / PUBLISHED[p.name]
        shutil.copyfile(p, dest)
        done.append(dest)
    return done
