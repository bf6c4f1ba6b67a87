"""The ray-marching render method: exact single scattering plus a multiple-scattering source.

    clvol render examples/cloud.toml --method raymarch -o cloud.exr

or from Python::

    from clvol.raymarch import render_raymarch
    result = render_raymarch(load_scene("examples/cloud.toml"))          # RenderResult
    result.layers["total"], result.layers["alpha"], result.header["simulated"]

For many frames of one volume (a moving camera or light) keep a ``RayMarcher``: it holds
the density, its majorant grid and the light field on the device; ``set_light`` recomputes
the light field (the cost of a light change), ``march`` renders a camera.

Multiple-scattering sources (``ms``): ``"none"`` (single scattering only), ``"wrenninge"``
(octaves, the games' analytic approximation; the default), ``"grid"`` (a precomputed
``MsGrid`` of F_ms sampled trilinearly; ``fill_ms_grid`` builds one from any point estimator,
e.g. the path tracer's ``point_query``) and ``"network"`` (that lattice filled by the trained
network: template gather in render mode + the fused OpenCL MLP, ``NetworkSource``; weights
from ``--weights FILE.npz``, docs/neural.md).

The kernel is specialised to what the scene calls for (cl/raymarch.cl defines); the header
of the result lists what was simulated, what was skipped and why. ``shortcuts=False``
forces the general kernel (all lobes evaluated, three colour planes, light lookups even at
albedo 0): the tests check that every shortcut gives the same image. The method, its
accuracy and its speed are described in docs/raymarch.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import ClvolError
from .kernels.raymarch import LIGHT_QUANTITIES, MAX_OCTAVES, SOURCES, DeviceArray, raymarch
from .render import RenderResult
from .runtime import Stopwatch, get_runtime

DEFAULT_STEP = 1.0         # segment length in voxels of the density grid
DEFAULT_THRESHOLD = 1e-3   # early termination when T_cam falls below this
DEFAULT_BLOCK = 8          # voxels per majorant block per axis (empty-space skipping)
MAX_LIGHT_RESOLUTION = 256
MAX_SUPERSAMPLE = 8
MS_SOURCES = tuple(sorted(SOURCES)) + ("network",)   # "network" marches as a "grid" source
DEFAULT_NETWORK_RESOLUTION = 32   # F_ms lattice points per side filled by the network
NETWORK_CHUNK = 32768             # lattice points per gather + MLP launch (~100 MiB of features)


# --------------------------------------------------------------------------- options

@dataclass(frozen=True)
class Octaves:
    """Wrenninge octaves: F_ms = sum_{i=1}^{n-1} b^i f(mu; g c^i) T_light^(a^i).

    ``a`` multiplies the optical depth toward the light, ``b`` the contribution, ``c`` the
    phase eccentricity. Energy condition (Wrenninge et al.): an octave's contribution
    multiplier must not exceed its extinction multiplier, i.e. ``b <= a`` in this formula's
    letters (Wrenninge et al. and issue 6 write it "a <= b" with the roles of the letters
    swapped; docs/raymarch.md). Defaults a = b = c = 0.5, n = 3 satisfy it.
    """
    n: int = 3
    a: float = 0.5
    b: float = 0.5
    c: float = 0.5

    @property
    def energy_conserving(self) -> bool:
        return self.b <= self.a


@dataclass(frozen=True)
class MsGrid:
    """Precomputed F_ms (radiance per unit irradiance, orders >= 2) on a grid over a box.

    ``values``: float32 (gz, gy, gx, 3) RGB or (gz, gy, gx) grey, voxel centres at
    bbox_min + (i + 0.5) * cell like every clvol grid, read trilinearly (clamped). F_ms
    depends on the view direction: a grid made for one camera holds F_ms(x, omega(x)) with
    omega(x) = normalize(camera.origin - x) (``fill_ms_grid`` does this).
    """
    values: np.ndarray
    bbox_min: tuple
    bbox_max: tuple

    def planes(self) -> np.ndarray:
        """(C, gz, gy, gx) float32, C = 1 (grey) or 3: the kernel's layout."""
        v = np.asarray(self.values, np.float32)
        if v.ndim == 3:
            return v[None]
        return np.ascontiguousarray(np.moveaxis(v, -1, 0))


def _check_ms_grid(g) -> MsGrid:
    if not isinstance(g, MsGrid):
        raise ClvolError(f"ms grid: expected a clvol.raymarch.MsGrid, got {type(g).__name__}")
    v = np.asarray(g.values)
    if not (v.ndim == 3 or (v.ndim == 4 and v.shape[3] == 3)) or min(v.shape[:3]) < 1:
        raise ClvolError(f"ms grid: values of shape {v.shape}; expected (gz, gy, gx, 3) or (gz, gy, gx)")
    if not np.isfinite(v).all() or (v < 0).any():
        raise ClvolError("ms grid: values must be finite and >= 0 (F_ms is a radiance)")
    lo, hi = np.asarray(g.bbox_min, np.float64), np.asarray(g.bbox_max, np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or not np.all(hi > lo):
        raise ClvolError(f"ms grid: bbox_min {lo.tolist()} must be below bbox_max {hi.tolist()} on every axis")
    return g


def load_ms_grid(path) -> MsGrid:
    """An ``.npz`` with arrays ``values`` ((gz, gy, gx, 3) or (gz, gy, gx)), ``bbox_min``, ``bbox_max``."""
    try:
        with np.load(path) as z:
            missing = [k for k in ("values", "bbox_min", "bbox_max") if k not in z]
            if missing:
                raise ClvolError(f"{path}: ms grid file lacks array(s) {missing}; needs values, "
                                 f"bbox_min, bbox_max")
            return _check_ms_grid(MsGrid(z["values"].astype(np.float32),
                                         tuple(z["bbox_min"]), tuple(z["bbox_max"])))
    except (OSError, ValueError) as exc:
        raise ClvolError(f"{path}: cannot read ms grid ({exc})") from None


def fill_ms_grid(scene, resolution, query, bbox_min=None, bbox_max=None) -> MsGrid:
    """Fill an MsGrid for the scene's camera from a point estimator of F_ms.

    ``query(points (N, 3), omegas (N, 3)) -> (N, 3)`` returns F_ms for a light of irradiance 1
    (e.g. ``lambda p, w: point_query(scene, p, w, n_paths)["Fms"]``, or the network).
    The lattice is ``resolution`` (int or (gx, gy, gz)) voxel centres over the box
    (default: the volume's box); omega at each point is toward the camera.
    """
    res, lo, hi, pts, om = ms_lattice(scene, resolution, bbox_min, bbox_max)
    vals = np.asarray(query(pts, om), np.float64).reshape(res[2], res[1], res[0], 3)
    return _check_ms_grid(MsGrid(np.maximum(vals, 0.0).astype(np.float32), tuple(lo), tuple(hi)))


def ms_lattice(scene, resolution, bbox_min=None, bbox_max=None):
    """(res (gx, gy, gz), lo, hi, points (N, 3), omegas (N, 3)) of an F_ms lattice: voxel
    centres over the box (default: the volume's), [z][y][x] order, omega toward the camera."""
    res = (resolution,) * 3 if np.isscalar(resolution) else tuple(resolution)
    if len(res) != 3 or min(res) < 1:
        raise ClvolError(f"ms grid resolution {resolution!r}: give n or (gx, gy, gz), each >= 1")
    if bbox_min is None or bbox_max is None:
        g = scene.volume.load()
        bbox_min, bbox_max = g.bbox_min, g.bbox_max
    lo, hi = np.asarray(bbox_min, np.float64), np.asarray(bbox_max, np.float64)
    axes = [lo[a] + (np.arange(res[a]) + 0.5) * (hi[a] - lo[a]) / res[a] for a in range(3)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    pts = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    om = np.asarray(scene.camera.origin, np.float64) - pts
    om /= np.maximum(np.linalg.norm(om, axis=1, keepdims=True), 1e-30)
    return res, lo, hi, pts, om


def load_network_weights(path):
    """A weight file checked against the contract of the gather that will feed it: this
    code's layout and packaged templates (hash, level map) at the file's base resolution and
    lambda (the pyramid is built to match those). Raises WeightsError naming the field."""
    from .export import MlpWeights, gather_contract, load_weights, read_meta
    from .errors import WeightsError
    if isinstance(path, MlpWeights):
        path = path.path
    c = read_meta(path)["contract"]
    base, lam = c.get("base_resolution"), c.get("lambda")
    if not (isinstance(base, int) and 2 <= base <= 512 and base & (base - 1) == 0):
        raise WeightsError(f"{path}: [contract.base_resolution] = {base!r}: must be a power of two "
                           f"from 2 to 512")
    if not (isinstance(lam, (int, float)) and 0 < lam <= 1):
        raise WeightsError(f"{path}: [contract.lambda] = {lam!r}: must be in (0, 1]")
    return load_weights(path, expect_contract=gather_contract(base, float(lam)))


class NetworkSource:
    """The network as the ray marcher's F_ms source for one volume and medium.

    Holds the checked weights on the device (``MlpKernel``) and the density pyramid at the
    weights' base resolution; ``fill`` makes the graded transmittance for the light (cached per
    light direction), gathers render-mode features (the weights' level combination baked by the
    gather) at an F_ms lattice and evaluates the network there: one evaluation per point for a
    grey albedo (``grey_shortcut``), else one per distinct non-zero channel albedo.
    """

    def __init__(self, weights, grid, medium, runtime=None):
        from .kernels.mlp import MlpKernel
        from .kernels.pyramid import build_pyramid
        self.rt = runtime or get_runtime()
        self.weights = load_network_weights(weights)
        self.grid, self.medium = grid, medium
        self.mlp = MlpKernel(self.weights, self.rt)
        self.base = int(self.weights.contract["base_resolution"])
        self.lam = float(self.weights.contract["lambda"])
        self.pyramid = build_pyramid(grid, self.base, self.rt)
        self._graded = (None, None)

    def graded(self, light_dir):
        from .kernels.transmittance import graded_transmittance
        l = np.asarray(light_dir, np.float64) / np.linalg.norm(light_dir)
        if self._graded[0] is None or not np.array_equal(self._graded[0], l):
            self._graded = (l, graded_transmittance(self.pyramid, self.medium.density_scale, l,
                                                    lam=self.lam))
        return self._graded[1]

    def fill(self, scene, light_dir, resolution=DEFAULT_NETWORK_RESOLUTION, bbox_min=None,
             bbox_max=None, grey_shortcut: bool = True):
        """(MsGrid, info): F_ms at the lattice (``ms_lattice``) for the scene's camera and a
        light toward ``light_dir``; info has seconds "light" (graded fields), "gather",
        "network", and "evaluations" (network evaluations per lattice point)."""
        from .kernels.gather import gather
        rt = self.rt
        if bbox_min is None or bbox_max is None:
            bbox_min, bbox_max = self.grid.bbox_min, self.grid.bbox_max
        res, lo, hi, pts, om = ms_lattice(scene, resolution, bbox_min, bbox_max)
        alb = np.asarray(self.medium.albedo, np.float64)
        grey = grey_shortcut and self.medium.is_grey
        l = np.asarray(light_dir, np.float64) / np.linalg.norm(light_dir)
        info = {"light": 0.0, "gather": 0.0, "network": 0.0}
        with Stopwatch() as sw:
            graded = self.graded(l)
            rt.finish()
        info["light"] = sw.seconds
        out = np.zeros((len(pts),) if grey else (len(pts), 3), np.float32)
        reuse = None
        for i in range(0, len(pts), NETWORK_CHUNK):
            sl = slice(i, i + NETWORK_CHUNK)
            with Stopwatch() as sw:
                g = gather(self.pyramid, graded, pts[sl], om[sl], l, self.medium, float(alb[0]),
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
        vals = out.reshape((res[2], res[1], res[0]) + (() if grey else (3,)))
        if not np.all(np.isfinite(vals)):
            raise ClvolError(f"{self.weights.path}: the network produced non-finite F_ms")
        return _check_ms_grid(MsGrid(np.maximum(vals, 0.0), tuple(lo), tuple(hi))), info


def _check_options(ms, octaves: Octaves, step, threshold, block, light_resolution,
                   supersample, ms_grid):
    def bad(name, value, allowed):
        return ClvolError(f"raymarch option {name} = {value!r}: {allowed}")
    if ms not in MS_SOURCES:
        raise bad("ms", ms, f"choose one of {list(MS_SOURCES)}")
    if not (isinstance(octaves.n, (int, np.integer)) and 1 <= octaves.n <= MAX_OCTAVES):
        raise bad("octaves", octaves.n, f"must be an integer from 1 to {MAX_OCTAVES}")
    # a = 0 would make T^(a^i) = 1 behind any amount of medium: light through walls.
    for name, v, lo_open in (("ms_a", octaves.a, True), ("ms_b", octaves.b, False),
                             ("ms_c", octaves.c, False)):
        ok = math.isfinite(v) and (0 < v <= 1 if lo_open else 0 <= v <= 1)
        if not ok:
            raise bad(name, v, "must be in (0, 1]" if lo_open else "must be in [0, 1]")
    if not (math.isfinite(step) and 0.01 <= step <= 64):
        raise bad("step", step, "must be in [0.01, 64] voxels")
    if not (math.isfinite(threshold) and 0 <= threshold < 1):
        raise bad("threshold", threshold, "must be in [0, 1) (0 disables early termination)")
    if not (isinstance(block, (int, np.integer)) and block >= 1):
        raise bad("block", block, "must be an integer >= 1")
    if light_resolution is not None and not (
            isinstance(light_resolution, (int, np.integer)) and 1 <= light_resolution <= 1024
            and light_resolution & (light_resolution - 1) == 0):
        raise bad("light_resolution", light_resolution, "must be a power of two from 1 to 1024")
    if not (isinstance(supersample, (int, np.integer)) and 1 <= supersample <= MAX_SUPERSAMPLE):
        raise bad("supersample", supersample, f"must be an integer from 1 to {MAX_SUPERSAMPLE}")
    if ms == "grid":
        if ms_grid is None:
            raise ClvolError("raymarch option ms = 'grid' needs an ms grid (--ms-grid FILE.npz, "
                             "or ms_grid=MsGrid(...) in Python)")
        _check_ms_grid(ms_grid)


def shipped_weights():
    """The model that ships with clvol, trained on procedural clouds and solids (albedo
    0.8-0.999; how it was made and how well it does: clvol/data/weights/cloud_small.md)."""
    import importlib.resources
    from pathlib import Path
    return Path(str(importlib.resources.files("clvol") / "data" / "weights" / "cloud_small.npz"))


def _check_network_options(weights, ms_resolution):
    if weights is None:
        raise ClvolError("raymarch option ms = 'network' needs a weight file (--weights FILE.npz, "
                         "or weights=... in Python)")
    r = ms_resolution
    ok = (isinstance(r, (int, np.integer)) and 2 <= r <= 256) or (
        not np.isscalar(r) and len(r) == 3 and all(isinstance(v, (int, np.integer)) and 2 <= v <= 256
                                                   for v in r))
    if not ok:
        raise ClvolError(f"raymarch option ms_resolution = {r!r}: an integer (or three) from 2 to 256")


def auto_light_resolution(grid) -> int:
    """The light field's default resolution: twice the grid's largest side rounded up to a
    power of two, at most MAX_LIGHT_RESOLUTION. The voxelised light field is the ray
    marcher's main bias against exact single scattering (image mean of the cloud example
    2.5% dark at 1x, 0.7% at 2x; docs/raymarch.md); 2x costs ~0.5 s of resampling once per
    volume and ~0.1 s per light change at 256^3."""
    n = 2 * max(grid.resolution)
    return min(1 << max(0, (n - 1).bit_length()), MAX_LIGHT_RESOLUTION)


# --------------------------------------------------------------------------- the renderer

class RayMarcher:
    """A volume kept on the device for many frames: density, majorant grid, light field.

    ``grid``: clvol Grid; ``medium``: clvol Medium. The light field (T_light, or its optical
    depth with light_interp="optical_depth", on the pyramid's cube) is made by ``set_light``
    (the light-change cost).
    """

    def __init__(self, grid, medium, runtime=None, block: int = DEFAULT_BLOCK,
                 light_resolution: int | None = None, light_interp: str = "transmittance"):
        from .kernels.majorant import build_majorant_buffer
        self.rt = runtime or get_runtime()
        self.grid = grid
        self.medium = medium
        self.block = int(block)
        self.light_resolution = light_resolution or auto_light_resolution(grid)
        if light_interp not in LIGHT_QUANTITIES:
            raise ClvolError(f"raymarch option light_interp = {light_interp!r}: choose one of "
                             f"{list(LIGHT_QUANTITIES)}")
        self.light_interp = light_interp
        self.density = DeviceArray.upload(grid.density, self.rt)
        buf, shape = build_majorant_buffer(self.density.buffer, grid.density.shape, self.block,
                                           self.rt)
        self.majorant = DeviceArray(buf, shape)
        self._pyramid = None
        self.light_field = None
        self.light_dir = None

    @property
    def pyramid(self):
        """Density resampled to the light field's cube (built once, on first use)."""
        if self._pyramid is None:
            from .kernels.pyramid import build_pyramid
            self._pyramid = build_pyramid(self.grid, self.light_resolution, self.rt)
        return self._pyramid

    def set_light(self, light_dir) -> None:
        """(Re)compute the exact light field for a light toward ``light_dir``."""
        from .kernels.transmittance import light_transmittance
        pyr = self.pyramid
        buf = light_transmittance(pyr, self.medium.density_scale, light_dir,
                                  quantity=self.light_interp, as_buffer=True)
        n = pyr.base_resolution
        self.light_field = DeviceArray(buf, (n, n, n))
        self.light_dir = np.asarray(light_dir, np.float64) / np.linalg.norm(light_dir)

    def march(self, camera, light, *, ms: str = "wrenninge", octaves: Octaves = Octaves(),
              ms_grid: MsGrid | None = None, step: float = DEFAULT_STEP,
              threshold: float = DEFAULT_THRESHOLD, skip_empty: bool = True,
              shortcuts: bool = True, read_back: bool = True, stats: bool = False):
        """Render ``camera`` lit by ``light`` (its direction must be the one of ``set_light``
        unless nothing is lit). Returns (layers, plan) with plan = the ``Plan`` used, or with
        ``read_back=False`` (event, buffers, plan)."""
        plan = Plan.make(self.medium, light, ms, octaves, ms_grid, shortcuts)
        if plan.lit:
            if self.light_field is None or not np.allclose(
                    self.light_dir, np.asarray(light.direction) / np.linalg.norm(light.direction),
                    rtol=0, atol=1e-12):
                self.set_light(light.direction)
        g = self.grid
        fwd, right, up = camera.basis()
        cube_min = self.pyramid.cube_min if plan.lit else np.zeros(3)
        cube_size = self.pyramid.cube_size if plan.lit else 1.0
        planes = plan.ms_planes
        res = raymarch(
            self.density, g.bbox_min, g.bbox_max, self.medium.density_scale,
            self.majorant, self.block,
            self.light_field if plan.lit else None, cube_min, cube_size,
            planes, *(plan.ms_box if planes is not None else (None, None)),
            camera.origin, fwd, right, up, math.tan(math.radians(camera.fov_y) / 2),
            camera.width, camera.height,
            light.direction, light.irradiance, self.medium.albedo, plan.lobes,
            plan.background, source=plan.source, octaves=octaves.n, a=octaves.a, b=octaves.b,
            c=octaves.c, step=step * float(np.min(g.cell_size)), threshold=threshold,
            skip_empty=skip_empty, lit=plan.lit, light_quantity=self.light_interp,
            runtime=self.rt, read_back=read_back, stats=stats)
        if read_back:
            return res, plan
        return res + (plan,)


@dataclass(frozen=True)
class Plan:
    """What the kernel simulates for a scene, and which shortcuts it takes (with reasons)."""
    lit: bool
    source: str
    lobes: list
    ms_planes: np.ndarray | None
    ms_box: tuple | None
    background: tuple
    simulated: tuple
    skipped: tuple
    channels: int = 1

    @classmethod
    def make(cls, medium, light, ms, octaves, ms_grid, shortcuts=True) -> "Plan":
        sim, skip = [], []
        ae = np.asarray(medium.albedo) * np.asarray(light.irradiance)
        lit = bool(np.any(ae > 0)) or not shortcuts
        phase = medium.phase
        lobes = [(lo.g, lo.weight) for lo in phase.lobes]
        if lit:
            sim.append("single scattering")
        else:
            skip.append("single and multiple scattering (albedo * irradiance = 0: no light "
                        "field, no source)")
        if shortcuts and phase.is_isotropic:
            lobes = []
            skip.append("phase evaluation (isotropic: constant 1/(4 pi))")
        source = ("grid" if ms == "network" else ms) if lit else "none"
        planes = box = None
        if lit and ms == "none":
            skip.append("multiple scattering (--ms none)")
        elif lit and ms == "wrenninge":
            if octaves.n > 1:
                sim.append(f"multiple scattering (Wrenninge octaves n={octaves.n} a={octaves.a:g} "
                           f"b={octaves.b:g} c={octaves.c:g})")
            else:
                skip.append("multiple scattering (Wrenninge with 1 octave: single only)")
        elif lit and ms in ("grid", "network"):
            planes = ms_grid.planes()
            grey_grid = planes.shape[0] == 1 or (np.array_equal(planes[0], planes[1])
                                                 and np.array_equal(planes[0], planes[2]))
            if shortcuts and grey_grid and medium.is_grey:
                planes = np.ascontiguousarray(planes[:1])
                skip.append("colour channels 2 and 3 of the F_ms grid (grey albedo, grey grid)")
            elif planes.shape[0] == 1:
                planes = np.ascontiguousarray(np.repeat(planes, 3, axis=0))
            gz, gy, gx = planes.shape[1:]
            what = "network-filled F_ms lattice" if ms == "network" else "precomputed F_ms grid"
            sim.append(f"multiple scattering ({what} {gx}x{gy}x{gz}, {planes.shape[0]} channel(s))")
            box = (tuple(ms_grid.bbox_min), tuple(ms_grid.bbox_max))
        channels = 1
        if planes is not None:
            channels = planes.shape[0]
        elif lit:
            skip.append("per-channel marching (albedo and irradiance are constant over the "
                        "medium: one colour-free march, colour applied once per ray)")
        env = light.environment
        if env is not None:
            sim.append("background (environment radiance behind the medium)")
            skip.append("environment in-scattering (the medium is lit by the sun only)")
        background = tuple(env) if env is not None else (0.0, 0.0, 0.0)
        sim.append("extinction along camera rays")
        return cls(lit, source, lobes, planes, box, background, tuple(sim), tuple(skip),
                   channels)


def render_raymarch(scene, *, ms: str = "wrenninge", octaves: int = 3, a: float = 0.5,
                    b: float = 0.5, c: float = 0.5, ms_grid: MsGrid | None = None,
                    step: float = DEFAULT_STEP, threshold: float = DEFAULT_THRESHOLD,
                    skip_empty: bool = True, block: int = DEFAULT_BLOCK,
                    light_resolution: int | None = None, light_interp: str = "transmittance",
                    supersample: int = 1, shortcuts: bool = True, grid=None,
                    runtime=None, weights=None,
                    ms_resolution=DEFAULT_NETWORK_RESOLUTION) -> RenderResult:
    """Render ``scene`` with the ray marcher. Returns a RenderResult with layers total,
    single, multiple (H, W, 3), alpha and depth (H, W), and the header.

    step: segment length in voxels of the density grid (smallest cell side);
    threshold: early termination transmittance (error < threshold x the largest source
    radiance along the ray); supersample: S x S rays per pixel on a regular sub-grid, box
    filtered (1 = pixel centres); grid: the loaded volume (else ``scene.volume.load()``).
    ms="network": ``weights`` (a weight file path) fills an F_ms lattice of ``ms_resolution``
    points per side for this camera and light (``NetworkSource``), which is then marched like
    ms="grid"; the header splits the time into gather, network and march.
    """
    oct_ = Octaves(int(octaves) if isinstance(octaves, (int, np.integer)) else octaves,
                   float(a), float(b), float(c))
    _check_options(ms, oct_, float(step), float(threshold), block, light_resolution,
                   supersample, ms_grid if ms != "network" else None)
    if ms == "network":
        weights = shipped_weights() if weights is None else weights
        _check_network_options(weights, ms_resolution)
    with Stopwatch() as sw_total:
        with Stopwatch() as sw_load:
            grid = grid if grid is not None else scene.volume.load()
        rm = RayMarcher(grid, scene.medium, runtime, block, light_resolution, light_interp)
        cam = scene.camera
        if supersample > 1:
            from dataclasses import replace
            cam = replace(cam, width=cam.width * supersample, height=cam.height * supersample)
        net_info = None
        if ms == "network":
            lit = bool(np.any(np.asarray(scene.medium.albedo) * np.asarray(scene.light.irradiance) > 0))
            if lit or not shortcuts:
                with Stopwatch() as sw_setup:
                    src = NetworkSource(weights, grid, scene.medium, rm.rt)
                    rm.rt.finish()
                ms_grid, net_info = src.fill(scene, scene.light.direction, ms_resolution,
                                             grey_shortcut=shortcuts)
                net_info["setup"] = sw_setup.seconds
            else:   # nothing is lit: the plan skips the source; an empty grid stands in
                ms_grid = MsGrid(np.zeros((1, 1, 1), np.float32), tuple(grid.bbox_min),
                                 tuple(grid.bbox_max))
        plan = Plan.make(scene.medium, scene.light, ms, oct_, ms_grid, shortcuts)
        with Stopwatch() as sw_light:
            if plan.lit:
                rm.set_light(scene.light.direction)
                rm.rt.finish()
        with Stopwatch() as sw_march:
            layers, plan = rm.march(cam, scene.light, ms=ms, octaves=oct_, ms_grid=ms_grid,
                                    step=step, threshold=threshold, skip_empty=skip_empty,
                                    shortcuts=shortcuts)
        if supersample > 1:
            layers = downsample(layers, supersample)
    cell = float(np.min(grid.cell_size))
    header = {
        "simulated": "; ".join(plan.simulated),
        "skipped": "; ".join(plan.skipped) or "nothing",
        "seconds": round(sw_total.seconds, 4),
        "seconds.load": round(sw_load.seconds, 4),
        "seconds.light_field": round(sw_light.seconds, 4),
        "seconds.march": round(sw_march.seconds, 4),
        "raymarch.ms": ms,
        "raymarch.step_voxels": float(step),
        "raymarch.step": step * cell,
        "raymarch.threshold": float(threshold),
        "raymarch.skip_empty": bool(skip_empty),
        "raymarch.block": int(block),
        "raymarch.light_resolution": int(rm.light_resolution) if plan.lit else 0,
        "raymarch.light_interp": light_interp,
        "raymarch.supersample": int(supersample),
        "raymarch.channels_marched": plan.channels,
        "raymarch.shortcuts": bool(shortcuts),
        "device": rm.rt.entry.label,
    }
    if ms == "network":
        w = src.weights if net_info is not None else None
        if net_info is not None and scene.medium.is_grey and shortcuts:
            extra = "network evaluations for colour channels 2 and 3 (grey albedo: one per lattice point)"
            header["skipped"] = extra if header["skipped"] == "nothing" else header["skipped"] + "; " + extra
        header.update({
            "raymarch.weights": str(w.path) if w else "",
            "raymarch.ms_resolution": str(ms_resolution),
            "raymarch.network_base_resolution": src.base if w else 0,
            "raymarch.network_evaluations_per_point": net_info["evaluations"] if net_info else 0,
            "seconds.network_setup": round(net_info["setup"], 4) if net_info else 0.0,
            "seconds.graded_transmittance": round(net_info["light"], 4) if net_info else 0.0,
            "seconds.gather": round(net_info["gather"], 4) if net_info else 0.0,
            "seconds.network": round(net_info["network"], 4) if net_info else 0.0,
        })
    if ms == "wrenninge":
        header.update({"raymarch.octaves": oct_.n, "raymarch.ms_a": oct_.a,
                       "raymarch.ms_b": oct_.b, "raymarch.ms_c": oct_.c,
                       "raymarch.energy_condition_b_le_a": oct_.energy_conserving})
    return RenderResult(layers, header)


def downsample(layers: dict, s: int) -> dict:
    """Box-filter S x S blocks of sub-pixel samples into pixels; depth is averaged with
    alpha weights (the mean distance of the extinction events in the whole pixel)."""
    def box(x):
        h, w = x.shape[0] // s, x.shape[1] // s
        return x.reshape((h, s, w, s) + x.shape[2:]).mean(axis=(1, 3), dtype=np.float64)
    out = {k: box(v).astype(np.float32) for k, v in layers.items() if k != "depth"}
    a = box(layers["alpha"])
    ad = box(layers["alpha"].astype(np.float64) * layers["depth"])
    out["depth"] = np.where(a > 0, ad / np.where(a > 0, a, 1.0), 0.0).astype(np.float32)
    return out


# --------------------------------------------------------------------------- CLI hooks

def add_arguments(group) -> None:
    group.add_argument("--ms", choices=list(MS_SOURCES), default="wrenninge",
                       help="multiple-scattering source: none (single only), wrenninge "
                            "(analytic octaves, default), grid (precomputed F_ms, --ms-grid), "
                            "network (trained network, --weights)")
    group.add_argument("--weights", metavar="FILE.npz",
                       help="network weight file for --ms network (default: the shipped "
                            "model, clvol/data/weights/cloud_small.npz)")
    group.add_argument("--ms-resolution", type=int, default=DEFAULT_NETWORK_RESOLUTION,
                       help=f"F_ms lattice points per side filled by the network (default "
                            f"{DEFAULT_NETWORK_RESOLUTION})")
    group.add_argument("--ms-grid", metavar="FILE.npz",
                       help="precomputed F_ms grid (arrays values, bbox_min, bbox_max) for --ms grid")
    group.add_argument("--octaves", type=int, default=3, help="Wrenninge octaves N (default 3)")
    group.add_argument("--ms-a", type=float, default=0.5,
                       help="octave extinction multiplier a (default 0.5)")
    group.add_argument("--ms-b", type=float, default=0.5,
                       help="octave contribution multiplier b (default 0.5; keep b <= a)")
    group.add_argument("--ms-c", type=float, default=0.5,
                       help="octave eccentricity multiplier c (default 0.5)")
    group.add_argument("--step", type=float, default=DEFAULT_STEP,
                       help=f"march step in voxels (default {DEFAULT_STEP:g})")
    group.add_argument("--threshold", type=float, default=DEFAULT_THRESHOLD,
                       help=f"stop a ray when its transmittance falls below this "
                            f"(default {DEFAULT_THRESHOLD:g}; 0 = never)")
    group.add_argument("--light-resolution", type=int, default=None,
                       help="light field resolution (power of two; default: twice the grid "
                            f"size rounded up to a power of two, at most {MAX_LIGHT_RESOLUTION})")
    group.add_argument("--light-interp", choices=list(LIGHT_QUANTITIES), default="transmittance",
                       help="what is blended trilinearly between light-field voxels: T "
                            "(default) or the optical depth (docs/raymarch.md)")
    group.add_argument("--supersample", type=int, default=1,
                       help="S x S rays per pixel (default 1)")
    group.add_argument("--no-skip-empty", action="store_true",
                       help="march through empty majorant blocks too (same image, slower)")
    group.add_argument("--no-shortcuts", action="store_true",
                       help="run the general kernel even where the scene allows a shortcut "
                            "(same image, slower; for testing)")


def render(scene, args) -> RenderResult:
    ms_grid = load_ms_grid(args.ms_grid) if getattr(args, "ms_grid", None) else None
    rt = get_runtime(getattr(args, "device", None), profiling=bool(getattr(args, "profile", False)))
    result = render_raymarch(
        scene, ms=args.ms, octaves=args.octaves, a=args.ms_a, b=args.ms_b, c=args.ms_c,
        ms_grid=ms_grid, step=args.step, threshold=args.threshold,
        skip_empty=not args.no_skip_empty, light_resolution=args.light_resolution,
        light_interp=args.light_interp,
        supersample=args.supersample, shortcuts=not args.no_shortcuts, runtime=rt,
        weights=getattr(args, "weights", None),
        ms_resolution=getattr(args, "ms_resolution", DEFAULT_NETWORK_RESOLUTION))
    if getattr(args, "profile", False):
        import sys
        print(rt.timing_report(), file=sys.stderr)
    return result
