"""Numbers that both a host and a kernel use are written in one place (STYLE.md 16, issue 23).

Two directions, each with its place:
- a number the kernel's code fixes (a tile side, a padding, an output row's width) is a
  ``#define`` of cl/include/constants.h, which the Python host reads
  (clvol/kernels/constants.py) and the C host gets through the bundle's host.* keys;
- a number the host decides (the feature contract, the weight format, measured lane counts)
  is passed as a -D define, and the kernel stops with #error without it.

Checked here: no module of clvol/ repeats a kernel's number as a literal (under its own name
or the host's name for it); the twins in reference/ state the same numbers as the kernels; a
built program sees the values the Python host read and passed; a kernel refuses to build
without a define the host must pass (no silent default).
"""
from __future__ import annotations

import ast
import dataclasses
import re
from pathlib import Path

import numpy as np
import pyopencl as cl
import pytest

from clvol.errors import BuildError, ClvolError
from clvol.scenemodel import Light, Medium, declared
from clvol.kernels import constants as kc
from clvol.runtime import _define_flags, get_runtime, include_dir
from media import light_of, medium_of

ROOT = Path(__file__).resolve().parents[1]
CL_SOURCES = sorted((ROOT / "cl").glob("*.cl")) + sorted((ROOT / "cl" / "include").glob("*.h"))

# The host's name of a kernel's number, where the two differ (Python name -> kernel name).
KERNEL_NAME = {
    "PT_OUT": "PT_OUT_NO_EMISSION",
    "MAX_VIEW_K": "VIEW_MAX_K", "MAX_VIEW_RAYS": "VIEW_MAX_RAYS", "MAX_OCTAVES": "MS_MAX_OCTAVES",
    "RR_START": "PT_RR_START", "MAX_VERTICES": "PT_MAX_VERTICES", "T_RR": "PT_T_RR",
    "ORDER_EXACT": "PT_ORDER_EXACT", "ORDER_EXACT_LOG2": "PT_ORDER_EXACT_LOG2",
    "ORDER_SUB": "PT_ORDER_SUB", "ORDER_END_LOG2": "PT_ORDER_END_LOG2",
    "SERIES_BELOW": "H_SERIES_BELOW", "EMPTY_WEIGHT": "VIEW_EMPTY_WEIGHT",
    "MIN_LEVEL": "VIEW_MIN_LEVEL", "SQUEEZE_DIM": "SQUEEZE", "GAMMA": "MLP_GAMMA",
    "ALBEDO_EPS": "MLP_ALBEDO_EPS", "M0": "PHILOX_M0", "M1": "PHILOX_M1", "W0": "PHILOX_W0",
    "W1": "PHILOX_W1",
}

_NUMBER = r"(0[xX][0-9a-fA-F]+|[0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)[uUfF]?"
_DEFINE = re.compile(r"^[ \t]*#[ \t]*define[ \t]+([A-Z][A-Z0-9_]*)[ \t]+(-?)" + _NUMBER
                     + r"[ \t]*(?:/\*.*)?$", re.MULTILINE)


def _name(path: Path) -> str:
    return path.relative_to(ROOT).as_posix() if path.is_relative_to(ROOT) else path.name


def _number(text: str) -> float:
    return float(int(text, 16)) if text.lower().startswith("0x") else float(text)


def kernel_numbers(sources=CL_SOURCES) -> dict[str, dict[str, float]]:
    """NAME -> {file: value} of every ``#define NAME number`` in the OpenCL sources (defaults
    under #ifndef included)."""
    out: dict[str, dict[str, float]] = {}
    for path in sources:
        for m in _DEFINE.finditer(path.read_text()):
            out.setdefault(m[1], {})[_name(path)] = \
                (-1 if m[2] else 1) * _number(m[3])
    return out


def _literal(node):
    """The number a module-level value states literally: 4, -1.5, np.uint32(0x9E3779B9);
    None for anything computed."""
    if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) \
            and not isinstance(node.value, bool):
        return float(node.value)
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
        v = _literal(node.operand)
        return None if v is None else -v
    if isinstance(node, ast.Call) and len(node.args) == 1 and not node.keywords:
        return _literal(node.args[0])        # a dtype around a literal
    return None


def python_literals(folder: Path) -> dict[str, tuple[str, float]]:
    """NAME -> (file, value) of every module-level ``NAME = <number literal>`` (tuples of names
    and literals too) in the modules under ``folder``."""
    out = {}
    for path in sorted(folder.rglob("*.py")):
        if "_cl" in path.parts:
            continue
        for node in ast.parse(path.read_text(), str(path)).body:
            if not isinstance(node, (ast.Assign, ast.AnnAssign)) or node.value is None:
                continue
            for target in (node.targets if isinstance(node, ast.Assign) else [node.target]):
                pairs = [(target, node.value)]
                if isinstance(target, ast.Tuple) and isinstance(node.value, ast.Tuple):
                    pairs = list(zip(target.elts, node.value.elts))
                for t, v in pairs:
                    value = _literal(v)
                    if isinstance(t, ast.Name) and value is not None:
                        out[t.id] = (_name(path), value)
    return out


def repeated(literals: dict, numbers: dict) -> dict[str, tuple]:
    """The Python literals that name (directly or through KERNEL_NAME) a kernel's number:
    name -> (python file, value, kernel name, {kernel file: value})."""
    out = {}
    for name, (path, value) in literals.items():
        k = KERNEL_NAME.get(name, name)
        if k in numbers:
            out[name] = (path, value, k, numbers[k])
    return out


# --------------------------------------------------------------------------- the scanners

def test_the_scanners_find_defines_and_literals(tmp_path):
    (tmp_path / "k.cl").write_text("#define TILE 4\n#ifndef X\n  #define X 0x1Fu  /* c */\n"
                                   "#endif\n#define Y 1e-5f\n#define LANES ((a)(0, 1))\n"
                                   "#define Z (A + 1)\n")
    got = kernel_numbers([tmp_path / "k.cl"])
    assert {k: list(v.values()) for k, v in got.items()} == \
        {"TILE": [4.0], "X": [31.0], "Y": [1e-5]}
    (tmp_path / "m.py").write_text("import numpy as np\nTILE = 4\nA, B = 1, np.uint32(7)\n"
                                   "C = len('abc')\nD: float = -0.5\nE = True\n"
                                   "def f():\n    F = 3\n")
    lits = python_literals(tmp_path)
    assert {k: v[1] for k, v in lits.items()} == {"TILE": 4.0, "A": 1.0, "B": 7.0, "D": -0.5}
    assert set(repeated(lits, got)) == {"TILE"}


# --------------------------------------------------------------------------- one place

def test_no_clvol_module_repeats_a_kernel_number():
    """A number a kernel #defines is read from cl/include/constants.h or passed as -D, never
    written again in clvol/ (where it would silently diverge from the kernel's)."""
    twice = repeated(python_literals(ROOT / "clvol"), kernel_numbers())
    assert not twice, "\n".join(
        f"{path}: {name} = {value:g} repeats {k} of {sorted(files)}: read it with "
        f"clvol.kernels.constants.kernel_constant or pass it as a -D define"
        for name, (path, value, k, files) in sorted(twice.items()))


def test_constants_h_holds_the_only_definition_of_its_names():
    """A kernel that #defined one of the header's names again would see its own value."""
    header = include_dir() / kc.HEADER
    names = set(kc.kernel_constants())
    again = {}
    for path in CL_SOURCES:
        if path.name == header.name:
            continue
        for m in re.finditer(r"^[ \t]*#[ \t]*define[ \t]+([A-Z][A-Z0-9_]*)\b", path.read_text(),
                             re.MULTILINE):
            if m[1] in names:
                again.setdefault(m[1], []).append(_name(path))
    assert not again


def test_twins_state_the_kernels_numbers():
    """reference/ imports nothing from clvol (test_architecture.py): its copies of the kernels'
    numbers are compared here instead."""
    numbers = kernel_numbers()
    both = repeated(python_literals(ROOT / "reference"), numbers)
    # the test would pass vacuously if the scanners stopped matching: these must be found
    assert {"RR_START", "MAX_VERTICES", "T_RR", "PT_OUT", "ORDER_EXACT", "ORDER_SUB",
            "SERIES_BELOW", "SKIP_PASSES", "EMPTY_WEIGHT", "MIN_LEVEL", "M0", "W1"} <= set(both)
    differ = {name: (path, value, k, files) for name, (path, value, k, files) in both.items()
              if any(np.float32(v) != np.float32(value) for v in files.values())}
    assert not differ


def test_the_header_is_read_strictly():
    assert kc.parse_constants("/* a\n b */\n#ifndef CLVOL_CONSTANTS_H\n#define CLVOL_CONSTANTS_H\n"
                              "#define  TILE   4  /* side */\n#define N -2\n#endif\n") == \
        {"TILE": 4, "N": -2}
    for bad in ("#define TILE (2 * 2)\n", "#define TILE 4\n#define TILE 4\n", "#include \"x.h\"\n",
                "#if X\n#define TILE 4\n#endif\n", "#define TILE 4.0f\n"):
        with pytest.raises(BuildError, match="constants.h"):
            kc.parse_constants(bad)
    with pytest.raises(BuildError, match="NOPE"):
        kc.kernel_constant("NOPE")


# --------------------------------------------------------------------------- what a kernel sees

def _probe(header: str, ints: list[str], floats: list[str], defines: dict) -> tuple[list, list]:
    """Build ``#include header`` and a kernel that writes the listed macros, with the host's
    -D options for ``defines`` (and the runtime's LANES); returns the values the program saw."""
    rt = get_runtime()
    defines = dict(defines, LANES=rt.lanes)
    src = (f'#include "{header}"\n__kernel void probe(__global long *i, __global float *f) {{\n'
           + "".join(f"    i[{j}] = {n};\n" for j, n in enumerate(ints))
           + "".join(f"    f[{j}] = {n};\n" for j, n in enumerate(floats)) + "}\n")
    prog = cl.Program(rt.context, src).build(
        options=["-I", str(include_dir())] + _define_flags(defines), devices=[rt.device])
    iv = np.zeros(max(len(ints), 1), np.int64)
    fv = np.zeros(max(len(floats), 1), np.float32)
    ib = cl.Buffer(rt.context, cl.mem_flags.WRITE_ONLY, iv.nbytes)
    fb = cl.Buffer(rt.context, cl.mem_flags.WRITE_ONLY, fv.nbytes)
    prog.probe(rt.queue, (1,), None, ib, fb)
    cl.enqueue_copy(rt.queue, iv, ib)
    cl.enqueue_copy(rt.queue, fv, fb)
    rt.queue.finish()
    return iv[:len(ints)].tolist(), fv[:len(floats)].tolist()


def test_a_program_sees_the_header_values_the_python_host_uses():
    from clvol.kernels import (blocks, gather, mlp, pathtrace, raymarch, transmittance,
                               viewdepth)
    host = {  # kernel name -> the values the Python wrappers launch with
        "TILE": [raymarch.TILE], "MS_MAX_OCTAVES": [raymarch.MAX_OCTAVES],
        "SWEEP_PAD": [transmittance.SWEEP_PAD], "SWEEP_BLOCK": [transmittance.SWEEP_BLOCK],
        "BAKE_SPAN": [gather.BAKE_SPAN],
        "PT_OUT_NO_EMISSION": [pathtrace.PT_OUT, pathtrace.ROW_EM_DIRECT.start],
        "PT_OUT_EMISSION": [pathtrace.PT_OUT_EMISSION, pathtrace.ROW_EM_SCATTERED.stop],
        "PT_ORDER_EXACT": [pathtrace.ORDER_EXACT], "PT_ORDER_EXACT_LOG2": [pathtrace.ORDER_EXACT_LOG2],
        "PT_ORDER_SUB": [pathtrace.ORDER_SUB], "PT_ORDER_END_LOG2": [pathtrace.ORDER_END_LOG2],
        "VIEW_MAX_K": [viewdepth.MAX_VIEW_K, raymarch.MAX_VIEW_K],
        "VIEW_MAX_RAYS": [viewdepth.MAX_VIEW_RAYS],
        "MEDIUM_FLOATS": [blocks.MEDIUM_FLOATS],
        "MEDIUM_DENSITY_SCALE": [blocks.SLOT_DENSITY_SCALE],
        "MEDIUM_ALBEDO": [blocks.SLOT_ALBEDO], "MEDIUM_LOBE_G": [blocks.SLOT_LOBE_G],
        "MEDIUM_LOBE_W": [blocks.SLOT_LOBE_W], "LIGHT_FLOATS": [blocks.LIGHT_FLOATS],
        "LIGHT_DIRECTION": [blocks.SLOT_DIRECTION], "LIGHT_IRRADIANCE": [blocks.SLOT_IRRADIANCE],
    }
    assert set(host) == set(kc.kernel_constants())       # every header value has a user here
    names = sorted(host)
    seen, _ = _probe(kc.HEADER, names, [], {})
    assert {n: [v] * len(host[n]) for n, v in zip(names, seen)} == host


def test_mlp_core_sees_the_contract_the_host_passes():
    from clvol.kernels.mlp import kernel_defines
    from clvol.features import layout, weights
    defines = kernel_defines(weights.Architecture(), 1, True)
    ints, floats = _probe("mlp_core.h", ["CONFIG_DIM", "CFG_GMEAN", "CFG_ALBEDO", "CFG_ALPHA",
                                        "N_TYPES", "SQUEEZE", "MLP_GAMMA"],
                          ["MLP_ALBEDO_EPS"], defines)
    f = layout.CONFIG_FIELDS
    assert ints == [len(f), f.index("g_mean"), f.index("albedo"), f.index("alpha"),
                    len(layout.FEATURE_TYPES), weights.SQUEEZE_DIM, weights.GAMMA]
    assert floats == [np.float32(weights.ALBEDO_EPS)]


def test_twin_reads_the_config_where_the_kernel_does():
    from reference import mlp as ref
    from clvol.kernels.mlp import contract_defines
    d = contract_defines()
    assert (ref.G_MEAN, ref.ALBEDO, ref.ALPHA, len(ref.CONFIG_FIELDS), ref.GAMMA) == \
        (d["CFG_GMEAN"], d["CFG_ALBEDO"], d["CFG_ALPHA"], d["CONFIG_DIM"], d["MLP_GAMMA"])


# --------------------------------------------------------------------------- no silent default

def _contract_names():
    from clvol.kernels.mlp import contract_defines
    return sorted(contract_defines())


@pytest.mark.parametrize("name", _contract_names())
def test_mlp_core_refuses_to_build_without_a_contract_define(name):
    from clvol.kernels.mlp import kernel_defines
    from clvol.features import weights
    defines = kernel_defines(weights.Architecture(), 1, True)
    del defines[name]
    with pytest.raises(cl.RuntimeError, match=f"needs -D {name}"):
        _probe("mlp_core.h", ["CONFIG_DIM"], [], defines)


@pytest.mark.parametrize("stem, defines, name", [
    ("viewdepth", {"VIEW_BLOCK": 4, "VIEW_RAYS": 2}, "VIEW_K"),
    ("viewdepth", {"VIEW_K": 4, "VIEW_RAYS": 2}, "VIEW_BLOCK"),
    ("viewdepth", {"VIEW_K": 4, "VIEW_BLOCK": 4}, "VIEW_RAYS"),
    ("pathtrace", {"PHASE_LOBES": 1}, "PT_LANES"),
])
def test_kernels_refuse_to_build_without_a_host_define(stem, defines, name):
    with pytest.raises(BuildError, match=f"needs -D {name}"):
        get_runtime().program(stem, defines)


def _run_probe(src: str, n: int, *blocks, defines=None) -> np.ndarray:
    """Build ``src`` (its kernel ``probe(blocks..., __global float *o)``) on the session's
    device with the include folder and ``defines``, run one work-item, return o[0..n)."""
    rt = get_runtime()
    prog = cl.Program(rt.context, src).build(
        options=["-I", str(include_dir())] + _define_flags(defines or {}), devices=[rt.device])
    out = np.zeros(n, np.float32)
    ob = cl.Buffer(rt.context, cl.mem_flags.WRITE_ONLY, out.nbytes)
    prog.probe(rt.queue, (1,), None, *blocks, ob)
    cl.enqueue_copy(rt.queue, out, ob)
    rt.queue.finish()
    return out


def test_the_kernels_read_each_property_of_the_medium_block_where_the_host_packs_it():
    """cl/include/medium.h's accessors on a block from ``medium_block``: every property comes
    back from its own slot (distinct values everywhere, so that two swapped slots show), the
    albedo's w is 0 and the free slots stay zero."""
    from clvol.kernels.blocks import medium_block
    lobes = [(0.61, 0.52), (-0.23, 0.31), (0.07, 0.17)]
    block = medium_block(medium_of(2.75, (0.91, 0.82, 0.73), lobes))
    src = ('#include "medium.h"\n__kernel void probe(const MediumBlock m, __global float *o) {\n'
           "    o[0] = MEDIUM_DENSITY_SCALE_OF(m);\n    vstore4(MEDIUM_ALBEDO_OF(m), 1, o);\n"
           "    vstore4(MEDIUM_LOBE_G_OF(m), 2, o);\n    vstore4(MEDIUM_LOBE_W_OF(m), 3, o);\n"
           "    vstore4(m.q3, 4, o);\n}\n")
    out = _run_probe(src, 20, block)
    want = np.float32([2.75, 0, 0, 0, 0.91, 0.82, 0.73, 0, 0.61, -0.23, 0.07, 0,
                       0.52, 0.31, 0.17, 0, 0, 0, 0, 0])
    assert out[0] == want[0] and np.array_equal(out[4:], want[4:]), out


def test_the_kernels_read_the_light_block_where_the_host_packs_it():
    """cl/include/light.h's accessors on a block from ``light_block``: direction and
    irradiance from their own slots (different values), w 0, the free slots zero."""
    from clvol.kernels.blocks import light_block
    block = light_block(light_of((0.48, 0.6, 0.64), (1.5, 0.25, 3.0)))
    src = ('#include "light.h"\n__kernel void probe(const LightBlock l, __global float *o) {\n'
           "    vstore4(LIGHT_DIRECTION_OF(l), 0, o);\n    vstore4(LIGHT_IRRADIANCE_OF(l), 1, o);\n"
           "    vstore4(l.q2, 2, o);\n    vstore4(l.q3, 3, o);\n}\n")
    out = _run_probe(src, 16, block)
    np.testing.assert_array_equal(out, np.float32([0.48, 0.6, 0.64, 0, 1.5, 0.25, 3.0, 0]
                                                  + [0] * 8))


@dataclasses.dataclass(frozen=True)
class _DeclaringMedium(Medium):
    """A medium with two declared kernel properties (a number, an RGB) around one the
    kernels do not read: the packer skips that one and gives the others the next slots."""
    extra_gain: float = declared(1.0, "a test's number", lo=0.0, kernel=True)
    file_only: float = declared(2.0, "read by no kernel")
    extra_tint: tuple = declared((1.0, 1.0, 1.0), "a test's RGB", kind="rgb", kernel=True)


@dataclasses.dataclass(frozen=True)
class _DeclaringLight(Light):
    extra_gain: float = declared(1.0, "the same name as the medium's", kernel=True)


def test_declared_kernel_properties_reach_the_kernel_at_the_slots_the_host_gives_them():
    """clvol/scenemodel.py ``declared(..., kernel=True)``: ``medium_block`` and
    ``light_block`` pack the values after their fixed slots, ``block_defines`` names their
    slots, and blocks.h's ``medium_float`` / ``light_float`` read them there (distinct
    values: a slot off by one, a swapped pair or the medium's for the light's shows)."""
    from clvol.kernels.blocks import (LIGHT_FIRST_FREE, MEDIUM_FIRST_FREE, block_defines,
                                      declared_slots, light_block, medium_block)
    m = _DeclaringMedium(**vars(medium_of(2.75, (0.91, 0.82, 0.73), [(0.61, 1.0)])),
                         extra_gain=0.37, file_only=9.0, extra_tint=(0.11, 0.22, 0.33))
    li = _DeclaringLight(**vars(light_of((0.0, 1.0, 0.0), (2.0, 2.0, 2.0))), extra_gain=0.59)
    defines = block_defines(_DeclaringMedium, _DeclaringLight)
    first = MEDIUM_FIRST_FREE + sum(w for _, w in declared_slots(Medium).values())
    first_l = LIGHT_FIRST_FREE + sum(w for _, w in declared_slots(Light).values())
    assert {k: defines[k] for k in ("MEDIUM_SLOT_EXTRA_GAIN", "MEDIUM_SLOT_EXTRA_TINT",
                                    "LIGHT_SLOT_EXTRA_GAIN")} == {
        "MEDIUM_SLOT_EXTRA_GAIN": first, "MEDIUM_SLOT_EXTRA_TINT": first + 1,
        "LIGHT_SLOT_EXTRA_GAIN": first_l}
    src = ('#include "medium.h"\n#include "light.h"\n'
           "__kernel void probe(const MediumBlock m, const LightBlock l, __global float *o) {\n"
           "    o[0] = medium_float(m, MEDIUM_SLOT_EXTRA_GAIN);\n"
           "    vstore4(medium_float3(m, MEDIUM_SLOT_EXTRA_TINT), 0, o + 8);\n"
           "    for (int c = 0; c < 3; ++c) o[1 + c] = medium_float(m, MEDIUM_SLOT_EXTRA_TINT + c);\n"
           "    o[4] = MEDIUM_DENSITY_SCALE_OF(m);\n    o[5] = light_float(l, LIGHT_SLOT_EXTRA_GAIN);\n"
           "    o[6] = LIGHT_IRRADIANCE_OF(l).x;\n    o[7] = -1.0f;\n}\n")
    out = _run_probe(src, 12, medium_block(m), light_block(li), defines=defines)
    np.testing.assert_array_equal(out, np.float32([0.37, 0.11, 0.22, 0.33, 2.75, 0.59, 2.0, -1,
                                                   0.11, 0.22, 0.33, 0]))


def test_a_block_refuses_more_declared_properties_than_its_free_slots():
    from clvol.kernels.blocks import declared_slots

    @dataclasses.dataclass(frozen=True)
    class Crowded(_DeclaringMedium):
        more_tint: tuple = declared((1.0, 1.0, 1.0), "one RGB too many", kind="rgb", kernel=True)
    with pytest.raises(ClvolError, match=r"Crowded's declared kernel properties need (19|2\d) "
                                         r"floats; its block .* holds 16"):
        declared_slots(Crowded)
