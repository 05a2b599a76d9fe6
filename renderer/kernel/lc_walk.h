/* lc_walk.h: the interval iterator (after Open VKL's vklIterateInterval and pbrt-v4's DDAMajorantIterator): a
 * ray's walk through the cells of a grid, handing out the runs of samples worth taking.
 *
 * lc_walk_next(w, iv, it) fills iv with the next interval (its whole steps at iv.qa + s iv.dqs for s in
 * [iv.s0, iv.s1), segment code iv.r, then one cut step at iv.qc, code iv.rc, if iv.cut; their cell for the
 * sampler) and returns 1, or returns 0 once the ray has no more; it asks the integrator `it` whether a cell can
 * be skipped (lc_integrator_skips: MIP's extremum so far and dual TF's running integrals change that along the
 * ray). One iterator per walk, chosen by the build:
 *   the lattice walk (default)  the ray's part [t0, t1] inside the box is cut into n = ceil((t1 - t0) / step)
 *       segments of length step (the last one shorter, so the segments add up to t1 - t0 exactly); segment k is
 *       sampled once at fraction u of its length. The samples lie on one lattice per ray whether or not cells are
 *       skipped: skipping changes nothing but which zero-contribution samples are taken. With LC_ESS (or
 *       LC_PASSES) a 3D DDA over the walk's cells (P->ess_grid; cell b covers voxel coordinates
 *       [b B - 1/2, (b + 1) B - 1/2)) skips cells whose info says nothing there can contribute (LC_PASSES: cells of
 *       blocks another pass owns), a run of skipped cells costing its DDA steps only; without, one interval.
 *   LC_ADAPTIVE  adaptive object-space sampling (thesis §3.6.1, see raycast.cl's header) over half-block cells.
 *   LC_ADAPTIVE_NAIVE  (benchmarks) one step of the starting cell's length per interval, not cut at cells.
 * LC_LEAP: space leaping (renderer/walk/leap.py): `leaps` holds planes over the walk's cells, one per octant of
 * ray directions the view's rays go in (octant (sx > 0) | (sy > 0) << 1 | (sz > 0) << 2, its plane named by
 * P->leap_planes, 4 bits per octant, LC_NO_PLANE for none): in an empty cell (adaptive: a skipped level-0 cell)
 * the edge r of the cube of empty cells that starts there and runs forward in that octant's directions; r >= 2:
 * the ray leaves that cube in one step instead of a DDA step per cell. With LC_SAMPLER_FULL (where only the cells
 * decide a skip) a run of cells to sample is found first and handed out as one interval.
 * LC_OCTANTS (adaptive, leap): a sampled cell's info holds the mask of its eight octants (quarter-block cells)
 * where the field can show something (renderer/walk/info.py: octant_masks, bit (z & 1) << 2 | (y & 1) << 1 |
 * (x & 1)); a sample in another octant adds nothing and is not taken (lc_interval_sees).
 */
#ifndef LC_WALK_H
#define LC_WALK_H
#include "lc_integrator.h"

/* 3D DDA over a grid of cells of `cell` voxels each (cell c covers voxel coordinates [c cell - 1/2, (c + 1) cell
 * - 1/2)), for the ray q0 + t dq: the cell (bx, by, bz), the step signs, the ray parameters of the next face
 * crossings and their increments. Shared by the lattice walk's cells and the adaptive walk's. */
typedef struct LcDda {
    int bx, by, bz;
    int sx, sy, sz;
    float tnx, tny, tnz;
    float tdx, tdy, tdz;
} LcDda;

/* the DDA entered at t0, its cell clamped into the nx x ny x nz grid */
static inline LcDda lc_dda_make(const float3 q0, const float3 dq, const float t0, const float cell, const int nx,
                                const int ny, const int nz) {
    LcDda d;
    const float3 g0 = (q0 + 0.5f) / cell, dg = dq / cell;
    const float3 ge = g0 + t0 * dg;
    int bx = (int)floor(ge.x), by = (int)floor(ge.y), bz = (int)floor(ge.z);
    d.bx = bx < 0 ? 0 : (bx >= nx ? nx - 1 : bx);
    d.by = by < 0 ? 0 : (by >= ny ? ny - 1 : by);
    d.bz = bz < 0 ? 0 : (bz >= nz ? nz - 1 : bz);
    d.sx = dg.x > 0.0f ? 1 : (dg.x < 0.0f ? -1 : 0);
    d.sy = dg.y > 0.0f ? 1 : (dg.y < 0.0f ? -1 : 0);
    d.sz = dg.z > 0.0f ? 1 : (dg.z < 0.0f ? -1 : 0);
    d.tnx = d.sx ? ((float)(d.bx + (d.sx > 0)) - g0.x) / dg.x : INFINITY;
    d.tny = d.sy ? ((float)(d.by + (d.sy > 0)) - g0.y) / dg.y : INFINITY;
    d.tnz = d.sz ? ((float)(d.bz + (d.sz > 0)) - g0.z) / dg.z : INFINITY;
    d.tdx = d.sx ? fabs(1.0f / dg.x) : INFINITY;
    d.tdy = d.sy ? fabs(1.0f / dg.y) : INFINITY;
    d.tdz = d.sz ? fabs(1.0f / dg.z) : INFINITY;
    return d;
}

/* when the ray leaves the cell */
static LC_HOT float lc_dda_exit(const LcDda* d) {
    return d->tnx < d->tny ? (d->tnx < d->tnz ? d->tnx : d->tnz) : (d->tny < d->tnz ? d->tny : d->tnz);
}

/* the axis of the face it leaves by */
static LC_HOT int lc_dda_axis(const LcDda* d) {
    return d->tnx <= d->tny && d->tnx <= d->tnz ? 0 : (d->tny <= d->tnz ? 1 : 2);
}

/* into the next cell; whether the coordinate it changed is still inside [0, n) of its axis */
static LC_HOT int lc_dda_step(LcDda* d, const int nx, const int ny, const int nz) {
    if (d->tnx <= d->tny && d->tnx <= d->tnz) {
        d->bx += d->sx;
        d->tnx += d->tdx;
        return d->bx >= 0 && d->bx < nx;
    }
    if (d->tny <= d->tnz) {
        d->by += d->sy;
        d->tny += d->tdy;
        return d->by >= 0 && d->by < ny;
    }
    d->bz += d->sz;
    d->tnz += d->tdz;
    return d->bz >= 0 && d->bz < nz;
}

/* Space leaping: every cell of the cube of r cells (r >= 2) that starts at the DDA's cell and runs forward along
 * the ray's step directions is one the walk would pass alike, so the ray leaves that cube in one step; returns
 * when it crosses the cube's far face, r - 1 cells ahead along the axis it leaves by, the DDA then in the cell it
 * enters there. The crossing times are summed step by step, as the DDA's own steps sum them, so that the leap
 * ends in the state the DDA would reach cell by cell (bit for bit, but for crossings at the very same time as the
 * cube's exit). The exit axis crosses r faces, the others those they cross before; ties go to the axis the DDA's
 * own step would take. */
static LC_HOT float lc_dda_leap(LcDda* d, const int r) {
    float ex = d->tnx, ey = d->tny, ez = d->tnz;
    for (int i = 1; i < r; ++i) {
        ex += d->tdx;
        ey += d->tdy;
        ez += d->tdz;
    }
    const int ax = ex <= ey && ex <= ez ? 0 : (ey <= ez ? 1 : 2);
    const float te = ax == 0 ? ex : (ax == 1 ? ey : ez);
    if (ax == 0) { d->bx += d->sx * r; d->tnx = ex + d->tdx; } else { while (d->tnx < te) { d->bx += d->sx; d->tnx += d->tdx; } }
    if (ax == 1) { d->by += d->sy * r; d->tny = ey + d->tdy; } else { while (d->tny < te) { d->by += d->sy; d->tny += d->tdy; } }
    if (ax == 2) { d->bz += d->sz * r; d->tnz = ez + d->tdz; } else { while (d->tnz < te) { d->bz += d->sz; d->tnz += d->tdz; } }
    return te;
}

#define LC_NO_PLANE 15
/* LC_LEAP: the plane of `leaps` (cells nx x ny x nz) for the octant of directions the DDA's steps go in; NULL where
 * LcParams.leap_planes names none (its rays walk cell by cell) */
static inline __global const uchar* lc_leap_plane(__constant const LcParams* P, __global const uchar* leaps,
                                                  const LcDda* d, const int nx, const int ny, const int nz) {
    const int plane = (int)((P->leap_planes >> (4 * ((d->sx > 0) | (d->sy > 0) << 1 | (d->sz > 0) << 2))) & 15u);
    return plane == LC_NO_PLANE ? 0 : leaps + (ulong)plane * ((ulong)nx * ny * nz);
}

/* The ray o + t d, t in [t0, t1], and the world box [lo, hi] (lc_common.h's slab test): whether they meet, and
 * where the ray leaves the box (*t_end): a pass owns no sample beyond, so its march stops there */
static inline int lc_meets_box(const float3 lo, const float3 hi, const float3 o, const float3 d, const float t0,
                               const float t1, float* t_end) {
    float tn;
    lc_slab(lo, hi, o, d, &tn, t_end);
    return fmax(tn, t0) <= fmin(*t_end, t1);
}

/* The ray's lattice: n segments of the base step from t0, the last one shorter, ending at t1 */
typedef struct LcLattice {
    float t0, t1, dt, inv_dt, u;
    int n, nlast;
    float last, len_last; /* where the last segment starts, its length */
    float r_last;         /* its segment code (lc_classify.h) */
    float3 q0, dq;        /* the ray in voxel coordinates: q0 + t dq */
    float3 qu, dqk;       /* sample k < nlast at qu + k dqk */
} LcLattice;

static inline LcLattice lc_lattice_make(__constant const LcParams* P, const LcMarch* m, const float3 o,
                                        const float t0, const float t1) {
    LcLattice L;
    L.t0 = t0;
    L.t1 = t1;
    L.dt = m->dt;
    L.inv_dt = m->inv_dt;
    L.u = m->u;
    float nf = ceil((t1 - t0) / L.dt);
    nf = nf < 1.0f ? 1.0f : (nf > (float)P->max_samples ? (float)P->max_samples : nf);
    L.n = (int)nf;
    L.nlast = L.n - 1;
    float last = t0 + (float)L.nlast * L.dt;
    L.last = last < t1 ? last : t1;
    L.len_last = t1 - L.last;
#ifdef LC_PRECISE
    L.r_last = L.len_last / L.dt;
#else
    L.r_last = L.len_last * P->inv_unit;
#endif
    L.q0 = (o - P->origin.xyz) * P->inv_spacing.xyz;
    L.dq = m->dq;
    L.qu = L.q0 + (t0 + L.u * L.dt) * L.dq;
    L.dqk = L.dt * L.dq;
    return L;
}

/* the position (ray parameter) of sample k */
static LC_HOT float lc_lattice_pos(const LcLattice* L, const int k) {
    return k < L->nlast ? L->t0 + ((float)k + L->u) * L->dt : L->last + L->u * L->len_last;
}

/* the first sample index >= kk whose position is at or after time tb (n: none) */
static LC_HOT int lc_lattice_first_at(const LcLattice* L, const float tb, const int kk) {
    const float kf = ceil((tb - L->t0) * L->inv_dt - L->u);
    int out = kf < (float)kk ? kk : (kf > (float)L->nlast ? L->nlast : (int)kf);
    while (out > kk && lc_lattice_pos(L, out - 1) >= tb) out--;
    while (out < L->n && lc_lattice_pos(L, out) < tb) out++;
    return out;
}

typedef struct LcInterval {
    float3 qa, dqs; /* whole steps: sample s at qa + s dqs, s in [s0, s1) */
    int s0, s1;
    float r;        /* their segment code (lc_classify.h) */
    int cut;        /* 1: then one cut step at qc, segment code rc */
    float3 qc;
    float rc;
    int4 cell;      /* the cell the samples lie in, for the sampler (lc_sampler_enter) */
    int oct;        /* LC_OCTANTS: its octant mask (255: all), unclamped DDA cell and octants per voxel */
    int ox, oy, oz;
    float oq;
} LcInterval;

/* the octant index of sample position c (voxel coordinates) along one axis of cell b: 0 or 1 inside the cell */
static LC_HOT int lc_octant(const LcInterval* iv, const float c, const int b) { return (int)((c + 0.5f) * iv->oq) - 2 * b; }

/* whether a whole step's sample q lies in an octant of the cell that can show something; one within rounding of a
 * face counts in the octant on the cell's side (whose bounds hold it, atlas_cells.cl) */
static LC_HOT int lc_interval_sees(const LcInterval* iv, const float3 q) {
#ifdef LC_OCTANTS
    return iv->oct == 255 || ((iv->oct >> (lc_clampi(lc_octant(iv, q.z, iv->oz), 1) << 2 |
                                           lc_clampi(lc_octant(iv, q.y, iv->oy), 1) << 1 |
                                           lc_clampi(lc_octant(iv, q.x, iv->ox), 1))) & 1);
#else
    return 1;
#endif
}

/* the same for the cut step, whose sample may lie past the cell's face (LC_LATTICE: a coarse cell's last step ends
 * on the level-0 lattice beyond it), where no octant of this cell bounds it: it is taken there */
static LC_HOT int lc_interval_sees_cut(const LcInterval* iv, const float3 q) {
#ifdef LC_OCTANTS
    return iv->oct == 255 || (uint)lc_octant(iv, q.z, iv->oz) > 1u || (uint)lc_octant(iv, q.y, iv->oy) > 1u ||
           (uint)lc_octant(iv, q.x, iv->ox) > 1u || lc_interval_sees(iv, q);
#else
    return 1;
#endif
}

#ifdef LC_ADAPTIVE
#include "lc_walk_adaptive.h"
#else
#include "lc_walk_lattice.h"
#endif

#endif
