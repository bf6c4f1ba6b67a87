/* Ray marcher: exact single scattering plus a pluggable multiple-scattering source.
 *
 * One work-item marches LANES camera rays (a tile of 4 x LANES/4 pixels) as vector lanes
 * (cl/include/lanes.h, LANES = 16, 8 or 4 by device): the explicit vector style that makes ray marching fast on PoCL (docs/conventions.md, docs/raymarch.md).
 * Twin: reference/raymarch.py (the algorithm is described there in full).
 *
 * Pixel equation (docs/conventions.md; l toward the light, omega = -d toward the camera):
 *     L = int T_cam(t) sigma_s(x_t) E (F_1 + F_ms)(x_t, omega) dt + T_cam(exit) L_background
 * F_1 = f(dot(-l, omega)) T_light(x), with T_light the exact light transmittance field
 * (lambda = 1: seed eq. 1 at its finest level, built by cl/transmittance.cl), trilinear. The seed's
 * rendering step "bring the predicted F into the radiative transfer equation" is this march;
 * F_ms is the slot the network fills.
 *
 * Quadrature (energy-conserving, Hillaire 2016): segments [t0 + k dt, min(t0 + (k+1) dt, t1)]
 * of the ray's stretch in the box; sigma_t at the segment midpoint, F at the segment's mean
 * extinction point; each segment adds T_cam (1 - exp(-tau)) F (tau = sigma_t * length;
 * -expm1 for thin segments) and multiplies T_cam by exp(-tau). Colour enters once per ray
 * (albedo and E are constant over the medium).
 *
 * Specialisation (-D defines, decided from the scene by clvol/render/raymarch.py and the
 * multiple-scattering sources of clvol/render/ms/):
 *   PHASE_ISOTROPIC / PHASE_LOBES   phase.h: constant 1/(4 pi) or 1..3 HG lobes
 *   LIT 0|1          0 when albedo * E = 0: no light lookups, no F_1 and no F_ms
 *   MS_SOURCE 0|1|2|3  0 none; 1 Wrenninge octaves sum_{i=1}^{N-1} b^i f(mu; g c^i) T_light^(a^i);
 *                    2 trilinear lookup in a precomputed lattice of F_ms; 3 the view-space table
 *                    (F_ms at VIEW_K depths per block of VIEW_BLOCK^2 pixels, see below)
 *   MS_OCTAVES N     octaves of source 1 (N = 1: none beyond F_1); at most MS_MAX_OCTAVES (constants.h)
 *   MS_CHANNELS 1|3  planes of F_ms in the source-2 lattice or source-3 table (1 when albedo is
 *                    grey: F_ms is then grey)
 *   VIEW_K, VIEW_BLOCK  source 3: knots per block, block side in pixels
 *   SKIP_EMPTY 0|1   jump over majorant blocks whose majorant is 0 (exact: such a block and
 *                    half a voxel around it have density exactly 0; see majorant.h)
 *   LIGHT_TAU 0|1    the light field holds T_light (0, default) or its optical depth (1);
 *                    which one is read trilinearly changes the result (docs/raymarch.md)
 *   RAYMARCH_STATS 0|1  count work per tile into `stats` (benchmarks; off otherwise)
 *   ENV 0|1          environment in-scattering: 1 reads the environment source field `env`
 *                    (clvol/render/environment.py) at each segment's source point; absent
 *                    (0) the kernel is the one without an environment, bit for bit
 *   ENV_CHANNELS 1|3 planes per part of `env` (1: grey, coloured by env_colour once per ray)
 *   BG_IMAGE 0|1     the background is the per-pixel image `bg_image` (an environment map
 *                    seen along each camera ray) instead of the constant `background`
 *   EMISSION 0|1     emission (clvol/emission.py): each segment adds T_cam (1 - e^-tau)
 *                    (1 - albedo) Le(x_ts), the exact integral of T_cam sigma_a Le for an Le
 *                    constant (or linear) over the segment, sigma_a = sigma_t (1 - albedo)
 *                    (docs/conventions.md "Emission"). Into the `emission` layer and `total`.
 *                    Absent (0) the kernel is the one without emission, bit for bit
 *   EMISSION_CHANNELS 1|3  planes of `em` (1: grey, coloured by em_colour once per ray)
 *   EMISSION_BOX 0|1 1: `em` has a box of its own (em_min .. em_max), Le = 0 outside it;
 *                    0: it lies on the density's grid (no test needed, as for the density)
 *
 * Arguments (float4 holds a 3-vector in xyz; world units throughout):
 *   density    float [nz][ny][nx]     raw density over bmin..bmax; sigma_t = density * density_scale
 *   medium     MediumBlock (medium.h, 16 floats): density_scale, albedo (RGB), lobe_g, lobe_w
 *   majorant   float [mz][my][mx]     max density per block of `block`^3 voxels (majorant.h)
 *   light      float [ln][ln][ln]     the exact light transmittance field (lambda = 1) over the
 *                                     cube cube_min .. + cube_size: T_light, or with LIGHT_TAU
 *                                     its optical depth (T_light = exp(-tau))
 *   ms_lattice    float [C][gz][gy][gx]  F_ms (radiance per unit irradiance) over gmin..gmax;
 *              source 3: float [1 + C][by = gz][bx = gy][VIEW_K = gx], plane 0 the blocks'
 *              query distances along the camera rays (increasing; -1: empty block), planes
 *              1..C F_ms there (clvol/render/ms/view.py). A pixel's knots are the bilinear blend,
 *              knot by knot, of the four nearest non-empty blocks' knots (weights
 *              renormalised); F_ms along its ray is piecewise linear in t between its knots,
 *              constant beyond the first and last (gmin, gmax unused)
 *   origin, forward, right, up, tan_half, width, height    pinhole camera (grid.h camera_ray)
 *   sun        LightBlock (light.h, 16 floats): unit direction toward the light, irradiance E (RGB)
 *   background RGB radiance seen where rays leave the box (environment radiance, or 0)
 *   env        (last arguments, only with ENV; then bg_image, only with BG_IMAGE)
 *              float [2 C][en][en][en]: the
 *              environment's in-scattered radiance per unit extinction over the cube
 *              env_min .. + env_size (voxel centres), planes 0..C-1 single scattering
 *              (albedo, phase and transmittance toward the sky directions folded in),
 *              planes C..2C-1 the multiple-scattering approximation; C = ENV_CHANNELS.
 *              With C = 3 the device layout is float [en][en][en][8]: the six planes of a
 *              voxel side by side, then two unused (lookupL_env6). The pixel gets env_colour (RGB) times their march integrals: into `single`
 *              and `multiple` respectively
 *   bg_image   float [height][width][3] with BG_IMAGE: background radiance per pixel
 *   em         (after those, only with EMISSION) float [C][ez][ey][ex], C = EMISSION_CHANNELS,
 *              over em_min .. em_max (voxel centres, trilinear, clamped); Le = em_colour (RGB)
 *              times the planes; emission_out float [height][width][3] out
 *   oct_a, oct_b, oct_c  Wrenninge extinction, contribution and eccentricity multipliers
 *   step       segment length; threshold: a ray stops once T_cam < threshold (the light it
 *              misses is < threshold * its largest source radiance; reference/raymarch.py)
 *   total, single, multiple   float [height][width][3] out
 *   alpha, depth              float [height][width] out: 1 - T_cam(exit) and the mean
 *              distance of the first extinction event (0 where alpha = 0)
 *   stats      uint [1 + tiles * 4] (1 without RAYMARCH_STATS), word 0 zeroed by the host:
 *              stats[0] += the rays the progress bound stopped (atomic; the header's
 *              raymarch.rays_stopped_at_bound); with RAYMARCH_STATS, per tile from word 1:
 *              march iterations, light lookups, majorant reads (each on LANES lanes),
 *              and active lane-segments
 * Global size: ceil(width / 4) * ceil(height / (LANES / 4)) work-items (padded; guarded here).
 */
#include "grid.h"
#include "phase.h"
#include "medium.h"   /* the medium block */
#include "light.h"    /* the light block */

#ifndef LIT
#define LIT 1
#endif
/* MS_SOURCE selects code inside the one march rather than separate kernels: the sources
 * differ in the F_ms lookup at a segment's source point (and its set-up per ray), while the
 * march around it (quadrature, single scattering, skipping, environment, emission, outputs)
 * is the same for all; entry points per source would repeat that loop four times. */
#ifndef MS_SOURCE
#define MS_SOURCE 1
#endif
#ifndef MS_OCTAVES
#define MS_OCTAVES 3
#endif
#ifndef MS_CHANNELS
#define MS_CHANNELS 3
#endif
#if MS_SOURCE == 3 && (!defined(VIEW_K) || !defined(VIEW_BLOCK))
#error "MS_SOURCE 3 needs VIEW_K and VIEW_BLOCK (the view table's knots and block side)"
#endif
#ifndef SKIP_EMPTY
#define SKIP_EMPTY 1
#endif
#ifndef RAYMARCH_STATS
#define RAYMARCH_STATS 0
#endif
#ifndef LIGHT_TAU
#define LIGHT_TAU 0
#endif
#ifndef ENV
#define ENV 0
#endif
#ifndef ENV_CHANNELS
#define ENV_CHANNELS 1
#endif
#ifndef BG_IMAGE
#define BG_IMAGE 0
#endif
#if ENV_CHANNELS != 1 && ENV_CHANNELS != 3
#error "ENV_CHANNELS must be 1 or 3"
#endif
#ifndef EMISSION
#define EMISSION 0
#endif
#ifndef EMISSION_CHANNELS
#define EMISSION_CHANNELS 1
#endif
#ifndef EMISSION_BOX
#define EMISSION_BOX 0
#endif
#if EMISSION_CHANNELS != 1 && EMISSION_CHANNELS != 3
#error "EMISSION_CHANNELS must be 1 or 3"
#endif

#include "constants.h"   /* TILE, MS_MAX_OCTAVES */
#if MS_OCTAVES < 1 || MS_OCTAVES > MS_MAX_OCTAVES
#error "MS_OCTAVES must be 1..MS_MAX_OCTAVES"
#endif

#include "lanes.h"
#if TILE != 4
#error "the lane pattern of raymarch() (px, py) is written for tiles 4 pixels wide"
#endif
#define TILE_ROWS (LANES / TILE)   /* a tile is TILE x TILE_ROWS pixels, one per lane */
#ifndef SKIP_PASSES
#define SKIP_PASSES 4
#endif
/* Below this optical depth the mean-position fraction uses its series (the direct form
 * cancels); truncation error < tau^5/30240. */
#define H_SERIES_BELOW 0.05f

/* Row pairs (x0, x0 + 1) of LANES lanes as one 8-byte load each, through private arrays
 * (building the vectors from 32 scalars directly crashes Oclgrind 21.10's
 * uninitialised-value checker; this form costs PoCL ~5%). */
#define LANE_PAIRS(P, I, LO, HI)                                                         \
    {                                                                                    \
        int id_[LANES];                                                                  \
        float lo_[LANES], hi_[LANES];                                                    \
        vstoreL(I, 0, id_);                                                              \
        for (int j_ = 0; j_ < LANES; ++j_) {                                                \
            const float2 e_ = vload2(0, P + id_[j_]);                                    \
            lo_[j_] = e_.x;                                                              \
            hi_[j_] = e_.y;                                                              \
        }                                                                                \
        LO = vloadL(0, lo_);                                                             \
        HI = vloadL(0, hi_);                                                            \
    }

/* grid_lookup (grid.h) on LANES lanes: trilinear at continuous voxel coordinates, clamped.
 * Each row pair (x0, x0 + 1) is one 8-byte load: x0 is clamped to nx - 2 so that x0 + 1
 * stays in the row, and fx becomes 1 at the last voxel (mix(a, b, 1) = b, the same value
 * grid.h's clamped x1 gives). Grids one voxel wide (nx = 1) take the plain gathers. */
__attribute__((always_inline))
vL lookupL(__global const float *d, int nx, int ny, int nz, vL gx, vL gy, vL gz) {
    /* Clamping first makes the casts floors (non-negative); it also keeps every index in
     * range for any finite coordinate. */
    /* Scalar bounds are broadcast explicitly: Oclgrind 21.10 applies the scalar argument of
     * min(int16, int) to lane 0 only (an out-of-bounds read it then reported itself). */
    vL x = clamp(gx, (vL)(0.0f), (vL)((float)(nx - 1)));
    vL y = clamp(gy, (vL)(0.0f), (vL)((float)(ny - 1)));
    vL z = clamp(gz, (vL)(0.0f), (vL)((float)(nz - 1)));
    iL x0 = min(convert_iL(x), (iL)(max(nx - 2, 0)));
    iL y0 = convert_iL(y), z0 = convert_iL(z);
    iL y1 = min(y0 + 1, (iL)(ny - 1)), z1 = min(z0 + 1, (iL)(nz - 1));
    vL fx = x - convert_vL(x0), fy = y - convert_vL(y0), fz = z - convert_vL(z0);
    iL r00 = (z0 * ny + y0) * nx + x0, r01 = (z0 * ny + y1) * nx + x0;
    iL r10 = (z1 * ny + y0) * nx + x0, r11 = (z1 * ny + y1) * nx + x0;
    vL a00, b00, a01, b01, a10, b10, a11, b11;
    if (nx >= 2) {
        LANE_PAIRS(d, r00, a00, b00)
        LANE_PAIRS(d, r01, a01, b01)
        LANE_PAIRS(d, r10, a10, b10)
        LANE_PAIRS(d, r11, a11, b11)
    } else {
        a00 = b00 = gatherL(d, r00);
        a01 = b01 = gatherL(d, r01);
        a10 = b10 = gatherL(d, r10);
        a11 = b11 = gatherL(d, r11);
    }
    vL c00 = mix(a00, b00, fx), c01 = mix(a01, b01, fx);
    vL c10 = mix(a10, b10, fx), c11 = mix(a11, b11, fx);
    return mix(mix(c00, c01, fy), mix(c10, c11, fy), fz);
}

#if ENV && ENV_CHANNELS == 3
/* An RGB environment field's six planes (single R G B, multiple R G B) at LANES lanes, from
 * its device layout (clvol/kernels/raymarch.py env_device_layout): 8 floats per voxel, six
 * used. A voxel pair (x0, x0 + 1) is one 16-float load (at LANES 16; else 16 / LANES
 * loads), and the trilinear blend runs on float8, so the six planes cost four loads a lane where six lookupL calls cost 24 pair
 * loads. Coordinates, clamping and weights as lookupL (n >= 2: the field is >= 4^3). */
__attribute__((always_inline))
void lookupL_env6(__global const float *d, int n, vL gx, vL gy, vL gz, float out[6][LANES]) {
    const vL hi = (vL)((float)(n - 1));
    vL x = clamp(gx, (vL)(0.0f), hi), y = clamp(gy, (vL)(0.0f), hi);
    vL z = clamp(gz, (vL)(0.0f), hi);
    iL x0 = min(convert_iL(x), (iL)(n - 2));
    iL y0 = convert_iL(y), z0 = convert_iL(z);
    iL y1 = min(y0 + 1, (iL)(n - 1)), z1 = min(z0 + 1, (iL)(n - 1));
    float fx[LANES], fy[LANES], fz[LANES];
    int r00[LANES], r01[LANES], r10[LANES], r11[LANES];
    vstoreL(x - convert_vL(x0), 0, fx);
    vstoreL(y - convert_vL(y0), 0, fy);
    vstoreL(z - convert_vL(z0), 0, fz);
    vstoreL((z0 * n + y0) * n + x0, 0, r00);
    vstoreL((z0 * n + y1) * n + x0, 0, r01);
    vstoreL((z1 * n + y0) * n + x0, 0, r10);
    vstoreL((z1 * n + y1) * n + x0, 0, r11);
    for (int j = 0; j < LANES; ++j) {
#if LANES == 16
        const float16 p00 = vload16(0, d + 8 * r00[j]), p01 = vload16(0, d + 8 * r01[j]);
        const float16 p10 = vload16(0, d + 8 * r10[j]), p11 = vload16(0, d + 8 * r11[j]);
        const float8 c00 = mix(p00.lo, p00.hi, fx[j]), c01 = mix(p01.lo, p01.hi, fx[j]);
        const float8 c10 = mix(p10.lo, p10.hi, fx[j]), c11 = mix(p11.lo, p11.hi, fx[j]);
        const float8 v = mix(mix(c00, c01, fy[j]), mix(c10, c11, fy[j]), fz[j]);
        out[0][j] = v.s0; out[1][j] = v.s1; out[2][j] = v.s2;
        out[3][j] = v.s3; out[4][j] = v.s4; out[5][j] = v.s5;
#else
        /* The voxel's 8 floats in 8 / LANES pieces of vL (nothing wider in a call). */
        const int H = 8 / LANES;
        float v[8];
        for (int h = 0; h < H; ++h) {
            __global const float *q00 = d + 8 * r00[j], *q01 = d + 8 * r01[j];
            __global const float *q10 = d + 8 * r10[j], *q11 = d + 8 * r11[j];
            const vL c00 = mix(vloadL(h, q00), vloadL(h + H, q00), fx[j]);
            const vL c01 = mix(vloadL(h, q01), vloadL(h + H, q01), fx[j]);
            const vL c10 = mix(vloadL(h, q10), vloadL(h + H, q10), fx[j]);
            const vL c11 = mix(vloadL(h, q11), vloadL(h + H, q11), fx[j]);
            vstoreL(mix(mix(c00, c01, fy[j]), mix(c10, c11, fy[j]), fz[j]), h, v);
        }
        for (int p = 0; p < 6; ++p) out[p][j] = v[p];
#endif
    }
}
#endif

/* Parameter where the ray o + t d leaves the slab [lo, lo + size] of one axis in the
 * direction of travel; INFINITY for d = 0 (the ray never leaves it). */
__attribute__((always_inline))
vL slab_exitL(float o, vL d, vL lo, float size) {
    vL face = lo + select((vL)(0.0f), (vL)(size), d > 0.0f);
    return select((face - o) / d, (vL)(INFINITY), d == 0.0f);
}

__attribute__((always_inline))
void store_lanes(__global float *out, int channels, int ch, vL v, iL idx, iL valid) {
    float val[LANES];
    int id[LANES], ok[LANES];
    vstoreL(v, 0, val);
    vstoreL(idx, 0, id);
    vstoreL(valid, 0, ok);
    for (int j = 0; j < LANES; ++j)
        if (ok[j]) out[(size_t)id[j] * channels + ch] = val[j];
}

/* Planes of the F_ms sums: one for the octaves (grey), MS_CHANNELS for a lattice or table.
 * Sums of 1 or 3 planes give RGB as planes [0], [N / 2], [N - 1]: a grey plane serves all three. */
#if MS_SOURCE >= 2
#define MS_PLANES MS_CHANNELS
#else
#define MS_PLANES 1
#endif

/* A tile's running sums along its rays, one lane per ray. Colour enters after the march. */
typedef struct {
    vL T;                          /* T_cam */
    vL S;                          /* sum of w T_light: single scattering before f and colour */
    vL A, D;                       /* sum of w (alpha) and of w t_s (depth before / A) */
#if LIT && MS_SOURCE == 1 && MS_OCTAVES > 1
    vL Mo[MS_OCTAVES - 1];         /* one sum per octave; its phase weight comes after */
#endif
#if MS_SOURCE >= 1
    vL M[MS_PLANES];               /* F_ms, weighted */
#endif
#if ENV
    vL ES[ENV_CHANNELS], EM[ENV_CHANNELS];   /* the environment's single and multiple */
#endif
#if EMISSION
    vL EE[EMISSION_CHANNELS];      /* Le, weighted: (1 - albedo) and colour come after */
#endif
} MarchSums;

__attribute__((always_inline))
MarchSums march_sums_new(void) {
    MarchSums m;
    MarchSums *s = &m;
    s->T = (vL)(1.0f);
    s->S = s->A = s->D = (vL)(0.0f);
#if LIT && MS_SOURCE == 1 && MS_OCTAVES > 1
    for (int i = 0; i < MS_OCTAVES - 1; ++i) s->Mo[i] = (vL)(0.0f);
#endif
#if MS_SOURCE >= 1
    for (int c = 0; c < MS_PLANES; ++c) s->M[c] = (vL)(0.0f);
#endif
#if ENV
    for (int c = 0; c < ENV_CHANNELS; ++c) s->ES[c] = s->EM[c] = (vL)(0.0f);
#endif
#if EMISSION
    for (int c = 0; c < EMISSION_CHANNELS; ++c) s->EE[c] = (vL)(0.0f);
#endif
    return m;
}

/* A tile's camera rays o + t d, one a lane, from one origin. */
typedef struct {
    float ox, oy, oz;
    vL dx, dy, dz;
} TileRays;

/* Camera rays of the tile's lanes: camera_ray of grid.h, lane by lane. */
__attribute__((always_inline))
TileRays camera_raysL(iL px, iL py, int width, int height, float tan_half, float4 origin,
                      float4 forward, float4 right, float4 up) {
    const vL sx = (2.0f * (convert_vL(px) + 0.5f) / (float)width - 1.0f) * tan_half
                   * ((float)width / (float)height);
    const vL sy = (1.0f - 2.0f * (convert_vL(py) + 0.5f) / (float)height) * tan_half;
    vL x = forward.x + sx * right.x + sy * up.x;
    vL y = forward.y + sx * right.y + sy * up.y;
    vL z = forward.z + sx * right.z + sy * up.z;
    const vL len = sqrt(x * x + y * y + z * z);  /* >= 1: forward is orthogonal */
    const TileRays r = {origin.x, origin.y, origin.z, x / len, y / len, z / len};
    return r;
}

/* The lanes set in a mask, counted through private memory: a horizontal sum of the mask
 * (LANE_SUM) crashed Oclgrind's --uninitialized plugin (SIGSEGV; Oclgrind as Debian ships it). */
uint lanes_set(iL m) {
    int lane[LANES];
    vstoreL(m, 0, lane);
    uint n = 0;
    for (int i = 0; i < LANES; ++i) n += lane[i] != 0;
    return n;
}

/* Box entry and exit from t = 0 (box_intersect of grid.h, lane by lane); returns the lanes
 * that hit. Missed and invalid lanes get the empty interval [0, 0]: finite, never active. */
__attribute__((always_inline))
iL box_spanL(const TileRays *r, float4 bmin, float4 bmax, iL valid, vL *t0, vL *t1) {
    vL lo = (vL)(0.0f), hi = (vL)(INFINITY);
    iL miss = ~valid;
#define SLAB(D, O, MN, MX)                                                              \
    {                                                                                   \
        const iL zero = D == 0.0f;                                                     \
        miss |= zero & (iL)((O < MN || O > MX) ? -1 : 0);                              \
        const vL inv = 1.0f / D;                                                       \
        const vL ta = (MN - O) * inv, tb = (MX - O) * inv;                             \
        lo = select(fmax(lo, fmin(ta, tb)), lo, zero);                                  \
        hi = select(fmin(hi, fmax(ta, tb)), hi, zero);                                  \
    }
    SLAB(r->dx, r->ox, bmin.x, bmax.x)
    SLAB(r->dy, r->oy, bmin.y, bmax.y)
    SLAB(r->dz, r->oz, bmin.z, bmax.z)
#undef SLAB
    miss |= lo > hi;
    *t0 = select(lo, (vL)(0.0f), miss);
    *t1 = select(hi, (vL)(0.0f), miss);
    return ~miss;
}

/* The phase function per lane at mu = dot(-l, omega): omega is constant along a camera ray,
 * so it is evaluated once per ray, not per step. */
__attribute__((always_inline))
vL ray_phaseL(vL mu, float4 lobe_g, float4 lobe_w) {
    float m[LANES], f[LANES];
    vstoreL(mu, 0, m);
    for (int j = 0; j < LANES; ++j) f[j] = phase_eval(m[j], lobe_g, lobe_w);
    return vloadL(0, f);
}

#if LIT && MS_SOURCE == 1 && MS_OCTAVES > 1
/* Each octave's weight b^i f(mu; g c^i) per lane, once per ray. */
__attribute__((always_inline))
void octave_weights(vL mu, float4 lobe_g, float4 lobe_w, float oct_b, float oct_c,
                    float ow[MS_OCTAVES - 1][LANES]) {
    float m[LANES];
    vstoreL(mu, 0, m);
    float ci = 1.0f, bi = 1.0f;
    for (int i = 0; i < MS_OCTAVES - 1; ++i) {
        ci *= oct_c;
        bi *= oct_b;
        /* Component-wise: Oclgrind 21.10's uninitialised-value checker crashed on the
         * float4 * float form here. */
        const float4 gi = (float4)(lobe_g.x * ci, lobe_g.y * ci, lobe_g.z * ci, lobe_g.w * ci);
        for (int j = 0; j < LANES; ++j) ow[i][j] = bi * phase_eval(m[j], gi, lobe_w);
    }
}
#endif

#if MS_SOURCE == 3
/* A lane's knots of the view table: depth vd[k], F_ms v0 + sum of ramps dv[k] over
 * [vd[k], vd[k+1]] (the piecewise-linear interpolant as a sum of clamped ramps: no per-step
 * search). */
typedef struct {
    vL vd[VIEW_K], vinv[VIEW_K], v0[MS_CHANNELS], dv[MS_CHANNELS][VIEW_K];
} ViewKnots;

/* Each pixel's knots: the bilinear blend, knot by knot, of its four nearest non-empty
 * blocks' knots (weights renormalised; the kernel header gives the table's layout). */
__attribute__((always_inline))
void view_knotsL(__global const float *ms_lattice, int gx, int gy, int gz, iL px, iL py,
                 ViewKnots *kn) {
    const int plane = gx * gy * gz;
    float kd[VIEW_K][LANES], kv[MS_CHANNELS][VIEW_K][LANES];
    int pxs[LANES], pys[LANES];
    vstoreL(px, 0, pxs);
    vstoreL(py, 0, pys);
    for (int j = 0; j < LANES; ++j) {
        /* Bilinear between block centres (block i's centre is pixel position (i + 1/2) B). */
        const float u = clamp(((float)pxs[j] + 0.5f) / (float)VIEW_BLOCK - 0.5f, 0.0f, (float)(gy - 1));
        const float v = clamp(((float)pys[j] + 0.5f) / (float)VIEW_BLOCK - 0.5f, 0.0f, (float)(gz - 1));
        const int i0 = (int)u, j0 = (int)v;
        const int i1 = min(i0 + 1, gy - 1), j1 = min(j0 + 1, gz - 1);
        const float fu = u - (float)i0, fv = v - (float)j0;
        const int blk[4] = {j0 * gy + i0, j0 * gy + i1, j1 * gy + i0, j1 * gy + i1};
        float bw[4] = {(1.0f - fu) * (1.0f - fv), fu * (1.0f - fv), (1.0f - fu) * fv, fu * fv};
        float sum = 0.0f;
        for (int q = 0; q < 4; ++q) {
            if (ms_lattice[blk[q] * gx] < 0.0f) bw[q] = 0.0f;   /* empty block */
            sum += bw[q];
        }
        /* sum = 0 only where no neighbour saw medium: no knots, F_ms = 0 */
        const float inv = sum > 0.0f ? 1.0f / sum : 0.0f;
        for (int k = 0; k < VIEW_K; ++k) {
            float a = 0.0f;
            for (int q = 0; q < 4; ++q) a += bw[q] * inv * ms_lattice[blk[q] * gx + k];
            kd[k][j] = a;
            for (int c = 0; c < MS_CHANNELS; ++c) {
                float b = 0.0f;
                for (int q = 0; q < 4; ++q)
                    b += bw[q] * inv * ms_lattice[(1 + c) * plane + blk[q] * gx + k];
                kv[c][k][j] = b;
            }
        }
    }
    for (int k = 0; k < VIEW_K; ++k) kn->vd[k] = vloadL(0, kd[k]);
    for (int k = 0; k + 1 < VIEW_K; ++k)
        kn->vinv[k] = 1.0f / fmax(kn->vd[k + 1] - kn->vd[k], (vL)(1e-30f));
    for (int c = 0; c < MS_CHANNELS; ++c) {
        kn->v0[c] = vloadL(0, kv[c][0]);
        for (int k = 0; k + 1 < VIEW_K; ++k)
            kn->dv[c][k] = vloadL(0, kv[c][k + 1]) - vloadL(0, kv[c][k]);
    }
}
#endif

#if SKIP_EMPTY
/* Lanes whose segment midpoint lies in an empty majorant block jump to the block's exit; a
 * few passes let lanes cross several empty blocks before the next lookup. Moves k, ta and
 * active; returns the majorant reads (LANES lanes each). */
__attribute__((always_inline))
uint skip_empty_blocksL(__global const float *majorant, int mx, int my, int mz, float3 bsize,
                        float4 bmin, const TileRays *r, vL t0, vL t1, float step, vL *k,
                        vL *ta, iL *active) {
    uint reads = 0;
    for (int pass = 0; pass < SKIP_PASSES; ++pass) {
        /* Untruncated midpoint of the current segment (0 for idle lanes: stays finite). */
        const vL tq = select((vL)(0.0f), *ta + 0.5f * step, *active);
        const iL bx = convert_iL(clamp((r->ox + tq * r->dx - bmin.x) / bsize.x, (vL)(0.0f),
                                       (vL)((float)(mx - 1))));
        const iL by = convert_iL(clamp((r->oy + tq * r->dy - bmin.y) / bsize.y, (vL)(0.0f),
                                       (vL)((float)(my - 1))));
        const iL bz = convert_iL(clamp((r->oz + tq * r->dz - bmin.z) / bsize.z, (vL)(0.0f),
                                       (vL)((float)(mz - 1))));
        const iL empty = *active & (gatherL(majorant, (bz * my + by) * mx + bx) == 0.0f);
        ++reads;
        if (!any(empty)) break;
        const vL t_exit = fmin(fmin(
            slab_exitL(r->ox, r->dx, bmin.x + convert_vL(bx) * bsize.x, bsize.x),
            slab_exitL(r->oy, r->dy, bmin.y + convert_vL(by) * bsize.y, bsize.y)),
            slab_exitL(r->oz, r->dz, bmin.z + convert_vL(bz) * bsize.z, bsize.z));
        /* First segment whose untruncated midpoint is at or past the block's exit;
         * at least one segment of progress whatever the rounding. */
        const vL k_star = ceil((t_exit - t0) / step - 0.5f);
        *k = select(*k, fmax(*k + 1.0f, k_star), empty);
        *ta = t0 + *k * step;
        *active &= *ta < t1;
    }
    return reads;
}
#endif

/* One segment [ta, ta + len] of each lane: returns its optical depth tau (sigma_t at the
 * midpoint); e = e^-tau, w = T_cam (1 - e^-tau) its weight, ts where its source is read. */
__attribute__((always_inline))
vL segmentL(__global const float *density, int nx, int ny, int nz, float4 bmin, float3 cell,
            float density_scale, const TileRays *r, vL ta, vL len, vL T, vL *e, vL *w,
            vL *ts) {
    const vL tm = ta + 0.5f * len;
    const vL qx = r->ox + tm * r->dx, qy = r->oy + tm * r->dy, qz = r->oz + tm * r->dz;
    const vL tau = density_scale * lookupL(density, nx, ny, nz,
                                             (qx - bmin.x) / cell.x - 0.5f,
                                             (qy - bmin.y) / cell.y - 0.5f,
                                             (qz - bmin.z) / cell.z - 0.5f) * len;
    /* 1 - e^-tau without cancellation: its series below 0.1 (truncation < tau^4/120
     * relative), 1 - e^-tau above (rounding < 1.2e-7 / tau relative). Cheaper than
     * expm1, which PoCL evaluates 4x slower than exp on float16. */
    *e = exp(-tau);
    const vL a_seg = select(1.0f - *e,
                             tau * (1.0f - tau * (0.5f - tau * ((1.0f / 6.0f) - tau * (1.0f / 24.0f)))),
                             tau < 0.1f);
    *w = T * a_seg;
    /* Where in the segment the light is scattered toward the camera, on average: the
     * fraction frac = 1/tau - e^-tau / (1 - e^-tau) of its length (1/2 for thin segments,
     * ~1/tau for opaque ones). Reading the source there rather than at the midpoint makes
     * the segment integral exact for a source varying linearly along it; the density
     * stays the midpoint's. Series below H_SERIES_BELOW (the direct form cancels; its 0/0
     * at tau = 0 is never selected). */
    const vL frac = select(1.0f / tau - *e / a_seg,
                            0.5f - tau * (1.0f / 12.0f - tau * tau * (1.0f / 720.0f)),
                            tau < H_SERIES_BELOW);
    *ts = ta + frac * len;
    return tau;
}

#if LIT
/* Single scattering from the light field at the source point (T_light, or its optical depth
 * with LIGHT_TAU), and with source 1 the Wrenninge octaves from it. */
__attribute__((always_inline))
void add_sunL(MarchSums *s, vL w, vL rx, vL ry, vL rz, __global const float *light, int ln,
              float4 cube_min, float cube_size, float oct_a) {
    const float lcell = cube_size / (float)ln;
    /* Trilinear; -log T_light (>= 0; +inf where T underflowed to 0, and the octaves'
     * exp(-a^i inf) = 0 then, a > 0 being enforced). */
    const vL lf = lookupL(light, ln, ln, ln,
                          (rx - cube_min.x) / lcell - 0.5f,
                          (ry - cube_min.y) / lcell - 0.5f,
                          (rz - cube_min.z) / lcell - 0.5f);
#if LIGHT_TAU
    const vL t_l = exp(-lf);
#define TAU_L lf
#else
    const vL t_l = lf;
#define TAU_L (-log(lf))
#endif
    s->S += w * t_l;
#if MS_SOURCE == 1 && MS_OCTAVES > 1
    /* T_light^(a^i) = exp(-a^i tau_l). */
    const vL tau_l = TAU_L;
    float ai = 1.0f;
    for (int i = 0; i < MS_OCTAVES - 1; ++i) {
        ai *= oct_a;
        s->Mo[i] += w * exp(-ai * tau_l);
    }
#endif
#undef TAU_L
}
#endif

#if LIT && MS_SOURCE == 2
/* Source 2: F_ms trilinear in the precomputed lattice over gmin..gmax at the source point. */
__attribute__((always_inline))
void add_ms_latticeL(MarchSums *s, vL w, vL rx, vL ry, vL rz, __global const float *ms_lattice,
                  int gx, int gy, int gz, float4 gmin, float4 gmax) {
    const float3 gcell = (gmax.xyz - gmin.xyz) / (float3)((float)gx, (float)gy, (float)gz);
    const int plane = gx * gy * gz;
    const vL ux = (rx - gmin.x) / gcell.x - 0.5f;
    const vL uy = (ry - gmin.y) / gcell.y - 0.5f;
    const vL uz = (rz - gmin.z) / gcell.z - 0.5f;
    for (int c = 0; c < MS_CHANNELS; ++c)
        s->M[c] += w * lookupL(ms_lattice + c * plane, gx, gy, gz, ux, uy, uz);
}
#endif

#if LIT && MS_SOURCE == 3
/* Source 3: F_ms at depth ts along the lane's ray, piecewise linear between its knots. */
__attribute__((always_inline))
void add_ms_viewL(MarchSums *s, vL w, vL ts, const ViewKnots *kn) {
    vL ramp[VIEW_K];
    for (int k = 0; k + 1 < VIEW_K; ++k)
        ramp[k] = clamp((ts - kn->vd[k]) * kn->vinv[k], 0.0f, 1.0f);
    vL f[MS_CHANNELS];
    for (int c = 0; c < MS_CHANNELS; ++c) f[c] = kn->v0[c];
    for (int k = 0; k + 1 < VIEW_K; ++k)
        for (int c = 0; c < MS_CHANNELS; ++c) f[c] += kn->dv[c][k] * ramp[k];
    for (int c = 0; c < MS_CHANNELS; ++c) s->M[c] += w * f[c];
}
#endif

#if ENV
/* The environment's source field at the source point (sky light is constant over the
 * medium's colour, so it is a field of its own, not a light lookup). */
__attribute__((always_inline))
void add_environmentL(MarchSums *s, vL w, vL rx, vL ry, vL rz, __global const float *env,
                      int en, float4 env_min, float env_size) {
    const float ecell = env_size / (float)en;
    const vL ex = (rx - env_min.x) / ecell - 0.5f;
    const vL ey = (ry - env_min.y) / ecell - 0.5f;
    const vL ez = (rz - env_min.z) / ecell - 0.5f;
#if ENV_CHANNELS == 1
    s->ES[0] += w * lookupL(env, en, en, en, ex, ey, ez);
    s->EM[0] += w * lookupL(env + en * en * en, en, en, en, ex, ey, ez);
#else
    float e6[6][LANES];
    lookupL_env6(env, en, ex, ey, ez, e6);
    for (int c = 0; c < 3; ++c) {
        s->ES[c] += w * vloadL(0, e6[c]);
        s->EM[c] += w * vloadL(0, e6[3 + c]);
    }
#endif
}
#endif

#if EMISSION
/* Emission at the source point: T_cam (1 - e^-tau) Le(x_ts); Le = 0 outside its own box
 * (EMISSION_BOX). (1 - albedo) and the colour are applied once per ray. */
__attribute__((always_inline))
void add_emissionL(MarchSums *s, vL w, vL rx, vL ry, vL rz, __global const float *em,
                   int emx, int emy, int emz, float4 em_min, float4 em_max) {
    const float3 emcell = (em_max.xyz - em_min.xyz) / (float3)((float)emx, (float)emy, (float)emz);
    const int emplane = emx * emy * emz;
    const vL ux = (rx - em_min.x) / emcell.x - 0.5f;
    const vL uy = (ry - em_min.y) / emcell.y - 0.5f;
    const vL uz = (rz - em_min.z) / emcell.z - 0.5f;
#if EMISSION_BOX
    const iL in_em = (rx >= em_min.x) & (rx <= em_max.x) & (ry >= em_min.y) &
                      (ry <= em_max.y) & (rz >= em_min.z) & (rz <= em_max.z);
    const vL we = select((vL)(0.0f), w, in_em);
#else
    const vL we = w;
#endif
    for (int c = 0; c < EMISSION_CHANNELS; ++c)
        s->EE[c] += we * lookupL(em + c * emplane, emx, emy, emz, ux, uy, uz);
}
#endif

#if LIT && MS_SOURCE == 1 && MS_OCTAVES > 1
/* The octaves' sums into F_ms, each with its per-ray phase weight. */
__attribute__((always_inline))
void fold_octavesL(MarchSums *s, float ow[MS_OCTAVES - 1][LANES]) {
    for (int i = 0; i < MS_OCTAVES - 1; ++i) s->M[0] += vloadL(0, ow[i]) * s->Mo[i];
}
#endif

/* The sun's single and multiple layers (RGB) from the sums: colour once per ray. */
__attribute__((always_inline))
void sun_layersL(const MarchSums *s, vL f0, float4 albedo, float4 irradiance, vL sgl[3],
                 vL mul[3]) {
    const float3 ae = albedo.xyz * irradiance.xyz;
    for (int c = 0; c < 3; ++c) sgl[c] = mul[c] = (vL)(0.0f);
#if LIT
    sgl[0] = ae.x * (f0 * s->S); sgl[1] = ae.y * (f0 * s->S); sgl[2] = ae.z * (f0 * s->S);
#if MS_SOURCE >= 1
    mul[0] = ae.x * s->M[0]; mul[1] = ae.y * s->M[MS_PLANES / 2];
    mul[2] = ae.z * s->M[MS_PLANES - 1];
#endif
#endif
}

#if ENV
/* The environment's share of the single and multiple layers, coloured once per ray. */
__attribute__((always_inline))
void add_environment_layersL(const MarchSums *s, float4 env_colour, vL sgl[3], vL mul[3]) {
    sgl[0] += env_colour.x * s->ES[0]; sgl[1] += env_colour.y * s->ES[ENV_CHANNELS / 2];
    sgl[2] += env_colour.z * s->ES[ENV_CHANNELS - 1];
    mul[0] += env_colour.x * s->EM[0]; mul[1] += env_colour.y * s->EM[ENV_CHANNELS / 2];
    mul[2] += env_colour.z * s->EM[ENV_CHANNELS - 1];
}
#endif

__attribute__((always_inline))
void store_rgb(__global float *out, const vL v[3], iL pix, iL valid) {
    for (int c = 0; c < 3; ++c) store_lanes(out, 3, c, v[c], pix, valid);
}

/* A tile's layers into the images: total (with the background seen through T_cam), single,
 * multiple, alpha, depth, and with EMISSION the emission layer. Padding lanes are not stored. */
__attribute__((always_inline))
void store_tileL(const MarchSums *s, const vL sgl[3], const vL mul[3], iL pix, iL valid,
                 float4 background, float4 albedo, __global float *total,
                 __global float *single, __global float *multiple, __global float *alpha,
                 __global float *depth
#if BG_IMAGE
                 , __global const float *bg_image
#endif
#if EMISSION
                 , float4 em_colour, __global float *emission_out
#endif
                 ) {
    vL bg[3];
#if BG_IMAGE
    /* Padding lanes read pixel 0 (never stored). */
    const iL bgi = select((iL)(0), pix, valid) * 3;
    for (int c = 0; c < 3; ++c) bg[c] = gatherL(bg_image, bgi + c);
#else
    bg[0] = (vL)(background.x); bg[1] = (vL)(background.y); bg[2] = (vL)(background.z);
#endif
    store_rgb(single, sgl, pix, valid);
    store_rgb(multiple, mul, pix, valid);
    vL tot[3];
#if EMISSION
    /* sigma_a Le = sigma_t (1 - albedo) em_colour planes: colour once per ray. */
    const float3 ea = (float3)(1.0f) - albedo.xyz;
    const vL emi[3] = {(ea.x * em_colour.x) * s->EE[0],
                       (ea.y * em_colour.y) * s->EE[EMISSION_CHANNELS / 2],
                       (ea.z * em_colour.z) * s->EE[EMISSION_CHANNELS - 1]};
    store_rgb(emission_out, emi, pix, valid);
    for (int c = 0; c < 3; ++c) tot[c] = sgl[c] + mul[c] + emi[c] + s->T * bg[c];
#else
    for (int c = 0; c < 3; ++c) tot[c] = sgl[c] + mul[c] + s->T * bg[c];
#endif
    store_rgb(total, tot, pix, valid);
    store_lanes(alpha, 1, 0, s->A, pix, valid);
    store_lanes(depth, 1, 0, select((vL)(0.0f), s->D / s->A, s->A > 0.0f), pix, valid);
}

__kernel void raymarch(
    __global const float *density, const int nx, const int ny, const int nz,
    const float4 bmin, const float4 bmax, const MediumBlock medium,
    __global const float *majorant, const int mx, const int my, const int mz, const int block,
    __global const float *light, const int ln, const float4 cube_min, const float cube_size,
    __global const float *ms_lattice, const int gx, const int gy, const int gz,
    const float4 gmin, const float4 gmax,
    const float4 origin, const float4 forward, const float4 right, const float4 up,
    const float tan_half, const int width, const int height,
    const LightBlock sun, const float4 background,
    const float oct_a, const float oct_b, const float oct_c,
    const float step, const float threshold,
    __global float *total, __global float *single, __global float *multiple,
    __global float *alpha, __global float *depth, __global uint *stats
    /* Only with the environment's defines, last: without them the argument list is the one
     * hosts of scenes without an environment (the C host) pass. */
#if ENV
    , __global const float *env, const int en, const float4 env_min, const float env_size,
    const float4 env_colour
#endif
#if BG_IMAGE
    , __global const float *bg_image
#endif
#if EMISSION
    , __global const float *em, const int emx, const int emy, const int emz,
    const float4 em_min, const float4 em_max, const float4 em_colour,
    __global float *emission_out
#endif
    )
{
    const float4 albedo = MEDIUM_ALBEDO_OF(medium);
    const int tiles_x = (width + TILE - 1) / TILE;
    const int tile = get_global_id(0);
    if (tile >= tiles_x * ((height + TILE_ROWS - 1) / TILE_ROWS)) return;
    const int ty = tile / tiles_x, tx = tile - ty * tiles_x;
    const iL px = tx * TILE + (LANE_IOTA & (iL)(TILE - 1));     /* lane = row * TILE + column */
    const iL py = ty * TILE_ROWS + (LANE_IOTA >> (iL)(2));
    const iL valid = (px < width) & (py < height);

    const TileRays rays = camera_raysL(px, py, width, height, tan_half, origin, forward, right,
                                       up);
    vL t0, t1;
    const iL hit = box_spanL(&rays, bmin, bmax, valid, &t0, &t1);

    /* dot(-l, omega) */
    const float4 light_dir = LIGHT_DIRECTION_OF(sun);
    const vL mu = rays.dx * light_dir.x + rays.dy * light_dir.y + rays.dz * light_dir.z;
    const vL f0 = ray_phaseL(mu, MEDIUM_LOBE_G_OF(medium), MEDIUM_LOBE_W_OF(medium));
#if LIT && MS_SOURCE == 1 && MS_OCTAVES > 1
    float ow[MS_OCTAVES - 1][LANES];
    octave_weights(mu, MEDIUM_LOBE_G_OF(medium), MEDIUM_LOBE_W_OF(medium), oct_b, oct_c, ow);
#endif
#if MS_SOURCE == 3
    ViewKnots knots;
    view_knotsL(ms_lattice, gx, gy, gz, px, py, &knots);
#endif
    const float3 cell = (bmax.xyz - bmin.xyz) / (float3)((float)nx, (float)ny, (float)nz);

    vL k = (vL)(0.0f);
    MarchSums s = march_sums_new();
#if RAYMARCH_STATS
    uint n_iter = 0, n_lit = 0, n_maj = 0, n_active = 0;
#endif
    uint n_stopped = 0;     /* lanes the progress bound stopped */
    for (;;) {
        vL ta = t0 + k * step;
        /* Bounded: a lane stops where its next segment would not start past this one (k past
         * 2^24, or step below t's float32 rounding: a camera far from a small box); nowhere
         * else does this hold, so it changes no image that can be marched. A lane it stops
         * keeps its k and T, so at the last pass it is still one that would go on but for
         * the bound: those lanes are counted into stats[0] (the header's
         * raymarch.rays_stopped_at_bound). */
        const iL go = hit & (ta < t1) & (s.T >= threshold);
        const iL progress = t0 + (k + 1.0f) * step > ta;
        iL active = go & progress;
        if (!any(active)) {
            n_stopped = lanes_set(go & ~progress);
            break;
        }
#if SKIP_EMPTY
        const uint reads = skip_empty_blocksL(majorant, mx, my, mz, cell * (float)block, bmin,
                                              &rays, t0, t1, step, &k, &ta, &active);
#endif
#if RAYMARCH_STATS
        ++n_iter;
#if SKIP_EMPTY
        n_maj += reads;
#endif
        n_active += (uint)LANE_SUM(active & (iL)(1));
#endif
        const vL len = select((vL)(0.0f), fmin(ta + step, t1) - ta, active);
        ta = select((vL)(0.0f), ta, active);
        vL e, w, ts;
        const vL tau = segmentL(density, nx, ny, nz, bmin, cell, MEDIUM_DENSITY_SCALE_OF(medium),
                                &rays, ta, len, s.T, &e, &w, &ts);
        const vL rx = rays.ox + ts * rays.dx, ry = rays.oy + ts * rays.dy;
        const vL rz = rays.oz + ts * rays.dz;
        /* Segments where all lanes are empty add nothing: no source lookups. */
        if (any(tau > 0.0f)) {
#if LIT
#if RAYMARCH_STATS
            ++n_lit;
#endif
            add_sunL(&s, w, rx, ry, rz, light, ln, cube_min, cube_size, oct_a);
#if MS_SOURCE == 2
            add_ms_latticeL(&s, w, rx, ry, rz, ms_lattice, gx, gy, gz, gmin, gmax);
#elif MS_SOURCE == 3
            add_ms_viewL(&s, w, ts, &knots);
#endif
#endif
#if ENV
            add_environmentL(&s, w, rx, ry, rz, env, en, env_min, env_size);
#endif
#if EMISSION
            add_emissionL(&s, w, rx, ry, rz, em, emx, emy, emz, em_min, em_max);
#endif
        }
        s.A += w;
        /* Depth: the same mean position, t_a + frac * len, weighted by this segment's share
         * of the extinction (exact for a constant sigma_t over the segment). */
        s.D += w * ts;
        s.T *= e;
        k += select((vL)(0.0f), (vL)(1.0f), active);
    }

#if LIT && MS_SOURCE == 1 && MS_OCTAVES > 1
    fold_octavesL(&s, ow);
#endif
    vL sgl[3], mul[3];   /* single and multiple, RGB */
    sun_layersL(&s, f0, albedo, LIGHT_IRRADIANCE_OF(sun), sgl, mul);
#if ENV
    add_environment_layersL(&s, env_colour, sgl, mul);
#endif
    store_tileL(&s, sgl, mul, py * width + px, valid, background, albedo, total, single,
                multiple, alpha, depth
#if BG_IMAGE
                , bg_image
#endif
#if EMISSION
                , em_colour, emission_out
#endif
                );
    {
        if (n_stopped) atomic_add(stats, n_stopped);
    }
#if RAYMARCH_STATS
    /* Per tile: march iterations (each one density lookup on LANES lanes), iterations
     * with a light lookup, majorant reads (LANES lanes each) and active lane-segments. */
    vstore4((uint4)(n_iter, n_lit, n_maj, n_active), tile, stats + 1);
#endif
}
