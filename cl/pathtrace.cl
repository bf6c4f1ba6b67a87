/* Reference volumetric path tracer: images and point queries (ground truth, training labels).
 *
 * Estimator (DESIGN.md; seed: the ground truth its network learns, "F(p, omega)")
 *   pixel = T(cam, exit) L_env + integral T(cam, x) sigma_s(x) [E F(x, omega) + env part] dt
 * sampled as a random walk:
 *   - free flight by delta tracking against the majorant grid (majorant.h; a 1-cell grid is
 *     the global majorant): tentative collisions at rate sigma_maj, real with probability
 *     sigma_t / sigma_maj; grey sigma_t, chromatic albedo carried as an RGB throughput
 *     (beta *= albedo at every real collision, no absorption sampling);
 *   - at every vertex k (k = 1 is the first scattering vertex; order = k): next-event
 *     estimation toward the sun, beta * E * f(dot(l, w)) * T(x -> sun), T by ratio tracking
 *     with roulette when T < PT_T_RR; f takes the cosine between propagation directions:
 *     light travels along -l and leaves along -w, so cos = dot(-l, -w) = dot(l, w);
 *   - new direction by exact phase sampling (phase.h, weight 1);
 *   - a path leaving the box collects beta * L_env as order k (order 0: the background
 *     seen through the medium, attenuated by the true transmittance in expectation).
 *   - Russian roulette from vertex PT_RR_START on: survive with q = min(1, max_c beta_c),
 *     beta /= q (unbiased; with albedo ~1, q ~ albedo, so long paths of clouds survive).
 *   - max_order > 0 stops after the NEE of vertex max_order (0 = unlimited); paths longer
 *     than PT_MAX_VERTICES are cut and counted (reported, never silent).
 * Point queries start at p as vertex 1 with beta = 1 and w = -omega (omega toward the
 * camera): order 1 gives F_1 = f(dot(-l, omega)) T(p -> sun), orders >= 2 give F_>=2.
 *
 * Random numbers (rng.h, Philox): one sequential stream per path, key = seed, counter =
 * (stream = pixel or query index, sample index, block); uniforms are used in order, 4 per
 * block. Draw order: [render: jitter x, y] then per flight step: u_tau and, at a tentative
 * collision inside the box, u_real; per NEE ratio-tracking step: u_tau (+ u_roulette when
 * T < PT_T_RR); per vertex before sampling a direction: u_rr (only if k >= PT_RR_START);
 * phase sample: 3 uniforms (lobe, polar, azimuth). reference/pathtrace.py draws the same.
 *
 * Defines: PHASE_LOBES / PHASE_ISOTROPIC (phase.h); PT_GREY (scalar throughput);
 * PT_ENV (a constant environment); PT_NO_SUN (no sun); PT_SINGLE_ONLY (stop after vertex
 * 1); PT_RR_START, PT_MAX_VERTICES; PT_TEST_BIAS (tests only: scales sun NEE by its value).
 *
 * Kernels (grid and majorant arguments first, then light, then the per-kernel ones):
 *   density   float [nz][ny][nx]    raw density; sigma_t = density * scale (1/length)
 *   maj       float [mz][my][mx]    majorant grid (cl/majorant.cl), raw density
 *   bmin,bmax float4                the grid's box (world); bsize float4 = coarse cell size
 *   albedo    float4                RGB single-scattering albedo
 *   lobe_g, lobe_w float4           phase lobes (phase.h)
 *   light_dir float4                unit vector toward the sun
 *   sun       float4                sun irradiance E (RGB, power / area perpendicular to l)
 *   env       float4                environment radiance (RGB), used with PT_ENV
 * pt_render: cam_o, cam_f, cam_r, cam_u float4, tan_half, width, height; seed ulong;
 *   sample0 uint; spl int (samples per launch; work-item g: pixel g % npix, sample
 *   sample0 + g / npix); max_order int; out float [spl*npix][PT_OUT]:
 *   (background rgb, order-1 rgb, orders>=2 rgb, vertices, tracking steps, truncated, 0, 0)
 * pt_query: points, omegas float [nq][3]; nq; seed; sample0; ppl (paths per launch,
 *   work-item g: query g % nq, path sample0 + g / nq); max_order; out as pt_render with
 *   background 0 (sun irradiance 1 and no environment are the caller's arguments).
 */
#include "rng.h"
#include "grid.h"
#include "phase.h"
#include "majorant.h"

#ifndef PT_RR_START
#define PT_RR_START 8
#endif
#ifndef PT_MAX_VERTICES
#define PT_MAX_VERTICES 100000
#endif
/* Ratio-tracking roulette threshold: below it, T survives with probability T / PT_T_RR. */
#define PT_T_RR 0.1f
#define PT_OUT 12

/* Colours are structs of three floats, and every value carried around a loop is a scalar:
 * Oclgrind's uninitialised-value checker (run in CI) crashes on loop-carried float3 /
 * float4 values (LLVM keeps a float3 in a 4-lane register with an undefined lane). */
typedef struct {
    float r, g, b;
} pt_rgb;

__attribute__((always_inline))
pt_rgb pt_rgb_of(float4 v) {
    pt_rgb c;
    c.r = v.x; c.g = v.y; c.b = v.z;
    return c;
}

/* *acc += a * s */
__attribute__((always_inline))
void pt_rgb_add(pt_rgb *acc, pt_rgb a, float s) {
    acc->r += a.r * s; acc->g += a.g * s; acc->b += a.b * s;
}

/* Throughput and albedo: one float when the albedo is grey (PT_GREY), else RGB. */
#ifdef PT_GREY
typedef float spec_t;
#define SPEC_OF(v4) ((v4).x)
#define SPEC_ONE 1.0f
#define SPEC_MAX(b) (b)
#define SPEC_MUL(b, a) ((b) * (a))
#define SPEC_DIV(b, q) ((b) / (q))
#define SPEC_TINT(c, b) pt_tint1((c), (b))
__attribute__((always_inline)) pt_rgb pt_tint1(pt_rgb c, float b) {
    c.r *= b; c.g *= b; c.b *= b;
    return c;
}
#else
typedef pt_rgb spec_t;
#define SPEC_OF(v4) pt_rgb_of(v4)
#define SPEC_ONE pt_rgb_of((float4)(1.0f))
#define SPEC_MAX(v) fmax(fmax((v).r, (v).g), (v).b)
#define SPEC_MUL(b, a) pt_tint3((b), (a))
#define SPEC_DIV(b, q) pt_div3((b), (q))
#define SPEC_TINT(c, b) pt_tint3((c), (b))
__attribute__((always_inline)) pt_rgb pt_tint3(pt_rgb c, pt_rgb b) {
    c.r *= b.r; c.g *= b.g; c.b *= b.b;
    return c;
}
__attribute__((always_inline)) pt_rgb pt_div3(pt_rgb c, float q) {
    c.r /= q; c.g /= q; c.b /= q;
    return c;
}
#endif

/* ------------------------------------------------------------------ random stream */

/* Scalar members: Oclgrind's uninitialised-value checker mis-handles vector members
 * of private structs updated in parts. */
typedef struct {
    ulong seed, stream;
    uint sample, block;
    float b0, b1, b2, b3;
    int used;
} pt_rng;

__attribute__((always_inline))
void pt_rng_init(pt_rng *r, ulong seed, ulong stream, uint sample) {
    r->seed = seed;
    r->stream = stream;
    r->sample = sample;
    r->block = 0;
    r->b0 = r->b1 = r->b2 = r->b3 = 0.0f;
    r->used = 4;
}

__attribute__((always_inline))
float pt_next(pt_rng *r) {
    if (r->used == 4) {
        float4 u = rng_uniform4(r->seed, r->stream, r->sample, r->block);
        r->b0 = u.x; r->b1 = u.y; r->b2 = u.z; r->b3 = u.w;
        r->block += 1;
        r->used = 0;
    }
    int k = r->used++;
    return k == 0 ? r->b0 : k == 1 ? r->b1 : k == 2 ? r->b2 : r->b3;
}

/* ------------------------------------------------------------------ medium */

typedef struct {
    __global const float *density;
    __global const float *maj;
    int nx, ny, nz, mx, my, mz;
    float3 bmin, bmax, bsize;
    float3 inv_cell;   /* n / (bmax - bmin): voxels per unit length */
    float scale;
} pt_medium;

__attribute__((always_inline))
float pt_sigma(const pt_medium *m, float3 p) {
    /* grid_density of grid.h with the cell size inverted once per launch, not per lookup. */
    if (any(p < m->bmin) || any(p > m->bmax)) return 0.0f;
    return grid_lookup(m->density, m->nx, m->ny, m->nz, (p - m->bmin) * m->inv_cell - 0.5f)
           * m->scale;
}

/* Exponential optical depth from a uniform in [0, 1): 1 - u is in (0, 1], no log(0). */
__attribute__((always_inline))
float pt_tau(pt_rng *r) {
    return -log(1.0f - pt_next(r));
}

/* Delta tracking from x along unit w. Returns 1 with *t_hit the distance to a real
 * collision, 0 if the ray leaves the box first. (A distance, not a float3 out-pointer:
 * see the note on colours above.) */
__attribute__((always_inline))
int pt_free_flight(const pt_medium *m, float3 x, float3 w, pt_rng *r, float *t_hit,
                   uint *steps) {
    maj_dda s;
    if (!maj_dda_init(&s, x, w, m->bmin, m->bmax, m->bsize, (int3)(m->mx, m->my, m->mz),
                      0.0f, INFINITY))
        return 0;
    for (;;) {
        float tau = pt_tau(r), t, sm;
        if (!maj_dda_track(&s, m->maj, m->scale, &tau, &t, &sm)) return 0;
        *steps += 1;
        /* Real with probability sigma / sigma_maj (u * sm < sigma: no division). */
        if (pt_next(r) * sm < pt_sigma(m, x + t * w)) {
            *t_hit = t;
            return 1;
        }
    }
}

/* Ratio-tracking transmittance from x along unit w to the box exit. */
__attribute__((always_inline))
float pt_transmittance(const pt_medium *m, float3 x, float3 w, pt_rng *r, uint *steps) {
    maj_dda s;
    if (!maj_dda_init(&s, x, w, m->bmin, m->bmax, m->bsize, (int3)(m->mx, m->my, m->mz),
                      0.0f, INFINITY))
        return 1.0f;
    float T = 1.0f;
    for (;;) {
        float tau = pt_tau(r), t, sm;
        if (!maj_dda_track(&s, m->maj, m->scale, &tau, &t, &sm)) return T;
        *steps += 1;
        /* sm > 0 at a tentative collision; rounding can put sigma a hair above sm. */
        T *= fmax(0.0f, 1.0f - pt_sigma(m, x + t * w) / sm);
        if (T < PT_T_RR) {
            if (pt_next(r) * PT_T_RR >= T) return 0.0f;
            T = PT_T_RR;
        }
    }
}

/* ------------------------------------------------------------------ random walk */

typedef struct {
    float3 dir;       /* toward the sun */
    pt_rgb sun;       /* irradiance */
    pt_rgb env;       /* environment radiance */
    spec_t albedo;
    float4 lobe_g, lobe_w;
} pt_light;

/* Add c to the order-1 sum (k == 1) or to the higher orders. */
__attribute__((always_inline))
void pt_add_order(int k, pt_rgb c, pt_rgb *l1, pt_rgb *lms) {
    if (k == 1) pt_rgb_add(l1, c, 1.0f); else pt_rgb_add(lms, c, 1.0f);
}

/* Continue a path at vertex k (position x, arrival propagation direction w, throughput
 * beta including the albedo of this vertex). Adds order-1 light to *l1 and higher orders
 * to *lms. Position and direction cross iterations as scalars (see pt_rgb). */
__attribute__((always_inline))
void pt_walk(const pt_medium *m, const pt_light *L, float3 x_in, float3 w_in, spec_t beta,
             int k, int max_order, pt_rng *r, pt_rgb *l1, pt_rgb *lms, uint *vertices,
             uint *steps, uint *truncated) {
    float x0 = x_in.x, x1 = x_in.y, x2 = x_in.z;
    float w0 = w_in.x, w1 = w_in.y, w2 = w_in.z;
    for (;;) {
        float3 x = (float3)(x0, x1, x2), w = (float3)(w0, w1, w2);
        if (SPEC_MAX(beta) <= 0.0f) return;  /* albedo 0: nothing can arrive any more */
        *vertices += 1;
#ifndef PT_NO_SUN
        /* Also tested at run time, so the general build of a sunless scene draws the same
         * random numbers as the PT_NO_SUN build. (fmax, not ||: LLVM turns a float || into
         * a 'freeze' that Oclgrind cannot run.) */
        if (fmax(fmax(L->sun.r, L->sun.g), L->sun.b) > 0.0f) {
            float f = phase_eval(dot(L->dir, w), L->lobe_g, L->lobe_w);
            float T = pt_transmittance(m, x, L->dir, r, steps);
            float s = f * T;
#ifdef PT_TEST_BIAS
            s *= PT_TEST_BIAS;
#endif
            pt_rgb c = SPEC_TINT(L->sun, beta);
            c.r *= s; c.g *= s; c.b *= s;
            pt_add_order(k, c, l1, lms);
        }
#endif
#ifdef PT_SINGLE_ONLY
        return;
#else
        if (k == max_order) return;
        if (k >= PT_MAX_VERTICES) {
            *truncated = 1;
            return;
        }
        if (k >= PT_RR_START) {
            float q = fmin(1.0f, SPEC_MAX(beta));
            if (pt_next(r) >= q) return;
            beta = SPEC_DIV(beta, q);
        }
        float u0 = pt_next(r), u1 = pt_next(r), u2 = pt_next(r);  /* in this order */
        w = phase_sample(w, L->lobe_g, L->lobe_w, (float3)(u0, u1, u2));
        float t;
        if (!pt_free_flight(m, x, w, r, &t, steps)) {
#ifdef PT_ENV
            pt_add_order(k, SPEC_TINT(L->env, beta), l1, lms);
#endif
            return;
        }
        x = x + t * w;
        x0 = x.x; x1 = x.y; x2 = x.z;
        w0 = w.x; w1 = w.y; w2 = w.z;
        beta = SPEC_MUL(beta, L->albedo);
        k += 1;
#endif
    }
}

__attribute__((always_inline))
void pt_store(__global float *out, size_t g, pt_rgb bg, pt_rgb a, pt_rgb b, uint vertices,
              uint steps, uint truncated) {
    __global float *o = out + PT_OUT * g;
    o[0] = bg.r; o[1] = bg.g; o[2] = bg.b;
    o[3] = a.r; o[4] = a.g; o[5] = a.b;
    o[6] = b.r; o[7] = b.g; o[8] = b.b;
    o[9] = (float)vertices;
    o[10] = (float)steps;
    o[11] = (float)truncated;
}

#define PT_MEDIUM_ARGS                                                                    \
    __global const float *density, __global const float *maj, const int nx, const int ny, \
        const int nz, const int mx, const int my, const int mz, const float4 bmin,       \
        const float4 bmax, const float4 bsize, const float scale, const float4 albedo,   \
        const float4 lobe_g, const float4 lobe_w, const float4 light_dir,                \
        const float4 sun, const float4 env

#define PT_SETUP                                                                          \
    pt_medium m;                                                                          \
    m.density = density; m.maj = maj;                                                     \
    m.nx = nx; m.ny = ny; m.nz = nz; m.mx = mx; m.my = my; m.mz = mz;                     \
    m.bmin = bmin.xyz; m.bmax = bmax.xyz; m.bsize = bsize.xyz; m.scale = scale;           \
    m.inv_cell = (float3)((float)nx, (float)ny, (float)nz) / (bmax.xyz - bmin.xyz);       \
    pt_light L;                                                                           \
    L.dir = light_dir.xyz; L.sun = pt_rgb_of(sun); L.env = pt_rgb_of(env);                \
    L.albedo = SPEC_OF(albedo);                                                           \
    L.lobe_g = lobe_g; L.lobe_w = lobe_w;

__kernel void pt_render(PT_MEDIUM_ARGS, const float4 cam_o, const float4 cam_f,
                        const float4 cam_r, const float4 cam_u, const float tan_half,
                        const int width, const int height, const ulong seed,
                        const uint sample0, const int spl, const int max_order,
                        __global float *out) {
    int g = get_global_id(0);
    int npix = width * height;
    if (g >= npix * spl) return;
    PT_SETUP
    int j = g / npix, pix = g - j * npix;
    int row = pix / width, col = pix - row * width;
    pt_rng r;
    pt_rng_init(&r, seed, (ulong)pix, sample0 + (uint)j);
    float px = (float)col + pt_next(&r), py = (float)row + pt_next(&r);
    float3 w = camera_ray(cam_f.xyz, cam_r.xyz, cam_u.xyz, tan_half, width, height, px, py);
    pt_rgb zero = pt_rgb_of((float4)(0.0f));
    pt_rgb l1 = zero, lms = zero, bg = zero;
    uint vertices = 0, steps = 0, truncated = 0;
    float t;
    if (pt_free_flight(&m, cam_o.xyz, w, &r, &t, &steps)) {
        pt_walk(&m, &L, cam_o.xyz + t * w, w, L.albedo, 1, max_order, &r, &l1, &lms, &vertices, &steps,
                &truncated);
    } else {
#ifdef PT_ENV
        bg = L.env;
#endif
    }
    pt_store(out, (size_t)g, bg, l1, lms, vertices, steps, truncated);
}

__kernel void pt_query(PT_MEDIUM_ARGS, __global const float *points,
                       __global const float *omegas, const int nq, const ulong seed,
                       const uint sample0, const int ppl, const int max_order,
                       __global float *out) {
    int g = get_global_id(0);
    if (g >= nq * ppl) return;
    PT_SETUP
    int j = g / nq, q = g - j * nq;
    pt_rng r;
    pt_rng_init(&r, seed, (ulong)q, sample0 + (uint)j);
    pt_rgb zero = pt_rgb_of((float4)(0.0f));
    pt_rgb l1 = zero, lms = zero;
    uint vertices = 0, steps = 0, truncated = 0;
    pt_walk(&m, &L, vload3(q, points), -vload3(q, omegas), SPEC_ONE, 1, max_order, &r, &l1,
            &lms, &vertices, &steps, &truncated);
    pt_store(out, (size_t)g, zero, l1, lms, vertices, steps, truncated);
}
