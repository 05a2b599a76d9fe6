/* lc_common.h: ray setup, ray/box intersection, jitter and the full-resolution sampler, shared by
 * raycast.cl and march_bare.cl. Voxel coordinates q have voxel centres at integers: q = (world - origin) / spacing.
 */
#ifndef LC_COMMON_H
#define LC_COMMON_H
#include "lc_types.h"

/* The voxel type of the volume and atlas buffers (-DLC_VOXEL=short etc.; KernelConfig.voxel): the store's own
 * integer type up to 16 bits, else float. Integer voxels convert exactly to float on reading, so only the bytes on
 * the device differ: half (or a quarter) of float32's. */
#ifndef LC_VOXEL
#define LC_VOXEL float
#define LC_VOXEL_FLOAT
#endif
typedef LC_VOXEL lc_voxel;

/* The deviations beside the atlas (LC_DIST: distribution classification), one per sample of a coarse brick, at the
 * atlas's offsets, in units of the volume's std_unit. With integer voxels (-DLC_VOXEL) each is a uint that holds
 * the sample's value as well, its 16 bits below the deviation's, and the coarse bricks live there alone (the atlas
 * holds level 0 alone, offsets from its own start): a coarse sample gathers one buffer per corner instead of
 * two, in the same bytes; with float voxels a ushort beside the float atlas, which holds every brick
 * (renderer/data/atlas.py: device_atlas). */
#ifndef LC_VOXEL_FLOAT
typedef uint lc_sig;
#define LC_SIG_PACKED
#define LC_SIG_VALUE(u) ((float)(lc_voxel)as_short((ushort)((u) & 0xFFFFu)))
#define LC_SIG_DEV(u) ((float)((u) >> 16))
#else
typedef ushort lc_sig;
#define LC_SIG_DEV(u) ((float)(u))
#endif

/* Linear voxel offset: ulong so that volumes beyond 2^31 voxels address correctly
 * (mirrored by lodcast.renderer.data.sampler.voxel_offset). */
#define LC_OFFSET(x, y, z, nx, ny) (((ulong)(z) * (ulong)(ny) + (ulong)(y)) * (ulong)(nx) + (ulong)(x))

/* For the atlas sampler's per-sample functions: PoCL's clang leaves them out of line (they have several callers),
 * and a call in the march makes every live value spill: both samplers run faster inlined, interblock also with its
 * eq. 3.5 sample, face blend and general sampler inlined, for a somewhat longer first build.
 * Other compilers keep their own judgement. */
#ifdef __clang__
#define LC_HOT inline __attribute__((always_inline))
#else
#define LC_HOT inline
#endif

/* For a large body on a path that is not the common one (a shading gradient's point by an edge or corner of the
 * walk's block: lc_hood_zone): kept out of line, so that the first build stays short. Other compilers keep their own
 * judgement. */
#ifdef __clang__
#define LC_COLD __attribute__((noinline))
#else
#define LC_COLD
#endif

/* v clamped to [0, hi] */
static inline int lc_clampi(const int v, const int hi) { return v < 0 ? 0 : (v > hi ? hi : v); }
/* ceil(x) for x > -1 (conversion truncates towards zero), without PoCL's out-of-line ceil() */
static inline int lc_ceil_i(const float x) { const int i = (int)x; return x > (float)i ? i + 1 : i; }

static inline float lc_exp_neg_big(const float x) { /* e^-x for 0.25 <= x <= 87 */
    /* e^-x = 2^-k e^-g, g = x - k ln 2 in [0, ln 2) up to rounding, taken in two parts (Cody and Waite: ln2_hi
     * has 15 significant bits, so k ln2_hi is exact for these k < 2^7) so that g keeps float32's precision where x
     * is large */
    const int k = (int)(x * 1.44269504089f); /* x > 0: truncation is floor */
    const float g = (x - (float)k * 0.693145751953125f) - (float)k * 1.428606765330187e-6f;
    const float p = 1.0f - g * (1.0f - g * (0.5f - g * (1.0f / 6.0f - g * (1.0f / 24.0f - g * (1.0f / 120.0f -
                    g * (1.0f / 720.0f - g * (1.0f / 5040.0f - g * (1.0f / 40320.0f))))))));
    return p * as_float((uint)(127 - k) << 23);
}

/* 1 - e^-x for an optical depth x >= 0, to float32's precision (relative error below 4e-7, tested against
 * float64), without a library call: PoCL calls exp and native_exp out of line, and the call makes every live value
 * of the march spill (a large share of a nearest-block LOD render's kernel time). A series where 1 - e^-x would
 * cancel; else e^-x = 2^-k e^-g from the exponent bits and a series in g <= 0.694 (truncation < 1e-7). */
static inline float lc_alpha_of_depth(const float x) {
    if (x < 0.25f)
        return x * (1.0f - x * (0.5f - x * (1.0f / 6.0f - x * (1.0f / 24.0f - x * (1.0f / 120.0f - x * (1.0f / 720.0f))))));
    if (x > 87.0f)
        return 1.0f;
    return 1.0f - lc_exp_neg_big(x);
}

/* e^-x for x >= 0 (a transmittance from an optical depth; +inf gives 0), relative error below 4e-7 up to x = 87
 * (float32's smallest normal number lies near e^-87.3; beyond, 0), no library call (lc_alpha_of_depth). */
static inline float lc_exp_neg(const float x) {
    if (x < 0.25f) return 1.0f - lc_alpha_of_depth(x);
    return x > 87.0f ? 0.0f : lc_exp_neg_big(x);
}

/* ln((1 + t) / (1 - t)) = 2 atanh(t) for |t| <= 0.172, by its series to t^9 (truncation below 1e-9) */
static inline float lc_atanh2(const float t) {
    const float t2 = t * t;
    return 2.0f * t * (1.0f + t2 * (1.0f / 3.0f + t2 * (1.0f / 5.0f + t2 * (1.0f / 7.0f + t2 * (1.0f / 9.0f)))));
}

/* ln x for a positive normal float x, without a library call (see lc_alpha_of_depth), to float32's precision: the
 * exponent from the bits and lc_atanh2 of s = (m - 1)/(m + 1), |s| <= 0.172 for the mantissa m in
 * [sqrt(1/2), sqrt(2)) */
static inline float lc_log(const float x) {
    uint b = as_uint(x);
    int k = (int)(b >> 23) - 127;
    float m = as_float((b & 0x007fffffU) | 0x3f800000U); /* in [1, 2) */
    if (m > 1.41421356f) { m *= 0.5f; ++k; }
    return lc_atanh2((m - 1.0f) / (m + 1.0f)) + (float)k * 0.69314718056f;
}

/* -ln(1 - a), the optical depth of opacity a in [0, 1] (+inf at 1): lc_atanh2(a / (2 - a)) (<= 1/7) where 1 - a
 * would lose a's digits, lc_log(1 - a) from a = 1/4 on (relative error below 4e-7 against float64, tested) */
static inline float lc_depth_of_alpha(const float a) {
    if (a < 0.25f) return lc_atanh2(a / (2.0f - a));
    return a >= 1.0f ? INFINITY : -lc_log(1.0f - a);
}

/* x^e for x in (0, 1] and e >= 0 (Blinn-Phong's highlight), without a library call (PoCL calls pow out of line:
 * see lc_alpha_of_depth), to an absolute error below 1e-6: e^(-e (-ln x)) from lc_log and lc_exp_neg. Subnormal x
 * counts as 0 (x^e <= 1e-19 there for e >= 1/2). */
static inline float lc_pow01(const float x, const float e) {
    if (e == 0.0f) return 1.0f;
    if (!(x >= 1.1754944e-38f)) return 0.0f;
    const float y = -e * lc_log(x); /* >= 0 (ln x <= 0 for x <= 1, up to rounding) */
    return y <= 0.0f ? 1.0f : lc_exp_neg(y);
}

static inline uint lc_hash(uint x) {
    x ^= x >> 16; x *= 0x7feb352dU; x ^= x >> 15; x *= 0x846ca68bU; x ^= x >> 16;
    return x;
}

/* uniform in [0, 1), reproducible per (seed, pixel) */
static inline float lc_jitter(uint seed, uint pixel) {
    return (float)(lc_hash(seed ^ lc_hash(pixel + 0x9e3779b9U)) >> 8) * (1.0f / 16777216.0f);
}

/* The ray through image position (x, y) in pixels from the top left corner (pixel (row i, column j)'s centre is
 * x = j + 1/2, y = i + 1/2): origin o, unit direction d (world). */
static inline void lc_pixel_ray(__constant const LcParams* P, float x, float y, float3* o, float3* d) {
    float px = (2.0f * x / (float)P->width - 1.0f) * P->half_w;
    float py = (1.0f - 2.0f * y / (float)P->height) * P->half_h;
    if (P->ortho) {
        *o = P->eye.xyz + px * P->cam_r.xyz + py * P->cam_u.xyz;
        *d = P->cam_f.xyz;
    } else {
        *o = P->eye.xyz;
        *d = normalize(P->cam_f.xyz + px * P->cam_r.xyz + py * P->cam_u.xyz);
    }
}

/* Slab test of the ray o + t d against the world box [lo, hi]: where it enters (*tn) and leaves (*tf) the box's
 * slabs (tn > tf: it misses) */
static inline void lc_slab(const float3 lo, const float3 hi, const float3 o, const float3 d, float* tn, float* tf) {
    const float3 inv = 1.0f / d;
    const float3 ta = (lo - o) * inv, tb = (hi - o) * inv;
    const float3 mn = fmin(ta, tb), mx = fmax(ta, tb);
    *tn = fmax(fmax(mn.x, mn.y), mn.z);
    *tf = fmin(fmin(mx.x, mx.y), mx.z);
}

/* Slab test in world space (and LC_CLIP: the clip planes); returns the parameter interval [t0, t1] (t0 >= 0: rays start at the eye/image plane). */
static inline int lc_hit_box(__constant const LcParams* P, float3 o, float3 d, float* t0, float* t1) {
    float tn, tf;
    lc_slab(P->box_lo.xyz, P->box_hi.xyz, o, d, &tn, &tf);
#ifdef LC_CLIP
    /* each plane keeps n.x + w >= 0: the ray's kept part of a convex region is one interval */
    for (int k = 0; k < P->n_clip; ++k) {
        const float4 pl = P->clip[k];
        const float nd = pl.x * d.x + pl.y * d.y + pl.z * d.z, no = pl.x * o.x + pl.y * o.y + pl.z * o.z + pl.w;
        if (nd > 0.0f) tn = fmax(tn, -no / nd);
        else if (nd < 0.0f) tf = fmin(tf, -no / nd);
        else if (no < 0.0f) return 0;
    }
#endif
    *t0 = fmax(tn, 0.0f);
    *t1 = tf;
    return tf > *t0;
}

#ifdef LC_SAMPLER_FULL
/* Trilinear between voxel centres, clamped to the edge in the half-voxel rim (qmax = dims - 1). Any NaN in the
 * stencil yields NaN (the caller treats it as transparent). The stencil is {floor, ceil} per axis: a voxel of
 * zero weight is not read (matters for NaN in the rim). 1-voxel-thick axes work (the stencil collapses).
 * Written without builtins (clamp, fmin, ...): PoCL calls them out of line, which costs more than the sample. */
static inline float lc_sample(__global const lc_voxel* vol, const int4 dims, const float3 qmax, float3 q) {
    float cx = q.x > 0.0f ? (q.x < qmax.x ? q.x : qmax.x) : 0.0f;
    float cy = q.y > 0.0f ? (q.y < qmax.y ? q.y : qmax.y) : 0.0f;
    float cz = q.z > 0.0f ? (q.z < qmax.z ? q.z : qmax.z) : 0.0f;
    int x0 = (int)cx, y0 = (int)cy, z0 = (int)cz;
    float fx = cx - (float)x0, fy = cy - (float)y0, fz = cz - (float)z0;
    ulong dx = (fx > 0.0f) ? 1UL : 0UL;
    ulong dy = (fy > 0.0f) ? (ulong)dims.x : 0UL;
    ulong dz = (fz > 0.0f) ? (ulong)dims.x * (ulong)dims.y : 0UL;
    ulong b = LC_OFFSET(x0, y0, z0, dims.x, dims.y);
    float v000 = (float)vol[b], v001 = (float)vol[b + dx], v010 = (float)vol[b + dy], v011 = (float)vol[b + dy + dx];
    b += dz;
    float v100 = (float)vol[b], v101 = (float)vol[b + dx], v110 = (float)vol[b + dy], v111 = (float)vol[b + dy + dx];
    float a0 = v000 + (v001 - v000) * fx, a1 = v010 + (v011 - v010) * fx;
    float a2 = v100 + (v101 - v100) * fx, a3 = v110 + (v111 - v110) * fx;
    float b0 = a0 + (a1 - a0) * fy, b1 = a2 + (a3 - a2) * fy;
    return b0 + (b1 - b0) * fz;
}
#endif

#endif
