/* lc_preint.h: pre-integrated classification of a ray segment (LC_PREINT), a piece of the classifier
 * (lc_classify.h).
 *
 * A segment of length len whose sample sits at q (fraction u of the segment) is classified by the scalars at its
 * ends, s_f at q - u len dq and s_b at q + (1 - u) len dq, through ptab (lodcast.renderer.kernel.preintegration: exact
 * float64 integral of the piecewise-linear TF with self-attenuation for the base step dt; bilinear in both
 * scalars, at table coordinates from the axis' warp rows after the n x n entries: its grid lines fall on the TF's
 * control points, a hard step between two lines). A segment of another length (the last, shorter one; a clipped
 * one; an adaptive step of dt 2^k) scales the entry as Roettger et al. do: alpha = 1 - (1 - alpha_0)^(len / dt),
 * with the segment's average colour kept.
 * The back sample of a segment is the front of the next one, so a ray takes one extra sample per segment, not two
 * (reused when the next front lies within 1e-4 voxels of it). A NaN at either end makes the segment transparent.
 * Coarse samples under LC_DIST keep their distribution classification (lc_classify).
 */
#ifndef LC_PREINT_H
#define LC_PREINT_H
#ifdef LC_PREINT

/* table coordinate of value s: warp row k = (b_k, g_k, slope_k, hard_k) for the last b_k <= s (row 0 below b_1),
 * clamped to the table (lodcast.renderer.kernel.preintegration.PreintTable.coord); *row = k */
static inline float lc_preint_coord(__global const float4* warp, const int nk, const float s, const float fmax,
                                    int* row) {
    int a = 0, b = nk - 1;
    while (a < b) {
        const int m = (a + b + 1) >> 1;
        if (s >= warp[m].x) a = m;
        else b = m - 1;
    }
    *row = a;
    const float4 w = warp[a];
    const float f = w.y + (s - w.x) * w.z;
    return f > 0.0f ? (f < fmax ? f : fmax) : 0.0f;
}

/* the table, bilinear at table coordinates (ff, fb) */
static inline float4 lc_preint_at(__global const float4* ptab, const float ff, const float fb, const int n) {
    const int i0 = (int)ff, j0 = (int)fb;
    const int i1 = i0 + (i0 < n - 1), j1 = j0 + (j0 < n - 1);
    const float wi = ff - (float)i0, wj = fb - (float)j0;
    const float4 a = ptab[i0 * n + j0] + (ptab[i0 * n + j1] - ptab[i0 * n + j0]) * wj;
    const float4 b = ptab[i1 * n + j0] + (ptab[i1 * n + j1] - ptab[i1 * n + j0]) * wj;
    return a + (b - a) * wi;
}

/* alpha' = 1 - (1 - a0)^ratio of a piece `ratio` base steps long whose base-step alpha is a0, composited with
 * colour col (in line: a library call in the march puts its state in memory, lc_common.h) */
static LC_HOT void lc_preint_blend(LcRay* ray, const float a0, const float ratio, const float3 col, const float t_stop) {
#ifdef LC_PRECISE
    lc_blend_depth(ray, lc_depth_of_alpha(a0) * ratio, col, t_stop);
#else
    const float al = ratio == 1.0f ? a0 : lc_alpha_of_depth(ratio * lc_depth_of_alpha(a0));
    lc_blend(ray, ray->T * al, col, t_stop);
#endif
}

/* one piece of a segment: table coordinates (fa, fb), length ratio (to the base step) */
static LC_HOT void lc_preint_piece(LcRay* ray, const LcTf* tf, const LcMarch* m, LcSampler* s, const LcShade* sh,
                                   const float fa, const float fb, const float ratio, const float3 q) {
    const float4 pe = lc_preint_at(tf->ptab, fa, fb, tf->pre_n);
    if (pe.w > 0.0f) {
        float ew;
        const float3 col = lc_gradient_look(tf, s, sh, pe.xyz / pe.w, q, &ew);
        lc_preint_blend(ray, pe.w, ratio * ew, col, m->t_stop);
    }
}

/* The segment r whose sample sits at q. A segment that crosses hard steps of the TF (warp rows with hard_k = 1
 * between its ends' rows) is cut where the (linear) field crosses each, every piece looked up between its own ends
 * (the step's value from below or from above), so that no lookup interpolates across a step: a short segment over
 * a step takes the exact split. */
static LC_HOT void lc_preint_segment(LcRay* ray, const LcTf* tf, const LcMarch* m, LcSampler* s, const LcShade* sh,
                                     const float r, const float3 q) {
    const float len = lc_seg_len(r, tf, m);
    const float3 qf = q - (m->u * len) * m->dq, qb = qf + len * m->dq;
    const float3 dd = qf - ray->pre_q;
    const float sf = dd.x * dd.x + dd.y * dd.y + dd.z * dd.z < 1e-8f ? ray->pre_v : lc_sampler_at(s, qf).x;
    const float sb = lc_sampler_at(s, qb).x;
    ray->pre_q = qb;
    ray->pre_v = sb;
    if (sf == sf && sb == sb) {
        __global const float4* warp = tf->ptab + tf->pre_n * tf->pre_n;
        const float fmax = (float)(tf->pre_n - 1), rl = len * m->inv_dt;
        int kf, kb;
        const float ff = lc_preint_coord(warp, tf->pre_knots, sf, fmax, &kf);
        const float fb = lc_preint_coord(warp, tf->pre_knots, sb, fmax, &kb);
        float fa = ff, x0 = 0.0f;
        const int up = kb > kf;
        for (int k = up ? kf + 1 : kf; up ? k <= kb : k > kb; k += up ? 1 : -1) {
            const float4 w = warp[k];
            if (w.w == 0.0f) continue;
            const float x = (w.x - sf) / (sb - sf);
            lc_preint_piece(ray, tf, m, s, sh, fa, up ? w.y - 1.0f : w.y, (x - x0) * rl, q);
            fa = up ? w.y : w.y - 1.0f;
            x0 = x;
        }
        lc_preint_piece(ray, tf, m, s, sh, fa, fb, (1.0f - x0) * rl, q);
    }
}
#endif
#endif
