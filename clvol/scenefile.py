"""Scene files: a TOML description of a volume, its medium, a light and a camera.

The format is documented in ``docs/scenes.md``; in short::

    [volume]   file = "x.vol" | "x.npy" | "x.npz" | "x.vdb" (+ grid, max_resolution for .vdb)
               or   generator = "cloud" (+ seed, resolution, params)
    [medium]   preset, density_scale, albedo, phase
    [light]    direction (toward the light), irradiance, environment (constant sky)
               or environment_map = "sky.exr" (+ environment_scale, environment_rotation)
    [camera]   origin, target, up, fov_y (degrees), width, height

Every field is validated when the scene is loaded and unknown keys are errors (a typo
must not be silently ignored). A bad field raises ``SceneError`` whose message starts
with the file name and the dotted field, quotes the bad value and says what is allowed::

    examples/x.toml: [medium.albedo] = [1.2, 0.5, 0.5]: each component must be in [0, 1]

``Scene`` (the whole scene, its dict form ``to_dict`` and ``with_overrides``) is defined here,
beside the parser it validates through; its parts are clvol/scenemodel.py's. Import all of them
from clvol/scene.py.
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .errors import SceneError, VolumeError
from .scenemodel import (_ALREADY_UNIT, HG_G_LIMIT, MAX_IMAGE_SIZE, MAX_VDB_RESOLUTION,
                         MHG_MAX_LOBES, MHG_WEIGHT_TOL, PRESETS, VOLUME_SUFFIXES, Camera,
                         EmissionSpec, Light, Lobe, Medium, Phase, VolumeSpec, declared_properties,
                         is_frame_pattern)


# --------------------------------------------------------------------------- the scene

# Fields that depend on another: overriding the key drops them unless they are overridden too
# (Scene.with_overrides). A constant sky (light.environment, not None) replaces a map.
OVERRIDE_RESETS = {
    "medium.preset": ("medium.albedo", "medium.phase"),
    "light.environment_map": ("light.environment_scale", "light.environment_rotation"),
    "light.environment": ("light.environment_map", "light.environment_scale",
                          "light.environment_rotation"),
}


@dataclass(frozen=True)
class Scene:
    path: Path | None
    volume: VolumeSpec
    medium: Medium
    light: Light
    camera: Camera
    emission: EmissionSpec | None = None

    def to_dict(self) -> dict:
        """Plain dict that ``scene_from_dict`` turns back into an equal scene.

        The volume file is written as an absolute path; the medium is written fully
        resolved (preset name kept for information, plus its albedo and phase).
        """
        v = self.volume
        vol: dict[str, Any] = {}
        if v.file is not None:
            vol["file"] = str(v.file)
            if v.grid is not None:
                vol["grid"] = v.grid
            if v.max_resolution is not None:
                vol["max_resolution"] = v.max_resolution
            if v.frame is not None:
                vol["frame"] = v.frame
        else:
            vol["generator"] = v.generator
            vol["seed"] = v.seed
            if v.resolution is not None:
                vol["resolution"] = (list(v.resolution) if isinstance(v.resolution, tuple)
                                     else v.resolution)
            if v.params:
                vol["params"] = dict(v.params)
        if v.bbox_min is not None:
            vol["bbox_min"] = list(v.bbox_min)
            vol["bbox_max"] = list(v.bbox_max)
        out = {"volume": vol, "medium": _medium_to_dict(self.medium),
               "light": _light_to_dict(self.light), "camera": _camera_to_dict(self.camera)}
        if self.emission is not None:
            e = self.emission
            out["emission"] = {"grid": e.grid, "kind": e.kind, "scale": e.scale}
            if e.kind == "radiance":
                out["emission"]["colour"] = list(e.colour)
        return out

    def with_overrides(self, overrides: dict[str, Any], source: str = "<override>") -> "Scene":
        """A validated copy with dotted fields replaced, e.g. ``{"camera.width": 512}``.

        A value of ``None`` removes the field (e.g. ``"light.environment"``). A field that
        others depend on takes them along unless they are overridden too (OVERRIDE_RESETS):
        setting ``"medium.preset"`` resets albedo and phase to the preset's; setting or
        removing ``"light.environment_map"`` drops its scale and rotation; a constant
        ``"light.environment"`` replaces the map with them. Errors name ``source`` as the file.
        """
        data = self.to_dict()
        for key, value in overrides.items():
            if key in OVERRIDE_RESETS and not (key == "light.environment" and value is None):
                for dep in OVERRIDE_RESETS[key]:
                    if dep not in overrides:
                        table, field = dep.split(".")
                        data.get(table, {}).pop(field, None)
        for dotted, value in overrides.items():
            parts = dotted.split(".")
            node = data
            for p in parts[:-1]:
                node = node.setdefault(p, {})
                if not isinstance(node, dict):
                    raise SceneError(f"{source}: [{dotted}]: {p} is not a table")
            if value is None:
                node.pop(parts[-1], None)
            else:
                node[parts[-1]] = value
        s = scene_from_dict(data, source=source)
        return dataclasses.replace(s, path=self.path)



def _medium_to_dict(m: Medium) -> dict:
    med: dict[str, Any] = {}
    if m.preset is not None:
        med["preset"] = m.preset
    med["density_scale"] = m.density_scale
    med["albedo"] = _listed(m.albedo)
    med["phase"] = _phase_to_dict(m.phase)
    med.update(_declared_to_dict(m))
    return med


def _declared_to_dict(obj) -> dict:
    """The declared properties of ``obj`` (clvol/scenemodel.py ``declared``) as the file
    writes them."""
    return {name: _listed(getattr(obj, name)) if prop.kind == "rgb" else getattr(obj, name)
            for name, prop, _ in declared_properties(type(obj))}


def _declared_keys(cls) -> tuple[str, ...]:
    return tuple(name for name, _, _ in declared_properties(cls))


def _parse_declared(ctx: "_Ctx", table: str, t: dict, cls) -> dict:
    """The declared properties of ``cls`` read from the file's ``[table]`` ``t`` by their
    declarations: kind, range, and the default where the file leaves one out."""
    out = {}
    for name, prop, default in declared_properties(cls):
        if name not in t:
            out[name] = default
        elif prop.kind == "rgb":
            out[name] = _vec3(ctx, f"{table}.{name}", t[name], lo=prop.lo, hi=prop.hi,
                              grey_ok=True)
        else:
            out[name] = _number(ctx, f"{table}.{name}", t[name], prop.lo, prop.hi,
                                prop.lo_open, prop.hi_open)
    return out


def _light_to_dict(li: Light) -> dict:
    light: dict[str, Any] = {"direction": _listed(li.direction),
                             "irradiance": _listed(li.irradiance)}
    if li.environment is not None:
        light["environment"] = _listed(li.environment)
    if li.environment_map is not None:
        light["environment_map"] = str(li.environment_map)
        light["environment_scale"] = _listed(li.environment_scale)
        light["environment_rotation"] = li.environment_rotation
    light.update(_declared_to_dict(li))
    return light


def _camera_to_dict(c: Camera) -> dict:
    return {"origin": _listed(c.origin), "target": _listed(c.target), "up": _listed(c.up),
            "fov_y": c.fov_y, "width": c.width, "height": c.height, **_declared_to_dict(c)}


def _listed(v):
    """A vector field as a list (a tuple, list or array); anything else as it is, for the
    parser to refuse with the field's own message."""
    return list(v) if isinstance(v, (tuple, list, np.ndarray)) else v


def _phase_to_dict(p: Phase) -> dict:
    if p.type == "isotropic":
        return {"type": "isotropic"}
    if p.type == "hg":
        return {"type": "hg", "g": p.lobes[0].g}
    return {"type": "mhg", "lobes": [{"g": l.g, "weight": l.weight} for l in p.lobes]}


# --------------------------------------------------------------------------- loading

def load_scene(path) -> Scene:
    """Read and validate a scene file. Relative volume paths resolve against its folder."""
    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise SceneError(f"{path}: scene file not found") from None
    except OSError as e:
        raise SceneError(f"{path}: cannot read scene file: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise SceneError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"{path}: not valid TOML: {e}") from None
    scene = scene_from_dict(data, source=str(path), base_dir=path.parent)
    return dataclasses.replace(scene, path=path)


# ``--set`` of clvol render, bundle and view (``load_scene_overridden``).
SET_HELP = ("override a scene field, as the file would set it (repeatable), e.g. --set "
            "medium.density_scale=30 --set 'light.irradiance=[2, 2, 2]'; checked like the "
            "file's own fields (docs/scenes.md)")


def load_scene_overridden(path, assignments=(), width: int | None = None,
                          height: int | None = None) -> Scene:
    """``load_scene``, then the command line's overrides (``clvol render``, ``bundle``,
    ``view``): each ``--set TABLE.FIELD=VALUE`` (VALUE a TOML value: ``30``, ``[2, 2, 2]``,
    ``"cloud"``, ``{ type = "hg", g = 0.5 }``), then ``--width`` and ``--height``, checked by
    the file's own rules (``Scene.with_overrides``); messages name the file and the options."""
    scene = load_scene(path)
    over = {}
    for item in assignments or ():
        key, eq, raw = item.partition("=")
        key = key.strip()
        parts = key.split(".")
        if not eq or len(parts) < 2 or not all(parts):
            raise SceneError(f"--set {item!r}: must be TABLE.FIELD=VALUE, e.g. "
                             "medium.density_scale=30 or light.irradiance=[2, 2, 2]")
        try:
            over[key] = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            raise SceneError(f"--set {item!r}: {raw.strip()!r} is not a TOML value (a number, "
                             '[r, g, b], a "string" or a { table })') from None
    for key, flag, value in (("camera.width", "--width", width),
                             ("camera.height", "--height", height)):
        if value is not None:
            if key in over:
                raise SceneError(f"{flag} {value} and --set {key}=...: give one of them")
            over[key] = value
    if not over:
        return scene
    return scene.with_overrides(over, source=f"{path} (with --set/--width/--height)")


def scene_from_dict(data: dict, source: str = "<scene>", base_dir: Path | None = None) -> Scene:
    """Validate a parsed scene. ``source`` names the file in messages; relative volume
    paths resolve against ``base_dir`` (default: the current directory)."""
    ctx = _Ctx(source)
    if not isinstance(data, dict):
        raise SceneError(f"{source}: a scene must be a table, got {type(data).__name__}")
    _check_keys(ctx, "", data, ("volume", "medium", "light", "camera", "emission"),
                kind="table")
    tables = {}
    for name in ("volume", "medium", "light", "camera"):
        if name not in data:
            raise SceneError(f"{source}: [{name}]: missing table")
        if not isinstance(data[name], dict):
            raise ctx.error(name, data[name], "must be a table")
        tables[name] = data[name]
    return Scene(
        path=None,
        volume=_parse_volume(ctx, tables["volume"], Path(base_dir) if base_dir else Path.cwd()),
        medium=_parse_medium(ctx, tables["medium"]),
        light=_parse_light(ctx, tables["light"], Path(base_dir) if base_dir else Path.cwd()),
        camera=_parse_camera(ctx, tables["camera"]),
        emission=_parse_emission(ctx, data["emission"], data["volume"])
        if "emission" in data else None,
    )


def check_part(name: str, value, source: str):
    """A ``Camera``, ``Light`` or ``Medium`` made in code (``dataclasses.replace(scene.camera,
    ...)``, the viewer's state) validated by the scene file's own rules: the same fields,
    ranges and one-line messages (``<source>: [camera.fov_y] = 0.0: must be in (0, 180)``),
    since it is read back through the parser (``name``: "camera", "light" or "medium").

    Returns the validated part: ``value`` itself when the parser leaves it unchanged, else the
    parser's (a unit light direction, MHG weights renormalised, plain floats for arrays)."""
    cls, to_dict, parse = _PARTS[name]
    if not isinstance(value, cls):
        raise SceneError(f"{source}: expected a clvol.scene.{cls.__name__} (e.g. "
                         f"dataclasses.replace(scene.{name}, ...)), got {type(value).__name__}")
    ctx = _Ctx(source)
    data = _plain(to_dict(value) if name != "medium" else _medium_to_check(ctx, value))
    parsed = parse(ctx, data)
    try:
        same = bool(value == parsed)
    except (TypeError, ValueError):       # arrays inside: use the parser's plain tuples
        same = False
    return value if same else parsed


def _medium_to_check(ctx: "_Ctx", m: Medium) -> dict:
    """``_medium_to_dict`` with the phase checked first: a ``Phase`` whose type and lobes agree."""
    p = m.phase
    kinds = {"isotropic": 1, "hg": 1, "mhg": MHG_MAX_LOBES}
    lobes = getattr(p, "lobes", None)
    if not (isinstance(p, Phase) and p.type in kinds and isinstance(lobes, (tuple, list))
            and all(isinstance(lo, Lobe) for lo in lobes)):
        raise SceneError(f"{ctx.source}: [medium.phase] = {p!r}: must be a clvol.scene.Phase: "
                         "Phase.isotropic(), Phase.hg(g) or Phase.mhg([(g, weight), ...])")
    if p.type != "mhg" and (len(lobes) != 1 or lobes[0].weight != 1.0 or
                            (p.type == "isotropic" and lobes[0].g != 0.0)):
        raise SceneError(f"{ctx.source}: [medium.phase] = {p!r}: {'an' if p.type[0] in 'im' else 'a'} {p.type} phase has one "
                         "lobe of weight 1" + (" and g = 0" if p.type == "isotropic" else "")
                         + f" (Phase.{p.type}({'' if p.type == 'isotropic' else 'g'}) makes it)")
    med = _medium_to_dict(m)
    if p.type == "mhg":
        med["phase"] = {"type": "mhg", "lobes": [{"g": lo.g, "weight": lo.weight}
                                                 for lo in lobes]}
    return med


def _plain(v):
    """Plain Python values of a part's dict (NumPy scalars and arrays, tuples, paths), as
    TOML would give them to the parser."""
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_plain(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, Path):
        return str(v)
    return v


def _parse_emission(ctx: "_Ctx", t, volume: dict) -> EmissionSpec:
    """``[emission]``: grid (a name in the volume file), kind, scale, colour (radiance only)."""
    if not isinstance(t, dict):
        raise ctx.error("emission", t, "must be a table")
    _check_keys(ctx, "emission", t, ("grid", "kind", "scale", "colour"))
    f = volume.get("file")
    if not isinstance(f, str) or Path(f).suffix.lower() not in (".vdb", ".npz"):
        raise ctx.error("emission", None, "needs [volume] file = a .vdb or .npz file that holds "
                        "the emission grid beside the density")
    g = t.get("grid")
    if not isinstance(g, str) or not g:
        raise ctx.error("emission.grid", g, "missing or empty; the name of a grid in the "
                        "volume file (e.g. \"temperature\")")
    kind = t.get("kind")
    if kind not in ("radiance", "blackbody"):
        raise ctx.error("emission.kind", kind, 'must be "radiance" (scale * colour * value) or '
                        '"blackbody" (value in kelvin)')
    scale = _number(ctx, "emission.scale", t["scale"], lo=0.0) if "scale" in t else 1.0
    colour = (1.0, 1.0, 1.0)
    if "colour" in t:
        if kind != "radiance":
            raise ctx.error("emission.colour", t["colour"], 'applies to kind = "radiance" only '
                            "(a blackbody's colour is its temperature's)")
        colour = _rgb(ctx, "emission.colour", t["colour"])
    return EmissionSpec(grid=g, kind=kind, scale=scale, colour=colour)


def _parse_volume(ctx: "_Ctx", t: dict, base_dir: Path) -> VolumeSpec:
    has_file, has_gen = "file" in t, "generator" in t
    if has_file and has_gen:
        raise ctx.error("volume", None, 'give exactly one of file = "..." or generator = "..."'
                        ", not both")
    if not has_file and not has_gen:
        raise ctx.error("volume", None, 'missing the volume: give file = "x.vol" (or .npy, '
                        '.npz) or generator = "<name>"')
    vdb_grid = max_res = None
    if has_file:
        _check_keys(ctx, "volume", t, ("file", "bbox_min", "bbox_max", "grid", "max_resolution",
                                       "frame"),
                    hint="seed, resolution and params go with generator = ..., not file")
        f = t["file"]
        if not isinstance(f, str) or not f:
            raise ctx.error("volume.file", f, "must be a non-empty path string")
        suffix = Path(f).suffix.lower()
        if suffix not in VOLUME_SUFFIXES:
            raise ctx.error("volume.file", f, "must end in " + ", ".join(VOLUME_SUFFIXES))
        for key in ("grid", "max_resolution"):
            if key in t and suffix != ".vdb":
                raise ctx.error(f"volume.{key}", t[key], f"applies to .vdb files only, not "
                                f"{suffix} (file = {_fmt(f)})")
        if "grid" in t:
            vdb_grid = t["grid"]
            if not isinstance(vdb_grid, str) or not vdb_grid:
                raise ctx.error("volume.grid", vdb_grid, "must be a non-empty grid name")
        if "max_resolution" in t:
            max_res = _int(ctx, "volume.max_resolution", t["max_resolution"], 4,
                           MAX_VDB_RESOLUTION)
        p = Path(f).expanduser()
        resolved = (p if p.is_absolute() else base_dir / p).resolve()
        frame = None
        if is_frame_pattern(p.name) or "frame" in t:
            frame = _parse_sequence(ctx, t, p, resolved)
        elif "{" in f:
            raise ctx.error("volume.file", f, "a {frame} field goes in the file name, not in "
                            "its folder")
        target = (resolved if not is_frame_pattern(p.name) else None if frame is None
                  else resolved.with_name(resolved.name.format(frame=frame)))
        if target is not None and not target.is_file():
            raise ctx.error("volume.file", f, f"file not found: {target}")
        gen, seed, res, params = None, 0, None, {}
    else:
        resolved = None
        gen, seed, res, params = _parse_generator(ctx, t)
    bmin, bmax = t.get("bbox_min"), t.get("bbox_max")
    if (bmin is None) != (bmax is None):
        which = "volume.bbox_max" if bmin is not None else "volume.bbox_min"
        raise ctx.error(which, None, "missing; bbox_min and bbox_max override the box "
                        "together")
    if bmin is not None:
        bmin = _vec3(ctx, "volume.bbox_min", bmin)
        bmax = _vec3(ctx, "volume.bbox_max", bmax)
        if not all(a < b for a, b in zip(bmin, bmax)):
            raise ctx.error("volume.bbox_max", list(bmax),
                            f"each component must be > bbox_min = {_fmt(list(bmin))}")
    return VolumeSpec(file=resolved, generator=gen, seed=seed, resolution=res, params=params,
                      bbox_min=bmin, bbox_max=bmax, grid=vdb_grid, max_resolution=max_res,
                      frame=frame if has_file else None)


def _parse_sequence(ctx: "_Ctx", t: dict, p: Path, resolved: Path):
    """A file name with a ``{frame}`` field (e.g. "fire_{frame:04d}.npz"): the pattern must
    format with an integer frame alone; ``frame`` (optional) picks the frame loaded when no
    ``--frames`` is given. Returns the frame or None."""
    f = t["file"]
    if not is_frame_pattern(p.name):
        raise ctx.error("volume.frame", t["frame"], "applies to a sequence only: a file name "
                        "with a {frame} field, e.g. \"fire_{frame:04d}.npz\"")
    try:
        a, b = p.name.format(frame=0), p.name.format(frame=1)
    except Exception as e:      # KeyError, IndexError, ValueError, AttributeError, TypeError
        raise ctx.error("volume.file", f, f"a sequence pattern takes one field, {{frame}} (an "
                        f"integer, e.g. {{frame:04d}}): {type(e).__name__}: {e}") from None
    if a == b:
        raise ctx.error("volume.file", f, "the pattern gives the same file for every frame")
    if "{" in str(p.parent):
        raise ctx.error("volume.file", f, "a {frame} field goes in the file name, not in its "
                        "folder")
    if "frame" in t:
        return _int(ctx, "volume.frame", t["frame"], 0, 10**9)
    return None


_VOLUME_GENERATOR_KEYS = ("generator", "seed", "resolution", "params", "bbox_min", "bbox_max")


def _parse_generator(ctx: "_Ctx", t: dict):
    # lazy: the volume package is optional here
    from .volume.generators import GENERATORS, _check_resolution as check_resolution
    name = t["generator"]
    if not isinstance(name, str) or name not in GENERATORS:
        raise ctx.error("volume.generator", name, "unknown generator; allowed: "
                        + ", ".join(sorted(GENERATORS)))
    allowed = GENERATORS[name].parameters
    for key in t:
        if key in allowed and key not in _VOLUME_GENERATOR_KEYS:
            # A common slip: a generator parameter written straight into [volume].
            raise ctx.error(f"volume.{key}", t[key], "unknown key; generator parameters go "
                            f"in [volume.params], e.g. params = {{ {key} = {_fmt(t[key])} }}")
    _check_keys(ctx, "volume", t, _VOLUME_GENERATOR_KEYS)
    seed = t.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ctx.error("volume.seed", seed, "must be an integer >= 0")
    res = t.get("resolution", None)
    if res is not None:
        if isinstance(res, list):
            if len(res) != 3:
                raise ctx.error("volume.resolution", res,
                                f"must be one integer or a list of 3 integers [nx, ny, nz] "
                                f"(got {len(res)} values)")
            if any(isinstance(r, bool) or not isinstance(r, int) for r in res):
                raise ctx.error("volume.resolution", res, "each component must be an integer")
            res = tuple(res)
        elif isinstance(res, bool) or not isinstance(res, int):
            raise ctx.error("volume.resolution", res,
                            "must be an integer or a list of 3 integers [nx, ny, nz]")
        try:            # the limits are the generators' (clvol/volume/generators.py)
            check_resolution(res)
        except VolumeError as e:
            raise ctx.error("volume.resolution", res, str(e)) from None
    raw = t.get("params", {})
    if not isinstance(raw, dict):
        raise ctx.error("volume.params", raw, "must be a table of generator parameters")
    params = {}
    for key, value in raw.items():
        fld = f"volume.params.{key}"
        if key not in allowed:
            close = difflib.get_close_matches(key, allowed, n=1)
            guess = f" (did you mean {close[0]}?)" if close else ""
            raise ctx.error(fld, value, f"unknown parameter of generator \"{name}\"{guess}; "
                            "allowed: " + _describe_params(allowed))
        params[key] = _check_param(ctx, fld, value, allowed[key])
    return name, seed, res, params


def _describe_params(params: dict) -> str:
    if not params:
        return "(none)"
    return ", ".join(f"{k} {_range_text(p)}" for k, p in sorted(params.items()))


def _range_text(p) -> str:
    if isinstance(p.default, bool):
        return "(true or false)"
    rng = _range(getattr(p, "lo", None), getattr(p, "hi", None), False, False)
    return "(any finite number)" if rng == "finite" else rng


def _check_param(ctx: "_Ctx", fld: str, value, p):
    default = p.default
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ctx.error(fld, value, "must be true or false")
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ctx.error(fld, value, f"must be an integer {_range_text(p)}")
    elif isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ctx.error(fld, value, f"must be a number {_range_text(p)}")
    if not math.isfinite(value):
        raise ctx.error(fld, value, f"must be finite, {_range_text(p)}")
    lo, hi = getattr(p, "lo", None), getattr(p, "hi", None)
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise ctx.error(fld, value, f"must be {_range_text(p)}")
    return value if isinstance(default, int) else float(value)


def _parse_medium(ctx: "_Ctx", t: dict) -> Medium:
    _check_keys(ctx, "medium", t, ("preset", "density_scale", "albedo", "phase")
                + _declared_keys(Medium))
    preset = t.get("preset")
    if preset is not None and (not isinstance(preset, str) or preset not in PRESETS):
        raise ctx.error("medium.preset", preset, "unknown preset; allowed: " + ", ".join(PRESETS))
    if "density_scale" not in t:
        raise ctx.error("medium.density_scale", None,
                        "missing; sigma_t = density * density_scale, a number >= 0")
    ds = _number(ctx, "medium.density_scale", t["density_scale"], lo=0.0)
    albedo, phase = PRESETS[preset] if preset else (None, None)
    hint = "; give it or pick a preset (" + ", ".join(PRESETS) + ")"
    if "albedo" in t:
        albedo = _rgb(ctx, "medium.albedo", t["albedo"], hi=1.0)
    elif albedo is None:
        raise ctx.error("medium.albedo", None, "missing" + hint)
    if "phase" in t:
        phase = _parse_phase(ctx, t["phase"])
    elif phase is None:
        raise ctx.error("medium.phase", None, "missing" + hint)
    return Medium(density_scale=ds, albedo=albedo, phase=phase, preset=preset,
                  **_parse_declared(ctx, "medium", t, Medium))


_PHASE_KEYS = {"isotropic": ("type",), "hg": ("type", "g"), "mhg": ("type", "lobes")}


def _parse_phase(ctx: "_Ctx", t) -> Phase:
    if not isinstance(t, dict):
        raise ctx.error("medium.phase", t, 'must be a table, e.g. { type = "hg", g = 0.8 }')
    kind = t.get("type")
    if kind is None:
        raise ctx.error("medium.phase.type", None, "missing; allowed: " + ", ".join(_PHASE_KEYS))
    if kind not in _PHASE_KEYS:
        raise ctx.error("medium.phase.type", kind, "unknown phase; allowed: "
                        + ", ".join(_PHASE_KEYS))
    _check_keys(ctx, "medium.phase", t, _PHASE_KEYS[kind], allowed_for=f' for type = "{kind}"')
    if kind == "isotropic":
        return Phase.isotropic()
    if kind == "hg":
        if "g" not in t:
            raise ctx.error("medium.phase.g", None,
                            f"missing; a number in [{-HG_G_LIMIT}, {HG_G_LIMIT}]")
        return Phase.hg(_g(ctx, "medium.phase.g", t["g"]))
    lobes = t.get("lobes")
    if lobes is None:
        raise ctx.error("medium.phase.lobes", None, "missing; a list of 1 to "
                        f"{MHG_MAX_LOBES} tables {{ g = .., weight = .. }}")
    if not isinstance(lobes, list) or not 1 <= len(lobes) <= MHG_MAX_LOBES:
        n = f" (got {len(lobes)})" if isinstance(lobes, list) else ""
        raise ctx.error("medium.phase.lobes", lobes, f"must be a list of 1 to {MHG_MAX_LOBES} "
                        f"tables {{ g = .., weight = .. }}{n}")
    out = []
    for i, lobe in enumerate(lobes):
        fld = f"medium.phase.lobes[{i}]"
        if not isinstance(lobe, dict):
            raise ctx.error(fld, lobe, "must be a table { g = .., weight = .. }")
        _check_keys(ctx, fld, lobe, ("g", "weight"))
        for key in ("g", "weight"):
            if key not in lobe:
                raise ctx.error(f"{fld}.{key}", None, "missing")
        out.append(Lobe(_g(ctx, f"{fld}.g", lobe["g"]),
                        _number(ctx, f"{fld}.weight", lobe["weight"], lo=0.0)))
    total = math.fsum(l.weight for l in out)
    if abs(total - 1.0) > MHG_WEIGHT_TOL:
        raise ctx.error("medium.phase.lobes", lobes, f"weights sum to {total:.6g}; they must "
                        f"sum to 1 (within {MHG_WEIGHT_TOL:g})")
    if abs(total - 1.0) > _ALREADY_UNIT:
        out = [Lobe(l.g, l.weight / total) for l in out]
    return Phase("mhg", tuple(out))


def _g(ctx, fld, v) -> float:
    return _number(ctx, fld, v, lo=-HG_G_LIMIT, hi=HG_G_LIMIT)


_LIGHT_KEYS = ("direction", "irradiance", "environment", "environment_map", "environment_scale",
               "environment_rotation")


def _parse_light(ctx: "_Ctx", t: dict, base_dir: Path) -> Light:
    _check_keys(ctx, "light", t, _LIGHT_KEYS + _declared_keys(Light))
    if "direction" not in t:
        raise ctx.error("light.direction", None, "missing; a vector [x, y, z] toward the light")
    raw = t["direction"]
    d = _vec3(ctx, "light.direction", raw)
    direction = _normalise(d)
    if direction is None:
        raise ctx.error("light.direction", raw, "must not be the zero vector")
    irr = _rgb(ctx, "light.irradiance", t["irradiance"]) if "irradiance" in t else (1.0, 1.0, 1.0)
    env = _rgb(ctx, "light.environment", t["environment"]) if "environment" in t else None
    env_map, scale, rot = None, (1.0, 1.0, 1.0), 0.0
    if "environment_map" in t:
        if env is not None:
            raise ctx.error("light.environment_map", t["environment_map"], "give either "
                            "environment (a constant sky) or environment_map, not both")
        env_map = _parse_environment_map(ctx, t["environment_map"], base_dir)
    else:
        for key in ("environment_scale", "environment_rotation"):
            if key in t:
                raise ctx.error(f"light.{key}", t[key], 'applies to environment_map = "..." '
                                "only (none is given)")
    if "environment_scale" in t:
        scale = _rgb(ctx, "light.environment_scale", t["environment_scale"])
    if "environment_rotation" in t:
        rot = _number(ctx, "light.environment_rotation", t["environment_rotation"],
                      lo=-360.0, hi=360.0)
    return Light(direction=direction, irradiance=irr, environment=env, environment_map=env_map,
                 environment_scale=scale, environment_rotation=rot,
                 **_parse_declared(ctx, "light", t, Light))


def _parse_environment_map(ctx: "_Ctx", f, base_dir: Path) -> Path:
    """The map's resolved path, its texels read and validated now (clvol/envmap.py), so a
    bad map fails when the scene loads, with the field named."""
    from .envmap import load_map
    from .errors import ImageError
    if not isinstance(f, str) or not f:
        raise ctx.error("light.environment_map", f, "must be a non-empty path string to a "
                        "lat-long .exr")
    p = Path(f).expanduser()
    resolved = (p if p.is_absolute() else base_dir / p).resolve()
    if not resolved.is_file():
        raise ctx.error("light.environment_map", f, f"file not found: {resolved}")
    try:
        load_map(resolved)
    except ImageError as e:
        # read_map's message starts with the path, already named here as the field's value.
        msg = str(e)
        prefix = f"{resolved}: "
        raise ctx.error("light.environment_map", f,
                        msg[len(prefix):] if msg.startswith(prefix) else msg) from None
    return resolved


def _parse_camera(ctx: "_Ctx", t: dict) -> Camera:
    _check_keys(ctx, "camera", t, ("origin", "target", "up", "fov_y", "width", "height")
                + _declared_keys(Camera))
    for key, what in (("origin", "a point [x, y, z]"), ("target", "a point [x, y, z]"),
                      ("fov_y", "the vertical field of view in degrees, in (0, 180)"),
                      ("width", f"an integer in 1..{MAX_IMAGE_SIZE}"),
                      ("height", f"an integer in 1..{MAX_IMAGE_SIZE}")):
        if key not in t:
            raise ctx.error(f"camera.{key}", None, f"missing; {what}")
    origin = _vec3(ctx, "camera.origin", t["origin"])
    target = _vec3(ctx, "camera.target", t["target"])
    up = _vec3(ctx, "camera.up", t["up"]) if "up" in t else (0.0, 1.0, 0.0)
    fov = _number(ctx, "camera.fov_y", t["fov_y"], lo=0.0, hi=180.0, lo_open=True, hi_open=True)
    width = _int(ctx, "camera.width", t["width"], 1, MAX_IMAGE_SIZE)
    height = _int(ctx, "camera.height", t["height"], 1, MAX_IMAGE_SIZE)
    fwd = _normalise(tuple(b - a for a, b in zip(origin, target)))
    if fwd is None:
        raise ctx.error("camera.target", t["target"], "equals [camera.origin]; the camera "
                        "needs target != origin to have a view direction")
    up_n = _normalise(up)
    if up_n is None:
        raise ctx.error("camera.up", t["up"], "must not be the zero vector")
    # sin of the angle between up and the view direction; too small and right is undefined.
    if np.linalg.norm(np.cross(fwd, up_n)) < 1e-6:
        raise ctx.error("camera.up", t.get("up", list(up)), "is parallel to target - origin = "
                        f"{_fmt([b - a for a, b in zip(origin, target)])}; pick an up vector "
                        "that is not along the view direction")
    return Camera(origin=origin, target=target, up=up, fov_y=fov, width=width, height=height,
                  **_parse_declared(ctx, "camera", t, Camera))


_PARTS = {"camera": (Camera, _camera_to_dict, _parse_camera),
          "light": (Light, _light_to_dict, lambda ctx, t: _parse_light(ctx, t, Path.cwd())),
          "medium": (Medium, _medium_to_dict, _parse_medium)}


# --------------------------------------------------------------------------- validation helpers

class _Ctx:
    """Names the source in messages."""

    def __init__(self, source: str):
        self.source = source

    def error(self, fld: str, value, msg: str) -> SceneError:
        """``<file>: [<field>] = <value>: <msg>`` (no ``= value`` when value is None)."""
        shown = "" if value is None else f" = {_fmt(value)}"
        return SceneError(f"{self.source}: [{fld}]{shown}: {msg}")


def _check_keys(ctx: _Ctx, prefix: str, t: dict, allowed, kind: str = "key",
                hint: str | None = None, allowed_for: str = "") -> None:
    for key in t:
        if key in allowed:
            continue
        fld = f"{prefix}.{key}" if prefix else key
        value = None if isinstance(t[key], dict) and kind == "table" else t[key]
        msg = f"unknown {kind}; allowed{allowed_for}: " + ", ".join(allowed)
        close = difflib.get_close_matches(key, allowed, n=1)
        if close:
            msg += f" (did you mean {close[0]}?)"
        if hint:
            msg += f"; {hint}"
        raise ctx.error(fld, value, msg)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _bound(x) -> str:
    """A range bound for messages: 0 not 0.0, 180 not 180.0."""
    return f"{x:g}" if isinstance(x, float) else str(x)


def _range(lo, hi, lo_open, hi_open) -> str:
    if lo is not None and hi is not None:
        return f"in {'(' if lo_open else '['}{_bound(lo)}, {_bound(hi)}{')' if hi_open else ']'}"
    if lo is not None:
        return f"{'>' if lo_open else '>='} {_bound(lo)}"
    if hi is not None:
        return f"{'<' if hi_open else '<='} {_bound(hi)}"
    return "finite"


def _in_range(x: float, lo, hi, lo_open, hi_open) -> bool:
    if not math.isfinite(x):
        return False
    if lo is not None and (x < lo or (lo_open and x == lo)):
        return False
    if hi is not None and (x > hi or (hi_open and x == hi)):
        return False
    return True


def _number(ctx, fld, v, lo=None, hi=None, lo_open=False, hi_open=False) -> float:
    rng = _range(lo, hi, lo_open, hi_open)
    if not _is_number(v):
        raise ctx.error(fld, v, f"must be a number {rng}")
    if not _in_range(float(v), lo, hi, lo_open, hi_open):
        raise ctx.error(fld, v, f"must be {rng}" if math.isfinite(v) else f"must be finite, {rng}")
    return float(v)


def _int(ctx, fld, v, lo, hi) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise ctx.error(fld, v, f"must be an integer in {lo}..{hi}")
    if not lo <= v <= hi:
        raise ctx.error(fld, v, f"must be an integer in {lo}..{hi}")
    return v


def _vec3(ctx, fld, v, lo=None, hi=None, grey_ok=False) -> tuple[float, float, float]:
    """Three finite numbers (a single number means grey when ``grey_ok``)."""
    rng = _range(lo, hi, False, False)
    if grey_ok and _is_number(v):
        if not _in_range(float(v), lo, hi, False, False):
            raise ctx.error(fld, v, f"must be {rng}" if math.isfinite(v)
                            else f"must be finite, {rng}")
        return (float(v),) * 3
    shape = "a number or a list of 3 numbers" if grey_ok else "a list of 3 numbers [x, y, z]"
    if not isinstance(v, list) or len(v) != 3 or not all(_is_number(x) for x in v):
        n = f" (got {len(v)} values)" if isinstance(v, list) and len(v) != 3 else ""
        raise ctx.error(fld, v, f"must be {shape}{n}")
    for x in v:
        if not _in_range(float(x), lo, hi, False, False):
            raise ctx.error(fld, v, f"each component must be {rng}" if math.isfinite(x)
                            else f"each component must be finite" + ("" if rng == "finite"
                                                                     else f", {rng}"))
    return tuple(float(x) for x in v)


def _rgb(ctx, fld, v, hi=None) -> tuple[float, float, float]:
    return _vec3(ctx, fld, v, lo=0.0, hi=hi, grey_ok=True)


def _normalise(v) -> tuple[float, float, float] | None:
    """Unit vector along v, or None for the zero vector. Already-unit vectors pass unchanged."""
    a = np.asarray(v, dtype=np.float64)
    m = np.max(np.abs(a))
    if m == 0.0:
        return None
    n = np.linalg.norm(a / m) * m    # scaled first: no underflow for tiny vectors
    if abs(n - 1.0) <= _ALREADY_UNIT:
        return tuple(float(x) for x in a)
    return tuple(float(x) for x in (a / m) / (n / m))


# --------------------------------------------------------------------------- writing

def _fmt(v) -> str:
    """A value as TOML inline text (also used to quote values in error messages)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)        # shortest text that reads back to the same double
    if isinstance(v, str):
        return _toml_string(v)
    if isinstance(v, Path):
        return _toml_string(str(v))
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, dict):
        if not v:
            return "{}"
        return "{ " + ", ".join(f"{_toml_key(k)} = {_fmt(x)}" for k, x in v.items()) + " }"
    if isinstance(v, (np.integer, np.floating)):
        return _fmt(v.item())
    return repr(v)


def _toml_string(s: str) -> str:
    out = []
    for ch in s:
        if ch == '"':
            out.append('\\"')
        elif ch == "\\":
            out.append("\\\\")
        elif ch < " " or ch == "\x7f":
            out.append(f"\\u{ord(ch):04x}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _toml_key(k: str) -> str:
    if k and all(c.isascii() and (c.isalnum() or c in "_-") for c in k):
        return k
    return _toml_string(k)


def dumps_scene(scene: Scene, relative_to: Path | None = None) -> str:
    """The scene as TOML text that ``load_scene`` reads back to an equal scene.

    The volume file is written relative to ``relative_to`` (the folder the text will be
    saved in) when it lies below it, else as an absolute path.
    """
    data = scene.to_dict()
    if relative_to is not None and scene.volume.file is not None:
        try:
            data["volume"]["file"] = scene.volume.file.relative_to(
                Path(relative_to).resolve()).as_posix()
        except ValueError:
            pass
    lines = ["# clvol scene (format: docs/scenes.md)"]
    for table in ("volume", "medium", "light", "camera", "emission"):
        if table not in data:
            continue
        lines.append("")
        lines.append(f"[{table}]")
        for key, value in data[table].items():
            lines.append(f"{_toml_key(key)} = {_fmt(value)}")
    return "\n".join(lines) + "\n"
