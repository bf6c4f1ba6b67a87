"""Volume-phase tables (seed eq. 6) and the per-frame phase-feature table (seed eq. 5).

Volume phase (docs/conventions.md): the phase function *averaged* over the cone of directions that a
template point's volume subtends from the query point,

    fbar(mu, beta) = 1 / (2 pi (1 - cos beta)) * integral over {phi : angle(phi, d) <= beta} of f(a . phi) dphi

with mu = a . d the cosine between the cone's axis d and the argument direction a, and beta
the cone's half-angle. fbar(mu, 0) = f(mu); a cone average of a constant is that constant;
and fbar is still normalised over the sphere (an average of rotated copies of f).

How a lobe table is computed (per |g|; HG only, isotropic is the constant 1 / 4 pi):
  write the cone in polar coordinates (t, psi) around d. With theta = acos(mu) the HG
  denominator is P + Q (1 - cos psi), P = (1-g)^2 + 4 g sin^2((theta - t)/2), Q = 2 g sin(theta)
  sin(t) (no cancellation near the peak), and its psi-integral is closed form:
      integral_0^2pi (P + Q - Q cos psi)^(-3/2) dpsi = 4 E(m) / (P sqrt(P + 2Q)),  m = 2Q / (P + 2Q)
  (E the complete elliptic integral of the second kind). The remaining t-integral
  K(theta, beta) = integral_0^beta sin t H(theta, t) dt is accumulated with 8-point Gauss-Legendre
  panels whose breaks are the table's beta nodes plus a geometric refinement around t = theta,
  where H peaks with width ~(1 - g). Node values are accurate to ~1e-9 relative (tested against
  the Legendre series fbar = sum_l (2l+1)/(4 pi) g^l c_l(beta) P_l(mu), c_l the cap average of P_l).

Table axes. Cone-averaging a sharp lobe gives sharp features at four angles theta between
the cone axis and the lobe axis: the lobe's peak (theta = 0, width ~(1 - g)), the step where the
cap's edge crosses the peak (theta = beta), and their mirror images at pi - beta and pi (the
latter matter for g < 0). Rows are beta nodes, uniform in eta = log(1 - cos beta + C), C = 1e-7,
beta in [0, BETA_MAX = pi/4] (cones of our templates reach 0.61 rad; volume_phase checks a
template against it); row 0
(beta = 0) holds f itself. Within a row, theta is first mapped piecewise linearly to an anchor
coordinate nu in [0, 3] (0, beta, pi - beta, pi -> 0, 1, 2, 3), so the features sit at the same
nu in every row and interpolating across rows follows them; columns are uniform in
      xi(nu) = sum over a in {0, 1, 2, 3} of asinh((nu - a) / S),   S = 0.001,
which clusters columns at each anchor (spacing ~0.05 S pi near one) and is odd about nu = 3/2:
a g < 0 lobe (f(mu; g) = f(-mu; -g)) is the g > 0 table with each row reversed, and a multi-lobe
(MHG) table is a plain weighted sum of lobe tables on the same nodes.
Lookups are bilinear in (eta, xi). Error bound (tests/test_phasetable.py, on random (mu, beta)
against the Legendre series): relative error <= ERROR_BOUND for |g| <= 0.99.

Phase-feature table (what the gather reads): for each template point j with unit direction
u_j (template frame) and cone half-angle beta_j, and alpha = acos(dot(-l, omega)) on a uniform
grid over [0, pi], the feature log1p(fbar(u_z; beta_j) * fbar(u_z cos alpha - u_x sin alpha; beta_j)).
In the frame, omega = (sin alpha, 0, -cos alpha) and the light travels from s_j to p along
d = -u_j, so dot(-l, d) = u_z and dot(d, omega) = u_z cos alpha - u_x sin alpha. The centre point
(u = 0) holds log1p(f(cos alpha)), the plain phase function.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy import special

from ..errors import ClvolError

INV_4PI = 1.0 / (4.0 * np.pi)
C_LOG = 1e-7
WARP_S = 0.001
N_THETA = 768
N_BETA = 112
BETA_MAX = np.pi / 4
N_ALPHA = 1024
G_MAX_ACCURATE = 0.99
ERROR_BOUND = 1e-2   # relative, table lookup vs exact, |g| <= 0.99 (measured 0.7% at g = 0.99, 0.2% at 0.857)

_ETA_MIN = float(np.log(C_LOG))
_ETA_MAX = float(np.log(1.0 - np.cos(BETA_MAX) + C_LOG))


class PhaseTableError(ClvolError):
    """Phase parameters the tables cannot represent."""


def beta_nodes(n: int = N_BETA) -> np.ndarray:
    """Cone half-angles of the rows, ascending from 0 to BETA_MAX, uniform in log(1 - cos beta + C)."""
    eta = np.linspace(_ETA_MIN, _ETA_MAX, n)
    one_minus_cos = np.maximum(np.exp(eta) - C_LOG, 0.0)
    beta = 2.0 * np.arcsin(np.sqrt(np.clip(one_minus_cos / 2.0, 0.0, 1.0)))
    beta[0] = 0.0
    return beta


def _xi(nu):
    s = WARP_S
    return (np.arcsinh(nu / s) + np.arcsinh((nu - 1.0) / s) + np.arcsinh((nu - 2.0) / s)
            + np.arcsinh((nu - 3.0) / s))


_XI_LO, _XI_HI = float(_xi(0.0)), float(_xi(3.0))


def nu_of_theta(theta, beta):
    """Anchor coordinate: 0, beta, pi - beta, pi -> 0, 1, 2, 3, linear in between."""
    theta, beta = np.broadcast_arrays(np.asarray(theta, np.float64), np.asarray(beta, np.float64))
    mid = np.pi - 2.0 * beta
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(beta > 0, theta / np.where(beta > 0, beta, 1.0), 1.0)
        b = np.where(mid > 0, 1.0 + (theta - beta) / np.where(mid > 0, mid, 1.0), 1.5)
        c = np.where(beta > 0, 2.0 + (theta - (np.pi - beta)) / np.where(beta > 0, beta, 1.0), 2.0)
    return np.clip(np.where(theta <= beta, a, np.where(theta < np.pi - beta, b, c)), 0.0, 3.0)


def theta_of_nu(nu, beta):
    nu = np.asarray(nu, np.float64)
    return np.where(nu <= 1.0, nu * beta,
                    np.where(nu <= 2.0, beta + (nu - 1.0) * (np.pi - 2.0 * beta),
                             np.pi - beta + (nu - 2.0) * beta))


@lru_cache(maxsize=2)
def nu_nodes(n: int = N_THETA) -> np.ndarray:
    """Column nodes in nu: uniform in xi, by bisection, exactly symmetric about 3/2."""
    target = np.linspace(_XI_LO, _XI_HI, n)
    lo, hi = np.zeros(n), np.full(n, 3.0)
    for _ in range(64):
        mid = 0.5 * (lo + hi)
        below = _xi(mid) < target
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    nu = 0.5 * (lo + hi)
    nu = 0.5 * (nu + (3.0 - nu[::-1]))
    nu[0], nu[-1] = 0.0, 3.0
    return nu


def _grid(n_theta: int = N_THETA, n_beta: int = N_BETA):
    """(beta nodes (n_beta,), theta nodes (n_beta, n_theta))."""
    betas = beta_nodes(n_beta)
    return betas, theta_of_nu(nu_nodes(n_theta)[None, :], betas[:, None])


def hg(mu, g):
    """HG phase function, evaluated in its stable forward-peaked form (float64)."""
    mu = np.asarray(mu, np.float64)
    ga = abs(g)
    m = -mu if g < 0 else mu
    a = 1.0 - ga
    den = a * a + 2.0 * ga * (1.0 - m)
    return a * (1.0 + ga) * INV_4PI / (den * np.sqrt(den))


def _hg_theta(theta, g):
    """HG at angle theta from the peak (g > 0), with 1 - cos written as 2 sin^2(theta/2)."""
    den = (1.0 - g) ** 2 + 4.0 * g * np.sin(0.5 * theta) ** 2
    return (1.0 - g * g) * INV_4PI / (den * np.sqrt(den))


_GL_X, _GL_W = np.polynomial.legendre.leggauss(8)
_UNIFORM_PANELS = 6


def _cap_average(thetas: np.ndarray, beta: float, g: float) -> np.ndarray:
    """fbar at angles ``thetas`` from the lobe axis for one cone half-angle ``beta`` > 0 (g > 0).

    K(theta, beta) = integral_0^beta sin t H(theta, t) dt with H the closed-form psi-integral;
    8-point Gauss-Legendre panels: a few uniform ones plus a geometric refinement around
    t = theta where H peaks (zero-width panels from clipping contribute nothing)."""
    width = max(1.0 - g, 1e-6)
    refine = width * 2.0 ** np.arange(-5, 9)
    th = thetas[:, None]
    brk = np.concatenate([np.broadcast_to(np.linspace(0.0, beta, _UNIFORM_PANELS + 1),
                                          (len(thetas), _UNIFORM_PANELS + 1)),
                          th, th - refine[None, :], th + refine[None, :]], axis=1)
    brk = np.sort(np.clip(brk, 0.0, beta), axis=1)
    a, b = brk[:, :-1], brk[:, 1:]
    half = 0.5 * (b - a)
    t = (0.5 * (a + b))[..., None] + half[..., None] * _GL_X
    th3 = thetas[:, None, None]
    p = (1.0 - g) ** 2 + 4.0 * g * np.sin(0.5 * (th3 - t)) ** 2
    q = 2.0 * g * np.sin(th3) * np.sin(t)
    m = 2.0 * q / (p + 2.0 * q)
    h = 4.0 * special.ellipe(m) / (p * np.sqrt(p + 2.0 * q))
    k = ((np.sin(t) * h * _GL_W).sum(-1) * half).sum(-1)
    cap = 2.0 * np.pi * 2.0 * np.sin(beta / 2.0) ** 2      # 2 pi (1 - cos beta)
    return (1.0 - g * g) * INV_4PI * k / cap


@lru_cache(maxsize=16)
def lobe_table(g: float, n_theta: int = N_THETA, n_beta: int = N_BETA) -> np.ndarray:
    """fbar for one HG lobe, float64 (n_beta, n_theta): row m at beta_nodes()[m], column k at
    theta_nodes(beta_m)[k], theta the angle between the cone axis and the lobe's axis.

    For |g| <= G_PACKED_MAX on the default grid, interpolated from the packaged table
    (``packed_lobe_table``; within PACKED_BOUND of ``lobe_table_exact`` at every node);
    otherwise the exact cap averages (slow: a quadrature per node; costs in docs/neural.md)."""
    g = _check_g(g)
    if g == 0.0:
        return np.full((n_beta, n_theta), INV_4PI)
    if g < 0.0:
        return lobe_table(-g, n_theta, n_beta)[:, ::-1].copy()
    if g <= G_PACKED_MAX and (n_theta, n_beta) == (N_THETA, N_BETA) and _packed() is not None:
        return packed_lobe_table(g)
    return lobe_table_exact(g, n_theta, n_beta)


def _check_g(g) -> float:
    g = float(g)
    if not -1.0 < g < 1.0:
        raise PhaseTableError(f"HG g = {g!r} must be in (-1, 1)")
    return g


@lru_cache(maxsize=4)
def lobe_table_exact(g: float, n_theta: int = N_THETA, n_beta: int = N_BETA) -> np.ndarray:
    """``lobe_table`` from the cap-average quadrature at every node (the reference; also what
    scripts/make_phase_table.py packs)."""
    g = _check_g(g)
    if g == 0.0:
        return np.full((n_beta, n_theta), INV_4PI)
    if g < 0.0:
        return lobe_table_exact(-g, n_theta, n_beta)[:, ::-1].copy()
    betas, thetas = _grid(n_theta, n_beta)
    out = np.empty((n_beta, n_theta))
    out[0] = _hg_theta(thetas[0], g)
    for m in range(1, n_beta):
        out[m] = _cap_average(thetas[m], betas[m], g)
    return out


# --------------------------------------------------------------------------- packaged lobe tables
# One table over (g, beta, theta) ships as clvol/data/phase_lobes.npz (scripts/make_phase_table.py):
# exact lobe tables at PACKED_U nodes of u = -log(1 - g), stored as log(fbar) quantised to uint16.
# A lobe table for any 0 < g <= 0.99 is a cubic spline (not-a-knot) in u of log(fbar) at each node
# of the (beta, theta) grid: log(fbar) is smooth in u (a peak of width ~(1 - g) = exp(-u) moving
# past fixed nodes), where fbar itself is not. Measured against exact tables at the midpoints of
# a 33-node u grid: worst 5.4e-4 relative (near g = 0.99), 4e-4 at g = 0.13; the uint16
# quantisation adds at most 1.7e-4. PACKED_BOUND is the tested bound (tests/test_phasetable.py).
PACKED_FILE = "phase_lobes.npz"
G_PACKED_MAX = 0.99
_U_MAX = float(-np.log(1.0 - G_PACKED_MAX))
# u nodes: 33 uniform steps of u_max / 32, every other one except near g = 0, where the
# spline needs them (indices 0, 1, 2, 4, 6, ..., 32).
PACKED_U = tuple(float(k) * _U_MAX / 32.0 for k in [0, 1, 2] + list(range(4, 33, 2)))
PACKED_BOUND = 1e-3


def packed_grid_meta() -> dict:
    """The grid constants a packaged table is valid for (checked on load)."""
    return {"n_theta": N_THETA, "n_beta": N_BETA, "c_log": C_LOG, "warp_s": WARP_S,
            "beta_max": float(BETA_MAX), "u": list(PACKED_U)}


def _packed_path():
    from importlib import resources
    from pathlib import Path
    return Path(str(resources.files("clvol") / "data" / PACKED_FILE))


@lru_cache(maxsize=1)
def _packed():
    """(spline weights, log fbar [len(PACKED_U)][N_BETA * N_THETA]) from the packaged file, or
    None if it is missing or was made for another grid (then lobe_table computes exactly:
    slower, never wrong). A cubic spline is linear in its node values, so the spline is kept as
    one of the unit vectors, whose piecewise-cubic coefficients the file carries (``basis_c``,
    scipy's CubicSpline(PACKED_U, eye, bc_type="not-a-knot").c, so loading needs no
    scipy.interpolate, whose import alone costs ~1 s), and applied as weights."""
    import json
    path = _packed_path()
    if not path.is_file():
        return None
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(z["meta"].tobytes().decode("utf-8"))
        if meta != packed_grid_meta():
            return None
        logtab = z["lo"] + z["step"] * z["q"].astype(np.float64)
        basis_c = z["basis_c"].astype(np.float64)
    return basis_c, logtab.reshape(len(PACKED_U), -1)


def _spline_weights(basis_c: np.ndarray, u: float) -> np.ndarray:
    """Weights of the node values in the not-a-knot cubic spline at u (PPoly evaluation)."""
    nodes = np.asarray(PACKED_U)
    i = int(np.clip(np.searchsorted(nodes, u, side="right") - 1, 0, len(nodes) - 2))
    t = u - nodes[i]
    c = basis_c[:, i]                       # [4][n]: t^3, t^2, t, 1
    return ((c[0] * t + c[1]) * t + c[2]) * t + c[3]


def packed_lobe_table(g: float) -> np.ndarray:
    """The lobe table for 0 < g <= G_PACKED_MAX interpolated from the packaged table; row 0
    (beta = 0, the plain HG) is evaluated exactly, as it costs nothing."""
    packed = _packed()
    if packed is None:
        raise PhaseTableError(f"packaged phase table {_packed_path()} missing or made for another "
                              f"grid; run scripts/make_phase_table.py")
    g = float(g)
    if not 0.0 < g <= G_PACKED_MAX:
        raise PhaseTableError(f"packaged phase table covers 0 < g <= {G_PACKED_MAX}, got {g!r}")
    basis_c, logtab = packed
    w = _spline_weights(basis_c, float(-np.log1p(-g)))   # [len(PACKED_U)] weights at this g
    out = np.exp(w @ logtab).reshape(N_BETA, N_THETA)
    out[0] = _hg_theta(_grid()[1][0], g)
    return out


def write_packed_table(path, tables: np.ndarray) -> dict:
    """Quantise exact lobe tables [len(PACKED_U)][N_BETA][N_THETA] (at g = 1 - exp(-u)) into the
    packaged file; returns {"lo", "step", "max_quantisation_error"}."""
    import json
    from scipy.interpolate import CubicSpline
    from ..atomic import atomic_open
    u = np.asarray(PACKED_U)
    basis_c = CubicSpline(u, np.eye(len(u)), axis=0, bc_type="not-a-knot").c
    logtab = np.log(np.asarray(tables, np.float64))
    lo, hi = float(logtab.min()), float(logtab.max())
    step = (hi - lo) / 65535.0
    q = np.round((logtab - lo) / step).astype(np.uint16)
    err = float(np.abs(np.expm1(lo + step * q.astype(np.float64) - logtab)).max())
    blob = np.frombuffer(json.dumps(packed_grid_meta()).encode("utf-8"), np.uint8)
    with atomic_open(path, "wb") as f:
        np.savez_compressed(f, meta=blob, q=q, lo=np.float64(lo), step=np.float64(step),
                            basis_c=basis_c)
    return {"lo": lo, "step": step, "max_quantisation_error": err}


def _lobes(lobes) -> tuple[tuple[float, float], ...]:
    """(g, weight) pairs from clvol.scene.Lobe objects or pairs; None/empty: isotropic."""
    out = []
    for lobe in lobes or [(0.0, 1.0)]:
        g, w = (lobe.g, lobe.weight) if hasattr(lobe, "g") else lobe
        out.append((float(g), float(w)))
    return tuple(out)


@dataclass(frozen=True)
class VolumePhase:
    """Cone-averaged phase function of a (multi-lobe) HG phase: ``eval(mu, beta)``."""
    lobes: tuple[tuple[float, float], ...]
    table: np.ndarray          # (N_MU, N_BETA) float64: weighted sum of lobe tables

    def eval(self, mu, beta) -> np.ndarray:
        """Bilinear lookup: linear in eta(beta) between two rows, each row read at the query's
        anchor coordinate nu(theta, beta) (so the features line up across rows), linear in xi."""
        mu = np.clip(np.asarray(mu, np.float64), -1.0, 1.0)   # rounding of unit dot products
        beta = np.asarray(beta, np.float64)
        if not (np.all(beta >= 0.0) and np.all(beta <= BETA_MAX * (1 + 1e-12))):
            raise PhaseTableError(f"cone half-angle {beta.min()}..{beta.max()} rad outside the "
                                  f"table's [0, {BETA_MAX:.4f}] (BETA_MAX)")
        beta = np.minimum(beta, BETA_MAX)
        mu, beta = np.broadcast_arrays(mu, beta)
        n_beta, n_theta = self.table.shape
        theta = 2.0 * np.arcsin(np.sqrt(np.clip((1.0 - mu) / 2.0, 0.0, 1.0)))
        eta = np.log(2.0 * np.sin(beta / 2.0) ** 2 + C_LOG)
        fe = np.clip((eta - _ETA_MIN) / (_ETA_MAX - _ETA_MIN) * (n_beta - 1), 0.0, n_beta - 1.0)
        j0 = np.minimum(fe.astype(np.int64), n_beta - 2)
        b = fe - j0
        fk = (_xi(nu_of_theta(theta, beta)) - _XI_LO) / (_XI_HI - _XI_LO) * (n_theta - 1)
        fk = np.clip(fk, 0.0, n_theta - 1.0)
        k0 = np.minimum(fk.astype(np.int64), n_theta - 2)
        a = fk - k0
        t = self.table
        return ((1 - b) * ((1 - a) * t[j0, k0] + a * t[j0, k0 + 1])
                + b * ((1 - a) * t[j0 + 1, k0] + a * t[j0 + 1, k0 + 1]))

    def point(self, mu) -> np.ndarray:
        """The plain phase function f(mu) (no cone)."""
        return sum(w * hg(mu, g) for g, w in self.lobes)


def volume_phase(lobes) -> VolumePhase:
    """Tables for these lobes ((g, weight) pairs or scene Lobes; None: isotropic). Lobe
    tables are cached per g, so reloading a scene with the same phase costs nothing."""
    lb = _lobes(lobes)
    for g, w in lb:
        if not (np.isfinite(g) and -1.0 < g < 1.0):
            raise PhaseTableError(f"[medium.phase] lobe g = {g!r} must be in (-1, 1)")
        if not (np.isfinite(w) and w >= 0.0):
            raise PhaseTableError(f"[medium.phase] lobe weight = {w!r} must be >= 0")
    total = sum(w for _, w in lb)
    if not abs(total - 1.0) < 1e-6:
        raise PhaseTableError(f"[medium.phase] lobe weights sum to {total!r}, must sum to 1")
    table = sum(w * lobe_table(g) for g, w in lb)
    return VolumePhase(lb, table)


def alpha_nodes(n: int = N_ALPHA) -> np.ndarray:
    return np.linspace(0.0, np.pi, n)


def feature_directions(points: np.ndarray) -> np.ndarray:
    """Unit directions of the template points in the frame (0 for the centre point)."""
    d = np.linalg.norm(points, axis=1, keepdims=True)
    return np.where(d > 0, points / np.where(d > 0, d, 1.0), 0.0)


def phase_features(vp: VolumePhase, points: np.ndarray, half_angle: np.ndarray,
                   alpha) -> np.ndarray:
    """log1p phase feature (seed eq. 5) of every template point for each alpha: (len(alpha), N).
    Used both to build the gather's table and (at exact alpha) as its reference."""
    alpha = np.atleast_1d(np.asarray(alpha, np.float64))
    u = feature_directions(points)
    ca, sa = np.cos(alpha)[:, None], np.sin(alpha)[:, None]
    mu_in = np.broadcast_to(u[None, :, 2], (len(alpha), len(u)))
    mu_out = u[None, :, 2] * ca - u[None, :, 0] * sa
    beta = np.broadcast_to(half_angle[None, :], mu_in.shape)
    feat = vp.eval(mu_in, beta) * vp.eval(mu_out, beta)
    centre = np.all(points == 0.0, axis=1)
    feat[:, centre] = vp.point(np.cos(alpha))[:, None]
    return np.log1p(feat)


def phase_feature_table(vp: VolumePhase, points: np.ndarray, half_angle: np.ndarray,
                        n_alpha: int = N_ALPHA) -> np.ndarray:
    """float32 (n_alpha, N) table over alpha = linspace(0, pi, n_alpha), read linearly by the gather."""
    return phase_features(vp, points, half_angle, alpha_nodes(n_alpha)).astype(np.float32)
