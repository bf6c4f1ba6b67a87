#!/usr/bin/env python3
"""Plant known physics bugs in a scratch copy of the checkout and show which tests catch them.

    python scripts/plant_bugs.py                 # baseline + every bug, the default tests
    python scripts/plant_bugs.py --bugs lattice-corners --keep
    python scripts/plant_bugs.py --tests tests/test_raymarch.py
    python scripts/plant_bugs.py --mutation c-nx-ny c-octave-ab --report /tmp/table.md

Each bug names the tests it is run against (its own ``tests``: the tests written for it and
the older ones it used to pass); ``--tests`` runs one list for all of them instead. The
baseline runs the union of the selected bugs' tests. For each bug the report gives the wall
time of its pytest run and, per failing test, the test's own time (pytest's junit "time":
setup + call, e.g. building the C host in a module fixture counts toward the first test
using it).

Each run copies the working tree (not .git, caches) to a fresh temporary folder, recreates the
``clvol/_cl -> ../cl`` link there so the kernels come from the copy (clvol finds them through
importlib.resources 'clvol._cl'), checks that the copy's clvol and kernels are the ones imported,
patches one file and runs pytest in the copy. The patches search for the code they change and
stop with an error if it is not there exactly once (the code may have been rewritten since this
script was written: then update the pattern, do not drop the bug). docs/testing.md lists the
bugs, why each one passed the twin tests, and the last recorded result.

Not part of CI (it runs the tests once per bug: a few minutes).
"""
from __future__ import annotations

import argparse
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_TESTS = ["tests/test_phase_world.py", "tests/test_ms_lattice_roundtrip.py",
                 "tests/test_pathtrace_closed_form.py"]


class PatchError(RuntimeError):
    pass


def function_span(text: str, start_pattern: str, end_pattern: str) -> tuple[int, int]:
    """(start, end) of the one region that starts at ``start_pattern`` and ends before the
    next ``end_pattern`` (a function body, found without parsing)."""
    starts = [m.start() for m in re.finditer(start_pattern, text, re.M)]
    if len(starts) != 1:
        raise PatchError(f"expected one match of {start_pattern!r}, found {len(starts)}")
    m = re.compile(end_pattern, re.M).search(text, starts[0] + 1)
    return starts[0], (m.start() if m else len(text))


def replace_once(text: str, span: tuple[int, int], pattern: str, repl: str) -> str:
    a, b = span
    body = text[a:b]
    new, n = re.subn(pattern, repl, body)
    if n != 1:
        raise PatchError(f"expected exactly one match of {pattern!r} in the region, found {n}:\n"
                         + body[:400])
    return text[:a] + new + text[b:]


@dataclass(frozen=True)
class Bug:
    name: str
    path: str
    what: str
    tests: tuple = tuple(DEFAULT_TESTS)

    def apply(self, root: Path) -> None:
        f = root / self.path
        text = f.read_text()
        new = PATCHES[self.name](text)
        if new == text:
            raise PatchError(f"{self.name}: patch changed nothing in {self.path}")
        f.write_text(new)


def _mirrored_frame(text: str) -> str:
    # The view term of the phase-feature table: dot(d, omega) = u_z cos(a) - u_x sin(a) in
    # the template frame (omega = (sin a, 0, -cos a)). The camera reflected across the light
    # axis is omega = (-sin a, 0, -cos a): the sign of the u_x term flips.
    span = function_span(text, r"^def phase_features\(", r"^(def |class )")
    return replace_once(text, span,
                        r"(mu_out\s*=\s*u\[None,\s*:,\s*2\]\s*\*\s*ca\s*)-(\s*u\[None,\s*:,\s*0\]\s*\*\s*sa)",
                        r"\1+\2")


def _lattice_corners(text: str) -> str:
    # ms_lattice's axes: lo + (i + 0.5) * cell (cell centres) -> lo + i * cell (corners).
    span = function_span(text, r"^def ms_lattice\(", r"^(def |class )")
    return replace_once(text, span, r"\(np\.arange\((res\[a\])\)\s*\+\s*0\.5\)",
                        r"np.arange(\1)")


def _exactly_once(text: str, pattern: str, repl: str) -> str:
    new, n = re.subn(pattern, repl, text, flags=re.M)
    if n != 1:
        raise PatchError(f"expected exactly one match of {pattern!r}, found {n}")
    return new


def _shadow_rate_bias(text: str) -> str:
    # Ratio tracking toward the sun with tentative collisions at 1.01 x the majorant rate and
    # the ratios unchanged: E[T] = exp(-1.01 int sigma_t), a 1% extinction bias. The lane
    # kernel draws a lane's optical depth to its next tentative collision in two places (ray
    # start, after a rejected collision); shadow lanes get tau / 1.01 in both.
    text = _exactly_once(
        text, r"vf tau = -log\(1\.0f - pt_lanes_take\(S, ok\)\);",
        "vf tau = -log(1.0f - pt_lanes_take(S, ok)) / select((vf)(1.0f), (vf)(1.01f), shadow);")
    return _exactly_once(
        text, r"tau = select\(tau, -log\(1\.0f - pt_lanes_take\(S, more\)\), more\);",
        "tau = select(tau, -log(1.0f - pt_lanes_take(S, more)) / "
        "select((vf)(1.0f), (vf)(1.01f), shadow), more);")


def _shadow_sigma_bias(text: str) -> str:
    # The same 1% written into the ratio instead: 1 - 1.01 sigma / sigma_maj. Where the
    # majorant equals sigma (a homogeneous box) the ratio is clamped at 0 either way and the
    # bias vanishes; elsewhere E[T] = exp(-1.01 int sigma_t) as long as 1.01 sigma <= sigma_maj.
    return _exactly_once(text, r"1\.0f - sigma / sm\)", "1.0f - 1.01f * sigma / sm)")


def _c_nx_ny(text: str) -> str:
    # libclvol's ray-march arguments: the density grid's nx and ny swapped (the majorant
    # kernel's and the view source's depth pass, which start the same way, are left alone).
    span = function_span(text, r"^static void march_stage\(", r"^(static |clvol_status |int |void )")
    return replace_once(text, span, r"h->d_density, h->nx, h->ny, h->nz, &bmin",
                        "h->d_density, h->ny, h->nx, h->nz, &bmin")


def _c_octave_ab(text: str) -> str:
    # libclvol's ray-march arguments: Wrenninge octave parameters a and b swapped.
    return _exactly_once(text, r"abc\[0\], abc\[1\], abc\[2\]", "abc[1], abc[0], abc[2]")


def _backward_limit(text: str) -> str:
    return _exactly_once(text, r"^BACKWARD_LIMIT = -0\.8\b", "BACKWARD_LIMIT = -0.7")


def _backward_albedo(text: str) -> str:
    return _exactly_once(text, r"^BACKWARD_ALBEDO = 0\.9\b", "BACKWARD_ALBEDO = 0.8")


def _coarse_level_plus_one(text: str) -> str:
    # The pyramid level of the gather's coarse occupancy grid one level too coarse.
    span = function_span(text, r"^def coarse_level\(", r"^(def |class |@)")
    return replace_once(text, span, r"(return max\(0, .*\))\n", r"\1 + 1\n")


def _furnace_any(text: str) -> str:
    # The white furnace (escape model for the sky) at albedo 1 in *any* channel.
    return _exactly_once(text, r"furnace = all\(a == 1\.0 for a in medium\.albedo\)",
                         "furnace = any(a == 1.0 for a in medium.albedo)")


def _lit_all(text: str) -> str:
    # Lit only when *every* channel has albedo * irradiance > 0.
    span = function_span(text, r"^def is_lit\(", r"^(def |class |@)")
    return replace_once(text, span, r"np\.any\(", "np.all(")


def _blackbody_hot(text: str) -> str:
    # The blackbody table read at a temperature 1% high.
    span = function_span(text, r"^def map_blackbody\(", r"^(def |class |@|# ---)")
    return replace_once(text, span, r"temperature\.astype\(np\.float64\)\.ravel\(\) \*",
                        "temperature.astype(np.float64).ravel() * 1.01 *")


def _vdb_affine_translation(text: str) -> str:
    # An AffineMap's (or UnitaryMap's) translation dropped.
    return _exactly_once(text, r"scale, trans = np\.diag\(m\)\[:3\]\.copy\(\), m\[3, :3\]\.copy\(\)",
                         "scale, trans = np.diag(m)[:3].copy(), np.zeros(3)")


def _sky_newest_first(text: str) -> str:
    # The network sky refreshes its stale cells newest first.
    return _exactly_once(text, r"stale = \[j for j in order if",
                         "stale = [j for j in reversed(order) if")


def _view_jitter_swap(text: str) -> str:
    # The stochastic source places its points on rays with the jitter's x and y swapped
    # against cl/viewdepth.cl (which marched x = i B + jitter.x B, y = j B + jitter.y B).
    text = _exactly_once(text, r"col = \(np\.arange\(bx\)\[None, :\] \+ jitter\[\.\.\., 0\]\)",
                         "col = (np.arange(bx)[None, :] + jitter[..., 1])")
    return _exactly_once(text, r"row = \(np\.arange\(by\)\[:, None\] \+ jitter\[\.\.\., 1\]\)",
                         "row = (np.arange(by)[:, None] + jitter[..., 0])")


def _pyramid_copy_unchecked(text: str) -> str:
    # The device copy of level 0 for any base^3 grid, cube box or not.
    return _exactly_once(text, r"if density is not None and is_identity\(grid, base\) and ",
                         "if density is not None and ")


def _chord_width(text: str) -> str:
    # The labels' upper bound: the chord over a bin one exponent wider than the bin.
    span = function_span(text, r"^def label_bounds\(", r"^(def |class |@)")
    return replace_once(text, span, r"width = np\.maximum\(hi_e - lo_e, 1\.0\)",
                        "width = np.maximum(hi_e - lo_e + 1, 1.0)")


def _block_blend_swap(text: str) -> str:
    # The view table's bilinear blend with the (i1, j0) and (i0, j1) weights swapped.
    return _exactly_once(
        text, r"float bw\[4\] = \{\(1\.0f - fu\) \* \(1\.0f - fv\), fu \* \(1\.0f - fv\), "
              r"\(1\.0f - fu\) \* fv, fu \* fv\};",
        "float bw[4] = {(1.0f - fu) * (1.0f - fv), (1.0f - fu) * fv, fu * (1.0f - fv), fu * fv};")


PATCHES = {"mirrored-frame": _mirrored_frame, "lattice-corners": _lattice_corners,
           "shadow-bias": _shadow_rate_bias, "shadow-bias-ratio": _shadow_sigma_bias,
           "c-nx-ny": _c_nx_ny, "c-octave-ab": _c_octave_ab,
           "backward-limit": _backward_limit, "backward-albedo": _backward_albedo,
           "coarse-level": _coarse_level_plus_one, "furnace-any": _furnace_any,
           "lit-all": _lit_all, "blackbody-hot": _blackbody_hot,
           "vdb-affine-translation": _vdb_affine_translation,
           "sky-newest-first": _sky_newest_first, "view-jitter-swap": _view_jitter_swap,
           "pyramid-copy-unchecked": _pyramid_copy_unchecked, "chord-width": _chord_width,
           "block-blend-swap": _block_blend_swap}
C_TESTS = ("tests/test_c_host.py::test_c_render_matches_python",
           "tests/test_c_host.py::test_c_render_matches_python_on_a_non_cubic_volume_and_image",
           "tests/test_c_host.py::test_c_octaves_with_distinct_parameters_match_python",
           "tests/test_capi.py")
FALLBACK_TESTS = ("tests/test_fallback_rule.py",
                  "tests/test_renderer.py::test_outside_the_domain_warns_and_uses_the_measured_alternative")
BUGS = [
    Bug("mirrored-frame", "clvol/features/phasetable.py",
        "phase feature's view term with the camera reflected across the light axis"),
    Bug("lattice-corners", "clvol/render/ms/lattice.py",
        "F_ms lattice points at cell corners instead of cell centres (ms_lattice)"),
    Bug("shadow-bias", "cl/pathtrace.cl",
        "1% extinction bias on shadow rays (tentative collisions at 1.01 x the majorant rate)"),
    Bug("shadow-bias-ratio", "cl/pathtrace.cl",
        "1% extinction bias on shadow rays written into the ratio (1 - 1.01 sigma/sigma_maj)"),
    Bug("c-nx-ny", "capi/src/renderer.c",
        "libclvol: nx and ny swapped in the ray-march kernel's arguments", C_TESTS),
    Bug("c-octave-ab", "capi/src/renderer.c",
        "libclvol: Wrenninge octave parameters a and b swapped", C_TESTS),
    Bug("backward-limit", "clvol/render/ms/network.py",
        "network fallback: BACKWARD_LIMIT -0.8 -> -0.7", FALLBACK_TESTS),
    Bug("backward-albedo", "clvol/render/ms/network.py",
        "network fallback: BACKWARD_ALBEDO 0.9 -> 0.8", FALLBACK_TESTS),
    Bug("coarse-level", "clvol/kernels/gather.py",
        "gather: coarse_level one level too coarse (+ 1)", ("tests/test_gather.py",)),
    # issue 41's survivors: the test written for each, then the older files it passed
    Bug("furnace-any", "clvol/render/plan.py",
        "white furnace with any channel at albedo 1 instead of all",
        ("tests/test_survivors.py", "tests/test_plan.py")),
    Bug("lit-all", "clvol/render/plan.py",
        "is_lit with all channels instead of any", ("tests/test_survivors.py",
                                                    "tests/test_plan.py")),
    Bug("blackbody-hot", "clvol/emission.py", "map_blackbody at a temperature 1% high",
        ("tests/test_survivors.py", "tests/test_emission.py")),
    Bug("vdb-affine-translation", "clvol/volume/vdb.py",
        "AffineMap/UnitaryMap translation dropped", ("tests/test_survivors.py",
                                                     "tests/test_vdb.py")),
    Bug("sky-newest-first", "clvol/render/environment.py",
        "network sky refreshes stale cells newest first",
        ("tests/test_survivors.py", "tests/test_raymarch_env.py::"
         "test_network_sky_refreshes_a_few_cells_per_frame_when_asked")),
    Bug("view-jitter-swap", "clvol/render/ms/view.py",
        "stochastic source: host jitter x/y swapped against cl/viewdepth.cl",
        ("tests/test_survivors.py::test_stochastic_points_lie_on_the_rays_the_depth_kernel_marched",
         "tests/test_stochastic_source.py", "tests/test_viewdepth.py")),
    Bug("pyramid-copy-unchecked", "clvol/kernels/pyramid.py",
        "pyramid: level 0 copied on the device without the cube (identity) check",
        ("tests/test_survivors.py::"
         "test_a_base_sized_grid_on_the_device_is_copied_only_when_its_box_is_a_cube",
         "tests/test_pyramid.py")),
    Bug("chord-width", "clvol/training/labels.py",
        "labels: the upper bound's chord one exponent wider than its bin",
        ("tests/test_survivors.py::"
         "test_the_chord_bound_is_exact_when_a_bin_holds_only_its_end_exponents",
         "tests/test_labels_orders.py")),
    Bug("block-blend-swap", "cl/raymarch.cl",
        "view table: bilinear block weights of (i1, j0) and (i0, j1) swapped",
        ("tests/test_survivors.py::test_each_pixel_blends_its_four_nearest_blocks_bilinearly",
         "tests/test_view_source.py", "tests/test_stochastic_source.py")),
]


def make_copy(dest: Path) -> Path:
    ignore = shutil.ignore_patterns(".git", "__pycache__", ".pytest_cache", "*.pyc", "_cl")
    shutil.copytree(ROOT, dest, ignore=ignore, symlinks=True)
    (dest / "clvol" / "_cl").symlink_to(Path("..") / "cl")
    # The copy's package and kernels must be the ones imported there.
    probe = subprocess.run(
        [sys.executable, "-c",
         "import clvol, importlib.resources as r; print(clvol.__file__); "
         "print(r.files('clvol._cl') / 'pathtrace.cl')"],
        cwd=dest, capture_output=True, text=True, check=True)
    pkg, kern = (Path(x).resolve() for x in probe.stdout.split())
    for p in (pkg, kern):
        if dest.resolve() not in p.parents:
            raise RuntimeError(f"the copy imports {p}, outside {dest}: the planted bug would not run")
    return dest


def run_tests(root: Path, tests: list[str]) -> tuple[dict, dict, float, dict]:
    """Run ``tests`` in the copy: ({test: pass/FAIL/skip}, {test: why}, wall seconds,
    {test: pytest's own seconds for it})."""
    xml = root / "plant-report.xml"
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                        f"--junitxml={xml}", *tests], cwd=root, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if not xml.exists():
        raise RuntimeError(f"pytest wrote no report (exit {p.returncode}):\n{p.stdout[-2000:]}"
                           f"{p.stderr[-2000:]}")
    results, why, times = {}, {}, {}
    for case in ET.parse(xml).getroot().iter("testcase"):
        name = f"{case.get('classname', '').split('.')[-1]}::{case.get('name')}"
        times[name] = float(case.get("time") or 0.0)
        bad = case.find("failure")
        bad = bad if bad is not None else case.find("error")
        if bad is not None:
            results[name] = "FAIL"
            why[name] = " ".join((bad.get("message") or "").split())[:160]
        elif case.find("skipped") is not None:
            results[name] = "skip"
        else:
            results[name] = "pass"
    return results, why, seconds, times


def _machine() -> str:
    """The machine and its load (bench/_common.py's line, without importing clvol here)."""
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    return (f"{platform.processor() or platform.machine()}; {os.cpu_count()} logical cores; "
            f"Python {platform.python_version()}; load average: {load}; "
            f"{time.strftime('%Y-%m-%d %H:%M')}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    names = [b.name for b in BUGS]
    ap.add_argument("--bugs", "--mutation", nargs="*", default=None, choices=names,
                    help="bugs to plant (default: all)")
    ap.add_argument("--tests", nargs="*", default=None,
                    help="one test list for every bug (default: each bug's own tests)")
    ap.add_argument("--no-baseline", action="store_true", help="skip the unpatched run")
    ap.add_argument("--keep", action="store_true", help="keep the scratch copies")
    ap.add_argument("--report", help="also write the summary table (markdown) to this file")
    args = ap.parse_args(argv)

    bugs = [b for b in BUGS if args.bugs is None or b.name in args.bugs]
    print(_machine())

    def tests_of(bug):
        if args.tests is not None:
            return list(args.tests)
        if bug is not None:
            return list(bug.tests)
        union = []
        for b in bugs:
            union += [t for t in b.tests if t not in union]
        return union

    runs = ([] if args.no_baseline else [None]) + bugs
    table, summary = {}, []
    scratch = Path(tempfile.mkdtemp(prefix="clvol-plant-"))
    try:
        for bug in runs:
            label = bug.name if bug else "baseline"
            root = make_copy(scratch / label)
            if bug:
                bug.apply(root)
            tests = tests_of(bug)
            results, why, seconds, times = run_tests(root, tests)
            table[label] = results
            failed = [k for k, v in results.items() if v == "FAIL"]
            print(f"{label:18s} {seconds:6.1f} s  {len(failed)}/{len(results)} tests fail"
                  + (f"  ({bug.what})" if bug else ""), flush=True)
            for k in failed:
                print(f"{'':20s}FAIL {k} ({times[k]:.2f} s)\n{'':25s}{why[k]}")
            if bug:
                summary.append((bug, failed, len(results), seconds, times, why))
    finally:
        if args.keep:
            print(f"scratch copies kept in {scratch}")
        else:
            shutil.rmtree(scratch, ignore_errors=True)

    names = sorted({k for r in table.values() for k in r})
    lines = ["| test | " + " | ".join(table) + " |", "|---|" + "---|" * len(table)]
    lines += [f"| {n} | " + " | ".join(table[c].get(n, "-") for c in table) + " |"
              for n in names]
    lines += ["", "| bug | caught by | test's own s | pytest run, wall s |", "|---|---|---|---|"]
    for bug, failed, n, seconds, times, why in summary:
        if failed:
            first = min(failed, key=lambda k: times[k])
            by = (f"`{first}`" + (f" (+{len(failed) - 1} more of {n})" if len(failed) > 1
                                  else f" (1 of {n})"))
            lines.append(f"| `{bug.name}` | {by} | {times[first]:.2f} | {seconds:.1f} |")
        else:
            lines.append(f"| `{bug.name}` | **none** (0 of {n} fail) | - | {seconds:.1f} |")
    print()
    print("\n".join(lines))
    print(_machine())                                   # the load after the runs
    if args.report:
        Path(args.report).write_text("\n".join(lines) + "\n")
    ok = True
    if "baseline" in table and any(v != "pass" for v in table["baseline"].values()):
        print("\nbaseline (no bug) does not pass: the results above mean nothing", file=sys.stderr)
        ok = False
    for bug in bugs:
        if not any(v == "FAIL" for v in table[bug.name].values()):
            print(f"\n{bug.name}: no test failed", file=sys.stderr)
            ok = False
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
