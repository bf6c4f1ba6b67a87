"""Environment light in the ray marcher (clvol/render/environment.py; docs/raymarch.md
"Environment light"): the white furnace, the map background, the path tracer on a sky-only
cloud, and the recompute table of a Renderer whose sky changes. The kernel's ENV and BG_IMAGE
paths against their twin are in tests/test_raymarch.py (test_kernel_matches_twin_environment).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import clvol
from clvol import envmap
from clvol.image import write_exr
from clvol.render import environment as env
from clvol.render.ms import source_class
from clvol.scene import scene_from_dict

SKY = (0.3, 0.5, 0.9)
CAM = {"origin": [0.0, 0.15, 1.6], "target": [0.0, 0.06, 0.0], "up": [0.0, 1.0, 0.0],
       "fov_y": 35.0}


def _scene(albedo=1.0, phase=None, light=None, size=(36, 28), res=24, scale=30.0):
    d = {"volume": {"generator": "cloud", "seed": 1, "resolution": res},
         "medium": {"preset": "cloud", "density_scale": scale, "albedo": albedo},
         "light": {"direction": [0.45, 0.4, -0.8], "irradiance": 0.0,
                   **({"environment": list(SKY)} if light is None else light)},
         "camera": {**CAM, "width": size[0], "height": size[1]}}
    if phase:
        d["medium"]["phase"] = phase
    return scene_from_dict(d)


def test_sky_directions_cover_the_sphere_evenly():
    d = env.sky_directions(64)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(d.mean(axis=0), 0.0, atol=0.02)   # no preferred side


@pytest.mark.parametrize("phase", [{"type": "isotropic"}, None], ids=["iso", "hg0.857"])
@pytest.mark.parametrize("ms", ["none", "network"])
def test_white_furnace_renders_the_sky_everywhere(phase, ms):
    """Albedo 1 under a uniform sky: the medium vanishes. The escape model is exact there for
    any phase function (environment.py: single + multiple = albedo sum_i E_i f_i = L), and the
    plan takes it there with the network sources too, so what is left is float32 rounding over
    a march of ~100 segments: measured 3e-7, bound 1e-5 (100x the rounding of a float32 sum of
    that length), far inside the 1% target."""
    r = clvol.Renderer(_scene(phase=phase), ms=ms).render()
    tot = r.layers["total"].astype(np.float64)
    assert (r.layers["alpha"] > 0.9).mean() > 0.2          # the cloud covers the image
    assert r.layers["multiple"].max() > 0.1 * max(SKY)       # and scatters many times
    np.testing.assert_allclose(tot, np.broadcast_to(SKY, tot.shape), rtol=1e-5)


def test_furnace_with_a_uniform_map_and_the_map_background(tmp_path):
    """A uniform map (scaled, turned) is a furnace too, its cells' solid angles being the map's
    own; where no ray meets the medium the map itself is seen."""
    write_exr(tmp_path / "u.exr", {"total": np.ones((8, 16, 3), np.float32)})
    light = {"environment_map": str(tmp_path / "u.exr"), "environment_scale": list(SKY),
             "environment_rotation": 30.0}
    r = clvol.Renderer(_scene(light=light), ms="none").render()
    tot = r.layers["total"].astype(np.float64)
    np.testing.assert_allclose(tot, np.broadcast_to(SKY, tot.shape), rtol=1e-5)
    assert "environment map along each camera ray" in r.header["simulated"]


def test_a_map_scaled_to_zero_scatters_nothing_and_costs_nothing(tmp_path):
    """A black sky, constant or a map scaled to 0 (the viewer's sky slider at 0), is not
    simulated: no transmittance sweeps, no field, and the header says it is skipped."""
    write_exr(tmp_path / "u.exr", {"total": np.ones((8, 16, 3), np.float32)})
    for light in ({"environment_map": str(tmp_path / "u.exr"), "environment_scale": 0.0},
                  {"environment": [0.0, 0.0, 0.0]}):
        r = clvol.Renderer(_scene(light=light), ms="none")
        res = r.render()
        assert r.counts["env_transmittance"] == 0 and r.counts["env_field"] == 0
        assert "environment" in res.header["skipped"]
        assert res.layers["total"].max() == 0.0


def test_map_background_is_the_map_along_each_camera_ray(tmp_path):
    rs = np.random.default_rng(3)
    m = (0.1 + rs.random((8, 16, 3))).astype(np.float32)
    write_exr(tmp_path / "m.exr", {"total": m})
    scene = _scene(albedo=0.0, light={"environment_map": str(tmp_path / "m.exr"),
                                      "environment_scale": [1.0, 0.5, 2.0],
                                      "environment_rotation": -40.0}, size=(33, 21))
    r = clvol.Renderer(scene, ms="none").render()
    clear = r.layers["alpha"] == 0
    assert 0.2 < clear.mean() < 0.95
    want = envmap.lookup(m, (1.0, 0.5, 2.0), -40.0, scene.camera.pixel_directions())
    t = r.layers["total"]
    # Nearest-texel lookups may flip at a texel border between float32 and float64 rays.
    agree = np.all(np.abs(t - want) <= 1e-6 * np.abs(want), axis=-1)
    assert agree[clear].mean() > 0.98
    assert "environment in-scattering (albedo 0" in r.header["skipped"]


def test_sky_only_cloud_matches_the_path_tracer():
    """A sky-only cloud (24^3, albedo 0.99, HG 0.857, optical depth ~10) against the path
    tracer at 2 x 128 spp, noise-corrected (the two runs' difference estimates the reference's
    noise). Measured: image mean -2.7%, RMSE x100 3.2 (reference noise 0.8). Bounds: the
    issue's 5% on the mean; RMSE x100 <= 4 (the 96^3 clouds measure 0.7-4.3 at albedo 0.8-1,
    docs/raymarch.md)."""
    scene = _scene(albedo=0.99, size=(32, 32))
    r = clvol.Renderer(scene, "pathtrace", spp=128)
    p1 = r.render(seed=5).layers["total"].astype(np.float64)
    p2 = r.render(seed=6).layers["total"].astype(np.float64)
    pt = 0.5 * (p1 + p2)
    noise = ((p1 - p2) ** 2).mean() / 4                  # variance of the two runs' mean
    rm = clvol.Renderer(scene, ms="none").render().layers["total"].astype(np.float64)
    rel = rm.mean() / pt.mean() - 1
    rmse = 100 * np.sqrt(max(((rm - pt) ** 2).mean() - noise, 0.0))
    print(f"mean {rel:+.4f}, rmse x100 {rmse:.3f} (reference noise {100 * np.sqrt(noise):.3f})")
    assert abs(rel) < 0.05, (rm.mean(), pt.mean())
    assert rmse < 4.0


def test_environment_change_recomputes_only_what_depends_on_it():
    scene = _scene(albedo=0.9, size=(16, 12))
    r = clvol.Renderer(scene, ms="none")
    r.render()
    base = dict(r.counts)
    assert base["env_transmittance"] == base["env_sky"] == base["env_field"] == 1
    r.render()                                                    # nothing changed
    assert dict(r.counts) == {**base, "march": 2}
    blue = dataclasses.replace(scene.light, environment=(0.1, 0.2, 0.6))
    a = r.render(light=blue)                                       # a new sky: no new sweeps
    assert r.counts["env_transmittance"] == 1 and r.counts["env_sky"] == 2
    assert r.counts["env_field"] == 2
    cam = dataclasses.replace(scene.camera, origin=(0.2, 0.15, 1.6))
    r.render(camera=cam, light=blue)                               # anisotropic: field per camera
    assert r.counts["env_field"] == 3 and r.counts["env_sky"] == 2
    thick = dataclasses.replace(scene.medium, density_scale=45.0)
    r.render(camera=cam, light=blue, medium=thick)                 # new density: new sweeps
    assert r.counts["env_transmittance"] == 2
    assert r.counts.get("light_field", 0) == 0                     # no sun: no light field
    # The new sky is what was rendered: a fresh Renderer agrees bit for bit.
    fresh = clvol.Renderer(dataclasses.replace(scene, light=blue), ms="none").render()
    np.testing.assert_array_equal(a.layers["total"], fresh.layers["total"])
    # Without an environment nothing of it is computed.
    plain = clvol.Renderer(_scene(light={}), ms="none")
    plain.render()
    assert not any(k.startswith("env_") for k in plain.counts)


@pytest.mark.parametrize("opts, text", [
    ({"env_resolution": 3}, "env_resolution = 3"),
    ({"env_resolution": 512}, "env_resolution = 512"),
    ({"env_resolution": 0}, "env_resolution = 0"),
    ({"env_directions": 0}, "environment directions = 0"),
    ({"env_directions": 2.5}, "environment directions = 2.5"),
    ({"env_ms": "diffusion"}, "env_ms = 'diffusion'"),
    ({"env_ms_directions": 0}, "env_ms_directions = 0"),
    ({"env_ms_directions": 300}, "env_ms_directions = 300"),
    ({"env_ms_per_frame": -1}, "env_ms_per_frame = -1"),
    ({"env_ms_per_frame": True}, "env_ms_per_frame = True"),
])
def test_bad_environment_options_are_refused_when_the_renderer_is_made(opts, text):
    """Refused at Renderer(...), with the option named, even for a scene without a sky (which
    never reads them): a mistake in a call should not wait for a sky scene to show."""
    sc = _scene(light={"irradiance": 1.0})
    from clvol.errors import ClvolError
    with pytest.raises(ClvolError, match=text.replace(".", r"\.")):
        clvol.Renderer(sc, ms="none", **opts)


def test_network_sky_beats_the_escape_model_against_the_path_tracer():
    """The sky's multiple scattering from the network (the default with --ms network) on a
    sky-only cloud (24^3, albedo 0.9, HG 0.857) against the path tracer at 2 x 128 spp,
    noise-corrected as above. Measured: network rmse x100 1.11, mean +0.1%; the escape model
    4.11, -3.8% (reference noise 1.06). Bounds: the issue's targets, RMSE x100 <= 2.0 and the
    mean within 5%; and the network below the escape model, measured in the same run."""
    scene = _scene(albedo=0.9, size=(32, 32))
    r = clvol.Renderer(scene, "pathtrace", spp=128)
    p1 = r.render(seed=5).layers["total"].astype(np.float64)
    p2 = r.render(seed=6).layers["total"].astype(np.float64)
    pt = 0.5 * (p1 + p2)
    noise = ((p1 - p2) ** 2).mean() / 4
    err = {}
    for how in ("network", "escape"):
        res = clvol.Renderer(scene, env_ms=how).render()
        assert res.header["raymarch.env_ms"] == how
        rm = res.layers["total"].astype(np.float64)
        err[how] = (rm.mean() / pt.mean() - 1,
                    100 * np.sqrt(max(((rm - pt) ** 2).mean() - noise, 0.0)))
    print(err)
    assert abs(err["network"][0]) < 0.05 and err["network"][1] <= 2.0
    assert err["network"][1] < err["escape"][1]


def test_network_sky_is_the_irradiance_weighted_sum_of_the_networks_f_ms():
    """environment.SkyNetwork against the network's own point evaluations: every lit cell's
    F_ms toward the camera at the field's voxel centres within reach, weighted by that cell's
    (distinct, coloured) irradiance; 0 at the voxels out of reach. A new sky over the same
    directions re-weights the cells without a network call."""
    from clvol.render.ms.network import NetworkSource, shipped_weights
    scene = _scene(albedo=0.8, size=(8, 8))
    grid = scene.volume.load()
    sky_net = env.SkyNetwork(source_class("network"), None, grid, scene.medium, None, None)
    dirs = np.array([[0.0, 1.0, 0.0], [0.6, 0.0, 0.8], [0.0, -0.6, -0.8]])
    E = np.array([[1.0, 2.0, 3.0], [0.5, 0.25, 0.0], [0.0, 0.0, 0.0]])   # one black cell
    cells = env.Sky(dirs, E, (1.0, 1.0, 1.0), 3, np.full(3, 4 * np.pi / 3))
    lo, size, n = np.asarray(grid.bbox_min) - 0.05, float(np.max(np.asarray(grid.bbox_max)
                                                               - grid.bbox_min)) + 0.1, 8
    origin = np.array([0.1, 0.3, 1.7])
    got = sky_net.field(cells, scene.medium, lo, size, n, origin, reach=0.05)
    assert sky_net.evaluated == 2 and sky_net.pending == 0       # the black cell is skipped
    act = sky_net.active(lo, size, n, 0.05)
    assert 0 < act.sum() < n ** 3 and np.all(got[:, ~act] == 0.0)
    pts = env.voxel_centres(lo, size, n)[act]
    toward = origin - pts
    toward /= np.linalg.norm(toward, axis=1, keepdims=True)
    net = NetworkSource(shipped_weights(), grid, scene.medium)
    want = np.zeros((3, len(pts)))
    for w, e in zip(dirs[:2], E[:2]):
        f, _ = net.evaluate(pts, toward, w, scene.medium)
        want += np.asarray(e)[:, None] * np.asarray(f, np.float64)[None, :]   # grey medium
    assert want.max() > 0
    np.testing.assert_allclose(got[:, act], want, rtol=1e-5, atol=1e-7)
    E2 = E[::-1].copy()                                         # a new sky: the third cell lit
    got2 = sky_net.field(env.Sky(dirs, E2, (1.0, 1.0, 1.0), 3, cells.solid_angles),
                         scene.medium, lo, size, n, origin, reach=0.05)
    assert sky_net.evaluated == 1                               # only the newly lit cell
    f3, _ = net.evaluate(pts, toward, dirs[2], scene.medium)
    f2, _ = net.evaluate(pts, toward, dirs[1], scene.medium)
    want2 = E2[2][:, None] * np.asarray(f3, np.float64) + E2[1][:, None] * np.asarray(f2, np.float64)
    np.testing.assert_allclose(got2[:, act], want2, rtol=1e-5, atol=1e-7)


def test_network_sky_refreshes_a_few_cells_per_frame_when_asked():
    """--env-ms-per-frame 1: after a camera move, one stale cell per frame, the header saying
    the view still refines; once every cell is current the image is the all-at-once one."""
    scene = _scene(albedo=0.9, size=(12, 10))
    r = clvol.Renderer(scene, env_ms_directions=3, env_ms_per_frame=1)
    first = [r.render().header for _ in range(3)]
    assert [h["raymarch.env_ms_cells_evaluated"] for h in first] == [1, 1, 1]
    assert [h["raymarch.env_refining"] for h in first] == [True, True, False]
    h = r.render().header                                      # settled: nothing to do
    assert h["raymarch.env_ms_cells_evaluated"] == 0 and h["raymarch.env_refining"] is False
    cam = dataclasses.replace(scene.camera, origin=(0.3, 0.15, 1.6))
    frames = [r.render(camera=cam) for _ in range(3)]
    assert [f.header["raymarch.env_refining"] for f in frames] == [True, True, False]
    whole = clvol.Renderer(dataclasses.replace(scene, camera=cam),
                           env_ms_directions=3).render()
    assert whole.header["raymarch.env_ms_cells_evaluated"] == 3
    np.testing.assert_allclose(frames[-1].layers["total"], whole.layers["total"], rtol=1e-6,
                               atol=1e-7)
    assert np.abs(frames[0].layers["total"] - whole.layers["total"]).max() > 1e-5


def test_network_sky_recomputes_per_camera_and_keeps_its_graded_fields():
    """With the network for the sky: a camera move refills the field (F_ms looks toward the
    camera) but builds no graded transmittance again (kept per cell); a new sky colour makes
    new cells and a new field, with the same network."""
    scene = _scene(albedo=0.9, size=(12, 10))
    r = clvol.Renderer(scene, env_ms_directions=4)
    r.render()
    assert r.counts["env_field"] == 1 and r.counts["env_ms_sky"] == 1
    net = r._marcher._env_net.net
    assert net.graded_builds == 4
    r.render()
    assert r.counts["env_field"] == 1                        # nothing changed
    cam = dataclasses.replace(scene.camera, origin=(0.3, 0.15, 1.6))
    r.render(camera=cam)
    assert r.counts["env_field"] == 2 and net.graded_builds == 4
    blue = dataclasses.replace(scene.light, environment=(0.1, 0.2, 0.6))
    a = r.render(camera=cam, light=blue)
    assert r.counts["env_ms_sky"] == 2 and r.counts["env_field"] == 3
    assert r.counts["env_network_setup"] == 1 and net.graded_builds == 4
    fresh = clvol.Renderer(dataclasses.replace(scene, light=blue, camera=cam),
                           env_ms_directions=4).render()
    np.testing.assert_array_equal(a.layers["total"], fresh.layers["total"])
