/* lc_types.h: the parameter block shared by the host and every lodcast kernel.
 *
 * Mirrored field by field by lodcast.renderer.kernel.structs.PARAMS_DTYPE (NumPy); tests/test_renderer_structs.py
 * checks size and every offset through a probe kernel. Vectors are float4/int4 (16-byte aligned, no float3
 * padding surprises) and come first; scalars are 4 bytes each. World vectors are (x, y, z, unused) with x the
 * last array axis. Append new fields at the end (keeping the size a multiple of 16) and mirror them.
 */
#ifndef LC_TYPES_H
#define LC_TYPES_H

typedef struct LcParams {
    float4 eye;         /* world; orthographic: centre of the image plane */
    float4 cam_f;       /* forward, right, up: orthonormal */
    float4 cam_r;
    float4 cam_u;
    float4 box_lo;      /* world box: origin - spacing/2 ... origin + (shape - 1/2) spacing */
    float4 box_hi;
    float4 origin;      /* world position of voxel (0,0,0)'s centre */
    float4 inv_spacing; /* 1 / spacing */
    float4 background;  /* premultiplied: (r a, g a, b a, a) */
    int4 dims;          /* voxels nx, ny, nz; w unused */
    int4 grid;          /* blocks gx, gy, gz; w: block edge B in voxels of this level */
    float half_w;       /* perspective: tan(fov/2) W/H; orthographic: half the view width (world) */
    float half_h;       /* perspective: tan(fov/2);     orthographic: half the view height (world) */
    float step;         /* world units */
    float inv_unit;     /* 1 / TF opacity unit distance (world) */
    float lut_lo;       /* LUT entry k holds the TF at value lut_lo + k / lut_scale */
    float lut_scale;
    int lut_n;
    float early_term;   /* stop when accumulated opacity >= this */
    int width;
    int height;
    uint seed;          /* jitter */
    int max_samples;    /* per ray, host-checked bound (int arithmetic on sample indices stays in range) */
    float lut_vis_lo;   /* the LUT interpolant has non-zero opacity only for LUT coordinates f in */
    float lut_vis_hi;   /* (lut_vis_lo, lut_vis_hi); samples outside are transparent without a lookup */
    int dist_n;         /* distribution table (LC_DIST): entries per row (plus one repeated), */
    int dist_rows;      /* rows (plus one repeated); entry i of row j: value dist_lo + i / dist_scale, */
    float dist_lo;      /* standard deviation std_max (j / (rows - 1))^2, i.e. j = sqrt(std) dist_sscale */
    float dist_scale;
    float dist_sscale;
    int jitter;         /* 1: each pixel's samples sit at a random fraction of their steps (seeded), else at 1/2 */
    float4 clip[6];     /* LC_CLIP: planes (nx, ny, nz, w) world; a point x is kept where n.x + w >= 0 */
    float4 light;       /* LC_SHADE: unit world direction towards the light (headlight: unused) */
    float4 shade;       /* LC_SHADE: ambient, diffuse, specular, shininess */
    float shade_gmin;   /* LC_SHADE: gradient magnitude (data units per world unit) below which a sample is unlit */
    int n_clip;         /* LC_CLIP: planes in use (<= 6) */
    int pre_n;          /* LC_PREINT: the pre-integration table has pre_n x pre_n entries, then pre_knots rows */
    int pre_knots;      /* of its axis' warp (lc_preint.h) */
    int ortho;          /* 1: orthographic projection, else perspective */
    float iso;          /* LC_MODE_ISO: the iso value */
    float shade_gref;   /* LC_SHADE: gradient magnitude at which a sample is fully lit (0: no weighting) */
    float grad_op;      /* LC_GRADIENT_OPACITY: 1 / the TF's gradient_opacity (0: none) */
    /* LC_TF2: the second TF. Its tables follow the first's in the same buffers, at these entry offsets */
    int tf2_lut_at;     /* float4 entries into lut */
    int tf2_ext_at;     /* float entries into lut_ext */
    int tf2_dtab_at;    /* float4 entries into dtab (LC_DIST) */
    int tf2_ptab_at;    /* float4 entries into ptab (LC_PREINT) */
    float tf2_lut_lo;   /* its LUT, as lut_lo, lut_scale, lut_n, lut_vis_lo, lut_vis_hi are the first's */
    float tf2_lut_scale;
    int tf2_lut_n;
    float tf2_vis_lo;
    float tf2_vis_hi;
    float tf2_inv_unit; /* 1 / its opacity unit distance (world) */
    int tf2_dist_n;     /* its distribution table's mean axis (rows and std axis as the first's) */
    float tf2_dist_lo;
    float tf2_dist_scale;
    int tf2_pre_knots;  /* its pre-integration table's axis */
    float tf2_grad_op;  /* the same of tf2 */
    int tf2_pre_n;
    int prio_tile;      /* priority map: one byte per prio_tile x prio_tile pixels (0: no map, every pixel has */
    int prio_w;         /* priority), prio_w tiles per row */
    int screen_n;       /* LC_SCREEN: the rays (tile samples) of this launch */
    int pad5;
    /* LC_PASSES: one pass of a render in several (renderer/data/passes.py) */
    float4 pass_lo;     /* world box that holds every sample this pass owns (rays that miss it only pass on */
    float4 pass_hi;     /* their state) */
    int4 pass_off;      /* full sampler: the voxel (x, y, z) of level 0 at which the pass's sub-volume starts, */
    int4 pass_dims;     /* and its extent */
    int pass_first;     /* 1: the first pass (the ray state starts fresh instead of being loaded) */
    uint leap_planes;   /* LC_LEAP: per octant o of ray directions (lc_common.h: LC_LEAP_BEGIN) the index of its plane
                         * in `leaps`, 4 bits at bit 4 o; 15 (LC_NO_PLANE): none (its rays walk cell by cell) */
    int pad7;
    int pad8;
    int4 ess_grid;      /* LC_ESS: the block walk's cells (x, y, z; w: edge in voxels, dividing grid.w): full
                         * resolution walks cells finer than the blocks, the atlas half-block cells */
} LcParams;

#endif
