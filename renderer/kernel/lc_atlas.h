/* lc_atlas.h: sampling the multiresolution field (thesis §3.5) from the brick atlas through the block index map.
 *
 * Atlas: one buffer of lc_voxel (the volume's device type, lc_common.h), the selected bricks packed one after
 * another; the brick of a level-k block holds its n = B >> k samples per edge in C order (z, y, x); a level-0 brick
 * sits inside a one-sample apron, m = n + 2 per edge, sample (i, j, l) of the block at ((l + 1) m + j + 1) m + i + 1.
 * The apron sample beyond a face, edge or corner is the neighbouring block's sample there when that block is at
 * level 0 too, else the brick's own nearest sample (renderer/data/aprons.py). Index map: one ulong per block
 * of the grid (C order z, y, x): 0 = block not loaded (level -1: empty space), else
 * (offset << 16) | ((sz + 1) << 12) | ((sy + 1) << 8) | ((sx + 1) << 4) | (level + 1), offset the brick's first
 * element in the atlas (48 bits), s_a the coarsest level among the 3x3 blocks of the block's own slice across axis
 * a (unloaded blocks count as level 0): see the fast path below and lodcast.renderer.data.atlas.pack_index.
 *
 * Coordinates: q = voxel coordinates of level 0 (centres at integers); block coordinates p = (q + 1/2) / B, so
 * block b covers p in [b, b + 1) and its level-k samples sit at intrablock coordinates (i + 1/2) / n. Brick
 * coordinates l = (q + 1/2 - bB)/2^k - 1/2: a position of the block has l in [-1/2, n - 1/2].
 *
 * LC_INTERP_NB, nearest block: eq. 3.5, the intrablock coordinate clamped to [delta, 1 - delta], delta = 1/(2n)
 *   (half a sample of that block), i.e. l clamped to [0, n - 1], then trilinear within the brick; a level-0 brick
 *   clamps to [-1, n] in its apron instead: trilinear interpolation of level 0 across faces between level-0 blocks
 *   (every block at level 0 gives the full-resolution image), eq. 3.5 where the neighbour is coarser or not loaded.
 * LC_INTERP_II, interblock interpolation (eq. 3.6 in 3D): the cell between the eight block centres around p has
 *   corner c = floor(p + 1/2) and interblock coordinate p* = p - c in [-1/2, 1/2) (= frac(p + 1/2) - 1/2); its
 *   blocks are c - 1 + s, s in {0,1}^3 (clamped to the grid: at the volume's faces the cell folds onto the face
 *   blocks, which gives DESIGN's clamp to the edge). phi = sum_b w_b phi_b / sum_b w_b, phi_b the eq. 3.5 sample
 *   of block b at p (lc_nb: l clamped to [0, n - 1], an apron unused), and w_b = prod over the three axes of (e if
 *   s_axis = 1 else 1 - e), e the edge weight of the
 *   edge of the cell's box that leaves b along that axis (the 2D weights of eq. 3.6, one more factor). Edge
 *   weight between a lower block L and an upper block U (half-sample widths delta_L, delta_U):
 *       e(x) = clamp((x + delta_L) / (delta_L + delta_U), 0, 1),   x = the axis' component of p*,
 *   i.e. 0 up to L's last sample, 1 from U's first sample on, linear between the two. Properties (tested in
 *   tests/test_lod_interblock.py): equal levels -> delta_L = delta_U = 1/(2n) and e is the trilinear fraction
 *   between L's last and U's first sample, so phi is trilinear interpolation of that level (which the walk takes
 *   from the apron where all eight blocks are at level 0: lc_blk_cell); C0: every e is
 *   continuous, e = 0 at x = -1/2 and 1 at x = +1/2 for any delta <= 1/2, so on a cell's face only the face's
 *   blocks carry weight, with weights from edges that the neighbouring cell shares; sum_b w_b > 0 (the block
 *   that holds p has w > 0: 1 - e > 0 for x < 0 and e > 0 for x >= 0 on every edge); 1-sample blocks: n = 1,
 *   delta = 1/2, the NB sample is the block's value and e runs from that block's centre to the neighbour's.
 * Missing blocks (index 0): a sample whose own block is missing is NaN (transparent: empty space, exactly what
 *   the selection promises for a block left out); in II a missing neighbour gets weight 0 and the others are
 *   renormalised (its delta taken as half a level-0 sample), so nothing is read from it and no data leaks into it.
 */
#ifndef LC_ATLAS_H
#define LC_ATLAS_H

typedef struct LcAtlasGeom {
    int gx, gy, gz; /* block grid */
    float B;        /* block edge in level-0 voxels */
} LcAtlasGeom;

/* 2^-k for a level k in [0, 126], exactly, from the exponent bits: no division per sample */
static inline float lc_exp2_neg(const int k) { return as_float((uint)(127 - k) << 23); }

/* Trilinear interpolation of the corner values v_zyx (v001: x + 1) with fractions fx, fy, fz. */
static inline float lc_tri8(const float v000, const float v001, const float v010, const float v011, const float v100,
                            const float v101, const float v110, const float v111, const float fx, const float fy,
                            const float fz) {
    const float a0 = v000 + (v001 - v000) * fx, a1 = v010 + (v011 - v010) * fx;
    const float a2 = v100 + (v101 - v100) * fx, a3 = v110 + (v111 - v110) * fx;
    const float b0 = a0 + (a1 - a0) * fy, b1 = a2 + (a3 - a2) * fy;
    return b0 + (b1 - b0) * fz;
}

/* Trilinear within a brick (n samples per edge, first element off; a level-0 brick, !coarse, inside its apron) at
 * brick coordinates l, already in [0, n - 1], or [-1, n] at level 0: (value, standard deviation). The deviations
 * (LC_DIST: distribution classification) live in `sig` (uint16, in units of the volume's std_unit) at the same
 * offsets as the values; only coarse bricks (level >= 1) read them, level 0 has none. */
static LC_HOT float2 lc_brick(__global const lc_voxel* atlas, __global const lc_sig* sig, const ulong off, const int n,
                              const int coarse, const float lx, const float ly, const float lz) {
    const float pad = coarse ? 0.0f : 1.0f;
    const float px = lx + pad, py = ly + pad, pz = lz + pad; /* in the (padded) brick, >= 0 */
    const int x0 = (int)px, y0 = (int)py, z0 = (int)pz;
    const float fx = px - (float)x0, fy = py - (float)y0, fz = pz - (float)z0;
    const ulong m = (ulong)n + (coarse ? 0UL : 2UL);
    const ulong dx = fx > 0.0f ? 1UL : 0UL;
    const ulong dy = fy > 0.0f ? m : 0UL;
    const ulong dz = fz > 0.0f ? m * m : 0UL;
    const ulong b = off + ((ulong)z0 * m + (ulong)y0) * m + (ulong)x0, c = b + dz;
#if defined(LC_DIST) && defined(LC_SIG_PACKED)
    if (coarse) { /* value and deviation from one uint per corner */
        const uint u0 = sig[b], u1 = sig[b + dx], u2 = sig[b + dy], u3 = sig[b + dy + dx];
        const uint u4 = sig[c], u5 = sig[c + dx], u6 = sig[c + dy], u7 = sig[c + dy + dx];
        return (float2)(lc_tri8(LC_SIG_VALUE(u0), LC_SIG_VALUE(u1), LC_SIG_VALUE(u2), LC_SIG_VALUE(u3), LC_SIG_VALUE(u4),
                                LC_SIG_VALUE(u5), LC_SIG_VALUE(u6), LC_SIG_VALUE(u7), fx, fy, fz),
                        lc_tri8(LC_SIG_DEV(u0), LC_SIG_DEV(u1), LC_SIG_DEV(u2), LC_SIG_DEV(u3), LC_SIG_DEV(u4),
                                LC_SIG_DEV(u5), LC_SIG_DEV(u6), LC_SIG_DEV(u7), fx, fy, fz));
    }
#endif
    float2 out = (float2)(lc_tri8((float)atlas[b], (float)atlas[b + dx], (float)atlas[b + dy], (float)atlas[b + dy + dx],
                                  (float)atlas[c], (float)atlas[c + dx], (float)atlas[c + dy], (float)atlas[c + dy + dx],
                                  fx, fy, fz), 0.0f);
#if defined(LC_DIST) && !defined(LC_SIG_PACKED)
    if (coarse)
        out.y = lc_tri8(LC_SIG_DEV(sig[b]), LC_SIG_DEV(sig[b + dx]), LC_SIG_DEV(sig[b + dy]), LC_SIG_DEV(sig[b + dy + dx]),
                        LC_SIG_DEV(sig[c]), LC_SIG_DEV(sig[c + dx]), LC_SIG_DEV(sig[c + dy]),
                        LC_SIG_DEV(sig[c + dy + dx]), fx, fy, fz);
#endif
    return out;
}

/* A sample of a loaded block (entry != 0) at level-0 voxel coordinates q, brick coordinates clamped to [-a, n - 1
 * + a]: a = 0 is eq. 3.5 (interblock's phi_b), a = 1 nearest block through a level-0 brick's apron (`apron`: use
 * it where there is one). */
static LC_HOT float2 lc_nb_in(__global const lc_voxel* atlas, __global const lc_sig* sig, const ulong entry,
                              const int bx, const int by, const int bz, const LcAtlasGeom g, const float3 q,
                              const int apron) {
    const int lvl = (int)(entry & 15UL) - 1;
    const int n = (int)g.B >> lvl;
    const float s = lc_exp2_neg(lvl);
    const float a = apron && lvl == 0 ? 1.0f : 0.0f;
    const float lo = -a, hi = (float)(n - 1) + a;
    float lx = (q.x + 0.5f - (float)bx * g.B) * s - 0.5f;
    float ly = (q.y + 0.5f - (float)by * g.B) * s - 0.5f;
    float lz = (q.z + 0.5f - (float)bz * g.B) * s - 0.5f;
    lx = lx > lo ? (lx < hi ? lx : hi) : lo;
    ly = ly > lo ? (ly < hi ? ly : hi) : lo;
    lz = lz > lo ? (lz < hi ? lz : hi) : lo;
    return lc_brick(atlas, sig, entry >> 16, n, lvl > 0, lx, ly, lz);
}

/* eq. 3.5 */
static LC_HOT float2 lc_nb(__global const lc_voxel* atlas, __global const lc_sig* sig, const ulong entry, const int bx,
                           const int by, const int bz, const LcAtlasGeom g, const float3 q) {
    return lc_nb_in(atlas, sig, entry, bx, by, bz, g, q, 0);
}


/* the index map's entry of block (x, y, z) */
static LC_HOT ulong lc_imap(__global const ulong* imap, const LcAtlasGeom g, const int x, const int y, const int z) {
    return imap[((ulong)z * (ulong)g.gy + (ulong)y) * (ulong)g.gx + (ulong)x];
}

/* half-sample width of the level in the 4-bit field at `shift` of an entry, in level-0 voxels: 2^(level - 1) */
static inline float lc_hw(const ulong entry, const int shift) {
    return 0.5f * (float)(1 << ((int)((entry >> shift) & 15UL) - 1));
}

/* half-sample width of a block in level-0 voxels: 2^(level - 1); missing blocks: 1/2 */
static inline float lc_half(const ulong entry) {
    const int lvl = entry ? (int)(entry & 15UL) - 1 : 0;
    return 0.5f * (float)(1 << lvl);
}

/* edge weight e(x) = clamp((x + hl) / (hl + hu), 0, 1), all in level-0 voxels, with rinv = 1 / (hl + hu): a
 * neighbourhood's reciprocals are taken once (LcHood), and every path multiplies by the same one, so that all give
 * the same bits */
static inline float lc_edge_r(const float x, const float hl, const float rinv) {
    const float e = (x + hl) * rinv;
    return e > 0.0f ? (e < 1.0f ? e : 1.0f) : 0.0f;
}

static inline float lc_edge(const float x, const float hl, const float hu) {
    return lc_edge_r(x, hl, 1.0f / (hl + hu));
}

/* The interblock neighbourhood of the cell with corner c (the eight blocks c - 1 + s around the blocks' common
 * corner, clamped to the grid): their index entries and half-sample widths, and the reciprocal of each edge's
 * (hl + hu). The same for every sample with the same corner (a half-block cell), so a ray keeps the last one it set
 * up (raycast.cl's `hood`) and reuses it while its samples stay there, instead of eight index reads and twelve
 * divisions per sample. */
typedef struct LcHood {
    ulong E[8];
    float h[8];
    float rx[4], ry[4], rz[4]; /* x-edges join s and s|1 (index (sy, sz)), y-edges s and s|2, z-edges s and s|4 */
    int X[2], Y[2], Z[2];
    int cx, cy, cz; /* the corner; cx = -1: none set up */
} LcHood;

static inline void lc_hood(LcHood* hd, __global const ulong* imap, const LcAtlasGeom g, const int cx, const int cy,
                           const int cz) {
    hd->cx = cx; hd->cy = cy; hd->cz = cz;
    hd->X[0] = lc_clampi(cx - 1, g.gx - 1); hd->X[1] = lc_clampi(cx, g.gx - 1);
    hd->Y[0] = lc_clampi(cy - 1, g.gy - 1); hd->Y[1] = lc_clampi(cy, g.gy - 1);
    hd->Z[0] = lc_clampi(cz - 1, g.gz - 1); hd->Z[1] = lc_clampi(cz, g.gz - 1);
    for (int s = 0; s < 8; ++s) {
        hd->E[s] = lc_imap(imap, g, hd->X[s & 1], hd->Y[(s >> 1) & 1], hd->Z[s >> 2]);
        hd->h[s] = lc_half(hd->E[s]);
    }
    for (int k = 0; k < 4; ++k) {
        const int sx = 2 * k, sy = (k & 1) | ((k & 2) << 1), sz = k; /* the lower block of each edge */
        hd->rx[k] = 1.0f / (hd->h[sx] + hd->h[sx | 1]);
        hd->ry[k] = 1.0f / (hd->h[sy] + hd->h[sy | 2]);
        hd->rz[k] = 1.0f / (hd->h[sz] + hd->h[sz | 4]);
    }
}

/* eq. 3.6 at q, a point of the neighbourhood's cell */
static inline float2 lc_hood_sample(__global const lc_voxel* atlas, __global const lc_sig* sig, const LcAtlasGeom g,
                                    const LcHood* hd, const float3 q) {
    /* interblock coordinate in level-0 voxels: distance from the cell's centre (the blocks' common corner) */
    const float xs = q.x + 0.5f - (float)hd->cx * g.B, ys = q.y + 0.5f - (float)hd->cy * g.B;
    const float zs = q.z + 0.5f - (float)hd->cz * g.B;
    float ex[4], ey[4], ez[4];
    for (int k = 0; k < 4; ++k) {
        const int sx = 2 * k, sy = (k & 1) | ((k & 2) << 1), sz = k;
        ex[k] = lc_edge_r(xs, hd->h[sx], hd->rx[k]);
        ey[k] = lc_edge_r(ys, hd->h[sy], hd->ry[k]);
        ez[k] = lc_edge_r(zs, hd->h[sz], hd->rz[k]);
    }
    float wsum = 0.0f;
    float2 acc = (float2)(0.0f);
    for (int s = 0; s < 8; ++s) {
        if (!hd->E[s]) continue;
        const int sx = s & 1, sy = (s >> 1) & 1, sz = s >> 2;
        const float fx = ex[s >> 1];      /* x-edge index: (sy, sz) */
        const float fy = ey[sx + 2 * sz]; /* y-edge index: (sx, sz) */
        const float fz = ez[sx + 2 * sy]; /* z-edge index: (sx, sy) */
        const float w = (sx ? fx : 1.0f - fx) * (sy ? fy : 1.0f - fy) * (sz ? fz : 1.0f - fz);
        if (w > 0.0f) {
            acc += w * lc_nb(atlas, sig, hd->E[s], hd->X[sx], hd->Y[sy], hd->Z[sz], g, q);
            wsum += w;
        }
    }
    return acc / wsum;
}

/* eq. 3.6 at q through the neighbourhood of q's cell, set up unless it is the last one (q + 1/2 > -B/2: (int) is
 * floor) */
static LC_HOT float2 lc_hood_at(__global const lc_voxel* atlas, __global const lc_sig* sig, __global const ulong* imap,
                                const LcAtlasGeom g, LcHood* hd, const float3 q) {
    const float3 p = (q + 0.5f) * (1.0f / g.B);
    const int cx = (int)(p.x + 0.5f), cy = (int)(p.y + 0.5f), cz = (int)(p.z + 0.5f);
    if (cx != hd->cx || cy != hd->cy || cz != hd->cz) lc_hood(hd, imap, g, cx, cy, cz);
    return lc_hood_sample(atlas, sig, g, hd, q);
}

/* A sample of block (bx, by, bz) (NB sample a, half-sample width ho) in the blend zone of one face only, along x
 * (in_x), y (in_y) or else z, o level-0 voxels from the block's lower face on that axis. Every block of the cell but
 * the own one and its neighbour across that face has weight 0 (the fast path's argument, below), and these two take
 * (1 - e, e) of the face's edge weight (the other axes' factors saturate to 1 for both): two NB samples instead of
 * the cell's eight. That holds up to the neighbour's centre, so q may lie beyond the face (a shading gradient's
 * stencil, `beyond`: there q belongs to the neighbour, and a missing neighbour makes it NaN, as lc_sample_atlas_h
 * gives it). */
static LC_HOT float2 lc_face_blend(__global const lc_voxel* atlas, __global const lc_sig* sig, __global const ulong* imap,
                                   const LcAtlasGeom g, const float2 a, const float ho, const int bx, const int by,
                                   const int bz, const int in_x, const int in_y, const float o, const float3 q,
                                   const int beyond) {
    const int up = o > 0.5f * g.B; /* the face above the own block along that axis */
    const int d = up ? 1 : -1;
    const int nx = bx + (in_x ? d : 0), ny = by + (in_y ? d : 0), nz = bz + (in_x | in_y ? 0 : d);
    if (nx < 0 || ny < 0 || nz < 0 || nx >= g.gx || ny >= g.gy || nz >= g.gz) return a; /* the cell folds onto own */
    const ulong nb = lc_imap(imap, g, nx, ny, nz);
    if (!nb) return beyond && (o < 0.0f || o >= g.B) ? (float2)(NAN, 0.0f) : a; /* a missing one weighs 0 */
    const float hn = lc_half(nb);
    /* e: the weight of the upper block of the edge, the interblock coordinate measured from the face */
    const float w = up ? lc_edge(o - g.B, ho, hn) : 1.0f - lc_edge(o, hn, ho);
    const float2 v = lc_nb(atlas, sig, nb, nx, ny, nz, g, q);
    return a + (v - a) * w;
}

/* eq. 3.6 at q in block (bx, by, bz) (index entry own != 0), through the interior fast path (the thesis' II two-pass
 * idea: NB inside the sample boundaries) and the one-face blend where they apply. A block b other than the own one
 * differs from it along some axis a; its weight has the factor of the a-edge joining b to the block b' of the cell
 * that shares the own block's a-coordinate, and that factor is 0 once the sample is at least b''s half-sample
 * width from the a-face (e = 0 for x <= -delta_L, 1 for x >= delta_U, the side of b' being the own side). b' lies
 * in the own block's slice across a, so at least hm_a (the largest half-sample width of that 3x3 slice) from both
 * a-faces on every axis, only the own block carries weight and phi is its NB sample. Nearest-block builds take
 * their shading gradients from it (lc_shade.h), so that normals across a level change come from both blocks. */
static LC_HOT float2 lc_sample_ii(__global const lc_voxel* atlas, __global const lc_sig* sig,
                                  __global const ulong* imap, const LcAtlasGeom g, LcHood* hd, const ulong own,
                                  const int bx, const int by, const int bz, const float3 q) {
    const float hx = lc_hw(own, 4), hy = lc_hw(own, 8), hz = lc_hw(own, 12);
    const float ox = q.x + 0.5f - (float)bx * g.B, oy = q.y + 0.5f - (float)by * g.B;
    const float oz = q.z + 0.5f - (float)bz * g.B;
    const int in_x = !(ox >= hx && g.B - ox >= hx), in_y = !(oy >= hy && g.B - oy >= hy);
    const int in_z = !(oz >= hz && g.B - oz >= hz);
    if (!(in_x | in_y | in_z)) return lc_nb(atlas, sig, own, bx, by, bz, g, q);
    if (in_x + in_y + in_z == 1)
        return lc_face_blend(atlas, sig, imap, g, lc_nb(atlas, sig, own, bx, by, bz, g, q), lc_half(own), bx, by, bz,
                             in_x, in_y, in_x ? ox : (in_y ? oy : oz), q, 0);
    return lc_hood_at(atlas, sig, imap, g, hd, q);
}

/* the block of q and its index entry (0: not loaded) */
static LC_HOT ulong lc_own(__global const ulong* imap, const LcAtlasGeom g, const float3 q, int* bx, int* by, int* bz) {
    /* p >= 0 inside the box (up to rounding, where truncation and the clamp agree): (int) is floor, without
     * PoCL's out-of-line floor() */
    const float3 p = (q + 0.5f) * (1.0f / g.B);
    *bx = lc_clampi((int)p.x, g.gx - 1);
    *by = lc_clampi((int)p.y, g.gy - 1);
    *bz = lc_clampi((int)p.z, g.gz - 1);
    return lc_imap(imap, g, *bx, *by, *bz);
}

/* The multiresolution field at q. hd: the last interblock neighbourhood this ray set up (cx = -1: none), reused
 * while the ray's samples stay in it */
static LC_HOT float2 lc_sample_atlas_h(__global const lc_voxel* atlas, __global const lc_sig* sig,
                                       __global const ulong* imap, const LcAtlasGeom g, LcHood* hd, const float3 q) {
    int bx, by, bz;
    const ulong own = lc_own(imap, g, q, &bx, &by, &bz);
    if (!own) return (float2)(NAN, 0.0f);
#ifndef LC_INTERP_II
    return lc_nb_in(atlas, sig, own, bx, by, bz, g, q, 1);
#else
    return lc_sample_ii(atlas, sig, imap, g, hd, own, bx, by, bz, q);
#endif
}

static inline float2 lc_sample_atlas(__global const lc_voxel* atlas, __global const lc_sig* sig,
                                     __global const ulong* imap, const LcAtlasGeom g, const float3 q) {
    LcHood hd;
    hd.cx = -1;
    return lc_sample_atlas_h(atlas, sig, imap, g, &hd, q);
}

/* A block the ray marches through (raycast.cl sets it up once per block/cell of its DDA): brick coordinates are
 * l = q s + c there; NB clamps l to [lo, hi] = [0, n - 1] ([-1, n] at level 0: the apron); eq. 3.6 (II's samples,
 * and every build's shading gradients: lc_sampler.h's lc_sampler_diff) is the brick itself where l lies in the
 * window [wlo, whi] (the interior fast path above: every edge weight saturated, or a level-0 octant's apron), one
 * face's blend in the zone of one face, and the interblock sum elsewhere. n = 0: no block (the general sampler; an
 * empty window).
 * Samples come out as lc_sample_atlas gives them (NB: up to which of two blocks a sample within rounding of their
 * common face is assigned to; II in a level-0 octant: up to float rounding, trilinear interpolation computed once
 * from the apron, once as eq. 3.6's weighted sum). */
typedef struct LcBlk {
    ulong off;
    int n;
    int coarse; /* level >= 1: has standard deviations */
    float s;
    float3 lo, hi;   /* NB's clamp */
    float3 wlo, whi; /* eq. 3.6's window */
    float3 c;
    int bx, by, bz; /* the block */
    float ho;       /* its half-sample width (level-0 voxels) */
    ulong ent;      /* its index entry */
    int side;       /* the window as lc_blk_cell set it for the cell's neighbourhood: the cell's half of the block
                     * per axis (bit a: the upper half), | 8 where it is a level-0 octant's apron, | 16 while it is
                     * still lc_blk's (lc_blk_ready); -1: lc_blk's window, for the whole block */
} LcBlk;

static inline LcBlk lc_blk(__global const ulong* imap, const LcAtlasGeom g, const int bx, const int by, const int bz) {
    LcBlk b;
    const ulong ent = lc_imap(imap, g, bx, by, bz);
    b.n = 0;
    b.coarse = 0;
    b.off = 0;
    b.s = 1.0f; b.lo = (float3)(0.0f); b.hi = (float3)(-1.0f);
    b.c = (float3)(0.0f);
    b.wlo = b.lo; b.whi = b.hi;
    b.ent = ent;
    b.side = -1;
    if (!ent) return b;
    const int lvl = (int)(ent & 15UL) - 1;
    b.off = ent >> 16;
    b.n = (int)g.B >> lvl;
    b.coarse = lvl > 0;
    b.s = lc_exp2_neg(lvl);
    b.c = ((float3)(0.5f) - (float3)((float)bx, (float)by, (float)bz) * g.B) * b.s - 0.5f;
    b.bx = bx; b.by = by; b.bz = bz;
    b.ho = 0.5f / b.s;
    const float3 hm = (float3)(lc_hw(ent, 4), lc_hw(ent, 8), lc_hw(ent, 12));
    b.wlo = hm * b.s - 0.5f;
    b.whi = (float)b.n - 0.5f - hm * b.s;
    b.lo = (float3)(lvl ? 0.0f : -1.0f); /* level 0: the apron */
    b.hi = (float3)((float)(lvl ? b.n - 1 : b.n));
    return b;
}

/* builds that take eq. 3.6 in the walk's cells: interblock's samples, and any build's gradients (lc_shade.h) */
#if defined(LC_INTERP_II) || defined(LC_SHADE) || defined(LC_GRADIENT_OPACITY)
#define LC_II_CELLS
#endif

#ifdef LC_II_CELLS
/* the largest of four (no fmax: PoCL calls builtins out of line) */
static inline float lc_max4(const float a, const float b, const float c, const float d) {
    const float ab = a > b ? a : b, cd = c > d ? c : d;
    return ab > cd ? ab : cd;
}
#endif

/* lc_blk for the samples of cell (x, y, z) of a walk with cpb cells per block edge. With half-block cells (cpb 2)
 * the cell lies in one interblock neighbourhood (its block's octant towards the cell's side on every
 * axis). Where all eight blocks of that neighbourhood are at level 0, phi is trilinear interpolation of level 0,
 * which the padded brick holds for the whole octant (its apron is the neighbours' samples): eq. 3.6's window becomes
 * the apron on the near side. Else on the near side of each axis a the window needs only the
 * half-sample widths of the four blocks of that neighbourhood that share the block's a-coordinate (the argument
 * above, restricted to the cell's own neighbourhood), not the largest of the 3x3 slice: the window widens wherever a
 * coarser block of the slice lies on the far side. The far side keeps lc_blk's bound, so that a point in the window
 * across the block's middle on some axes (a sample rounded into the next cell, a gradient's stencil) is still the
 * own sample: a block of its neighbourhood that differs from the own one across such an axis weighs 0 by the far
 * side's bound on that axis, and the others, which share the own block's coordinate there, lie in this cell's
 * neighbourhood. A point across the middle and outside the window on such an axis is not covered (lc_blk_out).
 * Seven more index reads per cell (lc_blk_narrow), only in builds that take eq. 3.6 (LC_II_CELLS), and in
 * nearest-block builds only in the cells where a gradient is taken. */
#ifdef LC_II_CELLS
static inline void lc_blk_narrow(__global const ulong* imap, const LcAtlasGeom g, LcBlk* b, const int side) {
    const int bx = b->bx, by = b->by, bz = b->bz;
    /* the neighbours towards the cell's side (off the grid: the neighbourhood folds onto the block, and the apron
     * there repeats the brick's edge, as the fold does) */
    const int nx = lc_clampi(bx + (side & 1 ? 1 : -1), g.gx - 1), ny = lc_clampi(by + (side & 2 ? 1 : -1), g.gy - 1);
    const int nz = lc_clampi(bz + (side & 4 ? 1 : -1), g.gz - 1);
    const ulong eX = lc_imap(imap, g, nx, by, bz), eY = lc_imap(imap, g, bx, ny, bz), eZ = lc_imap(imap, g, bx, by, nz);
    const ulong eXY = lc_imap(imap, g, nx, ny, bz), eXZ = lc_imap(imap, g, nx, by, nz), eYZ = lc_imap(imap, g, bx, ny, nz);
    const ulong eXYZ = lc_imap(imap, g, nx, ny, nz);
    if (!b->coarse && (eX & 15UL) == 1UL && (eY & 15UL) == 1UL && (eZ & 15UL) == 1UL && (eXY & 15UL) == 1UL &&
        (eXZ & 15UL) == 1UL && (eYZ & 15UL) == 1UL && (eXYZ & 15UL) == 1UL) { /* all eight at level 0 */
        b->side = side | 8;
        if (side & 1) b->whi.x = (float)b->n; else b->wlo.x = -1.0f;
        if (side & 2) b->whi.y = (float)b->n; else b->wlo.y = -1.0f;
        if (side & 4) b->whi.z = (float)b->n; else b->wlo.z = -1.0f;
        return;
    }
    const float hX = lc_half(eX), hY = lc_half(eY), hZ = lc_half(eZ);
    const float hXY = lc_half(eXY), hXZ = lc_half(eXZ), hYZ = lc_half(eYZ);
    const float3 hm = (float3)(lc_max4(b->ho, hY, hZ, hYZ), lc_max4(b->ho, hX, hZ, hXZ), lc_max4(b->ho, hX, hY, hXY));
    const float3 lo = hm * b->s - 0.5f, hi = (float)b->n - 0.5f - hm * b->s;
    b->side = side;
    if (side & 1) b->whi.x = hi.x; else b->wlo.x = lo.x;
    if (side & 2) b->whi.y = hi.y; else b->wlo.y = lo.y;
    if (side & 4) b->whi.z = hi.z; else b->wlo.z = lo.z;
}
#endif

static inline LcBlk lc_blk_cell(__global const ulong* imap, const LcAtlasGeom g, const int x, const int y,
                                const int z, const int cpb) {
    LcBlk b = lc_blk(imap, g, x / cpb, y / cpb, z / cpb);
#ifdef LC_II_CELLS
    if (cpb != 2 || !b.n) return b;
    const int side = (x & 1) | (y & 1) << 1 | (z & 1) << 2;
#ifdef LC_INTERP_II
    lc_blk_narrow(imap, g, &b, side);
#else
    b.side = side | 16; /* only gradients take eq. 3.6: narrowed where a sample of the cell takes one (lc_blk_ready) */
#endif
#endif
    return b;
}

/* the window of the walk's cell, narrowed if it is not yet */
static LC_HOT void lc_blk_ready(__global const ulong* imap, const LcAtlasGeom g, LcBlk* b) {
#ifdef LC_II_CELLS
    if (b->side >= 16) lc_blk_narrow(imap, g, b, b->side & 7);
#endif
}

/* The axes (bit a: axis a) on which brick coordinate l of block b lies outside eq. 3.6's window: those of a blend
 * zone's sum (lc_face_blend, lc_hood_zone), which needs the other axes' blocks to weigh 0. Where the window is a
 * level-0 octant's apron (there the neighbours weigh, as trilinear interpolation), or where l lies outside it on an
 * axis across the block's middle from the cell that set the window (lc_blk_cell: another neighbourhood), the axes
 * outside lc_blk's window for the whole block instead, the 3x3 slices' bound (exact anywhere in the block). */
static LC_HOT int lc_blk_out(const LcBlk* b, const float3 l) {
    const int f = (l.x >= b->wlo.x && l.x <= b->whi.x ? 0 : 1) | (l.y >= b->wlo.y && l.y <= b->whi.y ? 0 : 2) |
                  (l.z >= b->wlo.z && l.z <= b->whi.z ? 0 : 4);
    if (!f || b->side < 0) return f;
    const float mid = 0.5f * (float)b->n - 0.5f;
    const int across = ((l.x > mid) != (b->side & 1) ? 1 : 0) | ((l.y > mid) != ((b->side >> 1) & 1) ? 2 : 0) |
                       ((l.z > mid) != ((b->side >> 2) & 1) ? 4 : 0);
    if (!(f & across) && !(b->side & 8)) return f;
    const float3 hm = (float3)(lc_hw(b->ent, 4), lc_hw(b->ent, 8), lc_hw(b->ent, 12));
    const float3 lo = hm * b->s - 0.5f, hi = (float)b->n - 0.5f - hm * b->s;
    return (l.x >= lo.x && l.x <= hi.x ? 0 : 1) | (l.y >= lo.y && l.y <= hi.y ? 0 : 2) |
           (l.z >= lo.z && l.z <= hi.z ? 0 : 4);
}

/* Eq. 3.6 at q, up to one level-0 voxel from the walk's block, whose brick coordinate lies outside that block's
 * window on the axes of mask f = lc_blk_out (bit a: axis a) and inside it on the others: through the ray's
 * neighbourhood of q's cell (the walk's cell is one, so it is set up once per cell, with its edges' reciprocals). A
 * block of the cell that differs from q's own on an axis outside f weighs 0 (the fast path's argument: its edge
 * factor there is 0, and the own side's is 1), so only the 2^|f| blocks that differ on f's axes are summed, each
 * with the edge factors of those axes: lc_hood_sample's terms (f = 7: all of them, for a point outside the walk's
 * blocks). NaN where q's own block is missing. Out of line (LC_COLD): inlined into the march it makes the lit
 * nearest-block kernel's first build much longer. */
static LC_COLD float lc_hood_zone(__global const lc_voxel* atlas, __global const lc_sig* sig,
                                  __global const ulong* imap, const LcAtlasGeom g, LcHood* hd, const float3 q,
                                  const int f) {
    const float3 p = (q + 0.5f) * (1.0f / g.B); /* q + 1/2 > -B/2: (int) is floor */
    const int cx = (int)(p.x + 0.5f), cy = (int)(p.y + 0.5f), cz = (int)(p.z + 0.5f);
    if (cx != hd->cx || cy != hd->cy || cz != hd->cz) lc_hood(hd, imap, g, cx, cy, cz);
    const float3 c = q + 0.5f - (float3)((float)cx, (float)cy, (float)cz) * g.B;
    const int own = (c.x >= 0.0f ? 1 : 0) | (c.y >= 0.0f ? 2 : 0) | (c.z >= 0.0f ? 4 : 0);
    if (!hd->E[own]) return NAN;
    float acc = 0.0f, wsum = 0.0f;
#pragma unroll 1
    for (int s = 0; s < 8; ++s) {
        if (((s ^ own) & ~f) || !hd->E[s]) continue;
        const int sx = s & 1, sy = (s >> 1) & 1, sz = s >> 2;
        float w = 1.0f;
        if (f & 1) { /* x-edge index (sy, sz), its lower block s without x */
            const float e = lc_edge_r(c.x, hd->h[s & 6], hd->rx[s >> 1]);
            w *= sx ? e : 1.0f - e;
        }
        if (f & 2) {
            const float e = lc_edge_r(c.y, hd->h[s & 5], hd->ry[sx + 2 * sz]);
            w *= sy ? e : 1.0f - e;
        }
        if (f & 4) {
            const float e = lc_edge_r(c.z, hd->h[s & 3], hd->rz[sx + 2 * sy]);
            w *= sz ? e : 1.0f - e;
        }
        if (w > 0.0f) {
            acc += w * lc_nb(atlas, sig, hd->E[s], hd->X[sx], hd->Y[sy], hd->Z[sz], g, q).x;
            wsum += w;
        }
    }
    return acc / wsum;
}

static LC_HOT float2 lc_sample_blk(__global const lc_voxel* atlas, __global const lc_sig* sig, __global const ulong* imap,
                                   const LcAtlasGeom g, const LcBlk b, LcHood* hd, const float3 q) {
    float3 l = q * b.s + b.c;
#ifdef LC_INTERP_II
    /* the own NB sample always (inside the window it is the answer), the face neighbour's only in a one-face
     * blend zone, the general interblock sum only near an edge or corner: on a SIMD device lanes in the blend
     * zones then add one NB sample to the others' work, not a whole second path */
    const int in_x = !(l.x >= b.wlo.x && l.x <= b.whi.x), in_y = !(l.y >= b.wlo.y && l.y <= b.whi.y);
    const int in_z = !(l.z >= b.wlo.z && l.z <= b.whi.z);
    if (!b.n || in_x + in_y + in_z > 1) return lc_sample_atlas_h(atlas, sig, imap, g, hd, q);
    /* inside the window l lies in [0, n - 1], or in the apron of a level-0 octant, [-1, n]; in a blend zone the
     * own sample is eq. 3.5's, [0, n - 1] */
    const int inside = !(in_x | in_y | in_z);
    const float lo = inside ? -1.0f : 0.0f, hi = inside ? (float)b.n : (float)(b.n - 1);
    const float cx = l.x > lo ? (l.x < hi ? l.x : hi) : lo, cy = l.y > lo ? (l.y < hi ? l.y : hi) : lo;
    const float cz = l.z > lo ? (l.z < hi ? l.z : hi) : lo;
    const float2 a = lc_brick(atlas, sig, b.off, b.n, b.coarse, cx, cy, cz);
    if (inside) return a;
    return lc_face_blend(atlas, sig, imap, g, a, b.ho, b.bx, b.by, b.bz, in_x, in_y,
                         ((in_x ? l.x : (in_y ? l.y : l.z)) + 0.5f) / b.s, q, 0);
#else
    if (!b.n) return lc_sample_atlas_h(atlas, sig, imap, g, hd, q);
    l.x = l.x > b.lo.x ? (l.x < b.hi.x ? l.x : b.hi.x) : b.lo.x;
    l.y = l.y > b.lo.y ? (l.y < b.hi.y ? l.y : b.hi.y) : b.lo.y;
    l.z = l.z > b.lo.z ? (l.z < b.hi.z ? l.z : b.hi.z) : b.lo.z;
    return lc_brick(atlas, sig, b.off, b.n, b.coarse, l.x, l.y, l.z);
#endif
}

#endif
