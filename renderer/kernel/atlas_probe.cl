/* atlas_probe.cl: the atlas sampler (lc_atlas.h) at given points, for tests (built with -DLC_INTERP_NB or
 * -DLC_INTERP_II, and -DLC_DIST for the standard deviations). pts: level-0 voxel coordinates (x, y, z, unused);
 * out: (value, standard deviation) per point. lc_probe_diff: the shading gradient's central differences
 * (lc_sampler_diff, unscaled) at pts from the walk cell cells[i] (x, y, z, cells per block edge; 0: none), as a
 * ray in that cell takes them (with -DLC_SHADE: its eq. 3.6 window per cell). */
#define LC_SAMPLER_ATLAS
#include "lc_sampler.h"

static LcAtlasGeom lc_probe_geom(const int4 grid) {
    LcAtlasGeom geom;
    geom.gx = grid.x; geom.gy = grid.y; geom.gz = grid.z; geom.B = (float)grid.w;
    return geom;
}

__kernel void lc_probe_atlas(__global const lc_voxel* vol, __global const lc_sig* sig, __global const ulong* imap,
                             const int4 grid, __global const float4* pts, __global float2* out, const int n) {
    const int i = get_global_id(0);
    if (i >= n) return;
    out[i] = lc_sample_atlas(vol, sig, imap, lc_probe_geom(grid), pts[i].xyz);
}

__kernel void lc_probe_diff(__global const lc_voxel* vol, __global const lc_sig* sig, __global const ulong* imap,
                            const int4 grid, __global const float4* pts, __global const int4* cells,
                            __global float4* out, const int n) {
    const int i = get_global_id(0);
    if (i >= n) return;
    LcSampler s;
    s.vol = vol;
    s.sig = sig;
    s.imap = imap;
    s.geom = lc_probe_geom(grid);
    s.hood.cx = -1;
    s.blk = lc_blk(imap, s.geom, 0, 0, 0);
    lc_sampler_enter(&s, cells[i]);
    out[i] = (float4)(lc_sampler_diff(&s, pts[i].xyz), 0.0f);
}
