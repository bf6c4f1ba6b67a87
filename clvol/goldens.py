"""``clvol goldens DIR``: golden vectors for porting the kernels (C, CUDA, Metal, Vulkan).

For each kernel, DIR/<kernel>/ holds small adversarial inputs and the outputs of the NumPy
reference (reference/*.py, written independently of the kernels) as plain ``.npy`` files
(float32 ``<f4`` or int32 ``<i4``, C order), ``args.json`` (the kernel's arguments in order:
each a file, a scalar or a float4, with its meaning; the ``-D`` defines; the work size; the
tolerances and why) and ``manifest.txt``, the same facts as ``key = value`` lines for hosts that
do not parse JSON (examples/c/ reads it). DIR/cl/ is a copy of the kernel sources they build.

Tolerances are the ones the Python kernel tests hold the kernels to against the same twins
(tests/test_mlp.py, tests/test_gather.py, tests/test_pyramid.py, tests/test_transmittance.py),
each stated as (rtol, atol) with atol absolute unless the entry says otherwise.

Needs the reference package (``reference/`` of a source checkout): run from the repository root.
"""
from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .bundle import _fmt, program_options
from .errors import ClvolError


def _reference():
    # A source checkout keeps reference/ beside the clvol package: make it importable when
    # clvol runs as an installed command (sys.path[0] is then the script's folder).
    import sys
    root = Path(__file__).resolve().parents[1]
    if (root / "reference" / "__init__.py").is_file() and str(root) not in sys.path:
        sys.path.insert(0, str(root))
    try:
        import reference.gather as rgather
        import reference.majorant as rmajorant
        import reference.mlp as rmlp
        import reference.pyramid as rpyramid
        import reference.transmittance as rtrans
    except ImportError:
        raise ClvolError(f"clvol goldens needs the NumPy reference (reference/ of a source "
                         f"checkout, looked for in {root}): install clvol from a checkout "
                         f"(pip install -e .)") from None
    return rgather, rmajorant, rmlp, rpyramid, rtrans


class _Kernel:
    """One kernel's folder: arrays, arguments, tolerances."""

    def __init__(self, root: Path, name: str, source: str, kernel: str, doc: str,
                 work_size: str = ""):
        self.dir = root / name
        self.dir.mkdir(parents=True, exist_ok=True)
        self.info = {"kernel": kernel, "source": f"cl/{source}.cl", "doc": doc, "defines": {},
                     "defines_pocl": {}, "options": "", "args": [], "outputs": {},
                     "work_size": work_size, "tolerance": {}}
        self.kv = {"kernel": kernel}
        self.stem = source

    def array(self, name: str, a, dtype, doc: str, output: bool = False) -> None:
        a = np.ascontiguousarray(a, dtype=np.dtype(dtype).newbyteorder("<"))
        np.save(self.dir / f"{name}.npy", a)
        entry = {"name": name, "file": f"{name}.npy", "dtype": a.dtype.str, "shape": list(a.shape),
                 "doc": doc}
        if output:
            self.info["outputs"][name] = entry
        else:
            self.info["args"].append(entry)

    def scalar(self, name: str, value, ctype: str, doc: str) -> None:
        v = [float(x) for x in value] if ctype == "float4" else value
        self.info["args"].append({"name": name, "type": ctype, "value": v, "doc": doc})
        self.kv[f"arg.{name}"] = v

    def program(self, defines: dict, pocl: dict | None = None, name: str | None = None) -> None:
        from .runtime import _define_flags
        name = name or self.info["kernel"]
        opts = program_options(self.stem, defines)
        self.info.setdefault("programs", {})[name] = {
            "options": opts, "options_pocl": " ".join(_define_flags(pocl or {}))}
        self.kv[f"program.{name}"] = f"../cl/{self.stem}.cl"
        self.kv[f"program.{name}.options"] = opts.split()
        if pocl:
            self.kv[f"program.{name}.options_pocl"] = _define_flags(pocl)

    def tolerance(self, what: str, rtol: float, atol: float, why: str) -> None:
        self.info["tolerance"][what] = {"rtol": rtol, "atol": atol, "why": why}
        self.kv[f"tolerance.{what}"] = [rtol, atol]

    def write(self) -> None:
        self.kv["include_dir"] = "../cl/include"
        (self.dir / "args.json").write_text(json.dumps(self.info, indent=1) + "\n")
        lines = ["# key = value form of args.json (docs/embedding.md)"]
        lines += [f"{k} = {_fmt(v)}" for k, v in self.kv.items()]
        (self.dir / "manifest.txt").write_text("\n".join(lines) + "\n")


def _density(rng, shape, high: float, empty=None):
    """float32 density uniform in [0, high) with zeros at ``empty`` (an index: an empty slab,
    so the goldens cover T = 1 and entry points on an edge)."""
    d = rng.uniform(0, high, shape).astype(np.float32)
    if empty is not None:
        d[empty] = 0.0
    return d


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


class _Levels:
    """A pyramid stand-in for the reference gather (the attributes it reads)."""

    def __init__(self, level0, cube_min, cube_size, rpyramid):
        levels = rpyramid.mip_chain(level0)
        self.base_resolution = level0.shape[0]
        self.n_levels = len(levels)
        self.cube_min = np.asarray(cube_min, np.float64)
        self.cube_size = float(cube_size)
        sizes = [lv.size for lv in levels]
        self.level_offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self.data = np.concatenate([lv.ravel() for lv in levels]).astype(np.float32)


def write_goldens(out_dir) -> Path:
    """Write the golden folder of every kernel (module docstring) under ``out_dir``, and a copy
    of the kernel sources. All inputs come from one seeded generator, drawn kernel by kernel
    in this order, so every run writes the same files."""
    rgather, rmajorant, rmlp, rpyramid, rtrans = _reference()
    root = Path(out_dir)
    _copy_sources(root)
    rng = np.random.default_rng(20261123)
    _mlp_golden(root, rng, rmlp)
    case = _GatherCase.draw(rng, rgather, rpyramid)
    _gather_golden(root, case, rgather)
    _bake_golden(root, case)
    _pyramid_golden(root, rng, rpyramid)
    _majorant_golden(root, rng, rmajorant)
    _transmittance_golden(root, rng, rtrans)
    return root


def _copy_sources(root: Path) -> None:
    """DIR/cl/: the kernel sources and headers the goldens' programs build."""
    from .runtime import cl_source_dir, include_dir
    (root / "cl" / "include").mkdir(parents=True, exist_ok=True)
    for p in cl_source_dir().glob("*.cl"):
        shutil.copyfile(p, root / "cl" / p.name)
    for p in include_dir().glob("*.h"):
        shutil.copyfile(p, root / "cl" / "include" / p.name)


def _mlp_golden(root: Path, rng, rmlp) -> None:
    """The shipped network on 37 queries (two full work-items and a tail of 5)."""
    from .kernels import mlp as km
    from .features import layout
    from .features.weights import load_weights
    from .render.ms.network import shipped_weights
    w = load_weights(shipped_weights())
    arch = w.arch
    k = _Kernel(root, "mlp", "mlp", "mlp_forward",
                "the network's fused forward pass; y = log(F / albedo^4 + 1), F decoded",
                "ceil(n / LANES) work-items (LANES: the device's lane width, docs/opencl.md); "
                "local size 1 on CPU devices "
                f"(private arrays), else any")
    lobes = ((0.6, 0.8), (-0.2, 0.2))
    f, c = rmlp.random_inputs(37, rng, arch=arch, lobes=lobes)
    c[3, layout.CONFIG_FIELDS.index("alpha")] = 0.0           # looking into the light
    c[4, layout.CONFIG_FIELDS.index("alpha")] = np.pi         # light behind the camera
    alb = np.array([0.0, 0.6, 0.95], np.float32)              # an albedo-0 channel gives F = 0
    k.array("features", f, np.float32, "[n][3][N_POINTS] density, transmittance, phase features")
    k.array("config", c, np.float32, "[n][9] g0 g1 g2 w0 w1 w2 g_mean albedo alpha (radians)")
    k.array("params", km.pack_params(w), np.float32,
            "packed weights (clvol/kernels/mlp.py pack_params; docs/embedding.md)")
    k.array("channel_albedo", alb, np.float32, "float4 argument (w = 0) for MLP_CHANNELS = 3")
    k.scalar("n", len(f), "int", "number of queries")
    y = rmlp.forward(w.params, arch, f, c)
    k.array("y", rmlp.decode(y, c[:, layout.CONFIG_FIELDS.index("albedo")]), np.float32,
            "[n] output of program mlp_y (1 channel, config's albedo, decoded F: the grey "
            "medium's program)", output=True)
    k.array("F", rmlp.radiance(w.params, arch, f, c, alb), np.float32,
            "[n][3] output of program mlp_F (3 channels, channel_albedo, decoded)", output=True)
    pocl = km.POCL_DEFINES
    k.program(km.kernel_defines(arch, 1, True), pocl, "mlp_y")
    k.program(km.kernel_defines(arch, 3, True), pocl, "mlp_F")
    k.tolerance("mlp_y", 1e-4, 1e-6, "atol x max|F|: float32 vs the float64 twin over ~86k "
                "multiply-adds, amplified by the decode exp(y) - 1 (tests/test_mlp.py)")
    k.tolerance("mlp_F", 1e-4, 1e-6, "atol x max|F|: the decode exp(y) - 1 amplifies y's error "
                "(tests/test_mlp.py)")
    k.write()


@dataclass
class _GatherCase:
    """The inputs the gather and bake goldens share: a 64^3 pyramid (the shipped weights'
    base, so the programs are the ones a bundle builds) with an empty slab, any T field, level
    weights and bias, the medium, and 29 queries (some outside the cube, two with omega along
    +-l: the frame's fallback), with the twin's baked grid."""
    base: int
    pyr: _Levels
    graded: np.ndarray
    lw: np.ndarray
    bias: np.float32
    scale: float
    light: np.ndarray
    lobes: tuple
    pts: np.ndarray
    om: np.ndarray
    baked: np.ndarray

    @classmethod
    def draw(cls, rng, rgather, rpyramid) -> "_GatherCase":
        from .kernels import gather as kg
        base = 64
        d0 = _density(rng, (base, base, base), 1.5, np.s_[:, :, :24])
        pyr = _Levels(d0, np.array([-0.5, -0.4, -0.6]), 1.2, rpyramid)
        graded = rng.uniform(0.05, 1.0, pyr.data.size).astype(np.float32)  # any T field will do
        lw = rng.uniform(-0.3, 0.6, pyr.n_levels).astype(np.float32)
        bias, scale = np.float32(0.05), 7.0
        light = _unit([0.3, 0.8, -0.5])
        n = 29
        pts = rng.uniform(-0.8, 0.8, (n, 3)).astype(np.float32)          # some outside the cube
        om = _unit(rng.normal(size=(n, 3)))
        om[0] = -light                                # omega antiparallel to l: frame fallback
        om[1] = light
        baked_levels = rgather.baked_grid(pyr, graded, scale, lw.astype(np.float64), float(bias))
        baked = np.concatenate([np.stack([t, cc], -1).ravel() for t, cc in baked_levels]
                               + [np.zeros(kg.BAKE_PAD)]).astype(np.float32)
        return cls(base, pyr, graded, lw, bias, scale, light, ((0.6, 0.8), (-0.2, 0.2)), pts,
                   om.astype(np.float32), baked)


def _gather_golden(root: Path, case: _GatherCase, rgather) -> None:
    """The gather in render mode (the C host's), argument by argument."""
    from .kernels import gather as kg
    from .kernels.phase import lobe_vectors, phase_defines
    from .features import layout
    from .runtime import DEFAULT_PAD
    pyr, n = case.pyr, len(case.pts)
    want = rgather.gather(pyr, case.graded, case.pts, case.om, case.light, case.lobes,
                          case.scale, mode="render", level_weights=case.lw.astype(np.float64),
                          bias=float(case.bias))
    tpl, pinfo, hl = kg.template_arrays(case.base)
    ptab = kg._phase_table_padded(case.lobes)
    g4, w4 = lobe_vectors(case.lobes)
    k = _Kernel(root, "gather", "gather", "gather",
                "template gather, render mode: features of N queries from the baked grid",
                f"N work-items (padded to a multiple of {DEFAULT_PAD}; guarded)")
    k.array("dens", pyr.data, np.float32, "pyramid levels concatenated (read for t_enter)")
    k.info["args"].append({"name": "tlev", "same_as": "dens", "doc": "train mode only"})
    k.array("baked", case.baked, np.float32, "float2 (tau, C) per voxel of every level + BAKE_PAD zeros")
    k.array("loff", pyr.level_offsets, np.int32, "level offsets (elements)")
    k.scalar("L", pyr.n_levels, "int", "levels")
    k.scalar("n0", case.base, "int", "base resolution")
    k.scalar("cmin", list(pyr.cube_min), "float4", "cube corner (world)")
    k.scalar("csize", pyr.cube_size, "float", "cube edge (world)")
    k.info["args"].append({"name": "taufac", "type": "buffer",
                           "doc": "train mode only (any 4 bytes)"})
    k.array("tpl", tpl, np.float32, "template points [3][NPAD], x, y, z rows")
    k.array("pinfo", pinfo, np.int32, "level >= 0 (diffuse) or -(k+1) (highlight layer k)")
    k.array("hl_spacing", hl, np.float32, "highlight spacing per unit t_enter")
    k.array("ptab", ptab, np.float32, "phase features [NA][NPAD] over alpha = linspace(0, pi, NA)")
    k.scalar("NA", ptab.shape[0], "int", "rows of ptab")
    k.array("points", case.pts, np.float32, "[N][3] world")
    k.array("omegas", case.om, np.float32, "[N][3] unit, toward the camera")
    k.scalar("light", list(case.light), "float4", "unit, toward the light")
    k.scalar("lobe_g", list(g4), "float4", "HG g per lobe")
    k.scalar("lobe_w", list(w4), "float4", "lobe weights")
    c_out = float(np.float32(case.lw.astype(np.float64).sum() + float(case.bias)))
    k.scalar("c_out", c_out, "float", "C outside the cube: sum w + b")
    k.array("order", np.arange(n), np.int32, "processing order (a permutation)")
    k.scalar("N", n, "int", "queries")
    k.info["args"] += [{"name": "out", "doc": "[N][3][NP] features (output)"},
                       {"name": "levels", "doc": "train mode only (any 4 bytes)"},
                       {"name": "tenter", "doc": "[N] (output)"}]
    k.array("features", np.asarray(want["features"], np.float32), np.float32, "[N][3][NP]",
            output=True)
    k.array("t_enter", want["t_enter"], np.float32, "[N]", output=True)
    k.kv["gather.np"] = layout.N_POINTS
    k.program(dict(phase_defines(case.lobes), NP=layout.N_POINTS,
                   COARSE_LEVEL=kg.coarse_level(case.base), GATHER_RENDER=1),
              {"GATHER_SHUFFLE": 1} if kg.USE_SHUFFLE else {}, "gather")
    k.tolerance("t_enter", 0.0, 1e-5 * pyr.cube_size, "float32 DDA vs float64 slab tests")
    k.tolerance("density", 0.0, 2e-5, "log1p(tau): float32 trilinear lookups vs float64")
    k.tolerance("transmittance", 0.0, 2e-5, "baked C read trilinearly vs the twin's per-level sum")
    k.tolerance("phase", 0.0, 2e-3, "the kernel interpolates its alpha table linearly, the twin "
                "evaluates the exact alpha (tests/test_phasetable.py bound)")
    k.write()


def _bake_golden(root: Path, case: _GatherCase) -> None:
    """bake_small over every level of the gather's pyramid."""
    pyr, L = case.pyr, case.pyr.n_levels
    k = _Kernel(root, "bake", "gather", "bake_small",
                "render-time (tau, C) grid, one voxel per work-item (bake_rows/bake_xpass for "
                "levels >= 16 give the same values to rounding)",
                "total voxels of levels first.. (padded; guarded)")
    k.array("dens", pyr.data, np.float32, "pyramid")
    k.array("tlev", case.graded, np.float32, "graded T, same layout")
    k.array("loff", pyr.level_offsets, np.int32, "level offsets")
    k.scalar("L", L, "int", "levels")
    k.scalar("n0", case.base, "int", "base resolution")
    k.scalar("first", 0, "int", "first level baked (all)")
    taufac = np.array([case.scale * pyr.cube_size / (case.base >> l) for l in range(L)],
                      np.float32)
    k.array("taufac", taufac, np.float32, "density_scale x voxel size per level")
    k.array("weights", case.lw, np.float32, "level weights")
    k.scalar("bias", float(case.bias), "float", "level bias")
    k.array("baked", case.baked, np.float32, "(tau, C) pairs + BAKE_PAD zeros", output=True)
    k.program({})
    k.tolerance("tau", 1e-6, 0.0, "one float32 product")
    k.tolerance("C", 0.0, 2e-6, "float32 sum of L weighted lerps (tests/test_gather.py)")
    k.write()


def _pyramid_golden(root: Path, rng, rpyramid) -> None:
    """mip_reduce on an 8^3 level."""
    lv0 = _density(rng, (8, 8, 8), 2.0)
    k = _Kernel(root, "pyramid", "pyramid", "mip_reduce", "one 2x2x2 mean step of the mip chain",
                "n_dst^3 per launch (padded; guarded)")
    chain = rpyramid.mip_chain(lv0)
    k.array("data_in", np.concatenate([lv0.ravel(), np.zeros(sum(c.size for c in chain[1:]))]),
            np.float32, "the pyramid buffer before: level 0 filled (launch once per level)")
    k.array("data_out", np.concatenate([c.ravel() for c in chain]), np.float32,
            "after launches (src_off, dst_off, n_dst) = (0, 512, 4), (512, 576, 2), (576, 584, 1)",
            output=True)
    k.program({})
    k.tolerance("data", 0.0, 0.0, "the twin adds in the kernel's order: identical bits")
    k.write()


def _majorant_golden(root: Path, rng, rmajorant) -> None:
    """An 11 x 9 x 7 grid, block 4 (partial blocks on every axis)."""
    dens = _density(rng, (7, 9, 11), 1.0, np.s_[:, :, :4])
    k = _Kernel(root, "majorant", "majorant", "majorant_build",
                "per-block max density incl. the one-voxel trilinear apron",
                "3-D (mx, my, mz), first dimension padded")
    k.array("density", dens, np.float32, "[nz][ny][nx]")
    k.scalar("nx", 11, "int", "")
    k.scalar("ny", 9, "int", "")
    k.scalar("nz", 7, "int", "")
    k.scalar("block", 4, "int", "voxels per block")
    k.array("maj", rmajorant.build_majorant(dens, 4), np.float32, "[mz][my][mx] = [2][3][3]",
            output=True)
    k.program({})
    k.tolerance("maj", 0.0, 0.0, "a max: identical bits")
    k.write()


def _transmittance_golden(root: Path, rng, rtrans) -> None:
    """One level's optical depth by the sweep (oblique light)."""
    from .kernels import transmittance as kt
    lv = _density(rng, (16, 16, 16), 1.0, np.s_[4:9])
    ldir = _unit([0.35, -0.2, 0.9])
    tscale = 0.3
    k = _Kernel(root, "transmittance", "transmittance", "transmittance_sweep_block",
                "optical depth toward the light on one level (host tables: "
                "clvol/kernels/transmittance.py _sweep_level, docs/embedding.md)")
    k.array("level", lv, np.float32, "[n][n][n] density of the level")
    k.scalar("light", list(ldir), "float4", "unit, toward the light")
    k.scalar("scale", tscale, "float", "tau per (density x voxel-unit length)")
    k.array("tau", rtrans.sweep(lv.astype(np.float64), ldir, tscale), np.float32, "[n][n][n]",
            output=True)
    k.program({"SWEEP_WIDTH": kt.sweep_width_define(16)}, name="transmittance_wL")
    k.tolerance("tau", 0.0, 2e-5, "atol x max tau: the twin runs the same sweep in float64 "
                "(tests/test_transmittance.py KERNEL_TWIN_RTOL)")
    k.write()


def add_arguments(p) -> None:
    p.add_argument("dir", help="output folder (created)")


def run(args) -> int:
    out = write_goldens(args.dir)
    print(f"wrote golden vectors to {out}")
    return 0
