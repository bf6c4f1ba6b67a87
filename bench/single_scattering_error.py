#!/usr/bin/env python3
"""What the ray marcher's single scattering alone leaves against the path tracer's.

    python bench/single_scattering_error.py [--size 96] [--spp 512] [--scenes NAME ...]
                                            [--steps 1 0.5] [--light-factors 2 4]

For each scene of bench/neural_quality.py (default: cloud, smoke, backscatter): the path
tracer at ``--max-order 1`` twice (two seeds, --spp each, so that the score removes the
reference's noise as neural_quality's does) against ``--ms none`` at 1 and 3 x 3 rays per
pixel. Printed: noise-corrected RMSE x 100 and the image mean over the reference's, the same
metric as neural_quality's tables. It separates the single-scattering part (the voxelised
light field, pixel-centre sampling) from what an F_ms representation leaves there.
"""
from __future__ import annotations

import argparse
import sys

from _common import machine  # noqa: E402  (bench/ is on sys.path; puts the checkout first)
from neural_quality import bench_scene, resolve_scenes, scores  # noqa: E402

from clvol.render.plan import auto_light_resolution  # noqa: E402
from clvol.render.raymarch import DEFAULT_STEP, MAX_LIGHT_RESOLUTION  # noqa: E402
from clvol.render.renderer import Renderer  # noqa: E402
from clvol.runtime import get_runtime  # noqa: E402

SEEDS = (101, 102)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--spp", type=int, default=512, help="per reference half (default 512)")
    ap.add_argument("--scenes", nargs="+", default=["cloud", "smoke", "backscatter"])
    ap.add_argument("--steps", nargs="*", type=float, default=[],
                    help="also these march steps in voxels (3 x 3 rays per pixel)")
    ap.add_argument("--light-factors", nargs="*", type=int, default=[],
                    help="also light fields at this many times the grid's largest side")
    args = ap.parse_args(argv)
    print(machine(get_runtime()))
    print(f"{args.size}^2, path tracer --max-order 1 at 2 x {args.spp} spp (seeds {SEEDS})")
    print(f"defaults: step {DEFAULT_STEP:g} voxels, light field auto_light_resolution "
          f"(capped at {MAX_LIGHT_RESOLUTION})")
    print(f"{'scene':14s} {'rays/pixel':>10s} {'step':>5s} {'light':>5s} {'rmse100':>8s} "
          f"{'mean':>6s}")
    for name, path in resolve_scenes(args.scenes).items():
        sc = bench_scene(path, args.size)
        grid = sc.volume.load()
        halves = [Renderer(sc, "pathtrace", grid=grid, spp=args.spp, seed=s, max_order=1)
                  .render().layers["total"] for s in SEEDS]
        n = max(grid.resolution)
        rows = [(1, DEFAULT_STEP, auto_light_resolution(grid.resolution)),
                (3, DEFAULT_STEP, auto_light_resolution(grid.resolution))]
        for step in args.steps:
            for f in args.light_factors or [None]:
                lr = auto_light_resolution(grid.resolution) if f is None else min(
                    1 << max(0, (f * n - 1).bit_length()), MAX_LIGHT_RESOLUTION)
                rows.append((3, step, lr))
        for ss, step, lr in rows:
            img = Renderer(sc, "raymarch", grid=grid, ms="none", supersample=ss, step=step,
                           light_resolution=lr).render()
            s = scores(img.layers["total"], halves[0], halves[1])
            print(f"{name:14s} {ss * ss:10d} {step:5g} {lr:5d} {s['rmse100']:8.2f} "
                  f"{s['mean']:6.3f}", flush=True)
    print(machine(get_runtime()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
