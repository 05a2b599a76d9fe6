"""A volume of 8 GiB (issue 14 item 2): made, ingested and rendered with bounded memory.

    .venv/bin/python benchmarks/bench_large_volume.py [--shape 1024,2048,2048] [--json benchmarks/results/large_volume.json]

The volume: the chest CT (../shared/data/ct_chest_dicom, via its 16³ store) tiled 4x4 across and ~3.7x in depth,
every tile mirrored and shifted in intensity by its own amount, with a little noise, as uint16 (HU + 1024):
1024 x 2048 x 2048 voxels, 2^32 of them (past 32-bit addressing), 8 GiB raw. It is generated slab by slab straight
into ingest (`Body`, a store source: no raw copy on disk); the store goes to benchmarks/results/large/ (never
committed; delete it afterwards).

Measured, each step in its own process (peak RSS: that process's VmHWM, /proc/self/status):
- ingest: MB/s and peak RSS;
- the renderer (one process): the first image at 30:1 (cold: the page cache dropped first if this user may, else
  said so; under cProfile, whose table is written beside the store: where a cold image's time goes), a
  36-frame turntable at 30:1 (per-frame ms, bricks read per frame, brick-cache hit rate, MB read by
  the process; then every sixth frame with the selection weighed by the view, lod_visibility on), one frame at "lossless" and one at "full" under a device budget of 512 MB (a Renderer of their
  own, device_budget_mb=512) with the brick cache capped (LODCAST_BRICK_CACHE_MB=512), and the process's peak RSS against a quarter of the volume's size.
Prints a table and writes JSON. Takes tens of minutes on two cores, most of it ingest.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from lodcast.store.source import SourceInfo, VolumeSource

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
LARGE = RESULTS / "large"
TF = "ct-bone"
SPACING = (1.0, 0.78125, 0.78125)  # z, y, x: the chest CT's own


class Body(VolumeSource):
    """The volume as a store source, generated slice by slice as ingest asks for slabs: no raw copy on disk,
    whatever its size. A slice depends on its index alone (its noise is seeded by it), so a slab read twice is the
    same."""

    def __init__(self, shape: tuple[int, int, int]) -> None:
        sys.path.insert(0, str(HERE))
        from bench_consistent_lod import DATA, store_of

        self.chest = store_of("ct_chest", DATA / "ct_chest_dicom").read_level(0).astype(np.int32) + 1024  # z, y, x
        cz, cy, cx = self.chest.shape
        self.tiles = (-(-shape[1] // cy), -(-shape[2] // cx))
        self.shift = np.random.default_rng(7).integers(-40, 40, size=(-(-shape[0] // cz), *self.tiles))
        self.info = SourceInfo(shape=shape, dtype=np.dtype(np.uint16), spacing=SPACING, format="generated",
                               provenance={"generator": "benchmarks/bench_large_volume.py: Body"})

    def read(self, z0: int, z1: int) -> np.ndarray:
        (_, Y, X), (cz, cy, cx), (ty, tx) = self.info.shape, self.chest.shape, self.tiles
        out = np.empty((z1 - z0, Y, X), np.uint16)
        row = np.empty((ty * cy, tx * cx), np.int32)
        for z in range(z0, z1):
            tz, zz = divmod(z, cz)
            src = self.chest[zz if tz % 2 == 0 else cz - 1 - zz]
            for j in range(ty):
                for i in range(tx):
                    t = src[:, ::-1] if (i + j) % 2 else src
                    row[j * cy:(j + 1) * cy, i * cx:(i + 1) * cx] = t + self.shift[tz, j, i]
            noise = np.random.default_rng((7, z)).integers(-8, 9, size=(Y, X), dtype=np.int32)
            out[z - z0] = np.clip(row[:Y, :X] + noise, 0, 65535)
        return out


def peak_rss() -> int:
    """This process's peak resident set (VmHWM: per address space, so not inherited from a forking parent as
    getrusage's maximum is)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def child(args: list[str], env: dict | None = None) -> tuple[float, dict]:
    """(seconds, the JSON its last line of stdout holds) of a child process."""
    t = time.perf_counter()
    p = subprocess.run(args, env={**os.environ, **(env or {})}, capture_output=True, text=True)
    dt = time.perf_counter() - t
    if p.returncode:
        raise SystemExit(f"{' '.join(args)} failed:\n{p.stderr[-3000:]}")
    return dt, json.loads(p.stdout.strip().splitlines()[-1])


def ingest_step(shape: str, store: str) -> None:
    """Runs in the child: the volume of `shape` ("z,y,x") generated straight into ingest (Body), then its peak RSS."""
    import lodcast

    with Body(tuple(int(v) for v in shape.split(","))) as src:
        lodcast.ingest(src, store, progress=False)
    print(json.dumps({"peak_rss": peak_rss()}))


def drop_caches() -> bool:
    try:
        os.sync()
        Path("/proc/sys/vm/drop_caches").write_text("3\n")
        return True
    except OSError:
        return False


def _io() -> int:
    for line in Path("/proc/self/io").read_text().splitlines():
        if line.startswith("rchar:"):
            return int(line.split()[1])
    return 0


def render_step(store_path: str, frames: int, size: int) -> None:
    """Runs in the child: every render of the measurement, one JSON line."""
    import lodcast

    out: dict = {}
    eng = lodcast.Renderer()  # LODCAST_BRICK_CACHE_MB from main's env, read here
    st = lodcast.open_store(store_path)
    cam = lambda i: {"azimuth": 360.0 * i / frames, "elevation": 15}  # noqa: E731
    base = {"tf": TF, "width": size, "height": size, "format": "npy"}
    import cProfile
    import io
    import pstats

    prof = cProfile.Profile()
    t, io0 = time.perf_counter(), _io()
    prof.enable()
    r = eng.render(st, {**base, "quality": {"reduction": 30}, "camera": cam(0)})
    prof.disable()
    text = io.StringIO()
    pstats.Stats(prof, stream=text).sort_stats("cumulative").print_stats(30)
    (LARGE / "first_image_profile.txt").write_text(text.getvalue())  # where the cold image's time goes
    out["first_image"] = {"ms": (time.perf_counter() - t) * 1e3, "bricks_read": r.report["bricks_read"],
                          "mb_read": (_io() - io0) / 1e6, "reduction": r.report["reduction"],
                          "peak_rss_mb": peak_rss() / 1e6}
    per = []
    for i in range(1, frames):
        io0, t = _io(), time.perf_counter()
        if i == frames - 1:  # the last warm frame, profiled: where a warm frame's host time goes
            prof = cProfile.Profile()
            prof.enable()
        r = eng.render(st, {**base, "quality": {"reduction": 30}, "camera": cam(i)})
        if i == frames - 1:
            prof.disable()
            text = io.StringIO()
            pstats.Stats(prof, stream=text).sort_stats("cumulative").print_stats(30)
            (LARGE / "warm_frame_profile.txt").write_text(text.getvalue())
        read = r.report["bricks_read"]
        per.append({"ms": (time.perf_counter() - t) * 1e3, "bricks_read": read,
                    "bricks_cached": r.report["bricks_cached"], "mb_read": (_io() - io0) / 1e6})
    out["turntable"] = per
    out["turntable_peak_rss_mb"] = peak_rss() / 1e6
    # the budget for these two: their data is larger. An engine of their own; the turntable's gives up its bricks
    # and device buffers first, so that the process holds one brick cache's worth, as with one engine
    eng.bricks.clear()
    eng.device_cache.clear()
    budget = lodcast.Renderer(device_budget_mb=512)
    _ = budget.device.context  # opened outside the timing, as the turntable's engine had it open
    for q in ("lossless", "full"):
        t, io0 = time.perf_counter(), _io()
        r = budget.render(st, {**base, "quality": q, "camera": cam(0)})
        out[q] = {"ms": (time.perf_counter() - t) * 1e3, "passes": r.report["passes"],
                  "device_mb": r.report["device_bytes"] / 1e6, "kernel_ms": r.report["kernel_ms"],
                  "upload_ms": r.report["upload_ms"], "mb_read": (_io() - io0) / 1e6,
                  "reduction": r.report["reduction"], "peak_rss_mb": peak_rss() / 1e6}
    out["peak_rss"] = peak_rss()
    # last, apart from the figures above: a few of the turntable's frames with the selection weighed by the view
    # (lod_visibility on; the default leaves it off on a volume this large): each view selects, reads and packs
    # its atlas again, and the device cache fills with atlases
    del budget  # back to the turntable's engine, as the turntable ran
    seen = []
    for i in range(0, frames, max(1, frames // 6)):
        io0, t = _io(), time.perf_counter()
        r = eng.render(st, {**base, "quality": {"reduction": 30}, "camera": cam(i),
                            "sampling": {"lod_visibility": True}})
        seen.append({"ms": (time.perf_counter() - t) * 1e3, "bricks_read": r.report["bricks_read"],
                     "bricks_cached": r.report["bricks_cached"], "mb_read": (_io() - io0) / 1e6})
    out["turntable_view_weighted"] = seen
    out["view_weighted_peak_rss_mb"] = peak_rss() / 1e6
    print(json.dumps(out))


def report_table(res: dict, px: int) -> str:
    """The markdown table of a run's JSON (`res`), images of px² pixels."""
    shape, size = res["shape"], res["raw_bytes"]
    r = res["render"]
    tt = r["turntable"]
    hit = sum(f["bricks_cached"] for f in tt) / max(1, sum(f["bricks_cached"] + f["bricks_read"] for f in tt))
    lines = [f"{shape[0]}x{shape[1]}x{shape[2]} uint16 ({size / 2**30:.1f} GiB), ct-bone, {px}²", "",
             "| step | figure |", "|---|---|"]
    if "ingest" in res:
        lines.append(f"| ingest | {res['ingest']['mb_per_s']:.1f} MB/s, peak RSS {res['ingest']['peak_rss_mb']:.0f} MB |")
    lines += [
        f"| first image 30:1 ({'page cache dropped' if res['page_cache_dropped'] else 'page cache NOT dropped'}; "
        f"under cProfile: {LARGE.name}/first_image_profile.txt) | "
        f"{r['first_image']['ms']:.0f} ms, {r['first_image']['bricks_read']} bricks, {r['first_image']['mb_read']:.0f} MB read |",
        f"| turntable 30:1, {len(tt)} frames | {np.median([f['ms'] for f in tt]):.0f} ms/frame (median), "
        f"{np.mean([f['bricks_read'] for f in tt]):.0f} bricks read/frame, hit rate {hit:.3f}, "
        f"{np.mean([f['mb_read'] for f in tt]):.1f} MB read/frame |",
        *([f"| the same with the selection weighed by the view (lod_visibility on), {len(tv)} frames | "
           f"{np.median([f['ms'] for f in tv]):.0f} ms/frame (median), "
           f"{np.mean([f['bricks_read'] for f in tv]):.0f} bricks read/frame, peak RSS after them "
           f"{r['view_weighted_peak_rss_mb']:.0f} MB (measured last) |"]
          if (tv := r.get("turntable_view_weighted")) else []),
        f"| lossless, budget 512 MB | {r['lossless']['ms']:.0f} ms, {r['lossless']['passes']} passes, "
        f"{r['lossless']['device_mb']:.0f} MB on the device, {r['lossless']['mb_read']:.0f} MB read |",
        f"| full, budget 512 MB | {r['full']['ms']:.0f} ms, {r['full']['passes']} passes, "
        f"{r['full']['device_mb']:.0f} MB on the device, {r['full']['mb_read']:.0f} MB read |",
        f"| renderer peak RSS | {r['peak_rss'] / 1e6:.0f} MB (a quarter of the volume: {size / 4e6:.0f} MB); after "
        f"the first image {r['first_image']['peak_rss_mb']:.0f}, the turntable {r['turntable_peak_rss_mb']:.0f}, "
        f"lossless {r['lossless']['peak_rss_mb']:.0f}, full {r['full']['peak_rss_mb']:.0f} MB |",
    ]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shape", default="1024,2048,2048")
    ap.add_argument("--frames", type=int, default=36)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--json", type=Path, default=RESULTS / "large_volume.json")
    ap.add_argument("--render-step", help=argparse.SUPPRESS)
    ap.add_argument("--ingest-step", nargs=2, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.render_step:
        return render_step(a.render_step, a.frames, a.size)
    if a.ingest_step:
        return ingest_step(*a.ingest_step)
    shape = tuple(int(s) for s in a.shape.split(","))
    LARGE.mkdir(parents=True, exist_ok=True)
    size = int(np.prod(shape)) * 2  # uint16 voxels
    store = LARGE / f"body_{'x'.join(map(str, shape))}.zarr"
    res: dict = {"shape": shape, "voxels": int(np.prod(shape)), "raw_bytes": size}
    ingest_json = store.with_suffix(".ingest.json")  # kept beside the store: a rerun measures the renders only
    if not store.exists():
        dt, got = child([sys.executable, __file__, "--ingest-step", a.shape, str(store)])
        ingest_json.write_text(json.dumps({"s": dt, "mb_per_s": size / 1e6 / dt, "peak_rss_mb": got["peak_rss"] / 1e6}))
    if ingest_json.exists():
        res["ingest"] = json.loads(ingest_json.read_text())
        print(res["ingest"], flush=True)
    res["page_cache_dropped"] = drop_caches()
    dt, res["render"] = child([sys.executable, __file__, "--render-step", str(store), "--frames", str(a.frames),
                               "--size", str(a.size)],
                              env={"LODCAST_BRICK_CACHE_MB": "512"})
    table = report_table(res, a.size)
    res["table"] = table
    print("\n" + table)
    a.json.write_text(json.dumps(res, indent=2))
    print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
