"""One validation for every door: a camera, light or medium reaching a render through the
scene file (``scene_from_dict`` / ``Scene.with_overrides``), through ``Renderer.render(camera=
dataclasses.replace(...))``, or inside a scene made with ``dataclasses.replace`` and handed to
``Renderer(scene)``, passes the same checks (clvol/scenefile.py ``check_part``) and is refused
with the same one-line message after the source's name, in well under the issue's 5 s at 32^2.

Before the check, the Python API rendered ``width = 0`` as an empty image and ``fov_y = 0``
as a picture, and a camera at its target, a NaN origin or an ``up`` along the view ran until
killed (issue 41). The C library's setters are held to the same fields in tests/test_capi.py
(``test_setters_refuse_what_the_scene_file_refuses``).
"""
from __future__ import annotations

import dataclasses
import time

import pytest

import clvol
from clvol.errors import ClvolError, SceneError
from clvol.scene import Phase, scene_from_dict
from clvol.scenemodel import MAX_IMAGE_SIZE

NAN, INF = float("nan"), float("inf")

BASE = {
    "volume": {"generator": "sphere", "resolution": 8},
    "medium": {"preset": "cloud", "density_scale": 8.0},
    "light": {"direction": [0.0, 1.0, 0.0]},
    "camera": {"origin": [0.0, 0.0, 2.5], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0],
               "fov_y": 35.0, "width": 32, "height": 32},
}

# (dotted field, bad value): every camera, light and medium field a caller can set, with a
# value out of its range (or of the wrong kind).
BAD = [
    ("camera.origin", [NAN, 0.0, 2.5]),
    ("camera.origin", [0.0, 0.0, 0.0]),                 # at its target
    ("camera.origin", [0.0, INF, 2.5]),
    ("camera.origin", [0.0, 2.5]),
    ("camera.target", [0.0, 0.0, NAN]),
    ("camera.up", [0.0, 0.0, 1.0]),                     # parallel to the view direction
    ("camera.up", [0.0, 0.0, 0.0]),
    ("camera.up", [NAN, 1.0, 0.0]),
    ("camera.fov_y", 0.0),
    ("camera.fov_y", 180.0),
    ("camera.fov_y", NAN),
    ("camera.fov_y", -5.0),
    ("camera.width", 0),
    ("camera.height", 0),
    ("camera.width", -3),
    ("camera.width", MAX_IMAGE_SIZE + 1),
    ("camera.width", 2.5),
    ("light.direction", [0.0, 0.0, 0.0]),
    ("light.direction", [NAN, 1.0, 0.0]),
    ("light.irradiance", [1.0, -0.5, 1.0]),
    ("light.irradiance", [1.0, INF, 1.0]),
    ("light.environment", [NAN, 0.0, 0.0]),
    ("light.environment", [-1.0, 0.0, 0.0]),
    ("medium.density_scale", -1.0),
    ("medium.density_scale", NAN),
    ("medium.density_scale", INF),
    ("medium.albedo", [1.1, 0.5, 0.5]),
    ("medium.albedo", [0.5, -0.1, 0.5]),
    ("medium.albedo", [0.5, NAN, 0.5]),
]


def _scene():
    return scene_from_dict(BASE, "<doors>")


def _part(scene, dotted, value):
    """The scene's part with one field replaced in code, as an API user writes it."""
    table, field = dotted.split(".")
    part = getattr(scene, table)
    value = tuple(value) if isinstance(value, list) else value
    return table, dataclasses.replace(part, **{field: value})


def _tail(msg: str) -> str:
    """The message after its source ("<file>: " or "Renderer.render(camera=...): ")."""
    return msg[msg.index(": [") + 2:]


@pytest.fixture(scope="module")
def renderers():
    scene = _scene()
    return {"raymarch": clvol.Renderer(scene, ms="none"),
            "pathtrace": clvol.Renderer(scene, "pathtrace", spp=1)}


@pytest.mark.parametrize("dotted,value", BAD, ids=[f"{d}={v}" for d, v in BAD])
def test_every_field_is_refused_alike_through_every_door(renderers, dotted, value):
    scene = _scene()
    with pytest.raises(SceneError) as file_door:
        scene.with_overrides({dotted: value}, source="scene.toml")
    want = _tail(str(file_door.value))
    assert str(file_door.value).startswith(f"scene.toml: [{dotted.split('.')[0]}.")
    table, part = _part(scene, dotted, value)
    for method, r in renderers.items():
        t0 = time.perf_counter()
        with pytest.raises(SceneError) as api_door:
            r.render(**{table: part})
        assert time.perf_counter() - t0 < 5.0
        msg = str(api_door.value)
        assert msg == f"Renderer.render({table}=...): {want}", (method, msg)
        assert "\n" not in msg
    # a scene made in code, rendered with its own parts
    bad_scene = dataclasses.replace(scene, **{table: part})
    with pytest.raises(SceneError) as scene_door:
        clvol.Renderer(bad_scene, ms="none").render()
    assert str(scene_door.value) == f"Renderer(scene): {want}"
    # the plan (clvol bundle's door) checks the same
    with pytest.raises(SceneError):
        renderers["raymarch"].plan(**{table: part})


def test_wrong_types_and_phases_are_refused_in_one_line(renderers):
    r, scene = renderers["raymarch"], _scene()
    cases = [({"camera": (0, 0, 1)}, "expected a clvol.scene.Camera"),
             ({"camera": dataclasses.replace(scene.camera, origin="abc")},
              '[camera.origin] = "abc": must be a list of 3 numbers'),
             ({"medium": dataclasses.replace(scene.medium, phase=None)},
              "[medium.phase] = None: must be a clvol.scene.Phase"),
             ({"medium": dataclasses.replace(scene.medium, phase=Phase.hg(1.0))},
              "[medium.phase.g] = 1.0: must be in [-0.99, 0.99]"),
             ({"medium": dataclasses.replace(scene.medium,
                                             phase=Phase("isotropic", Phase.hg(0.5).lobes))},
              "an isotropic phase has one lobe of weight 1 and g = 0"),
             ({"medium": dataclasses.replace(scene.medium, phase=Phase.mhg([(0.5, 0.5)]))},
              "weights sum to 0.5")]
    for kw, text in cases:
        with pytest.raises(ClvolError) as e:
            r.render(**kw)
        assert text in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_density_scale_zero_is_accepted_by_every_door(renderers):
    """An empty medium (density_scale 0): the scene file takes it, as Renderer.render and the
    C library do; the image is the background alone, with no NaN."""
    import numpy as np
    scene = _scene().with_overrides({"medium.density_scale": 0.0,
                                     "light.environment": [0.2, 0.3, 0.4]})
    assert scene.medium.density_scale == 0.0
    for method in ("raymarch", "pathtrace"):
        opts = {"ms": "none"} if method == "raymarch" else {"spp": 1}
        img = clvol.Renderer(scene, method, **opts).render()
        assert np.isfinite(img.total).all()
        np.testing.assert_allclose(img.total, np.broadcast_to([0.2, 0.3, 0.4], img.total.shape),
                                   rtol=1e-6)
        if method == "raymarch":
            assert img.alpha.max() == 0.0


def test_validated_parts_are_the_parsers(renderers):
    """What the check returns is what the scene file would give: a unit light direction, and
    the caller's own object when nothing changes (the renderer's caches keep their keys)."""
    scene = _scene()
    from clvol.scenefile import check_part
    assert check_part("camera", scene.camera, "x") is scene.camera
    light = dataclasses.replace(scene.light, direction=(0.0, 2.0, 0.0))
    assert check_part("light", light, "x").direction == (0.0, 1.0, 0.0)
    import numpy as np
    cam = dataclasses.replace(scene.camera, origin=np.array([0.0, 0.5, 2.5]),
                              width=np.int64(16))
    got = check_part("camera", cam, "x")
    assert got.origin == (0.0, 0.5, 2.5) and got.width == 16


def test_fuzz_found_tiny_vectors_render(renderers):
    """Found by tests/test_fuzz.py's long run: the scene file accepts an ``up`` as short as
    1e-259 (it normalises after scaling), but Camera.basis crossed the raw vector, the cross
    product underflowed to 0, the basis was NaN and the march never ended. Tiny and huge
    vectors now give the basis of their direction, in well under 5 s."""
    import numpy as np
    scene = _scene()
    cams = [dataclasses.replace(scene.camera, up=(0.0, 2.4e-259, 1.4e-285)),
            dataclasses.replace(scene.camera, up=(0.0, 1e200, 0.0)),
            dataclasses.replace(scene.camera, origin=(0.0, 0.0, 1e-200), target=(0.0, 0.0, 0.0),
                                fov_y=35.0)]
    want = scene.camera.basis()
    for cam in cams[:2]:
        for a, b in zip(cam.basis(), want):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-15)
    for cam in cams:
        for method, r in renderers.items():
            t0 = time.perf_counter()
            img = r.render(camera=cam)
            assert time.perf_counter() - t0 < 5.0, method
            assert all(np.isfinite(v).all() for v in img.layers.values()), method
