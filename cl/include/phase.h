/* Phase functions: isotropic, Henyey-Greenstein (HG) and multi-lobe HG (MHG).
 *
 * Convention (docs/conventions.md): the cosine is taken between *propagation* directions, so
 * g > 0 scatters forward. HG is normalised over the sphere:
 *     f(mu; g) = (1 - g^2) / (4 pi (1 + g^2 - 2 g mu)^(3/2)).
 * An MHG phase is sum_k w_k f(mu; g_k), weights summing to 1, passed as float4 lobe g's
 * and weights; PHASE_LOBES (1..3, a -D define) says how many are used, PHASE_ISOTROPIC
 * compiles the constant 1/(4 pi) path. Twin: reference/phase.py.
 *
 * Numerics: the HG denominator is written (1-|g|)^2 + 2|g|(1 - mu') with mu' = sign(g) mu,
 * which has no cancellation near the peak for |g| -> 1; sampling returns 1 - mu from a
 * product formula (derived from the inverse CDF) that needs no division by g and keeps
 * full relative precision in the forward peak (1 - mu ~ 5e-5 at g = 0.99).
 */
#ifndef CLVOL_PHASE_H
#define CLVOL_PHASE_H

#include "grid.h"

#ifndef PHASE_LOBES
#define PHASE_LOBES 3
#endif

/* HG and MHG evaluation are written once for any float type T (float here; the path tracer's
 * lanes, cl/pathtrace.cl, define a vector version with the same two macros), g and the
 * lobes being the same for every lane.
 *
 * HG_EVAL_T(NAME, T): T NAME(T mu, float g) = f(mu; g). f(mu; g) = f(-mu; -g): the
 * forward-peaked form is evaluated, with 1 - mu' for mu' = sign(g) mu. */
#define HG_EVAL_T(NAME, T)                                                          \
    __attribute__((always_inline)) T NAME(T mu, float g) {                          \
        T m = g < 0.0f ? -mu : mu;                                                  \
        float ga = fabs(g), a = 1.0f - ga;                                          \
        T denom = a * a + 2.0f * ga * (1.0f - m);                                   \
        return a * (1.0f + ga) * CLVOL_INV_4PI / (denom * sqrt(denom));             \
    }

/* PHASE_EVAL_T(NAME, T, HG): T NAME(T mu, float4 lobe_g, float4 lobe_w), the MHG sum of the
 * PHASE_LOBES lobes with HG(T mu, float g) (or 1 / (4 pi) with PHASE_ISOTROPIC). */
#if PHASE_LOBES >= 2
#define PHASE_LOBE_Y(s) s
#else
#define PHASE_LOBE_Y(s)
#endif
#if PHASE_LOBES >= 3
#define PHASE_LOBE_Z(s) s
#else
#define PHASE_LOBE_Z(s)
#endif
#ifdef PHASE_ISOTROPIC
#define PHASE_EVAL_T(NAME, T, HG)                                                   \
    __attribute__((always_inline)) T NAME(T mu, float4 lobe_g, float4 lobe_w) {     \
        return (T)(CLVOL_INV_4PI);                                                  \
    }
#else
#define PHASE_EVAL_T(NAME, T, HG)                                                   \
    __attribute__((always_inline)) T NAME(T mu, float4 lobe_g, float4 lobe_w) {     \
        T f = lobe_w.x * HG(mu, lobe_g.x);                                          \
        PHASE_LOBE_Y(f += lobe_w.y * HG(mu, lobe_g.y);)                             \
        PHASE_LOBE_Z(f += lobe_w.z * HG(mu, lobe_g.z);)                             \
        return f;                                                                   \
    }
#endif

HG_EVAL_T(hg_eval, float)
PHASE_EVAL_T(phase_eval, float, hg_eval)

/* Inverse-CDF sample of HG: returns 1 - mu for uniform u in [0, 1).
 * With a = 1 - g + 2 g u:  1 - mu = (1 - g)^2 (1 - u) (2 + 2 g u) / a^2.
 * (mu = -1 at u = 0, mu = 1 at u = 1, mu = 2u - 1 at g = 0.) */
__attribute__((always_inline))
float hg_sample_one_minus_mu(float g, float u) {
    float a = 1.0f - g + 2.0f * g * u;
    float omg = 1.0f - g;
    float r = omg * omg * (1.0f - u) * (2.0f + 2.0f * g * u) / (a * a);
    return clamp(r, 0.0f, 2.0f);
}

/* Orthonormal basis around unit n (Duff et al. 2017), no branch on a near-zero divisor. */
__attribute__((always_inline))
void onb(float3 n, float3 *b1, float3 *b2) {
    float sgn = n.z >= 0.0f ? 1.0f : -1.0f;
    float a = -1.0f / (sgn + n.z);
    float b = n.x * n.y * a;
    *b1 = (float3)(1.0f + sgn * n.x * n.x * a, sgn * b, -sgn * n.x);
    *b2 = (float3)(b, sgn + n.y * n.y * a, -n.y);
}

/* Direction at angle acos(1 - omm) from w, azimuth 2 pi u_phi. */
__attribute__((always_inline))
float3 direction_around(float3 w, float one_minus_mu, float u_phi) {
    float mu = 1.0f - one_minus_mu;
    float s = sqrt(fmax(0.0f, one_minus_mu * (2.0f - one_minus_mu)));
    float phi = 2.0f * CLVOL_PI * u_phi;
    float3 b1, b2;
    onb(w, &b1, &b2);
    return normalize(s * cos(phi) * b1 + s * sin(phi) * b2 + mu * w);
}

/* Sample a new propagation direction after scattering from propagation direction w.
 * u.x picks the lobe (by weight), u.y the polar angle, u.z the azimuth. The sample is
 * distributed exactly as phase_eval, so the path weight f / pdf is 1. */
__attribute__((always_inline))
float3 phase_sample(float3 w, float4 lobe_g, float4 lobe_w, float3 u) {
#ifdef PHASE_ISOTROPIC
    return direction_around(w, 2.0f * (1.0f - u.y), u.z);
#else
    float g = lobe_g.x;
#if PHASE_LOBES >= 2
    if (u.x >= lobe_w.x) g = lobe_g.y;
#endif
#if PHASE_LOBES >= 3
    if (u.x >= lobe_w.x + lobe_w.y) g = lobe_g.z;
#endif
    /* For g < 0 sample the mirrored lobe about -w. */
    float omm = hg_sample_one_minus_mu(fabs(g), u.y);
    return direction_around(g < 0.0f ? -w : w, omm, u.z);
#endif
}

#endif
