"""Environment light in the ray marcher against the path tracer: sky-only and sun + sky clouds.

    python bench/env_accuracy.py [--spp 512] [--size 64] [--cases ...] [--env K:N[:J] ...]
                                 [--env-ms network|escape] [--order1]

Scene: the cloud generator (seed 1) at --volume^3 voxels, HG 0.857, density scale and albedo
per case, under the constant blue sky (0.3, 0.5, 0.9) with the sun off (irradiance 0) or on
(irradiance 1, direction of examples/cloud.toml); camera of examples/cloud.toml at
size x size. Reference: the path tracer, two runs of --spp samples per pixel with seeds 11
and 12; their mean is the reference and their difference its noise (subtracted from the
squared error: "noise-corrected"). The ray marcher runs with the default --ms network (which
serves the sun light; the sky is the environment source of clvol/render/environment.py, its
multiple scattering the network's or, with --env-ms escape, the escape model's) for each K:N
(sky directions : field resolution) or K:N:J (J: the network's sky cells). Printed per case: image means, their relative
difference, and rmse100: the metric of bench/neural_quality.py's tables (RMSE x 100 of
tonemapped luminance, the reference's noise removed; ``neural_quality.scores``), with the
score before noise removal beside it.

``--order1`` also splits the error: per case, over the pixels the march finds opaque
(alpha > 0.99), the mean of the march without its multiple-scattering layer (sky and sun
single scattering + background) against the path tracer at ``--max-order 1`` (two runs of
--spp), and the share of the full reference that orders >= 2 carry there.
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from _common import machine  # noqa: E402  (puts the checkout first on sys.path)
from neural_quality import scores  # noqa: E402  (bench/ is on sys.path)

from clvol.render.renderer import Renderer  # noqa: E402
from clvol.runtime import get_runtime  # noqa: E402
from clvol.scene import scene_from_dict  # noqa: E402

CASES = {  # name: (density scale, albedo, sun irradiance)
    "sky-0.999": (64.0, 0.999, 0.0), "sky-0.95": (64.0, 0.95, 0.0), "sky-0.9": (64.0, 0.9, 0.0),
    "sky-0.8-thin": (30.0, 0.8, 0.0), "sun+sky-0.999": (64.0, 0.999, 1.0),
    "sun+sky-0.9": (64.0, 0.9, 1.0)}


def scene(volume, size, ds, albedo, sun):
    return scene_from_dict({
        "volume": {"generator": "cloud", "seed": 1, "resolution": volume},
        "medium": {"preset": "cloud", "density_scale": ds, "albedo": albedo},
        "light": {"direction": [0.45, 0.4, -0.8], "irradiance": sun,
                  "environment": [0.3, 0.5, 0.9]},
        "camera": {"origin": [0.0, 0.15, 1.6], "target": [0, 0.06, 0], "up": [0, 1, 0],
                   "fov_y": 35.0, "width": size, "height": size}})


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spp", type=int, default=512)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--volume", type=int, default=96)
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--env", nargs="+", default=["64:32", "64:64"],
                    help="K:N pairs (sky directions : field resolution), or K:N:J with J "
                         "the network's sky cells")
    ap.add_argument("--env-ms", choices=["network", "escape"], default=None,
                    help="the sky's multiple scattering (default: the plan's, the network)")
    ap.add_argument("--order1", action="store_true",
                    help="also compare single scattering alone with the path tracer's order 1")
    args = ap.parse_args(argv)
    rt = get_runtime()
    print(machine(rt))
    print(f"cloud {args.volume}^3, {args.size}^2, path tracer 2 x {args.spp} spp (seeds 11, 12); "
          f"sky multiple scattering: {args.env_ms or 'the plan default (network)'}")
    print(f"{'case':14s} {'K:N':6s} {'mean rm':>8s} {'mean pt':>8s} {'rel':>7s} "
          f"{'rmse100':>8s} {'raw':>7s}")
    for name in args.cases:
        ds, alb, sun = CASES[name]
        sc = scene(args.volume, args.size, ds, alb, sun)
        r = Renderer(sc, "pathtrace", spp=args.spp)
        p1 = r.render(seed=11).layers["total"].astype(np.float64)
        p2 = r.render(seed=12).layers["total"].astype(np.float64)
        pt = 0.5 * (p1 + p2)
        for kn in args.env:
            k, n, *j = (int(x) for x in kn.split(":"))
            opts = {"env_ms_directions": j[0]} if j else {}
            a = Renderer(sc, env_directions=k, env_resolution=n, env_ms=args.env_ms,
                         **opts).render().layers["total"]
            s = scores(a.astype(np.float64), p1, p2, with_flip=False)
            print(f"{name:14s} {kn:6s} {a.mean():8.4f} {pt.mean():8.4f} "
                  f"{a.mean() / pt.mean() - 1:+7.3f} {s['rmse100']:8.2f} "
                  f"{s['rmse100_raw']:7.2f}", flush=True)
        if args.order1:
            march = Renderer(sc, ms="network").render().layers
            opaque = march["alpha"].reshape(march["alpha"].shape[:2]) > 0.99
            o1 = Renderer(sc, "pathtrace", spp=args.spp, max_order=1)
            pt1 = 0.5 * (o1.render(seed=13).layers["total"] + o1.render(seed=14).layers["total"])
            single = (march["total"] - march["multiple"])[opaque].mean()
            print(f"{name:14s} order 1, {int(opaque.sum())} opaque pixels: march "
                  f"{single:.4f}, path tracer {pt1[opaque].mean():.4f} "
                  f"({single / pt1[opaque].mean() - 1:+.3f}); orders >= 2 carry "
                  f"{1 - pt1[opaque].mean() / pt[opaque].mean():.0%} of the reference there",
                  flush=True)
    print(machine(rt))
    return 0


if __name__ == "__main__":
    sys.exit(main())
