// Optimal piecewise-constant segmentation of block histograms (thesis §3.2.1): one work-item per histogram.
// The same dynamic programme as histogram.simplify's NumPy path: bins compressed into runs of equal counts (an
// optimal boundary lies at a run end), D[m][j] = min_i D[m-1][i] + sse(i, j) over runs, then the best piece count
// <= K. sse(i, j) grows as i moves left and D >= 0, so the inner search stops once sse alone reaches the best.
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

inline double sse(__global const double* c, __global const double* s1, __global const double* s2, int i, int j) {
    double n = c[j] - c[i];
    double t = s1[j] - s1[i];
    double e = (s2[j] - s2[i]) - (n > 0.0 ? t * t / n : 0.0);
    return e > 0.0 ? e : 0.0;
}

__kernel void segment(__global const uint* hist, const int nbins, const int K, const int count,
                      __global double* scratch, __global int* run_end, __global short* arg,
                      __global ushort* starts_out, __global float* heights_out) {
    const int blk = get_global_id(0);
    if (blk >= count) return;
    const int n1 = nbins + 1;
    __global const uint* h = hist + (size_t)blk * nbins;
    __global double* c = scratch + (size_t)blk * 5 * n1;
    __global double* s1 = c + n1;
    __global double* s2 = s1 + n1;
    __global double* dprev = s2 + n1;
    __global double* dcur = dprev + n1;
    __global int* re = run_end + (size_t)blk * n1;
    __global short* a = arg + (size_t)blk * (K + 1) * n1;

    // runs: re[r] is the bin where run r ends (re[0] = 0); prefix sums over runs
    int r = 0;
    c[0] = 0.0; s1[0] = 0.0; s2[0] = 0.0; re[0] = 0;
    for (int i = 0; i < nbins;) {
        const uint v = h[i];
        int j = i + 1;
        while (j < nbins && h[j] == v) j++;
        const double len = (double)(j - i), dv = (double)v;
        r++;
        c[r] = c[r - 1] + len;
        s1[r] = s1[r - 1] + len * dv;
        s2[r] = s2[r - 1] + len * dv * dv;
        re[r] = j;
        i = j;
    }
    const int mmax = min(K, r);
    for (int j = 1; j <= r; j++) dprev[j] = sse(c, s1, s2, 0, j);
    double best_total = dprev[r];
    int best_m = 1;
    for (int m = 2; m <= mmax; m++) {
        for (int j = m; j <= r; j++) {
            double best = INFINITY;
            int bi = j - 1;
            for (int i = j - 1; i >= m - 1; i--) {
                const double e = sse(c, s1, s2, i, j);
                if (e >= best) break;
                const double val = dprev[i] + e;
                if (val < best) { best = val; bi = i; }
            }
            dcur[j] = best;
            a[m * n1 + j] = (short)bi;
        }
        if (dcur[r] < best_total) { best_total = dcur[r]; best_m = m; }
        __global double* t = dprev; dprev = dcur; dcur = t;
    }
    // backtrack the chosen piece count; unused pieces are empty at the end
    __global ushort* st = starts_out + (size_t)blk * (K + 1);
    __global float* ht = heights_out + (size_t)blk * K;
    int bounds[65];
    int j = r;
    bounds[best_m] = r;
    for (int m = best_m; m > 1; m--) {
        j = a[m * n1 + j];
        bounds[m - 1] = j;
    }
    bounds[0] = 0;
    for (int p = 0; p <= K; p++) st[p] = (ushort)(p <= best_m ? re[bounds[p]] : nbins);
    for (int p = 0; p < K; p++) {
        if (p < best_m) {
            const int lo = bounds[p], hi = bounds[p + 1];
            ht[p] = (float)((s1[hi] - s1[lo]) / (c[hi] - c[lo]));
        } else {
            ht[p] = 0.0f;
        }
    }
}
