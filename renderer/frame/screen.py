"""Adaptive screen-space sampling (thesis §3.6.3, fig. 3.17–3.18): the image is cut into tiles of TILE×TILE
pixels, each rendered at a resolution of n×n rays (n from 2 to TILE in steps of two) chosen from the level of
detail along its rays, and the mosaic is reconstructed by intertile interpolation, the 2D form of interblock
interpolation (eq. 3.6), so that tiles of different resolutions join continuously.

Pre-pass: rays through each tile's centre and corners sample the block grid every half block and collect the
block scale 2^-level of every loaded, visible block they pass; the tile's priority is the maximum, the average or
the root mean square of those scales (`statistic`), and n = clamp(2·ceil(priority·TILE/2), 2, TILE). A tile whose
rays meet level-0 blocks (max) — or mostly level-0 blocks (average, RMS) — is rendered at full resolution; at
quality "full" every tile is, and the image equals the plain render exactly.

Tile samples: tile t's sample i (of n) sits at image position x = t·TILE + (i + ½)·TILE/n (pixels, pixel j's centre
at j + ½), so a full-resolution tile's rays are its pixels' own rays.

Reconstruction, at a pixel centre u (tile coordinates p = u / TILE, tile b covering [b, b + 1)): the nearest-tile
sample φ_b(p) is bilinear in b's n×n samples at its intratile coordinate clamped to [δ, 1 − δ], δ = 1/(2n); the
cell between the four tile centres around p has corner c = floor(p + ½) and coordinate p* = p − c ∈ [−½, ½); per
axis the edge weight between the lower tile L and the upper U is e = clamp((p* + δ_L)/(δ_L + δ_U), 0, 1), each tile
weighs the product over both axes of e (upper) or 1 − e (lower), and the pixel is Σ w_b φ_b / Σ w_b. Equal
resolutions give bilinear interpolation of the sample lattice; the weights are continuous, so the image is.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from lodcast.renderer.scene import camera as cam

__all__ = ["TILE", "STATISTICS", "SCREEN_DELTA_E", "ScreenPlan", "tile_priorities", "resolutions", "plan", "reconstruct",
           "predicted_delta_e"]

TILE = 16
STATISTICS = ("max", "average", "rms")
#: the mean ΔE that reconstructing a 256² image's pixels from its tiles' sparse rays adds (what intertile
#: interpolation smooths away of edges and texture below a tile's ray spacing), per pixel without its own ray:
#: the geometric mean over the chest CT's pairs (five TFs, three views, 10:1 and 30:1, 256² and 128²), validated on
#: the engine and bonsai CTs (docs/measurements/prediction.md); it adds to the level of detail's error
SCREEN_DELTA_E = 2.2


@dataclass(frozen=True)
class ScreenPlan:
    res: np.ndarray  # (th, tw) int: samples per tile edge
    tile: int
    width: int
    height: int
    positions: np.ndarray  # (N, 2) float32 image positions (x, y) of the rays, tile by tile
    offsets: np.ndarray  # (th, tw) int64: index of each tile's first ray in `positions`

    @property
    def rays(self) -> int:
        return int(len(self.positions))


def predicted_delta_e(sp: ScreenPlan) -> float:
    """What the mosaic adds to an image's mean ΔE: SCREEN_DELTA_E times the share of pixels without a ray of their
    own (0 where every tile is at full resolution), scaled from a 256² image to this one's size: what
    interpolation smooths away is mostly edges, whose share of the pixels is about the tile's share of the image
    (a tile of 16 pixels spans twice as much of a 128² picture)."""
    return SCREEN_DELTA_E * max(0.0, 1.0 - sp.rays / float(sp.width * sp.height)) * 256.0 / np.sqrt(sp.width * sp.height)


def _ray_points(fr: cam.Frame, xy: np.ndarray, W: int, H: int, box: tuple, step: float, n: int) -> np.ndarray:
    """(R, n, 3) world points every `step` along the rays through image positions xy (R, 2), from where each
    enters the box; points past the exit are NaN."""
    o, d = cam.rays_at(fr, xy[:, 0], xy[:, 1], W, H)
    t0, t1 = cam.ray_box(o, d, *box)
    t = t0[:, None] + (np.arange(n) + 0.5)[None, :] * step
    pts = o[:, None, :] + t[..., None] * d[:, None, :]
    pts[t > t1[:, None]] = np.nan
    return pts


def tile_priorities(fr: cam.Frame, levels: np.ndarray, visible: np.ndarray, shape: Sequence[int],
                    spacing: Sequence[float], origin: Sequence[float], block_size: int, width: int, height: int,
                    tile: int = TILE, statistic: str = "rms") -> np.ndarray:
    """(th, tw) float in [0, 1]: the statistic of the block scales 2^-level along each tile's centre and corner
    rays (loaded and visible blocks only; 0 where the rays meet none)."""
    if statistic not in STATISTICS:
        raise ValueError(f"statistic {statistic!r}: one of {', '.join(STATISTICS)}")
    th, tw = -(-height // tile), -(-width // tile)
    box = cam.box_world(shape, spacing, origin)
    cy, cx = np.mgrid[:th, :tw]
    centres = np.stack([(cx + 0.5) * tile, (cy + 0.5) * tile], -1).reshape(-1, 2)
    ky, kx = np.mgrid[: th + 1, : tw + 1]
    corners = np.stack([kx * tile, ky * tile], -1).reshape(-1, 2).astype(np.float64)
    xy = np.concatenate([centres, corners]).astype(np.float64)
    step = 0.5 * block_size * float(min(spacing))
    n = int(np.ceil(np.linalg.norm(box[1] - box[0]) / step)) + 1
    scale = np.where((levels >= 0) & visible, 2.0 ** -np.maximum(levels, 0).astype(np.float64), np.nan)
    grid = np.asarray(levels.shape)
    s_sum = np.zeros(len(xy))
    s_sq = np.zeros(len(xy))
    s_max = np.zeros(len(xy))
    s_n = np.zeros(len(xy))
    for a in range(0, len(xy), 4096):
        pts = _ray_points(fr, xy[a:a + 4096], width, height, box, step, n)
        zyx = (pts[..., ::-1] - np.asarray(origin)) / np.asarray(spacing)  # voxel coordinates (z, y, x)
        b = np.floor((zyx + 0.5) / block_size)
        ok = np.isfinite(b).all(axis=-1)
        b = np.clip(np.nan_to_num(b), 0, grid - 1).astype(np.int64)
        v = np.where(ok, scale[b[..., 0], b[..., 1], b[..., 2]], np.nan)
        seen = np.isfinite(v)
        s_n[a:a + 4096] = seen.sum(axis=1)
        s_sum[a:a + 4096] = np.where(seen, v, 0).sum(axis=1)
        s_sq[a:a + 4096] = np.where(seen, v * v, 0).sum(axis=1)
        s_max[a:a + 4096] = np.where(seen, v, 0).max(axis=1)

    def per_tile(arr: np.ndarray, combine: Callable[[list[np.ndarray]], np.ndarray]) -> np.ndarray:
        c = arr[: th * tw].reshape(th, tw)
        k = arr[th * tw:].reshape(th + 1, tw + 1)
        return combine([c, k[:-1, :-1], k[:-1, 1:], k[1:, :-1], k[1:, 1:]])

    if statistic == "max":
        return per_tile(s_max, lambda xs: np.max(xs, axis=0))
    cnt = per_tile(s_n, lambda xs: np.sum(xs, axis=0))
    if statistic == "average":
        tot = per_tile(s_sum, lambda xs: np.sum(xs, axis=0))
        return np.where(cnt > 0, tot / np.maximum(cnt, 1), 0.0)
    tot = per_tile(s_sq, lambda xs: np.sum(xs, axis=0))
    return np.where(cnt > 0, np.sqrt(tot / np.maximum(cnt, 1)), 0.0)


def resolutions(priority: np.ndarray, tile: int = TILE) -> np.ndarray:
    """Samples per tile edge: 2·ceil(priority·tile/2), between 2 and tile (tile itself if it is odd or below 2)."""
    n = 2 * np.ceil(np.asarray(priority, np.float64) * tile / 2 - 1e-9).astype(np.int64)
    return np.clip(n, min(2, tile), tile)


def plan(res: np.ndarray, width: int, height: int, tile: int = TILE) -> ScreenPlan:
    """The rays of every tile at its resolution (image positions), a tile's n x n rays row by row and together;
    the tiles of one resolution follow each other in C order (all in C order when they share one)."""
    res = np.asarray(res, np.int64)
    offsets = np.zeros(res.shape, np.int64)
    parts, k = [], 0
    for n in np.unique(res):
        ts = np.argwhere(res == n)  # (m, 2) tile rows and columns, C order
        offsets[ts[:, 0], ts[:, 1]] = k + np.arange(len(ts)) * n * n
        k += len(ts) * n * n
        c = (np.arange(n) + 0.5) * (tile / n)
        yy, xx = np.meshgrid(c, c, indexing="ij")  # one tile's rays, row by row
        parts.append(np.stack([ts[:, 1, None] * tile + xx.ravel(), ts[:, 0, None] * tile + yy.ravel()], -1).reshape(-1, 2))
    pos = np.concatenate(parts).astype(np.float32) if parts else np.zeros((0, 2), np.float32)
    return ScreenPlan(res, tile, width, height, np.ascontiguousarray(pos), offsets)


def _nearest_tile(sp: ScreenPlan, samples: np.ndarray, ty: np.ndarray, tx: np.ndarray, py: np.ndarray,
                  px: np.ndarray) -> np.ndarray:
    """φ_b(p): bilinear in tile (ty, tx)'s samples at tile coordinates (py, px), clamped to its sample hull."""
    n = sp.res[ty, tx].astype(np.float64)
    ly = np.clip((py - ty) * n - 0.5, 0.0, n - 1)
    lx = np.clip((px - tx) * n - 0.5, 0.0, n - 1)
    y0, x0 = np.floor(ly).astype(np.int64), np.floor(lx).astype(np.int64)
    ni = n.astype(np.int64)
    y1, x1 = np.minimum(y0 + 1, ni - 1), np.minimum(x0 + 1, ni - 1)
    wy, wx = (ly - y0)[:, None], (lx - x0)[:, None]
    base = sp.offsets[ty, tx]
    at = lambda yi, xi: samples[base + yi * ni + xi]  # noqa: E731
    return (at(y0, x0) * (1 - wx) + at(y0, x1) * wx) * (1 - wy) + (at(y1, x0) * (1 - wx) + at(y1, x1) * wx) * wy


def reconstruct(sp: ScreenPlan, samples: np.ndarray, at: np.ndarray | None = None) -> np.ndarray:
    """Intertile interpolation of the rays' RGBA `samples` (N, 4), float64: at the pixel centres ((H, W, 4)) or,
    `at` given, at image positions (M, 2) as (x, y) in pixels ((M, 4))."""
    samples = np.asarray(samples, np.float64).reshape(-1, samples.shape[-1])
    if at is None and (sp.res == sp.tile).all():  # every tile at full resolution: its rays are the pixels' own
        th, tw = sp.res.shape
        t = sp.tile
        img = samples.reshape(th, tw, t, t, -1).transpose(0, 2, 1, 3, 4).reshape(th * t, tw * t, -1)
        return img[: sp.height, : sp.width]
    if at is None:
        yy, xx = np.mgrid[: sp.height, : sp.width]
        pts = np.stack([xx.ravel() + 0.5, yy.ravel() + 0.5], -1).astype(np.float64)
    else:
        pts = np.asarray(at, np.float64)
    th, tw = sp.res.shape
    px, py = pts[:, 0] / sp.tile, pts[:, 1] / sp.tile
    cx, cy = np.floor(px + 0.5), np.floor(py + 0.5)
    xs, ys = px - cx, py - cy
    T = [np.clip(cx - 1 + s, 0, tw - 1).astype(np.int64) for s in (0, 1)]
    S = [np.clip(cy - 1 + s, 0, th - 1).astype(np.int64) for s in (0, 1)]
    half = 0.5 / sp.res.astype(np.float64)

    def edge(x: np.ndarray, hl: np.ndarray, hu: np.ndarray) -> np.ndarray:
        return np.clip((x + hl) / (hl + hu), 0.0, 1.0)

    acc = np.zeros((len(pts), samples.shape[1]))
    wsum = np.zeros(len(pts))
    for sy in (0, 1):
        for sx in (0, 1):
            ty, tx = S[sy], T[sx]
            # x-edge of this tile's row (sy): between (sy, 0) and (sy, 1); y-edge of its column (sx)
            ex = edge(xs, half[ty, T[0]], half[ty, T[1]])
            ey = edge(ys, half[S[0], tx], half[S[1], tx])
            w = (ex if sx else 1 - ex) * (ey if sy else 1 - ey)
            live = w > 0
            if live.any():
                acc[live] += w[live, None] * _nearest_tile(sp, samples, ty[live], tx[live], py[live], px[live])
                wsum[live] += w[live]
    out = acc / wsum[:, None]
    return out.reshape(sp.height, sp.width, -1) if at is None else out
