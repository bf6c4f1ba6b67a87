"""Ray marcher benchmark: frame times, light-field update, lookups/s, and the baseline errors
of the analytic sources against the path tracer.

    python bench/bench_raymarch.py            # 128^3 and 256^3 clouds, 256^2 and 512^2 images
    python bench/bench_raymarch.py --quick    # 64^3 and 128^3 clouds, 128^2 and 256^2 images
    python bench/bench_raymarch.py --no-errors / --errors-only

Frame time = the ray-march kernel alone (OpenCL profiling), median of --repeat runs, for
ms = none (a) and wrenninge (b); reading the layers back to the host is reported apart.
The light-field update (the exact optical depth toward the light, recomputed when the light
moves) is timed separately, for three light directions. Also printed: process CPU time per
frame (all threads), a load-independent measure of the work (CPU time / cores estimates the
frame time on an idle machine), and lookups/s: trilinear lookups issued (LANES lanes per
density or light-field lookup, counted by the kernel) per second of kernel time, next to the
~0.7-0.8 G/s measured peak (docs/raymarch.md, Speed).

The error section renders each example at --err-size pixels with the path tracer (--spp
samples, cached in --cache) and the ray marcher (a) and (b), and prints compare_images
metrics (the MRPNN metric is RMSE x 100 of tone-mapped 8-bit luminance). The path tracer's
own noise is printed next to them: a floor below which differences mean nothing.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from _common import ROOT, cpu_seconds, machine  # noqa: E402  (bench/ is on sys.path; puts the checkout first)
from clvol.render.raymarch import RayMarcher  # noqa: E402
from clvol.render.renderer import Renderer  # noqa: E402
from clvol.runtime import get_runtime  # noqa: E402
from clvol.scene import load_scene  # noqa: E402
from clvol.volume.generators import generate  # noqa: E402

PEAK_LOOKUPS = (0.7e9, 0.8e9)
TARGET_MS = {256: 30.0, 512: 100.0}



def bench_frames(args, rt):
    scene = load_scene(ROOT / "examples" / "cloud.toml")
    cores = os.cpu_count() or 1
    print(f"\n== Frame times (examples/cloud.toml medium, light and camera; cloud generator seed 1; "
          f"step {args.step:g} voxel, threshold 1e-3, median of {args.repeat}) ==")
    print("Timings were taken with other jobs on the machine: see the load average above. "
          "'cpu/core' = process CPU time per frame / cores: the frame time to expect idle.")
    for res in args.res:
        t0 = time.perf_counter()
        grid = generate("cloud", seed=1, resolution=res)
        t_gen = time.perf_counter() - t0
        rm = RayMarcher(grid, scene.medium, runtime=rt)
        t0 = time.perf_counter()
        rm.pyramid                          # the DeviceMedium builds and keeps it
        rt.finish()
        t_pyr = time.perf_counter() - t0
        lights = [scene.light.direction, (-0.5, 0.8, 0.2), (0.1, 0.3, -0.9)]
        rm.set_light(lights[0])  # warm-up (build)
        rt.finish()
        t_light = []
        for i in range(args.repeat):
            t0 = time.perf_counter()
            rm.set_light(lights[i % len(lights)])
            rt.finish()
            t_light.append(time.perf_counter() - t0)
        rm.set_light(scene.light.direction)
        rt.finish()
        print(f"\ncloud {res}^3 (generated in {t_gen:.1f} s; pyramid/resample once per volume "
              f"{t_pyr * 1e3:.0f} ms): light-field update ({rm.light_resolution}^3, median over "
              f"3 directions) {np.median(t_light) * 1e3:.1f} ms")
        print(f"  {'image':>7} {'ms':>4} {'kernel ms':>10} {'target':>8} {'cpu/core ms':>12} "
              f"{'readback ms':>12} {'G lookups/s':>12} {'active %':>9}")
        for size in args.sizes:
            cam = replace(scene.camera, width=size, height=size)
            for ms in ("none", "wrenninge"):
                res_ = rm.march_with(cam, scene.light, ms, step=args.step, stats=True)[0]
                st = res_["stats"].astype(np.int64).sum(axis=0)
                lane_lookups = rt.lanes * (int(st[0]) + int(st[1]))
                k_times, c_times, r_times = [], [], []
                for _ in range(args.repeat + 1):
                    c0 = cpu_seconds()
                    evt, bufs, _plan = rm.march_with(cam, scene.light, ms, step=args.step,
                                                read_back=False)
                    evt.wait()
                    c1 = cpu_seconds()
                    k_times.append((evt.profile.end - evt.profile.start) * 1e-9)
                    c_times.append(c1 - c0)
                    r0 = time.perf_counter()
                    for name in ("total", "single", "multiple", "alpha", "depth"):
                        ch = 3 if name in ("total", "single", "multiple") else 1
                        rt.from_device(bufs[name], (size * size * ch,))
                    r_times.append(time.perf_counter() - r0)
                kt = float(np.median(k_times[1:]))
                ct = float(np.median(c_times[1:]))
                target = TARGET_MS.get(size)
                tgt = f"<= {target:.0f}" if target else "-"
                active = 100.0 * st[3] / max(rt.lanes * st[0], 1)
                print(f"  {size:>5}^2 {'(' + ms[0] + ')':>4} {kt * 1e3:>10.1f} {tgt:>8} "
                      f"{ct / cores * 1e3:>12.1f} {np.median(r_times[1:]) * 1e3:>12.1f} "
                      f"{lane_lookups / kt / 1e9:>12.3f} {active:>9.0f}")
    print(f"\nPeak measured with PoCL on 2 AVX-512 cores for a plain two-lookup march: "
          f"{PEAK_LOOKUPS[0] / 1e9:.1f}-{PEAK_LOOKUPS[1] / 1e9:.1f} G lookups/s "
          f"(docs/raymarch.md). "
          f"Lookups here = {rt.lanes} lanes x (density lookups + light-field lookups) issued, "
          "idle lanes included; 'active %' = lane-segments doing work / lanes issued.")


def _pt_reference(scene, spp, cache: Path, name: str, size: int):
    from clvol.render.pathtrace import render_pathtrace
    cache.mkdir(parents=True, exist_ok=True)
    f = cache / f"{name}_{size}px_{spp}spp.npz"
    if f.exists():
        z = np.load(f)
        return z["total"], z["total_se"], float(z["seconds"])
    t0 = time.perf_counter()
    r = render_pathtrace(scene, spp=spp, seed=1, progress=False)
    secs = time.perf_counter() - t0
    np.savez(f, total=r.layers["total"], total_se=r.layers["total_se"], seconds=secs)
    return r.layers["total"], r.layers["total_se"], secs


def bench_errors(args):
    from clvol.metrics import compare_images
    print(f"\n== Baseline errors against the path tracer ({args.err_size}^2, {args.spp} spp, "
          f"cached in {args.cache}) ==")
    print("(a) single scattering only, (b) + Wrenninge octaves (N=3, a=b=c=0.5). Baselines, "
          "not targets. 'PT noise' = mean over pixels of the path tracer's standard error / "
          "the image mean.")
    print(f"  {'scene':<8} {'method':<14} {'rmse':>10} {'relmse':>10} {'psnr':>7} {'mrpnn':>7} "
          f"{'mean ratio':>10} {'PT noise':>9}")
    for path in sorted((ROOT / "examples").glob("*.toml")):
        scene = load_scene(path)
        scene = replace(scene, camera=replace(scene.camera, width=args.err_size,
                                              height=args.err_size))
        ref, se, secs = _pt_reference(scene, args.spp, Path(args.cache), path.stem, args.err_size)
        noise = float(se.mean() / max(ref.mean(), 1e-30))
        for ms, label in (("none", "(a) single"), ("wrenninge", "(b) wrenninge")):
            img = Renderer(scene, "raymarch", ms=ms, step=args.step).render().layers["total"]
            m = compare_images(img, ref)
            print(f"  {path.stem:<8} {label:<14} {m['rmse']:>10.3g} {m['relmse']:>10.3g} "
                  f"{m['psnr']:>7.2f} {m['mrpnn']:>7.2f} {img.mean() / ref.mean():>10.3f} "
                  f"{noise:>9.4f}")
        print(f"  {'':<8} (path tracer reference took {secs:.0f} s)")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="smaller volumes and images, 3 repeats")
    p.add_argument("--repeat", type=int, default=None)
    p.add_argument("--step", type=float, default=1.0, help="march step in voxels")
    p.add_argument("--no-errors", action="store_true", help="skip the path-tracer comparison")
    p.add_argument("--errors-only", action="store_true")
    p.add_argument("--spp", type=int, default=None, help="path tracer samples per pixel")
    p.add_argument("--err-size", type=int, default=None, help="image size for the error table")
    p.add_argument("--cache", default="/tmp/clvol-bench-cache", help="path tracer reference cache")
    args = p.parse_args(argv)
    args.res = [64, 128] if args.quick else [128, 256]
    args.sizes = [128, 256] if args.quick else [256, 512]
    args.repeat = args.repeat or (3 if args.quick else 7)
    args.spp = args.spp or (16 if args.quick else 256)
    args.err_size = args.err_size or (64 if args.quick else 128)
    rt = get_runtime(profiling=True)
    print(machine(rt))
    print(f"python {platform.python_version()}, numpy {np.__version__}")
    if not args.errors_only:
        bench_frames(args, rt)
    if not args.no_errors:
        bench_errors(args)
    print("\n" + machine(rt).split("; load")[0] + "; load average at the end: "
          + " ".join(f"{x:.2f}" for x in os.getloadavg()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
