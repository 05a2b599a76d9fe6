/* march_bare.cl: the benchmark's yardstick. The same rays, box and trilinear sampler as raycast.cl, a fixed
 * step, no transfer function, no compositing: the machine's practical limit for this access pattern. */
#include "lc_common.h"

__kernel void lc_march_bare(__constant const LcParams* P, __global const lc_voxel* vol, __global float* out,
                            __global uint* nsamples) {
    const int j = get_global_id(0), i = get_global_id(1);
    if (j >= P->width || i >= P->height) return;
    const int4 dims = P->dims;
    const float3 qmax = convert_float3(dims.xyz - 1);
    const float dt = P->step;
    float3 o, d;
    lc_pixel_ray(P, (float)j + 0.5f, (float)i + 0.5f, &o, &d);
    float t0, t1, acc = 0.0f;
    uint n = 0;
    if (lc_hit_box(P, o, d, &t0, &t1)) {
        const float3 q0 = (o - P->origin.xyz) * P->inv_spacing.xyz;
        const float3 dq = d * P->inv_spacing.xyz;
        for (float t = t0 + 0.5f * dt; t < t1; t += dt) {
            acc += lc_sample(vol, dims, qmax, q0 + t * dq);
            n++;
        }
    }
    out[(uint)i * (uint)P->width + (uint)j] = acc;
    nsamples[(uint)i * (uint)P->width + (uint)j] = n;
}
