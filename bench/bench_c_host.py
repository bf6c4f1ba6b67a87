"""C host (examples/c/clvol-render) vs the Python host on the same bundle: frame time.

    python bench/bench_c_host.py                       # cloud and jade at their own 256^2
    python bench/bench_c_host.py --size 128 --frames 5

A frame is what a moving camera costs with the volume and light fixed: the F_ms lattice
toward the camera (host), gather, MLP, reading F_ms back, the ray march and reading the
image back. C: ``clvol-render --frames N`` (median of N frames in one process, after one
warm-up process that fills PoCL's kernel cache). Python: ``clvol.Renderer.render`` with the
camera moved by 1e-9 per frame (so the lattice is refilled at the same points, as in C; graded
fields and bake cached), median of N. Both run the network at the bundle's active lattice
points only. Also printed: the light change (light field + graded fields + bake) and the
whole run of one frame (C: one process incl. reading the bundle and building the programs
from PoCL's cache; Python: a new Renderer in a warm process, programs built). Both hosts
run side by side in one session; compare ratios, not absolute times (machine line).
"""
from __future__ import annotations

import argparse
import dataclasses
import re
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import ROOT, machine  # noqa: E402  (bench/ is on sys.path; puts the checkout first)
from clvol.bundle import write_bundle  # noqa: E402
from clvol.kernels.gather import bake_render_grid  # noqa: E402
from clvol.render.network import NetworkSource, shipped_weights  # noqa: E402
from clvol.render.raymarch import RayMarcher  # noqa: E402
from clvol.render.renderer import Renderer  # noqa: E402
from clvol.runtime import get_runtime  # noqa: E402
from clvol.scene import load_scene  # noqa: E402

LINE = re.compile(r"setup \(build \+ volume\) ([\d.]+) s, light ([\d.]+) s, frame median "
                  r"([\d.]+) s over \d+, total ([\d.]+) s")


def c_run(exe, bundle, frames):
    r = subprocess.run([str(exe), str(bundle), str(Path(bundle) / "out.pfm"), "--frames",
                        str(frames)], capture_output=True, text=True)
    if r.returncode:
        raise SystemExit(r.stderr)
    m = LINE.search(r.stderr)
    return {"setup": float(m[1]), "light": float(m[2]), "frame": float(m[3]), "total": float(m[4])}


def python_frames(scene, ms_res, frames):
    rt = get_runtime()
    grid = scene.volume.load()
    rm = RayMarcher(grid, scene.medium, rt)
    src = NetworkSource(shipped_weights(), grid, scene.medium, rt)
    w = src.weights
    t0 = time.perf_counter()                               # what C's "light" times
    rm.set_light(scene.light.direction)
    graded = src.graded(scene.light.direction)
    bake_render_grid(src.pyramid, graded, scene.medium.density_scale, w.level_weights, w.level_bias)
    rt.finish()
    light = time.perf_counter() - t0
    r = Renderer(scene, "raymarch", ms_resolution=ms_res, runtime=rt)
    r.render()
    times = []
    for i in range(frames):
        o = np.asarray(scene.camera.origin, np.float64) + 1e-9 * (i + 1)
        cam = dataclasses.replace(scene.camera, origin=tuple(o))
        t0 = time.perf_counter()
        res = r.render(camera=cam)
        times.append(time.perf_counter() - t0)
        assert res.header["raymarch.ms"] == "network"
    assert r.counts["ms_lattice"] == frames + 1       # every frame refilled the lattice
    return light, float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["cloud.toml", "jade.toml"])
    ap.add_argument("--size", type=int, default=None, help="image side (default: the scene's)")
    ap.add_argument("--ms-resolution", type=int, default=32)
    ap.add_argument("--frames", type=int, default=7)
    args = ap.parse_args()
    rt = get_runtime()
    print(machine(rt))
    work = Path(tempfile.mkdtemp(prefix="bench_c_host_"))
    for name in ("clvol_render.c", "Makefile"):
        shutil.copy(ROOT / "examples" / "c" / name, work / name)
    subprocess.run(["make", "-s", "-C", str(work), "clvol-render"], check=True)
    exe = work / "clvol-render"
    print(f"{'scene':<10} {'size':>7} {'host':<7} {'frame (median)':>15} {'light change':>13} "
          f"{'whole run':>10}")
    for name in args.scenes:
        scene = load_scene(ROOT / "examples" / name)
        if args.size:
            scene = scene.with_overrides({"camera.width": args.size, "camera.height": args.size})
        bundle = write_bundle(scene, work / name.replace(".toml", ""),
                              ms_resolution=args.ms_resolution)
        c_run(exe, bundle, 1)                                   # warm PoCL's kernel cache
        Renderer(scene, "raymarch", ms_resolution=args.ms_resolution).render()  # warm Python
        c = c_run(exe, bundle, args.frames)
        c["total"] = c_run(exe, bundle, 1)["total"]
        light, frame = python_frames(scene, args.ms_resolution, args.frames)
        t0 = time.perf_counter()
        Renderer(scene, "raymarch", ms_resolution=args.ms_resolution).render()
        whole = time.perf_counter() - t0
        size = f"{scene.camera.width}^2"
        print(f"{name:<10} {size:>7} {'C':<7} {c['frame'] * 1e3:>12.1f} ms {c['light']:>11.3f} s "
              f"{c['total']:>8.2f} s")
        print(f"{'':<10} {'':>7} {'Python':<7} {frame * 1e3:>12.1f} ms {light:>11.3f} s "
              f"{whole:>8.2f} s")
        print(f"{'':<10} {'':>7} {'C/Py':<7} {c['frame'] / frame:>15.2f} "
              f"{c['light'] / light:>13.2f} {c['total'] / whole:>10.2f}")
    print(machine(rt).split("; ")[-2])
    shutil.rmtree(work)


if __name__ == "__main__":
    main()
