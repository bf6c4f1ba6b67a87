/* Graded transmittance fields (seed eq. 1) and the exact light transmittance.
 *
 *   T_i(p) = exp(-tau_i(p)),   tau_i(p) = lambda^(i+1) * density_scale * integral_0^inf rho_i(p + t l) dt
 *
 * rho_i is level i of the density pyramid (cl/pyramid.cl) read trilinearly between voxel
 * centres, clamped at the faces, 0 outside the cube (grid.h conventions); l is the unit
 * direction toward the light; p runs over level i's voxel centres. The exact light
 * transmittance for single scattering is the same with lambda = 1 on level 0.
 *
 * Coordinates: "voxel units" of the level, voxel (x, y, z) centred at integer (x, y, z), the
 * cube spanning [-0.5, n - 0.5] on every axis. A level is float [z][y][x], x fastest.
 * Every kernel accumulates optical depth (never a product of transmittances) and writes
 * either exp(-tau) (out_depth = 0) or tau itself (out_depth = 1).
 *
 * Common arguments
 *   pyr      float*  the whole pyramid (all levels concatenated); level at element offset off
 *   n        int     voxels per side of this level
 *   scale    float   lambda^(i+1) * density_scale * voxel size (world units): tau per unit of
 *                    (density x voxel-unit length)
 *   out      float*  output, this level's n^3 values at element offset out_off
 *
 * transmittance_brute: one work-item per voxel, the accuracy reference. Marches from the voxel
 *   centre to the cube exit, split at every plane g = m / 2 (integer m) of each axis: between
 *   such planes the trilinear field is one trilinear polynomial, cubic along the ray, so
 *   2-point Gauss-Legendre per piece integrates it exactly (error = float32 rounding only).
 *   Cost O(n) per voxel, O(n^4) per level. dir = unit direction toward the light.
 *
 * transmittance_sweep_slice: one launch per slice, slices ordered from the light's side along
 *   the dominant light axis a (|l_a| largest). For voxel (u, v) of slice k, the ray toward the
 *   light reaches the previous slice kp = k + sa after one voxel along a, at lateral offset
 *   (su, sv) = (l_u, l_v) / |l_a| (|su|, |sv| <= 1). Then
 *       tau(u, v, k) = scale * len * Simpson(rho at start, middle, end) + tau_prev(u + su, v + sv)
 *   The segment stays inside one trilinear cell, so Simpson's rule is exact there; the only
 *   approximation is the bilinear interpolation of tau_prev in the previous slice (numerical
 *   diffusion: exact for axis-aligned and 45-degree lights; bound in docs/transmittance.md).
 *   Slice j = 0 (nearest the light) goes half a voxel to the face and has tau_prev = 0. A ray
 *   that leaves through a side face before reaching the previous slice is integrated to that
 *   face only (nothing lies beyond it). Between the last voxel centre and a side face
 *   (interpolation position in [-0.5, 0) or (n-1, n-0.5]) tau_prev falls linearly to 0 at the
 *   face, where the ray toward the light leaves the cube.
 *   tau_prev / tau_cur: float [n][n] indexed [v][u]; u, v the lateral axes in x, y, z order
 *   (a = z: u = x, v = y; a = y: u = x, v = z; a = x: u = y, v = z).
 *
 * combine_levels: base^3 field sum_l w_l T_l(centre) + bias, each T_l read trilinearly
 *   (clamped) at the base voxel centre (render-time bake of the learned 1x1x1 convolution
 *   across levels, the seed's "3D-CNN").
 *
 * Twin: reference/transmittance.py. Host wrapper: clvol/kernels/transmittance.py.
 */
#include "grid.h"

/* Lookup at voxel-unit coordinates given as (lateral u, lateral v, sweep axis a). */
__attribute__((always_inline))
float lookup_uva(__global const float *d, int n, int a, float pu, float pv, float pa) {
    float3 g = (a == 2) ? (float3)(pu, pv, pa) : (a == 1) ? (float3)(pu, pa, pv)
                                                          : (float3)(pa, pu, pv);
    return grid_lookup(d, n, n, n, g);
}

__kernel void transmittance_brute(__global const float *pyr, const int off, const int n,
                                  const float4 dir, const float scale, const int out_depth,
                                  __global float *out, const int out_off) {
    const int i = get_global_id(0);
    if (i >= n * n * n) return;
    __global const float *d = pyr + off;
    const float3 p = (float3)((float)(i % n), (float)((i / n) % n), (float)(i / (n * n)));
    const float3 l = dir.xyz;
    const float dc[3] = {l.x, l.y, l.z}, pc[3] = {p.x, p.y, p.z};
    float h[3], tn[3], texit = INFINITY;
    for (int a = 0; a < 3; ++a) {
        if (dc[a] != 0.0f) {
            float face = dc[a] > 0.0f ? (float)n - 0.5f : -0.5f;
            texit = fmin(texit, (face - pc[a]) / dc[a]);
            h[a] = 0.5f / fabs(dc[a]);  /* p is integer: every crossing of a half-integer */
        } else {                          /* or integer plane is a multiple of h[a] */
            h[a] = INFINITY;
        }
        tn[a] = h[a];
    }
    int kc[3] = {1, 1, 1};
    const float c = 0.57735026918962576f;  /* 1 / sqrt(3) */
    float t0 = 0.0f, sum = 0.0f;
    while (t0 < texit) {
        float t1 = fmin(fmin(fmin(tn[0], tn[1]), tn[2]), texit);
        float hw = 0.5f * (t1 - t0), mid = 0.5f * (t1 + t0);
        sum += hw * (grid_lookup(d, n, n, n, p + (mid - hw * c) * l)
                       + grid_lookup(d, n, n, n, p + (mid + hw * c) * l));
        for (int a = 0; a < 3; ++a)
            if (tn[a] <= t1) { kc[a] += 1; tn[a] = (float)kc[a] * h[a]; }
        t0 = t1;
    }
    const float tau = scale * sum;
    out[out_off + i] = out_depth ? tau : exp(-tau);
}

/* Element index of voxel (u, v) of slice k (lateral u, v; sweep axis a) in [z][y][x]. */
__attribute__((always_inline))
size_t elem_uva(int n, int a, int u, int v, int k) {
    const size_t N = (size_t)n;
    const size_t s_u = (a == 0) ? N : 1;                       /* u = y if a = x, else x */
    const size_t s_v = (a == 2) ? N : N * N;                   /* v = y if a = z, else z */
    const size_t s_a = (a == 2) ? N * N : (a == 1) ? N : 1;
    return (size_t)u * s_u + (size_t)v * s_v + (size_t)k * s_a;
}

/* ---------------------------------------------------------------- column sweep
 * Built twice: -D SWEEP_WIDTH=16 (explicit float16 across 16 columns / voxels of a row: the
 * fast path, levels with n >= 16) and -D SWEEP_WIDTH=1 (scalar, small levels).
 */
#ifndef SWEEP_WIDTH
#define SWEEP_WIDTH 1
#endif
#if SWEEP_WIDTH == 16
typedef float16 vecf;
typedef int16 veci;
#define VLOAD(p) vload16(0, (p))
#define VSTORE(v, p) vstore16((v), 0, (p))
#define LANES ((vecf)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15))
#define VSELECT(a, b, m) select((a), (b), (m))   /* m: int16 mask (-1 = true) */
#elif SWEEP_WIDTH == 1
typedef float vecf;
typedef int veci;
#define VLOAD(p) (*(p))
#define VSTORE(v, p) (*(p) = (v))
#define LANES 0.0f
#define VSELECT(a, b, m) ((m) ? (b) : (a))
#else
#error "SWEEP_WIDTH must be 1 or 16"
#endif

/* Padded copy of a level for a sweep along axis a ("sweep layout"): S[ka][vv][uu], the
 * level's voxel (u, v, k) at ka = k + 1, vv = v + SWEEP_PAD, uu = u + SWEEP_PAD, every index
 * clamped into the level, so a trilinear lookup in S at any lateral position in
 * [-2, n + 1] and any a-position in [-0.5, n - 0.5] returns the level's clamped field
 * without bounds tests, and rows are contiguous along u whatever the light's axis.
 * Plane size (n + 2 PAD)^2, row stride n + 2 PAD; the buffer carries SWEEP_SLACK extra
 * floats at its end because the last work-item's vector lanes run past the last row. */
#define SWEEP_PAD 3

__kernel void sweep_layout(__global const float *pyr, const int off, const int n, const int a,
                           __global float *S, const int s_off) {
    const int i = get_global_id(0);
    const int w = n + 2 * SWEEP_PAD;
    if (i >= (n + 2) * w * w) return;
    const int uu = i % w, vv = (i / w) % w, ka = i / (w * w);
    const int u = clamp(uu - SWEEP_PAD, 0, n - 1), v = clamp(vv - SWEEP_PAD, 0, n - 1);
    const int k = clamp(ka - 1, 0, n - 1);
    S[s_off + i] = pyr[off + elem_uva(n, a, u, v, k)];
}

/* Bilinear lookup in one plane of S for the lanes' row: row0 points at (vv0, uu of lane 0 +
 * node offset), i.e. the lower-left node of every lane; gu, gv the (uniform) fractions. */
__attribute__((always_inline))
vecf plane_bilinear(__global const float *row0, int rs, float gu, float gv) {
    vecf r0 = mix(VLOAD(row0), VLOAD(row0 + 1), gu);
    vecf r1 = mix(VLOAD(row0 + rs), VLOAD(row0 + rs + 1), gu);
    return mix(r0, r1, gv);
}

/* The clamped field at lateral positions (w + du, wv + dv) of every lane w = w0 + lane
 * (window-local column index, equal to the level index offset by the window origin, which
 * the caller has folded into p0 = &S[plane 0][row of wv][uu of w0]) and a-position pa. */
__attribute__((always_inline))
vecf field_at(__global const float *p0, int rs, int ps, float du, float dv, float pa) {
    const float fu_ = floor(du), fv_ = floor(dv);
    const float ka = pa + 1.0f;                  /* plane index in S (>= 0.5) */
    const int p = (int)ka;
    const float ga = ka - (float)p;
    __global const float *row = p0 + (size_t)p * (size_t)ps + (int)fv_ * rs + (int)fu_;
    vecf v0 = plane_bilinear(row, rs, du - fu_, dv - fv_);
    if (ga == 0.0f) return v0;
    return mix(v0, plane_bilinear(row + ps, rs, du - fu_, dv - fv_), ga);
}

/* Parameter interval of a lateral segment b -> b + d inside [-0.5, n - 0.5]. */
#define INSIDE_T(b, d, n, t0, t1)                                                        \
    do {                                                                                 \
        if ((d) != 0.0f) {                                                               \
            vecf ta_ = (-0.5f - (b)) / (d), tb_ = ((float)(n) - 0.5f - (b)) / (d);       \
            t0 = fmax(fmin(ta_, tb_), 0.0f);                                             \
            t1 = fmin(fmax(ta_, tb_), 1.0f);                                             \
        } else {                                                                         \
            t0 = (vecf)(0.0f);                                                           \
            t1 = VSELECT((vecf)(0.0f), (vecf)(1.0f),                                     \
                         ((b) >= -0.5f) & ((b) <= (float)(n) - 0.5f));                   \
        }                                                                                \
    } while (0)

/* One launch per sweep step j of one level (see the header and reference/transmittance.py).
 * Work-items, in three ranges:
 *  [0, n_col)             add segment j to the columns of window j (window-local column
 *                         w = 0..n, row wv = 0..n; lanes beyond n add nothing). Reads colP,
 *                         writes colC. The field at a segment's start is the field at the
 *                         previous segment's end, kept per column in rhoP / rhoC, except on
 *                         step 0 and for columns that just entered the window (fresh: bit 0
 *                         column w = 0, bit 1 w = n, bit 2 row 0, bit 3 row n), where it is
 *                         evaluated.
 *  [n_col, n_col + n_vox) voxels of step j - 1 (slice kv) from colP (the columns after step
 *                         j - 1), written as exp(-tau) or tau.
 *  [.., + n_flush)        a = x with float16 only: the voxel rows run along y, stride n in the
 *                         output, so voxels go to a two-slab buffer tmp[2][16][n][n] first and
 *                         each completed slab of 16 slices (x = flush_kb .. flush_kb + 15) is
 *                         written as contiguous x-runs.
 * Column buffers are [rows][cw] (global column index = window origin + window-local index),
 * ping-ponged between launches: a column never re-enters a window it has left and all start
 * at 0, so nothing needs copying.
 *
 *   S, s_off      sweep layout of the level (sweep_layout); n voxels per side; a the sweep axis
 *   sa, su, sv    sign of l_a; lateral offsets per voxel along a (|su|, |sv| <= 1)
 *   kscale        scale / |l_a| / 6 (Simpson's weights over a segment of one voxel along a)
 *   cw            row length of the column buffers colA/B, rhoA/B (ping-pong by the parity of j)
 *   itab[j]       int row (SWEEP_ITAB): do_cols (step j < n), k (its slice), first (j == 0: the
 *                 segment starts at the face, half a voxel), fresh, cu0, cv0 (window origin in
 *                 the column buffers), do_vox (j >= 1), kv (slice of step j - 1), vu0, vv0 (its
 *                 window origin), flush_kb (slab to write, -1 for none)
 *   ftab[j]       fu, fv: fractional parts of j * (su, sv); gu, gv: the same for step j - 1
 *   out_depth, out, out_off        output (level layout [z][y][x] at element offset out_off)
 */
#define SWEEP_ITAB 12
__kernel void transmittance_sweep_step(
        __global const float *S, const int s_off, const int n, const int a, const int sa,
        const float su, const float sv, const float kscale, const int cw,
        __global const int *itab, __global const float *ftab, const int j,
        __global float *colA, __global float *colB, __global float *rhoA, __global float *rhoB,
        const int out_depth, __global float *out, const int out_off, __global float *tmp,
        const int n_col, const int n_vox) {
    /* per-step parameters (one table row per launch: setting one argument per launch keeps
     * the host's enqueue cost small) */
    __global const int *it = itab + SWEEP_ITAB * j;
    const int do_cols = it[0], k = it[1], first = it[2], fresh = it[3], cu0 = it[4], cv0 = it[5];
    const int do_vox = it[6], kv = it[7], vu0 = it[8], vv0 = it[9], flush_kb = it[10];
    const float fu = ftab[4 * j], fv = ftab[4 * j + 1], gu = ftab[4 * j + 2], gv = ftab[4 * j + 3];
    /* launch j reads what launch j - 1 wrote */
    __global const float *colP = (j & 1) ? colA : colB;
    __global float *colC = (j & 1) ? colB : colA;
    __global const float *rhoP = (j & 1) ? rhoA : rhoB;
    __global float *rhoC = (j & 1) ? rhoB : rhoA;
    const int gid = get_global_id(0);
    const int rs = n + 2 * SWEEP_PAD, ps = rs * rs;
    if (gid < n_col) {
        if (!do_cols) return;
        const int chunks = (n + SWEEP_WIDTH) / SWEEP_WIDTH;       /* lanes over w = 0..n */
        const int wv = gid / chunks, w0 = (gid - wv * chunks) * SWEEP_WIDTH;
        if (wv > n) return;
        const float seg = first ? 0.5f : 1.0f;
        const vecf w = (float)w0 + LANES;
        /* lateral offsets from lane w's own index to its end (in slice k) and start */
        const float eu = -fu, ev = -fv;
        const float bu = eu + seg * su, bv = ev + seg * sv;
        __global const float *p0 = S + s_off + (wv + SWEEP_PAD) * rs + (w0 + SWEEP_PAD);
        const size_t ci = (size_t)(cv0 + wv) * (size_t)cw + (size_t)(cu0 + w0);
        const vecf r_end = field_at(p0, rs, ps, eu, ev, (float)k);
        const vecf r_mid = field_at(p0, rs, ps, 0.5f * (eu + bu), 0.5f * (ev + bv),
                                    (float)k + 0.5f * seg * (float)sa);
        const int is_fresh = first || ((fresh & 1) && w0 == 0)
                          || ((fresh & 2) && w0 + SWEEP_WIDTH > n)
                          || ((fresh & 4) && wv == 0) || ((fresh & 8) && wv == n);
        const vecf r_beg = is_fresh ? field_at(p0, rs, ps, bu, bv, (float)k + seg * (float)sa)
                                    : VLOAD(rhoP + ci);
        /* inside fraction of the lateral segment start -> end */
        vecf t0u, t1u, t0v, t1v;
        const vecf begu = w + bu;
        const vecf begv = (vecf)((float)wv + bv);
        INSIDE_T(begu, -seg * su, n, t0u, t1u);
        INSIDE_T(begv, -seg * sv, n, t0v, t1v);
        vecf c = fmax(fmin(t1u, t1v) - fmax(t0u, t0v), 0.0f);
        c = VSELECT(c, (vecf)(0.0f), w > (float)n);          /* lanes beyond the window */
        VSTORE(VLOAD(colP + ci) + (kscale * seg) * c * (r_beg + 4.0f * r_mid + r_end), colC + ci);
        VSTORE(r_end, rhoC + ci);
        return;
    }
    if (gid < n_col + n_vox) {
        if (!do_vox) return;
        const int chunks = (n + SWEEP_WIDTH - 1) / SWEEP_WIDTH;
        const int i = gid - n_col;
        const int v = i / chunks, u0 = (i - v * chunks) * SWEEP_WIDTH;
        if (v >= n) return;
        __global const float *c0 = colP + (size_t)(vv0 + v) * (size_t)cw + (size_t)(vu0 + u0);
        const vecf tau = mix(mix(VLOAD(c0), VLOAD(c0 + 1), gu),
                             mix(VLOAD(c0 + cw), VLOAD(c0 + cw + 1), gu), gv);
        const vecf val = out_depth ? tau : exp(-tau);
#if SWEEP_WIDTH == 16
        if (a == 0) {  /* slab buffer [(kv / 16) % 2][kv % 16][v][u] */
            const size_t nn = (size_t)n * (size_t)n;
            VSTORE(val, tmp + (size_t)(((kv >> 4) & 1) * 16 + (kv & 15)) * nn
                            + (size_t)v * (size_t)n + (size_t)u0);
            return;
        }
#endif
        VSTORE(val, out + (size_t)out_off + elem_uva(n, a, u0, v, kv));  /* u = x: contiguous */
        return;
    }
#if SWEEP_WIDTH == 16
    /* flush: one work-item per (z, y) = (v, u): 16 slab values -> out[z][y][kb .. kb + 15] */
    if (flush_kb < 0) return;
    const int i = gid - n_col - n_vox;
    if (i >= n * n) return;
    const size_t nn = (size_t)n * (size_t)n;
    __global const float *t = tmp + (size_t)(((flush_kb >> 4) & 1) * 16) * nn + (size_t)i;
    const float16 run = (float16)(t[0], t[nn], t[2 * nn], t[3 * nn], t[4 * nn], t[5 * nn],
                                  t[6 * nn], t[7 * nn], t[8 * nn], t[9 * nn], t[10 * nn],
                                  t[11 * nn], t[12 * nn], t[13 * nn], t[14 * nn], t[15 * nn]);
    vstore16(run, 0, out + (size_t)out_off + (size_t)i * (size_t)n + (size_t)flush_kb);
#endif
}

__kernel void combine_levels(__global const float *tgrid, __global const int *offsets,
                             __global const float *weights, const int n_levels, const int base,
                             const float bias, __global float *out) {
    const int i = get_global_id(0);
    if (i >= base * base * base) return;
    const float3 c = (float3)((float)(i % base), (float)((i / base) % base),
                              (float)(i / (base * base))) + 0.5f;
    float sum = bias;
    for (int l = 0; l < n_levels; ++l) {
        const int n = base >> l;
        /* base voxel centre in level-l voxel units: (i + 0.5) / 2^l - 0.5 */
        sum += weights[l] * grid_lookup(tgrid + offsets[l], n, n, n,
                                        c * (1.0f / (float)(1 << l)) - 0.5f);
    }
    out[i] = sum;
}
