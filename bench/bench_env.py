"""Environment light in the ray marcher: a sky's added frame cost and its precomputation.

    python bench/bench_env.py [--frames 5] [--size 256] [--ms network none]
                              [--env-directions K] [--env-resolution N]
                              [--env-ms-per-frame M]

Scene: the examples' cloud (tests/data/scenes/cloud.toml, 96^3, sun on) at size x size.
Skies: ``none`` (no environment), ``constant`` (a blue sky, [light] environment) and ``map``
(examples/sky_64x32.exr). For each multiple-scattering source (``--ms``) and sky, one
``Renderer`` renders an untimed warm-up frame (kernel builds, sweeps), then ``--frames``
timed frames of each motion:

    static   the same frame again: the static sky's cost is the march's extra lookups
    camera   an orbit, 3 degrees per frame (an anisotropic phase rebuilds the sky's source
             field per camera position: clvol/render/environment.py; with --ms network the
             sky's multiple scattering is the network's, one call per sky cell per position)

Printed per row: median wall and CPU ms per frame and the ratio to the same source without
an environment (target: a static sky adds <= 30%), and the median of the header's
``seconds.environment`` (the environment's host precomputation inside the frame). Then the
precomputation of an environment change, median over ``--frames`` changes, by what changed:
a new sky colour (cells + source field), a new map rotation (the map's cells + field), a new
density scale (K transmittance sweeps + field), for each --ms (network: the network's sky
multiple scattering is part of the field).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import numpy as np

from _common import ROOT, machine, rot_y  # noqa: E402  (puts the checkout first on sys.path)

from clvol.render.renderer import Renderer  # noqa: E402
from clvol.runtime import get_runtime  # noqa: E402
from clvol.scene import load_scene  # noqa: E402

SKY = (0.3, 0.5, 0.9)



def scene_with(sky: str, size: int):
    sc = load_scene(ROOT / "tests" / "data" / "scenes" / "cloud.toml")
    sc = dataclasses.replace(sc, camera=dataclasses.replace(sc.camera, width=size, height=size))
    li = sc.light
    if sky == "constant":
        li = dataclasses.replace(li, environment=SKY)
    elif sky == "map":
        li = dataclasses.replace(li, environment_map=(ROOT / "examples" / "sky_64x32.exr"))
    return dataclasses.replace(sc, light=li)


def options_for(ms: str, env_opts: dict) -> dict:
    """The environment options a source takes: --env-ms-per-frame only where the network
    takes the sky (the escape model of an analytic source has no cells to refresh)."""
    return {k: v for k, v in env_opts.items() if ms == "network" or k != "env_ms_per_frame"}


def warm_up(r) -> None:
    """Untimed frames until nothing is left to refine (kernel builds, sweeps, and with
    --env-ms-per-frame every stale sky cell), so that "static" is a settled frame."""
    for _ in range(300):
        if not r.render().header.get("raymarch.env_refining"):
            return


def timed_interleaved(renderers: dict, changes: list[dict]) -> dict:
    """{name: (median wall, median cpu, median env prep)} over ``changes``, the renderers
    taking turns frame by frame, so that a change of the machine's load during the run falls
    on all of them alike (the ratios are what this benchmark reports)."""
    rows = {name: ([], [], []) for name in renderers}
    for ch in changes:
        for name, r in renderers.items():
            t0, c0 = time.perf_counter(), time.process_time()
            res = r.render(**ch)
            wall, cpu, env = rows[name]
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            env.append(res.header.get("seconds.environment", 0.0))
    return {name: tuple(float(np.median(v)) for v in vals) for name, vals in rows.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--ms", nargs="+", default=["network", "none"])
    ap.add_argument("--env-directions", type=int, default=None)
    ap.add_argument("--env-resolution", type=int, default=None)
    ap.add_argument("--env-ms-per-frame", type=int, default=None,
                    help="the network sky's cells refreshed per frame (default: all)")
    args = ap.parse_args(argv)
    env_opts = {k: v for k, v in (("env_directions", args.env_directions),
                                  ("env_resolution", args.env_resolution),
                                  ("env_ms_per_frame", args.env_ms_per_frame)) if v is not None}
    rt = get_runtime()
    print(machine(rt))
    print(f"cloud 96^3 (tests/data/scenes/cloud.toml, sun on), {args.size}^2, medians over "
          f"{args.frames} frames, the three skies rendered in turn frame by frame; environment "
          f"options: "
          f"{env_opts or 'defaults'} (K directions, N^3 fields); ms = milliseconds")
    grid = scene_with("none", 16).volume.load()
    print(f"{'ms':8s} {'sky':9s} {'motion':7s} {'wall':>8s} {'cpu':>8s} {'wall/none':>9s} "
          f"{'cpu/none':>8s} {'env prep':>9s}")
    verdicts = []
    for ms in args.ms:
        scenes = {sky: scene_with(sky, args.size) for sky in ("none", "constant", "map")}
        opts = options_for(ms, env_opts)
        renderers = {sky: Renderer(sc, grid=grid, ms=ms, **(opts if sky != "none" else {}))
                     for sky, sc in scenes.items()}
        for r in renderers.values():
            warm_up(r)
        cam = scenes["none"].camera                              # the same camera in all three
        for motion in ("static", "camera"):
            if motion == "static":
                changes = [{}] * args.frames
            else:
                changes = [{"camera": dataclasses.replace(cam, origin=rot_y(cam.origin, 3 * i))}
                           for i in range(1, args.frames + 1)]
            got = timed_interleaved(renderers, changes)
            bw, bc, _ = got["none"]
            for sky, (w, c, e) in got.items():
                print(f"{ms:8s} {sky:9s} {motion:7s} {w * 1e3:8.1f} {c * 1e3:8.1f} "
                      f"{w / bw:9.2f} {c / bc:8.2f} {e * 1e3:9.1f}", flush=True)
                if sky != "none" and motion == "static":
                    verdicts.append(f"static {sky} sky, --ms {ms}: {(w / bw - 1) * 100:+.0f}% "
                                    f"wall, {(c / bc - 1) * 100:+.0f}% cpu (target <= +30%): "
                                    f"wall {'met' if w / bw <= 1.3 else 'NOT met'}, cpu "
                                    f"{'met' if c / bc <= 1.3 else 'NOT met'}")
    # Precomputation of an environment change, per source: with --ms none the escape model's
    # (nothing else is recomputed), with --ms network the network's sky cells too.
    print("\nprecomputation of an environment change (header seconds.environment):")
    for ms, what in [(ms, w) for ms in args.ms
                     for w in ("sky colour", "map rotation", "density scale")]:
        sc = scene_with("map" if what == "map rotation" else "constant", args.size)
        r = Renderer(sc, grid=grid, ms=ms, **options_for(ms, env_opts))
        warm_up(r)
        before = dict(r.counts)
        env, res = [], None
        for i in range(1, args.frames + 1):
            if what == "sky colour":
                ch = {"light": dataclasses.replace(sc.light, environment=(0.3, 0.5, 0.9 - 0.05 * i))}
            elif what == "map rotation":
                ch = {"light": dataclasses.replace(sc.light, environment_rotation=10.0 * i)}
            else:
                ch = {"medium": dataclasses.replace(sc.medium,
                                                    density_scale=sc.medium.density_scale * (1 + 0.05 * i))}
            res = r.render(**ch)
            env.append(res.header["seconds.environment"])
        grew = sorted(k for k in r.counts if k.startswith("env_") and r.counts[k] != before.get(k, 0))
        pts = res.header.get("raymarch.env_ms_points")
        print(f"  --ms {ms:8s} {what:14s} {np.median(env) * 1e3:8.1f} ms  (sky multiple "
              f"scattering: {r.plan().env_ms}" + (f", network at {pts} voxels" if pts else "")
              + f"; recomputed: {', '.join(grew)})", flush=True)
    print("\n".join(verdicts))
    print(machine(rt))
    return 0


if __name__ == "__main__":
    sys.exit(main())
