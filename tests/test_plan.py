"""plan_frame (clvol/render/plan.py): the one place that decides a ray-marched frame.

Each decision is checked on a small generated volume, with no device work: the plan is pure
(the test fails if deciding touches the OpenCL runtime). The expected values are written from
docs/raymarch.md's rules, not read back from the code's constants. The last test holds the
"one place" claim: no other module of clvol/ calls the deciding functions.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

from clvol.render.ms.network import load_network_weights, shipped_weights
from clvol.render.options import bind
from clvol.render.plan import VolumeFacts, plan_frame
from clvol.scene import scene_from_dict

ROOT = Path(__file__).resolve().parents[1]


def _scene(**medium):
    m = {"density_scale": 30.0, "albedo": 0.9, "phase": {"type": "hg", "g": 0.5}}
    m.update(medium)
    return scene_from_dict({
        "volume": {"generator": "sphere", "seed": 1, "resolution": 16},
        "medium": m,
        "light": {"direction": [0.4, 0.8, 0.3], "irradiance": [1, 1, 1]},
        "camera": {"origin": [0, 0, 2.5], "target": [0, 0, 0], "up": [0, 1, 0],
                   "fov_y": 30.0, "width": 10, "height": 8}}, "<plan>")


@pytest.fixture(scope="module")
def domain():
    from clvol.features.weights import weights_domain
    return weights_domain(load_network_weights(shipped_weights()).meta)


@pytest.fixture
def no_device(monkeypatch):
    """Deciding must not reach the OpenCL runtime."""
    import clvol.runtime as runtime

    def refuse(*a, **k):
        raise AssertionError("plan_frame touched the OpenCL runtime")
    monkeypatch.setattr(runtime, "get_runtime", refuse)
    monkeypatch.setattr(runtime.Runtime, "__init__", refuse)


def _plan(scene, domain, **given):
    given.setdefault("ms", "network")   # the domain and thin-medium rules, on the lattice source
    return plan_frame(scene, bind("raymarch", given), VolumeFacts(scene.volume.load()), domain)


def test_the_network_runs_inside_its_domain(domain, no_device):
    p = _plan(_scene(), domain)
    assert p.source == "network" and p.warning is None and p.lit
    assert p.defines["MS_SOURCE"] == 2 and p.defines["MS_CHANNELS"] == 1    # grey: one plane
    assert p.lattice_reach is not None and "LIT" in p.defines and p.defines["LIT"] == 1
    assert p.keys["ms"][0] == (0.0, 0.0, 2.5)        # the lattice follows the camera position


def test_thin_medium_runs_single_scattering_alone(domain, no_device):
    # the sphere's largest optical thickness at scale 0.01 is far below 0.5
    p = _plan(_scene(density_scale=0.01), domain)
    assert p.source == "none" and p.thin is not None and p.thin < 0.5
    assert any("optically thin" in s for s in p.skipped)
    assert p.defines["MS_SOURCE"] == 0 and p.lattice_reach is None
    # with shortcuts off the network runs all the same
    assert _plan(_scene(density_scale=0.01), domain, shortcuts=False).source == "network"


def test_strongly_backward_phase_falls_back_with_a_warning(domain, no_device):
    back = {"type": "hg", "g": -0.95}
    p = _plan(_scene(albedo=0.95, phase=back), domain)
    assert p.source == "wrenninge" and "outside the network's training domain" in p.warning
    assert p.defines["MS_SOURCE"] == 1
    assert _plan(_scene(albedo=0.5, phase=back), domain).source == "none"
    kept = _plan(_scene(albedo=0.95, phase=back), domain, domain_fallback=False)
    assert kept.source == "network" and "--no-domain-fallback" in kept.warning


def test_max_order_one_is_single_scattering(domain, no_device):
    p = _plan(_scene(), domain, max_order=1, ms="none")
    assert p.source == "none" and p.defines["MS_SOURCE"] == 0


def test_unlit_isotropic_coloured(domain, no_device):
    unlit = _plan(_scene(albedo=0.0), domain)
    assert not unlit.lit and unlit.defines["LIT"] == 0
    # the resolution is resolved (a bundle's host may light the medium later), but no light
    # field is built and the header reports none
    assert "transmittance" not in unlit.programs and "pyramid" not in unlit.programs
    assert unlit.header("-")["raymarch.light_resolution"] == 0
    iso = _plan(_scene(phase={"type": "isotropic"}), domain)
    assert iso.lobes == () and any("isotropic" in s for s in iso.skipped)
    colour = _plan(_scene(albedo=[0.9, 0.8, 0.7]), domain)
    assert colour.defines["MS_CHANNELS"] == 3 and colour.channels == 3


def test_supersample_marches_the_finer_camera(domain, no_device):
    p = _plan(_scene(), domain, supersample=3)
    assert (p.camera.width, p.camera.height) == (30, 24)


def test_stochastic_block_and_view_defines(domain, no_device):
    p = _plan(_scene(), domain, ms="stochastic", view_block=2)
    assert p.defines["MS_SOURCE"] == 3 and p.defines["VIEW_BLOCK"] == 2
    assert p.defines["VIEW_K"] == 1


def test_only_plan_py_decides_the_source():
    """The plan decides: ``choose_source`` is called in clvol/render/plan.py alone, and asks
    the configured source's ``choose_for``; the network's rule (``fallback_for``) is applied in
    its own module alone (the bundle writes the thresholds as data for the C library, and
    may ask whether the fixed phase lies outside the domain, but never chooses a source)."""
    callers = {"fallback_for": set(), "choose_source": set(), "choose_for": set()}
    for path in (ROOT / "clvol").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call):
                name = getattr(node.func, "id", None) or getattr(node.func, "attr", None)
                if name in callers:
                    callers[name].add(path.relative_to(ROOT).as_posix())
    assert callers == {"fallback_for": {"clvol/render/ms/network.py"},
                       "choose_source": {"clvol/render/plan.py"},
                       "choose_for": {"clvol/render/plan.py"}}, callers


def _sky(scene, albedo=None, **light):
    import dataclasses
    lt = dataclasses.replace(scene.light, environment=(0.3, 0.5, 0.9), **light)
    med = scene.medium if albedo is None else dataclasses.replace(scene.medium, albedo=albedo)
    return dataclasses.replace(scene, light=lt, medium=med)


def test_the_sky_multiple_scattering_follows_the_sun_source(domain, no_device):
    """docs/raymarch.md "Environment light": the network for the sky wherever it serves the
    sun; the escape model for an analytic source, on request, and in the white furnace (where
    it is exact); nothing at --max-order 1."""
    sc = _sky(_scene())
    p = _plan(sc, domain)
    assert p.env_scatter and p.env_ms == "network" and p.env_ms_directions == 32
    assert p.env_reach is not None                   # only voxels near density are queried
    assert p.header("x")["raymarch.env_ms"] == "network"
    assert p.keys["env_field"][4] == (0.0, 0.0, 2.5)  # the network's F_ms follows the camera
    assert _plan(sc, domain, env_ms_directions=8).env_ms_directions == 8
    assert _plan(sc, domain, ms="wrenninge").env_ms == "escape"
    assert _plan(sc, domain, env_ms="escape").env_ms == "escape"
    assert _plan(sc, domain, ms="stochastic").env_ms == "network"
    furnace = _plan(_sky(_scene(), albedo=(1.0, 1.0, 1.0)), domain)
    assert furnace.env_ms == "escape" and "uniform sky" in "; ".join(furnace.simulated)
    p1 = _plan(sc, domain, ms="none", max_order=1)
    assert p1.env_scatter and p1.env_ms == "none"
    assert "environment multiple scattering (--max-order 1)" in p1.skipped
    # sun-lit, no sky: none of it
    p0 = _plan(_scene(), domain)
    assert not p0.env_scatter and "env_field" not in p0.keys


def _built_programs(monkeypatch) -> list:
    """Record every (source stem, defines) handed to the runtime's program cache."""
    from clvol.runtime import Runtime
    built, real = [], Runtime.program

    def record(self, stem, defines=None, extra_options=()):
        built.append((stem, dict(defines or {})))
        return real(self, stem, defines, extra_options)
    monkeypatch.setattr(Runtime, "program", record)
    return built


@pytest.mark.parametrize("sky", [None, (0.3, 0.4, 0.5)])
@pytest.mark.parametrize("given", [{}, {"ms": "wrenninge"}, {"ms": "none"},
                                   {"light_interp": "optical_depth", "shortcuts": False}])
def test_the_programs_a_frame_builds_are_the_plans(monkeypatch, given, sky):
    """Every program a render builds (the first frame: majorant, light field, network,
    march; with a sky its fields and the network's share) is one of ``FramePlan.programs``
    with exactly its defines (plus PoCL's additions on PoCL), and every planned program is
    built: the executors decide no define. (This test renders: the device is used.)"""
    import dataclasses
    from clvol.render.plan import program_source
    from clvol.render.renderer import Renderer
    built = _built_programs(monkeypatch)
    scene = _scene()
    if sky is not None:
        scene = dataclasses.replace(scene, light=dataclasses.replace(scene.light,
                                                                     environment=sky))
    r = Renderer(scene, "raymarch", **given)
    r.render()
    plan = r.plan()
    pocl = r.rt.is_pocl

    def entry(stem, defines):
        return stem, tuple(sorted(defines.items()))
    want = {entry(program_source(name), dict(d, **(plan.programs_pocl.get(name, {})
                                                  if pocl else {})))
            for name, d in plan.programs.items()}
    assert {entry(stem, d) for stem, d in built} == want
