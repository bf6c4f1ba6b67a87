"""Labels at any albedo from one set of paths (docs/pathtrace.md, "Labels per scattering order").

``clvol.render.pathtrace.point_query_orders`` traces the label paths at albedo 1 and bins each
sun NEE by its albedo exponent e (the number of real collisions after the query point; a path
traced at albedo a carries a^e). Per query and bin b it returns the mean contribution S_b and
the mean of contribution x e, M_b. For a homogeneous albedo a the label is

    F(a) = sum_e a^e C_e ~ sum_b S_b a^(ebar_b),  ebar_b = M_b / S_b,

exact for the bins of one exponent (e < 32) and a lower bound for the wider bins (a^e is
convex in e, Jensen); the chord of a^e over the bin's exponents [lo_b, hi_b] at ebar_b is an
upper bound. ``label_bounds`` gives both, so the storage error of any label is known.
"""
from __future__ import annotations

import numpy as np

from ..kernels.pathtrace import order_bin_ranges

_RANGES = order_bin_ranges().astype(np.float64)


def _ebar(S, M):
    S, M = np.asarray(S, np.float64), np.asarray(M, np.float64)
    e = np.divide(M, S, out=np.zeros_like(M), where=S > 0)
    return S, np.clip(e, _RANGES[:, 0], _RANGES[:, 1])


def label_at(S, M, albedo) -> np.ndarray:
    """F_>=2 at ``albedo`` (a scalar, or one per query) from bins S, M [N][B]: [N]."""
    S, e = _ebar(S, M)
    a = np.broadcast_to(np.asarray(albedo, np.float64), S.shape[:1])[:, None]
    with np.errstate(divide="ignore"):
        la = np.log(a)                       # a = 0: -inf, a^e = 0 for e >= 1
    return (S * np.exp(e * la)).sum(axis=1)


def label_bounds(S, M, albedo) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) bounds on sum_e a^e C_e given only the bins: label_at and the chord."""
    S, e = _ebar(S, M)
    a = np.broadcast_to(np.asarray(albedo, np.float64), S.shape[:1])[:, None]
    with np.errstate(divide="ignore"):
        la = np.log(a)
    lo_e, hi_e = _RANGES[:, 0], _RANGES[:, 1]
    f_lo, f_hi = np.exp(lo_e * la), np.exp(hi_e * la)
    width = np.maximum(hi_e - lo_e, 1.0)
    chord = f_lo + (f_hi - f_lo) * (e - lo_e) / width
    return (S * np.exp(e * la)).sum(axis=1), (S * chord).sum(axis=1)


def se_at(se_nodes, node_albedos, albedo) -> np.ndarray:
    """The standard error of the label at ``albedo`` (scalar or [N]), interpolated linearly in
    log(1 - a + 1e-5) between the nodes' errors ``se_nodes`` [N][K] (point_query_orders)."""
    se_nodes = np.asarray(se_nodes, np.float64)
    u_nodes = np.log(1.0 - np.asarray(node_albedos, np.float64) + 1e-5)
    order = np.argsort(u_nodes)
    a = np.broadcast_to(np.asarray(albedo, np.float64), se_nodes.shape[:1])
    u = np.log(1.0 - a + 1e-5)
    out = np.empty(len(se_nodes))
    for i in range(len(se_nodes)):
        out[i] = np.interp(u[i], u_nodes[order], se_nodes[i, order])
    return out


def energy_above(S, e_min: int) -> np.ndarray:
    """Fraction of each label at albedo 1 carried by exponents >= e_min (rounded up to a bin
    edge: the bins whose first exponent is >= e_min)."""
    S = np.asarray(S, np.float64)
    tail = S[:, _RANGES[:, 0] >= e_min].sum(axis=1)
    tot = S.sum(axis=1)
    return np.divide(tail, tot, out=np.zeros_like(tot), where=tot > 0)
