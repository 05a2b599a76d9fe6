/* cells.cl: the border-inclusive value range of the cells of empty-space skipping at full resolution, computed
 * where level 0 already is (renderer/data/sampler.py: level0_cells; NumPy on the host was much slower).
 *
 * Work-item (x, y, z) is cell c = lo + (x, y, z) of edge C voxels: min and max, ignoring NaN, over the voxels
 * [c C - 1, (c + 1) C] of the volume (clipped to its dims), read from a sub-volume of `sub` voxels whose first
 * voxel is the volume's voxel `off`, which holds them. No finite voxel: NaN, as lodcast.renderer.data.volume's
 * cell_minmax_border gives. */
#include "lc_common.h"

__kernel void lc_cell_range(__global const lc_voxel* vol, const int4 sub, const int4 off, const int4 dims, const int C,
                            const int4 lo, const int4 n, __global float* out_min, __global float* out_max) {
    const int x = get_global_id(0), y = get_global_id(1), z = get_global_id(2);
    if (x >= n.x || y >= n.y || z >= n.z) return;
    const int cx = lo.x + x, cy = lo.y + y, cz = lo.z + z;
    const int x0 = max(cx * C - 1, 0), x1 = min((cx + 1) * C, dims.x - 1);
    const int y0 = max(cy * C - 1, 0), y1 = min((cy + 1) * C, dims.y - 1);
    const int z0 = max(cz * C - 1, 0), z1 = min((cz + 1) * C, dims.z - 1);
    float mn = INFINITY, mx = -INFINITY;
    for (int k = z0; k <= z1; ++k)
        for (int j = y0; j <= y1; ++j) {
            const ulong row = ((ulong)(k - off.z) * (ulong)sub.y + (ulong)(j - off.y)) * (ulong)sub.x - (ulong)off.x;
            for (int i = x0; i <= x1; ++i) {
                const float v = vol[row + (ulong)i];
                if (v == v) { mn = v < mn ? v : mn; mx = v > mx ? v : mx; }
            }
        }
    const uint o = ((uint)z * (uint)n.y + (uint)y) * (uint)n.x + (uint)x;
    out_min[o] = mn <= mx ? mn : NAN;
    out_max[o] = mn <= mx ? mx : NAN;
}
