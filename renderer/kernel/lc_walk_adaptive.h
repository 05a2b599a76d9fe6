/* lc_walk_adaptive.h: the adaptive walk (LC_ADAPTIVE, lc_walk.h), adaptive object-space sampling (thesis §3.6.1)
 * over half-block cells: cell h covers voxel coordinates [h B/2 - 1/2, (h + 1) B/2 - 1/2), so each cell lies in
 * one block and in one interblock neighbourhood (cell boundaries are block faces and block centres). step_level
 * holds each cell's step level s (grid 2G, C order z, y, x; renderer/data/atlas.py: from the cell's block's level,
 * one more at coarse levels, | LC_NEAR_LEVEL0 next to a level-0 cell; a skipped cell holds -(that + 1)); the step
 * there is step * 2^s.
 *
 * Level 0 is sampled on full resolution's lattice: from a level-0 cell into another the steps run on (those whose
 * sample lies in the cell are all whole; the last may end past the cell's exit, inside the next cell, which goes
 * on from its end), so a run of level-0 cells takes the samples of full resolution's walk. In a coarse cell the
 * steps start at the cell's entry and the last one is cut at its exit (limited: a coarse step never runs into a
 * finer block; running on there as well saved samples at high reductions but added image error), the nearest
 * whole number of steps (the last one h/2 to 3h/2 long). A skipped cell leaves t where sampling it would for the
 * cells after it: a level-0 one on the lattice (the next level-0 cell finds its first step there, a coarse one
 * starts at its entry anyway), a coarse one at its exit; so skipping it changes no other sample. LC_LATTICE
 * ("lossless"): a coarse cell's last step ends before a level-0 cell where the lattice's first step whose sample
 * lies in that cell begins (within a base step of the face), so that level 0 takes full resolution's samples there
 * too. Each segment's opacity is corrected for its length (lc_classify.h): constant regions stay exact.
 * LC_ADAPTIVE_NAIVE (benchmarks): the step is chosen by the cell where it starts and is not cut at cell boundaries
 * (it may run deep into a finer block). */
#ifndef LC_WALK_ADAPTIVE_H
#define LC_WALK_ADAPTIVE_H

#define LC_NEAR_LEVEL0 8 /* renderer/data/atlas.py: NEAR_LEVEL0 */

typedef struct LcWalk {
    LcLattice L;
    LcDda d;
    int hx, hy, hz;   /* the half-block cells */
    float Hc;         /* their edge in voxels */
    float t;          /* where the next step starts */
    float tc;         /* where the ray enters the cell */
    uint budget;      /* iterations left: at most one per sample plus one per cell crossed (a safety bound) */
    float inv_unit;
    float t_pass_end; /* LC_PASSES: where the ray leaves the pass's region */
    __global const char* level; /* step_level */
    __global const float* info; /* LC_OCTANTS: the sampled cells' octant masks */
    __global const uchar* leap; /* LC_LEAP: the ray's octant plane (0: none) */
} LcWalk;

static inline LcWalk lc_walk_make(__constant const LcParams* P, const LcMarch* m, const float3 o, const float t0,
                                  const float t1, const float t_pass_end, __global const float* block_info,
                                  __global const char* step_level, __global const uchar* own,
                                  __global const uchar* leaps) {
    LcWalk w;
    w.L = lc_lattice_make(P, m, o, t0, t1);
    const int cpb = 2; /* cells per block edge */
    w.Hc = (float)P->grid.w / (float)cpb;
    w.hx = cpb * P->grid.x;
    w.hy = cpb * P->grid.y;
    w.hz = cpb * P->grid.z;
    w.d = lc_dda_make(w.L.q0, w.L.dq, t0, w.Hc, w.hx, w.hy, w.hz);
    w.t = t0;
    w.tc = t0;
    w.budget = (uint)P->max_samples * 2u + 4u * (uint)(w.hx + w.hy + w.hz) + 64u;
    w.inv_unit = P->inv_unit;
    w.t_pass_end = t_pass_end;
    w.level = step_level;
    w.info = block_info;
#ifdef LC_LEAP
    w.leap = lc_leap_plane(P, leaps, &w.d, w.hx, w.hy, w.hz);
#endif
    return w;
}

/* the index of cell (x, y, z) in the cells' arrays (step_level, block_info), clamped into the grid (past it the
 * ray has left the box) */
static LC_HOT ulong lc_cell_at(const LcWalk* w, const int x, const int y, const int z) {
    return ((ulong)lc_clampi(z, w->hz - 1) * (ulong)w->hy + (ulong)lc_clampi(y, w->hy - 1)) * (ulong)w->hx +
           (ulong)lc_clampi(x, w->hx - 1);
}

static LC_HOT int lc_step_code(const LcWalk* w, const int x, const int y, const int z) {
    return (int)w->level[lc_cell_at(w, x, y, z)];
}

/* a level-0 cell's code, sampled or skipped */
static LC_HOT int lc_level0(const int code) { return code == 0 || code == -1; }

/* the segment code of a step of length len in a cell of step h (level lvl) */
static LC_HOT float lc_step_r(const LcWalk* w, const float len, const float h, const int lvl) {
#ifdef LC_PRECISE
    return len * w->L.inv_dt;
#else
    return len == h ? -1.0f - (float)lvl : len * w->inv_unit;
#endif
}

static LC_HOT int lc_walk_next(LcWalk* w, LcInterval* iv, const LcIntegrator* it) {
    const LcLattice* L = &w->L;
    LcDda* d = &w->d;
    const float t0 = L->t0, t1 = L->t1, dt = L->dt, inv_dt = L->inv_dt, u = L->u;
    while (w->t < t1 && w->tc < t1 && w->budget) {
        --w->budget;
#ifdef LC_PASSES
        if (w->t > w->t_pass_end) return 0; /* past the region: nothing more of this pass's */
#endif
        float tb = lc_dda_exit(d); /* leaves the cell */
        tb = tb < t1 ? tb : t1;
        const int code = lc_step_code(w, d->bx, d->by, d->bz);
        const int skip = code < 0, v = skip ? -code - 1 : code, lvl = v & (LC_NEAR_LEVEL0 - 1);
        int found = 0;
        iv->cell = (int4)(0);
        iv->oct = 255;
#ifdef LC_ADAPTIVE_NAIVE
        if (!skip) { /* one step of the starting cell's length, wherever it ends */
            const float h = dt * (float)(1 << lvl);
            const float len = t1 - w->t < h ? t1 - w->t : h;
            iv->s0 = 0;
            iv->s1 = 0;
            iv->cut = 1;
            iv->qc = L->q0 + (w->t + u * len) * L->dq;
            iv->rc = lc_step_r(w, len, h, lvl);
            w->t += len;
            found = 1;
        } else {
            w->t = tb;
        }
        while (tb <= w->t && tb < t1) { /* the DDA to the cell that holds t */
            lc_dda_step(d, w->hx, w->hy, w->hz);
            tb = lc_dda_exit(d);
        }
        w->tc = w->t;
#else
#ifdef LC_LEAP
        /* in a cube of skipped level-0 cells (renderer/walk/leap.py: step_leaps; its edge r >= 2 in the ray's plane)
         * leave the cube at once: such cells leave t where it is, so the walk goes on as it would cell by cell */
        if (code == -1 && w->leap && d->bx >= 0 && d->bx < w->hx && d->by >= 0 && d->by < w->hy && d->bz >= 0 &&
            d->bz < w->hz) {
            const int lf = w->leap[lc_cell_at(w, d->bx, d->by, d->bz)];
            if (lf >= 2) {
                const float te = lc_dda_leap(d, lf);
                w->tc = te < t1 ? te : t1;
                continue;
            }
        }
#endif
        const int ax = lc_dda_axis(d); /* the face the ray leaves by */
        const int nx = d->bx + (ax == 0 ? d->sx : 0), ny = d->by + (ax == 1 ? d->sy : 0);
        const int nz = d->bz + (ax == 2 ? d->sz : 0); /* the next cell */
        float t_exit = tb;
#ifdef LC_LATTICE
        if ((v & LC_NEAR_LEVEL0) && tb < t1 && lc_level0(lc_step_code(w, nx, ny, nz))) {
            t_exit = t0 + (float)lc_ceil_i((tb - t0) * inv_dt - u) * dt;
            t_exit = t_exit < t1 ? t_exit : t1;
        }
#endif
        float t = w->t;
        if (skip) {
            if (lvl > 0) t = t > t_exit ? t : t_exit;
        } else {
            if (lvl == 0) { /* the lattice's first step whose sample lies in the cell (after skipped cells) */
                const int kk = lc_ceil_i((w->tc - t) * inv_dt - u);
                t = kk > 0 ? t + (float)kk * dt : t;
            } else { /* a coarse cell's steps start at its entry */
                t = t > w->tc ? t : w->tc;
            }
            if (tb > t) {
                const float h = dt * (float)(1 << lvl);
                iv->cell = (int4)(lc_clampi(d->bx, w->hx - 1), lc_clampi(d->by, w->hy - 1), lc_clampi(d->bz, w->hz - 1), 2);
#ifdef LC_OCTANTS
                iv->oct = (int)w->info[lc_cell_at(w, d->bx, d->by, d->bz)];
                iv->oq = 2.0f / w->Hc; /* octants per voxel */
                iv->ox = d->bx;
                iv->oy = d->by;
                iv->oz = d->bz;
#endif
                int whole = 0, run_on = 0;
                float tcut = t_exit > t ? t_exit : tb;
                if (lvl == 0 && tb < t1) {
                    whole = lc_ceil_i((tb - t) * inv_dt - u); /* the steps whose sample lies before tb */
                    const float end = t + (float)whole * dt;
                    if (end > t1) {
                        tcut = t1; /* cut where the ray leaves the box, as full resolution's last step */
                    } else {
                        /* the next cell, and the cell of the last step's end if that lies past the next one (a ray
                         * through a cell's corner), at level 0 */
                        const float nnx = ax == 0 ? d->tnx + d->tdx : d->tnx, nny = ax == 1 ? d->tny + d->tdy : d->tny;
                        const float nnz = ax == 2 ? d->tnz + d->tdz : d->tnz;
                        const float tb_next = nnx < nny ? (nnx < nnz ? nnx : nnz) : (nny < nnz ? nny : nnz);
                        if (end > tb_next) {
                            const float3 pe = (L->q0 + end * L->dq + 0.5f) * (1.0f / w->Hc);
                            run_on = lc_level0(lc_step_code(w, (int)pe.x, (int)pe.y, (int)pe.z));
                        } else {
                            run_on = lc_level0(lc_step_code(w, nx, ny, nz));
                        }
                    }
                }
                if (!run_on) { /* all whole but the last one, which ends at tcut */
                    if (lvl == 0) { /* the last one cut: level 0 keeps full resolution's lattice */
                        whole = lc_ceil_i((tcut - t) * inv_dt) - 1;
                    } else {
                        /* the nearest whole number of steps (at least one): the last one h/2 to 3h/2 long. A cut
                         * step took one more sample per coarse cell, often for a sliver of it: rounding takes fewer
                         * samples at every reduction for about the same image error; rounding down (steps up to 2h)
                         * added error */
                        whole = (int)((tcut - t) * inv_dt * lc_exp2_neg(lvl) + 0.5f) - 1;
                    }
                    whole = whole < 0 ? 0 : whole;
                }
                iv->qa = L->q0 + (t + u * h) * L->dq;
                iv->dqs = h * L->dq;
                iv->s0 = 0;
                iv->s1 = whole;
#ifdef LC_PRECISE
                iv->r = (float)(1 << lvl);
#else
                iv->r = -1.0f - (float)lvl; /* alpha from the level's table */
#endif
                if (run_on) {
                    iv->cut = 0;
                    t += (float)whole * h;
                } else {
                    const float a = t + (float)whole * h;
                    float len = tcut - a;
                    len = lvl == 0 ? (len < h ? len : h) : len;
                    iv->qc = L->q0 + (a + u * len) * L->dq;
                    iv->rc = lc_step_r(w, len, h, lvl);
                    iv->cut = len > 0.0f;
                    t = tcut;
                }
                found = 1;
            }
        }
        w->t = t;
        w->tc = tb;
        lc_dda_step(d, w->hx, w->hy, w->hz);
#endif
        if (found) return 1;
    }
    return 0;
}

#endif
