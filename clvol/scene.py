"""The scene: its data model and its files, as users import them (``from clvol.scene import
Scene, load_scene``).

Two modules hold the code, and this one only re-exports their names:

- clvol/scenemodel.py: the parts (``VolumeSpec``, ``Medium``, ``Phase``, ``Lobe``, ``Light``,
  ``Camera``), the limits on them and the material ``PRESETS``;
- clvol/scenefile.py: ``Scene`` (with ``to_dict`` and ``with_overrides``), reading, validating
  and writing scene files (``load_scene``, ``scene_from_dict``, ``dumps_scene``; format in
  docs/scenes.md).

scenefile.py imports scenemodel.py, and neither imports this module.
"""
from __future__ import annotations

from .scenefile import Scene, dumps_scene, load_scene, load_scene_overridden, scene_from_dict
from .scenemodel import (HG_G_LIMIT, MAX_IMAGE_SIZE, MAX_VDB_RESOLUTION,
                         MHG_MAX_LOBES, MHG_WEIGHT_TOL, PRESETS, VOLUME_SUFFIXES, Camera, Light,
                         Lobe, Medium, Phase, VolumeSpec, EmissionSpec)

__all__ = ["Scene", "load_scene", "load_scene_overridden", "scene_from_dict", "dumps_scene", "VolumeSpec", "EmissionSpec", "Medium",
           "Phase", "Lobe", "Light", "Camera", "PRESETS", "HG_G_LIMIT", "MHG_MAX_LOBES",
           "MHG_WEIGHT_TOL", "MAX_IMAGE_SIZE", "MAX_VDB_RESOLUTION", "VOLUME_SUFFIXES"]
