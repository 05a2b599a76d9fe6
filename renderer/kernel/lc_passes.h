/* lc_passes.h: a render in several passes (LC_PASSES), for raycast.cl (renderer/data/passes.py plans them).
 *
 * When the volume data a render needs does not fit the device budget, the block grid is cut into regions of whole
 * blocks, and each pass uploads one region's data (plus the neighbours its samples read) and takes only the
 * samples of the blocks it owns (`own`, one byte per block). Every pass marches every ray exactly as a single pass
 * would — same entry, same lattice, same block walk or adaptive cell walk — so each sample falls to exactly one
 * pass, the one that owns the block the walk assigns it to; the passes run in a front-to-back visibility order of
 * the regions, and between passes each ray's integration state (colour, transmittance, saturation, compensated
 * sums, the pre-integration cache, the projections' accumulators, the sample count) waits in `state`. The result
 * is the single-pass image, bit for bit.
 *
 * LC_STATE_LOAD / LC_STATE_SAVE move the state of ray `pix` between its private variables and `state`, field f of
 * ray p at state[f * n_rays + p] (coalesced on a GPU), at most LC_STATE_FLOATS fields (mirrored by
 * lodcast.renderer.kernel.structs.STATE_FLOATS). One list, LC_STATE(X), names the fields of the compiled configuration:
 * X##F a float, X##I an int, X##U a uint, X##3 a float3, so that loading and saving cannot disagree on the order.
 */
#ifndef LC_PASSES_H
#define LC_PASSES_H
#ifdef LC_PASSES

#define LC_STATE_FLOATS 32

#define LC_LDF(v) v = st_[(ulong)(si_++) * st_rays];
#define LC_LDI(v) v = as_int(st_[(ulong)(si_++) * st_rays]);
#define LC_LDU(v) v = as_uint(st_[(ulong)(si_++) * st_rays]);
#define LC_LD3(v) LC_LDF(v.x) LC_LDF(v.y) LC_LDF(v.z)
#define LC_SVF(v) st_[(ulong)(si_++) * st_rays] = (v);
#define LC_SVI(v) st_[(ulong)(si_++) * st_rays] = as_float(v);
#define LC_SVU(v) st_[(ulong)(si_++) * st_rays] = as_float(v);
#define LC_SV3(v) LC_SVF(v.x) LC_SVF(v.y) LC_SVF(v.z)

#ifdef LC_PRECISE
#define LC_ST_PRECISE(X, S) X##3(C_c##S) X##F(tau##S) X##F(tau_c##S)
#else
#define LC_ST_PRECISE(X, S)
#endif
#ifdef LC_PREINT
#define LC_ST_PREINT(X, S) X##3(pre_q##S) X##F(pre_v##S)
#else
#define LC_ST_PREINT(X, S)
#endif
#ifdef LC_TF2
#define LC_ST_TF2(X) X##3(C2) X##F(T2) X##I(sat2) LC_ST_PRECISE(X, 2) LC_ST_PREINT(X, 2)
#else
#define LC_ST_TF2(X)
#endif

#if defined(LC_MODE_MIP)
#define LC_ST_MODE(X)
#elif defined(LC_MODE_AVG)
#define LC_ST_MODE(X) X##F(vsum) X##F(lsum)
#elif defined(LC_MODE_ISO)
#ifdef LC_SHADE
#define LC_ST_MODE(X) X##F(iso_pv) X##3(iso_pq) X##3(iso_q) X##I(hit) X##3(iso_g)
#else
#define LC_ST_MODE(X) X##F(iso_pv) X##3(iso_pq) X##3(iso_q) X##I(hit)
#endif
#else
#define LC_ST_MODE(X) X##3(C) X##F(T) X##I(sat) LC_ST_PRECISE(X, ) LC_ST_PREINT(X, ) LC_ST_TF2(X)
#endif

#define LC_STATE(X) X##U(taken) X##I(done) X##F(vmax) LC_ST_MODE(X)

#define LC_STATE_LOAD                                                            \
    {                                                                            \
        __global const float* st_ = state + pix;                                 \
        int si_ = 0;                                                             \
        LC_STATE(LC_LD)                                                          \
    }
#define LC_STATE_SAVE                                                            \
    {                                                                            \
        __global float* st_ = state + pix;                                       \
        int si_ = 0;                                                             \
        LC_STATE(LC_SV)                                                          \
    }

/* The ray o + t d, t in [t0, t1], and the world box [lo, hi] (lc_common.h's slab test): whether they meet, and
 * where the ray leaves the box (*t_end): the pass owns no sample beyond, so its march stops there */
static inline int lc_meets_box(const float3 lo, const float3 hi, const float3 o, const float3 d, const float t0,
                               const float t1, float* t_end) {
    float tn;
    lc_slab(lo, hi, o, d, &tn, t_end);
    return fmax(tn, t0) <= fmin(*t_end, t1);
}

#ifdef LC_SAMPLER_FULL
/* The full sampler on a pass's sub-volume: q clamped to the whole volume (as lc_sample does), then moved into the
 * sub-volume, which holds every voxel an owned sample's stencil reads (exact: the offset is an integer and q is far
 * below 2^24, so the fractions do not change). The second clamp only guards memory. */
static inline float lc_sample_pass(__global const lc_voxel* vol, const int4 pdims, const float3 pmax, const float3 qmax,
                                   const float3 poff, float3 q) {
    q.x = q.x > 0.0f ? (q.x < qmax.x ? q.x : qmax.x) : 0.0f;
    q.y = q.y > 0.0f ? (q.y < qmax.y ? q.y : qmax.y) : 0.0f;
    q.z = q.z > 0.0f ? (q.z < qmax.z ? q.z : qmax.z) : 0.0f;
    return lc_sample(vol, pdims, pmax, q - poff);
}
#endif

#endif
#endif
