"""NumPy twin of the progressive source's estimator (clvol/render/ms/progressive.py
``estimate``): the table entry of each pixel block from the network's mean and the path-traced
residuals gathered there. Written from the definitions below, block by block with explicit
loops; it imports nothing it checks.

Per block b and channel c (the channels are independent):

  m_nn       the block's mean network F_ms;  sc = max(|m_nn|, 1e-3 max_b |m_nn|, 1e-30)
  n          its path-traced points;  s, q = sums of r / sc and of (r / sc)^2 over them,
             r = F_pt - F_nn the residual at each point ("shrink": F_pt instead of r, and
             the centre m_nn / sc instead of 0)
  mean       s / n (0 without points);  dev = q - s mean for n > 1, else 0
  k          the safety factor 1 + 2 B / N (B blocks with points, N points in all)
  s2         pooled per-point variance, weights sc^2: k sum(dev sc^2) / sum((n - 1) sc^2),
             floored at 1e-12; with fewer than 32 degrees of freedom in all (sum of n - 1
             over blocks with points) every mode but "mean" gives m_nn
  s2b        per block: max((k dev + 2 s2) / (n - 1 + 2), k e2 / (sc^2 n), s2) where n > 0,
             else 0

Modes:
  network    m_nn (no paths)
  mean       m_nn + sc mean (no shrinkage)
  cv         m_nn + sc w mean, w = b2 / (b2 + s2b / n), b2 = max(pooled(mean^2 - s2b / n), 1e-12)
  shrink     sc (m_nn / sc + w (mean - m_nn / sc)) with the same w on F_pt's own mean
  cv_smooth  levels (whole image, radius 4 R, radius R, the block; R = 0: image and block):
             m_L = sum of s / sum of n over the level's blocks, v_L = sum(n s2b) / (sum n)^2;
             tau2_L = max(pooled((m_L - m_up)^2 - (v_L - v_up)) - 3 sqrt(2 / G) pooled(v_L),
             1e-12), (m_up, v_up) the level above's (0, 0 for the first), G = 1 for the
             whole image, else max(blocks with points / (2 radius + 1)^2, 1);
             est += tau2 / (tau2 + v_L) (m_L - est);
             entry m_nn + sc est

``pooled(x)``: the sc^2-weighted mean of x over the blocks where the level has points.
"""
from __future__ import annotations

import numpy as np

FLOOR = 1e-12


def _pooled(x, wt, where):
    num = den = 0.0
    for idx in zip(*np.nonzero(where)):
        num += x[idx] * wt[idx]
        den += wt[idx]
    return num / den if den > 0 else 0.0


def estimate(m_nn, n, s_r, q_r, mode="cv_smooth", radius=2, s_pt=None, q_pt=None, e2=None):
    """(C, by, bx) table entries (module doc)."""
    m_nn = np.asarray(m_nn, float)
    n = np.asarray(n, float)
    C, by, bx = m_nn.shape
    out = np.zeros_like(m_nn)
    for c in range(C):
        a = np.abs(m_nn[c])
        sc = np.maximum(a, max(1e-3 * a.max(), 1e-30))
        wt = sc * sc
        if mode == "shrink":
            s, q, centre = s_pt[c] / sc, q_pt[c] / wt, m_nn[c] / sc
        else:
            s, q, centre = s_r[c] / sc, q_r[c] / wt, np.zeros((by, bx))
        mean = np.zeros((by, bx))
        dev = np.zeros((by, bx))
        for j in range(by):
            for i in range(bx):
                if n[j, i] > 0:
                    mean[j, i] = s[j, i] / n[j, i]
                if n[j, i] > 1:
                    dev[j, i] = max(q[j, i] - s[j, i] * mean[j, i], 0.0)
        dof = (np.maximum(n - 1, 0) * wt).sum()
        if np.maximum(n - 1, 0).sum() < 32 and mode != "mean":
            out[c] = m_nn[c]
            continue
        k = 1.0 + 2.0 * (n > 0).sum() / max(n.sum(), 1.0)
        s2 = max(k * (dev * wt).sum() / dof if dof > 0 else 0.0, FLOOR)
        s2b = np.zeros((by, bx))
        for j in range(by):
            for i in range(bx):
                if n[j, i] > 0:
                    own = (k * dev[j, i] + 2.0 * s2) / (max(n[j, i] - 1, 0) + 2.0)
                    paths = k * e2[c][j, i] / (wt[j, i] * n[j, i]) if e2 is not None else 0.0
                    s2b[j, i] = max(own, paths, s2)
        has = n > 0
        if mode == "network":
            out[c] = m_nn[c]
            continue
        v_l = np.where(has, s2b / np.where(has, n, 1.0), 0.0)
        if mode == "mean":
            out[c] = m_nn[c] + sc * mean
            continue
        if mode in ("cv", "shrink"):
            x = mean - centre
            b2 = max(_pooled(x * x - v_l, wt, has), FLOOR)
            w = np.where(has, b2 / (b2 + v_l), 0.0)
            out[c] = (centre + w * x) * sc if mode == "shrink" else m_nn[c] + w * x * sc
            continue
        levels = [None] + ([4 * radius, radius] if radius > 0 else []) + [0]
        est = np.zeros((by, bx))
        m_up = np.zeros((by, bx))
        v_up = np.zeros((by, bx))
        for lev in levels:
            m = np.zeros((by, bx))
            v = np.zeros((by, bx))
            ns = np.zeros((by, bx))
            for j in range(by):
                for i in range(bx):
                    if lev is None:
                        rows, cols = slice(None), slice(None)
                    else:
                        rows = slice(max(j - lev, 0), j + lev + 1)
                        cols = slice(max(i - lev, 0), i + lev + 1)
                    nn = n[rows, cols].sum()
                    ns[j, i] = nn
                    if nn > 0:
                        m[j, i] = s[rows, cols].sum() / nn
                        v[j, i] = (n[rows, cols] * s2b[rows, cols]).sum() / (nn * nn)
            hl = ns > 0
            d = m - m_up
            groups = 1.0 if lev is None else max(hl.sum() / (2 * lev + 1) ** 2, 1.0)
            margin = 3.0 * np.sqrt(2.0 / groups) * _pooled(v, wt, hl)
            tau2 = max(_pooled(d * d - (v - v_up), wt, hl) - margin, FLOOR)
            w = np.where(hl, tau2 / (tau2 + v), 0.0)
            est = est + w * (m - est)
            m_up = np.where(hl, m, m_up)
            v_up = np.where(hl, v, v_up)
        out[c] = m_nn[c] + sc * est
    return out
