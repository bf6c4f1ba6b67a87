"""Host wrapper for cl/viewdepth.cl: the view-space source's query depths per pixel block
(twin: reference/viewdepth.py; same argument names)."""
from __future__ import annotations

import numpy as np

from ..errors import ClvolError
from ..runtime import DeviceArray, get_runtime
from .constants import kernel_constant
from .grid import f4

MAX_VIEW_K = kernel_constant("VIEW_MAX_K")
MAX_VIEW_RAYS = kernel_constant("VIEW_MAX_RAYS")


def block_grid(width: int, height: int, block: int) -> tuple[int, int]:
    """(bx, by): pixel blocks across and down (the last ones may be partial)."""
    return -(-int(width) // int(block)), -(-int(height) // int(block))


def view_depth_defines(k: int, block: int, rays: int, jitter: bool = False,
                       free_flight: bool = False) -> dict:
    """The -D defines of the view_depths program (view_depths builds with them; clvol
    bundle writes them for libclvol)."""
    d = {"VIEW_K": int(k), "VIEW_BLOCK": int(block), "VIEW_RAYS": int(rays)}
    if jitter:
        d["VIEW_JITTER"] = 1
    if free_flight:
        d["VIEW_FREE_FLIGHT"] = 1
    return d


def view_depths(density, bbox_min, bbox_max, density_scale, origin, forward, right, up,
                tan_half, width, height, block, rays, k, step, stop=1e-3, jitter=None,
                free_flight=False, runtime=None):
    """(depths float32 (by, bx, k), weight float32 (by, bx)): see the twin. ``density`` is
    a NumPy array or a DeviceArray already on the device; ``jitter`` None (the
    deterministic placement) or (by, bx, 3) values in [0, 1) (the stochastic source);
    ``free_flight`` (needs jitter, k = rays = 1): one unconditioned free flight per block
    instead of the quantile, weight 1 for a collision and 0 for none."""
    rt = runtime or get_runtime()
    if not (1 <= k <= MAX_VIEW_K and 1 <= rays <= MAX_VIEW_RAYS and block >= 1):
        raise ClvolError(f"view depths: k = {k} must be 1..{MAX_VIEW_K}, rays = {rays} "
                         f"1..{MAX_VIEW_RAYS}, block = {block} >= 1")
    if not step > 0:
        raise ClvolError(f"view depths: step must be > 0, got {step}")
    dens = density if isinstance(density, DeviceArray) else rt.upload(
        np.ascontiguousarray(density, np.float32))
    nz, ny, nx = dens.shape
    bx, by = block_grid(width, height, block)
    defines = view_depth_defines(k, block, rays, jitter is not None, free_flight)
    extra = ()
    if jitter is not None:
        jit = np.asarray(jitter, np.float32)
        if jit.shape != (by, bx, 3) or not np.all((jit >= 0) & (jit < 1)):
            raise ClvolError(f"view depths: jitter must be (by, bx, 3) = ({by}, {bx}, 3) values "
                             f"in [0, 1), got shape {jit.shape}")
        j4 = np.zeros((by, bx, 4), np.float32)
        j4[..., :3] = jit
        extra = (rt.upload(j4.reshape(-1)).buffer,)
    if free_flight:
        if jitter is None or k != 1 or rays != 1:
            raise ClvolError(f"view depths: a free flight needs jitter, k = 1 and rays = 1 "
                             f"(got k = {k}, rays = {rays}, jitter {'given' if jitter is not None else 'None'})")
    prog = rt.program("viewdepth", defines)
    kern = prog.kernel("view_depths", [None, np.int32, np.int32, np.int32, None, None, np.float32,
                                       None, None, None, None, np.float32, np.int32, np.int32,
                                       np.float32, np.float32, None, None] + [None] * len(extra))
    depths, weight = rt.empty((by * bx * k,)), rt.empty((by * bx,))
    evt = rt.launch(kern, bx * by, (dens.buffer, np.int32(nx), np.int32(ny), np.int32(nz),
                                    f4(bbox_min), f4(bbox_max), np.float32(density_scale),
                                    f4(origin), f4(forward), f4(right), f4(up),
                                    np.float32(tan_half), np.int32(width), np.int32(height),
                                    np.float32(step), np.float32(stop), depths, weight) + extra)
    return (rt.from_device(depths, (by, bx, k), wait_for=[evt]),
            rt.from_device(weight, (by, bx), wait_for=[evt]))
