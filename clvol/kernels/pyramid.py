"""The density mip pyramid of the feature pipeline (seed III.B.1; docs/transmittance.md).

``build_pyramid(grid, base_resolution=256)``:

1. Pad the grid's box with zero density to a cube (never stretched), centred on the box:
   ``cube_size = max(extent)``, ``cube_min = centre - cube_size / 2``.
2. Resample to ``base^3`` voxels over the cube (host, NumPy/SciPy, once per scene). Each base
   voxel holds the *mean over its cell* of the source density field, per axis:
   - where the base cell is at least as large as the source cell (downsampling or same size),
     the source is read as piecewise constant over its cells (box filter: exact overlap
     weights; identity when the cells coincide);
   - where the base cell is smaller (upsampling), the source is read as its clamped linear
     interpolant between voxel centres (the trilinear field the renderer sees), averaged
     exactly over the base cell (no blocky nearest-neighbour copies).
   Both readings integrate to the same total per source voxel (a clamped hat and a box over
   one cell both integrate to one cell), and density is 0 outside the source box, so the
   total mass ``sum(density) * voxel_volume`` is conserved exactly (up to float rounding).
3. Upload level 0 alone (or, for a grid that is already a base^3 cube, copy it on the device
   from the density a DeviceMedium holds: clvol/kernels/medium.py ``DeviceMedium.pyramid``)
   and build the mip chain on the device (cl/pyramid.cl): level l+1 is the 2x2x2 mean of level l,
   down to 1^3 (which holds the mean density of the cube). Every level has the same mass.

Densities stay raw: multiply by the medium's ``density_scale`` for the extinction sigma_t.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import sparse

from ..errors import ClvolError
from ..features.layout import is_power_of_two, n_levels
from ..runtime import DeviceArray, Runtime, get_runtime
from ..volume.grid import DensityGrid

MAX_BASE_RESOLUTION = 1024


@dataclass(eq=False)
class Pyramid:
    """All mip levels of the cube-padded, resampled density, on the device (a host copy on
    request).

    base_resolution  n_0 (a power of two); level l has n_l = base >> l voxels per side.
    n_levels         log2(base) + 1 (9 for 256, 11 for 1024).
    cube_min         float64 (3,) x, y, z: the cube's lower corner in world units.
    cube_size        float: the cube's edge length; voxel size of level l is cube_size / n_l.
    level_offsets    int64 (n_levels,): element offset of level l in ``device`` / ``data``.
    device           DeviceArray float32 (size,): all levels concatenated, level l stored
                     [z][y][x] (x fastest), on ``runtime``'s device (made once).
    max_density      the largest density of level 0 (no mean of it is larger).
    data             float32 1-D host copy of ``device``, read back on first access (rendering
                     never reads it: tests, twins and training do).
    """

    base_resolution: int
    n_levels: int
    cube_min: np.ndarray
    cube_size: float
    level_offsets: np.ndarray
    device: DeviceArray
    runtime: Runtime = field(repr=False)
    max_density: float = 0.0
    # Derived device data made on demand by other kernels (e.g. the transmittance sweep's
    # padded per-axis copies), kept as long as the pyramid lives.
    cache: dict = field(default_factory=dict, repr=False)
    _data: np.ndarray | None = field(default=None, repr=False)

    @property
    def cube_max(self) -> np.ndarray:
        return self.cube_min + self.cube_size

    @property
    def size(self) -> int:
        """Floats in all levels."""
        return self.device.size

    @property
    def data(self) -> np.ndarray:
        if self._data is None:
            self._data = self.device.read(label="pyramid (host copy)")
        return self._data

    def resolution(self, level: int) -> int:
        """Voxels per side of ``level``."""
        return self.base_resolution >> int(level)

    def voxel_size(self, level: int) -> float:
        return self.cube_size / self.resolution(level)

    def level(self, level: int) -> np.ndarray:
        """Level ``level`` as an (n, n, n) [z][y][x] view into ``data``."""
        n = self.resolution(level)
        off = int(self.level_offsets[level])
        return self.data[off:off + n ** 3].reshape(n, n, n)


def level_offsets(base_resolution: int) -> np.ndarray:
    """Element offsets of levels 0..log2(base) in the concatenated layout."""
    sizes = [(base_resolution >> l) ** 3 for l in range(n_levels(base_resolution))]
    return np.concatenate([[0], np.cumsum(sizes[:-1])]).astype(np.int64)


def pyramid_size(base_resolution: int) -> int:
    """Total number of floats in all levels."""
    return sum((base_resolution >> l) ** 3 for l in range(n_levels(base_resolution)))


def check_base_resolution(base_resolution, runtime: Runtime | None = None) -> int:
    """Return the base resolution as an int, or raise ClvolError naming the allowed values."""
    if not (is_power_of_two(base_resolution) and base_resolution <= MAX_BASE_RESOLUTION):
        raise ClvolError(
            f"pyramid base_resolution = {base_resolution!r} must be a power of two from 1 to "
            f"{MAX_BASE_RESOLUTION} (e.g. 128, 256, 512)")
    base = int(base_resolution)
    if runtime is not None:
        nbytes = 4 * pyramid_size(base)
        limit = int(runtime.device.max_mem_alloc_size)
        if nbytes > limit:
            fits = max(b for b in (1 << k for k in range(11)) if 4 * pyramid_size(b) <= limit)
            raise ClvolError(
                f"pyramid base_resolution = {base} needs one {nbytes / 2**30:.2f} GiB buffer but "
                f"the OpenCL device {runtime.entry.label!r} allows at most {limit / 2**30:.2f} GiB "
                f"per buffer; use base_resolution <= {fits}")
    return base


def cube_of(grid: DensityGrid) -> tuple[np.ndarray, float]:
    """(cube_min, cube_size): the smallest cube centred on the grid's box that contains it."""
    size = float(np.max(grid.extent))
    centre = 0.5 * (grid.bbox_min + grid.bbox_max)
    return centre - 0.5 * size, size


# ----------------------------------------------------------------------------- resampling

def _hat_cdf(x: np.ndarray) -> np.ndarray:
    """Integral of the unit hat max(0, 1 - |t|) from -inf to x."""
    x = np.clip(x, -1.0, 1.0)
    return np.where(x < 0, 0.5 * (x + 1) ** 2, 1 - 0.5 * (1 - x) ** 2)


def _basis_cdf(g: np.ndarray, i: np.ndarray, n: int, linear: bool) -> np.ndarray:
    """Integral over (-0.5, g] (source voxel units, box [-0.5, n-0.5]) of source voxel i's
    basis function: the box of cell i, or the clamped hat of the linear interpolant
    (constant 1 on the half cell beyond the first / last centre)."""
    g = np.clip(g, -0.5, n - 0.5)
    if not linear:
        return np.clip(g - (i - 0.5), 0.0, 1.0)
    if n == 1:
        return g + 0.5
    h = _hat_cdf(g - i)
    first = np.clip(g + 0.5, 0.0, 0.5) + np.maximum(h - 0.5, 0.0)  # i = 0: flat on [-0.5, 0]
    last = np.minimum(h, 0.5) + np.clip(g - (n - 1), 0.0, 0.5)      # i = n-1: flat on [n-1, n-0.5]
    return np.where(i == 0, first, np.where(i == n - 1, last, h))


def resample_matrix(n_src: int, src_lo: float, src_hi: float, n_dst: int, dst_lo: float,
                    dst_hi: float, dtype=np.float64) -> sparse.csr_matrix:
    """(n_dst, n_src) matrix A: dst[a] = sum_i A[a, i] src[i] is the mean over dst cell a of the
    1-D source field (box reading when dst cells >= src cells, clamped linear otherwise;
    0 outside [src_lo, src_hi]). Columns satisfy sum_a A[a, i] * dst_cell = src_cell."""
    src_cell = (src_hi - src_lo) / n_src
    dst_cell = (dst_hi - dst_lo) / n_dst
    linear = dst_cell < src_cell * (1 - 1e-12)
    edges = (dst_lo + np.arange(n_dst + 1) * dst_cell - src_lo) / src_cell - 0.5  # source voxel units
    lo, hi = edges[:-1], edges[1:]
    # Source voxels whose basis can touch [lo, hi]: the hat reaches one voxel further.
    first = np.clip(np.floor(lo).astype(np.int64) - 1, 0, n_src - 1)
    width = int(np.ceil(dst_cell / src_cell)) + 3
    rows = np.repeat(np.arange(n_dst), width)
    cols = (first[:, None] + np.arange(width)[None, :]).ravel()
    keep = cols < n_src
    rows, cols = rows[keep], cols[keep]
    vals = (_basis_cdf(hi[rows], cols, n_src, linear) - _basis_cdf(lo[rows], cols, n_src, linear)) \
        / (hi[rows] - lo[rows])
    nz = vals != 0
    return sparse.csr_matrix((vals[nz].astype(dtype), (rows[nz], cols[nz])),
                             shape=(n_dst, n_src))


def _apply_axis(d: np.ndarray, mat: sparse.csr_matrix, axis: int) -> np.ndarray:
    moved = np.moveaxis(d, axis, 0)
    rest = moved.shape[1:]
    out = mat @ moved.reshape(moved.shape[0], -1)
    return np.moveaxis(np.asarray(out).reshape((mat.shape[0],) + rest), 0, axis)


def resample_to_cube(grid: DensityGrid, base_resolution: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(base [z][y][x] float32, cube_min, cube_size): the grid padded to its centred cube and
    resampled to base^3 (cell means; see the module docstring)."""
    base = int(base_resolution)
    cube_min, size = cube_of(grid)
    if is_identity(grid, base):
        return grid.density.copy(), cube_min, size  # already a base^3 cube: identity
    dtype = np.float64 if base <= 256 else np.float32  # float64 temporaries up to 128 MiB
    mats = [resample_matrix(grid.resolution[a], grid.bbox_min[a], grid.bbox_max[a], base,
                            cube_min[a], cube_min[a] + size, dtype) for a in range(3)]
    d = grid.density.astype(dtype)
    # Array axis of world axis a is 2 - a ([z][y][x]); shrink the most-reducing axis first.
    for a in sorted(range(3), key=lambda a: base / grid.resolution[a]):
        d = _apply_axis(d, mats[a], 2 - a)
    return np.ascontiguousarray(d, dtype=np.float32), cube_min, size


# ----------------------------------------------------------------------------- pyramid

def build_mips(runtime: Runtime, levels: DeviceArray, base_resolution: int) -> None:
    """Fill levels 1.. of ``levels`` (the whole pyramid) from level 0 (in place, on the
    device)."""
    k = runtime.program("pyramid").kernel("mip_reduce", [None, np.int32, np.int32, np.int32])
    offs = level_offsets(base_resolution)
    for l in range(1, len(offs)):
        n = base_resolution >> l
        runtime.launch(k, n ** 3, (levels.buffer, np.int32(offs[l - 1]), np.int32(offs[l]),
                                   np.int32(n)))


def is_identity(grid: DensityGrid, base_resolution: int) -> bool:
    """The grid is already a base^3 cube: its density is level 0 as it is."""
    base = int(base_resolution)
    _, size = cube_of(grid)
    return tuple(grid.resolution) == (base,) * 3 and bool(
        np.allclose(grid.extent, size, rtol=1e-12, atol=0))


def build_pyramid(grid: DensityGrid, base_resolution: int = 256, runtime: Runtime | None = None,
                  density: DeviceArray | None = None) -> Pyramid:
    """Pad ``grid`` to a centred cube, resample to base^3 and build every mip level down to 1^3.

    Level 0 is resampled on the host (there is no resampling kernel) and uploaded alone; the
    mips are made on the device. ``density``: the grid's density already on the device (a
    DeviceMedium's): when the grid is already a base^3 cube, level 0 is copied from it on the
    device and nothing is uploaded."""
    if not isinstance(grid, DensityGrid):
        raise ClvolError(f"build_pyramid needs a clvol DensityGrid, got {type(grid).__name__}")
    rt = runtime or get_runtime()
    base = check_base_resolution(base_resolution, rt)
    levels = rt.alloc(pyramid_size(base))
    if density is not None and is_identity(grid, base) and density.shape == (base,) * 3:
        cube_min, size = cube_of(grid)
        rt.copy(levels, density)
        top = float(np.max(grid.density, initial=0.0))
    else:
        level0, cube_min, size = resample_to_cube(grid, base)
        rt.write(levels, level0.ravel(), label="pyramid level 0")
        top = float(np.max(level0, initial=0.0))
    build_mips(rt, levels, base)
    return Pyramid(base, n_levels(base), cube_min, size, level_offsets(base), levels, rt, top)
