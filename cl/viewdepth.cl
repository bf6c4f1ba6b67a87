/* Query depths of the view-space F_ms source: per block of VIEW_BLOCK x VIEW_BLOCK pixels,
 * VIEW_K distances along the camera rays at the quantiles (i + 1/2)/K (or (i + z)/K, see
 * jitter) of the block's
 * in-scattering weight T_cam sigma_t. Twin: reference/viewdepth.py (the algorithm in full).
 *
 * One work-item per block; its VIEW_RAYS^2 sample rays advance together over segments of
 * length `step` from the smallest box entry. Two marches: the first finds the block's total
 * weight W = C(end), the second the segments where C(t) = mean_r (1 - e^-tau_r(t)) crosses
 * each level (i + 1/2)/K W; C is linear inside a segment. Both marches take the same
 * segments and the same stop (every ray past its exit or below T_cam = stop), so C is the
 * same function in both.
 *
 * Arguments (float4 holds a 3-vector in xyz; world units):
 *   density  float [nz][ny][nx] over bmin..bmax; sigma_t = density * density_scale
 *   origin, forward, right, up, tan_half, width, height   pinhole camera (grid.h camera_ray)
 *   step     segment length; stop: transmittance below which a ray sees nothing more
 *   depths   float [by][bx][VIEW_K] out: distances along the rays, increasing; -1 for an
 *            empty block (W < VIEW_EMPTY_WEIGHT)
 *   weight   float [by][bx] out: W (0 for an empty block)
 *   jitter   (with VIEW_JITTER only) float4 [by][bx]: x, y in [0, 1) place sample ray (a, b)
 *            at (a + x, b + y) block/VIEW_RAYS within its block, z in [0, 1) moves the levels
 *            to (i + z)/K. Without VIEW_JITTER all three are 1/2 (the deterministic source);
 *            with uniform random values and VIEW_K = 1 the depth is a free-flight sample of
 *            the block's in-scattering weight (the stochastic source, docs/raymarch.md).
 *   VIEW_FREE_FLIGHT (with VIEW_JITTER, K = 1, one ray): one pass instead; the depth where
 *            the optical depth reaches -log(1 - z), -1 (weight 0) when the ray leaves the
 *            box or reaches `stop` first; weight 1 for a collision. See the block below.
 * Global size: bx * by work-items (guarded), bx = ceil(width / VIEW_BLOCK).
 */
#include "grid.h"
#include "constants.h"   /* VIEW_MAX_K, VIEW_MAX_RAYS */

/* The host passes them (clvol/kernels/viewdepth.py, from the source's options). */
#ifndef VIEW_K
#error "viewdepth.cl needs -D VIEW_K (clvol/kernels/viewdepth.py)"
#endif
#ifndef VIEW_BLOCK
#error "viewdepth.cl needs -D VIEW_BLOCK (clvol/kernels/viewdepth.py)"
#endif
#ifndef VIEW_RAYS
#error "viewdepth.cl needs -D VIEW_RAYS (clvol/kernels/viewdepth.py)"
#endif
#define VIEW_R2 (VIEW_RAYS * VIEW_RAYS)
#define VIEW_EMPTY_WEIGHT 1e-5f
#define VIEW_MIN_LEVEL 1e-6f

#if VIEW_K < 1 || VIEW_K > VIEW_MAX_K || VIEW_RAYS < 1 || VIEW_RAYS > VIEW_MAX_RAYS
#error "VIEW_K must be 1..VIEW_MAX_K and VIEW_RAYS 1..VIEW_MAX_RAYS"
#endif
#if defined(VIEW_FREE_FLIGHT) && (VIEW_K != 1 || VIEW_RAYS != 1 || !defined(VIEW_JITTER))
#error "VIEW_FREE_FLIGHT draws one depth on one jittered ray: VIEW_K 1, VIEW_RAYS 1, VIEW_JITTER"
#endif

/* Advance every sample ray over segment [ta, ta + step]; returns C at its end and whether
 * some ray still sees medium beyond it. */
/* Segments along one ray: at most VIEW_MAX_STEPS (float32 cannot place more segments of one
 * step on a ray: t / step >= 2^22 leaves steps below two rounding steps of t), 0 for an empty
 * or NaN span. A plain (int) cast of a larger or NaN float is undefined. */
#ifndef VIEW_MAX_STEPS
#define VIEW_MAX_STEPS 4194304
#endif
__attribute__((always_inline))
int segments(float span, float step) {
    const float n = ceil(span / step);
    return n >= (float)VIEW_MAX_STEPS ? VIEW_MAX_STEPS : (n > 0.0f ? (int)n : 0);
}

__attribute__((always_inline))
float advance(__global const float *density, int nx, int ny, int nz, float3 bmin, float3 cell,
              float density_scale, float3 o, const float3 *d, const float *t0, const float *t1,
              float *tau, float ta, float step, float stop, int *more) {
    const float tb = ta + step;
    float c = 0.0f;
    int go = 0;
    for (int r = 0; r < VIEW_R2; ++r) {
        const float lo = fmax(ta, t0[r]), hi = fmin(tb, t1[r]);
        if (hi > lo) {
            const float3 p = o + (0.5f * (lo + hi)) * d[r];
            tau[r] += density_scale * grid_lookup(density, nx, ny, nz, (p - bmin) / cell - 0.5f)
                      * (hi - lo);
        }
        const float T = exp(-tau[r]);
        /* 1 - e^-tau without cancellation for thin media */
        c += tau[r] < 0.1f ? -expm1(-tau[r]) : 1.0f - T;
        go |= (t0[r] <= t1[r]) && (tb < t1[r]) && (T >= stop);
    }
    *more = go;
    return c / (float)VIEW_R2;
}

/* VIEW_FREE_FLIGHT: one unconditioned free flight along d from t_in to t_out: march until
 * the optical depth reaches -log(1 - z), in one pass (it usually ends ~1 optical depth in).
 * Returns the depth, or -1 when the ray leaves the box, or its transmittance falls below
 * `stop`, first. Given a collision the depth is distributed as T_cam sigma_t / (1 - T(end)),
 * as the two-pass quantile with a random level, and tau is exactly linear in a segment. */
__attribute__((always_inline))
float free_flight_depth(__global const float *density, int nx, int ny, int nz, float3 bmin,
                        float3 cell, float density_scale, float3 o, float3 d, float t_in,
                        float t_out, float z, float step, float stop) {
    const float target = -log1p(-z);     /* exact for small z, where 1 - z rounds; z = 1: never met */
    const float tau_stop = stop > 0.0f ? -log(stop) : INFINITY;
    float depth = -1.0f, tau_acc = 0.0f;
    const int n = t_in <= t_out ? segments(t_out - t_in, step) : 0;
    for (int s = 0; s < n && depth < 0.0f && tau_acc <= tau_stop; ++s) {
        const float ta = t_in + (float)s * step, tb = fmin(ta + step, t_out);
        const float3 p = o + (0.5f * (ta + tb)) * d;
        const float dtau = density_scale
            * grid_lookup(density, nx, ny, nz, (p - bmin) / cell - 0.5f) * (tb - ta);
        /* target > tau_acc, so reaching it here means dtau > 0: no division by 0 */
        if (tau_acc + dtau >= target)
            depth = ta + (tb - ta) * (target - tau_acc) / dtau;
        tau_acc += dtau;
    }
    return depth;
}

__kernel void view_depths(__global const float *density, const int nx, const int ny,
                          const int nz, const float4 bmin, const float4 bmax,
                          const float density_scale,
                          const float4 origin, const float4 forward, const float4 right,
                          const float4 up, const float tan_half, const int width,
                          const int height, const float step, const float stop,
                          __global float *depths, __global float *weight
#ifdef VIEW_JITTER
                          , __global const float4 *jitter
#endif
                          )
{
    const int bx = (width + VIEW_BLOCK - 1) / VIEW_BLOCK, by = (height + VIEW_BLOCK - 1) / VIEW_BLOCK;
    const int b = get_global_id(0);
    if (b >= bx * by) return;
    const int j = b / bx, i = b - j * bx;
    const float3 o = origin.xyz;
#ifdef VIEW_JITTER
    /* z > 0 keeps every level above C = 0, so the crossing segment has c > c_prev */
    const float4 jit = (float4)(jitter[b].xy, clamp(jitter[b].z, VIEW_MIN_LEVEL, 1.0f), 0.0f);
#else
    const float4 jit = (float4)(0.5f);
#endif
    const float3 cell = (bmax.xyz - bmin.xyz) / (float3)((float)nx, (float)ny, (float)nz);
    float3 d[VIEW_R2];
    float t0[VIEW_R2], t1[VIEW_R2], tau[VIEW_R2];
    float t_lo = INFINITY, t_hi = -INFINITY;
    for (int r = 0; r < VIEW_R2; ++r) {
        const int a = r % VIEW_RAYS, c = r / VIEW_RAYS;
        const float x = (float)(i * VIEW_BLOCK) + ((float)a + jit.x) * (float)VIEW_BLOCK / (float)VIEW_RAYS;
        const float y = (float)(j * VIEW_BLOCK) + ((float)c + jit.y) * (float)VIEW_BLOCK / (float)VIEW_RAYS;
        d[r] = camera_ray(forward.xyz, right.xyz, up.xyz, tan_half, width, height, x, y);
        float lo, hi;
        if (box_intersect(o, d[r], bmin.xyz, bmax.xyz, 0.0f, &lo, &hi)) {
            t0[r] = lo;
            t1[r] = hi;
            t_lo = fmin(t_lo, lo);
            t_hi = fmax(t_hi, hi);
        } else {
            t0[r] = INFINITY;
            t1[r] = -INFINITY;
        }
    }
    __global float *out = depths + (size_t)b * VIEW_K;
#ifdef VIEW_FREE_FLIGHT
    /* One unconditioned free flight (free_flight_depth above). */
    out[0] = free_flight_depth(density, nx, ny, nz, bmin.xyz, cell, density_scale, o, d[0],
                               t0[0], t1[0], jit.z, step, stop);
    weight[b] = out[0] >= 0.0f ? 1.0f : 0.0f;
#else
    float w = 0.0f;
    int n_steps = 0;
    if (t_lo <= t_hi) {
        n_steps = segments(t_hi - t_lo, step);
        for (int r = 0; r < VIEW_R2; ++r) tau[r] = 0.0f;
        int more = 1;
        for (int s = 0; s < n_steps && more; ++s)
            w = advance(density, nx, ny, nz, bmin.xyz, cell, density_scale, o, d, t0, t1, tau,
                        t_lo + (float)s * step, step, stop, &more);
    }
    if (!(w >= VIEW_EMPTY_WEIGHT)) {
        for (int k = 0; k < VIEW_K; ++k) out[k] = -1.0f;
        weight[b] = 0.0f;
        return;
    }
    weight[b] = w;
    for (int r = 0; r < VIEW_R2; ++r) tau[r] = 0.0f;
    float c_prev = 0.0f;
    int k = 0, more = 1;
    for (int s = 0; s < n_steps && more && k < VIEW_K; ++s) {
        const float ta = t_lo + (float)s * step;
        const float c = advance(density, nx, ny, nz, bmin.xyz, cell, density_scale, o, d, t0, t1,
                                tau, ta, step, stop, &more);
        /* every level this segment reaches; c > c_prev whenever a level lies in (c_prev, c] */
        for (; k < VIEW_K; ++k) {
            const float u = ((float)k + jit.z) / (float)VIEW_K * w;
            if (c < u) break;
            out[k] = ta + step * (u - c_prev) / (c - c_prev);
        }
        c_prev = c;
    }
    /* Rounding may leave the top level just above the last C: put it at the last segment. */
    for (; k < VIEW_K; ++k) out[k] = t_lo + (float)n_steps * step;
#endif
}
