"""Every kernel program builds without a compiler warning (docs/opencl.md, "Building programs").

A warning was invisible on a warm kernel cache (PoCL's and pyopencl's caches serve the binary
without compiling, so the build log is empty) and showed on every first render of a fresh
machine, on whatever CPU it has. Two checks, over every define set the host code builds:

- on the chosen OpenCL device (PoCL here), with a define that no cache has seen, so each
  program really is compiled and its log is the compiler's;
- with clang-15 (the compiler of Debian's PoCL 3.1) for x86-64 CPUs without AVX-512 and
  without AVX, at the lane width the host chooses for them (clvol/runtime.py lanes_for: 8 and
  4): PoCL compiles for the host CPU, and with 16 lanes on such a CPU every 16- or 8-wide
  vector argument and return gave "AVX vector argument ... changes the ABI" (-Wpsabi), 48 to
  424 a program, none of which the AVX-512 development machine shows. No warning is turned
  off.

A third test holds the variant list to the sources: every macro a kernel tests with #if that
the sources do not define themselves is set by at least one variant.
"""
from __future__ import annotations

import re
import shutil
import subprocess
import uuid
import warnings
from pathlib import Path

import pytest

from clvol.kernels import gather as kg
from clvol.kernels import mlp as km
from clvol.kernels import raymarch as kr
from clvol.kernels.pathtrace import ORDER_BINS, QUERY_LANES, RENDER_LANES
from clvol.kernels.transmittance import sweep_width_define
from clvol.kernels.phase import phase_defines
from clvol.features import layout
from clvol.render.ms.network import load_network_weights, shipped_weights
from clvol.runtime import _define_flags, cl_source_dir, driver_defines_for, get_runtime, include_dir, lanes_for

LOBES = {"iso": [], "hg": [(0.857, 1.0)], "mhg2": [(0.8, 0.7), (-0.3, 0.3)],
         "mhg3": [(0.8, 0.5), (0.3, 0.3), (-0.3, 0.2)]}


def _gather(lobes, render: bool, shuffle: bool, res: int = 64) -> dict:
    d = dict(phase_defines(lobes), NP=layout.N_POINTS, COARSE_LEVEL=kg.coarse_level(res))
    if render:
        d["GATHER_RENDER"] = 1
    if shuffle:
        d["GATHER_SHUFFLE"] = 1
    return d


def _mlp(channels: int, decode: bool, pocl: bool) -> dict:
    arch = load_network_weights(shipped_weights()).arch
    d = km.kernel_defines(arch, channels, decode)
    if pocl:                      # MlpKernel.defines on PoCL
        d.update(MLP_TRANSPOSE16=1, MLP_PREFETCH=1)
    return d


def variants() -> list[tuple[str, str, dict]]:
    """(id, stem, defines): the define sets of clvol/kernels/*.py, clvol/bundle.py and
    clvol/goldens.py, each switch on and off at least once."""
    v = [(s, s, {}) for s in ("grid", "majorant", "pyramid", "rng")]
    v += [(f"phase-{k}", "phase", phase_defines(lb)) for k, lb in LOBES.items()]
    v += [("transmittance", "transmittance", {}),
          ("transmittance-wL", "transmittance", {"SWEEP_WIDTH": sweep_width_define(16)}),
          ("transmittance-nosync", "transmittance",
           {"SWEEP_WIDTH": sweep_width_define(16), "SWEEP_NO_SYNC": 1})]
    for source in kr.MS_SOURCE_DEFINES:
        for k, lb in (("iso", LOBES["iso"]), ("mhg3", LOBES["mhg3"])):
            for ch in ((1, 3) if source in ("lattice", "view") else (1,)):
                d = kr.raymarch_defines(lb, lit=True, source=source,
                                        octaves=4 if source == "wrenninge" else 1,
                                        channels=ch, skip_empty=True, view_k=4, view_block=4)
                v.append((f"raymarch-{source}-{k}-c{ch}", "raymarch", dict(d, LIGHT_TAU=0)))
    base = kr.raymarch_defines(LOBES["hg"], lit=True, source="lattice", octaves=1, channels=3,
                               skip_empty=True)
    v += [("raymarch-unlit-tau", "raymarch",
           dict(base, LIT=0, SKIP_EMPTY=0, LIGHT_TAU=1, RAYMARCH_STATS=1)),
          ("raymarch-env1-bg-em1", "raymarch",
           dict(base, LIGHT_TAU=0, ENV=1, ENV_CHANNELS=1, BG_IMAGE=1, EMISSION=1,
                EMISSION_CHANNELS=1, EMISSION_BOX=0)),
          ("raymarch-env3-em3-box", "raymarch",
           dict(base, LIGHT_TAU=0, ENV=1, ENV_CHANNELS=3, EMISSION=1, EMISSION_CHANNELS=3,
                EMISSION_BOX=1))]
    # cl/pathtrace.cl: kernels/pathtrace.py specialisation (general kernel, grey, env, map,
    # no sun, single only, emission), the query, order and environment-test programs
    pt = [("general", {"PHASE_LOBES": 3, "PT_ENV": 1}),
          ("general-map", {"PHASE_LOBES": 3, "PT_ENVMAP": 1}),
          ("grey-iso", dict(phase_defines([]), PT_GREY=1)),
          ("hg-env-nosun", dict(phase_defines(LOBES["hg"]), PT_ENV=1, PT_NO_SUN=1)),
          ("mhg2-single", dict(phase_defines(LOBES["mhg2"]), PT_GREY=1, PT_SINGLE_ONLY=1)),
          ("em1", dict(phase_defines([]), PT_EMISSION=1, PT_EMISSION_CHANNELS=1)),
          ("em3-map", dict(phase_defines(LOBES["hg"]), PT_ENVMAP=1, PT_EMISSION=1,
                           PT_EMISSION_CHANNELS=3)),
          ("stats-bias", dict(phase_defines([]), PT_STATS=1, PT_TEST_BIAS=1.01))]
    for k, d in pt:
        v.append((f"pathtrace-{k}", "pathtrace", dict(d, PT_LANES=RENDER_LANES)))
    v += [("pathtrace-query", "pathtrace", dict(pt[2][1], PT_LANES=QUERY_LANES)),
          ("pathtrace-orders", "pathtrace",
           dict(pt[2][1], PT_LANES=QUERY_LANES, PT_ORDER_BINS=ORDER_BINS))]
    v += [("gather-plain", "gather", {})]
    for k in ("iso", "hg", "mhg3"):
        for render in (False, True):
            for shuffle in (False, True):
                v.append((f"gather-{k}-r{int(render)}-s{int(shuffle)}", "gather",
                          _gather(LOBES[k], render, shuffle)))
    for ch in (1, 3):
        for decode in (False, True):
            for pocl in (False, True):
                v.append((f"mlp-c{ch}-d{int(decode)}-p{int(pocl)}", "mlp",
                          _mlp(ch, decode, pocl)))
    for k in ("iso", "mhg3"):
        for ch in (1, 3):
            for pocl in (False, True):
                v.append((f"gather_mlp-{k}-c{ch}-p{int(pocl)}", "gather_mlp",
                          dict(_gather(LOBES[k], True, pocl), **_mlp(ch, True, pocl))))
    # the dense layers' array form alone, and rusticl's whole rule (clvol/runtime.py
    # DRIVER_RULES: the array form with a * b + c)
    rusticl = driver_defines_for("rusticl")
    v.append(("mlp-dense-array", "mlp", dict(_mlp(3, True, False), MLP_DENSE_ARRAY=1)))
    v.append(("mlp-rusticl", "mlp", dict(_mlp(3, True, False), **rusticl)))
    v.append(("gather_mlp-rusticl", "gather_mlp",
              dict(_gather(LOBES["mhg3"], True, False), **_mlp(1, True, False), **rusticl)))
    for k, d in (("k4", {"VIEW_K": 4, "VIEW_BLOCK": 4, "VIEW_RAYS": 2}),
                 ("jitter", {"VIEW_K": 2, "VIEW_BLOCK": 8, "VIEW_RAYS": 1, "VIEW_JITTER": 1}),
                 ("flight", {"VIEW_K": 1, "VIEW_BLOCK": 4, "VIEW_RAYS": 1, "VIEW_JITTER": 1,
                             "VIEW_FREE_FLIGHT": 1})):
        v.append((f"viewdepth-{k}", "viewdepth", d))
    return v


VARIANTS = variants()


def _params():
    """The variants; the one with the most defines of each program is also run on Oclgrind
    (tests/test_oclgrind.py: ~6 s for the twelve, all of them took 63 s)."""
    richest = {}
    for vid, stem, d in VARIANTS:
        if len(d) > len(richest.get(stem, (None, {}))[1]):
            richest[stem] = (vid, d)
    richest = {v for v, _ in richest.values()} | {"grid", "majorant", "pyramid", "rng"}
    return [pytest.param(vid, stem, d, id=vid,
                         marks=[pytest.mark.oclgrind] if vid in richest else [])
            for vid, stem, d in VARIANTS]
WARNING = re.compile(r"warning|warnings? generated", re.IGNORECASE)


@pytest.fixture(scope="module")
def nonce():
    """A define no kernel cache has seen: each build below is a real compile."""
    return f"-DCLVOL_WARNING_CHECK=0x{uuid.uuid4().hex[:12]}"


@pytest.mark.parametrize("vid,stem,defines", _params())
def test_program_builds_without_warnings_on_the_device(vid, stem, defines, nonce):
    import pyopencl as cl
    rt = get_runtime()
    defines = {k: v for k, v in _at_width(defines, rt.lanes).items() if k != "LANES"}
    prog = rt.program(stem, defines, extra_options=(nonce,))
    log = prog._program.get_build_info(rt.device, cl.program_build_info.LOG) or ""
    assert not WARNING.search(log), f"{stem}.cl {defines} on {rt.entry.label}:\n{log[:3000]}"


CLANG = shutil.which("clang-15")


def _clang_resource_dir() -> Path | None:
    if CLANG is None:
        return None
    out = subprocess.run([CLANG, "-print-resource-dir"], capture_output=True, text=True)
    return Path(out.stdout.strip()) if out.returncode == 0 else None


# -target-cpu -> the CPU's native float vector width as PoCL reports it (x86-64-v3: AVX2,
# 256-bit; x86-64: SSE2, 128-bit), from which the host picks the lane width.
NATIVE_FLOATS = {"x86-64-v3": 8, "x86-64": 4}


def pt_lanes(want: int, lanes: int) -> int:
    """PT_LANES as clvol/kernels/pathtrace.py path_lanes sets it at width ``lanes``."""
    return min(want, lanes)


def _clang(cpu: str, path: Path, defines: dict) -> subprocess.CompletedProcess:
    """clang's front end as PoCL 3.1 runs it (OpenCL C 3.0, inline defined away, the host
    triple) for ``cpu``; -emit-llvm without optimisation is where these diagnostics come
    from, so no code generation is needed. ``defines`` hold LANES (the runtime adds it)."""
    res = _clang_resource_dir()
    cmd = [CLANG, "-cc1", "-triple", "x86_64-pc-linux-gnu", "-target-cpu", cpu,
           "-cl-std=CL3.0", "-internal-isystem", str(res / "include"),
           "-finclude-default-header", "-fdeclare-opencl-builtins",
           "-cl-ext=+cl_khr_fp64,+__opencl_c_fp64,+__opencl_c_int64",
           "-emit-llvm", "-o", "/dev/null", "-I", str(include_dir()), "-Dinline=",
           *_define_flags(defines), str(path)]
    return subprocess.run(cmd, capture_output=True, text=True)


def _at_width(defines: dict, lanes: int) -> dict:
    """A variant's defines as the runtime builds them at lane width ``lanes``."""
    d = dict(defines, LANES=lanes)
    if "PT_LANES" in d:
        d["PT_LANES"] = pt_lanes(d["PT_LANES"], lanes)
    return d


# x86-64-v3 is AVX2 without AVX-512 (16-wide vectors change the ABI), x86-64 plain SSE2
# (8-wide ones too): each at the width the host picks for it.
@pytest.mark.skipif(CLANG is None, reason="clang-15 (Debian's PoCL compiler) not installed")
@pytest.mark.parametrize("cpu", ["x86-64-v3", "x86-64"])
def test_every_program_compiles_without_warnings_for_cpus_without_avx512(cpu):
    lanes = lanes_for("cpu", NATIVE_FLOATS[cpu])
    assert lanes == NATIVE_FLOATS[cpu]
    bad = []
    for vid, stem, defines in VARIANTS:
        p = _clang(cpu, cl_source_dir() / f"{stem}.cl", _at_width(defines, lanes))
        assert p.returncode == 0, f"{vid}: clang failed:\n{p.stderr[:3000]}"
        if WARNING.search(p.stderr):
            first = next(l for l in p.stderr.splitlines() if "warning" in l)
            bad.append(f"{vid}: {p.stderr.count('warning:')} warnings, first: {first}")
    assert not bad, f"-target-cpu {cpu}:\n" + "\n".join(bad)


# A call with a vector of the lanes.h width, and an ordinary mistake.
PLANTED = """#include "lanes.h"
vL twice(vL v) { return v * 2.0f; }
__kernel void k(__global float *o) {
    int i = 1;
    float *p = &i;                                     /* incompatible pointer types */
    vstoreL(twice(vloadL(0, o)) + *p, 0, o);
}
"""


@pytest.mark.oclgrind
def test_the_checks_see_a_planted_warning_and_no_warning_is_off(tmp_path, nonce):
    """The device's log shows the ordinary mistake. clang for an AVX2 CPU shows the ABI
    warning of a 16-wide call (the checks can see it: nothing turns it off), and at the width
    the host picks for that CPU only the ordinary mistake."""
    import pyopencl as cl
    src = tmp_path / "planted.cl"
    src.write_text(PLANTED)
    rt = get_runtime()
    prg = cl.Program(rt.context, PLANTED)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", cl.CompilerWarning)      # the log is read below
        prg.build(options=["-I", str(include_dir()), f"-DLANES={rt.lanes}", nonce],
                  devices=[rt.device])
    log = prg.get_build_info(rt.device, cl.program_build_info.LOG) or ""
    assert "incompatible pointer" in log and WARNING.search(log), log
    if CLANG is not None:
        for cpu in NATIVE_FLOATS:
            wide = _clang(cpu, src, {"LANES": 16}).stderr
            assert "changes the ABI" in wide and "incompatible pointer" in wide, wide
            p = _clang(cpu, src, {"LANES": lanes_for("cpu", NATIVE_FLOATS[cpu])})
            assert p.stderr.count("warning:") == 1 and "incompatible pointer" in p.stderr, \
                p.stderr


def _sources(stem: str) -> list[Path]:
    """The program's file and the headers it includes, transitively."""
    seen, todo = [], [cl_source_dir() / f"{stem}.cl"]
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.append(p)
        for name in re.findall(r'#\s*include\s+"([^"]+)"', p.read_text()):
            todo.append(include_dir() / name)
    return seen


def test_variants_set_every_macro_the_sources_test():
    stems = sorted({s for _, s, _ in VARIANTS})
    assert stems == sorted(p.stem for p in cl_source_dir().glob("*.cl"))   # every program
    missing = []
    for stem in stems:
        text = "\n".join(p.read_text() for p in _sources(stem))
        text = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)
        tested = set()
        for cond in re.findall(r"^\s*#\s*(?:if|ifdef|ifndef|elif)\b(.*)$", text, re.M):
            tested |= set(re.findall(r"\b[A-Z_][A-Z0-9_]+\b", cond))
        own = set(re.findall(r"^\s*#\s*define\s+([A-Z_][A-Z0-9_]*)", text, re.M))
        given = set().union(*(d for _, s, d in VARIANTS if s == stem)) | {"LANES"}  # runtime
        missing += [f"{stem}: {m}" for m in sorted(tested - own - given)]
    assert not missing, "macros no variant sets (add a variant): " + ", ".join(missing)


def _log(prog) -> str:
    import pyopencl as cl
    return prog._program.get_build_info(prog.runtime.device, cl.program_build_info.LOG) or ""


def test_compiler_output_is_shown_only_on_request(monkeypatch, nonce):
    """A build log that is not empty (here a macro redefined on the command line, a warning
    on any compiler) is pyopencl's CompilerWarning only with PYOPENCL_COMPILER_OUTPUT=1, which
    --verbose sets; before, every first render printed it, --quiet or not."""
    import pyopencl as cl
    rt = get_runtime()
    monkeypatch.delenv("PYOPENCL_COMPILER_OUTPUT", raising=False)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        prog = rt.program("grid", extra_options=("-DCLVOL_PI=3.0f", nonce + "1"))
    assert "redefined" in _log(prog)                  # the compiler did warn
    assert not [w for w in seen if issubclass(w.category, cl.CompilerWarning)]
    monkeypatch.setenv("PYOPENCL_COMPILER_OUTPUT", "1")
    with pytest.warns(cl.CompilerWarning, match="redefined"):
        rt.program("grid", extra_options=("-DCLVOL_PI=3.0f", nonce + "2"))


def test_verbose_turns_compiler_output_on(monkeypatch, capsys):
    from clvol.cli import main
    from clvol.runtime import compiler_output_shown
    monkeypatch.setenv("PYOPENCL_COMPILER_OUTPUT", "0")     # restored after the test
    assert main(["info"]) == 0 and not compiler_output_shown()
    assert main(["info", "--verbose"]) == 0 and compiler_output_shown()
    capsys.readouterr()
