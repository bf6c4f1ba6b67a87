/* Test and utility kernels for cl/include/rng.h (Philox4x32-10).
 *
 * philox_raw:     out[i] = philox4x32_10(ctr[i], key)          (uint4 per item)
 * rng_uniforms:   out[i] = rng_uniform4(seed, stream0 + i, sample, block)  (float4 per item)
 * Twin: reference/rng.py.
 */
#include "rng.h"

/* ctr and out are n x 4 uints, accessed with vload4/vstore4 (no uint4 alignment needed;
 * Oclgrind also flagged the uint4-pointer form's store as uninitialised). */
__kernel void philox_raw(__global const uint *ctr, const uint key_lo, const uint key_hi,
                         const int n, __global uint *out) {
    int i = get_global_id(0);
    if (i >= n) return;
    vstore4(philox4x32_10(vload4(i, ctr), (uint2)(key_lo, key_hi)), i, out);
}

__kernel void rng_uniforms(const ulong seed, const ulong stream0, const uint sample,
                           const uint block, const int n, __global float4 *out) {
    int i = get_global_id(0);
    if (i >= n) return;
    out[i] = rng_uniform4(seed, stream0 + (ulong)i, sample, block);
}
