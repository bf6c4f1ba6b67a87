"""NumPy twin of cl/include/phase.h: isotropic, HG and multi-lobe HG phase functions.

Cosines are between propagation directions (g > 0 forward). Functions compute in the
dtype of their inputs (float32 arrays stay float32, as in the kernel). ``lobes`` is a
sequence of (g, weight) pairs; an empty sequence or None means isotropic.
"""
import numpy as np

INV_4PI = 1.0 / (4.0 * np.pi)


def hg_eval(mu, g):
    mu = np.asarray(mu)
    ga = abs(g)
    m = -mu if g < 0 else mu
    a = 1.0 - ga
    denom = a * a + 2.0 * ga * (1.0 - m)
    return a * (1.0 + ga) * INV_4PI / (denom * np.sqrt(denom))


def phase_eval(mu, lobes):
    mu = np.asarray(mu)
    if not lobes:
        return np.full_like(mu, INV_4PI)
    return sum(w * hg_eval(mu, g) for g, w in lobes)


def hg_sample_one_minus_mu(g, u):
    """1 - mu of an inverse-CDF HG sample (see phase.h for the derivation)."""
    u = np.asarray(u)
    a = 1.0 - g + 2.0 * g * u
    r = (1.0 - g) ** 2 * (1.0 - u) * (2.0 + 2.0 * g * u) / (a * a)
    return np.clip(r, 0.0, 2.0)


def onb(n):
    """Orthonormal basis (b1, b2) around unit vectors n (..., 3), Duff et al. 2017."""
    n = np.asarray(n)
    sgn = np.where(n[..., 2] >= 0, 1.0, -1.0).astype(n.dtype)
    a = -1.0 / (sgn + n[..., 2])
    b = n[..., 0] * n[..., 1] * a
    b1 = np.stack([1.0 + sgn * n[..., 0] ** 2 * a, sgn * b, -sgn * n[..., 0]], axis=-1)
    b2 = np.stack([b, sgn + n[..., 1] ** 2 * a, -n[..., 1]], axis=-1)
    return b1, b2


def direction_around(w, one_minus_mu, u_phi):
    w = np.asarray(w)
    mu = 1.0 - one_minus_mu
    s = np.sqrt(np.maximum(0.0, one_minus_mu * (2.0 - one_minus_mu)))
    phi = 2.0 * np.float32(np.pi) * u_phi if w.dtype == np.float32 else 2.0 * np.pi * u_phi
    b1, b2 = onb(w)
    d = (s * np.cos(phi))[..., None] * b1 + (s * np.sin(phi))[..., None] * b2 + mu[..., None] * w
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def phase_sample(w, lobes, u):
    """New propagation directions (..., 3) from directions w (..., 3) and uniforms u (..., 3)."""
    w, u = np.asarray(w), np.asarray(u)
    if not lobes:
        return direction_around(w, 2.0 * (1.0 - u[..., 1]), u[..., 2])
    g = np.full(u.shape[:-1], lobes[0][0], dtype=u.dtype)
    cum = 0.0
    for k in range(1, len(lobes)):
        cum = cum + lobes[k - 1][1]
        g = np.where(u[..., 0] >= np.asarray(cum, u.dtype), np.asarray(lobes[k][0], u.dtype), g)
    omm = hg_sample_one_minus_mu(np.abs(g), u[..., 1])
    axis = np.where((g < 0)[..., None], -w, w)
    return direction_around(axis, omm, u[..., 2])
