/* lc_shade.h: local illumination of a sample (LC_SHADE), for raycast.cl (Real-Time Volume Graphics ch. 5: the
 * gradient of the scalar field as the surface normal, Blinn-Phong).
 *
 * The gradient is taken by central differences one level-0 voxel either side along each axis, through the same
 * sampler the ray uses (LC_SAMPLE: the full-resolution buffer, or the atlas with nearest-block or interblock
 * interpolation, so that with interblock interpolation the normals are continuous across blocks of different
 * levels), and scaled to data units per world unit. Lighting is two-sided (|n.l|, |n.h|: a ray meets surfaces from
 * either side). A sample whose gradient magnitude is below shade_gmin (or NaN: a stencil reaches a missing block or
 * NaN data) has no defined normal and is lit as a surface facing the light without a highlight: col (ka + kd).
 * With shade_gref > 0 the lit colour is blended with that unlit one by min(1, |g| / shade_gref) (shading weighted
 * by gradient magnitude). Shading changes the colour only, never the opacity. Uses, from the kernel: sh_l, sh_h
 * (per ray), sh_k, sh_gmin, sh_gref, sh_gs, and LC_SAMPLE.
 */
#ifndef LC_SHADE_H
#define LC_SHADE_H
#ifdef LC_SHADE

/* Blinn-Phong of colour col for gradient g (world units), unit light l and half vector h; k = (ka, kd, ks, n) */
static LC_HOT float3 lc_lit(const float3 col, const float3 g, const float3 l, const float3 h, const float4 k,
                            const float gmin, const float gref) {
    const float gm = sqrt(g.x * g.x + g.y * g.y + g.z * g.z);
    const float3 unlit = col * (k.x + k.y);
    if (!(gm >= gmin) || gm == 0.0f) return unlit;
    const float3 n = g / gm;
    const float ndl = fabs(n.x * l.x + n.y * l.y + n.z * l.z);
    const float ndh = fabs(n.x * h.x + n.y * h.y + n.z * h.z);
    const float3 lit = col * (k.x + k.y * ndl) + (ndh > 0.0f ? k.z * lc_pow01(ndh < 1.0f ? ndh : 1.0f, k.w) : 0.0f);
    if (gref <= 0.0f || gm >= gref) return lit;
    return unlit + (lit - unlit) * (gm / gref); /* weighted by gradient magnitude: noise in flat tissue stays unlit */
}

#define LC_GRAD(q)                                                                                          \
    ((float3)(LC_SAMPLE((q) + (float3)(1.0f, 0.0f, 0.0f)).x - LC_SAMPLE((q) - (float3)(1.0f, 0.0f, 0.0f)).x, \
              LC_SAMPLE((q) + (float3)(0.0f, 1.0f, 0.0f)).x - LC_SAMPLE((q) - (float3)(0.0f, 1.0f, 0.0f)).x, \
              LC_SAMPLE((q) + (float3)(0.0f, 0.0f, 1.0f)).x - LC_SAMPLE((q) - (float3)(0.0f, 0.0f, 1.0f)).x) * sh_gs)
#define LC_SHADE_COL(col, q) lc_lit((col), LC_GRAD(q), sh_l, sh_h, sh_k, sh_gmin, sh_gref)
#else
#define LC_SHADE_COL(col, q) (col)
#endif
#endif
