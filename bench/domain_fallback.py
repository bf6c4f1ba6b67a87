"""Which multiple-scattering source to use outside the network's training domain.

For scenes outside the shipped weights' domain (HG g < 0, albedo < 0.8, more lobes), render
the ray marcher with --ms none, wrenninge and network (forced: --no-domain-fallback) and
compare each with a path-traced reference of the same scene (RMSE of the total image over
pixels; the reference's own noise is printed as the RMS of its standard error):

    python bench/domain_fallback.py [--size 32] [--spp 64]

The scenes are the cloud and milk examples (tests/data/scenes) with the medium changed.
docs/raymarch.md ("Validity domain") records a run and the choice it supports.
"""
from __future__ import annotations

import dataclasses
import sys

from _common import ROOT, machine, parser, rms, square  # noqa: E402  (bench/ is on sys.path; puts the checkout first)

from clvol.render.renderer import Renderer  # noqa: E402
from clvol.runtime import get_runtime  # noqa: E402
from clvol.scene import Phase, load_scene  # noqa: E402

CASES = [  # (scene, albedo, phase)
    ("cloud", 0.999, Phase.hg(0.857)),          # inside the domain, for comparison
    ("cloud", 0.999, Phase.hg(-0.3)),
    ("cloud", 0.999, Phase.hg(-0.7)),
    ("cloud", 0.5, Phase.hg(0.857)),
    ("cloud", 0.95, Phase.mhg([(0.8, 0.7), (-0.3, 0.3)])),
    ("milk", 0.999, Phase.mhg([(0.8, 0.7), (-0.3, 0.3)])),
    ("milk", 0.6, Phase.hg(-0.5)),
]


def main(argv=None) -> int:
    args = parser(__doc__, size=32, spp=64).parse_args(argv)
    print(machine(get_runtime()))
    print(f"{'scene':6s} {'albedo':>6s} {'phase':28s} {'ref mean':>9s} {'ref se':>8s} "
          f"{'none':>8s} {'wrenninge':>9s} {'network':>8s}  best")
    for name, albedo, phase in CASES:
        sc = square(load_scene(ROOT / "tests" / "data" / "scenes" / f"{name}.toml"), args.size)
        sc = dataclasses.replace(sc, medium=dataclasses.replace(sc.medium, albedo=(albedo,) * 3,
                                                                phase=phase))
        grid = sc.volume.load()
        ref = Renderer(sc, "pathtrace", spp=args.spp, seed=1, grid=grid).render()
        se = rms(ref.layers["total_se"])
        err = {}
        for ms in ("none", "wrenninge", "network"):
            kw = {"domain_fallback": False} if ms == "network" else {}
            img = Renderer(sc, ms=ms, grid=grid, **kw).render()
            err[ms] = rms(img.total - ref.total)
        lobes = ",".join(f"{l.g:g}x{l.weight:g}" for l in phase.lobes)
        print(f"{name:6s} {albedo:6g} {lobes:28s} {float(ref.total.mean()):9.5f} {se:8.5f} "
              f"{err['none']:8.5f} {err['wrenninge']:9.5f} {err['network']:8.5f}  "
              f"{min(err, key=err.get)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
