/* Fused render-mode gather + network: F_ms for N queries without writing their features.
 *
 * The unfused pair, cl/gather.cl `gather` (render mode) then cl/mlp.cl `mlp_forward`, writes
 * 3 x 266 floats per query (~200 MiB for 65,536 queries) and reads them back. Here one
 * work-item takes LANES queries (the network's lanes; cl/include/lanes.h) and, per chunk of
 * LANES template points, gathers each query's chunk as the gather kernel does (template points
 * in lanes), then transposes the LANES x LANES blocks in registers into the network's layout (queries in lanes):
 * the features stay in private memory. Both halves are the shared device functions of
 * cl/include/gather_core.h and mlp_core.h, so the output equals the unfused pair's (tested,
 * tests/test_gather_mlp.py). Twin: reference/gather_mlp.py. Host: clvol/kernels/gather_mlp.py.
 *
 * Arguments: those of `gather` in render mode (cl/gather.cl; dens is read only for t_enter's
 * coarse level), then config [N][9] (clvol/kernels/gather.py config_vectors), params and
 * channel_albedo as `mlp_forward`'s, N, then where the output goes (the caller's layout:
 * device in, caller-owned device out):
 *   out_index      int [N]    element of query q's channel 0 in out
 *   channel_stride int        elements between a query's channels
 *   out            float [..] decoded F (MLP_DECODE 1): channel c of query q at
 *                             out[out_index[q] + c * channel_stride], whatever the processing
 *                             order; no other element is written. [N][C] rows are
 *                             out_index[q] = q C, stride 1; the ray marcher's F_ms lattice
 *                             (C planes of gz gy gx) is out_index[q] = the point's flat
 *                             lattice index, stride gz gy gx (the caller zeroes the rest).
 *   nonfinite      int [1]    1 is ORed in (atomic_or) when a stored value is not finite
 *                             (the caller zeroes it and reads it: no silent NaN or inf).
 * Defines: the gather's (NP, COARSE_LEVEL, phase, GATHER_SHUFFLE) and the network's (cl/mlp.cl);
 * NP must equal N_POINTS. Private memory is the network's (~105 KB) plus LANES queries' gather
 * state and three LANES x LANES blocks: the host launches groups of one work-item on CPUs, as
 * for mlp_forward.
 */
#include "gather_core.h"
#include "mlp_core.h"

#if NP != N_POINTS
#error "gather_mlp: the gather's template points (NP) must be the network's (N_POINTS)"
#endif

__kernel void gather_mlp(__global const float *dens, __global const float *baked,
                         __global const int *loff, const int L, const int n0,
                         const float4 cmin4, const float csize, __global const float *tpl,
                         __global const int *pinfo, __global const float *hl_spacing,
                         __global const float *ptab, const int NA,
                         __global const float *points, __global const float *omegas,
                         const float4 light4, const float4 lobe_g, const float4 lobe_w,
                         const float c_out, __global const int *order,
                         __global const float *config, __global const float *params,
                         const float4 channel_albedo, const int N,
                         __global const int *out_index, const int channel_stride,
                         __global float *out, __global int *nonfinite) {
    const int q0 = get_global_id(0) * LANES;
    if (q0 >= N) return;
    const float3 cmin = cmin4.xyz;
    const float3 l = light4.xyz;

    int qs[LANES], coff[LANES], dst[LANES];
    for (int j = 0; j < LANES; ++j) {
        qs[j] = order[min(q0 + j, N - 1)];   /* tail lanes repeat the last query, never stored */
        coff[j] = qs[j] * CONFIG_DIM;
        dst[j] = out_index[qs[j]];
    }
    V cfg[CONFIG_DIM], albedo_cfg;
    mlp_config(config, coff, params, cfg, &albedo_cfg);

    gather_query s[LANES];
    float centre[LANES];   /* the centre point's exact phase feature, per query */
    for (int j = 0; j < LANES; ++j) {
        gather_query_init(&s[j], vload3(qs[j], points), vload3(qs[j], omegas), l,
                          dens + loff[COARSE_LEVEL], n0, cmin, csize, L, hl_spacing, NA);
        centre[j] = log1p(phase_eval(s[j].mu, lobe_g, lobe_w));
    }

    V x[N_TYPES * N_POINTS];
    for (int c = 0; c < CHUNKS; ++c) {
        V fd[LANES], ft[LANES], fp[LANES];   /* row j: query j's LANES points of this chunk */
        for (int j = 0; j < LANES; ++j) {
            iL lvl, n, off, inside;
            vL gx, gy, gz;
            gather_chunk_points(&s[j], c, l, cmin, csize, n0, tpl, pinfo, loff, &lvl, &n, &off,
                                &inside, &gx, &gy, &gz);
            gather_render_chunk(baked, n, off, inside, gx, gy, gz, c_out, &fd[j], &ft[j]);
            fp[j] = gather_phase_chunk(&s[j], c, ptab);
        }
        /* row i: point LANES c + i of the LANES queries (the network's lanes) */
        transposeL(fd);
        transposeL(ft);
        transposeL(fp);
        const int np = c < CHUNKS - 1 ? LANES : TAIL;
        for (int i = 0; i < np; ++i) {
            x[LANES * c + i] = fd[i];
            x[N_POINTS + LANES * c + i] = ft[i];
            x[2 * N_POINTS + LANES * c + i] = fp[i];
        }
    }
    x[2 * N_POINTS] = vloadL(0, centre);
    if (mlp_run(x, cfg, albedo_cfg, params, channel_albedo, out, dst, min(LANES, N - q0),
                channel_stride))
        atomic_or(nonfinite, 1);
}
