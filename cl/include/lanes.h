/* Explicit vector lanes: LANES rays, queries or template points per work-item (floatL across
 * them), the style that makes PoCL fast on CPUs (docs/conventions.md). LANES (16, 8 or 4) is
 * the device's choice, passed by the host (clvol/runtime.py device_lanes): no call may pass a
 * vector wider than the CPU's registers, whose calling convention would otherwise differ
 * from PoCL's kernel library (clang's -Wpsabi, docs/opencl.md "Compiler warnings").
 * Twin: plain NumPy fancy indexing (p[i]) in each kernel's reference. */
#ifndef CLVOL_LANES_H
#define CLVOL_LANES_H

#ifndef LANES
#error "needs -D LANES (16, 8 or 4: clvol/runtime.py device_lanes)"
#elif LANES != 16 && LANES != 8 && LANES != 4
#error "LANES must be 16, 8 or 4"
#endif

#define LANES_CAT_(a, b) a##b
#define LANES_CAT(a, b) LANES_CAT_(a, b)
typedef LANES_CAT(float, LANES) vL;
typedef LANES_CAT(int, LANES) iL;
typedef LANES_CAT(uint, LANES) uL;
#define convert_vL LANES_CAT(convert_float, LANES)
#define convert_iL LANES_CAT(convert_int, LANES)
#define vloadL LANES_CAT(vload, LANES)
#define vstoreL LANES_CAT(vstore, LANES)
#define gatherL LANES_CAT(gather, LANES)
#define gatheriL LANES_CAT(gatheri, LANES)

/* Lane indices 0..LANES-1, and the masks that interleave two vectors (shuffle2: lanes
 * a0 b0 a1 b1 ... of the low half, then of the high half). */
#if LANES == 16
#define LANE_IOTA (iL)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15)
#define LANE_ZIP_LO (uL)(0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6, 22, 7, 23)
#define LANE_ZIP_HI (uL)(8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31)
#elif LANES == 8
#define LANE_IOTA (iL)(0, 1, 2, 3, 4, 5, 6, 7)
#define LANE_ZIP_LO (uL)(0, 8, 1, 9, 2, 10, 3, 11)
#define LANE_ZIP_HI (uL)(4, 12, 5, 13, 6, 14, 7, 15)
#else
#define LANE_IOTA (iL)(0, 1, 2, 3)
#define LANE_ZIP_LO (uL)(0, 4, 1, 5)
#define LANE_ZIP_HI (uL)(2, 6, 3, 7)
#endif

/* Sum of an iL's lanes (no call: halves added in place). */
#if LANES == 16
#define LANE_SUM(v) ((v).s0 + (v).s1 + (v).s2 + (v).s3 + (v).s4 + (v).s5 + (v).s6 + (v).s7 \
                     + (v).s8 + (v).s9 + (v).sa + (v).sb + (v).sc + (v).sd + (v).se + (v).sf)
#elif LANES == 8
#define LANE_SUM(v) ((v).s0 + (v).s1 + (v).s2 + (v).s3 + (v).s4 + (v).s5 + (v).s6 + (v).s7)
#else
#define LANE_SUM(v) ((v).s0 + (v).s1 + (v).s2 + (v).s3)
#endif

/* Lane-wise scalar loads p[i.sK] into one vector (no hardware gather: on PoCL's AVX-512 target
 * LLVM's gathers were measured slower than scalar loads for these access patterns). Only
 * widths up to LANES are defined: a wider one would be a call with a too-wide vector. */
#if LANES >= 16
__attribute__((always_inline))
float16 gather16(__global const float *p, int16 i) {
    return (float16)(p[i.s0], p[i.s1], p[i.s2], p[i.s3], p[i.s4], p[i.s5], p[i.s6], p[i.s7],
                     p[i.s8], p[i.s9], p[i.sa], p[i.sb], p[i.sc], p[i.sd], p[i.se], p[i.sf]);
}
#endif
#if LANES >= 8
__attribute__((always_inline))
float8 gather8(__global const float *p, int8 i) {
    return (float8)(p[i.s0], p[i.s1], p[i.s2], p[i.s3], p[i.s4], p[i.s5], p[i.s6], p[i.s7]);
}
#endif
__attribute__((always_inline))
float4 gather4(__global const float *p, int4 i) {
    return (float4)(p[i.s0], p[i.s1], p[i.s2], p[i.s3]);
}

#endif
