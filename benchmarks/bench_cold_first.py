"""The cold 30:1 first image of a large volume against DESIGN.md's bound (issue 44 item 3), old and new alternating.

    .venv/bin/python benchmarks/bench_cold_first.py [--store benchmarks/results/large/body_1024x2048x2048.zarr]
        [--base OTHER/.venv/bin/python] [--base-store STORE] [--pairs 5] [--json docs/measurements/cold_first.json]

Per pair, each run in a fresh process with the page cache dropped just before it (the order alternates: the base
first in even pairs, this tree first in odd ones): the time from the process's start to the 30:1 image (ct-bone,
512², default brick pool and device), with its selection (prepare) and atlas (device_atlas) seconds, the process's
page faults and the load average. `--base` is a Python whose `lodcast` is the code to compare with (another
checkout's virtual environment); without it only this tree runs. `--base-store`: the base reads that store instead
(the same volume written by the base's ingest, where the change is in how a store is written); the bound is this
tree's store's.

In the same run, once: the read rate of the files the image reads (levels 1-4 of the values and of their
deviations, whole files: `cat` after a drop) and the decoding alone (the image's bricks, values and deviations,
read from the page cache and cut into bricks on one thread, as the readers do): DESIGN.md's bound is
max(2 x read time, decode time alone) + 2 s. Needs root to drop the page cache (else it says so). Prints a table and
writes JSON and the table beside it (.md).
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

from bench_large_volume import LARGE, drop_caches  # noqa: E402
from record import alternating, base_revision, write_result  # noqa: E402

SCENE = {"tf": "ct-bone", "width": 512, "height": 512, "format": "npy", "quality": {"reduction": 30},
         "camera": {"azimuth": 30, "elevation": 15}}


def _faults() -> tuple[int, int]:
    """(minor, major) page faults of this process so far (/proc/self/stat)."""
    f = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
    return int(f[7]), int(f[9])


def render_step(store: str, started: float) -> None:
    """Runs in the child: the cold image, its stages timed through the modules' own names; one JSON line."""
    import lodcast
    from lodcast.renderer.data import atlas
    from lodcast.renderer.frame import prepare

    spent = {"prepare_s": 0.0, "atlas_s": 0.0}

    def timed(name: str, f):  # noqa: ANN001, ANN202 (a wrapper of either tree's function)
        def g(*a, **k):  # noqa: ANN002, ANN003, ANN202
            t = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                spent[name] += time.perf_counter() - t
        return g

    prepare.prepare = timed("prepare_s", prepare.prepare)
    atlas.device_atlas = timed("atlas_s", atlas.device_atlas)
    eng = lodcast.Renderer()
    st = lodcast.open_store(store)
    f0 = _faults()
    r = eng.render(st, SCENE)
    s = time.time() - started
    f1 = _faults()
    print(json.dumps({"s": s, **spent, "kernel_ms": r.report["kernel_ms"], "bricks_read": r.report["bricks_read"],
                      "reduction": r.report["reduction"], "minflt": f1[0] - f0[0], "majflt": f1[1] - f0[1],
                      "image_sum": float(np.asarray(r.rgba, np.float64).sum())}))


def decode_step(store: str) -> None:
    """Runs in the child, the store's files in the page cache: the image's chunks (values, then deviations)
    decompressed on one thread, their bytes read beforehand (`decode_s`: blosc alone), and the bricks read,
    decoded and cut on one thread as a reader does it (`path_s`); one JSON line."""
    from numcodecs import blosc

    import lodcast
    from lodcast.renderer.data import bricks
    from lodcast.renderer.frame.prepare import prepare
    from lodcast.store.layout import Layout

    eng = lodcast.Renderer()
    st = lodcast.open_store(store)
    pr = prepare(eng, st, SCENE)
    assert pr.lod is not None
    vol = pr.volume
    lay = Layout(tuple(vol.shape), int(vol.block_size))
    flat = np.asarray(pr.lod.levels).ravel()
    out = {}
    for what in ("mean", "std"):
        lo = 0 if what == "mean" else 1
        missing = [(k, np.flatnonzero(flat == k)) for k in np.unique(flat[flat >= lo]).tolist()]
        groups = bricks._by_shard(lay, missing)
        decode, chunks, nbytes = 0.0, 0, 0
        for k, _, zyx in groups:  # the chunks that hold the group's bricks, as bricks._read_group finds them
            reader = st._reader(f"std/{k}" if what == "std" else str(k))
            c = np.array(lay.chunk_shape(k))
            coords = np.unique(zyx * lay.block_edge(k) // c, axis=0)
            key = reader._key(tuple(int(v) for v in coords[0] // np.array(reader._per_shard)))
            fd = reader._files.open(key)
            entries = reader._entries(fd, reader._files.name(key), key, coords)
            raws = [reader._files.pread(fd, int(n), int(o)) for o, n in entries.tolist()]
            reader._files.close(fd)
            raws = [r[:-4] for r in raws] if reader._chunk_crc else raws
            box = np.empty((len(raws), *reader.chunk), reader._chunk_dtype)
            t = time.perf_counter()
            for i, r in enumerate(raws):
                blosc.decompress(r, box[i])
            decode += time.perf_counter() - t
            chunks += len(raws)
            nbytes += box.nbytes
        table = bricks.std_table(vol) if what == "std" else None
        t = time.perf_counter()
        n = sum(len(bricks._read_group(vol, lay, k, zyx, what, table)) for k, _, zyx in groups)
        out[what] = {"decode_s": decode, "path_s": time.perf_counter() - t, "chunks": chunks,
                     "decoded_mb": nbytes / 1e6, "bricks": n, "shards": len(groups)}
    print(json.dumps(out))


def read_files(store: Path) -> list[Path]:
    """The files a 30:1 image reads: levels 1-4 of the values and of the deviations."""
    return sorted(p for d in [*(store / str(k) for k in range(1, 5)), *(store / "std" / str(k) for k in range(1, 5))]
                  for p in d.rglob("*") if p.is_file())


def child(python: str, args: list[str]) -> dict:
    p = subprocess.run([python, __file__, *args], capture_output=True, text=True)
    if p.returncode:
        raise SystemExit(f"{python} {' '.join(args)} failed:\n{p.stderr[-3000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def table(res: dict) -> str:
    pairs = res["pairs"]
    b = res["bound"]
    lines = [f"Cold 30:1 first image, 512², ct-bone, {res['store']}, "
             f"{'page cache dropped before each process' if res['page_cache_dropped'] else 'page cache NOT dropped'}; "
             f"seconds from the process's start. {res['date']}, {res['nproc']} x {res['cpu']} (kernel "
             f"{res['kernel']}), base {res['base']}"
             f"{' reading ' + res['base_store'] if res.get('base_store') else ''} against this tree {res['tree']}; "
             f"`{res['command']}`", "",
             "| pair | order | base s | this tree s | ratio | base prepare / atlas s | this prepare / atlas s | "
             "base / this minor faults | load avg (1 min) |", "|---|---|---|---|---|---|---|---|---|"]
    for i, p in enumerate(pairs):
        o, n = p.get("base"), p["new"]
        lines.append(
            f"| {i} | {p['order']} | {o['s']:.1f} | {n['s']:.1f} | {n['s'] / o['s']:.2f} | "
            f"{o['prepare_s']:.1f} / {o['atlas_s']:.1f} | {n['prepare_s']:.1f} / {n['atlas_s']:.1f} | "
            f"{o['minflt']} / {n['minflt']} | {p['load']:.1f} |" if o else
            f"| {i} | new | - | {n['s']:.1f} | - | - | {n['prepare_s']:.1f} / {n['atlas_s']:.1f} | {n['minflt']} | "
            f"{p['load']:.1f} |")
    med_new = float(np.median([p["new"]["s"] for p in pairs]))
    lines += ["", f"Median: this tree {med_new:.1f} s"
              + (f", base {np.median([p['base']['s'] for p in pairs]):.1f} s, median ratio "
                 f"{np.median([p['new']['s'] / p['base']['s'] for p in pairs]):.2f}" if pairs[0].get("base") else ""),
              f"Bound: read {b['read_mb']:.0f} MB in {b['read_s']:.2f} s ({b['read_mb'] / b['read_s']:.0f} MB/s, "
              f"`cat` after a drop); decoding alone {b['decode_s']:.2f} s on one thread (blosc: values "
              f"{b['decode']['mean']['decode_s']:.2f} s, deviations {b['decode']['std']['decode_s']:.2f} s; "
              f"read from the page cache, decoded and cut as a reader does, one thread: "
              f"{b['decode']['mean']['path_s'] + b['decode']['std']['path_s']:.2f} s); "
              f"max(2 x {b['read_s']:.2f}, {b['decode_s']:.2f}) + 2 = **{b['bound_s']:.1f} s**"]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", type=Path, default=LARGE / "body_1024x2048x2048.zarr")
    ap.add_argument("--base", help="a Python whose lodcast is the code to compare with")
    ap.add_argument("--base-store", type=Path, help="the store the base reads (default: --store)")
    ap.add_argument("--pairs", type=int, default=5)
    ap.add_argument("--json", type=Path, default=ROOT / "docs" / "measurements" / "cold_first.json")
    ap.add_argument("--render-step", help=argparse.SUPPRESS)
    ap.add_argument("--decode-step", help=argparse.SUPPRESS)
    ap.add_argument("--started", type=float, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.render_step:
        return render_step(a.render_step, a.started)
    if a.decode_step:
        return decode_step(a.decode_step)
    store = a.store.resolve()
    files = read_files(store)
    if not files:
        raise SystemExit(f"{store}: no levels 1-4 to read (make it with benchmarks/bench_large_volume.py)")
    dropped = drop_caches()
    t = time.perf_counter()
    subprocess.run(["cat", *map(str, files)], stdout=subprocess.DEVNULL, check=True)
    read_s = time.perf_counter() - t
    dec = child(sys.executable, ["--decode-step", str(store)])  # the files are in the page cache now
    dec_s = dec["mean"]["decode_s"] + dec["std"]["decode_s"]
    bound = {"read_mb": sum(p.stat().st_size for p in files) / 1e6, "read_s": read_s, "decode": dec,
             "decode_s": dec_s, "bound_s": max(2 * read_s, dec_s) + 2}
    print(json.dumps(bound), flush=True)
    all_dropped = [dropped]

    def run(who: str) -> dict:
        all_dropped.append(drop_caches())
        where = (a.base_store or store).resolve() if who == "base" else store
        return child(a.base if who == "base" else sys.executable,
                     ["--render-step", str(where), "--started", repr(time.time())])

    pairs = alternating(a.pairs, run, bool(a.base))
    dropped = all(all_dropped)
    cpu = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                if ln.startswith("model name")), platform.processor())
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()
    res = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "nproc": os.cpu_count(), "cpu": cpu,
           "kernel": platform.release(), "command": " ".join(sys.argv), "store": store.name,
           "page_cache_dropped": dropped, "base": base_revision(a.base), "tree": head, "bound": bound, "pairs": pairs,
           "base_store": None if a.base_store is None else a.base_store.resolve().name}
    res["table"] = table(res)
    write_result(a.json, res)


if __name__ == "__main__":
    main()
