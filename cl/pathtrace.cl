/* Reference volumetric path tracer: images and point queries (ground truth, training labels).
 *
 * Estimator (docs/conventions.md; seed: the ground truth its network learns, "F(p, omega)")
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
 *   - with an environment map (PT_ENVMAP; docs/pathtrace.md "Environment maps"): after the
 *     sun NEE, every vertex also samples a direction d of the map by its luminance
 *     (pt_env_sample) and adds beta * L(d) f(dot(d, w)) T(x -> d) w_env / p_env(d), with
 *     T by ratio tracking as for the sun; a path leaving the box after phase sampling
 *     from vertex k adds beta * L(w) w_phase; power heuristic
 *     w_env = p_env^2 / (p_env^2 + f^2), w_phase = f^2 / (f^2 + p_env^2) (phase sampling
 *     is exact: its pdf is f). At the last vertex (k = max_order, or PT_SINGLE_ONLY) no
 *     direction is phase-sampled, so w_env = 1 there. Camera rays that escape add L(w).
 *   - Russian roulette from vertex PT_RR_START on: survive with q = min(1, max_c beta_c),
 *     beta /= q (unbiased; with albedo ~1, q ~ albedo, so long paths of clouds survive).
 *   - max_order > 0 stops after the NEE of vertex max_order (0 = unlimited); paths longer
 *     than PT_MAX_VERTICES are cut and counted (reported, never silent).
 *   - emission (PT_EMISSION; docs/pathtrace.md "Emission"): the medium emits sigma_a Le,
 *     sigma_a = sigma_t (1 - albedo); at every real collision, before beta *= albedo, the
 *     path adds beta * (1 - albedo) * Le(x) (the collision estimator: collisions have
 *     density sigma_t T, so its expectation is int T sigma_a Le dt along each flight). The
 *     first collision's goes to the row's unscattered emission, later ones' to its scattered
 *     emission. No random numbers are drawn for it.
 * Point queries start at p as vertex 1 with beta = 1 and w = -omega (omega toward the
 * camera): order 1 gives F_1 = f(dot(-l, omega)) T(p -> sun), orders >= 2 give F_>=2.
 *
 * Random numbers (rng.h, Philox): one sequential stream per path, key = seed, counter =
 * (stream = pixel or query index, sample index, block); uniforms are used in order, 4 per
 * block. Draw order: [render: jitter x, y] then per flight step: u_tau and, at a tentative
 * collision inside the box, u_real; per NEE ratio-tracking step: u_tau (+ u_roulette when
 * T < PT_T_RR); PT_ENVMAP: per vertex after the sun NEE, 2 uniforms (row, column of the
 * map) and the env NEE's ratio-tracking draws; per vertex before sampling a direction:
 * u_rr (only if k >= PT_RR_START); phase sample: 3 uniforms (lobe, polar, azimuth).
 * reference/pathtrace.py draws the same.
 *
 * Defines: PT_EMISSION, PT_EMISSION_CHANNELS 1|3 (emission grid planes, below);
 * PHASE_LOBES / PHASE_ISOTROPIC (phase.h); PT_GREY (scalar throughput);
 * PT_ENV (a constant environment); PT_ENVMAP (a lat-long environment map); PT_NO_SUN (no sun); PT_SINGLE_ONLY (stop after vertex
 * 1); PT_RR_START, PT_MAX_VERTICES; PT_TEST_BIAS (tests only: scales sun NEE by its value);
 * PT_LANES (4, 8 or 16 paths per work-item, at most LANES), PT_BATCH (lanes waiting before the vertex code
 * runs), PT_STATS (loop counts in next[1..4], benchmarks only), PT_ORDER_BINS (point
 * queries: per-order bins after each row, below).
 *
 * Kernels (grid and majorant arguments first, then light, then the per-kernel ones):
 *   density   float [nz][ny][nx]    raw density; sigma_t = density * density scale (1/length)
 *   maj       float [mz][my][mx]    majorant grid (cl/majorant.cl), raw density
 *   bmin,bmax float4                the grid's box (world); bsize float4 = coarse cell size
 *   medium    MediumBlock           the medium block (medium.h, 16 floats): density scale, RGB
 *                                   single-scattering albedo, phase lobes (phase.h)
 *   light     LightBlock            the light block (light.h, 16 floats): unit direction l
 *                                   toward the sun, its irradiance E (RGB, power / area
 *                                   perpendicular to l)
 *   env       float4                environment radiance (RGB), used with PT_ENV
 *   PT_ENVMAP only (clvol/envmap.py Tables): env_rgbl float [h][w][4] (scaled RGB and
 *             luminance), env_marg float [h+1], env_cond float [h][w+1] (CDFs, last 1),
 *             env_w, env_h int, env_rot float (radians about +y), env_inv_total float
 *   PT_EMISSION only (after those): em float [C][ez][ey][ex] over em_min .. em_max (its
 *             own box: trilinear between voxel centres, clamped, Le = 0 outside it),
 *             emx, emy, emz int, em_min, em_max float4, em_colour float4 (Le = em_colour
 *             times the planes; C = PT_EMISSION_CHANNELS, 1 plane coloured by em_colour)
 * pt_render: cam_o, cam_f, cam_r, cam_u float4, tan_half, width, height; seed ulong;
 *   sample0 uint; spl int (samples per launch; path g: pixel g % npix, sample
 *   sample0 + g / npix); max_order int; out float [spl*npix][PT_OUT]:
 *   (background rgb, order-1 rgb, orders>=2 rgb, vertices, tracking steps, truncated;
 *   with PT_EMISSION then: emission seen unscattered rgb, emission scattered >= 1 time rgb);
 *   next uint [1] (5 with PT_STATS), zero at launch: the next path to start.
 * pt_query: points, omegas float [nq][3]; nq; seed; sample0; ppl (paths per launch,
 *   path g: query g % nq, path sample0 + g / nq); max_order; out as pt_render with
 *   background 0 (sun irradiance 1 and no environment are the caller's arguments); next.
 * Any number of work-items (local size 1) runs all paths of a launch: each takes paths
 * from *next until none are left.
 */
#include "rng.h"
#include "grid.h"
#include "phase.h"
#include "medium.h"
#include "light.h"
#include "majorant.h"
#include "lanes.h"
#include "constants.h"   /* PT_OUT_*, PT_ORDER_* */

#ifndef PT_RR_START
#define PT_RR_START 8
#endif
#ifndef PT_MAX_VERTICES
#define PT_MAX_VERTICES 100000
#endif
/* Bounds on the tracking loop (clvol/kernels/pathtrace.py passes them; docs/pathtrace.md,
 * "Bounds"): a path ends, its row's truncated word set to 2, after PT_MAX_STEPS tentative
 * collisions (about 10 per vertex at PT_MAX_VERTICES; the examples' paths take at most
 * ~900), or after PT_MAX_STALLS tentative collisions in a row that each move t by less
 * than PT_STALL_FRACTION of the majorant block's smallest side (a majorant so large that
 * crossing one block takes millions of draws, or 1/sigma_maj below t's rounding step: the
 * flight never gets anywhere). Neither binds in a path whose row is written otherwise. */
#ifndef PT_MAX_STEPS
#define PT_MAX_STEPS 1048576
#endif
#ifndef PT_MAX_STALLS
#define PT_MAX_STALLS 256
#endif
#ifndef PT_STALL_FRACTION
#define PT_STALL_FRACTION 9.5367431640625e-07f   /* 2^-20 */
#endif
/* Ratio-tracking roulette threshold: below it, T survives with probability T / PT_T_RR. */
#define PT_T_RR 0.1f
/* The row: PT_OUT floats (constants.h), of which the first PT_ACC are accumulated (all but
 * vertices, steps, truncated): background, order 1, orders >= 2 (then emission unscattered,
 * scattered). */
#ifdef PT_EMISSION
#define PT_OUT PT_OUT_EMISSION
#ifndef PT_EMISSION_CHANNELS
#define PT_EMISSION_CHANNELS 1
#endif
#if PT_EMISSION_CHANNELS != 1 && PT_EMISSION_CHANNELS != 3
#error "PT_EMISSION_CHANNELS must be 1 or 3"
#endif
#ifdef PT_ORDER_BINS
#error "PT_ORDER_BINS bins the sun's light per order: point queries have no emission"
#endif
#else
#define PT_OUT PT_OUT_NO_EMISSION
#endif
#define PT_ACC (PT_OUT - 3)

/* Per-order point queries (-D PT_ORDER_BINS, grey, sun only; docs/pathtrace.md "Labels per
 * scattering order"): every sun NEE of vertex k >= 2 adds its value v to bin b(e) of its
 * path's row, with e = k - 1 the number of real collisions after p (the power of the albedo
 * in its throughput), and v * e to the bin's first moment. Exponents below PT_ORDER_EXACT
 * have a bin each; above, each octave [2^o, 2^(o+1)) is split into PT_ORDER_SUB equal bins
 * (integer arithmetic, so the host and the twin compute the same bins). Row: PT_OUT floats,
 * then PT_ORDER_BINS sums, then PT_ORDER_BINS first moments. */
#ifdef PT_ORDER_BINS
#if PT_ORDER_EXACT != (1 << PT_ORDER_EXACT_LOG2)
#error "PT_ORDER_EXACT must be 2^PT_ORDER_EXACT_LOG2"
#endif
#if PT_ORDER_BINS != (PT_ORDER_EXACT - 1 + (PT_ORDER_END_LOG2 - PT_ORDER_EXACT_LOG2) * PT_ORDER_SUB)
#error "PT_ORDER_BINS must cover exponents up to 2^PT_ORDER_END_LOG2 - 1 > PT_MAX_VERTICES"
#endif
#if defined(PT_ENV) || defined(PT_ENVMAP)
#error "PT_ORDER_BINS bins the sun's contributions only: no environment (labels are per unit sun)"
#endif
#define PT_ROW (PT_OUT + 2 * PT_ORDER_BINS)

__attribute__((always_inline))
int pt_order_bin(int e) {
    if (e < PT_ORDER_EXACT) return e - 1;
    int o = 31 - (int)clz((uint)e);                       /* floor(log2(e)) */
    int s = ((e - (1 << o)) * PT_ORDER_SUB) >> o;          /* 0 .. PT_ORDER_SUB - 1 */
    return min(PT_ORDER_EXACT - 1 + (o - PT_ORDER_EXACT_LOG2) * PT_ORDER_SUB + s,
               PT_ORDER_BINS - 1);
}
#else
#define PT_ROW PT_OUT
#endif

/* Colours are structs of three floats (lane vectors in pt_lanes). */
typedef struct {
    float r, g, b;
} pt_rgb;

__attribute__((always_inline))
pt_rgb pt_rgb_of(float4 v) {
    pt_rgb c;
    c.r = v.x; c.g = v.y; c.b = v.z;
    return c;
}

/* Albedo: one float when it is grey (PT_GREY; the throughput is then one float too). */
#ifdef PT_GREY
typedef float spec_t;
#define SPEC_OF(v4) ((v4).x)
#else
typedef pt_rgb spec_t;
#define SPEC_OF(v4) pt_rgb_of(v4)
#endif

/* ------------------------------------------------------------------ lanes
 *
 * PT_LANES paths run side by side in one work-item, one path per lane (PoCL vectorises
 * explicit vector types, not this divergent loop across work-items: docs/pathtrace.md).
 * The state of every lane lives in the arrays of pt_lanes (structure of arrays). One
 * loop, pt_run, shared by images and point queries, moves every tracking lane to its next
 * tentative collision (majorant cells walked in a vector inner loop) and processes the
 * collisions together (trilinear lookups, accept test or ratio-tracking update). A lane
 * whose ray ends gets a pending step; once PT_BATCH lanes wait (or none tracks),
 * pt_events runs the steps between rays (vertex, sun NEE set-up, roulette, phase
 * sampling, escape, writing a finished path, starting the next one) for all of them at
 * once under masks. A lane whose path ends takes the next path of the launch from a
 * global counter, so lanes stay busy until the launch runs out of paths. Each path still
 * reads its own Philox stream in the documented order and writes its own output row:
 * which lane or work-item ran it changes nothing. */
#ifndef PT_LANES
#error "pathtrace.cl needs -D PT_LANES (clvol/kernels/pathtrace.py RENDER_LANES, QUERY_LANES)"
#endif
#if PT_LANES != 4 && PT_LANES != 8 && PT_LANES != 16
#error "PT_LANES must be 4, 8 or 16"
#endif
#if PT_LANES > LANES
#error "PT_LANES must be at most the device's LANES (lanes.h: no wider vector in a call)"
#endif
typedef LANES_CAT(float, PT_LANES) vf;
typedef LANES_CAT(int, PT_LANES) vi;
typedef LANES_CAT(uint, PT_LANES) vu;
#define VLOAD(a) LANES_CAT(vload, PT_LANES)(0, a)
#define VSTORE(v, a) LANES_CAT(vstore, PT_LANES)(v, 0, a)
#define VGATHER(p, i) LANES_CAT(gather, PT_LANES)(p, i)
#define VCONVERT_F(x) LANES_CAT(convert_float, PT_LANES)(x)
#define VCONVERT_I(x) LANES_CAT(convert_int, PT_LANES)(x)
RNG_DEFINE_LANES(PT_LANES)
#define VPHILOX LANES_CAT(philox4x32_10_x, PT_LANES)
#define as_vu(x) LANES_CAT(as_uint, PT_LANES)(x)

#define PT_IDLE 0
#define PT_FLIGHT 1     /* delta tracking: a real collision is a scattering vertex */
#define PT_SHADOW 2     /* ratio tracking toward the sun */

typedef struct {
    /* ray: origin o (current vertex or camera), path direction w (the flight's direction;
     * a shadow ray goes along the light), majorant DDA of maj_dda (majorant.h) */
    float ox[PT_LANES], oy[PT_LANES], oz[PT_LANES];
    float wx[PT_LANES], wy[PT_LANES], wz[PT_LANES];
    float t[PT_LANES], te[PT_LANES], tnx[PT_LANES], tny[PT_LANES], tnz[PT_LANES];
    float tdx[PT_LANES], tdy[PT_LANES], tdz[PT_LANES];
    int cx[PT_LANES], cy[PT_LANES], cz[PT_LANES], sx[PT_LANES], sy[PT_LANES], sz[PT_LANES];
    float tau[PT_LANES];   /* optical depth left to the next tentative collision */
    float T[PT_LANES];     /* ratio-tracking transmittance */
    int mode[PT_LANES];
    int steps[PT_LANES];
    int stall[PT_LANES];   /* tentative collisions in a row that (almost) left t unchanged */
    /* random stream of the path: counter words; the next 8 uniforms of the stream are
     * u[used..7] (two Philox blocks; block = the next block to generate) */
    uint slo[PT_LANES], shi[PT_LANES], sample[PT_LANES], block[PT_LANES];
    float u[8][PT_LANES];
    int used[PT_LANES];
    /* path */
    float br[PT_LANES], bg[PT_LANES], bb[PT_LANES];   /* throughput (PT_GREY: br only) */
    float f[PT_LANES];                                /* phase value of the pending NEE */
    int pend[PT_LANES];                               /* pending step (H_*), 0 = none */
    float acc[PT_ACC][PT_LANES];                      /* background, order 1, orders >= 2 */
#ifdef PT_ENVMAP
    float lx[PT_LANES], ly[PT_LANES], lz[PT_LANES];   /* shadow ray direction */
    float ec[3][PT_LANES];      /* env NEE: L f w_env / p_env of the pending shadow ray */
    float pf[PT_LANES];         /* phase pdf of the last phase-sampled direction */
    int envnee[PT_LANES];       /* the pending shadow ray is the env NEE's */
#endif
    int k[PT_LANES], vertices[PT_LANES], truncated[PT_LANES], path[PT_LANES];
} pt_lanes;

/* Make at least 4 uniforms ready in every lane of mask: a lane with 4 or fewer left moves
 * its second block to the first and generates the next block of its stream. One Philox
 * (for all lanes) serves up to 4 draws after it, not one per draw. */
__attribute__((always_inline))
void pt_lanes_refill(pt_lanes *S, vi mask, uint2 key) {
    vi used = VLOAD(S->used);
    vi need = mask & (used >= 4);
    if (!any(need)) return;
    vu blk = VLOAD(S->block);
    vu c0 = VLOAD(S->slo), c1 = VLOAD(S->shi), c2 = VLOAD(S->sample), c3 = blk;
    VPHILOX(&c0, &c1, &c2, &c3, key);
    const float s = 1.0f / 16777216.0f;   /* top 24 bits, as u01x4 of rng.h */
    vf fresh[4] = {VCONVERT_F(c0 >> 8) * s, VCONVERT_F(c1 >> 8) * s,
                   VCONVERT_F(c2 >> 8) * s, VCONVERT_F(c3 >> 8) * s};
    for (int i = 0; i < 4; ++i) {
        vf second = VLOAD(S->u[i + 4]);
        VSTORE(select(VLOAD(S->u[i]), second, need), S->u[i]);
        VSTORE(select(second, fresh[i], need), S->u[i + 4]);
    }
    VSTORE(select(blk, blk + 1u, need), S->block);
    VSTORE(select(used, used - 4, need), S->used);
}

/* Next uniform of every lane in mask (after pt_lanes_refill: at most 4 draws per refill);
 * other lanes draw nothing. */
__attribute__((always_inline))
vf pt_lanes_take(pt_lanes *S, vi mask) {
    vi used = VLOAD(S->used);
    vf u = VLOAD(S->u[7]);
    for (int i = 6; i >= 0; --i) u = select(u, VLOAD(S->u[i]), used == i);
    VSTORE(used - mask, S->used);   /* mask lanes are -1: one more used */
    return u;
}

/* ------------------------------------------------------------------ medium */

typedef struct {
    __global const float *density;
    __global const float *maj;
    int nx, ny, nz, mx, my, mz;
    float3 bmin, bmax, bsize;
    float3 inv_cell;   /* n / (bmax - bmin): voxels per unit length */
    float scale;
#ifdef PT_EMISSION
    __global const float *em;
    int emx, emy, emz;
    float3 em_min, em_max, em_inv_cell, em_colour;
#endif
} pt_medium;

/* sigma_t at (px, py, pz) in the lanes of mask (0 elsewhere and outside the box):
 * grid_lookup of grid.h per lane, the cell size inverted once per launch. */
__attribute__((always_inline))
vf pt_sigma_lanes(const pt_medium *m, vf px, vf py, vf pz, vi mask) {
    vi in = mask & (px >= m->bmin.x) & (px <= m->bmax.x) & (py >= m->bmin.y) &
            (py <= m->bmax.y) & (pz >= m->bmin.z) & (pz <= m->bmax.z);
    /* Lanes outside look up voxel 0 (any finite coordinate would do: clamped below). */
    vf gx = select((vf)(0.0f), (px - m->bmin.x) * m->inv_cell.x - 0.5f, in);
    vf gy = select((vf)(0.0f), (py - m->bmin.y) * m->inv_cell.y - 0.5f, in);
    vf gz = select((vf)(0.0f), (pz - m->bmin.z) * m->inv_cell.z - 0.5f, in);
    /* Builtins get vector arguments only (Oclgrind mis-runs min(int8, int) and kin). */
    vf x = clamp(gx, (vf)(0.0f), (vf)((float)(m->nx - 1)));
    vf y = clamp(gy, (vf)(0.0f), (vf)((float)(m->ny - 1)));
    vf z = clamp(gz, (vf)(0.0f), (vf)((float)(m->nz - 1)));
    vi x0 = VCONVERT_I(x), y0 = VCONVERT_I(y), z0 = VCONVERT_I(z);
    vi dx = select((vi)(0), (vi)(1), x0 < m->nx - 1);
    vi y1 = min(y0 + 1, (vi)(m->ny - 1)), z1 = min(z0 + 1, (vi)(m->nz - 1));
    vf fx = x - VCONVERT_F(x0), fy = y - VCONVERT_F(y0), fz = z - VCONVERT_F(z0);
    int sz = m->nx * m->ny;
    vi r00 = z0 * sz + y0 * m->nx + x0, r01 = z0 * sz + y1 * m->nx + x0;
    vi r10 = z1 * sz + y0 * m->nx + x0, r11 = z1 * sz + y1 * m->nx + x0;
    __global const float *d = m->density;
    vf c00 = mix(VGATHER(d, r00), VGATHER(d, r00 + dx), fx);
    vf c01 = mix(VGATHER(d, r01), VGATHER(d, r01 + dx), fx);
    vf c10 = mix(VGATHER(d, r10), VGATHER(d, r10 + dx), fx);
    vf c11 = mix(VGATHER(d, r11), VGATHER(d, r11 + dx), fx);
    vf v = mix(mix(c00, c01, fy), mix(c10, c11, fy), fz) * m->scale;
    return select((vf)(0.0f), v, in);
}

#ifdef PT_EMISSION
/* Plane `p` of the emission grid at (px, py, pz) in the lanes of mask, trilinear between
 * voxel centres, clamped; 0 outside the grid's box and outside mask (grid.h's lookup). */
__attribute__((always_inline))
vf pt_emission_lanes(const pt_medium *m, int p, vf px, vf py, vf pz, vi mask) {
    vi in = mask & (px >= m->em_min.x) & (px <= m->em_max.x) & (py >= m->em_min.y) &
            (py <= m->em_max.y) & (pz >= m->em_min.z) & (pz <= m->em_max.z);
    vf gx = select((vf)(0.0f), (px - m->em_min.x) * m->em_inv_cell.x - 0.5f, in);
    vf gy = select((vf)(0.0f), (py - m->em_min.y) * m->em_inv_cell.y - 0.5f, in);
    vf gz = select((vf)(0.0f), (pz - m->em_min.z) * m->em_inv_cell.z - 0.5f, in);
    vf x = clamp(gx, (vf)(0.0f), (vf)((float)(m->emx - 1)));
    vf y = clamp(gy, (vf)(0.0f), (vf)((float)(m->emy - 1)));
    vf z = clamp(gz, (vf)(0.0f), (vf)((float)(m->emz - 1)));
    vi x0 = VCONVERT_I(x), y0 = VCONVERT_I(y), z0 = VCONVERT_I(z);
    vi dx = select((vi)(0), (vi)(1), x0 < m->emx - 1);
    vi y1 = min(y0 + 1, (vi)(m->emy - 1)), z1 = min(z0 + 1, (vi)(m->emz - 1));
    vf fx = x - VCONVERT_F(x0), fy = y - VCONVERT_F(y0), fz = z - VCONVERT_F(z0);
    int sz = m->emx * m->emy;
    vi r00 = z0 * sz + y0 * m->emx + x0, r01 = z0 * sz + y1 * m->emx + x0;
    vi r10 = z1 * sz + y0 * m->emx + x0, r11 = z1 * sz + y1 * m->emx + x0;
    __global const float *d = m->em + (size_t)p * (size_t)(sz * m->emz);
    vf c00 = mix(VGATHER(d, r00), VGATHER(d, r00 + dx), fx);
    vf c01 = mix(VGATHER(d, r01), VGATHER(d, r01 + dx), fx);
    vf c10 = mix(VGATHER(d, r10), VGATHER(d, r10 + dx), fx);
    vf c11 = mix(VGATHER(d, r11), VGATHER(d, r11 + dx), fx);
    return select((vf)(0.0f), mix(mix(c00, c01, fy), mix(c10, c11, fy), fz), in);
}
#endif

/* ------------------------------------------------------------------ random walk */

typedef struct {
    float3 dir;       /* toward the sun */
    pt_rgb sun;       /* irradiance */
    pt_rgb env;       /* environment radiance */
    spec_t albedo;
    float4 lobe_g, lobe_w;
#ifdef PT_ENVMAP
    __global const float *env_rgbl, *env_marg, *env_cond;
    int env_w, env_h;
    float env_rot, env_inv_total;
#endif
} pt_light;

#if defined(PT_ENV) && defined(PT_ENVMAP)
#error "PT_ENV (constant) and PT_ENVMAP (map) are exclusive"
#endif

#ifdef PT_ENVMAP
/* Largest i in [0, n - 1] with cdf[i] <= u, for cdf[0] = 0 <= u < 1 = cdf[n]: then
 * cdf[i] <= u < cdf[i + 1], so the bin drawn has a positive width. */
__attribute__((always_inline))
int pt_cdf_find(__global const float *cdf, int n, float u) {
    int lo = 0, hi = n;
    while (hi - lo > 1) {
        int mid = (lo + hi) >> 1;
        if (cdf[mid] <= u) lo = mid; else hi = mid;
    }
    return lo;
}

/* Direction d of the map (world) for uniforms u0 (row), u1 (column): texel by the CDFs,
 * then uniform in cos(theta) and phi inside it (clvol/envmap.py). Returns the texel's
 * scaled RGB in .xyz and the pdf per solid angle, lum * inv_total (> 0), in .w. */
__attribute__((always_inline))
float4 pt_env_sample(const pt_light *L, float u0, float u1, float3 *d) {
    const int w = L->env_w, h = L->env_h;
    int i = pt_cdf_find(L->env_marg, h, u0);
    float m0 = L->env_marg[i], m1 = L->env_marg[i + 1];
    float fv = (u0 - m0) / (m1 - m0);                 /* m1 > m0: see pt_cdf_find */
    __global const float *c = L->env_cond + (size_t)i * (w + 1);
    int j = pt_cdf_find(c, w, u1);
    float fu = (u1 - c[j]) / (c[j + 1] - c[j]);
    float ct0 = cos(CLVOL_PI * (float)i / (float)h), ct1 = cos(CLVOL_PI * (float)(i + 1) / (float)h);
    float ct = ct0 + fv * (ct1 - ct0);
    float st = sqrt(fmax(0.0f, 1.0f - ct * ct));
    float phi = 2.0f * CLVOL_PI * ((float)j + fu) / (float)w + L->env_rot;
    *d = (float3)(st * cos(phi), ct, -st * sin(phi));
    float4 t = vload4((size_t)i * w + j, L->env_rgbl);
    t.w *= L->env_inv_total;
    return t;
}

/* The map along unit direction d: scaled RGB in .xyz, pdf of pt_env_sample in .w. */
__attribute__((always_inline))
float4 pt_env_lookup(const pt_light *L, float3 d) {
    const int w = L->env_w, h = L->env_h;
    float u = (atan2(-d.z, d.x) - L->env_rot) * (0.5f / CLVOL_PI);
    u -= floor(u);                                    /* [0, 1] */
    float v = acos(clamp(d.y, -1.0f, 1.0f)) * (1.0f / CLVOL_PI);
    int j = min((int)(u * (float)w), w - 1), i = min((int)(v * (float)h), h - 1);
    float4 t = vload4((size_t)i * w + j, L->env_rgbl);
    t.w *= L->env_inv_total;
    return t;
}
#endif

/* What a launch computes: path g of n is (stream g % nstream, sample sample0 + g / nstream). */
typedef struct {
    int is_query;
    ulong seed;
    uint sample0;
    int n, nstream, max_order;
    float3 cam_o, cam_f, cam_r, cam_u;     /* render */
    float tan_half;
    int width, height;
    __global const float *points;          /* query */
    __global const float *omegas;
    __global float *out;
    __global volatile uint *next;          /* next path of the launch to start */
} pt_job;

/* ------------------------------------------------------------------ lanes of phase.h, grid.h, majorant.h
 * The same formulas as the scalar helpers, one lane per path (the twin tests compare the
 * result path by path, so a slip here fails them). */

/* hg_eval and phase_eval of phase.h on every lane (the lobes the same in every lane). */
HG_EVAL_T(pt_hg_eval_v, vf)
PHASE_EVAL_T(pt_phase_eval_v, vf, pt_hg_eval_v)

/* phase_sample of phase.h (lobe by u0, hg_sample_one_minus_mu by u1, direction_around
 * with the onb by u2): the new direction replaces (*wx, *wy, *wz). */
__attribute__((always_inline))
void pt_phase_sample_v(vf *wx, vf *wy, vf *wz, float4 lobe_g, float4 lobe_w, vf u0, vf u1,
                       vf u2) {
#ifdef PHASE_ISOTROPIC
    vf omm = 2.0f * (1.0f - u1);
    vf nx = *wx, ny = *wy, nz = *wz;
#else
    vf g = (vf)(lobe_g.x);
#if PHASE_LOBES >= 2
    g = select(g, (vf)(lobe_g.y), u0 >= lobe_w.x);
#endif
#if PHASE_LOBES >= 3
    g = select(g, (vf)(lobe_g.z), u0 >= lobe_w.x + lobe_w.y);
#endif
    vf ga = fabs(g);
    vf a = 1.0f - ga + 2.0f * ga * u1;
    vf omg = 1.0f - ga;
    vf omm = clamp(omg * omg * (1.0f - u1) * (2.0f + 2.0f * ga * u1) / (a * a), (vf)(0.0f),
                    (vf)(2.0f));
    vi neg = g < 0.0f;   /* sample the mirrored lobe about -w */
    vf nx = select(*wx, -*wx, neg), ny = select(*wy, -*wy, neg), nz = select(*wz, -*wz, neg);
#endif
    vf mu = 1.0f - omm;
    vf s = sqrt(fmax((vf)(0.0f), omm * (2.0f - omm)));
    vf phi = 2.0f * CLVOL_PI * u2;
    vf sgn = select((vf)(-1.0f), (vf)(1.0f), nz >= 0.0f);
    vf ia = -1.0f / (sgn + nz);
    vf b = nx * ny * ia;
    vf b1x = 1.0f + sgn * nx * nx * ia, b1y = sgn * b, b1z = -sgn * nx;
    vf b2x = b, b2y = sgn + ny * ny * ia, b2z = -ny;
    /* cos and sin, not sincos: Oclgrind's checker cannot follow sincos's private pointer. */
    vf sc = s * cos(phi), ss = s * sin(phi);
    vf vx = sc * b1x + ss * b2x + mu * nx;
    vf vy = sc * b1y + ss * b2y + mu * ny;
    vf vz = sc * b1z + ss * b2z + mu * nz;
    vf len = sqrt(vx * vx + vy * vy + vz * vz);
    *wx = vx / len; *wy = vy / len; *wz = vz / len;
}

/* One axis of box_intersect (grid.h). */
__attribute__((always_inline))
void pt_slab_v(vf o, vf d, float mn, float mx, vf *lo, vf *hi, vi *ok) {
    vi zero = d == 0.0f;
    *ok &= ~(zero & ((o < mn) | (o > mx)));
    vf inv = 1.0f / d;
    vf ta = (mn - o) * inv, tb = (mx - o) * inv;
    *lo = select(fmax(*lo, fmin(ta, tb)), *lo, zero);
    *hi = select(fmin(*hi, fmax(ta, tb)), *hi, zero);
}

/* One axis of maj_dda_init (majorant.h). */
__attribute__((always_inline))
void pt_dda_axis_v(vf o, vf d, float bmin, float bsize, vi cell, vi *step, vf *tn, vf *td) {
    vi pos = d > 0.0f, any_d = pos | (d < 0.0f);
    *step = select(select((vi)(0), (vi)(-1), any_d), (vi)(1), pos);
    vf edge = bmin + VCONVERT_F(cell - pos) * bsize;   /* pos lanes are -1: cell + 1 */
    *tn = select((vf)(INFINITY), (edge - o) / d, any_d);
    *td = select((vf)(INFINITY), select(-bsize / d, bsize / d, pos), any_d);
}

/* Start tracking rays in the lanes of mask (maj_dda_init from S.o along the path
 * direction, or along the light for PT_SHADOW lanes) and draw their first optical depth.
 * Returns the lanes whose ray misses the box (nothing drawn there). */
__attribute__((always_inline))
vi pt_rays_v(pt_lanes *S, vi mask, const pt_medium *m, const pt_light *L, uint2 key) {
    vi shadow = VLOAD(S->mode) == PT_SHADOW;
    vf ox = VLOAD(S->ox), oy = VLOAD(S->oy), oz = VLOAD(S->oz);
#ifdef PT_ENVMAP
    vf dx = select(VLOAD(S->wx), VLOAD(S->lx), shadow);
    vf dy = select(VLOAD(S->wy), VLOAD(S->ly), shadow);
    vf dz = select(VLOAD(S->wz), VLOAD(S->lz), shadow);
#else
    vf dx = select(VLOAD(S->wx), (vf)(L->dir.x), shadow);
    vf dy = select(VLOAD(S->wy), (vf)(L->dir.y), shadow);
    vf dz = select(VLOAD(S->wz), (vf)(L->dir.z), shadow);
#endif
    vf lo = (vf)(0.0f), hi = (vf)(INFINITY);
    vi ok = mask;
    pt_slab_v(ox, dx, m->bmin.x, m->bmax.x, &lo, &hi, &ok);
    pt_slab_v(oy, dy, m->bmin.y, m->bmax.y, &lo, &hi, &ok);
    pt_slab_v(oz, dz, m->bmin.z, m->bmax.z, &lo, &hi, &ok);
    ok &= lo < hi;   /* box_intersect's lo <= hi, then maj_dda_init's t0 < t1 */
    if (any(ok)) {
        vf zero = (vf)(0.0f);
        vi cx = VCONVERT_I(clamp((ox + lo * dx - m->bmin.x) / m->bsize.x, zero, (vf)((float)(m->mx - 1))));
        vi cy = VCONVERT_I(clamp((oy + lo * dy - m->bmin.y) / m->bsize.y, zero, (vf)((float)(m->my - 1))));
        vi cz = VCONVERT_I(clamp((oz + lo * dz - m->bmin.z) / m->bsize.z, zero, (vf)((float)(m->mz - 1))));
        vi sx, sy, sz;
        vf tnx, tny, tnz, tdx, tdy, tdz;
        pt_dda_axis_v(ox, dx, m->bmin.x, m->bsize.x, cx, &sx, &tnx, &tdx);
        pt_dda_axis_v(oy, dy, m->bmin.y, m->bsize.y, cy, &sy, &tny, &tdy);
        pt_dda_axis_v(oz, dz, m->bmin.z, m->bsize.z, cz, &sz, &tnz, &tdz);
        VSTORE(select(VLOAD(S->t), lo, ok), S->t);
        VSTORE(select(VLOAD(S->te), hi, ok), S->te);
        VSTORE(select(VLOAD(S->cx), cx, ok), S->cx);
        VSTORE(select(VLOAD(S->cy), cy, ok), S->cy);
        VSTORE(select(VLOAD(S->cz), cz, ok), S->cz);
        VSTORE(select(VLOAD(S->sx), sx, ok), S->sx);
        VSTORE(select(VLOAD(S->sy), sy, ok), S->sy);
        VSTORE(select(VLOAD(S->sz), sz, ok), S->sz);
        VSTORE(select(VLOAD(S->tnx), tnx, ok), S->tnx);
        VSTORE(select(VLOAD(S->tny), tny, ok), S->tny);
        VSTORE(select(VLOAD(S->tnz), tnz, ok), S->tnz);
        VSTORE(select(VLOAD(S->tdx), tdx, ok), S->tdx);
        VSTORE(select(VLOAD(S->tdy), tdy, ok), S->tdy);
        VSTORE(select(VLOAD(S->tdz), tdz, ok), S->tdz);
        /* Exponential optical depth: 1 - u is in (0, 1], no log(0). */
        pt_lanes_refill(S, ok, key);
        vf tau = -log(1.0f - pt_lanes_take(S, ok));
        VSTORE(select(VLOAD(S->tau), tau, ok), S->tau);
    }
    return mask & ~ok;
}

/* acc += (r, g, b) * s in the slot of order k (0 background, 1 single, else multiple),
 * lanes of mask. */
__attribute__((always_inline))
void pt_add_v(pt_lanes *S, vi mask, vi k, vf r, vf g, vf b) {
    vi m0 = mask & (k == 0), m1 = mask & (k == 1), m2 = mask & (k >= 2);
    VSTORE(VLOAD(S->acc[0]) + select((vf)(0.0f), r, m0), S->acc[0]);
    VSTORE(VLOAD(S->acc[1]) + select((vf)(0.0f), g, m0), S->acc[1]);
    VSTORE(VLOAD(S->acc[2]) + select((vf)(0.0f), b, m0), S->acc[2]);
    VSTORE(VLOAD(S->acc[3]) + select((vf)(0.0f), r, m1), S->acc[3]);
    VSTORE(VLOAD(S->acc[4]) + select((vf)(0.0f), g, m1), S->acc[4]);
    VSTORE(VLOAD(S->acc[5]) + select((vf)(0.0f), b, m1), S->acc[5]);
    VSTORE(VLOAD(S->acc[6]) + select((vf)(0.0f), r, m2), S->acc[6]);
    VSTORE(VLOAD(S->acc[7]) + select((vf)(0.0f), g, m2), S->acc[7]);
    VSTORE(VLOAD(S->acc[8]) + select((vf)(0.0f), b, m2), S->acc[8]);
}

/* Throughput as three lane vectors (PT_GREY: one value in all three). */
__attribute__((always_inline))
void pt_beta_v(const pt_lanes *S, vf *r, vf *g, vf *b) {
    *r = VLOAD(S->br);
#ifdef PT_GREY
    *g = *r; *b = *r;
#else
    *g = VLOAD(S->bg); *b = VLOAD(S->bb);
#endif
}

__attribute__((always_inline))
void pt_set_beta_v(pt_lanes *S, vi mask, vf r, vf g, vf b) {
    VSTORE(select(VLOAD(S->br), r, mask), S->br);
#ifndef PT_GREY
    VSTORE(select(VLOAD(S->bg), g, mask), S->bg);
    VSTORE(select(VLOAD(S->bb), b, mask), S->bb);
#endif
}

/* Steps between rays; a lane's pending step is h[j] (H_NONE while it tracks a ray). */
#define H_NONE 0
#define H_ACCEPT 1      /* flight collided for real: the collision becomes vertex k + 1 */
#define H_ESCAPE 2      /* flight left the box */
#define H_FINISH 3      /* write the path's row */
#define H_START 4       /* take the next path of the launch */
#define H_VERTEX 5      /* scattering vertex at S.o: sun NEE */
#define H_NEE_DONE 6    /* shadow ray done with transmittance S.T */
#define H_CONTINUE 7    /* roulette, phase sampling, next flight */
#define H_RAY 8         /* start the ray of S.mode from S.o */
#define H_ENV_NEE 9     /* PT_ENVMAP: sample the map, start its shadow ray */

#ifdef PT_EMISSION
/* beta (1 - albedo) Le(x) at a real collision, before the albedo enters beta: slots 9..11
 * for the first collision (k = 0: seen unscattered), 12..14 for later ones. */
__attribute__((always_inline))
void pt_add_emission_v(pt_lanes *S, vi e, const pt_medium *m, const pt_light *L, vf br, vf bg,
                       vf bb) {
    vf px = VLOAD(S->ox), py = VLOAD(S->oy), pz = VLOAD(S->oz);
    vf l0 = pt_emission_lanes(m, 0, px, py, pz, e);
#if PT_EMISSION_CHANNELS == 3
    vf l1 = pt_emission_lanes(m, 1, px, py, pz, e);
    vf l2 = pt_emission_lanes(m, 2, px, py, pz, e);
#else
    vf l1 = l0, l2 = l0;
#endif
#ifdef PT_GREY
    const float ar = 1.0f - L->albedo, ag = ar, ab = ar;
#else
    const float ar = 1.0f - L->albedo.r, ag = 1.0f - L->albedo.g,
                ab = 1.0f - L->albedo.b;
#endif
    vf er = br * (ar * m->em_colour.x) * l0;
    vf eg = bg * (ag * m->em_colour.y) * l1;
    vf eb = bb * (ab * m->em_colour.z) * l2;
    vi first = e & (VLOAD(S->k) == 0), later = e & (VLOAD(S->k) != 0);
    VSTORE(VLOAD(S->acc[9]) + select((vf)(0.0f), er, first), S->acc[9]);
    VSTORE(VLOAD(S->acc[10]) + select((vf)(0.0f), eg, first), S->acc[10]);
    VSTORE(VLOAD(S->acc[11]) + select((vf)(0.0f), eb, first), S->acc[11]);
    VSTORE(VLOAD(S->acc[12]) + select((vf)(0.0f), er, later), S->acc[12]);
    VSTORE(VLOAD(S->acc[13]) + select((vf)(0.0f), eg, later), S->acc[13]);
    VSTORE(VLOAD(S->acc[14]) + select((vf)(0.0f), eb, later), S->acc[14]);
}
#endif

/* H_ACCEPT: the collision becomes vertex k + 1 (with PT_EMISSION its emission is added
 * first); beta takes the albedo. */
__attribute__((always_inline))
vi pt_on_accept(pt_lanes *S, vi h, const pt_medium *m, const pt_light *L) {
    vi e = h == H_ACCEPT;
    if (!any(e)) return h;
    vf t = VLOAD(S->t);
    VSTORE(select(VLOAD(S->ox), VLOAD(S->ox) + t * VLOAD(S->wx), e), S->ox);
    VSTORE(select(VLOAD(S->oy), VLOAD(S->oy) + t * VLOAD(S->wy), e), S->oy);
    VSTORE(select(VLOAD(S->oz), VLOAD(S->oz) + t * VLOAD(S->wz), e), S->oz);
    vf br, bg, bb;
    pt_beta_v(S, &br, &bg, &bb);
#ifdef PT_EMISSION
    pt_add_emission_v(S, e, m, L, br, bg, bb);
#endif
#ifdef PT_GREY
    pt_set_beta_v(S, e, br * L->albedo, br, br);
#else
    pt_set_beta_v(S, e, br * L->albedo.r, bg * L->albedo.g, bb * L->albedo.b);
#endif
    VSTORE(VLOAD(S->k) - e, S->k);
    h = select(h, (vi)(H_VERTEX), e);
    return h;
}

#ifdef PT_ENVMAP
/* An escaped flight sees the map's L(w), MIS-weighted against the env NEE unless k = 0
 * (camera ray). */
__attribute__((always_inline))
void pt_add_envmap_escape_v(pt_lanes *S, vi e, const pt_light *L) {
    float lr[PT_LANES], lg[PT_LANES], lb[PT_LANES], lp[PT_LANES];
    int on[PT_LANES];
    VSTORE(e, on);
    for (int j = 0; j < PT_LANES; ++j) {
        lr[j] = lg[j] = lb[j] = lp[j] = 0.0f;
        if (!on[j]) continue;
        float4 t = pt_env_lookup(L, (float3)(S->wx[j], S->wy[j], S->wz[j]));
        lr[j] = t.x; lg[j] = t.y; lb[j] = t.z; lp[j] = t.w;
    }
    vf pf = VLOAD(S->pf), pe = VLOAD(lp);
    vf den = pf * pf + pe * pe;
    vf wm = select((vf)(0.0f), pf * pf / den, den > 0.0f);
    wm = select(wm, (vf)(1.0f), VLOAD(S->k) == 0);
    vf br, bg, bb;
    pt_beta_v(S, &br, &bg, &bb);
    pt_add_v(S, e, VLOAD(S->k), VLOAD(lr) * br * wm, VLOAD(lg) * bg * wm,
             VLOAD(lb) * bb * wm);
}
#endif

/* H_ESCAPE: the flight left the box: the environment it sees, then the path's row. */
__attribute__((always_inline))
vi pt_on_escape(pt_lanes *S, vi h, const pt_light *L) {
    vi e = h == H_ESCAPE;
    if (!any(e)) return h;
#ifdef PT_ENV
    vf br, bg, bb;
    pt_beta_v(S, &br, &bg, &bb);
    pt_add_v(S, e, VLOAD(S->k), L->env.r * br, L->env.g * bg, L->env.b * bb);
#endif
#ifdef PT_ENVMAP
    pt_add_envmap_escape_v(S, e, L);
#endif
    h = select(h, (vi)(H_FINISH), e);
    return h;
}

/* H_FINISH: write the path's row. */
__attribute__((always_inline))
vi pt_on_finish(pt_lanes *S, vi h, const pt_job *J) {
    vi e = h == H_FINISH;
    if (!any(e)) return h;
    int fin[PT_LANES];
    VSTORE(e, fin);
    for (int j = 0; j < PT_LANES; ++j) {
        if (!fin[j]) continue;
        __global float *o = J->out + PT_ROW * (size_t)S->path[j];
        for (int c = 0; c < 9; ++c) o[c] = S->acc[c][j];
        o[9] = (float)S->vertices[j];
        o[10] = (float)S->steps[j];
        o[11] = (float)S->truncated[j];
#ifdef PT_EMISSION
        for (int c = 9; c < PT_ACC; ++c) o[c + 3] = S->acc[c][j];
#endif
    }
    h = select(h, (vi)(H_START), e);
    return h;
}

/* Camera rays of the lanes of e through their jittered pixels (col, row) (camera_ray of
 * grid.h); k = 0 until the first real collision (then beta = albedo). */
__attribute__((always_inline))
void pt_camera_rays_v(pt_lanes *S, vi e, const pt_job *J, vi col, vi row, uint2 key) {
    pt_lanes_refill(S, e, key);
    vf px = VCONVERT_F(col) + pt_lanes_take(S, e);
    vf py = VCONVERT_F(row) + pt_lanes_take(S, e);
    float fw = (float)J->width, fh = (float)J->height;
    vf sx = (2.0f * px / fw - 1.0f) * J->tan_half * (fw / fh);
    vf sy = (1.0f - 2.0f * py / fh) * J->tan_half;
    vf dx = J->cam_f.x + sx * J->cam_r.x + sy * J->cam_u.x;
    vf dy = J->cam_f.y + sx * J->cam_r.y + sy * J->cam_u.y;
    vf dz = J->cam_f.z + sx * J->cam_r.z + sy * J->cam_u.z;
    vf len = sqrt(dx * dx + dy * dy + dz * dz);
    VSTORE(select(VLOAD(S->wx), dx / len, e), S->wx);
    VSTORE(select(VLOAD(S->wy), dy / len, e), S->wy);
    VSTORE(select(VLOAD(S->wz), dz / len, e), S->wz);
    VSTORE(select(VLOAD(S->ox), (vf)(J->cam_o.x), e), S->ox);
    VSTORE(select(VLOAD(S->oy), (vf)(J->cam_o.y), e), S->oy);
    VSTORE(select(VLOAD(S->oz), (vf)(J->cam_o.z), e), S->oz);
    VSTORE(select(VLOAD(S->k), (vi)(0), e), S->k);
    VSTORE(select(VLOAD(S->mode), (vi)(PT_FLIGHT), e), S->mode);
}

/* Per lane of e: the next path of the launch (J->n or more when none is left), its stream
 * and sample, the query's point or the pixel (col, row; integer division has no vector
 * instruction here). */
__attribute__((always_inline))
void pt_take_paths(pt_lanes *S, vi e, const pt_job *J, int col[PT_LANES], int row[PT_LANES]) {
    int st[PT_LANES];
    VSTORE(e, st);
    for (int j = 0; j < PT_LANES; ++j) {
        col[j] = row[j] = 0;
        if (!st[j]) continue;
        int g = (int)min(atomic_inc(J->next), (uint)J->n);
        S->path[j] = g;
        if (g >= J->n) continue;
        int sj = g / J->nstream, stream = g - sj * J->nstream;
        S->slo[j] = (uint)stream;
        S->sample[j] = J->sample0 + (uint)sj;
#ifdef PT_ORDER_BINS
        {   /* the path's bins start at 0 (the row is its own: no other path adds) */
            __global float *o = J->out + PT_ROW * (size_t)g + PT_OUT;
            for (int b = 0; b < 2 * PT_ORDER_BINS; ++b) o[b] = 0.0f;
        }
#endif
        if (J->is_query) {
            /* Vertex 1 at p with beta = 1, w = -omega. */
            float3 p = vload3(stream, J->points), w = -vload3(stream, J->omegas);
            S->ox[j] = p.x; S->oy[j] = p.y; S->oz[j] = p.z;
            S->wx[j] = w.x; S->wy[j] = w.y; S->wz[j] = w.z;
        } else {
            row[j] = stream / J->width;
            col[j] = stream - row[j] * J->width;
        }
    }
}

/* H_START: the lanes take the launch's next paths (PT_IDLE when none is left) and start
 * them: a query at its vertex 1, an image path with its camera ray. */
__attribute__((always_inline))
vi pt_on_start(pt_lanes *S, vi h, const pt_job *J, uint2 key) {
    vi e = h == H_START;
    if (!any(e)) return h;
    int col[PT_LANES], row[PT_LANES];
    pt_take_paths(S, e, J, col, row);
    vi none = e & (VLOAD(S->path) >= J->n);
    VSTORE(select(VLOAD(S->mode), (vi)(PT_IDLE), none), S->mode);
    h = select(h, (vi)(H_NONE), none);
    e &= ~none;
    VSTORE(select(VLOAD(S->shi), (vu)(0u), e), S->shi);
    VSTORE(select(VLOAD(S->block), (vu)(0u), e), S->block);
    VSTORE(select(VLOAD(S->used), (vi)(8), e), S->used);   /* nothing buffered */
    for (int c = 0; c < PT_ACC; ++c) VSTORE(select(VLOAD(S->acc[c]), (vf)(0.0f), e), S->acc[c]);
    VSTORE(select(VLOAD(S->steps), (vi)(0), e), S->steps);
    VSTORE(select(VLOAD(S->stall), (vi)(0), e), S->stall);
    VSTORE(select(VLOAD(S->vertices), (vi)(0), e), S->vertices);
    VSTORE(select(VLOAD(S->truncated), (vi)(0), e), S->truncated);
    pt_set_beta_v(S, e, (vf)(1.0f), (vf)(1.0f), (vf)(1.0f));
    if (J->is_query) {
        VSTORE(select(VLOAD(S->k), (vi)(1), e), S->k);
        h = select(h, (vi)(H_VERTEX), e);
    } else {
        pt_camera_rays_v(S, e, J, VLOAD(col), VLOAD(row), key);
        h = select(h, (vi)(H_RAY), e);
    }
    return h;
}

/* H_VERTEX: a scattering vertex at S.o: the sun's shadow ray (NEE), then the env NEE or
 * the next direction. */
__attribute__((always_inline))
vi pt_on_vertex(pt_lanes *S, vi h, const pt_light *L) {
    vi e = h == H_VERTEX;
    if (!any(e)) return h;
    vf br, bg, bb;
    pt_beta_v(S, &br, &bg, &bb);
    vi dead = e & (fmax(fmax(br, bg), bb) <= 0.0f);   /* albedo 0: nothing arrives */
    h = select(h, (vi)(H_FINISH), dead);
    e &= ~dead;
    VSTORE(VLOAD(S->vertices) - e, S->vertices);
#ifdef PT_ENVMAP
    h = select(h, (vi)(H_ENV_NEE), e);
#else
    h = select(h, (vi)(H_CONTINUE), e);
#endif
#ifndef PT_NO_SUN
    /* Also tested at run time, so the general build of a sunless scene draws the
     * same random numbers as the PT_NO_SUN build. (fmax, not ||: LLVM turns a
     * float || into a 'freeze' that Oclgrind cannot run.) */
    if (fmax(fmax(L->sun.r, L->sun.g), L->sun.b) > 0.0f) {
        /* Cosine between propagation directions: dot(-l, -w) = dot(l, w). */
        vf mu = L->dir.x * VLOAD(S->wx) + L->dir.y * VLOAD(S->wy) + L->dir.z * VLOAD(S->wz);
        VSTORE(select(VLOAD(S->f), pt_phase_eval_v(mu, L->lobe_g, L->lobe_w), e), S->f);
        VSTORE(select(VLOAD(S->T), (vf)(1.0f), e), S->T);
        VSTORE(select(VLOAD(S->mode), (vi)(PT_SHADOW), e), S->mode);
#ifdef PT_ENVMAP
        VSTORE(select(VLOAD(S->lx), (vf)(L->dir.x), e), S->lx);
        VSTORE(select(VLOAD(S->ly), (vf)(L->dir.y), e), S->ly);
        VSTORE(select(VLOAD(S->lz), (vf)(L->dir.z), e), S->lz);
        VSTORE(select(VLOAD(S->envnee), (vi)(0), e), S->envnee);
#endif
        h = select(h, (vi)(H_RAY), e);
    }
#endif
    return h;
}

#ifdef PT_ORDER_BINS
/* The sun NEE's first channel v at the lanes of mask into the path's order bins: the bin of
 * exponent k - 1, and its weighted sum. */
__attribute__((always_inline))
void pt_add_order_bins(const pt_lanes *S, vi mask, const pt_job *J, vf v) {
    int on[PT_LANES];
    float val[PT_LANES];
    VSTORE(mask, on);
    VSTORE(v, val);
    for (int j = 0; j < PT_LANES; ++j) {
        if (!on[j]) continue;
        int ex = S->k[j] - 1, b = pt_order_bin(ex);
        __global float *o = J->out + PT_ROW * (size_t)S->path[j] + PT_OUT;
        o[b] += val[j];
        o[PT_ORDER_BINS + b] += val[j] * (float)ex;
    }
}
#endif

#ifdef PT_ENVMAP
/* H_NEE_DONE of the env NEE's shadow ray: add beta L f w_env / p_env T as order k, then
 * continue; returns h, and takes those lanes out of e. */
__attribute__((always_inline))
vi pt_env_nee_done(pt_lanes *S, vi h, vi *e_) {
    vi e = *e_;
    vi en = e & (VLOAD(S->envnee) != 0);
    if (any(en)) {
        vf br, bg, bb;
        pt_beta_v(S, &br, &bg, &bb);
        vf T = VLOAD(S->T);
        pt_add_v(S, en, VLOAD(S->k), VLOAD(S->ec[0]) * br * T,
                 VLOAD(S->ec[1]) * bg * T, VLOAD(S->ec[2]) * bb * T);
        VSTORE(select(VLOAD(S->envnee), (vi)(0), en), S->envnee);
        h = select(h, (vi)(H_CONTINUE), en);
        e &= ~en;
    }
    *e_ = e;
    return h;
}
#endif

/* H_NEE_DONE: a shadow ray is done with transmittance S.T: the env NEE's (PT_ENVMAP) or
 * the sun's, whose f T beta sun is added as order k. */
__attribute__((always_inline))
vi pt_on_nee_done(pt_lanes *S, vi h, const pt_light *L, const pt_job *J) {
    vi e = h == H_NEE_DONE;
#ifdef PT_ENVMAP
    h = pt_env_nee_done(S, h, &e);
#endif
    if (!any(e)) return h;
    vf s = VLOAD(S->f) * VLOAD(S->T);
#ifdef PT_TEST_BIAS
    s *= PT_TEST_BIAS;
#endif
    vf br, bg, bb;
    pt_beta_v(S, &br, &bg, &bb);
    pt_add_v(S, e, VLOAD(S->k), L->sun.r * br * s, L->sun.g * bg * s, L->sun.b * bb * s);
#ifdef PT_ORDER_BINS
    pt_add_order_bins(S, e & (VLOAD(S->k) >= 2), J, L->sun.r * br * s);
#endif
#ifdef PT_ENVMAP
    h = select(h, (vi)(H_ENV_NEE), e);
#else
    h = select(h, (vi)(H_CONTINUE), e);
#endif
    return h;
}

#ifdef PT_ENVMAP
/* H_ENV_NEE: sample a direction from the map and start its shadow ray (weights f w_env /
 * p_env into S.ec); lanes with nothing to sample continue. */
__attribute__((always_inline))
vi pt_on_env_nee(pt_lanes *S, vi h, const pt_light *L, const pt_job *J, uint2 key) {
    vi e = h == H_ENV_NEE;
    if (!any(e)) return h;
    pt_lanes_refill(S, e, key);   /* 2 draws: row, column */
    vf u0 = pt_lanes_take(S, e);
    vf u1 = pt_lanes_take(S, e);
    float a0[PT_LANES], a1[PT_LANES], dx[PT_LANES], dy[PT_LANES], dz[PT_LANES];
    float lr[PT_LANES], lg[PT_LANES], lb[PT_LANES], lp[PT_LANES];
    int on[PT_LANES];
    VSTORE(e, on); VSTORE(u0, a0); VSTORE(u1, a1);
    for (int j = 0; j < PT_LANES; ++j) {
        dx[j] = dy[j] = 0.0f; dz[j] = 1.0f;
        lr[j] = lg[j] = lb[j] = lp[j] = 0.0f;
        if (!on[j]) continue;
        float3 d;
        float4 t = pt_env_sample(L, a0[j], a1[j], &d);
        dx[j] = d.x; dy[j] = d.y; dz[j] = d.z;
        lr[j] = t.x; lg[j] = t.y; lb[j] = t.z; lp[j] = t.w;
    }
    vf ddx = VLOAD(dx), ddy = VLOAD(dy), ddz = VLOAD(dz), pe = VLOAD(lp);
    /* Cosine between propagation directions: dot(-d, -w) = dot(d, w). */
    vf mu = ddx * VLOAD(S->wx) + ddy * VLOAD(S->wy) + ddz * VLOAD(S->wz);
    vf f = pt_phase_eval_v(mu, L->lobe_g, L->lobe_w);
#ifdef PT_SINGLE_ONLY
    vi last = e;
#else
    vi last = VLOAD(S->k) == J->max_order;
#endif
    /* f w_env / p_env: f / p_env at the last vertex, else f p_env / (p_env^2 + f^2);
     * p_env > 0 for a drawn texel (pt_cdf_find), guarded all the same. */
    vf s = select(f * pe / (pe * pe + f * f), f / pe, last);
    vi go = e & (pe > 0.0f);
    s = select((vf)(0.0f), s, go);
    VSTORE(select(VLOAD(S->ec[0]), VLOAD(lr) * s, e), S->ec[0]);
    VSTORE(select(VLOAD(S->ec[1]), VLOAD(lg) * s, e), S->ec[1]);
    VSTORE(select(VLOAD(S->ec[2]), VLOAD(lb) * s, e), S->ec[2]);
    VSTORE(select(VLOAD(S->lx), ddx, go), S->lx);
    VSTORE(select(VLOAD(S->ly), ddy, go), S->ly);
    VSTORE(select(VLOAD(S->lz), ddz, go), S->lz);
    VSTORE(select(VLOAD(S->T), (vf)(1.0f), go), S->T);
    VSTORE(select(VLOAD(S->mode), (vi)(PT_SHADOW), go), S->mode);
    VSTORE(select(VLOAD(S->envnee), (vi)(1), go), S->envnee);
    h = select(h, (vi)(H_RAY), go);
    h = select(h, (vi)(H_CONTINUE), e & ~go);
    return h;
}
#endif

/* H_CONTINUE: the order cap, Russian roulette, then a phase-sampled direction for the
 * next flight. */
__attribute__((always_inline))
vi pt_on_continue(pt_lanes *S, vi h, const pt_light *L, const pt_job *J, uint2 key) {
    vi e = h == H_CONTINUE;
    if (!any(e)) return h;
#ifdef PT_SINGLE_ONLY
    h = select(h, (vi)(H_FINISH), e);
#else
    vi k = VLOAD(S->k);
    vi stop = e & (k == J->max_order);
    VSTORE(select(VLOAD(S->truncated), (vi)(1), e & ~stop & (k >= PT_MAX_VERTICES)),
           S->truncated);
    stop |= e & (k >= PT_MAX_VERTICES);
    e &= ~stop;
    pt_lanes_refill(S, e, key);   /* roulette + 3 for the direction: <= 4 draws */
    vi rr = e & (k >= PT_RR_START);
    if (any(rr)) {
        vf br, bg, bb;
        pt_beta_v(S, &br, &bg, &bb);
        vf q = fmin((vf)(1.0f), fmax(fmax(br, bg), bb));
        vi die = rr & (pt_lanes_take(S, rr) >= q);
        stop |= die;
        e &= ~die;
        rr &= ~die;
        pt_set_beta_v(S, rr, br / q, bg / q, bb / q);
    }
    h = select(h, (vi)(H_FINISH), stop);
    if (any(e)) {
        vf u0 = pt_lanes_take(S, e);   /* in this order */
        vf u1 = pt_lanes_take(S, e);
        vf u2 = pt_lanes_take(S, e);
        vf wx = VLOAD(S->wx), wy = VLOAD(S->wy), wz = VLOAD(S->wz);
        vf nx = wx, ny = wy, nz = wz;
        pt_phase_sample_v(&nx, &ny, &nz, L->lobe_g, L->lobe_w, u0, u1, u2);
#ifdef PT_ENVMAP
        VSTORE(select(VLOAD(S->pf), pt_phase_eval_v(wx * nx + wy * ny + wz * nz,
                                                    L->lobe_g, L->lobe_w), e), S->pf);
#endif
        VSTORE(select(wx, nx, e), S->wx);
        VSTORE(select(wy, ny, e), S->wy);
        VSTORE(select(wz, nz, e), S->wz);
        VSTORE(select(VLOAD(S->mode), (vi)(PT_FLIGHT), e), S->mode);
        h = select(h, (vi)(H_RAY), e);
    }
#endif
    return h;
}

/* H_RAY: start the ray of S.mode from S.o; lanes whose ray misses the box go on to their
 * next step at once. */
__attribute__((always_inline))
vi pt_on_ray(pt_lanes *S, vi h, const pt_medium *m, const pt_light *L, uint2 key) {
    vi e = h == H_RAY;
    if (!any(e)) return h;
    vi miss = pt_rays_v(S, e, m, L, key);
    /* A shadow ray that misses: T = 1 (set at the vertex); a flight: escape. */
    vi shadow = VLOAD(S->mode) == PT_SHADOW;
    h = select(h, (vi)(H_NONE), e);
    h = select(h, select((vi)(H_ESCAPE), (vi)(H_NEE_DONE), shadow), miss);
    return h;
}

/* Run every lane with a pending step to its next ray (or to PT_IDLE when the launch has
 * no paths left), all lanes together, one step kind after the other. A lane's steps (and
 * its draws) still come in its own path's order. */
__attribute__((always_inline))
void pt_events(pt_lanes *S, vi h, const pt_medium *m, const pt_light *L, const pt_job *J,
               uint2 key) {
    for (;;) {
        h = pt_on_accept(S, h, m, L);
        h = pt_on_escape(S, h, L);
        h = pt_on_finish(S, h, J);
        h = pt_on_start(S, h, J, key);
        h = pt_on_vertex(S, h, L);
        h = pt_on_nee_done(S, h, L, J);
#ifdef PT_ENVMAP
        h = pt_on_env_nee(S, h, L, J, key);
#endif
        h = pt_on_continue(S, h, L, J, key);
        h = pt_on_ray(S, h, m, L, key);
        if (!any(h != H_NONE)) return;
    }
}

#ifndef PT_BATCH
#define PT_BATCH (PT_LANES / 2)
#endif

/* Number of lanes set in mask. (A sum over an array: Oclgrind's uninitialised-value
 * checker crashes on the .lo / .hi halving of a vector.) */
__attribute__((always_inline))
int pt_count(vi mask) {
    int a[PT_LANES], n = 0;
    VSTORE(mask, a);
    for (int j = 0; j < PT_LANES; ++j) n -= a[j];
    return n;
}

/* The tentative collisions of the lanes of hit at t + tau / sm (sm their majorant, tb the
 * end of their cell): a flight's is real with probability sigma / sm (H_ACCEPT), a shadow
 * ray's ratio T takes 1 - sigma / sm (roulette below PT_T_RR); lanes that go on draw their
 * next tau. Moves t and tau; returns ev with those lanes' next steps, H_FINISH at a bound. */
__attribute__((always_inline))
vi pt_collide_v(pt_lanes *S, vi hit, vi mode, vf sm, vf tb, float stall_len, vf *t_, vf *tau_,
                vi ev, const pt_medium *m, const pt_light *L, uint2 key) {
    vf t = *t_, tau = *tau_;
    /* tau / sm <= tb - t, so the hit stays inside the segment (clamped for rounding). */
    vf th = fmin(t + tau / sm, tb);
    /* this collision moved t by less than a stall (or not at all; NaN counts) */
    vi stuck = hit & ~(th - t >= stall_len);
    t = select(t, th, hit);
    vi steps = VLOAD(S->steps) - hit;
    VSTORE(steps, S->steps);
    vi stall = select(select((vi)(0), VLOAD(S->stall) + 1, stuck), VLOAD(S->stall), ~hit);
    VSTORE(stall, S->stall);
    vi bound = hit & ((steps >= PT_MAX_STEPS) | (stall >= PT_MAX_STALLS));
    vi shadow = mode == PT_SHADOW;
#ifdef PT_ENVMAP
    vf dx = select(VLOAD(S->wx), VLOAD(S->lx), shadow);
    vf dy = select(VLOAD(S->wy), VLOAD(S->ly), shadow);
    vf dz = select(VLOAD(S->wz), VLOAD(S->lz), shadow);
#else
    vf dx = select(VLOAD(S->wx), (vf)(L->dir.x), shadow);
    vf dy = select(VLOAD(S->wy), (vf)(L->dir.y), shadow);
    vf dz = select(VLOAD(S->wz), (vf)(L->dir.z), shadow);
#endif
    pt_lanes_refill(S, hit, key);   /* accept or roulette, then tau: <= 2 draws */
    vf sigma = pt_sigma_lanes(m, VLOAD(S->ox) + th * dx, VLOAD(S->oy) + th * dy,
                              VLOAD(S->oz) + th * dz, hit);
    vi fl = hit & ~shadow, sh = hit & shadow;
    vi accept = (vi)(0), kill = (vi)(0);
    if (any(fl)) {
        /* Real with probability sigma / sigma_maj (u * sm < sigma: no division). */
        accept = fl & (pt_lanes_take(S, fl) * sm < sigma);
    }
    if (any(sh)) {
        /* sm > 0 at a tentative collision; rounding can put sigma a hair above sm. */
        vf T = VLOAD(S->T);
        T = select(T, T * fmax((vf)(0.0f), 1.0f - sigma / sm), sh);
        vi low = sh & (T < PT_T_RR);
        if (any(low)) {
            /* Roulette: T survives with probability T / PT_T_RR, then is PT_T_RR. */
            kill = low & (pt_lanes_take(S, low) * PT_T_RR >= T);
            T = select(T, (vf)(PT_T_RR), low);
            T = select(T, (vf)(0.0f), kill);
        }
        VSTORE(T, S->T);
    }
    vi more = hit & ~accept & ~kill;
    if (any(more)) tau = select(tau, -log(1.0f - pt_lanes_take(S, more)), more);
    ev = select(ev, (vi)(H_ACCEPT), accept);
    ev = select(ev, (vi)(H_NEE_DONE), kill);
    if (any(bound)) {
        /* A bound: the path ends here with what it has (row's truncated word 2). */
        ev = select(ev, (vi)(H_FINISH), bound);
        VSTORE(select(VLOAD(S->truncated), (vi)(2), bound), S->truncated);
    }
    *t_ = t;
    *tau_ = tau;
    return ev;
}

/* The one tracking loop (images and point queries). */
__attribute__((always_inline))
void pt_run(const pt_medium *m, const pt_light *L, const pt_job *J) {
    pt_lanes S;
    {   /* zero every lane's state word by word (all lanes are loaded from the start) */
        __private int *w = (__private int *)&S;
        for (uint i = 0; i < sizeof(pt_lanes) / sizeof(int); ++i) w[i] = 0;
    }
    uint2 key = (uint2)((uint)J->seed, (uint)(J->seed >> 32));
    const int mx = m->mx, my = m->my, mz = m->mz;
    const float scale = m->scale;
    const float stall_len = PT_STALL_FRACTION * fmin(fmin(m->bsize.x, m->bsize.y), m->bsize.z);
    VSTORE((vi)(H_START), S.pend);
#ifdef PT_STATS
    uint n_it = 0, n_act = 0, n_ev = 0, n_cross = 0;
#endif
    for (;;) {
        /* Lanes between rays wait until PT_BATCH of them do (or nothing else tracks), so
         * the event code runs for several lanes at once. */
        vi pend = VLOAD(S.pend);
        vi waiting = pend != H_NONE;
        vi tracking = (VLOAD(S.mode) != PT_IDLE) & ~waiting;
        /* Bitwise, not && / ||: LLVM turns those into a 'freeze' that Oclgrind cannot run. */
        if (any(waiting) & (!any(tracking) | (pt_count(waiting) >= PT_BATCH))) {
#ifdef PT_STATS
            n_ev += 1;
#endif
            pt_events(&S, pend, m, L, J, key);
            pend = (vi)(H_NONE);
            VSTORE(pend, S.pend);
        }
        vi mode = VLOAD(S.mode);
        vi act = (mode != PT_IDLE) & (pend == H_NONE);
        if (!any(act)) {
            if (any(pend != H_NONE)) continue;
            break;
        }
        vf t = VLOAD(S.t), te = VLOAD(S.te), tau = VLOAD(S.tau);
        vf tnx = VLOAD(S.tnx), tny = VLOAD(S.tny), tnz = VLOAD(S.tnz);
        vi cx = VLOAD(S.cx), cy = VLOAD(S.cy), cz = VLOAD(S.cz);
        /* maj_dda_track of majorant.h: every lane walks cells (cheap) until its next
         * tentative collision or the box exit; then the collisions are processed together. */
        vi ev = (vi)(0), hit = (vi)(0), todo = act;
        vf sm = (vf)(0.0f), tb;
        for (;;) {
            tb = fmin(fmin(fmin(tnx, tny), tnz), te);
            vf s = VGATHER(m->maj, select((vi)(0), (cz * my + cy) * mx + cx, todo)) * scale;
            vf dtau = s * (tb - t);
            vi h = todo & (s > 0.0f) & (dtau >= tau);
            hit |= h;
            sm = select(sm, s, h);
            vi cross = todo & ~h;
#ifdef PT_STATS
            n_cross += 1;
#endif
            if (!any(cross)) break;
            /* maj_dda_step: leave at t_end, else advance the axis whose boundary is first. */
            tau = select(tau, tau - dtau, cross);
            t = select(t, tb, cross);
            vi mv = cross & (tb < te);
            vi ax = (tnx <= tny) & (tnx <= tnz);
            vi ay = ~ax & (tny <= tnz);
            vi az = ~ax & ~ay;
            cx = select(cx, cx + VLOAD(S.sx), mv & ax);
            cy = select(cy, cy + VLOAD(S.sy), mv & ay);
            cz = select(cz, cz + VLOAD(S.sz), mv & az);
            tnx = select(tnx, tnx + VLOAD(S.tdx), mv & ax);
            tny = select(tny, tny + VLOAD(S.tdy), mv & ay);
            tnz = select(tnz, tnz + VLOAD(S.tdz), mv & az);
            vi inside = (cx >= 0) & (cx < mx) & (cy >= 0) & (cy < my) & (cz >= 0) & (cz < mz);
            vi out = cross & ~(mv & inside);
            ev = select(ev, select((vi)(H_ESCAPE), (vi)(H_NEE_DONE), mode == PT_SHADOW), out);
            todo = cross & ~out;
            if (!any(todo)) break;
        }
        VSTORE(cx, S.cx); VSTORE(cy, S.cy); VSTORE(cz, S.cz);
        VSTORE(tnx, S.tnx); VSTORE(tny, S.tny); VSTORE(tnz, S.tnz);
        if (any(hit))
            ev = pt_collide_v(&S, hit, mode, sm, tb, stall_len, &t, &tau, ev, m, L, key);
        VSTORE(t, S.t);
        VSTORE(tau, S.tau);
        VSTORE(select(pend, ev, act), S.pend);
#ifdef PT_STATS
        n_it += 1;
        n_act += pt_count(act);
#endif
    }
#ifdef PT_STATS
    atomic_add(J->next + 1, n_it); atomic_add(J->next + 2, n_act);
    atomic_add(J->next + 3, n_ev); atomic_add(J->next + 4, n_cross);
#endif
}

#define PT_MEDIUM_ARGS                                                                    \
    __global const float *density, __global const float *maj, const int nx, const int ny, \
        const int nz, const int mx, const int my, const int mz, const float4 bmin,       \
        const float4 bmax, const float4 bsize, const MediumBlock medium,                  \
        const LightBlock light, const float4 env PT_ENVMAP_ARGS PT_EMISSION_ARGS

#ifdef PT_ENVMAP
#define PT_ENVMAP_ARGS                                                                    \
    , __global const float *env_rgbl, __global const float *env_marg,                     \
        __global const float *env_cond, const int env_w, const int env_h,                 \
        const float env_rot, const float env_inv_total
#define PT_ENVMAP_SETUP                                                                   \
    L.env_rgbl = env_rgbl; L.env_marg = env_marg; L.env_cond = env_cond;                  \
    L.env_w = env_w; L.env_h = env_h; L.env_rot = env_rot; L.env_inv_total = env_inv_total;
#else
#define PT_ENVMAP_ARGS
#define PT_ENVMAP_SETUP
#endif

#ifdef PT_EMISSION
#define PT_EMISSION_ARGS                                                                  \
    , __global const float *em, const int emx, const int emy, const int emz,              \
        const float4 em_min, const float4 em_max, const float4 em_colour
#define PT_EMISSION_SETUP                                                                 \
    m.em = em; m.emx = emx; m.emy = emy; m.emz = emz;                                     \
    m.em_min = em_min.xyz; m.em_max = em_max.xyz; m.em_colour = em_colour.xyz;            \
    m.em_inv_cell = (float3)((float)emx, (float)emy, (float)emz) / (em_max.xyz - em_min.xyz);
#else
#define PT_EMISSION_ARGS
#define PT_EMISSION_SETUP
#endif

#define PT_SETUP                                                                          \
    pt_medium m;                                                                          \
    m.density = density; m.maj = maj;                                                     \
    m.nx = nx; m.ny = ny; m.nz = nz; m.mx = mx; m.my = my; m.mz = mz;                     \
    m.bmin = bmin.xyz; m.bmax = bmax.xyz; m.bsize = bsize.xyz;                            \
    m.scale = MEDIUM_DENSITY_SCALE_OF(medium);                                            \
    m.inv_cell = (float3)((float)nx, (float)ny, (float)nz) / (bmax.xyz - bmin.xyz);       \
    pt_light L;                                                                           \
    L.dir = LIGHT_DIRECTION_OF(light).xyz; L.sun = pt_rgb_of(LIGHT_IRRADIANCE_OF(light)); \
    L.env = pt_rgb_of(env);                                                               \
    L.albedo = SPEC_OF(MEDIUM_ALBEDO_OF(medium));                                         \
    L.lobe_g = MEDIUM_LOBE_G_OF(medium); L.lobe_w = MEDIUM_LOBE_W_OF(medium);             \
    PT_ENVMAP_SETUP                                                                       \
    PT_EMISSION_SETUP

/* Work-items share the launch's paths through *next (zero at launch); any number of
 * work-items gives the same rows. */
__kernel void pt_render(PT_MEDIUM_ARGS, const float4 cam_o, const float4 cam_f,
                        const float4 cam_r, const float4 cam_u, const float tan_half,
                        const int width, const int height, const ulong seed,
                        const uint sample0, const int spl, const int max_order,
                        __global float *out, __global volatile uint *next) {
    PT_SETUP
    pt_job J;
    J.is_query = 0; J.seed = seed; J.sample0 = sample0;
    J.nstream = width * height; J.n = J.nstream * spl; J.max_order = max_order;
    J.cam_o = cam_o.xyz; J.cam_f = cam_f.xyz; J.cam_r = cam_r.xyz; J.cam_u = cam_u.xyz;
    J.tan_half = tan_half; J.width = width; J.height = height;
    J.points = out; J.omegas = out;   /* unused */
    J.out = out; J.next = next;
    pt_run(&m, &L, &J);
}

__kernel void pt_query(PT_MEDIUM_ARGS, __global const float *points,
                       __global const float *omegas, const int nq, const ulong seed,
                       const uint sample0, const int ppl, const int max_order,
                       __global float *out, __global volatile uint *next) {
    PT_SETUP
    pt_job J;
    J.is_query = 1; J.seed = seed; J.sample0 = sample0;
    J.nstream = nq; J.n = nq * ppl; J.max_order = max_order;
    J.cam_o = J.cam_f = J.cam_r = J.cam_u = (float3)(0.0f);   /* unused */
    J.tan_half = 0.0f; J.width = J.height = 1;
    J.points = points; J.omegas = omegas;
    J.out = out; J.next = next;
    pt_run(&m, &L, &J);
}

#ifdef PT_ENVMAP
/* Tests only (tests/test_envmap.py): the map's sampler and lookup on given uniforms
 * u [n][2]; out [n][8] = direction xyz, pdf of the draw, RGB of the draw, pdf of
 * pt_env_lookup along the drawn direction. */
__kernel void pt_env_sample_test(__global const float *env_rgbl, __global const float *env_marg,
                                 __global const float *env_cond, const int env_w,
                                 const int env_h, const float env_rot, const float env_inv_total,
                                 __global const float *u, const int n, __global float *out) {
    int g = get_global_id(0);
    if (g >= n) return;
    pt_light L;
    PT_ENVMAP_SETUP
    float3 d;
    float4 t = pt_env_sample(&L, u[2 * g], u[2 * g + 1], &d);
    float4 b = pt_env_lookup(&L, d);
    __global float *o = out + 8 * (size_t)g;
    o[0] = d.x; o[1] = d.y; o[2] = d.z; o[3] = t.w;
    o[4] = t.x; o[5] = t.y; o[6] = t.z; o[7] = b.w;
}
#endif
