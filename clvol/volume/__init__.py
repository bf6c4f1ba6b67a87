"""Density grids: the ``DensityGrid`` type, file I/O, procedural generators and statistics.

    from clvol.volume import DensityGrid, read_volume, write_volume, generate, GENERATORS, volume_stats

Conventions (docs/volumes.md): density is float32 ``[z][y][x]`` (x fastest), finite and >= 0,
filling the box ``bbox_min..bbox_max``; voxel ``i`` sits at the centre of cell ``i``.

The names are resolved lazily (PEP 562), so ``import clvol.volume.grid`` does not import the
generators (or anything else) as a side effect.
"""
import importlib

_EXPORTS = {
    "DensityGrid": "grid",
    "read_volume": "io", "write_volume": "io",
    "generate": "generators", "GENERATORS": "generators", "GeneratorInfo": "generators",
    "Param": "generators",
    "volume_stats": "stats", "format_stats": "stats",
}
__all__ = list(_EXPORTS)


def __getattr__(name):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'clvol.volume' has no attribute {name!r}")
    return getattr(importlib.import_module(f".{module}", __name__), name)


def __dir__():
    return sorted(set(globals()) | set(__all__))
