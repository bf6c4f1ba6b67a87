/* The network's forward pass, fused: squeeze-and-excitation layer walks of the six modules
 * {density, transmittance, phase} x {diffuse, highlight}, the per-type merges and the MLP head
 * in one kernel (seed III.C; architecture in clvol/features/weights.py, twin reference/mlp.py).
 *
 * Work split: one work-item evaluates LANES queries (cl/include/lanes.h: 16, 8 or 4 by device),
 * one per vector lane; every layer is a loop over its inputs with 16 (or 8) output accumulators
 * (a vector each) fed by scalar weights. Weights are shared by all lanes, so every weight load
 * serves LANES queries, no layer width needs padding
 * to 16, and ReLU/sigmoid/pooling are vector operations. (docs/conventions.md: explicit vectors are what
 * makes PoCL fast; local-memory tiling is slow there.)
 *
 * Arguments (inputs first, output last)
 *   features       float [n][3][N_POINTS]   gather output, types (density, transmittance, phase),
 *                                           points in layer order (clvol/features/layout.py)
 *   config         float [n][9]             g0 g1 g2 w0 w1 w2 g_mean albedo alpha (radians)
 *   params         float [..]               packed by clvol/kernels/mlp.py: feature_shift[3],
 *                                           feature_scale[3], config_shift[9], config_scale[9],
 *                                           then every linear layer in execution order as
 *                                           W^T [n_in][pad8(n_out)] followed by bias [pad8(n_out)]
 *                                           (padding rows/columns are 0)
 *   channel_albedo float4                   MLP_CHANNELS == 3: albedo of channel c (replaces
 *                                           config's albedo); unused when MLP_CHANNELS == 1
 *   n              int                      number of queries
 *   out            float [n][MLP_CHANNELS]  y = log(F / albedo^4 + 1), or with MLP_DECODE
 *                                           F = albedo^4 * max(exp(y) - 1, 0) (0 for albedo 0)
 *
 * Defines (set by the wrapper from the Architecture): N_LAYERS, N_DIFFUSE, LAYER_COUNTS (comma
 * list), N_POINTS, SE_HIDDEN, MODULE_WIDTH, HEAD_DEPTH, HEAD_WIDTHS (comma list), MAXW (largest
 * padded width), MLP_CHANNELS (1 or 3), MLP_DECODE (0/1); and the contract's numbers that
 * cl/include/mlp_core.h lists (CONFIG_DIM, CFG_*, N_TYPES, SQUEEZE, MLP_GAMMA = 4, the weight
 * format's, and MLP_ALBEDO_EPS).
 * Optional (the host sets both on PoCL): MLP_TRANSPOSE16 (feature rows read contiguously and
 * transposed in registers instead of per-lane loads; Clang), MLP_PREFETCH (software prefetch of
 * the rows; Clang).
 *
 * Equations (clvol/features/weights.py docstring): squeeze v_k = (mean, max per type over layer k, g_mean,
 * alpha); excitation w = sigmoid(E2 relu(E1 v)); z = w * [h, c]; u = relu(FC1 z) + x_{k+1};
 * h = relu(FC2 u) + x_{k+1}; module out relu(OUT z); merge relu(M [diffuse, highlight]);
 * head on [merged x3, c]. Output per seed eq. 20's normalised log space.
 */

#include "mlp_core.h"   /* the device functions, shared with cl/gather_mlp.cl */

__kernel void mlp_forward(__global const float *features, __global const float *config,
                          __global const float *params, const float4 channel_albedo,
                          const int n, __global float *out) {
    const int q0 = get_global_id(0) * LANES;
    if (q0 >= n) return;

    int foff[LANES], coff[LANES], dst[LANES];
    for (int j = 0; j < LANES; ++j) {
        const int q = min(q0 + j, n - 1);  // tail lanes recompute the last query, never stored
        foff[j] = q * (N_TYPES * N_POINTS);
        coff[j] = q * CONFIG_DIM;
        dst[j] = (q0 + j) * MLP_CHANNELS;
    }
    V cfg[CONFIG_DIM], albedo_cfg;
    mlp_config(config, coff, params, cfg, &albedo_cfg);
    V x[N_TYPES * N_POINTS];
    load_features(features, foff, x);
    mlp_run(x, cfg, albedo_cfg, params, channel_albedo, out, dst, min(LANES, n - q0), 1);
}
