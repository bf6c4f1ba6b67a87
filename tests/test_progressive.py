"""The progressive source (``--ms progressive``, clvol/render/ms/progressive.py): the network's
F_ms refined by path-traced point queries while the view is still. The estimator against its
NumPy twin (reference/progressive.py) and a closed form; consistency and "never worse than the
network" on synthetic data with a known truth; the source with stand-in queries (convergence
to the path-traced table, the first budgets), the real path tracer on a small scene
(reproducible from the seed, what a change resets) and the CLI."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from clvol.errors import ClvolError
from clvol.render.ms import progressive as pg
from clvol.render.renderer import Renderer
from reference import progressive as twin
from test_stochastic_source import S, _relative_error
from test_view_source import _scene


# --------------------------------------------------------------------------- synthetic data

def _synthetic(rng, by=12, bx=15, C=3, points=3.0, sigma=0.4, bias=None, empty=0.1):
    """Blocks with a network mean m_nn, a true relative residual (the network's error) and
    path-traced points whose residuals are the truth plus noise of relative std ``sigma``.
    Returns (m_nn, truth F, n, s_r, q_r, s_pt, q_pt, e2)."""
    yy, xx = np.mgrid[0:by, 0:bx]
    m_nn = (0.1 + 0.05 * np.sin(xx / 3.0)[None] * np.ones((C, 1, 1))
            + 0.01 * np.arange(C)[:, None, None])
    if bias is None:      # smooth: the network's error varies slowly across the image
        bias = 0.15 * np.cos(yy / 4.0)[None] + 0.05 * np.arange(C)[:, None, None]
    truth = m_nn * (1.0 + bias)
    n = rng.poisson(points, (by, bx)).astype(float)
    n[rng.random((by, bx)) < empty] = 0
    s_r, q_r = np.zeros((C, by, bx)), np.zeros((C, by, bx))
    s_pt, q_pt, e2 = np.zeros((C, by, bx)), np.zeros((C, by, bx)), np.zeros((C, by, bx))
    for j in range(by):
        for i in range(bx):
            k = int(n[j, i])
            if not k:
                continue
            f_nn = m_nn[:, j, i, None] * (1 + 0.1 * rng.standard_normal((C, k)))
            f_pt = (truth[:, j, i, None] + (f_nn - m_nn[:, j, i, None])
                    + sigma * m_nn[:, j, i, None] * rng.standard_normal((C, k)))
            r = f_pt - f_nn
            s_r[:, j, i], q_r[:, j, i] = r.sum(1), (r * r).sum(1)
            s_pt[:, j, i], q_pt[:, j, i] = f_pt.sum(1), (f_pt * f_pt).sum(1)
            e2[:, j, i] = (sigma * m_nn[:, j, i]) ** 2 * k
    return m_nn, truth, n, s_r, q_r, s_pt, q_pt, e2


@pytest.mark.parametrize("mode", pg.ESTIMATORS)
@pytest.mark.parametrize("radius", [0, 1, 2])
def test_estimator_matches_its_twin(mode, radius):
    """Every mode and level count, 1 and 3 channels, against the loop-by-loop twin."""
    rng = np.random.default_rng(4 + radius)
    for C in (1, 3):
        m_nn, _, n, s_r, q_r, s_pt, q_pt, e2 = _synthetic(rng, by=7, bx=9, C=C)
        got, info = pg.estimate(m_nn, n, s_r, q_r, mode, radius, s_pt=s_pt, q_pt=q_pt, e2=e2)
        want = twin.estimate(m_nn, n, s_r, q_r, mode, radius, s_pt=s_pt, q_pt=q_pt, e2=e2)
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-14)
        assert np.isfinite(got).all() and np.isfinite(info["error"]).all()


def test_one_point_per_block_keeps_the_network():
    """No block with two points: a residual's spread is unknown (4 paths' standard errors
    understate it), so every shrunk mode keeps the network's F_ms; "mean" does not."""
    rng = np.random.default_rng(9)
    m_nn, _, n, s_r, q_r, s_pt, q_pt, e2 = _synthetic(rng, by=5, bx=6, C=1, points=1.0, empty=0)
    n = np.minimum(n, 1.0)
    s_r, q_r, e2 = s_r * (n > 0), q_r * (n > 0), e2 * (n > 0)
    for mode in ("cv_smooth", "cv"):
        got, info = pg.estimate(m_nn, n, s_r, q_r, mode, 1, e2=e2)
        np.testing.assert_array_equal(got, m_nn)
        assert info["error"] is None
        np.testing.assert_array_equal(twin.estimate(m_nn, n, s_r, q_r, mode, 1, e2=e2), m_nn)
    assert not np.allclose(pg.estimate(m_nn, n, s_r, q_r, "mean", 1, e2=e2)[0], m_nn)


def test_closed_form_on_one_block():
    """A single block (a homogeneous medium's image seen as one block): every level is the
    block, so cv_smooth is the positive-part shrinkage of the relative residual mean
    m = s / n toward 0 at the first level, w = tau2 / (tau2 + v), tau2 = max(m^2 - v -
    3 sqrt(2) v, 0) (the spread less three standard errors of a one-group estimate), v = s2 / n,
    and the finer levels add nothing (their spread is 0). s2 is the block's own
    sample variance times the few-points safety factor 1 + 2 / n."""
    m_nn = np.array([[[0.2]]])
    r = 0.01 + 0.04 * np.sin(np.arange(40.0))       # residuals, absolute (40 points: the
                                                    # estimator waits for 32 beyond the first)
    n = np.array([[float(len(r))]])
    got, _ = pg.estimate(m_nn, n, np.array([[[r.sum()]]]), np.array([[[(r * r).sum()]]]),
                         "cv_smooth", 2)
    x = r / 0.2
    m, s2 = x.mean(), x.var(ddof=1) * (1 + 2 / len(x))     # the few-points safety factor
    v = s2 / len(x)
    tau2 = max(m * m - v - 3 * np.sqrt(2) * v, 0.0)    # less 3 standard errors of one group
    want = 0.2 * (1 + tau2 / (tau2 + v) * m)
    assert got[0, 0, 0] == pytest.approx(want, rel=1e-9)
    assert 0.2 < want < 0.2 * 1.01 * (1 + m)          # shrunk toward 0.2, and not all the way
    # paths without end: the block's path-traced mean
    big = 1e8
    got, _ = pg.estimate(m_nn, np.array([[big]]), np.array([[[0.05 * big]]]),
                         np.array([[[(0.05 ** 2 + 1e-4) * big]]]), "cv_smooth", 2)
    assert got[0, 0, 0] == pytest.approx(0.25, rel=1e-6)


@pytest.mark.parametrize("mode", ["cv_smooth", "cv", "shrink"])
def test_consistent_with_paths_without_end(mode):
    """Points per block 3 -> 3e5: the error to the truth (the path-traced mean) falls to
    nothing; the residual's own bias field is recovered block by block, even where it is
    not smooth (a checkerboard the neighbourhood levels cannot follow)."""
    rng = np.random.default_rng(2)
    yy, xx = np.mgrid[0:10, 0:12]
    bias = 0.2 * ((yy + xx) % 2)[None] * np.ones((3, 1, 1)) - 0.1
    errs = []
    for points in (3.0, 300.0, 30000.0):
        m_nn, truth, n, s_r, q_r, s_pt, q_pt, e2 = _synthetic(rng, 10, 12, points=points,
                                                              bias=bias, empty=0)
        got, _ = pg.estimate(m_nn, n, s_r, q_r, mode, 2, s_pt=s_pt, q_pt=q_pt, e2=e2)
        errs.append(float(np.sqrt(np.mean(((got - truth) / truth) ** 2))))
    assert errs[2] < 0.01 < errs[0]
    assert errs[0] > errs[1] > errs[2]


def test_never_worse_than_the_network_at_the_first_budgets():
    """Noisy points (0.3-100 per block, path noise 3x the F_ms itself: 4 paths of a
    heavy-tailed estimator; the network off by 5-20%): over 20 draws the mean squared
    relative error of cv_smooth is within 5% of the network's at every budget (measured: at
    most +4%, at 10 points), and below 0.8 of it at 100 points per block (0.67 measured).
    Planted: "mean" (the residual without shrinkage) is worse
    than the network at 0.3 and 1 point."""
    rng = np.random.default_rng(5)
    for points in (0.3, 1.0, 3.0, 10.0, 100.0):
        e_net = e_cv = e_mean = 0.0
        for _ in range(20):
            m_nn, truth, n, s_r, q_r, s_pt, q_pt, e2 = _synthetic(rng, 12, 15, points=points,
                                                                  sigma=3.0)
            rel = lambda f: float(np.mean(((f - truth) / truth) ** 2))  # noqa: E731
            e_net += rel(m_nn)
            e_cv += rel(pg.estimate(m_nn, n, s_r, q_r, "cv_smooth", 2, e2=e2)[0])
            e_mean += rel(pg.estimate(m_nn, n, s_r, q_r, "mean", 2, e2=e2)[0])
        assert e_cv <= e_net * 1.05, (points, e_cv, e_net)
        if points >= 100.0:
            assert e_cv < 0.8 * e_net, (points, e_cv, e_net)
        if points <= 1.0:
            assert e_mean > e_net


def test_estimator_refuses_an_unknown_mode():
    with pytest.raises(ClvolError, match="one of"):
        pg.estimate(np.ones((1, 2, 2)), np.ones((2, 2)), np.ones((1, 2, 2)), np.ones((1, 2, 2)),
                    "median")


def test_box_sum():
    x = np.arange(20.0).reshape(4, 5)
    got = pg.box_sum(x, 1)
    for j in range(4):
        for i in range(5):
            assert got[j, i] == x[max(j - 1, 0):j + 2, max(i - 1, 0):i + 2].sum()


# --------------------------------------------------------------------------- the source

def _stand_in_paths(scene, gain=1.0, noise=0.0):
    """Path stand-in: F_pt = gain x S t (t the distance from the camera) plus Gaussian noise
    of std ``noise`` x F, seeded by the round's path seed (reproducible)."""
    o = np.asarray(scene.camera.origin)

    def query(p, w, n_paths, seed):
        f = gain * S * np.linalg.norm(p - o, axis=1)[:, None].repeat(3, 1)
        rng = np.random.default_rng(seed)
        out = f + noise * f * rng.standard_normal(f.shape) / np.sqrt(n_paths)
        return {"Fms": out, "Fms_se": noise * f / np.sqrt(n_paths)}
    return query


def _progressive(scene, net_gain=0.5, noise=0.0, **opts):
    r = Renderer(scene, "raymarch", ms="progressive", **opts)
    o = np.asarray(scene.camera.origin)
    r.source.query = lambda p, w: (net_gain * S * np.linalg.norm(p - o, axis=1))[:, None].repeat(
        3, 1)
    r.source.path_query = _stand_in_paths(scene, 1.0, noise)
    return r


def test_source_converges_to_the_path_traced_table():
    """Network stand-in 0.5 x the truth (F = S t), paths exact: after the first frame the
    image sits at -50% (the network's error); refined, the mean relative error falls below
    2% (the stochastic source with the true F as its query: the same bound)."""
    scene = _scene(**{"medium.preset": "smoke", "medium.density_scale": 8.0})
    r = _progressive(scene, view_block=2, seed=1)
    first = r.render()                      # the first frame of a view: the network only
    rel0 = _relative_error(scene, first, lambda dep: S * dep)
    assert np.median(rel0) == pytest.approx(-0.5, abs=0.05)
    for _ in range(40):                     # then a round per render (the viewer's frames)
        res = r.render()
    rel = _relative_error(scene, res, lambda dep: S * dep)
    assert abs(np.mean(rel)) < 0.02 and np.median(np.abs(rel)) < 0.05
    h = res.header
    assert h["raymarch.progressive_rounds"] == 40
    assert h["raymarch.progressive_paths_per_block"].startswith("mean ")
    assert "% of F_ms" in h["raymarch.progressive_error"]


def test_source_first_budgets_are_no_worse_than_the_network():
    """Paths with noise 8x F per path (4 per point) and a network off by 10%: after 1, 2 and
    4 rounds the image's RMS relative error is at most the network-only image's (the same
    draws: the estimator "network")."""
    scene = _scene(**{"medium.preset": "smoke", "medium.density_scale": 8.0})
    r = _progressive(scene, net_gain=0.9, noise=8.0, view_block=2, seed=3)
    r.render()
    for rounds in (1, 2, 4):
        res = r.render()
        src = r.source
        rel = _relative_error(scene, res, lambda dep: S * dep)
        src.estimator = "network"
        src.table = r.rt.upload(src.table_now()[0])
        plan = r.plan()
        layers, _ = r._marcher.march(plan.camera, scene.light, plan, src)
        src.estimator = "cv_smooth"
        base = _relative_error(scene, dataclasses.replace(res, layers=layers),
                               lambda dep: S * dep)
        assert np.sqrt(np.mean(rel ** 2)) <= np.sqrt(np.mean(base ** 2)) * 1.01, rounds


def test_real_paths_reproducible_and_reset_by_changes():
    """The real path tracer on a small scene: the same seed and rounds give the same image
    bit for bit; a camera move drops the paths (a network-only frame), a light change starts
    afresh, and the header says paths per block and the estimated error."""
    scene = _scene(**{"camera.width": 16, "camera.height": 12})
    imgs = []
    for _ in range(2):
        r = Renderer(scene, "raymarch", ms="progressive", seed=7, progressive_rounds=3)
        res = r.render()                    # the first frame and 3 rounds, in one render
        imgs.append(res.layers["total"])
    np.testing.assert_array_equal(imgs[0], imgs[1])
    h = res.header
    assert h["raymarch.progressive_rounds"] == 3 and h["raymarch.progressive_paths_per_query"] == 4
    assert float(h["raymarch.progressive_paths_per_block"].split()[1].rstrip(",")) > 0
    assert "F_ms" in h["raymarch.progressive_error"]
    r = Renderer(scene, "raymarch", ms="progressive", seed=7)
    src = r.source
    r.render()
    assert src.paths.n.sum() == 0           # a first frame: no paths
    r.render()
    assert src.paths.n.sum() > 0
    cam = dataclasses.replace(scene.camera, origin=(0.1, 0.3, 2.4))
    moved = r.render(camera=cam)
    assert moved.header["raymarch.progressive_rounds"] == 0 and src.paths.n.sum() == 0
    r.render(camera=cam)
    assert src.paths.n.sum() > 0
    light = dataclasses.replace(scene.light, direction=(0.5, 0.9, 0.4))
    r.render(camera=cam, light=light)
    assert src.paths.n.sum() == 0 and src.history.count.max() == 1
    assert np.isfinite(moved.layers["total"]).all()


def test_time_budget_records_its_rounds():
    scene = _scene(**{"camera.width": 16, "camera.height": 12})
    res = Renderer(scene, "raymarch", ms="progressive", seed=2, time=0.3).render()
    assert res.header["raymarch.progressive_time"] == 0.3
    assert res.header["raymarch.progressive_rounds"] >= 1


def test_cli_render_progressive(tmp_path, capsys):
    """clvol render --ms progressive --time / --progressive-rounds; the header says the
    rounds, paths per block and estimated error; --time with another source is refused."""
    from clvol.cli import main
    from clvol.image import read_exr
    from scene_toml import CAMERA, write_scene
    scene = write_scene(tmp_path / "s.toml", volume={"generator": "cloud", "resolution": 16},
                        medium={"preset": "cloud", "density_scale": 20.0},
                        light={"direction": [0.3, 1.0, 0.4]},
                        camera={**CAMERA, "origin": [0.0, 0.2, 2.2], "width": 12, "height": 10})
    out = tmp_path / "o.exr"
    assert main(["render", str(scene), "-o", str(out), "--ms", "progressive", "--time", "0.2",
                 "--seed", "4"]) == 0
    h = read_exr(out).header
    rounds = int(h["raymarch.progressive_rounds"])
    assert rounds >= 1 and "paths_per_block" in " ".join(h)
    again = tmp_path / "p.exr"
    assert main(["render", str(scene), "-o", str(again), "--ms", "progressive",
                 "--progressive-rounds", str(rounds), "--seed", "4"]) == 0
    np.testing.assert_array_equal(read_exr(out).rgb, read_exr(again).rgb)
    capsys.readouterr()
    assert main(["render", str(scene), "-o", str(out), "--ms", "stochastic", "--time", "1"]) == 2
    assert "progressive" in capsys.readouterr().err


@pytest.mark.parametrize("opts, msg", [
    ({"progressive_rounds": 0}, "progressive_rounds"),
    ({"time": -1.0}, "time"),
    ({"time": float("nan")}, "time"),
    ({"time": 1.0, "progressive_rounds": 2}, "not both"),
])
def test_bad_options_are_refused(opts, msg):
    with pytest.raises(ClvolError, match=msg):
        Renderer(_scene(), "raymarch", ms="progressive", **opts)


def test_progressive_options_are_refused_by_other_sources():
    with pytest.raises(ClvolError, match="progressive"):
        Renderer(_scene(), "raymarch", ms="stochastic", progressive_rounds=3)
    with pytest.raises(ClvolError, match="progressive"):
        Renderer(_scene(), "raymarch", ms="network", time=1.0)


def test_paths_go_first_to_bright_blocks():
    """Scheduling: a network stand-in 10x brighter on the image's left half (world x < 0)
    draws more paths there (selection probability ~ F_ms / sqrt(points + 1), at most half
    of a round's points)."""
    scene = _scene(**{"medium.preset": "smoke", "medium.density_scale": 8.0})
    r = Renderer(scene, "raymarch", ms="progressive", view_block=2, seed=5)
    r.source.query = lambda p, w: np.where(p[:, :1] < 0, 1.0, 0.1).repeat(3, 1)
    r.source.path_query = _stand_in_paths(scene)
    for _ in range(8):
        r.render()
    src = r.source
    paths, count = src.paths.paths, src.history.count
    bx = paths.shape[1]
    left, right = paths[:, : bx // 2][count[:, : bx // 2] > 0], paths[:, bx - bx // 2:][
        count[:, bx - bx // 2:] > 0]
    assert left.mean() > 1.5 * right.mean() > 0
    drawn = (count > 0).sum()
    assert src.paths.n.sum() <= 0.5 * 8 * drawn + 1e-9
