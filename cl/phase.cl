/* Test and utility kernels for cl/include/phase.h.
 *
 * phase_eval_many:   out[i] = phase_eval(mu[i], lobe_g, lobe_w)
 * phase_sample_many: out[i] = phase_sample(w[i], lobe_g, lobe_w, u[i])   (float3 packed as 3 floats)
 * Define PHASE_LOBES (1..3) or PHASE_ISOTROPIC. Twin: reference/phase.py.
 */
#include "phase.h"

__kernel void phase_eval_many(__global const float *mu, const float4 lobe_g, const float4 lobe_w,
                              const int n, __global float *out) {
    int i = get_global_id(0);
    if (i >= n) return;
    out[i] = phase_eval(mu[i], lobe_g, lobe_w);
}

__kernel void phase_sample_many(__global const float *w, __global const float *u,
                                const float4 lobe_g, const float4 lobe_w, const int n,
                                __global float *out) {
    int i = get_global_id(0);
    if (i >= n) return;
    vstore3(phase_sample(vload3(i, w), lobe_g, lobe_w, vload3(i, u)), i, out);
}
