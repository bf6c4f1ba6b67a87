"""Host wrapper for cl/majorant.cl: the coarse majorant grid and its DDA (cl/include/majorant.h).
The volume on the device that owns a majorant grid (``DeviceMedium``) is clvol/kernels/medium.py.

``build_majorant(density, block)`` returns the grid as a NumPy array;
``build_majorant_buffer`` (a DeviceArray in, a DeviceArray out) keeps it on the device for
kernels that include majorant.h;
``majorant_args(grid_shape, bmin, bmax, block)`` gives the coarse size and the coarse cell
size (world units) those kernels take. A global majorant is ``block >= max(nx, ny, nz)``.
"""
from __future__ import annotations

import numpy as np

from ..errors import ClvolError
from ..runtime import DeviceArray, get_runtime
from .grid import f4

# Voxels per majorant block per axis, for every method: small enough to skip the empty space
# around a cloud, large enough that the coarse grid's DDA takes few steps.
DEFAULT_BLOCK = 8

_BUILD_ARGS = [None, np.int32, np.int32, np.int32, np.int32, np.int32, np.int32, np.int32, None]


def coarse_shape(grid_shape, block: int) -> tuple[int, int, int]:
    """(mz, my, mx) = ceil((nz, ny, nx) / block)."""
    if int(block) < 1:
        raise ClvolError(f"majorant block must be >= 1, got {block}")
    return tuple(-(-int(n) // int(block)) for n in grid_shape)


def majorant_args(grid_shape, bmin, bmax, block: int):
    """((mx, my, mz), bsize) for majorant.h: coarse size in x, y, z order and the coarse
    cell size in world units as a float4 argument."""
    mz, my, mx = coarse_shape(grid_shape, block)
    nz, ny, nx = grid_shape
    cell = (np.asarray(bmax, np.float64) - np.asarray(bmin, np.float64)) / np.array([nx, ny, nz])
    return (mx, my, mz), f4(cell * block)


def build_majorant_buffer(density: DeviceArray, block: int = DEFAULT_BLOCK,
                          runtime=None) -> DeviceArray:
    """Majorant grid (mz, my, mx) of a [z][y][x] density already on the device."""
    rt = runtime or density.runtime or get_runtime()
    nz, ny, nx = (int(n) for n in density.shape)
    mz, my, mx = coarse_shape(density.shape, block)
    out = rt.alloc((mz, my, mx))
    k = rt.program("majorant").kernel("majorant_build", _BUILD_ARGS)
    rt.launch(k, (mx, my, mz), (density.buffer, np.int32(nx), np.int32(ny), np.int32(nz),
                                np.int32(block), np.int32(mx), np.int32(my), np.int32(mz),
                                out.buffer))
    return out


def build_majorant(density: np.ndarray, block: int = DEFAULT_BLOCK, runtime=None) -> np.ndarray:
    """float32 [ceil(nz/b)][ceil(ny/b)][ceil(nx/b)]: per coarse cell, the max of every fine
    voxel the trilinear lookup can blend inside it (its block plus one voxel around)."""
    rt = runtime or get_runtime()
    density = np.ascontiguousarray(density, np.float32)
    if density.ndim != 3:
        raise ClvolError(f"density must be 3-D [z][y][x], got shape {density.shape}")
    return build_majorant_buffer(rt.upload(density), block, rt).read()


def majorant_block(block, grid_shape) -> int:
    """Voxels per majorant block per axis; 0 means one global majorant."""
    if isinstance(block, bool) or not isinstance(block, (int, np.integer)) or block < 0:
        raise ClvolError(f"majorant block = {block!r}: must be an integer >= 0 (0 = one global "
                         f"majorant)")
    return int(block) if block else max(grid_shape)


def dda_segments(origins, dirs, bmin, bmax, grid_shape, maj: np.ndarray, block: int,
                 tmin: float = 0.0, tmax: float = np.inf, max_seg: int = 256, runtime=None):
    """Run majorant.h's DDA on rays: (segments (n, max_seg, 3) as (t_a, t_b, majorant),
    counts (n,)). Test and debugging aid."""
    rt = runtime or get_runtime()
    o = np.ascontiguousarray(origins, np.float32).reshape(-1, 3)
    d = np.ascontiguousarray(dirs, np.float32).reshape(-1, 3)
    n = len(o)
    (mx, my, mz), bsize = majorant_args(grid_shape, bmin, bmax, block)
    if maj.shape != (mz, my, mx):
        raise ClvolError(f"majorant grid shape {maj.shape} != {(mz, my, mx)}")
    k = rt.program("majorant").kernel("majorant_segments", [
        None, None, np.int32, None, None, None, None, np.int32, np.int32, np.int32,
        np.float32, np.float32, np.int32, None, None])
    seg = rt.empty((n, max_seg, 4))
    cnt = rt.empty(n, np.int32)
    rt.launch(k, n, (rt.to_device(o), rt.to_device(d), np.int32(n), f4(bmin), f4(bmax), bsize,
                     rt.to_device(np.ascontiguousarray(maj, np.float32)), np.int32(mx),
                     np.int32(my), np.int32(mz), np.float32(tmin), np.float32(tmax),
                     np.int32(max_seg), seg, cnt))
    return rt.from_device(seg, (n, max_seg, 4))[..., :3], rt.from_device(cnt, n, np.int32)
