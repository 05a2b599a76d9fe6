/* lc_shade.h: local illumination of a sample (LC_SHADE), for the classifier (Real-Time Volume Graphics ch. 5: the
 * gradient of the scalar field as the surface normal, Blinn-Phong).
 *
 * The gradient is taken by central differences one level-0 voxel either side along each axis, through the ray's
 * sampler (lc_sampler.h: the full-resolution buffer, or the atlas with nearest-block or interblock interpolation,
 * so that with interblock interpolation the normals are continuous across blocks of different levels), and scaled
 * to data units per world unit. Lighting is two-sided (|n.l|, |n.h|: a ray meets surfaces from either side). A
 * sample whose gradient magnitude is below gmin (or NaN: a stencil reaches a missing block or NaN data) has no
 * defined normal and is lit as a surface facing the light without a highlight: col (ka + kd). With gref > 0 the
 * lit colour is blended with that unlit one by min(1, |g| / gref) (shading weighted by gradient magnitude).
 * Shading changes the colour only, never the opacity. Without LC_SHADE lc_shade returns the colour as it is.
 */
#ifndef LC_SHADE_H
#define LC_SHADE_H
#include "lc_sampler.h"

typedef struct LcShade {
    float3 l, h; /* unit direction towards the light, half vector (per ray: a headlight follows it) */
    float4 k;    /* ambient, diffuse, specular, shininess */
    float3 gs;   /* central differences over two voxels, in world units */
    float gmin, gref;
} LcShade;

/* the lighting of a ray of direction d */
static inline LcShade lc_shade_make(__constant const LcParams* P, const float3 d) {
    LcShade sh;
    sh.k = P->shade;
    sh.gmin = P->shade_gmin;
    sh.gref = P->shade_gref;
    sh.gs = 0.5f * P->inv_spacing.xyz;
    sh.l = P->light.w > 0.0f ? -d : P->light.xyz; /* w > 0: headlight */
    const float3 h = sh.l - d;
    const float hn = sqrt(h.x * h.x + h.y * h.y + h.z * h.z);
    sh.h = hn > 0.0f ? h / hn : sh.l;
    return sh;
}

/* Blinn-Phong of colour col for gradient g (world units) */
static LC_HOT float3 lc_lit(const LcShade* sh, const float3 col, const float3 g) {
    const float4 k = sh->k;
    const float3 l = sh->l, h = sh->h;
    const float gm = sqrt(g.x * g.x + g.y * g.y + g.z * g.z);
    const float3 unlit = col * (k.x + k.y);
    if (!(gm >= sh->gmin) || gm == 0.0f) return unlit;
    const float3 n = g / gm;
    const float ndl = fabs(n.x * l.x + n.y * l.y + n.z * l.z);
    const float ndh = fabs(n.x * h.x + n.y * h.y + n.z * h.z);
    const float3 lit = col * (k.x + k.y * ndl) + (ndh > 0.0f ? k.z * lc_pow01(ndh < 1.0f ? ndh : 1.0f, k.w) : 0.0f);
    if (sh->gref <= 0.0f || gm >= sh->gref) return lit;
    return unlit + (lit - unlit) * (gm / sh->gref); /* weighted by gradient magnitude: noise in flat tissue stays unlit */
}

/* the field's gradient at q, world units, continuous across blocks (lc_sampler_diff) */
static LC_HOT float3 lc_gradient(LcSampler* s, const LcShade* sh, const float3 q) { return lc_sampler_diff(s, q) * sh->gs; }

/* the colour col of a sample at q as lit (LC_SHADE), or as it is */
static LC_HOT float3 lc_shade(LcSampler* s, const LcShade* sh, const float3 col, const float3 q) {
#ifdef LC_SHADE
    return lc_lit(sh, col, lc_gradient(s, sh, q));
#else
    return col;
#endif
}

#endif
