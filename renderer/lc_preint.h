/* lc_preint.h: pre-integrated classification of a ray segment (LC_PREINT), for lc_classify.h.
 *
 * A segment of length len whose sample sits at q (fraction u of the segment) is classified by the scalars at its
 * ends, s_f at q - u len dq and s_b at q + (1 - u) len dq, through ptab (lodcast.renderer.preintegration: exact
 * float64 integral of the piecewise-linear TF with self-attenuation for the base step dt; bilinear in both
 * scalars). A segment of another length (the last, shorter one; a clipped one; an adaptive step of dt 2^k) scales
 * the entry as Roettger et al. do: alpha = 1 - (1 - alpha_0)^(len / dt), with the segment's average colour kept.
 * The back sample of a segment is the front of the next one, so a ray takes one extra sample per segment, not two
 * (reused when the next front lies within 1e-4 voxels of it). A NaN at either end makes the segment transparent.
 * Coarse samples under LC_DIST keep their distribution classification (the `else` of LC_DIST_BODY leads here).
 * Per TF (suffix S, see lc_classify.h): ptab, pre_lo, pre_scale, pre_n, the reuse cache pre_q, pre_v and the ray
 * state; shared: u, dq, dt, inv_dt, LC_SEG_LEN (lc_classify.h) and LC_SAMPLE.
 */
#ifndef LC_PREINT_H
#define LC_PREINT_H
#ifdef LC_PREINT

static inline float4 lc_preint_lookup(__global const float4* ptab, const float sf, const float sb, const float lo,
                                      const float scale, const int n) {
    const float fmax_ = (float)(n - 1);
    float ff = (sf - lo) * scale, fb = (sb - lo) * scale;
    ff = ff > 0.0f ? (ff < fmax_ ? ff : fmax_) : 0.0f;
    fb = fb > 0.0f ? (fb < fmax_ ? fb : fmax_) : 0.0f;
    const int i0 = (int)ff, j0 = (int)fb;
    const int i1 = i0 + (i0 < n - 1), j1 = j0 + (j0 < n - 1);
    const float wi = ff - (float)i0, wj = fb - (float)j0;
    const float4 a = ptab[i0 * n + j0] + (ptab[i0 * n + j1] - ptab[i0 * n + j0]) * wj;
    const float4 b = ptab[i1 * n + j0] + (ptab[i1 * n + j1] - ptab[i1 * n + j0]) * wj;
    return a + (b - a) * wi;
}

#ifdef LC_PRECISE
#define LC_PREINT_COMPOSITE(a0, ratio, col, S) LC_KAHAN_COMPOSITE(-log1p(-(a0)) * (ratio), col, S)
#else
#define LC_PREINT_COMPOSITE(a0, ratio, col, S)                                   \
    {                                                                            \
        const float al_ = (ratio) == 1.0f ? (a0) : -expm1((ratio) * log1p(-(a0))); \
        LC_BLEND(T##S * al_, col, S)                                             \
    }
#endif

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
            const float4 pe_ = lc_preint_lookup(ptab##S, sf_, sb_, pre_lo##S, pre_scale##S, pre_n##S); \
            if (pe_.w > 0.0f) LC_PREINT_COMPOSITE(pe_.w, len_ * inv_dt, LC_SHADE_COL(pe_.xyz / pe_.w, q), S) \
        }                                                                        \
    }
#endif
#endif
