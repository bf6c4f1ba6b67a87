"""Rendering: the method registry, the result type, and (in this package) the pipeline.

Layout: ``renderer`` (the stateful ``Renderer`` applications hold), ``options`` (options
bound to methods), the two methods ``raymarch`` (the ray marcher and its plan) and
``pathtrace`` (the reference path tracer and point queries), the package ``ms`` (the
multiple-scattering sources, one module each, and the ``--ms`` registry in its ``__init__``),
``environment`` (sky light for the marcher) and ``sphere`` (direction sets). The volume on the
device that every method reads (``DeviceMedium``) is clvol/kernels/medium.py's.

Render-method registry shared by the CLI and Python callers.

A render method lives in its own module and exposes ``add_arguments(group)``: its own
``argparse`` options (names must not clash with the common ones defined in ``clvol.cli``).
The ``Renderer`` (clvol/render/renderer.py) runs every method; the CLI builds one from the
options the user gave.

Methods are imported lazily so that ``clvol info`` or ``clvol compare`` never build kernels.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field

import numpy as np

from ..errors import ClvolError

# name -> (module, one-line description)
METHODS: dict[str, tuple[str, str]] = {
    "pathtrace": ("clvol.render.pathtrace", "reference volumetric path tracer (ground truth, noisy, slow)"),
    "raymarch": ("clvol.render.raymarch", "real-time ray marcher: exact single scattering + "
                 "multiple scattering from the trained network (default) or an analytic source"),
}


@dataclass
class RenderResult:
    """``layers``: "total" (H, W, 3) plus AOVs; ``header``: metadata for the EXR header,
    including which effects were simulated and which were skipped."""
    layers: dict[str, np.ndarray]
    header: dict[str, str | int | float] = field(default_factory=dict)

    def layer(self, name: str) -> np.ndarray:
        """One layer, or a ClvolError naming the layers this method made (the path tracer,
        for one, makes no alpha or depth)."""
        if name not in self.layers:
            method = self.header.get("method", "this method")
            raise ClvolError(f"RenderResult: {method} made no {name!r} layer; it has "
                             f"{', '.join(sorted(self.layers))}")
        return self.layers[name]

    total = property(lambda self: self.layer("total"))
    single = property(lambda self: self.layer("single"))
    multiple = property(lambda self: self.layer("multiple"))
    alpha = property(lambda self: self.layer("alpha"))
    depth = property(lambda self: self.layer("depth"))


def method_module(name: str):
    """Import the module of a render method, or say clearly that it is not available."""
    if name not in METHODS:
        raise ClvolError(f"unknown render method {name!r}; choose one of {sorted(METHODS)}")
    modname = METHODS[name][0]
    try:
        return importlib.import_module(modname)
    except ModuleNotFoundError as exc:
        if exc.name != modname:
            raise
        raise ClvolError(f"render method {name!r} is not implemented in this version of clvol")


def available_methods() -> dict[str, object]:
    """The methods whose modules import, by name."""
    out = {}
    for name in METHODS:
        try:
            out[name] = method_module(name)
        except ClvolError:
            pass
    return out
