/* aprons.cl: the one-sample aprons of the atlas's level-0 bricks (renderer/data/aprons.py; the host's fill_aprons
 * is the reference). Brick b's apron sample (x, y, z) in [0, m)³, m = n + 2, lies towards direction d (per axis
 * -1, 0 or +1 where the coordinate is 0, inside, or m - 1); along an axis where that leaves the grid d folds to 0.
 * It is a sample of the neighbouring brick in the folded direction when that block is at level 0 too (`nbr`, -1
 * otherwise): along an axis of d the neighbour's edge sample next to this brick, along a folded one its edge on
 * this brick's side, elsewhere the same coordinate; else this brick's own nearest sample (clamp to edge). Reads
 * interiors only and writes aprons only, so the work-items may run in any order. Only the samples whose folded
 * direction has its bit 9 (dz + 1) + 3 (dy + 1) + (dx + 1) in the brick's `dirs` are written, all of them where
 * bit 13 (the brick itself) is set: a brick copied from the last atlas with its apron keeps the samples towards
 * blocks whose level-0 status held (renderer/data/atlas.py: dirty_blocks). LC_ELEM: an unsigned type of the
 * voxels' size (the samples are copied, not read). */
#ifndef LC_ELEM
#define LC_ELEM uint
#endif

/* One work-item per row (y, z) of a brick: a row inside the brick has its two ends in the apron, a row in the apron
 * all of its samples. */
__kernel void lc_aprons(__global LC_ELEM* atlas, __global const long* own, __global const long* nbr,
                        __global const int4* pos, __global const uint* dirs, const int4 grid, const int n,
                        const int k) {
    const int b = get_global_id(1);
    const int m = n + 2;
    const int r = get_global_id(0);
    if (b >= k || r >= m * m) return;
    const int y = r % m, z = r / m;
    const int dy = y == 0 ? -1 : (y == m - 1 ? 1 : 0);
    const int dz = z == 0 ? -1 : (z == m - 1 ? 1 : 0);
    const int4 p = pos[b];
    const int fy = dy && (p.y + dy < 0 || p.y + dy >= grid.y);
    const int fz = dz && (p.z + dz < 0 || p.z + dz >= grid.z);
    const int ey = fy ? 0 : dy, ez = fz ? 0 : dz;
    const long at = own[b];
    const uint want = dirs[b];
    if (!(want & ((1u << 13) | (7u << ((ez + 1) * 9 + (ey + 1) * 3))))) return; /* no direction of this row */
    const int step = (dy || dz) ? 1 : m - 1;  /* an inner row: its two ends only */
    for (int x = 0; x < m; x += step) {
        const int dx = x == 0 ? -1 : (x == m - 1 ? 1 : 0);
        const int fx = dx && (p.x + dx < 0 || p.x + dx >= grid.x);
        const int ex = fx ? 0 : dx;
        if (!(want & ((1u << 13) | (1u << ((ez + 1) * 9 + (ey + 1) * 3 + (ex + 1)))))) continue;
        long src = -1;
        int sx = clamp(x, 1, n), sy = clamp(y, 1, n), sz = clamp(z, 1, n);
        if (ex || ey || ez) {
            const long o = nbr[(long)b * 27 + (ez + 1) * 9 + (ey + 1) * 3 + (ex + 1)];
            if (o >= 0) {
                src = o;
                sx = dx == 0 ? x : (fx ? (dx < 0 ? 1 : n) : (dx < 0 ? n : 1));
                sy = dy == 0 ? y : (fy ? (dy < 0 ? 1 : n) : (dy < 0 ? n : 1));
                sz = dz == 0 ? z : (fz ? (dz < 0 ? 1 : n) : (dz < 0 ? n : 1));
            }
        }
        if (src < 0) src = at;
        atlas[at + ((long)z * m + y) * m + x] = atlas[src + ((long)sz * m + sy) * m + sx];
    }
}
