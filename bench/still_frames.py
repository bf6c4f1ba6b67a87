#!/usr/bin/env python
"""A still view's frames, stochastic against progressive, through clvol.Renderer: the first
frame, the second (progressive's first refinement round, which builds the path tracer's
point-query program) and the median of the rest, interleaved in one run.

    python bench/still_frames.py [SCENE.toml] [--size 256] [--frames 8]

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
    print(machine(get_runtime()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
