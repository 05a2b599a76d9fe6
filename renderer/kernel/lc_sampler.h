/* lc_sampler.h: the sampler, the first of the kernel's pieces (sampler -> interval iterator (lc_walk.h) ->
 * classifier (lc_classify.h) -> integrator (lc_integrator.h)).
 *
 * LcSampler holds everything one ray reads the scalar field through; which field is a build option:
 *   LC_SAMPLER_FULL   level 0 from a plain buffer of lc_voxel (lc_common.h: lc_sample), with LC_PASSES the
 *                     sub-volume of one pass (lc_sample_pass below);
 *   LC_SAMPLER_ATLAS  the multiresolution field from the brick atlas through the block index map (lc_atlas.h), with
 *                     LC_INTERP_NB or LC_INTERP_II.
 * lc_sampler_at(s, q) is the field at voxel coordinates q anywhere: (value, standard deviation of the level-0
 * values behind it; 0 at level 0 and without LC_DIST). The walk tells the sampler which cell its samples lie in
 * (lc_sampler_enter: the atlas sets that block's brick up once, lc_blk_cell) and lc_sampler_in_cell(s, q) samples
 * there; both give the same values (lc_atlas.h: up to which of two blocks a sample on their common face goes to).
 */
#ifndef LC_SAMPLER_H
#define LC_SAMPLER_H
#include "lc_common.h"
#ifdef LC_SAMPLER_ATLAS
#include "lc_atlas.h"
#endif

typedef struct LcSampler {
    __global const lc_voxel* vol;
    int4 dims;   /* level 0's voxels */
    float3 qmax; /* dims - 1: the last voxel centre */
#ifdef LC_SAMPLER_ATLAS
    __global const lc_sig* sig;
    __global const ulong* imap;
    LcAtlasGeom geom;
    LcBlk blk;   /* the cell the walk is in (n = 0: none, the general sampler) */
    LcHood hood; /* the interblock neighbourhood last set up (lc_atlas.h) */
#endif
#if defined(LC_PASSES) && defined(LC_SAMPLER_FULL)
    int4 pdims; /* the pass's sub-volume: its extent, last voxel centre and first voxel (x, y, z) in level 0 */
    float3 pmax, poff;
#endif
} LcSampler;

static inline LcSampler lc_sampler_make(__constant const LcParams* P, __global const lc_voxel* vol,
                                        __global const lc_sig* sig, __global const ulong* imap) {
    LcSampler s;
    s.vol = vol;
    s.dims = P->dims;
    s.qmax = convert_float3(s.dims.xyz - 1);
#ifdef LC_SAMPLER_ATLAS
    s.sig = sig;
    s.imap = imap;
    s.geom.gx = P->grid.x;
    s.geom.gy = P->grid.y;
    s.geom.gz = P->grid.z;
    s.geom.B = (float)P->grid.w;
    s.blk.n = 0;
    s.blk.off = 0;
    s.blk.s = 1.0f;
    s.blk.lo = (float3)(0.0f);
    s.blk.hi = (float3)(-1.0f);
    s.blk.c = (float3)(0.0f);
    s.blk.wlo = s.blk.lo;
    s.blk.whi = s.blk.hi;
    s.blk.coarse = 0;
    s.blk.bx = s.blk.by = s.blk.bz = 0;
    s.blk.ho = 0.5f;
    s.blk.ent = 0UL;
    s.blk.side = -1; /* no block: nothing for lc_blk_ready to narrow (a walk that enters no cell keeps it) */
    s.hood.cx = -1;
#endif
#if defined(LC_PASSES) && defined(LC_SAMPLER_FULL)
    s.pdims = P->pass_dims;
    s.pmax = convert_float3(s.pdims.xyz - 1);
    s.poff = convert_float3(P->pass_off.xyz);
#endif
    return s;
}

#if defined(LC_PASSES) && defined(LC_SAMPLER_FULL)
/* The full sampler on a pass's sub-volume: q clamped to the whole volume (as lc_sample does), then moved into the
 * sub-volume, which holds every voxel an owned sample's stencil reads (exact: the offset is an integer and q is far
 * below 2^24, so the fractions do not change). The second clamp only guards memory. */
static inline float lc_sample_pass(__global const lc_voxel* vol, const int4 pdims, const float3 pmax, const float3 qmax,
                                   const float3 poff, float3 q) {
    q.x = q.x > 0.0f ? (q.x < qmax.x ? q.x : qmax.x) : 0.0f;
    q.y = q.y > 0.0f ? (q.y < qmax.y ? q.y : qmax.y) : 0.0f;
    q.z = q.z > 0.0f ? (q.z < qmax.z ? q.z : qmax.z) : 0.0f;
    return lc_sample(vol, pdims, pmax, q - poff);
}
#endif

/* the field at q */
static LC_HOT float2 lc_sampler_at(LcSampler* s, const float3 q) {
#if defined(LC_SAMPLER_ATLAS)
    return lc_sample_atlas_h(s->vol, s->sig, s->imap, s->geom, &s->hood, q);
#elif defined(LC_PASSES)
    return (float2)(lc_sample_pass(s->vol, s->pdims, s->pmax, s->qmax, s->poff, q), 0.0f);
#else
    return (float2)(lc_sample(s->vol, s->dims, s->qmax, q), 0.0f);
#endif
}

/* The central differences of the field for shading gradients (lc_shade.h) at q: x, y, z, the samples ahead minus
 * those behind, one level-0 voxel away. On the atlas that field is the interblock one whatever the interpolation,
 * so that a normal near a face between blocks takes both blocks' data (eq. 3.6 is C0 across level changes) instead
 * of the difference between one block's clamped samples and the next block's. Each of the six points through the
 * block the walk is in: a read of its brick inside eq. 3.6's window, two NB samples in the blend zone of one face
 * (lc_face_blend), four by an edge and eight by a corner, or anywhere outside the walk's blocks, from the ray's
 * interblock neighbourhood (lc_hood_zone). */
static LC_HOT float3 lc_sampler_diff(LcSampler* s, const float3 q) {
#if defined(LC_SAMPLER_ATLAS)
    lc_blk_ready(s->imap, s->geom, &s->blk);
    float3 d = (float3)(0.0f);
#pragma unroll 1
    for (int k = 0; k < 6; ++k) {
        const float o = (k & 1) ? -1.0f : 1.0f;
        const int a = k >> 1;
        const float3 e = (float3)(a == 0 ? o : 0.0f, a == 1 ? o : 0.0f, a == 2 ? o : 0.0f);
        const LcBlk* b = &s->blk;
        const float3 l = (q + e) * b->s + b->c;
        const int f = lc_blk_out(b, l);
        float v;
        if (b->n && (f & (f - 1)) == 0) {
            /* inside the window l lies in [-1, n] (a level-0 octant's apron) or [0, n - 1]; by one face the own sample
             * is eq. 3.5's, [0, n - 1], blended with the neighbour's */
            const float lo = f ? 0.0f : -1.0f, hi = (float)(f ? b->n - 1 : b->n);
            v = lc_brick(s->vol, s->sig, b->off, b->n, b->coarse, l.x > lo ? (l.x < hi ? l.x : hi) : lo,
                         l.y > lo ? (l.y < hi ? l.y : hi) : lo, l.z > lo ? (l.z < hi ? l.z : hi) : lo).x;
            if (f)
                v = lc_face_blend(s->vol, s->sig, s->imap, s->geom, (float2)(v, 0.0f), b->ho, b->bx, b->by, b->bz, f == 1,
                                  f == 2, ((f == 1 ? l.x : (f == 2 ? l.y : l.z)) + 0.5f) / b->s, q + e, 1).x;
        } else v = lc_hood_zone(s->vol, s->sig, s->imap, s->geom, &s->hood, q + e, b->n ? f : 7);
        d += e * v; /* + the sample ahead, - the one behind, on axis a */
    }
    return d;
#else
    return (float3)(lc_sampler_at(s, q + (float3)(1.0f, 0.0f, 0.0f)).x - lc_sampler_at(s, q - (float3)(1.0f, 0.0f, 0.0f)).x,
                    lc_sampler_at(s, q + (float3)(0.0f, 1.0f, 0.0f)).x - lc_sampler_at(s, q - (float3)(0.0f, 1.0f, 0.0f)).x,
                    lc_sampler_at(s, q + (float3)(0.0f, 0.0f, 1.0f)).x - lc_sampler_at(s, q - (float3)(0.0f, 0.0f, 1.0f)).x);
#endif
}

/* the walk's samples lie in cell (x, y, z) of its grid, cell.w cells per block edge (0: in no cell of the block
 * grid, the general sampler) */
static LC_HOT void lc_sampler_enter(LcSampler* s, const int4 cell) {
#ifdef LC_SAMPLER_ATLAS
    if (cell.w) s->blk = lc_blk_cell(s->imap, s->geom, cell.x, cell.y, cell.z, cell.w);
    else {
        s->blk.n = 0;
        s->blk.side = -1;
    }
#endif
}

/* the field at q, inside the cell last entered */
static LC_HOT float2 lc_sampler_in_cell(LcSampler* s, const float3 q) {
#ifdef LC_SAMPLER_ATLAS
    return lc_sample_blk(s->vol, s->sig, s->imap, s->geom, s->blk, &s->hood, q);
#else
    return lc_sampler_at(s, q);
#endif
}

#endif
