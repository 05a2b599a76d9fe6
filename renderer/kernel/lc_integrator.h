/* lc_integrator.h: the integrator, what a ray makes of its samples, by mode:
 *   composite (default)  emission-absorption, front to back, through the classifier (lc_classify.h); with LC_TF2 a
 *                        second TF integrated concurrently (thesis §3.6.2), its integral composited over the
 *                        first's. The ray ends once both integrals are saturated, or once the second alone is (what
 *                        lies behind an opaque second integral cannot show through it). A pixel of zero priority
 *                        (the priority map: its ray meets no block where tf2 is visible) starts with the second
 *                        integral saturated — the thesis' "upper threshold set to zero" — and so terminates on the
 *                        first integral alone;
 *   LC_MODE_MIP          the largest value (LC_MINIP: the smallest, kept as the largest of -v, so that the walk's
 *                        test "nothing here can beat the extremum so far" is one comparison for both: block_info
 *                        holds -min for MinIP); MIP keeps the mean of coarse samples (the store keeps no maximum);
 *   LC_MODE_AVG          the length-weighted mean of the field over the ray's non-NaN segments (a DRR-like
 *                        projection);
 *   LC_MODE_ISO          the first crossing of the iso value between two consecutive non-NaN samples, placed by
 *                        linear interpolation between them (a NaN sample breaks the pair), its gradient taken there
 *                        (LC_SHADE).
 * The projections and the isosurface look at values only and take the TF's colour and opacity, as given, at the
 * projected value (the isosurface: at the iso value, lit, opaque) when the ray ends (lc_integrator_finish).
 *
 * LC_PASSES: between the passes of a render in several (renderer/data/passes.py) each ray's integrator waits in
 * `state`, field f of ray p at state[f * n_rays + p] (coalesced on a GPU), at most LC_STATE_FLOATS floats
 * (mirrored by lodcast.renderer.kernel.structs.STATE_FLOATS); lc_state_move both loads and saves it, so the two
 * cannot disagree on the order.
 */
#ifndef LC_INTEGRATOR_H
#define LC_INTEGRATOR_H
#include "lc_classify.h"

/* what the integrator applies to every sample: the TF(s), the march, the lighting */
typedef struct LcClassifier {
    LcTf tf, tf2;
    LcMarch m;
    LcShade sh;
} LcClassifier;

typedef struct LcIntegrator {
    LcRay ray, ray2;    /* composite: the first TF's integral, LC_TF2 the second's */
    float vmax;         /* MIP: the extremum so far (-inf: none) */
    float vsum, lsum;   /* average: the length-weighted sum and the length */
    float iso_pv;       /* iso: the previous sample's value (NaN: none) and position */
    float3 iso_pq;
    float3 iso_q, iso_g; /* iso: the hit's position and (LC_SHADE) gradient */
    int hit;
    uint taken;         /* samples taken */
    int done;           /* 1 once the ray can end */
} LcIntegrator;

/* The integrator of the ray through image position xy */
static inline LcIntegrator lc_integrator_make(__constant const LcParams* P, __global const uchar* prio, const float2 xy) {
    LcIntegrator it;
    it.ray = lc_ray_make();
    it.ray2 = lc_ray_make();
#ifdef LC_TF2
    /* zero priority: the threshold of the second integral is zero, it counts as saturated from the start */
    const int ptile = P->prio_tile;
    const int pi = lc_clampi((int)xy.y, P->height - 1), pj = lc_clampi((int)xy.x, P->width - 1);
    it.ray2.sat = ptile > 0 && prio[(uint)(pi / ptile) * (uint)P->prio_w + (uint)(pj / ptile)] == 0;
#endif
    it.vmax = -INFINITY;
    it.vsum = 0.0f;
    it.lsum = 0.0f;
    it.iso_pv = NAN;
    it.iso_pq = (float3)(0.0f);
    it.iso_q = (float3)(0.0f);
    it.iso_g = (float3)(0.0f);
    it.hit = 0;
    it.taken = 0;
    it.done = 0;
    return it;
}

#ifdef LC_MINIP
#define LC_EXTREMUM_SIGN -1.0f
#else
#define LC_EXTREMUM_SIGN 1.0f
#endif

/* one sample of value v (standard deviation sd) at q on segment r (lc_classify.h) */
static LC_HOT void lc_integrate(LcIntegrator* it, const LcClassifier* c, LcSampler* s, const float v, const float sd,
                                const float r, const float3 q) {
#if defined(LC_MODE_MIP)
    const float x = LC_EXTREMUM_SIGN * v;
    if (x == x) it->vmax = x > it->vmax ? x : it->vmax;
#elif defined(LC_MODE_AVG)
    if (v == v) {
        const float l = lc_seg_len(r, &c->tf, &c->m);
        it->vsum += v * l;
        it->lsum += l;
    }
#elif defined(LC_MODE_ISO)
    if (v == v) {
        const float iso = c->m.iso;
        if (it->iso_pv == it->iso_pv && ((it->iso_pv < iso) != (v < iso))) {
            it->iso_q = it->iso_pq + ((iso - it->iso_pv) / (v - it->iso_pv)) * (q - it->iso_pq);
#ifdef LC_SHADE /* here, where the sampler holds the data around the hit (in passes, only this one does) */
            it->iso_g = lc_gradient(s, &c->sh, it->iso_q);
#endif
            it->hit = 1;
            it->done = 1;
        }
        it->iso_pv = v;
        it->iso_pq = q;
    } else {
        it->iso_pv = NAN;
    }
#elif defined(LC_TF2)
    if (!it->ray.sat) lc_classify(&it->ray, &c->tf, &c->m, s, &c->sh, v, sd, r, q);
    if (!it->ray2.sat) lc_classify(&it->ray2, &c->tf2, &c->m, s, &c->sh, v, sd, r, q);
    it->done = (it->ray.sat && it->ray2.sat) || it->ray2.T == 0.0f;
#else
    lc_classify(&it->ray, &c->tf, &c->m, s, &c->sh, v, sd, r, q);
    it->done = it->ray.sat;
#endif
}

/* whether a cell whose walk info is `info` can hold nothing for the integrals still running (renderer/walk/info.py:
 * the TF's largest opacity over the cell, or its extremum, or which TFs see it) */
static LC_HOT int lc_integrator_skips(const LcIntegrator* it, const float info) {
#if defined(LC_MODE_MIP)
    return info <= it->vmax; /* nothing here can beat the extremum so far */
#elif defined(LC_TF2)
    return ((int)info & ((it->ray.sat ? 0 : 1) | (it->ray2.sat ? 0 : 2))) == 0; /* no running integral sees it */
#else
    return info <= 0.0f; /* TF opacity zero over the cell's border-inclusive value range */
#endif
}

/* the pixel: premultiplied RGBA */
static inline float4 lc_integrator_finish(const LcIntegrator* it, const LcClassifier* c) {
#if defined(LC_MODE_MIP) || defined(LC_MODE_AVG) || defined(LC_MODE_ISO)
#if defined(LC_MODE_MIP)
    const int found = it->vmax > -INFINITY;
    const float vfin = LC_EXTREMUM_SIGN * it->vmax;
#elif defined(LC_MODE_AVG)
    const int found = it->lsum > 0.0f;
    const float vfin = it->vsum / it->lsum;
#else
    const int found = it->hit;
    const float vfin = c->m.iso;
#endif
    if (!found) return (float4)(0.0f);
    const LcTf* tf = &c->tf;
    float f = vfin * tf->scale + tf->off;
    f = f > 0.0f ? (f < tf->fmax ? f : tf->fmax) : 0.0f;
    const int i0 = (int)f;
    const float4 e = tf->lut[i0] + (tf->lut[i0 + 1] - tf->lut[i0]) * (f - (float)i0);
#ifdef LC_MODE_ISO
#ifdef LC_SHADE
    return (float4)(lc_lit(&c->sh, e.xyz, it->iso_g), 1.0f);
#else
    return (float4)(e.xyz, 1.0f);
#endif
#else
    return (float4)(e.xyz * e.w, e.w);
#endif
#elif defined(LC_TF2) && defined(LC_PRECISE) /* the second integral over the first */
    return (float4)(it->ray2.C + it->ray2.T * it->ray.C, lc_alpha_of_depth(it->ray.tau + it->ray2.tau));
#elif defined(LC_TF2)
    return (float4)(it->ray2.C + it->ray2.T * it->ray.C, 1.0f - it->ray2.T * it->ray.T);
#elif defined(LC_PRECISE)
    return (float4)(it->ray.C, lc_alpha_of_depth(it->ray.tau));
#else
    return (float4)(it->ray.C, 1.0f - it->ray.T);
#endif
}

#ifdef LC_PASSES
#define LC_STATE_FLOATS 32

/* field *i of the state at st (stride floats apart), loaded into or saved from v */
static LC_HOT void lc_state_f(__global float* st, const uint stride, int* i, float* v, const int save) {
    __global float* a = st + (ulong)((*i)++) * stride;
    if (save) *a = *v;
    else *v = *a;
}
static LC_HOT void lc_state_i(__global float* st, const uint stride, int* i, int* v, const int save) {
    float f = as_float(*v);
    lc_state_f(st, stride, i, &f, save);
    *v = as_int(f);
}
static LC_HOT void lc_state_3(__global float* st, const uint stride, int* i, float3* v, const int save) {
    float x = v->x, y = v->y, z = v->z;
    lc_state_f(st, stride, i, &x, save);
    lc_state_f(st, stride, i, &y, save);
    lc_state_f(st, stride, i, &z, save);
    *v = (float3)(x, y, z);
}

static LC_HOT void lc_state_ray(__global float* st, const uint stride, int* i, LcRay* r, const int save) {
    lc_state_3(st, stride, i, &r->C, save);
    lc_state_f(st, stride, i, &r->T, save);
    lc_state_i(st, stride, i, &r->sat, save);
#ifdef LC_PRECISE
    lc_state_3(st, stride, i, &r->C_c, save);
    lc_state_f(st, stride, i, &r->tau, save);
    lc_state_f(st, stride, i, &r->tau_c, save);
#endif
#ifdef LC_PREINT
    lc_state_3(st, stride, i, &r->pre_q, save);
    lc_state_f(st, stride, i, &r->pre_v, save);
#endif
}

/* the integrator of the ray whose state starts at st, save = 0 loads it, 1 saves it */
static LC_HOT void lc_state_move(LcIntegrator* it, __global float* st, const uint stride, const int save) {
    int i = 0;
    int taken = (int)it->taken;
    lc_state_i(st, stride, &i, &taken, save);
    it->taken = (uint)taken;
    lc_state_i(st, stride, &i, &it->done, save);
    lc_state_f(st, stride, &i, &it->vmax, save);
#if defined(LC_MODE_MIP)
#elif defined(LC_MODE_AVG)
    lc_state_f(st, stride, &i, &it->vsum, save);
    lc_state_f(st, stride, &i, &it->lsum, save);
#elif defined(LC_MODE_ISO)
    lc_state_f(st, stride, &i, &it->iso_pv, save);
    lc_state_3(st, stride, &i, &it->iso_pq, save);
    lc_state_3(st, stride, &i, &it->iso_q, save);
    lc_state_i(st, stride, &i, &it->hit, save);
#ifdef LC_SHADE
    lc_state_3(st, stride, &i, &it->iso_g, save);
#endif
#else
    lc_state_ray(st, stride, &i, &it->ray, save);
#ifdef LC_TF2
    lc_state_ray(st, stride, &i, &it->ray2, save);
#endif
#endif
}
#endif

#endif
