/* zeta.cl: the level-of-detail selection's per-block TF errors (renderer/lod/level_error.py: block_zetas; its
 * module doc says what they are), one work-item per block, on the device.
 *
 * Per block: the quadrature of its simplified histogram (LC_K pieces, three Gauss-Legendre nodes each), and at
 * each node the unit-slab colour T* in CIELUV (a bilinear lookup in `luv`, the distribution table's grid over
 * (row j, mean entry i)) against what level k shows there (row of the block's spread s_k, or for "mean"
 * classification (LC_MEAN) the value shrunk towards the block mean). The sums over nodes run in one pass with a
 * register per level, so a block costs O(K * L) lookups and nothing is kept per node. level_error.py's NumPy
 * path is the reference this reproduces (tests/test_level_error.py compares them); the float32 arithmetic is
 * the same as its table lookups', whose results the selection compares with 0.5 ΔE.
 *
 * LC_K: pieces per block; LC_L: levels; LC_WORST: also the worst value's error per level; LC_NO_LEVEL_ERRORS: not
 * the level errors (out stays 0), the rest alike (the prediction's pass under distribution classification). */

typedef struct {
    float lo, scale, std_scale, sheet_floor;
    int n, rows, n_points, n_blocks;
} LcZetaTable;

/* Position along the table's mean axis: entry i, next entry i1, weight *w (classification.py: mean_axis). */
inline int lc_mean_axis(const LcZetaTable* T, float v, int* i1, float* w) {
    const float fi = clamp((v - T->lo) * T->scale, 0.0f, (float)(T->n - 1));
    const int i = min((int)fi, max(T->n - 2, 0));
    *i1 = i + (T->n > 1);
    *w = fi - (float)i;
    return i;
}

/* Position along the table's sqrt(std) axis (classification.py: std_axis). */
inline int lc_std_axis(const LcZetaTable* T, float s, int* j1, float* w) {
    const float fj = clamp(sqrt(fmax(s, 0.0f)) * T->std_scale, 0.0f, (float)(T->rows - 1));
    const int j = min((int)fj, max(T->rows - 2, 0));
    *j1 = j + (T->rows > 1);
    *w = fj - (float)j;
    return j;
}

inline float3 lc_luv_at(__global const float* luv, int n, int j, int i) {
    return vload3(j * n + i, luv);
}

/* Bilinear lookup (classification.py: lerp) at mean position (i, i1, wi) and row position (j, j1, wj). */
inline float3 lc_lerp(__global const float* luv, int n, int i, int i1, float wi, int j, int j1, float wj) {
    const float3 g00 = lc_luv_at(luv, n, j, i), g01 = lc_luv_at(luv, n, j, i1);
    const float3 a = g00 + (g01 - g00) * wi;
    if (wj == 0.0f) return a;
    const float3 g10 = lc_luv_at(luv, n, j1, i), g11 = lc_luv_at(luv, n, j1, i1);
    const float3 b = g10 + (g11 - g10) * wi;
    return a + (b - a) * wj;
}

/* The colour of point classification (row 0) at value v. */
inline float3 lc_row0(const LcZetaTable* T, __global const float* luv, float v) {
    int i1;
    float wi;
    const int i = lc_mean_axis(T, v, &i1, &wi);
    return lc_lerp(luv, T->n, i, i1, wi, 0, T->rows > 1, 0.0f);
}

/* The TF's opacity at v: piecewise linear between its points, constant beyond the ends (np.interp). */
inline float lc_tf_opacity(__global const float2* pts, int m, float v) {
    if (v <= pts[0].x) return pts[0].y;
    if (v >= pts[m - 1].x) return pts[m - 1].y;
    int lo = 0, hi = m - 1;  /* pts[lo].x <= v < pts[hi].x */
    while (hi - lo > 1) {
        const int mid = (lo + hi) / 2;
        if (pts[mid].x <= v) lo = mid; else hi = mid;
    }
    const float2 a = pts[lo], b = pts[hi];
    return a.y + (b.y - a.y) * (v - a.x) / (b.x - a.x);
}

inline float lc_sq(float3 d) { return dot(d, d); }

/* ax: (lo, scale, std_scale, sheet floor), sz: (n, rows, TF points, blocks), LcZetaTable's fields (vectors, not a
 * struct by value: every OpenCL driver passes those alike). */
__kernel void lc_zeta(const float4 ax, const int4 sz, __global const float* luv, __global const float2* pts,
                      __global const int* starts,      /* (n_blocks, LC_K + 1) bin indices */
                      __global const float* edges,     /* bin edges */
                      __global const float* heights,   /* (n_blocks, LC_K) */
                      __global const float* level_std, /* (n_blocks, LC_L) */
                      __global const float* mean_hr,   /* (n_blocks, 2): mean, half the border-inclusive range */
                      __global float* out,             /* (n_blocks, LC_L) */
                      __global float* out_worst,       /* (n_blocks, LC_L), written with LC_WORST */
                      __global float* out_step,        /* (n_blocks, 5): step, mean opacity, mean squared opacity,
                                                        * visible share, the step's error-weighted opacity */
                      __global float* out_spread) {    /* (n_blocks, LC_L): the spread ς(k) (prediction.py) */
    const LcZetaTable T = {ax.x, ax.y, ax.z, ax.w, sz.x, sz.y, sz.z, sz.w};
    const int b = get_global_id(0);
    if (b >= T.n_blocks) return;
    const float NODE = 0.7745966692414834f;  /* sqrt(3/5) */
    __global const int* st = starts + (size_t)b * (LC_K + 1);
    __global const float* hb = heights + (size_t)b * LC_K;
    __global const float* sb = level_std + (size_t)b * LC_L;
    float total = 0.0f;
    for (int p = 0; p < LC_K; ++p) total += (float)(st[p + 1] - st[p]) * hb[p];
    const float inv_total = 1.0f / fmax(total, 1e-30f);
    const float mbar = mean_hr[2 * b], half_range = mean_hr[2 * b + 1];

    int rj[LC_L], rj1[LC_L];  /* each level's row position (distribution), or shrink factor (mean) */
    float rw[LC_L];
    const float s_top = fmax(sb[LC_L - 1], 1e-30f);
#ifdef LC_MEAN
    float rho[LC_L];
#endif
#ifdef LC_WORST
    float sw[LC_L];
    int wj[LC_L], wj1[LC_L];
    float ww[LC_L], worst[LC_L];
#endif
    float acc[LC_L];
    for (int k = 0; k < LC_L; ++k) {
        acc[k] = 0.0f;
        rj[k] = lc_std_axis(&T, sb[k], &rj1[k], &rw[k]);
#ifdef LC_MEAN
        const float r = sb[k] / s_top;
        rho[k] = sqrt(clamp(1.0f - r * r, 0.0f, 1.0f));
#endif
#ifdef LC_WORST
        const float blocks_per = (float)(1 << (LC_L - 1 - k));
        sw[k] = fmin(sb[k] * sqrt(blocks_per * blocks_per * blocks_per), half_range);
        wj[k] = lc_std_axis(&T, sw[k], &wj1[k], &ww[k]);
        worst[k] = 0.0f;
#endif
    }
#if LC_L > 1
    const float s1 = sb[1];
#endif
    float a1 = 0.0f, a2 = 0.0f, vis = 0.0f, step = 0.0f, step_a = 0.0f;
    float3 held = (float3)(0.0f);  /* the mean colour of the values the block holds */
    for (int p = 0; p < LC_K; ++p) {
        const float lo = edges[st[p]], hi = edges[st[p + 1]];
        const float wp = (float)(st[p + 1] - st[p]) * hb[p] * inv_total;
        if (wp == 0.0f) continue;
        const float mid = 0.5f * (lo + hi), width = 0.5f * (hi - lo);
        for (int q = 0; q < 3; ++q) {
            const float x = mid + width * (float)(q - 1) * NODE;
            const float wq = wp * (q == 1 ? 8.0f / 18.0f : 5.0f / 18.0f);  /* level_error.py: _WEIGHTS */
            const float a = lc_tf_opacity(pts, T.n_points, x);
            a1 += wq * a;
            a2 += wq * a * a;
            vis += a > 0.0f ? wq : 0.0f;
#if LC_L > 1
            const float3 d = lc_row0(&T, luv, x + s1) - lc_row0(&T, luv, x - s1);
            step += wq * 0.25f * lc_sq(d);
            step_a += wq * 0.25f * lc_sq(d) * a;
            int i1;
            float wi;
            const int i = lc_mean_axis(&T, x, &i1, &wi);
            const float3 tstar = lc_lerp(luv, T.n, i, i1, wi, 0, T.rows > 1, 0.0f);
            held += wq * tstar;
#ifndef LC_NO_LEVEL_ERRORS
            for (int k = 1; k < LC_L; ++k) {
#ifdef LC_MEAN
                const float3 shown = lc_row0(&T, luv, mbar + rho[k] * (x - mbar));
#else
                const float3 shown = lc_lerp(luv, T.n, i, i1, wi, rj[k], rj1[k], rw[k]);
#endif
                const float d2 = lc_sq(tstar - shown);
                acc[k] += wq * d2;
#ifdef LC_WORST
                float dw = d2;
                for (int sh = -1; sh <= 1; ++sh) {
                    int m1;
                    float mw;
                    const int m0 = lc_mean_axis(&T, x + (float)sh * sw[k], &m1, &mw);
                    dw = fmax(dw, lc_sq(tstar - lc_lerp(luv, T.n, m0, m1, mw, wj[k], wj1[k], ww[k])));
                }
                worst[k] = fmax(worst[k], dw);
#endif
            }
#endif
#endif
        }
    }
    const float sheet = fmax(vis, T.sheet_floor);
    for (int k = 0; k < LC_L; ++k) {
        out[(size_t)b * LC_L + k] = k == 0 ? 0.0f : sqrt(fmax(acc[k], 0.0f) / sheet);
#ifdef LC_WORST
        out_worst[(size_t)b * LC_L + k] = k == 0 ? 0.0f : sqrt(worst[k]);
#endif
    }
    const float step_b = LC_L > 1 ? sqrt(fmax(step, 0.0f) / sheet) : 0.0f;
    /* the spread (level_error.py): the step's colour change scaled to the level's deviation, and how far the
     * classification's colour at the block's mean is from the mean colour of its values, by (s_k / s_top)^2 */
    int im1;
    float wim;
    const int im = lc_mean_axis(&T, mbar, &im1, &wim);
#ifdef LC_MEAN
    const float3 modelled = lc_lerp(luv, T.n, im, im1, wim, 0, T.rows > 1, 0.0f);  /* the TF at the mean */
#endif
    for (int k = 0; k < LC_L; ++k) {
        if (k == 0) {
            out_spread[(size_t)b * LC_L] = 0.0f;
            continue;
        }
        const float hidden = sb[1] > 0.0f ? step_b * sb[k] / sb[1] : 0.0f;  /* (k >= 1: LC_L > 1) */
#ifndef LC_MEAN
        const float3 modelled = lc_lerp(luv, T.n, im, im1, wim, rj[k], rj1[k], rw[k]);
#endif
        const float r = sb[k] / s_top;
        const float model = lc_sq(held - modelled) * r * r;
        out_spread[(size_t)b * LC_L + k] = sqrt(hidden * hidden + model / sheet);
    }
    out_step[5 * b] = step_b;
    out_step[5 * b + 1] = a1;
    out_step[5 * b + 2] = a2;
    out_step[5 * b + 3] = vis;
    out_step[5 * b + 4] = step > 0.0f ? step_a / step : 0.0f;
}
