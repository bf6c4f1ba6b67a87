"""The dense density grid every part of clvol shares.

Conventions (docs/volumes.md, docs/conventions.md):
- ``density`` is float32, C-contiguous, shape ``(nz, ny, nx)``: indexed ``[z][y][x]``, x fastest,
  the layout of Mitsuba's ``.vol``. Values are finite and >= 0 (extinction = density * density_scale).
- The grid fills the axis-aligned box ``bbox_min..bbox_max`` (float64, x, y, z order). Voxel ``i``
  sits at the centre of cell ``i``: ``bbox_min + (i + 0.5) * cell_size``.

``DensityGrid(...)`` validates itself on construction, so a ``DensityGrid`` in hand is always well formed.
Readers and generators call ``DensityGrid.validate`` style checks themselves first with their own
``source`` (the file name), so the user sees which file was wrong.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import VolumeError

# The box every generator and bare-array reader uses unless told otherwise.
DEFAULT_BBOX_MIN = (-0.5, -0.5, -0.5)
DEFAULT_BBOX_MAX = (0.5, 0.5, 0.5)


def _index_str(flat_index: int, shape: tuple[int, ...]) -> str:
    """'[z, y, x] = (1, 2, 3)' for a flat index into a (nz, ny, nx) array."""
    idx = tuple(int(i) for i in np.unravel_index(flat_index, shape))
    if len(shape) == 3:
        return f"[z, y, x] = {idx}"
    return f"index {idx}"


def check_density_values(density: np.ndarray, source: str) -> None:
    """Raise VolumeError if ``density`` holds NaN, +-Inf or negative values.

    The message says how many offending voxels there are and where the first one is, so a
    user can find it. Works on any real dtype (readers call it before converting to float32).
    """
    # One pass over the data in the common (clean) case: all finite and >= 0.
    finite = np.isfinite(density)
    if not finite.all():
        nan = np.isnan(density)
        n_nan = int(np.count_nonzero(nan))
        if n_nan:
            first = int(np.flatnonzero(nan)[0])
            raise VolumeError(
                f"{source}: density has {n_nan} NaN value(s); first at "
                f"{_index_str(first, density.shape)}")
        inf = ~finite
        n_inf = int(np.count_nonzero(inf))
        first = int(np.flatnonzero(inf)[0])
        raise VolumeError(
            f"{source}: density has {n_inf} infinite value(s); first at "
            f"{_index_str(first, density.shape)} = {density.flat[first]}")
    negative = density < 0
    if negative.any():
        n_neg = int(np.count_nonzero(negative))
        first = int(np.flatnonzero(negative)[0])
        raise VolumeError(
            f"{source}: density has {n_neg} negative value(s) (density must be >= 0); first at "
            f"{_index_str(first, density.shape)} = {float(density.flat[first])!r}")


MIN_RELATIVE_SIDE = 1e-5        # 2^-16.6: ~80 float32 rounding steps of the box's scale


def check_bbox(bbox_min, bbox_max, source: str) -> tuple[np.ndarray, np.ndarray]:
    """Return (bbox_min, bbox_max) as float64 (3,) arrays, or raise naming the bad value.

    Accepts any real sequence of three numbers (converting a float32 or integer bbox to
    float64 is exact); rejects non-finite values and boxes with min >= max on any axis.
    """
    out = []
    for name, value in (("bbox_min", bbox_min), ("bbox_max", bbox_max)):
        arr = np.asarray(value)
        if arr.shape != (3,):
            raise VolumeError(f"{source}: {name} must hold 3 numbers (x, y, z), got shape {arr.shape}")
        if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)) \
                or arr.dtype == np.bool_:
            raise VolumeError(f"{source}: {name} must be real numbers, got dtype {arr.dtype}")
        arr = arr.astype(np.float64)
        if not np.isfinite(arr).all():
            raise VolumeError(f"{source}: {name} = {arr.tolist()} is not finite")
        out.append(arr)
    lo, hi = out
    bad = [ax for ax, a, b in zip("xyz", lo, hi) if not a < b]
    if bad:
        raise VolumeError(
            f"{source}: bbox_min {lo.tolist()} must be < bbox_max {hi.tolist()} on every axis "
            f"(not on {', '.join(bad)})")
    # The kernels place points in float32 (24-bit mantissa): a side shorter than
    # MIN_RELATIVE_SIDE of the box's scale (its longest side, or its farthest coordinate
    # from the origin) cannot be resolved, and resampling it to the cube would need more
    # cells than exist (a 1e-30 thick slab of a unit box overflowed the pyramid's matrix).
    ext = hi - lo
    scale = max(float(ext.max()), float(np.abs(lo).max()), float(np.abs(hi).max()))
    thin = [ax for ax, e in zip("xyz", ext) if e < MIN_RELATIVE_SIDE * scale]
    if thin:
        raise VolumeError(
            f"{source}: the box {lo.tolist()} .. {hi.tolist()} is too thin on "
            f"{', '.join(thin)} (sides {ext.tolist()}): each side must be at least "
            f"{MIN_RELATIVE_SIDE:g} of {scale:g}, the box's scale, to be resolved in float32")
    return lo, hi


def density_to_float32(arr: np.ndarray, source: str) -> np.ndarray:
    """Convert a real 3-D array to C-contiguous float32, refusing lossy or surprising casts.

    float16/float32/float64 are accepted. float64 values must be finite and fit in float32
    (rounding to float32's ~7 digits is the only change). Integer, bool and complex arrays
    are refused: an integer density has no implied scale (is 255 full density?), so the
    user should convert it deliberately.
    """
    if not isinstance(arr, np.ndarray):
        raise VolumeError(f"{source}: density must be a NumPy array, got {type(arr).__name__}")
    if arr.ndim != 3:
        raise VolumeError(
            f"{source}: density must be a 3-D array indexed [z][y][x], got {arr.ndim}-D "
            f"with shape {arr.shape}")
    if 0 in arr.shape:
        raise VolumeError(f"{source}: density grid is empty: shape (nz, ny, nx) = {arr.shape}")
    if arr.dtype.kind != "f":
        raise VolumeError(
            f"{source}: density dtype {arr.dtype} is not a floating-point type; convert it to "
            f"float32 yourself, choosing the density scale (e.g. uint8 / 255)")
    check_density_values(arr, source)
    if arr.dtype.itemsize > 4:
        big = float(np.max(arr))
        if big > float(np.finfo(np.float32).max):
            raise VolumeError(
                f"{source}: density value {big!r} overflows float32 (max "
                f"{float(np.finfo(np.float32).max):.6g}); rescale the data")
    return np.ascontiguousarray(arr, dtype=np.float32)


@dataclass(eq=False)
class DensityGrid:
    """A dense density grid over an axis-aligned box.

    density:  float32, C-contiguous, shape (nz, ny, nx), finite, >= 0.
    bbox_min, bbox_max: float64 (3,), x, y, z order, min < max on every axis.

    The constructor converts bbox sequences to float64 (exact) but never converts the
    density: use ``DensityGrid.from_array`` to build one from a float64 or non-contiguous array.
    """

    density: np.ndarray
    bbox_min: np.ndarray
    bbox_max: np.ndarray

    def __post_init__(self) -> None:
        self.bbox_min, self.bbox_max = check_bbox(self.bbox_min, self.bbox_max, "DensityGrid")
        self.validate("DensityGrid")

    @classmethod
    def from_array(cls, density: np.ndarray, bbox_min=DEFAULT_BBOX_MIN, bbox_max=DEFAULT_BBOX_MAX,
                   source: str = "array") -> "DensityGrid":
        """Build a grid from any real float array [z][y][x], converting it to float32 safely."""
        lo, hi = check_bbox(bbox_min, bbox_max, source)
        return cls(density_to_float32(density, source), lo, hi)

    def validate(self, source: str) -> None:
        """Raise VolumeError, starting with ``source``, if the grid breaks any invariant."""
        d = self.density
        if not isinstance(d, np.ndarray):
            raise VolumeError(f"{source}: density must be a NumPy array, got {type(d).__name__}")
        if d.dtype != np.float32:
            raise VolumeError(
                f"{source}: density must be float32, got {d.dtype} (DensityGrid.from_array converts safely)")
        if d.ndim != 3:
            raise VolumeError(
                f"{source}: density must be 3-D [z][y][x], got {d.ndim}-D with shape {d.shape}")
        if 0 in d.shape:
            raise VolumeError(f"{source}: density grid is empty: shape (nz, ny, nx) = {d.shape}")
        if not d.flags.c_contiguous:
            raise VolumeError(f"{source}: density must be C-contiguous (use np.ascontiguousarray)")
        check_density_values(d, source)
        check_bbox(self.bbox_min, self.bbox_max, source)

    @property
    def resolution(self) -> tuple[int, int, int]:
        """(nx, ny, nz): the grid size in x, y, z order (density.shape reversed)."""
        nz, ny, nx = self.density.shape
        return int(nx), int(ny), int(nz)

    @property
    def extent(self) -> np.ndarray:
        """bbox_max - bbox_min, float64 (3,), x, y, z."""
        return self.bbox_max - self.bbox_min

    @property
    def cell_size(self) -> np.ndarray:
        """Size of one voxel along x, y, z: extent / resolution, float64 (3,)."""
        return self.extent / np.asarray(self.resolution, dtype=np.float64)

    def voxel_centers(self, axis: int) -> np.ndarray:
        """World coordinates of the voxel centres along ``axis`` (0 = x, 1 = y, 2 = z)."""
        n = self.resolution[axis]
        return self.bbox_min[axis] + (np.arange(n, dtype=np.float64) + 0.5) * self.cell_size[axis]

    def __repr__(self) -> str:
        nx, ny, nz = self.resolution
        return (f"DensityGrid({nx}x{ny}x{nz} (x*y*z), bbox_min={self.bbox_min.tolist()}, "
                f"bbox_max={self.bbox_max.tolist()})")
