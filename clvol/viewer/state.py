"""What a viewer client may ask for, checked, and how it becomes scene objects.

A client sends partial updates (JSON objects); ``ViewState.update`` checks every field against
``LIMITS`` and refuses the whole message on the first bad one, so a bad message never leaves a
half-applied state. The orbit and the sun are angles about the scene camera's ``up`` axis, so
the first frame is exactly the scene file's own view (azimuth 0 = the file's camera).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ClvolError
from ..scene import PRESETS, Camera, Light, Medium, Phase, Scene


class ViewerMessageError(ClvolError):
    """A client message the viewer refuses (the reply names the field and the allowed range)."""


# The viewer's method menu: label -> Renderer keyword options. The first is the default, the
# same source as every other front door's (clvol.render.ms DEFAULT_SOURCE; tests/test_defaults.py
# holds them together): the paper's network at one free-flight point per pixel block per frame,
# reprojected while the camera moves and accumulated while it is still (clvol/render/ms/view.py).
# "progressive" refines a still view further, toward path-traced F_ms (clvol/render/ms/
# progressive.py; Python only, so not the default). Both beat the lattice ("network") under
# motion because a camera move costs them no refill (docs/accuracy.md, "Defaults").
# The interactive methods refresh the network's sky for one sky cell per frame after a camera
# move (all 32 at once cost about 1 s on 2 CPU cores, docs/raymarch.md "Environment light");
# a still view refines until every cell is current.
METHODS: dict[str, dict] = {
    "stochastic": {"method": "raymarch", "ms": "stochastic", "env_ms_per_frame": 1},
    "progressive": {"method": "raymarch", "ms": "progressive", "env_ms_per_frame": 1},
    "network": {"method": "raymarch", "ms": "network", "env_ms_per_frame": 1},  # 32^3 lattice
    "wrenninge": {"method": "raymarch", "ms": "wrenninge"},
    "single": {"method": "raymarch", "ms": "none"},
    "pathtrace": {"method": "pathtrace"},
}
RESOLUTIONS = (64, 128, 256, 512)
MAX_SKY_MAPS = 32          # .exr files looked at in the scene's folder


def sky_maps(scene: Scene) -> dict[str, Path]:
    """The environment maps the viewer's map menu offers, by file name: the scene's own map
    and every valid lat-long EXR (clvol.envmap.read_map's checks) in the scene file's folder.
    Rendered images lying there (not 2:1, or without RGB) are left out, silently: the menu
    lists what can be picked, nothing else. A client names a map; it never sends a path."""
    from ..envmap import has_map_shape, load_map
    from ..errors import ImageError
    maps: dict[str, Path] = {}
    own = scene.light.environment_map
    if own is not None:
        maps[Path(own).name] = Path(own)
    folder = Path(scene.path).parent if getattr(scene, "path", None) else None
    if folder is not None and folder.is_dir():
        for p in sorted(folder.glob("*.exr"))[:MAX_SKY_MAPS]:
            if p.name in maps or not has_map_shape(p):    # header only: renders are skipped
                continue
            try:
                load_map(p)
            except ImageError:
                continue
            maps[p.name] = p.resolve()
    return maps

# field -> (lo, hi) for numbers; every number must also be finite.
LIMITS: dict[str, tuple[float, float]] = {
    "azimuth": (-1e6, 1e6),        # degrees, any winding
    "elevation": (-89.0, 89.0),    # degrees; the poles would make the orbit frame degenerate
    "distance": (0.05, 100.0),     # world units, camera to target
    "sun_azimuth": (-1e6, 1e6),
    "sun_elevation": (-90.0, 90.0),
    "g": (-0.99, 0.99),
    "density_scale": (1e-4, 1e4),
    "exposure": (-20.0, 20.0),     # stops
    "albedo": (0.0, 1.0),          # per channel
    "sky": (0.0, 1e3),             # per channel: sky radiance (or an environment map's scale)
}


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    n = float(np.linalg.norm(v))
    if not n > 0.0:
        raise ClvolError("zero-length vector")
    return v / n


def orbit_frame(camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(up, x0, y0)``: the orbit axis and two unit vectors spanning its plane, with ``x0``
    toward the scene camera's horizontal direction (azimuth 0)."""
    up = _unit(camera.up)
    d = np.subtract(camera.origin, camera.target, dtype=np.float64)
    flat = d - np.dot(d, up) * up
    if np.linalg.norm(flat) < 1e-9 * max(1.0, float(np.linalg.norm(d))):
        # Camera straight above/below the target: any horizontal direction will do.
        flat = np.cross(up, [1.0, 0.0, 0.0])
        if np.linalg.norm(flat) < 1e-6:
            flat = np.cross(up, [0.0, 0.0, 1.0])
    x0 = _unit(flat)
    return up, x0, np.cross(up, x0)


def _direction(frame, azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    up, x0, y0 = frame
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return math.cos(el) * (math.cos(az) * x0 + math.sin(az) * y0) + math.sin(el) * up


def _angles(frame, v) -> tuple[float, float]:
    up, x0, y0 = frame
    v = _unit(v)
    el = math.degrees(math.asin(max(-1.0, min(1.0, float(np.dot(v, up))))))
    az = math.degrees(math.atan2(float(np.dot(v, y0)), float(np.dot(v, x0))))
    return az, el


@dataclass
class ViewState:
    """Everything a frame depends on. ``exposure`` only changes the tone mapping."""
    azimuth: float
    elevation: float
    distance: float
    sun_azimuth: float
    sun_elevation: float
    albedo: tuple[float, float, float]
    g: float
    density_scale: float
    # None: chosen from the image (clvol.image.auto_exposure); "scene": from the scene's light
    # (clvol.image.scene_exposure); a number: stops.
    exposure: float | str | None = None
    method: str = next(iter(METHODS))
    resolution: int = 256
    preset: str | None = None
    # The sky: a constant environment radiance (RGB; all 0 = no sky), or with ``sky_map``
    # the map's scale.
    sky: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # None: the constant sky above; else the file name of an environment map (sky_maps()).
    sky_map: str | None = None
    # A volume sequence's frame (the play control); None for a single volume.
    frame: int | None = None

    @classmethod
    def from_scene(cls, scene: Scene) -> "ViewState":
        cam = scene.camera
        frame = orbit_frame(cam)
        d = np.subtract(cam.origin, cam.target, dtype=np.float64)
        _, el = _angles(frame, d)
        sun_az, sun_el = _angles(frame, scene.light.direction)
        lobes = scene.medium.phase.lobes
        return cls(azimuth=0.0, elevation=float(np.clip(el, *LIMITS["elevation"])),
                   distance=float(np.linalg.norm(d)), sun_azimuth=sun_az, sun_elevation=sun_el,
                   albedo=tuple(float(a) for a in scene.medium.albedo),
                   g=float(lobes[0].g) if len(lobes) == 1 else scene.medium.phase.mean_cosine,
                   density_scale=float(scene.medium.density_scale),
                   resolution=int(cam.width) if cam.width in RESOLUTIONS else 256,
                   preset=scene.medium.preset,
                   sky=tuple(float(v) for v in (
                       scene.light.environment_scale if scene.light.environment_map is not None
                       else scene.light.environment or (0.0, 0.0, 0.0))),
                   sky_map=(Path(scene.light.environment_map).name
                            if scene.light.environment_map is not None else None),
                   frame=_first_frame(scene))

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    def update(self, changes: dict, maps=()) -> "ViewState":
        """A new state with ``changes`` applied, every field checked; raises
        ``ViewerMessageError`` naming the first bad field. ``maps``: the names ``sky_map``
        may take (sky_maps())."""
        if not isinstance(changes, dict):
            raise ViewerMessageError("state: expected a JSON object")
        new = dataclasses.replace(self)
        names = {f.name for f in dataclasses.fields(self)}
        for key, value in changes.items():
            if key not in names:
                raise ViewerMessageError(f"{key!r}: unknown field; allowed: {', '.join(sorted(names))}")
            if key == "sky_map":
                if value is not None and (not isinstance(value, str) or value not in maps):
                    raise ViewerMessageError(
                        f"sky_map: {value!r} is not one of the maps offered "
                        f"({', '.join(maps) or 'none'}); null for a constant sky")
                new.sky_map = value
                continue
            setattr(new, key, _check_field(key, value))
        if "preset" in changes and new.preset is not None and not (
                {"albedo", "g"} & changes.keys()):
            albedo, phase = PRESETS[new.preset]
            new.albedo = tuple(albedo)
            new.g = phase.mean_cosine
        return new

    # --------------------------------------------------------------- scene objects
    def camera(self, base: Camera) -> Camera:
        frame = orbit_frame(base)
        target = np.asarray(base.target, dtype=np.float64)
        origin = target + self.distance * _direction(frame, self.azimuth, self.elevation)
        return dataclasses.replace(base, origin=tuple(origin.tolist()), width=self.resolution,
                                   height=self.resolution)

    def light(self, base: Light, camera: Camera, maps=None) -> Light:
        """The scene's light with the client's sun and sky. ``maps``: sky_maps() of the
        scene, where ``sky_map`` is looked up (the scene's own map needs none)."""
        d = _direction(orbit_frame(camera), self.sun_azimuth, self.sun_elevation)
        if self.sky_map is not None:
            own = base.environment_map
            path = (Path(own) if own is not None and Path(own).name == self.sky_map
                    else (maps or {}).get(self.sky_map))
            if path is None:
                raise ViewerMessageError(f"sky_map: {self.sky_map!r} is not a known map")
            return dataclasses.replace(base, direction=tuple(d.tolist()), environment=None,
                                       environment_map=path, environment_scale=tuple(self.sky))
        sky = tuple(self.sky) if any(v > 0 for v in self.sky) else None
        return dataclasses.replace(base, direction=tuple(d.tolist()), environment=sky,
                                   environment_map=None)

    def medium(self, base: Medium) -> Medium:
        """The scene's medium with the client's albedo, density scale and phase. A preset
        keeps its own (multi-lobe) phase until the client moves the g slider."""
        phase = base.phase
        preset_phase = PRESETS[self.preset][1] if self.preset else None
        if preset_phase is not None and abs(preset_phase.mean_cosine - self.g) < 1e-9:
            phase = preset_phase
        elif len(phase.lobes) != 1 or phase.lobes[0].g != self.g:
            phase = Phase.hg(self.g)
        return dataclasses.replace(base, albedo=self.albedo, density_scale=self.density_scale,
                                   phase=phase, preset=self.preset)

    def accumulation_key(self) -> tuple:
        """Frames that may be averaged by the progressive path tracer share this key."""
        d = self.to_json()
        d.pop("exposure")
        return tuple(sorted((k, tuple(v) if isinstance(v, list) else v) for k, v in d.items()))


def _number(key: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ViewerMessageError(f"{key}: expected a number, got {value!r}")
    lo, hi = LIMITS[key]
    if not (math.isfinite(value) and lo <= value <= hi):
        raise ViewerMessageError(f"{key}: {value!r} is out of range [{lo:g}, {hi:g}]")
    return float(value)


def _first_frame(scene) -> int | None:
    """A sequence's frame to show first: the scene's ``frame``, else the first file found."""
    if not scene.volume.is_sequence:
        return None
    if scene.volume.frame is not None:
        return int(scene.volume.frame)
    from ..sequence import available_frames
    found = available_frames(scene.volume)
    return found[0] if found else None


def _check_field(key: str, value):
    if key in ("albedo", "sky"):
        if not isinstance(value, (list, tuple)) or len(value) != 3:
            raise ViewerMessageError(f"{key}: expected [r, g, b], got {value!r}")
        return tuple(_number(key, v) for v in value)
    if key == "exposure" and (value is None or (isinstance(value, str) and value == "scene")):
        return value
    if key == "exposure" and isinstance(value, str):
        raise ViewerMessageError(f"exposure: {value!r} is not a number of stops, null (from "
                                 f"the image) or \"scene\" (from the light)")
    if key in LIMITS:
        return _number(key, value)
    if key == "method":
        if not isinstance(value, str) or value not in METHODS:
            raise ViewerMessageError(f"method: {value!r} is not one of {', '.join(METHODS)}")
        return value
    if key == "resolution":
        if value not in RESOLUTIONS or isinstance(value, bool):
            raise ViewerMessageError(f"resolution: {value!r} is not one of {RESOLUTIONS}")
        return int(value)
    if key == "frame":
        if value is not None and (isinstance(value, bool) or not isinstance(value, int)
                                  or not 0 <= value <= 10**9):
            raise ViewerMessageError(f"frame: {value!r} is not a frame number (an integer >= 0)")
        return value
    if key == "preset":
        # a str first: a list or dict would raise TypeError in the dict lookup (fuzzing)
        if value is not None and (not isinstance(value, str) or value not in PRESETS):
            raise ViewerMessageError(f"preset: {value!r} is not one of {', '.join(PRESETS)}")
        return value
    raise ViewerMessageError(f"{key}: unknown field")
