/* lc_classify.h: the classifier, one transfer function applied to one sample and composited into one integral.
 *
 * LcTf holds one TF's tables and constants, LcRay the state of one integral along the ray (colour, transmittance,
 * saturation, LC_PRECISE's compensated sums, the pre-integration cache), LcMarch what every sample shares (the
 * lattice's step and offset, the stop rule, the distribution table's deviation axis). lc_classify(ray, tf, ...)
 * takes one sample of value v at voxel coordinates q (lighting and pre-integration sample around it), the
 * standard deviation sd of the level-0 values behind it (0 at level 0 and without LC_DIST), on a segment r:
 *   r < 0   a whole step of the level -1 - r (step * 2^(-1 - r));
 *   r >= 0  the last segment's length in TF units (LC_PRECISE: the segment's length in steps).
 * A second TF (LC_TF2) is a second LcTf and LcRay through the same functions (lc_integrator.h).
 *
 * Where the TF is zero (and for NaN) a sample is transparent: no lookup, no blend — exactly what the lookup and
 * blend would give (alpha 0 adds nothing and leaves T unchanged).
 *
 * LC_DIST, classification by distribution (lodcast.renderer.lod.classification): a sample with sd > 0 takes the
 * expected extinction and colour under N(v, sd^2) from the 2D table dtab (bilinear in value and sqrt(sd)) and
 * composites in extinction form, alpha = 1 - exp(-ext * length): exact for any segment length, so adaptive steps
 * need no per-level table. sd = 0 takes the point classification, unchanged.
 * LC_PREINT: the segment is classified by the scalars at its ends (lc_preint.h).
 */
#ifndef LC_CLASSIFY_H
#define LC_CLASSIFY_H
#include "lc_shade.h"

typedef struct LcTf {
    __global const float4* lut; /* LUT entry k holds the TF at value (k - off) / scale; entry n repeats n - 1 */
    __global const float* ext;  /* the extinction per entry; with adaptive sampling one alpha row per level after */
    float scale, off, fmax;     /* fmax = n - 1 */
    float vis_lo, vis_hi;       /* LUT coordinates outside (vis_lo, vis_hi) have opacity zero */
    int row;                    /* entries per row of ext */
    float r_units;              /* a last segment's length in this TF's units per the same in the first TF's */
    float unit_w;               /* the TF's unit distance (world) */
    float dt_u;                 /* a base step in TF units */
    __global const float4* dtab; /* LC_DIST: the distribution table (rows of `drow` entries, then its spans) */
    float dscale, doff, dfmax;
    int drow, dspans;
    __global const float4* ptab; /* LC_PREINT: the pre-integration table (pre_n x pre_n, then pre_knots warp rows) */
    int pre_n, pre_knots;
    float gop;                   /* LC_GRADIENT_OPACITY: 1 / the gradient magnitude of full opacity (0: none) */
} LcTf;

/* the first TF (second = 0) or the second (LC_TF2), whose tables follow the first's in the same buffers */
static inline LcTf lc_tf_make(__constant const LcParams* P, __global const float4* lut, __global const float* ext,
                              __global const float4* dtab, __global const float4* ptab, const int second) {
    LcTf f;
    const int n = second ? P->tf2_lut_n : P->lut_n;
    const float lo = second ? P->tf2_lut_lo : P->lut_lo, inv_unit = second ? P->tf2_inv_unit : P->inv_unit;
    f.lut = lut + (second ? P->tf2_lut_at : 0);
    f.ext = ext + (second ? P->tf2_ext_at : 0);
    f.scale = second ? P->tf2_lut_scale : P->lut_scale;
    f.off = -lo * f.scale;
    f.fmax = (float)(n - 1);
    f.vis_lo = second ? P->tf2_vis_lo : P->lut_vis_lo;
    f.vis_hi = second ? P->tf2_vis_hi : P->lut_vis_hi;
    f.row = n + 1;
    f.r_units = second ? P->tf2_inv_unit / P->inv_unit : 1.0f;
    f.unit_w = 1.0f / inv_unit;
    f.dt_u = P->step * inv_unit;
    const int dn = second ? P->tf2_dist_n : P->dist_n;
    const float dlo = second ? P->tf2_dist_lo : P->dist_lo;
    f.dtab = dtab + (second ? P->tf2_dtab_at : 0);
    f.dscale = second ? P->tf2_dist_scale : P->dist_scale;
    f.doff = -dlo * f.dscale;
    f.dfmax = (float)(dn - 1);
    f.drow = dn + 1;
    f.dspans = (P->dist_rows + 1) * f.drow;
    f.ptab = ptab + (second ? P->tf2_ptab_at : 0);
    f.pre_n = second ? P->tf2_pre_n : P->pre_n;
    f.pre_knots = second ? P->tf2_pre_knots : P->pre_knots;
    f.gop = second ? P->tf2_grad_op : P->grad_op;
    return f;
}

typedef struct LcMarch {
    float dt, inv_dt; /* the base step (world) */
    float u;          /* a whole step's sample sits at fraction u of it (1/2, or the pixel's jitter) */
    float3 dq;        /* the ray's direction in voxel coordinates per world unit */
    float t_stop;     /* an integral ends once its transmittance is down to this */
    float dist_sscale, dist_jmax; /* LC_DIST: the table's deviation axis */
    float iso;        /* LC_MODE_ISO: the iso value */
} LcMarch;

/* the march of a ray of direction d through pixel pix */
static inline LcMarch lc_march_make(__constant const LcParams* P, const float3 d, const uint pix) {
    LcMarch m;
    m.dt = P->step;
    m.inv_dt = 1.0f / m.dt;
    m.u = P->jitter ? lc_jitter(P->seed, pix) : 0.5f;
    m.dq = d * P->inv_spacing.xyz;
    m.t_stop = 1.0f - P->early_term;
    m.dist_sscale = P->dist_sscale;
    m.dist_jmax = (float)(P->dist_rows - 1);
    m.iso = P->iso;
    return m;
}

typedef struct LcRay {
    float3 C;        /* premultiplied colour */
    float T;         /* transmittance */
    int sat;         /* 1 once the integral is (nearly) opaque: it takes no more samples */
    float3 C_c;      /* LC_PRECISE: the compensation terms of C and of the optical depth tau */
    float tau, tau_c;
    float3 pre_q;    /* LC_PREINT: the last segment's back end and its value */
    float pre_v;
} LcRay;

static inline LcRay lc_ray_make(void) {
    LcRay r;
    r.C = (float3)(0.0f);
    r.T = 1.0f;
    r.sat = 0;
    r.C_c = (float3)(0.0f);
    r.tau = 0.0f;
    r.tau_c = 0.0f;
    r.pre_q = (float3)(INFINITY);
    r.pre_v = 0.0f;
    return r;
}

/* Front-to-back blend of weight w = T alpha and colour col. Once the transmittance is down to t_stop the integral
 * ends and what is left of it takes this sample's colour: the rest of the ray would add T' <= t_stop of colours
 * like the ones just met, so the bias is at most t_stop times a colour difference instead of t_stop times the
 * colour (alpha ends at 1, as the exact integral of an opaque object does). */
static LC_HOT void lc_blend(LcRay* r, const float w, const float3 col, const float t_stop) {
    r->C += w * col;
    r->T -= w;
    if (r->T <= t_stop) {
        r->C += r->T * col;
        r->T = 0.0f;
        r->sat = 1;
    }
}

/* LC_PRECISE: a segment of optical depth `depth` and colour col, with compensated (Kahan) sums of colour and
 * optical depth */
static LC_HOT void lc_blend_depth(LcRay* r, const float depth, const float3 col, const float t_stop) {
    const float alpha = lc_alpha_of_depth(depth);
    const float3 y3 = (r->T * alpha) * col - r->C_c;
    const float3 s3 = r->C + y3;
    r->C_c = (s3 - r->C) - y3;
    r->C = s3;
    const float y = depth - r->tau_c;
    const float s = r->tau + y;
    r->tau_c = (s - r->tau) - y;
    r->tau = s;
    r->T = lc_exp_neg(r->tau);
    if (r->T <= t_stop) { /* finish the ray: what is left shows this colour */
        r->C += r->T * col;
        r->tau = INFINITY;
        r->T = 0.0f;
        r->sat = 1;
    }
}

/* world length of the segment r describes */
static LC_HOT float lc_seg_len(const float r, const LcTf* tf, const LcMarch* m) {
#ifdef LC_PRECISE
    return r * m->dt;
#else
    return r >= 0.0f ? r * tf->unit_w : m->dt * (float)(1 << (int)(-1.0f - r));
#endif
}

/* length in TF units of the segment r describes */
static LC_HOT float lc_len_units(const float r, const LcTf* tf) {
#ifdef LC_PRECISE
    return r * tf->dt_u;
#else
    return r >= 0.0f ? r : tf->dt_u * (float)(1 << (int)(-1.0f - r));
#endif
}

/* What the field's gradient at q does to a sample of colour col that shows something: its colour as lit
 * (lc_shade), and into *ew the factor on its TF's extinction, 1 but with LC_GRADIENT_OPACITY (Levoy 1988's
 * boundary emphasis, as VTK's gradient opacity): min(1, |gradient| / gradient_opacity), so that a segment's alpha
 * becomes 1 - (1 - alpha)^ew, independent of the step as opacity per unit distance is. One gradient serves both,
 * and only samples that show something take it. */
static LC_HOT float3 lc_gradient_look(const LcTf* tf, LcSampler* s, const LcShade* sh, const float3 col, const float3 q,
                                      float* ew) {
    *ew = 1.0f;
#ifdef LC_GRADIENT_OPACITY
    if (tf->gop > 0.0f) {
        const float3 g = lc_gradient(s, sh, q);
        const float w = sqrt(g.x * g.x + g.y * g.y + g.z * g.z) * tf->gop;
        *ew = w < 1.0f ? w : (w == w ? 1.0f : 0.0f); /* NaN (a stencil into missing data): no defined boundary */
#ifdef LC_SHADE
        return lc_lit(sh, col, g);
#endif
    }
#endif
    return lc_shade(s, sh, col, q);
}

/* alpha of a segment whose extinction is scaled by w */
static LC_HOT float lc_weighted_alpha(const float alpha, const float w) {
    return w == 1.0f ? alpha : lc_alpha_of_depth(w * lc_depth_of_alpha(alpha));
}

#include "lc_preint.h"

/* LC_DIST: a coarse sample (sd > 0) by its distribution. The row after the table holds, per row pair (j, j + 1),
 * the span of entries where the expected extinction is non-zero: outside it the sample is transparent without the
 * bilinear lookup. */
static LC_HOT void lc_classify_dist(LcRay* ray, const LcTf* tf, const LcMarch* m, LcSampler* s, const LcShade* sh,
                                    const float v, const float sd, const float r, const float3 q) {
    float fj = sqrt(sd) * m->dist_sscale;
    fj = fj < m->dist_jmax ? fj : m->dist_jmax;
    const float4 sp = tf->dtab[tf->dspans + (int)fj];
    float fi = v * tf->dscale + tf->doff;
    if (fi > sp.x - 1.0f && fi < sp.y + 1.0f) {
        fi = fi > 0.0f ? (fi < tf->dfmax ? fi : tf->dfmax) : 0.0f;
        const int ii = (int)fi, jj = (int)fj;
        const float wi = fi - (float)ii, wj = fj - (float)jj;
        __global const float4* r0 = tf->dtab + jj * tf->drow + ii;
        const float4 a = r0[0] + (r0[1] - r0[0]) * wi;
        const float4 b = r0[tf->drow] + (r0[tf->drow + 1] - r0[tf->drow]) * wi;
        const float4 e = a + (b - a) * wj;
        if (e.w > 0.0f) {
            float ew;
            const float3 col = lc_gradient_look(tf, s, sh, e.xyz, q, &ew);
#ifdef LC_PRECISE
            const float depth = (e.w * lc_len_units(r, tf)) * ew;
            lc_blend_depth(ray, depth, col, m->t_stop);
#else
            const float wgt = ray->T * lc_alpha_of_depth((e.w * lc_len_units(r, tf)) * ew);
            lc_blend(ray, wgt, col, m->t_stop);
#endif
        }
    }
}

/* the TF at value v, for v with lc_visible: that bounds the LUT coordinate below vis_hi <= n, so only the lower
 * clamp is needed; *i, *w: the entry and the weight of the next one */
static LC_HOT float4 lc_tf_at(const LcTf* tf, const float v, int* i, float* w) {
    float f = v * tf->scale + tf->off;
    f = f > 0.0f ? f : 0.0f;
    *i = (int)f; /* f < vis_hi <= n: i <= n - 1, and entry n exists */
    *w = f - (float)*i;
    const float4 e0 = tf->lut[*i], e1 = tf->lut[*i + 1];
    return e0 + (e1 - e0) * *w;
}

static LC_HOT int lc_visible(const LcTf* tf, const float v) {
    return (v * tf->scale + tf->off) > tf->vis_lo && (v * tf->scale + tf->off) < tf->vis_hi;
}

/* The point classification of a sample. The LUT holds each entry's alpha over a whole base step (or, LC_PRECISE,
 * its optical depth); a last segment (r >= 0, its length in TF units) takes its alpha from the extinction,
 * 1 - (1 - a)^r = 1 - e^(-r sigma), exact even where the step's alpha rounds to 1 in float32 (lc_alpha_of_depth,
 * not expm1: a library call anywhere in the march makes its ray state live in memory); a whole adaptive step of
 * step * 2^k (r = -1 - k, k >= 1) from row k of ext, which the host fills with that step's alphas. */
static LC_HOT void lc_classify_point(LcRay* ray, const LcTf* tf, const LcMarch* m, LcSampler* s, const LcShade* sh,
                                     const float v, const float r, const float3 q) {
    if (!lc_visible(tf, v)) return;
    int i;
    float w, ew;
    const float4 e = lc_tf_at(tf, v, &i, &w);
    const float3 col = lc_gradient_look(tf, s, sh, e.xyz, q, &ew);
#ifdef LC_PRECISE
    const float depth = (e.w * r) * ew;
    lc_blend_depth(ray, depth, col, m->t_stop);
#else
    float alpha = e.w;
    if (r >= 0.0f) {
        const float sg = tf->ext[i] + (tf->ext[i + 1] - tf->ext[i]) * w;
        alpha = lc_alpha_of_depth(r * sg);
    } else if (r < -1.5f) {
        const int o = (int)(-1.0f - r) * tf->row + i;
        alpha = tf->ext[o] + (tf->ext[o + 1] - tf->ext[o]) * w;
    }
    lc_blend(ray, ray->T * lc_weighted_alpha(alpha, ew), col, m->t_stop);
#endif
}

/* one sample through tf into ray; r is the first TF's segment code (a last segment's length is rescaled to this
 * TF's unit: whole steps and LC_PRECISE's lengths in steps are the same for every TF) */
static LC_HOT void lc_classify(LcRay* ray, const LcTf* tf, const LcMarch* m, LcSampler* s, const LcShade* sh,
                               const float v, const float sd, float r, const float3 q) {
#ifndef LC_PRECISE
    r = r >= 0.0f ? r * tf->r_units : r;
#endif
#ifdef LC_DIST
    if (sd > 0.0f) {
        lc_classify_dist(ray, tf, m, s, sh, v, sd, r, q);
        return;
    }
#endif
#ifdef LC_PREINT
    lc_preint_segment(ray, tf, m, s, sh, r, q);
#else
    lc_classify_point(ray, tf, m, s, sh, v, r, q);
#endif
}

#endif
