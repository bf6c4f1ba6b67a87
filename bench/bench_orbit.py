"""Frame cost under motion: the default method (raymarch + network MS) next to the plain
single-scattering march of the same frames, in one run.

    python bench/bench_orbit.py [--frames 5] [--sizes 256 512] [--volumes cloud cloud128 cloud256]
                                [--ms network|view|stochastic|progressive] [--view-block B]
                                [--view-knots K]
                                [--view-samples N]

Volumes: ``cloud`` (examples' cloud, 96^3, tests/data/scenes/cloud.toml) and the same cloud
generator at 128^3 and 256^3. Motions, one change every frame: ``camera`` (an orbit, 3 degrees
per frame), ``light`` (the light turns 5 degrees per frame), ``medium`` (albedo and g
alternate). Each (volume, size, motion) keeps one ``Renderer`` per method, renders one
untimed warm-up frame (kernel builds), then ``--frames`` timed frames, the two methods
interleaved frame by frame (one change rendered by each, then the next). Printed per row:
median frame time of each method and their ratio (wall clock and this process's CPU time), and
the default method's median split by stage (light field, graded transmittance, view-space
query depths, gather, network, interpolation of the view-independent cache, march; a stage the
change did not invalidate costs 0). ``--ms view`` times the view-space source instead of the
world lattice (clvol/render/ms/view.py), ``--ms stochastic`` its stochastic mode (one draw per
block per frame; the camera motion then includes the reprojection stage). Targets (docs/raymarch.md): camera motion at 256^2 costs <= 1.5x the
plain march; a light change costs <= 250 ms at 128^3.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import numpy as np

from _common import ROOT, machine, rot_y  # noqa: E402  (bench/ is on sys.path; puts the checkout first)

from clvol.render.renderer import Renderer  # noqa: E402
from clvol.runtime import get_runtime  # noqa: E402
from clvol.scene import Phase, load_scene  # noqa: E402

STAGES = ("light_field", "graded_transmittance", "view_depths", "view_reproject", "gather",
          "network", "ms_interpolate", "march")


def base_scene(volume: str, size: int):
    sc = load_scene(ROOT / "tests" / "data" / "scenes" / "cloud.toml")
    if volume != "cloud":
        n = int(volume[len("cloud"):])
        sc = dataclasses.replace(sc, volume=dataclasses.replace(sc.volume, resolution=n))
    return dataclasses.replace(sc, camera=dataclasses.replace(sc.camera, width=size, height=size))



def frames(scene, motion: str, n: int) -> list[dict]:
    out = []
    for i in range(1, n + 1):
        if motion == "camera":
            out.append({"camera": dataclasses.replace(scene.camera,
                                                      origin=rot_y(scene.camera.origin, 3 * i))})
        elif motion == "light":
            out.append({"light": dataclasses.replace(scene.light,
                                                     direction=rot_y(scene.light.direction, 5 * i))})
        else:
            a = 0.99 if i % 2 else 0.95
            g = 0.8 if i % 2 else 0.857
            out.append({"medium": dataclasses.replace(scene.medium, albedo=(a, a, a),
                                                      phase=Phase.hg(g))})
    return out


def _frame(renderer: Renderer, change: dict, times: list, cpu: list, stages: dict) -> None:
    """Render one change, recording its wall and CPU time and the stages it recomputed."""
    before = dict(renderer.counts)
    t0, c0 = time.perf_counter(), time.process_time()
    res = renderer.render(**change)
    times.append(time.perf_counter() - t0)
    cpu.append(time.process_time() - c0)
    h = res.header
    grew = {k for k in renderer.counts if renderer.counts[k] != before.get(k, 0)}
    stages["light_field"].append(h["seconds.light_field"] if "light_field" in grew else 0.0)
    filled = "ms_lattice" in grew or "ms_view_table" in grew
    stages["view_depths"].append(h.get("seconds.view_depths", 0.0) if filled else 0.0)
    stages["view_reproject"].append(h.get("seconds.view_reproject", 0.0) if filled else 0.0)
    stages["graded_transmittance"].append(
        h.get("seconds.graded_transmittance", 0.0) if "graded_transmittance" in grew else 0.0)
    stages["gather"].append(h.get("seconds.gather", 0.0) if filled else 0.0)
    stages["network"].append(h.get("seconds.network", 0.0) if filled else 0.0)
    stages["ms_interpolate"].append(h.get("seconds.ms_interpolate", 0.0) if filled else 0.0)
    stages["march"].append(h["seconds.march"])


def run(renderers: list[Renderer], todo: list[dict]) -> list[tuple[list[float], dict]]:
    """Each renderer's (wall times, median stages and CPU) over ``todo``, the renderers
    interleaved frame by frame (change i by each, then change i + 1), so that a change of
    the machine's load falls on both sides of the ratio alike."""
    for r in renderers:
        r.render()                                     # warm-up: builds, uploads, first fill
    rec = [([], [], {s: [] for s in STAGES}) for _ in renderers]
    for change in todo:
        for r, (times, cpu, stages) in zip(renderers, rec):
            _frame(r, change, times, cpu, stages)
    out = []
    for times, cpu, stages in rec:
        st = {k: float(np.median(v)) for k, v in stages.items()}
        st["cpu"] = float(np.median(cpu))
        out.append((times, st))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--volumes", nargs="+", default=["cloud", "cloud128", "cloud256"])
    ap.add_argument("--motions", nargs="+", default=["camera", "light", "medium"])
    ap.add_argument("--ms-resolution", type=int, default=None,
                    help="network lattice points per side (default: the Renderer's)")
    ap.add_argument("--ms-directions", type=int, default=None,
                    help="network view-independent cache directions (default: the Renderer's)")
    ap.add_argument("--ms-refresh", type=int, default=None,
                    help="network progressive refresh, 1/K of the lattice per camera move "
                         "(default: the Renderer's)")
    ap.add_argument("--ms", choices=["network", "view", "stochastic", "progressive"],
                    default="network",
                    help="the multiple-scattering source of the timed method (default network)")
    ap.add_argument("--view-block", type=int, default=None, help="--ms view: block side")
    ap.add_argument("--view-knots", type=int, default=None, help="--ms view: queries per block")
    ap.add_argument("--view-samples", type=int, default=None,
                    help="--ms stochastic: draws per block per frame")
    args = ap.parse_args(argv)
    reads = {"network": ("ms_resolution", "ms_directions", "ms_refresh"),
             "view": ("view_block", "view_knots"),
             "stochastic": ("view_block", "view_samples"),
             "progressive": ("view_block",)}[args.ms]
    unused = [n for n in ("ms_resolution", "ms_directions", "ms_refresh", "view_block",
                          "view_knots", "view_samples") if getattr(args, n) and n not in reads]
    if unused:
        ap.error(f"--{unused[0].replace('_', '-')} is not read with --ms {args.ms}")
    rt = get_runtime()
    print(machine(rt))
    print(f"medians over {args.frames} frames, one change per frame; ms = milliseconds; "
          f"default method options: ms_resolution={args.ms_resolution or 'default'}, "
          f"ms_directions={args.ms_directions or 0}, ms_refresh={args.ms_refresh or 1}, "
          f"ms={args.ms}" + "".join(f", {n}={getattr(args, n) or 'default'}" for n in reads
                                    if args.ms != "network"))
    print("default/plain: wall-clock ms per frame; cpu: CPU time of this process (host + PoCL "
          "threads) per frame, less sensitive to other processes' load")
    print(f"{'volume':9s} {'size':>5s} {'motion':7s} {'timed':>8s} {'plain':>7s} {'ratio':>6s} "
          f"{'cpu def':>8s} {'cpu pl':>7s} {'ratio':>6s} "
          + " ".join(f"{s[:12]:>12s}" for s in STAGES) + "  network points")
    verdicts = []
    for volume in args.volumes:
        grid = base_scene(volume, 16).volume.load()
        for size in args.sizes:
            sc = base_scene(volume, size)
            for motion in args.motions:
                todo = frames(sc, motion, args.frames)
                kw = {n: getattr(args, n) for n in reads if getattr(args, n) is not None}
                d = Renderer(sc, grid=grid, ms=args.ms, **kw)
                (td, st), (tp, sp) = run([d, Renderer(sc, ms="none", grid=grid)], todo)
                md, mp = float(np.median(td)), float(np.median(tp))
                pts = d.source.info["points"] if d.source.info else 0
                cd, cp = st["cpu"], sp["cpu"]
                print(f"{volume:9s} {size:5d} {motion:7s} {md * 1e3:8.1f} {mp * 1e3:7.1f} "
                      f"{md / mp:6.2f} {cd * 1e3:8.1f} {cp * 1e3:7.1f} {cd / cp:6.2f} " + " ".join(f"{st[s] * 1e3:12.1f}" for s in STAGES)
                      + f"  {pts}", flush=True)
                if motion == "camera" and size == 256:
                    verdicts.append(f"camera motion, {volume}, 256^2: default / plain = "
                                    f"{md / mp:.2f} wall, {cd / cp:.2f} cpu (target <= 1.5): "
                                    f"wall {'met' if md / mp <= 1.5 else 'NOT met'}, "
                                    f"cpu {'met' if cd / cp <= 1.5 else 'NOT met'}")
                if motion == "light" and volume == "cloud128":
                    verdicts.append(f"light change, 128^3, {size}^2: {md * 1e3:.0f} ms per frame "
                                    f"wall, {cd * 1e3:.0f} ms cpu (target <= 250 ms): "
                                    f"wall {'met' if md <= 0.25 else 'NOT met'}, "
                                    f"cpu {'met' if cd <= 0.25 else 'NOT met'}")
    print("\n".join(verdicts))
    print(machine(rt))
    return 0


if __name__ == "__main__":
    sys.exit(main())
