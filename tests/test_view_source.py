"""The view-space F_ms source (``--ms view``, clvol/render/ms/view.py) inside the Renderer:
plumbing checked with stand-in queries whose image is known, what each change recomputes,
the shortcuts and the options."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from clvol.errors import ClvolError
from clvol.render.renderer import Renderer
from clvol.scene import scene_from_dict


def _scene(**over):
    data = {
        "volume": {"generator": "cloud", "seed": 3, "resolution": 24},
        "medium": {"preset": "cloud", "density_scale": 30.0},
        "light": {"direction": [0.6, 0.9, 0.3], "irradiance": [1.5, 1.5, 1.5]},
        "camera": {"origin": [0.0, 0.3, 2.4], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0],
                   "fov_y": 30.0, "width": 26, "height": 19},     # partial blocks both ways
    }
    for key, value in over.items():
        table, field = key.split(".")
        data[table][field] = value
    return scene_from_dict(data, "<test>")


def _renderer(scene, query=None, **opts):
    r = Renderer(scene, "raymarch", ms="view", **opts)
    r.source.query = query
    return r


def test_constant_source_gives_alpha_times_it():
    """F_ms = c everywhere: multiple = albedo E c alpha wherever a pixel has knots. Pixels
    whose nearest blocks all missed the medium (a thin rim) get none: they must carry < 2% of
    the alpha."""
    scene = _scene()
    c = 0.21
    res = _renderer(scene, lambda p, w: np.full((len(p), 3), c)).render()
    alb = np.asarray(scene.medium.albedo)
    want = res.layers["alpha"][..., None] * alb * 1.5 * c
    got = res.layers["multiple"]
    covered = np.abs(got - want).max(axis=2) <= 1e-5 * want.max()
    assert res.layers["alpha"][~covered].sum() < 0.02 * res.layers["alpha"].sum()
    assert covered.sum() > 0.5 * (res.layers["alpha"] > 1e-3).sum()


def test_source_linear_in_distance_is_interpolated_exactly():
    """F_ms = s * |p - camera| (the same function on every block): each pixel's knots then
    satisfy v = s d, so between its first and last knot F_ms(t) = s t exactly, and outside
    it is clamped. The image must lie between s * albedo E times the alpha-weighted first
    and last knot distance, and equal s * albedo E * alpha * depth where the whole
    extinction lies between the knots: checked through the depth layer as a bound."""
    scene = _scene(**{"medium.preset": "smoke", "medium.density_scale": 8.0})
    s = 0.05
    o = np.asarray(scene.camera.origin)
    r = _renderer(scene, lambda p, w: (s * np.linalg.norm(p - o, axis=1))[:, None].repeat(3, 1))
    res = r.render()
    alb = np.asarray(scene.medium.albedo)
    a, dep = res.layers["alpha"], res.layers["depth"]
    pred = (alb * 1.5 * s)[None, None, :] * (a * dep)[..., None]    # alpha-weighted mean t
    got = res.layers["multiple"]
    inner = a > 0.05
    # Clamping outside the knots moves F toward the middle: a few per cent at most for this
    # smooth medium. A query off its ray, or a knot blend that mixed blocks' orders, moves
    # pixels by far more.
    rel = np.abs(got[inner] - pred[inner]) / pred[inner]
    assert np.median(rel) < 0.01 and rel.max() < 0.08          # measured 0.002 and 0.042


def test_recompute_table_by_change():
    scene = _scene()
    r = _renderer(scene, lambda p, w: np.full((len(p), 3), 0.1))
    r.render()
    assert r.counts["ms_view_table"] == 1
    r.render()
    assert r.counts["ms_view_table"] == 1                           # nothing changed
    cam = scene.camera
    r.render(camera=dataclasses.replace(cam, origin=(0.1, 0.3, 2.4)))
    assert r.counts["ms_view_table"] == 2                           # the camera moved
    r.render(camera=dataclasses.replace(cam, fov_y=25.0))
    assert r.counts["ms_view_table"] == 3                           # the view changed
    light = dataclasses.replace(scene.light, direction=(0.0, 1.0, 0.0))
    r.render(light=light)
    assert r.counts["ms_view_table"] == 4                           # the light changed
    assert r.counts["network_setup"] == 1                           # weights, pyramid: once


def test_grey_albedo_evaluates_once_and_chromatic_three_times():
    grey = _renderer(_scene()).render()
    assert grey.header["raymarch.channels_marched"] == 1
    assert grey.header["raymarch.network_evaluations_per_point"] == 1
    assert "colour channels 2 and 3" in grey.header["skipped"]
    chrom = _renderer(_scene(**{"medium.albedo": [0.9, 0.95, 0.99], "medium.preset": "cloud"})).render()
    assert chrom.header["raymarch.channels_marched"] == 3
    assert chrom.header["raymarch.network_evaluations_per_point"] == 3
    for res in (grey, chrom):
        m = res.layers["multiple"]
        assert np.isfinite(m).all() and m.max() > 0


def test_empty_view_asks_nothing():
    scene = _scene(**{"camera.target": [0.0, 0.3, 5.0]})          # looking away from the cloud
    calls = []
    r = _renderer(scene, lambda p, w: calls.append(len(p)) or np.zeros((len(p), 3)))
    res = r.render()
    assert calls == [] and res.header["raymarch.view_blocks_queried"] == 0
    assert res.layers["alpha"].max() == 0.0


@pytest.mark.parametrize("opts,text", [({"view_block": 0}, "view_block"),
                                       ({"view_knots": 17}, "view_knots"),
                                       ({"view_block": 2.5}, "view_block")])
def test_bad_view_options_are_named(opts, text):
    with pytest.raises(ClvolError, match=text):
        Renderer(_scene(), "raymarch", ms="view", **opts)


def test_view_options_are_refused_for_other_sources():
    with pytest.raises(ClvolError, match="--view-knots"):
        Renderer(_scene(), "raymarch", ms="network", view_knots=8)
