"""``clvol bundle SCENE.toml DIR``: everything a C host needs to render a scene as ``clvol
render`` does by default (the network method: light field, graded transmittance, bake,
gather, MLP, F_ms lattice, ray march; or the analytic source the renderer falls back to), in
plain files that need no Python to read. The format is docs/embedding.md; the C host that
reads it is examples/c/.

    from clvol.bundle import write_bundle
    write_bundle(load_scene("examples/jade.toml"), "jade.bundle", ms_resolution=32)

DIR/manifest.txt is ``key = value`` lines (``#`` starts a comment; lists are space-separated;
strings have no spaces). Every binary file is raw little-endian float32 or int32, C order.
The bundle serialises the renderer's plan of the scene's frame (clvol/render/plan.py
``plan_frame``, through ``Renderer.plan``): the source it chose, every program's ``-D``
defines as the plan lists them (``FramePlan.programs``; the network's gather and MLP apart,
as the C host runs them, from the same source's ``network_programs``), the network's
active-point rule (its ``active_points``), formatted by the runtime's own
``_define_flags``; the host constants
(padding, tile and chunk sizes) are read from the Python modules that launch the kernels, so
the C host hard-codes none. tests/test_c_host.py checks the image, the source, the network's
point count and the recorded defines against a Python render.
"""
from __future__ import annotations

import dataclasses
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import ClvolError
from .features import layout
from .scenefile import SET_HELP

FORMAT = "clvol-bundle"
FORMAT_VERSION = 3        # 2: the ray marcher takes the medium block; 3: and the light block


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
                 light_interp: str = "transmittance", skip_empty: bool = True,
                 runtime=None, octaves=None, ms: str = "network", view_block=None,
                 view_samples=None, seed=None) -> Path:
    """Write the bundle of ``scene`` (a clvol Scene) as ``clvol render`` renders it by default
    (--method raymarch --ms network, with its domain fallback and shortcuts) with these
    options (None: the renderer's defaults). Returns DIR.

    The options, the source actually used (the network, or the analytic source the renderer
    falls back to: none or wrenninge), the kernel defines and the lattice points the network
    evaluates are all taken from the plan of a ``clvol.Renderer`` built for the scene; nothing
    is rendered. ``runtime``: the OpenCL runtime it is built on (default: clvol's).
    ``octaves``: an ``Octaves`` for the Wrenninge fallback (default the renderer's: 3 octaves,
    a = b = c = 0.5); used only where the renderer falls back to it. ``ms``: the network
    source the C host runs, ``network`` (the world lattice) or ``stochastic`` (the
    view-space table: ``view_block``, ``view_samples`` and ``seed`` are its options)."""
    out = check_out_dir(out_dir)
    b = _plan(scene, dict(weights=weights, ms_resolution=ms_resolution, step=step,
                          threshold=threshold, majorant_block=block,
                          light_resolution=light_resolution, light_interp=light_interp,
                          skip_empty=skip_empty, view_block=view_block,
                          view_samples=view_samples, seed=seed), runtime, octaves, ms)
    m = _Manifest()
    _write_sources(m, scene, out)
    _write_programs(m, b)
    _write_host_constants(m, b)
    _write_volume(m, b, out)
    _write_medium_light_camera(m, b)
    _write_raymarch(m, b)
    _write_domain(m, b)
    _write_view(m, b)
    _write_network(m, b, out)
    _write_gather_tables(m, b, out)
    (out / "manifest.txt").write_text(m.text())
    return out


@dataclass
class _Planned:
    """The renderer's plan of the scene's frame and what the sections write from it."""
    scene: object
    grid: object
    options: object
    plan: object
    domain: dict
    source: object             # the configured network source (clvol/render/ms/network.py)
    weights: object            # the network's MlpWeights
    res: tuple                 # the F_ms lattice (gx, gy, gz)
    active: object             # the network's active lattice points ([z][y][x] indices)
    network: bool              # the network runs (lit, and the plan's source)
    light_res: int
    block: int                 # majorant block (voxels)
    view: dict | None = None   # a view-space source's bundle_view (view.* keys, viewdepth)

    @property
    def base(self) -> int:
        return int(self.weights.contract["base_resolution"])

    @property
    def med_lobes(self):
        from .kernels import gather as kg
        return kg._lobes(self.scene.medium)


def _plan(scene, given: dict, runtime, octaves, ms: str = "network") -> _Planned:
    """The renderer validates and completes the options exactly as `clvol render` does, and
    its plan (clvol/render/plan.py) is what the bundle serialises: the source it chose, the
    kernel defines, the active lattice points, the light field's resolution. What the C host
    does not implement is refused here, naming it."""
    from .kernels.majorant import majorant_block
    from .render.ms import source_class
    from .render.renderer import Renderer
    grid = scene.volume.load()
    r = Renderer(scene, "raymarch", grid=grid, runtime=runtime, ms=ms,
                 **{k: v for k, v in given.items() if v is not None})
    o = r.options
    if octaves is not None:        # the Wrenninge fallback's octaves, used where it runs
        for k, v in octaves.as_options().items():
            o.set(k, v)
    plan = r.plan()
    configured = r.source        # the network source the C host runs (its declarations)
    view = configured.bundle_view(plan.camera)    # None: the world lattice
    res = ((1, 1, 1) if view is not None else
           (o["ms_resolution"],) * 3 if np.isscalar(o["ms_resolution"])
           else tuple(int(v) for v in o["ms_resolution"]))
    chunk = configured.lattice_points_per_launch
    if int(np.prod(res)) > chunk:
        # The Python host splits bigger lattices into chunks; the C host runs one launch.
        raise ClvolError(f"bundle option ms_resolution = {o['ms_resolution']!r}: at most "
                         f"{chunk} lattice points (32^3) in a bundle")
    if plan.supersample != 1:
        raise ClvolError("bundle: supersampling is not in the bundle format")
    # The C host runs the sources that declare ``bundle_supported`` (the network, none and
    # wrenninge); another is refused by name.
    ran = source_class(plan.source)
    if plan.lit and not ran.bundle_supported:
        raise ClvolError(f"{scene.path or 'scene'}: the renderer would use --ms {plan.source} "
                         f"for this medium, which the C host (examples/c/) does not implement")
    if plan.env_scatter or plan.env_background == "map":
        raise ClvolError(f"{scene.path or 'scene'}: the renderer lights this medium with the "
                         f"sky (or shows a map behind it), which the C host (examples/c/) "
                         f"does not implement; a bundle renders the sun and a constant "
                         f"background only (docs/embedding.md)")
    network = plan.lit and ran.uses_network
    if network and view is not None and \
            plan.programs["raymarch"].get("VIEW_BLOCK") != view["keys"]["block"]:
        raise ClvolError(f"bundle: the march's VIEW_BLOCK "
                         f"{plan.programs['raymarch'].get('VIEW_BLOCK')} is not the view "
                         f"source's block {view['keys']['block']}")
    # Lattice points the network evaluates (the others hold F_ms = 0): the plan's rule.
    active = (np.flatnonzero(configured.active_points(grid, res, plan.lattice_reach))
              if network and view is None else np.zeros(0, np.int64))
    return _Planned(scene, grid, o, plan, r.domain, configured, configured.network_weights(),
                    res, active, network, plan.light_resolution,
                    majorant_block(o["majorant_block"], grid.density.shape),
                    view if network else None)


def check_out_dir(out_dir) -> Path:
    """The bundle folder, refused before anything is planned or written (one line): a file of
    that name, or a missing parent folder (as clvol render and the viewer refuse one: a typo
    in the path must not create folders from the root down). An existing folder is written
    into."""
    from .errors import ClvolError
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ClvolError(f"{out}: exists and is not a folder; a bundle is a folder "
                         f"(manifest.txt, cl/, arrays): name a new or existing folder")
    parent = out.resolve().parent
    if not parent.is_dir():
        raise ClvolError(f"{out}: cannot write, folder {parent} does not exist")
    return out


def _write_sources(m: "_Manifest", scene, out: Path) -> None:
    """The OpenCL sources the programs build from, copied, and the manifest's head."""
    from .runtime import cl_source_dir, include_dir
    out.mkdir(exist_ok=True)                    # its parent exists: check_out_dir
    (out / "cl" / "include").mkdir(parents=True, exist_ok=True)
    src = cl_source_dir()
    cl_files = sorted(p.name for p in src.glob("*.cl"))
    headers = sorted(p.name for p in include_dir().glob("*.h"))
    for name in cl_files:
        shutil.copyfile(src / name, out / "cl" / name)
    for name in headers:
        shutil.copyfile(include_dir() / name, out / "cl" / "include" / name)
    m.comment("clvol bundle: key = value, lists space-separated; format in docs/embedding.md")
    m["format"] = FORMAT
    m["format_version"] = FORMAT_VERSION
    m["scene"] = "_".join(str(scene.path.name).split()).replace("#", "_") if scene.path else "-"
    m["sources"] = ["cl/" + n for n in cl_files]
    m["headers"] = ["cl/include/" + n for n in headers]
    m["include_dir"] = "cl/include"


# The manifest's order of the programs (those of the plan that the C host builds).
PROGRAM_ORDER = ("pyramid", "majorant", "transmittance", "transmittance_w1", "transmittance_wL",
                 "gather", "gather_bake", "mlp", "viewdepth", "raymarch")


def _write_programs(m: "_Manifest", b: _Planned) -> None:
    """The plan's programs (FramePlan.programs and programs_pocl) with their -D options,
    written as they are; the network's gather and MLP as the C host runs them, apart (the
    source's ``network_programs`` with ``fused=False``, where Python fuses them)."""
    from .render.plan import program_source
    from .runtime import _define_flags
    plan = b.plan
    m.comment("programs: <name> = source file; options (all devices); options_pocl (added on PoCL)")
    programs, pocl = dict(plan.programs), dict(plan.programs_pocl)
    if b.network:
        apart, apart_pocl = b.source.network_programs(b.scene.medium, plan.shortcuts,
                                                      b.weights, fused=False)
        programs.pop("gather_mlp", None)
        programs.update(apart)
        pocl.update(apart_pocl)
    if b.view is not None:       # the view source's free-flight draws (cl/viewdepth.cl)
        programs["viewdepth"] = b.view["viewdepth"]
    unknown = set(programs) - set(PROGRAM_ORDER)
    if unknown:
        raise ClvolError(f"bundle: programs {sorted(unknown)} have no place in the manifest")
    names = [n for n in PROGRAM_ORDER if n in programs]
    m["programs"] = names
    for name in names:
        stem = program_source(name)
        m[f"program.{name}"] = f"cl/{stem}.cl"
        m[f"program.{name}.options"] = program_options(stem, programs[name]).split()
        if pocl.get(name):
            m[f"program.{name}.options_pocl"] = _define_flags(pocl[name])


def _write_host_constants(m: "_Manifest", b: _Planned) -> None:
    from .kernels import gather as kg
    from .kernels import mlp as km
    from .kernels import raymarch as kr
    from .kernels import transmittance as kt
    from .kernels import blocks as kblk
    from .runtime import DEFAULT_PAD
    m.comment("host constants of the launches (clvol/runtime.py, clvol/kernels/*.py)")
    host = {"pad": DEFAULT_PAD, "sweep_pad": kt.SWEEP_PAD, "sweep_block": kt.SWEEP_BLOCK,
            "sweep_slack": kt.SWEEP_SLACK, "sweep_group": kt.SWEEP_GROUP,
            "sweep_vector_min_n": kt.VECTOR_MIN_N, "bake_min_row_level": kg.MIN_ROW_LEVEL,
            "bake_span": kg.BAKE_SPAN, "bake_pad": kg.BAKE_PAD, "sort_bits": kg.SORT_BITS,
            "raymarch_tile": kr.TILE,
            "raymarch_local_size": kr.LOCAL_SIZE,
            # the network's config layout (clvol/features/layout.py CONFIG_FIELDS): the phase
            # fields first (medium.config_phase), then the albedo and alpha the host adds
            "config_dim": layout.CONFIG_DIM,
            "config_albedo": layout.CONFIG_FIELDS.index("albedo"),
            "config_alpha": layout.CONFIG_FIELDS.index("alpha"),
            # the blocks' slots the C host writes (cl/include/constants.h MEDIUM_*, LIGHT_*)
            "medium_floats": kblk.MEDIUM_FLOATS, "medium_density_scale": kblk.SLOT_DENSITY_SCALE,
            "medium_albedo": kblk.SLOT_ALBEDO, "light_floats": kblk.LIGHT_FLOATS,
            "light_direction": kblk.SLOT_DIRECTION, "light_irradiance": kblk.SLOT_IRRADIANCE}
    if b.source.lattice_points_per_launch:   # the most queries of one gather + MLP launch
        host["network_chunk"] = int(b.source.lattice_points_per_launch)
    for key, value in host.items():
        m[f"host.{key}"] = value


def _write_volume(m: "_Manifest", b: _Planned, out: Path) -> None:
    grid = b.grid
    m.comment("volume: raw density [nz][ny][nx] float32, sigma_t = density * density_scale")
    m["density.file"] = "density.f32"
    _write_raw(out / "density.f32", grid.density, np.float32)
    nz, ny, nx = grid.density.shape
    m["density.dims"] = [nx, ny, nz]
    m["density.bbox_min"] = [float(v) for v in grid.bbox_min]
    m["density.bbox_max"] = [float(v) for v in grid.bbox_max]


def _write_medium_light_camera(m: "_Manifest", b: _Planned) -> None:
    from .kernels import gather as kg
    from .kernels import transmittance as kt
    from .kernels.phase import lobe_vectors
    medium, light, cam = b.scene.medium, b.scene.light, b.scene.camera
    m.comment("medium")
    m["medium.density_scale"] = float(medium.density_scale)
    m["medium.albedo"] = [float(a) for a in medium.albedo]
    m["medium.grey"] = medium.is_grey
    m["medium.lobes"] = len(b.med_lobes)
    g4, w4 = lobe_vectors(b.med_lobes)
    m["medium.lobe_g"] = g4.tolist()
    m["medium.lobe_w"] = w4.tolist()
    # config fields g0 g1 g2 w0 w1 w2 g_mean of every query (clvol/features/layout.py), as the gather
    # makes them; the host adds albedo and alpha per query
    cfg = kg.config_vectors(medium, 0.0, np.array([[0.0, 0.0, 1.0]]), np.array([0.0, 0.0, 1.0]))
    n_phase = layout.CONFIG_FIELDS.index("albedo")       # the fields before the albedo
    m["medium.config_phase"] = cfg[0, :n_phase].tolist()

    m.comment("light: direction toward the light (unit), irradiance RGB, background RGB")
    m["light.direction"] = kt.check_light_dir(light.direction, "light.direction").tolist()
    m["light.irradiance"] = [float(v) for v in light.irradiance]
    m["light.background"] = [float(v) for v in b.plan.background]

    m.comment("camera: pinhole, orthonormal basis (clvol.scene.Camera.basis)")
    fwd, right, up = cam.basis()
    m["camera.origin"] = [float(v) for v in cam.origin]
    m["camera.forward"] = fwd.tolist()
    m["camera.right"] = right.tolist()
    m["camera.up"] = up.tolist()
    m["camera.tan_half"] = cam.tan_half_fov
    m["camera.width"] = cam.width
    m["camera.height"] = cam.height


def _write_raymarch(m: "_Manifest", b: _Planned) -> None:
    from .kernels.blocks import light_block, medium_block
    plan = b.plan
    m.comment("ray march (step in world units = step_voxels x smallest cell side)")
    m["raymarch.lit"] = plan.lit
    # the multiple-scattering source: network (the lattice below), none or wrenninge (the
    # kernel's octaves: raymarch.octave_abc); only the network reads the network.* keys
    m["raymarch.ms_source"] = plan.source if plan.lit else "none"
    m["raymarch.step"] = plan.step_voxels * float(np.min(b.grid.cell_size))
    m["raymarch.step_voxels"] = plan.step_voxels   # the option: libclvol's step on a new grid
    m["raymarch.threshold"] = plan.threshold
    m["raymarch.block"] = int(b.block)
    m["raymarch.skip_empty"] = bool(plan.skip_empty)
    m["raymarch.light_resolution"] = int(b.light_res)
    m["raymarch.light_tau"] = plan.programs["raymarch"]["LIGHT_TAU"]
    m["raymarch.channels"] = plan.channels if plan.lit else 1
    # the kernel's medium and light arguments as they are (cl/include/medium.h, light.h),
    # every property the scene declares for the kernels included; libclvol writes the slots
    # it changes at run time (host.medium_*, host.light_*)
    m["raymarch.medium"] = medium_block(b.scene.medium).tolist()
    m["raymarch.light"] = light_block(b.scene.light).tolist()
    oc = plan.ms.octaves
    m["raymarch.octave_abc"] = [oc.a, oc.b, oc.c]


def _write_domain(m: "_Manifest", b: _Planned) -> None:
    medium, dom, rules = b.scene.medium, b.domain, b.source.domain_rules()
    m.comment("domain: what clvol.Renderer needs to pick its source for another medium or "
              "volume (clvol/render/plan.py); libclvol refuses a change that would switch it")
    m["domain.thin_optical_thickness"] = rules["thin_optical_thickness"]
    m["domain.albedo"] = [float(v) for v in dom.get("albedo", [0.0, 1.0])]
    ot_range = dom.get("optical_thickness")
    m["domain.optical_thickness"] = "none" if ot_range is None else [float(v) for v in ot_range]
    # the phase cannot change in a bundle: whether it lies outside the domain is fixed
    phase_only = dataclasses.replace(medium, albedo=(1.0, 1.0, 1.0))
    m["domain.phase_outside"] = bool(b.source.outside_training_domain(
        {k: v for k, v in dom.items() if k in ("g", "max_lobes")}, phase_only))
    m["domain.backward"] = bool(medium.phase.mean_cosine < rules["backward_limit"])
    m["domain.backward_albedo"] = rules["backward_albedo"]


def _write_view(m: "_Manifest", b: _Planned) -> None:
    """The stochastic view source's options and constants (clvol/render/ms/view.py), which
    libclvol's view stage repeats; only a bundle whose source is the view table has them."""
    if b.view is None:
        return
    m.comment("view: the stochastic view-space table (clvol/render/ms/view.py): block side "
              "(auto: about blocks_across blocks across the longer side), draws per frame, "
              "seed, the still view's samples, the history a move keeps, the draw's step factor")
    for key, value in b.view["keys"].items():
        m[f"view.{key}"] = value


def _write_network(m: "_Manifest", b: _Planned, out: Path) -> None:
    from .kernels import mlp as km
    from .kernels import pyramid as kp
    w, grid = b.weights, b.grid
    m.comment("network: feature contract, lattice, weights (network.bin, float32)")
    c = w.contract
    m["network.layout_version"] = int(c["layout_version"])
    m["network.template_hash"] = str(c["template_hash"])
    m["network.base_resolution"] = b.base
    m["network.n_levels"] = kp.n_levels(b.base)
    m["network.lambda"] = float(c["lambda"])
    if b.view is None:           # the world lattice (a view source's points are drawn)
        m["network.ms_resolution"] = list(b.res)
        m["network.ms_bbox_min"] = [float(v) for v in grid.bbox_min]
        m["network.ms_bbox_max"] = [float(v) for v in grid.bbox_max]
        # the lattice points the network evaluates ([z][y][x] indices, ascending); the others
        # hold F_ms = 0 (no density within reach: their F_ms never reaches the image)
        m["network.active_points"] = int(len(b.active))
        m["network.active_file"] = "active.i32"
        _write_raw(out / "active.i32", b.active, np.int32)
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


def _write_gather_tables(m: "_Manifest", b: _Planned, out: Path) -> None:
    from .kernels import gather as kg
    m.comment("gather tables: template points [3][NPAD] (frame units), pinfo int [NPAD], "
              "phase features [NA][NPAD]")
    tpl, pinfo, hl = kg.template_arrays(b.base)
    ptab = kg._phase_table_padded(b.med_lobes)
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
    from .kernels.raymarch import DEFAULT_THRESHOLD
    from .render.ms import DEFAULT_SOURCE
    from .render.raymarch import DEFAULT_STEP
    p.add_argument("scene", help="scene .toml file")
    p.add_argument("dir", help="output folder (created)")
    p.add_argument("--weights", metavar="FILE.npz", help="network weights (default: shipped)")
    p.add_argument("--ms", default=DEFAULT_SOURCE,
                   help=f"multiple-scattering source (default {DEFAULT_SOURCE}, as clvol render): "
                        "the C host implements stochastic (the view-space table) and network "
                        "(the world lattice); view and progressive are Python-only and "
                        "refused (docs/embedding.md)")
    p.add_argument("--ms-resolution", type=int, default=None,
                   help="--ms network: F_ms lattice points per side (default: as clvol "
                        "render; at most 32)")
    p.add_argument("--view-block", type=int, default=None, metavar="B",
                   help="--ms stochastic: pixels per block side (default: as clvol render)")
    p.add_argument("--view-samples", type=int, default=None, metavar="N",
                   help="--ms stochastic: free-flight samples per block per frame (default: "
                        "as clvol render)")
    p.add_argument("--seed", type=int, default=None,
                   help="--ms stochastic: the draws' seed (default: as clvol render)")
    p.add_argument("--light-resolution", type=int, default=None,
                   help="light field resolution (power of two; default as clvol render)")
    p.add_argument("--light-interp", choices=["transmittance", "optical_depth"],
                   default="transmittance",
                   help="what the light field holds and is blended (as clvol render)")
    p.add_argument("--step", type=float, default=None, help=f"march step in voxels (default: the renderer's, {DEFAULT_STEP:g})")
    p.add_argument("--threshold", type=float, default=None,
                   help=f"early termination transmittance (default {DEFAULT_THRESHOLD:g})")
    p.add_argument("--set", action="append", metavar="TABLE.FIELD=VALUE", help=SET_HELP)
    p.add_argument("--width", type=int, default=None, help="override the camera's width")
    p.add_argument("--height", type=int, default=None, help="override the camera's height")


def run(args) -> int:
    from .errors import ClvolError
    from .render.ms import source_classes
    from .scene import load_scene_overridden
    check_out_dir(args.dir)
    ms = source_classes().get(args.ms)
    # The C host is configured with a network source (the world lattice or the stochastic
    # view table); the other sources it implements run only where the plan chooses them.
    if ms is None or not (ms.bundle_supported and ms.uses_network):
        raise ClvolError(f"clvol bundle: --ms {args.ms} is not implemented by the C host, which "
                         f"renders the network on the world lattice (--ms network) or the "
                         f"stochastic view table (--ms stochastic); view and progressive run "
                         f"only in Python (docs/embedding.md)")
    scene = load_scene_overridden(args.scene, args.set, args.width, args.height)
    out = write_bundle(scene, args.dir, weights=args.weights, ms_resolution=args.ms_resolution,
                       step=args.step, threshold=args.threshold,
                       light_resolution=args.light_resolution, light_interp=args.light_interp,
                       ms=args.ms, view_block=args.view_block, view_samples=args.view_samples,
                       seed=args.seed)
    print(f"wrote {out}/manifest.txt")
    return 0
