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

/* 1-D interpolation weights of tau_prev at lateral position q in [-0.5, n - 0.5]. */
__attribute__((always_inline))
void prev_weights(float q, int n, int *i0, int *i1, float *w0, float *w1) {
    if (q < 0.0f) {                      /* between the face (tau 0) and centre 0 */
        *i0 = 0; *i1 = 0; *w0 = fmax(2.0f * (q + 0.5f), 0.0f); *w1 = 0.0f;
    } else if (q > (float)(n - 1)) {     /* between centre n-1 and the face */
        *i0 = n - 1; *i1 = n - 1; *w0 = fmax(2.0f * ((float)n - 0.5f - q), 0.0f); *w1 = 0.0f;
    } else {
        int k = (int)q;                  /* q >= 0: the cast is a floor */
        float f = q - (float)k;
        *i0 = k; *i1 = min(k + 1, n - 1); *w0 = 1.0f - f; *w1 = f;
    }
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

/* tau of voxel (u, v) in slice k: the sweep step in its general (scalar) form. */
__attribute__((always_inline))
float sweep_voxel(__global const float *d, int n, int a, int sa, int k, int first, float su,
                  float sv, float inv_la, float scale, __global const float *tau_prev,
                  int u, int v) {
    const float seg = first ? 0.5f : 1.0f;   /* distance along a to the previous plane */
    const float du = su * seg, dv = sv * seg, da = (float)sa * seg;
    const float fu = (float)u, fv = (float)v, lo = -0.5f, hi = (float)n - 0.5f;
    float c = 1.0f;                          /* fraction of the segment inside the cube */
    if (fu + du < lo) c = fmin(c, (lo - fu) / du);
    if (fu + du > hi) c = fmin(c, (hi - fu) / du);
    if (fv + dv < lo) c = fmin(c, (lo - fv) / dv);
    if (fv + dv > hi) c = fmin(c, (hi - fv) / dv);
    const float r0 = d[elem_uva(n, a, u, v, k)];             /* a voxel centre: no lerp */
    const float rm = lookup_uva(d, n, a, fu + 0.5f * c * du, fv + 0.5f * c * dv,
                                (float)k + 0.5f * c * da);
    const float r1 = lookup_uva(d, n, a, fu + c * du, fv + c * dv, (float)k + c * da);
    float tau = scale * (seg * inv_la * c) * (r0 + 4.0f * rm + r1) * (1.0f / 6.0f);
    if (!first && c >= 1.0f) {
        int u0, u1, v0, v1;
        float wu0, wu1, wv0, wv1;
        prev_weights(fu + du, n, &u0, &u1, &wu0, &wu1);
        prev_weights(fv + dv, n, &v0, &v1, &wv0, &wv1);
        tau += wv0 * (wu0 * tau_prev[v0 * n + u0] + wu1 * tau_prev[v0 * n + u1])
             + wv1 * (wu0 * tau_prev[v1 * n + u0] + wu1 * tau_prev[v1 * n + u1]);
    }
    return tau;
}

__kernel void transmittance_sweep_slice(__global const float *pyr, const int off, const int n,
                                        const int a, const int sa, const int k, const int first,
                                        const float su, const float sv, const float inv_la,
                                        const float scale, __global const float *tau_prev,
                                        __global float *tau_cur, const int out_depth,
                                        __global float *out, const int out_off) {
    const int i = get_global_id(0);
    if (i >= n * n) return;
    const int u = i % n, v = i / n;
    const float tau = sweep_voxel(pyr + off, n, a, sa, k, first, su, sv, inv_la, scale,
                                  tau_prev, u, v);
    tau_cur[i] = tau;
    out[(size_t)out_off + elem_uva(n, a, u, v, k)] = out_depth ? tau : exp(-tau);
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
