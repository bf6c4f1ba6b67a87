"""Host wrapper for cl/transmittance.cl: graded transmittance fields (seed eq. 1), the exact
light transmittance, and the render-time combination across levels (docs/transmittance.md).

    pyr = build_pyramid(grid, 256)                                   # clvol/kernels/pyramid.py
    g = graded_transmittance(pyr, medium.density_scale, light.direction, lam=0.6)
    g.level(3)            # (32, 32, 32) T_3 at level-3 voxel centres, [z][y][x]
    g.buffer              # all levels on the device, offsets g.level_offsets (= pyr.level_offsets)
    t = light_transmittance(pyr, medium.density_scale, light.direction)   # (256,)*3, lambda = 1
    c = combine_levels(g, weights, bias)  # base^3: sum_l w_l T_l + b at base voxel centres

Fields are sampled at their level's voxel centres (cube_min + (i + 0.5) * cube_size / n_l);
read them trilinearly, clamped at the faces, and use T = 1 outside the cube (nothing there
attenuates). ``light_dir`` is the direction *toward* the light (DESIGN.md); it is normalised here.

Methods: "sweep" (default, fast: one launch per slice along the dominant light axis, error
bounded in tests/test_transmittance.py and docs/transmittance.md) and "brute" (a per-voxel
march that integrates the trilinear field exactly: the accuracy reference, O(n^4) per level).
``quantity="optical_depth"`` returns tau instead of T = exp(-tau) (better to interpolate in
opaque media, where T underflows to 0 for tau > ~104).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pyopencl as cl

from ..errors import ClvolError
from ..runtime import Runtime
from .grid import f4
from .pyramid import Pyramid

METHODS = ("sweep", "brute")
QUANTITIES = ("transmittance", "optical_depth")
DEFAULT_LAMBDA = 0.6


@dataclass(eq=False)
class GradedT:
    """Graded transmittance T_l (or optical depth) for every level, concatenated like the pyramid.

    buffer         cl.Buffer on the pyramid's device, level l at element offset level_offsets[l],
                   n_l^3 values [z][y][x] at level l's voxel centres.
    data           float32 1-D host copy (made on first access; rendering needs only ``buffer``).
    """

    pyramid: Pyramid = field(repr=False)
    density_scale: float
    light_dir: np.ndarray
    lam: float
    method: str
    quantity: str
    buffer: "cl.Buffer" = field(repr=False)
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
            self._data = self.pyramid.runtime.from_device(self.buffer, self.pyramid.data.shape)
        return self._data

    def level(self, level: int) -> np.ndarray:
        n = self.pyramid.resolution(level)
        off = int(self.level_offsets[level])
        return self.data[off:off + n ** 3].reshape(n, n, n)


# ----------------------------------------------------------------------------- checks

def check_light_dir(light_dir, where: str = "light_dir") -> np.ndarray:
    d = np.asarray(light_dir, dtype=np.float64)
    if d.shape != (3,) or not np.isfinite(d).all() or not np.linalg.norm(d) > 0:
        raise ClvolError(f"{where} = {np.asarray(light_dir).tolist()!r} must be a finite, "
                         f"non-zero 3-vector (x, y, z) pointing toward the light")
    return d / np.linalg.norm(d)


def _check_args(pyramid, density_scale, lam, method, quantity) -> tuple[float, float]:
    if not isinstance(pyramid, Pyramid):
        raise ClvolError(f"expected a Pyramid (clvol.kernels.pyramid.build_pyramid), "
                         f"got {type(pyramid).__name__}")
    try:
        s = float(density_scale)
    except (TypeError, ValueError):
        s = float("nan")
    if not (np.isfinite(s) and s >= 0):
        raise ClvolError(f"density_scale = {density_scale!r} must be a finite number >= 0")
    # The largest optical depth must stay a finite float32 (inf * 0 would make NaN).
    worst = s * float(np.max(pyramid.data, initial=0.0)) * pyramid.cube_size * np.sqrt(3.0)
    if not worst < 1e37:
        raise ClvolError(f"density_scale = {density_scale!r} times the largest density over the "
                         f"cube gives optical depths beyond float32 range; rescale the density")
    try:
        lam_f = float(lam)
    except (TypeError, ValueError):
        lam_f = float("nan")
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


def _run_level(rt: Runtime, pyr: Pyramid, level: int, scale: float, light_dir, method: str,
               out_depth: bool, out: "cl.Buffer", out_off: int, scratch) -> None:
    n = pyr.resolution(level)
    off = int(pyr.level_offsets[level])
    prog = rt.program("transmittance")
    if method == "brute":
        k = prog.kernel("transmittance_brute", [None, np.int32, np.int32, None, np.float32,
                                                np.int32, None, np.int32])
        rt.launch(k, n ** 3, (pyr.buffer, np.int32(off), np.int32(n), f4(light_dir),
                              np.float32(scale), np.int32(out_depth), out, np.int32(out_off)))
        return
    k = prog.kernel("transmittance_sweep_slice",
                    [None, np.int32, np.int32, np.int32, np.int32, np.int32, np.int32,
                     np.float32, np.float32, np.float32, np.float32, None, None, np.int32,
                     None, np.int32])
    a, sa, su, sv, inv_la = sweep_geometry(light_dir)
    prev, cur = scratch
    for j in range(n):
        kk = n - 1 - j if sa > 0 else j
        rt.launch(k, n * n, (pyr.buffer, np.int32(off), np.int32(n), np.int32(a), np.int32(sa),
                             np.int32(kk), np.int32(j == 0), np.float32(su), np.float32(sv),
                             np.float32(inv_la), np.float32(scale), prev, cur,
                             np.int32(out_depth), out, np.int32(out_off)))
        prev, cur = cur, prev


def _scratch(rt: Runtime, n: int, method: str):
    if method != "sweep":
        return None
    return rt.empty(n * n), rt.empty(n * n)


def graded_transmittance(pyramid: Pyramid, density_scale: float, light_dir, lam: float = DEFAULT_LAMBDA,
                         method: str = "sweep", quantity: str = "transmittance") -> GradedT:
    """T_l = exp(-integral toward the light of lam^(l+1) * density_scale * rho_l) on every level
    l, at level l's voxel centres (seed eq. 1). Returns a GradedT (device buffer + lazy host copy)."""
    s, lam_f = _check_args(pyramid, density_scale, lam, method, quantity)
    l = check_light_dir(light_dir)
    rt = pyramid.runtime
    out = rt.empty(pyramid.data.shape)
    scratch = _scratch(rt, pyramid.base_resolution, method)
    for level in range(pyramid.n_levels):
        scale = lam_f ** (level + 1) * s * pyramid.voxel_size(level)
        _run_level(rt, pyramid, level, scale, l, method, quantity == "optical_depth", out,
                   int(pyramid.level_offsets[level]), scratch)
    return GradedT(pyramid, s, l, lam_f, method, quantity, out)


def light_transmittance(pyramid: Pyramid, density_scale: float, light_dir, method: str = "sweep",
                        quantity: str = "transmittance", as_buffer: bool = False):
    """The exact light transmittance (lambda = 1, level 0) for single scattering: an (n, n, n)
    float32 array [z][y][x] over the cube at base voxel centres, or its cl.Buffer when
    ``as_buffer`` (nothing is copied back). T = 1 outside the cube."""
    s, _ = _check_args(pyramid, density_scale, 1.0, method, quantity)
    l = check_light_dir(light_dir)
    rt = pyramid.runtime
    n = pyramid.base_resolution
    out = rt.empty(n ** 3)
    _run_level(rt, pyramid, 0, s * pyramid.voxel_size(0), l, method,
               quantity == "optical_depth", out, 0, _scratch(rt, n, method))
    return out if as_buffer else rt.from_device(out, (n, n, n))


def combine_levels(graded: GradedT, weights, bias: float = 0.0, as_buffer: bool = False):
    """Bake sum_l w_l T_l + bias at the base voxel centres (each T_l read trilinearly, clamped):
    the learned 1x1x1 convolution across levels (the seed's "3D-CNN") applied once per light
    change. Returns a (base,)*3 float32 array [z][y][x], or its cl.Buffer when ``as_buffer``.
    Outside the cube every T_l is 1, so the combined value there is sum_l w_l + bias."""
    if not isinstance(graded, GradedT):
        raise ClvolError(f"combine_levels needs a GradedT, got {type(graded).__name__}")
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != (graded.n_levels,) or not np.isfinite(w).all():
        raise ClvolError(f"combine_levels weights must be {graded.n_levels} finite numbers (one "
                         f"per level), got {np.asarray(weights).tolist()!r}")
    if not np.isfinite(float(bias)):
        raise ClvolError(f"combine_levels bias = {bias!r} must be finite")
    rt = graded.pyramid.runtime
    base = graded.base_resolution
    k = rt.program("transmittance").kernel("combine_levels",
                                           [None, None, None, np.int32, np.int32, np.float32, None])
    out = rt.empty(base ** 3)
    rt.launch(k, base ** 3, (graded.buffer, rt.to_device(graded.level_offsets.astype(np.int32)),
                             rt.to_device(w.astype(np.float32)), np.int32(graded.n_levels),
                             np.int32(base), np.float32(bias), out))
    return out if as_buffer else rt.from_device(out, (base,) * 3)
