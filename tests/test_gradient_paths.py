"""Shading gradients on the atlas (renderer/kernel/lc_sampler.h: lc_sampler_diff) take the interblock field
(eq. 3.6) in every build, through the walk's block: its brick inside eq. 3.6's window, the blocks of a point's blend
zone near a face (lc_atlas.h: lc_face_blend), edge or corner (lc_hood_zone), the ray's interblock neighbourhood
outside the walk's blocks. Checked against float64 evaluations of eq. 3.6 at the six stencil points, and a lit nearest-block image
against the same kernel whose gradients take six general interblock samples each."""
from __future__ import annotations

import shutil
from pathlib import Path

import lod_reference as ref
import numpy as np
import pyopencl as cl
import pytest
from phantoms import SPHERE_TF, sphere_ramp

import lodcast
from lodcast import opencl
from lodcast.opencl import Device
from lodcast.renderer.data.atlas import pack

B = 8
NL = 4  # levels 0..3; level 3 = one sample per block
E = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float64)


def _diff_probe(levels, bricks, pts, cells, options, device=None) -> np.ndarray:
    """lc_probe_diff (atlas_probe.cl): the kernel's central differences at pts (N, 3) = (x, y, z), each from the
    walk cell cells[i] = (x, y, z, cells per block edge)."""
    dev = device or Device()
    ctx, queue = dev.context, dev.queue
    prg = dev.program("atlas_probe.cl", options).program
    atlas, idx = pack(levels, {k: np.asarray(v, np.float32) for k, v in bricks.items()}, B, max_bytes=2**31)
    p4 = np.zeros((len(pts), 4), np.float32)
    p4[:, :3] = pts
    mf = cl.mem_flags
    bufs = [cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)
            for a in (atlas, np.zeros(1, np.uint16), idx, p4, np.ascontiguousarray(cells, np.int32))]
    out = np.zeros((len(pts), 4), np.float32)
    d_out = cl.Buffer(ctx, mf.WRITE_ONLY, out.nbytes)
    G = levels.shape
    cl.Kernel(prg, "lc_probe_diff")(queue, (len(pts),), None, *bufs[:3], np.array([G[2], G[1], G[0], B], np.int32),
                                    bufs[3], bufs[4], d_out, np.int32(len(pts)))
    cl.enqueue_copy(queue, out, d_out)
    queue.finish()
    return out[:, :3].astype(np.float64)


def _want(levels, bricks, pts) -> np.ndarray:
    """Eq. 3.6 (float64) one level-0 voxel ahead minus one behind, per axis."""
    return np.array([[ref.sample(levels, bricks, B, q + e) - ref.sample(levels, bricks, B, q - e) for e in E]
                     for q in pts])


def _points(G, n, rng) -> np.ndarray:
    """Stencil centres: half anywhere in the volume, half within two voxels of a block face on every axis (the
    blend zones' edges and corners)."""
    hi = np.array([G[2], G[1], G[0]]) * B - 0.5
    anywhere = rng.uniform(-0.5, hi, (n // 2, 3))
    near = (rng.integers(0, np.array([G[2], G[1], G[0]]) + 1, (n - n // 2, 3)) * B - 0.5
            + rng.uniform(-2.0, 2.0, (n - n // 2, 3)))
    return np.concatenate([anywhere, np.clip(near, -0.5, hi)])


def _cells(G, pts, cpb) -> np.ndarray:
    """The walk cell that holds each point, cpb cells per block edge (0: no cell, the general sampler)."""
    top = np.array([G[2], G[1], G[0]]) * max(cpb, 1) - 1
    c = np.clip(np.floor((pts + 0.5) / (B / max(cpb, 1))).astype(np.int32), 0, top)
    return np.column_stack([c, np.full(len(pts), cpb, np.int32)])


@pytest.mark.parametrize("interp", ["nearest_block", "interblock"])
def test_differences_match_float64_eq36_on_random_levels(interp):
    """Random levels with missing blocks and one-sample blocks, stencils anywhere and crowded around faces, edges
    and corners, from half-block cells (the adaptive walk: each cell's own window), whole-block cells and none:
    each component is eq. 3.6's difference up to float32 rounding, and NaN exactly where a stencil point lies in a
    missing block."""
    rng = np.random.default_rng(11)
    G = (3, 4, 5)
    pyr = [p.astype(np.float64) for p in ref.pyramid(rng.random(tuple(g * B for g in G)), NL)]
    levels = rng.integers(-1, NL, G).astype(np.int8)
    levels[1, 1:3, 1:4] = rng.integers(0, 2, (2, 3))  # a patch of fine blocks
    br = ref.bricks_of(levels, pyr, B)
    pts = _points(G, 3000, rng)
    want = _want(levels, br, pts)
    nan = np.isnan(want).any(axis=1)
    assert 100 < nan.sum() < len(pts) // 2
    dev = Device()
    for cpb in (2, 1, 0):
        got = _diff_probe(levels, br, pts, _cells(G, pts, cpb),
                          [f"-DLC_INTERP_{'II' if interp == 'interblock' else 'NB'}", "-DLC_SHADE"], dev)
        np.testing.assert_array_equal(np.isnan(got).any(axis=1), nan, err_msg=f"cells per block {cpb}")
        np.testing.assert_allclose(got[~nan], want[~nan], atol=4e-6, rtol=0, err_msg=f"cells per block {cpb}")


#: lc_sampler_diff's dispatch of a stencil point, and what reference kernels put there instead
DISPATCH = "        float v;\n        if (b->n && (f & (f - 1)) == 0) {"
#: eq. 3.6 as II samples it, at the point's own block (NaN in a missing one)
GENERAL = ("        float v;\n        int bx, by, bz;\n"
           "        const ulong own = lc_own(s->imap, s->geom, q + e, &bx, &by, &bz);\n"
           "        if (1) v = own ? lc_sample_ii(s->vol, s->sig, s->imap, s->geom, &s->hood, own, bx, by, bz, q + e).x"
           " : NAN;\n        else if (0) {")
#: the build's own field: nearest block's clamped samples
NEAREST = "        float v;\n        if (1) v = lc_sampler_at(s, q + e).x;\n        else if (0) {"


def _kernels(src: Path, dest: Path, line: str) -> Path:
    """The kernel sources of src in dest with every gradient point through `line` instead of its paths."""
    dest.mkdir()
    for f in src.iterdir():
        if f.suffix in (".cl", ".h"):
            shutil.copy(f, dest / f.name)
    text = (dest / "lc_sampler.h").read_text()
    assert text.count(DISPATCH) == 1
    (dest / "lc_sampler.h").write_text(text.replace(DISPATCH, line))
    return dest


@pytest.mark.parametrize("steps", [{}, {"adaptive_naive": True}])
def test_lit_nearest_block_image_is_the_interblock_fields(tmp_path, monkeypatch, steps):
    """The lit smooth sphere at 30:1, nearest block (the default): the same image, up to float32 rounding, as a
    kernel whose every gradient point is a general interblock sample (lc_sample_ii); gradients from nearest
    block's own clamped samples would change it visibly (the block grid issue 45 removed). Also with naive adaptive
    steps, whose walk enters no cell: the sampler's block is then none (it read a window from uninitialised
    fields and crashed the process)."""
    store = lodcast.ingest(sphere_ramp(128), tmp_path / "sphere.zarr", block_size=16, progress=False)
    scene = {"camera": {"azimuth": 30, "elevation": 20}, "width": 128, "height": 128, "tf": SPHERE_TF, "shading": {},
             "format": "npy", "quality": {"reduction": 30}, "sampling": {"interpolation": "nearest_block", **steps}}
    img = lodcast.render(store, scene).rgba
    out, src = {}, opencl.renderer_folder()
    for name, line in (("general", GENERAL), ("nearest", NEAREST)):
        folder = _kernels(src, tmp_path / name, line)
        monkeypatch.setattr(opencl, "renderer_folder", lambda folder=folder: folder)
        out[name] = lodcast.render(store, scene).rgba
    monkeypatch.undo()
    assert (img[..., 3] > 0.5).sum() > 1500
    d_general, d_nearest = np.abs(img - out["general"]).max(), np.abs(img - out["nearest"]).max()
    assert d_general <= 2e-5
    assert d_nearest > 0.05
