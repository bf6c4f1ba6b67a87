"""libclvol's stochastic view-space source (``clvol bundle --ms stochastic``; docs/embedding.md,
"The stochastic view source") against clvol.Renderer with ``--ms stochastic``
(clvol/render/ms/view.py StochasticViewMs).

- The jitter both hosts draw is one Philox4x32-10 stream (docs/conventions.md,
  "Randomness"): libclvol's C function and Python's view_jitter give the same float32 bits,
  and both equal the NumPy twin reference/rng.py (checked against Random123's known answers
  in tests/test_rng.py).
- A scripted 10-frame orbit (still frames, moves, one light change) at 48x40 on a 32^3 cloud:
  every frame's RGB within 1e-3 relative RMS of Python's (the issue's bar; both hosts launch
  the same kernels with the same jitter on one device, so what may differ is the last bits
  of float64 host arithmetic: the camera basis and the reprojection's projections; 0 on this
  script, ~5e-8 once by hand on an orbit with other vectors). Multiple scattering is 0.92 of
  this cloud's image (RMS), so a wrong table shows: a bundle with another seed misses Python's
  first frame by a relative RMS of 0.128, and the assertion asks for > 0.05 (both printed by
  ``python -m pytest -q -s tests/test_capi_view.py``).
- The stage counters after each frame, equal to clvol.Renderer's counters (ms_view_table,
  light_field) over the same script, and spelled out: a camera move and a still frame draw
  (the view table stage), a light change reruns the light stage and restarts the history,
  a still view stops drawing after view.still_samples draws, an irradiance change alone
  draws nothing, an image size whose automatic block differs from the bundle's is refused.
- Three draws a frame with a fixed block; the network in launches of 257 queries (an edited
  host.network_chunk); the bundle's programs equal those a Python render builds; the view
  stage under ASan + UBSan.
"""
from __future__ import annotations

import ctypes
import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from clvol.bundle import write_bundle
from clvol.render.ms.view import MIN_SAMPLES, STILL_SAMPLES, view_jitter
from clvol.render.renderer import Renderer
from clvol.scene import load_scene

from test_capi import OK, UNSUPPORTED, _hex, _sanitizer_clean, _Server   # the C API's helpers
from test_capi import asan_serve, capi, lib   # noqa: F401  (fixtures: the built library)

ROOT = Path(__file__).resolve().parents[1]
LIGHT_RES = 32
SEED = 3
TOL = 1e-3


def _scene(width=48, height=40):
    return load_scene(ROOT / "examples" / "cloud.toml").with_overrides(
        {"volume.resolution": 32, "camera.width": width, "camera.height": height})


def _f32(v):
    a = np.asarray(v, np.float32).ravel()
    return a.ctypes.data_as(ctypes.POINTER(ctypes.c_float)), a


def _exact(v):
    """A vector as the float32 values the C API receives, as Python floats."""
    return tuple(float(x) for x in np.float32(v))


def _open(lib, bundle):
    r = ctypes.c_void_p()
    assert lib.clvol_create(str(bundle).encode(), None, None, None, ctypes.byref(r)) == OK, \
        lib.clvol_last_error(None)
    return r


class _Both:
    """One libclvol renderer and one clvol.Renderer driven through the same changes."""

    def __init__(self, lib, bundle, scene, seed=SEED, **options):
        self.lib, self.r = lib, _open(lib, bundle)
        self.py = Renderer(scene, "raymarch", ms="stochastic", light_resolution=LIGHT_RES,
                           seed=seed, **options)
        self.cam, self.light = scene.camera, scene.light

    def camera(self, origin, target, up, fov, w, h):
        args = [_f32(origin), _f32(target), _f32(up)]
        st = self.lib.clvol_set_camera(self.r, args[0][0], args[1][0], args[2][0], fov, w, h)
        if st == OK:
            self.cam = dataclasses.replace(self.cam, origin=_exact(origin), target=_exact(target),
                                           up=_exact(up), fov_y=float(np.float32(fov)),
                                           width=w, height=h)
        return st

    def set_light(self, direction, irradiance):
        d, i = _f32(direction), _f32(irradiance)
        assert self.lib.clvol_set_light(self.r, d[0], i[0]) == OK
        self.light = dataclasses.replace(self.light, direction=_exact(direction),
                                         irradiance=_exact(irradiance))

    def render(self):
        w, h = self.cam.width, self.cam.height
        out = np.zeros(w * h * 4, np.float32)
        assert self.lib.clvol_render(self.r, out.ctypes.data_as(ctypes.POINTER(ctypes.c_float))) \
            == OK, self.lib.clvol_last_error(self.r)
        res = self.py.render(camera=self.cam, light=self.light)
        return out.reshape(h, w, 4), res

    def counts(self):
        """(C: volume, light, view table, march), (Python: the same stages' counters)."""
        c = tuple(self.lib.clvol_stage_count(self.r, i) for i in range(4))
        k = self.py.counts
        return c, (k["volume"], k["light_field"], k["ms_view_table"], k["march"])

    def close(self):
        self.lib.clvol_destroy(self.r)


def _rel_rms(got, want):
    return float(np.sqrt(np.mean((got - want) ** 2)) / np.sqrt(np.mean(want ** 2)))


# ------------------------------------------------------------------------------ the RNG

def test_c_and_python_draw_the_same_jitter(capi, tmp_path):
    """libclvol's view_jitter (an internal of libclvol.a, linked into a probe program) and
    Python's view_jitter: the same float32 bits for several seeds, draws and layouts (the
    seed, draw and block counts all differ, so a swap of two of them shows), and both equal
    reference/rng.py's uniform4(seed, block, draw, 0)[:3]."""
    src = tmp_path / "jitter.c"
    src.write_text(
        "#include <stdint.h>\n#include <stdio.h>\n#include <stdlib.h>\n"
        "void clvol__view_jitter(uint32_t seed, uint32_t draw, long n, float *out);\n"
        "int main(int argc, char **argv) {\n"
        "    (void)argc;\n"
        "    uint32_t seed = (uint32_t)strtoul(argv[1], NULL, 10);\n"
        "    uint32_t draw = (uint32_t)strtoul(argv[2], NULL, 10);\n"
        "    long n = strtol(argv[3], NULL, 10);\n"
        "    float *out = malloc(sizeof(float) * 3 * (size_t)n);\n"
        "    if (!out) return 1;\n"
        "    clvol__view_jitter(seed, draw, n, out);\n"
        "    fwrite(out, sizeof(float), 3 * (size_t)n, stdout);\n"
        "    free(out);\n"
        "    return 0;\n}\n")
    exe = tmp_path / "jitter"
    r = subprocess.run(["cc", "-std=c11", "-Wall", "-Wextra", "-Werror", "-o", str(exe), str(src),
                        str(capi / "libclvol.a"), "-lOpenCL", "-lm"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    sys.path.insert(0, str(ROOT))
    from reference.rng import uniform4
    for seed, draw, bx, by in ((0, 0, 3, 2), (7, 12345, 37, 5), (4294967295, 70000, 11, 13)):
        out = subprocess.run([str(exe), str(seed), str(draw), str(bx * by)], capture_output=True,
                             check=True).stdout
        c = np.frombuffer(out, np.float32).reshape(by, bx, 3)
        py = view_jitter(seed, draw, bx, by)
        assert py.dtype == np.float32 and py.shape == (by, bx, 3)
        assert np.array_equal(c.view(np.uint32), py.view(np.uint32)), (seed, draw)
        twin = uniform4(seed, np.arange(bx * by), draw, 0)[:, :3].reshape(by, bx, 3)
        assert np.array_equal(py, twin)
        assert ((py >= 0) & (py < 1)).all()
        # another draw and another seed give other numbers (the stream moves)
        assert not np.array_equal(py, view_jitter(seed, draw + 1, bx, by))
        assert not np.array_equal(py, view_jitter(seed ^ 1, draw, bx, by))


# ---------------------------------------------------------------------------- the orbit

@pytest.fixture(scope="module")
def view_bundle(tmp_path_factory):
    b = write_bundle(_scene(), tmp_path_factory.mktemp("view") / "cloud", ms="stochastic",
                     light_resolution=LIGHT_RES, seed=SEED)
    text = (b / "manifest.txt").read_text()
    assert "raymarch.ms_source = stochastic" in text and f"view.seed = {SEED}" in text
    assert "network.active_file" not in text      # no lattice: the points are drawn
    return b


TARGET, UP, FOV = (0.02, 0.05, -0.03), (0.1, 1.0, 0.05), 35.0


def _eye(angle):
    return (1.6 * np.sin(angle), 0.3, 1.6 * np.cos(angle))


# (what happens, eye angle or None for the light change, expected C counts after the render:
# volume, light, view table, march)
ORBIT = [
    ("first frame", 0.0, (1, 1, 1, 1)),
    ("still", 0.0, (1, 1, 2, 2)),                 # draws again, accumulates
    ("move", 0.15, (1, 1, 3, 3)),                 # reprojects and draws
    ("move", 0.30, (1, 1, 4, 4)),
    ("still", 0.30, (1, 1, 5, 5)),
    ("light", 0.30, (1, 2, 6, 6)),                # light stage, history restarts
    ("still", 0.30, (1, 2, 7, 7)),
    ("move", 0.45, (1, 2, 8, 8)),
    ("move", 0.60, (1, 2, 9, 9)),
    ("still", 0.60, (1, 2, 10, 10)),
]


def test_orbit_matches_python_frame_by_frame(lib, view_bundle):
    both = _Both(lib, view_bundle, _scene())
    worst = 0.0
    try:
        for what, angle, counts in ORBIT:
            if what == "light":
                both.set_light((-0.4, 0.8, 0.45), (1.0, 1.2, 1.4))
            assert both.camera(_eye(angle), TARGET, UP, FOV, 48, 40) == OK
            got, res = both.render()
            assert res.header["raymarch.ms"] == "stochastic"
            rel = _rel_rms(got[..., :3], res.layers["total"])
            worst = max(worst, rel)
            assert rel <= TOL, (what, angle, rel)
            assert np.abs(got[..., 3] - res.layers["alpha"]).max() <= 1e-4
            assert np.isfinite(got).all()
            c, p = both.counts()
            assert c == counts and c == p, (what, c, p)
            if what == "first frame":
                first = res.layers["total"]
                share = np.sqrt(np.mean(res.layers["multiple"] ** 2) / np.mean(first ** 2))
                print(f"multiple scattering's share of the image (RMS) {share:.2f}")
                assert share > 0.5            # the view table carries most of the image
            if what == "light":               # the history restarted: MIN_SAMPLES per block
                assert res.header["raymarch.view_accumulated"] == MIN_SAMPLES
        print(f"orbit: largest relative RMS C vs Python {worst:.3g}")
    finally:
        both.close()
    # planted: the same script's first frame from a bundle with another seed is far off
    other = write_bundle(_scene(), view_bundle.parent / "seed4", ms="stochastic",
                         light_resolution=LIGHT_RES, seed=SEED + 1)
    r = _open(lib, other)
    try:
        p = [_f32(_eye(0.0)), _f32(TARGET), _f32(UP)]
        assert lib.clvol_set_camera(r, p[0][0], p[1][0], p[2][0], FOV, 48, 40) == OK
        out = np.zeros(48 * 40 * 4, np.float32)
        assert lib.clvol_render(r, out.ctypes.data_as(ctypes.POINTER(ctypes.c_float))) == OK
        other = _rel_rms(out.reshape(40, 48, 4)[..., :3], first)
        print(f"another seed: relative RMS {other:.3f} from this seed's image")
        assert other > 0.05
    finally:
        lib.clvol_destroy(r)


# ---------------------------------------------------------------------- the still view

def test_still_view_stops_drawing_as_python_does(lib, tmp_path):
    """16x12 (automatic block 1): a still view draws STILL_SAMPLES times (MIN_SAMPLES in its
    first frame, then one a frame) and then only
    marches; an irradiance change alone draws nothing; a light direction change restarts the
    history; a move draws again. C's counters equal the Python renderer's after each render,
    and the last image equals Python's."""
    scene = _scene(16, 12)
    b = write_bundle(scene, tmp_path / "small", ms="stochastic", light_resolution=LIGHT_RES,
                     seed=11)
    both = _Both(lib, b, scene, seed=11)
    try:
        assert both.camera(_eye(0.2), TARGET, UP, FOV, 16, 12) == OK
        both.render()        # the bundle's light (libclvol computed its field at create)
        assert both.counts() == ((1, 1, 1, 1),) * 2
        both.set_light((0.3, 0.9, -0.2), (1.0, 1.1, 1.2))   # float32 from here on, as C's
        # the new history's first frame draws MIN_SAMPLES, each later one 1, up to STILL_SAMPLES
        drawing = STILL_SAMPLES - MIN_SAMPLES + 1
        for k in range(drawing + 2):
            both.render()
            c, p = both.counts()
            assert c == p
            assert c[1:] == (2, 1 + min(k + 1, drawing), k + 2)
        both.set_light((0.3, 0.9, -0.2), (0.5, 0.7, 0.9))          # irradiance alone
        got, res = both.render()
        c, p = both.counts()
        assert c == p == (1, 2, drawing + 1, drawing + 4)
        assert _rel_rms(got[..., :3], res.layers["total"]) <= TOL
        both.set_light((-0.5, 0.7, 0.4), (0.5, 0.7, 0.9))          # direction: restart
        both.render()
        c, p = both.counts()
        assert c == p == (1, 3, drawing + 2, drawing + 5)
        assert both.camera(_eye(0.35), TARGET, UP, FOV, 16, 12) == OK
        got, res = both.render()
        c, p = both.counts()
        assert c == p == (1, 3, drawing + 3, drawing + 6)
        assert _rel_rms(got[..., :3], res.layers["total"]) <= TOL
        # a size whose automatic block (about 64 across) is 2, not the bundle's 1: refused
        # and nothing changes; one with the same block restarts the history
        assert both.camera(_eye(0.35), TARGET, UP, FOV, 128, 96) == UNSUPPORTED
        msg = lib.clvol_last_error(both.r).decode()
        assert "view blocks of 2 pixels" in msg and "--view-block 1" in msg
        assert lib.clvol_get_size(both.r, ctypes.byref(w := ctypes.c_int()),
                                  ctypes.byref(h := ctypes.c_int())) == OK
        assert (w.value, h.value) == (16, 12)
        assert both.camera(_eye(0.35), TARGET, UP, FOV, 20, 14) == OK
        got, res = both.render()
        c, p = both.counts()
        assert c == p and c[2] == drawing + 4
        assert res.header["raymarch.view_accumulated"] == MIN_SAMPLES
        assert _rel_rms(got[..., :3], res.layers["total"]) <= TOL
    finally:
        both.close()


def test_bundle_cli_writes_the_view_keys(tmp_path):
    """clvol bundle --ms stochastic with its options (the refusals of view and progressive:
    tests/test_c_host.py)."""
    from clvol.cli import main
    scene = ROOT / "examples" / "cloud.toml"
    out = tmp_path / "b"
    assert main(["bundle", str(scene), str(out), "--ms", "stochastic", "--width", "40",
                 "--height", "30", "--view-block", "3", "--view-samples", "2",
                 "--seed", "5"]) == 0
    keys = dict(line.split(" = ", 1) for line in (out / "manifest.txt").read_text().splitlines()
                if " = " in line and not line.startswith("#"))
    assert keys["raymarch.ms_source"] == "stochastic"
    assert (keys["view.block"], keys["view.block_auto"], keys["view.samples"],
            keys["view.seed"]) == ("3", "0", "2", "5")
    assert "viewdepth" in keys["programs"].split()
    opts = keys["program.viewdepth.options"].split()
    assert {"-DVIEW_BLOCK=3", "-DVIEW_K=1", "-DVIEW_RAYS=1", "-DVIEW_JITTER=1",
            "-DVIEW_FREE_FLIGHT=1"} <= set(opts)
    assert "-DVIEW_BLOCK=3" in keys["program.raymarch.options"].split()
    assert "-DMS_SOURCE=3" in keys["program.raymarch.options"].split()


def test_view_stage_clean_under_the_sanitizers(asan_serve, view_bundle, tmp_path):
    """The stochastic bundle through the AddressSanitizer + UBSan build (test_capi serve):
    still frames, moves (reprojection), a light change, a refused size, a size with the same
    block, a new density (with a density of zero somewhere: empty blocks) and a reopen; every
    call answers OK (or UNSUPPORTED for the size) and every image is finite; no report."""
    from clvol.volume.generators import generate
    dens = tmp_path / "d.f32"
    g = np.array(generate("cloud", seed=2, resolution=12).density, np.float32)
    g[:, :, :3] = 0.0
    np.ascontiguousarray(g, "<f4").tofile(dens)
    nz, ny, nx = g.shape

    def cam(angle, w, h):
        v = list(_eye(angle)) + list(TARGET) + list(UP) + [FOV]
        return "camera " + " ".join(_hex(x) for x in v) + f" {w} {h}"

    server = _Server(*asan_serve)
    try:
        assert server.call(f"open {view_bundle}") == "open 0 0 "
        calls = [cam(0.0, 48, 40), "render", "render", cam(0.2, 48, 40), "render",
                 "light " + " ".join(_hex(x) for x in (-0.4, 0.8, 0.45, 1.0, 1.2, 1.4)),
                 "render", cam(0.4, 40, 30), "render", f"density {nx} {ny} {nz} {dens}",
                 "render", cam(0.5, 40, 30), "render"]
        for line in calls:
            assert server.call(line) == f"{line.split()[0]} 0 0 ", line
        out = server.call(cam(0.5, 200, 160))
        assert out.startswith(f"camera {UNSUPPORTED} 0 ") and "view blocks of 3" in out, out
        assert server.call(f"open {view_bundle}") == "open 0 0 "
        assert server.call("render") == "render 0 0 "
    finally:
        _sanitizer_clean(server)


def test_network_queries_in_chunks_give_the_same_image(lib, view_bundle, tmp_path):
    """host.network_chunk (the network source's lattice_points_per_launch, 32768) cuts the
    gather + MLP into launches; a bundle edited to 257 queries a launch (~1,000 drawn points
    a frame here: several launches and a partial last one) still renders Python's frames
    (still, move)."""
    import shutil
    edited = tmp_path / "chunked"
    shutil.copytree(view_bundle, edited)
    mf = edited / "manifest.txt"
    text = mf.read_text()
    assert "host.network_chunk = 32768\n" in text
    mf.write_text(text.replace("host.network_chunk = 32768\n", "host.network_chunk = 257\n"))
    both = _Both(lib, edited, _scene())
    try:
        for angle in (0.1, 0.1, 0.25):
            assert both.camera(_eye(angle), TARGET, UP, FOV, 48, 40) == OK
            got, res = both.render()
            assert _rel_rms(got[..., :3], res.layers["total"]) <= TOL
        assert both.py.source.info["points"] > 3 * 257
    finally:
        both.close()


def test_several_draws_a_frame_and_a_fixed_block(lib, tmp_path):
    """--view-samples 3 (three draws a frame; the move's reprojection uses the first, as
    Python's) with --view-block 2, at a size whose automatic block would be 1, and then at
    another size (a fixed block takes any): Python's frames."""
    opts = dict(view_block=2, view_samples=3)
    b = write_bundle(_scene(), tmp_path / "b", ms="stochastic", light_resolution=LIGHT_RES,
                     seed=5, **opts)
    both = _Both(lib, b, _scene(), seed=5, **opts)
    try:
        for angle, w, h in ((0.1, 48, 40), (0.1, 48, 40), (0.3, 48, 40), (0.3, 130, 90)):
            assert both.camera(_eye(angle), TARGET, UP, FOV, w, h) == OK
            got, res = both.render()
            assert _rel_rms(got[..., :3], res.layers["total"]) <= TOL, (angle, w, h)
        c, p = both.counts()
        assert c == p and c[2] == 4
        # the last size restarted the history: max(3, MIN_SAMPLES) draws
        assert res.header["raymarch.view_accumulated"] == max(3, MIN_SAMPLES)
    finally:
        both.close()


def test_the_bundle_records_the_programs_python_builds(view_bundle, monkeypatch):
    """Every program (stem and -D defines) a Python --ms stochastic render builds on the same
    runtime is one the bundle lists, and nothing else: the viewdepth draw's defines
    included (the network's gather and MLP apart, as libclvol runs them; tests/test_c_host.py
    does the same for the lattice)."""
    import clvol.render.ms.network as network
    import clvol.runtime as rtm
    rt = rtm.get_runtime()
    built = set()
    orig = rtm.Runtime.program

    def recording(self, stem, defines=None, extra_options=()):
        if self is rt:
            built.add((stem, tuple(sorted(rtm._define_flags(defines)))))
        return orig(self, stem, defines, extra_options)
    monkeypatch.setattr(rtm.Runtime, "program", recording)
    monkeypatch.setattr(network, "FUSED_DEFAULT", False)
    res = Renderer(_scene(), "raymarch", ms="stochastic", light_resolution=LIGHT_RES, seed=SEED,
                   runtime=rt).render()
    assert res.header["raymarch.ms"] == "stochastic"
    lines = dict(line.split(" = ", 1) for line in
                 (view_bundle / "manifest.txt").read_text().splitlines()
                 if " = " in line and not line.startswith("#"))
    recorded = set()
    for name in lines["programs"].split():
        opts = [o for o in lines[f"program.{name}.options"].split()
                if not o.startswith("-DCLVOL_SOURCES_HASH")]
        if rt.is_pocl:
            opts += lines.get(f"program.{name}.options_pocl", "").split()
        recorded.add((Path(lines[f"program.{name}"]).stem, tuple(sorted(opts))))
    assert ("viewdepth", tuple(sorted(["-DVIEW_BLOCK=1", "-DVIEW_FREE_FLIGHT=1",
                                       "-DVIEW_JITTER=1", "-DVIEW_K=1", "-DVIEW_RAYS=1"]))) \
        in recorded
    assert built == recorded
