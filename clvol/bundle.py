"""``clvol bundle SCENE.toml DIR``: everything a C host needs to render a scene with the
network method (light field, graded transmittance, bake, gather, MLP, F_ms lattice, ray
march), in plain files that need no Python to read. The format is docs/embedding.md; the C
host that reads it is examples/c/.

    from clvol.bundle import write_bundle
    write_bundle(load_scene("examples/jade.toml"), "jade.bundle", ms_resolution=32)

DIR/manifest.txt is ``key = value`` lines (``#`` starts a comment; lists are space-separated;
strings have no spaces). Every binary file is raw little-endian float32 or int32, C order.
The ``-D`` defines are computed by the same functions the Python host calls
(``raymarch_defines``, ``mlp.kernel_defines``, ``phase_defines``, ``coarse_level``) and
formatted by the runtime's own ``_define_flags``; the host constants (padding, tile and chunk
sizes) are read from the Python modules that launch the kernels, so the C host hard-codes none.
tests/test_c_host.py checks the recorded defines against the ones a Python render builds.
"""
from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np

from . import layout
from .errors import ClvolError

FORMAT = "clvol-bundle"
FORMAT_VERSION = 1


def _fmt(v) -> str:
    if isinstance(v, (bool, np.bool_)):
        return str(int(v))
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))   # round-trips through strtod
    if isinstance(v, str):
        if any(c.isspace() for c in v) or "#" in v:
            raise ValueError(f"bundle manifest strings may not hold spaces or '#': {v!r}")
        return v
    return " ".join(_fmt(x) for x in v)


class _Manifest:
    def __init__(self):
        self.lines: list[str] = []

    def comment(self, text: str) -> None:
        self.lines.append(f"# {text}")

    def __setitem__(self, key, value) -> None:
        self.lines.append(f"{key} = {_fmt(value)}")

    def text(self) -> str:
        return "\n".join(self.lines) + "\n"


def _write_raw(path: Path, array, dtype) -> int:
    a = np.ascontiguousarray(array, dtype=np.dtype(dtype).newbyteorder("<"))
    path.write_bytes(a.tobytes())
    return a.size


def program_options(stem: str, defines: dict) -> str:
    """``-D`` options of a program as clvol.runtime builds it (the ``-I`` is the host's)."""
    from .runtime import _define_flags, _sources_hash, cl_source_dir
    h = _sources_hash(cl_source_dir() / f"{stem}.cl")
    return " ".join([f"-DCLVOL_SOURCES_HASH=0x{h}"] + _define_flags(defines))


def write_bundle(scene, out_dir, *, weights=None, ms_resolution=None, step=None,
                 threshold=None, block=None, light_resolution=None,
                 light_interp: str = "transmittance", skip_empty: bool = True) -> Path:
    """Write the bundle of ``scene`` (a clvol Scene) rendered with --method raymarch
    --ms network and these options (defaults: the ray marcher's). Returns DIR."""
    from .kernels import gather as kg
    from .kernels import mlp as km
    from .kernels import pyramid as kp
    from .kernels import raymarch as kr
    from .kernels import transmittance as kt
    from .kernels.phase import lobe_vectors, phase_defines
    from .raymarch import (DEFAULT_BLOCK, DEFAULT_NETWORK_RESOLUTION, DEFAULT_STEP,
                           DEFAULT_THRESHOLD, NETWORK_CHUNK, Octaves, Plan, MsGrid,
                           _check_network_options, _check_options, auto_light_resolution,
                           load_network_weights, shipped_weights)
    from .runtime import DEFAULT_PAD, cl_source_dir, include_dir

    step = DEFAULT_STEP if step is None else float(step)
    threshold = DEFAULT_THRESHOLD if threshold is None else float(threshold)
    block = DEFAULT_BLOCK if block is None else block
    ms_resolution = DEFAULT_NETWORK_RESOLUTION if ms_resolution is None else ms_resolution
    octaves = Octaves()
    _check_options("network", octaves, step, threshold, block, light_resolution, 1, None)
    weights = shipped_weights() if weights is None else weights
    _check_network_options(weights, ms_resolution)
    if light_interp not in kr.LIGHT_QUANTITIES:
        raise ClvolError(f"bundle option light_interp = {light_interp!r}: choose one of "
                         f"{list(kr.LIGHT_QUANTITIES)}")
    w = load_network_weights(weights)
    grid = scene.volume.load()
    medium, light, cam = scene.medium, scene.light, scene.camera
    res = ((ms_resolution,) * 3 if np.isscalar(ms_resolution)
           else tuple(int(v) for v in ms_resolution))
    if int(np.prod(res)) > NETWORK_CHUNK:
        # The Python host splits bigger lattices into chunks; the C host runs one launch.
        raise ClvolError(f"bundle option ms_resolution = {ms_resolution!r}: at most "
                         f"{NETWORK_CHUNK} lattice points (32^3) in a bundle")
    light_res = light_resolution or auto_light_resolution(grid)
    base = int(w.contract["base_resolution"])
    lam = float(w.contract["lambda"])
    L = kp.n_levels(base)

    # The plan the Python host would make: which lobes the ray marcher evaluates, how many
    # colour planes the F_ms lattice has (a stand-in grid of the right channel count).
    grey = medium.is_grey
    stand_in = MsGrid(np.zeros((1, 1, 1) if grey else (1, 1, 1, 3), np.float32),
                      tuple(grid.bbox_min), tuple(grid.bbox_max))
    plan = Plan.make(medium, light, "network", octaves, stand_in, True)
    channels = plan.channels if plan.lit else 1
    med_lobes = kg._lobes(medium)

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "cl" / "include").mkdir(parents=True, exist_ok=True)
    src = cl_source_dir()
    cl_files = sorted(p.name for p in src.glob("*.cl"))
    headers = sorted(p.name for p in include_dir().glob("*.h"))
    for name in cl_files:
        shutil.copyfile(src / name, out / "cl" / name)
    for name in headers:
        shutil.copyfile(include_dir() / name, out / "cl" / "include" / name)

    m = _Manifest()
    m.comment("clvol bundle: key = value, lists space-separated; format in docs/embedding.md")
    m["format"] = FORMAT
    m["format_version"] = FORMAT_VERSION
    m["scene"] = "_".join(str(scene.path.name).split()).replace("#", "_") if scene.path else "-"
    m["sources"] = ["cl/" + n for n in cl_files]
    m["headers"] = ["cl/include/" + n for n in headers]
    m["include_dir"] = "cl/include"

    m.comment("programs: <name> = source file; options (all devices); options_pocl (added on PoCL)")
    mlp_defs = km.kernel_defines(w.arch, 1 if grey else 3, True)
    gather_defs = dict(phase_defines(med_lobes), NP=layout.N_POINTS,
                       COARSE_LEVEL=kg.coarse_level(base), GATHER_RENDER=1)
    rm_defs = kr.raymarch_defines(plan.lobes, plan.lit, plan.source, octaves.n, channels,
                                  skip_empty)
    rm_defs["LIGHT_TAU"] = int(light_interp == "optical_depth")
    programs = {
        "pyramid": ("pyramid", {}, {}),
        "majorant": ("majorant", {}, {}),
        "transmittance": ("transmittance", {}, {}),
        "transmittance_w1": ("transmittance", {"SWEEP_WIDTH": 1}, {}),
        "transmittance_w16": ("transmittance", {"SWEEP_WIDTH": 16}, {}),
        "gather": ("gather", gather_defs, {"GATHER_SHUFFLE": 1} if kg.USE_SHUFFLE else {}),
        "gather_bake": ("gather", {}, {}),
        "mlp": ("mlp", mlp_defs, {"MLP_TRANSPOSE16": 1, "MLP_PREFETCH": 1}),
        "raymarch": ("raymarch", rm_defs, {}),
    }
    if not plan.lit:    # nothing lit: no light field, no network (the Python host builds none)
        programs = {k: v for k, v in programs.items() if k in ("majorant", "raymarch")}
    m["programs"] = list(programs)
    for name, (stem, defs, pocl) in programs.items():
        m[f"program.{name}"] = f"cl/{stem}.cl"
        m[f"program.{name}.options"] = program_options(stem, defs).split()
        if pocl:
            from .runtime import _define_flags
            m[f"program.{name}.options_pocl"] = _define_flags(pocl)

    m.comment("host constants of the launches (clvol/runtime.py, clvol/kernels/*.py)")
    m["host.pad"] = DEFAULT_PAD
    m["host.sweep_pad"] = kt.SWEEP_PAD
    m["host.sweep_block"] = kt.SWEEP_BLOCK
    m["host.sweep_slack"] = kt.SWEEP_SLACK
    m["host.sweep_group"] = kt.SWEEP_GROUP
    m["host.sweep_vector_min_n"] = kt.VECTOR_MIN_N
    m["host.bake_min_row_level"] = kg.MIN_ROW_LEVEL
    m["host.bake_span"] = kg.BAKE_SPAN
    m["host.bake_pad"] = kg.BAKE_PAD
    m["host.sort_bits"] = kg.SORT_BITS
    m["host.mlp_queries_per_item"] = km.QUERIES_PER_ITEM
    m["host.raymarch_tile"] = kr.TILE
    m["host.raymarch_local_size"] = kr.LOCAL_SIZE

    m.comment("volume: raw density [nz][ny][nx] float32, sigma_t = density * density_scale")
    m["density.file"] = "density.f32"
    _write_raw(out / "density.f32", grid.density, np.float32)
    nz, ny, nx = grid.density.shape
    m["density.dims"] = [nx, ny, nz]
    m["density.bbox_min"] = [float(v) for v in grid.bbox_min]
    m["density.bbox_max"] = [float(v) for v in grid.bbox_max]

    m.comment("medium")
    m["medium.density_scale"] = float(medium.density_scale)
    m["medium.albedo"] = [float(a) for a in medium.albedo]
    m["medium.grey"] = grey
    m["medium.lobes"] = len(med_lobes)
    g4, w4 = lobe_vectors(med_lobes)
    m["medium.lobe_g"] = g4.tolist()
    m["medium.lobe_w"] = w4.tolist()
    # config fields g0 g1 g2 w0 w1 w2 g_mean of every query (clvol/layout.py), as the gather
    # makes them; the host adds albedo and alpha per query
    cfg = kg.config_vectors(medium, 0.0, np.array([[0.0, 0.0, 1.0]]), np.array([0.0, 0.0, 1.0]))
    m["medium.config_phase"] = cfg[0, :7].tolist()

    m.comment("light: direction toward the light (unit), irradiance RGB, background RGB")
    l = np.asarray(light.direction, np.float64)
    m["light.direction"] = (l / np.linalg.norm(l)).tolist()
    m["light.irradiance"] = [float(v) for v in light.irradiance]
    m["light.background"] = [float(v) for v in plan.background]

    m.comment("camera: pinhole, orthonormal basis (clvol.scene.Camera.basis)")
    fwd, right, up = cam.basis()
    m["camera.origin"] = [float(v) for v in cam.origin]
    m["camera.forward"] = fwd.tolist()
    m["camera.right"] = right.tolist()
    m["camera.up"] = up.tolist()
    m["camera.tan_half"] = math.tan(math.radians(cam.fov_y) / 2)
    m["camera.width"] = cam.width
    m["camera.height"] = cam.height

    m.comment("ray march (step in world units = step_voxels x smallest cell side)")
    m["raymarch.lit"] = plan.lit
    m["raymarch.step"] = step * float(np.min(grid.cell_size))
    m["raymarch.threshold"] = threshold
    m["raymarch.block"] = int(block)
    m["raymarch.skip_empty"] = bool(skip_empty)
    m["raymarch.light_resolution"] = int(light_res)
    m["raymarch.light_tau"] = rm_defs["LIGHT_TAU"]
    m["raymarch.channels"] = channels
    rg, rw = lobe_vectors(plan.lobes)
    m["raymarch.lobe_g"] = rg.tolist()
    m["raymarch.lobe_w"] = rw.tolist()
    m["raymarch.octave_abc"] = [octaves.a, octaves.b, octaves.c]

    m.comment("network: feature contract, lattice, weights (network.bin, float32)")
    c = w.contract
    m["network.layout_version"] = int(c["layout_version"])
    m["network.template_hash"] = str(c["template_hash"])
    m["network.base_resolution"] = base
    m["network.n_levels"] = L
    m["network.lambda"] = lam
    m["network.ms_resolution"] = list(res)
    m["network.ms_bbox_min"] = [float(v) for v in grid.bbox_min]
    m["network.ms_bbox_max"] = [float(v) for v in grid.bbox_max]
    m["network.file"] = "network.bin"
    packed = km.pack_params(w)
    lw = np.asarray(w.level_weights, np.float32)
    blob = np.concatenate([packed, lw, np.float32([w.level_bias])])
    _write_raw(out / "network.bin", blob, np.float32)
    m["network.params"] = [0, packed.size]
    m["network.level_weights"] = [packed.size, lw.size]
    m["network.level_bias"] = packed.size + lw.size
    tensors = _packed_tensors(w, km._pad8)
    tensors.append(("level_weights", packed.size, (lw.size,), "level-weights"))
    tensors.append(("level_bias", packed.size + lw.size, (1,), "level-bias"))
    m["network.tensors"] = len(tensors)
    for i, (name, off, shape, role) in enumerate(tensors):
        m[f"network.tensor.{i}"] = [name, off, "x".join(str(s) for s in shape), role]

    m.comment("gather tables: template points [3][NPAD] (frame units), pinfo int [NPAD], "
              "phase features [NA][NPAD]")
    tpl, pinfo, hl = kg.template_arrays(base)
    ptab = kg._phase_table_padded(med_lobes)
    m["gather.np"] = layout.N_POINTS
    m["gather.npad"] = tpl.shape[1]
    m["gather.templates"] = "templates.f32"
    m["gather.pinfo"] = "pinfo.i32"
    m["gather.hl_spacing"] = hl.tolist()
    m["gather.phase_table"] = "phase_table.f32"
    m["gather.n_alpha"] = ptab.shape[0]
    _write_raw(out / "templates.f32", tpl, np.float32)
    _write_raw(out / "pinfo.i32", pinfo, np.int32)
    _write_raw(out / "phase_table.f32", ptab, np.float32)
    (out / "manifest.txt").write_text(m.text())
    return out


def _packed_tensors(w, pad8) -> list:
    """(name, float offset in network.bin, shape as stored, role) of pack_params' layout."""
    out, off = [], 0
    for name, n in (("feature_shift", 3), ("feature_scale", 3),
                    ("config_shift", layout.CONFIG_DIM), ("config_scale", layout.CONFIG_DIM)):
        out.append((name, off, (n,), "normalisation"))
        off += n
    for name, n_in, n_out in w.arch.linear_layers():
        out.append((f"{name}.weight_t", off, (n_in, pad8(n_out)), "linear-weight-transposed"))
        off += n_in * pad8(n_out)
        out.append((f"{name}.bias", off, (pad8(n_out),), "linear-bias"))
        off += pad8(n_out)
    return out


def add_arguments(p) -> None:
    from .raymarch import DEFAULT_NETWORK_RESOLUTION
    p.add_argument("scene", help="scene .toml file")
    p.add_argument("dir", help="output folder (created)")
    p.add_argument("--weights", metavar="FILE.npz", help="network weights (default: shipped)")
    p.add_argument("--ms-resolution", type=int, default=DEFAULT_NETWORK_RESOLUTION,
                   help=f"F_ms lattice points per side (default {DEFAULT_NETWORK_RESOLUTION}, "
                        f"at most 32)")
    p.add_argument("--light-resolution", type=int, default=None,
                   help="light field resolution (power of two; default as clvol render)")
    p.add_argument("--light-interp", choices=["transmittance", "optical_depth"],
                   default="transmittance",
                   help="what the light field holds and is blended (as clvol render)")
    p.add_argument("--step", type=float, default=None, help="march step in voxels (default 1)")
    p.add_argument("--threshold", type=float, default=None,
                   help="early termination transmittance (default 1e-3)")
    p.add_argument("--width", type=int, default=None, help="override the camera's width")
    p.add_argument("--height", type=int, default=None, help="override the camera's height")


def run(args) -> int:
    from .scene import load_scene
    scene = load_scene(args.scene)
    over = {k: v for k, v in (("camera.width", args.width), ("camera.height", args.height))
            if v is not None}
    if over:
        scene = scene.with_overrides(over, source=str(args.scene))
    out = write_bundle(scene, args.dir, weights=args.weights, ms_resolution=args.ms_resolution,
                       step=args.step, threshold=args.threshold,
                       light_resolution=args.light_resolution, light_interp=args.light_interp)
    print(f"wrote {out}/manifest.txt")
    return 0
