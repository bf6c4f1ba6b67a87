#!/usr/bin/env python
"""Is the image independent of the volume's bounding box? The same density with and without a
one-voxel zero border (the box grown by one cell on each side, as a .vdb's dense grid carries),
rendered by each multiple-scattering source; RMSE x 100 of tonemapped luminance between the two
(bench/neural_quality.py's scale) and the ratio of image means. For the stochastic sources the
same difference between two seeds on one grid is printed too: their own noise.

    python bench/bbox_border.py [SCENE.toml] [--size 128] [--samples 64]
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from _common import ROOT, machine, square  # noqa: E402  (bench/ is on sys.path)
from clvol.metrics import LUMA, mrpnn_exposure, tonemap_srgb  # noqa: E402
from clvol.render.renderer import Renderer  # noqa: E402
from clvol.runtime import get_runtime  # noqa: E402
from clvol.scene import load_scene  # noqa: E402
from clvol.volume.grid import DensityGrid  # noqa: E402


def rmse100(a, b) -> float:
    k = mrpnn_exposure(b)
    ya, yb = (tonemap_srgb(np.asarray(x, np.float64), k) @ LUMA for x in (a, b))
    return 100.0 * float(np.sqrt(np.mean((ya - yb) ** 2)))


def with_border(g: DensityGrid) -> DensityGrid:
    cell = (np.asarray(g.bbox_max) - np.asarray(g.bbox_min)) / np.array(g.density.shape[::-1])
    return DensityGrid(np.ascontiguousarray(np.pad(g.density, 1)), np.asarray(g.bbox_min) - cell,
                np.asarray(g.bbox_max) + cell)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene", nargs="?", default=str(ROOT / "examples" / "cloud.toml"))
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--samples", type=int, default=64,
                    help="frames of the still view for the stochastic sources")
    args = ap.parse_args(argv)
    print(machine(get_runtime()))
    sc = square(load_scene(args.scene), args.size)
    g = sc.volume.load()
    gb = with_border(g)
    print(f"scene {args.scene}, {args.size}^2, grid {g.resolution} and {gb.resolution} "
          f"(a zero border), {args.samples} frames for the stochastic sources")

    def image(ms, grid, seed=0):
        still = ms in ("stochastic", "progressive")
        r = Renderer(sc, ms=ms, grid=grid, **({"seed": seed} if still else {}))
        frames = args.samples if still else 1
        for _ in range(frames):
            res = r.render()
        return res.total

    print("| source | with / without the border: rmse100 | image mean ratio | two seeds, one grid: rmse100 |")
    print("|---|---|---|---|")
    for ms in ("none", "network", "stochastic", "progressive"):
        a, b = image(ms, g), image(ms, gb)
        noise = (f"{rmse100(image(ms, g, seed=1), a):.3f}"
                 if ms in ("stochastic", "progressive") else "- (deterministic)")
        print(f"| {ms} | {rmse100(b, a):.3f} | {b.mean() / a.mean():.4f} | {noise} |", flush=True)
    print(machine(get_runtime()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
