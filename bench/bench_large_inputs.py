#!/usr/bin/env python3
"""Memory and time under large input (issue 26, item 5): three cases, each in a fresh process
so that its peak resident set (ru_maxrss) is its own.

    python bench/bench_large_inputs.py vdb    [--extent 2048] [--balls 12] [--max-resolution 256]
    python bench/bench_large_inputs.py render [--size 4096]
    python bench/bench_large_inputs.py loop   [--frames 10000] [--size 32] [--ms network]

- ``vdb``: OpenVDB (system Python, tests/openvdb_fixtures.py) writes a sparse cloud whose
  active region spans the whole ``extent``^3 (soft balls in the middle, a small ball in two
  opposite corners); clvol reads it with ``max_resolution`` (time, peak RSS, output size, mass),
  and ``clvol render`` of a scene naming the file without ``max_resolution`` must refuse it in
  one line (exit 2) before allocating the dense grid (its peak RSS is printed too).
- ``render``: ``clvol render examples/cloud.toml --width S --height S -o big.exr --quiet`` (the
  default method), wall time and the peak RSS of that process (and of its children).
- ``loop``: one ``Renderer`` of examples/cloud.toml at ``size``^2, the camera orbiting 1 degree
  a frame, ``frames`` renders; RSS (/proc/self/statm) and the OpenCL buffers alive
  (pyopencl Buffer objects found by the garbage collector: count and bytes; clvol allocates
  every buffer through clvol.runtime, and a live Buffer object holds its device memory) at
  frames 1, 10, 100, 1000, ... and the last; growth from frame 100 to the last.

Prints the machine line, the settings and the figures.
"""
from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import ROOT, machine  # noqa: E402  (bench/ is on sys.path; puts the checkout first)

PAGE = os.sysconf("SC_PAGE_SIZE")


def mib(n: float) -> str:
    return f"{n / 2**20:.1f} MiB"


def rss_now() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE


def peak_rss_self() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def env() -> dict:
    return dict(os.environ, PYTHONPATH=os.pathsep.join(
        filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))


def timed_child(cmd: list, **kw) -> tuple[subprocess.CompletedProcess, float]:
    """Run ``cmd`` with this checkout first on PYTHONPATH: (result, wall seconds). The child
    prints its own peak RSS (ru_maxrss): RUSAGE_CHILDREN here would be the largest child's."""
    t = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env(), **kw)
    return r, time.perf_counter() - t


def render_child(cmd):
    """(process, seconds, peak RSS bytes printed as "PEAK n", stderr lines) of a child
    render run by ``timed_child``."""
    r, dt = timed_child(cmd)
    peak = next((int(line.split()[1]) for line in r.stdout.splitlines()
                 if line.startswith("PEAK")), 0)
    return r, dt, peak, r.stderr.strip().splitlines()


# -- vdb ----------------------------------------------------------------------------------------
LOAD = """
import json, resource, sys, time
import numpy as np
import clvol.volume.vdb as v
path, maxres = sys.argv[1], int(sys.argv[2])
rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
t, c = time.perf_counter(), time.process_time()
g = v.read_vdb(path, max_resolution=maxres)
dt, cpu = time.perf_counter() - t, time.process_time() - c
rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
d = g.density
print(json.dumps(dict(seconds=dt, cpu=cpu, rss_before=rss0, rss_peak=rss1, out_bytes=d.nbytes,
                      shape=list(d.shape), finite=bool(np.isfinite(d).all()),
                      min=float(d.min()), mass=float(d.sum(dtype=np.float64)
                      * np.prod(g.cell_size)))))
"""

CORNERS = """
import sys
extent, out = int(sys.argv[1]), sys.argv[2]
g = vdb.read(out, "density")
r = 6
ax = np.arange(2 * r + 1) - r
X, Y, Z = np.meshgrid(ax, ax, ax, indexing="ij")
ball = np.clip(1 - np.sqrt(X**2 + Y**2 + Z**2) / r, 0, None).astype(np.float32)
for o in (0, extent - 2 * r - 1):
    g.copyFromArray(ball, ijk=(o, o, o))
vdb.write(out, grids=[g])
lo, hi = g.evalActiveVoxelBoundingBox()
print(g.activeVoxelCount(), g.leafCount(), *lo, *hi)
"""


def case_vdb(args) -> None:
    from bench_vdb import write_cloud
    from tests.openvdb_fixtures import openvdb_missing, run_openvdb
    missing = openvdb_missing()
    if missing:
        print(f"vdb: skipped: {missing}")
        return
    with tempfile.TemporaryDirectory(dir=args.tmp) as tmp:
        d = Path(tmp)
        path = write_cloud(d, args.extent, args.balls)
        active, leaves, *box = run_openvdb(CORNERS, d, (args.extent, path)).split()
        print(f"  + a ball in two opposite corners: {int(active):,} active voxels "
              f"({int(active) / args.extent**3:.2%} of {args.extent}^3), {int(leaves):,} leaves, "
              f"active box {box[:3]}..{box[3:]}, {mib(path.stat().st_size)} on disk")
        dense = 4 * math.prod(int(h) - int(l) + 3 for l, h in zip(box[:3], box[3:]))
        print(f"  the dense grid at full resolution would be {dense / 2**30:.2f} GiB")
        for maxres in args.max_resolution:
            r, dt = timed_child([sys.executable, "-c", LOAD, str(path), str(maxres)])
            if r.returncode != 0:
                print(f"  max_resolution {maxres}: FAILED (exit {r.returncode}): "
                      f"{r.stderr.strip()[-1500:]}")
                continue
            x = json.loads(r.stdout)
            print(f"  read_vdb(max_resolution={maxres}): output "
                  f"{'x'.join(map(str, x['shape'][::-1]))} (x, y, z) = {mib(x['out_bytes'])}; "
                  f"{x['seconds']:.1f} s wall, {x['cpu']:.1f} s CPU; peak RSS {mib(x['rss_peak'])} "
                  f"(interpreter + NumPy + clvol before loading {mib(x['rss_before'])}; growth "
                  f"{(x['rss_peak'] - x['rss_before']) / x['out_bytes']:.2f}x the output); "
                  f"finite {x['finite']}, min {x['min']:.3g}, mass {x['mass']:.6g}")
        scene = d / "big.toml"
        cloud = (ROOT / "examples" / "cloud.toml").read_text()
        scene.write_text(f'[volume]\nfile = "{path}"\n\n'
                         + cloud[cloud.index("[medium]"):])     # cloud.toml's medium, light, camera
        cmd = [sys.executable, "-c",
               "import resource, sys; from clvol.cli import main; rc = main(sys.argv[1:]); "
               "print('PEAK', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024); "
               "sys.exit(rc)", "render", str(scene), "-o", str(d / "x.exr"), "--quiet"]
        r, dt, peak, err = render_child(cmd)
        print(f"  clvol render of the file without max_resolution: exit {r.returncode} in "
              f"{dt:.1f} s, peak RSS {mib(peak)}, {len(err)} line(s) on stderr: "
              f"{err[-1] if err else ''}")
        # and rendered (the default method) with the smallest max_resolution, at 64^2
        maxres = min(args.max_resolution)
        scene.write_text(f'[volume]\nfile = "{path}"\nmax_resolution = {maxres}\n\n'
                         + cloud[cloud.index("[medium]"):])
        cmd += ["--width", "64", "--height", "64"]
        r, dt, peak, err = render_child(cmd)
        print(f"  clvol render with max_resolution = {maxres} at 64^2 (default method): exit "
              f"{r.returncode} in {dt:.1f} s, peak RSS {mib(peak)}"
              + (f"; stderr: {' | '.join(err[-3:])}" if err else ""))


# -- render ---------------------------------------------------------------------------------------
def case_render(args) -> None:
    out = Path(args.tmp) / f"big_{args.size}.exr"
    cmd = [sys.executable, "-c",
           "import resource, sys; from clvol.cli import main; rc = main(sys.argv[1:]); "
           "print('PEAK', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024, "
           "resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024); sys.exit(rc)",
           "render", str(ROOT / "examples" / "cloud.toml"), "--width", str(args.size),
           "--height", str(args.size), "-o", str(out), "--quiet"]
    print(f"  command: clvol render examples/cloud.toml --width {args.size} --height {args.size} "
          f"-o {out} --quiet")
    r, dt = timed_child(cmd)
    peak = [int(x) for line in r.stdout.splitlines() if line.startswith("PEAK")
            for x in line.split()[1:]]
    err = r.stderr.strip().splitlines()
    size = out.stat().st_size if out.exists() else 0
    print(f"  exit {r.returncode}, {dt:.1f} s wall; peak RSS {mib(peak[0]) if peak else '?'} "
          f"(children {mib(peak[1]) if peak else '?'}); output {mib(size)}; "
          f"pixels {args.size * args.size:,} -> {mib(4 * 3 * args.size**2)} per float32 RGB layer")
    if err:
        print("  stderr: " + " | ".join(err[-5:]))
    if size and not args.keep:
        out.unlink()


# -- loop -----------------------------------------------------------------------------------------
def live_buffers() -> tuple[int, int]:
    import pyopencl as cl
    gc.collect()
    bufs = [o for o in gc.get_objects() if isinstance(o, cl.Buffer)]
    return len(bufs), sum(b.size for b in bufs)


def case_loop(args) -> None:
    from clvol.render.renderer import Renderer
    from clvol.scene import load_scene
    sc = load_scene(ROOT / "examples" / "cloud.toml")
    sc = dataclasses.replace(sc, camera=dataclasses.replace(sc.camera, width=args.size,
                                                            height=args.size))
    opts = {} if args.ms == "default" else {"ms": args.ms}
    r = Renderer(sc, **opts)
    o = sc.camera.origin
    marks = {1, args.frames} | {10 ** k for k in range(1, 9) if 10 ** k < args.frames}
    print(f"  Renderer(examples/cloud.toml at {args.size}^2, {opts or 'default options'}), "
          f"camera orbiting 1 degree a frame, {args.frames} frames")
    rows = {}
    t0 = time.perf_counter()
    for i in range(1, args.frames + 1):
        a = math.radians(i)
        cam = dataclasses.replace(sc.camera, origin=(o[0] * math.cos(a) + o[2] * math.sin(a), o[1],
                                                     -o[0] * math.sin(a) + o[2] * math.cos(a)))
        res = r.render(camera=cam)
        if i in marks:
            n, nbytes = live_buffers()
            rows[i] = (time.perf_counter() - t0, rss_now(), n, nbytes)
            print(f"  frame {i:6d}: {rows[i][0]:8.1f} s, RSS {mib(rows[i][1])}, "
                  f"{n} live OpenCL buffers ({mib(nbytes)}), "
                  f"header ms={res.header.get('raymarch.ms')}", flush=True)
    last = args.frames
    first = 100 if 100 in rows else min(rows)
    (t1, rss1, n1, b1), (t2, rss2, n2, b2) = rows[first], rows[last]
    print(f"  frames {first}..{last}: {(t2 - t1) / max(last - first, 1) * 1e3:.2f} ms a frame; "
          f"RSS {mib(rss1)} -> {mib(rss2)} ({(rss2 - rss1) / 2**20:+.1f} MiB); live buffers "
          f"{n1} -> {n2} ({(b2 - b1) / 2**20:+.2f} MiB); peak RSS {mib(peak_rss_self())}; "
          f"stages counted: {dict(r.counts)}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", choices=("vdb", "render", "loop"))
    ap.add_argument("--extent", type=int, default=2048)
    ap.add_argument("--balls", type=int, default=12)
    ap.add_argument("--max-resolution", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--size", type=int, default=None,
                    help="image side (render: 4096, loop: 32)")
    ap.add_argument("--frames", type=int, default=10000)
    ap.add_argument("--ms", default="default", help="loop: the ms option ('default': none given)")
    ap.add_argument("--tmp", default=tempfile.gettempdir())
    ap.add_argument("--keep", action="store_true", help="render: keep the .exr")
    args = ap.parse_args()
    if args.size is None:
        args.size = 4096 if args.case == "render" else 32
    print(machine())
    print(f"case {args.case}: {vars(args)}")
    {"vdb": case_vdb, "render": case_render, "loop": case_loop}[args.case](args)
    print(f"after: load average {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
