"""What accuracy costs in time: every clvol method on one scene, error against a long path-traced
reference of our own, with the seconds each took, measured in one run.

    python bench/accuracy_vs_time.py [--scene examples/cloud.toml] [--size 128] [--ref-spp 1024]
                                     [--quick] [--out out/bench]

Methods and settings (each point is the median of up to 3 renders, timed warm: kernels are compiled by a first
untimed run at the smallest setting):
  pathtrace     spp 1, 4, 16, 64, 256 (unbiased; error falls as 1/sqrt(time))
  raymarch/none        single scattering only, step 2, 1, 0.5 voxels
  raymarch/wrenninge   + Wrenninge octaves (N=3, a=b=c=0.5), step 2, 1, 0.5 voxels
  raymarch/lattice        + F_ms from a lattice of path-traced point queries (8^3 and 16^3 points,
                       64 paths each); the time includes filling the lattice
  raymarch/network     + F_ms from the trained network (--weights, default
                       clvol/data/weights/full_albedo.npz) on a 16^3, 32^3 and 64^3 lattice: frame = the
                       march; light update = graded transmittance + gather + network fill + the
                       light field (the lattice depends on the camera too: a camera move costs
                       the gather + network part again)
  raymarch/view        + the same network at the camera's view (--ms view), blocks of 4, 2 and
                       1 pixels: frame = the march; light update = light field + query depths +
                       gather + network (a camera move costs the same)
  raymarch/stochastic  + the same network at one free-flight point per pixel block per frame
                       (--ms stochastic), after 1, 4, 16 and 64 frames of a still view: frame =
                       the median whole frame (a draw, the queries and the march); light update
                       = the N frames since the change, summed (what an image of that quality
                       costs after a change; the first frame rebuilds the light field)
  raymarch/progressive + that source refined by path-traced point queries (--ms progressive),
                       after --progressive checkpoints (default 0.1, 0.3, 1, 3, 10, 30 s of wall
                       time since a light change): frame = the march; light update = the wall
                       time since the change (the first frame and the rounds)
Times: "frame" is what one more image costs (the march for the ray marcher; the whole render
for the path tracer), "light update" what a light change costs once (the light field, and the
lattice fill for the lattice source). Errors: the MRPNN metric (RMSE x 100 of tonemapped 8-bit luminance), relMSE and RMSE against the
reference (a different seed from the test renders). Writes a CSV and an SVG plot (log-log,
error against seconds) to --out, and prints the table.
"""
from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

import numpy as np

from _common import ROOT, machine, square  # noqa: E402  (bench/ is on sys.path; puts the checkout first)
from clvol.image import read_exr, write_exr  # noqa: E402
from clvol.metrics import compare_images  # noqa: E402
from clvol.render.ms.network import NetworkSource  # noqa: E402
from clvol.render.pathtrace import point_query, render_pathtrace  # noqa: E402
from clvol.render.raymarch import RayMarcher  # noqa: E402
from clvol.render.ms.lattice import fill_fms_lattice  # noqa: E402
from clvol.runtime import get_runtime  # noqa: E402
from clvol.scene import load_scene  # noqa: E402


def reference(scene, grid, spp, out_dir: Path):
    """The long path-traced reference, cached on disk by (scene, size, spp)."""
    cam = scene.camera
    name = f"ref_{Path(scene.path).stem}_{cam.width}x{cam.height}_{spp}spp.exr"
    path = out_dir / name
    if path.exists():
        img = read_exr(path)
        print(f"reference: {path} (cached; {img.header.get('seconds', '?')} s when made)")
        return img.rgb
    print(f"reference: path tracing {spp} spp at {cam.width}x{cam.height} ...", flush=True)
    res = render_pathtrace(scene, spp=spp, seed=987654321, grid=grid)
    write_exr(path, {"total": res.layers["total"]}, res.header)
    print(f"reference: {res.header.get('seconds')} s, written to {path}")
    return res.layers["total"]


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def median_of(n, fn):
    """(result of the last run, median seconds of n runs): the machine is shared; the
    median is the project's figure for a time (docs/testing.md, benchmarks)."""
    out, times = None, []
    for _ in range(n):
        out, t = timed(fn)
        times.append(t)
    return out, float(np.median(times))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default=str(ROOT / "examples" / "cloud.toml"))
    ap.add_argument("--size", type=int, default=128, help="image width and height")
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--quick", action="store_true", help="64x64, 256-spp reference, fewer points")
    ap.add_argument("--out", default=str(ROOT / "out" / "bench"))
    ap.add_argument("--weights", default=str(ROOT / "clvol" / "data" / "weights" / "full_albedo.npz"),
                    help="network weight file for the raymarch/network points ('' to skip them)")
    ap.add_argument("--progressive", type=float, nargs="*", default=[0.1, 0.3, 1, 3, 10, 30],
                    metavar="SECONDS",
                    help="checkpoints (wall seconds after a light change) of the "
                         "raymarch/progressive rows (none: skip them)")
    ap.add_argument("--only", nargs="*", default=None, metavar="METHOD",
                    help="run only these method groups (pathtrace, simple, lattice, network, "
                         "view, stochastic, progressive; default all)")
    args = ap.parse_args(argv)
    if args.quick:
        args.size, args.ref_spp = 64, 256
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)

    rt = get_runtime()
    scene = square(load_scene(args.scene), args.size)
    grid = scene.volume.load()
    print(machine(rt))
    print(f"scene: {args.scene}, {args.size}x{args.size}, grid {grid.resolution}, "
          f"density_scale {scene.medium.density_scale}, albedo {scene.medium.albedo}, "
          f"phase {scene.medium.phase.type} {[(l.g, l.weight) for l in scene.medium.phase.lobes]}")
    ref = reference(scene, grid, args.ref_spp, out_dir)

    # Warm-up: compile the path tracer once, untimed.
    render_pathtrace(scene, spp=1, grid=grid, progress=False)
    rows = []

    def record(method, setting, layers, frame, light=0.0):
        """frame: the per-frame cost (the march for the ray marcher, the whole render for the
        path tracer); light: the once-per-light-change cost (light field, lattice fill)."""
        m = compare_images(layers["total"], ref)
        rows.append({"method": method, "setting": setting, "seconds": frame,
                     "light_update_seconds": light, **m})
        print(f"  {method:<19} {setting:<27} {frame:8.3f} s {light:8.3f} s   MRPNN {m['mrpnn']:7.3f}"
              f"   relMSE {m['relmse']:.3e}   RMSE {m['rmse']:.3e}", flush=True)

    print("\nmethod              setting                        frame  light upd.   error vs reference")
    spps = (1, 4, 16, 64) if args.quick else (1, 4, 16, 64, 256)
    def want(group):
        return args.only is None or group in args.only

    for spp in (spps if want("pathtrace") else ()):
        repeats = 3 if spp <= 16 else 1
        res, s = median_of(repeats, lambda: render_pathtrace(scene, spp=spp, seed=1, grid=grid,
                                                           progress=False))
        record("pathtrace", f"{spp} spp", res.layers, s)

    # The ray marcher as a real-time renderer uses it: volume resident on the device, the light
    # field remade when the light moves (timed as a change from another direction), then frames.
    rm = RayMarcher(grid, scene.medium, rt)
    other = np.array(scene.light.direction) + np.array([0.3, 0.0, -0.2])
    rm.set_light(other / np.linalg.norm(other))  # builds the pyramid once, untimed

    def light_change():
        rm.set_light(other / np.linalg.norm(other))
        rm.rt.finish()
        rm.set_light(scene.light.direction)
        rm.rt.finish()

    light_s = median_of(3, light_change)[1] / 2  # two light changes per run
    cam = scene.camera
    for ms in (("none", "wrenninge") if want("simple") else ()):
        for step in (2.0, 1.0, 0.5):
            rm.march_with(cam, scene.light, ms, step=step)  # compile this variant, untimed
            (layers, _), s = median_of(3, lambda: rm.march_with(cam, scene.light, ms, step=step))
            record(f"raymarch/{ms}", f"step {step:g} voxel", layers, s, light_s)
    for lattice in ((8,) if args.quick else (8, 16)) if want("lattice") else ():
        def query(points, omegas):
            return point_query(scene, points, omegas, n_paths=64, seed=2, grid=grid)["Fms"]
        msg, fill_s = timed(lambda: fill_fms_lattice(scene, lattice, query, grid.bbox_min,
                                                 grid.bbox_max))
        rm.march_with(cam, scene.light, "lattice", ms_lattice=msg)
        (layers, _), s = median_of(3, lambda: rm.march_with(cam, scene.light, "lattice", ms_lattice=msg))
        record("raymarch/lattice", f"{lattice}^3 lattice, 64 paths", layers, s, light_s + fill_s)

    if args.weights and Path(args.weights).exists():
        src = NetworkSource(args.weights, grid, scene.medium, rt)
        unit_other = other / np.linalg.norm(other)
        for lattice in ((16, 32) if args.quick else (16, 32, 64)) if want("network") else ():
            src.fill(unit_other, lattice, origin=scene.camera.origin)   # compile and bake once, untimed

            def network_change():
                """Two light changes (graded T + gather + network); info of the second."""
                a = src.fill(unit_other, lattice, origin=scene.camera.origin)[1]
                msg, b = src.fill(scene.light.direction, lattice, origin=scene.camera.origin)
                return msg, {k: (a[k] + b[k]) / 2 for k in ("light", "gather", "network")}
            (msg, info), _ = median_of(3, network_change)
            fill_s = info["light"] + info["gather"] + info["network"]
            rm.march_with(cam, scene.light, "lattice", ms_lattice=msg)
            (layers, _), s = median_of(3, lambda: rm.march_with(cam, scene.light, "lattice", ms_lattice=msg))
            record("raymarch/network", f"{lattice}^3 lattice", layers, s, light_s + fill_s)
            print(f"{'':21}(light update: light field {light_s:.3f} s, graded T {info['light']:.3f} s, "
                  f"gather {info['gather']:.3f} s, network {info['network']:.3f} s)")
        # The same network queried where the camera sees (clvol/render/ms/view.py): per block of
        # pixels. An unchanged view costs the march; a light (or camera) change costs the light
        # field, the query depths, the gather and the network (from the render's header).
        import dataclasses
        from clvol.render.renderer import Renderer
        for block in ((4,) if args.quick else (4, 2, 1)) if want("view") else ():
            r = Renderer(scene, "raymarch", grid=grid, ms="view", view_block=block,
                         weights=args.weights)
            moved = dataclasses.replace(scene.light, direction=tuple(unit_other))
            r.render(light=moved)                       # compile, untimed
            updates = []
            for _ in range(3):                          # a light change each way, median of 3
                r.render(light=moved)
                h = r.render().header
                updates.append(sum(float(h.get(k, 0.0)) for k in (
                    "seconds.light_field", "seconds.graded_transmittance", "seconds.view_depths",
                    "seconds.gather", "seconds.network")))
            res, _ = median_of(3, r.render)               # unchanged: the march
            record("raymarch/view", f"block {block}", res.layers,
                   float(res.header["seconds.march"]), float(np.median(updates)))
        # Stochastic: frames of a still view after a light change (which starts it afresh).
        r = Renderer(scene, "raymarch", grid=grid, ms="stochastic", weights=args.weights)
        r.render(light=dataclasses.replace(scene.light, direction=tuple(unit_other)))  # compile
        walls = []
        for frame in range(1, 65) if want("stochastic") else ():
            res, s = timed(r.render)          # the first after the change resets the history
            walls.append(s)
            if frame in (1, 4, 16, 64):
                # frame: the median frame so far; per change: all N frames since the change
                # (the first rebuilds the light field)
                record("raymarch/stochastic",
                       f"block {r.source.block}, {frame} frame{'s' * (frame > 1)}",
                       res.layers, float(np.median(walls)), float(sum(walls)))
        # Progressive (--ms progressive): the stochastic view refined by path-traced point
        # queries. After a light change (which starts it afresh): the first frame, then rounds
        # until each checkpoint of wall time since the change; the error after that long.
        if args.progressive and want("progressive"):
            r = Renderer(scene, "raymarch", grid=grid, ms="progressive", weights=args.weights,
                         seed=3)
            r.render(light=dataclasses.replace(scene.light, direction=tuple(unit_other)))
            r.render(light=dataclasses.replace(scene.light, direction=tuple(unit_other)))
            t0 = time.perf_counter()
            res = r.render()                             # the change: the first frame
            for cp in args.progressive:
                left = cp - (time.perf_counter() - t0)
                if left > 0:
                    r.source.budget = left
                    res = r.render()
                spent = time.perf_counter() - t0
                h = res.header
                record("raymarch/progressive",
                       f"{cp:g} s ({h['raymarch.progressive_rounds']} rounds, "
                       f"{h['raymarch.progressive_paths_per_block'].split(',')[0]} paths/block)",
                       res.layers, float(h["seconds.march"]), spent)
    elif args.weights:
        print(f"raymarch/network skipped: no weight file {args.weights}")

    csv_path = out_dir / f"accuracy_vs_time_{Path(args.scene).stem}_{args.size}.csv"
    with open(csv_path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    svg_path = csv_path.with_suffix(".svg")
    svg_path.write_text(svg_plot(rows, f"{Path(args.scene).name} {args.size}x{args.size}, "
                                       f"reference {args.ref_spp} spp"))
    print(f"\nwrote {csv_path} and {svg_path}")
    print(machine(rt))                                   # the load after the run
    return 0


def svg_plot(rows, title: str, w: int = 640, h: int = 420) -> str:
    """A log-log scatter of MRPNN error against seconds, one colour per method (no plotting
    dependency: a plain SVG): filled dots joined by a line at the per-frame cost, rings joined
    by a dashed line at the per-change cost (light update) where a method has one."""
    xs = np.array([r["seconds"] for r in rows] +
                  [r["light_update_seconds"] for r in rows if r["light_update_seconds"] > 0])
    ys = np.array([max(r["mrpnn"], 1e-3) for r in rows])
    lx0, lx1 = np.floor(np.log10(xs.min())), np.ceil(np.log10(xs.max()))
    ly0, ly1 = np.floor(np.log10(ys.min())), np.ceil(np.log10(ys.max()))
    ml, mr, mt, mb = 60, 170, 30, 45

    def px(x):
        return ml + (np.log10(x) - lx0) / max(lx1 - lx0, 1) * (w - ml - mr)

    def py(y):
        return h - mb - (np.log10(y) - ly0) / max(ly1 - ly0, 1) * (h - mt - mb)

    colours = {"pathtrace": "#1f77b4", "raymarch/none": "#7f7f7f",
               "raymarch/wrenninge": "#ff7f0e", "raymarch/lattice": "#2ca02c",
               "raymarch/network": "#d62728", "raymarch/view": "#9467bd",
               "raymarch/stochastic": "#8c564b", "raymarch/progressive": "#e377c2"}
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" '
           f'font-family="sans-serif" font-size="11">',
           f'<rect width="{w}" height="{h}" fill="white"/>',
           f'<text x="{ml}" y="18" font-size="13">{title}</text>']
    for e in range(int(lx0), int(lx1) + 1):
        x = px(10.0 ** e)
        out.append(f'<line x1="{x:.1f}" y1="{mt}" x2="{x:.1f}" y2="{h - mb}" stroke="#ddd"/>')
        out.append(f'<text x="{x:.1f}" y="{h - mb + 15}" text-anchor="middle">1e{e} s</text>')
    for e in range(int(ly0), int(ly1) + 1):
        y = py(10.0 ** e)
        out.append(f'<line x1="{ml}" y1="{y:.1f}" x2="{w - mr}" y2="{y:.1f}" stroke="#ddd"/>')
        out.append(f'<text x="{ml - 5}" y="{y + 4:.1f}" text-anchor="end">{10.0 ** e:g}</text>')
    out.append(f'<text x="{(ml + w - mr) / 2}" y="{h - 8}" text-anchor="middle">seconds per '
               f'frame (dots) and per light change (rings), log</text>')
    out.append(f'<text x="14" y="{(mt + h - mb) / 2}" transform="rotate(-90 14 {(mt + h - mb) / 2})" '
               f'text-anchor="middle">MRPNN error (log)</text>')
    for k, (method, colour) in enumerate(colours.items()):
        pts = [(px(r["seconds"]), py(max(r["mrpnn"], 1e-3))) for r in rows if r["method"] == method]
        if not pts:
            continue
        path = " ".join(f"{x:.1f},{y:.1f}" for x, y in pts)
        out.append(f'<polyline points="{path}" fill="none" stroke="{colour}" stroke-width="1.5"/>')
        out += [f'<circle cx="{x:.1f}" cy="{y:.1f}" r="3.5" fill="{colour}"/>' for x, y in pts]
        change = [(px(r["light_update_seconds"]), py(max(r["mrpnn"], 1e-3))) for r in rows
                  if r["method"] == method and r["light_update_seconds"] > 0]
        if change:
            path = " ".join(f"{x:.1f},{y:.1f}" for x, y in change)
            out.append(f'<polyline points="{path}" fill="none" stroke="{colour}" '
                       f'stroke-width="1" stroke-dasharray="4 3"/>')
            out += [f'<circle cx="{x:.1f}" cy="{y:.1f}" r="3.5" fill="white" stroke="{colour}"/>'
                    for x, y in change]
        ly = mt + 10 + 18 * k
        out.append(f'<circle cx="{w - mr + 15}" cy="{ly}" r="4" fill="{colour}"/>')
        out.append(f'<text x="{w - mr + 25}" y="{ly + 4}">{method}</text>')
    out.append("</svg>")
    return "\n".join(out)


if __name__ == "__main__":
    sys.exit(main())
