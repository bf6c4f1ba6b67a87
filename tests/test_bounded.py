"""Every render bounded (issue 41): degenerate geometry through the path tracer (and the ray
marcher where it has a bound of its own) finishes in seconds at 32 x 32, renders a finite image
or raises a one-line ClvolError, and says in its header when a bound stopped it.

The bounds (docs/pathtrace.md, "Bounds"; cl/pathtrace.cl, cl/raymarch.cl, cl/viewdepth.cl):
- path tracer: a path ends (row's truncated word 2, header ``paths_stopped_at_bound``) after
  PT_MAX_STEPS = 2^20 tentative collisions, or after PT_MAX_STALLS = 256 in a row that each
  move t by less than 2^-20 of a majorant block (1/sigma_maj below t's float32 rounding, or
  a block that takes millions of draws to cross: density_scale 1e12 on a unit cloud ran past
  60 s before, at 32 x 32 and 1 spp);
- ray marcher: a ray stops where its next segment would not start past the current one;
  the kernel counts those rays (header ``raymarch.rays_stopped_at_bound``, 0 normally);
- path tracer images: a medium whose majorant optical depth per majorant cell exceeds 2^13
  (clvol/kernels/transmittance.py check_tracking_depth) is refused before rendering;
- view depths: at most 2^22 segments a ray, and no undefined (int) cast of a NaN or huge span.

Each case runs in a child process with a hard timeout (a hang must fail the test, not stall
the suite): WALL_S covers Python's start, clvol's import and the first build of a kernel
variant on a cold cache (5-10 s at load ~8); the renders themselves took 0.5-4 s (measured
at load 2-7, builds cached), the stalled path tracer 0.5-1 s.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
WALL_S = 60           # the child's hard limit; a render must take RENDER_S
RENDER_S = 15.0

CHILD = textwrap.dedent('''
    import json, sys, time
    import numpy as np
    import clvol
    from clvol.errors import ClvolError
    from clvol.scene import scene_from_dict
    from clvol.volume.grid import DensityGrid
    case = json.loads(sys.argv[1])
    d = {"volume": {"generator": "cloud", "seed": 3, "resolution": 16},
         "medium": {"preset": "cloud", "density_scale": 30.0},
         "light": {"direction": [0.6, 0.9, 0.3], "irradiance": [1.5, 1.5, 1.5]},
         "camera": {"origin": [0.0, 0.3, 2.4], "target": [0.0, 0.0, 0.0],
                    "up": [0.0, 1.0, 0.0], "fov_y": 30.0, "width": 32, "height": 32}}
    for key, value in case.get("scene", {}).items():
        table, field = key.split(".")
        d[table][field] = value
    out = {}
    t = time.perf_counter()
    try:
        grid = None
        if "grid" in case:
            g = case["grid"]
            dens = np.full((8, 9, 10), g.get("value", 1.0), np.float32)
            if "corner" in g:
                dens[:2, :2, :2] = g["corner"]
            grid = DensityGrid.from_array(dens, g.get("bmin", (-0.5,) * 3), g.get("bmax", (0.5,) * 3))
        scene = scene_from_dict(d, "<bounded>")
        opts = dict(case.get("options", {}))
        extra = opts.pop("extra_defines", None)
        if extra is not None:
            from clvol.render.pathtrace import render_pathtrace
            res = render_pathtrace(scene, spp=1, grid=grid, extra_defines=extra)
        else:
            res = clvol.Renderer(scene, case["method"], grid=grid, **opts).render()
        rgb = res.layers["total"]
        out.update(ok=True, finite=bool(np.isfinite(rgb).all()), shape=list(rgb.shape),
                   header={k: v for k, v in res.header.items()
                           if k in ("paths_stopped_at_bound", "paths_truncated",
                                    "mean_tracking_steps",
                                    "raymarch.rays_stopped_at_bound")})
    except ClvolError as e:
        out.update(ok=False, error=str(e))
    out["seconds"] = time.perf_counter() - t
    print("RESULT " + json.dumps(out, default=float))
''')


def _run(case: dict) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    try:
        p = subprocess.run([sys.executable, "-c", CHILD, json.dumps(case)], cwd=ROOT, env=env,
                           capture_output=True, text=True, timeout=WALL_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{case}: still running after {WALL_S} s (unbounded)")
    lines = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
    assert p.returncode == 0 and lines, p.stderr[-3000:]
    return json.loads(lines[-1][len("RESULT "):])


PT = {"method": "pathtrace", "options": {"spp": 1}}


@pytest.mark.parametrize("name,case", [
    ("density_scale 1e6", {"scene": {"medium.density_scale": 1e6}}),
    ("density_scale 1e7, albedo 1", {"scene": {"medium.density_scale": 1e7,
                                               "medium.albedo": [1.0, 1.0, 1.0]}}),
    ("density_scale 1e7, albedo 0.9", {"scene": {"medium.density_scale": 1e7,
                                                 "medium.albedo": [0.9, 0.9, 0.9]}}),
    ("density_scale 1e12", {"scene": {"medium.density_scale": 1e12}}),
    ("density_scale 1e30", {"scene": {"medium.density_scale": 1e30}}),
    ("density 1e30 corner", {"grid": {"value": 0.0, "corner": 1e30}}),
    ("density 1e30 everywhere", {"grid": {"value": 1e30}}),
])
def test_extreme_extinction_is_refused_before_rendering(name, case):
    """A medium whose majorant optical depth per majorant cell is above MAX_CELL_DEPTH
    (clvol/kernels/transmittance.py check_tracking_depth): its paths would take about that many
    tentative collisions each (density_scale 1e6-1e7 on a unit cloud took 4-23 s at 32 x 32,
    1 spp, with 0.3-65% of the paths stopped at PT_MAX_STEPS; 1e12 and up stopped at the
    stall bound, a black, biased image). Refused in one line, naming the value and the limit,
    in under 5 s (measured 0.01-0.1 s: nothing is uploaded or built)."""
    r = _run({**PT, **case})
    assert not r["ok"], r
    assert "\n" not in r["error"] and "above its limit 8192" in r["error"], r
    assert r["seconds"] < 5.0, r


def test_the_tracking_rule_is_the_documented_product_just_either_side():
    """density_scale x the largest density x the majorant cell's longest side (inside the box)
    against 2^13, written here from docs/pathtrace.md: the unit cloud (16^3, largest density
    d) at block 8 has cells 0.5 across, so density_scale = 2^14 / d passes and 1.001 x that
    does not, and the refusal names the coarsest block that passes (7: 7/8 of the depth); at
    block 2 (cells 0.125) that scale passes; one global majorant (block 0) spans the box (1
    across, 16 voxels)."""
    from clvol.errors import ClvolError
    from clvol.render.pathtrace import check_walks
    from clvol.scene import scene_from_dict
    grid = scene_from_dict({
        "volume": {"generator": "cloud", "seed": 3, "resolution": 16},
        "medium": {"preset": "cloud", "density_scale": 30.0},
        "light": {"direction": [0.0, 0.0, 1.0], "irradiance": [1.0, 1.0, 1.0]},
        "camera": {"origin": [0.0, 0.3, 2.4], "target": [0.0, 0.0, 0.0], "fov_y": 30.0,
                   "width": 8, "height": 8}}, "<rule>").volume.load()
    assert grid.density.shape == (16, 16, 16)
    d = float(grid.density.max())
    edge = 2.0 ** 13 / (0.5 * d)
    assert check_walks(edge, grid, 8) == pytest.approx(2.0 ** 13)
    with pytest.raises(ClvolError, match=r"cell 0.5 across \(8 voxels\).*above its limit 8192.*block of 7 voxels or fewer"):
        check_walks(edge * 1.001, grid, 8)
    assert check_walks(edge * 1.001, grid, 2) == pytest.approx(2.0 ** 13 * 1.001 / 4)
    with pytest.raises(ClvolError, match=r"cell 1 across \(16 voxels\).*block of 13 voxels or fewer"):
        check_walks(edge * 0.6, grid, 0)
    assert check_walks(edge * 0.49, grid, 0) == pytest.approx(2.0 ** 13 * 0.49 * 2)


def test_the_cli_exits_2_on_a_medium_too_thick_to_path_trace(tmp_path):
    """The issue's command: examples/cloud.toml at density_scale 1e7, 32 x 32 (4-23 s before,
    bench/bench_thick_media.py): exit 2, one line naming the value and the limit."""
    import time
    text = (ROOT / "examples" / "cloud.toml").read_text()
    text = text.replace("density_scale = 64.0", "density_scale = 1e7")
    assert "density_scale = 1e7" in text
    scene = tmp_path / "thick.toml"
    scene.write_text(text)
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    t = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "clvol", "render", str(scene), "--method",
                        "pathtrace", "--width", "32", "--height", "32", "--spp", "1", "-o",
                        str(tmp_path / "out.exr")], cwd=ROOT, env=env, capture_output=True,
                       text=True, timeout=WALL_S)
    wall = time.perf_counter() - t
    assert p.returncode == 2, (p.returncode, p.stderr[-2000:])
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "density_scale = 10000000.0" in lines[0], lines
    assert "above its limit 8192" in lines[0] and not (tmp_path / "out.exr").exists()
    assert wall < RENDER_S, wall       # Python's start and clvol's import included


def test_the_stall_bound_stops_paths_and_is_counted():
    """The stall bound can no longer be met by an image the rule accepts (a stall needs a
    majorant optical depth of ~2^20 per cell, the rule stops at 2^13), so it is provoked from
    the host: PT_STALL_FRACTION = 0.5 (of a 0.5-wide cell) with PT_MAX_STALLS = 4 makes almost
    every tentative collision a stall (mean step 1/sigma_maj ~ 0.01 here), so paths that
    enter the cloud stop after 4 draws and are counted."""
    r = _run({**PT, "options": {"extra_defines": {"PT_STALL_FRACTION": 0.5,
                                                  "PT_MAX_STALLS": 4}}})
    assert r["ok"] and r["finite"], r
    assert r["header"]["paths_stopped_at_bound"] > 100, r
    assert r["header"]["mean_tracking_steps"] <= 4.0, r


def test_an_ordinary_scene_hits_no_bound():
    r = _run(PT)
    assert r["ok"] and r["finite"], r
    assert r["header"]["paths_stopped_at_bound"] == 0 and r["header"]["paths_truncated"] == 0
    r = _run({"method": "raymarch"})
    assert r["ok"] and r["finite"] and r["header"]["raymarch.rays_stopped_at_bound"] == 0, r


def test_the_step_bound_stops_paths_and_is_counted():
    """PT_MAX_STEPS set to 4 from the host (render_pathtrace's extra_defines): every path that
    enters the cloud takes more than 4 tentative collisions (mean ~50 at density_scale 30), so
    most stop, and none takes more than the bound's worth of steps on average."""
    r = _run({**PT, "options": {"extra_defines": {"PT_MAX_STEPS": 4}}})
    assert r["ok"] and r["finite"], r
    assert r["header"]["paths_stopped_at_bound"] > 100, r
    assert r["header"]["mean_tracking_steps"] <= 4.0, r


@pytest.mark.parametrize("name,case,method", [
    ("camera inside the medium", {"scene": {"camera.origin": [0.05, 0.02, 0.01]}}, "pathtrace"),
    ("camera 1e30 away", {"scene": {"camera.origin": [0.0, 0.0, 1e30]}}, "pathtrace"),
    ("camera 1e30 away", {"scene": {"camera.origin": [0.0, 0.0, 1e30]}}, "raymarch"),
    ("field of view 1e-6 degrees", {"scene": {"camera.fov_y": 1e-6}}, "pathtrace"),
    ("a box 1e-30 on a side", {"grid": {"bmin": [0, 0, 0], "bmax": [1e-30] * 3}}, "pathtrace"),
])
def test_degenerate_cameras_and_boxes_render_finite(name, case, method):
    r = _run({"method": method, "options": {"spp": 1} if method == "pathtrace" else {},
              **case})
    assert r["ok"] and r["finite"] and r["shape"] == [32, 32, 3], r
    assert r["seconds"] < RENDER_S, r
    if method == "raymarch" and name == "camera 1e30 away":
        # the box is thinner than t's float32 rounding step there (t0 == t1): every ray ends
        # at once at the box's far side, not at the bound (the prediction this count replaced
        # said "rays may stop early")
        assert r["header"]["raymarch.rays_stopped_at_bound"] == 0, r


@pytest.mark.parametrize("name,case,words", [
    ("camera at its target", {"scene": {"camera.origin": [0.0, 0.0, 0.0]}}, "target"),
    ("up parallel to the view", {"scene": {"camera.up": [0.0, -0.3, -2.4]}}, "up"),
    ("zero-size box", {"grid": {"bmin": [0, 0, 0], "bmax": [1, 1, 0]}}, "bbox"),
    ("a slab 1e-30 thick", {"grid": {"bmin": [0, 0, 0], "bmax": [1, 1, 1e-30]}}, "too thin"),
    ("NaN density", {"grid": {"value": float("nan")}}, "NaN"),
    ("infinite density", {"grid": {"value": float("inf")}}, "finite"),
])
def test_degenerate_inputs_are_refused_in_one_line(name, case, words):
    r = _run({**PT, **case})
    assert not r["ok"], r
    assert "\n" not in r["error"] and words in r["error"], r
    assert r["seconds"] < 5.0, r


def test_the_march_counts_the_rays_its_bound_stopped():
    """The kernel counts (atomically) the rays its progress bound stopped, and the header
    reports that count. The camera 2e6 from the unit cloud with a view 1e-5 degrees high
    (every ray crosses the box's middle): t's float32 rounding step there is 0.25, the step
    (half a voxel of 16) 0.031, so t0 + step == t0 and each of the 32 x 32 rays stops at its
    first segment; the image is the background alone. 2e4 away (rounding step 0.002) every
    ray is marched and the count is 0."""
    far = {"camera.origin": [0.0, 0.0, 2e6], "camera.fov_y": 1e-5}
    r = _run({"method": "raymarch", "scene": far})
    assert r["ok"] and r["finite"], r
    assert r["header"]["raymarch.rays_stopped_at_bound"] == 32 * 32, r
    assert r["seconds"] < RENDER_S, r
    near = {"camera.origin": [0.0, 0.0, 2e4], "camera.fov_y": 1e-3}
    r = _run({"method": "raymarch", "scene": near})
    assert r["ok"] and r["finite"] and r["header"]["raymarch.rays_stopped_at_bound"] == 0, r


@pytest.mark.parametrize("method", ["raymarch", "pathtrace"])
def test_fuzz_found_float32_overflowing_extinction_is_refused(method):
    """Found by the API fuzz's 500-example run (after the bounds): density_scale = 3.4e38
    (float32's largest) with albedo 0 rendered a NaN alpha through the path tracer and the
    unlit march (inf * 0). Both methods now refuse, in one line, what the light field
    already refused: density_scale x the largest density x the box's diagonal >= 1e37. Just
    below it (1e30) the march renders; the path tracer refuses it by its tracking rule."""
    import clvol
    from clvol.errors import ClvolError
    from clvol.scene import Camera, Light, Medium, Phase, scene_from_dict
    scene = scene_from_dict({
        "volume": {"generator": "cloud", "seed": 3, "resolution": 16},
        "medium": {"preset": "cloud", "density_scale": 30.0},
        "light": {"direction": [0.0, 0.0, 1.0], "irradiance": [1.0, 1.0, 1.0]},
        "camera": {"origin": [0.0, 0.3, 2.4], "target": [0.0, 0.0, 0.0], "fov_y": 30.0,
                   "width": 8, "height": 8}}, "<float32>")
    r = clvol.Renderer(scene, method, **({"spp": 1} if method == "pathtrace" else {}))
    cam = Camera(origin=(0.0, 0.0, 0.0), target=(0.0, 0.0, 0.5), up=(0.0, 1.0, 0.0), fov_y=1.0,
                 width=1, height=1)
    light = Light(direction=(0.0, 0.0, 1.0), irradiance=(0.0, 0.0, 0.0))
    for scale in (3.4028235677973366e+38, 1e37):
        medium = Medium(density_scale=scale, albedo=(0.0, 0.0, 0.0), phase=Phase.isotropic())
        with pytest.raises(ClvolError, match="beyond float32 range") as e:
            r.render(camera=cam, light=light, medium=medium)
        assert "\n" not in str(e.value)
    below = Medium(density_scale=1e30, albedo=(0.0, 0.0, 0.0), phase=Phase.isotropic())
    if method == "pathtrace":   # within float32, but far beyond the path tracer's walks
        with pytest.raises(ClvolError, match="above its limit 8192"):
            r.render(camera=cam, light=light, medium=below)
        return
    ok = r.render(camera=cam, light=light, medium=below)
    assert all(np.isfinite(v).all() for v in ok.layers.values())


def test_point_queries_inside_an_extreme_medium_stop_and_say_so():
    """Labels (point_query) start their walks at t = 0 inside the medium, where t's rounding
    does not stop a flight: at density_scale 1e30 a tentative step is ~1e-31, so before the
    stall rule counted steps shorter than 2^-20 of a majorant block a path ran to the step
    bound (2^20 draws) instead. Now such paths stop after 256 short steps: 64 paths at 4
    points in a few seconds, every one counted, the labels finite."""
    import time
    from clvol.render.pathtrace import point_query
    from clvol.scene import scene_from_dict
    scene = scene_from_dict({
        "volume": {"generator": "cloud", "seed": 3, "resolution": 16},
        "medium": {"preset": "cloud", "density_scale": 1e30},
        "light": {"direction": [0.6, 0.9, 0.3], "irradiance": [1.0, 1.0, 1.0]},
        "camera": {"origin": [0.0, 0.3, 2.4], "target": [0.0, 0.0, 0.0], "fov_y": 30.0,
                   "width": 8, "height": 8}}, "<queries>")
    p = np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [-0.45, 0.4, 0.45], [0.2, 0.2, -0.3]])
    w = np.tile([0.0, 0.0, 1.0], (4, 1))
    t0 = time.perf_counter()
    out = point_query(scene, p, w, 64, seed=1)
    assert time.perf_counter() - t0 < RENDER_S
    assert out["stopped_at_bound"] > 0 and out["truncated"] == 0, out["stopped_at_bound"]
    assert all(np.isfinite(out[k]).all() for k in ("F1", "Fms", "F1_se", "Fms_se"))
