#!/usr/bin/env python
"""A still view's frames, stochastic against progressive, through clvol.Renderer: the first
frame, the second (progressive's first refinement round, which builds the path tracer's
point-query program) and the median of the rest, interleaved in one run.

    python bench/still_frames.py [SCENE.toml] [--size 256] [--frames 8] [--still-images 5]

Then a still image as ``clvol render`` makes it (a new Renderer, ``render(still=True)``: the
default stochastic source draws its 64 samples at once) against the 32^3 lattice
(``ms="network"``), one warm-up each, then ``--still-images`` of each interleaved: medians and
their ratio (docs/raymarch.md, "One default").

Run it with POCL_CACHE_DIR and XDG_CACHE_HOME pointed at empty folders for a cold kernel
cache (what the viewer's first still frame costs on a fresh machine); docs/viewer.md.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from _common import ROOT, machine, square  # noqa: E402  (bench/ is on sys.path)
from clvol.render.renderer import Renderer  # noqa: E402
from clvol.runtime import get_runtime  # noqa: E402
from clvol.scene import load_scene  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene", nargs="?", default=str(ROOT / "examples" / "cloud.toml"))
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--still-images", type=int, default=5,
                    help="still images per source, interleaved (0: skip)")
    args = ap.parse_args(argv)
    print(machine(get_runtime()))
    print(f"scene {args.scene}, {args.size}^2, {args.frames} still frames per source; "
          f"POCL_CACHE_DIR={os.environ.get('POCL_CACHE_DIR', '(default)')}")
    sc = square(load_scene(args.scene), args.size)
    for ms in ("stochastic", "progressive"):
        r = Renderer(sc, ms=ms, env_ms_per_frame=1)
        ts = []
        for _ in range(args.frames):
            t = time.perf_counter()
            r.render()
            ts.append(time.perf_counter() - t)
        print(f"{ms:12s} first {1e3 * ts[0]:7.0f} ms, second {1e3 * ts[1]:7.0f} ms, "
              f"median of the rest {1e3 * float(np.median(ts[2:])):6.0f} ms", flush=True)
    if args.still_images:
        grid = sc.volume.load()
        times = {"stochastic": [], "network": []}
        for i in range(args.still_images + 1):           # the first round warms up
            for ms in times:
                t = time.perf_counter()
                Renderer(sc, ms=ms, grid=grid).render(still=True)
                if i:
                    times[ms].append(time.perf_counter() - t)
        st, net = (float(np.median(times[k])) for k in ("stochastic", "network"))
        print(f"still image (new Renderer, render(still=True)), medians of {args.still_images}: "
              f"stochastic (default, 64 samples) {st:.2f} s, lattice {net:.2f} s, "
              f"ratio {st / net:.2f}", flush=True)
    print(machine(get_runtime()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
