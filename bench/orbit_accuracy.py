"""Accuracy of the motion levers against the path tracer: the cloud example orbited 3 degrees
per frame for 8 frames; the last frame of each setting against a path-traced reference of that
camera (RMSE of the total image, and the reference's own noise).

    python bench/orbit_accuracy.py [--size 32] [--spp 4096]
"""
from __future__ import annotations

import dataclasses
import math
import sys

from _common import ROOT, machine, parser, rms, square  # noqa: E402  (bench/ is on sys.path; puts the checkout first)

from clvol.render.renderer import Renderer  # noqa: E402
from clvol.runtime import get_runtime  # noqa: E402
from clvol.scene import load_scene  # noqa: E402

NET = {"ms": "network"}
SETTINGS = {"per-position lattice 32^3": NET, "lattice 64^3": {**NET, "ms_resolution": 64},
            "--ms-refresh 4": {**NET, "ms_refresh": 4}, "--ms-refresh 8": {**NET, "ms_refresh": 8},
            "--ms-directions 48": {**NET, "ms_directions": 48},
            "--ms stochastic (default)": {"ms": "stochastic"},
            "--ms wrenninge": {"ms": "wrenninge"}, "--ms none": {"ms": "none"}}


def main(argv=None) -> int:
    args = parser(__doc__, size=32, spp=4096).parse_args(argv)
    print(machine(get_runtime()))
    sc = square(load_scene(ROOT / "tests" / "data" / "scenes" / "cloud.toml"), args.size)
    grid = sc.volume.load()

    def cam(i):
        a = math.radians(3 * i)
        x, y, z = sc.camera.origin
        return dataclasses.replace(sc.camera, origin=(x * math.cos(a) + z * math.sin(a), y,
                                                      -x * math.sin(a) + z * math.cos(a)))
    last = dataclasses.replace(sc, camera=cam(8))
    ref = Renderer(last, "pathtrace", spp=args.spp, seed=5, grid=grid).render()
    noise = rms(ref.layers["total_se"])
    print(f"reference: {args.spp} spp at {args.size}^2, image mean {ref.total.mean():.5f}, "
          f"RMS standard error {noise:.2e}")
    for name, opts in SETTINGS.items():
        r = Renderer(sc, grid=grid, **opts)
        for i in range(9):
            img = r.render(camera=cam(i))
        err = rms(img.total - ref.total)
        print(f"{name:38s} RMSE {err:.3e}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
