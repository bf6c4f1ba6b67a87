"""A volume on the device: its density and the majorant grid built from it.

``DeviceMedium`` is what every render method needs of a volume before any light or camera:
the density grid (raw, sigma_t = density * density_scale) and the per-block maximum that
empty-space skipping and delta tracking read (cl/include/majorant.h). Derived device data
(e.g. the light field's pyramid) is kept in ``cache`` and lives as long as the medium.
The ray marcher (clvol/render/raymarch.py) and the path tracer (clvol/kernels/pathtrace.py)
both read it; a ``Renderer`` uploads one per volume.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ClvolError
from ..runtime import DeviceArray, get_runtime

# Voxels per majorant block per axis, for every method: small enough to skip the empty space
# around a cloud, large enough that the coarse grid's DDA takes few steps.
DEFAULT_BLOCK = 8


def majorant_block(block, grid_shape) -> int:
    """Voxels per majorant block per axis; 0 means one global majorant."""
    if isinstance(block, bool) or not isinstance(block, (int, np.integer)) or block < 0:
        raise ClvolError(f"majorant block = {block!r}: must be an integer >= 0 (0 = one global "
                         f"majorant)")
    return int(block) if block else max(grid_shape)


@dataclass(eq=False)
class DeviceMedium:
    """``grid``: the volume (a clvol Grid, or anything with a [z][y][x] ``density`` and
    ``bbox_min``/``bbox_max``); ``block``: voxels per majorant cell (already resolved: never 0)."""
    grid: object
    block: int
    density: DeviceArray
    majorant: DeviceArray
    runtime: object = field(repr=False)
    cache: dict = field(default_factory=dict, repr=False)

    @classmethod
    def upload(cls, grid, block: int = DEFAULT_BLOCK, runtime=None) -> "DeviceMedium":
        from ..kernels.majorant import build_majorant_buffer
        rt = runtime or get_runtime()
        if np.ndim(grid.density) != 3:
            raise ClvolError(f"density must be 3-D [z][y][x], got shape {np.shape(grid.density)}")
        b = majorant_block(block, grid.density.shape)
        density = rt.upload(grid.density)
        buf, shape = build_majorant_buffer(density.buffer, density.shape, b, rt)
        return cls(grid, b, density, DeviceArray(buf, shape, np.dtype(np.float32), rt), rt)
