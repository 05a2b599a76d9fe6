/* lc_classify.h: classification and compositing of one sample (the integrator's step), for raycast.cl.
 *
 * LC_SAMPLE_BODY(v, sd, r, q): a sample at voxel coordinates q (lighting and pre-integration sample around it) of
 * value v, standard deviation sd of the level-0 values behind it (0 at level 0 and without LC_DIST) on a segment
 * described by r (see raycast.cl's header: r < 0 a whole step of the level -1 - r, r >= 0 the last segment's
 * length in TF units; LC_PRECISE: r is the segment's length in steps). MIP keeps the maximum of v; compositing
 * classifies and composites front to back; done = 1 once the ray can end.
 *
 * One transfer function's classification is LC_CLASSIFY(v, sd, r, q, S): every table, constant and piece of ray
 * state it uses carries the suffix S — empty for the first TF (lut, lut_ext, C, T, sat, ...), 2 for the second
 * (LC_TF2: lut2, lut_ext2, C2, T2, sat2, ...), so that both integrals run the same code. sat##S = 1 once that
 * integral is (nearly) opaque.
 *
 * LC_TF2, dual-TF compositing (thesis §3.6.2, item 3): both TFs are integrated concurrently along the ray, the
 * second integral is composited over the first (raycast.cl). The ray ends once both integrals are saturated, or
 * once the second alone is (what lies behind an opaque second integral cannot show through it). A pixel of zero
 * priority (the priority map: its ray meets no block where tf2 is visible) starts with sat2 = 1 — the thesis'
 * "upper threshold set to zero" — and so terminates on the first integral alone.
 *
 * LC_DIST, classification by distribution (lodcast.renderer.lod.classification): a sample with sd > 0 takes the
 * expected extinction and colour under N(v, sd^2) from the 2D table dtab (bilinear in value and sqrt(sd)) and
 * composites in extinction form, alpha = 1 - exp(-ext * length): exact for any segment length, so adaptive steps
 * need no per-level table. sd = 0 takes the point classification below, unchanged.
 * Uses, from the kernel, per TF: lut, lut_ext, lut_scale, lut_off, lut_vis_lo, lut_vis_hi, lut_row (LC_ADAPTIVE),
 * (LC_DIST) dtab, dist_scale, dist_off, dist_fmax, dist_row, dist_spans, dt_u, (LC_PREINT) ptab, pre_*, unit_w, and
 * the ray state C, T, sat (LC_PRECISE: C_c, tau, tau_c); shared: dist_jmax, dist_sscale, t_stop (MIP: vmax).
 */
#ifndef LC_CLASSIFY_H
#define LC_CLASSIFY_H

#ifdef LC_PRECISE
/* compensated (Kahan) sums of colour and optical depth for a segment of optical depth `depth` and colour `col` */
#define LC_KAHAN_COMPOSITE(depth, col, S)                                        \
    {                                                                            \
        const float alpha = lc_alpha_of_depth(depth);                           \
        const float3 col_ = (col);                                               \
        const float3 y3 = (T##S * alpha) * col_ - C_c##S;                        \
        const float3 s3 = C##S + y3;                                             \
        C_c##S = (s3 - C##S) - y3;                                               \
        C##S = s3;                                                               \
        const float y = (depth) - tau_c##S;                                      \
        const float s = tau##S + y;                                              \
        tau_c##S = (s - tau##S) - y;                                             \
        tau##S = s;                                                              \
        T##S = lc_exp_neg(tau##S);                                               \
        if (T##S <= t_stop) { /* finish the ray: what is left shows this colour */ \
            C##S += T##S * col_;                                                 \
            tau##S = INFINITY;                                                   \
            T##S = 0.0f;                                                         \
            sat##S = 1;                                                          \
        }                                                                        \
    }
#endif

/* front-to-back blend of weight w = T alpha and colour col; once the transmittance is down to t_stop the integral
 * ends and what is left of it takes this sample's colour: the rest of the ray would add T' <= t_stop of colours
 * like the ones just met, so the bias is at most t_stop times a colour difference instead of t_stop times the
 * colour (alpha ends at 1, as the exact integral of an opaque object does) */
#define LC_BLEND(w, col, S)                                                      \
    {                                                                            \
        const float3 col_ = (col);                                               \
        const float w_ = (w);                                                    \
        C##S += w_ * col_;                                                       \
        T##S -= w_;                                                              \
        if (T##S <= t_stop) {                                                    \
            C##S += T##S * col_;                                                 \
            T##S = 0.0f;                                                         \
            sat##S = 1;                                                          \
        }                                                                        \
    }

#ifdef LC_DIST
/* length in TF units of the segment r describes */
#ifdef LC_PRECISE
#define LC_LEN_UNITS(r, S) ((r) * dt_u##S)
#else
#define LC_LEN_UNITS(r, S) ((r) >= 0.0f ? (r) : dt_u##S * (float)(1 << (int)(-1.0f - (r))))
#endif

/* the bilinear lookup at table coordinates (fi, fj), fi already clamped to the value axis */
#define LC_DIST_LOOKUP(fi, fj, e, S)                                             \
    float4 e;                                                                    \
    {                                                                            \
        const int ii_ = (int)(fi), jj_ = (int)(fj);                              \
        const float wi_ = (fi) - (float)ii_, wj_ = (fj) - (float)jj_;            \
        __global const float4* r0_ = dtab##S + jj_ * dist_row##S + ii_;          \
        const float4 a_ = r0_[0] + (r0_[1] - r0_[0]) * wi_;                      \
        const float4 b_ = r0_[dist_row##S] + (r0_[dist_row##S + 1] - r0_[dist_row##S]) * wi_; \
        e = a_ + (b_ - a_) * wj_;                                                \
    }
#ifdef LC_PRECISE
#define LC_DIST_COMPOSITE(e, r, q, S)                                            \
    {                                                                            \
        const float depth_ = e.w * LC_LEN_UNITS(r, S);                           \
        LC_KAHAN_COMPOSITE(depth_, LC_SHADE_COL(e.xyz, q), S)                    \
    }
#else
#define LC_DIST_COMPOSITE(e, r, q, S)                                            \
    {                                                                            \
        const float wgt = T##S * lc_alpha_of_depth(e.w * LC_LEN_UNITS(r, S)); \
        LC_BLEND(wgt, LC_SHADE_COL(e.xyz, q), S)                                 \
    }
#endif
/* a coarse sample (sd > 0, not NaN): by its distribution; else falls through to the point classification.
 * The row after the table holds, per row pair (j, j + 1), the span of entries where the expected extinction is
 * non-zero: outside it the sample is transparent without the bilinear lookup. */
#define LC_DIST_BODY(v, sd, r, q, S)                                             \
    if ((sd) > 0.0f) {                                                           \
        float fj_ = sqrt(sd) * dist_sscale;                                      \
        fj_ = fj_ < dist_jmax ? fj_ : dist_jmax;                                 \
        const float4 sp_ = dtab##S[dist_spans##S + (int)fj_];                    \
        float fi_ = (v) * dist_scale##S + dist_off##S;                           \
        if (fi_ > sp_.x - 1.0f && fi_ < sp_.y + 1.0f) {                          \
            fi_ = fi_ > 0.0f ? (fi_ < dist_fmax##S ? fi_ : dist_fmax##S) : 0.0f; \
            LC_DIST_LOOKUP(fi_, fj_, e, S)                                       \
            if (e.w > 0.0f) LC_DIST_COMPOSITE(e, r, q, S)                        \
        }                                                                        \
    } else
#else
#define LC_DIST_BODY(v, sd, r, q, S)
#endif

/* world length of the segment r describes (see raycast.cl's header for r; unit_w: the TF's unit distance) */
#ifdef LC_PRECISE
#define LC_SEG_LEN(r, S) ((r) * dt)
#else
#define LC_SEG_LEN(r, S) ((r) >= 0.0f ? (r) * unit_w##S : dt * (float)(1 << (int)(-1.0f - (r))))
#endif

#include "lc_preint.h"

/* One sample of value v on a segment of r steps. The projections (MIP, MinIP, average) and the isosurface mode
 * only look at values; compositing looks the TF up, takes the segment's opacity and composites front to back;
 * done = 1 once the ray is (nearly) opaque (or, isosurface, has hit). */
#ifdef LC_MODE_MIP
/* MIP keeps the maximum; MinIP (LC_MINIP) the maximum of -v, i.e. the minimum, so that the block walk's test
 * "nothing here can beat the extremum so far" is one comparison for both (block_info holds -min for MinIP) */
#ifdef LC_MINIP
#define LC_EXT(v) (-(v))
#else
#define LC_EXT(v) (v)
#endif
#define LC_SAMPLE_BODY(v, sd, r, q)                                              \
    {                                                                            \
        const float x_ = LC_EXT(v);                                              \
        if (x_ == x_) vmax = x_ > vmax ? x_ : vmax;                              \
    }
#elif defined(LC_MODE_AVG)
/* average intensity (a DRR-like projection): the length-weighted mean of the field over the ray's non-NaN
 * segments */
#define LC_SAMPLE_BODY(v, sd, r, q)                                              \
    if ((v) == (v)) {                                                            \
        const float l_ = LC_SEG_LEN(r, );                                        \
        vsum += (v) * l_;                                                        \
        lsum += l_;                                                              \
    }
#elif defined(LC_MODE_ISO)
/* isosurface: the first crossing of iso between two consecutive non-NaN samples, placed by linear interpolation
 * between them (a NaN sample breaks the pair) */
#if defined(LC_PASSES) && defined(LC_SHADE)
/* in passes the hit's normal is taken by the pass that holds the data around it, kept with the ray state */
#define LC_ISO_GRAD iso_g = LC_GRAD(iso_q);
#else
#define LC_ISO_GRAD
#endif
#define LC_SAMPLE_BODY(v, sd, r, q)                                              \
    if ((v) == (v)) {                                                            \
        if (iso_pv == iso_pv && ((iso_pv < iso) != ((v) < iso))) {               \
            iso_q = iso_pq + ((iso - iso_pv) / ((v) - iso_pv)) * ((q) - iso_pq);  \
            LC_ISO_GRAD                                                          \
            hit = 1;                                                             \
            done = 1;                                                            \
        }                                                                        \
        iso_pv = (v);                                                            \
        iso_pq = (q);                                                            \
    } else                                                                       \
        iso_pv = NAN;
#else
/* Where the TF is zero (and for NaN) a sample is transparent: no lookup, no blend — exactly what the lookup and
 * blend would give (alpha 0 adds nothing and leaves T unchanged). */
#define lc_visible(v, S) (((v) * lut_scale##S + lut_off##S) > lut_vis_lo##S && ((v) * lut_scale##S + lut_off##S) < lut_vis_hi##S)
/* only after lc_visible(v, S): that bounds f below lut_vis_hi <= lut_n, so only the lower clamp is needed */
#define LC_TF_LOOKUP(v, e, S)                                                    \
    float4 e;                                                                    \
    int i_;                                                                      \
    float w_;                                                                    \
    {                                                                            \
        float f_ = (v) * lut_scale##S + lut_off##S;                              \
        f_ = f_ > 0.0f ? f_ : 0.0f;                                              \
        i_ = (int)f_; /* f_ < lut_vis_hi <= n: i_ <= n - 1, and entry n exists */ \
        w_ = f_ - (float)i_;                                                     \
        const float4 e0_ = lut##S[i_], e1_ = lut##S[i_ + 1];                     \
        e = e0_ + (e1_ - e0_) * w_;                                              \
    }
#ifdef LC_PREINT
#define LC_CLASSIFY(v, sd, r, q, S)                                              \
    LC_DIST_BODY(v, sd, r, q, S)                                                 \
    LC_PREINT_BODY(r, q, S)
#elif defined(LC_PRECISE)
#define LC_CLASSIFY(v, sd, r, q, S)                                              \
    LC_DIST_BODY(v, sd, r, q, S)                                                 \
    if (lc_visible(v, S)) {                                                      \
        LC_TF_LOOKUP(v, e, S)                                                    \
        const float depth_ = e.w * (r);                                          \
        LC_KAHAN_COMPOSITE(depth_, LC_SHADE_COL(e.xyz, q), S)                    \
    }
#else
#ifdef LC_ADAPTIVE
/* adaptive: r = -1 - k (k >= 1) is a whole step of step * 2^k: alpha from row k of lut_ext (the host appends one
 * alpha table per level after the extinction row), no transcendental call */
#define LC_LEVEL_ALPHA(r, S)                                                     \
        else if ((r) < -1.5f) {                                                  \
            const int o_ = (int)(-1.0f - (r)) * lut_row##S + i_;                 \
            alpha = lut_ext##S[o_] + (lut_ext##S[o_ + 1] - lut_ext##S[o_]) * w_; \
        }
#else
#define LC_LEVEL_ALPHA(r, S)
#endif
/* r < 0: a uniform segment (alpha from the table); else the last segment's length in TF units (alpha from the
 * extinction table: 1 - (1 - a)^r = 1 - e^(-r sigma), exact even where the step's alpha rounds to 1 in float32;
 * lc_alpha_of_depth, not expm1: a library call anywhere in the march makes its ray state live in memory) */
#define LC_CLASSIFY(v, sd, r, q, S)                                              \
    LC_DIST_BODY(v, sd, r, q, S)                                                 \
    if (lc_visible(v, S)) {                                                      \
        LC_TF_LOOKUP(v, e, S)                                                    \
        float alpha = e.w;                                                       \
        if ((r) >= 0.0f) {                                                       \
            const float sg_ = lut_ext##S[i_] + (lut_ext##S[i_ + 1] - lut_ext##S[i_]) * w_; \
            alpha = lc_alpha_of_depth((r) * sg_);                                \
        }                                                                        \
        LC_LEVEL_ALPHA(r, S)                                                     \
        LC_BLEND(T##S * alpha, LC_SHADE_COL(e.xyz, q), S)                        \
    }
#endif

#ifdef LC_TF2
/* r of the second TF: a last segment's length is in TF units, so it is rescaled to tf2's unit (r2_units =
 * unit / unit2); whole steps (r < 0) and LC_PRECISE's lengths in steps are the same for both TFs */
#ifdef LC_PRECISE
#define LC_R2(r) (r)
#else
#define LC_R2(r) ((r) >= 0.0f ? (r) * r2_units : (r))
#endif
#define LC_SAMPLE_BODY(v, sd, r, q)                                              \
    {                                                                            \
        if (!sat) { LC_CLASSIFY(v, sd, r, q, ) }                                 \
        if (!sat2) { const float r2_ = LC_R2(r); LC_CLASSIFY(v, sd, r2_, q, 2) } \
        done = (sat && sat2) || T2 == 0.0f;                                      \
    }
#else
#define LC_SAMPLE_BODY(v, sd, r, q)                                              \
    {                                                                            \
        LC_CLASSIFY(v, sd, r, q, )                                               \
        done = sat;                                                              \
    }
#endif
#endif

#endif
