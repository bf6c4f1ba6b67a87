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
 * sweep_layout + transmittance_sweep_block: the fast sweep, O(n^3) per level. Along the dominant
 *   light axis a (|l_a| largest) the light rays drift laterally by (su, sv) = (l_u, l_v) / |l_a|
 *   per slice (|su|, |sv| <= 1). "Columns" are the light rays through the voxel centres of the
 *   first slice (nearest the light), extended to a lattice: column c sits at lateral position
 *   c - j (su, sv) in the slice of sweep step j, so all columns share one fractional offset and
 *   every lookup is a uniform stencil (a vector across LANES columns). Each step adds to every column
 *       scale / |l_a| * seg * c * (rho_start + 4 rho_mid + rho_end) / 6
 *   over its segment from the previous slice (from the face, half a voxel, for j = 0) to the
 *   current one: inside the cube a segment stays in one trilinear cell, so Simpson is exact;
 *   c is the fraction of the segment inside the side faces (the field clamped beyond them),
 *   exact when the field is constant along the segment. Each voxel of the slice then takes the
 *   bilinear interpolation of optical depth between its 4 surrounding columns: the sweep's only
 *   approximation inside the cube, made once per voxel (not carried from slice to slice). Exact
 *   for axis-aligned and 45-degree lights; bounds in docs/transmittance.md.
 *   Lateral axes (u, v) in x, y, z order without a: a = z: (x, y); a = y: (x, z); a = x: (y, z).
 *
 * combine_levels: base^3 field sum_l w_l T_l(centre) + bias, each T_l read trilinearly
 *   (clamped) at the base voxel centre (render-time bake of the learned 1x1x1 convolution
 *   across levels, the seed's "3D-CNN").
 *
 * Twin: reference/transmittance.py. Host wrapper: clvol/kernels/transmittance.py.
 */
#include "grid.h"

__kernel void transmittance_brute(__global const float *pyr, const int off, const int n,
                                  const float4 dir, const float scale, const int out_depth,
                                  __global float *out, const int out_off) {
    const int i = get_global_id(0);
    if (i >= n * n * n) return;
    __global const float *d = pyr + off;
    const int zy = i / n, z = zy / n;           /* no '%' (see cl/pyramid.cl) */
    const float3 p = (float3)((float)(i - zy * n), (float)(zy - z * n), (float)z);
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
 * Built twice: -D SWEEP_WIDTH=LANES (explicit vectors across LANES columns / voxels of a row,
 * cl/include/lanes.h: the fast path, levels with n >= 16) and -D SWEEP_WIDTH=1 (scalar, small
 * levels).
 */
#include "lanes.h"
#ifndef SWEEP_WIDTH
#define SWEEP_WIDTH 1
#endif
#if SWEEP_WIDTH == LANES
typedef vL vecf;
typedef iL veci;
#define VLOAD(p) vloadL(0, (p))
#define VSTORE(v, p) vstoreL((v), 0, (p))
#define LANE_POS convert_vL(LANE_IOTA)
#define VSELECT(a, b, m) select((a), (b), (m))   /* m: iL mask (-1 = true) */
#elif SWEEP_WIDTH == 1
typedef float vecf;
typedef int veci;
#define VLOAD(p) (*(p))
#define VSTORE(v, p) (*(p) = (v))
#define LANE_POS 0.0f
#define VSELECT(a, b, m) ((m) ? (b) : (a))
#else
#error "SWEEP_WIDTH must be 1 or LANES"
#endif

/* Padded copy of a level for a sweep along axis a ("sweep layout"): S[ka][vv][uu] holds the
 * level's voxel (u, v, k) at ka = k + 1, vv = v + SWEEP_PAD, uu = u + SWEEP_PAD, every index
 * clamped into the level. A trilinear lookup in S at lateral positions in
 * [-SWEEP_PAD, n + 2 SWEEP_PAD - 2] (u) or [-SWEEP_PAD, n + SWEEP_PAD - 1] (v) and any
 * a-position in [-0.5, n - 0.5] returns the level's clamped field without bounds tests, and
 * rows are contiguous along u whatever the light's axis. The column work-items of a block
 * reach up to 16 voxels beyond the level laterally (15 steps of drift) plus their (at most)
 * 15 extra lanes on the u side: hence the padding. */
#include "constants.h"                     /* SWEEP_PAD, SWEEP_BLOCK (sweep steps per launch) */
#define SWEEP_RS(n) ((n) + 3 * SWEEP_PAD)      /* row length (u) */
#define SWEEP_RV(n) ((n) + 2 * SWEEP_PAD + 1)  /* rows per plane (v) */

__kernel void sweep_layout(__global const float *pyr, const int off, const int n, const int a,
                           __global float *S, const int s_off) {
    const int i = get_global_id(0);
    const int rs = SWEEP_RS(n), rv = SWEEP_RV(n);
    if (i >= (n + 2) * rv * rs) return;
    const int kv = i / rs, ka = kv / rv;        /* no '%' (see cl/pyramid.cl) */
    const int uu = i - kv * rs, vv = kv - ka * rv;
    const int u = clamp(uu - SWEEP_PAD, 0, n - 1), v = clamp(vv - SWEEP_PAD, 0, n - 1);
    const int k = clamp(ka - 1, 0, n - 1);
    S[s_off + i] = pyr[off + elem_uva(n, a, u, v, k)];
}

/* Bilinear lookup in one plane of S for the lanes' row: row0 points at the lower-left node
 * of lane 0 (the lanes' nodes follow contiguously); gu, gv the (uniform) fractions. */
__attribute__((always_inline))
vecf plane_bilinear(__global const float *row0, int rs, float gu, float gv) {
    vecf r0 = mix(VLOAD(row0), VLOAD(row0 + 1), gu);
    vecf r1 = mix(VLOAD(row0 + rs), VLOAD(row0 + rs + 1), gu);
    return mix(r0, r1, gv);
}

/* The clamped field for every lane at lateral S indices (uu + du, vv + dv), du, dv offsets in
 * [-2, 1) given as (integer part already folded into uu / vv) + fraction, and a-position pa:
 * uu is lane 0's S column index, vv the row index. */
__attribute__((always_inline))
vecf field_at(__global const float *S, int rs, int ps, int uu, int vv, float gu, float gv,
              float pa) {
    const float ka = pa + 1.0f;                  /* plane index in S (>= 0.5) */
    const int p = (int)ka;                       /* non-negative: the cast is a floor */
    const float ga = ka - (float)p;
    __global const float *row = S + (size_t)p * (size_t)ps + (size_t)vv * (size_t)rs + (size_t)uu;
    vecf v0 = plane_bilinear(row, rs, gu, gv);
    if (ga == 0.0f) return v0;
    return mix(v0, plane_bilinear(row + ps, rs, gu, gv), ga);
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

/* Split an offset x in (-2, 2) into floor and fraction without floor() (slow on PoCL). */
__attribute__((always_inline))
int split_offset(float x, float *frac) {
    int i = (int)(x + 2.0f) - 2;                 /* x + 2 > 0: the cast is a floor ... */
    /* ... except that x + 2 rounds to 2 for -6e-8 < x < 0 (a light grazing a face), which
     * gave i = 0 and a negative fraction: mix() then extrapolated to a negative optical depth. */
    if ((float)i > x) i -= 1;
    *frac = x - (float)i;
    return i;
}

/* One launch per block of SWEEP_BLOCK sweep steps of one level (launch b = 0 .. nb):
 *  - column work-items (block b < nb): each marches SWEEP_WIDTH light-ray columns (global
 *    column indices c0 .. c0 + SWEEP_WIDTH - 1 in row cv) through the block's steps: per step, tau +=
 *    kscale * seg * c * (rho_start + 4 rho_mid + rho_end) (the start of a segment is the end of
 *    the previous one, so only the block's first step evaluates it), and tau after every step
 *    goes to the block buffer bb[b % 2] for the voxels. tau persists in col (in place: one
 *    owner per column and launch; all zero before the first launch).
 *  - voxel work-items (block b - 1 >= 0): each voxel of those steps' slices takes the bilinear
 *    interpolation of its 4 columns from bb[(b - 1) % 2]. Lanes run along u (rows contiguous
 *    in the output when u = x); for a = x they run along x instead (16 consecutive slices
 *    form one block, so the output is written as contiguous 16-voxel runs).
 *
 *   S, s_off      sweep layout of the level (sweep_layout); n voxels per side; a the sweep axis
 *   sa, su, sv    sign of l_a; lateral offsets per voxel along a (|su|, |sv| <= 1)
 *   kscale        scale / |l_a| / 6 (Simpson's weights over a segment one voxel long along a)
 *   col, cw, ou, ov   column tau, [rows][cw], global column (cu, cv) at (cv + ov) * cw + cu + ou
 *   bb, bw, brows     block buffers [2][16][brows][bw], block-local column (cu - umin_b, cv - vmin_b)
 *   stab[j], sftab[j] step j: int (k, iu, iv): its slice and floor(j * (su, sv));
 *                     float (fu, fv): the fractional parts (the columns' drift after j steps)
 *   btab[b]       int (umin, vmin, chunks, rows): the block's column range (from its first
 *                 window to its last) and work-item counts
 *   b, nb         this launch; number of blocks
 *   out_depth, out, out_off   output (level layout [z][y][x] at element offset out_off)
 *   n_col         work-items reserved for the columns (max over blocks of rows * chunks);
 *                 the voxels take the next n^2 / SWEEP_WIDTH (a = x, SWEEP_WIDTH > 1) or
 *                 16 n^2 / SWEEP_WIDTH
 */
/* transmittance_sweep_block's column items: item gid advances its SWEEP_WIDTH columns of the
 * sweep through block b's SWEEP_BLOCK steps (the optical depth so far in col, each step's
 * value into the block buffer bb for the voxel items of the next launch). */
__attribute__((always_inline))
void sweep_block_columns(const int gid, __global const float *S, const int s_off, const int n,
                         const int sa, const float su, const float sv, const float kscale,
                         __global float *col, const int cw, const int ou, const int ov,
                         __global float *bb, const int bw, const size_t bplane,
                         __global const int *stab, __global const float *sftab,
                         __global const int *btab, const int b, const int nb) {
    const int rs = SWEEP_RS(n), ps = rs * SWEEP_RV(n);
    /* n_col is a multiple of the work-group size, so a group holds only column items and
     * all of them reach every barrier. The barrier after each step makes the group's
     * columns advance together: each step's loads then sweep whole rows of two planes,
     * which the caches stream, instead of each work-item marching its own pencil through
     * 16 planes (latency-bound, several times slower on a CPU). */
    const int live = b < nb;
    const int umin = live ? btab[4 * b] : 0, vmin = live ? btab[4 * b + 1] : 0;
    const int chunks = live ? btab[4 * b + 2] : 1;
    const int r = gid / chunks, m = gid - r * chunks;
    const int active = live && r < btab[4 * b + 3 * live];
    const int cv = vmin + r, c0 = umin + m * SWEEP_WIDTH;
    __global float *colp = col + (size_t)(cv + ov) * (size_t)cw + (size_t)(c0 + ou);
    __global float *bbp = bb + (size_t)((b & 1) * SWEEP_BLOCK) * bplane
                             + (size_t)r * (size_t)bw + (size_t)(m * SWEEP_WIDTH);
    __global const float *Sl = S + s_off;
    vecf tau = active ? VLOAD(colp) : (vecf)(0.0f), r_beg = 0.0f;
    for (int jj = 0; jj < SWEEP_BLOCK; ++jj) {
        const int j = b * SWEEP_BLOCK + jj;
        if (!live || j >= n) break;          /* uniform over the launch */
        if (active) {
            const int k = stab[3 * j], iu = stab[3 * j + 1], iv = stab[3 * j + 2];
            const float fu = sftab[2 * j], fv = sftab[2 * j + 1];
            const float seg = (j == 0) ? 0.5f : 1.0f;  /* step 0 starts at the face */
            /* lane 0's column relative to the slice's window; its position there is that
             * minus (fu, fv); the segment runs from there + seg * (su, sv) to there */
            const int wu = c0 - iu, wv = cv - iv;
            float gu, gv;
            int ou_, ov_;
            ou_ = split_offset(-fu, &gu);
            ov_ = split_offset(-fv, &gv);
            const vecf r_end = field_at(Sl, rs, ps, wu + ou_ + SWEEP_PAD,
                                        wv + ov_ + SWEEP_PAD, gu, gv, (float)k);
            ou_ = split_offset(-fu + 0.5f * seg * su, &gu);
            ov_ = split_offset(-fv + 0.5f * seg * sv, &gv);
            const vecf r_mid = field_at(Sl, rs, ps, wu + ou_ + SWEEP_PAD,
                                        wv + ov_ + SWEEP_PAD, gu, gv,
                                        (float)k + 0.5f * seg * (float)sa);
            if (jj == 0) {
                ou_ = split_offset(-fu + seg * su, &gu);
                ov_ = split_offset(-fv + seg * sv, &gv);
                r_beg = field_at(Sl, rs, ps, wu + ou_ + SWEEP_PAD, wv + ov_ + SWEEP_PAD,
                                 gu, gv, (float)k + seg * (float)sa);
            }
            /* inside fraction of the lateral segment start -> end */
            vecf t0u, t1u, t0v, t1v;
            const vecf begu = (float)wu + LANE_POS + (-fu + seg * su);
            const vecf begv = (vecf)((float)wv + (-fv + seg * sv));
            INSIDE_T(begu, -seg * su, n, t0u, t1u);
            INSIDE_T(begv, -seg * sv, n, t0v, t1v);
            const vecf c = fmax(fmin(t1u, t1v) - fmax(t0u, t0v), 0.0f);
            tau += (kscale * seg) * c * (r_beg + 4.0f * r_mid + r_end);
            VSTORE(tau, bbp + (size_t)jj * bplane);
            r_beg = r_end;
        }
#ifndef SWEEP_NO_SYNC
        barrier(CLK_GLOBAL_MEM_FENCE);
#endif
    }
    if (active) VSTORE(tau, colp);
}

/* transmittance_sweep_block's voxel items: item i writes its share of block b - 1's voxels
 * (the block buffer bb, resampled onto the grid's axes) into out, as T or optical depth. */
__attribute__((always_inline))
void write_block_voxels(const int i, const int n, const int a, const int sa,
                        __global const float *bb, const int bw, const size_t bplane,
                        __global const int *stab, __global const float *sftab,
                        __global const int *btab, const int b, const int out_depth,
                        __global float *out, const int out_off) {
    /* voxels of block bp = b - 1 */
    const int bp = b - 1;
    if (bp < 0) return;
    const int umin = btab[4 * bp], vmin = btab[4 * bp + 1];
    __global const float *bbq = bb + (size_t)((bp & 1) * SWEEP_BLOCK) * bplane;
#if SWEEP_WIDTH == 16
    if (a == 0) {
        /* u = y, v = z; x runs along the sweep, and the block's 16 slices are 16 consecutive
         * x = kb .. kb + 15: interpolate a 16 (slices) x 16 (y) tile, then write it
         * transposed as 16 contiguous x-runs. Item i = (v, chunk of y). */
        const int chunks = n / 16;
        if (i >= n * chunks) return;
        const int v = i / chunks, u0 = (i - v * chunks) * 16;
        const int kb = (sa > 0) ? n - SWEEP_BLOCK - bp * SWEEP_BLOCK : bp * SWEEP_BLOCK;
        float tile[16 * 16];                     /* [slice jj][y lane] */
        for (int jj = 0; jj < 16; ++jj) {
            const int j = bp * SWEEP_BLOCK + jj;
            const float fu = sftab[2 * j], fv = sftab[2 * j + 1];
            __global const float *c0 = bbq + (size_t)jj * bplane
                + (size_t)(stab[3 * j + 2] - vmin + v) * (size_t)bw
                + (size_t)(stab[3 * j + 1] - umin + u0);
            const float16 t = mix(mix(vload16(0, c0), vload16(0, c0 + 1), fu),
                                  mix(vload16(0, c0 + bw), vload16(0, c0 + bw + 1), fu), fv);
            vstore16(out_depth ? t : exp(-t), jj, tile);
        }
        for (int q = 0; q < 16; ++q) {           /* x = kb + x_lane is step jj(x_lane) */
            float16 run;
            if (sa > 0)
                run = (float16)(tile[15 * 16 + q], tile[14 * 16 + q], tile[13 * 16 + q],
                                tile[12 * 16 + q], tile[11 * 16 + q], tile[10 * 16 + q],
                                tile[9 * 16 + q], tile[8 * 16 + q], tile[7 * 16 + q],
                                tile[6 * 16 + q], tile[5 * 16 + q], tile[4 * 16 + q],
                                tile[3 * 16 + q], tile[2 * 16 + q], tile[16 + q], tile[q]);
            else
                run = (float16)(tile[q], tile[16 + q], tile[2 * 16 + q], tile[3 * 16 + q],
                                tile[4 * 16 + q], tile[5 * 16 + q], tile[6 * 16 + q],
                                tile[7 * 16 + q], tile[8 * 16 + q], tile[9 * 16 + q],
                                tile[10 * 16 + q], tile[11 * 16 + q], tile[12 * 16 + q],
                                tile[13 * 16 + q], tile[14 * 16 + q], tile[15 * 16 + q]);
            vstore16(run, 0, out + (size_t)out_off
                             + ((size_t)v * (size_t)n + (size_t)(u0 + q)) * (size_t)n + (size_t)kb);
        }
        return;
    }
#elif SWEEP_WIDTH > 1
    if (a == 0) {
        /* As above with SWEEP_WIDTH y lanes: the 16 x-runs are written SWEEP_WIDTH at a time. */
        const int chunks = n / SWEEP_WIDTH;
        if (i >= n * chunks) return;
        const int v = i / chunks, u0 = (i - v * chunks) * SWEEP_WIDTH;
        const int kb = (sa > 0) ? n - SWEEP_BLOCK - bp * SWEEP_BLOCK : bp * SWEEP_BLOCK;
        float tile[SWEEP_BLOCK * SWEEP_WIDTH];   /* [slice jj][y lane] */
        for (int jj = 0; jj < SWEEP_BLOCK; ++jj) {
            const int j = bp * SWEEP_BLOCK + jj;
            const float fu = sftab[2 * j], fv = sftab[2 * j + 1];
            __global const float *c0 = bbq + (size_t)jj * bplane
                + (size_t)(stab[3 * j + 2] - vmin + v) * (size_t)bw
                + (size_t)(stab[3 * j + 1] - umin + u0);
            const vecf t = mix(mix(VLOAD(c0), VLOAD(c0 + 1), fu),
                               mix(VLOAD(c0 + bw), VLOAD(c0 + bw + 1), fu), fv);
            VSTORE(out_depth ? t : exp(-t), tile + jj * SWEEP_WIDTH);
        }
        for (int q = 0; q < SWEEP_WIDTH; ++q) {  /* x = kb + x_lane is step jj(x_lane) */
            float run[SWEEP_BLOCK];
            for (int x = 0; x < SWEEP_BLOCK; ++x)
                run[x] = tile[(sa > 0 ? SWEEP_BLOCK - 1 - x : x) * SWEEP_WIDTH + q];
            __global float *o = out + (size_t)out_off
                                + ((size_t)v * (size_t)n + (size_t)(u0 + q)) * (size_t)n + (size_t)kb;
            for (int h = 0; h < SWEEP_BLOCK; h += SWEEP_WIDTH) VSTORE(VLOAD(run + h), o + h);
        }
        return;
    }
#endif
    /* lanes along u: item i = (jj, v, chunk) */
    const int chunks = n / SWEEP_WIDTH;          /* n >= SWEEP_WIDTH, both powers of two */
    if (i >= SWEEP_BLOCK * n * chunks) return;
    const int jj = i / (n * chunks), rem = i - jj * (n * chunks);
    const int v = rem / chunks, u0 = (rem - v * chunks) * SWEEP_WIDTH;
    const int j = bp * SWEEP_BLOCK + jj;
    if (j >= n) return;
    const float fu = sftab[2 * j], fv = sftab[2 * j + 1];
    __global const float *c0 = bbq + (size_t)jj * bplane
        + (size_t)(stab[3 * j + 2] - vmin + v) * (size_t)bw + (size_t)(stab[3 * j + 1] - umin + u0);
    const vecf t = mix(mix(VLOAD(c0), VLOAD(c0 + 1), fu),
                       mix(VLOAD(c0 + bw), VLOAD(c0 + bw + 1), fu), fv);
    VSTORE(out_depth ? t : exp(-t), out + (size_t)out_off + elem_uva(n, a, u0, v, stab[3 * j]));
}

__kernel void transmittance_sweep_block(
        __global const float *S, const int s_off, const int n, const int a, const int sa,
        const float su, const float sv, const float kscale,
        __global float *col, const int cw, const int ou, const int ov,
        __global float *bb, const int bw, const int brows,
        __global const int *stab, __global const float *sftab, __global const int *btab,
        const int b, const int nb, const int out_depth, __global float *out, const int out_off,
        const int n_col) {
    const int gid = get_global_id(0);
    const size_t bplane = (size_t)brows * (size_t)bw;
    if (gid < n_col)
        sweep_block_columns(gid, S, s_off, n, sa, su, sv, kscale, col, cw, ou, ov, bb, bw,
                            bplane, stab, sftab, btab, b, nb);
    else
        write_block_voxels(gid - n_col, n, a, sa, bb, bw, bplane, stab, sftab, btab, b,
                           out_depth, out, out_off);
}

__kernel void combine_levels(__global const float *tgrid, __global const int *offsets,
                             __global const float *weights, const int n_levels, const int base,
                             const float bias, __global float *out) {
    const int i = get_global_id(0);
    if (i >= base * base * base) return;
    const int zy = i / base, z = zy / base;     /* no '%' (see cl/pyramid.cl) */
    const float3 c = (float3)((float)(i - zy * base), (float)(zy - z * base), (float)z) + 0.5f;
    float sum = bias;
    for (int l = 0; l < n_levels; ++l) {
        const int n = base >> l;
        /* base voxel centre in level-l voxel units: (i + 0.5) / 2^l - 0.5 */
        sum += weights[l] * grid_lookup(tgrid + offsets[l], n, n, n,
                                        c * (1.0f / (float)(1 << l)) - 0.5f);
    }
    out[i] = sum;
}
