"""The first frame after a camera move, against the path tracer and the analytic baselines
(issue 39: "no moving frame worse than the best analytic baseline").

    python bench/moving_frames.py [--size 64] [--ref-spp 4096] [--scenes NAME ...] [--seed 5]

Each scene (bench/neural_quality.py's names; default the hard ones: back-scattering, lit from
behind, low albedo, chromatic jade, and an out-of-family cumulus from behind) is rendered at the
camera c1 = its own camera c0 orbited 3 degrees about the target, by one Renderer that has seen
a different history before it:

    lattice            the 32^3 world lattice (the CLI's default): rendered at c0, then c1
    stochastic_fresh   --ms stochastic, c1 is the Renderer's first frame (one sample per block)
    stochastic_moved   --ms stochastic, one frame at c0, then c1 (reprojected + one new sample)
    stochastic_still   --ms stochastic, 64 frames at c0 (a converged still view), then c1
    stochastic_64      --ms stochastic, 64 frames at c1 (the still view a CLI render should reach)
    wrenninge, single  the analytic octaves and single scattering at c1 (the baselines)

Scores are bench/neural_quality.py's (``scores``: RMSE x 100 of tonemapped luminance with the
reference's noise removed) against its cached two-half references of the c1 frame (made at
--ref-spp if missing; shared cache). Printed per scene: each row's rmse100 and image mean over the
reference's, and whether each real-time row is no worse than the better baseline.
"""
from __future__ import annotations

import dataclasses
import math
import sys
import time
from pathlib import Path

import numpy as np

from _common import ROOT, machine, parser  # noqa: E402
import neural_quality as nq  # noqa: E402
from clvol.render.renderer import Renderer  # noqa: E402
from clvol.runtime import get_runtime  # noqa: E402

HARD = ("backscatter", "cloud_a1_back", "cloud_backlit", "low_albedo", "jade_chromatic",
        "oof_sphcu_back")
BASELINES = ("wrenninge", "single")
STILL = 64


def orbit(camera, degrees: float):
    """The camera turned about its target around the world up axis +y."""
    a = math.radians(degrees)
    o, t = np.asarray(camera.origin, float), np.asarray(camera.target, float)
    x, z = o[0] - t[0], o[2] - t[2]
    return dataclasses.replace(camera, origin=(float(t[0] + x * math.cos(a) - z * math.sin(a)),
                                               float(o[1]),
                                               float(t[2] + x * math.sin(a) + z * math.cos(a))))


def moved_frames(scene, grid, seed: int) -> dict:
    """name -> total image at c1 (scene.camera is c1; c0 is it turned back 3 degrees)."""
    c1 = scene.camera
    c0 = orbit(c1, -3.0)
    out = {}
    r = Renderer(scene, "raymarch", grid=grid, ms="network")
    r.render(camera=c0)
    out["lattice"] = r.render(camera=c1).total
    for name, before in (("stochastic_fresh", 0), ("stochastic_moved", 1),
                         ("stochastic_still", STILL)):
        r = Renderer(scene, "raymarch", grid=grid, ms="stochastic", seed=seed)
        for _ in range(before):
            r.render(camera=c0)
        out[name] = r.render(camera=c1).total
    r = Renderer(scene, "raymarch", grid=grid, ms="stochastic", seed=seed)
    for _ in range(STILL):
        img = r.render(camera=c1).total
    out["stochastic_64"] = img
    out["wrenninge"] = Renderer(scene, "raymarch", grid=grid, ms="wrenninge").render().total
    out["single"] = Renderer(scene, "raymarch", grid=grid, ms="none").render().total
    return out


def main(argv=None) -> int:
    ap = parser(__doc__, size=64)
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--scenes", nargs="+", default=list(HARD), choices=sorted(nq.SCENES))
    ap.add_argument("--seed", type=int, default=5, help="the stochastic rows' seed (default 5)")
    ap.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "clvol" / "neural_quality")
    a = ap.parse_args(argv)
    print(machine(get_runtime()))
    print(f"settings: {a.size}^2, references {a.ref_spp} spp (two halves), camera moved 3 degrees, "
          f"stochastic seed {a.seed}, still view {STILL} frames")
    worst = {}
    for name in a.scenes:
        sc = nq.bench_scene(nq.SCENES[name], a.size)
        sc = dataclasses.replace(sc, camera=orbit(sc.camera, 3.0))
        grid = sc.volume.load()
        t0 = time.perf_counter()
        h1, h2, _ = nq.reference(f"{name}_moved3", sc, grid, a.ref_spp // 2, a.cache)
        imgs = moved_frames(sc, grid, a.seed)
        ref_mean = float(((h1 + h2) / 2).mean())
        s = {k: nq.scores(v, h1, h2, with_flip=False) for k, v in imgs.items()}
        best = min(s[b]["rmse100"] for b in BASELINES)
        print(f"\n{name} ({time.perf_counter() - t0:.0f} s); best baseline rmse100 {best:.2f}")
        print(f"  {'row':<18}{'rmse100':>9}{'mean/ref':>10}  no worse than the best baseline")
        for k, v in s.items():
            ok = "" if k in BASELINES else ("yes" if v["rmse100"] <= best else "NO")
            print(f"  {k:<18}{v['rmse100']:>9.2f}{float(imgs[k].mean()) / ref_mean:>10.3f}  {ok}")
            if k not in BASELINES:
                worst[k] = max(worst.get(k, 0.0), v["rmse100"] / best)
    print("\nworst rmse100 / best baseline over the scenes (<= 1: the target holds everywhere):")
    for k, v in worst.items():
        print(f"  {k:<18}{v:>7.2f}")
    print(f"at the end: {machine()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
