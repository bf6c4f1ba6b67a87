"""cl/raymarch.cl against reference/raymarch.py, and the ray marcher's physics and shortcuts.

Kernel vs twin tolerance: every layer within 2e-5 x the layer's largest value (absolute).
The kernel marches in float32 (positions, transmittance products and sums over up to ~100
segments each carry ~1e-7 relative rounding per operation; positions move lookups by
<= 1e-6 voxel), the twin in float64 on the same float32 inputs; measured differences are
3e-7..3e-6 of the layer maximum (7e-6 for the tiny single-scattering layer of the opaque
grid), so the bound has a margin of 3 or more without hiding a real error (a one-segment
shift or a wrong sample point changes layers by >= 1e-3 of their maximum).
Empty-space skipping and the scene shortcuts must not change the image: those tests compare
bit for bit (skipping) or within 2e-6 relative (different -D builds may contract multiply-adds
differently: a few float32 ULP).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from clvol.errors import ClvolError
from clvol.kernels import raymarch as kraymarch
from clvol.kernels.majorant import build_majorant
from render_helpers import render_raymarch
from clvol.render.ms.lattice import FmsLattice
from clvol.render.ms.base import Octaves
from clvol.scene import Phase, scene_from_dict
from clvol.volume.grid import DensityGrid
from reference import raymarch as rraymarch
from reference.phase import phase_eval
from media import light_of, medium_of
from scene_toml import CAMERA, look_at, write_scene

LAYER_NAMES = ("total", "single", "multiple", "alpha", "depth")
REL_TOL = 2e-5




def _inputs(case: str, source: str = "wrenninge", octaves=(3, 0.5, 0.5, 0.5), seed=0):
    """Keyword arguments shared by the kernel wrapper and the twin (float32-exact values)."""
    rs = np.random.default_rng(seed)
    shape = (7, 5, 9)                                      # nz, ny, nx: odd, non-cubic
    density = rs.random(shape).astype(np.float32)
    density[:, :, :4] = 0.0                                # an empty slab for the skipper
    bmin = np.array([-0.5, -0.4, -0.3], np.float32).astype(np.float64)
    bmax = np.array([0.4, 0.3, 0.5], np.float32).astype(np.float64)
    scale, width, height = 6.0, 13, 11
    origin, target = np.array([0.3, 0.8, 2.0]), np.zeros(3)
    up = (0.0, 1.0, 0.0)
    if case == "empty":
        density[:] = 0.0
    elif case == "opaque":
        density[:] = 1.0
        scale = 1e4                                        # ~100 optical depths per voxel
    elif case == "inside":
        origin, target = np.array([0.1, -0.1, 0.2]), np.array([-0.4, 0.0, -0.3])
        width, height = 9, 7
    elif case == "axis":
        origin, target = np.array([0.0, 0.0, 2.0]), np.zeros(3)   # forward = -z exactly
        width, height = 9, 9
    elif case == "graze":
        # Eye in the plane of the top face, looking along -z: the middle row (odd height,
        # sy = 0) travels inside that face plane.
        origin = np.array([0.0, bmax[1], 2.0])
        target = np.array([0.0, bmax[1], 0.0])
        width, height = 7, 5
    f, r, u = look_at(origin, target, up)
    block = 2
    # A smooth, varied light field over a cube holding the box (any field will do for
    # kernel vs twin; the physical one is tested below), held as T_light.
    n = 8
    zz, yy, xx = np.meshgrid(*(np.arange(n),) * 3, indexing="ij")
    light_tau = 0.3 * xx + 0.5 * (n - 1 - yy) + 0.1 * zz * xx / n
    if case == "opaque":
        light_tau *= 100                                   # T_light underflows to 0
    ms_lattice = None
    if source == "lattice1":
        ms_lattice = (0.05 + 0.1 * rs.random((1, 4, 3, 5))).astype(np.float32)
    elif source == "lattice3":
        ms_lattice = (0.05 + 0.1 * rs.random((3, 4, 3, 5))).astype(np.float32)
    elif source.startswith("view"):
        # (1 + C, by, bx, K) over blocks of 3 pixels (13 x 11 image: 5 x 4 blocks, the last
        # partial). Depths in the box's range from the camera (~1.6..2.6), unsorted spans
        # made increasing, one pair of equal knots (a step), two empty blocks.
        ch = 3 if source == "view3" else 1
        k = 4
        depth = np.sort(1.6 + rs.random((4, 5, k)), axis=2)
        depth[1, 2, 2] = depth[1, 2, 1]
        depth[1, 1, :] = -1.0                              # in front of the box
        depth[3, 4, :] = -1.0
        vals = 0.05 + 0.2 * rs.random((ch, 4, 5, k))
        vals[:, 1, 1] = 7.0                                # must never be read
        ms_lattice = np.concatenate([depth[None], vals]).astype(np.float32)
    n_oct, a, b, c = octaves
    return dict(
        density=density, bbox_min=bmin, bbox_max=bmax,
        medium=medium_of(scale, (0.9, 0.8, 0.7), [(0.8, 0.7), (-0.3, 0.3)]),
        majorant=build_majorant(density, block), block=block,
        light=np.exp(-light_tau).astype(np.float32), cube_min=np.array([-0.5, -0.5, -0.5]),
        cube_size=1.0,
        ms_lattice=ms_lattice, ms_bbox_min=np.array([-0.45, -0.4, -0.3]),
        ms_bbox_max=np.array([0.4, 0.25, 0.5]),
        origin=origin, forward=f, right=r, up=u,
        tan_half=math.tan(math.radians(40.0) / 2), width=width, height=height,
        sun=light_of((0.6, 0.8, 0.0), (1.0, 0.9, 0.8)),
        background=(0.1, 0.2, 0.3),
        source="lattice" if source.startswith("lattice") else "view" if source.startswith("view")
        else source, octaves=n_oct, a=a, b=b, c=c, step=0.05, threshold=0.0,
        **({"view_block": 3} if source.startswith("view") else {}))


def _f32(kw):
    """What the kernel sees: geometry rounded to float32 (the twin then runs in float64)."""
    out = dict(kw)
    for key in ("bbox_min", "bbox_max", "cube_min", "ms_bbox_min", "ms_bbox_max", "origin",
                "forward", "right", "up"):
        out[key] = np.asarray(kw[key], np.float32).astype(np.float64)
    for key in ("tan_half", "step", "cube_size"):
        out[key] = float(np.float32(kw[key]))
    out["sun"] = dataclasses.replace(kw["sun"], direction=tuple(
        np.asarray(kw["sun"].direction, np.float32).astype(np.float64)))
    out["medium"] = dataclasses.replace(
        kw["medium"], density_scale=float(np.float32(kw["medium"].density_scale)))
    return out


def _assert_layers_close(got, want, rel=REL_TOL):
    for name in LAYER_NAMES:
        scale = max(float(np.abs(want[name]).max()), 1e-30)
        err = float(np.abs(got[name] - want[name]).max())
        assert err <= rel * scale, f"layer {name}: max |kernel - twin| = {err:.3g} > {rel} x {scale:.3g}"


@pytest.mark.parametrize("case", ["odd", "inside", "axis", "graze", "empty", "opaque"])
def test_kernel_matches_twin(case):
    kw = _f32(_inputs(case))
    got = kraymarch.raymarch(**kw)
    want = rraymarch.raymarch(**kw)
    _assert_layers_close(got, want)
    assert got["stopped_at_bound"] == want["stopped_at_bound"] == 0
    if case == "empty":
        # Nothing in the box: the background alone, no alpha, depth 0 by definition.
        np.testing.assert_array_equal(got["alpha"], 0.0)
        np.testing.assert_array_equal(got["depth"], 0.0)
        np.testing.assert_allclose(got["total"], np.broadcast_to([0.1, 0.2, 0.3], got["total"].shape),
                                   rtol=1e-7)
    if case == "opaque":
        hit = want["alpha"] > 0
        assert hit.any()
        np.testing.assert_allclose(got["alpha"][hit], 1.0, atol=1e-6)
        assert np.all(got["total"][hit] < 1e-6)        # T_light ~ 0 and no background through


def test_kernel_and_twin_count_the_rays_the_progress_bound_stops():
    """The camera 2e6 from the box, the view narrow enough that every ray crosses it (0.25
    of half-height at 2e6): float32's rounding step of t there is 0.25, above twice the
    step (0.05), so t0 + step == t0 and every ray stops at its first segment, counted by the
    kernel (atomic, stats[0]) and by the twin (its float32 rule), 143 = 13 x 11 each; the
    layers agree (nothing marched: alpha 0, the background). 2e5 away (rounding step
    0.016, below the step) every ray marches and both count 0."""
    for distance, stopped in ((2e6, 13 * 11), (2e5, 0)):
        kw = _inputs("odd", "none")
        origin = np.array([0.0, 0.0, distance])
        f, r, u = look_at(origin, np.zeros(3), (0.0, 1.0, 0.0))
        kw.update(origin=origin, forward=f, right=r, up=u, tan_half=0.25 / distance)
        kw = _f32(kw)
        got = kraymarch.raymarch(**kw)
        want = rraymarch.raymarch(**kw)
        assert got["stopped_at_bound"] == want["stopped_at_bound"] == stopped, distance
        if stopped:
            _assert_layers_close(got, want)
            np.testing.assert_array_equal(got["alpha"], 0.0)
        else:   # (the layers: float32 positions 2e5 away are 0.016 apart, the twin's not)
            assert got["alpha"].max() > 0.5 and want["alpha"].max() > 0.5     # rays marched


@pytest.mark.parametrize("source,octaves", [("none", (3, 0.5, 0.5, 0.5)),
                                            ("wrenninge", (5, 0.7, 0.4, 0.9)),
                                            ("wrenninge", (1, 0.5, 0.5, 0.5)),
                                            ("lattice1", (3, 0.5, 0.5, 0.5)),
                                            ("lattice3", (3, 0.5, 0.5, 0.5)),
                                            ("view1", (3, 0.5, 0.5, 0.5)),
                                            ("view3", (3, 0.5, 0.5, 0.5))])
def test_kernel_matches_twin_sources(source, octaves):
    kw = _f32(_inputs("odd", source, octaves))
    got = kraymarch.raymarch(**kw)
    want = rraymarch.raymarch(**kw)
    _assert_layers_close(got, want)
    if source == "none" or octaves[0] == 1:
        np.testing.assert_array_equal(got["multiple"], 0.0)
    else:
        assert got["multiple"].max() > 1e-3 * got["single"].max()


def test_kernel_matches_twin_optical_depth_field():
    kw = _f32(_inputs("odd"))
    kw["light"] = (-np.log(kw["light"])).astype(np.float32)
    kw["light_quantity"] = "optical_depth"
    _assert_layers_close(kraymarch.raymarch(**kw), rraymarch.raymarch(**kw))


def test_kernel_matches_twin_isotropic_and_unlit():
    kw = _f32(_inputs("odd"))
    kw["medium"] = dataclasses.replace(kw["medium"], phase=Phase.isotropic())
    _assert_layers_close(kraymarch.raymarch(**kw), rraymarch.raymarch(**kw))
    kw["lit"] = False
    got = kraymarch.raymarch(**kw)
    _assert_layers_close(got, rraymarch.raymarch(**kw))
    np.testing.assert_array_equal(got["single"], 0.0)


def _env_inputs(channels, seed=5):
    """An environment source field (2 C, 6, 6, 6) over a cube offset from the box and of its
    own size (distinct from the light field's), per-plane distinct values, and a per-pixel
    background of distinct values."""
    rs = np.random.default_rng(seed)
    env = (0.02 + 0.3 * rs.random((2 * channels, 6, 6, 6))).astype(np.float32)
    for p in range(2 * channels):
        env[p] *= 1.0 + 0.5 * p
    return dict(env=env, env_min=np.array([-0.6, -0.55, -0.45]), env_size=1.15,
                env_colour=(0.7, 1.3, 2.1))


@pytest.mark.parametrize("channels,lit,bg", [(1, True, False), (3, True, True),
                                             (1, False, True), (3, False, False)])
def test_kernel_matches_twin_environment(channels, lit, bg):
    """ENV (grey and RGB fields) and BG_IMAGE, with and without the sun, on the non-cubic
    box and 13 x 11 image of _inputs."""
    kw = _f32(_inputs("odd"))
    kw.update(_env_inputs(channels))
    kw["env_min"] = np.asarray(kw["env_min"], np.float32).astype(np.float64)
    kw["env_size"] = float(np.float32(kw["env_size"]))
    kw["lit"] = lit
    if bg:
        rs = np.random.default_rng(9)
        kw["bg_image"] = (rs.random((kw["height"], kw["width"], 3)) * 2).astype(np.float32)
    got = kraymarch.raymarch(**kw)
    want = rraymarch.raymarch(**kw)
    _assert_layers_close(got, want)
    # The environment is really there: without it the image differs.
    plain = rraymarch.raymarch(**{k: v for k, v in kw.items()
                                  if k not in ("env", "bg_image")})
    hit = want["alpha"] > 0.05
    assert np.all(want["single"][hit] > plain["single"][hit])
    assert np.all(want["multiple"][hit] > plain["multiple"][hit])
    if bg:
        miss = want["alpha"] == 0
        assert miss.any()
        np.testing.assert_allclose(got["total"][miss], kw["bg_image"][miss], rtol=1e-6)


@pytest.mark.oclgrind
@pytest.mark.rusticl
def test_raymarch_tiny():
    """One full tile and one partial tile (5 x 3 pixels), a 3 x 2 x 3 grid."""
    kw = _inputs("odd")
    rs = np.random.default_rng(3)
    kw["density"] = rs.random((3, 2, 3)).astype(np.float32)
    kw["majorant"] = build_majorant(kw["density"], 2)
    kw["light"] = kw["light"][:3, :3, :3].copy()
    kw.update(width=5, height=3, step=0.2)
    kw = _f32(kw)
    _assert_layers_close(kraymarch.raymarch(**kw), rraymarch.raymarch(**kw))


def test_skipping_is_exact_and_uses_the_majorant():
    kw = _f32(_inputs("odd"))
    kw["density"][:, :, 4:6] = 0.0           # more empty blocks
    kw["majorant"] = build_majorant(kw["density"], 2)
    skip = kraymarch.raymarch(**kw)
    full = kraymarch.raymarch(**dict(kw, skip_empty=False))
    for name in LAYER_NAMES:
        np.testing.assert_array_equal(skip[name], full[name], err_msg=name)
    # Power check: a majorant that wrongly says "empty" over occupied blocks must change
    # the image, or the skipper is not consulting it at all.
    wrong = kw["majorant"].copy()
    wrong[:, :, -1] = 0.0
    lied = kraymarch.raymarch(**dict(kw, majorant=wrong))
    assert np.abs(lied["alpha"] - skip["alpha"]).max() > 1e-3


# --------------------------------------------------------------------------- physics

def _scene(**over):
    data = {
        "volume": {"generator": "cloud", "seed": 2, "resolution": 24},
        "medium": {"preset": "cloud", "density_scale": 30.0},
        "light": {"direction": [0.6, 0.9, 0.3], "irradiance": [1.0, 1.0, 1.0]},
        "camera": {"origin": [0.0, 0.3, 2.4], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0],
                   "fov_y": 30.0, "width": 24, "height": 20},
    }
    for key, value in over.items():
        table, field = key.split(".")
        if value is None:
            data[table].pop(field, None)
        else:
            data[table][field] = value
    return scene_from_dict(data, "<test>")


def test_homogeneous_box_matches_closed_form():
    """A uniform box lit from +y, seen along -z: every term has a closed form.

    The optical-depth field toward the light is sigma (y_max - y), linear in y, so its
    trilinear reading (light_interp="optical_depth") is exact (except in the top half voxel,
    where the lookup clamps: rows there are left out). Along a ray y(t) = o_y + t d_y, T_cam = exp(-sigma (t - t0)), so
        single = albedo E f(d_y) [e^{-sigma (0.5 - y(t0))} - e^{-sigma (0.5 - y(t1)) - tau}] / (1 - d_y),
        alpha = 1 - e^-tau,   depth = t0 + (1 - (1 + tau) e^-tau) / (sigma alpha),
    tau = sigma (t1 - t0). Tolerance 1e-4 relative: a float32 march (the midpoint rule's
    error for a source varying by sigma d_y per unit length is ~1e-9 here).
    """
    n, sigma = 16, 3.0
    grid = DensityGrid(np.ones((n, n, n), np.float32), np.array([-0.5] * 3), np.array([0.5] * 3))
    scene = _scene(**{"medium.density_scale": sigma, "medium.preset": None,
                      "medium.albedo": 0.8, "medium.phase": {"type": "hg", "g": 0.5},
                      "light.direction": [0.0, 1.0, 0.0], "light.irradiance": [2.0, 2.0, 2.0],
                      "camera.origin": [0.0, 0.0, 40.0], "camera.fov_y": 1.0,
                      "camera.width": 9, "camera.height": 9})
    res = render_raymarch(scene, grid=grid, ms="none", step=0.25, threshold=0.0,
                          light_interp="optical_depth")
    cam = scene.camera
    d = cam.pixel_directions()
    o = np.array(cam.origin)
    t0 = (0.5 - o[2]) / d[..., 2]                     # enters at z = 0.5, leaves at z = -0.5
    t1 = (-0.5 - o[2]) / d[..., 2]
    tau = sigma * (t1 - t0)
    y0, y1 = o[1] + t0 * d[..., 1], o[1] + t1 * d[..., 1]
    alpha = -np.expm1(-tau)
    dy = d[..., 1]
    f = phase_eval(dy, [(0.5, 1.0)])                  # mu = dot(l, d), l = +y
    single = 0.8 * 2.0 * f * (np.exp(-sigma * (0.5 - y0))
                              - np.exp(-sigma * (0.5 - y1) - tau)) / (1.0 - dy)
    inner = np.maximum(y0, y1) < 0.5 - 1.0 / (2 * n)
    depth = t0 + (1 - (1 + tau) * np.exp(-tau)) / (sigma * alpha)
    np.testing.assert_allclose(res.layers["alpha"], alpha, rtol=1e-4)
    np.testing.assert_allclose(res.layers["depth"], depth, rtol=1e-4)
    np.testing.assert_allclose(res.layers["single"][..., 0][inner], single[inner], rtol=1e-4)
    assert inner.sum() >= 40


def test_constant_ms_lattice_gives_alpha_times_source():
    """F_ms = c everywhere: multiple = albedo E c alpha exactly (sum of T (1 - e^-tau) = alpha)."""
    scene = _scene(**{"medium.albedo": [0.9, 0.6, 0.3], "light.irradiance": [1.0, 2.0, 0.5]})
    g = FmsLattice(np.full((3, 4, 5, 3), 0.25, np.float32), (-0.5,) * 3, (0.5,) * 3)
    res = render_raymarch(scene, ms="lattice", ms_lattice=g)
    want = res.layers["alpha"][..., None] * 0.25 * np.array([0.9, 1.2, 0.15])
    np.testing.assert_allclose(res.layers["multiple"], want, rtol=1e-5, atol=1e-7)
    assert res.layers["alpha"].max() > 0.5


def test_early_termination_error_is_within_its_bound():
    """Stopping at T_cam < eps misses at most eps x the largest source radiance of the ray:
    albedo E (f(mu) + sum_i b^i f(mu; g c^i)) (T_light <= 1) or the background."""
    scene = _scene(**{"light.environment": [0.3, 0.3, 0.3], "medium.density_scale": 80.0})
    eps = 0.05
    exact = render_raymarch(scene, threshold=0.0)
    cut = render_raymarch(scene, threshold=eps)
    d = scene.camera.pixel_directions()
    mu = d @ np.asarray(scene.light.direction)
    lobes = [(lo.g, lo.weight) for lo in scene.medium.phase.lobes]
    f_max = phase_eval(mu, lobes) + sum(0.5 ** i * phase_eval(mu, [(g * 0.5 ** i, w) for g, w in lobes])
                                        for i in (1, 2))
    bound = eps * np.maximum(0.999 * f_max, 0.3)
    err = np.abs(cut.layers["total"] - exact.layers["total"]).max(axis=-1)
    assert np.all(err <= bound * (1 + 1e-4) + 1e-7)
    assert err.max() > 0.01 * bound.max()   # the threshold did cut some rays


@pytest.mark.parametrize("over", [
    {"medium.phase": {"type": "isotropic"}},                     # constant phase
    {"medium.albedo": 0.0},                                        # nothing scatters
    {"light.irradiance": [0.0, 0.0, 0.0]},                         # nothing lit
])
def test_shortcut_gives_the_general_image(over):
    scene = _scene(**over)
    fast = render_raymarch(scene)
    general = render_raymarch(scene, shortcuts=False)
    assert fast.header["skipped"] != general.header["skipped"]
    for name in LAYER_NAMES:
        np.testing.assert_allclose(fast.layers[name], general.layers[name], rtol=2e-6, atol=0,
                                   err_msg=name)


def test_grey_grid_shortcut_gives_the_general_image():
    scene = _scene(**{"medium.albedo": 0.9})
    rs = np.random.default_rng(5)
    g = FmsLattice((0.1 * rs.random((5, 4, 6))).astype(np.float32), (-0.5,) * 3, (0.5,) * 3)
    fast = render_raymarch(scene, ms="lattice", ms_lattice=g)
    general = render_raymarch(scene, ms="lattice", ms_lattice=g, shortcuts=False)
    assert "colour channels 2 and 3" in fast.header["skipped"]
    assert "1 channel" in fast.header["simulated"] and "3 channel" in general.header["simulated"]
    for name in LAYER_NAMES:
        np.testing.assert_allclose(fast.layers[name], general.layers[name], rtol=2e-6, atol=0,
                                   err_msg=name)


def test_header_lists_simulated_and_skipped_effects():
    r = render_raymarch(_scene(**{"light.environment": [0.2, 0.2, 0.2]}), ms="none")
    assert "single scattering" in r.header["simulated"]
    assert "background" in r.header["simulated"]
    assert "multiple scattering (--ms none)" in r.header["skipped"]
    assert "environment single scattering" in r.header["simulated"]
    assert "environment multiple scattering (approximation" in r.header["simulated"]
    assert "environment" not in r.header["skipped"]
    r = render_raymarch(_scene(**{"medium.albedo": 0.0, "light.environment": [0.2, 0.2, 0.2]}))
    assert "environment in-scattering (albedo 0" in r.header["skipped"]
    r = render_raymarch(_scene(**{"medium.albedo": 0.0}))
    assert "single and multiple scattering" in r.header["skipped"]
    assert r.header["raymarch.light_resolution"] == 0        # no light field was built
    np.testing.assert_array_equal(r.layers["total"], 0.0)
    assert r.layers["alpha"].max() > 0.3


def test_step_halving_changes_the_image_little():
    """Halving the step from 1 to 0.5 voxel changes the image by < 3% of its mean (mean
    absolute difference per pixel and channel) and by < 1 MRPNN unit, on a cloud of ~1
    optical depth per voxel (measured: 1.9%, 0.6). The segment integral is second order, so
    the next halving must change it at least twice less (measured: 4x less, 0.5%)."""
    from clvol.metrics import mrpnn_metric
    scene = _scene(**{"volume.resolution": 32, "camera.width": 32, "camera.height": 32})
    imgs = [render_raymarch(scene, step=s, threshold=0.0).layers["total"] for s in (1.0, 0.5, 0.25)]
    d1 = np.abs(imgs[0] - imgs[1]).mean() / imgs[1].mean()
    d2 = np.abs(imgs[1] - imgs[2]).mean() / imgs[2].mean()
    assert d1 < 0.03
    assert d2 < 0.5 * d1
    assert mrpnn_metric(imgs[0], imgs[1]) < 1.0


def test_supersampling_is_a_box_filter():
    scene = _scene()
    s2 = render_raymarch(scene, supersample=2)
    from dataclasses import replace
    big = replace(scene, camera=replace(scene.camera, width=48, height=40))
    full = render_raymarch(big)
    want = full.layers["total"].reshape(20, 2, 24, 2, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(s2.layers["total"], want, rtol=1e-6, atol=1e-9)
    a = full.layers["alpha"].reshape(20, 2, 24, 2)
    ad = (full.layers["alpha"] * full.layers["depth"]).reshape(20, 2, 24, 2)
    m = a.sum(axis=(1, 3)) > 0
    want_depth = ad.sum(axis=(1, 3))[m] / a.sum(axis=(1, 3))[m]
    np.testing.assert_allclose(s2.layers["depth"][m], want_depth, rtol=1e-5)


@pytest.mark.parametrize("kwargs,text", [
    ({"step": 0.0}, "step = 0.0"),
    ({"threshold": 1.0}, "threshold = 1.0"),
    ({"octaves": 9}, "octaves = 9"),
    ({"a": 0.0}, "ms_a = 0.0"),
    ({"b": 1.5}, "ms_b = 1.5"),
    ({"ms": "network", "ms_resolution": 1}, "ms_resolution = 1"),
    ({"ms": "lattice"}, "needs an F_ms lattice"),
    ({"light_resolution": 100}, "light_resolution = 100"),
    ({"supersample": 0}, "supersample = 0"),
])
def test_bad_options_are_named(kwargs, text):
    with pytest.raises(ClvolError, match=text.replace("(", r"\(").replace(".", r"\.")):
        render_raymarch(_scene(), **kwargs)


def test_octaves_energy_flag():
    assert Octaves(3, 0.5, 0.5, 0.5).energy_conserving
    assert not Octaves(3, 0.4, 0.6, 0.5).energy_conserving


def test_cli_renders_a_scene_with_the_ray_marcher(tmp_path):
    from clvol.cli import main
    from clvol.image import read_exr
    scene = write_scene(tmp_path / "s.toml", volume={"generator": "cloud", "seed": 2, "resolution": 24},
                        medium={"preset": "cloud", "density_scale": 30.0},
                        light={"direction": [0.6, 0.9, 0.3], "environment": [0.1, 0.1, 0.1]},
                        camera={**CAMERA, "origin": [0.0, 0.3, 2.4], "fov_y": 30.0, "width": 20,
                                "height": 16})
    out = tmp_path / "o.exr"
    assert main(["render", str(scene), "--method", "raymarch", "--ms", "none", "--step", "0.5",
                 "-o", str(out)]) == 0
    img = read_exr(out)
    assert set(img.layers) == {"total", "single", "multiple", "alpha", "depth"}
    assert img.layers["total"].shape == (16, 20, 3)
    assert "single scattering" in img.header["simulated"]
    assert img.header["raymarch.step_voxels"] == "0.5"
    # Where nothing is in the way the background (environment 0.1) comes through unchanged.
    clear = img.layers["alpha"] == 0
    assert clear.any()
    np.testing.assert_allclose(img.layers["total"][clear], 0.1, rtol=1e-6)
    assert main(["render", str(scene), "--method", "raymarch", "--step", "-1",
                 "-o", str(out)]) == 2


def test_a_renderer_marches_into_the_same_outputs_frame_after_frame():
    """The march writes into its RayMarcher's own buffers (kernels/raymarch.py MarchOutputs):
    made once per image size, not per frame, with the count in stats word 0 set to zero before
    each launch. The camera 2e6 from the unit cloud with a view 1e-5 degrees high (as in
    tests/test_bounded.py) stops every one of the 16 x 12 rays at the march's bound, so a count
    that carried over would read 2 x 192 on the second frame."""
    import dataclasses

    import clvol
    from clvol.scene import scene_from_dict
    scene = scene_from_dict({
        "volume": {"generator": "cloud", "seed": 3, "resolution": 16},
        "medium": {"preset": "cloud", "density_scale": 30.0},
        "light": {"direction": [0.6, 0.9, 0.3]},
        "camera": {"origin": [0.0, 0.0, 2e6], "target": [0.0, 0.0, 0.0], "fov_y": 1e-5,
                   "width": 16, "height": 12}})
    r = clvol.Renderer(scene, "raymarch", ms="none")
    first, second = r.render(), r.render()
    outs = r._marcher.outputs
    assert outs.allocations == 1
    assert first.header["raymarch.rays_stopped_at_bound"] == 16 * 12
    assert second.header["raymarch.rays_stopped_at_bound"] == 16 * 12
    assert np.array_equal(first.layers["total"], second.layers["total"])
    bigger = dataclasses.replace(scene.camera, width=20)
    assert r.render(camera=bigger).layers["total"].shape == (12, 20, 3)
    assert outs.allocations == 2
