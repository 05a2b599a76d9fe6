/* raycast.cl: lodcast's ray caster. One work-item per pixel.
 *
 * Specialised only by -D options (lodcast.renderer.config.KernelConfig.build_options()):
 *   LC_SAMPLER_FULL   sample the full-resolution volume from a plain float buffer (the only sampler so far;
 *                     the brick atlas with nearest-block / interblock interpolation adds LC_SAMPLER_ATLAS)
 *   LC_MODE_MIP       maximum intensity projection (default: emission-absorption compositing)
 *   LC_ORTHO          orthographic projection (default: perspective)
 *   LC_ESS            empty-space skipping: march block by block (3D DDA over the block grid) and skip blocks
 *                     whose block_info says nothing there can contribute, without sampling them
 *   LC_JITTER         per-pixel random offset of the sample positions (seeded, reproducible)
 *   LC_PRECISE        compensated (Kahan) sums of optical depth and colour, for rays of very many samples
 *   LC_BACKGROUND     composite the background under the integral
 *
 * Sampling: the part [t0, t1] of the ray inside the box is cut into n = ceil((t1 - t0) / step) segments of
 * length step (the last one shorter, so the segments add up to t1 - t0 exactly); segment k is sampled once at
 * fraction u of its length (u = 1/2, or the pixel's jitter). The samples therefore lie on one lattice per ray,
 * whether or not blocks are skipped: skipping changes nothing but which zero-contribution samples are taken.
 * A segment of length l with TF extinction s = -log1p(-a) (per unit distance) has opacity
 * alpha = -expm1(-(l / unit) s), exact for a -> 1 and l -> 0.
 */
#include "lc_common.h"

typedef struct {
    float t0, t1, dt, u, last;  /* last: start of the last segment */
    int n;
} LcSteps;

typedef struct {
    float3 C;      /* premultiplied colour */
    float T;       /* transmittance */
    float tau;     /* optical depth (LC_PRECISE) */
    float tau_c;   /* Kahan compensations (LC_PRECISE) */
    float3 C_c;
    float vmax;    /* LC_MODE_MIP */
    uint n;        /* samples taken */
    int done;
} LcAcc;

/* World parameter of segment k's sample, and the segment's length. */
inline float lc_pos(const LcSteps* S, int k, float* len) {
    if (k < S->n - 1) {
        *len = S->dt;
        return S->t0 + ((float)k + S->u) * S->dt;
    }
    float l = S->t1 - S->last;
    *len = l;
    return S->last + S->u * l;
}

/* TF lookup: linear interpolation of (r, g, b, extinction) between LUT entries. */
inline float4 lc_tf(__global const float4* lut, __constant const LcParams* P, float v) {
    float f = clamp((v - P->lut_lo) * P->lut_scale, 0.0f, (float)(P->lut_n - 1));
    int i0 = min((int)f, P->lut_n - 2);
    float w = f - (float)i0;
    float4 a = lut[i0], b = lut[i0 + 1];
    return a + (b - a) * w;
}

/* Samples k, k+1, ... whose position is below t_lim; returns the first index not taken. */
inline int lc_march(int k, float t_lim, const LcSteps* S, float3 q0, float3 dq, __global const float* vol,
                    __global const float4* lut, __constant const LcParams* P, LcAcc* A) {
    for (; k < S->n; ++k) {
        float len;
        float t = lc_pos(S, k, &len);
        if (t >= t_lim) break;
        float v = lc_sample(vol, P->dims, q0 + t * dq);
        A->n++;
        if (isnan(v)) continue;  /* a stencil touching a NaN voxel: transparent */
#ifdef LC_MODE_MIP
        A->vmax = fmax(A->vmax, v);
#else
        float4 e = lc_tf(lut, P, v);
        float d = len * P->inv_unit * e.w;
        float alpha = -expm1(-d);
        float w = A->T * alpha;
#ifdef LC_PRECISE
        float3 y3 = w * e.xyz - A->C_c;
        float3 s3 = A->C + y3;
        A->C_c = (s3 - A->C) - y3;
        A->C = s3;
        float y = d - A->tau_c;
        float s = A->tau + y;
        A->tau_c = (s - A->tau) - y;
        A->tau = s;
        A->T = exp(-A->tau);
#else
        A->C += w * e.xyz;
        A->T -= w;
#endif
        if (1.0f - A->T >= P->early_term || A->T <= 0.0f) {
            A->done = 1;
            return k + 1;
        }
#endif
    }
    return k;
}

/* Can block `info` be skipped? Composite: info is 1 where the TF is non-zero somewhere on the block's
 * border-inclusive value range, else 0. MIP: info is the block's border-inclusive maximum. */
inline int lc_block_empty(float info, const LcAcc* A) {
#ifdef LC_MODE_MIP
    return info <= A->vmax;
#else
    return info == 0.0f;
#endif
}

#define LC_DDA_AXIS(c)                                                   \
    if (dg.c > 0.0f) {                                                   \
        st.c = 1; tn.c = ((float)(b.c + 1) - g0.c) / dg.c; td.c = 1.0f / dg.c;   \
    } else if (dg.c < 0.0f) {                                            \
        st.c = -1; tn.c = ((float)b.c - g0.c) / dg.c; td.c = -1.0f / dg.c;       \
    } else {                                                             \
        st.c = 0; tn.c = INFINITY; td.c = INFINITY;                      \
    }

__kernel void lc_render(__constant const LcParams* P, __global const float* vol, __global const float4* lut,
                        __global const float* block_info, __global float4* out, __global uint* nsamples) {
    const int j = get_global_id(0), i = get_global_id(1);
    if (j >= P->width || i >= P->height) return;
    const uint pix = (uint)i * (uint)P->width + (uint)j;

    LcAcc A;
    A.C = (float3)(0.0f); A.T = 1.0f; A.tau = 0.0f; A.tau_c = 0.0f; A.C_c = (float3)(0.0f);
    A.vmax = -INFINITY; A.n = 0; A.done = 0;

    float3 o, d;
    lc_pixel_ray(P, i, j, &o, &d);
    LcSteps S;
    if (lc_hit_box(P, o, d, &S.t0, &S.t1)) {
        S.dt = P->step;
        S.n = (int)min(ceil((S.t1 - S.t0) / S.dt), (float)P->max_samples);
        S.n = max(S.n, 1);
        S.last = S.t0 + (float)(S.n - 1) * S.dt;
        if (S.last >= S.t1) S.last = S.t1;
#ifdef LC_JITTER
        S.u = lc_jitter(P->seed, pix);
#else
        S.u = 0.5f;
#endif
        const float3 q0 = (o - P->origin.xyz) * P->inv_spacing.xyz;
        const float3 dq = d * P->inv_spacing.xyz;
        int k = 0;
#ifdef LC_ESS
        /* 3D DDA over the block grid: block b covers voxel coordinates [b B - 1/2, (b + 1) B - 1/2). */
        const float B = (float)P->grid.w;
        const float3 g0 = (q0 + 0.5f) / B, dg = dq / B;
        const int3 gmax = P->grid.xyz - 1;
        int3 b = clamp(convert_int3_rtn(g0 + S.t0 * dg), (int3)(0), gmax);
        int3 st;
        float3 tn, td;
        LC_DDA_AXIS(x)
        LC_DDA_AXIS(y)
        LC_DDA_AXIS(z)
        while (k < S.n && !A.done) {
            const float tb = fmin(tn.x, fmin(tn.y, tn.z)); /* where the ray leaves block b */
            const float info = block_info[(b.z * P->grid.y + b.y) * P->grid.x + b.x];
            if (lc_block_empty(info, &A)) {
                if (tb >= S.t1) { k = S.n; break; }
                int kn = (int)clamp(ceil((tb - S.t0) / S.dt - S.u), (float)k, (float)(S.n - 1));
                float len;
                while (kn > k && lc_pos(&S, kn - 1, &len) >= tb) kn--;  /* guard against rounding */
                while (kn < S.n && lc_pos(&S, kn, &len) < tb) kn++;
                k = kn;
            } else {
                k = lc_march(k, tb, &S, q0, dq, vol, lut, P, &A);
            }
            if (tn.x <= tn.y && tn.x <= tn.z) {
                b.x += st.x; tn.x += td.x;
                if (b.x < 0 || b.x > gmax.x) break;
            } else if (tn.y <= tn.z) {
                b.y += st.y; tn.y += td.y;
                if (b.y < 0 || b.y > gmax.y) break;
            } else {
                b.z += st.z; tn.z += td.z;
                if (b.z < 0 || b.z > gmax.z) break;
            }
        }
        /* samples the DDA did not reach because of rounding at the box exit */
        if (!A.done && k < S.n) k = lc_march(k, INFINITY, &S, q0, dq, vol, lut, P, &A);
#else
        k = lc_march(k, INFINITY, &S, q0, dq, vol, lut, P, &A);
#endif
    }

    float4 res;
#ifdef LC_MODE_MIP
    if (A.vmax > -INFINITY) {
        float4 e = lc_tf(lut, P, A.vmax);
        float a = -expm1(-e.w); /* the TF's opacity as given */
        res = (float4)(e.xyz * a, a);
    } else {
        res = (float4)(0.0f);
    }
#else
#ifdef LC_PRECISE
    res = (float4)(A.C, -expm1(-A.tau));
#else
    res = (float4)(A.C, 1.0f - A.T);
#endif
#endif
#ifdef LC_BACKGROUND
    res += (1.0f - res.w) * P->background;
#endif
    out[pix] = res;
    nsamples[pix] = A.n;
}
