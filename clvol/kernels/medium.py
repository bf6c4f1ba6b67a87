"""``DeviceMedium``: a volume on the device and the grids derived from it alone, owned in one
place (as pbrt-v4's ``GridMedium`` owns its density grid and its ``MajorantGrid``).

    dm = DeviceMedium.upload(grid, block)       # the density (uploaded once) + majorant grid
    pyr = dm.pyramid(64)                        # density on a 64^3 cube + mips (kept)
    T = dm.light_field(light_dir, density_scale, "transmittance", 256)   # (256,)*3 DeviceArray

- ``density``: the [z][y][x] density (raw: sigma_t = density * density_scale), a DeviceArray
  uploaded once per volume (the only upload of the full density);
- ``majorant``: the per-block maximum that empty-space skipping and delta tracking read
  (clvol/kernels/majorant.py), built on the device from ``density``;
- ``pyramid(res)``: the density padded to its centred cube, resampled to res^3 and mip-mapped
  (clvol/kernels/pyramid.py), one per resolution, kept: the light field's, the network's (at
  its weights' base resolution) and the environment's sweeps all come from here. No kernel
  resamples, so level 0 is resampled on the host from the grid and only those res^3 values go
  up; a grid that already is the res^3 cube is copied from ``density`` on the device;
- ``light_field(light_dir, density_scale, quantity, res)``: the exact transmittance (or optical
  depth) toward the light at the voxel centres of ``pyramid(res)``'s cube, for the ray
  marcher's single scattering (clvol/kernels/transmittance.py); the last one per resolution
  and quantity is kept and returned again for the same light direction and density scale.

Everything derived lives in ``cache`` and dies with the medium; a ``Renderer`` makes one
medium per volume (``Renderer.device_medium``, again on ``set_density``) and both methods read
it: the ray marcher (clvol/render/raymarch.py) and its network source, and the path tracer
(clvol/kernels/pathtrace.py). The sources get it in their frame input
(``SourceFrame.device_medium``), the environment's transmittance when it is made.

This module wraps no kernel of its own: it composes the wrappers of majorant.cl, pyramid.cl
and transmittance.cl.

The medium block the kernels take (its optical properties) is clvol/kernels/blocks.py's.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ClvolError
from ..runtime import DeviceArray, get_runtime
from .majorant import DEFAULT_BLOCK, build_majorant_buffer, majorant_block


@dataclass(eq=False)
class DeviceMedium:
    """``grid``: the volume (a clvol DensityGrid, or for the path tracer anything with a [z][y][x]
    ``density`` and ``bbox_min``/``bbox_max``); ``block``: voxels per majorant cell (already
    resolved: never 0); ``density``, ``majorant``: DeviceArrays."""
    grid: object
    block: int
    density: DeviceArray
    majorant: DeviceArray
    runtime: object = field(repr=False)
    cache: dict = field(default_factory=dict, repr=False)
    light_builds: int = 0          # light fields computed (light_field calls that missed)

    @classmethod
    def upload(cls, grid, block: int = DEFAULT_BLOCK, runtime=None) -> "DeviceMedium":
        rt = runtime or get_runtime()
        if np.ndim(grid.density) != 3:
            raise ClvolError(f"density must be 3-D [z][y][x], got shape {np.shape(grid.density)}")
        b = majorant_block(block, grid.density.shape)
        density = rt.upload(grid.density, label="density")
        return cls(grid, b, density, build_majorant_buffer(density, b, rt), rt)

    def pyramid(self, resolution: int):
        """The density resampled to a ``resolution``^3 cube with its mips (a Pyramid), built
        on first use and kept."""
        from .pyramid import build_pyramid
        key = ("pyramid", int(resolution))
        if key not in self.cache:
            self.cache[key] = build_pyramid(self.grid, resolution, self.runtime,
                                            density=self.density)
        return self.cache[key]

    def light_field(self, light_dir, density_scale: float, quantity: str = "transmittance",
                    resolution: int = 256) -> DeviceArray:
        """The exact light field toward ``light_dir`` (unit or not) for ``density_scale``:
        T, or the optical depth with ``quantity="optical_depth"``, at the voxel centres of
        ``pyramid(resolution)``'s cube, as an (n, n, n) DeviceArray. The last one per
        (resolution, quantity) is kept and returned again while the light direction and the
        density scale stay the same."""
        from .transmittance import check_light_dir, light_transmittance
        l = check_light_dir(light_dir)
        key = ("light_field", int(resolution), quantity)
        want = (tuple(l), float(density_scale))
        hit = self.cache.get(key)
        if hit is not None and hit[0] == want:
            return hit[1]
        self.cache.pop(key, None)          # one at a time: the old field's memory goes first
        out = light_transmittance(self.pyramid(resolution), density_scale, l,
                                  quantity=quantity, as_buffer=True)
        self.cache[key] = (want, out)
        self.light_builds += 1
        return out
