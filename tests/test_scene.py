"""Scene files: validation messages, presets, paths, camera convention, round trip, examples."""
from __future__ import annotations

import copy
import math
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from clvol.errors import ClvolError, SceneError, VolumeError
from clvol.scene import (PRESETS, Camera, Lobe, Phase, VolumeSpec, dumps_scene, load_scene,
                         scene_from_dict)

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


# --------------------------------------------------------------------------- helpers

def _toml_value(v) -> str:
    """Minimal TOML writer for test inputs, independent of clvol.scene's writer."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(v)


def _toml(data: dict) -> str:
    lines = []
    for table, body in data.items():
        if not isinstance(body, dict):
            lines.append(f"{table} = {_toml_value(body)}")
    for table, body in data.items():
        if isinstance(body, dict):
            lines.append(f"[{table}]")
            lines += [f"{k} = {_toml_value(v)}" for k, v in body.items()]
    return "\n".join(lines) + "\n"


def _fake_generators():
    """A stand-in for clvol.volume.generators with known parameters (so these tests do not
    depend on the real generators' parameter list) and a generate() that records its call."""
    Param = types.SimpleNamespace
    calls = []
    mod = types.ModuleType("clvol.volume.generators")
    mod.GENERATORS = {
        "cloud": types.SimpleNamespace(name="cloud", doc="test cloud", parameters={
            "coverage": Param(default=0.5, lo=0.0, hi=1.0, doc=""),
            "octaves": Param(default=4, lo=1, hi=8, doc=""),
        }),
        "sphere": types.SimpleNamespace(name="sphere", doc="test sphere", parameters={
            "radius": Param(default=0.4, lo=0.01, hi=0.5, doc=""),
        }),
    }

    def generate(name, seed=0, resolution=64, **params):
        from clvol.volume.grid import DensityGrid
        calls.append((name, seed, resolution, params))
        n = (resolution,) * 3 if isinstance(resolution, int) else tuple(resolution)
        return DensityGrid.from_array(np.ones(n[::-1], dtype=np.float32))

    mod.generate = generate
    mod.calls = calls
    # The resolution limits are the real generators' (the scene parser asks them).
    from clvol.volume import generators as real
    mod._check_resolution = real._check_resolution
    return mod


@pytest.fixture
def gens(monkeypatch):
    mod = _fake_generators()
    monkeypatch.setitem(sys.modules, "clvol.volume.generators", mod)
    return mod


BASE = {
    "volume": {"generator": "cloud", "seed": 3, "resolution": 16},
    "medium": {"density_scale": 64.0, "albedo": [0.9, 0.8, 0.7],
               "phase": {"type": "hg", "g": 0.5}},
    "light": {"direction": [0.0, 1.0, 0.0], "irradiance": [1.0, 1.0, 1.0]},
    "camera": {"origin": [0.0, 0.0, 3.0], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0],
               "fov_y": 35.0, "width": 32, "height": 24},
}


def _write(tmp_path, data, name="scene.toml") -> Path:
    p = tmp_path / name
    p.write_text(_toml(data))
    return p


def _mutate(data: dict, dotted: str, value):
    """Set (or delete, for value is DELETE) a dotted key in a deep copy of data."""
    d = copy.deepcopy(data)
    node = d
    *parents, last = dotted.split(".")
    for p in parents:
        node = node[p]
    if value is DELETE:
        del node[last]
    else:
        node[last] = value
    return d


DELETE = object()
NAN, INF = float("nan"), float("inf")


def _load_error(tmp_path, data) -> str:
    path = _write(tmp_path, data)
    with pytest.raises(SceneError) as e:
        load_scene(path)
    return str(e.value), str(path)


# --------------------------------------------------------------------------- bad values

# (dotted key to set, value, field named in the message, fragment of the message)
BAD = [
    # [volume]
    ("volume.file", "a.vol", "volume", "not both"),
    ("volume.generator", DELETE, "volume", "give file"),
    ("volume.generator", "clod", "volume.generator", "allowed: cloud, sphere"),
    ("volume.generator", 3, "volume.generator", "allowed: cloud, sphere"),
    ("volume.seed", -1, "volume.seed", "integer >= 0"),
    ("volume.seed", 1.5, "volume.seed", "integer >= 0"),
    ("volume.seed", True, "volume.seed", "integer >= 0"),
    ("volume.resolution", 0, "volume.resolution", "every axis must be in [1, 2048]"),
    ("volume.resolution", 2049, "volume.resolution", "every axis must be in [1, 2048]"),
    ("volume.resolution", 1024, "volume.resolution", "the limit is 134217728"),
    ("volume.resolution", 64.0, "volume.resolution", "must be an integer or a list of 3"),
    ("volume.resolution", "64", "volume.resolution", "must be an integer or a list of 3"),
    ("volume.resolution", [64, 64], "volume.resolution", "got 2 values"),
    ("volume.resolution", [64, 0, 64], "volume.resolution", "every axis must be in [1, 2048]"),
    ("volume.resolution", [64, 1.5, 64], "volume.resolution", "each component"),
    ("volume.params", 3, "volume.params", "must be a table"),
    ("volume.params", {"coverag": 0.5}, "volume.params.coverag",
     "allowed: coverage in [0, 1], octaves in [1, 8]"),
    ("volume.params", {"coverage": 1.5}, "volume.params.coverage", "in [0, 1]"),
    ("volume.params", {"coverage": NAN}, "volume.params.coverage", "finite"),
    ("volume.params", {"coverage": "half"}, "volume.params.coverage", "must be a number"),
    ("volume.params", {"octaves": 2.5}, "volume.params.octaves", "must be an integer"),
    ("volume.coverage", 0.5, "volume.coverage", "[volume.params]"),
    ("volume.bbox", [0, 0, 0], "volume.bbox", "unknown key"),
    ("volume.bbox_min", [-1.0, -1.0, -1.0], "volume.bbox_max", "together"),
    # [medium]
    ("medium.preset", "jadee", "medium.preset", "allowed: cloud, fog, smoke, milk, jade, wax, skin"),
    ("medium.density_scale", DELETE, "medium.density_scale", "missing"),
    ("medium.density_scale", -1.0, "medium.density_scale", ">= 0"),
    ("medium.density_scale", NAN, "medium.density_scale", "finite"),
    ("medium.density_scale", INF, "medium.density_scale", "finite"),
    ("medium.density_scale", "64", "medium.density_scale", "must be a number"),
    ("medium.density_scale", True, "medium.density_scale", "must be a number"),
    ("medium.albedo", [1.2, 0.5, 0.5], "medium.albedo", "each component must be in [0, 1]"),
    ("medium.albedo", [0.5, -0.1, 0.5], "medium.albedo", "each component must be in [0, 1]"),
    ("medium.albedo", 1.5, "medium.albedo", "must be in [0, 1]"),
    ("medium.albedo", [0.5, 0.5], "medium.albedo", "got 2 values"),
    ("medium.albedo", [0.5, 0.5, 0.5, 0.5], "medium.albedo", "got 4 values"),
    ("medium.albedo", "grey", "medium.albedo", "a number or a list of 3 numbers"),
    ("medium.albedo", [0.5, NAN, 0.5], "medium.albedo", "finite"),
    ("medium.albedo", DELETE, "medium.albedo", "pick a preset"),
    ("medium.phase", DELETE, "medium.phase", "pick a preset"),
    ("medium.phase", "hg", "medium.phase", "must be a table"),
    ("medium.phase", {"g": 0.5}, "medium.phase.type", "missing"),
    ("medium.phase", {"type": "rayleigh"}, "medium.phase.type", "allowed: isotropic, hg, mhg"),
    ("medium.phase", {"type": "hg"}, "medium.phase.g", "missing"),
    ("medium.phase", {"type": "hg", "g": 1.0}, "medium.phase.g", "in [-0.99, 0.99]"),
    ("medium.phase", {"type": "hg", "g": -0.995}, "medium.phase.g", "in [-0.99, 0.99]"),
    ("medium.phase", {"type": "hg", "g": NAN}, "medium.phase.g", "finite"),
    ("medium.phase", {"type": "hg", "g": [0.5]}, "medium.phase.g", "must be a number"),
    ("medium.phase", {"type": "hg", "g": 0.5, "lobes": []}, "medium.phase.lobes", "unknown key"),
    ("medium.phase", {"type": "isotropic", "g": 0.5}, "medium.phase.g", "unknown key"),
    ("medium.phase", {"type": "mhg"}, "medium.phase.lobes", "missing"),
    ("medium.phase", {"type": "mhg", "lobes": []}, "medium.phase.lobes", "1 to 3"),
    ("medium.phase", {"type": "mhg", "lobes": [{"g": 0.1, "weight": 0.25}] * 4},
     "medium.phase.lobes", "got 4"),
    ("medium.phase", {"type": "mhg", "lobes": [0.5]}, "medium.phase.lobes[0]", "must be a table"),
    ("medium.phase", {"type": "mhg", "lobes": [{"weight": 1.0}]}, "medium.phase.lobes[0].g",
     "missing"),
    ("medium.phase", {"type": "mhg", "lobes": [{"g": 0.5, "weight": 1.1},
                                               {"g": 0.1, "weight": -0.1}]},
     "medium.phase.lobes[1].weight", ">= 0"),
    ("medium.phase", {"type": "mhg", "lobes": [{"g": 0.5, "weight": 0.6},
                                               {"g": 1.5, "weight": 0.4}]},
     "medium.phase.lobes[1].g", "in [-0.99, 0.99]"),
    ("medium.phase", {"type": "mhg", "lobes": [{"g": 0.5, "weight": 0.6},
                                               {"g": 0.1, "weight": 0.3}]},
     "medium.phase.lobes", "sum to 0.9"),
    ("medium.phase", {"type": "mhg", "lobes": [{"g": 0.5, "weight": 1.0, "w": 0}]},
     "medium.phase.lobes[0].w", "unknown key"),
    ("medium.albdo", [0.5, 0.5, 0.5], "medium.albdo", "did you mean albedo"),
    # [light]
    ("light.direction", DELETE, "light.direction", "missing"),
    ("light.direction", [0.0, 0.0, 0.0], "light.direction", "zero vector"),
    ("light.direction", [0.0, 1.0], "light.direction", "got 2 values"),
    ("light.direction", [0.0, NAN, 1.0], "light.direction", "finite"),
    ("light.direction", "up", "light.direction", "list of 3 numbers"),
    ("light.irradiance", [1.0, -1.0, 1.0], "light.irradiance", ">= 0"),
    ("light.irradiance", INF, "light.irradiance", "finite"),
    ("light.environment", -0.5, "light.environment", ">= 0"),
    ("light.environment", [0.1, 0.2], "light.environment", "got 2 values"),
    ("light.color", [1.0, 1.0, 1.0], "light.color", "unknown key"),
    # [camera]
    ("camera.origin", DELETE, "camera.origin", "missing"),
    ("camera.origin", [0.0, 3.0], "camera.origin", "got 2 values"),
    ("camera.origin", [0.0, INF, 3.0], "camera.origin", "finite"),
    ("camera.target", [0.0, 0.0, 3.0], "camera.target", "equals [camera.origin]"),
    ("camera.up", [0.0, 0.0, -2.0], "camera.up", "parallel"),
    ("camera.up", [0.0, 0.0, 0.0], "camera.up", "zero vector"),
    ("camera.fov_y", 0.0, "camera.fov_y", "in (0, 180)"),
    ("camera.fov_y", 180.0, "camera.fov_y", "in (0, 180)"),
    ("camera.fov_y", -5.0, "camera.fov_y", "in (0, 180)"),
    ("camera.fov_y", NAN, "camera.fov_y", "finite"),
    ("camera.fov_y", DELETE, "camera.fov_y", "missing"),
    ("camera.width", 0, "camera.width", "1..16384"),
    ("camera.width", 16385, "camera.width", "1..16384"),
    ("camera.width", 256.0, "camera.width", "integer"),
    ("camera.width", True, "camera.width", "integer"),
    ("camera.height", "tall", "camera.height", "integer"),
    ("camera.height", DELETE, "camera.height", "missing"),
    ("camera.fov", 35.0, "camera.fov", "did you mean fov_y"),
    # top level
    ("render", {"spp": 4}, "render", "unknown table; allowed: volume, medium, light, camera"),
    ("camera", DELETE, "camera", "missing table"),
    ("light", 3, "light", "must be a table"),
]


@pytest.mark.parametrize("dotted,value,fld,fragment", BAD,
                         ids=[f"{b[0]}={'DELETE' if b[1] is DELETE else b[1]!r}"[:60] for b in BAD])
def test_bad_field_message(tmp_path, gens, dotted, value, fld, fragment):
    msg, path = _load_error(tmp_path, _mutate(BASE, dotted, value))
    assert msg.startswith(f"{path}: [{fld}]"), msg
    assert fragment in msg, msg


def test_message_quotes_the_bad_value(tmp_path, gens):
    msg, path = _load_error(tmp_path, _mutate(BASE, "medium.albedo", [1.2, 0.5, 0.5]))
    assert msg == f"{path}: [medium.albedo] = [1.2, 0.5, 0.5]: each component must be in [0, 1]"


def test_file_volume_rejects_generator_keys(tmp_path, gens):
    (tmp_path / "a.npy").write_bytes(b"")
    data = _mutate(BASE, "volume", {"file": "a.npy", "seed": 1})
    msg, path = _load_error(tmp_path, data)
    assert msg.startswith(f"{path}: [volume.seed] = 1: unknown key"), msg
    assert "go with generator" in msg


def test_file_volume_bad_suffix(tmp_path, gens):
    msg, path = _load_error(tmp_path, _mutate(BASE, "volume", {"file": "a.raw"}))
    assert msg.startswith(f'{path}: [volume.file] = "a.raw": must end in .vol, .npy, .npz'), msg


def test_file_volume_wrong_type(tmp_path, gens):
    msg, path = _load_error(tmp_path, _mutate(BASE, "volume", {"file": 3}))
    assert msg.startswith(f"{path}: [volume.file] = 3: must be a non-empty path string"), msg


def test_missing_volume_file_names_resolved_path(tmp_path, gens):
    msg, path = _load_error(tmp_path, _mutate(BASE, "volume", {"file": "vols/../nothere.vol"}))
    assert msg.startswith(f'{path}: [volume.file] = "vols/../nothere.vol"'), msg
    assert str((tmp_path / "nothere.vol").resolve()) in msg, msg


@pytest.mark.parametrize("bbox_min,bbox_max,fld,fragment", [
    ([0.0, 0.0], [1.0, 1.0, 1.0], "volume.bbox_min", "got 2 values"),
    ([0.0, NAN, 0.0], [1.0, 1.0, 1.0], "volume.bbox_min", "finite"),
    ([0.0, 0.0, 0.0], [1.0, 0.0, 1.0], "volume.bbox_max", "> bbox_min"),
    ([0.0, 0.0, 0.0], [1.0, -1.0, 1.0], "volume.bbox_max", "> bbox_min"),
])
def test_bad_bbox(tmp_path, gens, bbox_min, bbox_max, fld, fragment):
    data = _mutate(_mutate(BASE, "volume.bbox_min", bbox_min), "volume.bbox_max", bbox_max)
    msg, path = _load_error(tmp_path, data)
    assert msg.startswith(f"{path}: [{fld}]"), msg
    assert fragment in msg, msg


def test_invalid_toml_names_file(tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text("[medium\ndensity_scale = 1\n")
    with pytest.raises(SceneError, match=r"broken\.toml: not valid TOML"):
        load_scene(p)


def test_missing_scene_file(tmp_path):
    with pytest.raises(SceneError, match="scene file not found"):
        load_scene(tmp_path / "nope.toml")


def test_scene_from_dict_names_its_source(gens):
    with pytest.raises(SceneError, match=r"^cli-args: \[camera\.width\] = 0: "):
        scene_from_dict(_mutate(BASE, "camera.width", 0), source="cli-args")


# --------------------------------------------------------------------------- good values

def test_base_scene_values(tmp_path, gens):
    s = load_scene(_write(tmp_path, BASE))
    assert s.path == tmp_path / "scene.toml"
    assert s.volume == VolumeSpec(file=None, generator="cloud", seed=3, resolution=16, params={})
    assert s.medium.density_scale == 64.0
    assert s.medium.albedo == (0.9, 0.8, 0.7) and not s.medium.is_grey
    assert s.medium.phase == Phase("hg", (Lobe(0.5, 1.0),))
    assert s.medium.preset is None
    assert s.light.environment is None
    assert (s.camera.width, s.camera.height, s.camera.fov_y) == (32, 24, 35.0)


# docs/conventions.md's preset table, typed in independently: (albedo, lobes as (g, weight), type).
DESIGN_PRESETS = {
    "cloud": ((0.999,) * 3, [(0.857, 1.0)], "hg"),
    "fog": ((0.95,) * 3, [(0.7, 1.0)], "hg"),
    "smoke": ((0.4,) * 3, [(0.3, 1.0)], "hg"),
    "milk": ((0.999,) * 3, [(0.8, 0.7), (-0.3, 0.3)], "mhg"),
    "jade": ((0.92, 0.99, 0.94), [(0.6, 0.8), (-0.2, 0.2)], "mhg"),
    "wax": ((0.99, 0.97, 0.93), [(0.4, 0.8), (-0.1, 0.2)], "mhg"),
    "skin": ((0.99, 0.85, 0.75), [(0.8, 0.5), (0.3, 0.3), (-0.3, 0.2)], "mhg"),
}


@pytest.mark.parametrize("name", sorted(DESIGN_PRESETS))
def test_preset(tmp_path, gens, name):
    albedo, lobes, kind = DESIGN_PRESETS[name]
    data = _mutate(BASE, "medium", {"preset": name, "density_scale": 10.0})
    m = load_scene(_write(tmp_path, data)).medium
    assert m.preset == name and m.density_scale == 10.0
    assert m.albedo == albedo
    assert m.phase.type == kind
    assert [(l.g, l.weight) for l in m.phase.lobes] == lobes
    assert m.phase.mean_cosine == pytest.approx(sum(g * w for g, w in lobes), abs=1e-12)
    assert (m.albedo, m.phase) == PRESETS[name]


def test_preset_set_is_design_set():
    assert set(PRESETS) == set(DESIGN_PRESETS)


def test_explicit_fields_override_preset(tmp_path, gens):
    data = _mutate(BASE, "medium", {"preset": "jade", "density_scale": 30.0, "albedo": 0.5})
    m = load_scene(_write(tmp_path, data)).medium
    assert m.albedo == (0.5, 0.5, 0.5) and m.is_grey
    assert m.phase == PRESETS["jade"][1]
    data = _mutate(data, "medium.phase", {"type": "isotropic"})
    m = load_scene(_write(tmp_path, data)).medium
    assert m.phase == Phase("isotropic", (Lobe(0.0, 1.0),))
    assert m.phase.is_isotropic and m.phase.mean_cosine == 0.0
    assert m.preset == "jade"


def test_mhg_weights_renormalised(tmp_path, gens):
    lobes = [{"g": 0.8, "weight": 0.70004}, {"g": -0.3, "weight": 0.3}]   # off by 4e-5
    data = _mutate(BASE, "medium.phase", {"type": "mhg", "lobes": lobes})
    p = load_scene(_write(tmp_path, data)).medium.phase
    assert math.fsum(l.weight for l in p.lobes) == pytest.approx(1.0, abs=1e-15)
    assert p.lobes[0].weight == pytest.approx(0.70004 / 1.00004, rel=1e-15)
    # Off by more than 1e-4: refused rather than silently rescaled.
    data = _mutate(BASE, "medium.phase", {"type": "mhg", "lobes": [{"g": 0.8, "weight": 0.7002},
                                                                    {"g": -0.3, "weight": 0.3}]})
    msg, _ = _load_error(tmp_path, data)
    assert "[medium.phase.lobes]" in msg and "sum to 1.0002" in msg


def test_phase_is_isotropic_for_zero_g_lobes():
    assert Phase.mhg([(0.0, 0.5), (0.0, 0.5)]).is_isotropic
    assert not Phase.hg(0.1).is_isotropic


@pytest.mark.parametrize("raw,expected", [
    ([0.0, 2.0, 0.0], (0.0, 1.0, 0.0)),
    ([3.0, 0.0, -4.0], (0.6, 0.0, -0.8)),
    ([1e-300, 0.0, 0.0], (1.0, 0.0, 0.0)),       # no underflow to a zero length
    ([1e300, 1e300, 0.0], (math.sqrt(0.5), math.sqrt(0.5), 0.0)),   # no overflow
])
def test_light_direction_normalised(tmp_path, gens, raw, expected):
    d = load_scene(_write(tmp_path, _mutate(BASE, "light.direction", raw))).light.direction
    assert d == pytest.approx(expected, abs=1e-15)
    assert math.fsum(x * x for x in d) == pytest.approx(1.0, abs=1e-15)


def test_grey_rgb_and_environment(tmp_path, gens):
    data = _mutate(_mutate(BASE, "light.irradiance", 2), "light.environment", [0.1, 0.2, 0.3])
    li = load_scene(_write(tmp_path, data)).light
    assert li.irradiance == (2.0, 2.0, 2.0)
    assert li.environment == (0.1, 0.2, 0.3)


def test_optional_defaults(tmp_path, gens):
    data = _mutate(_mutate(BASE, "camera.up", DELETE), "light.irradiance", DELETE)
    data = _mutate(data, "volume.seed", DELETE)
    s = load_scene(_write(tmp_path, data))
    assert s.camera.up == (0.0, 1.0, 0.0)
    assert s.light.irradiance == (1.0, 1.0, 1.0)
    assert s.volume.seed == 0


def test_relative_volume_path_resolves_against_scene_folder(tmp_path, gens, monkeypatch):
    scene_dir = tmp_path / "scenes"
    (scene_dir / "vols").mkdir(parents=True)
    (scene_dir / "vols" / "a.npy").write_bytes(b"")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    s = load_scene(_write(scene_dir, _mutate(BASE, "volume", {"file": "vols/a.npy"})))
    assert s.volume.file == (scene_dir / "vols" / "a.npy").resolve()
    assert s.volume.generator is None and s.volume.resolution is None


def test_generator_params_and_resolution_list(tmp_path, gens):
    data = _mutate(BASE, "volume", {"generator": "cloud", "resolution": [8, 6, 4],
                                    "params": {"coverage": 1, "octaves": 2}})
    v = load_scene(_write(tmp_path, data)).volume
    assert v.resolution == (8, 6, 4)
    assert v.params == {"coverage": 1.0, "octaves": 2}
    assert isinstance(v.params["coverage"], float) and isinstance(v.params["octaves"], int)


def test_volume_load_runs_generator_and_applies_bbox(tmp_path, gens):
    data = _mutate(BASE, "volume", {"generator": "sphere", "seed": 7, "resolution": [4, 3, 2],
                                    "params": {"radius": 0.3},
                                    "bbox_min": [0.0, 0.0, 0.0], "bbox_max": [2.0, 1.5, 1.0]})
    grid = load_scene(_write(tmp_path, data)).volume.load()
    assert gens.calls == [("sphere", 7, (4, 3, 2), {"radius": 0.3})]
    assert grid.density.shape == (2, 3, 4)
    np.testing.assert_array_equal(grid.bbox_min, [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(grid.bbox_max, [2.0, 1.5, 1.0])


def test_volume_load_reads_file_with_bbox_override(tmp_path, gens):
    density = np.arange(3 * 5 * 7, dtype=np.float32).reshape(3, 5, 7)
    np.save(tmp_path / "d.npy", density)
    data = _mutate(BASE, "volume", {"file": "d.npy"})
    grid = load_scene(_write(tmp_path, data)).volume.load()
    np.testing.assert_array_equal(grid.density, density)
    np.testing.assert_array_equal(grid.bbox_min, [-0.5] * 3)      # the file's default box
    data["volume"].update(bbox_min=[1.0, 2.0, 3.0], bbox_max=[2.0, 4.0, 6.0])
    grid = load_scene(_write(tmp_path, data)).volume.load()
    np.testing.assert_array_equal(grid.density, density)
    np.testing.assert_array_equal(grid.bbox_min, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(grid.bbox_max, [2.0, 4.0, 6.0])


def test_volume_load_missing_file_names_path(tmp_path):
    spec = VolumeSpec(file=tmp_path / "gone.vol", generator=None)
    with pytest.raises(VolumeError, match="gone.vol: volume file not found"):
        spec.load()


# --------------------------------------------------------------------------- camera

def _cam(**kw) -> Camera:
    args = dict(origin=(0.0, 0.0, 0.0), target=(0.0, 0.0, -1.0), up=(0.0, 1.0, 0.0),
                fov_y=90.0, width=4, height=2)
    args.update(kw)
    return Camera(**args)


def test_camera_basis_is_orthonormal_and_right_handed():
    fwd, right, up = Camera(origin=(1.0, 2.0, 3.0), target=(-2.0, 0.5, 0.0), up=(0.3, 1.0, 0.1),
                            fov_y=40.0, width=8, height=8).basis()
    assert fwd == pytest.approx(np.array([-3.0, -1.5, -3.0]) / 4.5, abs=1e-15)
    for v in (fwd, right, up):
        assert v.dtype == np.float64 and np.dot(v, v) == pytest.approx(1.0, abs=1e-15)
    assert np.dot(fwd, right) == pytest.approx(0.0, abs=1e-15)
    assert np.dot(fwd, up) == pytest.approx(0.0, abs=1e-15)
    assert np.dot(right, up) == pytest.approx(0.0, abs=1e-15)
    assert np.dot(up, [0.3, 1.0, 0.1]) > 0          # the true up leans toward the given up
    # Looking down -z with y up, right is +x (OpenGL / Mitsuba look_at).
    fwd, right, up = _cam().basis()
    np.testing.assert_allclose([fwd, right, up], [[0, 0, -1], [1, 0, 0], [0, 1, 0]], atol=1e-15)


def test_pixel_directions_hand_computed():
    # 4x2 image, fov_y 90 (tan = 1), aspect 2: pixel (row 0, col 0) has sx = -0.75, sy = 0.5,
    # so d = forward - 0.75*2*right + 0.5*up = (-1.5, 0.5, -1).
    d = _cam().pixel_directions()
    assert d.shape == (2, 4, 3) and d.dtype == np.float64
    np.testing.assert_allclose(d[0, 0], np.array([-1.5, 0.5, -1.0]) / math.sqrt(3.5), atol=1e-15)
    np.testing.assert_allclose(d[1, 3], np.array([1.5, -0.5, -1.0]) / math.sqrt(3.5), atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-15)


def test_centre_pixel_of_odd_image_looks_at_target():
    cam = Camera(origin=(1.0, 2.0, 3.0), target=(-0.5, 0.2, 0.1), up=(0.0, 1.0, 0.0),
                 fov_y=30.0, width=9, height=7)
    d = cam.pixel_directions()
    to_target = np.subtract(cam.target, cam.origin)
    np.testing.assert_allclose(d[3, 4], to_target / np.linalg.norm(to_target), atol=1e-15)


def test_column_0_is_left_and_row_0_is_top():
    cam = Camera(origin=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0),
                 fov_y=30.0, width=9, height=7)
    d = cam.pixel_directions()
    # Camera on +z looking at the origin with y up: the viewer's left is -x, top is +y.
    assert d[3, 0, 0] < 0 < d[3, 8, 0]
    assert d[0, 4, 1] > 0 > d[6, 4, 1]
    _, right, up = cam.basis()
    assert np.dot(d[3, 0], right) < 0 and np.dot(d[0, 4], up) > 0


def test_jitter_moves_within_the_pixel():
    cam = _cam(fov_y=60.0, width=5, height=3)
    tan_half = math.tan(math.radians(30.0))
    # jitter (-0.5, -0.5) puts every sample on its pixel's top-left corner: col, row integers.
    d = cam.pixel_directions(jitter=np.array([-0.5, -0.5]))
    assert d[0, 0] == pytest.approx(_unit([-tan_half * 5 / 3, tan_half, -1.0]), abs=1e-15)
    # A per-pixel jitter array of shape (H, W, 2): x moves right, y moves down.
    j = np.zeros((3, 5, 2))
    j[1, 2] = (0.25, 0.5)
    d = cam.pixel_directions(jitter=j)
    sx = (2 * 2.75 / 5 - 1) * tan_half * 5 / 3
    sy = (1 - 2 * 2.0 / 3) * tan_half
    assert d[1, 2] == pytest.approx(_unit([sx, sy, -1.0]), abs=1e-15)
    np.testing.assert_array_equal(d[0, 0], cam.pixel_directions()[0, 0])


def test_jitter_rejects_bad_input():
    cam = _cam()
    with pytest.raises(ClvolError, match="broadcast"):
        cam.pixel_directions(jitter=np.zeros((2, 4, 3)))
    with pytest.raises(ClvolError, match=r"\[-0.5, 0.5\]"):
        cam.pixel_directions(jitter=np.full((2, 4, 2), 0.75))
    with pytest.raises(ClvolError, match=r"\[-0.5, 0.5\]"):
        cam.pixel_directions(jitter=np.full((2, 4, 2), np.nan))


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


# --------------------------------------------------------------------------- round trip

def test_round_trip_generator_scene(tmp_path, gens):
    data = _mutate(BASE, "volume", {"generator": "cloud", "seed": 11, "resolution": [8, 6, 4],
                                    "params": {"coverage": 0.3, "octaves": 5},
                                    "bbox_min": [-1.0, -0.5, -0.25], "bbox_max": [1.0, 0.5, 0.25]})
    data = _mutate(data, "medium", {"preset": "skin", "density_scale": 0.1 + 0.2})
    data = _mutate(data, "light.direction", [0.3, 1.0, 0.4])
    data = _mutate(data, "light.environment", [0.01, 0.02, 0.03])
    s1 = load_scene(_write(tmp_path, data, "a.toml"))
    text = dumps_scene(s1)
    p2 = tmp_path / "b.toml"
    p2.write_text(text)
    s2 = load_scene(p2)
    assert s2.path == p2
    assert s2.volume == s1.volume and s2.medium == s1.medium
    assert s2.light == s1.light and s2.camera == s1.camera
    assert dumps_scene(s2) == text


def test_round_trip_file_scene_relative(tmp_path, gens):
    (tmp_path / "v").mkdir()
    (tmp_path / "v" / "x.vol").write_bytes(b"")
    data = _mutate(BASE, "volume", {"file": "v/x.vol"})
    data = _mutate(data, "medium.phase", {"type": "mhg", "lobes": [
        {"g": 0.3, "weight": 0.1}, {"g": 0.2, "weight": 0.2}, {"g": -0.9, "weight": 0.7}]})
    s1 = load_scene(_write(tmp_path, data))
    text = dumps_scene(s1, relative_to=tmp_path)
    assert 'file = "v/x.vol"' in text
    out = tmp_path / "copy.toml"
    out.write_text(text)
    s2 = load_scene(out)
    assert (s2.volume, s2.medium, s2.light, s2.camera) == (s1.volume, s1.medium, s1.light,
                                                         s1.camera)


def test_with_overrides(tmp_path, gens):
    s = load_scene(_write(tmp_path, BASE))
    s2 = s.with_overrides({"camera.width": 64, "light.environment": [0.5, 0.5, 0.5]})
    assert s2.camera.width == 64 and s2.light.environment == (0.5, 0.5, 0.5)
    assert s2.path == s.path and s2.medium == s.medium and s2.camera.height == s.camera.height
    s3 = s.with_overrides({"medium.preset": "wax"})
    assert (s3.medium.albedo, s3.medium.phase) == PRESETS["wax"]
    assert s3.medium.density_scale == s.medium.density_scale
    with pytest.raises(SceneError, match=r"^--width: \[camera\.width\] = -3: "):
        s.with_overrides({"camera.width": -3}, source="--width")


# --------------------------------------------------------------------------- examples

EXAMPLE_FILES = sorted(EXAMPLES.glob("*.toml"))


def test_examples_exist():
    assert {p.stem for p in EXAMPLE_FILES} >= {"cloud", "smoke", "jade", "milk"}


@pytest.mark.parametrize("path", EXAMPLE_FILES, ids=[p.stem for p in EXAMPLE_FILES])
def test_example_camera_is_outside_and_frames_the_medium(path):
    """The camera looks at the volume from outside its box, and (almost) all of the medium is
    in the frame: the examples are framed tight on the medium, not on the box (whose corners
    may be cut off). tests/test_examples.py checks that the medium fills the frame."""
    s = load_scene(path)
    assert s.volume.file is None, "examples keep their volumes generated (no binary files)"
    grid = s.volume.load()
    lo, hi = np.asarray(grid.bbox_min), np.asarray(grid.bbox_max)
    origin = np.array(s.camera.origin)
    assert np.any((origin < lo) | (origin > hi)), "camera inside the box"
    fwd, right, up = s.camera.basis()
    tan_half = math.tan(math.radians(s.camera.fov_y) / 2)
    aspect = s.camera.width / s.camera.height
    d = np.asarray(grid.density)
    idx = np.argwhere(d > 0.01 * d.max())                      # (z, y, x) of the medium
    n = np.array(d.shape)
    centres = lo + (idx[:, ::-1] + 0.5) / n[::-1] * (hi - lo)
    v = centres - origin
    depth = v @ fwd
    assert np.all(depth > 0)
    inside = (np.abs(v @ right / depth) < tan_half * aspect) & (np.abs(v @ up / depth) < tan_half)
    # At most 2% of the medium's voxels (stray wisps at the edge) may fall outside.
    assert inside.mean() >= 0.98, inside.mean()


@pytest.mark.parametrize("name", ["jade", "milk"])
def test_translucent_examples_are_optically_thick(name):
    # The brief asks for optical thickness of tens through these solids: integrate
    # sigma_t along the central x row of the generated grid.
    s = load_scene(EXAMPLES / f"{name}.toml")
    grid = s.volume.load()
    nz, ny, nx = grid.density.shape
    tau = float(grid.density[nz // 2, ny // 2, :].sum()) * grid.cell_size[0] * s.medium.density_scale
    assert 10.0 <= tau <= 100.0, tau


@pytest.mark.parametrize("path", EXAMPLE_FILES, ids=[p.stem for p in EXAMPLE_FILES])
def test_example_round_trips(tmp_path, path):
    s1 = load_scene(path)
    out = tmp_path / path.name
    out.write_text(dumps_scene(s1, relative_to=tmp_path))
    s2 = load_scene(out)
    assert (s2.volume, s2.medium, s2.light, s2.camera) == (s1.volume, s1.medium, s1.light,
                                                         s1.camera)


def test_the_tests_scene_writer_writes_what_it_is_given(tmp_path):
    """tests/scene_toml.py (the small scenes other tests render) writes its tables as given."""
    import tomllib
    from scene_toml import CAMERA, SMALL_CLOUD, write_scene
    tables = {**SMALL_CLOUD, "medium": {"density_scale": 4.0, "albedo": [0.9, 0.8, 0.7],
                                        "phase": {"type": "hg", "g": 0.5}, "preset": 'a"b'}}
    path = write_scene(tmp_path / "s.toml", **tables)
    assert tomllib.loads(path.read_text()) == tables
    assert load_scene(write_scene(tmp_path / "c.toml", **SMALL_CLOUD)).camera.fov_y == CAMERA["fov_y"]


def test_a_declared_medium_property_is_read_checked_and_written_from_its_declaration(
        monkeypatch):
    """clvol/scenemodel.py ``declared``: the reader takes the property from [medium] (its
    default when left out), refuses a value outside its declared range with the file's
    one-line message, and the writer gives it back, all with no code of its own (the
    medium class is swapped for one that declares a number and an RGB)."""
    import dataclasses as dc

    import clvol.scenefile as sf
    from clvol.scenemodel import Medium, declared

    @dc.dataclass(frozen=True)
    class Declaring(Medium):
        gain: float = declared(1.0, "a number", lo=0.0, hi=2.0, hi_open=True)
        tint: tuple = declared((1.0, 1.0, 1.0), "an RGB", kind="rgb", lo=0.0, hi=1.0)

    monkeypatch.setattr(sf, "Medium", Declaring)
    base = {"volume": {"generator": "sphere"},
            "medium": {"density_scale": 3.0, "albedo": 0.9, "phase": {"type": "isotropic"}},
            "light": {"direction": [0, 1, 0]},
            "camera": {"origin": [0, 0, 3], "target": [0, 0, 0], "up": [0, 1, 0],
                       "fov_y": 40.0, "width": 8, "height": 8}}
    plain = scene_from_dict(copy.deepcopy(base))
    assert (plain.medium.gain, plain.medium.tint) == (1.0, (1.0, 1.0, 1.0))
    data = copy.deepcopy(base)
    data["medium"].update(gain=1.5, tint=[0.2, 0.4, 0.6])
    s = scene_from_dict(data)
    assert (s.medium.gain, s.medium.tint) == (1.5, (0.2, 0.4, 0.6))
    assert scene_from_dict(s.to_dict()).medium == s.medium          # written and read back
    assert "gain = 1.5" in dumps_scene(s)
    assert s.with_overrides({"medium.gain": 0.25}).medium.gain == 0.25
    data["medium"]["gain"] = 2.0
    with pytest.raises(SceneError, match=r"\[medium.gain\] = 2.0: must be in \[0, 2\)"):
        scene_from_dict(data, source="x.toml")
    data["medium"]["gian"] = 1.0
    with pytest.raises(SceneError, match="did you mean gain"):
        scene_from_dict(data)
    # a declaration the reader could not honour is refused where it is written
    from clvol.scenemodel import Property
    for bad in (dict(kind="vector"), dict(kind="rgb", lo=0.0, lo_open=True)):
        with pytest.raises(TypeError):
            Property(help="x", **bad)
