"""The ``clvol`` command line.

Subcommands: ``info`` (OpenCL platforms and the chosen device), ``volume`` (inspect,
generate and convert density grids), ``render`` (a scene to EXR with one of the render
methods), ``compare`` (image error metrics; FLIP with the ``quality`` extra), ``dataset make`` (training data, on Ray if
installed), ``bundle`` and ``goldens`` (for C hosts and ports, docs/embedding.md). Bad input
exits with status 2 and one line
on stderr; ``CLVOL_TRACEBACK=1`` shows the traceback instead.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

from .errors import BuildError, ClvolError
from .scenefile import SET_HELP


def _code_paths(kind: str, cus: int, lanes: int, lanes_line: str = "") -> list[str]:
    """Which code path each kernel takes on a device of ``kind`` with ``cus`` compute units
    and lane width ``lanes`` (clvol/runtime.py device_lanes): its work per work-item and launch
    shape (the places the host code asks the device)."""
    from .kernels.gather import GATHER_LOCAL
    from .kernels.pathtrace import QUERY_LANES, RENDER_LANES, launch_shape
    from .kernels.raymarch import LOCAL_SIZE, TILE, tile_rows
    from .kernels.transmittance import SWEEP_GROUP
    render_lanes, query_lanes = min(RENDER_LANES, lanes), min(QUERY_LANES, lanes)
    items, local = launch_shape(kind, cus, 256 * 256, render_lanes)
    cpu = kind == "cpu"
    return [
        lanes_line or f"lanes: {lanes} per work-item",
        f"raymarch: {TILE}x{tile_rows(lanes)} pixel tile per work-item (one pixel a lane), "
        f"groups of {LOCAL_SIZE} tiles",
        f"pathtrace: {render_lanes} paths per work-item (render), {query_lanes} (point "
        f"queries); {'CPU' if kind != 'gpu' else 'GPU'} launch: a 256^2 frame runs {items} "
        f"work-items in groups of {local[0]}",
        f"mlp, gather_mlp: {lanes} queries per work-item (one a lane, private arrays), groups "
        f"of {'1 (PoCL stack)' if cpu else 'the driver’s choice'}",
        f"gather: one query per work-item ({lanes} template points a chunk), groups of "
        f"{GATHER_LOCAL if cpu else 'the driver’s choice'}",
        f"transmittance sweep: {lanes} columns per work-item on levels of 16 and more, groups "
        f"of {SWEEP_GROUP}",
    ]


def _check_builds(entry) -> list[str]:
    """Render a tiny scene with the default method and with the path tracer on ``entry``'s
    device: one line per method, "ok" or the failing kernel and its build log's first error."""
    from .render.renderer import Renderer
    from .runtime import get_runtime
    from .scenefile import scene_from_dict
    out = []
    for method, kw in (("default (raymarch + network MS at the view)", {}),
                       ("pathtrace", {"method": "pathtrace", "spp": 1})):
        try:
            sc = scene_from_dict({   # examples/cloud.toml, small
                "volume": {"generator": "cloud", "seed": 1, "resolution": 32},
                "medium": {"preset": "cloud", "density_scale": 64.0},
                "light": {"direction": [0.45, 0.4, -0.8]},
                "camera": {"origin": [0.0, 0.15, 1.6], "target": [0.0, 0.06, 0.0], "fov_y": 35.0,
                           "width": 8, "height": 8}}, "<clvol info --check>")
            rt = get_runtime(entry.spec)
            Renderer(sc, runtime=rt, **kw).render()
            out.append(f"{method}: ok")
        except BuildError as exc:
            out.append(f"{method}: BUILD FAILED: {exc.one_line()}")
        except Exception as exc:  # noqa: BLE001 - a diagnosis reports, it does not stop
            out.append(f"{method}: FAILED: {type(exc).__name__}: {str(exc).splitlines()[0][:200]}")
    return out


def _cmd_info(args) -> int:
    from . import __version__
    from .runtime import (choose_device, describe_devices, describe_lanes, describe_workarounds,
                          device_lanes, list_devices)
    print(f"clvol {__version__}")
    print(describe_devices(args.device))
    try:
        chosen, _ = choose_device(args.device)
    except ClvolError:
        return 0                # describe_devices said why
    from .render.memory import describe_limits
    print(describe_limits(chosen.device))
    entries = list_devices()
    if args.check:
        entries = [chosen] if args.device else entries
    for e in entries:
        print(f"code paths on {e.spec} ({e.kind}):")
        for ln in _code_paths(e.kind, e.device.max_compute_units, device_lanes(e),
                              describe_lanes(e)) + describe_workarounds(e):
            print(f"  {ln}")
        if args.check:
            print(f"build check on {e.spec} {e.label} (8x8 renders of a 32^3 cloud):",
                  flush=True)
            for ln in _check_builds(e):
                print(f"  {ln}", flush=True)
    return 0


def _cmd_volume_info(args) -> int:
    from .volume.io import read_volume
    from .volume.stats import format_stats, volume_stats
    for path in args.files:
        if Path(path).suffix.lower() == ".vdb":
            if args.density_scale is not None:
                raise ClvolError(f"{path}: --density-scale is for the statistics of a dense "
                                 f"grid; a .vdb gets its grid listing (convert it to .npz for "
                                 f"statistics)")
            from .volume.vdb import format_vdb_info
            print(format_vdb_info(path))
            continue
        grid = read_volume(path)
        print(f"{path}:")
        scale = 1.0 if args.density_scale is None else args.density_scale
        print(format_stats(volume_stats(grid, scale)))
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
    """Every grid of the input is written, or the conversion is refused with one line."""
    from .volume.io import read_volume_grids, write_volume_grids
    density, extras = read_volume_grids(args.input, grid=args.grid,
                                        max_resolution=args.max_resolution)
    write_volume_grids(args.output, density, extras, source=str(args.input))
    print(f"wrote {args.output}" + (f" (grids: density, {', '.join(extras)})" if extras else ""))
    return 0


def _cmd_compare(args) -> int:
    from .image import read_image
    from .metrics import FLIP_MISSING, compare_images, flip_available
    test, ref = read_image(args.test), read_image(args.reference)
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


def parse_exposure(text):
    """``--exposure``: None (not given: from the image), "image", "scene" or a finite number
    of stops (a float). Anything else raises ``ClvolError`` with one line."""
    if text is None or text in ("image", "scene"):
        return text
    try:
        stops = float(text)
    except (TypeError, ValueError):
        stops = None
    if stops is None or not math.isfinite(stops):
        raise ClvolError(f"--exposure {text}: give a finite number of stops, 'image' (chosen "
                         f"from the image) or 'scene' (from the scene's light)")
    return stops


def _frame_field(name: str) -> bool:
    """Whether ``name`` holds a ``{frame}`` field (``{frame}``, ``{frame:04d}``, ...)."""
    import string
    try:
        return any(field == "frame" or (field or "").startswith(("frame.", "frame["))
                   for _, field, _, _ in string.Formatter().parse(name))
    except ValueError:          # an unmatched brace: no field (format would fail anyway)
        return False


def check_render_outputs(output: str, png: str | None, exposure, frames: str | None = None):
    """Refuse, before any rendering, outputs that would be lost or mislabelled: the EXR must
    be named .exr, the preview .png and not the EXR's own path; both folders must exist, no
    output may be a folder, a ``{frame}`` field needs --frames, and the exposure must be
    finite. Returns the preview's path (None: no preview)."""
    out = Path(output)
    if out.suffix.lower() != ".exr":
        raise ClvolError(f"-o {output}: the output is an OpenEXR image; name it .exr (the "
                         f"tonemapped preview is --png [FILE.png])")
    if png is not None:
        png = png or str(out.with_suffix(".png"))
        if Path(png).suffix.lower() != ".png":
            raise ClvolError(f"--png {png}: the preview is a PNG; name it .png")
        if Path(png).resolve() == out.resolve():
            raise ClvolError(f"--png {png}: the same file as -o; the preview would overwrite the EXR")
    parse_exposure(exposure)
    if frames is None:          # a single image: a {frame} field would be written literally
        for opt, name in (("-o", output), ("--png", png)):
            if name is not None and _frame_field(name):
                raise ClvolError(f"{opt} {name}: {{frame}} names the files of a volume "
                                 f"sequence; give --frames (e.g. --frames 1-48), or drop it")
    for p in (out, Path(png) if png is not None else None):
        if p is not None and p.is_dir():     # found only when the temporary file is renamed
            raise ClvolError(f"{p}: is a folder; name the image file to write")
        folder = p.resolve().parent if p is not None else None
        if folder is not None and not folder.is_dir():
            raise ClvolError(f"{p}: cannot write, folder {folder} does not exist")
        if folder is not None and not os.access(folder, os.W_OK):
            raise ClvolError(f"{p}: cannot write, folder {folder} is not writable")
    return png


def preview_alpha(scene, layers):
    """The PNG preview's alpha: the image's coverage when nothing is behind the medium (a
    black background: the beauty is then premultiplied by it); None with a sky, which the
    beauty already shows through the medium, so the preview stays opaque."""
    light = scene.light
    sky = (light.environment_map is not None
           or (light.environment is not None and max(light.environment) > 0))
    return None if sky else layers.get("alpha")


def _cmd_render(args) -> int:
    from .image import choose_exposure, write_exr, write_png_preview
    from .render import METHODS
    from .render.options import given_options
    from .render.renderer import Renderer
    from .runtime import configure, get_runtime
    from .scene import load_scene_overridden
    if args.png is None:
        for name in ("exposure", "tone"):
            if getattr(args, name) is not None:
                raise ClvolError(f"--{name} sets the PNG preview: give --png too")
    png = check_render_outputs(args.output, args.png, args.exposure, args.frames)
    exposure = parse_exposure(args.exposure)
    tone = args.tone or "filmic"
    configure(device=args.device, profiling=args.profile)
    scene = load_scene_overridden(args.scene, args.set, args.width, args.height)
    renderer = Renderer(scene, args.method, **given_options(args, list(METHODS)))
    if args.frames is not None:
        return _render_frames(args, scene, renderer, png, exposure, tone)
    result = renderer.render(still=True)      # a still image (Renderer.render's ``still``)
    if args.profile:
        rt = get_runtime()
        print("device time per kernel:\n" + rt.timing_report(), file=sys.stderr)
        print("host<->device transfers:\n" + rt.transfers.report(), file=sys.stderr)
    header = {"scene": str(args.scene), **result.header}
    if png is not None:     # the preview's exposure, also recorded in the EXR's header
        stops, how = choose_exposure(exposure, result.layers["total"], scene.light)
        header.update({"preview.exposure": f"{stops:+.4f}", "preview.exposure_from": how,
                       "preview.tone": tone})
    write_exr(args.output, result.layers, header)
    print(f"wrote {args.output}", file=sys.stderr)
    if png is not None:
        used = write_png_preview(png, result.layers["total"], exposure=stops, curve=tone,
                                 alpha=preview_alpha(scene, result.layers))
        print(f"wrote {png} (exposure {used:+.2f} stops, {how}; {tone} tone curve)",
              file=sys.stderr)
    if not args.quiet:
        for key, value in result.header.items():
            print(f"  {key}: {value}", file=sys.stderr)
    return 0


def _cmd_bundle(args) -> int:
    """``clvol bundle``, after refusing what the C host does not render (emission, a volume
    sequence), in one line."""
    from . import bundle
    from .scene import load_scene_overridden
    scene = load_scene_overridden(args.scene, args.set, args.width, args.height)
    if scene.emission is not None:
        raise ClvolError(f"{args.scene}: clvol bundle: the C host has no emission; render "
                         f"[emission] scenes with clvol render (docs/embedding.md)")
    if scene.volume.is_sequence:
        raise ClvolError(f"{args.scene}: clvol bundle: the volume is a sequence "
                         f"({scene.volume.file.name}); bundle one frame's file instead")
    return bundle.run(args)


def _render_frames(args, scene, renderer, png, exposure, tone) -> int:
    """``--frames``: one EXR (and PNG) per frame of the scene's volume sequence, the next
    frame read on a second thread while this one renders (clvol/sequence.py)."""
    from .image import choose_exposure, write_exr, write_png_preview
    from .progress import Progress
    from .sequence import check_output_pattern, frame_path, parse_frames, render_sequence
    frames = parse_frames(args.frames)
    if not scene.volume.is_sequence:
        raise ClvolError(f"--frames {args.frames}: the scene's volume is not a sequence; give "
                         f"[volume] file a {{frame}} field, e.g. \"fire_{{frame:04d}}.npz\"")
    check_output_pattern(args.output, frames)
    if png:
        check_output_pattern(png, frames)
    written = []

    def on_frame(n, result, loaded):
        out = frame_path(args.output, n)
        header = {"scene": str(args.scene), "frame": n, "volume.file": str(loaded.file),
                  **result.header}
        if png:
            stops, how = choose_exposure(exposure, result.layers["total"], scene.light)
            header.update({"preview.exposure": f"{stops:+.4f}", "preview.exposure_from": how,
                           "preview.tone": tone})
        write_exr(out, result.layers, header)
        written.append(out)
        if png:
            write_png_preview(frame_path(png, n), result.layers["total"], exposure=stops,
                              curve=tone, alpha=preview_alpha(scene, result.layers))

    with Progress(len(frames), label="frames", unit=" frames") as bar:
        stats = render_sequence(scene, renderer, frames, on_frame, progress=bar)
    print(f"wrote {len(written)} frames: {written[0]} .. {written[-1]} ({stats.wall:.1f} s)",
          file=sys.stderr)
    return 0


def _cmd_view(args) -> int:
    from .runtime import configure
    from .scene import load_scene_overridden
    from .viewer.server import serve
    try:
        import aiohttp  # noqa: F401
    except ImportError:
        raise ClvolError("clvol view needs aiohttp: pip install 'clvol[view]'") from None
    if not 0 <= args.port <= 65535:
        raise ClvolError(f"--port {args.port}: allowed range 0-65535 (0 = any free port)")
    configure(device=args.device)
    scene = load_scene_overridden(args.scene, args.set)
    return serve(scene, host=args.host, port=args.port, open_browser=not args.no_browser,
                 save_dir=Path(args.save_dir) if args.save_dir else None)


def _cmd_dataset_make(args) -> int:
    import time
    from .training.dataset import DatasetSpec
    from .training.distributed import generate
    if args.workers is not None and args.workers < 1:
        raise ClvolError(f"--workers {args.workers}: must be >= 1")
    spec = DatasetSpec(seed=args.seed, n_volumes=args.volumes, n_heldout_volumes=args.heldout,
                       configs_per_volume=args.configs, points_per_config=args.points,
                       n_paths=args.paths,
                       resolution=_parse_pair("--resolution", args.resolution, int),
                       base_resolution=args.base,
                       optical_thickness=_parse_pair("--optical-thickness", args.optical_thickness),
                       albedo=_parse_pair("--albedo", args.albedo), g=_parse_pair("--g", args.g),
                       max_lobes=args.max_lobes, per_order_labels=args.per_order_labels,
                       families=tuple(f for f in args.families.split(",") if f),
                       augment=args.augment, visible_fraction=args.visible_fraction)
    part = None
    if args.part is not None:
        try:
            part = tuple(int(x) for x in args.part.split("/"))
            if len(part) != 2:
                raise ValueError
        except ValueError:
            raise ClvolError(f"--part {args.part!r}: expected I/N, e.g. 0/4") from None
    t0 = time.perf_counter()
    r = generate(spec, args.out, address=args.address, serial=args.serial, workers=args.workers,
                 progress=not args.no_progress, part=part)
    dt = time.perf_counter() - t0
    print(f"{args.out}: made {r['made']} shards ({r['made'] * spec.points_per_config} labels), "
          f"skipped {r['skipped']} finished ones, {spec.n_shards} in the spec, {dt:.1f} s "
          f"({r['engine']})", flush=True)
    return 0


def _pair(r) -> str:
    return ",".join(str(x) for x in r)


def _parse_pair(name: str, text: str, kind=float) -> tuple:
    try:
        lo, hi = (kind(x) for x in text.split(","))
    except ValueError:
        raise ClvolError(f"{name} {text!r}: expected two numbers low,high") from None
    return (lo, hi)


def add_dataset_make_arguments(p: argparse.ArgumentParser) -> None:
    """Options of `clvol dataset make` (also scripts/make_dataset.py)."""
    from .training.dataset import DatasetSpec
    d = DatasetSpec()
    p.add_argument("out", help="data set folder (e.g. runs/data; runs/ is ignored by git)")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--volumes", type=int, default=d.n_volumes,
                   help="every volume; the last --heldout come from a separate random stream")
    p.add_argument("--heldout", type=int, default=d.n_heldout_volumes,
                   help="volumes held out of training by construction")
    p.add_argument("--configs", type=int, default=d.configs_per_volume, help="per volume")
    p.add_argument("--points", type=int, default=d.points_per_config, help="labels per shard")
    p.add_argument("--paths", type=int, default=d.n_paths, help="paths per label")
    p.add_argument("--resolution", default=_pair(d.resolution), help="low,high voxels per side")
    p.add_argument("--base", type=int, default=d.base_resolution, help="pyramid base resolution")
    p.add_argument("--optical-thickness", default=_pair(d.optical_thickness), help="low,high")
    p.add_argument("--albedo", default=_pair(d.albedo), help="low,high per channel")
    p.add_argument("--g", default=_pair(d.g), help="low,high HG g of every lobe")
    p.add_argument("--max-lobes", type=int, default=d.max_lobes)
    p.add_argument("--families", default=",".join(d.families),
                   help="volume families, cycled through (docs/neural.md); the out-of-family "
                        "clouds nubis and sphere_cumulus make evaluation sets only")
    p.add_argument("--augment", type=float, default=d.augment, metavar="FRACTION",
                   help="fraction of the volumes whose density structure is randomised "
                        "(remap and modulation; docs/neural.md)")
    p.add_argument("--visible-fraction", type=float, default=d.visible_fraction, metavar="FRACTION",
                   help="fraction of each shard's points drawn where its camera looks (optical "
                        "depth 0.3-4 from the camera; docs/neural.md)")
    p.add_argument("--per-order-labels", action="store_true",
                   help="trace labels at albedo 1 and store them per scattering order, so "
                        "training can label every point at any albedo (docs/pathtrace.md)")
    g = p.add_argument_group("where it runs (default: a local Ray on all cores, if installed)")
    g.add_argument("--address", metavar="auto|HOST:PORT|ray://HOST:PORT",
                   help="join a running Ray cluster instead of starting a local one")
    g.add_argument("--workers", type=int, metavar="N", help="CPUs of the local Ray (default all)")
    g.add_argument("--serial", action="store_true", help="no Ray: one shard after another here")
    g.add_argument("--part", metavar="I/N", help="with --serial: make only volumes v %% N == I, so "
                   "N processes can share one device and folder (e.g. one GPU)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def build_parser() -> argparse.ArgumentParser:
    """The ``clvol`` command line: one sub-command per task, each added by its own function
    (in the order ``clvol --help`` lists them)."""
    parser = argparse.ArgumentParser(
        prog="clvol",
        description="Render participating media with multiple scattering on any OpenCL device.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in (_add_info, _add_volume, _add_render, _add_view, _add_bundle_and_goldens,
                _add_compare, _add_dataset):
        add(sub)
    _add_verbose(parser)
    return parser


VERBOSE_HELP = ("show the OpenCL compiler's output when a kernel is built (as "
                "PYOPENCL_COMPILER_OUTPUT=1; hidden otherwise)")


def _add_verbose(parser) -> None:
    """``--verbose`` before or after any sub-command: the sub-commands' copies default to
    SUPPRESS so that ``clvol --verbose render ...`` is not reset by the sub-parser."""
    parser.add_argument("--verbose", action="store_true", help=VERBOSE_HELP)
    todo = [parser]
    while todo:
        p = todo.pop()
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                for child in action.choices.values():
                    child.add_argument("--verbose", action="store_true",
                                       default=argparse.SUPPRESS, help=VERBOSE_HELP)
                    todo.append(child)


def _add_info(sub) -> None:
    p = sub.add_parser("info", help="list OpenCL platforms and devices, and which one is chosen")
    p.add_argument("--device", help="device spec to try: P:D, gpu, cpu or a name substring")
    p.add_argument("--check", action="store_true",
                   help="build and run the default method and the path tracer on a tiny render "
                        "on each device (or the --device one); a kernel that fails to build is "
                        "named with its build log's first error")
    p.set_defaults(func=_cmd_info)


def _add_volume(sub) -> None:
    pv = sub.add_parser("volume", help="inspect, generate and convert density grids")
    vsub = pv.add_subparsers(dest="volume_command", required=True, metavar="ACTION")
    p = vsub.add_parser("info", help="resolution, bbox, density range, occupancy, optical thickness")
    p.add_argument("files", nargs="+", help=".vol, .npy, .npz or .vdb files (a .vdb: its grids)")
    p.add_argument("--density-scale", type=float, default=None,
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
    p = vsub.add_parser("convert", help="convert between .vol, .npy, .npz and .vdb")
    p.add_argument("input")
    p.add_argument("output")
    p.add_argument("--grid", help=".vdb input: the grid to read (default: density, else the "
                   "only scalar grid)")
    p.add_argument("--max-resolution", type=int, metavar="N",
                   help=".vdb input: box-filter while reading to at most N voxels per axis")
    p.set_defaults(func=_cmd_volume_convert)


def _add_render(sub) -> None:
    from .render import METHODS, available_methods
    from .render.options import add_cli_arguments
    methods = "; ".join(f"{k}: {v[1]}" for k, v in METHODS.items())
    p = sub.add_parser("render", help="render a scene to EXR", description=f"Methods: {methods}.")
    p.add_argument("scene", help="scene .toml file")
    p.add_argument("--method", choices=sorted(METHODS), default=None,
                   help="render method (default: raymarch, with the network's multiple "
                        "scattering: the paper's method)")
    p.add_argument("-o", "--output", required=True, help="output .exr")
    _add_preview_arguments(p)
    p.add_argument("--device", help="OpenCL device: P:D, gpu, cpu or a name substring")
    p.add_argument("--profile", action="store_true",
                   help="print per-kernel device times and the host<->device transfers")
    p.add_argument("--set", action="append", metavar="TABLE.FIELD=VALUE", help=SET_HELP)
    p.add_argument("--width", type=int, default=None, help="override the camera's width")
    p.add_argument("--height", type=int, default=None, help="override the camera's height")
    p.add_argument("--quiet", action="store_true",
                   help="print only the files written, not the render summary")
    p.add_argument("--frames", default=None, metavar="LIST",
                   help="a volume sequence (file = \"x_{frame:04d}.vdb\"): the frames to "
                        "render, e.g. 1-48 or 1,5,9; -o then names each file with {frame}, "
                        "e.g. -o out_{frame:04d}.exr (docs/scenes.md, 'Sequences')")
    # Each method's options, bound to it: one the chosen method does not use is refused.
    add_cli_arguments(p, list(available_methods()))
    p.set_defaults(func=_cmd_render)


def _add_preview_arguments(p) -> None:
    """The PNG preview's options of ``clvol render`` (the EXR is never changed by them)."""
    p.add_argument("--png", nargs="?", const="", default=None, metavar="FILE",
                   help="also write a tonemapped PNG preview (default: next to the EXR)")
    p.add_argument("--exposure", default=None, metavar="STOPS|image|scene",
                   help="preview exposure: a number of stops; 'image' (the default: chosen from "
                        "the image so its bright parts sit below white); or 'scene' (from the "
                        "light only, so a dark medium looks dark: docs/scenes.md, 'Previews'). "
                        "The EXR's pixels are never changed")
    p.add_argument("--tone", choices=["filmic", "linear"], default=None,
                   help="preview tone curve: filmic (default; highlights roll off) or linear "
                        "(clamp to [0, 1], then sRGB)")


def _add_view(sub) -> None:
    p = sub.add_parser("view", help="interactive viewer in the browser (served on 127.0.0.1)")
    p.add_argument("scene", help="scene .toml file")
    p.add_argument("--port", type=int, default=8765, help="port (default 8765; 0 = any free port)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1; anything else is reachable "
                        "from other machines and has no authentication)")
    p.add_argument("--no-browser", action="store_true", help="do not open a browser")
    p.add_argument("--save-dir", help="folder for 'save EXR' (default: the current folder)")
    p.add_argument("--device", help="OpenCL device: P:D, gpu, cpu or a name substring")
    p.add_argument("--set", action="append", metavar="TABLE.FIELD=VALUE", help=SET_HELP)
    p.set_defaults(func=_cmd_view)


def _add_bundle_and_goldens(sub) -> None:
    """The two commands for hosts in other languages (docs/embedding.md)."""
    from . import bundle, goldens
    p = sub.add_parser("bundle", help="write what a C host needs to render a scene "
                                      "(docs/embedding.md)")
    bundle.add_arguments(p)
    p.set_defaults(func=_cmd_bundle)
    p = sub.add_parser("goldens", help="write golden inputs and outputs of every kernel "
                                       "(docs/embedding.md)")
    goldens.add_arguments(p)
    p.set_defaults(func=goldens.run)


def _add_compare(sub) -> None:
    p = sub.add_parser("compare", help="error metrics of a test image against a reference")
    p.add_argument("test", help="test .exr or .pfm (the C demo's output)")
    p.add_argument("reference", help="reference .exr or .pfm")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=_cmd_compare)


def _add_dataset(sub) -> None:
    pd = sub.add_parser("dataset", help="training data for the network")
    dsub = pd.add_subparsers(dest="dataset_command", required=True, metavar="ACTION")
    p = dsub.add_parser(
        "make", help="make (or finish) a data set folder; resumable",
        description="Procedural volumes, random configurations, path-traced labels "
                    "(docs/dataset.md). Rerun the same command to resume; the folder's "
                    "spec.json must match the options.")
    add_dataset_make_arguments(p)
    p.set_defaults(func=_cmd_dataset_make)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.verbose:    # read by clvol/runtime.py (compiler_output_shown) and by pyopencl
        os.environ["PYOPENCL_COMPILER_OUTPUT"] = "1"
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
