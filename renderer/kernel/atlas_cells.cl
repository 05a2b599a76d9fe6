/* atlas_cells.cl: what the multiresolution field can take inside each half-block cell, for empty-space skipping on
 * the brick atlas (renderer/data/atlas.py: atlas_cells), computed where the atlas already is.
 *
 * Half-block cell h (grid 2G, edge C = B/2) covers voxel coordinates [h C - 1/2, (h + 1) C - 1/2) and lies in block
 * h >> 1 and in one interblock neighbourhood, the blocks c - 1 and c per axis, c = (h + 1) >> 1 (lc_atlas.h). Every
 * sample there is a convex combination of eq. 3.5 samples of those blocks (LC_INTERP_II: brick coordinates clamped
 * to [0, n - 1]; LC_INTERP_NB: the own block alone, clamped to [0, n - 1], or [-1, n] in a level-0 brick's apron),
 * each a trilinear combination of its brick's samples around the clamped brick coordinate. So the values any sample
 * of the cell takes lie in [min, max] of the brick samples those coordinates reach, and its standard deviation
 * (LC_DIST) is at most their largest one (level 0 bricks: none, 0). (II in a level-0 octant reads the apron, whose
 * samples are those of the neighbours that the loop over the neighbourhood reaches.)
 *
 * Per cell of the grid LC_CPB G (below): out_min/out_max the extrema of the values (NaN ignored; no finite value, or
 * the own block not loaded: NaN, nothing to see), out_sd the largest deviation in the sig buffer's units; over a box
 * of cells (lc_atlas_cells) or over a list of cells (lc_atlas_cells_at). */
#include "lc_common.h"
#include "lc_atlas.h"

/* LC_CPB cells per block edge: 2, the half-block cells above; 4, quarter-block cells (the octants of the half-block
 * cells, for the adaptive walk's octant masks: renderer/walk/info.py), each inside one half-block cell and so in its
 * interblock neighbourhood */
#ifndef LC_CPB
#define LC_CPB 2
#endif

/* brick sample index range [i0, i1] that brick coordinates of the voxel interval [a, b] reach, clamped to
 * [-ext, n - 1 + ext] (ext 1: nearest block in a level-0 brick's apron), trilinear; indices in a brick stored
 * `shift` samples into its allocation (1: a level-0 brick inside its apron) */
static inline int2 lc_reach(const float a, const float b, const float lo_face, const float s, const int n,
                            const int ext, const int shift) {
    const float lo = -(float)ext, hi = (float)(n - 1 + ext);
    float la = (a + 0.5f - lo_face) * s - 0.5f, lb = (b + 0.5f - lo_face) * s - 0.5f;
    la = la > lo ? (la < hi ? la : hi) : lo;
    lb = lb > lo ? (lb < hi ? lb : hi) : lo;
    const int i0 = (int)(la + (float)shift);
    int i1 = (int)ceil(lb + (float)shift);
    i1 = i1 < n - 1 + ext + shift ? i1 : n - 1 + ext + shift;
    return (int2)(i0, i1);
}

/* the bounds of cell (x, y, z) of the grid LC_CPB G: (min, max, largest deviation) */
static float3 lc_cell_bounds(__global const lc_voxel* atlas, __global const lc_sig* sig, __global const ulong* imap,
                             const int4 grid, const int x, const int y, const int z) {
    LcAtlasGeom g;
    g.gx = grid.x; g.gy = grid.y; g.gz = grid.z; g.B = (float)grid.w;
    /* eps: samples assigned to the cell within rounding of its faces */
    const float C = g.B / (float)LC_CPB, eps = 1e-3f;
    const float3 a = (float3)((float)x * C - 0.5f - eps, (float)y * C - 0.5f - eps, (float)z * C - 0.5f - eps);
    const float3 b = a + (C + 2.0f * eps);
    float mn = INFINITY, mx = -INFINITY, sd = 0.0f;
    if (lc_imap(imap, g, x / LC_CPB, y / LC_CPB, z / LC_CPB)) {
#ifdef LC_INTERP_II
        const int hx = x / (LC_CPB / 2), hy = y / (LC_CPB / 2), hz = z / (LC_CPB / 2); /* the half-block cell */
        const int cx = (hx + 1) >> 1, cy = (hy + 1) >> 1, cz = (hz + 1) >> 1;
        const int x0 = max(cx - 1, 0), x1 = min(cx, g.gx - 1), y0 = max(cy - 1, 0), y1 = min(cy, g.gy - 1);
        const int z0 = max(cz - 1, 0), z1 = min(cz, g.gz - 1);
#else
        const int x0 = x / LC_CPB, x1 = x0, y0 = y / LC_CPB, y1 = y0, z0 = z / LC_CPB, z1 = z0;
#endif
        for (int bz = z0; bz <= z1; ++bz)
            for (int by = y0; by <= y1; ++by)
                for (int bx = x0; bx <= x1; ++bx) {
                    const ulong ent = lc_imap(imap, g, bx, by, bz);
                    if (!ent) continue; /* a missing neighbour weighs 0 */
                    const int lvl = (int)(ent & 15UL) - 1, n = (int)g.B >> lvl;
                    const float s = 1.0f / (float)(1 << lvl);
                    const ulong off = ent >> 16;
                    const int pad = lvl == 0, m = n + 2 * pad; /* a level-0 brick sits inside its apron */
#ifdef LC_INTERP_II
                    const int ext = 0; /* eq. 3.5's samples */
#else
                    const int ext = pad;
#endif
                    const int2 rx = lc_reach(a.x, b.x, (float)bx * g.B, s, n, ext, pad);
                    const int2 ry = lc_reach(a.y, b.y, (float)by * g.B, s, n, ext, pad);
                    const int2 rz = lc_reach(a.z, b.z, (float)bz * g.B, s, n, ext, pad);
                    for (int k = rz.x; k <= rz.y; ++k)
                        for (int j = ry.x; j <= ry.y; ++j) {
                            const ulong row = off + ((ulong)k * (ulong)m + (ulong)j) * (ulong)m;
                            for (int i = rx.x; i <= rx.y; ++i) {
#if defined(LC_DIST) && defined(LC_SIG_PACKED) /* coarse bricks live in the deviations' buffer alone */
                                const float v = lvl > 0 ? LC_SIG_VALUE(sig[row + (ulong)i]) : (float)atlas[row + (ulong)i];
#else
                                const float v = atlas[row + (ulong)i];
#endif
                                if (v == v) { mn = v < mn ? v : mn; mx = v > mx ? v : mx; }
#ifdef LC_DIST
                                if (lvl > 0) {
                                    const float d = LC_SIG_DEV(sig[row + (ulong)i]);
                                    sd = d > sd ? d : sd;
                                }
#endif
                            }
                        }
                }
    }
    return (float3)(mn <= mx ? mn : NAN, mn <= mx ? mx : NAN, sd);
}

/* the cells [lo, hi) of the grid (x, y, z), written in C order over that box */
__kernel void lc_atlas_cells(__global const lc_voxel* atlas, __global const lc_sig* sig, __global const ulong* imap,
                             const int4 grid, const int4 lo, const int4 hi, __global float* out_min,
                             __global float* out_max, __global float* out_sd) {
    const int x = lo.x + get_global_id(0), y = lo.y + get_global_id(1), z = lo.z + get_global_id(2);
    if (x >= hi.x || y >= hi.y || z >= hi.z) return;
    const float3 r = lc_cell_bounds(atlas, sig, imap, grid, x, y, z);
    const uint o = ((uint)(z - lo.z) * (uint)(hi.y - lo.y) + (uint)(y - lo.y)) * (uint)(hi.x - lo.x) + (uint)(x - lo.x);
    out_min[o] = r.x;
    out_max[o] = r.y;
    out_sd[o] = r.z;
}

/* the `n` cells at `cells` (x, y, z of the grid LC_CPB G), written in the list's order (renderer/data/atlas_cells.py:
 * an atlas built from the last one, the cells a new selection's change of levels can reach) */
__kernel void lc_atlas_cells_at(__global const lc_voxel* atlas, __global const lc_sig* sig, __global const ulong* imap,
                                const int4 grid, __global const int4* cells, const int n, __global float* out_min,
                                __global float* out_max, __global float* out_sd) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const int4 c = cells[i];
    const float3 r = lc_cell_bounds(atlas, sig, imap, grid, c.x, c.y, c.z);
    out_min[i] = r.x;
    out_max[i] = r.y;
    out_sd[i] = r.z;
}
