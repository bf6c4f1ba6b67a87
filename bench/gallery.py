"""The gallery: every example rendered by the paper's method, the path-traced reference, the
Wrenninge octaves and single scattering only, with an error image, side by side, and the
measured error and time of each -- all from this one run.

    python bench/gallery.py                  # docs/gallery/*.png and docs/gallery.md
    python bench/gallery.py --quick          # small and noisy, to check it runs
    python bench/gallery.py --examples fire --update   # re-make some rows, keep the others

``fire`` is examples/fire/fire.toml (frame 6 of the generated sequence: its frames are made
by examples/fire/make_fire.py when missing); its row's strip adds no emission column: every
method shows its emission (the ray marcher the unscattered part only, docs/raymarch.md).
With ``--update`` the rows made in this run replace theirs in the existing gallery.md (or are
appended), each with the machine line of its own run; the other rows stay as they were.

Each row is one PNG strip (paper | reference | Wrenninge | single | error of the paper's
method), every image of a row tone-mapped with the same exposure (chosen from the reference)
and the filmic curve, so brightness differences are real. The error image shows
|luminance(paper) - luminance(reference)| after that exposure, times ERROR_GAIN, on a
black-red-yellow-white ramp. Frame times are wall-clock medians of warm frames (device state
kept by ``clvol.Renderer``, as in an application); the reference's time is its whole render.
Errors: the MRPNN metric (RMSE x100 of 8-bit codes after its exposure, ``clvol.metrics``)
and relMSE, both against the reference, whose own noise is included in them.
"""
from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import numpy as np

import _common

ROOT = _common.ROOT
EXAMPLES = ("cloud", "cloud_silver", "cloud_sky", "cloud_large", "jade", "milk", "wax", "smoke",
            "fire")


def example_path(name: str) -> Path:
    if name == "fire":
        fire = ROOT / "examples" / "fire"
        if not (fire / "fire_0006.npz").exists():
            sys.path.insert(0, str(fire))
            import make_fire
            make_fire.main([])
        return fire / "fire.toml"
    return ROOT / "examples" / f"{name}.toml"
ERROR_GAIN = 4.0
GAP = 4
# label -> Renderer options (the paper's method is the default: no options)
METHODS = {
    "paper": {},
    "reference": {"method": "pathtrace"},
    "wrenninge": {"method": "raymarch", "ms": "wrenninge"},
    "single": {"method": "raymarch", "ms": "none"},
}
TITLES = {"paper": "paper's method (network)", "reference": "path-traced reference",
          "wrenninge": "Wrenninge octaves", "single": "single scattering only"}


def error_ramp(e: np.ndarray) -> np.ndarray:
    """[0, 1] -> black, red, yellow, white (uint8 RGB)."""
    e = np.clip(e, 0.0, 1.0)[..., None]
    rgb = np.clip(np.concatenate([3 * e, 3 * e - 1, 3 * e - 2], axis=-1), 0.0, 1.0)
    return (rgb * 255 + 0.5).astype(np.uint8)


def timed_render(renderer, warm_frames: int) -> tuple[object, float]:
    """(result, seconds): the median over ``warm_frames`` renders after a first, cold one;
    with ``warm_frames`` = 0, the one render's time."""
    t0 = time.perf_counter()
    result = renderer.render()
    cold = time.perf_counter() - t0
    if warm_frames == 0:
        return result, cold
    times = []
    for _ in range(warm_frames):
        t0 = time.perf_counter()
        result = renderer.render()
        times.append(time.perf_counter() - t0)
    return result, statistics.median(times)


def main(argv=None) -> int:
    ap = _common.parser(__doc__, size=160, spp=1024)
    ap.add_argument("--warm-frames", type=int, default=3, help="timed warm frames per method")
    ap.add_argument("--examples", nargs="+", default=list(EXAMPLES))
    ap.add_argument("--out", default=str(ROOT / "docs" / "gallery"), help="folder for the PNGs")
    ap.add_argument("--markdown", default=str(ROOT / "docs" / "gallery.md"))
    ap.add_argument("--quick", action="store_true", help="64 pixels, 16 spp, 1 warm frame")
    ap.add_argument("--update", action="store_true",
                    help="replace only this run's rows in the existing markdown")
    args = ap.parse_args(argv)
    if args.quick:
        args.size, args.spp, args.warm_frames = 64, 16, 1

    import clvol
    from clvol.image import auto_exposure, encode_png_rgb8, tonemap_srgb8
    from clvol.metrics import mrpnn_metric, relmse
    from clvol.progress import Progress
    from clvol.runtime import get_runtime

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rt = get_runtime()
    machine = _common.machine(rt)
    print(machine)
    rows = []
    bar = Progress(len(args.examples) * len(METHODS), label="gallery", unit=" images")
    for name in args.examples:
        scene = _common.square(clvol.load_scene(example_path(name)), args.size)
        images, facts = {}, {}
        for label, options in METHODS.items():
            if label == "reference":
                r = clvol.Renderer(scene, spp=args.spp, seed=1, **options)
                result, seconds = timed_render(r, 0)
            else:
                r = clvol.Renderer(scene, **options)
                result, seconds = timed_render(r, args.warm_frames)
            rgb = np.asarray(result.layers["total"], dtype=np.float64)
            if not np.isfinite(rgb).all():
                raise SystemExit(f"{name}/{label}: non-finite pixels")
            images[label] = rgb
            facts[label] = {"seconds": seconds, "method": result.header.get("method", label)}
            bar.update(1)
        ref = images["reference"]
        ev = auto_exposure(ref)
        tiles = []
        for label in METHODS:
            px, _ = tonemap_srgb8(images[label], ev, "filmic")
            tiles.append(px)
            if label != "reference":
                facts[label]["mrpnn"] = mrpnn_metric(images[label], ref)
                facts[label]["relmse"] = relmse(images[label], ref)
                facts[label]["mean_ratio"] = float(images[label].mean() / max(ref.mean(), 1e-30))
        luma = np.array([0.2126, 0.7152, 0.0722])
        err = np.abs((images["paper"] - ref) @ luma) * 2.0 ** ev * ERROR_GAIN
        tiles.append(error_ramp(err))
        gap = np.full((args.size, GAP, 3), 40, np.uint8)
        strip = np.concatenate(sum(([t, gap] for t in tiles), [])[:-1], axis=1)
        png = out / f"{name}.png"
        png.write_bytes(encode_png_rgb8(strip))
        rows.append((name, png, facts, ev))
        print(f"{name}: " + "; ".join(
            f"{k} {v['seconds'] * 1e3:.0f} ms" + (f", MRPNN {v['mrpnn']:.2f}" if "mrpnn" in v else "")
            for k, v in facts.items()))
    bar.close()
    write_markdown(Path(args.markdown), rows, args, machine, update=args.update)
    print(f"wrote {args.markdown} and {len(rows)} images in {out}")
    return 0


def _sections(text: str) -> tuple[str, dict]:
    """(the text before the first row, {name: that row's section text})."""
    parts = text.split("\n## ")
    head, out = parts[0], {}
    for p in parts[1:]:
        out[p.split(" ", 1)[0]] = "## " + p
    return head, out


def write_markdown(path: Path, rows, args, machine: str, update: bool = False) -> None:
    rel = lambda p: Path(p).resolve().relative_to(path.parent.resolve()).as_posix()  # noqa: E731
    if update and path.exists():
        head, old = _sections(path.read_text())
        for name, png, facts, ev in rows:
            where = ("examples/fire/fire.toml, frame 6" if name == "fire"
                     else f"examples/{name}.toml")
            lines = [f"## {name} (`{where}`)", "", f"![{name}]({rel(png)})", "",
                     f"Made by `python bench/gallery.py --examples {' '.join(args.examples)} "
                     f"--update` ({args.spp} spp reference, {args.size}x{args.size}); machine: "
                     f"{machine}.", ""]
            lines += _table(facts)
            old[name] = "\n".join(lines) + "\n"
        order = [n for n in EXAMPLES if n in old] + [n for n in old if n not in EXAMPLES]
        path.write_text(head.rstrip("\n") + "\n\n" + "\n".join(old[n].rstrip("\n") + "\n"
                                                                  for n in order))
        return
    lines = [
        "# Gallery",
        "",
        "Made by `python bench/gallery.py` (every image and number below comes from that run; "
        "do not edit by hand).",
        "",
        f"Each row, left to right: **{TITLES['paper']}** | **{TITLES['reference']}** "
        f"({args.spp} spp) | **{TITLES['wrenninge']}** | **{TITLES['single']}** | "
        f"**error of the paper's method** (|luminance difference| x {ERROR_GAIN:g}, black-red-"
        "yellow-white). One exposure per row (from the reference), filmic tone curve; "
        f"{args.size}x{args.size} pixels.",
        "",
        "Times: median of warm frames with the device state kept (`clvol.Renderer`), the "
        "same view each frame, so the paper's method reuses its F_ms lattice (a moving camera "
        "refills it: `bench/bench_orbit.py`); the reference's time is its whole render. MRPNN: RMSE x100 of 8-bit codes after the MRPNN "
        "exposure (`clvol.metrics.mrpnn_metric`); relMSE; mean: image mean over the "
        "reference's. Errors include the reference's own noise.",
        "",
        f"Machine: {machine}.",
        "",
    ]
    for name, png, facts, ev in rows:
        where = "examples/fire/fire.toml, frame 6" if name == "fire" else f"examples/{name}.toml"
        lines += [f"## {name} (`{where}`)", "", f"![{name}]({rel(png)})", ""]
        lines += _table(facts)
    path.write_text("\n".join(lines))


def _table(facts) -> list[str]:
    lines = ["| method | time | MRPNN RMSE x100 | relMSE | mean / reference |",
             "|---|---|---|---|---|"]
    for label, f in facts.items():
        if label == "reference":
            lines.append(f"| {TITLES[label]} | {f['seconds']:.1f} s | - | - | 1 |")
        else:
            lines.append(f"| {TITLES[label]} | {f['seconds'] * 1e3:.1f} ms | {f['mrpnn']:.2f} | "
                         f"{f['relmse']:.4f} | {f['mean_ratio']:.3f} |")
    lines.append("")
    return lines


if __name__ == "__main__":
    sys.exit(main())
