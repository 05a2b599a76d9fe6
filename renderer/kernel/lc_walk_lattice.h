/* lc_walk_lattice.h: the lattice walk (lc_walk.h), the interval iterator of fixed steps: samples on the ray's
 * lattice (LcLattice), with LC_ESS or LC_PASSES only those of the cells a DDA over the walk's cells does not skip. */
#ifndef LC_WALK_LATTICE_H
#define LC_WALK_LATTICE_H

typedef struct LcWalk {
    LcLattice L;
    int k;            /* the next sample to hand out */
    float t_pass_end; /* LC_PASSES: where the ray leaves the pass's region (nothing of this pass's beyond) */
#if defined(LC_ESS) || defined(LC_PASSES)
    LcDda d;
    int gx, gy, gz;   /* the walk's cells */
    int inside;       /* the DDA's cell is in the grid (rounding can leave samples beyond its last cell) */
    float t_skip;     /* a run of skipped cells just left ends here (-inf: none): its first sample after is found once */
    int cpb;          /* walk cells per block edge */
    __global const float* info;
#ifdef LC_PASSES
    __global const uchar* own; /* one byte per block: this pass owns it */
    int bgx, bgy;
    int owned;                 /* the last block's owner is this pass (samples past the grid go with it) */
#endif
#ifdef LC_LEAP
    __global const uchar* leap; /* the ray's octant plane (0: none) */
#endif
#endif
} LcWalk;

static inline LcWalk lc_walk_make(__constant const LcParams* P, const LcMarch* m, const float3 o, const float t0,
                                  const float t1, const float t_pass_end, __global const float* block_info,
                                  __global const char* step_level, __global const uchar* own,
                                  __global const uchar* leaps) {
    LcWalk w;
    w.L = lc_lattice_make(P, m, o, t0, t1);
    w.k = 0;
    w.t_pass_end = t_pass_end;
#if defined(LC_ESS) || defined(LC_PASSES)
    w.gx = P->ess_grid.x;
    w.gy = P->ess_grid.y;
    w.gz = P->ess_grid.z;
    w.d = lc_dda_make(w.L.q0, w.L.dq, t0, (float)P->ess_grid.w, w.gx, w.gy, w.gz);
    w.inside = 1;
    w.t_skip = -INFINITY;
#if defined(LC_PASSES) || defined(LC_SAMPLER_ATLAS)
    w.cpb = P->grid.w / P->ess_grid.w;
#endif
    w.info = block_info;
#ifdef LC_PASSES
    w.own = own;
    w.bgx = P->grid.x;
    w.bgy = P->grid.y;
    w.owned = 1;
#endif
#ifdef LC_LEAP
    w.leap = lc_leap_plane(P, leaps, &w.d, w.gx, w.gy, w.gz);
#endif
#endif
    return w;
}

static LC_HOT int lc_walk_next(LcWalk* w, LcInterval* iv, const LcIntegrator* it) {
    const LcLattice* L = &w->L;
    int k_end = L->n;
    iv->cell = (int4)(0);
#if defined(LC_ESS) || defined(LC_PASSES)
    for (;;) {
        if (w->k >= L->n) return 0;
#ifdef LC_PASSES
        if (lc_lattice_pos(L, w->k) > w->t_pass_end) return 0;
#endif
        k_end = L->n;
        int skip = 0;
        if (w->inside) {
            LcDda* d = &w->d;
            const float tb = lc_dda_exit(d);
            const int ci = (d->bz * w->gy + d->by) * w->gx + d->bx;
#ifdef LC_ESS
            skip = lc_integrator_skips(it, w->info[ci]);
#endif
#ifdef LC_PASSES
            w->owned = w->own[((d->bz / w->cpb) * w->bgy + d->by / w->cpb) * w->bgx + d->bx / w->cpb];
            skip = skip || !w->owned;
#endif
            if (!skip) {
#if defined(LC_SAMPLER_ATLAS) && defined(LC_ESS) /* (without LC_ESS the walk only splits samples among passes) */
                iv->cell = (int4)(d->bx, d->by, d->bz, w->cpb);
#endif
#if defined(LC_LEAP) && defined(LC_SAMPLER_FULL)
                /* the run of cells to sample that this one begins, handed out as one interval: each further cell
                 * costs its DDA step alone (the samples are the same: only a skip cuts the run) */
                float t_run = tb;
                for (;;) {
                    w->inside = lc_dda_step(d, w->gx, w->gy, w->gz);
                    if (!w->inside || t_run >= L->t1 || w->info[(d->bz * w->gy + d->by) * w->gx + d->bx] <= 0.0f) break;
                    t_run = lc_dda_exit(d);
                }
                if (t_run < L->t1) k_end = lc_lattice_first_at(L, t_run, w->k);
#else
                /* from k before a pending run of skipped cells is resolved below: the same index, since the
                 * samples the run covers lie before t_skip <= tb */
                if (tb < L->t1) k_end = lc_lattice_first_at(L, tb, w->k);
#endif
            }
#ifdef LC_LEAP
            const int lr = skip && w->leap ? w->leap[ci] : 0;
            if (lr >= 2) { /* the cube of lr cells ahead of this one is empty: leave it at once */
                const float te = lc_dda_leap(d, lr);
                if (te >= L->t1) return 0; /* the ray leaves the box in the cube: nothing after it */
                w->inside = d->bx >= 0 && d->bx < w->gx && d->by >= 0 && d->by < w->gy && d->bz >= 0 && d->bz < w->gz;
                w->t_skip = te;
                continue;
            }
#endif
#if defined(LC_LEAP) && defined(LC_SAMPLER_FULL)
            if (skip) w->inside = lc_dda_step(d, w->gx, w->gy, w->gz); /* (a run to sample has stepped past itself) */
#else
            w->inside = lc_dda_step(d, w->gx, w->gy, w->gz);
#endif
            if (skip) {
                if (tb >= L->t1) return 0; /* the ray leaves the box in this cell: nothing after it */
#ifdef LC_PASSES
                if (tb > w->t_pass_end) return 0; /* every later sample lies past the region */
#endif
                w->t_skip = tb;
                continue;
            }
        }
#ifdef LC_PASSES
        else {
            skip = !w->owned;
        }
#endif
        if (w->t_skip > -INFINITY) { /* the first sample after the run of skipped cells just left */
            w->k = lc_lattice_first_at(L, w->t_skip, w->k);
            w->t_skip = -INFINITY;
        }
        if (!skip) break;
        w->k = k_end;
    }
#else
    if (w->k >= L->n) return 0;
#endif
    /* uniform segments, then the last, shorter one if the interval reaches it */
    iv->qa = L->qu;
    iv->dqs = L->dqk;
    iv->s0 = w->k;
    iv->s1 = k_end < L->nlast ? k_end : L->nlast;
#ifdef LC_PRECISE
    iv->r = 1.0f;
#else
    iv->r = -1.0f;
#endif
    iv->cut = k_end == L->n && w->k < L->n; /* (a run of skipped cells can end past the last sample) */
    iv->qc = L->q0 + (L->last + L->u * L->len_last) * L->dq;
    iv->rc = L->r_last;
    iv->oct = 255;
    w->k = k_end;
    return 1;
}

#endif
