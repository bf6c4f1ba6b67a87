#!/usr/bin/env python3
"""Benchmark the reference path tracer (cl/pathtrace.cl).

    python bench/bench_pathtrace.py [--quick] [--no-mitsuba] [--no-design] [--no-accuracy]

Prints the machine, then
1. throughput: samples/s, path vertices/s (real scattering vertices) and tracking steps/s
   for a 128^3 cloud (albedo 0.99, HG g 0.8, density_scale 64) and the same cloud as a thin
   medium (density_scale 2), 256x256, one sample per pixel per launch (65,536 paths);
2. Mitsuba 3 volpath on the same scene if it is installed and renders (llvm_ad_rgb is tried
   first; it needs libLLVM >= 17; then scalar_rgb), and the ratio; the issue's target is
   at least Mitsuba's samples/s on this CPU;
3. the design measurement behind the kernel's structure: one delta-tracking step (Philox
   draw, exponential distance, trilinear lookup, accept test) done (a) in a loop inside one
   work-item, (b) one step per launch with the state in global memory (wavefront style, no
   loop, so PoCL may vectorise across work-items), (c) in a loop with 8 explicit float lanes;
4. accuracy vs time: error of 1, 4, 16, 64, 256 spp renders against a long reference render
   of ours (independent seed), with the seconds each took.
The machine is shared with other work: figures are best and median of repeats.
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import numpy as np

from _common import cpu_model  # noqa: E402  (bench/ is on sys.path)
from clvol.kernels.pathtrace import ROW_STEPS, ROW_VERTICES, PathTracer
from clvol.metrics import compare_images
from clvol.pathtrace import _medium, render_pathtrace
from clvol.runtime import get_runtime
from clvol.scene import Camera, Light, Phase, Scene, VolumeSpec
from clvol.scene import Medium as SceneMedium




def bench_scene(density_scale: float, size: int) -> Scene:
    l = np.array([0.6, 0.9, 0.3])
    return Scene(
        path=None, volume=VolumeSpec(file=None, generator="cloud", seed=1, resolution=128),
        medium=SceneMedium(density_scale=density_scale, albedo=(0.99, 0.99, 0.99), phase=Phase.hg(0.8)),
        light=Light(direction=tuple(l / np.linalg.norm(l))),
        camera=Camera((0.0, 0.3, 2.4), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 35.0, size, size))


def throughput(scene, grid, repeats, rt):
    pt = PathTracer(_medium(scene, grid, None, scene.light.irradiance, None), 8, runtime=rt)
    pt.render_batch(scene.camera, 0, 0, 1)  # build + first-launch compile
    secs, verts, steps = [], [], []
    for i in range(repeats):
        t0 = time.perf_counter()
        rows = pt.render_batch(scene.camera, 0, i + 1, 1)
        secs.append(time.perf_counter() - t0)
        verts.append(float(rows[..., ROW_VERTICES].sum()))
        steps.append(float(rows[..., ROW_STEPS].sum()))
    n = scene.camera.width * scene.camera.height
    best, med = min(secs), statistics.median(secs)
    return {"paths": n, "best_s": best, "median_s": med, "samples_s_best": n / best,
            "samples_s_median": n / med, "vertices_s_best": np.mean(verts) / best,
            "steps_s_best": np.mean(steps) / best, "vertices_per_path": np.mean(verts) / n,
            "steps_per_path": np.mean(steps) / n, "defines": pt.defines}


MITSUBA_CHILD = r"""
import json, sys, time
import numpy as np
import mitsuba as mi
sys.path.insert(0, sys.argv[4])
variant, density_scale, spp = sys.argv[1], float(sys.argv[2]), int(sys.argv[3])
mi.set_variant(variant)
from bench_pathtrace import bench_scene
from clvol.pathtrace import mitsuba_scene_dict
scene = bench_scene(density_scale, 256)
grid = scene.volume.load()
mi.render(mi.load_dict(mitsuba_scene_dict(scene, grid, 1)))  # warm-up / JIT
t0 = time.perf_counter()
img = np.asarray(mi.render(mi.load_dict(mitsuba_scene_dict(scene, grid, spp))))
secs = time.perf_counter() - t0
print(json.dumps({"variant": variant, "seconds": secs, "samples_s": 256 * 256 * spp / secs,
                  "mean": float(img[..., :3].mean())}))
"""


def mitsuba_throughput(density_scale, spp):
    """Each variant runs in a child process: a failing LLVM backend aborts its process."""
    import json
    import subprocess
    import sys
    try:
        import mitsuba  # noqa: F401
    except ImportError:
        return None, "mitsuba not installed (pip install mitsuba)"
    notes = []
    here = os.path.dirname(os.path.abspath(__file__))
    for variant in ("llvm_ad_rgb", "scalar_rgb"):
        proc = subprocess.run([sys.executable, "-c", MITSUBA_CHILD, variant, str(density_scale),
                               str(spp), here], capture_output=True, text=True, timeout=1800)
        lines = proc.stdout.strip().splitlines()
        if proc.returncode == 0 and lines:
            return json.loads(lines[-1]), "; ".join(notes)
        err = (proc.stderr.strip().splitlines() or ["no output"])[0][:120]
        notes.append(f"{variant} failed (exit {proc.returncode}): {err}")
    return None, "; ".join(notes)


DESIGN_SRC = r"""
#include "rng.h"
#include "grid.h"
/* One tracking step: a Philox draw -> exponential distance, wrap into the unit box,
 * trilinear lookup, accept test. */
__attribute__((always_inline))
void step_once(__global const float *d, int n, uint id, uint k, float *x0, float *x1, float *x2,
               float *acc) {
    float4 u = rng_uniform4(1, id, k, 0);
    float t = -log(1.0f - u.x) * 0.05f;
    float3 p = (float3)(*x0, *x1, *x2) + t * (float3)(0.9f, 0.3f, 0.2f);
    p -= convert_float3(convert_int3(p));
    float dens = grid_lookup(d, n, n, n, p * (float)n - 0.5f);
    *acc += u.y < dens ? dens : 0.0f;
    *x0 = p.x; *x1 = p.y; *x2 = p.z;
}
__kernel void loop_kernel(__global const float *d, int n, int K, __global float *out) {
    uint i = get_global_id(0);
    float x0 = 0.1f * (float)(i % 7), x1 = 0.3f, x2 = 0.5f, acc = 0.0f;
    for (int k = 0; k < K; ++k) step_once(d, n, i, k, &x0, &x1, &x2, &acc);
    out[i] = acc;
}
__kernel void step_kernel(__global const float *d, int n, int k, __global float *state,
                          __global float *out) {
    uint i = get_global_id(0);
    float x0 = state[3 * i], x1 = state[3 * i + 1], x2 = state[3 * i + 2], acc = out[i];
    step_once(d, n, i, k, &x0, &x1, &x2, &acc);
    state[3 * i] = x0; state[3 * i + 1] = x1; state[3 * i + 2] = x2;
    out[i] = acc;
}
/* 8 lanes per work-item: Philox on uint8, distances on float8, lookups per lane. */
__kernel void lanes_kernel(__global const float *d, int n, int K, __global float *out) {
    uint i = get_global_id(0);
    uint8 id = (uint8)(i * 8u) + (uint8)(0, 1, 2, 3, 4, 5, 6, 7);
    float8 x = convert_float8(id % 7u) * 0.1f, y = 0.3f, z = 0.5f, acc = 0.0f;
    for (int k = 0; k < K; ++k) {
        uint8 c0 = id, c1 = 0, c2 = (uint8)((uint)k), c3 = 0;
        uint k0 = 1u, k1 = 0u;
        for (int r = 0; r < 10; ++r) {
            uint8 hi0 = mul_hi((uint8)0xD2511F53u, c0), lo0 = (uint8)0xD2511F53u * c0;
            uint8 hi1 = mul_hi((uint8)0xCD9E8D57u, c2), lo1 = (uint8)0xCD9E8D57u * c2;
            c0 = hi1 ^ c1 ^ k0; c2 = hi0 ^ c3 ^ k1; c1 = lo1; c3 = lo0;
            k0 += 0x9E3779B9u; k1 += 0xBB67AE85u;
        }
        float8 u0 = convert_float8(c0 >> 8) * (1.0f / 16777216.0f);
        float8 u1 = convert_float8(c1 >> 8) * (1.0f / 16777216.0f);
        float8 t = -log(1.0f - u0) * 0.05f;
        x += t * 0.9f; y += t * 0.3f; z += t * 0.2f;
        x -= convert_float8(convert_int8(x)); y -= convert_float8(convert_int8(y));
        z -= convert_float8(convert_int8(z));
        float xs[8], ys[8], zs[8], dv[8];
        vstore8(x, 0, xs); vstore8(y, 0, ys); vstore8(z, 0, zs);
        for (int j = 0; j < 8; ++j)
            dv[j] = grid_lookup(d, n, n, n, (float3)(xs[j], ys[j], zs[j]) * (float)n - 0.5f);
        float8 dens = vload8(0, dv);
        acc += select((float8)0.0f, dens, u1 < dens);
    }
    vstore8(acc, i, out);
}
"""


def design_measurement(rt, repeats):
    import pyopencl as cl
    from clvol.runtime import include_dir
    prg = cl.Program(rt.context, DESIGN_SRC).build(options=["-I", str(include_dir())])
    n = 128
    d = rt.to_device(np.random.default_rng(0).random((n, n, n)).astype(np.float32))
    N, K = 65536, 32
    out = rt.empty(N)
    state = rt.to_device(np.random.default_rng(1).random((N, 3)).astype(np.float32), writable=True)
    kl, ks, kv = (cl.Kernel(prg, k) for k in ("loop_kernel", "step_kernel", "lanes_kernel"))
    runs = {"loop (megakernel style)": lambda: kl(rt.queue, (N,), (64,), d, np.int32(n), np.int32(K), out),
            "one step per launch (wavefront style)": lambda: [
                ks(rt.queue, (N,), (64,), d, np.int32(n), np.int32(k), state, out) for k in range(K)],
            "loop, 8 explicit float lanes": lambda: kv(rt.queue, (N // 8,), (8,), d, np.int32(n), np.int32(K), out)}
    res = {}
    for name, fn in runs.items():
        fn()
        rt.queue.finish()
        best = float("inf")
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            rt.queue.finish()
            best = min(best, time.perf_counter() - t0)
        res[name] = N * K / best
    return res


def accuracy_vs_time(scene, grid, spps, ref_spp, rt):
    t0 = time.perf_counter()
    ref = render_pathtrace(scene, spp=ref_spp, seed=12345, grid=grid, runtime=rt, progress=False)
    ref_secs = time.perf_counter() - t0
    rows = []
    for spp in spps:
        t0 = time.perf_counter()
        img = render_pathtrace(scene, spp=spp, seed=1, grid=grid, runtime=rt, progress=False)
        secs = time.perf_counter() - t0
        rows.append((spp, secs, compare_images(img.layers["total"], ref.layers["total"])))
    return ref, ref_secs, rows


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true",
                    help="3 repeats, Mitsuba 1 spp, accuracy at 128x128 with a 256-spp reference")
    ap.add_argument("--no-mitsuba", action="store_true")
    ap.add_argument("--no-design", action="store_true")
    ap.add_argument("--no-accuracy", action="store_true")
    ap.add_argument("--device", default=None)
    args = ap.parse_args()
    repeats = 3 if args.quick else 7
    rt = get_runtime(args.device)
    print("== machine")
    print(f"cpu: {cpu_model()}, {os.cpu_count()} logical cores; load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())} (shared machine: other work runs too)")
    print(f"device: {rt.entry.label} ({rt.entry.platform.version.strip()})")

    dense = bench_scene(64.0, 256)
    grid = dense.volume.load()
    thin = bench_scene(2.0, 256)
    print("\n== throughput (256x256, 1 spp per launch, best / median of", repeats, "launches)")
    results = {}
    for name, sc in (("cloud 128^3, density_scale 64", dense), ("thin, density_scale 2", thin)):
        r = throughput(sc, grid, repeats, rt)
        results[name] = r
        print(f"{name}: {r['samples_s_best']:,.0f} samples/s best ({r['samples_s_median']:,.0f} median), "
              f"{r['vertices_s_best'] / 1e6:.2f} M vertices/s, {r['steps_s_best'] / 1e6:.2f} M tracking steps/s; "
              f"{r['vertices_per_path']:.2f} vertices and {r['steps_per_path']:.1f} steps per path "
              f"(defines {r['defines']})")

    if not args.no_mitsuba:
        print("\n== Mitsuba 3 volpath, same cloud scene (target: ours >= Mitsuba samples/s)")
        m, note = mitsuba_throughput(64.0, 1 if args.quick else 4)
        if note:
            print(f"note: {note}")
        if m is None:
            print("Mitsuba: not measured")
        else:
            ours = results["cloud 128^3, density_scale 64"]["samples_s_best"]
            print(f"Mitsuba {m['variant']}: {m['samples_s']:,.0f} samples/s ({m['seconds']:.2f} s); "
                  f"ours / Mitsuba = {ours / m['samples_s']:.1f}x "
                  f"({'meets' if ours >= m['samples_s'] else 'misses'} the target)")

    if not args.no_design:
        print("\n== design: one delta-tracking step, 65,536 items x 32 steps, best of", repeats)
        for name, v in design_measurement(rt, repeats).items():
            print(f"{name:<40} {v / 1e6:8.1f} M steps/s")

    if not args.no_accuracy:
        size, spps, ref_spp = (128, [1, 4, 16, 64], 256) if args.quick else (256, [1, 4, 16, 64, 256], 1024)
        sc = bench_scene(64.0, size)
        print(f"\n== accuracy vs time: cloud at {size}x{size}, reference {ref_spp} spp (seed 12345), "
              f"renders with seed 1")
        ref, ref_secs, rows = accuracy_vs_time(sc, grid, spps, ref_spp, rt)
        se = float(np.sqrt(np.mean(ref.layers["total_se"].astype(np.float64) ** 2)))
        print(f"reference: {ref_secs:.1f} s; its own noise (rms standard error per pixel) {se:.3g}, "
              f"the floor of the rmse column")
        print(f"{'spp':>5} {'seconds':>8} {'rmse':>10} {'relmse':>10} {'psnr dB':>8} {'MRPNN x100':>11}")
        for spp, secs, e in rows:
            print(f"{spp:>5} {secs:>8.2f} {e['rmse']:>10.4g} {e['relmse']:>10.4g} {e['psnr']:>8.2f} "
                  f"{e['mrpnn']:>11.3f}")


if __name__ == "__main__":
    main()
