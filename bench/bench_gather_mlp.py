#!/usr/bin/env python3
"""Benchmark the fused gather + network kernel (cl/gather_mlp.cl) against the unfused pair
(cl/gather.cl render mode -> cl/mlp.cl), side by side, at 16,384, 65,536 and 262,144 queries.

    python bench/bench_gather_mlp.py [--rgb] [--repeats 5] [--sizes 16384 65536 262144]

Two paths run as the renderer runs them: ``NetworkSource.evaluate`` (clvol/render/ms/network.py)
with ``fused=True`` / ``fused=False`` on the shipped network (clvol/data/weights/full_albedo.npz,
its 64^3 pyramid) and a 128^3 procedural cloud, queries at random occupied voxels (jittered)
looking in random directions; the unfused pair goes through device memory in chunks of
NETWORK_CHUNK queries (as evaluate does; ~100 MiB of features per chunk, fresh buffers per
call), the fused kernel in one launch. A third, "pair reused", is the unfused pair at its best:
gather(as_buffers) into feature buffers kept from the previous repeat (no fresh buffers, no
chunks) then MlpKernel.forward, as a caller that keeps its buffers would run it. The graded
transmittance and the bake are made once before timing (per light, not per query batch). The
machine is shared with other engineers, so each figure is a median over repeats in which the
three paths alternate, given as wall time of the call and as process CPU time / cores (what it
would take with the cores to itself); load average before and after.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np

from _common import cpu_seconds, load_average, machine  # bench/ is on sys.path
from clvol.kernels.gather import gather
from clvol.render.ms import network as rnet
from clvol.runtime import get_runtime
from clvol.scene import Medium, Phase
from clvol.volume.generators import generate



def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[16384, 65536, 262144])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--rgb", action="store_true",
                    help="chromatic albedo (0.9, 0.95, 0.999): three evaluations per query")
    args = ap.parse_args()
    rt = get_runtime()
    cores = rt.device.max_compute_units
    print(f"{machine(rt)}; {cores} compute units")
    print(f"load average before: {load_average()} (other engineers' jobs share the cores; "
          f"medians over {args.repeats} alternating repeats)")
    grid = generate("cloud", seed=1, resolution=128)
    albedo = (0.9, 0.95, 0.999) if args.rgb else (0.999,) * 3
    medium = Medium(40.0, albedo, Phase.hg(0.857))
    light = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
    t0 = time.perf_counter()
    src = {f: rnet.NetworkSource(rnet.shipped_weights(), grid, medium, rt, fused=f)
           for f in (True, False)}
    pyr = src[True].pyramid
    rs = np.random.default_rng(0)
    occ = np.argwhere(pyr.level(0) > 0)
    n_max = max(args.sizes)
    pick = occ[rs.integers(0, len(occ), n_max)][:, ::-1]
    vox = pyr.cube_size / pyr.base_resolution
    pts = pyr.cube_min + (pick + rs.uniform(0, 1, pick.shape)) * vox
    om = rs.normal(size=(n_max, 3))
    om /= np.linalg.norm(om, axis=1, keepdims=True)
    for s in src.values():                        # compile, graded fields, bake; warm
        s.evaluate(pts[:256], om[:256], light)
    rt.finish()
    print(f"settings: shipped network ({os.path.basename(str(src[True].weights.path))}), pyramid base "
          f"{pyr.base_resolution}^3 ({pyr.n_levels} levels), 128^3 cloud, HG g 0.857, albedo "
          f"{'RGB ' + str(albedo) + ' (3 evaluations)' if args.rgb else '0.999 grey (1 evaluation)'}"
          f", unfused chunk {rnet.NETWORK_CHUNK}, fused chunk {rnet.FUSED_CHUNK}; "
          f"setup {time.perf_counter() - t0:.1f} s")
    print("figures: wall = the call (upload, sort, kernels, read-back); cpu/core = its process "
          "CPU time / cores; ratio = that path's time / the fused path's (> 1: fused is faster)")
    grey = not args.rgb
    net, w = src[False].mlp, src[False].weights
    graded = src[False].graded(light, medium.density_scale)
    kept = {}

    def pair(n):
        """The unfused kernels with feature buffers kept between calls."""
        g = gather(src[False].pyramid, graded, pts[:n], om[:n], light, medium, albedo[0], mode="render",
                   level_weights=w.level_weights, bias=w.level_bias, as_buffers=True,
                   reuse=kept.get("g"))
        kept["g"] = g
        return net.forward(g["features"], g["config"], channel_albedo=None if grey else albedo,
                           decode=True, n=n)

    paths = {"fused": lambda n: src[True].evaluate(pts[:n], om[:n], light),
             "unfused": lambda n: src[False].evaluate(pts[:n], om[:n], light),
             "pair reused": pair}
    print(f"{'queries':>8} {'path':>12} | {'wall ms':>8} {'cpu/core ms':>11} | "
          f"{'ratio wall':>10} {'ratio cpu':>9} | {'Mqueries/s (wall)':>17}")
    for n in args.sizes:
        pair(n)                                   # buffers of this size exist before timing
        res = {k: ([], []) for k in paths}
        for _ in range(args.repeats):
            for name, fn in paths.items():
                rt.finish()
                c0, w0 = cpu_seconds(), time.perf_counter()
                fn(n)
                rt.finish()
                res[name][0].append((time.perf_counter() - w0) * 1e3)
                res[name][1].append((cpu_seconds() - c0) * 1e3 / cores)
        med = statistics.median
        # (wall and CPU times of a launch are > 0; the floor only guards the ratios)
        fw, fc = max(med(res["fused"][0]), 1e-9), max(med(res["fused"][1]), 1e-9)
        for name in paths:
            wl, cp = med(res[name][0]), med(res[name][1])
            print(f"{n:>8} {name:>12} | {wl:>8.1f} {cp:>11.1f} | {wl / fw:>10.2f} {cp / fc:>9.2f}"
                  f" | {n / max(wl, 1e-9) * 1e-3:>17.3f}")
    print(f"load average after: {load_average()}")


if __name__ == "__main__":
    main()
