"""Timings of block significance (eq. 3.1) and LOD selection (eq. 3.2) on synthetic metadata of 212,000 blocks
(the thesis' full-body data set, paper IX). Targets (issue 5): significance ≤ 0.1 µs per block, selection of
212,000 blocks ≤ 0.1 s.

    .venv/bin/python benchmarks/bench_lod.py [--blocks 212000] [--repeat 7] [--out benchmarks/results/bench_lod.json]

Synthetic metadata: block size 32 (6 levels), 256 bins over [−1000, 3000], each block's border-inclusive value
range spans 3–220 bins, its simplified histogram 12 pieces inside that range (what ingest writes for CT). TFs:
"all visible" (opacity > 0 everywhere: every block evaluated, the worst case) and a skin + bone CT TF (air and
the gap between skin and bone transparent). Timings are medians; "warm" = a TF change on a store already seen
(the TF-independent gather indices and coefficients are cached per store: BlockMeta.pre), "cold" includes
computing them; the selections' per-TF tables are kept in an engine's tables, as a render keeps them.
The significance runs its gather + batched product on a thread pool of min(4, cores) threads: on a shared
2-core machine the numbers move by ±30 % with the other load.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from lodcast.renderer.frame.render import Renderer
from lodcast.renderer.lod.selection import greedy, select_from_meta
from lodcast.renderer.lod.significance import BlockMeta, block_significance, level_profile
from lodcast.renderer.scene.transfer_function import CT_PRESETS
from lodcast.store.histogram import Bins

ALL_VISIBLE = {"points": [{"value": -1000, "color": [0.2, 0.3, 0.9], "opacity": 0.05}, {"value": 3000, "color": [1, 1, 0.8], "opacity": 0.9}]}
SKIN_BONE = CT_PRESETS["ct-skin-bone"]


def synthetic(n: int, seed: int = 0) -> BlockMeta:
    rng = np.random.default_rng(seed)
    bins = Bins.for_range(-1000.0, 3000.0, integer=False, max_bins=256)
    nb, k = bins.count, 12
    span = rng.integers(3, 221, n)
    lo = rng.integers(0, nb - span + 1)
    hi = lo + span  # exclusive
    inner = np.sort(rng.random((n, k - 1)), axis=1)
    starts = np.empty((n, k + 1), np.int64)
    starts[:, 0] = 0
    starts[:, -1] = nb
    starts[:, 1] = lo
    starts[:, 2:-1] = lo[:, None] + np.floor(inner[:, :-1] * span[:, None]).astype(np.int64) + 1
    starts[:, -2] = hi
    starts = np.maximum.accumulate(np.minimum(starts, nb), axis=1)
    heights = (rng.random((n, k)) * 400).astype(np.float32)
    heights[:, 0] = 0.0
    heights[:, -1] = 0.0
    edges = bins.edges
    vmin, vmax = edges[lo], edges[hi] - 1e-6
    mean = vmin + rng.random(n) * (vmax - vmin)
    return BlockMeta((1, 1, n), 6, bins, mean, np.full(n, 32768.0), vmin, vmax, starts.astype(np.uint16), heights, None)


def median_time(fn, repeat: int) -> float:
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--blocks", type=int, default=212_000)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    n = a.blocks
    meta = synthetic(n)
    block_significance(meta, ALL_VISIBLE)  # imports, colour-science warm-up
    res: dict = {"blocks": n}

    def cold() -> None:
        meta.__dict__.pop("pre", None)  # BlockMeta.pre is a cached_property: drop what it computed
        block_significance(meta, ALL_VISIBLE)

    res["significance_cold_all_visible_s"] = median_time(cold, a.repeat)
    _ = meta.pre  # computed once, outside the warm timings
    for name, tf in (("all_visible", ALL_VISIBLE), ("skin_bone", SKIN_BONE)):
        t = median_time(lambda: block_significance(meta, tf), a.repeat)
        z, vis = block_significance(meta, tf)
        res[f"significance_{name}_s"] = t
        res[f"significance_{name}_us_per_block"] = t / n * 1e6
        res[f"visible_fraction_{name}"] = float(vis.mean())

    z0, vis = block_significance(meta, SKIN_BONE)
    prof = level_profile(6)
    nsamp = np.array([(32 >> k) ** 3 for k in range(6)], np.int64)
    rows = np.flatnonzero(z0 > 0)
    ztab = z0[rows, None] * prof[None, :]
    maxlev = np.zeros(rows.size, np.int64)
    n_vox = n * 32**3
    for r in (5, 30, 64):
        budget = n_vox / r - rows.size
        res[f"greedy_{r}to1_s"] = median_time(lambda: greedy(ztab, maxlev, nsamp, budget, profile=prof), a.repeat)
    res["greedy_blocks"] = int(rows.size)
    # all 212,000 blocks refinable (every block visible and significant)
    z_all, _ = block_significance(meta, ALL_VISIBLE)
    ztab_all = z_all[:, None] * prof[None, :]
    ml_all = np.zeros(n, np.int64)
    res["greedy_all_blocks_64to1_s"] = median_time(lambda: greedy(ztab_all, ml_all, nsamp, n_vox / 64 - n, profile=prof), a.repeat)
    res["greedy_all_blocks_64to1_general_chains_s"] = median_time(lambda: greedy(ztab_all, ml_all, nsamp, n_vox / 64 - n), a.repeat)
    eng = Renderer()  # its settings and tables only (no device is opened): "warm" selections reuse its tables
    for q in ({"reduction": 64}, "lossless"):
        key = "select_lod_" + (q if isinstance(q, str) else "64to1") + "_warm_s"
        res[key] = median_time(lambda: select_from_meta(meta, [SKIN_BONE], q, n_voxels=n_vox, block_size=32,
                                                        lossless_zeta=eng.settings.lossless_zeta, tables=eng.tables),
                               a.repeat)
    for k, v in res.items():
        print(f"{k:48s} {v:.4g}" if isinstance(v, float) else f"{k:48s} {v}")
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
