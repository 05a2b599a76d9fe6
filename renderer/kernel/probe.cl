/* probe.cl: reads every LcParams field back, so that tests can check NumPy's mirror of the layout. */
#include "lc_types.h"

__kernel void lc_probe(__constant const LcParams* P, __global float* f, __global int* n) {
    const float4 v[9] = {P->eye, P->cam_f, P->cam_r, P->cam_u, P->box_lo, P->box_hi, P->origin,
                         P->inv_spacing, P->background};
    for (int k = 0; k < 9; ++k) vstore4(v[k], k, f);
    f[36] = P->half_w; f[37] = P->half_h; f[38] = P->step; f[39] = P->inv_unit;
    f[40] = P->lut_lo; f[41] = P->lut_scale; f[42] = P->early_term;
    vstore4(P->dims, 0, n);
    vstore4(P->grid, 1, n);
    n[8] = P->lut_n; n[9] = P->width; n[10] = P->height; n[11] = (int)P->seed; n[12] = P->max_samples;
    n[13] = (int)sizeof(LcParams);
    f[43] = P->lut_vis_lo; f[44] = P->lut_vis_hi;
    n[14] = P->dist_n; n[15] = P->dist_rows;
    f[45] = P->dist_lo; f[46] = P->dist_scale; f[47] = P->dist_sscale;
    for (int k = 0; k < 6; ++k) vstore4(P->clip[k], 12 + k, f); /* f[48..71] */
    vstore4(P->light, 18, f); vstore4(P->shade, 19, f);       /* f[72..79] */
    f[80] = P->shade_gmin; f[83] = P->iso; f[84] = P->shade_gref;
    n[16] = P->n_clip; n[17] = P->pre_n;
    n[18] = P->tf2_lut_at; n[19] = P->tf2_ext_at; n[20] = P->tf2_dtab_at; n[21] = P->tf2_ptab_at;
    n[22] = P->tf2_lut_n; n[23] = P->tf2_dist_n; n[24] = P->tf2_pre_n; n[25] = P->prio_tile; n[26] = P->prio_w;
    f[85] = P->tf2_lut_lo; f[86] = P->tf2_lut_scale; f[87] = P->tf2_vis_lo; f[88] = P->tf2_vis_hi;
    f[89] = P->tf2_inv_unit; f[90] = P->tf2_dist_lo; f[91] = P->tf2_dist_scale;
    n[44] = P->pre_knots; n[45] = P->tf2_pre_knots;
    n[46] = P->jitter; n[47] = P->ortho;
    f[92] = P->grad_op; f[93] = P->tf2_grad_op;
    vstore4(P->pass_lo, 24, f); vstore4(P->pass_hi, 25, f); /* f[96..103] */
    vstore4(P->pass_off, 7, n); vstore4(P->pass_dims, 8, n); /* n[28..35] */
    n[36] = P->pass_first;
    vstore4(P->ess_grid, 10, n); /* n[40..43] */
}
