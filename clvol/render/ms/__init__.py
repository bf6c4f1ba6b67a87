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
from .lattice import LatticeMs
from .analytic import NoMs, OctavesMs
from .base import SourceOption, option
from .view import StochasticViewMs, ViewMs
from .progressive import ProgressiveViewMs

# In the order --ms's help lists them (their options follow in the same order).
SOURCES: dict[str, type] = {cls.name: cls for cls in
                            (NetworkMs, ViewMs, StochasticViewMs, ProgressiveViewMs, OctavesMs,
                             LatticeMs, NoMs)}
DEFAULT_SOURCE = NetworkMs.name


def source_classes() -> dict[str, type]:
    """Every ``--ms`` source by name."""
    return SOURCES


def source_class(ms: str) -> type:
    if ms not in SOURCES:
        raise ClvolError(f"raymarch option ms = {ms!r}: choose one of {sorted(SOURCES)}")
    return SOURCES[ms]


def source_options() -> list[SourceOption]:
    """The ray marcher's source options: ``--ms`` (its help lists each source's ``summary``),
    then every source's own ``options``, each once (the sources that share one, such as
    ``--weights``, declare the same object)."""
    entries = ", ".join(f"{name} ({cls.summary}{', default' if name == DEFAULT_SOURCE else ''})"
                        for name, cls in SOURCES.items())
    out = [option("--ms", choices=sorted(SOURCES), default=DEFAULT_SOURCE,
                  help=f"multiple-scattering source: {entries}")]
    seen = {"ms"}
    for cls in SOURCES.values():
        for opt in cls.options:
            if opt.name not in seen:
                seen.add(opt.name)
                out.append(opt)
    return out
