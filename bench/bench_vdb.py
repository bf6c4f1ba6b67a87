#!/usr/bin/env python3
"""Benchmark .vdb loading: a synthetic sparse cloud of 1024^3 extent, written by OpenVDB itself
(Debian's python3-openvdb, system Python) in the set-up, read with ``max_resolution``.

    PYTHONPATH=. python bench/bench_vdb.py [--extent 1024] [--max-resolution 256] [--repeats 3]
                                           [--compare]

Reports load + downsample time (median of the repeats, each in a fresh process so that peak
memory is per load; wall and CPU time) and peak memory two ways: tracemalloc's peak of Python and NumPy
allocations, and the growth of the process's maximum resident set (ru_maxrss) over the
interpreter with NumPy and clvol imported. Target: peak <= 2x the dense output array.
``--compare`` also times the other candidates on the same file at full resolution of a smaller
cloud: OpenVDB's own copyToArray (system Python, timed inside it) and tinyvdb if installed,
and checks them against OpenVDB's values.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import ROOT, machine  # noqa: E402  (bench/ is on sys.path; puts the checkout first)
from tests.openvdb_fixtures import openvdb_missing, run_openvdb  # noqa: E402

# Soft balls scattered over the extent, written 128^3 chunk by chunk (the dense 1024^3 array
# would need 4 GiB); chunks no ball reaches are never created. Same seed, same file.
WRITE = """
import sys
extent, nballs, out, tile = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4] == "1"
rng = np.random.default_rng(11)
r = rng.uniform(0.03, 0.09, nballs) * extent
c = rng.uniform(0.15, 0.85, (nballs, 3)) * extent
g = vdb.FloatGrid(); g.name = "density"
g.transform = vdb.createLinearTransform(voxelSize=1.0 / extent)
C = 128
ax = np.arange(C)
for ox in range(0, extent, C):
    for oy in range(0, extent, C):
        for oz in range(0, extent, C):
            o = np.array([ox, oy, oz])
            near = [i for i in range(nballs)
                    if np.all(c[i] + r[i] >= o) and np.all(c[i] - r[i] <= o + C - 1)]
            if not near:
                continue
            X, Y, Z = np.meshgrid(ax + ox, ax + oy, ax + oz, indexing="ij")
            a = np.zeros((C, C, C), np.float32)
            for i in near:
                d = np.sqrt((X - c[i, 0]) ** 2 + (Y - c[i, 1]) ** 2 + (Z - c[i, 2]) ** 2)
                np.maximum(a, np.clip(1 - d / r[i], 0, None).astype(np.float32), out=a)
            g.copyFromArray(a, ijk=(ox, oy, oz))
if tile:   # a constant 128^3 block, stored as one tile (as a dense cloud interior often is)
    g.fill((0, 0, 0), (C - 1, C - 1, C - 1), 0.3, True)
vdb.write(out, grids=[g])
print(g.activeVoxelCount(), g.leafCount())
"""

# One load in a fresh process: time, tracemalloc peak, ru_maxrss before and after.
LOAD = """
import json, resource, sys, time, tracemalloc
import numpy as np
import clvol.volume.vdb as v
path, maxres = sys.argv[1], (int(sys.argv[2]) if sys.argv[2] != "none" else None)
rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
tracemalloc.start()
t, c = time.perf_counter(), time.process_time()
g = v.read_vdb(path, max_resolution=maxres)
dt, cpu = time.perf_counter() - t, time.process_time() - c
_, peak = tracemalloc.get_traced_memory()
rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps(dict(seconds=dt, cpu=cpu, tracemalloc_peak=peak, rss_before=rss0 * 1024,
                      rss_after=rss1 * 1024, out_bytes=g.density.nbytes,
                      shape=list(g.density.shape), mass=float(g.density.sum(dtype=np.float64)
                      * np.prod(g.cell_size)))))
"""

OPENVDB_LOAD = """
import sys, time
t = time.perf_counter()
g = vdb.read(sys.argv[1], "density")
lo, hi = g.evalActiveVoxelBoundingBox()
a = np.zeros([h - l + 1 for l, h in zip(lo, hi)], np.float32)
g.copyToArray(a, ijk=lo)
dt = time.perf_counter() - t
np.save(sys.argv[2], a)
print(dt, lo[0], lo[1], lo[2])
"""


def mib(n: float) -> str:
    return f"{n / 2**20:.1f} MiB"


def run_load(path: Path, maxres) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-c", LOAD, str(path), str(maxres)], env=env,
                       capture_output=True, text=True, check=True)
    return json.loads(r.stdout)


def write_cloud(d: Path, extent: int, nballs: int, tile: bool = False) -> Path:
    path = d / f"cloud_{extent}.vdb"
    t = time.perf_counter()
    active, leaves = run_openvdb(WRITE, d, (extent, nballs, path, int(tile))).split()
    print(f"set-up: OpenVDB wrote {path.name}: {extent}^3 extent, {int(active):,} active voxels "
          f"({int(active) / extent**3:.1%}), {int(leaves):,} leaves, "
          f"{path.stat().st_size / 2**20:.1f} MiB, in {time.perf_counter() - t:.1f} s")
    return path


def compare(d: Path, extent: int) -> None:
    """Candidates on one full-resolution load, checked against OpenVDB's own copyToArray."""
    import numpy as np
    from clvol.volume.vdb import read_vdb
    path = write_cloud(d, extent, 12, tile=True)
    ref = d / "ref.npy"
    times = []
    for _ in range(3):
        t, *lo = run_openvdb(OPENVDB_LOAD, d, (path, ref)).split()
        times.append(float(t))
    want = np.load(ref).transpose(2, 1, 0)
    print(f"  OpenVDB copyToArray (system Python, in-process time): "
          f"{statistics.median(times) * 1e3:.0f} ms median of 3")
    times = []
    for _ in range(3):
        t = time.perf_counter()
        g = read_vdb(path)
        times.append(time.perf_counter() - t)
    ok = np.array_equal(g.density[1:-1, 1:-1, 1:-1], want)
    print(f"  clvol reader: {statistics.median(times) * 1e3:.0f} ms median of 3; equal to "
          f"OpenVDB: {ok}")
    try:
        import tinyvdb
    except ImportError:
        print("  tinyvdb: not installed")
        return
    times = []
    lo = [int(v) for v in lo]
    for _ in range(3):
        t = time.perf_counter()
        with tinyvdb.open(str(path)) as f:
            f.read_grids()
            tg = f.grid(0)
            hi = tuple(a + n for a, n in zip(lo, want.shape[::-1]))
            r = tg.materialize_dense(tuple(lo), hi)
            a = np.frombuffer(r, np.float32).reshape(tuple(r.shape)[::-1])
        times.append(time.perf_counter() - t)
    print(f"  tinyvdb materialize_dense: {statistics.median(times) * 1e3:.0f} ms median of 3; "
          f"equal to OpenVDB: {np.array_equal(a, want)}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--extent", type=int, default=1024)
    ap.add_argument("--balls", type=int, default=40)
    ap.add_argument("--max-resolution", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--compare", action="store_true")
    args = ap.parse_args()
    missing = openvdb_missing()
    if missing:
        print(f"bench_vdb: {missing}")
        return 1
    print(machine())
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        path = write_cloud(d, args.extent, args.balls)
        runs = [run_load(path, args.max_resolution) for _ in range(args.repeats)]
        r0 = runs[0]
        out = r0["out_bytes"]
        secs = statistics.median(r["seconds"] for r in runs)
        tm = statistics.median(r["tracemalloc_peak"] for r in runs)
        rss = statistics.median(r["rss_after"] - r["rss_before"] for r in runs)
        print(f"load + downsample to max_resolution {args.max_resolution}: output "
              f"{'x'.join(map(str, r0['shape'][::-1]))} (x, y, z) = {mib(out)}")
        each = ", ".join(f"{r['seconds']:.2f}" for r in runs)
        cpu = statistics.median(r["cpu"] for r in runs)
        print(f"  time: {secs:.2f} s median of {args.repeats} ({each}); CPU time of the "
              f"process {cpu:.2f} s (what the load costs on a machine shared with others)")
        print(f"  peak tracemalloc: {mib(tm)} = {tm / out:.2f}x the output array (target <= 2x)")
        print(f"  peak RSS growth over the imported interpreter: {mib(rss)} = {rss / out:.2f}x "
              f"(interpreter + NumPy + clvol before loading: {mib(r0['rss_before'])})")
        print(f"  mass (sum x cell volume): {r0['mass']:.6g}")
        if args.compare:
            print(f"candidates at full resolution (a smaller cloud with one 128^3 tile, extent "
                  f"{args.extent // 2}):")
            compare(d, args.extent // 2)
    print(f"after: load average {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
