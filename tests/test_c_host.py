"""The C host (examples/c/, the demo of libclvol in capi/) against the Python host, its memory check, and the golden vectors.

- Images: ``clvol bundle`` of two shipped examples (cloud: grey albedo, one lobe; jade:
  chromatic albedo, two lobes) rendered by clvol-render and by ``clvol.Renderer`` with the
  same options and otherwise its defaults (what ``clvol render`` runs: the network at the
  lattice points with density within reach, domain fallback on): relative RMS difference of
  the total <= 1e-3 (the issue's bar; both hosts launch the same kernels with the same
  arguments on one device, so the difference is in practice 0). Also the scenes the renderer
  gives another source: unlit, optically thin (--ms none) and strongly backward (wrenninge).
- The -D defines a bundle records equal the ones the Python render builds with (same device).
- AddressSanitizer + LeakSanitizer + UBSan build on a tiny bundle: exit 0, no report (the ICD
  loader restricted to PoCL, ``pocl_only``: other drivers a machine has are not loaded). No
  suppression file is used: a cl_mem the host forgets to release is reported (its allocation
  is PoCL's), so suppressing PoCL would hide the host's own leaks; instead a first run fills
  PoCL's kernel cache (its compiler leaks when it builds) and the second is checked
  (docs/embedding.md). Valgrind's memcheck takes ~9 minutes here (PoCL loads LLVM).
- Golden vectors: the C host checks the MLP and the gather against ``clvol goldens`` within
  the tolerances the goldens state (those of tests/test_mlp.py and tests/test_gather.py), and
  fails on a golden output moved by 1e-3 relative (the check can fail).
"""
from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from clvol.bundle import write_bundle
from clvol.cli import main
from clvol.render.renderer import Renderer
from clvol.scene import load_scene

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "examples" / "c"
SIZE = 32          # image side in pixels
MS_RES = 8         # F_ms lattice points per side (the method's cost, not its correctness)


def _have_toolchain() -> str | None:
    cc = shutil.which(os.environ.get("CC", "cc"))
    if cc is None or shutil.which("make") is None:
        return "no C compiler or make"
    probe = subprocess.run([cc, "-E", "-x", "c", "-"], input="#include <CL/cl.h>\n",
                           capture_output=True, text=True)
    if probe.returncode != 0:
        return "no OpenCL headers (apt-get install opencl-headers ocl-icd-opencl-dev)"
    return None


def pocl_only(tmp: Path, env: dict) -> dict:
    """``env`` for a sanitizer run, with the ICD loader restricted to PoCL: an OCL_ICD_VENDORS
    folder holding PoCL's .icd file alone, so that other drivers installed on the machine (Mesa's
    rusticl leaked under ASan here) are not loaded. Unchanged where no PoCL .icd file is found."""
    vendors = Path("/etc/OpenCL/vendors")
    icds = sorted(vendors.glob("*pocl*.icd")) if vendors.is_dir() else []
    if not icds:
        return env
    only = tmp / "pocl_only_icd"
    only.mkdir(exist_ok=True)
    shutil.copy(icds[0], only / icds[0].name)
    env = dict(env, OCL_ICD_VENDORS=str(only))
    env.pop("OCL_ICD_FILENAMES", None)
    return env


def test_sanitizer_runs_load_pocl_alone(tmp_path):
    """pocl_only's folder holds PoCL's .icd file and nothing else, and OCL_ICD_FILENAMES (which
    would add drivers) is dropped; without PoCL installed the environment is left as it is."""
    env = pocl_only(tmp_path, {"OCL_ICD_FILENAMES": "/x/libother.so", "KEEP": "1"})
    if not sorted(Path("/etc/OpenCL/vendors").glob("*pocl*.icd")):
        assert env == {"OCL_ICD_FILENAMES": "/x/libother.so", "KEEP": "1"}
        return
    only = Path(env["OCL_ICD_VENDORS"])
    assert [p.name for p in only.iterdir()] and all("pocl" in p.name for p in only.iterdir())
    assert len(list(only.iterdir())) == 1
    assert "OCL_ICD_FILENAMES" not in env and env["KEEP"] == "1"


@pytest.fixture(scope="module")
def host(tmp_path_factory):
    why = _have_toolchain()
    if why:
        pytest.skip(why)
    # built in a copy (the demo and the library it links), so the checkout stays clean
    root = tmp_path_factory.mktemp("c_host")
    out = root / "c"
    shutil.copytree(SRC, out, ignore=shutil.ignore_patterns("clvol-render", "clvol-render-asan"))
    shutil.copytree(ROOT / "capi", root / "capi",
                    ignore=shutil.ignore_patterns("build", "libclvol.*"))
    r = subprocess.run(["make", "-C", str(out), "CAPI=../capi", "clvol-render",
                        "clvol-render-asan"], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "warning" not in r.stderr, r.stderr
    return out


def read_pfm(path) -> np.ndarray:
    with open(path, "rb") as f:
        assert f.readline().strip() == b"PF"
        w, h = map(int, f.readline().split())
        assert float(f.readline()) < 0          # little-endian
        data = np.frombuffer(f.read(), "<f4")
    return data.reshape(h, w, 3)[::-1]           # PFM rows run bottom to top


def run(cmd, **kw):
    return subprocess.run([str(c) for c in cmd], capture_output=True, text=True, **kw)


def small(name, overrides=None):
    return load_scene(ROOT / "examples" / name).with_overrides(
        dict(overrides or {}, **{"camera.width": SIZE, "camera.height": SIZE}))


# cloud: grey, one lobe; jade: chromatic, two lobes; smoke at albedo 0 with an environment:
# nothing lit (no light field, no network; the kernels get placeholder buffers)
UNLIT = {"medium.albedo": [0.0, 0.0, 0.0], "light.environment": [0.2, 0.3, 0.4]}
# cloud at density scale 0.5: largest optical thickness 0.4 < 0.5, the renderer's thin-medium
# shortcut (--ms none); smoke with a strongly backward phase at albedo 0.95: outside the
# network's domain, the renderer's fallback is Wrenninge octaves (clvol/render/ms/network.py)
THIN = {"medium.density_scale": 0.5}
# beyond the default model's domain (g >= -0.9) and strongly backward: the Wrenninge fallback
BACKWARD = {"medium.albedo": [0.95, 0.95, 0.95], "medium.phase": {"type": "hg", "g": -0.95}}


@pytest.mark.parametrize("name, overrides, grey, lobes, source", [
    ("cloud.toml", None, True, 1, "network"), ("jade.toml", None, False, 2, "network"),
    ("smoke.toml", UNLIT, True, 1, "none"), ("cloud.toml", THIN, True, 1, "none"),
    ("smoke.toml", BACKWARD, True, 1, "wrenninge")])
def test_c_render_matches_python(host, tmp_path, monkeypatch, name, overrides, grey, lobes,
                                 source):
    from clvol import runtime as rtm
    scene = small(name, overrides)
    assert scene.medium.is_grey == grey and len(scene.medium.phase.lobes) == lobes
    bundle = write_bundle(scene, tmp_path / "b", ms_resolution=MS_RES)
    lines = dict(l.split(" = ", 1) for l in (bundle / "manifest.txt").read_text().splitlines()
                 if " = " in l and not l.startswith("#"))
    assert lines["raymarch.ms_source"] == source
    if source == "network":
        # the lattice points with no density within reach are skipped, as in Python
        n_active = int(lines["network.active_points"])
        assert 0 < n_active < MS_RES ** 3
    # jade goes through the embedding path (a context and queue handed in)
    attach = ["--external-context"] if name == "jade.toml" else []
    r = run([host / "clvol-render", bundle, tmp_path / "c.pfm"] + attach)
    assert r.returncode == 0, r.stderr
    got = read_pfm(tmp_path / "c.pfm")

    rt = rtm.get_runtime()
    built = set()
    orig = rtm.Runtime.program

    # Patched on the class: patching the shared instance would leave, after undo, the bound
    # method as an instance attribute that hides later class patches (tests/test_plan.py's)
    def recording(self, stem, defines=None, extra_options=()):
        if self is rt:
            built.add((stem, tuple(rtm._define_flags(defines))))
        return orig(self, stem, defines, extra_options)
    monkeypatch.setattr(rtm.Runtime, "program", recording)
    # The C host launches the gather and the network as two kernels; Python's default fuses
    # them (cl/gather_mlp.cl, the same bits: tests/test_gather_mlp.py). The programs are
    # compared with Python's unfused path, the image with both.
    import clvol.render.ms.network as network
    monkeypatch.setattr(network, "FUSED_DEFAULT", False)
    res = Renderer(scene, "raymarch", ms_resolution=MS_RES, runtime=rt).render()
    want = res.layers["total"]
    monkeypatch.undo()
    fused = Renderer(scene, "raymarch", ms_resolution=MS_RES, runtime=rt).render()
    np.testing.assert_array_equal(fused.layers["total"], want)
    if scene.medium.albedo[0] > 0:
        assert res.header["raymarch.ms"] == source
    if source == "network":
        assert res.header["raymarch.network_points"] == n_active

    assert got.shape == want.shape == (SIZE, SIZE, 3)
    assert np.all(np.isfinite(got)) and want.max() > 0
    rel = np.sqrt(np.mean((got - want) ** 2)) / np.sqrt(np.mean(want ** 2))
    print(f"{name}: relative RMS difference C vs Python {rel:.3g}")
    assert rel <= 1e-3

    # the defines the bundle records are the ones Python built with
    recorded = set()
    for name_ in lines["programs"].split():
        stem = Path(lines[f"program.{name_}"]).stem
        opts = [o for o in lines[f"program.{name_}.options"].split()
                if not o.startswith("-DCLVOL_SOURCES_HASH")]
        if rt.is_pocl:
            opts += lines.get(f"program.{name_}.options_pocl", "").split()
        recorded.add((stem, tuple(sorted(opts))))
    assert {(s, tuple(sorted(o))) for s, o in built} == recorded


def test_c_render_matches_python_on_a_non_cubic_volume_and_image(host, tmp_path):
    """nx, ny, nz all different (and a box to match) and a wide image: a swap of nx and ny,
    or of width and height, in the C host's arguments shows here (every example is cubic and
    square)."""
    from clvol.volume.generators import generate
    g = generate("cloud", seed=5, resolution=24)
    dens = np.ascontiguousarray(g.density[2:22, 5:19, :])          # (nz, ny, nx) = (20, 14, 24)
    np.savez(tmp_path / "v.npz", density=dens, bbox_min=np.array([-0.6, -0.35, -0.5]),
             bbox_max=np.array([0.6, 0.35, 0.5]))
    (tmp_path / "s.toml").write_text(
        '[volume]\nfile = "v.npz"\n[medium]\npreset = "cloud"\ndensity_scale = 40.0\n'
        '[light]\ndirection = [0.5, 0.8, 0.3]\n'
        '[camera]\norigin = [0.4, 0.3, 2.0]\ntarget = [0.0, 0.0, 0.0]\nfov_y = 40.0\n'
        'width = 40\nheight = 24\n')
    scene = load_scene(tmp_path / "s.toml")
    bundle = write_bundle(scene, tmp_path / "b", ms_resolution=MS_RES)
    r = run([host / "clvol-render", bundle, tmp_path / "c.pfm"])
    assert r.returncode == 0, r.stderr
    got = read_pfm(tmp_path / "c.pfm")
    want = Renderer(scene, "raymarch", ms_resolution=MS_RES).render().layers["total"]
    assert got.shape == want.shape == (24, 40, 3) and want.max() > 0
    rel = np.sqrt(np.mean((got - want) ** 2)) / np.sqrt(np.mean(want ** 2))
    assert rel <= 1e-3, f"relative RMS difference C vs Python {rel:.3g}"


def test_c_host_takes_the_lane_width_of_its_device_or_clvol_lanes(host, tmp_path):
    """libclvol decides the lane width as clvol/runtime.py does (docs/embedding.md) and
    sizes its launches from it: $CLVOL_LANES 8 and 4 give the default's bits, on an image
    whose height is no multiple of a tile's (4 x 4, 4 x 2, 4 x 1); a width it does not know
    is an error that names it."""
    scene = small("jade.toml").with_overrides({"camera.width": 21, "camera.height": 11})
    bundle = write_bundle(scene, tmp_path / "b", ms_resolution=MS_RES)
    images = {}
    for lanes in ("", "8", "4"):
        env = dict(os.environ, CLVOL_LANES=lanes)
        r = run([host / "clvol-render", bundle, tmp_path / f"c{lanes}.pfm"], env=env)
        assert r.returncode == 0, r.stderr
        images[lanes] = read_pfm(tmp_path / f"c{lanes}.pfm")
    assert images[""].shape == (11, 21, 3) and images[""].max() > 0
    for lanes in ("8", "4"):
        np.testing.assert_array_equal(images[lanes], images[""])
    r = run([host / "clvol-render", bundle, tmp_path / "bad.pfm"],
            env=dict(os.environ, CLVOL_LANES="5"))
    assert r.returncode != 0 and "CLVOL_LANES=5" in r.stderr, r.stderr


def test_c_octaves_with_distinct_parameters_match_python(host, tmp_path):
    """The Wrenninge fallback with a, b, c all different (and 4 octaves): a swap of any two of
    the C host's octave arguments changes the image (bundles otherwise carry a = b = c)."""
    from clvol.render.ms.base import Octaves
    scene = small("smoke.toml", BACKWARD)
    oc = Octaves(4, 0.7, 0.4, 0.9)
    bundle = write_bundle(scene, tmp_path / "b", ms_resolution=MS_RES, octaves=oc)
    r = run([host / "clvol-render", bundle, tmp_path / "c.pfm"])
    assert r.returncode == 0, r.stderr
    got = read_pfm(tmp_path / "c.pfm")
    want = Renderer(scene, "raymarch", ms="wrenninge", **oc.as_options()).render().layers["total"]
    plain = Renderer(scene, "raymarch", ms="wrenninge").render().layers["total"]
    assert np.abs(want - plain).max() > 0.05 * want.max()     # the parameters matter here
    rel = np.sqrt(np.mean((got - want) ** 2)) / np.sqrt(np.mean(want ** 2))
    assert rel <= 1e-3, f"relative RMS difference C vs Python {rel:.3g}"


def tiny_bundle(tmp_path) -> Path:
    scene = load_scene(ROOT / "examples" / "jade.toml").with_overrides(
        {"volume.resolution": 12, "camera.width": 8, "camera.height": 8})
    # an 8^3 lattice: some points have no density within reach (the network skips them)
    return write_bundle(scene, tmp_path / "tiny", ms_resolution=8, light_resolution=16)


def test_asan_no_leaks_or_errors(host, tmp_path):
    """The first run (memory errors checked, leaks not) fills PoCL's kernel cache, because
    PoCL's compiler (LLVM) leaks on every build; the next ones build nothing and must report
    no error and no leak, with the host's own context and with one handed in (the caller's
    context and queue outlive the host; --external-context); the same for a bundle whose
    scene falls back to an analytic source."""
    bundle = tiny_bundle(tmp_path)
    mf = (bundle / "manifest.txt").read_text()
    assert "raymarch.ms_source = network" in mf
    assert 0 < int(mf.split("network.active_points = ")[1].split()[0]) < 8 ** 3
    # and a scene the renderer gives Wrenninge octaves (light field and march only)
    scene = load_scene(ROOT / "examples" / "smoke.toml").with_overrides(
        dict(BACKWARD, **{"volume.resolution": 12, "camera.width": 8, "camera.height": 8}))
    octaves = write_bundle(scene, tmp_path / "octaves", ms_resolution=8, light_resolution=16)
    assert "raymarch.ms_source = wrenninge" in (octaves / "manifest.txt").read_text()
    for b, leaks, extra in ((bundle, 0, []), (bundle, 1, []), (bundle, 1, ["--external-context"]),
                            (octaves, 0, []), (octaves, 1, [])):
        env = pocl_only(tmp_path, dict(os.environ, ASAN_OPTIONS=f"detect_leaks={leaks}:exitcode=23",
                                       UBSAN_OPTIONS="halt_on_error=1:print_stacktrace=1"))
        r = run([host / "clvol-render-asan", b, tmp_path / "t.pfm"] + extra, env=env)
        report = r.stdout + r.stderr
        assert r.returncode == 0, report
        for marker in ("AddressSanitizer", "LeakSanitizer", "runtime error"):
            assert marker not in report, report
        assert np.all(np.isfinite(read_pfm(tmp_path / "t.pfm")))


def test_bad_bundle_exits_nonzero_with_a_message(host, tmp_path):
    bundle = tiny_bundle(tmp_path)
    mf = bundle / "manifest.txt"
    mf.write_text("".join(l for l in mf.read_text().splitlines(True)
                          if not l.startswith("camera.width")))
    r = run([host / "clvol-render", bundle, tmp_path / "t.pfm"])
    assert r.returncode == 1
    assert "missing key camera.width" in r.stderr
    (bundle / "density.f32").write_bytes(b"\0" * 12)
    mf.write_text(mf.read_text() + "camera.width = 8\n")
    r = run([host / "clvol-render", bundle, tmp_path / "t.pfm"])
    assert r.returncode == 1 and "density.f32: 12 bytes, expected 6912" in r.stderr


@pytest.mark.parametrize("mutation, message", [
    (("manifest", "host.pad = ", "0"), "host.pad = 0: must be in [1, 1024]"),
    (("manifest", "host.pad = ", "-1"), "host.pad = -1: must be in [1, 1024]"),
    (("flip", "pinfo.i32", 0.21875), "gather.pinfo["),
])
def test_fuzz_found_bundles_are_refused(host, tmp_path, mutation, message):
    """Regression cases the bundle fuzzing below found: a zero work-size padding (division by
    zero in the host) and a bit-flipped template level (the gather kernel read outside its
    buffers and crashed)."""
    b = tiny_bundle(tmp_path)
    if mutation[0] == "manifest":
        mf = b / "manifest.txt"
        mf.write_text("".join(mutation[1] + mutation[2] + "\n" if l.startswith(mutation[1]) else l
                              for l in mf.read_text().splitlines(True)))
    else:
        f = b / mutation[1]
        data = bytearray(f.read_bytes())
        data[int(mutation[2] * len(data))] ^= 0xFF
        f.write_bytes(bytes(data))
    env = pocl_only(tmp_path, dict(os.environ, ASAN_OPTIONS="detect_leaks=0:exitcode=23"))
    r = run([host / "clvol-render-asan", b, tmp_path / "t.pfm"], env=env, timeout=120)
    assert r.returncode == 1 and message in r.stderr, r.stdout + r.stderr


def test_mutated_bundles_fail_cleanly_under_asan(host, tmp_path_factory):
    """Fuzzing (hypothesis, seeded): a bundle with one manifest value replaced (junk, huge,
    negative, NaN, empty) or a line dropped, or an array file cut short or bit-flipped, must
    give exit 0 or 1 with a message, never a signal or a sanitizer report. 40 examples,
    ~30 s; each runs the ASan build."""
    hyp = pytest.importorskip("hypothesis")
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st
    base = tiny_bundle(tmp_path_factory.mktemp("fuzzbase"))
    lines = (base / "manifest.txt").read_text().splitlines(True)
    keyed = [i for i, l in enumerate(lines) if " = " in l and not l.startswith("#")]
    arrays = sorted(p.name for p in base.iterdir() if p.suffix in (".f32", ".i32", ".u32", ".bin"))
    junk = st.sampled_from(["-1", "0", "1e30", "nan", "inf", "abc", "", "99999999999",
                            "1 2 3 4 5 6 7 8 9", "-2147483648", "0.5 nan 0.5"])
    env = pocl_only(tmp_path_factory.mktemp("icd"),
                    dict(os.environ, ASAN_OPTIONS="detect_leaks=0:exitcode=23",
                         UBSAN_OPTIONS="halt_on_error=1:print_stacktrace=1"))

    @settings(max_examples=int(os.environ.get("CLVOL_FUZZ_EXAMPLES_C", "40")), derandomize=True,
              deadline=None, suppress_health_check=list(HealthCheck))
    @given(kind=st.sampled_from(["value", "drop", "cut", "flip"]), which=st.integers(0, 10**6),
           value=junk, where=st.floats(0, 1))
    def check(kind, which, value, where):
        b = tmp_path_factory.mktemp("fuzz") / "b"
        shutil.copytree(base, b)
        new = list(lines)
        if kind in ("value", "drop"):
            i = keyed[which % len(keyed)]
            new[i] = "" if kind == "drop" else new[i].split(" = ")[0] + " = " + value + "\n"
            (b / "manifest.txt").write_text("".join(new))
        else:
            f = b / arrays[which % len(arrays)]
            data = bytearray(f.read_bytes())
            k = min(int(where * len(data)), len(data) - 1)
            if kind == "cut":
                del data[k:]
            else:
                data[k] ^= 0xFF
            f.write_bytes(bytes(data))
        r = run([host / "clvol-render-asan", b, b / "t.pfm"], env=env, timeout=120)
        report = r.stdout + r.stderr
        assert r.returncode in (0, 1), f"exit {r.returncode}: {report[-2000:]}"
        for marker in ("AddressSanitizer", "runtime error", "LeakSanitizer"):
            assert marker not in report, report[-2000:]
        if r.returncode == 1:
            assert r.stderr.strip(), "a refusal must say why"
    check()


def test_bundle_cli_refuses_bad_options(tmp_path, capsys):
    scene = ROOT / "examples" / "cloud.toml"
    assert main(["bundle", str(scene), str(tmp_path / "b"), "--ms-resolution", "64"]) == 2
    assert "ms_resolution = 64: at most 32768 lattice points" in capsys.readouterr().err
    assert main(["bundle", str(scene), str(tmp_path / "b"), "--step", "0"]) == 2
    assert "step = 0.0" in capsys.readouterr().err


def test_bundle_refuses_a_sky_lit_scene(tmp_path, capsys):
    """The sky's in-scattering and a map background are Python-only: a bundle of
    examples/cloud_sky.toml would render another image in C, so it is refused by name."""
    scene = ROOT / "examples" / "cloud_sky.toml"
    assert main(["bundle", str(scene), str(tmp_path / "b"), "--ms-resolution", "4"]) == 2
    err = capsys.readouterr().err
    assert "cloud_sky.toml" in err and "sky" in err and "C host" in err
    assert not (tmp_path / "b").exists()


@pytest.mark.parametrize("ms", ["view", "progressive"])
def test_bundle_refuses_the_view_space_sources(tmp_path, capsys, ms):
    scene = ROOT / "examples" / "cloud.toml"
    assert main(["bundle", str(scene), str(tmp_path / "b"), "--ms", ms]) == 2
    err = capsys.readouterr().err
    assert f"--ms {ms} is not implemented by the C host" in err and "embedding.md" in err
    assert not (tmp_path / "b").exists()


def test_bundle_refuses_a_source_the_c_host_lacks(tmp_path, capsys, monkeypatch):
    """A scene the renderer would render with a source the C host does not run (none does
    today: the fallbacks are none and wrenninge) is refused with exit 2, naming it."""
    import clvol.render.plan as plan
    # the plan's choice is the one the bundle reads: make it choose the view-space source
    monkeypatch.setattr(plan, "choose_source", lambda *a, **k: plan.SourceChoice("view"))
    scene = ROOT / "examples" / "cloud.toml"
    assert main(["bundle", str(scene), str(tmp_path / "b"), "--ms-resolution", "4"]) == 2
    err = capsys.readouterr().err
    assert "cloud.toml" in err and "--ms view" in err and "does not implement" in err
    assert not (tmp_path / "b").exists()


@pytest.fixture(scope="module")
def goldens(tmp_path_factory):
    gold = tmp_path_factory.mktemp("goldens") / "gold"
    assert main(["goldens", str(gold)]) == 0      # in-process: shares the phase-table cache
    return gold


def test_goldens_checked_by_the_c_host(host, goldens, tmp_path):
    r = run([host / "clvol-render", "--golden", goldens])
    assert r.returncode == 0, r.stdout + r.stderr
    checked = [l for l in r.stdout.splitlines() if l.startswith("golden ")]
    assert len(checked) == 6 and all(" ok " in l for l in checked), r.stdout

    # a golden output moved by 1e-3 relative must fail (the bound is 1e-4 relative)
    bad = shutil.copytree(goldens, tmp_path / "bad")
    y = np.load(bad / "mlp" / "y.npy")
    np.save(bad / "mlp" / "y.npy", (y * np.float32(1.001)).astype("<f4"))
    r = run([host / "clvol-render", "--golden", bad])
    assert r.returncode == 1
    assert any(l.startswith("golden mlp_y") and "FAIL" in l for l in r.stdout.splitlines())


def test_goldens_command_runs_from_the_repository_root(tmp_path):
    """As docs/embedding.md says: the installed `clvol` command from the checkout's root. Its
    sys.path starts at the script's folder, not the root, so reference/ is found beside the
    clvol package, not through the current folder."""
    import subprocess
    import sys
    from pathlib import Path
    exe = Path(sys.executable).parent / "clvol"
    if not exe.is_file():
        pytest.skip("no installed clvol command beside this Python")
    r = subprocess.run([str(exe), "goldens", str(tmp_path / "g")], cwd=ROOT, capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "g" / "mlp" / "y.npy").is_file()


def test_goldens_match_the_python_kernels(goldens):
    """The mip and majorant goldens (reference outputs) against the OpenCL kernels the
    Python host runs: the goldens describe the kernels' arguments correctly."""
    from clvol.kernels.majorant import build_majorant
    from clvol.kernels.pyramid import build_mips
    from clvol.runtime import get_runtime
    rt = get_runtime()
    data = np.load(goldens / "pyramid" / "data_in.npy")
    buf = rt.upload(data)
    build_mips(rt, buf, 8)
    np.testing.assert_array_equal(buf.read(),
                                  np.load(goldens / "pyramid" / "data_out.npy"))
    dens = np.load(goldens / "majorant" / "density.npy")
    np.testing.assert_array_equal(build_majorant(dens, 4),
                                  np.load(goldens / "majorant" / "maj.npy"))
