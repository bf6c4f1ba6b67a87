"""The ``clvol`` command line.

Subcommands: ``info`` (OpenCL platforms and the chosen device), ``volume`` (inspect,
generate and convert density grids), ``render`` (a scene to EXR with one of the render
methods), ``compare`` (image error metrics; FLIP with the ``quality`` extra). Bad input exits
with status 2 and one line on stderr; ``CLVOL_TRACEBACK=1`` shows the traceback instead.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

from .errors import BuildError, ClvolError


def _cmd_info(args) -> int:
    from . import __version__
    from .runtime import describe_devices
    print(f"clvol {__version__}")
    print(describe_devices(args.device))
    return 0


def _cmd_volume_info(args) -> int:
    from .volume.io import read_volume
    from .volume.stats import format_stats, volume_stats
    for path in args.files:
        grid = read_volume(path)
        print(f"{path}:")
        print(format_stats(volume_stats(grid, args.density_scale)))
    return 0


def _parse_params(pairs: list[str]) -> dict:
    params = {}
    for pair in pairs or []:
        if "=" not in pair:
            raise ClvolError(f"--param {pair!r}: expected NAME=VALUE")
        key, value = pair.split("=", 1)
        try:
            params[key] = json.loads(value)
        except json.JSONDecodeError:
            raise ClvolError(f"--param {pair!r}: VALUE must be a number or JSON list") from None
    return params


def _cmd_volume_generate(args) -> int:
    from .volume.generators import GENERATORS, generate
    from .volume.io import write_volume
    from .volume.stats import format_stats, volume_stats
    if args.list:
        for info in GENERATORS.values():
            print(f"{info.name}: {info.doc}")
            for pname, p in info.parameters.items():
                print(f"    {pname} = {p.default}  [{p.lo}, {p.hi}]  {p.doc}")
        return 0
    if not args.name or not args.output:
        raise ClvolError("volume generate: give a generator NAME and -o FILE (or --list)")
    res = args.resolution
    resolution = res[0] if len(res) == 1 else tuple(res)
    grid = generate(args.name, seed=args.seed, resolution=resolution, **_parse_params(args.param))
    write_volume(args.output, grid)
    print(f"wrote {args.output}")
    print(format_stats(volume_stats(grid, args.density_scale)))
    return 0


def _cmd_volume_convert(args) -> int:
    from .volume.io import read_volume, write_volume
    write_volume(args.output, read_volume(args.input))
    print(f"wrote {args.output}")
    return 0


def _cmd_compare(args) -> int:
    from .image import read_exr
    from .metrics import FLIP_MISSING, compare_images, flip_available
    test, ref = read_exr(args.test), read_exr(args.reference)
    has_flip = flip_available()
    result = compare_images(test.rgb, ref.rgb, with_flip=has_flip)
    if not has_flip:
        print(f"clvol: note: no FLIP score; {FLIP_MISSING}", file=sys.stderr)
    result = {"test": str(args.test), "reference": str(args.reference), **result}
    if args.json:
        # Identical images have PSNR = inf, which strict JSON cannot hold: write null.
        clean = {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                 for k, v in result.items()}
        print(json.dumps(clean, indent=2, allow_nan=False))
    else:
        for key, value in result.items():
            print(f"{key:>12}: {value:.6g}" if isinstance(value, float) else f"{key:>12}: {value}")
    return 0


def _cmd_render(args) -> int:
    from .image import write_exr, write_png_preview
    from .render import method_module
    from .runtime import configure, get_runtime
    from .scene import load_scene
    configure(device=args.device, profiling=args.profile)
    scene = load_scene(args.scene)
    module = method_module(args.method)
    result = module.render(scene, args)
    if args.profile:
        print("device time per kernel:\n" + get_runtime().timing_report(), file=sys.stderr)
    header = {"scene": str(args.scene), "method": args.method, **result.header}
    write_exr(args.output, result.layers, header)
    print(f"wrote {args.output}", file=sys.stderr)
    if args.png is not None:
        png = args.png or str(Path(args.output).with_suffix(".png"))
        write_png_preview(png, result.layers["total"], exposure=args.exposure)
        print(f"wrote {png}", file=sys.stderr)
    for key, value in result.header.items():
        print(f"  {key}: {value}", file=sys.stderr)
    return 0


def build_parser() -> argparse.ArgumentParser:
    from .render import METHODS, available_methods
    parser = argparse.ArgumentParser(
        prog="clvol",
        description="Render participating media with multiple scattering on any OpenCL device.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("info", help="list OpenCL platforms and devices, and which one is chosen")
    p.add_argument("--device", help="device spec to try: P:D, gpu, cpu or a name substring")
    p.set_defaults(func=_cmd_info)

    pv = sub.add_parser("volume", help="inspect, generate and convert density grids")
    vsub = pv.add_subparsers(dest="volume_command", required=True, metavar="ACTION")
    p = vsub.add_parser("info", help="resolution, bbox, density range, occupancy, optical thickness")
    p.add_argument("files", nargs="+", help=".vol, .npy or .npz files")
    p.add_argument("--density-scale", type=float, default=1.0,
                   help="sigma_t = density * scale, for the optical thickness figures (default 1)")
    p.set_defaults(func=_cmd_volume_info)
    p = vsub.add_parser("generate", help="make a procedural volume (cloud, smoke, solids)")
    p.add_argument("name", nargs="?", help="generator name (see --list)")
    p.add_argument("-o", "--output", help="output .vol, .npy or .npz")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--resolution", type=int, nargs="+", default=[64], metavar="N",
                   help="N (cubic) or NX NY NZ")
    p.add_argument("--param", action="append", metavar="NAME=VALUE",
                   help="generator parameter (repeatable)")
    p.add_argument("--density-scale", type=float, default=1.0)
    p.add_argument("--list", action="store_true", help="list generators and their parameters")
    p.set_defaults(func=_cmd_volume_generate)
    p = vsub.add_parser("convert", help="convert between .vol, .npy and .npz")
    p.add_argument("input")
    p.add_argument("output")
    p.set_defaults(func=_cmd_volume_convert)

    methods = "; ".join(f"{k}: {v[1]}" for k, v in METHODS.items())
    p = sub.add_parser("render", help="render a scene to EXR", description=f"Methods: {methods}.")
    p.add_argument("scene", help="scene .toml file")
    p.add_argument("--method", choices=sorted(METHODS), default="raymarch")
    p.add_argument("-o", "--output", required=True, help="output .exr")
    p.add_argument("--png", nargs="?", const="", default=None, metavar="FILE",
                   help="also write a tonemapped PNG preview (default: next to the EXR)")
    p.add_argument("--exposure", type=float, default=0.0, help="preview exposure in stops")
    p.add_argument("--device", help="OpenCL device: P:D, gpu, cpu or a name substring")
    p.add_argument("--seed", type=int, default=0, help="random seed (same seed, same image)")
    p.add_argument("--profile", action="store_true", help="print per-kernel device times")
    for name, module in available_methods().items():
        if hasattr(module, "add_arguments"):
            module.add_arguments(p.add_argument_group(f"{name} options"))
    p.set_defaults(func=_cmd_render)

    p = sub.add_parser("compare", help="error metrics of a test image against a reference")
    p.add_argument("test", help="test .exr")
    p.add_argument("reference", help="reference .exr")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=_cmd_compare)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except ClvolError as exc:
        if os.environ.get("CLVOL_TRACEBACK") == "1":
            raise
        # One line for bad input; a compiler log is kept whole because it is the only clue.
        text = str(exc) if isinstance(exc, BuildError) else str(exc).splitlines()[0]
        print(f"clvol: error: {text}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("clvol: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
