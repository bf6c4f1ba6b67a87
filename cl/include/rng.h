/* Counter-based random numbers: Philox4x32-10 (Salmon et al. 2011, "Random123").
 *
 * A draw is a pure function of (key, counter), so a kernel and its NumPy twin
 * (reference/rng.py) see identical streams, and a render is bit-identical for a seed.
 * clvol's convention for the 128-bit counter and 64-bit key:
 *   key     = (seed low 32 bits, seed high 32 bits)
 *   counter = (stream id low, stream id high, sample index, dimension block)
 * The stream is a pixel or a query point; each call gives 4 uniforms, so dimension
 * block d yields dimensions 4d..4d+3 of that sample.
 */
#ifndef CLVOL_RNG_H
#define CLVOL_RNG_H

#define PHILOX_M0 0xD2511F53u
#define PHILOX_M1 0xCD9E8D57u
#define PHILOX_W0 0x9E3779B9u
#define PHILOX_W1 0xBB67AE85u

__attribute__((always_inline))
uint4 philox4x32_round(uint4 c, uint2 k) {
    uint hi0 = mul_hi(PHILOX_M0, c.x), lo0 = PHILOX_M0 * c.x;
    uint hi1 = mul_hi(PHILOX_M1, c.z), lo1 = PHILOX_M1 * c.z;
    return (uint4)(hi1 ^ c.y ^ k.x, lo1, hi0 ^ c.w ^ k.y, lo0);
}

__attribute__((always_inline))
uint4 philox4x32_10(uint4 c, uint2 k) {
    for (int r = 0; r < 9; ++r) {
        c = philox4x32_round(c, k);
        k += (uint2)(PHILOX_W0, PHILOX_W1);
    }
    return philox4x32_round(c, k);
}

/* Top 24 bits -> float in [0, 1): exactly representable, never 1.0f. */
__attribute__((always_inline))
float4 u01x4(uint4 x) {
    return convert_float4(x >> 8) * (1.0f / 16777216.0f);
}

/* Four uniforms in [0, 1) for (seed, stream, sample, dimension block). */
__attribute__((always_inline))
float4 rng_uniform4(ulong seed, ulong stream, uint sample, uint block) {
    uint4 ctr = (uint4)((uint)stream, (uint)(stream >> 32), sample, block);
    uint2 key = (uint2)((uint)seed, (uint)(seed >> 32));
    return u01x4(philox4x32_10(ctr, key));
}

/* The same Philox on one counter per lane (structure of arrays: c0..c3 hold counter words
 * 0..3 of every lane), for kernels with explicit lanes: RNG_DEFINE_LANES(8) defines
 * philox4x32_10_x8 on uint8. Lane i gets exactly philox4x32_10 of its counter. */
#define RNG_DEFINE_LANES(W) RNG_DEFINE_LANES_(W)   /* expands W first (W may be a macro) */
#define RNG_DEFINE_LANES_(W)                                                                \
    __attribute__((always_inline)) void philox4x32_10_x##W(                                 \
        uint##W *c0, uint##W *c1, uint##W *c2, uint##W *c3, uint2 k) {                      \
        for (int r = 0; r < 10; ++r) {                                                      \
            uint##W hi0 = mul_hi((uint##W)(PHILOX_M0), *c0), lo0 = PHILOX_M0 * *c0;         \
            uint##W hi1 = mul_hi((uint##W)(PHILOX_M1), *c2), lo1 = PHILOX_M1 * *c2;         \
            *c0 = hi1 ^ *c1 ^ k.x;                                                          \
            *c1 = lo1;                                                                      \
            *c2 = hi0 ^ *c3 ^ k.y;                                                          \
            *c3 = lo0;                                                                      \
            k += (uint2)(PHILOX_W0, PHILOX_W1);                                             \
        }                                                                                   \
    }

#endif
