"""Host wrapper for cl/transmittance.cl: graded transmittance fields (seed eq. 1), the exact
light transmittance, and the render-time combination across levels (docs/transmittance.md).

    pyr = build_pyramid(grid, 256)                                   # clvol/kernels/pyramid.py
    g = graded_transmittance(pyr, medium.density_scale, light.direction, lam=0.6)
    g.level(3)            # (32, 32, 32) T_3 at level-3 voxel centres, [z][y][x]
    g.device              # all levels on the device (DeviceArray), offsets g.level_offsets
    t = light_transmittance(pyr, medium.density_scale, light.direction, as_buffer=True)
                          # (n, n, n) DeviceArray, nothing read back
    t = light_transmittance(pyr, medium.density_scale, light.direction)   # (256,)*3, lambda = 1
    c = combine_levels(g, weights, bias)  # base^3: sum_l w_l T_l + b at base voxel centres

Fields are sampled at their level's voxel centres (cube_min + (i + 0.5) * cube_size / n_l);
read them trilinearly, clamped at the faces, and use T = 1 outside the cube (nothing there
attenuates). ``light_dir`` is the direction *toward* the light (docs/conventions.md); it is
normalised here.

Methods: "sweep" (default, fast: light-ray columns swept slice by slice along the dominant
light axis, 16 slices per launch; error bounded in tests/test_transmittance.py and
docs/transmittance.md) and "brute" (a per-voxel march that integrates the trilinear field
exactly: the accuracy reference, O(n^4) per level).
``quantity="optical_depth"`` returns tau instead of T = exp(-tau) (better to interpolate in
opaque media, where T underflows to 0 for tau > ~104).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ClvolError
from ..features.layout import DEFAULT_LAMBDA  # the contract's graded-transmittance lambda
from ..runtime import DeviceArray, Runtime, padded
from .constants import kernel_constant
from .grid import f4
from .pyramid import Pyramid

METHODS = ("sweep", "brute")
QUANTITIES = ("transmittance", "optical_depth")


@dataclass(eq=False)
class GradedT:
    """Graded transmittance T_l (or optical depth) for every level, concatenated like the pyramid.

    device         DeviceArray (size,) on the pyramid's device, level l at element offset
                   level_offsets[l], n_l^3 values [z][y][x] at level l's voxel centres.
    data           float32 1-D host copy (made on first access; rendering needs only ``device``).
    """

    pyramid: Pyramid = field(repr=False)
    density_scale: float
    light_dir: np.ndarray
    lam: float
    method: str
    quantity: str
    device: DeviceArray = field(repr=False)
    _data: np.ndarray | None = field(default=None, repr=False)

    @property
    def level_offsets(self) -> np.ndarray:
        return self.pyramid.level_offsets

    @property
    def n_levels(self) -> int:
        return self.pyramid.n_levels

    @property
    def base_resolution(self) -> int:
        return self.pyramid.base_resolution

    @property
    def data(self) -> np.ndarray:
        if self._data is None:
            self._data = self.device.read(label="graded transmittance (host copy)")
        return self._data

    def level(self, level: int) -> np.ndarray:
        n = self.pyramid.resolution(level)
        off = int(self.level_offsets[level])
        return self.data[off:off + n ** 3].reshape(n, n, n)


# ----------------------------------------------------------------------------- checks

def check_level_weights(weights, bias, n_levels: int, name: str = "level_weights",
                        error=ClvolError) -> tuple[np.ndarray, float]:
    """(float64 weights, float bias) of a learned combination of the graded levels, or
    ``error`` naming ``name`` (the gather raises its GatherError)."""
    w = np.asarray(weights, np.float64)
    if w.shape != (n_levels,) or not np.all(np.isfinite(w)):
        raise error(f"{name} must be {n_levels} finite numbers (one per graded level), "
                    f"got {np.asarray(weights).tolist()!r}")
    if not np.isfinite(float(bias)):
        raise error(f"{name}: bias = {bias!r} must be finite")
    return w, float(bias)


def check_light_dir(light_dir, where: str = "light_dir") -> np.ndarray:
    d = np.asarray(light_dir, dtype=np.float64)
    if d.shape != (3,) or not np.isfinite(d).all() or not np.linalg.norm(d) > 0:
        raise ClvolError(f"{where} = {np.asarray(light_dir).tolist()!r} must be a finite, "
                         f"non-zero 3-vector (x, y, z) pointing toward the light")
    return d / np.linalg.norm(d)


def _as_float(value) -> float:
    """float(value), or NaN for anything that is not a number (then refused by the range check)."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


# The largest optical depth a render may meet (density_scale x the largest density x the
# longest path through the volume): beyond it float32 optical depths overflow and inf * 0
# makes NaN. Renderer.render applies it too; libclvol as CLVOL_MAX_OPTICAL_DEPTH (clvol.h).
MAX_OPTICAL_DEPTH = 1e37


def check_optical_range(density_scale: float, max_density: float, length: float,
                        name: str = "density_scale", over: str = "the box's diagonal") -> None:
    """The one rule on optical range (MAX_OPTICAL_DEPTH): density_scale x the largest density x
    ``length`` (the longest path the caller's rays take, named ``over`` in the message)."""
    if not density_scale * max_density * length < MAX_OPTICAL_DEPTH:
        raise ClvolError(f"{name} = {density_scale!r} times the largest density {max_density:g} "
                         f"over {over} gives optical depths beyond float32 range; rescale the "
                         f"density")


# The path tracer's tracking rule (issue 41; docs/pathtrace.md, "Bounds"). Delta tracking
# draws tentative collisions at the majorant's rate, so a flight that crosses a majorant cell
# where the density is far below the cell's majorant (a cloud's edge, the empty corner of a
# cell, a grazing shadow ray) takes about the majorant's optical depth across the cell in
# draws. Measured on the 96^3 cloud at 32^2, 1 spp (bench/bench_thick_media.py): a path's mean
# tentative collisions are 0.5-1.5 x density_scale x the largest density x the cell's side at
# albedo 0.9 (blocks of 1 to 96 voxels; ~7 vertices a path whatever the scale), 2.6-2.9 x at
# 0.999 and 3.7-5.3 x at 1 (hundreds to thousands of vertices: at albedo 1 a walk ends only by
# leaving the medium); the render's time follows (~40 ns a draw on 2 cores). The rule refuses a
# medium whose depth per cell exceeds MAX_CELL_DEPTH = 2^13 = PT_MAX_STEPS / 128: below it a
# path's mean is at most ~4e4 draws, a 32^2 image at 1 spp takes ~1-3 s, and paths do not meet
# the step bound; above it they take 1e5 draws and more (4 s at 2e5 x the cloud, albedo 1, 23
# s at 1e7, albedo 0.9), the slow ones stop at PT_MAX_STEPS and the image is biased (0.3-65% of
# the paths stopped at 1e6-1e7). A finer majorant lowers the depth, which is the cheaper walk
# (1e7 at a 1-voxel block: 47,000 draws a path, 1.9 s, none stopped; 638,000 at 8 voxels): the
# message names the coarsest block that passes, if there is one.
MAX_CELL_DEPTH = 2.0 ** 13


def check_tracking_depth(density_scale: float, max_density: float, cell_side: float,
                         voxel_side: float, block: int,
                         name: str = "medium.density_scale") -> float:
    """The one rule on the path tracer's walks (MAX_CELL_DEPTH): density_scale x the largest
    density x the longest side of a majorant cell (``block`` voxels of ``voxel_side``; the
    box for one global majorant). Returns that depth; raises a one-line ClvolError above it."""
    depth = float(density_scale) * float(max_density) * float(cell_side)
    if not depth <= MAX_CELL_DEPTH:
        per_voxel = float(density_scale) * float(max_density) * float(voxel_side)
        finer = int(MAX_CELL_DEPTH // per_voxel) if per_voxel > 0 and np.isfinite(per_voxel) else 0
        fix = (f"a majorant block of {finer} voxels or fewer (--majorant-block) or a smaller "
               f"density_scale" if 1 <= finer < block else "a smaller density_scale")
        raise ClvolError(f"{name} = {density_scale!r} times the largest density {max_density:g} "
                         f"over a majorant cell {cell_side:.3g} across ({block} voxels) gives "
                         f"the path tracer an optical depth of {depth:.3g} per cell, above its "
                         f"limit {MAX_CELL_DEPTH:g}: each path would take about that many "
                         f"tentative collisions; use {fix}")
    return depth


def _check_args(pyramid, density_scale, lam, method, quantity) -> tuple[float, float]:
    if not isinstance(pyramid, Pyramid):
        raise ClvolError(f"expected a Pyramid (clvol.kernels.pyramid.build_pyramid), "
                         f"got {type(pyramid).__name__}")
    s = _as_float(density_scale)
    if not (np.isfinite(s) and s >= 0):
        raise ClvolError(f"density_scale = {density_scale!r} must be a finite number >= 0")
    check_optical_range(s, pyramid.max_density, pyramid.cube_size * np.sqrt(3.0),
                        over="the cube's diagonal")
    lam_f = _as_float(lam)
    if not 0 < lam_f <= 1:
        raise ClvolError(f"lambda = {lam!r} must be in (0, 1] (the seed uses 0.6)")
    if method not in METHODS:
        raise ClvolError(f"transmittance method = {method!r}; allowed: {', '.join(METHODS)}")
    if quantity not in QUANTITIES:
        raise ClvolError(f"transmittance quantity = {quantity!r}; allowed: {', '.join(QUANTITIES)}")
    return s, lam_f


# ----------------------------------------------------------------------------- kernels

def sweep_geometry(light_dir: np.ndarray) -> tuple[int, int, float, float, float]:
    """(a, sa, su, sv, inv_la): dominant axis a (0 = x, 1 = y, 2 = z) and the sign of the light's
    component on it, lateral offsets per voxel step along a (lateral axes in x, y, z order
    without a), and 1 / |l_a| (ray length per voxel step along a)."""
    l = np.asarray(light_dir, np.float64)
    a = int(np.argmax(np.abs(l)))
    lat = [ax for ax in range(3) if ax != a]
    la = abs(l[a])
    return a, (1 if l[a] > 0 else -1), l[lat[0]] / la, l[lat[1]] / la, 1.0 / la


SWEEP_PAD = kernel_constant("SWEEP_PAD")      # padding of the sweep layout
SWEEP_BLOCK = kernel_constant("SWEEP_BLOCK")  # sweep steps per launch
SWEEP_SLACK = 64  # floats after the last level (lanes of the last work-items run past it)
SWEEP_GROUP = 64  # work-group size (column groups step together, see the kernel)
VECTOR_MIN_N = 16  # levels with n >= 16 use the LANES-wide kernel, smaller ones the scalar one


def _layout_size(n: int) -> int:
    return (n + 2) * (n + 2 * SWEEP_PAD + 1) * (n + 3 * SWEEP_PAD)


def sweep_layout(pyr: Pyramid, axis: int):
    """(DeviceArray, offsets): every level padded and permuted for sweeps along ``axis`` (made
    once per pyramid and axis on the device, then cached on the pyramid)."""
    key = ("sweep_layout", axis)
    if key not in pyr.cache:
        rt = pyr.runtime
        sizes = [_layout_size(pyr.resolution(l)) for l in range(pyr.n_levels)]
        offs = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        buf = rt.alloc(int(sum(sizes)) + SWEEP_SLACK)
        k = rt.program("transmittance").kernel(
            "sweep_layout", [None, np.int32, np.int32, np.int32, None, np.int32])
        for l in range(pyr.n_levels):
            rt.launch(k, sizes[l], (pyr.device.buffer, np.int32(pyr.level_offsets[l]),
                                    np.int32(pyr.resolution(l)), np.int32(axis), buf.buffer,
                                    np.int32(offs[l])))
        pyr.cache[key] = (buf, offs)
    return pyr.cache[key]


def sweep_steps(n: int, light_dir) -> list[tuple[int, int, int, float, float]]:
    """Per step j: (slice k, floor(j su), floor(j sv), and the fractional parts), in float64."""
    a, sa, su, sv, _ = sweep_geometry(light_dir)
    out = []
    for j in range(n):
        iu, iv = int(np.floor(j * su)), int(np.floor(j * sv))
        out.append((n - 1 - j if sa > 0 else j, iu, iv, j * su - iu, j * sv - iv))
    return out


_SWEEP_ARGS = ([None, np.int32, np.int32, np.int32, np.int32, np.float32, np.float32,
                np.float32, None, np.int32, np.int32, np.int32, None, np.int32, np.int32,
                None, None, None, np.int32, np.int32, np.int32, None, np.int32, np.int32])
_ARG_B = 18  # index of the per-launch block argument b


def sweep_width_define(width: int):
    """-D SWEEP_WIDTH of a sweep ``width`` columns wide: the vector one is written ``LANES``
    (the device's lane width, cl/include/lanes.h), so a bundle's options hold for any device."""
    return "LANES" if width > 1 else 1


def sweep_programs(sizes) -> dict:
    """{program name: defines} of the sweeps over cubes of these ``sizes`` (voxels per side):
    "transmittance_wL" (LANES-wide columns) for levels of at least VECTOR_MIN_N voxels,
    "transmittance_w1" for smaller ones (``_sweep_level`` builds each level by this rule)."""
    out = {}
    for n in sorted(set(int(n) for n in sizes), reverse=True):
        wide = n >= VECTOR_MIN_N
        out["transmittance_wL" if wide else "transmittance_w1"] = {
            "SWEEP_WIDTH": sweep_width_define(16 if wide else 1)}
    return out


def _sweep_level(rt: Runtime, pyr: Pyramid, level: int, scale: float, light_dir,
                 out_depth: bool, out: DeviceArray, out_off: int) -> None:
    n = pyr.resolution(level)
    a, sa, su, sv, inv_la = sweep_geometry(light_dir)
    # the plan's rule for this level's program (LANES is never 1: cl/include/lanes.h)
    (defines,) = sweep_programs([n]).values()
    width = rt.lanes if defines["SWEEP_WIDTH"] == "LANES" else 1
    k = rt.program("transmittance", defines).kernel("transmittance_sweep_block", _SWEEP_ARGS)
    layout, offs = sweep_layout(pyr, a)
    steps = sweep_steps(n, light_dir)
    stab = np.array([s[:3] for s in steps], np.int32)
    sftab = np.array([s[3:] for s in steps], np.float32)
    nb = -(-n // SWEEP_BLOCK)
    btab = np.zeros((nb, 4), np.int32)
    for b in range(nb):
        blk = stab[b * SWEEP_BLOCK:(b + 1) * SWEEP_BLOCK]
        umin, umax = blk[:, 1].min(), blk[:, 1].max()
        vmin, vmax = blk[:, 2].min(), blk[:, 2].max()
        btab[b] = (umin, vmin, -(-(umax - umin + n + 1) // width), vmax - vmin + n + 1)
    ou, ov = -int(stab[:, 1].min()), -int(stab[:, 2].min())
    cw = int(stab[:, 1].max()) + ou + n + width + 2
    col_rows = int(stab[:, 2].max()) + ov + n + 1
    col = rt.empty(col_rows * cw, zero=True)
    bw, brows = int(btab[:, 2].max()) * width, int(btab[:, 3].max())
    bb = rt.empty(2 * SWEEP_BLOCK * brows * bw)
    n_col = padded(int((btab[:, 2] * btab[:, 3]).max()), SWEEP_GROUP)
    n_vox = n * n // width if (width > 1 and a == 0) else SWEEP_BLOCK * n * (n // width)
    # clSetKernelArg does not retain buffers: keep every one referenced until the last enqueue.
    tables = [rt.to_device(t) for t in (stab, sftab, btab)]
    k.set_args(layout.buffer, np.int32(offs[level]), np.int32(n), np.int32(a), np.int32(sa),
               np.float32(su), np.float32(sv), np.float32(scale * inv_la / 6.0),
               col, np.int32(cw), np.int32(ou), np.int32(ov), bb, np.int32(bw), np.int32(brows),
               *tables, np.int32(0), np.int32(nb), np.int32(out_depth), out.buffer, np.int32(out_off),
               np.int32(n_col))
    for b in range(nb + 1):
        k.set_arg(_ARG_B, np.int32(b))
        rt.launch(k, n_col + n_vox, None, local_size=(SWEEP_GROUP,), pad=SWEEP_GROUP)


def _run_level(rt: Runtime, pyr: Pyramid, level: int, scale: float, light_dir, method: str,
               out_depth: bool, out: DeviceArray, out_off: int) -> None:
    if method == "sweep":
        _sweep_level(rt, pyr, level, scale, light_dir, out_depth, out, out_off)
        return
    n = pyr.resolution(level)
    k = rt.program("transmittance").kernel("transmittance_brute", [
        None, np.int32, np.int32, None, np.float32, np.int32, None, np.int32])
    rt.launch(k, n ** 3, (pyr.device.buffer, np.int32(pyr.level_offsets[level]), np.int32(n),
                          f4(light_dir), np.float32(scale), np.int32(out_depth), out.buffer,
                          np.int32(out_off)))


def graded_transmittance(pyramid: Pyramid, density_scale: float, light_dir, lam: float = DEFAULT_LAMBDA,
                         method: str = "sweep", quantity: str = "transmittance") -> GradedT:
    """T_l = exp(-integral toward the light of lam^(l+1) * density_scale * rho_l) on every level
    l, at level l's voxel centres (seed eq. 1). Returns a GradedT (device array + lazy host copy)."""
    s, lam_f = _check_args(pyramid, density_scale, lam, method, quantity)
    l = check_light_dir(light_dir)
    rt = pyramid.runtime
    out = rt.alloc(pyramid.size)  # read by later kernels (gather)
    for level in range(pyramid.n_levels):
        scale = lam_f ** (level + 1) * s * pyramid.voxel_size(level)
        _run_level(rt, pyramid, level, scale, l, method, quantity == "optical_depth", out,
                   int(pyramid.level_offsets[level]))
    return GradedT(pyramid, s, l, lam_f, method, quantity, out)


def light_transmittance(pyramid: Pyramid, density_scale: float, light_dir, method: str = "sweep",
                        quantity: str = "transmittance", as_buffer: bool = False):
    """The exact light transmittance (lambda = 1, level 0) for single scattering: an (n, n, n)
    float32 array [z][y][x] over the cube at base voxel centres, or the (n, n, n) DeviceArray
    holding it when ``as_buffer`` (nothing is copied back). T = 1 outside the cube."""
    s, _ = _check_args(pyramid, density_scale, 1.0, method, quantity)
    l = check_light_dir(light_dir)
    rt = pyramid.runtime
    n = pyramid.base_resolution
    out = rt.alloc((n, n, n))  # read by later kernels (ray marcher)
    _run_level(rt, pyramid, 0, s * pyramid.voxel_size(0), l, method,
               quantity == "optical_depth", out, 0)
    return out if as_buffer else out.read()


def combine_levels(graded: GradedT, weights, bias: float = 0.0, as_buffer: bool = False):
    """Bake sum_l w_l T_l + bias at the base voxel centres (each T_l read trilinearly, clamped):
    the learned 1x1x1 convolution across levels (the seed's "3D-CNN") applied once per light
    change. Returns a (base,)*3 float32 array [z][y][x], or its DeviceArray when ``as_buffer``.
    Outside the cube every T_l is 1, so the combined value there is sum_l w_l + bias."""
    if not isinstance(graded, GradedT):
        raise ClvolError(f"combine_levels needs a GradedT, got {type(graded).__name__}")
    if graded.quantity != "transmittance":
        raise ClvolError(f"combine_levels needs transmittance fields, got quantity = "
                         f"{graded.quantity!r} (call graded_transmittance with the default quantity)")
    w, bias = check_level_weights(weights, bias, graded.n_levels, "combine_levels weights")
    rt = graded.pyramid.runtime
    base = graded.base_resolution
    k = rt.program("transmittance").kernel("combine_levels",
                                           [None, None, None, np.int32, np.int32, np.float32, None])
    out = rt.alloc((base,) * 3)
    rt.launch(k, base ** 3, (graded.device.buffer,
                             rt.to_device(graded.level_offsets.astype(np.int32)),
                             rt.to_device(w.astype(np.float32)), np.int32(graded.n_levels),
                             np.int32(base), np.float32(bias), out.buffer))
    return out if as_buffer else out.read()
