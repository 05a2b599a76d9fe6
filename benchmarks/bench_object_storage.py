"""Requests and bytes per frame from object storage (issue 14 item 3): the chest CT's store on moto's S3 server on
loopback (behind a counting proxy), a turntable at 30:1, lossless and full resolution, with lodcast's shard-level
reader and with zarr-python's per-chunk reads for comparison.

    .venv/bin/python benchmarks/bench_object_storage.py [--frames 6] [--size 256] [--json benchmarks/results/object_storage.json]
        [--store PATH] [--readers lodcast zarr-python] [--qualities 30 lossless full]

`--store` puts another local store on the server instead (e.g. the 8 GiB volume of bench_large_volume.py:
`--store benchmarks/results/large/body_1024x2048x2048.zarr --readers lodcast --qualities 30`).

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
from bench_consistent_lod import DATA, RESULTS, store_of

import lodcast
from lodcast.renderer.frame.render import Renderer
from lodcast.service.testing import s3_server


def _fresh(eng: Renderer) -> None:
    eng.bricks.clear()
    eng.device_cache.clear()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--json", type=Path, default=RESULTS / "object_storage.json")
    ap.add_argument("--store", type=Path, help="a local store to put on the server (default: the chest CT's)")
    ap.add_argument("--readers", nargs="+", default=["lodcast", "zarr-python"], choices=["lodcast", "zarr-python"])
    ap.add_argument("--qualities", nargs="+", default=["30", "lossless", "full"],
                    help="reductions (numbers), lossless, full")
    a = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    local = lodcast.open_store(a.store) if a.store else store_of("ct_chest", DATA / "ct_chest_dicom")
    qualities = [q if q in ("lossless", "full") else {"reduction": float(q)} for q in a.qualities]
    name = Path(local.location).name
    eng = Renderer()
    rows = []
    with s3_server() as srv:
        fs = fsspec.filesystem("s3", skip_instance_cache=True)
        fs.mkdir("bench")
        t = time.perf_counter()
        fs.put(str(local.location), f"bench/{name}", recursive=True)
        upload_s = time.perf_counter() - t
        on_s3 = sum(f["size"] for f in fs.find(f"bench/{name}", detail=True).values())
        print(f"{on_s3 / 1e6:.0f} MB uploaded in {upload_s:.0f} s", flush=True)
        for reader in a.readers:
            for quality in qualities:
                _fresh(eng)
                st = lodcast.open_store(f"s3://bench/{name}")
                if reader == "zarr-python":
                    n = st.layout.n_levels
                    st._readers.update({k: False for k in [str(i) for i in range(n)] + [f"std/{i}" for i in range(1, n)]})
                # the store's per-block statistics and histograms, with a few bricks (cleared next)
                eng.render(st, {"tf": "ct-bone", "width": 8, "height": 8, "quality": {"reduction": 1000}})
                _fresh(eng)
                frames = []
                for i in range(a.frames):
                    srv.reset()
                    t = time.perf_counter()
                    r = eng.render(st, {"tf": "ct-bone", "width": a.size, "height": a.size, "quality": quality,
                                        "camera": {"azimuth": 360.0 * i / a.frames, "elevation": 15}})
                    n, nbytes = srv.counts()
                    frames.append({"ms": (time.perf_counter() - t) * 1e3, "requests": n, "bytes": nbytes,
                                   "bricks_read": r.report["bricks_read"]})
                warm = frames[1:]
                rows.append({"reader": reader, "quality": quality if isinstance(quality, str) else f"{quality['reduction']:g}:1",
                             "cold": frames[0],
                             "warm_ms": float(np.mean([f["ms"] for f in warm])) if warm else None,
                             "warm_requests": float(np.mean([f["requests"] for f in warm])) if warm else None,
                             "warm_bytes": float(np.mean([f["bytes"] for f in warm])) if warm else None})
                print(rows[-1], flush=True)
    lines = [f"{name} on loopback S3 ({on_s3 / 1e6:.0f} MB, uploaded in {upload_s:.1f} s), ct-bone, "
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
