/* Template gather: the network's input features for N query points (seed III.B.2-5), and the
 * render-time bake of the combined graded transmittance it reads.
 *
 * Contract: clvol/features/layout.py (features [N][3][NP], levels [N][L][NP]); docs/templates.md.
 * Twin: reference/gather.py. Host wrapper: clvol/kernels/gather.py.
 *
 * For query q (point p, unit omega toward the camera) and template point j:
 *   frame     z = l (toward the light), x = normalize(omega - (omega.l) l), y = z x x; when
 *             |omega x l| < 1e-4, x comes from the world axis least aligned with l (docs/conventions.md).
 *   position  s_j = p + scale_j (u.x x + u.y y + u.z z), u = template point j; scale_j = cube_size
 *             for diffuse points, t_enter for highlight points.
 *   t_enter   where the light enters the medium along p + t l: the far end of the last non-empty
 *             cell of the coarse level (COARSE_LEVEL, <= 32^3: a mip average of non-negative
 *             densities is > 0 iff its block holds density) met by the DDA of majorant.h; 0 if
 *             none. Highlight layer k reads level round(log2(hl_spacing[k] * t_enter)) (spacing in
 *             base voxels), clamped to [0, L-1]; diffuse points read the fixed level pinfo[j].
 *   density   log1p(tau), tau = rho_lvl(s_j) * density_scale * voxel_size(lvl): trilinear, clamped,
 *             0 outside the cube.
 *   T         train: levels[q][m][j] = T_m sampled at the voxel centres of level lvl and
 *             interpolated trilinearly to s_j (the same weights as the density), 1 outside the cube.
 *             render: the baked grid C_lvl = sum_m w_m T_m + b at level lvl's centres (bake_*
 *             kernels below) read with those weights: equals sum_m w_m levels[m] + b up to rounding.
 *   phase     log1p of seed eq. 5: j = 0 (centre) evaluates f(dot(-l, omega)) exactly; other
 *             points read the per-frame table ptab[NA][NPAD] linearly in alpha = acos(dot(-l, omega)).
 *
 * Speed (docs/conventions.md, PoCL on the CPU): one work-item per query, the template points in
 * vector lanes (cl/include/lanes.h; 17 chunks of 16 for NP = 266 at LANES 16), so the table reads and the output stores are
 * contiguous vector operations and only the grid reads are per-lane gathers. Render mode reads
 * (tau, C) pairs interleaved: one 16-byte load per lane and row serves both features and both
 * x corners (x0, y0, z0 stop at n - 2, so a weight of 1 at the top face replaces grid.h's
 * clamped corner: the same value to rounding), and the four rows of a lane are its base plus
 * fixed strides (see TRANSPOSE4 for how the loads become vectors). Queries come in the order
 * given by `order` (the host sorts them by coarse cell: ~1.3x fewer cache misses).
 * Oclgrind (CI, --uninitialized): its checker crashed on a float3 merged after a branch (the
 * template frame is computed in scalars) and on the float4 row loads (GATHER_SHUFFLE only); no
 * struct has vector members, no '/' and '%' on the same operands (see cl/pathtrace.cl).
 *
 * gather arguments (float32 unless said; world units; offsets in elements):
 *   dens      pyramid levels concatenated (raw density), offsets loff[L]          (train)
 *   tlev      graded T levels, same layout                                         (train)
 *   baked     float2 (tau, C) per voxel, offsets 2 loff, + 8 floats of padding     (render)
 *   loff      int[L]; L levels; n0 base resolution; cmin (float4), csize cube edge
 *   taufac    float[L]: density_scale * voxel size of level l                      (train)
 *   tpl       float[3][NPAD] template points (frame units), x row, y row, z row; pinfo int[NPAD]:
 *             level >= 0 for diffuse, -(k+1) for highlight layer k (padding lanes: level 0, u = 0);
 *             hl_spacing float[4]: spacing per unit t_enter (x n0/csize: base voxels)
 *   ptab      float[NA][NPAD] log1p phase feature over alpha = linspace(0, pi, NA)
 *   points, omegas  float[N][3]; light (float4, unit); lobe_g, lobe_w (float4, phase.h)
 *   c_out     render: value of C outside the cube (sum w + b)
 *   order     int[N]: work-item i handles query order[i] (a permutation: queries sorted by
 *             coarse cell share cache lines; every output row is still written at its query)
 *   out       features [N][3][NP]; levels [N][L][NP] (train); tenter [N]
 * Indices are int: the largest pyramid (1024^3) has 1.23e9 voxels, 2.45e9 floats as pairs, so
 * the host refuses render mode above 2^31 floats (kernels/gather.py).
 */
#include "gather_core.h"   /* the device functions, shared with cl/gather_mlp.cl */

#ifndef GATHER_RENDER
/* Train mode, one chunk of template points: the density feature at the points' level
 * (transmittance feature 0: the model combines the levels) and every graded level m sampled
 * at that level's voxel centres around the points, with the density's trilinear weights. */
__attribute__((always_inline))
void gather_train_chunk(__global const float *dens, __global const float *tlev,
                        __global const float *taufac, __global const int *loff, const int L,
                        const int n0, const int c, const iL lvl, const iL n, const iL off,
                        const iL inside, const vL gx, const vL gy, const vL gz,
                        __global float *o, __global float *lv) {
    const iL nm1 = n - (iL)(1);
    const iL x0 = convert_iL(gx), y0 = convert_iL(gy), z0 = convert_iL(gz);
    const iL x1 = min(x0 + (iL)(1), nm1), y1 = min(y0 + (iL)(1), nm1);
    const iL z1 = min(z0 + (iL)(1), nm1);
    const vL wx = gx - convert_vL(x0), wy = gy - convert_vL(y0);
    const vL wz = gz - convert_vL(z0);
    {
        const iL r00 = off + (z0 * n + y0) * n, r01 = off + (z0 * n + y1) * n;
        const iL r10 = off + (z1 * n + y0) * n, r11 = off + (z1 * n + y1) * n;
        const vL d00 = mix(gatherL(dens, r00 + x0), gatherL(dens, r00 + x1), wx);
        const vL d01 = mix(gatherL(dens, r01 + x0), gatherL(dens, r01 + x1), wx);
        const vL d10 = mix(gatherL(dens, r10 + x0), gatherL(dens, r10 + x1), wx);
        const vL d11 = mix(gatherL(dens, r11 + x0), gatherL(dens, r11 + x1), wx);
        const vL rho = mix(mix(d00, d01, wy), mix(d10, d11, wy), wz);
        const vL tau = rho * gatherL(taufac, lvl);
        store_chunk(o, c, log1p(select((vL)(0.0f), tau, inside)));
        store_chunk(o + NP, c, (vL)(0.0f));
    }
    /* Every graded level m, sampled at level lvl's centres around s (trilinear weights).
     * Level-lvl centre i sits at level-m coordinate (i + 0.5) nm / n - 0.5 (exact ratio). */
    const vL cx0 = convert_vL(x0) + 0.5f, cx1 = convert_vL(x1) + 0.5f;
    const vL cy0 = convert_vL(y0) + 0.5f, cy1 = convert_vL(y1) + 0.5f;
    const vL cz0 = convert_vL(z0) + 0.5f, cz1 = convert_vL(z1) + 0.5f;
    const vL nf = convert_vL(n);
    for (int m = 0; m < L; ++m) {
        const int nmi = n0 >> m;
        __global const float *tm = tlev + loff[m];
        const vL r = (float)nmi / nf;
        const vL ax0 = cx0 * r - 0.5f, ax1 = cx1 * r - 0.5f;
        const vL ay0 = cy0 * r - 0.5f, ay1 = cy1 * r - 0.5f;
        const vL az0 = cz0 * r - 0.5f, az1 = cz1 * r - 0.5f;
        const vL e00 = mix(lookupL(tm, nmi, ax0, ay0, az0), lookupL(tm, nmi, ax1, ay0, az0), wx);
        const vL e01 = mix(lookupL(tm, nmi, ax0, ay1, az0), lookupL(tm, nmi, ax1, ay1, az0), wx);
        const vL e10 = mix(lookupL(tm, nmi, ax0, ay0, az1), lookupL(tm, nmi, ax1, ay0, az1), wx);
        const vL e11 = mix(lookupL(tm, nmi, ax0, ay1, az1), lookupL(tm, nmi, ax1, ay1, az1), wx);
        const vL val = mix(mix(e00, e01, wy), mix(e10, e11, wy), wz);
        store_chunk(lv + (size_t)m * NP, c, select((vL)(1.0f), val, inside));
    }
}
#endif

/* One entry point for both modes (-D GATHER_RENDER: render): they share the query set-up,
 * the template points, the phase and t_enter, and differ in one step per chunk (the baked
 * grid's lookup or the train chunk above); the hosts (Python, the C host, the goldens) launch
 * both with the same arguments. */
__kernel void gather(__global const float *dens, __global const float *tlev,
                     __global const float *baked, __global const int *loff, const int L,
                     const int n0, const float4 cmin4, const float csize,
                     __global const float *taufac, __global const float *tpl,
                     __global const int *pinfo, __global const float *hl_spacing,
                     __global const float *ptab, const int NA,
                     __global const float *points, __global const float *omegas,
                     const float4 light4, const float4 lobe_g, const float4 lobe_w,
                     const float c_out, __global const int *order, const int N,
                     __global float *out, __global float *levels, __global float *tenter) {
    const int i = get_global_id(0);
    if (i >= N) return;
    const int q = order[i];     /* queries run in a cache-friendly order, rows stay in place */
    const float3 cmin = cmin4.xyz;
    const float3 l = light4.xyz;
    gather_query s;
    gather_query_init(&s, vload3(q, points), vload3(q, omegas), l, dens + loff[COARSE_LEVEL],
                      n0, cmin, csize, L, hl_spacing, NA);
    tenter[q] = s.t_enter;

    __global float *o = out + (size_t)q * 3 * NP;
#ifndef GATHER_RENDER
    __global float *lv = levels + (size_t)q * L * NP;
#endif

    for (int c = 0; c < CHUNKS; ++c) {
        iL lvl, n, off, inside;
        vL gx, gy, gz;
        gather_chunk_points(&s, c, l, cmin, csize, n0, tpl, pinfo, loff, &lvl, &n, &off,
                            &inside, &gx, &gy, &gz);
#ifdef GATHER_RENDER
        vL fd, ft;
        gather_render_chunk(baked, n, off, inside, gx, gy, gz, c_out, &fd, &ft);
        store_chunk(o, c, fd);
        store_chunk(o + NP, c, ft);
#else
        gather_train_chunk(dens, tlev, taufac, loff, L, n0, c, lvl, n, off, inside, gx, gy, gz,
                           o, lv);
#endif
        store_chunk(o + 2 * NP, c, gather_phase_chunk(&s, c, ptab));
    }
    o[2 * NP] = log1p(phase_eval(s.mu, lobe_g, lobe_w));
}

/* ------------------------------------------------------------------------------- bake
 * Render-time grid, once per light or weight change: for every voxel v of level lvl,
 *     baked[2 (off_lvl + v)] = (rho_lvl[v] * taufac[lvl], sum_m w_m T_m(centre of v) + bias),
 * T_m(centre) the trilinear lookup of grid.h at level-m coordinate (i + 0.5) n_m / n_lvl - 0.5.
 * That lookup is separable at these regular positions, so levels with n >= 16 are baked as:
 *   bake_xpass (per coarser m > lvl): X_m[zm][ym][x] = T_m row (zm, ym) interpolated in x at the
 *              n_lvl centres (the c00..c11 row values of grid_lookup);
 *   bake_rows  (per level): up to BAKE_SPAN consecutive x of one row per work-item; for m > lvl the y and z
 *              lerps of four X_m rows (grid_lookup's order), m == lvl the voxel itself, m < lvl
 *              the 2x2x2 fine block around the centre (coordinates fall exactly halfway), so the
 *              result equals the direct lookups up to float rounding (tested against train mode).
 * Levels with n < 16 (a few hundred voxels) use bake_small: the direct lookups, one voxel per
 * work-item. */

/* X_m rows: dst[dst_off + (row * n + x)], row = zm * nm + ym, for rows < nm^2, x < n. */
__kernel void bake_xpass(__global const float *tlev, const int src_off, const int nm,
                         const int n, const int log2n, __global float *dst, const int dst_off) {
    const int i = get_global_id(0);
    if (i >= nm * nm * n) return;
    const int row = i >> log2n, x = i & (n - 1);
    const float r = (float)nm / (float)n;
    const float g = clamp(((float)x + 0.5f) * r - 0.5f, 0.0f, (float)(nm - 1));
    const int x0 = (int)g, x1 = min(x0 + 1, nm - 1);
    __global const float *s = tlev + src_off + (size_t)row * nm;
    dst[dst_off + i] = mix(s[x0], s[x1], g - (float)x0);
}

/* One level with n >= 16: a work-item bakes span = min(n, BAKE_SPAN) consecutive x of row
 * (y, z) as span / LANES vector chunks, so the per-level row set-up is shared by the
 * chunks. xoff[m]: offset of X_m in xbuf (m > lvl). */
#include "constants.h"   /* BAKE_SPAN */
__kernel void bake_rows(__global const float *dens, __global const float *tlev,
                        __global const float *xbuf, __global const int *loff,
                        __global const int *xoff, const int L, const int n0, const int lvl,
                        const int log2n, const float taufac_lvl, __global const float *weights,
                        const float bias, __global float *baked) {
    const int n = n0 >> lvl;
    const int span = min(n, BAKE_SPAN), ns = span / LANES;
    const int i = get_global_id(0);           /* row segment index */
    if (i >= (n * n * n) / span) return;
    const int v = i * span;                   /* voxel index of the first lane in the level */
    const int x = v & (n - 1);
    const int zy = v >> log2n;
    const int y = zy & (n - 1), z = zy >> log2n;
    vL acc[BAKE_SPAN / LANES];
    for (int s = 0; s < ns; ++s) acc[s] = (vL)(0.0f);
    for (int m = 0; m < L; ++m) {
        const int nmi = n0 >> m;
        __global const float *tm = tlev + loff[m];
        const float wm = weights[m];
        if (m == lvl) {
            for (int s = 0; s < ns; ++s) acc[s] += wm * vloadL(s, tm + v);
        } else if (m < lvl) {
            /* centre of v at level m: x 2^k + 2^(k-1) - 1/2 per axis, k = lvl - m: the mean
             * of the 2x2x2 block from b = x 2^k + 2^(k-1) - 1, lerped at 1/2 like grid.h */
            const int k = lvl - m, h = (1 << (k - 1)) - 1;
            const int by = (y << k) + h, bz = (z << k) + h;
            const int r00 = (bz * nmi + by) * nmi, r01 = r00 + nmi;
            const int r10 = r00 + nmi * nmi, r11 = r10 + nmi;
            for (int s = 0; s < ns; ++s) {
                const iL bx = (((iL)(x + LANES * s) + LANE_IOTA) << k) + (iL)(h);
                const vL c00 = mix(gatherL(tm, bx + (iL)(r00)), gatherL(tm, bx + (iL)(r00 + 1)), 0.5f);
                const vL c01 = mix(gatherL(tm, bx + (iL)(r01)), gatherL(tm, bx + (iL)(r01 + 1)), 0.5f);
                const vL c10 = mix(gatherL(tm, bx + (iL)(r10)), gatherL(tm, bx + (iL)(r10 + 1)), 0.5f);
                const vL c11 = mix(gatherL(tm, bx + (iL)(r11)), gatherL(tm, bx + (iL)(r11 + 1)), 0.5f);
                acc[s] += wm * mix(mix(c00, c01, 0.5f), mix(c10, c11, 0.5f), 0.5f);
            }
        } else {
            const float r = (float)nmi / (float)n;
            const float gy = clamp(((float)y + 0.5f) * r - 0.5f, 0.0f, (float)(nmi - 1));
            const float gz = clamp(((float)z + 0.5f) * r - 0.5f, 0.0f, (float)(nmi - 1));
            const int y0 = (int)gy, z0 = (int)gz;
            const int y1 = min(y0 + 1, nmi - 1), z1 = min(z0 + 1, nmi - 1);
            const float fy = gy - (float)y0, fz = gz - (float)z0;
            __global const float *xm = xbuf + xoff[m] + x;
            __global const float *q00 = xm + (size_t)(z0 * nmi + y0) * n;
            __global const float *q01 = xm + (size_t)(z0 * nmi + y1) * n;
            __global const float *q10 = xm + (size_t)(z1 * nmi + y0) * n;
            __global const float *q11 = xm + (size_t)(z1 * nmi + y1) * n;
            for (int s = 0; s < ns; ++s)
                acc[s] += wm * mix(mix(vloadL(s, q00), vloadL(s, q01), fy),
                                   mix(vloadL(s, q10), vloadL(s, q11), fy), fz);
        }
    }
    __global float *b = baked + 2 * ((size_t)loff[lvl] + v);
    for (int s = 0; s < ns; ++s) {
        const vL tau = vloadL(s, dens + loff[lvl] + v) * taufac_lvl;
        const vL cc = acc[s] + bias;
        vstoreL(shuffle2(tau, cc, LANE_ZIP_LO), 2 * s, b);
        vstoreL(shuffle2(tau, cc, LANE_ZIP_HI), 2 * s + 1, b);
    }
}

/* Levels first..L-1 (all with n < 16): one voxel per work-item, direct lookups. */
__kernel void bake_small(__global const float *dens, __global const float *tlev,
                         __global const int *loff, const int L, const int n0, const int first,
                         __global const float *taufac, __global const float *weights,
                         const float bias, __global float *baked) {
    const int i = loff[first] + get_global_id(0);
    if (i >= loff[L - 1] + 1) return;
    int lvl = first;
    while (lvl + 1 < L && i >= loff[lvl + 1]) ++lvl;
    const int n = n0 >> lvl;
    const int v = i - loff[lvl];
    const int zy = v / n, z = zy / n;          /* no '%' (Oclgrind) */
    const int x = v - zy * n, y = zy - z * n;
    float acc = 0.0f;
    for (int m = 0; m < L; ++m) {
        const int nm = n0 >> m;
        const float r = (float)nm / (float)n;
        const float3 g = ((float3)((float)x, (float)y, (float)z) + 0.5f) * r - 0.5f;
        acc += weights[m] * grid_lookup(tlev + loff[m], nm, nm, nm, g);
    }
    baked[2 * i] = dens[i] * taufac[lvl];
    baked[2 * i + 1] = acc + bias;
}
