/* Included first by every program in cl/ (docs/opencl.md, "Compiler warnings").
 *
 * On a CPU without AVX-512 (or without AVX), clang warns at every call that passes or
 * returns a 16-wide (8-wide) vector, builtins included: "AVX vector argument of type
 * 'float16' without 'avx512f' enabled changes the ABI" (-Wpsabi), 48 to 170 times a program
 * with the explicit lanes of lanes.h. The warning is about linking objects compiled for
 * different CPUs, whose calling conventions for such vectors differ. An OpenCL program is one
 * module compiled for one device, linked only with PoCL's kernel library built for that same
 * CPU, so no call can cross that boundary: the warning cannot apply here, and it is the only
 * one turned off. Any other warning still fails tests/test_kernel_warnings.py. */
#ifndef CLVOL_PSABI_H
#define CLVOL_PSABI_H
#if defined(__clang__)
#pragma clang diagnostic ignored "-Wpsabi"
#endif
#endif
