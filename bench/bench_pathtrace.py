#!/usr/bin/env python3
"""Benchmark the reference path tracer (cl/pathtrace.cl).

    python bench/bench_pathtrace.py [--quick] [--no-mitsuba] [--no-design] [--no-accuracy]

Prints the machine, then
1. throughput: samples/s, path vertices/s (real scattering vertices) and tracking steps/s
   for a 128^3 cloud (albedo 0.99, HG g 0.8, density_scale 64) and the same cloud as a thin
   medium (density_scale 2), 256x256, one sample per pixel per launch (65,536 paths), for
   the lane kernel and, side by side in the same run, the scalar kernel it replaced
   (built from git commit BEFORE, one path per work-item); lane statistics (-D PT_STATS);
2. training labels: labels/s of point_query for the dataset's default configuration
   (clvol.training.dataset.DatasetSpec(): shard (0, 0), its points and paths per label), before
   and after, and the largest label difference between the two;
3. Mitsuba 3 volpath on the cloud scene if it is installed and renders (llvm_ad_rgb first,
   then scalar_rgb), and the ratio; llvm_ad_rgb needs libLLVM >= 17 (docs/pathtrace.md);
4. the design measurement: one delta-tracking step (Philox draw, exponential distance,
   trilinear lookup, accept test) done (a) in a loop inside one work-item, (b) one step per
   launch with the state in global memory (wavefront style), (c) in a loop with 8 explicit
   float lanes;
5. accuracy vs time: error of 1, 4, 16, 64, 256 spp renders against a long reference render
   of ours (independent seed), with the seconds each took.
The machine is shared with other work: figures are best and median of repeats, and ratios
come from runs interleaved in the same process.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(1, str(Path(__file__).resolve().parents[1]))  # measure this checkout's clvol

from _common import machine  # noqa: E402  (bench/ is on sys.path)
from clvol.kernels.grid import f4
from clvol.kernels.pathtrace import (_MEDIUM_DTYPES, _QUERY_DTYPES, _RENDER_DTYPES, PT_OUT,
                                     ROW_L1, ROW_LMS, ROW_STEPS, ROW_VERTICES, PathTracer)
from clvol.metrics import compare_images
from clvol.render.pathtrace import PATHS_PER_LAUNCH, _medium, point_query, render_pathtrace
from clvol.runtime import _define_flags, get_runtime
from clvol.scene import Camera, Light, Phase, Scene, VolumeSpec
from clvol.scene import Medium as SceneMedium

# The last commit with the scalar kernel (one path per work-item): built from git for the
# side-by-side "before" figures.
BEFORE = "473565d"
ROOT = Path(__file__).resolve().parents[1]


def bench_scene(density_scale: float, size: int) -> Scene:
    l = np.array([0.6, 0.9, 0.3])
    return Scene(
        path=None, volume=VolumeSpec(file=None, generator="cloud", seed=1, resolution=128),
        medium=SceneMedium(density_scale=density_scale, albedo=(0.99, 0.99, 0.99), phase=Phase.hg(0.8)),
        light=Light(direction=tuple(l / np.linalg.norm(l))),
        camera=Camera((0.0, 0.3, 2.4), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 35.0, size, size))


class Before:
    """The scalar kernel of commit BEFORE, launched with the same arguments as the lane
    kernel (which only added the path counter), one work-item per path."""

    def __init__(self, pt: PathTracer):
        import pyopencl as cl
        self.pt = pt
        tmp = tempfile.mkdtemp(prefix="clvol_before_")
        subprocess.run(f"git -C {ROOT} archive {BEFORE} cl | tar -x -C {tmp}", shell=True,
                       check=True, capture_output=True)
        src = Path(tmp, "cl", "pathtrace.cl").read_text()
        prg = cl.Program(pt.rt.context, src).build(
            options=["-I", str(Path(tmp, "cl", "include"))] + _define_flags(pt.defines))
        # That kernel took the medium as four arguments (scale, albedo, lobe_g, lobe_w) and
        # the light as two (direction, sun) where today's takes one block each
        # (cl/include/medium.h, light.h): the blocks are split back for it.
        i = len(_MEDIUM_DTYPES) - 3                 # the medium block's place in pt._medium_args
        block, light = pt._medium_args[i], pt._medium_args[i + 1]
        old = (np.float32(block[0]), np.append(block[1:4], np.float32(0)), block[4:8],
               block[8:12], light[0:4], light[4:8])
        self.medium_args = pt._medium_args[:i] + old + pt._medium_args[i + 2:]
        old_dtypes = (_MEDIUM_DTYPES[:i] + [np.float32, None, None, None, None, None]
                      + _MEDIUM_DTYPES[i + 2:])
        self.render_k = cl.Kernel(prg, "pt_render")
        self.render_k.set_scalar_arg_dtypes(old_dtypes + _RENDER_DTYPES[len(_MEDIUM_DTYPES):-1])
        self.query_k = cl.Kernel(prg, "pt_query")
        self.query_k.set_scalar_arg_dtypes(old_dtypes + _QUERY_DTYPES[len(_MEDIUM_DTYPES):-1])

    def render_batch(self, camera, seed, sample0, spl):
        pt, rt = self.pt, self.pt.rt
        fwd, right, up = camera.basis()
        n = camera.width * camera.height * spl
        out = rt.empty((n, PT_OUT))
        rt.launch(self.render_k, n, self.medium_args + (
            f4(camera.origin), f4(fwd), f4(right), f4(up),
            np.float32(camera.tan_half_fov), np.int32(camera.width),
            np.int32(camera.height), np.uint64(seed), np.uint32(sample0), np.int32(spl),
            np.int32(pt.max_order), out))
        return rt.from_device(out, (spl, camera.width * camera.height, PT_OUT))

    def query_batch(self, points_buf, omegas_buf, nq, seed, sample0, ppl):
        pt, rt = self.pt, self.pt.rt
        out = rt.empty((nq * ppl, PT_OUT))
        rt.launch(self.query_k, nq * ppl, self.medium_args + (
            points_buf, omegas_buf, np.int32(nq), np.uint64(seed), np.uint32(sample0),
            np.int32(ppl), np.int32(pt.max_order), out))
        return rt.from_device(out, (ppl, nq, PT_OUT))


def before_or_none(pt):
    try:
        return Before(pt)
    except Exception as exc:  # no git history (an exported tree): print recorded figures
        print(f"note: the scalar kernel of commit {BEFORE} could not be built ({exc!s:.100}); "
              f"docs/pathtrace.md records its figures")
        return None


def throughput(scene, grid, repeats, rt, before=True):
    """Lane kernel and, interleaved, the scalar kernel of BEFORE: figures per kernel."""
    pt = PathTracer(_medium(scene, grid, None, scene.light.irradiance, None), 8, runtime=rt)
    kernels = {"lanes": pt}
    old = before_or_none(pt) if before else None
    if old is not None:
        kernels["before"] = old
    n = scene.camera.width * scene.camera.height
    res = {}
    for name, k in kernels.items():
        k.render_batch(scene.camera, 0, 0, 1)  # build + first-launch compile
        res[name] = {"secs": [], "verts": [], "steps": []}
    for i in range(repeats):
        for name, k in kernels.items():
            t0 = time.perf_counter()
            rows = k.render_batch(scene.camera, 0, i + 1, 1)
            r = res[name]
            r["secs"].append(time.perf_counter() - t0)
            r["verts"].append(float(rows[..., ROW_VERTICES].sum()))
            r["steps"].append(float(rows[..., ROW_STEPS].sum()))
    out = {}
    for name, r in res.items():
        best, med = min(r["secs"]), statistics.median(r["secs"])
        out[name] = {"paths": n, "best_s": best, "median_s": med, "samples_s_best": n / best,
                     "samples_s_median": n / med, "vertices_s_best": np.mean(r["verts"]) / best,
                     "steps_s_best": np.mean(r["steps"]) / best,
                     "vertices_per_path": np.mean(r["verts"]) / n,
                     "steps_per_path": np.mean(r["steps"]) / n, "defines": pt.defines}
    return out


def lane_stats(scene, grid, rt):
    """Loop counts of one launch (-D PT_STATS): how busy the lanes are."""
    med = _medium(scene, grid, None, scene.light.irradiance, None)
    med.extra_defines = {"PT_STATS": 1}
    pt = PathTracer(med, 8, runtime=rt)
    rows = pt.render_batch(scene.camera, 0, 1, 1)
    s = pt.stats
    n = rows.shape[1]
    return {"lanes": s["lanes"],
            "busy": s["lane_iterations_busy"] / max(1, s["tracking_iterations"] * s["lanes"]),
            "collisions_per_path": float(rows[..., ROW_STEPS].sum()) / n,
            "lane_iterations_per_path": s["lane_iterations_busy"] / n,
            "cell_iterations_per_iteration": s["cell_iterations"] / max(1, s["tracking_iterations"]),
            "event_pass_fraction": s["event_passes"] / max(1, s["tracking_iterations"])}


def labels(rt, repeats, before=True):
    """point_query at the dataset's defaults (shard (0, 0) of DatasetSpec()): labels/s of
    the lane kernel (the public API, end to end) and of the scalar kernel of BEFORE (the
    same launches and sums), interleaved."""
    from clvol.training.dataset import DatasetSpec, make_volume, sample_points, scene_for
    from clvol.render.pathtrace import DEFAULT_BLOCK
    spec = DatasetSpec()
    scene, grid = scene_for(spec, 0, 0), make_volume(spec, 0)
    pts = sample_points(spec, grid, 0, 0).astype(np.float64)
    om = np.asarray(scene.camera.origin, np.float64) - pts
    om /= np.linalg.norm(om, axis=1, keepdims=True)
    nq, n_paths = len(pts), spec.n_paths
    pt = PathTracer(_medium(scene, grid, None, (1.0, 1.0, 1.0), None), DEFAULT_BLOCK, runtime=rt)
    old = before_or_none(pt) if before else None

    def run_new():
        return point_query(scene, pts, om, n_paths, seed=5, grid=grid, runtime=rt)

    def run_old():
        pbuf = rt.to_device(pts.astype(np.float32))
        wbuf = rt.to_device(om.astype(np.float32))
        ppl_max = max(1, PATHS_PER_LAUNCH // nq)
        s1, sm = np.zeros((nq, 3)), np.zeros((nq, 3))
        done = 0
        while done < n_paths:
            ppl = min(ppl_max, n_paths - done)
            rows = old.query_batch(pbuf, wbuf, nq, 5, done, ppl).astype(np.float64)
            s1 += rows[..., ROW_L1].sum(axis=0)
            sm += rows[..., ROW_LMS].sum(axis=0)
            done += ppl
        return {"F1": s1 / n_paths, "Fms": sm / n_paths}

    runs = {"lanes": run_new}
    if old is not None:
        runs["before"] = run_old
    secs = {k: [] for k in runs}
    last = {}
    for name, fn in runs.items():
        last[name] = fn()  # build + first launch
    for _ in range(repeats):
        for name, fn in runs.items():
            t0 = time.perf_counter()
            last[name] = fn()
            secs[name].append(time.perf_counter() - t0)
    out = {"points": nq, "paths_per_label": n_paths, "resolution": spec.resolution,
           "density_scale": scene.medium.density_scale}
    for name in runs:
        out[name] = {"labels_s_best": nq / min(secs[name]),
                     "labels_s_median": nq / statistics.median(secs[name])}
    if "before" in last:
        a, b = last["lanes"], last["before"]
        out["max_rel_diff"] = max(float(np.max(np.abs(a[k] - b[k]) / np.maximum(np.abs(b[k]), 1e-12)))
                                  for k in ("F1", "Fms"))
    return out


MITSUBA_CHILD = r"""
import json, sys, time
import numpy as np
import mitsuba as mi
sys.path.insert(0, sys.argv[4])
variant, density_scale, spp = sys.argv[1], float(sys.argv[2]), int(sys.argv[3])
mi.set_variant(variant)
from bench_pathtrace import bench_scene
from clvol.render.pathtrace import mitsuba_scene_dict
scene = bench_scene(density_scale, 256)
grid = scene.volume.load()
mscene = mi.load_dict(mitsuba_scene_dict(scene, grid, spp))
mi.render(mscene)  # warm-up: the LLVM variant compiles its kernels on the first render
t0 = time.perf_counter()
img = np.asarray(mi.render(mscene))
secs = time.perf_counter() - t0
print(json.dumps({"variant": variant, "seconds": secs, "samples_s": 256 * 256 * spp / secs,
                  "mean": float(img[..., :3].mean())}))
"""


def mitsuba_throughput(density_scale, spp):
    """Each variant runs in a child process: a failing LLVM backend aborts its process."""
    import json
    try:
        import mitsuba  # noqa: F401
    except ImportError:
        return None, "mitsuba not installed (pip install mitsuba)"
    notes = []
    here = os.path.dirname(os.path.abspath(__file__))
    env = dict(os.environ)
    # llvm_ad_rgb needs libLLVM >= 17 (Debian: apt-get install libllvm19).
    llvm = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
    if "DRJIT_LIBLLVM_PATH" not in env and os.path.exists(llvm):
        env["DRJIT_LIBLLVM_PATH"] = llvm
    for variant in ("llvm_ad_rgb", "scalar_rgb"):
        proc = subprocess.run([sys.executable, "-c", MITSUBA_CHILD, variant, str(density_scale),
                               str(spp), here], capture_output=True, text=True, timeout=1800,
                              env=env)
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
RNG_DEFINE_LANES(8)
__kernel void lanes_kernel(__global const float *d, int n, int K, __global float *out) {
    uint i = get_global_id(0);
    uint8 id = (uint8)(i * 8u) + (uint8)(0, 1, 2, 3, 4, 5, 6, 7);
    float8 x = convert_float8(id % 7u) * 0.1f, y = 0.3f, z = 0.5f, acc = 0.0f;
    for (int k = 0; k < K; ++k) {
        uint8 c0 = id, c1 = 0, c2 = (uint8)((uint)k), c3 = 0;
        philox4x32_10_x8(&c0, &c1, &c2, &c3, (uint2)(1u, 0u));
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
    ap.add_argument("--no-before", action="store_true",
                    help="skip the scalar kernel of commit BEFORE (needs git)")
    ap.add_argument("--device", default=None)
    args = ap.parse_args()
    repeats = 3 if args.quick else 7
    rt = get_runtime(args.device)
    print("== machine")
    print(machine(rt))

    dense = bench_scene(64.0, 256)
    grid = dense.volume.load()
    thin = bench_scene(2.0, 256)
    print(f"\n== throughput (256x256, 1 spp per launch, best / median of {repeats} launches; "
          f"'before' = scalar kernel of commit {BEFORE}, interleaved)")
    results = {}
    for name, sc in (("cloud 128^3, density_scale 64", dense), ("thin, density_scale 2", thin)):
        r = throughput(sc, grid, repeats, rt, before=not args.no_before)
        results[name] = r
        for kind, x in r.items():
            print(f"{name} [{kind}]: {x['samples_s_best']:,.0f} samples/s best "
                  f"({x['samples_s_median']:,.0f} median), {x['vertices_s_best'] / 1e6:.2f} M vertices/s, "
                  f"{x['steps_s_best'] / 1e6:.2f} M tracking steps/s; {x['vertices_per_path']:.2f} "
                  f"vertices and {x['steps_per_path']:.1f} steps per path")
        if "before" in r:
            print(f"{name}: lanes / before = {r['before']['median_s'] / r['lanes']['median_s']:.2f}x "
                  f"(medians; best {r['before']['best_s'] / r['lanes']['best_s']:.2f}x)")
    print(f"defines: {results['cloud 128^3, density_scale 64']['lanes']['defines']}")
    st = lane_stats(dense, grid, rt)
    print(f"lanes (cloud): {st['lanes']} per work-item, {100 * st['busy']:.1f}% busy per tracking "
          f"iteration; per path {st['lane_iterations_per_path']:.1f} lane-iterations for "
          f"{st['collisions_per_path']:.1f} tentative collisions; {st['cell_iterations_per_iteration']:.2f} "
          f"majorant-cell passes per iteration; event code in {100 * st['event_pass_fraction']:.0f}% "
          f"of iterations")

    print(f"\n== training labels (point_query, dataset defaults; best / median of {repeats})")
    lab = labels(rt, repeats, before=not args.no_before)
    print(f"shard (0, 0) of DatasetSpec(): {lab['points']} points, {lab['paths_per_label']} paths "
          f"per label, {lab['resolution']}^3 volume, density_scale {lab['density_scale']:.1f}")
    for kind in ("lanes", "before"):
        if kind in lab:
            print(f"[{kind}]: {lab[kind]['labels_s_best']:,.0f} labels/s best "
                  f"({lab[kind]['labels_s_median']:,.0f} median)")
    if "before" in lab:
        print(f"labels: lanes / before = {lab['lanes']['labels_s_median'] / lab['before']['labels_s_median']:.2f}x "
              f"(medians; target >= 3x); same streams: largest relative label difference "
              f"{lab['max_rel_diff']:.2g}")

    if not args.no_mitsuba:
        print("\n== Mitsuba 3 volpath, same cloud scene (target: ours >= 10x Mitsuba samples/s)")
        m, note = mitsuba_throughput(64.0, 1 if args.quick else 4)
        if note:
            print(f"note: {note}")
        if m is None:
            print("Mitsuba: not measured")
        else:
            # Ours again right after Mitsuba: the load of the shared machine drifts.
            again = throughput(dense, grid, 5, rt, before=False)["lanes"]
            best, med = again["samples_s_best"], again["samples_s_median"]
            print(f"Mitsuba {m['variant']}: {m['samples_s']:,.0f} samples/s ({m['seconds']:.2f} s); "
                  f"ours right after it {best:,.0f} best, {med:,.0f} median of 5 launches; "
                  f"ours / Mitsuba = {best / m['samples_s']:.1f}x best, {med / m['samples_s']:.1f}x "
                  f"median ({'meets' if med >= 10 * m['samples_s'] else 'misses'} the 10x target "
                  f"on the median)")

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
