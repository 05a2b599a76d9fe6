"""Which distribution should a coarse voxel keep? (issue 9 item 1: "measure at least Gaussian, two-point and their
combination, on several TFs, and keep what wins").

    .venv/bin/python benchmarks/bench_distribution_models.py [--levels 1 2] [--json benchmarks/results/distribution_models.json]

Per coarse voxel of the chest CT (../shared/data/ct_chest_dicom, level 0 of its 16³ store, HU) at levels 1 and 2
(2³ and 4³ level-0 voxels), the classification each model gives is compared with the exact one, the mean of the
classified level-0 values behind the voxel (the box filter of the classified field, which every model tries to
reproduce): expected extinction σ̄ = E[σ_t(v)] and emission ε̄ = E[σ_t(v)·rgb(v)], σ_t = −ln(1 − a) capped as the
kernel's table caps it. Models, from what the voxel would keep:
- mean: T at the mean (what a store without distributions shows);
- gaussian: N(mean, std²), lodcast's table (renderer/lod/classification.py) — what the store keeps today (mean, std);
- two-point: lo = mean of the values at or below the mean, hi = mean of those above, f = the share above:
  (1 − f)·T(lo) + f·T(hi) — keeps (mean, lo, hi);
- mixture: the two-point split with each part a Gaussian of the within-part spread w, w² = std² − (mean − lo)(hi −
  mean) (the law of total variance, one w for both parts): (1 − f)·G(lo, w) + f·G(hi, w) — keeps (mean, std, lo, hi).
Each voxel's colour is its own slab along one edge (2^k level-0 voxels, the unit distance being one voxel):
α = 1 − e^(−σ̄·2^k), premultiplied colour α·ε̄/σ̄; the figures are ΔE (CIELUV, as docs/design.md's image ΔE) over the
voxels either side shows (α ≥ 1/255), the share of voxels a model shows that the exact classification does not
("haze") and of those it loses.

Then images, because a renderer does not show voxels: every level-0 voxel of the middle 272×256×256 voxels is
reconstructed from level k by trilinear interpolation (coarse voxel centres at (i + ½)·2^k − ½) and the field is
composited front to back along y (one unit slab per level-0 voxel), against the same projection of the exactly
classified level 0. Either the parameters are interpolated and then classified (what the kernel does), or each
coarse voxel is classified and its σ̄, ε̄ interpolated (what per-voxel pre-classification would do); "exact per
voxel" classifies each coarse voxel by the mean of its classified level-0 values, the best any per-voxel model can
give. Prints tables, writes JSON.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_consistent_lod import DATA, RESULTS, store_of  # noqa: E402

from lodcast.renderer.image.delta_e import delta_e_stats, srgb_to_luv  # noqa: E402
from lodcast.renderer.lod.classification import EXT_CAP, cached_dist_table  # noqa: E402
from lodcast.renderer.lod.significance import as_tf  # noqa: E402
from lodcast.renderer.scene.transfer_function import CT_PRESETS, evaluate, extinction  # noqa: E402

TFS = ("ct-bone", "ct-skin", "ct-skin-bone")
MODELS = ("mean", "gaussian", "two-point", "mixture")


def point(tf, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(σ_t, σ_t·rgb) of each value, the exact point classification (σ_t capped as the table caps it)."""
    rgb, a = evaluate(tf, v)
    s = np.minimum(extinction(a), EXT_CAP)
    return s, s[..., None] * rgb


def gauss(table, mean: np.ndarray, std: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return table.interp(table.ext[..., None], mean, std)[..., 0], table.interp(table.emission, mean, std)


def colour(s: np.ndarray, e: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """(premultiplied colour, α) of a slab of `length` units with extinction s and emission e."""
    alpha = -np.expm1(-s * length)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.where(s[..., None] > 0, e / s[..., None], 0.0)
    return alpha[..., None] * c, alpha


def stats_of(vox: np.ndarray) -> dict[str, np.ndarray]:
    """Per coarse voxel (rows of `vox`, its level-0 values): mean, std, the two-point split."""
    mean = vox.mean(axis=1)
    std = vox.std(axis=1)
    above = vox > mean[:, None]
    n_hi = above.sum(axis=1)
    n = vox.shape[1]
    s_hi = np.where(above, vox, 0.0).sum(axis=1)
    hi = np.where(n_hi > 0, s_hi / np.maximum(n_hi, 1), mean)
    lo = np.where(n_hi < n, (vox.sum(axis=1) - s_hi) / np.maximum(n - n_hi, 1), mean)
    return {"mean": mean, "std": std, "lo": lo, "hi": hi, "f": n_hi / n}


def model(name: str, tf, table, st: dict) -> tuple[np.ndarray, np.ndarray]:
    if name == "mean":
        return point(tf, st["mean"])
    if name == "gaussian":
        return gauss(table, st["mean"], st["std"])
    f = st["f"]
    if name == "two-point":
        (s0, e0), (s1, e1) = point(tf, st["lo"]), point(tf, st["hi"])
    else:
        w = np.sqrt(np.maximum(st["std"] ** 2 - (st["mean"] - st["lo"]) * (st["hi"] - st["mean"]), 0.0))
        (s0, e0), (s1, e1) = gauss(table, st["lo"], w), gauss(table, st["hi"], w)
    return (1 - f) * s0 + f * s1, (1 - f)[:, None] * e0 + f[:, None] * e1


def study(vol: np.ndarray, level: int, std_max: float, value_range: tuple[float, float], chunk: int = 4) -> dict:
    m = 1 << level
    Z, Y, X = (s // m for s in vol.shape)
    acc = {tf: {mo: {"de_sum": 0.0, "n_fp": 0, "haze": 0, "lost": 0, "shown_exact": 0} for mo in MODELS} for tf in TFS}
    tfs = {name: as_tf(CT_PRESETS[name]) for name in TFS}
    tables = {name: cached_dist_table(tfs[name], value_range, std_max) for name in TFS}
    for z0 in range(0, Z, chunk):
        z1 = min(Z, z0 + chunk)
        a = vol[z0 * m : z1 * m, : Y * m, : X * m].astype(np.float64)
        vox = a.reshape(z1 - z0, m, Y, m, X, m).transpose(0, 2, 4, 1, 3, 5).reshape(-1, m**3)
        st = stats_of(vox)
        for name in TFS:
            tf = tfs[name]
            s, e = point(tf, vox)
            ex_c, ex_a = colour(s.mean(axis=1), e.mean(axis=1), m)
            ex_luv, ex_vis = srgb_to_luv(ex_c), ex_a >= 1 / 255
            for mo in MODELS:
                c, al = colour(*model(mo, tf, tables[name], st), m)
                vis = al >= 1 / 255
                fp = vis | ex_vis
                r = acc[name][mo]
                r["de_sum"] += float(np.linalg.norm(srgb_to_luv(c[fp]) - ex_luv[fp], axis=-1).sum())
                r["n_fp"] += int(fp.sum())
                r["haze"] += int((vis & ~ex_vis).sum())
                r["lost"] += int((ex_vis & ~vis).sum())
                r["shown_exact"] += int(ex_vis.sum())
    out = {}
    for name in TFS:
        out[name] = {}
        for mo in MODELS:
            r = acc[name][mo]
            out[name][mo] = {"mean_delta_e": r["de_sum"] / max(r["n_fp"], 1),
                             "haze": r["haze"] / max(r["shown_exact"], 1), "lost": r["lost"] / max(r["shown_exact"], 1)}
    return out


def project(s: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Front-to-back compositing along axis 1 of extinction s and emission e, a unit slab per voxel: the
    premultiplied RGBA image (axis 0, axis 2)."""
    a = -np.expm1(-s)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.where(s[..., None] > 0, e / s[..., None], 0.0)
    T = np.ones((s.shape[0], s.shape[2]))
    C = np.zeros((s.shape[0], s.shape[2], 3))
    for j in range(s.shape[1]):
        C += (T * a[:, j])[..., None] * c[:, j]
        T *= 1 - a[:, j]
    return np.concatenate([C, (1 - T)[..., None]], -1)


def upsample(a: np.ndarray, m: int) -> np.ndarray:
    """Level k to level 0 by trilinear interpolation (voxel centres aligned, edges clamped)."""
    return ndimage.zoom(a, m, order=1, mode="nearest", grid_mode=True)


def image_study(vol: np.ndarray, level: int, std_max: float, value_range: tuple[float, float]) -> dict:
    sub = vol[:272, 128:384, 128:384].astype(np.float64)
    m = 1 << level
    Z, Y, X = (n // m for n in sub.shape)
    vox = sub.reshape(Z, m, Y, m, X, m).transpose(0, 2, 4, 1, 3, 5).reshape(-1, m**3)
    st = {key: v.reshape(Z, Y, X) for key, v in stats_of(vox).items()}
    par = {key: upsample(st[key], m) for key in ("mean", "std", "lo", "hi")}
    par["f"] = np.clip(np.where(par["hi"] > par["lo"], (par["mean"] - par["lo"]) / np.maximum(par["hi"] - par["lo"], 1e-9),
                                0.0), 0.0, 1.0)
    par = {key: v.ravel() for key, v in par.items()}
    flat = {key: v.ravel() for key, v in st.items()}
    out = {}
    for name in TFS:
        tf = as_tf(CT_PRESETS[name])
        table = cached_dist_table(tf, value_range, std_max)
        s0, e0 = point(tf, sub)
        ref = project(s0, e0)
        imgs = {}
        for mo in ("mean", "gaussian", "mixture"):
            s, e = model(mo, tf, table, par)
            imgs[f"{mo}: interpolate, classify"] = project(s.reshape(sub.shape), e.reshape(sub.shape + (3,)))
        coarse = {mo: model(mo, tf, table, flat) for mo in ("gaussian", "mixture")}
        coarse["exact per voxel"] = (s0.reshape(Z, m, Y, m, X, m).mean(axis=(1, 3, 5)).ravel(),
                                     e0.reshape(Z, m, Y, m, X, m, 3).mean(axis=(1, 3, 5)).reshape(-1, 3))
        for mo, (s, e) in coarse.items():
            s, e = s.reshape(Z, Y, X), e.reshape(Z, Y, X, 3)
            imgs[f"{mo}: classify, interpolate"] = project(upsample(s, m),
                                                           np.stack([upsample(e[..., c], m) for c in range(3)], -1))
        out[name] = {lab: delta_e_stats(img, ref)["mean"] for lab, img in imgs.items()}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--levels", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--json", type=Path, default=RESULTS / "distribution_models.json")
    a = ap.parse_args()
    store = store_of("ct_chest", DATA / "ct_chest_dicom")
    vol = store.read_level(0)
    value_range = (float(np.nanmin(vol)), float(np.nanmax(vol)))
    res = {"volume": "chest CT", "shape": list(vol.shape), "levels": {}}
    lines = ["| TF | level | " + " | ".join(MODELS) + " |", "|---|---|" + "---|" * len(MODELS)]
    for k in a.levels:
        got = study(vol, k, store.std_max, value_range)
        res["levels"][str(k)] = got
        for name in TFS:
            cells = [f"{got[name][mo]['mean_delta_e']:.2f} ({100 * got[name][mo]['haze']:.0f}% / "
                     f"{100 * got[name][mo]['lost']:.0f}%)" for mo in MODELS]
            lines.append(f"| {name} | {k} | " + " | ".join(cells) + " |")
        print("\n".join(lines[-len(TFS):]), flush=True)
    table = "mean ΔE per coarse voxel against the exact classification (haze / lost, % of the voxels it shows)\n\n"
    table += "\n".join(lines)
    res["images"] = {}
    img_lines = []
    for k in a.levels:
        got = image_study(vol, k, store.std_max, value_range)
        res["images"][str(k)] = got
        if not img_lines:
            img_lines = ["| TF | level | " + " | ".join(got[TFS[0]]) + " |", "|---|---|" + "---|" * len(got[TFS[0]])]
        for name in TFS:
            img_lines.append(f"| {name} | {k} | " + " | ".join(f"{v:.2f}" for v in got[name].values()) + " |")
            print(img_lines[-1], flush=True)
    table += "\n\nmean ΔE of the projected image against the exactly classified level 0\n\n" + "\n".join(img_lines)
    res["table"] = table
    print("\n" + table)
    a.json.parent.mkdir(parents=True, exist_ok=True)
    a.json.write_text(json.dumps(res, indent=2))
    print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
