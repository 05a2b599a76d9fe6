"""The brick reads of a new view, alone (issue 44): what the reader threads spend per shard, without the rest of
the render and without the other threads beside them.

    .venv/bin/python benchmarks/bench_brick_reads.py [--store benchmarks/results/large/lz4_body_1024x2048x2048.zarr]
        [--size 512] [--reduction 30] [--repeat 5] [--against ../base-worktree --pairs 20] [--json FILE]

One renderer renders the view at azimuth 30° and then the one 2° further (elevation 20°, ct-bone, `{"reduction":
R}`, `size`², `"sampling": {"lod_visibility": true}`, as benchmarks/bench_new_view.py does); the shard reads of
the second view (each reader task's level, blocks and kind: values or deviations) are recorded. Then the reads
alone: every recorded shard read again with `bricks._read_group`, in order, on one thread, `repeat` times; the
figure is the least thread CPU time of a round (the store's files are in the page cache after the first).

`--against DIR` (a worktree of another commit, with its own .venv): `pairs` interleaved pairs of processes, this
checkout's and DIR's (the order alternating), each timing the same recorded reads with its own lodcast; the ratio
this / other: its median and a bootstrap 95 % interval, and whether both read the same bricks, bit for bit.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import pickle
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_new_view import scene  # noqa: E402
from record import bootstrap, provenance, write_result  # noqa: E402

import lodcast  # noqa: E402
from lodcast.renderer.data import bricks  # noqa: E402


def record(store: Path, size: int, reduction: float) -> list[tuple[int, np.ndarray, str]]:
    """The shard reads (level, blocks (n, 3), "mean" or "std") of the view 2° after the first."""
    reads: list[tuple[int, np.ndarray, str]] = []
    real = bricks._read_into

    def spy(vol, lay, k, blocks, zyx, what, *rest):
        reads.append((k, np.array(zyx), what))
        return real(vol, lay, k, blocks, zyx, what, *rest)

    eng = lodcast.Renderer()
    eng.render(str(store), scene(30.0, size, reduction))
    bricks._read_into = spy
    try:
        eng.render(str(store), scene(32.0, size, reduction))
    finally:
        bricks._read_into = real
        eng.close()
    return reads


def time_reads(store: Path, reads: list, repeat: int) -> dict:
    """The least thread CPU of `repeat` rounds over `reads`, and a digest of the bricks read."""
    from lodcast.renderer.data.volume import as_volume
    from lodcast.store.layout import Layout

    vol = as_volume(str(store))
    lay = Layout(tuple(vol.shape), int(vol.block_size))
    table = bricks.std_table(vol)
    digest = hashlib.sha1()
    for k, zyx, what in reads:  # (the first round, which also brings the files into the page cache)
        digest.update(bricks._read_group(vol, lay, k, zyx, what, table).tobytes())
    best = float("inf")
    for _ in range(repeat):
        t = time.thread_time()
        for k, zyx, what in reads:
            bricks._read_group(vol, lay, k, zyx, what, table)
        best = min(best, time.thread_time() - t)
    return {"cpu_ms": best * 1e3, "reads": len(reads), "bricks": int(sum(len(z) for _, z, _ in reads)),
            "sha1": digest.hexdigest()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--store", type=Path, default=HERE / "results" / "large" / "lz4_body_1024x2048x2048.zarr")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--reduction", type=float, default=30.0)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--against", type=Path, default=None)
    ap.add_argument("--pairs", type=int, default=20)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--reads", type=Path, default=None, help=argparse.SUPPRESS)  # (a recording: time it, print JSON)
    a = ap.parse_args(argv)
    if not a.store.is_dir():
        print(f"--store: {a.store} is not a store (make one with benchmarks/bench_large_volume.py)", file=sys.stderr)
        return 2
    if a.reads is not None:
        print(json.dumps(time_reads(a.store, pickle.loads(a.reads.read_bytes()), a.repeat)))
        return 0
    reads = record(a.store, a.size, a.reduction)
    res: dict = {**provenance("bench_brick_reads.py"), "load": os.getloadavg(), "store": a.store.name,
                 "size": a.size, "reduction": a.reduction, "repeat": a.repeat}
    if a.against is None:
        res.update(time_reads(a.store, reads, a.repeat))
        print(f"{res['reads']} shard reads, {res['bricks']} bricks: {res['cpu_ms']:.0f} ms of thread CPU "
              f"({res['cpu_ms'] * 1e3 / res['reads']:.0f} µs a read)")
    else:
        pythons = {"this": Path(sys.executable), "other": a.against / ".venv" / "bin" / "python"}
        runs: dict[str, list[dict]] = {"this": [], "other": []}
        with tempfile.TemporaryDirectory() as tmp:
            rec = Path(tmp) / "reads.pkl"
            rec.write_bytes(pickle.dumps(reads))
            for i in range(a.pairs):
                for who in (("other", "this") if i % 2 == 0 else ("this", "other")):
                    out = subprocess.run([str(pythons[who]), str(Path(__file__).resolve()), "--store",
                                          str(a.store.resolve()), "--repeat", str(a.repeat), "--reads", str(rec)],
                                         check=True, capture_output=True, text=True).stdout
                    runs[who].append({**json.loads(out.strip().splitlines()[-1]), "load": os.getloadavg()[0]})
                    print(f"pair {i + 1} {who}: {runs[who][-1]['cpu_ms']:.0f} ms", flush=True)
        ratio = np.array([t["cpu_ms"] / o["cpu_ms"] for t, o in zip(runs["this"], runs["other"])])
        res.update({"against": str(a.against), "runs": runs, "ratio_median": float(np.median(ratio)),
                    "ratio_ci95": bootstrap(ratio), "ratios": ratio.tolist(),
                    "same_bricks": len({r["sha1"] for w in runs.values() for r in w}) == 1})
        print(f"{len(reads)} shard reads: thread CPU this / other {res['ratio_median']:.3f} "
              f"[{res['ratio_ci95'][0]:.3f}, {res['ratio_ci95'][1]:.3f}]; the same bricks: {res['same_bricks']}")
    res["load_after"] = os.getloadavg()
    if a.json is not None:
        write_result(a.json, res, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
