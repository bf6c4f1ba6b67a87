"""The ray-marching render method (moved to clvol/render/; these names stay importable).

New code: ``clvol.Renderer(scene, "raymarch", ms=...)`` (clvol/render/renderer.py), the
sources in clvol/render/sources.py and clvol/render/network.py.
"""
from .render.network import (DEFAULT_NETWORK_RESOLUTION, NETWORK_CHUNK, NetworkMs,  # noqa: F401
                             NetworkSource, load_network_weights, shipped_weights)
from .render.network import check_ms_resolution as _check_ms_resolution
from .render.raymarch import (DEFAULT_BLOCK, DEFAULT_STEP, DEFAULT_THRESHOLD,  # noqa: F401
                              MAX_LIGHT_RESOLUTION, MAX_SUPERSAMPLE, Plan, RayMarcher,
                              add_arguments, auto_light_resolution, downsample, render,
                              render_raymarch)
from .render.sources import (SOURCES, MsGrid, Octaves, fill_ms_grid, load_ms_grid,  # noqa: F401
                             ms_lattice)
from .render.sources import check_ms_grid as _check_ms_grid  # noqa: F401

MS_SOURCES = tuple(sorted(SOURCES))


def _check_network_options(weights, ms_resolution):
    from .errors import ClvolError
    if weights is None:
        raise ClvolError("raymarch option ms = 'network' needs a weight file (--weights FILE.npz, "
                         "or weights=... in Python)")
    _check_ms_resolution(ms_resolution)
