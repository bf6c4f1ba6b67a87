"""Multiple-scattering sources of the ray marcher, one module each, and the ``--ms`` registry.

An explicit table: every source module is imported here and listed once, so reading the registry
never depends on which module happened to be imported first (no registration by import side
effect). The interface is base.py's; the sources are analytic.py's (none, wrenninge), grid.py's
(grid), network.py's (network: the paper's world lattice) and view.py's (view, stochastic: the
network where the camera sees), progressive.py's (progressive: that refined by path-traced
point queries). This module sits above them all (they never import it).
"""
from __future__ import annotations

from ...errors import ClvolError
from .network import NetworkMs
from .grid import GridMs
from .analytic import NoMs, OctavesMs
from .view import StochasticViewMs, ViewMs
from .progressive import ProgressiveViewMs

SOURCES: dict[str, type] = {cls.name: cls for cls in
                            (NoMs, OctavesMs, GridMs, NetworkMs, ViewMs, StochasticViewMs,
                                                  ProgressiveViewMs)}


def source_classes() -> dict[str, type]:
    """Every ``--ms`` source by name."""
    return SOURCES


def source_class(ms: str) -> type:
    if ms not in SOURCES:
        raise ClvolError(f"raymarch option ms = {ms!r}: choose one of {sorted(SOURCES)}")
    return SOURCES[ms]
