"""Requests and bytes per frame from object storage (issue 14 item 3): the chest CT's store on moto's S3 server on
loopback (behind a counting proxy), a turntable at 30:1, lossless and full resolution, with lodcast's shard-level
reader and with zarr-python's per-chunk reads for comparison.

    .venv/bin/python benchmarks/bench_object_storage.py [--frames 6] [--size 256] [--json benchmarks/results/object_storage.json]

Per quality: the first frame after opening (cold: no brick cached; the store's per-block statistics were read by
a warm-up render at another quality) and the mean of the following frames (each a new azimuth: bricks come from
the brick cache). Loopback has no network latency: on real S3 every request costs tens of milliseconds, so the
request count is the figure to read. The machine is shared: compare ratios within one run.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import fsspec
import numpy as np

import lodcast
from bench_consistent_lod import DATA, RESULTS, store_of
from lodcast.renderer.atlas import brick_cache
from lodcast.renderer.sampler import device_cache
from lodcast.service.testing import s3_server


def _fresh() -> None:
    brick_cache().clear()
    device_cache().clear()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--json", type=Path, default=RESULTS / "object_storage.json")
    a = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    local = store_of("ct_chest", DATA / "ct_chest_dicom")
    rows = []
    with s3_server() as srv:
        fs = fsspec.filesystem("s3", skip_instance_cache=True)
        fs.mkdir("bench")
        t = time.perf_counter()
        fs.put(str(local.location), "bench/chest.zarr", recursive=True)
        upload_s = time.perf_counter() - t
        on_s3 = sum(f["size"] for f in fs.find("bench/chest.zarr", detail=True).values())
        for reader in ("lodcast", "zarr-python"):
            for quality in ({"reduction": 30}, "lossless", "full"):
                _fresh()
                st = lodcast.open_store("s3://bench/chest.zarr")
                if reader == "zarr-python":
                    st._readers.update({k: False for k in ["0", "1", "2", "3", "4", "std/1", "std/2", "std/3", "std/4"]})
                lodcast.render(st, {"tf": "ct-bone", "width": 8, "height": 8, "quality": "lossless"})  # statistics
                _fresh()
                frames = []
                for i in range(a.frames):
                    srv.reset()
                    t = time.perf_counter()
                    r = lodcast.render(st, {"tf": "ct-bone", "width": a.size, "height": a.size, "quality": quality,
                                            "camera": {"azimuth": 360.0 * i / a.frames, "elevation": 15}})
                    n, nbytes = srv.counts()
                    frames.append({"ms": (time.perf_counter() - t) * 1e3, "requests": n, "bytes": nbytes,
                                   "bricks_read": r.report["bricks_read"]})
                warm = frames[1:]
                rows.append({"reader": reader, "quality": quality if isinstance(quality, str) else "30:1",
                             "cold": frames[0],
                             "warm_ms": float(np.mean([f["ms"] for f in warm])) if warm else None,
                             "warm_requests": float(np.mean([f["requests"] for f in warm])) if warm else None,
                             "warm_bytes": float(np.mean([f["bytes"] for f in warm])) if warm else None})
                print(rows[-1], flush=True)
    lines = [f"chest CT store on loopback S3 ({on_s3 / 1e6:.0f} MB, uploaded in {upload_s:.1f} s), ct-bone, "
             f"{a.size}², {a.frames} frames", "",
             "| reader | quality | cold: requests | cold: MB | cold: bricks | cold ms | warm: requests/frame | "
             "warm ms/frame |", "|" + "---|" * 8]
    for r in rows:
        c = r["cold"]
        lines.append(f"| {r['reader']} | {r['quality']} | {c['requests']} | {c['bytes'] / 1e6:.1f} | "
                     f"{c['bricks_read']} | {c['ms']:.0f} | {r['warm_requests']:.0f} | {r['warm_ms']:.0f} |")
    table = "\n".join(lines)
    print("\n" + table)
    a.json.write_text(json.dumps({"rows": rows, "store_bytes": on_s3, "table": table}, indent=2))
    print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
