"""cl/include/phase.h (via cl/phase.cl) against reference/phase.py, plus the sampler's
properties and chi-square goodness of fit (STYLE.md, pattern 8).

Tolerances: eval and sample are float32 in the kernel; the twin runs in float64 for eval
(kernel within 4e-6 relative, ~30 ULP, from a sqrt, a division and the 4pi constant) and in
float32 for sampling on the same uniforms (directions within 2e-6 absolute per component,
~16 ULP of 1.0; sin/cos differ by a few ULP between PoCL and NumPy).
"""
import numpy as np
import pytest
from scipy import integrate, stats

from clvol.kernels import phase as kphase
from reference import phase as rphase
from reference.rng import uniform4

G_VALUES = [-0.99, -0.9, -1e-4, 0.0, 1e-4, 0.3, 0.5, 0.857, 0.99]
MIXTURES = {
    "iso": [],
    "hg-0.9": [(-0.9, 1.0)],
    "hg0": [(0.0, 1.0)],
    "hg1e-4": [(1e-4, 1.0)],
    "hg0.5": [(0.5, 1.0)],
    "hg0.99": [(0.99, 1.0)],
    "milk": [(0.8, 0.7), (-0.3, 0.3)],
    "skin": [(0.8, 0.5), (0.3, 0.3), (-0.3, 0.2)],
}


def mu_grid():
    """Cosines dense near both poles (in float32, as the kernel sees them)."""
    omm = np.geomspace(1e-7, 2.0, 30001)
    mu = np.unique(np.concatenate([1.0 - omm, -1.0 + omm]).astype(np.float32))
    return mu[(mu >= -1) & (mu <= 1)]


@pytest.mark.parametrize("name", MIXTURES)
def test_eval_kernel_matches_reference(name):
    lobes = MIXTURES[name]
    mu = mu_grid()
    got = kphase.phase_eval(mu, lobes).astype(np.float64)
    want = rphase.phase_eval(mu.astype(np.float64), lobes)
    assert np.all(np.isfinite(got)) and np.all(got > 0)
    np.testing.assert_allclose(got, want, rtol=4e-6, atol=0)


@pytest.mark.oclgrind
@pytest.mark.rusticl
def test_eval_tiny():
    lobes = MIXTURES["skin"]
    mu = np.array([-1, -0.5, 0, 0.999, 1], np.float32)
    np.testing.assert_allclose(kphase.phase_eval(mu, lobes), rphase.phase_eval(mu.astype(float), lobes),
                               rtol=4e-6)


@pytest.mark.parametrize("g", G_VALUES)
def test_hg_normalised_and_mean_cosine_is_g(g):
    mu = mu_grid().astype(np.float64)
    f = kphase.phase_eval(mu, [(g, 1.0)]).astype(np.float64)
    norm = 2 * np.pi * integrate.trapezoid(f, mu)
    mean = 2 * np.pi * integrate.trapezoid(f * mu, mu)
    # The trapezoid rule on this grid is accurate to ~1e-5 even for the g = 0.99 peak.
    assert norm == pytest.approx(1.0, abs=2e-4)
    assert mean == pytest.approx(g, abs=2e-4)


def _uniforms(n, seed, sample=0):
    return uniform4(seed, np.arange(n, dtype=np.uint64), sample, 0)[:, :3].copy()


def _axes(n, seed):
    rs = np.random.default_rng(seed)
    w = rs.normal(size=(n, 3))
    special = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, -1, 0], [0, 0, -0.0], [0, 1, 0]])
    special[4] = [0, 0, -1]
    k = min(n, len(special))
    w[:k] = special[:k]
    return (w / np.linalg.norm(w, axis=1, keepdims=True)).astype(np.float32)


@pytest.mark.parametrize("name", MIXTURES)
def test_sample_kernel_matches_reference_on_same_uniforms(name):
    lobes = MIXTURES[name]
    n = 4099
    u = _uniforms(n, 5)
    u[:4, 1] = [0.0, 1 - 2**-24, 0.5, 0.0]  # the extremes of the polar uniform
    w = _axes(n, 6)
    got = kphase.phase_sample(w, u, lobes)
    want = rphase.phase_sample(w, lobes, u)
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(got, want, atol=2e-6, rtol=0)


@pytest.mark.oclgrind
@pytest.mark.rusticl
def test_sample_tiny():
    lobes = MIXTURES["milk"]
    u = _uniforms(5, 1)
    w = _axes(5, 2)
    np.testing.assert_allclose(kphase.phase_sample(w, u, lobes), rphase.phase_sample(w, lobes, u),
                               atol=2e-6)


@pytest.mark.parametrize("g", [-0.99, 0.99])
def test_sampler_extremes_finite(g):
    u = np.array([[0.2, 0.0, 0.0], [0.2, 1 - 2**-24, 0.999], [0.9, 0.5, 0.5]], np.float32)
    w = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0]], np.float32)
    d = kphase.phase_sample(w, u, [(g, 1.0)])
    assert np.all(np.isfinite(d))
    omm = rphase.hg_sample_one_minus_mu(abs(g), np.array([0.0, 1 - 2**-24], np.float64))
    assert omm[0] == pytest.approx(2.0) and 0 <= omm[1] < 1e-9


# ---------------------------------------------------------------- chi-square goodness of fit
N_SAMPLES = 200_000
# Bins: 1 - mu geometric from 1e-6 to 2 (fine where HG peaks at |g| -> 1), and an odd
# number of azimuth bins around the lobe axis.
OMM_EDGES = np.concatenate([[0.0], np.geomspace(1e-6, 2.0, 48)])
N_PHI = 7
N_TESTS = len(MIXTURES) + 2  # Bonferroni: every chi-square test in this file


def _expected_mu_mass(lobes):
    f = lambda omm: 2 * np.pi * rphase.phase_eval(np.array(1.0 - omm), lobes)  # noqa: E731
    return np.array([integrate.quad(f, a, b, epsabs=1e-12, epsrel=1e-10, limit=200)[0]
                     for a, b in zip(OMM_EDGES[:-1], OMM_EDGES[1:])])


def _chi2_pvalue(lobes_sampled, lobes_expected, seed=11):
    w = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (N_SAMPLES, 1))
    d = kphase.phase_sample(w, _uniforms(N_SAMPLES, seed), lobes_sampled).astype(np.float64)
    # 1 - mu from the chord length keeps precision near the pole (d and w are float32).
    omm = 0.5 * np.sum((d - w) ** 2, axis=1)
    phi = np.arctan2(d[:, 1], d[:, 0])
    obs, _, _ = np.histogram2d(omm, phi, bins=[OMM_EDGES, np.linspace(-np.pi, np.pi, N_PHI + 1)])
    mass = _expected_mu_mass(lobes_expected)
    assert mass.sum() == pytest.approx(1.0, abs=1e-6)
    exp = np.repeat(mass[:, None] / N_PHI, N_PHI, axis=1) * N_SAMPLES
    obs, exp = obs.ravel(), exp.ravel()
    # Pool cells with expected count < 5 into one cell (Mitsuba chi2 practice).
    low = exp < 5
    obs = np.append(obs[~low], obs[low].sum())
    exp = np.append(exp[~low], exp[low].sum())
    if exp[-1] == 0:
        obs, exp = obs[:-1], exp[:-1]
    chi2 = np.sum((obs - exp) ** 2 / exp)
    return stats.chi2.sf(chi2, len(exp) - 1), obs, exp


@pytest.mark.parametrize("name", MIXTURES)
def test_chi_square_sampler_matches_density(name):
    p, obs, exp = _chi2_pvalue(MIXTURES[name], MIXTURES[name])
    # Family-wise false-alarm rate 1%: alpha = 0.01 / N_TESTS.
    assert p > 0.01 / N_TESTS, f"p = {p:.3g}\nobserved {obs}\nexpected {np.round(exp, 1)}"


def test_chi_square_has_power():
    """The test above must reject a sampler that is slightly wrong (g 0.5 vs 0.53) and a
    mirrored one (a sign error, g 0.5 vs -0.5)."""
    p_close, _, _ = _chi2_pvalue([(0.5, 1.0)], [(0.53, 1.0)])
    p_sign, _, _ = _chi2_pvalue([(0.5, 1.0)], [(-0.5, 1.0)])
    assert p_close < 0.01 / N_TESTS and p_sign < 1e-12


@pytest.mark.parametrize("g", [-0.9, 0.5, 0.99])
def test_orientation_mean_cosine_of_samples(g):
    """Mean cosine between incoming and outgoing propagation directions equals g: a sign
    error in sampling or in the lobe axis fails this (chi-square alone might not)."""
    n = N_SAMPLES
    w = _axes(n, 3)
    d = kphase.phase_sample(w, _uniforms(n, 21), [(g, 1.0)]).astype(np.float64)
    mu = np.sum(d * w, axis=1)
    se = mu.std() / np.sqrt(n)
    assert abs(mu.mean() - g) < 5 * se + 1e-6, (mu.mean(), g, se)
