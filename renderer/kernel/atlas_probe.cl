/* atlas_probe.cl: the atlas sampler (lc_atlas.h) at given points, for tests (built with -DLC_INTERP_NB or
 * -DLC_INTERP_II, and -DLC_DIST for the standard deviations). pts: level-0 voxel coordinates (x, y, z, unused);
 * out: (value, standard deviation) per point. */
#include "lc_common.h"
#include "lc_atlas.h"

__kernel void lc_probe_atlas(__global const lc_voxel* vol, __global const lc_sig* sig, __global const ulong* imap,
                             const int4 grid, __global const float4* pts, __global float2* out, const int n) {
    const int i = get_global_id(0);
    if (i >= n) return;
    LcAtlasGeom geom;
    geom.gx = grid.x; geom.gy = grid.y; geom.gz = grid.z; geom.B = (float)grid.w;
    out[i] = lc_sample_atlas(vol, sig, imap, geom, pts[i].xyz);
}
