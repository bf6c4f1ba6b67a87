"""Small scene files for tests, written from the four tables of docs/scenes.md.

    write_scene(tmp_path / "s.toml", volume={"generator": "sphere", "resolution": 8},
                medium={"preset": "cloud", "density_scale": 8.0},
                light={"direction": [0.0, 1.0, 0.0]},
                camera={**CAMERA, "width": 6, "height": 5})

Values are written as TOML literals: str, bool, int, float, list, and dict as an inline table.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

# The camera most tests look from (width and height are each test's own).
CAMERA = {"origin": [0.0, 0.0, 2.5], "target": [0.0, 0.0, 0.0], "fov_y": 35.0}
# A small procedural cloud that renders in well under a second.
SMALL_CLOUD = {"volume": {"generator": "cloud", "seed": 4, "resolution": 16},
               "medium": {"preset": "cloud", "density_scale": 30.0},
               "light": {"direction": [0.5, 0.8, 0.3]},
               "camera": {"origin": [0.3, 0.4, 2.2], "target": [0.0, 0.0, 0.0], "fov_y": 35.0,
                          "width": 12, "height": 10}}


def toml_value(v) -> str:
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    return repr(v)


def scene_toml(volume: dict, medium: dict, light: dict, camera: dict,
               emission: dict | None = None) -> str:
    tables = {"volume": volume, "medium": medium, "light": light, "camera": camera}
    if emission is not None:
        tables["emission"] = emission
    return "".join(f"[{name}]\n" + "".join(f"{k} = {toml_value(v)}\n" for k, v in t.items())
                   for name, t in tables.items())


def write_scene(path, **tables) -> Path:
    path = Path(path)
    path.write_text(scene_toml(**tables))
    return path


def look_at(origin, target, up=(0.0, 1.0, 0.0)):
    """(forward, right, up) unit vectors of a pinhole at ``origin`` looking at ``target``, as
    grid.h's camera_ray reads them (right = forward x up), for kernel tests that pass a camera
    by its basis."""
    f = np.subtract(target, origin, dtype=np.float64)
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    return f, r, np.cross(r, f)
