"""The stochastic view-space source (``--ms stochastic``, clvol/render/ms/view.py): MRPNN's
one free-flight point per pixel block per frame, accumulated while the view is still and
reprojected when the camera moves. Stand-in queries with known images check the estimator;
counters check what each change recomputes."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from clvol.errors import ClvolError
from clvol.render.renderer import Renderer
from clvol.render.ms.view import MIN_SAMPLES, MOVE_HISTORY, STILL_SAMPLES
from test_view_source import _scene

S = 0.05


def _renderer(scene, query=None, **opts):
    r = Renderer(scene, "raymarch", ms="stochastic", **opts)
    r.source.query = query
    return r


def _distance_query(scene):
    o = np.asarray(scene.camera.origin)
    return lambda p, w: (S * np.linalg.norm(p - o, axis=1))[:, None].repeat(3, 1)


def _relative_error(scene, res, f_of_mean_depth):
    """Per pixel with alpha > 0.05: (multiple - expected) / expected, where a source F that
    is affine in the distance t along the ray gathers albedo E alpha F(mean t) (the depth
    layer is the alpha-weighted mean t)."""
    alb = np.asarray(scene.medium.albedo)
    a, dep = res.layers["alpha"], res.layers["depth"]
    pred = (alb * 1.5)[None, None, :] * (a * f_of_mean_depth(dep))[..., None]
    inner = a > 0.05
    return (res.layers["multiple"][inner] - pred[inner]) / pred[inner]


def test_free_flight_estimate_converges_to_the_integral():
    """F = s t (distance from the camera): the pixel's multiple scattering is albedo E s
    int T sigma_t t dt = albedo E s alpha mean(t). One block per pixel, N samples per block:
    the estimate averages F over N jittered free-flight points, so its relative error
    shrinks like 1/sqrt(N) down to what the pixel's centre ray and the jittered rays
    disagree on (their depth distributions differ across the pixel) and the quadratures of
    the depth pass and the marcher: measured per-pixel spread 0.0195 at N = 4, 0.0071 at
    64, 0.0046 at 256, mean error 0.0003-0.0005. Bounds: at N = 256 the median below 0.01
    and every pixel below 0.04 (the spread's 8 sigma); the spread falls by more than 2x
    from N = 4 to 64 (4x for pure noise; the floor takes some); the mean error below 0.003.
    Planted: the levels' z held at 1/2 (every sample at the median depth, not a draw) moves
    the mean error to 0.0064 (measured)."""
    scene = _scene(**{"medium.preset": "smoke", "medium.density_scale": 8.0})
    spread = {}
    for n in (4, 64, 256):
        res = _renderer(scene, _distance_query(scene), view_block=1, view_samples=n,
                        seed=1).render()
        rel = _relative_error(scene, res, lambda dep: S * dep)
        assert len(rel) > 100
        spread[n] = rel.std()
        if n == 256:
            assert np.median(np.abs(rel)) < 0.01 and np.abs(rel).max() < 0.04
            assert abs(rel.mean()) < 0.003
    assert spread[4] > 2 * spread[64]


def test_same_seed_same_image_and_another_seed_another():
    scene = _scene()
    q = _distance_query(scene)
    a = _renderer(scene, q, seed=7).render().layers["multiple"]
    b = _renderer(scene, q, seed=7).render().layers["multiple"]
    c = _renderer(scene, q, seed=8).render().layers["multiple"]
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-3 * a.max()


def test_still_view_accumulates_then_stops_drawing():
    scene = _scene()
    r = _renderer(scene, _distance_query(scene), view_samples=3)
    # a new history draws MIN_SAMPLES (> 3), then each still frame view_samples
    for want in (MIN_SAMPLES, MIN_SAMPLES + 3):
        res = r.render()
        assert res.header["raymarch.view_accumulated"] == want
    assert r.counts["ms_view_table"] == 2
    r = _renderer(scene, _distance_query(scene), view_samples=STILL_SAMPLES)
    first = r.render()
    again = r.render()                           # converged: no draw, the same image
    assert r.counts["ms_view_table"] == 1
    np.testing.assert_array_equal(first.layers["total"], again.layers["total"])


def test_recompute_by_change():
    """A camera move keeps at most MOVE_HISTORY samples per block (plus the new one); a
    light or medium change starts afresh; the network is set up once."""
    scene = _scene()
    r = _renderer(scene, _distance_query(scene), view_samples=8)
    r.render()
    cam = scene.camera
    res = r.render(camera=dataclasses.replace(cam, origin=(0.05, 0.3, 2.4)))
    assert res.header["raymarch.view_accumulated"] == MOVE_HISTORY + 8
    res = r.render(light=dataclasses.replace(scene.light, direction=(0.0, 1.0, 0.0)))
    assert res.header["raymarch.view_accumulated"] == 8
    res = r.render(medium=dataclasses.replace(scene.medium, density_scale=20.0))
    assert res.header["raymarch.view_accumulated"] == 8
    assert r.counts["ms_view_table"] == 4
    assert r.counts["network_setup"] == 1


def test_reprojection_carries_values_to_where_the_points_went():
    """F = a + b x (world x, the same for every direction): after 64 samples at camera A the
    camera slides 0.25 along x (the cloud moves ~5 pixels), and one more
    sample is drawn. Reprojected history keeps F where its points are: each pixel must
    still gather albedo E alpha F(mean x): median error < 2%, every pixel < 6% (5 samples'
    noise, spread of x along a ray ~0.1 -> 0.5% of F each, the move's change of the mean x
    along a ray < 1%, and the reprojection's nearest-block lookup at silhouettes).
    (The test image is 26 pixels wide: one pixel per block.) Planted: new points looked up
    in the new view's own blocks (no reprojection) give a median error of 0.092; old points
    splatted through the old camera instead of the new one fail the bound as well."""
    scene = _scene(**{"medium.preset": "smoke", "medium.density_scale": 8.0})
    a, b = 0.1, 0.05
    r = _renderer(scene, lambda p, w: (a + b * p[:, 0])[:, None].repeat(3, 1), view_samples=64)
    r.render()
    r.source.samples = 1
    cam = dataclasses.replace(scene.camera, origin=(0.25, 0.3, 2.4), target=(0.25, 0.0, 0.0))
    res = r.render(camera=cam)
    assert res.header["raymarch.view_accumulated"] == MOVE_HISTORY + 1
    h, w = cam.height, cam.width
    dirs = cam.directions_at((np.arange(w) + 0.5)[None, :], (np.arange(h) + 0.5)[:, None])
    o = np.asarray(cam.origin)

    def f_of_depth(dep):
        return a + b * (o[0] + dep * dirs[..., 0])
    rel = _relative_error(scene, res, f_of_depth)
    assert np.median(np.abs(rel)) < 0.02 and np.abs(rel).max() < 0.06


def test_default_block_follows_the_image_size():
    from clvol.render.ms.view import auto_block
    assert [auto_block(w, h) for w, h in ((26, 19), (96, 96), (128, 72), (256, 256),
                                          (300, 512))] == [1, 2, 2, 4, 8]
    res = _renderer(_scene(**{"camera.width": 130, "camera.height": 40})).render()
    assert res.header["raymarch.view_block"] == 2
    res = _renderer(_scene(), view_block=3).render()
    assert res.header["raymarch.view_block"] == 3


def test_grey_evaluates_once_and_empty_view_asks_nothing():
    res = _renderer(_scene()).render()
    assert res.header["raymarch.channels_marched"] == 1
    assert res.header["raymarch.network_evaluations_per_point"] == 1
    assert np.isfinite(res.layers["multiple"]).all() and res.layers["multiple"].max() > 0
    calls = []
    away = _scene(**{"camera.target": [0.0, 0.3, 5.0]})
    res = _renderer(away, lambda p, w: calls.append(len(p)) or np.zeros((len(p), 3))).render()
    assert calls == [] and res.layers["alpha"].max() == 0.0


@pytest.mark.parametrize("opts,text", [({"view_samples": 0}, "view_samples"),
                                       ({"view_samples": 2.0}, "view_samples"),
                                       ({"seed": -1}, "seed"),
                                       ({"view_block": 65}, "view_block")])
def test_bad_stochastic_options_are_named(opts, text):
    with pytest.raises(ClvolError, match=text):
        Renderer(_scene(), "raymarch", ms="stochastic", **opts)


@pytest.mark.parametrize("ms,opts,flag", [("view", {"seed": 3}, "--seed"),
                                          ("network", {"view_samples": 4}, "--view-samples"),
                                          ("stochastic", {"view_knots": 2}, "--view-knots")])
def test_options_of_one_source_are_refused_for_another(ms, opts, flag):
    with pytest.raises(ClvolError, match=flag):
        Renderer(_scene(), "raymarch", ms=ms, **opts)


def test_refining_flag_ends_for_empty_and_unlit_views():
    """The viewer re-renders a still view while the header says ``raymarch.view_refining``.
    It must end: after STILL_SAMPLES draws even where no block ever collects a sample (the
    camera looking away: the count stays 0), and at once when nothing is lit (the source is
    not prepared; its last frame's figures must not be reported as this frame's)."""
    away = _scene(**{"camera.target": [0.0, 0.3, 5.0]})
    r = _renderer(away, lambda p, w: np.zeros((len(p), 3)), view_samples=STILL_SAMPLES // 2)
    assert r.render().header["raymarch.view_refining"] is True
    res = r.render()
    assert res.header["raymarch.view_refining"] is False
    assert res.header["raymarch.view_accumulated"] == 0
    scene = _scene()
    r = _renderer(scene, _distance_query(scene))
    assert r.render().header["raymarch.view_refining"] is True
    dark = dataclasses.replace(scene.medium, albedo=(0.0, 0.0, 0.0))
    assert r.render(medium=dark).header["raymarch.view_refining"] is False


def test_a_still_render_is_the_64_frame_still_view_and_follows_its_seed():
    """Renderer.render(still=True) (what clvol render asks for) draws at once what a still
    view accumulates over STILL_SAMPLES frames: the same draws in the same order, so the image
    equals the one after that many real-time frames bit for bit; the same seed gives the
    same image, another seed another one."""
    from pathlib import Path

    import clvol
    sc = clvol.load_scene(Path(__file__).resolve().parents[1] / "examples" / "cloud.toml")
    sc = dataclasses.replace(sc, camera=dataclasses.replace(sc.camera, width=24, height=20))
    still = clvol.Renderer(sc, seed=3).render(still=True)
    assert still.header["raymarch.view_accumulated"] == STILL_SAMPLES
    assert still.header["raymarch.view_refining"] is False
    r = clvol.Renderer(sc, seed=3)
    for _ in range(STILL_SAMPLES):
        frames = r.render()
    assert np.array_equal(still.total, frames.total)
    assert np.array_equal(still.total, clvol.Renderer(sc, seed=3).render(still=True).total)
    other = clvol.Renderer(sc, seed=4).render(still=True).total
    assert not np.array_equal(still.total, other)


def test_a_young_history_draws_up_to_min_samples():
    """One draw a frame (the default) except where the history is younger than MIN_SAMPLES
    draws: a new history (the first frame, a light change) draws MIN_SAMPLES at once; under
    motion the carried min(age, MOVE_HISTORY) plus the frame's own draw suffice, so each
    moving frame draws one. The draw counter (the RNG stream) advances by exactly the draws
    made. Planted: without the rule the first frame holds 1 sample per block."""
    assert MOVE_HISTORY + 1 >= MIN_SAMPLES > 1
    scene = _scene()
    r = _renderer(scene, _distance_query(scene))
    cam = scene.camera
    res = r.render()
    assert res.header["raymarch.view_accumulated"] == MIN_SAMPLES
    assert r.source.draws == MIN_SAMPLES
    seen = [r.source.draws]
    for x in (0.02, 0.04, 0.06):
        res = r.render(camera=dataclasses.replace(cam, origin=(x, 0.3, 2.4)))
        seen.append(r.source.draws)
        assert res.header["raymarch.view_accumulated"] == MOVE_HISTORY + 1
    assert np.diff(seen).tolist() == [1, 1, 1]
    res = r.render(light=dataclasses.replace(scene.light, direction=(0.0, 1.0, 0.0)))
    assert res.header["raymarch.view_accumulated"] == MIN_SAMPLES
