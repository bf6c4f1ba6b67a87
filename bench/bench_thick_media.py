#!/usr/bin/env python3
"""Path-traced optically thick media (issue 41): wall time of ``clvol render`` at 32^2, 1 spp.

    python bench/bench_thick_media.py [--scales 1e3 1e4 ...] [--albedos 1 0.9] [--size 32]
                                      [--spp 1] [--timeout 120] [--scene examples/cloud.toml]

Each case writes the scene with ``[medium] density_scale`` and ``albedo`` replaced and runs
``clvol render SCENE --method pathtrace --width S --height S --spp N -o out.exr`` in a fresh
process (kernel builds cached after the first case), killed after ``timeout`` s. Prints per
case: the exit status, the wall time, and from the render summary the header's
``paths_stopped_at_bound``, ``paths_truncated`` and ``mean_tracking_steps`` (or the error's
one line).
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import ROOT, machine, parser  # noqa: E402


def scene_text(src: str, scale: float, albedo: float, resolution=None) -> str:
    lines = []
    for line in src.splitlines():
        if resolution and re.match(r"\s*resolution\s*=", line):
            line = f"resolution = {resolution}"
        if re.match(r"\s*density_scale\s*=", line):
            line = f"density_scale = {scale!r}"
        lines.append(line)
        if line.strip() == "[medium]":
            lines.append(f"albedo = [{albedo!r}, {albedo!r}, {albedo!r}]")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = parser(__doc__, size=32, spp=1)
    ap.add_argument("--scales", type=float, nargs="+",
                    default=[1e3, 1e4, 1e5, 1e6, 1e7, 1e8])
    ap.add_argument("--albedos", type=float, nargs="+", default=[1.0, 0.9])
    ap.add_argument("--timeout", type=float, default=120.0)
    ap.add_argument("--scene", default=str(ROOT / "examples" / "cloud.toml"))
    ap.add_argument("--resolution", type=int, default=None,
                    help="replace the generator's [volume] resolution")
    ap.add_argument("--majorant-block", type=int, default=None)
    a = ap.parse_args()
    from clvol.runtime import get_runtime
    print(machine(get_runtime()))          # the device the CLI children pick (the default)
    src = Path(a.scene).read_text()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    print(f"scene {a.scene}, {a.size}^2, {a.spp} spp, timeout {a.timeout:g} s")
    print(f"{'albedo':>6} {'density_scale':>13} {'exit':>4} {'wall s':>7}  result")
    with tempfile.TemporaryDirectory() as tmp:
        for albedo in a.albedos:
            for scale in a.scales:
                p = Path(tmp) / "scene.toml"
                p.write_text(scene_text(src, scale, albedo, a.resolution))
                cmd = [sys.executable, "-m", "clvol", "render", str(p), "--method", "pathtrace",
                       "--width", str(a.size), "--height", str(a.size), "--spp", str(a.spp),
                       "-o", str(Path(tmp) / "out.exr")]
                if a.majorant_block is not None:
                    cmd += ["--majorant-block", str(a.majorant_block)]
                t = time.perf_counter()
                try:
                    r = subprocess.run(cmd, capture_output=True, text=True, env=env,
                                       timeout=a.timeout, cwd=ROOT)
                    code, out = r.returncode, r.stdout + r.stderr
                except subprocess.TimeoutExpired:
                    code, out = "kill", ""
                dt = time.perf_counter() - t
                keys = ("seconds", "mean_vertices", "paths_stopped_at_bound", "paths_truncated", "mean_tracking_steps")
                found = [m.group(0).strip() for k in keys
                         for m in [re.search(rf"(?m)^\s*{k}: [0-9.e+-]+", out)] if m]
                err = [x for x in out.splitlines() if "error" in x.lower()][:1]
                print(f"{albedo:>6g} {scale:>13g} {code!s:>4} {dt:>7.1f}  "
                      f"{'; '.join(found) or (err[0] if err else '')}", flush=True)
    print(f"at the end: {machine()}")


if __name__ == "__main__":
    main()
