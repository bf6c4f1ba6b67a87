"""The trained network as the ray marcher's multiple-scattering source (the paper's method).

``NetworkSource`` holds one weight file and one volume on the device (the MLP's packed
weights, the density pyramid at the weights' base resolution: the DeviceMedium's, when it is
given one) and fills an F_ms lattice for a camera position, a light and a medium: graded
transmittance toward the light, then the render-mode template gather at the lattice points
and the OpenCL network, in one kernel by default (clvol/kernels/gather_mlp.py) or as two.
``fill_device`` writes the lattice straight into a device array in the marcher's layout
(device in, caller-owned device out: nothing is read back); ``fill`` returns it as an
``FmsLattice`` on the host. ``NetworkMs`` is the marcher's source built on it: it refills the
lattice only when the camera position, the light or the medium changed, on the device unless
``ms_refresh`` or ``ms_directions`` need the values on the host.

The weight file states the domain it was trained on (clvol/features/weights.py's
``weights_domain``); ``outside_domain`` says how a medium lies outside it.
"""
from __future__ import annotations


import numpy as np

from ...errors import ClvolError, WeightsError
from ...features.layout import MAX_NETWORK_BASE, MIN_NETWORK_BASE, is_power_of_two
from ...runtime import DeviceArray, Stopwatch, get_runtime
from ..sphere import fibonacci_directions, spherical_barycentric
from .lattice import LatticeMs, FmsLattice, check_fms_lattice, ms_lattice
from .base import MsPlan, MsSource, SourceChoice, option

DEFAULT_NETWORK_RESOLUTION = 32   # F_ms lattice points per side filled by the network
NETWORK_CHUNK = 32768             # lattice points per gather + MLP launch (~100 MiB of features)
FUSED_CHUNK = 262144              # lattice points per fused launch (no features in memory)
# The fused gather + network kernel (cl/gather_mlp.cl) as NetworkSource's default path; the
# unfused pair (gather, then mlp_forward) stays reachable with fused=False
# (bench/bench_gather_mlp.py compares them; docs/network.md has the figures).
FUSED_DEFAULT = True
# Outside the domain the network is still the best source measured, except for strongly
# backward phases (docs/raymarch.md, "Validity domain"; bench/domain_fallback.py).
BACKWARD_LIMIT = -0.8          # mean cosine below this: an analytic source instead
BACKWARD_ALBEDO = 0.9          # ... Wrenninge octaves at albedo >= this, else single only


# Below this largest optical thickness (along an axis, clvol/volume/stats.py) the network is
# not run: single scattering alone measured at least as accurate against the path tracer
# (the network's share of the image is far above the true one in thin media, outside its
# training data; docs/raymarch.md, "Validity domain").
THIN_OPTICAL_THICKNESS = 0.5


def fallback_for(medium) -> str | None:
    """The source to use instead of the network for a medium outside its domain, or None to
    keep the network (with a warning)."""
    if medium.phase.mean_cosine >= BACKWARD_LIMIT:
        return None
    alb = [a for a in medium.albedo if a > 0]
    return "wrenninge" if alb and min(alb) >= BACKWARD_ALBEDO else "none"


def shipped_weights():
    """The model that ships with clvol, trained on procedural clouds and solids (albedo
    0.3-1, HG g -0.9-0.99; how it was made and how well it does:
    clvol/data/weights/full_albedo.md)."""
    import importlib.resources
    from pathlib import Path
    return Path(str(importlib.resources.files("clvol") / "data" / "weights" / "full_albedo.npz"))


def load_network_weights(path):
    """A weight file checked against the contract of the gather that will feed it: this
    code's layout and packaged templates (hash, level map) at the file's base resolution and
    lambda (the pyramid is built to match those). Raises WeightsError naming the field."""
    from ...features.weights import MlpWeights, gather_contract, load_weights, read_meta
    if isinstance(path, MlpWeights):
        path = path.path
    c = read_meta(path)["contract"]
    base, lam = c.get("base_resolution"), c.get("lambda")
    if not (is_power_of_two(base) and MIN_NETWORK_BASE <= base <= MAX_NETWORK_BASE):
        raise WeightsError(f"{path}: [contract.base_resolution] = {base!r}: must be a power of two "
                           f"from {MIN_NETWORK_BASE} to {MAX_NETWORK_BASE}")
    if not (isinstance(lam, (int, float)) and 0 < lam <= 1):
        raise WeightsError(f"{path}: [contract.lambda] = {lam!r}: must be in (0, 1]")
    return load_weights(path, expect_contract=gather_contract(base, float(lam)))


def check_ms_resolution(r):
    ok = (isinstance(r, (int, np.integer)) and not isinstance(r, bool) and 2 <= r <= 256) or (
        not np.isscalar(r) and len(r) == 3 and all(isinstance(v, (int, np.integer)) and 2 <= v <= 256
                                                   for v in r))
    if not ok:
        raise ClvolError(f"raymarch option ms_resolution = {r!r}: an integer (or three) from 2 to 256")
    return r


# --------------------------------------------------------------------------- domain

def outside_domain(domain: dict, medium, optical_thickness: float | None = None) -> list[str]:
    """The ways ``medium`` lies outside ``domain`` (empty: inside). Channels of albedo 0 are
    not checked (the network is not evaluated there)."""
    out = []
    alb = [a for a in medium.albedo if a > 0]
    lo, hi = domain.get("albedo", [0.0, 1.0])
    bad = [a for a in alb if not lo <= a <= hi]
    if bad:
        out.append(f"albedo {bad[0]:g} outside [{lo:g}, {hi:g}]")
    lo, hi = domain.get("g", [-1.0, 1.0])
    gs = [l.g for l in medium.phase.lobes if l.weight > 0]
    bad = [g for g in gs if not lo <= g <= hi]
    if bad:
        out.append(f"phase g {bad[0]:g} outside [{lo:g}, {hi:g}]")
    n = domain.get("max_lobes")
    if n is not None and len(medium.phase.lobes) > n:
        out.append(f"{len(medium.phase.lobes)} phase lobes > {n}")
    ot = domain.get("optical_thickness")
    if ot is not None and optical_thickness is not None and not ot[0] <= optical_thickness <= ot[1]:
        out.append(f"optical thickness {optical_thickness:.3g} outside [{ot[0]:g}, {ot[1]:g}]")
    return out


# --------------------------------------------------------------------------- the lattice

def lattice_reach(grid, step_voxels: float) -> float:
    """The ``reach`` of ``lattice_reach_mask`` for a march of ``step_voxels`` (the ray
    marcher's step option): one voxel (largest cell side) plus one step (smallest side)."""
    return float(np.max(grid.cell_size)) + float(step_voxels) * float(np.min(grid.cell_size))


def lattice_reach_mask(grid, resolution, reach: float, box=None) -> np.ndarray:
    """Boolean mask over the F_ms lattice points ([z][y][x], the volume's box): True where
    some voxel of non-zero density has its centre within one lattice cell plus ``reach``
    (world units, per axis) of the point. The march reads a lattice point only at samples
    inside its trilinear support (one lattice cell) and adds F_ms weighted by the density
    there (a trilinear read: non-zero only within one voxel of an occupied centre), so F_ms at
    the other points never reaches the image: they need no network evaluation.
    ``reach`` must cover one voxel plus the distance between the density sample and the F_ms
    sample of a march segment (one step). ``box`` = (lo, hi): a lattice over that box instead
    of the volume's (the environment's field covers the pyramid's cube)."""
    res = (resolution,) * 3 if np.isscalar(resolution) else tuple(resolution)
    lo_box, hi_box = (grid.bbox_min, grid.bbox_max) if box is None else box
    occ = (np.asarray(grid.density) > 0).astype(np.int32)
    # 3-D summed-area table: occupied voxels in any index box in O(1).
    sat = np.zeros(tuple(n + 1 for n in occ.shape), np.int64)
    sat[1:, 1:, 1:] = occ.cumsum(0).cumsum(1).cumsum(2)
    lo_ix, hi_ix = [], []
    for a in range(3):                      # a = x, y, z; density axis 2 - a
        n = occ.shape[2 - a]
        cell_d = float(grid.bbox_max[a] - grid.bbox_min[a]) / n
        cell_l = float(hi_box[a] - lo_box[a]) / res[a]
        # lattice centres, measured from the density's bbox_min
        p = float(lo_box[a] - grid.bbox_min[a]) + (np.arange(res[a]) + 0.5) * cell_l
        r = cell_l + reach
        lo_ix.append(np.clip(np.ceil((p - r) / cell_d - 0.5), 0, n).astype(np.int64))
        hi_ix.append(np.clip(np.floor((p + r) / cell_d - 0.5) + 1, 0, n).astype(np.int64))
    z0, y0, x0 = np.meshgrid(lo_ix[2], lo_ix[1], lo_ix[0], indexing="ij")
    z1, y1, x1 = np.meshgrid(hi_ix[2], hi_ix[1], hi_ix[0], indexing="ij")
    count = (sat[z1, y1, x1] - sat[z0, y1, x1] - sat[z1, y0, x1] - sat[z1, y1, x0]
             + sat[z0, y0, x1] + sat[z0, y1, x0] + sat[z1, y0, x0] - sat[z0, y0, x0])
    return (count > 0).ravel()



class NetworkSource:
    """The network's F_ms lattice for one volume: weights and pyramid on the device.

    ``fill`` makes the graded transmittance for the light (cached per light direction and
    density scale), gathers render-mode features (the weights' level combination baked by the
    gather) at an F_ms lattice and evaluates the network there: one evaluation per point for a
    grey albedo (``grey_shortcut``), else one per distinct non-zero channel albedo.
    ``fused`` (default ``FUSED_DEFAULT``): gather and network in one kernel
    (clvol/kernels/gather_mlp.py), else the gather's features through device memory to the
    network's kernel. ``device_medium``: the volume's DeviceMedium (clvol/kernels/medium.py),
    whose pyramid at the weights' base resolution is used; without one (tests, benchmarks)
    the pyramid is built from the grid alone (its level 0 is all that is uploaded).
    """

    def __init__(self, weights, grid, medium, runtime=None, fused: bool | None = None,
                 device_medium=None):
        from ...kernels.mlp import MlpKernel
        self.rt = runtime or get_runtime()
        self.weights = load_network_weights(weights)
        self.grid, self.medium = grid, medium
        self.mlp = MlpKernel(self.weights, self.rt)
        self.base = int(self.weights.contract["base_resolution"])
        self.lam = float(self.weights.contract["lambda"])
        self.pyramid = self._pyramid(grid, device_medium)
        self._graded = {}          # (direction, density scale) -> GradedT, oldest first
        self.graded_keep = 1
        self.graded_builds = 0
        self.fused = FUSED_DEFAULT if fused is None else bool(fused)
        # The frame's planned programs (FramePlan.device_programs; the owner sets them each
        # frame): the fused kernel is built with their "gather_mlp" defines. None: formed
        # by the kernel wrappers (tests, benchmarks).
        self.programs: dict | None = None

    def _pyramid(self, grid, device_medium):
        if device_medium is None:
            from ...kernels.pyramid import build_pyramid
            return build_pyramid(grid, self.base, self.rt)
        if device_medium.grid is not grid:
            raise ClvolError("NetworkSource: the device medium holds another grid")
        return device_medium.pyramid(self.base)

    def set_grid(self, grid, device_medium=None) -> None:
        """A new density for the same weights (Renderer.set_density): the pyramid is the new
        medium's (or rebuilt) and the graded transmittance dropped; the weights and kernels
        stay."""
        self.grid = grid
        self.pyramid = self._pyramid(grid, device_medium)
        self._graded = {}

    def graded(self, light_dir, density_scale=None):
        """The graded transmittance toward ``light_dir`` (the last ``graded_keep`` directions
        are kept: the sky's network source asks for the same few on every camera move)."""
        from ...kernels.transmittance import check_light_dir, graded_transmittance
        l = check_light_dir(light_dir)
        s = float(self.medium.density_scale if density_scale is None else density_scale)
        key = (tuple(l), s)
        if key not in self._graded:
            while len(self._graded) >= max(1, self.graded_keep):
                self._graded.pop(next(iter(self._graded)))      # the oldest
            self._graded[key] = graded_transmittance(self.pyramid, s, l, lam=self.lam)
            self.graded_builds += 1
        return self._graded[key]

    def fill(self, light_dir, resolution=DEFAULT_NETWORK_RESOLUTION, bbox_min=None,
             bbox_max=None, grey_shortcut: bool = True, medium=None, origin=None, active=None,
             omegas=None):
        """(FmsLattice, info): F_ms at the lattice (``ms_lattice``) for the camera at ``origin``
        and a light toward ``light_dir``; info has seconds
        "light" (graded fields), "gather", "network", "evaluations" (network evaluations
        per lattice point) and "points" (lattice points evaluated). ``active``: a boolean
        mask over the lattice points ([z][y][x] order); the others get F_ms = 0. ``omegas``:
        one unit direction (3,) for every point instead of toward the camera."""
        medium = self.medium if medium is None else medium
        if bbox_min is None or bbox_max is None:
            bbox_min, bbox_max = self.grid.bbox_min, self.grid.bbox_max
        if origin is None and omegas is None:
            raise ClvolError("NetworkSource.fill: give the camera's origin (or omegas)")
        res, lo, hi, pts_all, om_all = ms_lattice(None, resolution, bbox_min, bbox_max,
                                                  (0.0, 0.0, 0.0) if omegas is not None else origin)
        if omegas is not None:
            om_all = np.broadcast_to(np.asarray(omegas, np.float64), om_all.shape)
        if active is None:
            active = np.ones(len(pts_all), bool)
        active = np.asarray(active, bool).ravel()
        out, info = self.evaluate(pts_all[active], om_all[active], light_dir, medium,
                                  grey_shortcut)
        grey = out.ndim == 1
        full = np.zeros((len(pts_all),) + out.shape[1:], np.float32)
        full[active] = out
        vals = full.reshape((res[2], res[1], res[0]) + (() if grey else (3,)))
        return check_fms_lattice(FmsLattice(vals, tuple(lo), tuple(hi))), info

    def fill_device(self, light_dir, resolution=DEFAULT_NETWORK_RESOLUTION, bbox_min=None,
                    bbox_max=None, grey_shortcut: bool = True, medium=None, origin=None,
                    active=None, out: DeviceArray | None = None):
        """(lattice, (bbox_min, bbox_max), info): ``fill``'s F_ms on the device, in the ray
        marcher's layout: a (C, gz, gy, gx) float32 DeviceArray of planes, C = 1 for a grey
        albedo with the shortcut else 3, 0 at the points not ``active``. ``out``: the
        caller's lattice to overwrite when it has that shape, else a new one is made. On the
        fused path the kernel writes each active point's F_ms straight into it (at the
        point's flat lattice index) and nothing is read back but a 4-byte non-finite flag
        (checked: no silent NaN); on the unfused path the values come from ``fill`` and are
        written into it from the host."""
        medium = self.medium if medium is None else medium
        if bbox_min is None or bbox_max is None:
            bbox_min, bbox_max = self.grid.bbox_min, self.grid.bbox_max
        if origin is None:
            raise ClvolError("NetworkSource.fill_device: give the camera's origin")
        rt = self.rt
        res, lo, hi, pts_all, om_all = ms_lattice(None, resolution, bbox_min, bbox_max, origin)
        grey = grey_shortcut and medium.is_grey
        shape = (1 if grey else 3, res[2], res[1], res[0])
        if out is None or tuple(out.shape) != shape or out.runtime is not rt:
            out = rt.alloc(shape)
        if not self.fused:
            g, info = self.fill(light_dir, resolution, bbox_min, bbox_max, grey_shortcut,
                                medium, origin, active)
            rt.write(out, g.planes(), label="F_ms lattice (unfused path)")
            return out, (tuple(lo), tuple(hi)), info
        n = len(pts_all)
        idx = (np.arange(n) if active is None else
               np.flatnonzero(np.asarray(active, bool).ravel()))
        rt.zero(out)
        flag = rt.alloc(1, np.int32, zero=True)
        _, info = self._evaluate(pts_all[idx], om_all[idx], light_dir, medium, grey, out=out,
                                 out_index=idx, nonfinite=flag)
        if flag.read(label="network non-finite flag")[0]:
            raise ClvolError(f"{self.weights.path}: the network produced non-finite F_ms")
        return out, (tuple(lo), tuple(hi)), info

    def evaluate(self, pts, om, light_dir, medium=None, grey_shortcut: bool = True):
        """(F_ms, info) at world points ``pts`` (N, 3) toward unit directions ``om`` (N, 3)
        for a light toward ``light_dir``: float32 (N,) for a grey albedo with the shortcut,
        else (N, 3); >= 0 (the network's rare negative outputs are clipped). info: seconds
        "light", "gather", "network", "evaluations" (per point) and "points"; on the fused
        path (``self.fused``) "network" holds the gather's time too and "gather" is 0."""
        medium = self.medium if medium is None else medium
        out, info = self._evaluate(pts, om, light_dir, medium,
                                   grey_shortcut and medium.is_grey)
        if not np.all(np.isfinite(out)):
            raise ClvolError(f"{self.weights.path}: the network produced non-finite F_ms")
        return np.maximum(out, 0.0), info

    def _evaluate(self, pts, om, light_dir, medium, grey: bool, out=None, out_index=None,
                  nonfinite=None):
        """evaluate's work: (F_ms, info) with F_ms on the host, or (None, info) with ``out``
        (fused path only): F_ms of point i written into the device lattice ``out`` at
        ``out_index[i]`` of each plane (clvol/kernels/gather_mlp.py), non-finite values
        flagged in ``nonfinite``."""
        from ...kernels.gather import gather
        from ...kernels.gather_mlp import gather_mlp
        from ...kernels.transmittance import check_light_dir
        rt = self.rt
        pts = np.asarray(pts, np.float64).reshape(-1, 3)
        om = np.asarray(om, np.float64).reshape(-1, 3)
        alb = np.asarray(medium.albedo, np.float64)
        l = check_light_dir(light_dir)
        info = {"light": 0.0, "gather": 0.0, "network": 0.0}
        with Stopwatch() as sw:
            graded = self.graded(l, medium.density_scale)
            rt.finish()
        info["light"] = sw.seconds
        host = out is None
        if host:
            out = np.zeros((len(pts),) if grey else (len(pts), 3), np.float32)
        elif not self.fused:
            raise ClvolError("NetworkSource: device output needs the fused kernel")
        reuse = None
        if self.fused:
            for i in range(0, len(pts), FUSED_CHUNK):
                sl = slice(i, i + FUSED_CHUNK)
                args = (self.mlp, self.pyramid, graded, pts[sl], om[sl], l, medium,
                        float(alb[0]), self.weights.level_weights, self.weights.level_bias,
                        None if grey else alb)   # grey: the config's albedo is the medium's
                planned = None if self.programs is None else self.programs["gather_mlp"]
                with Stopwatch() as sw:
                    if host:
                        out[sl] = gather_mlp(*args, defines=planned)
                    else:
                        gather_mlp(*args, out=out, out_index=out_index[sl], nonfinite=nonfinite,
                                   defines=planned)
                        rt.finish()
                info["network"] += sw.seconds
        else:
            for i in range(0, len(pts), NETWORK_CHUNK):
                sl = slice(i, i + NETWORK_CHUNK)
                with Stopwatch() as sw:
                    g = gather(self.pyramid, graded, pts[sl], om[sl], l, medium, float(alb[0]),
                               mode="render", level_weights=self.weights.level_weights,
                               bias=self.weights.level_bias, as_buffers=True, reuse=reuse)
                    rt.finish()
                info["gather"] += sw.seconds
                reuse = g
                with Stopwatch() as sw:
                    if grey:     # the config's albedo is the medium's: one evaluation per point
                        out[sl] = self.mlp.forward(g["features"], g["config"], decode=True, n=g["n"])
                    else:        # one per distinct non-zero channel albedo (the kernel dedupes)
                        out[sl] = self.mlp.forward(g["features"], g["config"], channel_albedo=alb,
                                                   decode=True, n=g["n"])
                info["network"] += sw.seconds
        info["evaluations"] = 1 if grey else len(set(float(a) for a in alb if a > 0))
        info["points"] = int(len(pts))
        return (out if host else None), info


# The options every network-backed source reads (this module's and view.py's).
WEIGHTS_OPTION = option(
    "--weights", metavar="FILE.npz",
    help="network weight file of the network sources (network, view, stochastic, "
         "progressive; default: the shipped model, clvol/data/weights/full_albedo.npz)")
DOMAIN_FALLBACK_OPTION = option(
    "--no-domain-fallback", dest="domain_fallback", action="store_false",
    help="use the network even for a scene outside the domain its weight file was trained "
         "on (default: warn and use the measured fallback, docs/raymarch.md)")


class NetworkMs(LatticeMs):
    """The network's lattice marched like a precomputed grid. The lattice depends on the
    camera position (omega toward it), the light direction and the medium; ``prepare``
    refills it only when one of those changed."""
    name = "network"
    summary = "the trained network on a world lattice"
    uses_network = True
    bundle_supported = True            # the C host's network on the world lattice
    options = (
        WEIGHTS_OPTION,
        option("--ms-resolution", type=int, default=DEFAULT_NETWORK_RESOLUTION,
               help=f"F_ms lattice points per side filled by the network (default "
                    f"{DEFAULT_NETWORK_RESOLUTION})"),
        option("--ms-directions", type=int, default=0, metavar="K",
               help="network: fill F_ms at K fixed directions per lattice point once per "
                    "light and blend them for each camera (camera motion then costs no "
                    "network evaluation; 0 = a lattice per camera position, default)"),
        option("--ms-refresh", type=int, default=1, metavar="K",
               help="network: when only the camera moves, refill 1/K of the lattice per "
                    "frame (interleaved; the rest keeps earlier positions' values until "
                    "its turn; default 1 = all of it)"),
        DOMAIN_FALLBACK_OPTION,
    )

    @classmethod
    def choose_for(cls, medium, options, volume, domain) -> SourceChoice:
        """Single scattering alone in an optically thin medium (THIN_OPTICAL_THICKNESS, unless
        shortcuts are off) and the measured fallback outside the weights' training domain
        (``fallback_for``, unless ``domain_fallback`` is off); this source otherwise, and
        when the volume or the domain is not known (no judgement)."""
        configured = cls.name
        use_fallback = options["domain_fallback"]
        if volume is None or domain is None:
            return SourceChoice(configured)
        ot = volume.max_optical_thickness * medium.density_scale
        if ot < THIN_OPTICAL_THICKNESS and options["shortcuts"]:
            return SourceChoice(MsSource.name, thin=ot, thin_reason=(
                f"multiple scattering (optically thin: largest optical thickness "
                f"{ot:.3g} < {THIN_OPTICAL_THICKNESS:g}, where single "
                f"scattering alone measured as accurate; docs/raymarch.md)"))
        out = outside_domain(domain, medium, ot)
        if not out:
            return SourceChoice(configured)
        alt = fallback_for(medium) if use_fallback else None
        what = ("the network is used all the same (--no-domain-fallback)" if not use_fallback else
                "the network is used all the same (measured better than the analytic sources "
                "there)" if alt is None else f"multiple scattering from --ms {alt} instead")
        msg = (f"scene outside the network's training domain ({'; '.join(out)}): {what} "
               f"(docs/raymarch.md)")
        return SourceChoice(alt or configured, warning=msg)

    lattice_points_per_launch = NETWORK_CHUNK

    def network_weights(self):
        return load_network_weights(self.weights_path)

    @classmethod
    def domain_rules(cls) -> dict:
        return {"thin_optical_thickness": THIN_OPTICAL_THICKNESS,
                "backward_limit": BACKWARD_LIMIT, "backward_albedo": BACKWARD_ALBEDO}

    @classmethod
    def outside_training_domain(cls, domain: dict, medium) -> list[str]:
        return outside_domain(domain, medium)

    @classmethod
    def active_points(cls, grid, resolution, reach: float, box=None):
        return lattice_reach_mask(grid, resolution, reach, box=box)

    @classmethod
    def network_programs(cls, medium, shortcuts: bool, weights, fused: bool | None = None):
        """The programs ``NetworkSource`` builds: the pyramid's sweeps (graded
        transmittance), the gather's bake, and the gather with the network (fused, as
        ``FUSED_DEFAULT``) or apart; one colour plane for a grey medium with shortcuts."""
        from ...kernels import gather as kg
        from ...kernels import mlp as km
        from ...kernels.pyramid import n_levels
        from ...kernels.transmittance import sweep_programs
        base = int(weights.contract["base_resolution"])
        channels = 1 if shortcuts and medium.is_grey else 3
        gather = kg.program_defines(base, kg._lobes(medium), render=True)
        mlp = km.kernel_defines(weights.arch, channels, True)
        programs = dict(sweep_programs([base >> lv for lv in range(n_levels(base))]),
                        gather_bake={})
        if FUSED_DEFAULT if fused is None else fused:
            programs["gather_mlp"] = dict(gather, **mlp)
            return programs, {"gather_mlp": dict(kg.POCL_DEFINES, **km.POCL_DEFINES)}
        programs.update(gather=gather, mlp=mlp)
        return programs, {"gather": dict(kg.POCL_DEFINES), "mlp": dict(km.POCL_DEFINES)}

    @classmethod
    def sky_evaluator(cls, weights, grid, medium, runtime, device_medium):
        return NetworkSource(shipped_weights() if weights is None else weights, grid, medium,
                             runtime, device_medium=device_medium)

    @classmethod
    def network_reach(cls, volume, step_voxels: float) -> float:
        """The network's active-point reach for this step (``lattice_reach``)."""
        return lattice_reach(volume.grid, step_voxels)

    @classmethod
    def lattice_reach_for(cls, volume, step_voxels: float) -> float:
        return cls.network_reach(volume, step_voxels)

    @property
    def label(self) -> str:
        from pathlib import Path
        return f"network multiple scattering (weights {Path(str(self.weights_path)).name})"

    what = "network-filled F_ms lattice"

    def __init__(self, weights=None, ms_resolution=DEFAULT_NETWORK_RESOLUTION, runtime=None,
                 directions: int = 0, refresh: int = 1):
        super().__init__(None, runtime)
        if isinstance(directions, bool) or not isinstance(directions, (int, np.integer)) or \
                not (directions == 0 or 6 <= directions <= 256):
            raise ClvolError(f"raymarch option ms_directions = {directions!r}: 0 (a lattice per "
                             f"camera position) or an integer from 6 to 256")
        self.directions = int(directions)
        self._table = None
        if isinstance(refresh, bool) or not isinstance(refresh, (int, np.integer)) or \
                not 1 <= refresh <= 64:
            raise ClvolError(f"raymarch option ms_refresh = {refresh!r}: an integer from 1 (the "
                             f"whole lattice every camera position) to 64")
        self.refresh, self._phase, self._todo = int(refresh), 0, 0
        self.resolution = check_ms_resolution(ms_resolution)
        self._init_network(weights)

    def _init_network(self, weights) -> None:
        """The state every network-backed source keeps (this one and view.py's)."""
        self.weights_path = shipped_weights() if weights is None else weights
        self.net: NetworkSource | None = None
        self.lattice = None       # (DeviceArray (C, gz, gy, gx), box): the device-filled lattice
        self.info = None
        self.setup_seconds = 0.0
        self._key = None

    def _ensure_network(self, frame) -> None:
        """Weights and pyramid on the device for the frame's volume (once per volume; the
        pyramid is the frame's DeviceMedium's); the header's setup seconds are this frame's
        (0 when an earlier frame did it)."""
        self.setup_seconds = 0.0
        if self.net is None or self.net.grid is not frame.grid:
            dm = frame.device_medium
            dm = dm if dm is not None and dm.grid is frame.grid else None
            with Stopwatch() as sw:
                if self.net is None:
                    self.net = NetworkSource(self.weights_path, frame.grid, frame.medium,
                                             frame.runtime, device_medium=dm)
                    frame.count("network_setup")
                else:                    # a new density (Renderer.set_density): same weights
                    self.net.set_grid(frame.grid, dm)
                    frame.count("network_pyramid")
                frame.runtime.finish()
            self.setup_seconds = sw.seconds
            self._key = None
        self.net.programs = frame.programs

    @classmethod
    def from_options(cls, o, runtime=None) -> "NetworkMs":
        r = cls.read(o, "ms_resolution")
        cls.read(o, "domain_fallback")  # read by plan_frame for every network source
        return cls(cls.read(o, "weights"), DEFAULT_NETWORK_RESOLUTION if r is None else r,
                   runtime, cls.read(o, "ms_directions"), cls.read(o, "ms_refresh"))

    def training_domain(self) -> dict:
        """The validity domain the weight file records (clvol/features/weights.py); loading it
        also checks the file against this gather's contract."""
        from ...features.weights import weights_domain
        return weights_domain(load_network_weights(self.weights_path).meta)

    def prepare(self, frame) -> None:
        self.count = frame.count
        # The header's seconds.* are this frame's costs: 0 for work an earlier frame did.
        if self.info:
            self.info = dict(self.info, light=0.0, gather=0.0, network=0.0,
                             **({"interpolate": 0.0} if "interpolate" in self.info else {}))
        self._ensure_network(frame)
        key = frame.key                 # None (no plan): what the lattice depends on is unknown
        if key is not None and key == self._key and not self._todo:
            return
        active = None
        if frame.reach is not None:     # the plan's active-point rule (shortcuts on)
            mkey = ("network_active", self.resolution, frame.reach)
            dm = frame.device_medium
            cache = dm.cache if dm is not None else {}
            if mkey not in cache:
                cache[mkey] = lattice_reach_mask(frame.grid, self.resolution, frame.reach)
            active = cache[mkey]
        builds = self.net.graded_builds
        if self.directions:
            self._prepare_directional(frame, key[1:], active)
        else:
            self._prepare_lattice(frame, key, active)
        if self.net.graded_builds != builds:
            frame.count("graded_transmittance")
        self._key = key

    def _prepare_lattice(self, frame, key, active) -> None:
        """The lattice for the camera position: all of it when the light or the medium changed
        (or ``refresh`` is 1); else, when only the camera moved, one of ``refresh`` interleaved
        subsets of the active points per frame (the others keep the values of the positions
        they were last filled for), continuing at rest until every subset is current."""
        fill = dict(grey_shortcut=frame.shortcuts, medium=frame.medium,
                    origin=frame.camera.origin)
        light = frame.light.direction
        if self.refresh == 1:   # the default: the lattice stays on the device (no round trip)
            old = self.lattice[0] if self.lattice is not None else None
            planes, box, self.info = self.net.fill_device(light, self.resolution, active=active,
                                                          out=old, **fill)
            self.lattice, self.ms_lattice, self._todo = (planes, box), None, 0
        elif self._key is None or self.ms_lattice is None or key[1:] != self._key[1:]:
            self.ms_lattice, self.info = self.net.fill(light, self.resolution, active=active, **fill)
            self._todo = 0
        else:
            if key[0] != self._key[0]:           # the camera moved: every subset is stale
                self._todo = self.refresh
            part = self._phase % self.refresh
            self._phase += 1
            n = self.ms_lattice.values.shape[0] * self.ms_lattice.values.shape[1] * \
                self.ms_lattice.values.shape[2]
            idx = np.flatnonzero(active) if active is not None else np.arange(n)
            subset = np.zeros(n, bool)
            subset[idx[part::self.refresh]] = True
            g, self.info = self.net.fill(light, self.resolution, active=subset, **fill)
            vals = np.array(self.ms_lattice.values, np.float32, copy=True)
            flat, new = vals.reshape(n, -1), np.asarray(g.values).reshape(n, -1)
            flat[subset] = new[subset]
            self.ms_lattice = FmsLattice(vals, g.bbox_min, g.bbox_max)
            self._todo = max(self._todo - 1, 0)
        frame.count("ms_lattice")

    def _prepare_directional(self, frame, light_key, active) -> None:
        """View-independent cache: F_ms at ``directions`` fixed directions per lattice point,
        filled once per light and medium; each camera position then interpolates them toward
        omega (barycentric on the directions' spherical triangulation)."""
        self.lattice = None
        dirs = fibonacci_directions(self.directions)
        if self._table is None or self._table[0] != light_key:
            tables, info = [], None
            for d in dirs:
                g, i = self.net.fill(frame.light.direction, self.resolution,
                                     grey_shortcut=frame.shortcuts, medium=frame.medium,
                                     active=active, omegas=d)
                tables.append(np.asarray(g.values, np.float32))
                if info is None:
                    info = dict(i)
                else:
                    for k in ("light", "gather", "network"):
                        info[k] += i[k]
            self._table = (light_key, np.stack(tables), g.bbox_min, g.bbox_max, info)
            frame.count("ms_directional_fill")
            filled = True
        else:
            filled = False
        _, table, lo, hi, info = self._table
        with Stopwatch() as sw:
            _, _, _, _, om = ms_lattice(None, self.resolution, lo, hi, frame.camera.origin)
            flat = table.reshape(len(dirs), om.shape[0], -1)          # (K, N, C)
            vals = np.zeros(flat.shape[1:], np.float32)
            act = np.flatnonzero(active) if active is not None else np.arange(om.shape[0])
            idx, w = spherical_barycentric(dirs, om[act])
            vals[act] = (flat[idx, act[:, None]] * w[..., None]).sum(axis=1)   # (n, 3, C) -> (n, C)
            self.ms_lattice = FmsLattice(vals.reshape(table.shape[1:]), lo, hi)
        # This frame's costs: the K fills only when they ran, and the interpolation.
        self.info = dict(info) if filled else dict(info, light=0.0, gather=0.0, network=0.0)
        self.info["interpolate"] = sw.seconds
        frame.count("ms_lattice")

    @classmethod
    def key_for(cls, camera, light, medium, shortcuts: bool):
        """The lattice depends on the camera position (omega toward it; first, as the
        refresh mode reads it), the light direction and the medium."""
        return (tuple(camera.origin), tuple(light.direction), medium.density_scale,
                tuple(medium.albedo), medium.phase, bool(shortcuts))

    @classmethod
    def plan_for(cls, medium, camera, shortcuts: bool, options) -> MsPlan:
        """The lattice the network fills: one plane for a grey medium with shortcuts (one
        evaluation per point), else three."""
        res = check_ms_resolution(options.get("ms_resolution") or DEFAULT_NETWORK_RESOLUTION)
        res = (res,) * 3 if np.isscalar(res) else tuple(res)
        p = cls._grid_plan(bool(shortcuts and medium.is_grey), res[::-1])
        if medium.is_grey and shortcuts:
            p.skipped.append("network evaluations for colour channels 2 and 3 (grey albedo: "
                             "one per lattice point)")
        if shortcuts:
            p.skipped.append("network evaluations at lattice points with no density within "
                             "reach (their F_ms never reaches the image)")
        return p

    def device_data(self, medium, shortcuts: bool):
        """The lattice as the network filled it on the device (no host round trip), or the
        host-filled grid of the refresh and directional modes, uploaded."""
        if self.lattice is not None:
            planes, box = self.lattice
            return self._lattice_for(planes, medium, shortcuts), box
        return super().device_data(medium, shortcuts)

    def _lattice_for(self, planes: DeviceArray, medium, shortcuts: bool) -> DeviceArray:
        """The device lattice in the planes ``LatticeMs.device_data`` would give this medium: as
        filled (one plane exactly for a grey medium with shortcuts, as ``prepare`` fills it
        for the same frame), or a grey lattice repeated into three planes on the device."""
        if planes.shape[0] == 1 and not (shortcuts and medium.is_grey):
            rt = planes.runtime
            three = rt.alloc((3,) + tuple(planes.shape[1:]))
            for c in range(3):
                rt.copy(three, planes, dst_offset=c * planes.nbytes)
            return three
        return planes

    def header(self) -> dict:
        return {"raymarch.ms_resolution": str(self.resolution), **self._network_header()}

    def _network_header(self) -> dict:
        """The entries every network-backed source writes: weights, evaluations, time split."""
        info = self.info
        # Fused (the default), the gather runs inside the network's kernel and has no time of
        # its own: no seconds.gather (it read 0.0 in every header and the viewer), and
        # seconds.network is both, as network_fused says.
        fused = self.net.fused if self.net else FUSED_DEFAULT
        return {
            "raymarch.weights": str(self.net.weights.path) if self.net else str(self.weights_path),
            "raymarch.network_base_resolution": self.net.base if self.net else 0,
            "raymarch.network_evaluations_per_point": info["evaluations"] if info else 0,
            "raymarch.network_points": info["points"] if info else 0,
            "raymarch.network_fused": fused,
            "seconds.network_setup": round(self.setup_seconds, 4) if info else 0.0,
            "seconds.graded_transmittance": round(info["light"], 4) if info else 0.0,
            **({} if fused else {"seconds.gather": round(info["gather"], 4) if info else 0.0}),
            "seconds.network": round(info["network"], 4) if info else 0.0,
            **({"seconds.ms_interpolate": round(info["interpolate"], 4)}
               if info and "interpolate" in info else {}),
        }
