/* The template gather's device functions (cl/gather.cl documents the gather; twin
 * reference/gather.py), shared by the gather kernel and the fused gather + network kernel
 * (cl/gather_mlp.cl): per query gather_query_init, per chunk of LANES template points
 * (cl/include/lanes.h) gather_chunk_points, then gather_render_chunk (render mode) and gather_phase_chunk. */
#ifndef CLVOL_GATHER_CORE_H
#define CLVOL_GATHER_CORE_H

#include "grid.h"
#include "phase.h"
#include "majorant.h"

#ifndef NP
#define NP 266
#endif
#include "lanes.h"

/* Table rows are padded to whole 16s (the widest LANES: one host layout for every width,
 * clvol/kernels/gather.py n_pad); a work-item takes LANES points a chunk. */
#define NPAD (16 * ((NP + 15) / 16))
#define CHUNKS ((NP + LANES - 1) / LANES)
#define TAIL (NP - LANES * (CHUNKS - 1))   /* points in the last chunk, 1..LANES */
#ifndef COARSE_LEVEL
#define COARSE_LEVEL 3
#endif

__attribute__((always_inline))
iL gatheriL(__global const int *p, iL i) {
    return (iL)(p[i.s0], p[i.s1], p[i.s2], p[i.s3]
#if LANES >= 8
                , p[i.s4], p[i.s5], p[i.s6], p[i.s7]
#endif
#if LANES == 16
                , p[i.s8], p[i.s9], p[i.sa], p[i.sb], p[i.sc], p[i.sd], p[i.se], p[i.sf]
#endif
                );
}

/* Render lookups read, per lane and row, the float4 (tau, C at x0; tau, C at x0 + 1).
 * GATHER_SHUFFLE (the host sets it on PoCL): each lane's four row addresses are scalars (a base
 * and two strides, extracted from the vectors once), the LANES float4 of a row are loaded
 * and transposed into four vL in registers with Clang's __builtin_shufflevector (~24
 * instructions a row). Written lane by lane instead, LLVM turns them into four AVX-512 gathers
 * a row, ~2x slower here. Without it (Oclgrind, other compilers): per-lane scalar loads; its
 * uninitialised-value checker crashed on the float4 form and reports shuffle results as
 * undefined (a false positive, cl/mlp.cl). Both read the same values and give the same bits
 * (tests/test_gather.py). */
#ifdef GATHER_SHUFFLE
#define SV __builtin_shufflevector
#if LANES == 16
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
        const vL m0 = SV(p0, p1, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);    \
        const vL m1 = SV(p2, p3, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);    \
        const vL m2 = SV(p4, p5, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);    \
        const vL m3 = SV(p6, p7, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);    \
        const vL u0 = SV(m0, m1, 0, 4, 8, 12, 16, 20, 24, 28, 1, 5, 9, 13, 17, 21, 25, 29); \
        const vL u1 = SV(m0, m1, 2, 6, 10, 14, 18, 22, 26, 30, 3, 7, 11, 15, 19, 23, 27, 31); \
        const vL u2 = SV(m2, m3, 0, 4, 8, 12, 16, 20, 24, 28, 1, 5, 9, 13, 17, 21, 25, 29); \
        const vL u3 = SV(m2, m3, 2, 6, 10, 14, 18, 22, 26, 30, 3, 7, 11, 15, 19, 23, 27, 31); \
        X = SV(u0, u2, 0, 1, 2, 3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 22, 23);             \
        Y = SV(u0, u2, 8, 9, 10, 11, 12, 13, 14, 15, 24, 25, 26, 27, 28, 29, 30, 31);       \
        Z = SV(u1, u3, 0, 1, 2, 3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 22, 23);             \
        W = SV(u1, u3, 8, 9, 10, 11, 12, 13, 14, 15, 24, 25, 26, 27, 28, 29, 30, 31);       \
    }
#elif LANES == 8
#define TRANSPOSE4(E, X, Y, Z, W)                                                          \
    {                                                                                      \
        const float8 p0 = SV(E##0, E##1, 0, 1, 2, 3, 4, 5, 6, 7);                          \
        const float8 p1 = SV(E##2, E##3, 0, 1, 2, 3, 4, 5, 6, 7);                          \
        const float8 p2 = SV(E##4, E##5, 0, 1, 2, 3, 4, 5, 6, 7);                          \
        const float8 p3 = SV(E##6, E##7, 0, 1, 2, 3, 4, 5, 6, 7);                          \
        const float8 u0 = SV(p0, p1, 0, 4, 8, 12, 1, 5, 9, 13);                            \
        const float8 u1 = SV(p0, p1, 2, 6, 10, 14, 3, 7, 11, 15);                          \
        const float8 u2 = SV(p2, p3, 0, 4, 8, 12, 1, 5, 9, 13);                            \
        const float8 u3 = SV(p2, p3, 2, 6, 10, 14, 3, 7, 11, 15);                          \
        X = SV(u0, u2, 0, 1, 2, 3, 8, 9, 10, 11);                                          \
        Y = SV(u0, u2, 4, 5, 6, 7, 12, 13, 14, 15);                                        \
        Z = SV(u1, u3, 0, 1, 2, 3, 8, 9, 10, 11);                                          \
        W = SV(u1, u3, 4, 5, 6, 7, 12, 13, 14, 15);                                        \
    }
#else
#define TRANSPOSE4(E, X, Y, Z, W)                                                          \
    {                                                                                      \
        const float4 u0 = SV(E##0, E##1, 0, 4, 1, 5), u1 = SV(E##0, E##1, 2, 6, 3, 7);    \
        const float4 u2 = SV(E##2, E##3, 0, 4, 1, 5), u3 = SV(E##2, E##3, 2, 6, 3, 7);    \
        X = SV(u0, u2, 0, 1, 4, 5);                                                        \
        Y = SV(u0, u2, 2, 3, 6, 7);                                                        \
        Z = SV(u1, u3, 0, 1, 4, 5);                                                        \
        W = SV(u1, u3, 2, 3, 6, 7);                                                        \
    }
#endif

/* Lane J's four rows (z0, y0), (z0, y1), (z1, y0), (z1, y1). */
#define LANE_ROWS(P, J)                                                                    \
    const float4 ra##J = vload4(0, P + ib[0x##J]);                                         \
    const float4 rb##J = vload4(0, P + ib[0x##J] + iy[0x##J]);                             \
    const float4 rc##J = vload4(0, P + ib[0x##J] + iz[0x##J]);                             \
    const float4 rd##J = vload4(0, P + ib[0x##J] + iy[0x##J] + iz[0x##J]);
#endif

/* grid_lookup (grid.h) on LANES lanes of one level (off, n uniform), clamped coordinates.
 * Scalar bounds are broadcast explicitly: Oclgrind 21.10 applies the scalar argument of
 * min(int16, int) to lane 0 only (found by the ray marcher's engineer). */
__attribute__((always_inline))
vL lookupL(__global const float *d, int n, vL gx, vL gy, vL gz) {
    const vL hi = (vL)((float)(n - 1));
    vL x = clamp(gx, (vL)(0.0f), hi), y = clamp(gy, (vL)(0.0f), hi);
    vL z = clamp(gz, (vL)(0.0f), hi);
    iL x0 = convert_iL(x), y0 = convert_iL(y), z0 = convert_iL(z);
    const iL nm1 = (iL)(n - 1), nn = (iL)(n);
    iL x1 = min(x0 + 1, nm1), y1 = min(y0 + 1, nm1), z1 = min(z0 + 1, nm1);
    vL fx = x - convert_vL(x0), fy = y - convert_vL(y0), fz = z - convert_vL(z0);
    iL r00 = (z0 * nn + y0) * nn, r01 = (z0 * nn + y1) * nn;
    iL r10 = (z1 * nn + y0) * nn, r11 = (z1 * nn + y1) * nn;
    vL c00 = mix(gatherL(d, r00 + x0), gatherL(d, r00 + x1), fx);
    vL c01 = mix(gatherL(d, r01 + x0), gatherL(d, r01 + x1), fx);
    vL c10 = mix(gatherL(d, r10 + x0), gatherL(d, r10 + x1), fx);
    vL c11 = mix(gatherL(d, r11 + x0), gatherL(d, r11 + x1), fx);
    return mix(mix(c00, c01, fy), mix(c10, c11, fy), fz);
}

/* Store the first NP - LANES c values of a chunk (all LANES except in the last chunk). */
__attribute__((always_inline))
void store_chunk(__global float *row, int c, vL v) {
    if (c < CHUNKS - 1) {
        vstoreL(v, c, row);
    } else {
        float t[LANES];
        vstoreL(v, 0, t);
        for (int i = 0; i < TAIL; ++i) row[LANES * c + i] = t[i];
    }
}

/* The template frame of docs/conventions.md (twin: clvol.features.templates.template_frame): f[0..2] = x,
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

/* What every chunk of a query's template points reads (scalars only: Oclgrind, see above). */
typedef struct {
    float px, py, pz;                       /* query point p */
    float fxx, fxy, fxz, fyx, fyy, fyz;     /* frame x and y axes (z = l) */
    float t_enter, mu, at;                  /* light entry; dot(-l, omega); alpha-table weight */
    int h0, h1, h2, h3, a0;                 /* levels of highlight layers 0-3; alpha-table row */
} gather_query;

/* Frame, t_enter (coarse: the pyramid's COARSE_LEVEL, nc = n0 >> COARSE_LEVEL cells a side),
 * highlight levels and the phase table row of the query at p looking along w. */
__attribute__((always_inline))
void gather_query_init(gather_query *s, float3 p, float3 w, float3 l,
                       __global const float *coarse, int n0, float3 cmin, float csize, int L,
                       __global const float *hl_spacing, int NA) {
    float fr[6];
    template_frame(l, w, fr);
    s->px = p.x;
    s->py = p.y;
    s->pz = p.z;
    s->fxx = fr[0]; s->fxy = fr[1]; s->fxz = fr[2];
    s->fyx = fr[3]; s->fyy = fr[4]; s->fyz = fr[5];
    const float mu = clamp(-dot(l, w), -1.0f, 1.0f);
    const float alpha = acos(mu);
    s->mu = mu;

    const int nc = n0 >> COARSE_LEVEL;
    const float t_enter = light_entry(coarse, nc, cmin, csize, p, l);
    s->t_enter = t_enter;

    /* Highlight layer levels for this query (uniform over the layer). */
    const float tv = t_enter * ((float)n0 / csize);
    s->h0 = highlight_level(hl_spacing[0] * tv, L);
    s->h1 = highlight_level(hl_spacing[1] * tv, L);
    s->h2 = highlight_level(hl_spacing[2] * tv, L);
    s->h3 = highlight_level(hl_spacing[3] * tv, L);

    const float fa = alpha * ((float)(NA - 1) / CLVOL_PI);
    s->a0 = min((int)fa, NA - 2);
    s->at = fa - (float)s->a0;
}

/* Chunk c (LANES template points) of query s: each point's level lvl, the level's resolution n
 * and offset off, whether it lies in the cube, and its clamped grid coordinates g. */
__attribute__((always_inline))
void gather_chunk_points(const gather_query *s, int c, float3 l, float3 cmin, float csize,
                         int n0, __global const float *tpl, __global const int *pinfo,
                         __global const int *loff, iL *lvl_out, iL *n_out, iL *off_out,
                         iL *inside_out, vL *gx_out, vL *gy_out, vL *gz_out) {
    const float3 cmax = cmin + (float3)(csize);
    const vL ux = vloadL(c, tpl), uy = vloadL(c, tpl + NPAD), uz = vloadL(c, tpl + 2 * NPAD);
    const iL info = vloadL(c, pinfo);
    const iL h0 = (iL)(s->h0), h1 = (iL)(s->h1), h2 = (iL)(s->h2), h3 = (iL)(s->h3);
    const iL hl = info == (iL)(-1) ? h0 : (info == (iL)(-2) ? h1 : (info == (iL)(-3) ? h2 : h3));
    const iL diffuse = info >= (iL)(0);
    const iL lvl = diffuse ? info : hl;
    const vL scale = select((vL)(s->t_enter), (vL)(csize), diffuse);
    const vL sx = s->px + scale * (ux * s->fxx + uy * s->fyx + uz * l.x);
    const vL sy = s->py + scale * (ux * s->fxy + uy * s->fyy + uz * l.y);
    const vL sz = s->pz + scale * (ux * s->fxz + uy * s->fyz + uz * l.z);
    const iL n = (iL)(n0) >> lvl;
    const vL vox = csize / convert_vL(n);
    const iL inside = (sx >= cmin.x) & (sx <= cmax.x) & (sy >= cmin.y) & (sy <= cmax.y)
                     & (sz >= cmin.z) & (sz <= cmax.z);
    const iL nm1 = n - (iL)(1);
    const vL hi = convert_vL(nm1);
    *gx_out = clamp((sx - cmin.x) / vox - 0.5f, (vL)(0.0f), hi);
    *gy_out = clamp((sy - cmin.y) / vox - 0.5f, (vL)(0.0f), hi);
    *gz_out = clamp((sz - cmin.z) / vox - 0.5f, (vL)(0.0f), hi);
    *off_out = gatheriL(loff, lvl);
    *lvl_out = lvl;
    *n_out = n;
    *inside_out = inside;
}

/* Render mode: the density feature log1p(tau) and the combined transmittance C of a chunk
 * from the baked (tau, C) grid (0 and c_out outside the cube). */
__attribute__((always_inline))
void gather_render_chunk(__global const float *baked, iL n, iL off, iL inside, vL gx,
                         vL gy, vL gz, float c_out, vL *dens_out, vL *t_out) {
    /* Corners (x0, y0, z0) <= n - 2, so x0 + 1, y0 + 1, z0 + 1 are in the level and every
     * row pair is one 16-byte load; at the top face the weight is 1 instead of grid.h's
     * clamped corner (the same value up to rounding). A 1-voxel level reads one row beyond
     * itself with weight 0: the next level's data, or the buffer's padding. */
    const iL top = max(n - (iL)(2), (iL)(0));
    const iL x0 = min(convert_iL(gx), top), y0 = min(convert_iL(gy), top);
    const iL z0 = min(convert_iL(gz), top);
    const vL wx = gx - convert_vL(x0), wy = gy - convert_vL(y0);
    const vL wz = gz - convert_vL(z0);
    const iL base = (iL)(2) * (off + (z0 * n + y0) * n + x0);
    const iL dy = (iL)(2) * n, dz = (iL)(2) * n * n;     /* row strides */
    vL t0, c0, t1, c1;
#ifdef GATHER_SHUFFLE
    int ib[LANES], iy[LANES], iz[LANES];
    vstoreL(base, 0, ib);
    vstoreL(dy, 0, iy);
    vstoreL(dz, 0, iz);
    LANE_ROWS(baked, 0) LANE_ROWS(baked, 1) LANE_ROWS(baked, 2) LANE_ROWS(baked, 3)
#if LANES >= 8
    LANE_ROWS(baked, 4) LANE_ROWS(baked, 5) LANE_ROWS(baked, 6) LANE_ROWS(baked, 7)
#endif
#if LANES == 16
    LANE_ROWS(baked, 8) LANE_ROWS(baked, 9) LANE_ROWS(baked, a) LANE_ROWS(baked, b)
    LANE_ROWS(baked, c) LANE_ROWS(baked, d) LANE_ROWS(baked, e) LANE_ROWS(baked, f)
#endif
#define ROW(E, R) TRANSPOSE4(E, t0, c0, t1, c1)
#else
#define ROW(E, R)                                                                          \
    t0 = gatherL(baked, R); c0 = gatherL(baked, R + (iL)(1));                           \
    t1 = gatherL(baked, R + (iL)(2)); c1 = gatherL(baked, R + (iL)(3));
#endif
    ROW(ra, base)
    const vL t00 = mix(t0, t1, wx), k00 = mix(c0, c1, wx);
    ROW(rb, base + dy)
    const vL t01 = mix(t0, t1, wx), k01 = mix(c0, c1, wx);
    ROW(rc, base + dz)
    const vL t10 = mix(t0, t1, wx), k10 = mix(c0, c1, wx);
    ROW(rd, base + dy + dz)
    const vL t11 = mix(t0, t1, wx), k11 = mix(c0, c1, wx);
#undef ROW
    const vL tau = mix(mix(t00, t01, wy), mix(t10, t11, wy), wz);
    const vL tc = mix(mix(k00, k01, wy), mix(k10, k11, wy), wz);
    *dens_out = log1p(select((vL)(0.0f), tau, inside));
    *t_out = select((vL)(c_out), tc, inside);
}

/* The phase feature of chunk c: the table ptab[NA][NPAD] read linearly in alpha. (The
 * centre point, j = 0, is replaced by log1p(phase_eval(mu, ...)) by the caller.) */
__attribute__((always_inline))
vL gather_phase_chunk(const gather_query *s, int c, __global const float *ptab) {
    __global const float *row0 = ptab + (size_t)s->a0 * NPAD;
    __global const float *row1 = row0 + NPAD;
    return mix(vloadL(c, row0), vloadL(c, row1), s->at);
}

#endif
