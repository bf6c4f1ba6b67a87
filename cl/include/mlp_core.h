/* The network's forward pass as device functions (cl/mlp.cl documents it; twin
 * reference/mlp.py), shared by the mlp_forward kernel and the fused gather + network kernel
 * (cl/gather_mlp.cl): mlp_config (the LANES lanes' config), transposeL, mlp_run (normalise,
 * pool, every channel's evaluation, decode, store). Needs the defines listed in cl/mlp.cl. */
#ifndef CLVOL_MLP_CORE_H
#define CLVOL_MLP_CORE_H

#include "lanes.h"   /* LANES: queries per work-item, one per lane */

/* The feature contract's and the weight format's numbers, written once on the host
 * (clvol/features/layout.py, clvol/features/weights.py) and passed by clvol/kernels/mlp.py
 * (contract_defines): CONFIG_DIM config fields, of which g_mean, albedo and alpha are read
 * at CFG_GMEAN, CFG_ALBEDO, CFG_ALPHA; N_TYPES feature types; SQUEEZE squeeze inputs;
 * MLP_GAMMA the albedo exponent of the output encoding; MLP_ALBEDO_EPS the log1m input's
 * epsilon. */
#ifndef CONFIG_DIM
#error "mlp_core.h needs -D CONFIG_DIM (clvol/kernels/mlp.py contract_defines)"
#endif
#ifndef CFG_GMEAN
#error "mlp_core.h needs -D CFG_GMEAN (clvol/kernels/mlp.py contract_defines)"
#endif
#ifndef CFG_ALBEDO
#error "mlp_core.h needs -D CFG_ALBEDO (clvol/kernels/mlp.py contract_defines)"
#endif
#ifndef CFG_ALPHA
#error "mlp_core.h needs -D CFG_ALPHA (clvol/kernels/mlp.py contract_defines)"
#endif
#ifndef N_TYPES
#error "mlp_core.h needs -D N_TYPES (clvol/kernels/mlp.py contract_defines)"
#endif
#ifndef SQUEEZE
#error "mlp_core.h needs -D SQUEEZE (clvol/kernels/mlp.py contract_defines)"
#endif
#ifndef MLP_GAMMA
#error "mlp_core.h needs -D MLP_GAMMA (clvol/kernels/mlp.py contract_defines)"
#endif
#ifndef MLP_ALBEDO_EPS
#error "mlp_core.h needs -D MLP_ALBEDO_EPS (clvol/kernels/mlp.py contract_defines)"
#endif
/* What the code below is written for: */
#if SQUEEZE != 2 * N_TYPES + 2
#error "the squeeze vector is the mean and max of every type, then g_mean and alpha"
#endif
#if MLP_GAMMA != 4
#error "the decode computes albedo^MLP_GAMMA as (a^2)^2"
#endif

/* The albedo as the network reads it (-D MLP_ALBEDO_LOG1M: -log(1 - a + eps), which
 * resolves 0.99 .. 1; docs/network.md), before the config normalisation. */
#ifdef MLP_ALBEDO_LOG1M
#define ALBEDO_INPUT(a) (-log1p(MLP_ALBEDO_EPS - (a)))
#else
#define ALBEDO_INPUT(a) (a)
#endif
#define PAD8(x) (((x) + 7) & ~7)

typedef vL V;

__constant int COUNTS[N_LAYERS] = {LAYER_COUNTS};
__constant int HEADW[HEAD_DEPTH] = {HEAD_WIDTHS};

/* y[0 .. pad8(n_out)) = b + W x over n_in inputs; returns the next layer's parameters.
 * Outputs go in blocks of 16 accumulators (one x load per 16 FMAs, 16 independent chains to
 * hide the FMA latency), the last 8 of a width that is not a multiple of 16 in a block of 8. */
#define ACC8(A, B, C, D, E, F, G, H, OFF) \
    A = MLP_FMA(xi, (V)(w[OFF]), A); B = MLP_FMA(xi, (V)(w[OFF + 1]), B); \
    C = MLP_FMA(xi, (V)(w[OFF + 2]), C); D = MLP_FMA(xi, (V)(w[OFF + 3]), D); \
    E = MLP_FMA(xi, (V)(w[OFF + 4]), E); F = MLP_FMA(xi, (V)(w[OFF + 5]), F); \
    G = MLP_FMA(xi, (V)(w[OFF + 6]), G); H = MLP_FMA(xi, (V)(w[OFF + 7]), H)
#define INIT8(A, B, C, D, E, F, G, H, OFF) \
    A = (V)(bias[OFF]); B = (V)(bias[OFF + 1]); C = (V)(bias[OFF + 2]); D = (V)(bias[OFF + 3]); \
    E = (V)(bias[OFF + 4]); F = (V)(bias[OFF + 5]); G = (V)(bias[OFF + 6]); H = (V)(bias[OFF + 7])
#define STORE8(A, B, C, D, E, F, G, H, OFF) \
    if (relu) { A = fmax(A, 0.0f); B = fmax(B, 0.0f); C = fmax(C, 0.0f); D = fmax(D, 0.0f); \
                E = fmax(E, 0.0f); F = fmax(F, 0.0f); G = fmax(G, 0.0f); H = fmax(H, 0.0f); } \
    y[OFF] = A; y[OFF + 1] = B; y[OFF + 2] = C; y[OFF + 3] = D; \
    y[OFF + 4] = E; y[OFF + 5] = F; y[OFF + 6] = G; y[OFF + 7] = H

/* The multiply-add of the dense layers: fma(), or with -D MLP_MULADD (rusticl) a * b + c, which
 * PoCL contracts into the same fused multiply-add (FP_CONTRACT, on by default in OpenCL C;
 * bit-identical, tests/test_mlp.py::test_dense_forms_agree). On Mesa's rusticl (22.3, llvmpipe)
 * fma() of float is a software fma (exact; presumably libclc's) inlined at every call: a loop
 * of a * b + c ran 17x faster there, and llvmpipe's compile at the network's first launch
 * took minutes (docs/opencl.md, "rusticl"). rusticl does not contract, so its sums round twice
 * (within the twins' tolerance). */
#ifdef MLP_MULADD
#pragma OPENCL FP_CONTRACT ON
#define MLP_FMA(a, b, c) ((a) * (b) + (c))
#else
#define MLP_FMA(a, b, c) fma(a, b, c)
#endif

/* The activations are private arrays; a layer reads x[xo ..) and writes y[yo ..) (offsets, not
 * pointers into the arrays: llvmpipe miscompiles a private pointer with a run-time offset,
 * which then reads far off the stack; docs/opencl.md, "rusticl"). */
#ifdef MLP_DENSE_ARRAY
/* The same sums in the same order (each output: its bias, then fma over the inputs in order,
 * so the results are bit-identical), with the 8 accumulators of a block in an array and no
 * pointer induction. For Mesa's rusticl (22.3, llvmpipe): its NIR passes at clCreateKernel took
 * 2.3 s for one dense() of the named-accumulator form below on 8 inputs and 8 outputs, against
 * 0.05 s for this one, and never finished the network's ~150 calls (docs/opencl.md, "rusticl");
 * clvol/runtime.py's driver_defines sets it on rusticl. */
__attribute__((always_inline))
static inline __global const float *dense(__global const float *p, const int n_in, const int n_out,
                                          const V *x, const int xo, V *y, const int yo,
                                          const int relu) {
    const int np = PAD8(n_out);
    __global const float *bias = p + n_in * np;
    for (int o = 0; o < np; o += 8) {
        V acc[8];
        for (int r = 0; r < 8; ++r) acc[r] = (V)(bias[o + r]);
        for (int i = 0; i < n_in; ++i) {
            const V xi = x[xo + i];
            for (int r = 0; r < 8; ++r) acc[r] = MLP_FMA(xi, (V)(p[i * np + o + r]), acc[r]);
        }
        for (int r = 0; r < 8; ++r) y[yo + o + r] = relu ? fmax(acc[r], 0.0f) : acc[r];
    }
    return bias + np;
}
#else
__attribute__((always_inline))
static inline __global const float *dense(__global const float *p, const int n_in, const int n_out,
                                          const V *x, const int xo, V *y, const int yo,
                                          const int relu) {
    const int np = PAD8(n_out);
    __global const float *bias = p + n_in * np;
    x += xo;
    y += yo;
    int o = 0;
    for (; o + 16 <= np; o += 16) {
        V a0, a1, a2, a3, a4, a5, a6, a7, b0, b1, b2, b3, b4, b5, b6, b7;
        INIT8(a0, a1, a2, a3, a4, a5, a6, a7, o);
        INIT8(b0, b1, b2, b3, b4, b5, b6, b7, o + 8);
        __global const float *w = p + o;
        for (int i = 0; i < n_in; ++i, w += np) {
            const V xi = x[i];
            ACC8(a0, a1, a2, a3, a4, a5, a6, a7, 0);
            ACC8(b0, b1, b2, b3, b4, b5, b6, b7, 8);
        }
        STORE8(a0, a1, a2, a3, a4, a5, a6, a7, o);
        STORE8(b0, b1, b2, b3, b4, b5, b6, b7, o + 8);
    }
    if (o < np) {
        V a0, a1, a2, a3, a4, a5, a6, a7;
        INIT8(a0, a1, a2, a3, a4, a5, a6, a7, o);
        __global const float *w = p + o;
        for (int i = 0; i < n_in; ++i, w += np) {
            const V xi = x[i];
            ACC8(a0, a1, a2, a3, a4, a5, a6, a7, 0);
        }
        STORE8(a0, a1, a2, a3, a4, a5, a6, a7, o);
    }
    return bias + np;
}
#endif

/* One value per lane: src[off[j] + idx] for the LANES queries (off: lane offsets, clamped to
 * n-1). */
__attribute__((always_inline))
static inline V lanes(__global const float *src, const int *off, const int idx) {
    return (V)(src[off[0] + idx], src[off[1] + idx], src[off[2] + idx], src[off[3] + idx]
#if LANES >= 8
               , src[off[4] + idx], src[off[5] + idx], src[off[6] + idx], src[off[7] + idx]
#endif
#if LANES == 16
               , src[off[8] + idx], src[off[9] + idx], src[off[10] + idx], src[off[11] + idx],
               src[off[12] + idx], src[off[13] + idx], src[off[14] + idx], src[off[15] + idx]
#endif
               );
}

#ifdef MLP_TRANSPOSE16
/* In-register LANES x LANES transpose: round b swaps bit b of the row index with bit b of the
 * lane index (log2(LANES) rounds x LANES two-source shuffles, one instruction each with Clang's
 * __builtin_shufflevector). The host enables it on PoCL only: other compilers may lack the
 * builtin, and Oclgrind reports its shuffles' results as uninitialised although the transpose is
 * exact (a false positive of its per-instruction vector shadows; tests/test_mlp.py checks both
 * load paths give bit-identical outputs). */
#if LANES == 16
#define TR0L 0, 16, 2, 18, 4, 20, 6, 22, 8, 24, 10, 26, 12, 28, 14, 30
#define TR0H 1, 17, 3, 19, 5, 21, 7, 23, 9, 25, 11, 27, 13, 29, 15, 31
#define TR1L 0, 1, 16, 17, 4, 5, 20, 21, 8, 9, 24, 25, 12, 13, 28, 29
#define TR1H 2, 3, 18, 19, 6, 7, 22, 23, 10, 11, 26, 27, 14, 15, 30, 31
#define TR2L 0, 1, 2, 3, 16, 17, 18, 19, 8, 9, 10, 11, 24, 25, 26, 27
#define TR2H 4, 5, 6, 7, 20, 21, 22, 23, 12, 13, 14, 15, 28, 29, 30, 31
#define TR3L 0, 1, 2, 3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 22, 23
#define TR3H 8, 9, 10, 11, 12, 13, 14, 15, 24, 25, 26, 27, 28, 29, 30, 31
#elif LANES == 8
#define TR0L 0, 8, 2, 10, 4, 12, 6, 14
#define TR0H 1, 9, 3, 11, 5, 13, 7, 15
#define TR1L 0, 1, 8, 9, 4, 5, 12, 13
#define TR1H 2, 3, 10, 11, 6, 7, 14, 15
#define TR2L 0, 1, 2, 3, 8, 9, 10, 11
#define TR2H 4, 5, 6, 7, 12, 13, 14, 15
#elif LANES == 4
#define TR0L 0, 4, 2, 6
#define TR0H 1, 5, 3, 7
#define TR1L 0, 1, 4, 5
#define TR1H 2, 3, 6, 7
#endif
#define TR_ROUND(B, LO, HI)                                                  \
    for (int i = 0; i < LANES; ++i)                                          \
        if (!(i & (1 << B))) {                                               \
            const V lo = r[i], hi = r[i | (1 << B)];                         \
            r[i] = __builtin_shufflevector(lo, hi, LO);                      \
            r[i | (1 << B)] = __builtin_shufflevector(lo, hi, HI);           \
        }
#endif

/* r[i] lane j <- r[j] lane i (a LANES x LANES transpose in place). */
__attribute__((always_inline))
static inline void transposeL(V *r) {
#ifdef MLP_TRANSPOSE16
    TR_ROUND(0, TR0L, TR0H)
    TR_ROUND(1, TR1L, TR1H)
#if LANES >= 8
    TR_ROUND(2, TR2L, TR2H)
#endif
#if LANES == 16
    TR_ROUND(3, TR3L, TR3H)
#endif
#else
    float t[LANES * LANES], col[LANES];
    for (int j = 0; j < LANES; ++j) vstoreL(r[j], 0, t + LANES * j);
    for (int i = 0; i < LANES; ++i) {
        for (int j = 0; j < LANES; ++j) col[j] = t[LANES * j + i];
        r[i] = vloadL(0, col);
    }
#endif
}

/* All features of the LANES queries, lane = query: x[t * N_POINTS + point]. With
 * MLP_TRANSPOSE16, rows of LANES consecutive floats are read per query and transposed in
 * registers (per-lane reads, LANES cache lines per vector, were half of the kernel's time on
 * PoCL); features still come from memory, hence the optional prefetch. */
__attribute__((always_inline))
static inline void load_features(__global const float *features, const int *off, V *x) {
    int c = 0;
#ifdef MLP_TRANSPOSE16
    for (; c + LANES <= N_TYPES * N_POINTS; c += LANES) {
        V r[LANES];
        for (int j = 0; j < LANES; ++j) {
#ifdef MLP_PREFETCH
            /* LANES rows 3 KB apart: ask for the line 8 ahead (+10-20% on PoCL; the host sets
             * MLP_PREFETCH on PoCL only, as Oclgrind has no prefetch intrinsic) */
            __builtin_prefetch((const __global void *)(features + off[j] + c + 128));
#endif
            r[j] = vloadL(0, features + off[j] + c);
        }
        transposeL(r);
        for (int j = 0; j < LANES; ++j) x[c + j] = r[j];
    }
#endif
    for (; c < N_TYPES * N_POINTS; ++c) x[c] = lanes(features, off, c);
}

/* The normalised config of the LANES queries (rows coff[j] of config) and their albedo as given. */
__attribute__((always_inline))
static inline void mlp_config(__global const float *config, const int *coff,
                              __global const float *params, V *cfg, V *albedo_cfg) {
    __global const float *cshift = params + 2 * N_TYPES, *cscale = cshift + CONFIG_DIM;
    for (int i = 0; i < CONFIG_DIM; ++i)
        cfg[i] = (lanes(config, coff, i) - cshift[i]) * cscale[i];
    *albedo_cfg = lanes(config, coff, CFG_ALBEDO);
#ifdef MLP_ALBEDO_LOG1M
    cfg[CFG_ALBEDO] = (ALBEDO_INPUT(*albedo_cfg) - cshift[CFG_ALBEDO]) * cscale[CFG_ALBEDO];
#endif
}

/* The network on the raw features x of LANES queries (normalised here, in place) with their
 * config (mlp_config); lane j's channel ch goes to out[rows[j] + ch * stride], j < count (the
 * caller's layout: rows[j] = query * MLP_CHANNELS and stride 1 for [n][C] rows, or a lattice
 * index and the plane size for C planes). Returns 1 when a stored value is not finite. */
__attribute__((always_inline))
static inline int mlp_run(V *x, V *cfg, const V albedo_cfg, __global const float *params,
                          const float4 channel_albedo, __global float *out, const int *rows,
                          const int count, const int stride) {
    /* pack_params (clvol/kernels/mlp.py): feature shift and scale per type, config shift
     * and scale per field, then the layers */
    __global const float *fshift = params, *fscale = params + N_TYPES;
    __global const float *cshift = params + 2 * N_TYPES, *cscale = cshift + CONFIG_DIM;
    __global const float *layers = cscale + CONFIG_DIM;
    /* Features, normalised in the same pass that pools them into the squeeze vectors of all
     * layers (channel independent). Layer k's squeeze vector: v[k * SQUEEZE ..). */
    V v[N_LAYERS * SQUEEZE];
    {
        int start = 0;
        for (int k = 0; k < N_LAYERS; ++k) {
            const int cnt = COUNTS[k];
            for (int t = 0; t < N_TYPES; ++t) {
                const float sh = fshift[t], sc = fscale[t];
                const int xt = t * N_POINTS + start;
                V y = (x[xt] - sh) * sc;
                V s = y, m = y;
                x[xt] = y;
                for (int j = 1; j < cnt; ++j) {
                    y = (x[xt + j] - sh) * sc;
                    x[xt + j] = y;
                    s += y;
                    m = fmax(m, y);
                }
                v[k * SQUEEZE + t] = s / (float)cnt;
                v[k * SQUEEZE + N_TYPES + t] = m;
            }
            v[k * SQUEEZE + 2 * N_TYPES] = cfg[CFG_GMEAN];
            v[k * SQUEEZE + 2 * N_TYPES + 1] = cfg[CFG_ALPHA];
            start += cnt;
        }
    }

    float albedos[4] = {channel_albedo.s0, channel_albedo.s1, channel_albedo.s2, 0.0f};
    V res[MLP_CHANNELS];
    for (int ch = 0; ch < MLP_CHANNELS; ++ch) {
#if MLP_CHANNELS == 3
        /* A channel with the albedo of an earlier one is the same evaluation; albedo 0 has
         * no multiple scattering to predict (y = 0, F = 0). */
        int same = -1;
        for (int e = 0; e < ch; ++e)
            if (albedos[e] == albedos[ch]) same = e;
        if (same >= 0) { res[ch] = res[same]; continue; }
        if (albedos[ch] == 0.0f) { res[ch] = (V)(0.0f); continue; }
        cfg[CFG_ALBEDO] = (V)((ALBEDO_INPUT(albedos[ch]) - cshift[CFG_ALBEDO]) * cscale[CFG_ALBEDO]);
#endif
        __global const float *p = layers;
        /* module 2t+s's output: mod[(2t+s) * PAD8(MODULE_WIDTH) ..) (dense writes whole blocks
         * of 8); hu: h = hu[0 .. MAXW), u = hu[MAXW .. 2 MAXW) */
        V mod[N_TYPES * 2 * PAD8(MODULE_WIDTH)];
        V hu[2 * MAXW], a[MAXW], e[MAXW], z[MAXW];
        for (int t = 0; t < N_TYPES; ++t) {
            for (int s = 0; s < 2; ++s) {
                const int k0 = s ? N_DIFFUSE : 0, k1 = s ? N_LAYERS : N_DIFFUSE;
                int start = 0;
                for (int k = 0; k < k0; ++k) start += COUNTS[k];
                const int xt = t * N_POINTS;
                for (int i = 0; i < COUNTS[k0]; ++i) hu[i] = x[xt + start + i];
                for (int k = k0; k < k1; ++k) {
                    const int cnt = COUNTS[k], width = cnt + CONFIG_DIM;
                    for (int i = 0; i < cnt; ++i) a[i] = hu[i];
                    for (int i = 0; i < CONFIG_DIM; ++i) a[cnt + i] = cfg[i];
                    p = dense(p, SQUEEZE, SE_HIDDEN, v, k * SQUEEZE, e, 0, 1);
                    p = dense(p, SE_HIDDEN, width, e, 0, z, 0, 0);
                    for (int i = 0; i < width; ++i) z[i] = a[i] / (1.0f + exp(-z[i]));
                    start += cnt;
                    if (k + 1 < k1) {
                        const int nxt = COUNTS[k + 1];
                        const int xn = xt + start;   /* the next layer's features */
                        p = dense(p, width, nxt, z, 0, hu, MAXW, 1);
                        for (int i = 0; i < nxt; ++i) hu[MAXW + i] += x[xn + i];
                        p = dense(p, nxt, nxt, hu, MAXW, hu, 0, 1);
                        for (int i = 0; i < nxt; ++i) hu[i] += x[xn + i];
                    } else {
                        p = dense(p, width, MODULE_WIDTH, z, 0, mod, (2 * t + s) * PAD8(MODULE_WIDTH), 1);
                    }
                }
            }
        }
        /* Merges per type, written straight into the head's input [m_d, m_T, m_p, c] (u). */
        for (int t = 0; t < N_TYPES; ++t) {
            for (int i = 0; i < MODULE_WIDTH; ++i) {
                a[i] = mod[2 * t * PAD8(MODULE_WIDTH) + i];
                a[MODULE_WIDTH + i] = mod[(2 * t + 1) * PAD8(MODULE_WIDTH) + i];
            }
            p = dense(p, 2 * MODULE_WIDTH, MODULE_WIDTH, a, 0, e, 0, 1);
            for (int i = 0; i < MODULE_WIDTH; ++i) hu[MAXW + t * MODULE_WIDTH + i] = e[i];
        }
        for (int i = 0; i < CONFIG_DIM; ++i) hu[MAXW + N_TYPES * MODULE_WIDTH + i] = cfg[i];
        int width = N_TYPES * MODULE_WIDTH + CONFIG_DIM;
        int src = MAXW, dst = 0;   /* u -> h, then back and forth */
        for (int j = 0; j < HEAD_DEPTH; ++j) {
            p = dense(p, width, HEADW[j], hu, src, hu, dst, 1);
            width = HEADW[j];
            const int tmp = src; src = dst; dst = tmp;
        }
        p = dense(p, width, 1, hu, src, hu, dst, 0);
        res[ch] = hu[dst];
    }

    int bad = 0;
    for (int ch = 0; ch < MLP_CHANNELS; ++ch) {
        V y = res[ch];
#if MLP_DECODE
#if MLP_CHANNELS == 3
        const V alb = (V)(albedos[ch]);
#else
        const V alb = albedo_cfg;
#endif
        const V a2 = alb * alb;
        y = (a2 * a2) * fmax(expm1(y), 0.0f);   /* albedo^MLP_GAMMA, MLP_GAMMA = 4 */
#endif
        float r[LANES];
        vstoreL(y, 0, r);
        for (int j = 0; j < count; ++j) {
            out[rows[j] + ch * stride] = r[j];
            bad |= !isfinite(r[j]);
        }
    }
    return bad;
}

#endif
