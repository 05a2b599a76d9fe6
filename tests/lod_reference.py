"""Float64 NumPy evaluation of the multiresolution sampling formulas (nearest block: thesis eq. 3.5, and through
the level-0 bricks' aprons across faces between level-0 blocks; eq. 3.6 in 3D interblock interpolation with the edge weights documented
in renderer/kernel/lc_atlas.h), written from the formulas,
plus a probe that runs the kernel's sampler at given points. Coordinates are level-0 voxel coordinates
q = (x, y, z), voxel centres at integers; arrays are (z, y, x)."""
from __future__ import annotations

import math

import numpy as np
import pyopencl as cl

from lodcast.opencl import Device
from lodcast.renderer.data.atlas import pack, pack_std


def pyramid(v0: np.ndarray, n_levels: int) -> list[np.ndarray]:
    """Level k = the 2^k-cube averages of level 0 (shape a multiple of 2^(n_levels-1))."""
    out = [np.asarray(v0, np.float64)]
    for _ in range(1, n_levels):
        a = out[-1]
        z, y, x = a.shape
        out.append(a.reshape(z // 2, 2, y // 2, 2, x // 2, 2).mean(axis=(1, 3, 5)))
    return out


def bricks_of(levels: np.ndarray, pyr: list[np.ndarray], B: int) -> dict:
    out = {}
    for (z, y, x), k in np.ndenumerate(levels):
        if k < 0:
            continue
        n = B >> int(k)
        out[(int(k), z, y, x)] = pyr[int(k)][z * n:(z + 1) * n, y * n:(y + 1) * n, x * n:(x + 1) * n]
    return out


def _trilinear(a: np.ndarray, p: tuple[float, float, float]) -> float:
    """a[z, y, x] at brick coordinates p = (x, y, z), clamped to the array (clamp to edge)."""
    c = [min(max(p[i], 0.0), a.shape[2 - i] - 1) for i in range(3)]
    i0 = [int(math.floor(v)) for v in c]
    f = [v - i for v, i in zip(c, i0)]
    i1 = [min(i + 1, a.shape[2 - k] - 1) for k, i in enumerate(i0)]
    r = 0.0
    for s in range(8):
        ix = [i1[k] if (s >> k) & 1 else i0[k] for k in range(3)]
        w = np.prod([f[k] if (s >> k) & 1 else 1 - f[k] for k in range(3)])
        if w:
            r += w * a[ix[2], ix[1], ix[0]]
    return float(r)


def nb(levels, bricks, B, b, q) -> float:
    """Eq. 3.5: block b = (bx, by, bz)'s brick at q, intrablock coordinate clamped to [delta, 1 - delta]."""
    bx, by, bz = b
    k = int(levels[bz, by, bx])
    n = B >> k
    p_local = [((q[a] + 0.5) / B - b[a]) for a in range(3)]  # intrablock coordinate p' (may lie outside [0, 1))
    d = 0.5 / n
    pc = [min(max(v, d), 1 - d) for v in p_local]
    return _trilinear(bricks[(k, bz, by, bx)], tuple(v * n - 0.5 for v in pc))


def nb_apron(levels, bricks, B, b, q) -> float:
    """Nearest block as lodcast samples it: eq. 3.5 in a coarse block; in a level-0 block trilinear at its brick
    coordinate, where a stencil sample beyond the brick is the sample of the block there when that block is at
    level 0 too, else b's own nearest sample (off the grid along an axis: b's edge along that axis, the volume's
    clamp)."""
    G = (levels.shape[2], levels.shape[1], levels.shape[0])
    k = int(levels[b[2], b[1], b[0]])
    if k != 0:
        return nb(levels, bricks, B, b, q)
    n = B >> k
    p = [min(max((q[a] + 0.5 - b[a] * B) / 2.0**k - 0.5, -1.0), float(n)) for a in range(3)]
    i0 = [int(math.floor(v)) for v in p]
    f = [v - i for v, i in zip(p, i0)]

    def at(idx) -> float:
        d = [-1 if i < 0 else (1 if i > n - 1 else 0) for i in idx]
        for a in range(3):  # off the grid: the volume's clamp to edge along that axis
            if not 0 <= b[a] + d[a] < G[a]:
                d[a], idx[a] = 0, min(max(idx[a], 0), n - 1)
        nbk = [b[a] + d[a] for a in range(3)]
        if any(d) and levels[nbk[2], nbk[1], nbk[0]] == k:
            j = [idx[a] - d[a] * n for a in range(3)]
            return float(bricks[(k, nbk[2], nbk[1], nbk[0])][j[2], j[1], j[0]])
        j = [min(max(i, 0), n - 1) for i in idx]
        return float(bricks[(k, b[2], b[1], b[0])][j[2], j[1], j[0]])

    r = 0.0
    for s in range(8):
        w = float(np.prod([f[a] if (s >> a) & 1 else 1 - f[a] for a in range(3)]))
        if w:
            r += w * at([i0[a] + ((s >> a) & 1) for a in range(3)])
    return r


def edge(x: float, hl: float, hu: float) -> float:
    return min(max((x + hl) / (hl + hu), 0.0), 1.0)


def sample(levels, bricks, B, q, interp: str = "interblock") -> float:
    G = (levels.shape[2], levels.shape[1], levels.shape[0])
    p = [(q[a] + 0.5) / B for a in range(3)]
    own = tuple(min(max(int(math.floor(p[a])), 0), G[a] - 1) for a in range(3))
    if levels[own[2], own[1], own[0]] < 0:
        return float("nan")
    if interp == "nearest_block":
        return nb_apron(levels, bricks, B, own, q)
    c = [math.floor(p[a] + 0.5) for a in range(3)]
    xs = [p[a] - c[a] for a in range(3)]  # interblock coordinate p* in block units
    blk = [[min(max(c[a] - 1 + s, 0), G[a] - 1) for s in (0, 1)] for a in range(3)]

    def lev(s):
        return int(levels[blk[2][s[2]], blk[1][s[1]], blk[0][s[0]]])

    def half(s):  # delta in block units: half a sample of the block; missing blocks: half a level-0 sample
        k = lev(s)
        return 0.5 / (B >> max(k, 0))

    acc = wsum = 0.0
    for s in np.ndindex(2, 2, 2):
        s = (s[2], s[1], s[0])  # (sx, sy, sz)
        if lev(s) < 0:
            continue
        w = 1.0
        for a in range(3):
            lo, hi = list(s), list(s)
            lo[a], hi[a] = 0, 1
            e = edge(xs[a], half(lo), half(hi))
            w *= e if s[a] else 1 - e
        if w > 0:
            acc += w * nb(levels, bricks, B, (blk[0][s[0]], blk[1][s[1]], blk[2][s[2]]), q)
            wsum += w
    return acc / wsum


def trilinear_level(pyr, k: int, B: int, q) -> float:
    """Trilinear interpolation of the whole level-k volume at q (clamp to edge)."""
    s = 2.0 ** k
    return _trilinear(pyr[k], tuple((q[a] + 0.5) / s - 0.5 for a in range(3)))


def probe(levels: np.ndarray, bricks: dict, B: int, pts: np.ndarray, interp: str = "interblock",
          std_bricks: dict | None = None, std_unit: float = 1.0, device: Device | None = None) -> np.ndarray:
    """The kernel's sampler (lc_atlas.h through atlas_probe.cl) at pts (N, 3) = (x, y, z): the values, or with
    `std_bricks` (value, standard deviation) pairs (N, 2) as the distribution sampler (LC_DIST) gives them; the
    deviations travel as the device holds them, whole multiples of `std_unit` in uint16 (volume.std_unit). On
    `device`, else a Device of this call's own."""
    dev = device or Device()
    ctx, queue = dev.context, dev.queue
    opts = ["-DLC_INTERP_II" if interp == "interblock" else "-DLC_INTERP_NB"] + (["-DLC_DIST"] if std_bricks else [])
    prg = dev.program("atlas_probe.cl", opts).program
    atlas, idx = pack(levels, {k: np.asarray(v, np.float32) for k, v in bricks.items()}, B, max_bytes=2**31)
    sig = pack_std(levels, {k: np.rint(quantized_std(v, std_unit) / std_unit) for k, v in (std_bricks or {}).items()},
                   B)
    p4 = np.zeros((len(pts), 4), np.float32)
    p4[:, :3] = pts
    mf = cl.mem_flags
    bufs = [cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a) for a in (atlas, sig, idx, p4)]
    out = np.zeros((len(pts), 2), np.float32)
    d_out = cl.Buffer(ctx, mf.WRITE_ONLY, out.nbytes)
    G = levels.shape
    cl.Kernel(prg, "lc_probe_atlas")(queue, (len(pts),), None, bufs[0], bufs[1], bufs[2],
                                     np.array([G[2], G[1], G[0], B], np.int32), bufs[3], d_out, np.int32(len(pts)))
    cl.enqueue_copy(queue, out, d_out)
    queue.finish()
    if not std_bricks:
        return out[:, 0]
    out[:, 1] *= np.float32(std_unit)
    return out


def quantized_std(a: np.ndarray, unit: float) -> np.ndarray:
    """Standard deviations as the device holds them: the nearest whole multiple of `unit` (uint16 range), float64."""
    return np.clip(np.rint(np.asarray(a, np.float64) / unit), 0, 65535) * unit
