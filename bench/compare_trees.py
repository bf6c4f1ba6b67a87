"""Is this checkout slower than an older one? The same frames rendered by both trees, in
alternating child processes, medians side by side.

    python bench/compare_trees.py --base 4848b3c [--size 256] [--rounds 5] [--frames 4]

``--base`` is any git revision; it is checked out once into a temporary worktree (removed at
the end). Each round runs one child process per tree (the order alternating round by round, so
a drift in the machine's load falls on both), and each child, after one untimed warm-up frame
per workload (kernel builds, weights), times ``--frames`` frames of each workload through the
public API (``clvol.Renderer``, the default method and source, then ``ms="none"``):

    still       the scene's own camera, nothing changed (the march alone)
    camera      the camera orbits 3 degrees a frame (what a camera move recomputes)
    light       the light turns 5 degrees a frame (light field, network, march)
    none_still  the plain single-scattering march, ``ms="none"``

Printed: the machine, per workload the median frame time of each tree over every frame of every
round (wall clock, and the child's CPU time over all its threads, which other processes' load
disturbs less), their ratio (this tree / base) with each side's interquartile range, and the
load average before and after. The issue-37
target is "no benchmark slower": a ratio above 1 by more than the spread of the rounds.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from _common import ROOT, load_average, machine, parser  # noqa: E402

WORKLOADS = ("still", "camera", "light", "none_still")

CHILD = r"""
import dataclasses, json, math, sys, time
import numpy as np
sys.path.insert(0, sys.argv[1])
import clvol
from clvol.scene import load_scene
size, frames = int(sys.argv[2]), int(sys.argv[3])
sc = load_scene(sys.argv[1] + "/examples/cloud.toml")
sc = dataclasses.replace(sc, camera=dataclasses.replace(sc.camera, width=size, height=size))

def turn(v, deg, about):
    a = math.radians(deg); v = np.asarray(v, float); c = np.asarray(about, float)
    x, z = v[0] - c[0], v[2] - c[2]
    return (c[0] + x * math.cos(a) - z * math.sin(a), v[1], c[2] + x * math.sin(a) + z * math.cos(a))

out = {}
for name, ms in (("default", None), ("none", "none")):
    r = clvol.Renderer(sc) if ms is None else clvol.Renderer(sc, "raymarch", ms=ms)
    r.render()                                            # warm-up: builds, weights
    cam, light = sc.camera, sc.light
    works = ("still", "camera", "light") if ms is None else ("still",)
    for w in works:
        ts = []
        for i in range(frames):
            kw = {}
            if w == "camera":
                cam = dataclasses.replace(cam, origin=turn(cam.origin, 3.0, cam.target))
                kw["camera"] = cam
            elif w == "light":
                d = turn(light.direction, 5.0, (0, 0, 0))
                light = dataclasses.replace(light, direction=tuple(d / np.linalg.norm(d)))
                kw["light"] = light
            t0, c0 = time.perf_counter(), time.process_time()
            r.render(**kw)
            ts.append((time.perf_counter() - t0, time.process_time() - c0))
        out[w if ms is None else "none_still"] = ts
print(json.dumps(out))
"""


def run_child(tree: Path, size: int, frames: int) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    p = subprocess.run([sys.executable, "-c", CHILD, str(tree), str(size), str(frames)],
                       capture_output=True, text=True, env=env, cwd=tree)
    if p.returncode != 0:
        sys.exit(f"compare_trees: the child in {tree} failed:\n{p.stderr[-2000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = parser(__doc__, size=256)
    ap.add_argument("--base", required=True, help="git revision to compare against")
    ap.add_argument("--rounds", type=int, default=5, help="child processes per tree (default 5)")
    ap.add_argument("--frames", type=int, default=4, help="timed frames per workload per child")
    a = ap.parse_args(argv)
    print(machine())
    print(f"settings: examples/cloud.toml at {a.size}^2, {a.rounds} rounds x {a.frames} frames, "
          f"base {a.base} against this checkout ({ROOT})")
    load0 = load_average()
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "base"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(base),
                        a.base], check=True)
        try:
            times = {"base": {w: [] for w in WORKLOADS}, "this": {w: [] for w in WORKLOADS}}
            for i in range(a.rounds):
                order = (("base", base), ("this", ROOT))
                for label, tree in (order if i % 2 == 0 else order[::-1]):
                    for w, ts in run_child(tree, a.size, a.frames).items():
                        times[label][w] += ts
                print(f"round {i + 1}/{a.rounds} done (load {load_average()})", flush=True)
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(base)],
                           check=False)
    iqr = lambda x: np.percentile(x, 75) - np.percentile(x, 25)  # noqa: E731
    for k, what in ((0, "wall clock"), (1, "CPU time of the child (all its threads; less "
                                           "sensitive to other processes' load)")):
        print(f"\n{what}, ms per frame")
        print(f"{'workload':<12}{'base':>9}{'this':>9}{'this/base':>11}{'base IQR':>10}"
              f"{'this IQR':>10}")
        for w in WORKLOADS:
            b = np.array(times["base"][w])[:, k] * 1e3
            t = np.array(times["this"][w])[:, k] * 1e3
            print(f"{w:<12}{np.median(b):>9.1f}{np.median(t):>9.1f}"
                  f"{np.median(t) / np.median(b):>11.3f}{iqr(b):>10.1f}{iqr(t):>10.1f}")
    print(f"load average before: {load0}; after: {load_average()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
