"""Where a lit nearest-block (NB) 30:1 image's shading gradients go (issue 45, item 4): how many shaded samples take
each of lc_gradient's paths, counted by a copy of this checkout's kernel sources with counters patched in (never
the product kernel: the copy lives in a temporary folder).

    .venv/bin/python benchmarks/grad_paths.py [--rev REV] [--size 256] [--chest-size 512]

Each counter is one render whose `nsamples` output holds that counter per ray instead of the samples taken
(`-DLC_COUNT_WHAT=k`), so the report's sample total is the counter's total. The counters are named in COUNTERS; a
counter whose anchor this checkout's sources lack (a path that no longer exists) is left out and said so.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))

from bench_seams import lod, scenes  # noqa: E402
from kernel_gate import kernels_from, old_sources  # noqa: E402

from lodcast import opencl  # noqa: E402
from lodcast.renderer.frame.render import Renderer  # noqa: E402

#: a stencil point's axes outside eq. 3.6's window of the walk's block (lc_blk_out), as f_
FLAGS_ = ("{ const float3 l_ = (q + e) * s->blk.s + s->blk.c; const int f_ = s->blk.n ? popcount(lc_blk_out(&s->blk, l_)) "
          ": -1; ")

#: (file, anchor, text put before the anchor) per counter; k = the counter's index
COUNTERS: dict[str, list[tuple[str, str, str]]] = {
    "visible samples": [("lc_classify.h", "    int i;\n    float w, ew;\n    const float4 e = lc_tf_at", "LC_CNT(s, @);\n")],
    "visible with opacity 0": [("lc_classify.h", "    const float3 col = lc_gradient_look(tf, s, sh, e.xyz, q, &ew);\n#ifdef LC_PRECISE\n    const float depth = (e.w * r)",
                                "if (e.w == 0.0f) LC_CNT(s, @);\n")],
    "gradients": [("lc_shade.h", "    float3 g;\n    if (lc_sampler_diff", "LC_CNT(s, @);\n")],
    "fast window": [("lc_sampler.h", "        *d = g;\n        return 1;\n    }\n    const LcAtlasGeom g = s->geom;",
                     "LC_CNT(s, @);\n")],
    "hood diff": [("lc_sampler.h", "    *d = lc_hood_diff(", "LC_CNT(s, @);\n")],
    "hood set up (gradient)": [("lc_sampler.h", "lc_hood(&s->hood, s->imap, g, cx, cy, cz);\n    *d = lc_hood_diff",
                                "{ LC_CNT(s, @); }\n    if (cx != s->hood.cx || cy != s->hood.cy || cz != s->hood.cz) ")],
    "six samples": [("lc_shade.h", "    g = (float3)(0.0f);\n#pragma unroll 1", "LC_CNT(s, @);\n")],
    "NB reads in hood diff": [("lc_atlas.h", "                acc[k] += w * lc_nb(", "LC_CNTH(hd, @);\n")],
    "hood diff, own block only": [("lc_atlas.h", "    float acc[6] = {0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f}, ws[6]", "    uint nb_w = 0;\n"),
                                   ("lc_atlas.h", "                acc[k] += w * lc_nb(", "nb_w |= 1u << s;\n"), ("lc_atlas.h", "    float v[6];\n    for (int k = 0; k < 6; ++k) {\n        /* the block that holds",
                                   "if (LC_NBLK(nb_w) == 1) LC_CNTH(hd, @);\n")],
    "hood diff, two blocks": [("lc_atlas.h", "    float acc[6] = {0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f}, ws[6]", "    uint nb_w = 0;\n"),
                                   ("lc_atlas.h", "                acc[k] += w * lc_nb(", "nb_w |= 1u << s;\n"), ("lc_atlas.h", "    float v[6];\n    for (int k = 0; k < 6; ++k) {\n        /* the block that holds",
                               "if (LC_NBLK(nb_w) == 2) LC_CNTH(hd, @);\n")],
    "gradients (per point)": [("lc_sampler.h", "    float3 d = (float3)(0.0f);\n#pragma unroll 1", "LC_CNT(s, @);\n")],
    "points in the window": [("lc_sampler.h", "        const LcBlk* b = &s->blk;\n        const float3 l = (q + e)", FLAGS_ + "if (f_ == 0) LC_CNT(s, @); }\n")],
    "points by one face": [("lc_sampler.h", "        const LcBlk* b = &s->blk;\n        const float3 l = (q + e)", FLAGS_ + "if (f_ == 1) LC_CNT(s, @); }\n")],
    "points by an edge": [("lc_sampler.h", "        const LcBlk* b = &s->blk;\n        const float3 l = (q + e)", FLAGS_ + "if (f_ == 2) LC_CNT(s, @); }\n")],
    "points by a corner": [("lc_sampler.h", "        const LcBlk* b = &s->blk;\n        const float3 l = (q + e)", FLAGS_ + "if (f_ == 3) LC_CNT(s, @); }\n")],
    "points outside the walk's blocks": [("lc_sampler.h", "        const LcBlk* b = &s->blk;\n        const float3 l = (q + e)", FLAGS_ + "if (f_ < 0) LC_CNT(s, @); }\n")],
    "hood set up": [("lc_atlas.h", "    hd->cx = cx; hd->cy = cy; hd->cz = cz;\n    hd->X[0]", "LC_CNTH(hd, @);\n")],
}


def patched(src: Path, dest: Path, which: str, k: int) -> bool:
    """The kernel sources of src in dest with counter `which` (index k) patched in; False if an anchor is
    missing."""
    for f in src.iterdir():
        if f.suffix in (".cl", ".h"):
            shutil.copy(f, dest / f.name)
    common = (dest / "lc_common.h").read_text()
    common = common.replace("#endif", "#endif\n#define LC_CNT(s, k) ((s)->hood.cnt++)\n#define LC_CNTH(hd, k) "
                            "(((LcHood*)(hd))->cnt++)\n#define LC_NBLK(m) popcount(m)\n", 1)
    (dest / "lc_common.h").write_text(common)
    edits = [("lc_atlas.h", "    int cx, cy, cz; /* the corner", "    uint cnt;\n"),
             ("lc_sampler.h", "    s.hood.cx = -1;", "    s.hood.cnt = 0;\n"),
             ("raycast.cl", "    nsamples[pix] = it.taken;", "    it.taken = smp.hood.cnt;\n")]
    for f, anchor, text in edits + [(f, a, t.replace("@", str(k))) for f, a, t in COUNTERS[which]]:
        body = (dest / f).read_text()
        if anchor not in body:
            return False
        (dest / f).write_text(body.replace(anchor, text + anchor, 1))
    return True


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rev", default=None, help="count in this git revision's kernel sources (default: this checkout's)")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--chest-size", type=int, default=512)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    src = old_sources(args.rev, Path(tempfile.mkdtemp())) if args.rev else opencl.renderer_folder()
    eng = Renderer()
    out: dict[str, dict[str, int]] = {}
    for name, (store, base) in scenes(args.size, ["sphere", "chest"]).items():
        if name == "chest":
            base = {**base, "width": args.chest_size, "height": args.chest_size}
        sc = lod(base, "nearest_block")
        row: dict[str, int] = {"samples": eng.render(store, sc).report["samples"]}
        for k, which in enumerate(COUNTERS):
            folder = Path(tempfile.mkdtemp(prefix="lodcast-count-"))
            if not patched(src, folder, which, k):
                print(f"{name}: {which}: no such path in this checkout", flush=True)
                continue
            with kernels_from(folder):
                row[which] = Renderer().render(store, sc).report["samples"]
            shutil.rmtree(folder)
        out[name] = row
        print(name, json.dumps(row), flush=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
