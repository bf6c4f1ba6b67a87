"""libclvol (capi/) vs clvol.Renderer on the same scene: frame, camera change, light change,
density update.

    python bench/bench_c_host.py                       # cloud and jade at their own 256^2
    python bench/bench_c_host.py --size 128 --frames 5

The library is built with ``make -C capi`` (in a temporary copy) and called through ctypes
(the call overhead is microseconds); both hosts run side by side in one process, on the same
OpenCL device. Each figure is the median of N renders, each render after one change:

  frame            render with nothing changed (the march only);
  camera change    the camera moved (alternating between two positions): F_ms lattice toward
                   the camera (host), gather, MLP, F_ms read back, march, image read back;
  light change     the light direction changed (alternating): light field, graded
                   transmittance, bake, lattice, march;
  density update   a new density of the same size (alternating between the scene's and
                   0.9 x it): C ``clvol_set_density`` (upload, majorant, resampled cubes,
                   pyramid, then the light and the lattice); Python has no call for a new
                   density, so its figure is a new ``Renderer(scene, grid=...)`` with a warm
                   program cache, rendering once.

Both run the network at the bundle's active lattice points only. Compare ratios, not
absolute times: the machine line (CPU, device, load average) is printed before and after.
"""
from __future__ import annotations

import argparse
import ctypes
import dataclasses
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import ROOT, load_average, machine  # noqa: E402  (bench/ is on sys.path)
from clvol.bundle import write_bundle  # noqa: E402
from clvol.render.renderer import Renderer  # noqa: E402
from clvol.runtime import get_runtime  # noqa: E402
from clvol.scene import load_scene  # noqa: E402
from clvol.volume.grid import DensityGrid  # noqa: E402

FP = ctypes.POINTER(ctypes.c_float)


def build_library(work: Path) -> ctypes.CDLL:
    src = work / "capi"
    shutil.copytree(ROOT / "capi", src, ignore=shutil.ignore_patterns("build", "libclvol.*"))
    subprocess.run(["make", "-s", "-C", str(src), "libclvol.so"], check=True)
    lib = ctypes.CDLL(str(src / "libclvol.so"))
    vp = ctypes.c_void_p
    lib.clvol_create.argtypes = [ctypes.c_char_p, vp, vp, vp, ctypes.POINTER(vp)]
    lib.clvol_set_camera.argtypes = [vp, FP, FP, FP, ctypes.c_float, ctypes.c_int, ctypes.c_int]
    lib.clvol_set_light.argtypes = [vp, FP, FP]
    lib.clvol_set_density.argtypes = [vp, FP, ctypes.c_int, ctypes.c_int, ctypes.c_int]
    lib.clvol_render.argtypes = [vp, FP]
    lib.clvol_last_error.argtypes = [vp]
    lib.clvol_last_error.restype = ctypes.c_char_p
    lib.clvol_destroy.argtypes = [vp]
    return lib


def f32(v) -> np.ndarray:
    return np.ascontiguousarray(v, np.float32)


def ptr(a: np.ndarray):
    return a.ctypes.data_as(FP)


def timed(fn, n: int) -> float:
    """Median seconds of fn(i) over i = 0..n-1."""
    times = []
    for i in range(n):
        t0 = time.perf_counter()
        fn(i)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def c_figures(lib, bundle, scene, grid, frames):
    r = ctypes.c_void_p()
    t0 = time.perf_counter()
    if lib.clvol_create(str(bundle).encode(), None, None, None, ctypes.byref(r)):
        raise SystemExit(lib.clvol_last_error(None).decode())
    create = time.perf_counter() - t0
    cam = scene.camera
    img = np.empty((cam.height, cam.width, 4), np.float32)

    def check(status):
        if status:
            raise SystemExit(lib.clvol_last_error(r).decode())

    origins = [f32(cam.origin), f32(np.asarray(cam.origin) * 1.05)]
    target, up = f32(cam.target), f32(cam.up)
    dirs = [f32(scene.light.direction), f32(np.asarray(scene.light.direction) + [0.1, 0.05, 0])]
    irr = f32(scene.light.irradiance)
    dens = [f32(grid.density), f32(grid.density * np.float32(0.9))]
    nz, ny, nx = grid.density.shape
    try:
        check(lib.clvol_render(r, ptr(img)))                        # first frame: the lattice
        out = {"create": create}
        out["frame"] = timed(lambda i: check(lib.clvol_render(r, ptr(img))), frames)

        def camera(i):
            check(lib.clvol_set_camera(r, ptr(origins[(i + 1) % 2]), ptr(target), ptr(up),
                                       cam.fov_y, cam.width, cam.height))
            check(lib.clvol_render(r, ptr(img)))
        out["camera"] = timed(camera, frames)

        def light(i):
            check(lib.clvol_set_light(r, ptr(dirs[(i + 1) % 2]), ptr(irr)))
            check(lib.clvol_render(r, ptr(img)))
        out["light"] = timed(light, frames)

        def density(i):
            check(lib.clvol_set_density(r, ptr(dens[(i + 1) % 2]), nx, ny, nz))
            check(lib.clvol_render(r, ptr(img)))
        out["density"] = timed(density, frames)
    finally:
        lib.clvol_destroy(r)
    return out


def python_figures(scene, grid, opts, frames, rt):
    t0 = time.perf_counter()
    r = Renderer(scene, "raymarch", grid=grid, runtime=rt, **opts)
    r.render()
    out = {"create": time.perf_counter() - t0}
    out["frame"] = timed(lambda i: r.render(), frames)
    cams = [scene.camera, dataclasses.replace(
        scene.camera, origin=tuple(float(v) for v in np.asarray(scene.camera.origin) * 1.05))]
    out["camera"] = timed(lambda i: r.render(camera=cams[(i + 1) % 2]), frames)
    lights = [scene.light, dataclasses.replace(scene.light, direction=tuple(
        float(v) for v in np.asarray(scene.light.direction) + [0.1, 0.05, 0]))]
    out["light"] = timed(lambda i: r.render(camera=cams[frames % 2], light=lights[(i + 1) % 2]),
                         frames)
    grids = [grid, DensityGrid(grid.density * np.float32(0.9), grid.bbox_min, grid.bbox_max)]
    out["density"] = timed(lambda i: Renderer(scene, "raymarch", grid=grids[(i + 1) % 2],
                                              runtime=rt, **opts).render(), frames)
    assert r.counts["ms_lattice"] >= 2 * frames
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["cloud.toml", "jade.toml"])
    ap.add_argument("--size", type=int, default=None, help="image side (default: the scene's)")
    ap.add_argument("--ms-resolution", type=int, default=32)
    ap.add_argument("--frames", type=int, default=5, help="renders per figure (median)")
    args = ap.parse_args()
    rt = get_runtime()
    print(machine(rt))
    work = Path(tempfile.mkdtemp(prefix="bench_c_host_"))
    try:
        lib = build_library(work)
        print(f"settings: --ms-resolution {args.ms_resolution}, median of {args.frames} "
              f"renders per figure, image side {args.size or 'of the scene'}")
        cols = ("create", "frame", "camera", "light", "density")
        heads = ("create", "frame", "camera chg", "light chg", "density upd")
        print(f"{'scene':<10} {'size':>9} {'host':<7}" + "".join(f"{h:>12}" for h in heads)
              + "   (ms; C/Py: ratio)")
        for name in args.scenes:
            scene = load_scene(ROOT / "examples" / name)
            if args.size:
                scene = scene.with_overrides({"camera.width": args.size,
                                              "camera.height": args.size})
            grid = scene.volume.load()
            bundle = write_bundle(scene, work / name.replace(".toml", ""),
                                  ms_resolution=args.ms_resolution)
            light_res = int([l for l in (bundle / "manifest.txt").read_text().splitlines()
                             if l.startswith("raymarch.light_resolution")][0].split()[-1])
            # the library keeps the bundle's light resolution on a new density: Python too
            opts = dict(ms_resolution=args.ms_resolution, light_resolution=light_res)
            c_figures(lib, bundle, scene, grid, 1)                  # warm both program caches
            Renderer(scene, "raymarch", grid=grid, runtime=rt, **opts).render()
            c = c_figures(lib, bundle, scene, grid, args.frames)
            py = python_figures(scene, grid, opts, args.frames, rt)
            size = f"{scene.camera.width}x{scene.camera.height}"

            print(f"{name:<10} {size:>9} {'C':<7}" + "".join(f"{c[k] * 1e3:>12.1f}" for k in cols))
            print(f"{'':<10} {'':>9} {'Python':<7}" + "".join(f"{py[k] * 1e3:>12.1f}" for k in cols))
            print(f"{'':<10} {'':>9} {'C/Py':<7}" + "".join(f"{c[k] / py[k]:>12.2f}" for k in cols))
    finally:
        shutil.rmtree(work)
    print(f"load average after: {load_average()}")


if __name__ == "__main__":
    main()
