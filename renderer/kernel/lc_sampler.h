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
    s.blk.glo = s.blk.lo;
    s.blk.ghi = s.blk.hi;
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

/* the field at q for shading gradients (lc_shade.h): the atlas's interblock field whatever the interpolation, so
 * that a normal near a face between blocks takes both blocks' data (eq. 3.6 is C0 across level changes) instead
 * of the difference between one block's clamped samples and the next block's */
static LC_COLD float lc_sampler_grad_at(LcSampler* s, const float3 q) {
#if defined(LC_SAMPLER_ATLAS)
    return lc_sample_ii_h(s->vol, s->sig, s->imap, s->geom, &s->hood, q).x;
#else
    return lc_sampler_at(s, q).x;
#endif
}

/* The central differences of lc_sampler_grad_at at q (x, y, z: the samples ahead minus those behind, one level-0
 * voxel away) where that is cheaper than six samples: where the stencil lies in the fast window of the block the walk
 * is in (there the interblock field is that block's own trilinear field: six reads of its brick, no index map), or
 * else in one interblock cell (lc_hood_diff); 0 where neither holds (the caller samples six times). */
static LC_HOT int lc_sampler_diff(LcSampler* s, const float3 q, float3* d) {
#if defined(LC_SAMPLER_ATLAS)
    const LcBlk* b = &s->blk;
    const float3 l = q * b->s + b->c;
    if (l.x >= b->glo.x && l.x <= b->ghi.x && l.y >= b->glo.y && l.y <= b->ghi.y && l.z >= b->glo.z &&
        l.z <= b->ghi.z) {
        float3 g = (float3)(0.0f);
#pragma unroll 1
        for (int k = 0; k < 6; ++k) {
            const float o = (k & 1) ? -1.0f : 1.0f;
            const int a = k >> 1;
            const float3 e = (float3)(a == 0 ? o : 0.0f, a == 1 ? o : 0.0f, a == 2 ? o : 0.0f);
            const float3 m = l + e * b->s; /* one level-0 voxel in brick coordinates */
            g += e * lc_brick(s->vol, s->sig, b->off, b->n, b->coarse, m.x, m.y, m.z).x;
        }
        *d = g;
        return 1;
    }
    const LcAtlasGeom g = s->geom;
    /* q's interblock cell (corner c, q >= -1/2 in the box: (int) is floor) and q's coordinate in it */
    const float3 p = (q + 0.5f) * (1.0f / g.B);
    const int cx = (int)(p.x + 0.5f), cy = (int)(p.y + 0.5f), cz = (int)(p.z + 0.5f);
    const float3 c = q + 0.5f - (float3)((float)cx, (float)cy, (float)cz) * g.B;
    const float hb = 0.5f * g.B - 1.0f; /* the stencil stays in the cell: |c +- 1| within half a block */
    if (!(c.x >= -hb && c.x < hb && c.y >= -hb && c.y < hb && c.z >= -hb && c.z < hb)) return 0;
    if (cx != s->hood.cx || cy != s->hood.cy || cz != s->hood.cz) lc_hood(&s->hood, s->imap, g, cx, cy, cz);
    *d = lc_hood_diff(s->vol, s->sig, g, &s->hood, q);
    return 1;
#else
    d->x = lc_sampler_at(s, q + (float3)(1.0f, 0.0f, 0.0f)).x - lc_sampler_at(s, q - (float3)(1.0f, 0.0f, 0.0f)).x;
    d->y = lc_sampler_at(s, q + (float3)(0.0f, 1.0f, 0.0f)).x - lc_sampler_at(s, q - (float3)(0.0f, 1.0f, 0.0f)).x;
    d->z = lc_sampler_at(s, q + (float3)(0.0f, 0.0f, 1.0f)).x - lc_sampler_at(s, q - (float3)(0.0f, 0.0f, 1.0f)).x;
    return 1;
#endif
}

/* the walk's samples lie in cell (x, y, z) of its grid, cell.w cells per block edge (0: in no cell of the block
 * grid, the general sampler) */
static LC_HOT void lc_sampler_enter(LcSampler* s, const int4 cell) {
#ifdef LC_SAMPLER_ATLAS
    if (cell.w) s->blk = lc_blk_cell(s->imap, s->geom, cell.x, cell.y, cell.z, cell.w);
    else s->blk.n = 0;
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
