"""Volume-phase tables (clvol/features/phasetable.py): exactness for an isotropic function, the
beta -> 0 limit, normalisation, the lookup error bound against an independent Legendre
series, g < 0 symmetry, MHG sums, and the per-frame phase-feature table.

Tolerances: ``phasetable.PACKED_BOUND`` (1e-3) bounds the packaged (g, beta, theta) table,
interpolated in g, against the exact cap averages at the table's nodes. ``phasetable.ERROR_BOUND``
(1%) is the stated worst relative error of a table lookup for |g| <= 0.99 (measured 0.7% at g = 0.99 on 3000 random (mu, beta), mostly at tiny
beta on the peak's shoulder); node values themselves are ~1e-7 relative or better.
"""
import numpy as np
import pytest

from clvol.features import phasetable as P
from clvol.features.templates import load_templates

INV4PI = 1.0 / (4.0 * np.pi)


def legendre_series(mu, beta, g):
    """fbar = sum_l (2l+1)/(4pi) g^l c_l(beta) P_l(mu), c_l = (P_{l-1} - P_{l+1})(cos b) / ((2l+1)(1 - cos b))
    (the cap average of P_l; Funk-Hecke). Independent of the table's quadrature."""
    mu = np.asarray(mu, float)
    x = np.cos(beta)
    omx = 2 * np.sin(np.asarray(beta) / 2) ** 2
    lmax = int(np.log(1e-14) / np.log(abs(g))) + 10
    total = np.full_like(mu, INV4PI)
    pm_prev, pm = np.ones_like(mu), mu.copy()
    px_prev, px = np.ones_like(x), x.copy()
    gl = g
    for l in range(1, lmax):
        px_next = ((2 * l + 1) * x * px - l * px_prev) / (l + 1)
        cl = np.where(omx > 0, (px_prev - px_next) / ((2 * l + 1) * np.where(omx > 0, omx, 1)), 1.0)
        total = total + (2 * l + 1) * INV4PI * gl * cl * pm
        pm_prev, pm = pm, ((2 * l + 1) * mu * pm - l * pm_prev) / (l + 1)
        px_prev, px = px, px_next
        gl *= g
    return total


def random_queries(n, seed):
    rs = np.random.default_rng(seed)
    mu = 1 - np.exp(rs.uniform(np.log(1e-8), np.log(2), n))   # dense near the forward peak
    mu[: n // 3] = rs.uniform(-1, 1, n // 3)
    beta = np.exp(rs.uniform(np.log(1e-4), np.log(P.BETA_MAX), n))
    beta[: n // 4] = rs.uniform(0, P.BETA_MAX, n // 4)
    return mu, beta


@pytest.mark.parametrize("g", [0.3, 0.857, 0.99, -0.857, 0.123, -0.9, -0.99])
def test_lookup_within_error_bound(g):
    vp = P.volume_phase([(g, 1.0)])
    mu, beta = random_queries(600, seed=int(abs(g) * 1000))
    want = legendre_series(mu, beta, g)
    got = vp.eval(mu, beta)
    assert np.max(np.abs(got / want - 1)) < P.ERROR_BOUND


def test_node_values_match_series():
    # the exact path's quadrature (what the packaged table is made of), node by node
    betas, thetas = P._grid()
    rs = np.random.default_rng(5)
    j = rs.integers(1, len(betas), 30)
    k = rs.integers(0, thetas.shape[1], 30)
    got = np.array([P._cap_average(thetas[a, b:b + 1], betas[a], 0.99)[0] for a, b in zip(j, k)])
    want = legendre_series(np.cos(thetas[j, k]), betas[j], 0.99)
    np.testing.assert_allclose(got, want, rtol=2e-6)


def _exact_rows(g, rows):
    """Rows of lobe_table_exact(g) without the whole table (the cap-average reference)."""
    betas, thetas = P._grid()
    ga = abs(g)
    out = np.array([P._hg_theta(thetas[0], ga) if m == 0 else P._cap_average(thetas[m], betas[m], ga)
                    for m in rows])
    return out[:, ::-1] if g < 0 else out


@pytest.mark.parametrize("g", [0.05, 0.2, 0.45, 0.7, 0.857, 0.93, 0.975, 0.985, 0.99,
                               -0.3, -0.9, -0.99])
def test_packaged_table_matches_the_exact_cap_average(g):
    """The packaged table interpolated to g (mostly between its nodes) against the exact cap
    averages on every theta node of 10 beta rows (incl. the smallest and largest cones):
    within PACKED_BOUND = 1e-3 relative (measured worst 5.4e-4 at the midpoint nearest 0.99)."""
    assert P._packed() is not None, "clvol/data/phase_lobes.npz missing or made for another grid"
    rows = [0, 1, 2, 5, 20, 50, 80, 100, 110, P.N_BETA - 1]
    got = P.lobe_table(g)[rows]
    want = _exact_rows(g, rows)
    assert np.max(np.abs(got / want - 1)) < P.PACKED_BOUND


def test_packaged_table_is_used_for_any_g(monkeypatch):
    """No cap-average quadrature runs for |g| <= 0.99 (what made a cold render slow); above it
    the exact path runs."""
    def boom(*a, **k):
        raise AssertionError("exact quadrature called")
    monkeypatch.setattr(P, "_cap_average", boom)
    for g in (0.123457, -0.654321, 0.99):
        assert np.all(np.isfinite(P.volume_phase([(g, 1.0)]).table))
    with pytest.raises(AssertionError, match="exact quadrature"):
        P.lobe_table(0.995)


def test_packaged_file_is_small_and_rebuildable():
    """A few MB of package data, made by scripts/make_phase_table.py for this grid."""
    path = P._packed_path()
    assert path.stat().st_size < 4_000_000
    with np.load(path) as z:
        import json
        assert json.loads(z["meta"].tobytes().decode()) == P.packed_grid_meta()
        assert z["q"].shape == (len(P.PACKED_U), P.N_BETA, P.N_THETA)
    # the stored spline basis is scipy's not-a-knot cubic spline through the nodes
    from scipy.interpolate import CubicSpline
    u = np.asarray(P.PACKED_U)
    ref = CubicSpline(u, np.eye(len(u)), axis=0, bc_type="not-a-knot")
    basis_c, _ = P._packed()
    for x in np.concatenate([u, np.random.default_rng(0).uniform(0, u[-1], 50)]):
        np.testing.assert_allclose(P._spline_weights(basis_c, x), ref(x), atol=1e-12)


def test_cone_average_of_isotropic_is_exact():
    # the quadrature itself, on a constant function (g -> 0 through the general code path)
    th = np.linspace(0, np.pi, 37)
    for beta in (1e-5, 0.01, 0.3, P.BETA_MAX):
        np.testing.assert_allclose(P._cap_average(th, beta, 1e-12), INV4PI, rtol=1e-9)
    vp = P.volume_phase(None)
    mu, beta = random_queries(100, 1)
    np.testing.assert_allclose(vp.eval(mu, beta), INV4PI, rtol=1e-14)   # bilinear rounding only


@pytest.mark.parametrize("g", [0.857, 0.99])
def test_half_angle_to_zero_gives_point_value(g):
    vp = P.volume_phase([(g, 1.0)])
    mu = 1 - np.geomspace(1e-7, 2, 200)
    for beta in (0.0, 1e-7, 1e-5):
        np.testing.assert_allclose(vp.eval(mu, beta), P.hg(mu, g), rtol=P.ERROR_BOUND)
    # row 0 holds f exactly at its nodes
    _, thetas = P._grid()
    np.testing.assert_allclose(P.lobe_table(g)[0], P.hg(np.cos(thetas[0]), g), rtol=1e-10)


@pytest.mark.parametrize("g", [0.0, 0.857, 0.99, -0.857])
@pytest.mark.parametrize("beta", [0.0, 0.003, 0.1, P.BETA_MAX])
def test_averages_stay_normalised(g, beta):
    vp = P.volume_phase([(g, 1.0)])
    # theta grid dense at both poles and around the cap edge, trapezoid in mu
    th = np.unique(np.concatenate([np.geomspace(1e-6, np.pi / 2, 4000),
                                   np.pi - np.geomspace(1e-6, np.pi / 2, 4000),
                                   beta + np.linspace(-0.05, 0.05, 2001), [0, np.pi]]))
    th = th[(th >= 0) & (th <= np.pi)]
    mu = np.cos(th)[::-1]
    norm = 2 * np.pi * np.trapezoid(vp.eval(mu, beta), mu)
    assert norm == pytest.approx(1.0, abs=2e-3)


def test_negative_g_is_the_mirror_and_mhg_is_the_weighted_sum():
    pos, neg = P.volume_phase([(0.857, 1.0)]), P.volume_phase([(-0.857, 1.0)])
    mu, beta = random_queries(300, 7)
    np.testing.assert_allclose(neg.eval(mu, beta), pos.eval(-mu, beta), rtol=1e-10)
    mix = P.volume_phase([(0.857, 0.7), (-0.857, 0.3)])
    np.testing.assert_allclose(mix.eval(mu, beta), 0.7 * pos.eval(mu, beta) + 0.3 * neg.eval(mu, beta),
                               rtol=1e-12)


def test_bad_phase_parameters_rejected():
    with pytest.raises(P.PhaseTableError, match="g = 1.0"):
        P.volume_phase([(1.0, 1.0)])
    with pytest.raises(P.PhaseTableError, match="sum to"):
        P.volume_phase([(0.5, 0.5), (0.2, 0.4)])
    with pytest.raises(P.PhaseTableError, match="half-angle"):
        P.volume_phase([(0.5, 1.0)]).eval(0.0, 1.0)


def test_phase_feature_table():
    tpl = load_templates()
    vp = P.volume_phase([(0.857, 1.0)])
    assert tpl.half_angle.max() <= P.BETA_MAX
    tab = P.phase_feature_table(vp, tpl.points, tpl.half_angle)
    assert tab.shape == (P.N_ALPHA, tpl.n_points) and tab.dtype == np.float32
    alpha = P.alpha_nodes()
    np.testing.assert_allclose(tab[:, 0], np.log1p(P.hg(np.cos(alpha), 0.857)), rtol=1e-6)
    # linear interpolation in alpha vs exact alpha: the gather's only extra approximation
    rs = np.random.default_rng(2)
    a = rs.uniform(0, np.pi, 400)
    exact = P.phase_features(vp, tpl.points, tpl.half_angle, a)
    fa = a / np.pi * (P.N_ALPHA - 1)
    i0 = np.minimum(fa.astype(int), P.N_ALPHA - 2)
    t = (fa - i0)[:, None]
    interp = (1 - t) * tab[i0] + t * tab[i0 + 1]
    # log1p features: absolute error; the centre column (plain f, peak width 0.01 rad at
    # alpha = 0) is computed exactly by the kernel, so it is left out here
    assert np.max(np.abs(interp[:, 1:] - exact[:, 1:])) < 2e-3
