"""Density grids: the ``Grid`` type, file I/O, procedural generators and statistics.

    from clvol.volume import Grid, read_volume, write_volume, generate, GENERATORS, volume_stats

Conventions (docs/volumes.md): density is float32 ``[z][y][x]`` (x fastest), finite and >= 0,
filling the box ``bbox_min..bbox_max``; voxel ``i`` sits at the centre of cell ``i``.
"""
from .generators import GENERATORS, GeneratorInfo, Param, generate
from .grid import Grid
from .io import read_volume, write_volume
from .stats import format_stats, volume_stats

__all__ = ["Grid", "read_volume", "write_volume", "generate", "GENERATORS", "GeneratorInfo",
           "Param", "volume_stats", "format_stats"]
