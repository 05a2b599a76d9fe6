"""What format 4's checksums cost (issue 49, item 1; target: the bootstrap 95 % interval's upper end <= 1.05):
ingest with and without them, and a cold full-resolution render of each store, in interleaved A/B pairs in one
process. "Without" (A) is this checkout's ingest with no `crc32c` codec after the chunks and no manifest or
attribute digests (store/ingest.py: CHECKSUMS and seal), which is what format 3 wrote; "with" (B) is the default.
A cold render opens the store afresh in a new Renderer (no brick cache) after the page cache is dropped (as root:
/proc/sys/vm/drop_caches, else posix_fadvise DONTNEED on every file of the store): its time includes opening
(format 4 checks the metadata and manifest) and reading every level-0 shard (format 4 checks every checksum).

    .venv/bin/python benchmarks/bench_checksums.py --pairs 20 --json docs/measurements/checksums.json
"""
from __future__ import annotations

import argparse
import contextlib
import datetime as _dt
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

import lodcast
from lodcast.store import ingest as ingest_module

sys.path.insert(0, str(Path(__file__).resolve().parent))
from record import bootstrap  # noqa: E402

DATA = Path(os.environ.get("LODCAST_SHARED_DATA", "/work/shared/data"))
SCENE = {"camera": {"azimuth": 30, "elevation": 20}, "width": 256, "height": 256, "quality": "full", "format": "npy",
         "tf": {"points": [{"value": 40, "color": [0.3, 0.7, 0.2], "opacity": 0.0},
                           {"value": 120, "color": [0.9, 0.8, 0.5], "opacity": 0.4},
                           {"value": 255, "color": [1, 1, 1], "opacity": 0.9}]}}


@contextlib.contextmanager
def without_checksums() -> Iterator[None]:
    """Ingest as format 3 did: no crc32c after the chunks, no manifest, no attribute digests."""
    codecs, seal = ingest_module.CHECKSUMS, ingest_module.seal
    ingest_module.CHECKSUMS = ()
    ingest_module.seal = lambda root, group, known=None: None  # type: ignore[assignment]
    try:
        yield
    finally:
        ingest_module.CHECKSUMS, ingest_module.seal = codecs, seal


def drop_cache(root: Path) -> str:
    os.sync()
    try:
        Path("/proc/sys/vm/drop_caches").write_text("3\n")
        return "drop_caches"
    except OSError:
        for p in root.rglob("*"):
            if p.is_file():
                fd = os.open(p, os.O_RDONLY)
                try:
                    os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
                finally:
                    os.close(fd)
        return "fadvise"


def pairs(run: Callable[[bool], tuple[float, float]], n: int) -> dict[str, Any]:
    """n interleaved (without, with) pairs, the order alternating between pairs; ratio = with / without, of the
    wall time and of the process's CPU time (all threads: on a shared machine the wall time also measures the
    neighbours' load, the CPU time much less)."""
    runs: dict[bool, list[tuple[float, float]]] = {False: [], True: []}
    for i in range(n):
        for checked in ((False, True) if i % 2 == 0 else (True, False)):
            runs[checked].append(run(checked))
    out: dict[str, Any] = {"pairs": n}
    for j, clock in enumerate(("wall", "cpu")):
        a, b = (np.array([r[j] for r in runs[c]]) for c in (False, True))
        lo, hi = bootstrap(b / a)
        out[clock] = {"without_s_median": float(np.median(a)), "with_s_median": float(np.median(b)),
                      "ratio_median": float(np.median(b / a)), "ratio_ci95": [lo, hi],
                      "without_s": a.tolist(), "with_s": b.tolist()}
    return out


@contextlib.contextmanager
def clocks() -> Iterator[list[float]]:
    """[wall, cpu] seconds of the block, filled in when it ends."""
    out: list[float] = []
    w0, c0 = time.perf_counter(), time.process_time()
    yield out
    out += [time.perf_counter() - w0, time.process_time() - c0]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--source", type=Path, default=DATA / "bonsai.nii.gz", help="volume to ingest (default bonsai)")
    ap.add_argument("--pairs", type=int, default=20)
    ap.add_argument("--json", type=Path, default=None, help="write the results there too")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="lodcast-crc-"))
    stores = {False: work / "plain.zarr", True: work / "checked.zarr"}
    how = {"cache": ""}

    def ingest(checked: bool) -> tuple[float, float]:
        dest = stores[checked]
        with contextlib.ExitStack() as stack:
            if not checked:
                stack.enter_context(without_checksums())
            with clocks() as took:
                lodcast.ingest(args.source, dest, overwrite=True, progress=False)
        return took[0], took[1]

    def render(checked: bool) -> tuple[float, float]:
        how["cache"] = drop_cache(stores[checked])
        engine = lodcast.Renderer()
        with clocks() as took:
            engine.render(lodcast.open_store(stores[checked]), SCENE)
        return took[0], took[1]

    try:
        ingest(False), ingest(True)
        images = [lodcast.Renderer().render(lodcast.open_store(stores[c]), SCENE).rgba for c in (False, True)]
        assert np.array_equal(*images), "the two stores render differently"
        sizes = {str(c): sum(p.stat().st_size for p in stores[c].rglob("*") if p.is_file()) for c in (False, True)}
        out = {
            "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "machine": {"nproc": os.cpu_count(), "cpu": _cpu(), "python": platform.python_version(),
                        "load_average_at_start": list(os.getloadavg())},
            "command": " ".join([Path(sys.executable).name, *sys.argv]),
            "source": str(args.source), "scene": SCENE, "bytes_on_disk": {"without": sizes["False"],
                                                                        "with": sizes["True"]},
            "ingest": pairs(ingest, args.pairs),
            "cold_render": pairs(render, args.pairs),
        }
        out["page_cache"] = how["cache"]
    finally:
        shutil.rmtree(work, ignore_errors=True)
    for name in ("ingest", "cold_render"):
        for clock in ("wall", "cpu"):
            r = out[name][clock]
            print(f"{name:12s} {clock:4s} without {r['without_s_median']:.3f} s  with {r['with_s_median']:.3f} s  "
                  f"ratio {r['ratio_median']:.3f} [{r['ratio_ci95'][0]:.3f}, {r['ratio_ci95'][1]:.3f}] "
                  f"({out[name]['pairs']} pairs)")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


def _cpu() -> str:
    try:
        return next(line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                    if line.startswith("model name"))
    except (OSError, StopIteration):
        return subprocess.run(["uname", "-m"], capture_output=True, text=True).stdout.strip()


if __name__ == "__main__":
    sys.exit(main())
