/* Template gather: the network's input features for N query points (seed III.B.2-5).
 *
 * Contract: clvol/layout.py (features [N][3][NP], levels [N][L][NP]); docs/templates.md.
 * Twin: reference/gather.py. Host wrapper: clvol/kernels/gather.py.
 *
 * For query q (point p, unit omega toward the camera) and template point j:
 *   frame     z = l (toward the light), x = normalize(omega - (omega.l) l), y = z x x; when
 *             |omega x l| < 1e-4, x comes from the world axis least aligned with l (DESIGN.md).
 *   position  s_j = p + scale_j (u.x x + u.y y + u.z z), u = tpl[j].xyz; scale_j = cube_size for
 *             diffuse points, t_enter for highlight points.
 *   t_enter   where the light enters the medium along p + t l: the far end of the last non-empty
 *             cell of the coarse level (COARSE_LEVEL, <= 32^3: a mip average of non-negative
 *             densities is > 0 iff its block holds density) met by the DDA of majorant.h; 0 if
 *             none. Highlight layer k reads level round(log2(hl_spacing[k] * t_enter)) (spacing in
 *             base voxels), clamped to [0, L-1]; diffuse points read the fixed level pinfo[j].
 *   density   log1p(tau), tau = rho_lvl(s_j) * density_scale * voxel_size(lvl): trilinear, clamped,
 *             0 outside the cube.
 *   T         train: levels[q][m][j] = T_m sampled at the voxel centres of level lvl and
 *             interpolated trilinearly to s_j (the same weights as the density), 1 outside the cube.
 *             render: the baked grid C_lvl = sum_m w_m T_m + b at level lvl's centres (gather_bake)
 *             read with those weights: equals sum_m w_m levels[m] + b up to rounding.
 *   phase     log1p of seed eq. 5: j = 0 (centre) evaluates f(dot(-l, omega)) exactly; other
 *             points read the per-frame table ptab[NA][NP] linearly in alpha = acos(dot(-l, omega)).
 *
 * Arguments (all float32 unless said; world units; offsets in elements):
 *   dens      pyramid levels concatenated (raw density), offsets loff[L]          (train)
 *   tlev      graded T levels, same layout                                         (train)
 *   baked     float2 per voxel (tau, C), same offsets x 2                          (render)
 *   loff      int[L]; L levels; n0 base resolution; cmin (float4), csize cube edge
 *   taufac    float[L]: density_scale * voxel size of level l
 *   tpl       float4[NP] template points (frame units); pinfo int[NP]: level >= 0 for diffuse,
 *             -(k+1) for highlight layer k; hl_spacing float[4]: spacing per unit t_enter (x n0/csize: voxels)
 *   ptab      float[NA][NP] log1p phase feature over alpha = linspace(0, pi, NA)
 *   points, omegas  float[N][3]; light (float4, unit); lobe_g, lobe_w (float4, phase.h)
 *   c_out     render: value of C outside the cube (sum w + b)
 *   out       features [N][3][NP]; levels [N][L][NP] (train); tenter [N]
 */
#include "grid.h"
#include "phase.h"
#include "majorant.h"

#ifndef NP
#define NP 266
#endif
#ifndef COARSE_LEVEL
#define COARSE_LEVEL 3
#endif

__attribute__((always_inline))
float2 lookup2(__global const float2 *d, int n, float3 g) {
    float x = clamp(g.x, 0.0f, (float)(n - 1));
    float y = clamp(g.y, 0.0f, (float)(n - 1));
    float z = clamp(g.z, 0.0f, (float)(n - 1));
    int x0 = (int)x, y0 = (int)y, z0 = (int)z;
    int x1 = min(x0 + 1, n - 1), y1 = min(y0 + 1, n - 1), z1 = min(z0 + 1, n - 1);
    float fx = x - (float)x0, fy = y - (float)y0, fz = z - (float)z0;
    size_t sy = (size_t)n, sz = (size_t)n * (size_t)n;
    size_t r00 = (size_t)z0 * sz + (size_t)y0 * sy, r01 = (size_t)z0 * sz + (size_t)y1 * sy;
    size_t r10 = (size_t)z1 * sz + (size_t)y0 * sy, r11 = (size_t)z1 * sz + (size_t)y1 * sy;
    float2 c00 = mix(d[r00 + x0], d[r00 + x1], fx);
    float2 c01 = mix(d[r01 + x0], d[r01 + x1], fx);
    float2 c10 = mix(d[r10 + x0], d[r10 + x1], fx);
    float2 c11 = mix(d[r11 + x0], d[r11 + x1], fx);
    return mix(mix(c00, c01, fy), mix(c10, c11, fy), fz);
}

/* The template frame of DESIGN.md (twin: clvol.templates.template_frame). */
__attribute__((always_inline))
void template_frame(float3 l, float3 w, float3 *x, float3 *y) {
    float3 perp = w - dot(w, l) * l;
    if (length(cross(w, l)) < 1e-4f) {
        float3 a = fabs(l);
        float3 e = (a.x <= a.y && a.x <= a.z) ? (float3)(1.0f, 0.0f, 0.0f)
                 : (a.y <= a.z ? (float3)(0.0f, 1.0f, 0.0f) : (float3)(0.0f, 0.0f, 1.0f));
        perp = e - dot(e, l) * l;
    }
    *x = normalize(perp);
    *y = cross(l, *x);
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
                     __global const float2 *baked, __global const int *loff, const int L,
                     const int n0, const float4 cmin4, const float csize,
                     __global const float *taufac, __global const float4 *tpl,
                     __global const int *pinfo, __global const float *hl_spacing,
                     __global const float *ptab, const int NA,
                     __global const float *points, __global const float *omegas,
                     const float4 light4, const float4 lobe_g, const float4 lobe_w,
                     const float c_out, const int N, __global float *out,
                     __global float *levels, __global float *tenter) {
    int q = get_global_id(0);
    if (q >= N) return;
    float3 cmin = cmin4.xyz, cmax = cmin4.xyz + (float3)(csize);
    float3 l = light4.xyz;
    float3 p = vload3(q, points), w = vload3(q, omegas);
    float3 fx, fy;
    template_frame(l, w, &fx, &fy);
    float mu = clamp(-dot(l, w), -1.0f, 1.0f);
    float alpha = acos(mu);

    const int nc = n0 >> COARSE_LEVEL;
    float t_enter = light_entry(dens + loff[COARSE_LEVEL], nc, cmin, csize, p, l);
    tenter[q] = t_enter;

    float fa = alpha * ((float)(NA - 1) / CLVOL_PI);
    int a0 = min((int)fa, NA - 2);
    float at = fa - (float)a0;
    __global const float *row0 = ptab + (size_t)a0 * NP;
    __global const float *row1 = row0 + NP;

    __global float *o = out + (size_t)q * 3 * NP;
    float inv_vox0 = (float)n0 / csize;

    for (int j = 0; j < NP; ++j) {
        float4 u = tpl[j];
        int info = pinfo[j];
        float scale;
        int lvl;
        if (info >= 0) {
            scale = csize;
            lvl = info;
        } else {
            scale = t_enter;
            lvl = highlight_level(hl_spacing[-info - 1] * t_enter * inv_vox0, L);
        }
        float3 s = p + scale * (u.x * fx + u.y * fy + u.z * l);
        int n = n0 >> lvl;
        float vox = csize / (float)n;
        float3 g = (s - cmin) / vox - 0.5f;
        int inside = all(s >= cmin) && all(s <= cmax);
        float tau, tcomb;
#ifdef GATHER_RENDER
        float2 v = lookup2(baked + loff[lvl], n, g);
        tau = inside ? v.x : 0.0f;
        tcomb = inside ? v.y : c_out;
#else
        tau = inside ? grid_lookup(dens + loff[lvl], n, n, n, g) * taufac[lvl] : 0.0f;
        tcomb = 0.0f;
        /* every graded level, sampled at level lvl's centres around s (trilinear weights) */
        float gx = clamp(g.x, 0.0f, (float)(n - 1)), gy = clamp(g.y, 0.0f, (float)(n - 1));
        float gz = clamp(g.z, 0.0f, (float)(n - 1));
        int x0 = (int)gx, y0 = (int)gy, z0 = (int)gz;
        int x1 = min(x0 + 1, n - 1), y1 = min(y0 + 1, n - 1), z1 = min(z0 + 1, n - 1);
        float wx = gx - (float)x0, wy = gy - (float)y0, wz = gz - (float)z0;
        __global float *lv = levels + (size_t)q * L * NP + j;
        for (int m = 0; m < L; ++m) {
            float val = 1.0f;
            if (inside) {
                int nm = n0 >> m;
                /* level-lvl centre i -> level-m voxel coordinate (i + 0.5) nm / n - 0.5 (exact ratio) */
                float r = (float)nm / (float)n;
                float cx0 = ((float)x0 + 0.5f) * r - 0.5f, cx1 = ((float)x1 + 0.5f) * r - 0.5f;
                float cy0 = ((float)y0 + 0.5f) * r - 0.5f, cy1 = ((float)y1 + 0.5f) * r - 0.5f;
                float cz0 = ((float)z0 + 0.5f) * r - 0.5f, cz1 = ((float)z1 + 0.5f) * r - 0.5f;
                __global const float *tm = tlev + loff[m];
                float c000 = grid_lookup(tm, nm, nm, nm, (float3)(cx0, cy0, cz0));
                float c100 = grid_lookup(tm, nm, nm, nm, (float3)(cx1, cy0, cz0));
                float c010 = grid_lookup(tm, nm, nm, nm, (float3)(cx0, cy1, cz0));
                float c110 = grid_lookup(tm, nm, nm, nm, (float3)(cx1, cy1, cz0));
                float c001 = grid_lookup(tm, nm, nm, nm, (float3)(cx0, cy0, cz1));
                float c101 = grid_lookup(tm, nm, nm, nm, (float3)(cx1, cy0, cz1));
                float c011 = grid_lookup(tm, nm, nm, nm, (float3)(cx0, cy1, cz1));
                float c111 = grid_lookup(tm, nm, nm, nm, (float3)(cx1, cy1, cz1));
                val = mix(mix(mix(c000, c100, wx), mix(c010, c110, wx), wy),
                          mix(mix(c001, c101, wx), mix(c011, c111, wx), wy), wz);
            }
            lv[(size_t)m * NP] = val;
        }
#endif
        o[j] = log1p(tau);
        o[NP + j] = tcomb;
        o[2 * NP + j] = mix(row0[j], row1[j], at);
    }
    o[2 * NP] = log1p(phase_eval(mu, lobe_g, lobe_w));
}

/* Render-time bake (once per light or weight change): for every voxel v of every level l,
 * baked[off_l + v] = (rho_l[v] * taufac[l], sum_m w_m T_m(centre of v) + bias), T_m trilinear. */
__kernel void gather_bake(__global const float *dens, __global const float *tlev,
                          __global const int *loff, const int L, const int n0,
                          __global const float *taufac, __global const float *weights,
                          const float bias, const int total, __global float2 *baked) {
    int i = get_global_id(0);
    if (i >= total) return;
    int lvl = 0;
    while (lvl + 1 < L && i >= loff[lvl + 1]) ++lvl;
    int n = n0 >> lvl;
    int v = i - loff[lvl];
    int x = v % n, y = (v / n) % n, z = v / (n * n);
    float c = bias;
    for (int m = 0; m < L; ++m) {
        int nm = n0 >> m;
        float r = (float)nm / (float)n;
        float3 g = ((float3)((float)x, (float)y, (float)z) + 0.5f) * r - 0.5f;
        c += weights[m] * grid_lookup(tlev + loff[m], nm, nm, nm, g);
    }
    baked[i] = (float2)(dens[i] * taufac[lvl], c);
}
