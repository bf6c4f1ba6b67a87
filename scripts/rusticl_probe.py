"""Probes of Mesa's rusticl (llvmpipe) behind the driver rule of clvol/runtime.py DRIVER_RULES
(docs/opencl.md, "rusticl"). Each probe runs in a fresh process with Mesa's shader cache off,
so a first launch includes llvmpipe's compile:

    OCL_ICD_VENDORS=DIR RUSTICL_ENABLE=llvmpipe python scripts/rusticl_probe.py fma
    OCL_ICD_VENDORS=DIR RUSTICL_ENABLE=llvmpipe python scripts/rusticl_probe.py dense
    OCL_ICD_VENDORS=DIR RUSTICL_ENABLE=llvmpipe python scripts/rusticl_probe.py mlp [--lanes 4 16]
        [--drop MLP_MULADD] [--arch "layer_counts=(48, 48, 48, 48, 48), n_diffuse_layers=2"]

fma:   a loop of 200,000 float16 multiply-adds per work-item (64 work-items), fma() against
       a * b + c: the second launch's time (compiled), and whether each is fused (against a
       float64 reference on random data).
dense: one dense layer (32 inputs, 32 outputs, the MLP_DENSE_ARRAY form of
       cl/include/mlp_core.h) in a kernel of its own: first-launch time with fma() and with
       a * b + c, at 16 and 4 lanes.
mlp:   the shipped architecture's mlp_forward (clvol/kernels/mlp.py, 37 queries): first
       forward's time (build, create, llvmpipe's compile, run) at each lane width, with the
       driver rule's defines, and its largest error against reference/mlp.py. --arch: the
       keyword arguments of clvol.features.weights.Architecture instead of the shipped one.
Without a rusticl platform it says so and exits 2. Each child has --timeout seconds.
"""
import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

FMA_SRC = r"""
__kernel void k(__global const float *x, __global const float *w, __global float *out,
                const int n) {
    float16 acc = (float16)(0.0f);
    for (int i = 0; i < n; ++i) acc = MULADD(vload16(i, x), (float16)(w[i]), acc);
    out[get_global_id(0)] = acc.s0 + acc.sf;
}
__kernel void check(__global const float *a, __global const float *b, __global const float *c,
                    __global float *o) {
    const int i = get_global_id(0);
    o[i] = MULADD(a[i], b[i], c[i]);
}
"""

DENSE_SRC = r"""
#include "lanes.h"
typedef vL V;
#define PAD8(x) (((x) + 7) & ~7)
__kernel void k(__global const float *xin, __global const float *p, __global float *out) {
    const int g = get_global_id(0);
    V x[32], y[32];
    for (int i = 0; i < 32; ++i) x[i] = vloadL(g * 32 + i, xin);
    const int n_in = 32, np = 32;
    __global const float *bias = p + n_in * np;
    for (int o = 0; o < np; o += 8) {
        V acc[8];
        for (int r = 0; r < 8; ++r) acc[r] = (V)(bias[o + r]);
        for (int i = 0; i < n_in; ++i) {
            const V xi = x[i];
            for (int r = 0; r < 8; ++r) acc[r] = MULADD(xi, (V)(p[i * np + o + r]), acc[r]);
        }
        for (int r = 0; r < 8; ++r) y[o + r] = fmax(acc[r], 0.0f);
    }
    V s = y[0];
    for (int o = 1; o < 32; ++o) s += y[o];
    out[g] = s.s0 + s.s3;
}
"""

FORMS = {"fma": "fma(a, b, c)", "a*b+c": "((a) * (b) + (c))"}


def _rusticl():
    import pyopencl as cl
    for p in cl.get_platforms():
        if "rusticl" in p.name.lower() and p.get_devices():
            return cl, p.get_devices()[0]
    return cl, None


def _src(src, form):
    return f"#define MULADD(a, b, c) {FORMS[form]}\n" + src


def child_fma(form):
    import numpy as np
    cl, dev = _rusticl()
    ctx = cl.Context([dev])
    q = cl.CommandQueue(ctx)
    prg = cl.Program(ctx, _src(FMA_SRC, form)).build()
    mf = cl.mem_flags
    n = 200_000
    x = cl.Buffer(ctx, mf.READ_WRITE, 4 * 16 * n)
    w = cl.Buffer(ctx, mf.READ_WRITE, 4 * n)
    cl.enqueue_fill_buffer(q, x, np.float32(0.5), 0, 4 * 16 * n)
    cl.enqueue_fill_buffer(q, w, np.float32(0.25), 0, 4 * n)
    out = cl.Buffer(ctx, mf.READ_WRITE, 4 * 64)
    k = prg.k
    k.set_args(x, w, out, np.int32(n))
    times = []
    for _ in range(2):
        t = time.perf_counter()
        cl.enqueue_nd_range_kernel(q, k, (64,), (8,))
        q.finish()
        times.append(time.perf_counter() - t)
    rng = np.random.default_rng(0)
    a, b, c = (rng.standard_normal(1 << 16).astype(np.float32) for _ in range(3))
    bufs = [cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=v) for v in (a, b, c)]
    o = cl.Buffer(ctx, mf.READ_WRITE, a.nbytes)
    prg.check(q, a.shape, None, *bufs, o)
    got = np.empty_like(a)
    cl.enqueue_copy(q, got, o)
    fused = np.mean(got == (a.astype(np.float64) * b + c).astype(np.float32))
    print(f"fma probe, {form:6s}: first launch {times[0]:.2f} s, second {times[1]:.3f} s "
          f"(200,000 float16 multiply-adds x 64 work-items); equal to the fused result in "
          f"{100 * fused:.1f}% of 65,536 random cases", flush=True)


def child_dense(form, lanes):
    import numpy as np
    cl, dev = _rusticl()
    ctx = cl.Context([dev])
    q = cl.CommandQueue(ctx)
    t0 = time.perf_counter()
    prg = cl.Program(ctx, _src(DENSE_SRC, form)).build(
        options=f"-I {ROOT / 'cl' / 'include'} -DLANES={lanes}")
    k = prg.k
    t1 = time.perf_counter()
    mf = cl.mem_flags
    xin = cl.Buffer(ctx, mf.READ_WRITE, 4 * 16 * 32 * 8)
    p = cl.Buffer(ctx, mf.READ_WRITE, 4 * 33 * 32)
    cl.enqueue_fill_buffer(q, xin, np.float32(0.5), 0, 4 * 16 * 32 * 8)
    cl.enqueue_fill_buffer(q, p, np.float32(0.01), 0, 4 * 33 * 32)
    out = cl.Buffer(ctx, mf.READ_WRITE, 4 * 8)
    k.set_args(xin, p, out)
    q.finish()
    t2 = time.perf_counter()
    cl.enqueue_nd_range_kernel(q, k, (8,), (8,))
    q.finish()
    t3 = time.perf_counter()
    print(f"dense probe, 32x32, {form:6s}, {lanes:2d} lanes: build + create {t1 - t0:.2f} s, "
          f"first launch {t3 - t2:.2f} s", flush=True)


def child_mlp(lanes, drop, arch_kw=""):
    import numpy as np
    from clvol.features.weights import Architecture, MlpWeights, default_params, feature_contract
    from clvol.kernels.mlp import MlpKernel
    from reference import mlp as ref
    arch = eval(f"Architecture({arch_kw})", {"Architecture": Architecture})  # noqa: S307 (a probe)
    w = MlpWeights(arch, default_params(arch, np.random.default_rng(21)), feature_contract())
    net = MlpKernel(w)
    for name in drop:   # a workaround left out (the kernels are built at the first forward)
        net.rt.driver_defines.pop(name, None)
    f, c = ref.random_inputs(37, np.random.default_rng(5), arch=arch)
    t = time.perf_counter()
    got = net.forward(f, c)
    dt = time.perf_counter() - t
    want = ref.forward(w.params, arch, f, c)
    f2, c2 = ref.random_inputs(4096, np.random.default_rng(6), arch=arch)
    t = time.perf_counter()
    net.forward(f2, c2)
    dt2 = time.perf_counter() - t
    print(f"mlp probe, {'Architecture(' + arch_kw + ')' if arch_kw else 'shipped architecture'}, "
          f"{net.rt.lanes:2d} lanes, defines "
          f"{sorted(net.rt.driver_defines)}: first forward {dt:.2f} s; max |error| "
          f"{np.abs(got - want).max():.2g} (max |y| {np.abs(want).max():.3g}); then 4,096 "
          f"queries in {dt2:.2f} s", flush=True)


def run_child(args, timeout, env_extra=None):
    env = dict(os.environ, MESA_SHADER_CACHE_DISABLE="true",
               PYTHONPATH=os.pathsep.join([str(ROOT)] + [os.environ.get("PYTHONPATH", "")]))
    env.update(env_extra or {})
    t = time.perf_counter()
    try:
        r = subprocess.run([sys.executable, __file__, "--child"] + args, env=env,
                           capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        print(f"{' '.join(args)}: not done in {timeout} s", flush=True)
        return
    lines = [ln for ln in r.stdout.splitlines() if ln.strip()]
    if r.returncode or not lines:
        print(f"{' '.join(args)}: exit {r.returncode} after {time.perf_counter() - t:.1f} s "
              f"{r.stderr.strip().splitlines()[-1:] if r.stderr.strip() else ''}", flush=True)
    for ln in lines:
        print(ln, flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("probe", choices=["fma", "dense", "mlp"])
    ap.add_argument("--lanes", type=int, nargs="+", default=None)
    ap.add_argument("--timeout", type=float, default=300)
    ap.add_argument("--drop", nargs="+", default=[],
                    help="mlp: leave these driver-rule defines out (e.g. MLP_MULADD)")
    ap.add_argument("--arch", default="", help="mlp: Architecture(...) keyword arguments")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("rest", nargs="*", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        if a.probe == "fma":
            child_fma(a.rest[0])
        elif a.probe == "dense":
            child_dense(a.rest[0], int(a.rest[1]))
        else:
            child_mlp(int(a.rest[0]), a.drop, a.arch)
        return 0
    if _rusticl()[1] is None:
        print("no rusticl device (OCL_ICD_VENDORS=DIR with rusticl.icd, RUSTICL_ENABLE=llvmpipe)")
        return 2
    if a.probe == "fma":
        for form in FORMS:
            run_child(["fma", form], a.timeout)
    elif a.probe == "dense":
        for lanes in a.lanes or (16, 4):
            for form in FORMS:
                run_child(["dense", form, str(lanes)], a.timeout)
    else:
        for lanes in a.lanes or (4, 16):
            run_child(["mlp", str(lanes)] + (["--drop"] + a.drop if a.drop else [])
                      + (["--arch", a.arch] if a.arch else []), a.timeout,
                      {"CLVOL_LANES": str(lanes)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
