/* raycast.cl: lodcast's ray caster. One work-item per pixel (or per tile sample, LC_SCREEN).
 *
 * The kernel is four pieces, each a struct and the functions over it, as Open VKL and pbrt-v4 cut a volume
 * integrator: the sampler (lc_sampler.h: LcSampler, the field at a point), the interval iterator (lc_walk.h:
 * LcWalk and lc_walk_next, the runs of samples worth taking), the classifier (lc_classify.h: LcTf and LcRay, one
 * TF applied to one sample and composited into one integral; lc_preint.h, lc_shade.h) and the integrator
 * (lc_integrator.h: LcIntegrator, what a ray makes of its samples in each mode). lc_render below sets them up and
 * runs the loop: for each interval, its samples through the sampler into the integrator.
 *
 * Specialised only by -D options (lodcast.renderer.kernel.config.KernelConfig.build_options()); the projection
 * (P->ortho), jitter (P->jitter, P->seed) and the background (P->background, zero for none) are parameters:
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
 *   LC_PRECISE        compensated (Kahan) sums of optical depth and colour, for rays of very many samples
 *   LC_CLIP           clip planes (lc_common.h: the ray's interval is cut exactly at each plane; a crop box needs no
 *                     option, the host intersects it with the volume's box)
 *   LC_PREINT         pre-integrated classification of each segment by the scalars at its ends (lc_preint.h)
 *   LC_GRADIENT_OPACITY  (composite) a TF's extinction scaled by min(1, |gradient| / its gradient_opacity)
 *                     (lc_classify.h: lc_gradient_look; P->grad_op, P->tf2_grad_op)
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
 *   LC_PASSES         one pass of a render in several (renderer/data/passes.py): samples only in the blocks `own` marks, the
 *                     full sampler on a sub-volume at P->pass_off, the integrator's state carried in `state`
 *                     (lc_integrator.h); implies the block walk (without LC_ESS it skips nothing else). Every
 *                     pass marches every ray exactly as a single pass would, so each sample falls to exactly one
 *                     pass, and the result is the single-pass image, bit for bit
 *
 * Sampling (lc_walk.h): the ray's part inside the box is cut into segments of the base step, the last one
 * shorter, each sampled once at fraction u of its length (1/2, or the pixel's jitter): one lattice per ray whether
 * or not cells are skipped.
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
#include "lc_walk.h"

/* The ray of this work-item: its index pix among the launch's rays and its image position xy (LC_SCREEN: the
 * rays are laid out in rows of P->width, as many rows as they need, each through a tile's sample spos[pix]) */
static inline int lc_ray_of_item(__constant const LcParams* P, __global const float2* spos, uint* pix, float2* xy) {
    const int j = get_global_id(0), i = get_global_id(1);
    if (j >= P->width) return 0;
    *pix = (uint)i * (uint)P->width + (uint)j;
#ifdef LC_SCREEN
    if (*pix >= (uint)P->screen_n) return 0;
    *xy = spos[*pix];
#else
    if (i >= P->height) return 0;
    *xy = (float2)((float)j + 0.5f, (float)i + 0.5f);
#endif
    return 1;
}

/* the rays of this launch (LC_PASSES: the stride of their state) */
static inline uint lc_rays(__constant const LcParams* P) {
#ifdef LC_SCREEN
    return (uint)P->screen_n;
#else
    return (uint)P->width * (uint)P->height;
#endif
}

__kernel void lc_render(__constant const LcParams* P, __global const lc_voxel* vol, __global const float4* lut,
                        __global const float* lut_ext, __global const float* block_info, __global float4* out,
                        __global uint* nsamples, __global const ulong* imap, __global const char* step_level,
                        __global const lc_sig* sig, __global const float4* dtab, __global const float4* ptab,
                        __global const uchar* prio, __global const float2* spos, __global const uchar* own,
                        __global float* state, __global const uchar* leaps) {
    uint pix;
    float2 xy;
    if (!lc_ray_of_item(P, spos, &pix, &xy)) return;

    float3 o, d;
    float t0, t1;
    lc_pixel_ray(P, xy.x, xy.y, &o, &d);
    LcSampler smp = lc_sampler_make(P, vol, sig, imap);
    LcClassifier cls;
    cls.tf = lc_tf_make(P, lut, lut_ext, dtab, ptab, 0);
#ifdef LC_TF2
    cls.tf2 = lc_tf_make(P, lut, lut_ext, dtab, ptab, 1);
#endif
    cls.m = lc_march_make(P, d, pix);
    cls.sh = lc_shade_make(P, d);
    LcIntegrator it = lc_integrator_make(P, prio, xy);
#ifdef LC_PASSES
    if (!P->pass_first) lc_state_move(&it, state + pix, lc_rays(P), 0);
#endif

    int march = lc_hit_box(P, o, d, &t0, &t1);
    float t_pass_end = INFINITY;
#ifdef LC_PASSES
    /* a ray that misses the region owns no sample in this pass: it only passes its state on */
    march = march && !it.done && lc_meets_box(P->pass_lo.xyz, P->pass_hi.xyz, o, d, t0, t1, &t_pass_end);
#endif
    if (march) {
        LcWalk walk = lc_walk_make(P, &cls.m, o, t0, t1, t_pass_end, block_info, step_level, own, leaps);
        LcInterval iv;
        while (!it.done && lc_walk_next(&walk, &iv, &it)) {
            lc_sampler_enter(&smp, iv.cell);
            int s = iv.s0;
            uint unseen = 0; /* whole steps not taken (LC_OCTANTS) */
            for (; s < iv.s1 && !it.done; ++s) {
                const float3 q = iv.qa + (float)s * iv.dqs;
                if (!lc_interval_sees(&iv, q)) {
                    ++unseen;
                    continue;
                }
                const float2 vs = lc_sampler_in_cell(&smp, q);
                lc_integrate(&it, &cls, &smp, vs.x, vs.y, iv.r, q);
            }
            it.taken += (uint)(s - iv.s0) - unseen;
            if (iv.cut && !it.done && lc_interval_sees_cut(&iv, iv.qc)) {
                const float2 vs = lc_sampler_in_cell(&smp, iv.qc);
                ++it.taken;
                lc_integrate(&it, &cls, &smp, vs.x, vs.y, iv.rc, iv.qc);
            }
        }
    }
#ifdef LC_PASSES
    lc_state_move(&it, state + pix, lc_rays(P), 1);
#endif
    float4 res = lc_integrator_finish(&it, &cls);
    res += (1.0f - res.w) * P->background; /* (premultiplied; none: zero) */
    out[pix] = res;
    nsamples[pix] = it.taken;
}
