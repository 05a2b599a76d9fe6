/* raycast.cl: lodcast's ray caster. One work-item per pixel.
 *
 * Specialised only by -D options (lodcast.renderer.kernel.config.KernelConfig.build_options()):
 *   LC_SAMPLER_FULL   sample the full-resolution volume from a plain buffer of lc_voxel (LC_VOXEL: lc_common.h)
 *   LC_SAMPLER_ATLAS  sample the multiresolution field from the brick atlas through the block index map
 *                     (lc_atlas.h), with LC_INTERP_NB (nearest block, eq. 3.5) or LC_INTERP_II (interblock, eq. 3.6)
 *   LC_ADAPTIVE       (atlas) adaptive object-space sampling (thesis §3.6.1): march half-block cells; in a
 *                     cell whose step level is s (step_level, renderer/data/atlas.py: from the cell's block's level,
 *                     one more at coarse levels, | 8 next to a level-0 cell; a skipped cell holds -(that + 1)) the
 *                     step is step * 2^s; the steps restart at every face of a coarse cell (limited: a long step
 *                     never runs into a finer block) and run on between level-0 cells (level 0 is sampled on full
 *                     resolution's lattice);
 *                     a coarse cell's part of the ray takes the nearest whole number of steps (the last one h/2
 *                     to 3h/2 long), a level-0 cell's its whole steps and a cut one;
 *                     each segment's opacity is corrected for its length (whole steps from a per-level alpha
 *                     table, the last one from the extinction): constant regions stay exact
 *   LC_LATTICE        with LC_ADAPTIVE: level 0 on full resolution's lattice after coarse cells too (the coarse
 *                     cell's last step ends where the lattice's first step into the level-0 cell begins)
 *   LC_ADAPTIVE_NAIVE with LC_ADAPTIVE: for comparison/benchmarks only: the step is chosen by the cell where it
 *                     starts and is not cut at cell boundaries (it may run deep into a finer block)
 *   LC_DIST           (atlas, composite) classification by distribution: coarse samples carry the standard
 *                     deviation of the level-0 values behind them (sig, beside the atlas) and are classified by
 *                     their expected extinction and colour (dtab; lc_classify.h)
 *   LC_MODE_AVG       average intensity projection (length-weighted mean of the field along the ray; no block walk)
 *   LC_MODE_ISO       isosurface: the first crossing of P->iso, shaded with LC_SHADE, opaque (no block walk)
 *   LC_MINIP          with LC_MODE_MIP: minimum intensity projection
 *   LC_MODE_MIP       maximum intensity projection (default: emission-absorption compositing; MIP keeps the mean
 *                     of coarse samples: the store keeps no coarse maximum)
 *   LC_ORTHO          orthographic projection (default: perspective)
 *   LC_ESS            empty-space skipping: march cell by cell (3D DDA over P->ess_grid: at full resolution cells
 *                     finer than the blocks, on the atlas half-block cells) and skip cells whose block_info says
 *                     nothing there can contribute, without sampling them
 *   LC_LEAP           with LC_ESS (composite, one TF, one pass): space leaping (renderer/walk/leap.py). `leaps` holds
 *                     planes over the walk's cells, one per octant of ray directions the view's rays go in (octant
 *                     (sx > 0) | (sy > 0) << 1 | (sz > 0) << 2, its plane named by P->leap_planes: LC_LEAP_BEGIN):
 *                     in an empty cell (with LC_ADAPTIVE: a skipped level-0 cell) the edge r of the cube of empty
 *                     cells that starts there and runs forward in that octant's directions; r >= 2: the ray
 *                     leaves that cube in one step instead of a DDA step per cell.
 *                     With LC_SAMPLER_FULL (where only the cells decide a skip) a run of cells to sample is found
 *                     first and sampled in one loop
 *   LC_OCTANTS        with LC_LEAP and LC_ADAPTIVE (no pre-integration): a sampled cell's block_info holds the mask of
 *                     its eight octants (quarter-block cells) where the field can show something (walk.py:
 *                     octant_masks, bit (z & 1) << 2 | (y & 1) << 1 | (x & 1)); a sample in another octant adds
 *                     nothing and is not taken (no lookup, no blend: the image is the same)
 *   LC_JITTER         per-pixel random offset of the sample positions (seeded, reproducible)
 *   LC_PRECISE        compensated (Kahan) sums of optical depth and colour, for rays of very many samples
 *   LC_BACKGROUND     composite the background under the integral
 *   LC_CLIP           clip planes (lc_common.h: the ray's interval is cut exactly at each plane; a crop box needs no
 *                     option, the host intersects it with the volume's box)
 *   LC_PREINT         pre-integrated classification of each segment by the scalars at its ends (lc_preint.h)
 *   LC_SHADE          local illumination, Blinn-Phong with gradients through the ray's sampler (lc_shade.h)
 *   LC_SCREEN         adaptive screen-space sampling: work-item pix < P->screen_n casts the ray through image
 *                     position spos[pix] (a tile's sample, renderer/frame/screen.py) instead of its pixel's centre
 *   LC_TF2            (composite) dual-TF compositing: a second TF integrated concurrently, its integral composited
 *                     over the first's (lc_classify.h). Its tables follow the first TF's in lut, lut_ext, dtab and
 *                     ptab (offsets P->tf2_*_at); block_info holds bit 1 where tf is visible, bit 2 where tf2 is,
 *                     and the block walk skips a block only if no integral still running can see it; prio (one
 *                     byte per prio_tile x prio_tile pixels, prio_w per row; prio_tile = 0: none) is the priority
 *                     map: a zero-priority pixel's ray meets no block where tf2 is visible, so it ends on the
 *                     first integral alone
 *   LC_PASSES         one pass of a render in several (lc_passes.h): samples only in the blocks `own` marks, the
 *                     full sampler on a sub-volume at P->pass_off, the ray state carried in `state`; implies the
 *                     block walk (without LC_ESS it skips nothing else)
 *
 * Sampling: the part [t0, t1] of the ray inside the box is cut into n = ceil((t1 - t0) / step) segments of
 * length step (the last one shorter, so the segments add up to t1 - t0 exactly); segment k is sampled once at
 * fraction u of its length (u = 1/2, or the pixel's jitter). The samples therefore lie on one lattice per ray
 * whether or not blocks are skipped: skipping changes nothing but which zero-contribution samples are taken.
 *
 * The LUT (lut_n entries plus a copy of the last, so that entry i + 1 exists for every i <= lut_n - 1) has a
 * fourth channel that depends on the mode (lodcast.renderer.scene.transfer_function.Lut.kernel_table):
 *   composite: alpha_step = 1 - (1 - a)^(step / unit), exact in float64 on the host, so the uniform segments
 *              need no transcendental function; the last, shorter segment of length l takes
 *              1 - e^(-(l / unit) sigma) (lc_alpha_of_depth: no library call) from lut_ext, the extinction
 *              sigma = -log1p(-a) per entry (a = 1 maps to a huge finite sigma, so alpha = 1);
 *   LC_PRECISE: the segment's optical depth (step / unit) * (-log1p(-a)), alpha = 1 - e^-depth (lc_common.h);
 *   MIP:       the TF opacity a as given.
 * A later per-block step (adaptive sampling) takes alpha from lut_ext the same way (or a table per step).
 * Loops avoid OpenCL builtins such as clamp/fmin (PoCL calls them out of line) and read parameters from private
 * copies (on the CPU device __constant and private memory may alias, so loads in loops are not hoisted).
 */
#include "lc_common.h"
#ifdef LC_SAMPLER_ATLAS
#include "lc_atlas.h"
/* (value, standard deviation) of the multiresolution field at q */
#define LC_SAMPLE(q) lc_sample_atlas_h(vol, sig, imap, geom, &hood, (q))
/* inside the block (or adaptive cell) the march is in: its brick set up once (lc_blk), see lc_atlas.h */
#define LC_SAMPLE_B(q) lc_sample_blk(vol, sig, imap, geom, blk, &hood, (q))
#elif defined(LC_PASSES)
#define LC_SAMPLE(q) ((float2)(lc_sample_pass(vol, pdims, pmax, qmax, poff, (q)), 0.0f))
#define LC_SAMPLE_B(q) LC_SAMPLE(q)
#else
#define LC_SAMPLE(q) ((float2)(lc_sample(vol, dims, qmax, (q)), 0.0f))
#define LC_SAMPLE_B(q) LC_SAMPLE(q)
#endif
#include "lc_passes.h"


#include "lc_shade.h"
#include "lc_classify.h"

__kernel void lc_render(__constant const LcParams* P, __global const lc_voxel* vol, __global const float4* lut,
                        __global const float* lut_ext, __global const float* block_info, __global float4* out,
                        __global uint* nsamples, __global const ulong* imap, __global const char* step_level,
                        __global const lc_sig* sig, __global const float4* dtab, __global const float4* ptab,
                        __global const uchar* prio, __global const float2* spos, __global const uchar* own,
                        __global float* state, __global const uchar* leaps) {
    const int j = get_global_id(0), i = get_global_id(1);
#ifdef LC_SCREEN /* the rays are laid out in rows of P->width, as many rows as they need */
    if (j >= P->width) return;
    const uint pix = (uint)i * (uint)P->width + (uint)j;
    if (pix >= (uint)P->screen_n) return;
    const float2 xy = spos[pix]; /* this ray's image position (adaptive screen-space sampling: a tile's sample) */
#else
    if (j >= P->width || i >= P->height) return;
    const uint pix = (uint)i * (uint)P->width + (uint)j;
    const float2 xy = (float2)((float)j + 0.5f, (float)i + 0.5f);
#endif

    const int4 dims = P->dims;
    const float3 qmax = convert_float3(dims.xyz - 1);
#ifdef LC_PASSES
#ifdef LC_SCREEN
    const uint st_rays = (uint)P->screen_n;
#else
    const uint st_rays = (uint)P->width * (uint)P->height;
#endif
#ifdef LC_SAMPLER_FULL
    const int4 pdims = P->pass_dims;
    const float3 pmax = convert_float3(pdims.xyz - 1), poff = convert_float3(P->pass_off.xyz);
#endif
#endif
#ifdef LC_SAMPLER_ATLAS
    LcAtlasGeom geom;
    geom.gx = P->grid.x; geom.gy = P->grid.y; geom.gz = P->grid.z; geom.B = (float)P->grid.w;
    LcBlk blk;
    blk.n = 0; blk.off = 0; blk.s = 1.0f; blk.lo = (float3)(0.0f); blk.hi = (float3)(-1.0f); blk.c = (float3)(0.0f);
    LcHood hood; /* the interblock neighbourhood last set up (lc_atlas.h) */
    hood.cx = -1;
#endif
    const float lut_scale = P->lut_scale, lut_off = -P->lut_lo * P->lut_scale, lut_fmax = (float)(P->lut_n - 1);
    const float lut_vis_lo = P->lut_vis_lo, lut_vis_hi = P->lut_vis_hi;
    const float t_stop = 1.0f - P->early_term; /* terminate once transmittance <= this */
#ifdef LC_DIST
    const float dist_scale = P->dist_scale, dist_off = -P->dist_lo * P->dist_scale;
    const float dist_fmax = (float)(P->dist_n - 1), dist_jmax = (float)(P->dist_rows - 1);
    const float dist_sscale = P->dist_sscale, dt_u = P->step * P->inv_unit; /* dt_u: a base step in TF units */
    const int dist_row = P->dist_n + 1, dist_spans = (P->dist_rows + 1) * dist_row;
#endif

    float3 C = (float3)(0.0f);
    float T = 1.0f;
#ifdef LC_PRECISE
    float3 C_c = (float3)(0.0f);
    float tau = 0.0f, tau_c = 0.0f;
#endif
#if !defined(LC_MODE_MIP) && !defined(LC_MODE_AVG) && !defined(LC_MODE_ISO)
    int sat = 0; /* the (first) integral is saturated */
#endif
#ifdef LC_TF2
    /* the second TF: its constants and ray state, named as the first's with the suffix 2 (lc_classify.h) */
    __global const float4* lut2 = lut + P->tf2_lut_at;
    __global const float* lut_ext2 = lut_ext + P->tf2_ext_at;
    const float lut_scale2 = P->tf2_lut_scale, lut_off2 = -P->tf2_lut_lo * P->tf2_lut_scale;
    const float lut_vis_lo2 = P->tf2_vis_lo, lut_vis_hi2 = P->tf2_vis_hi;
    const float r2_units = P->tf2_inv_unit / P->inv_unit;
    float3 C2 = (float3)(0.0f);
    float T2 = 1.0f;
    /* zero priority: the threshold of the second integral is zero, it counts as saturated from the start */
    const int ptile = P->prio_tile;
    const int pi_ = lc_clampi((int)xy.y, P->height - 1), pj_ = lc_clampi((int)xy.x, P->width - 1);
    int sat2 = ptile > 0 && prio[(uint)(pi_ / ptile) * (uint)P->prio_w + (uint)(pj_ / ptile)] == 0;
#ifdef LC_PRECISE
    float3 C_c2 = (float3)(0.0f);
    float tau2 = 0.0f, tau_c2 = 0.0f;
#endif
#ifdef LC_DIST
    __global const float4* dtab2 = dtab + P->tf2_dtab_at;
    const float dist_scale2 = P->tf2_dist_scale, dist_off2 = -P->tf2_dist_lo * P->tf2_dist_scale;
    const float dist_fmax2 = (float)(P->tf2_dist_n - 1), dt_u2 = P->step * P->tf2_inv_unit;
    const int dist_row2 = P->tf2_dist_n + 1, dist_spans2 = (P->dist_rows + 1) * dist_row2;
#endif
#ifdef LC_PREINT
    __global const float4* ptab2 = ptab + P->tf2_ptab_at;
    const float unit_w2 = 1.0f / P->tf2_inv_unit;
    const int pre_n2 = P->tf2_pre_n, pre_knots2 = P->tf2_pre_knots;
    float3 pre_q2 = (float3)(INFINITY);
    float pre_v2 = 0.0f;
#endif
#endif
#if defined(LC_PREINT) || defined(LC_MODE_AVG)
    const float unit_w = 1.0f / P->inv_unit; /* the TF's unit distance (world), for LC_SEG_LEN */
#endif
#ifdef LC_MODE_AVG
    float vsum = 0.0f, lsum = 0.0f;
#endif
#ifdef LC_MODE_ISO
    const float iso = P->iso;
    float iso_pv = NAN; /* the previous sample's value (NaN: none) and position, the hit's position */
    float3 iso_pq = (float3)(0.0f), iso_q = (float3)(0.0f);
    int hit = 0;
#if defined(LC_PASSES) && defined(LC_SHADE)
    float3 iso_g = (float3)(0.0f); /* the hit's gradient (lc_classify.h's LC_ISO_GRAD) */
#endif
#endif
#ifdef LC_PREINT
    const int pre_n = P->pre_n, pre_knots = P->pre_knots;
    float3 pre_q = (float3)(INFINITY); /* the last segment's back end and its value */
    float pre_v = 0.0f;
#endif
    float vmax = -INFINITY;
    uint taken = 0;
    int done = 0;
#ifdef LC_PASSES
    if (!P->pass_first) LC_STATE_LOAD
#endif

    float3 o, d;
    float t0, t1;
    lc_pixel_ray(P, xy.x, xy.y, &o, &d);
#ifdef LC_SHADE
    const float4 sh_k = P->shade;
    const float sh_gmin = P->shade_gmin, sh_gref = P->shade_gref;
    const float3 sh_gs = 0.5f * P->inv_spacing.xyz; /* central differences over two voxels, in world units */
    const float3 sh_l = P->light.w > 0.0f ? -d : P->light.xyz; /* w > 0: headlight */
    float3 sh_h = sh_l - d;
    const float sh_hn = sqrt(sh_h.x * sh_h.x + sh_h.y * sh_h.y + sh_h.z * sh_h.z);
    sh_h = sh_hn > 0.0f ? sh_h / sh_hn : sh_l;
#endif
    int march = lc_hit_box(P, o, d, &t0, &t1);
#ifdef LC_PASSES
    /* a ray that misses the region owns no sample in this pass: it only passes its state on */
    float t_pass_end = INFINITY;
    march = march && !done && lc_meets_box(P->pass_lo.xyz, P->pass_hi.xyz, o, d, t0, t1, &t_pass_end);
#endif
    if (march) {
        const float dt = P->step, inv_dt = 1.0f / dt;
        float nf = ceil((t1 - t0) / dt);
        nf = nf < 1.0f ? 1.0f : (nf > (float)P->max_samples ? (float)P->max_samples : nf);
        const int n = (int)nf, nlast = n - 1;
        float last = t0 + (float)nlast * dt; /* start of the last segment */
        last = last < t1 ? last : t1;
        const float len_last = t1 - last, r_last = len_last / dt, len_last_units = len_last * P->inv_unit;
#ifdef LC_JITTER
        const float u = lc_jitter(P->seed, pix);
#else
        const float u = 0.5f;
#endif
        const float3 q0 = (o - P->origin.xyz) * P->inv_spacing.xyz;
        const float3 dq = d * P->inv_spacing.xyz;
        /* sample k < nlast sits at t = t0 + (k + u) dt, i.e. at voxel coordinates qu + k dqk */
        const float3 qu = q0 + (t0 + u * dt) * dq, dqk = dt * dq;
#define LC_POS(kk) ((kk) < nlast ? t0 + ((float)(kk) + u) * dt : last + u * len_last)
/* out = the first sample index >= kk whose position is at or after time tb (n: none) */
#define LC_FIRST_AT(tb, kk, out)                                                     \
    {                                                                            \
        const float kf_ = ceil(((tb) - t0) * inv_dt - u);                        \
        out = kf_ < (float)(kk) ? (kk) : (kf_ > (float)nlast ? nlast : (int)kf_); \
        while (out > (kk) && LC_POS(out - 1) >= (tb)) out--;                     \
        while (out < n && LC_POS(out) < (tb)) out++;                             \
    }

#ifdef LC_ADAPTIVE
        /* 3D DDA over half-block cells: cell h covers voxel coordinates [h B/2 - 1/2, (h + 1) B/2 - 1/2), so each
         * cell lies in one block and in one interblock neighbourhood (cell boundaries are block faces and block
         * centres). step_level holds the cell's step level (grid 2G, C order z, y, x; -1: skip the cell). */
        const int cpb = 2; /* cells per block edge */
        const float Hc = (float)P->grid.w / (float)cpb;
        const int hx = cpb * P->grid.x, hy = cpb * P->grid.y, hz = cpb * P->grid.z;
        LC_DDA_BEGIN(Hc, hx, hy, hz)
        const float inv_unit = P->inv_unit;
#ifdef LC_LEAP
        LC_LEAP_BEGIN(hx, hy, hz)
#endif
/* the step code of cell (x, y, z), clamped into the grid (past it the ray has left the box) */
/* the index of cell (x, y, z) in the cells' arrays (step_level, block_info), clamped into the grid */
#define LC_CELL(x, y, z)                                                                                       \
    (((ulong)lc_clampi((z), hz - 1) * (ulong)hy + (ulong)lc_clampi((y), hy - 1)) * (ulong)hx +                  \
     (ulong)lc_clampi((x), hx - 1))
#define LC_STEP_CODE(x, y, z) ((int)step_level[LC_CELL(x, y, z)])
/* a level-0 cell's code, sampled or skipped */
#define LC_LEVEL0(c) ((c) == 0 || (c) == -1)
#define LC_NEAR_LEVEL0 8 /* renderer/data/atlas.py: NEAR_LEVEL0 */
        float t = t0;  /* where the next step starts */
        float tc = t0; /* where the ray enters the cell */
        /* iterations: at most one per sample plus one per cell crossed (a safety bound, never reached) */
        uint budget = (uint)P->max_samples * 2u + 4u * (uint)(hx + hy + hz) + 64u;
#ifdef LC_PRECISE
#define LC_R(len) ((len) * inv_dt)
#else
#define LC_R(len) ((len) == h ? -1.0f - (float)lvl : (len) * inv_unit)
        const int lut_row = P->lut_n + 1;
#ifdef LC_TF2
        const int lut_row2 = P->tf2_lut_n + 1;
#endif
#endif
        while (t < t1 && tc < t1 && !done && budget) {
            --budget;
#ifdef LC_PASSES
            if (t > t_pass_end) break; /* past the region: nothing more of this pass's */
#endif
            float tb = tnx < tny ? (tnx < tnz ? tnx : tnz) : (tny < tnz ? tny : tnz); /* leaves the cell */
            tb = tb < t1 ? tb : t1;
            const int code = LC_STEP_CODE(bx, by, bz);
            /* a skipped cell holds -(v + 1); v: the step level, | LC_NEAR_LEVEL0 for a coarse cell next to a
             * level-0 one */
            const int skip = code < 0, v_ = skip ? -code - 1 : code, lvl = v_ & (LC_NEAR_LEVEL0 - 1);
#ifdef LC_ADAPTIVE_NAIVE
            if (!skip) { /* one step of the starting cell's length, wherever it ends */
                const float h = dt * (float)(1 << lvl);
                const float len = t1 - t < h ? t1 - t : h;
                const float3 qs = q0 + (t + u * len) * dq;
                const float2 vs = LC_SAMPLE(qs);
                ++taken;
                LC_SAMPLE_BODY(vs.x, vs.y, LC_R(len), qs)
                t += len;
            } else {
                t = tb;
            }
            /* advance the DDA to the cell that holds t */
            while (tb <= t && tb < t1) {
                if (tnx <= tny && tnx <= tnz) { bx += sx; tnx += tdx; }
                else if (tny <= tnz) { by += sy; tny += tdy; }
                else { bz += sz; tnz += tdz; }
                tb = tnx < tny ? (tnx < tnz ? tnx : tnz) : (tny < tnz ? tny : tnz);
            }
            tc = t;
#else
            /* Level 0 is sampled on full resolution's lattice: from a level-0 cell into another the steps run
             * on (those whose sample lies in the cell are all whole; the last may end past tb, inside the next
             * cell, which goes on from its end), so a run of level-0 cells takes the samples of full resolution's
             * walk. In a coarse cell the steps start at the cell's entry and the last one is cut at tb (limited:
             * a coarse step never runs into a finer block; running on there as well saved samples at high
             * reductions but added image error). A skipped cell leaves t
             * where sampling it would for the cells after it: a level-0 one on the lattice (the next level-0 cell
             * finds its first step there, a coarse one starts at its entry anyway), a coarse one at its exit; so
             * skipping it changes no other sample. */
            /* a coarse cell's last step ends at its exit, or with LC_LATTICE ("lossless") before a level-0 cell
             * where the lattice's first step whose sample lies in that cell begins (within a base step of the
             * face), so that level 0 takes full resolution's samples there too */
#ifdef LC_LEAP
            /* in a cube of skipped level-0 cells (renderer/walk/leap.py: step_leaps; its edge r >= 2 in the ray's plane)
             * leave the cube at once: such cells leave t where it is, so the walk goes on as it would cell by cell */
            if (code == -1 && leap_on && bx >= 0 && bx < hx && by >= 0 && by < hy && bz >= 0 && bz < hz) {
                const int lf = leap_plane[LC_CELL(bx, by, bz)];
                if (lf >= 2) {
                    float te;
                    LC_DDA_LEAP(lf, te)
                    tc = te < t1 ? te : t1;
                    continue;
                }
            }
#endif
            const int ax = tnx <= tny && tnx <= tnz ? 0 : (tny <= tnz ? 1 : 2); /* the face the ray leaves by */
            float t_exit = tb;
#ifdef LC_LATTICE
            if ((v_ & LC_NEAR_LEVEL0) && tb < t1 &&
                LC_LEVEL0(LC_STEP_CODE(bx + (ax == 0 ? sx : 0), by + (ax == 1 ? sy : 0), bz + (ax == 2 ? sz : 0)))) {
                t_exit = t0 + (float)lc_ceil_i((tb - t0) * inv_dt - u) * dt;
                t_exit = t_exit < t1 ? t_exit : t1;
            }
#endif
            if (skip) {
                if (lvl > 0) t = t > t_exit ? t : t_exit;
            } else {
                if (lvl == 0) { /* the lattice's first step whose sample lies in the cell (after skipped cells) */
                    const int kk = lc_ceil_i((tc - t) * inv_dt - u);
                    t = kk > 0 ? t + (float)kk * dt : t;
                } else { /* a coarse cell's steps start at its entry */
                    t = t > tc ? t : tc;
                }
                if (tb > t) {
                    const float h = dt * (float)(1 << lvl);
                    blk = lc_blk_cell(imap, geom, lc_clampi(bx, hx - 1), lc_clampi(by, hy - 1), lc_clampi(bz, hz - 1),
                                      cpb);
#ifdef LC_OCTANTS
                    const int oct = (int)block_info[LC_CELL(bx, by, bz)];
                    const float inv_q = 2.0f / Hc; /* octants per voxel */
                    uint unseen = 0;               /* samples of the loop below not taken */
/* the octant index of sample position qs (voxel coordinates) along one axis: 0 or 1 inside the cell */
#define LC_OCT(c, b) ((int)(((c) + 0.5f) * inv_q) - 2 * (b))
/* whether a whole step's sample qs lies in an octant of the cell that can show something; one within rounding of
 * a face counts in the octant on the cell's side (whose bounds hold it, atlas_cells.cl) */
#define LC_SEEN(qs)                                                                                            \
    (oct == 255 || ((oct >> (lc_clampi(LC_OCT((qs).z, bz), 1) << 2 | lc_clampi(LC_OCT((qs).y, by), 1) << 1 |   \
                             lc_clampi(LC_OCT((qs).x, bx), 1))) & 1))
/* the same for the cut last step, whose sample may lie past the cell's face (LC_LATTICE: a coarse cell's last step
 * ends on the level-0 lattice beyond it), where no octant of this cell bounds it: it is taken there */
#define LC_SEEN_CUT(qs)                                                                                        \
    (oct == 255 || (uint)LC_OCT((qs).z, bz) > 1u || (uint)LC_OCT((qs).y, by) > 1u ||                             \
     (uint)LC_OCT((qs).x, bx) > 1u || LC_SEEN(qs))
#endif
                    int whole = 0, run_on = 0;
                    float tcut = t_exit > t ? t_exit : tb;
                    if (lvl == 0 && tb < t1) {
                        whole = lc_ceil_i((tb - t) * inv_dt - u); /* the steps whose sample lies before tb */
                        const float end = t + (float)whole * dt;
                        if (end > t1) {
                            tcut = t1; /* cut where the ray leaves the box, as full resolution's last step */
                        } else {
                            /* the next cell, and the cell of the last step's end if that lies past the next one
                             * (a ray through a cell's corner), at level 0 */
                            const float nnx = ax == 0 ? tnx + tdx : tnx, nny = ax == 1 ? tny + tdy : tny;
                            const float nnz = ax == 2 ? tnz + tdz : tnz;
                            const float tb_next = nnx < nny ? (nnx < nnz ? nnx : nnz) : (nny < nnz ? nny : nnz);
                            if (end > tb_next) {
                                const float3 pe = (q0 + end * dq + 0.5f) * (1.0f / Hc);
                                run_on = LC_LEVEL0(LC_STEP_CODE((int)pe.x, (int)pe.y, (int)pe.z));
                            } else {
                                run_on = LC_LEVEL0(LC_STEP_CODE(bx + (ax == 0 ? sx : 0), by + (ax == 1 ? sy : 0),
                                                                bz + (ax == 2 ? sz : 0)));
                            }
                        }
                    }
                    if (!run_on) { /* all whole but the last one, which ends at tcut */
                        if (lvl == 0) { /* the last one cut: level 0 keeps full resolution's lattice */
                            whole = lc_ceil_i((tcut - t) * inv_dt) - 1;
                        } else {
                            /* the nearest whole number of steps (at least one): the last one h/2 to 3h/2 long. A
                             * cut step took one more sample per coarse cell, often for a sliver of it: rounding
                             * takes fewer samples at every reduction for about the same image error; rounding
                             * down (steps up to 2h) added error */
                            whole = (int)((tcut - t) * inv_dt * lc_exp2_neg(lvl) + 0.5f) - 1;
                        }
                        whole = whole < 0 ? 0 : whole;
                    }
                    const float3 qa = q0 + (t + u * h) * dq, dqh = h * dq;
#ifdef LC_PRECISE
                    const float r_whole = (float)(1 << lvl);
#else
                    const float r_whole = -1.0f - (float)lvl;
#endif
                    int s = 0;
                    for (; s < whole && !done; ++s) { /* alpha from the level's table */
                        const float3 qs = qa + (float)s * dqh;
#ifdef LC_OCTANTS
                        if (!LC_SEEN(qs)) { ++unseen; continue; }
#endif
                        const float2 vs = LC_SAMPLE_B(qs);
                        LC_SAMPLE_BODY(vs.x, vs.y, r_whole, qs)
                    }
#ifdef LC_OCTANTS
                    taken += (uint)s - unseen;
#else
                    taken += (uint)s;
#endif
                    if (run_on) {
                        t += (float)whole * h;
                    } else {
                        if (!done) {
                            const float a = t + (float)whole * h;
                            float len = tcut - a;
                            len = lvl == 0 ? (len < h ? len : h) : len;
                            const float3 qs = q0 + (a + u * len) * dq;
#ifdef LC_OCTANTS
                            if (len > 0.0f && LC_SEEN_CUT(qs)) {
#else
                            if (len > 0.0f) {
#endif
                                const float2 vs = LC_SAMPLE_B(qs);
                                ++taken;
                                LC_SAMPLE_BODY(vs.x, vs.y, LC_R(len), qs)
                            }
                        }
                        t = tcut;
                    }
                }
            }
            tc = tb;
            if (tnx <= tny && tnx <= tnz) { bx += sx; tnx += tdx; }
            else if (tny <= tnz) { by += sy; tny += tdy; }
            else { bz += sz; tnz += tdz; }
#endif
        }
#undef LC_R
#undef LC_SEEN
#undef LC_SEEN_CUT
#undef LC_OCT
#undef LC_STEP_CODE
#undef LC_CELL
#undef LC_LEVEL0
#undef LC_NEAR_LEVEL0
#else
        int k = 0;
#if defined(LC_ESS) || defined(LC_PASSES)
        /* 3D DDA over the walk's cells: cell b covers voxel coordinates [b B - 1/2, (b + 1) B - 1/2). */
        const float B = (float)P->ess_grid.w;
        const int gx = P->ess_grid.x, gy = P->ess_grid.y, gz = P->ess_grid.z;
        LC_DDA_BEGIN(B, gx, gy, gz)
        int inside = 1;
#ifdef LC_LEAP
        LC_LEAP_BEGIN(gx, gy, gz)
#endif
#if defined(LC_PASSES) || defined(LC_SAMPLER_ATLAS)
        const int cpb = P->grid.w / P->ess_grid.w; /* walk cells per block edge */
#endif
#ifdef LC_PASSES
        int owned = 1; /* the last block's owner is this pass (samples past the grid's last block go with it) */
        const int bgx = P->grid.x, bgy = P->grid.y;
#endif
        /* A run of skipped cells costs its DDA steps only: the first sample after it is found once, where the
         * run ends (t_skip: the time it ends at; -inf: none), with the same result as cell by cell (the first
         * index >= k whose position is >= the time, and positions are monotone in k). */
        float t_skip = -INFINITY;
/* the walk's step into the next cell */
#define LC_WALK_STEP                                                                                           \
    {                                                                                                          \
        if (tnx <= tny && tnx <= tnz) {                                                                        \
            bx += sx; tnx += tdx; inside = bx >= 0 && bx < gx;                                                 \
        } else if (tny <= tnz) {                                                                               \
            by += sy; tny += tdy; inside = by >= 0 && by < gy;                                                 \
        } else {                                                                                               \
            bz += sz; tnz += tdz; inside = bz >= 0 && bz < gz;                                                 \
        }                                                                                                      \
    }
        while (k < n && !done) {
#ifdef LC_PASSES
            if (LC_POS(k) > t_pass_end) break; /* past the region: nothing more of this pass's */
#endif
            int k_end = n;
            int skip = 0;
            if (inside) {
                const float tb = tnx < tny ? (tnx < tnz ? tnx : tnz) : (tny < tnz ? tny : tnz); /* leaves block */
#ifdef LC_ESS
                const float info = block_info[(bz * gy + by) * gx + bx];
#endif
#ifndef LC_ESS
#elif defined(LC_MODE_MIP)
                skip = info <= vmax; /* nothing here can exceed the maximum so far */
#elif defined(LC_TF2)
                skip = ((int)info & ((sat ? 0 : 1) | (sat2 ? 0 : 2))) == 0; /* no running integral sees it */
#else
                skip = info <= 0.0f; /* TF opacity zero over the block's border-inclusive value range */
#endif
#ifdef LC_PASSES
                owned = own[((bz / cpb) * bgy + by / cpb) * bgx + bx / cpb];
                skip = skip || !owned;
#endif
                if (!skip) {
#if defined(LC_SAMPLER_ATLAS) && defined(LC_ESS) /* (without LC_ESS the walk only splits samples among passes) */
                    blk = lc_blk_cell(imap, geom, bx, by, bz, cpb);
#endif
#if defined(LC_LEAP) && defined(LC_SAMPLER_FULL)
                    /* the run of cells to sample that this one begins, sampled in one loop: each further cell
                     * costs its DDA step alone (the samples are the same: only a skip cuts the loop) */
                    float t_run = tb;
                    for (;;) {
                        LC_WALK_STEP
                        if (!inside || t_run >= t1 || block_info[(bz * gy + by) * gx + bx] <= 0.0f) break;
                        t_run = tnx < tny ? (tnx < tnz ? tnx : tnz) : (tny < tnz ? tny : tnz);
                    }
                    if (t_run < t1) LC_FIRST_AT(t_run, k, k_end)
#else
                    /* from k before a pending run of skipped cells is resolved below: the same index, since the
                     * samples the run covers lie before t_skip <= tb */
                    if (tb < t1) LC_FIRST_AT(tb, k, k_end)
#endif
                }
#ifdef LC_LEAP
                const int lr = skip && leap_on ? leap_plane[(bz * gy + by) * gx + bx] : 0;
                if (lr >= 2) { /* the cube of lr cells ahead of this one is empty: leave it at once */
                    float te;
                    LC_DDA_LEAP(lr, te)
                    if (te >= t1) break; /* the ray leaves the box in the cube: nothing after it */
                    inside = bx >= 0 && bx < gx && by >= 0 && by < gy && bz >= 0 && bz < gz;
                    t_skip = te;
                    continue;
                }
#endif
#if defined(LC_LEAP) && defined(LC_SAMPLER_FULL)
                if (skip) LC_WALK_STEP /* (a run to sample has stepped past itself) */
#else
                LC_WALK_STEP
#endif
                if (skip) {
                    if (tb >= t1) break; /* the ray leaves the box in this cell: nothing after it */
#ifdef LC_PASSES
                    if (tb > t_pass_end) break; /* every later sample lies past the region */
#endif
                    t_skip = tb;
                    continue;
                }
            }
            else {
#ifdef LC_SAMPLER_ATLAS
                blk.n = 0; /* rounding left samples beyond the grid's last block: march them (general sampler) */
#endif
#ifdef LC_PASSES
                skip = !owned;
#endif
            }
            if (t_skip > -INFINITY) { /* the first sample after the run of skipped cells just left */
                int k_at;
                LC_FIRST_AT(t_skip, k, k_at)
                k = k_at;
                t_skip = -INFINITY;
            }
            if (skip) {
                k = k_end;
                continue;
            }
#else
        {
            const int k_end = n;
#endif
            const int k_begin = k;
            /* uniform segments: no transcendental call in this loop (a call makes every live value spill) */
            const int k_uni = k_end < nlast ? k_end : nlast;
            for (; k < k_uni && !done; ++k) {
                const float3 qs = qu + (float)k * dqk;
                const float2 vs = LC_SAMPLE_B(qs);
#ifdef LC_PRECISE
                LC_SAMPLE_BODY(vs.x, vs.y, 1.0f, qs)
#else
                LC_SAMPLE_BODY(vs.x, vs.y, -1.0f, qs)
#endif
            }
            if (k == nlast && k_end == n && !done) { /* the last, shorter segment */
                const float3 qs = q0 + (last + u * len_last) * dq;
                const float2 vs = LC_SAMPLE_B(qs);
                ++k;
#ifdef LC_PRECISE
                LC_SAMPLE_BODY(vs.x, vs.y, r_last, qs)
#else
                LC_SAMPLE_BODY(vs.x, vs.y, len_last_units, qs)
#endif
            }
            taken += (uint)(k - k_begin);
        }
#endif /* LC_ADAPTIVE */
#undef LC_POS
#undef LC_FIRST_AT
#undef LC_WALK_STEP
    }

#ifdef LC_PASSES
    LC_STATE_SAVE
#endif
    float4 res;
#if defined(LC_MODE_MIP) || defined(LC_MODE_AVG) || defined(LC_MODE_ISO)
    /* the projections: the TF's colour and opacity, as given, at the projected value; isosurface: the TF's colour
     * at the iso value (lit with LC_SHADE), opaque */
#ifdef LC_MODE_MIP
    const int found = vmax > -INFINITY;
    const float vfin = LC_EXT(vmax);
#elif defined(LC_MODE_AVG)
    const int found = lsum > 0.0f;
    const float vfin = vsum / lsum;
#else
    const int found = hit;
    const float vfin = iso;
#endif
    if (found) {
        float f = vfin * lut_scale + lut_off;
        f = f > 0.0f ? (f < lut_fmax ? f : lut_fmax) : 0.0f;
        int i0 = (int)f;
        const float4 e = lut[i0] + (lut[i0 + 1] - lut[i0]) * (f - (float)i0);
#ifdef LC_MODE_ISO
#if defined(LC_PASSES) && defined(LC_SHADE)
        res = (float4)(lc_lit(e.xyz, iso_g, sh_l, sh_h, sh_k, sh_gmin, sh_gref), 1.0f);
#else
        res = (float4)(LC_SHADE_COL(e.xyz, iso_q), 1.0f);
#endif
#else
        res = (float4)(e.xyz * e.w, e.w);
#endif
    } else {
        res = (float4)(0.0f);
    }
#elif defined(LC_TF2) && defined(LC_PRECISE) /* the second integral over the first */
    res = (float4)(C2 + T2 * C, lc_alpha_of_depth(tau + tau2));
#elif defined(LC_TF2)
    res = (float4)(C2 + T2 * C, 1.0f - T2 * T);
#elif defined(LC_PRECISE)
    res = (float4)(C, lc_alpha_of_depth(tau));
#else
    res = (float4)(C, 1.0f - T);
#endif
#ifdef LC_BACKGROUND
    res += (1.0f - res.w) * P->background;
#endif
    out[pix] = res;
    nsamples[pix] = taken;
}
