"""The kernels' argument blocks: ``medium_block`` packs the scene's ``Medium`` and
``light_block`` its ``Light`` into the 16-float arguments (``MediumBlock``, ``LightBlock``:
cl/include/blocks.h, medium.h, light.h) that the ray marcher and the path tracer read. This
module is the only code that knows where each property sits:

- the fixed slots of cl/include/constants.h (MEDIUM_*: density scale, albedo, lobes;
  LIGHT_*: direction, irradiance), which the C host also writes at run time (the bundle names
  them: host.medium_*, host.light_*);
- then each property the scene model declares with ``kernel=True`` (clvol/scenemodel.py
  ``declared``), in the block's free slots in declaration order; the kernels get each one's
  slot as -D MEDIUM_SLOT_<NAME> or LIGHT_SLOT_<NAME> (``block_defines``) and read it with
  ``medium_float`` / ``light_float``.

Both are passed whole (a clvol.scene.Medium or Light): the wrappers, the renderers, the bundle
and libclvol take a new property with no change of their own (docs/architecture.md, "Add a
scene field").
"""
from __future__ import annotations

import numpy as np

from ..errors import ClvolError
from ..scenemodel import Light, Medium, declared_properties
from .constants import kernel_constant
from .phase import lobe_vectors

MEDIUM_FLOATS = kernel_constant("MEDIUM_FLOATS")
SLOT_DENSITY_SCALE = kernel_constant("MEDIUM_DENSITY_SCALE")
SLOT_ALBEDO = kernel_constant("MEDIUM_ALBEDO")
SLOT_LOBE_G = kernel_constant("MEDIUM_LOBE_G")
SLOT_LOBE_W = kernel_constant("MEDIUM_LOBE_W")
LIGHT_FLOATS = kernel_constant("LIGHT_FLOATS")
SLOT_DIRECTION = kernel_constant("LIGHT_DIRECTION")
SLOT_IRRADIANCE = kernel_constant("LIGHT_IRRADIANCE")
MEDIUM_FIRST_FREE = SLOT_LOBE_W + 4       # the first slot for the declared properties
LIGHT_FIRST_FREE = SLOT_IRRADIANCE + 4
# (block's define prefix, its size, its first free slot) per scene-model class
_BLOCKS = {Medium: ("MEDIUM", MEDIUM_FLOATS, MEDIUM_FIRST_FREE),
           Light: ("LIGHT", LIGHT_FLOATS, LIGHT_FIRST_FREE)}


def _block_of(cls):
    for base, spec in _BLOCKS.items():
        if issubclass(cls, base):
            return spec
    raise ClvolError(f"{cls.__name__} has no kernel block (only Medium and Light have)")


def declared_slots(cls) -> dict[str, tuple[int, int]]:
    """{property name: (first slot, floats)} of the properties ``cls`` (Medium or Light, or
    a subclass) declares for the kernels, packed from its block's first free slot in
    declaration order."""
    _, floats, at = _block_of(cls)
    slots = {}
    for name, prop, _ in declared_properties(cls):
        if prop.kernel:
            width = 3 if prop.kind == "rgb" else 1
            slots[name] = (at, width)
            at += width
    if at > floats:
        raise ClvolError(f"{cls.__name__}'s declared kernel properties need {at} floats; its "
                         f"block (cl/include/blocks.h) holds {floats}")
    return slots


def block_defines(medium_cls=Medium, light_cls=Light) -> dict:
    """-D MEDIUM_SLOT_<NAME> and LIGHT_SLOT_<NAME> = slot of each declared kernel property:
    every program that takes the blocks builds with these."""
    d = {}
    for cls in (medium_cls, light_cls):
        prefix = _block_of(cls)[0]
        d.update({f"{prefix}_SLOT_{name.upper()}": at
                  for name, (at, _) in declared_slots(cls).items()})
    return d


def _pack_declared(b: np.ndarray, part) -> np.ndarray:
    for name, (at, width) in declared_slots(type(part)).items():
        b[at:at + width] = getattr(part, name)
    return b


def medium_block(medium) -> np.ndarray:
    """The medium block (cl/include/medium.h) of ``medium`` (a clvol.scene.Medium): float32
    [MEDIUM_FLOATS] holding ``density_scale`` (sigma_t = density * density_scale), the RGB
    ``albedo``, the phase's lobes as ``lobe_vectors`` gives them, then its declared kernel
    properties; the free slots are zero."""
    b = np.zeros(MEDIUM_FLOATS, np.float32)
    b[SLOT_DENSITY_SCALE] = float(medium.density_scale)
    b[SLOT_ALBEDO:SLOT_ALBEDO + 3] = np.asarray(medium.albedo, np.float64)
    b[SLOT_LOBE_G:SLOT_LOBE_G + 4], b[SLOT_LOBE_W:SLOT_LOBE_W + 4] = lobe_vectors(
        medium.phase.pairs)
    return _pack_declared(b, medium)


def light_block(light) -> np.ndarray:
    """The light block (cl/include/light.h) of ``light`` (a clvol.scene.Light): float32
    [LIGHT_FLOATS] holding the unit ``direction`` toward the light and the RGB ``irradiance``
    (each w = 0), then its declared kernel properties; the free slots are zero."""
    b = np.zeros(LIGHT_FLOATS, np.float32)
    b[SLOT_DIRECTION:SLOT_DIRECTION + 3] = np.asarray(light.direction, np.float64)
    b[SLOT_IRRADIANCE:SLOT_IRRADIANCE + 3] = np.asarray(light.irradiance, np.float64)
    return _pack_declared(b, light)
