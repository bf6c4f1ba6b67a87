"""A volume sequence rendered frame after frame: wall time with the next frame read on a second
thread (what ``clvol render --frames`` does) against strict serial order.

    python bench/bench_sequence.py                      # 48 frames, 128^3, 256^2 (issue 28)
    python bench/bench_sequence.py --frames 8 --resolution 64 --size 128   # quick

The frames are the fire example's generator (examples/fire/make_fire.py) at --resolution,
written once to --cache (compressed .npz, as the example ships them; reused while the
generator and the settings are the same). Both runs render the same frames with one
``clvol.Renderer`` of examples/fire/fire.toml (density + blackbody emission, the default
method: ray marching + the network's multiple scattering) and write each frame's EXR like
the CLI. Serial first, then prefetch, then serial and prefetch again; the figures are
per-run walls and per-frame medians of: load (reading and preparing a frame: .npz
decompression, checks, the blackbody mapping), wait (how long the render thread waited for
it: all of load when serial), render (``Renderer.render(grid=...)``: upload, light field,
network lattice, march) and write (EXR). Prints the machine line and the load average before
and after.
"""
from __future__ import annotations

import hashlib
import statistics
import sys
import tempfile
from pathlib import Path

import _common

ROOT = _common.ROOT


def make_frames(folder: Path, n: int, res: int) -> Path:
    """The generator's frames in ``folder`` (made once per generator version and size)."""
    src = (ROOT / "examples" / "fire" / "make_fire.py").read_bytes()
    tag = hashlib.sha256(src + f"{n} {res}".encode()).hexdigest()[:12]
    out = folder / f"fire_{res}_{n}_{tag}"
    if not (out / f"fire_{n:04d}.npz").exists():
        sys.path.insert(0, str(ROOT / "examples" / "fire"))
        import make_fire
        print(f"making {n} frames at {res}^3 in {out} ...", flush=True)
        make_fire.main(["--frames", str(n), "--resolution", str(res), "--out", str(out)])
    return out


def main(argv=None) -> int:
    ap = _common.parser(__doc__, size=256)
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=2, help="serial/prefetch pairs (default 2)")
    ap.add_argument("--ms", default="network", help="--ms of the renderer (default network)")
    ap.add_argument("--cache", default=str(Path.home() / ".cache" / "clvol" / "bench_sequence"))
    args = ap.parse_args(argv)

    import clvol
    from clvol.image import write_exr
    from clvol.runtime import get_runtime
    from clvol.sequence import render_sequence

    rt = get_runtime()
    print(_common.machine(rt))
    folder = make_frames(Path(args.cache), args.frames, args.resolution)
    scene = clvol.load_scene(ROOT / "examples" / "fire" / "fire.toml")
    scene = _common.square(scene, args.size)
    spec = scene.volume
    import dataclasses
    scene = dataclasses.replace(scene, volume=dataclasses.replace(
        spec, file=folder / spec.file.name, frame=1))
    frames = list(range(1, args.frames + 1))
    print(f"{args.frames} frames of {args.resolution}^3 (density + temperature, "
          f"{sum(p.stat().st_size for p in folder.glob('*.npz')) / 2**20:.0f} MiB of .npz), "
          f"{args.size}^2, --ms {args.ms}, examples/fire/fire.toml; load average before: "
          f"{_common.load_average()}", flush=True)
    renderer = clvol.Renderer(scene, ms=args.ms)
    renderer.render(grid=scene.volume.load(),
                    emission=scene.emission.load(scene.volume, scene.volume.load()))  # warm-up
    results = {"serial": [], "prefetch": []}
    with tempfile.TemporaryDirectory() as tmp:
        def on_frame(n, result, loaded):
            write_exr(Path(tmp) / f"out_{n:04d}.exr", result.layers, result.header)
        for rep in range(args.repeats):
            for mode in ("serial", "prefetch"):
                stats = render_sequence(scene, renderer, frames, on_frame,
                                        prefetch=(mode == "prefetch"))
                results[mode].append(stats)
                med = {k: statistics.median(f[k] for f in stats.frames)
                       for k in ("load", "wait", "render", "write")}
                print(f"  {mode:<8} run {rep + 1}: wall {stats.wall:6.1f} s "
                      f"({stats.wall / len(frames) * 1e3:.0f} ms/frame); medians per frame: "
                      f"load {med['load'] * 1e3:.0f} ms, wait {med['wait'] * 1e3:.0f} ms, "
                      f"render {med['render'] * 1e3:.0f} ms, write {med['write'] * 1e3:.0f} ms",
                      flush=True)
    s = statistics.median(r.wall for r in results["serial"])
    p = statistics.median(r.wall for r in results["prefetch"])
    load = statistics.median(f["load"] for r in results["serial"] for f in r.frames)
    print(f"median wall: serial {s:.1f} s, prefetch {p:.1f} s: {s / p:.2f}x, "
          f"{(s - p):.1f} s saved of the {load * len(frames):.1f} s spent loading "
          f"({100 * (s - p) / max(load * len(frames), 1e-9):.0f}% of the load hidden)")
    print(f"load average after: {_common.load_average()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
