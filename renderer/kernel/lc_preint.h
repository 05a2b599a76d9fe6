/* lc_preint.h: pre-integrated classification of a ray segment (LC_PREINT), for lc_classify.h.
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
 * Coarse samples under LC_DIST keep their distribution classification (the `else` of LC_DIST_BODY leads here).
 * Per TF (suffix S, see lc_classify.h): ptab, pre_n, pre_knots, the reuse cache pre_q, pre_v and the ray
 * state; shared: u, dq, dt, inv_dt, LC_SEG_LEN (lc_classify.h) and LC_SAMPLE.
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

#ifdef LC_PRECISE
#define LC_PREINT_COMPOSITE(a0, ratio, col, S) LC_KAHAN_COMPOSITE(lc_depth_of_alpha(a0) * (ratio), col, S)
#else
/* alpha' = 1 - (1 - a0)^ratio, in line (lc_common.h: a library call in the march puts its state in memory) */
#define LC_PREINT_COMPOSITE(a0, ratio, col, S)                                   \
    {                                                                            \
        const float al_ = (ratio) == 1.0f ? (a0) : lc_alpha_of_depth((ratio) * lc_depth_of_alpha(a0)); \
        LC_BLEND(T##S * al_, col, S)                                             \
    }
#endif

/* one piece of a segment: table coordinates (fa, fb), length ratio (to the base step) */
#define LC_PREINT_PIECE(fa, fb, ratio, q, S)                                     \
    {                                                                            \
        const float4 pe_ = lc_preint_at(ptab##S, (fa), (fb), pre_n##S);          \
        if (pe_.w > 0.0f) LC_PREINT_COMPOSITE(pe_.w, (ratio), LC_SHADE_COL(pe_.xyz / pe_.w, q), S) \
    }

/* A segment that crosses hard steps of the TF (warp rows with hard_k = 1 between its ends' rows) is cut where the
 * (linear) field crosses each, every piece looked up between its own ends (the step's value from below or from
 * above), so that no lookup interpolates across a step: a short segment over a step takes the exact split. */
#define LC_PREINT_BODY(r, q, S)                                                  \
    {                                                                            \
        const float len_ = LC_SEG_LEN(r, S);                                     \
        const float3 qf_ = (q) - (u * len_) * dq, qb_ = qf_ + len_ * dq;         \
        const float3 dd_ = qf_ - pre_q##S;                                       \
        const float sf_ = dd_.x * dd_.x + dd_.y * dd_.y + dd_.z * dd_.z < 1e-8f ? pre_v##S : LC_SAMPLE(qf_).x; \
        const float sb_ = LC_SAMPLE(qb_).x;                                      \
        pre_q##S = qb_;                                                          \
        pre_v##S = sb_;                                                          \
        if (sf_ == sf_ && sb_ == sb_) {                                          \
            __global const float4* warp_ = ptab##S + pre_n##S * pre_n##S;        \
            const float fmax_ = (float)(pre_n##S - 1), rl_ = len_ * inv_dt;       \
            int kf_, kb_;                                                        \
            const float ff_ = lc_preint_coord(warp_, pre_knots##S, sf_, fmax_, &kf_); \
            const float fb_ = lc_preint_coord(warp_, pre_knots##S, sb_, fmax_, &kb_); \
            float fa_ = ff_, x0_ = 0.0f;                                         \
            const int up_ = kb_ > kf_;                                           \
            for (int k_ = up_ ? kf_ + 1 : kf_; up_ ? k_ <= kb_ : k_ > kb_; k_ += up_ ? 1 : -1) { \
                const float4 w_ = warp_[k_];                                     \
                if (w_.w == 0.0f) continue;                                      \
                const float x_ = (w_.x - sf_) / (sb_ - sf_);                     \
                LC_PREINT_PIECE(fa_, up_ ? w_.y - 1.0f : w_.y, (x_ - x0_) * rl_, q, S) \
                fa_ = up_ ? w_.y : w_.y - 1.0f;                                  \
                x0_ = x_;                                                        \
            }                                                                    \
            LC_PREINT_PIECE(fa_, fb_, (1.0f - x0_) * rl_, q, S)                  \
        }                                                                        \
    }
#endif
#endif
