"""Host wrapper for cl/pathtrace.cl: one launch = one batch of independent paths.

``PathTracer`` takes a volume on the device (a ``DeviceMedium``: density and majorant grid,
shared with the other methods, or uploaded here when none is given), picks the ``-D``
specialisation the scene allows, and runs render or query batches, returning the raw
per-path rows (layout ``ROW_*`` below) for the caller to average. Rendering policy
(progress, time budget, images, standard errors) lives in ``clvol/render/pathtrace.py``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import envmap as envmap_mod
from ..errors import ClvolError
from ..runtime import DeviceArray, get_runtime
from . import phase as kphase
from .constants import kernel_constant
from .grid import f4
from .majorant import DEFAULT_BLOCK, majorant_args
from .majorant import majorant_block as resolve_block
from .blocks import block_defines, light_block, medium_block
from .medium import DeviceMedium

# Per-path output row of the kernels (PT_OUT floats; the widths are cl/include/constants.h's).
ROW_BG, ROW_L1, ROW_LMS = slice(0, 3), slice(3, 6), slice(6, 9)
ROW_VERTICES, ROW_STEPS, ROW_TRUNCATED = 9, 10, 11
PT_OUT = kernel_constant("PT_OUT_NO_EMISSION")
# -D PT_EMISSION rows: 6 more floats, emission seen unscattered, then scattered (RGB each).
PT_OUT_EMISSION = kernel_constant("PT_OUT_EMISSION")
ROW_EM_DIRECT, ROW_EM_SCATTERED = slice(PT_OUT, PT_OUT + 3), slice(PT_OUT + 3, PT_OUT_EMISSION)
# ROW_TRUNCATED: 1 for a path cut at PT_MAX_VERTICES, 2 for one stopped by a tracking bound.
TRUNCATED_VERTICES, TRUNCATED_BOUND = 1, 2
# The tracking loop's bounds (cl/pathtrace.cl; docs/pathtrace.md, "Bounds"). MAX_STEPS
# tentative collisions a path: ~10 per vertex at the vertex limit (100,000), where the
# examples' paths take at most ~900 (48^2 x 4 spp, max per path; 47-53 on average for the
# clouds and milk) and a homogeneous medium's take one per vertex. MAX_STALLS in a row that
# each move t by less than STALL_FRACTION of the majorant block's smallest side: the medium's
# majorant then makes crossing one block a matter of millions of draws (or 1/sigma_maj is below
# t's float32 rounding and the flight never advances). A draw moves t by Exp(1)/sigma_maj, so
# where sigma_maj x block x STALL_FRACTION <= 1/2 (majorant optical depth per block <= 2^19)
# a stall has odds <= 0.4 and 256 in a row <= 1e-100: it never binds where flights progress.
MAX_STEPS, MAX_STALLS, STALL_FRACTION = 1 << 20, 256, 2.0 ** -20
BOUND_DEFINES = {"PT_MAX_STEPS": MAX_STEPS, "PT_MAX_STALLS": MAX_STALLS,
                 "PT_STALL_FRACTION": STALL_FRACTION}


def truncation_counts(rows) -> tuple[int, int]:
    """(paths cut at the vertex limit, paths stopped by a tracking bound) of rows [..., row]."""
    t = np.asarray(rows)[..., ROW_TRUNCATED]
    return int(np.count_nonzero(t == TRUNCATED_VERTICES)), int(np.count_nonzero(t == TRUNCATED_BOUND))


# Per-order rows (cl/pathtrace.cl -D PT_ORDER_BINS): exponents e = 1..ORDER_EXACT-1 one bin
# each, then ORDER_SUB bins per octave up to 2^ORDER_END_LOG2 - 1 (> the kernel's
# PT_MAX_VERTICES).
ORDER_EXACT, ORDER_EXACT_LOG2, ORDER_SUB, ORDER_END_LOG2 = (
    kernel_constant(f"PT_ORDER_{n}") for n in ("EXACT", "EXACT_LOG2", "SUB", "END_LOG2"))
ORDER_BINS = ORDER_EXACT - 1 + (ORDER_END_LOG2 - ORDER_EXACT_LOG2) * ORDER_SUB


def order_bin_ranges() -> np.ndarray:
    """[ORDER_BINS][2] int64: the first and last albedo exponent e of each bin (the kernel's
    pt_order_bin, inverted)."""
    lo, hi = [], []
    for e in range(1, ORDER_EXACT):
        lo.append(e)
        hi.append(e)
    for o in range(ORDER_EXACT_LOG2, ORDER_END_LOG2):
        width = (1 << o) // ORDER_SUB
        for s in range(ORDER_SUB):
            lo.append((1 << o) + s * width)
            hi.append((1 << o) + (s + 1) * width - 1)
    return np.stack([lo, hi], axis=1).astype(np.int64)

_MEDIUM_DTYPES = [None, None, np.int32, np.int32, np.int32, np.int32, np.int32, np.int32,
                  None, None, None, None, None, None]
_RENDER_DTYPES = _MEDIUM_DTYPES + [None, None, None, None, np.float32, np.int32, np.int32,
                                   np.uint64, np.uint32, np.int32, np.int32, None, None]
_QUERY_DTYPES = _MEDIUM_DTYPES + [None, None, np.int32, np.uint64, np.uint32, np.int32,
                                  np.int32, None, None]
# -D PT_ENVMAP: the map's buffers and numbers follow the medium arguments.
_ENVMAP_DTYPES = [None, None, None, np.int32, np.int32, np.float32, np.float32]
_ENV_TEST_DTYPES = _ENVMAP_DTYPES + [None, np.int32, None]
# -D PT_EMISSION: em, emx, emy, emz, em_min, em_max, em_colour (after the map's).
_EMISSION_DTYPES = [None, np.int32, np.int32, np.int32, None, None, None]
# Paths side by side per work-item (cl/pathtrace.cl PT_LANES), measured best on PoCL/AVX-512
# (docs/pathtrace.md): 8 for images; 16 for point queries, whose long paths spend more of
# their time in the per-vertex code that 16 lanes share better.
# At most the device's LANES (Runtime.lanes, cl/include/lanes.h): see path_lanes.
RENDER_LANES, QUERY_LANES = 8, 16


def path_lanes(rt, want: int) -> int:
    """PT_LANES on ``rt``'s device: ``want`` (RENDER_LANES or QUERY_LANES), capped at the
    device's lane width (a CPU without AVX-512 gets no 16-wide vector in a call)."""
    return min(int(want), int(rt.lanes))


# A lat-long map of radiance 1 everywhere (2:1, the smallest with a texel per hemisphere row).
UNIFORM_MAP = np.ones((2, 4, 3), np.float32)
UNIFORM_MAP.setflags(write=False)


@dataclass
class PathMedium:
    """What the path-tracing kernels simulate: the density over its box, the scene's
    ``medium`` (a clvol.scene.Medium, its optical properties, passed whole and packed by
    clvol/kernels/blocks.py medium_block), the ``light`` (a clvol.scene.Light, passed whole:
    the sun's direction and irradiance, packed by light_block; a zero irradiance: no sun),
    the sky and the limits.
    ``environment`` None for none; ``max_order`` None for unlimited. ``env_map``: a lat-long
    map (H, W, 3) (clvol/envmap.py; exclusive with ``environment``) times ``env_scale``,
    turned by ``env_rotation`` degrees about +y; None for none."""
    density: np.ndarray
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    medium: object
    light: object
    environment: tuple | None = None
    max_order: int | None = None
    extra_defines: dict = field(default_factory=dict)
    env_map: np.ndarray | None = None
    env_scale: tuple = (1.0, 1.0, 1.0)
    env_rotation: float = 0.0
    emission: object = None     # an EmissionGrid (clvol/emission.py), or None

    def __post_init__(self):
        # A path collects a constant sky only when it escapes after phase sampling, which the
        # vertex max_order never does: that order's sky light would be lost (an order-1
        # render showed no sky-lit medium at all). As a uniform map the sky is sampled at
        # every vertex, the last one included (cl/pathtrace.cl), and a uniform map renders
        # the constant sky (tests/test_envmap.py). Done here, so that every caller (and the
        # twin, built from this object) gets it.
        if (self.max_order is not None and self.env_map is None
                and self.environment is not None and max(self.environment) > 0):
            self.env_map, self.env_scale = UNIFORM_MAP, tuple(float(v) for v in self.environment)
            self.env_rotation, self.environment = 0.0, None

    def env_tables(self):
        """The map's sampling tables (clvol/envmap.py), or None without a map or for a
        black one (nothing to simulate)."""
        if self.env_map is None:
            return None
        if self.environment is not None:
            raise ClvolError("a constant environment and an environment map are exclusive")
        t = envmap_mod.build_tables(self.env_map, self.env_scale, self.env_rotation)
        return t if t.total > 0 else None


def specialisation(med: PathMedium, specialise: bool = True) -> tuple[dict, list[str], list[str]]:
    """(-D defines, simulated effects, skipped effects). With ``specialise=False`` the
    general kernel is built (three lobes, RGB, environment and sun code all compiled)."""
    simulated, skipped = [], []
    grey, iso = med.medium.is_grey, med.medium.phase.is_isotropic
    lobes = list(med.medium.phase.pairs)
    env = med.environment is not None and max(med.environment) > 0
    sun = max(med.light.irradiance) > 0
    single = med.max_order == 1
    tables = med.env_tables()
    if specialise:
        defines = kphase.phase_defines([] if iso else lobes)
        if grey:
            defines["PT_GREY"] = 1
        if env:
            defines["PT_ENV"] = 1
        if tables is not None:
            defines["PT_ENVMAP"] = 1
        if not sun:
            defines["PT_NO_SUN"] = 1
        if single:
            defines["PT_SINGLE_ONLY"] = 1
    else:
        defines = {"PHASE_LOBES": 3, "PT_ENV" if tables is None else "PT_ENVMAP": 1}
    defines.update(block_defines())
    if med.emission is not None:
        defines.update(PT_EMISSION=1, PT_EMISSION_CHANNELS=med.emission.channels)
        simulated.append("emission (sigma_a Le, sigma_a = sigma_t (1 - albedo), added at every "
                         "real collision: seen directly and scattered)")
    defines.update(med.extra_defines)
    simulated.append("sun NEE (ratio tracking)" if sun else "no sun")
    if tables is not None:
        simulated.append(f"environment map {tables.w}x{tables.h} (NEE of luminance-sampled "
                         "texels and escaping paths, MIS power heuristic)")
    elif med.env_map is not None:
        skipped.append("environment map (black: no light)")
    else:
        (simulated if env else skipped).append("environment (escaping paths)")
    simulated.append("isotropic phase" if iso else f"HG phase, {len(lobes)} lobe(s)")
    simulated.append("grey albedo" if grey else "RGB albedo")
    if single:
        simulated.append("single scattering")
        skipped.append("multiple scattering (max order 1)")
    elif med.max_order:
        simulated.append(f"scattering orders 1..{med.max_order}")
    else:
        simulated.append("all scattering orders")
    if tables is None:
        skipped.append("environment NEE")
    return defines, simulated, skipped


# Work-items per compute unit of a GPU launch, and its work-group size (see launch_shape).
GPU_ITEMS_PER_CU, GPU_GROUP = 1024, 64


def launch_shape(kind: str, compute_units: int, n_paths: int, lanes: int) -> tuple:
    """(work-items, local size) of a launch of ``n_paths`` paths, ``lanes`` per work-item.
    Every work-item takes the next path of the launch from a shared counter, and a path's
    result depends only on its index, so the shape changes the speed, never the rows. A CPU
    (kind "cpu", "accelerator", ...) gets a few work-items per core in groups of one (each core
    runs its lanes until the launch runs out); a GPU compute unit needs many threads in flight
    to hide memory latency: up to GPU_ITEMS_PER_CU each, in groups of GPU_GROUP (a group of
    one would fill one thread of a 32-wide warp)."""
    need = max(1, -(-int(n_paths) // int(lanes)))
    if kind == "gpu":
        items = min(need, GPU_ITEMS_PER_CU * int(compute_units))
        return -(-items // GPU_GROUP) * GPU_GROUP, (GPU_GROUP,)
    return min(need, 4 * int(compute_units)), (1,)


class PathTracer:
    """A medium on the device and the kernels specialised for it."""

    def __init__(self, med: PathMedium, majorant_block: int | None = None, specialise: bool = True,
                 runtime=None, device_medium=None):
        """``device_medium``: ``med``'s density already on the device with its majorant
        (clvol/kernels/majorant.py), built with ``majorant_block`` (None: its default);
        None uploads one."""
        self.rt = rt = runtime or get_runtime()
        self.med = med
        if device_medium is None:
            block = DEFAULT_BLOCK if majorant_block is None else majorant_block
            device_medium = DeviceMedium.upload(med, block, rt)
        else:
            if np.shape(med.density) != device_medium.density.shape:
                raise ClvolError(f"PathTracer: device medium of shape "
                                 f"{device_medium.density.shape} for a density of shape "
                                 f"{np.shape(med.density)}")
            if (majorant_block is not None and resolve_block(
                    majorant_block, device_medium.density.shape) != device_medium.block):
                raise ClvolError(f"PathTracer: majorant block {majorant_block} but the device "
                                 f"medium's is {device_medium.block}")
        self.dm = device_medium
        self.shape = device_medium.density.shape
        self.block = block = device_medium.block
        (self.mres, self.bsize) = majorant_args(self.shape, med.bbox_min, med.bbox_max, block)
        self.defines, self.simulated, self.skipped = specialisation(med, specialise)
        self.render_lanes = path_lanes(rt, RENDER_LANES)
        self.query_lanes = path_lanes(rt, QUERY_LANES)
        self.program = rt.program("pathtrace", {"PT_LANES": self.render_lanes, **BOUND_DEFINES,
                                                  **self.defines})
        self._query_program = None
        self._order_program = None
        env = med.environment if med.environment is not None else (0.0, 0.0, 0.0)
        nz, ny, nx = self.shape
        mx, my, mz = self.mres
        self._medium_args = (
            device_medium.density.buffer, device_medium.majorant.buffer, np.int32(nx),
            np.int32(ny), np.int32(nz), np.int32(mx), np.int32(my), np.int32(mz),
            f4(med.bbox_min), f4(med.bbox_max), self.bsize,
            medium_block(med.medium), light_block(med.light), f4(env))
        if "PT_ENVMAP" in self.defines:
            self._medium_args += self.env_args(rt, med.env_tables())
        self.row = PT_OUT
        if med.emission is not None:
            em = med.emission
            ez, ey, ex = em.shape
            buf = em.device.buffer if getattr(em, "device", None) is not None else rt.to_device(
                np.ascontiguousarray(em.values, np.float32).ravel())
            self._medium_args += (buf, np.int32(ex), np.int32(ey), np.int32(ez),
                                  f4(em.bbox_min), f4(em.bbox_max), f4(em.colour))
            self.row = PT_OUT_EMISSION
        self.max_order = int(med.max_order or 0)

    @staticmethod
    def env_args(rt, t) -> tuple:
        """The PT_ENVMAP kernel arguments of tables t (clvol/envmap.py)."""
        return (rt.to_device(t.rgbl.ravel()), rt.to_device(t.marginal),
                rt.to_device(t.conditional.ravel()), np.int32(t.w), np.int32(t.h),
                np.float32(t.rotation), np.float32(t.inv_total))

    @property
    def _env_dtypes(self) -> list:
        return ((_ENVMAP_DTYPES if "PT_ENVMAP" in self.defines else [])
                + (_EMISSION_DTYPES if "PT_EMISSION" in self.defines else []))

    def query_program(self):
        """The program for point queries (built on first use: see QUERY_LANES)."""
        if self._query_program is None:
            self._query_program = self.rt.program(
                "pathtrace", {"PT_LANES": self.query_lanes, **BOUND_DEFINES, **self.defines})
        return self._query_program

    def _launch(self, kernel, n_paths: int, args, lanes: int):
        """Run n_paths paths: each work-item runs LANES paths at a time and takes the next
        path of the launch from a shared counter when one ends (cl/pathtrace.cl), so a few
        work-items per compute unit keep every core busy until the launch runs out."""
        rt = self.rt
        lanes = int(self.defines.get("PT_LANES", lanes))
        items, local = launch_shape(rt.entry.kind, rt.device.max_compute_units, n_paths, lanes)
        # Word 0: next path; 1-4: loop counts with -D PT_STATS (benchmarks).
        counter = rt.to_device(np.zeros(5, np.uint32), writable=True)
        rt.launch(kernel, items, args + (counter,), local_size=local, pad=1)
        if "PT_STATS" in self.defines:
            c = rt.from_device(counter, (5,), np.uint32)
            self.stats = {"tracking_iterations": int(c[1]), "lane_iterations_busy": int(c[2]),
                          "event_passes": int(c[3]), "cell_iterations": int(c[4]),
                          "lanes": lanes, "work_items": items}

    def render_batch(self, camera, seed: int, sample0: int, spl: int, wait: bool = True):
        """Rows (spl, H*W, self.row) for samples sample0..sample0+spl-1 of every pixel
        (self.row = PT_OUT, or PT_OUT_EMISSION with emission)."""
        rt = self.rt
        fwd, right, up = camera.basis()
        w, h = camera.width, camera.height
        n = w * h * spl
        out = rt.empty((n, self.row))
        k = self.program.kernel("pt_render", _MEDIUM_DTYPES + self._env_dtypes
                                + _RENDER_DTYPES[len(_MEDIUM_DTYPES):])
        self._launch(k, n, self._medium_args + (
            f4(camera.origin), f4(fwd), f4(right), f4(up),
            np.float32(camera.tan_half_fov), np.int32(w), np.int32(h),
            np.uint64(seed), np.uint32(sample0), np.int32(spl), np.int32(self.max_order), out),
            self.render_lanes)
        return rt.from_device(out, (spl, w * h, self.row))

    def query_batch(self, points_buf, omegas_buf, nq: int, seed: int, sample0: int, ppl: int,
                    orders: bool = False):
        """Rows (ppl, nq, PT_OUT) for paths sample0..sample0+ppl-1 of every query; with
        ``orders``, (ppl, nq, PT_OUT + 2 ORDER_BINS): each row followed by its per-order
        sums and first moments (grey media with a sun and no environment only).
        ``points_buf``, ``omegas_buf``: the queries' float32 (nq, 3) on the device, as
        DeviceArrays (a raw cl.Buffer is still taken from callers not yet converted)."""
        rt = self.rt
        points_buf, omegas_buf = (b.buffer if isinstance(b, DeviceArray) else b
                                  for b in (points_buf, omegas_buf))
        if "PT_EMISSION" in self.defines:
            raise ClvolError("point queries are per unit sun: build the PathTracer without "
                             "emission")
        n = nq * ppl
        width = PT_OUT + (2 * ORDER_BINS if orders else 0)
        if orders:
            if ("PT_GREY" not in self.defines or "PT_ENV" in self.defines
                    or "PT_ENVMAP" in self.defines):
                raise ClvolError("per-order point queries need a grey albedo and no environment")
            if self._order_program is None:
                self._order_program = self.rt.program(
                    "pathtrace", {"PT_LANES": self.query_lanes, **BOUND_DEFINES, **self.defines,
                                  "PT_ORDER_BINS": ORDER_BINS})
            program = self._order_program
        else:
            program = self.query_program()
        out = rt.empty((n, width))
        k = program.kernel("pt_query", _MEDIUM_DTYPES + self._env_dtypes
                           + _QUERY_DTYPES[len(_MEDIUM_DTYPES):])
        self._launch(k, n, self._medium_args + (
            points_buf, omegas_buf, np.int32(nq), np.uint64(seed), np.uint32(sample0),
            np.int32(ppl), np.int32(self.max_order), out), self.query_lanes)
        return rt.from_device(out, (ppl, nq, width))


def env_sample_test(tables, u, runtime=None) -> np.ndarray:
    """Tests only: cl/pathtrace.cl's map sampler on uniforms u [n][2] (float32):
    rows [n][8] = direction xyz, pdf of the draw, RGB of the draw, pdf of the lookup
    along the drawn direction."""
    rt = runtime or get_runtime()
    u = np.ascontiguousarray(u, np.float32).reshape(-1, 2)
    n = len(u)
    program = rt.program("pathtrace", {"PT_LANES": path_lanes(rt, RENDER_LANES), "PT_ENVMAP": 1,
                                       **kphase.phase_defines([])})
    out = rt.empty((max(n, 1), 8))
    k = program.kernel("pt_env_sample_test", _ENV_TEST_DTYPES)
    rt.launch(k, max(n, 1), PathTracer.env_args(rt, tables) + (rt.to_device(u), np.int32(n), out))
    return rt.from_device(out, (max(n, 1), 8))[:n]
