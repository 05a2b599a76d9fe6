/* visibility.cl: how much of each block the camera can see, for the view-dependent level-of-detail selection
 * (renderer/lod/visibility.py).
 *
 * One work-item per ray of a low-resolution cast (P->width x P->height rays over the scene's image, the scene's
 * camera, box and clip planes), marched front to back through a coarse level of the store (vol: float, kdims
 * voxels, level k: level-0 voxel coordinates q sit at (q + 1/2) 2^-k - 1/2 there) in steps of P->step (one coarse
 * voxel), each sample classified by the TF at its value: alpha per step from `alpha` (P->lut_n entries plus a copy
 * of the last, over the LUT's range). On entering a block (the level-0 block grid P->grid) the ray's transmittance
 * one step (a coarse voxel) before goes into vis[block] by atomic maximum, as T * 2^24: the brightest any ray of
 * the cast arrives there. The step back keeps the block behind an opaque surface visible where the surface's
 * first opaque sample falls just in front of its face: the interpolated surface moves by up to a coarse voxel,
 * and the block holds the values that draw it. Rays end once that is below 2^-10. NaN samples are transparent.
 * A sample in a block that `quiet` marks is not taken: its alpha is exactly 0 (renderer/lod/visibility.py: quiet_blocks),
 * so the cast records what it would cell by cell, at a fraction of a sample's cost where the TF shows nothing.
 *
 * lc_visibility_entry: the block where each ray of the image itself (n_rays.x x n_rays.y) enters the box (or the
 * clip region) gets transmittance 1: nothing lies in front of it. The cast's rays are fewer than the image's, and
 * where a face of the box is seen at a grazing angle (a cut through the data, a partial last layer of blocks a few
 * voxels thick) its blocks project thinner than the cast's ray spacing: the cast skips rows of them, which the
 * image then shows at the coarsest level. */
#define LC_SAMPLER_FULL
#include "lc_common.h"

__kernel void lc_visibility(__constant const LcParams* P, __global const float* vol, const int4 kdims, const int k,
                            __global const float* alpha, __global const uchar* quiet, __global uint* vis) {
    const int j = get_global_id(0), i = get_global_id(1);
    if (j >= P->width || i >= P->height) return;
    float3 o, d;
    float t0, t1;
    lc_pixel_ray(P, (float)j + 0.5f, (float)i + 0.5f, &o, &d);
    if (!lc_hit_box(P, o, d, &t0, &t1)) return;
    const float3 q0 = (o - P->origin.xyz) * P->inv_spacing.xyz, dq = d * P->inv_spacing.xyz;
    const float3 kmax = convert_float3(kdims.xyz - 1);
    const float s = 1.0f / (float)(1 << k), B = (float)P->grid.w;
    const int gx = P->grid.x, gy = P->grid.y, gz = P->grid.z;
    const float lut_scale = P->lut_scale, lut_off = -P->lut_lo * P->lut_scale, fmax_ = (float)(P->lut_n - 1);
    const float dt = P->step;
    const int n = (int)ceil((t1 - t0) / dt);
    float T = 1.0f, T_back = 1.0f; /* transmittance at the sample, and one step before it */
    int last = -1;
    for (int m = 0; m < n && T_back > 0.0009765625f; ++m) {
        const float3 q = q0 + (t0 + ((float)m + 0.5f) * dt) * dq;
        const int bx = lc_clampi((int)((q.x + 0.5f) / B), gx - 1), by = lc_clampi((int)((q.y + 0.5f) / B), gy - 1);
        const int bz = lc_clampi((int)((q.z + 0.5f) / B), gz - 1);
        const int b = (bz * gy + by) * gx + bx;
        if (b != last) {
            atomic_max(&vis[b], (uint)(T_back * 16777216.0f));
            last = b;
        }
        T_back = T;
        if (quiet[b]) continue; /* every value a sample here can take is one the TF shows nothing of */
        const float v = lc_sample(vol, kdims, kmax, (q + 0.5f) * s - 0.5f);
        if (v == v) {
            float f = v * lut_scale + lut_off;
            f = f > 0.0f ? (f < fmax_ ? f : fmax_) : 0.0f;
            const int i0 = (int)f;
            T *= 1.0f - (alpha[i0] + (alpha[i0 + 1] - alpha[i0]) * (f - (float)i0));
        }
    }
}

__kernel void lc_visibility_entry(__constant const LcParams* P, const int2 n_rays, __global uint* vis) {
    const int j = get_global_id(0), i = get_global_id(1);
    if (j >= n_rays.x || i >= n_rays.y) return;
    float3 o, d;
    float t0, t1;
    /* pixel (j, i) of the image in the cast's pixel units (P->width x P->height) */
    lc_pixel_ray(P, ((float)j + 0.5f) * (float)P->width / (float)n_rays.x,
                 ((float)i + 0.5f) * (float)P->height / (float)n_rays.y, &o, &d);
    if (!lc_hit_box(P, o, d, &t0, &t1)) return;
    /* a hundredth of the way in: inside the box and its block on the ray's side of a face it enters at */
    const float3 q = (o + (t0 + 0.01f * (t1 - t0)) * d - P->origin.xyz) * P->inv_spacing.xyz;
    const float B = (float)P->grid.w;
    const int bx = lc_clampi((int)((q.x + 0.5f) / B), P->grid.x - 1), by = lc_clampi((int)((q.y + 0.5f) / B), P->grid.y - 1);
    const int bz = lc_clampi((int)((q.z + 0.5f) / B), P->grid.z - 1);
    atomic_max(&vis[(bz * P->grid.y + by) * P->grid.x + bx], 16777216u);
}
