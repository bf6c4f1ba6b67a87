/* Helpers for kernels written with 16 explicit lanes per work-item (float16 across rays,
 * queries or template points), the style that makes PoCL fast on CPUs (docs/conventions.md).
 * Twin: plain NumPy fancy indexing (p[i]) in each kernel's reference. */
#ifndef CLVOL_LANES_H
#define CLVOL_LANES_H

typedef float16 v16;
typedef int16 i16;

/* 16 scalar loads p[i.sK] into one vector (no hardware gather: on PoCL's AVX-512 target
 * LLVM's gathers were measured slower than scalar loads for these access patterns). */
__attribute__((always_inline))
v16 gather16(__global const float *p, i16 i) {
    return (v16)(p[i.s0], p[i.s1], p[i.s2], p[i.s3], p[i.s4], p[i.s5], p[i.s6], p[i.s7],
                 p[i.s8], p[i.s9], p[i.sa], p[i.sb], p[i.sc], p[i.sd], p[i.se], p[i.sf]);
}

/* The same with 8 lanes. */
__attribute__((always_inline))
float8 gather8(__global const float *p, int8 i) {
    return (float8)(p[i.s0], p[i.s1], p[i.s2], p[i.s3], p[i.s4], p[i.s5], p[i.s6], p[i.s7]);
}

#endif
