/* Template gather: the network's input features for N query points (seed III.B.2-5), and the
 * render-time bake of the combined graded transmittance it reads.
 *
 * Contract: clvol/neural/layout.py (features [N][3][NP], levels [N][L][NP]); docs/templates.md.
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
 * Speed (docs/conventions.md, PoCL on the CPU): one work-item per query, the template points in float16
 * lanes (17 chunks of 16 for NP = 266), so the table reads and the output stores are
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
#include "grid.h"
#include "phase.h"
#include "majorant.h"

#ifndef NP
#define NP 266
#endif
#define CHUNKS ((NP + 15) / 16)
#define NPAD (16 * CHUNKS)
#define TAIL (NP - 16 * (CHUNKS - 1))   /* points in the last chunk, 1..16 */
#ifndef COARSE_LEVEL
#define COARSE_LEVEL 3
#endif

#include "lanes.h"

__attribute__((always_inline))
i16 gatheri16(__global const int *p, i16 i) {
    return (i16)(p[i.s0], p[i.s1], p[i.s2], p[i.s3], p[i.s4], p[i.s5], p[i.s6], p[i.s7],
                 p[i.s8], p[i.s9], p[i.sa], p[i.sb], p[i.sc], p[i.sd], p[i.se], p[i.sf]);
}

/* Render lookups read, per lane and row, the float4 (tau, C at x0; tau, C at x0 + 1).
 * GATHER_SHUFFLE (the host sets it on PoCL): each lane's four row addresses are scalars (a base
 * and two strides, extracted from the vectors once), the sixteen float4 of a row are loaded
 * and transposed into four float16 in registers with Clang's __builtin_shufflevector (~24
 * instructions a row). Written lane by lane instead, LLVM turns them into four AVX-512 gathers
 * a row, ~2x slower here. Without it (Oclgrind, other compilers): per-lane scalar loads; its
 * uninitialised-value checker crashed on the float4 form and reports shuffle results as
 * undefined (a false positive, cl/mlp.cl). Both read the same values and give the same bits
 * (tests/test_gather.py). */
#ifdef GATHER_SHUFFLE
#define SV __builtin_shufflevector
#define TRANSPOSE4(E, X, Y, Z, W)                                                          \
    {                                                                                      \
        const float8 p0 = SV(E##0, E##1, 0, 1, 2, 3, 4, 5, 6, 7);                          \
        const float8 p1 = SV(E##2, E##3, 0, 1, 2, 3, 4, 5, 6, 7);                          \
        const float8 p2 = SV(E##4, E##5, 0, 1, 2, 3, 4, 5, 6, 7);                          \
        const float8 p3 = SV(E##6, E##7, 0, 1, 2, 3, 4, 5, 6, 7);                          \
        const float8 p4 = SV(E##8, E##9, 0, 1, 2, 3, 4, 5, 6, 7);                          \
        const float8 p5 = SV(E##a, E##b, 0, 1, 2, 3, 4, 5, 6, 7);                          \
        const float8 p6 = SV(E##c, E##d, 0, 1, 2, 3, 4, 5, 6, 7);                          \
        const float8 p7 = SV(E##e, E##f, 0, 1, 2, 3, 4, 5, 6, 7);                          \
        const v16 m0 = SV(p0, p1, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);   \
        const v16 m1 = SV(p2, p3, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);   \
        const v16 m2 = SV(p4, p5, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);   \
        const v16 m3 = SV(p6, p7, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);   \
        const v16 u0 = SV(m0, m1, 0, 4, 8, 12, 16, 20, 24, 28, 1, 5, 9, 13, 17, 21, 25, 29); \
        const v16 u1 = SV(m0, m1, 2, 6, 10, 14, 18, 22, 26, 30, 3, 7, 11, 15, 19, 23, 27, 31); \
        const v16 u2 = SV(m2, m3, 0, 4, 8, 12, 16, 20, 24, 28, 1, 5, 9, 13, 17, 21, 25, 29); \
        const v16 u3 = SV(m2, m3, 2, 6, 10, 14, 18, 22, 26, 30, 3, 7, 11, 15, 19, 23, 27, 31); \
        X = SV(u0, u2, 0, 1, 2, 3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 22, 23);             \
        Y = SV(u0, u2, 8, 9, 10, 11, 12, 13, 14, 15, 24, 25, 26, 27, 28, 29, 30, 31);       \
        Z = SV(u1, u3, 0, 1, 2, 3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 22, 23);             \
        W = SV(u1, u3, 8, 9, 10, 11, 12, 13, 14, 15, 24, 25, 26, 27, 28, 29, 30, 31);       \
    }

/* Lane J's four rows (z0, y0), (z0, y1), (z1, y0), (z1, y1). */
#define LANE_ROWS(P, J)                                                                    \
    const float4 ra##J = vload4(0, P + ib[0x##J]);                                         \
    const float4 rb##J = vload4(0, P + ib[0x##J] + iy[0x##J]);                             \
    const float4 rc##J = vload4(0, P + ib[0x##J] + iz[0x##J]);                             \
    const float4 rd##J = vload4(0, P + ib[0x##J] + iy[0x##J] + iz[0x##J]);
#endif

/* grid_lookup (grid.h) on 16 lanes of one level (off, n uniform), clamped coordinates.
 * Scalar bounds are broadcast explicitly: Oclgrind 21.10 applies the scalar argument of
 * min(int16, int) to lane 0 only (found by the ray marcher's engineer). */
__attribute__((always_inline))
v16 lookup16(__global const float *d, int n, v16 gx, v16 gy, v16 gz) {
    const v16 hi = (v16)((float)(n - 1));
    v16 x = clamp(gx, (v16)(0.0f), hi), y = clamp(gy, (v16)(0.0f), hi);
    v16 z = clamp(gz, (v16)(0.0f), hi);
    i16 x0 = convert_int16(x), y0 = convert_int16(y), z0 = convert_int16(z);
    const i16 nm1 = (i16)(n - 1), nn = (i16)(n);
    i16 x1 = min(x0 + 1, nm1), y1 = min(y0 + 1, nm1), z1 = min(z0 + 1, nm1);
    v16 fx = x - convert_float16(x0), fy = y - convert_float16(y0), fz = z - convert_float16(z0);
    i16 r00 = (z0 * nn + y0) * nn, r01 = (z0 * nn + y1) * nn;
    i16 r10 = (z1 * nn + y0) * nn, r11 = (z1 * nn + y1) * nn;
    v16 c00 = mix(gather16(d, r00 + x0), gather16(d, r00 + x1), fx);
    v16 c01 = mix(gather16(d, r01 + x0), gather16(d, r01 + x1), fx);
    v16 c10 = mix(gather16(d, r10 + x0), gather16(d, r10 + x1), fx);
    v16 c11 = mix(gather16(d, r11 + x0), gather16(d, r11 + x1), fx);
    return mix(mix(c00, c01, fy), mix(c10, c11, fy), fz);
}

/* Store the first NP - 16 c values of a chunk (all 16 except in the last chunk). */
__attribute__((always_inline))
void store_chunk(__global float *row, int c, v16 v) {
    if (c < CHUNKS - 1) {
        vstore16(v, c, row);
    } else {
        float t[16];
        vstore16(v, 0, t);
        for (int i = 0; i < TAIL; ++i) row[16 * c + i] = t[i];
    }
}

/* The template frame of docs/conventions.md (twin: clvol.neural.templates.template_frame): f[0..2] = x,
 * f[3..5] = y. In scalars: Oclgrind's uninitialised-value checker crashed on the float3
 * merged after the fallback branch (a vector phi). */
__attribute__((always_inline))
void template_frame(float3 l, float3 w, float *f) {
    const float d = dot(w, l);
    float px = w.x - d * l.x, py = w.y - d * l.y, pz = w.z - d * l.z;
    const float cx = w.y * l.z - w.z * l.y, cy = w.z * l.x - w.x * l.z, cz = w.x * l.y - w.y * l.x;
    if (sqrt(cx * cx + cy * cy + cz * cz) < 1e-4f) {
        /* omega (anti)parallel to l: x from the world axis least aligned with l (ties: lowest) */
        const float ax = fabs(l.x), ay = fabs(l.y), az = fabs(l.z);
        const int ix = (ax <= ay) & (ax <= az);
        const int iy = (ix == 0) & (ay <= az);
        const float ex = ix ? 1.0f : 0.0f, ey = iy ? 1.0f : 0.0f, ez = (ix | iy) ? 0.0f : 1.0f;
        const float de = ex * l.x + ey * l.y + ez * l.z;
        px = ex - de * l.x;
        py = ey - de * l.y;
        pz = ez - de * l.z;
    }
    const float inv = 1.0f / sqrt(px * px + py * py + pz * pz);
    f[0] = px * inv;
    f[1] = py * inv;
    f[2] = pz * inv;
    f[3] = l.y * f[2] - l.z * f[1];     /* y = l x x */
    f[4] = l.z * f[0] - l.x * f[2];
    f[5] = l.x * f[1] - l.y * f[0];
}

/* Distance along p + t l (t >= 0) to the far end of the last non-empty coarse cell. */
__attribute__((always_inline))
float light_entry(__global const float *coarse, int nc, float3 cmin, float csize, float3 p,
                  float3 l) {
    maj_dda s;
    float bs = csize / (float)nc;
    float3 cmax = cmin + (float3)(csize);
    float t_enter = 0.0f;
    if (maj_dda_init(&s, p, l, cmin, cmax, (float3)(bs), (int3)(nc), 0.0f, INFINITY)) {
        do {
            float tb = maj_dda_seg_end(&s);
            if (maj_dda_value(&s, coarse) > 0.0f) t_enter = tb;
        } while (maj_dda_step(&s));
    }
    return t_enter;
}

/* Level of highlight layer k: round(log2(spacing in base voxels)), clamped. */
__attribute__((always_inline))
int highlight_level(float spacing_vox, int L) {
    if (!(spacing_vox > 0.0f)) return 0;
    float lv = log2(spacing_vox) + 0.5f;
    if (lv < 1.0f) return 0;              /* floor for the non-negative range only (cast) */
    return min((int)lv, L - 1);
}

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
    const float3 cmin = cmin4.xyz, cmax = cmin4.xyz + (float3)(csize);
    const float3 l = light4.xyz;
    const float3 p = vload3(q, points), w = vload3(q, omegas);
    float fr[6];
    template_frame(l, w, fr);
    const float fxx = fr[0], fxy = fr[1], fxz = fr[2], fyx = fr[3], fyy = fr[4], fyz = fr[5];
    const float mu = clamp(-dot(l, w), -1.0f, 1.0f);
    const float alpha = acos(mu);

    const int nc = n0 >> COARSE_LEVEL;
    const float t_enter = light_entry(dens + loff[COARSE_LEVEL], nc, cmin, csize, p, l);
    tenter[q] = t_enter;

    /* Highlight layer levels for this query (uniform over the layer). */
    const float tv = t_enter * ((float)n0 / csize);
    const i16 h0 = (i16)(highlight_level(hl_spacing[0] * tv, L));
    const i16 h1 = (i16)(highlight_level(hl_spacing[1] * tv, L));
    const i16 h2 = (i16)(highlight_level(hl_spacing[2] * tv, L));
    const i16 h3 = (i16)(highlight_level(hl_spacing[3] * tv, L));

    const float fa = alpha * ((float)(NA - 1) / CLVOL_PI);
    const int a0 = min((int)fa, NA - 2);
    const float at = fa - (float)a0;
    __global const float *row0 = ptab + (size_t)a0 * NPAD;
    __global const float *row1 = row0 + NPAD;

    __global float *o = out + (size_t)q * 3 * NP;
#ifndef GATHER_RENDER
    __global float *lv = levels + (size_t)q * L * NP;
#endif

    for (int c = 0; c < CHUNKS; ++c) {
        const v16 ux = vload16(c, tpl), uy = vload16(c, tpl + NPAD), uz = vload16(c, tpl + 2 * NPAD);
        const i16 info = vload16(c, pinfo);
        const i16 hl = info == (i16)(-1) ? h0 : (info == (i16)(-2) ? h1 : (info == (i16)(-3) ? h2 : h3));
        const i16 diffuse = info >= (i16)(0);
        const i16 lvl = diffuse ? info : hl;
        const v16 scale = select((v16)(t_enter), (v16)(csize), diffuse);
        const v16 sx = p.x + scale * (ux * fxx + uy * fyx + uz * l.x);
        const v16 sy = p.y + scale * (ux * fxy + uy * fyy + uz * l.y);
        const v16 sz = p.z + scale * (ux * fxz + uy * fyz + uz * l.z);
        const i16 n = (i16)(n0) >> lvl;
        const v16 vox = csize / convert_float16(n);
        const i16 inside = (sx >= cmin.x) & (sx <= cmax.x) & (sy >= cmin.y) & (sy <= cmax.y)
                         & (sz >= cmin.z) & (sz <= cmax.z);
        const i16 nm1 = n - (i16)(1);
        const v16 hi = convert_float16(nm1);
        const v16 gx = clamp((sx - cmin.x) / vox - 0.5f, (v16)(0.0f), hi);
        const v16 gy = clamp((sy - cmin.y) / vox - 0.5f, (v16)(0.0f), hi);
        const v16 gz = clamp((sz - cmin.z) / vox - 0.5f, (v16)(0.0f), hi);
        const i16 off = gatheri16(loff, lvl);
#ifdef GATHER_RENDER
        /* Corners (x0, y0, z0) <= n - 2, so x0 + 1, y0 + 1, z0 + 1 are in the level and every
         * row pair is one 16-byte load; at the top face the weight is 1 instead of grid.h's
         * clamped corner (the same value up to rounding). A 1-voxel level reads one row beyond
         * itself with weight 0: the next level's data, or the buffer's padding. */
        const i16 top = max(n - (i16)(2), (i16)(0));
        const i16 x0 = min(convert_int16(gx), top), y0 = min(convert_int16(gy), top);
        const i16 z0 = min(convert_int16(gz), top);
        const v16 wx = gx - convert_float16(x0), wy = gy - convert_float16(y0);
        const v16 wz = gz - convert_float16(z0);
        const i16 base = (i16)(2) * (off + (z0 * n + y0) * n + x0);
        const i16 dy = (i16)(2) * n, dz = (i16)(2) * n * n;     /* row strides */
        v16 t0, c0, t1, c1;
#ifdef GATHER_SHUFFLE
        int ib[16], iy[16], iz[16];
        vstore16(base, 0, ib);
        vstore16(dy, 0, iy);
        vstore16(dz, 0, iz);
        LANE_ROWS(baked, 0) LANE_ROWS(baked, 1) LANE_ROWS(baked, 2) LANE_ROWS(baked, 3)
        LANE_ROWS(baked, 4) LANE_ROWS(baked, 5) LANE_ROWS(baked, 6) LANE_ROWS(baked, 7)
        LANE_ROWS(baked, 8) LANE_ROWS(baked, 9) LANE_ROWS(baked, a) LANE_ROWS(baked, b)
        LANE_ROWS(baked, c) LANE_ROWS(baked, d) LANE_ROWS(baked, e) LANE_ROWS(baked, f)
#define ROW(E, R) TRANSPOSE4(E, t0, c0, t1, c1)
#else
#define ROW(E, R)                                                                          \
        t0 = gather16(baked, R); c0 = gather16(baked, R + (i16)(1));                       \
        t1 = gather16(baked, R + (i16)(2)); c1 = gather16(baked, R + (i16)(3));
#endif
        ROW(ra, base)
        const v16 t00 = mix(t0, t1, wx), k00 = mix(c0, c1, wx);
        ROW(rb, base + dy)
        const v16 t01 = mix(t0, t1, wx), k01 = mix(c0, c1, wx);
        ROW(rc, base + dz)
        const v16 t10 = mix(t0, t1, wx), k10 = mix(c0, c1, wx);
        ROW(rd, base + dy + dz)
        const v16 t11 = mix(t0, t1, wx), k11 = mix(c0, c1, wx);
#undef ROW
        const v16 tau = mix(mix(t00, t01, wy), mix(t10, t11, wy), wz);
        const v16 tc = mix(mix(k00, k01, wy), mix(k10, k11, wy), wz);
        store_chunk(o, c, log1p(select((v16)(0.0f), tau, inside)));
        store_chunk(o + NP, c, select((v16)(c_out), tc, inside));
#else
        const i16 x0 = convert_int16(gx), y0 = convert_int16(gy), z0 = convert_int16(gz);
        const i16 x1 = min(x0 + (i16)(1), nm1), y1 = min(y0 + (i16)(1), nm1);
        const i16 z1 = min(z0 + (i16)(1), nm1);
        const v16 wx = gx - convert_float16(x0), wy = gy - convert_float16(y0);
        const v16 wz = gz - convert_float16(z0);
        {
            const i16 r00 = off + (z0 * n + y0) * n, r01 = off + (z0 * n + y1) * n;
            const i16 r10 = off + (z1 * n + y0) * n, r11 = off + (z1 * n + y1) * n;
            const v16 d00 = mix(gather16(dens, r00 + x0), gather16(dens, r00 + x1), wx);
            const v16 d01 = mix(gather16(dens, r01 + x0), gather16(dens, r01 + x1), wx);
            const v16 d10 = mix(gather16(dens, r10 + x0), gather16(dens, r10 + x1), wx);
            const v16 d11 = mix(gather16(dens, r11 + x0), gather16(dens, r11 + x1), wx);
            const v16 rho = mix(mix(d00, d01, wy), mix(d10, d11, wy), wz);
            const v16 tau = rho * gather16(taufac, lvl);
            store_chunk(o, c, log1p(select((v16)(0.0f), tau, inside)));
            store_chunk(o + NP, c, (v16)(0.0f));
        }
        /* Every graded level m, sampled at level lvl's centres around s (trilinear weights).
         * Level-lvl centre i sits at level-m coordinate (i + 0.5) nm / n - 0.5 (exact ratio). */
        const v16 cx0 = convert_float16(x0) + 0.5f, cx1 = convert_float16(x1) + 0.5f;
        const v16 cy0 = convert_float16(y0) + 0.5f, cy1 = convert_float16(y1) + 0.5f;
        const v16 cz0 = convert_float16(z0) + 0.5f, cz1 = convert_float16(z1) + 0.5f;
        const v16 nf = convert_float16(n);
        for (int m = 0; m < L; ++m) {
            const int nmi = n0 >> m;
            __global const float *tm = tlev + loff[m];
            const v16 r = (float)nmi / nf;
            const v16 ax0 = cx0 * r - 0.5f, ax1 = cx1 * r - 0.5f;
            const v16 ay0 = cy0 * r - 0.5f, ay1 = cy1 * r - 0.5f;
            const v16 az0 = cz0 * r - 0.5f, az1 = cz1 * r - 0.5f;
            const v16 e00 = mix(lookup16(tm, nmi, ax0, ay0, az0), lookup16(tm, nmi, ax1, ay0, az0), wx);
            const v16 e01 = mix(lookup16(tm, nmi, ax0, ay1, az0), lookup16(tm, nmi, ax1, ay1, az0), wx);
            const v16 e10 = mix(lookup16(tm, nmi, ax0, ay0, az1), lookup16(tm, nmi, ax1, ay0, az1), wx);
            const v16 e11 = mix(lookup16(tm, nmi, ax0, ay1, az1), lookup16(tm, nmi, ax1, ay1, az1), wx);
            const v16 val = mix(mix(e00, e01, wy), mix(e10, e11, wy), wz);
            store_chunk(lv + (size_t)m * NP, c, select((v16)(1.0f), val, inside));
        }
#endif
        store_chunk(o + 2 * NP, c, mix(vload16(c, row0), vload16(c, row1), at));
    }
    o[2 * NP] = log1p(phase_eval(mu, lobe_g, lobe_w));
}

/* ------------------------------------------------------------------------------- bake
 * Render-time grid, once per light or weight change: for every voxel v of level lvl,
 *     baked[2 (off_lvl + v)] = (rho_lvl[v] * taufac[lvl], sum_m w_m T_m(centre of v) + bias),
 * T_m(centre) the trilinear lookup of grid.h at level-m coordinate (i + 0.5) n_m / n_lvl - 0.5.
 * That lookup is separable at these regular positions, so levels with n >= 16 are baked as:
 *   bake_xpass (per coarser m > lvl): X_m[zm][ym][x] = T_m row (zm, ym) interpolated in x at the
 *              n_lvl centres (the c00..c11 row values of grid_lookup);
 *   bake_rows  (per level): 16 consecutive x of one row per work-item; for m > lvl the y and z
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
 * (y, z) as span / 16 float16 chunks, so the per-level row set-up is shared by up to four
 * chunks. xoff[m]: offset of X_m in xbuf (m > lvl). */
#ifndef BAKE_SPAN
#define BAKE_SPAN 64
#endif
__kernel void bake_rows(__global const float *dens, __global const float *tlev,
                        __global const float *xbuf, __global const int *loff,
                        __global const int *xoff, const int L, const int n0, const int lvl,
                        const int log2n, const float taufac_lvl, __global const float *weights,
                        const float bias, __global float *baked) {
    const int n = n0 >> lvl;
    const int span = min(n, BAKE_SPAN), ns = span >> 4;
    const int i = get_global_id(0);           /* row segment index */
    if (i >= (n * n * n) / span) return;
    const int v = i * span;                   /* voxel index of the first lane in the level */
    const int x = v & (n - 1);
    const int zy = v >> log2n;
    const int y = zy & (n - 1), z = zy >> log2n;
    v16 acc[BAKE_SPAN / 16];
    for (int s = 0; s < ns; ++s) acc[s] = (v16)(0.0f);
    for (int m = 0; m < L; ++m) {
        const int nmi = n0 >> m;
        __global const float *tm = tlev + loff[m];
        const float wm = weights[m];
        if (m == lvl) {
            for (int s = 0; s < ns; ++s) acc[s] += wm * vload16(s, tm + v);
        } else if (m < lvl) {
            /* centre of v at level m: x 2^k + 2^(k-1) - 1/2 per axis, k = lvl - m: the mean
             * of the 2x2x2 block from b = x 2^k + 2^(k-1) - 1, lerped at 1/2 like grid.h */
            const int k = lvl - m, h = (1 << (k - 1)) - 1;
            const int by = (y << k) + h, bz = (z << k) + h;
            const int r00 = (bz * nmi + by) * nmi, r01 = r00 + nmi;
            const int r10 = r00 + nmi * nmi, r11 = r10 + nmi;
            for (int s = 0; s < ns; ++s) {
                const i16 bx = (((i16)(x + 16 * s)
                                 + (i16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15)) << k)
                               + (i16)(h);
                const v16 c00 = mix(gather16(tm, bx + (i16)(r00)), gather16(tm, bx + (i16)(r00 + 1)), 0.5f);
                const v16 c01 = mix(gather16(tm, bx + (i16)(r01)), gather16(tm, bx + (i16)(r01 + 1)), 0.5f);
                const v16 c10 = mix(gather16(tm, bx + (i16)(r10)), gather16(tm, bx + (i16)(r10 + 1)), 0.5f);
                const v16 c11 = mix(gather16(tm, bx + (i16)(r11)), gather16(tm, bx + (i16)(r11 + 1)), 0.5f);
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
                acc[s] += wm * mix(mix(vload16(s, q00), vload16(s, q01), fy),
                                   mix(vload16(s, q10), vload16(s, q11), fy), fz);
        }
    }
    __global float *b = baked + 2 * ((size_t)loff[lvl] + v);
    for (int s = 0; s < ns; ++s) {
        const v16 tau = vload16(s, dens + loff[lvl] + v) * taufac_lvl;
        const v16 cc = acc[s] + bias;
        vstore16(shuffle2(tau, cc, (uint16)(0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6, 22, 7, 23)), 2 * s, b);
        vstore16(shuffle2(tau, cc, (uint16)(8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31)), 2 * s + 1, b);
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
