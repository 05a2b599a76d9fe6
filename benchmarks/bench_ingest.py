"""Ingest throughput (MB/s of raw input) and peak RSS, for the largest real volume in ../shared/data and a
generated 1 GiB uint16 volume. Each ingest runs in a fresh subprocess so its peak RSS is its own.

    .venv/bin/python benchmarks/bench_ingest.py [--quick] [--json benchmarks/results/ingest.json]

Targets (2-core machine): >= 40 MB/s, and peak RSS < 400 MB for the 1 GiB volume.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
DATA = Path(os.environ.get("LODCAST_SHARED_DATA", HERE.parents[1] / "shared" / "data"))
RESULTS = HERE / "results"

CHILD = r"""
import json, resource, sys, time
import lodcast
t = time.perf_counter()
st = lodcast.ingest(sys.argv[1], sys.argv[2], progress=False)
dt = time.perf_counter() - t
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print(json.dumps({"seconds": dt, "peak_rss": rss, "voxels": int(st.layout.n_voxels), "itemsize": st.dtype.itemsize,
                  "bytes_on_disk": st.bytes_on_disk(), "blocks": st.layout.n_blocks}))
"""


def synthetic(path: Path, shape: tuple[int, int, int]) -> Path:
    """A CT-like uint16 volume: nested ellipsoidal shells, a few dense inclusions and noise; written slab by slab."""
    if path.exists():
        return path
    rng = np.random.default_rng(0)
    out = np.lib.format.open_memmap(path.with_suffix(".tmp.npy"), mode="w+", dtype=np.uint16, shape=shape)
    z, y, x = shape
    yy, xx = np.mgrid[:y, :x].astype(np.float32)
    yy, xx = (yy - y / 2) / (y / 2), (xx - x / 2) / (x / 2)
    spheres = rng.uniform(0.2, 0.8, (12, 3)), rng.uniform(0.02, 0.08, 12)
    for z0 in range(0, z, 32):
        zz = (np.arange(z0, min(z, z0 + 32), dtype=np.float32)[:, None, None] - z / 2) / (z / 2)
        r = np.sqrt(xx**2 + yy**2 + (0.8 * zz) ** 2)
        v = np.where(r < 0.9, 1000.0, 0.0) + np.where((r > 0.8) & (r < 0.86), 800.0, 0.0)
        v = v + 200.0 * np.sin(6 * xx) * np.cos(5 * yy)
        for (cz, cy, cx), rad in zip(spheres[0], spheres[1]):
            d = (zz - (2 * cz - 1)) ** 2 + (yy - (2 * cy - 1)) ** 2 + (xx - (2 * cx - 1)) ** 2
            v = v + np.where(d < rad**2, 1500.0, 0.0)
        v += rng.normal(0, 20, v.shape).astype(np.float32)
        out[z0 : z0 + v.shape[0]] = np.clip(v, 0, 4095).astype(np.uint16)
    out.flush()
    del out
    os.replace(path.with_suffix(".tmp.npy"), path)
    return path


def measure(name: str, src: Path, raw_bytes_hint: int | None, work: Path) -> dict:
    dest = work / f"{name}.zarr"
    shutil.rmtree(dest, ignore_errors=True)
    p = subprocess.run([sys.executable, "-c", CHILD, str(src), str(dest)], capture_output=True, text=True)
    if p.returncode:
        raise SystemExit(f"ingest of {src} failed:\n{p.stderr}")
    r = json.loads(p.stdout.strip().splitlines()[-1])
    raw = r["voxels"] * r["itemsize"]
    shutil.rmtree(dest, ignore_errors=True)
    return {
        "volume": name,
        "raw_mb": raw / 1e6,
        "seconds": r["seconds"],
        "mb_per_s": raw / 1e6 / r["seconds"],
        "peak_rss_mb": r["peak_rss"] / 1e6,
        "store_mb": r["bytes_on_disk"] / 1e6,
        "blocks": r["blocks"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a 256 MiB synthetic volume instead of 1 GiB")
    ap.add_argument("--json", type=Path, default=RESULTS / "ingest.json")
    args = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory(dir=RESULTS) as tmp:
        work = Path(tmp)
        largest = DATA / "ct_chest_dicom"
        if largest.is_dir():
            rows.append(measure("ct_chest_dicom (275x512x512 int16)", largest, None, work))
        else:
            print(f"note: {DATA} not found; only the generated volume is measured", file=sys.stderr)
        shape = (256, 512, 1024) if args.quick else (512, 1024, 1024)
        src = synthetic(RESULTS / f"synthetic_{'x'.join(map(str, shape))}_u16.npy", shape)
        rows.append(measure(f"generated {'x'.join(map(str, shape))} uint16", src, None, work))
    print(f"{'volume':<40} {'raw MB':>8} {'s':>7} {'MB/s':>7} {'peak RSS MB':>12} {'store MB':>9}")
    for r in rows:
        print(f"{r['volume']:<40} {r['raw_mb']:8.0f} {r['seconds']:7.2f} {r['mb_per_s']:7.1f} {r['peak_rss_mb']:12.0f} {r['store_mb']:9.1f}")
    result = {"rows": rows, "targets": {"mb_per_s": 40, "peak_rss_mb_1gib": 400}, "cpu_count": os.cpu_count(),
              "max_rss_self_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3, "time": time.time()}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
