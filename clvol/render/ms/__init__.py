"""The ``--ms`` names of the ray marcher's multiple-scattering sources, and their classes.

An explicit table: every source module is imported here and listed once, so reading the registry
never depends on which module happened to be imported first. The interface and the analytic
sources are clvol/render/sources.py's; the network sources are clvol/render/network.py's and
clvol/render/view.py's. This module sits above all three (they never import it).
"""
from __future__ import annotations

from ..errors import ClvolError
from .network import NetworkMs
from .sources import GridMs, NoMs, OctavesMs
from .view import StochasticViewMs, ViewMs

SOURCES: dict[str, type] = {cls.name: cls for cls in
                            (NoMs, OctavesMs, GridMs, NetworkMs, ViewMs, StochasticViewMs)}


def source_classes() -> dict[str, type]:
    """Every ``--ms`` source by name."""
    return SOURCES


def source_class(ms: str) -> type:
    if ms not in SOURCES:
        raise ClvolError(f"raymarch option ms = {ms!r}: choose one of {sorted(SOURCES)}")
    return SOURCES[ms]
