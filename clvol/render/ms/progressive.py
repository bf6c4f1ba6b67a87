"""The network's answer refined by path-traced point queries while the view is still
(``--ms progressive``, issue 38).

The stochastic view source (view.py, ``StochasticViewMs``) draws one free-flight point per
pixel block per frame and keeps the block's mean network F_ms. This source draws the same
points and, while the view is still, also path-traces some of them (clvol/render/pathtrace.py
``point_query``, ``PATHS_PER_QUERY`` paths each). At a path-traced point the residual
``r = F_pt - F_nn`` is kept beside the network's value; the table entry is

    F = m_nn + sc * r_hat

with m_nn the block's mean network F_ms over all its points and sc its scale (m_nn, floored),
and r_hat the relative residual's estimate: a control variate (the network is the control;
only the residual's mean is estimated from paths, not F itself), shrunk through levels by
empirical Bayes (``estimate``, mode "cv_smooth", the default). The levels, coarse to fine, are
the whole image, neighbourhoods of (8 R + 1)^2 and (2 R + 1)^2 blocks (R = SMOOTH_RADIUS) and
the block; each level's residual mean m (noise v = its points' variance over their count
squared) is shrunk toward the coarser level's estimate by w = tau2 / (tau2 + v), with tau2
the measured spread of that level's true means about the coarser level's (pooled over the
image: mean of (m - m_up)^2 - (v - v_up), less SPREAD_SIGMAS standard errors of that mean).

The per-point variance of the relative residual (the paths' noise and the network's
point-to-point error) is pooled over the image per channel (weights F_ms^2), used as a prior
for each block's own, floored by its points' path standard errors, and taken (1 +
SAFETY_POINTS / points per block) times larger while points are few; nothing moves from the
network before MIN_DOF points lie beyond their block's first. Few paths: v large, w small, the
entry stays at the network's; paths without end: every v -> 0, every w -> 1, the entry -> the
block's path-traced mean, the path-traced table's bound (consistent). The alternatives
measured against it (docs/accuracy.md, "Progressive"): "cv" (one level, the block) and
"shrink" (the issue's (k F_nn + sum F_pt) / (k + n) on F itself, k = s2 / b2 from the same
pooling); "network" and "mean" (no shrinkage) are the two ends. The NumPy twin is
reference/progressive.py.

Scheduling: each round draws one point per block (as a stochastic frame) and path-traces up
to ``ROUND_FRACTION`` of them, block b chosen with probability proportional to
``sc_b / sqrt(n_b + 1)`` (the standard deviation of its residual mean under the pooled s2:
bright multiple scattering first, then the blocks with the fewest paths), capped at 1.

A camera move draws a network-only frame (costs what a stochastic frame costs), reprojects
the network history as the stochastic source does and drops the paths (F_ms depends on the
direction toward the camera); a light, medium or density change starts afresh.

Reproducible: the rounds are numbered; round i's draw, choice and paths use streams keyed by
(seed, i). Rounds per render: ``time`` (--time) refines for that wall time after the render's
first frame (how many rounds fit depends on the machine, so the header records them,
``raymarch.progressive_rounds``); ``progressive_rounds`` (--progressive-rounds N) makes N
instead, the same image bit for bit on the same device and seed; with neither, a render of a
still view makes one round and the first frame of a view none (the viewer's frames: a moving
camera costs what a stochastic frame costs).
"""
from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np

from ...errors import ClvolError
from ...runtime import Stopwatch
from .base import option
from .view import (DOMAIN_FALLBACK_OPTION, STILL_SAMPLES, VIEW_BLOCK_OPTION, WEIGHTS_OPTION,
                   StochasticViewMs, _is_int)

PATHS_PER_QUERY = 4          # paths per path-traced point (a round's paths: PATHS_PER_QUERY x
                             # the chosen points)
ROUND_FRACTION = 0.5         # at most this share of a round's points is path-traced
SMOOTH_RADIUS = 2            # the neighbourhood of the first level: (2 R + 1)^2 blocks
MAX_ROUNDS = 100_000
ESTIMATORS = ("cv_smooth", "cv", "shrink", "mean", "network")
# Relative floors: a block's scale is at least SCALE_FLOOR x the brightest block's (no division
# by a zero F_ms), and a pooled variance at least VAR_FLOOR (relative units, squared).
SCALE_FLOOR = 1e-3
VAR_FLOOR = 1e-12
MIN_DOF = 32                 # degrees of freedom (points beyond a block's first) before paths count
SPREAD_SIGMAS = 3.0          # a level's pooled spread: its estimate less this many standard errors
NOISE_SAFETY = 1.0           # the residual variances are taken this many times their estimate ...
SAFETY_POINTS = 2.0          # ... times (1 + this / mean points per block)
PRIOR_POINTS = 2.0           # the pooled residual variance's weight in a block's own, in points


# The source's own options (clvol/render/ms/base.py ``option``), beside the view options it shares.
PROGRESSIVE_OPTIONS = (
    option("--progressive-rounds", type=int, default=None, metavar="N",
           help="--ms progressive: refinement rounds per render instead of --time (a --time "
                "render records its count in the header, raymarch.progressive_rounds: N "
                "reproduces it bit for bit with the same --seed)"),
    option("--time", type=float, default=None, metavar="SECONDS",
           help="--ms progressive: refine for this wall time after the first frame (the rounds "
                "that fit depend on the machine; the header records them)"),
)


def check_progressive_options(rounds, budget):
    if rounds is not None and not (_is_int(rounds) and 1 <= rounds <= MAX_ROUNDS):
        raise ClvolError(f"raymarch option progressive_rounds = {rounds!r}: an integer from 1 "
                         f"to {MAX_ROUNDS} (refinement rounds per render)")
    if budget is not None and (isinstance(budget, bool) or
                               not isinstance(budget, (int, float, np.floating, np.integer))
                               or not np.isfinite(budget) or not budget > 0):
        raise ClvolError(f"option time = {budget!r}: must be a finite number of seconds > 0")


# --------------------------------------------------------------------------- estimator

def box_sum(x: np.ndarray, radius: int) -> np.ndarray:
    """Sum of ``x`` (..., by, bx) over the (2 radius + 1)^2 blocks around each block (blocks
    outside the image count 0), by cumulative sums."""
    if radius <= 0:
        return np.array(x, np.float64)
    x = np.asarray(x, np.float64)
    pad = [(0, 0)] * (x.ndim - 2) + [(radius + 1, radius), (radius + 1, radius)]
    c = np.pad(x, pad).cumsum(axis=-2).cumsum(axis=-1)
    w = 2 * radius + 1
    return c[..., w:, w:] - c[..., :-w, w:] - c[..., w:, :-w] + c[..., :-w, :-w]


def _ratio(num, den):
    """num / den where den > 0, else 0 (no division by zero, no NaN)."""
    num, den = np.broadcast_arrays(np.asarray(num, np.float64), np.asarray(den, np.float64))
    return np.divide(num, den, out=np.zeros(num.shape), where=den > 0)


def block_scale(m_nn: np.ndarray) -> np.ndarray:
    """(C, by, bx) the per-block scale of the residual: |m_nn| floored at SCALE_FLOOR x the
    largest per channel (and at a tiny absolute floor)."""
    m = np.abs(np.asarray(m_nn, np.float64))
    top = m.reshape(len(m), -1).max(axis=1, initial=0.0)
    floor = np.maximum(SCALE_FLOOR * top, 1e-30)[:, None, None]
    return np.maximum(m, floor)


def _pooled(x, wt, where):
    """The wt-weighted mean of x (C, by, bx) over the blocks ``where``, per channel (C,)."""
    C = len(wt)
    wsum = np.where(where, wt, 0.0).reshape(C, -1).sum(axis=1)
    return _ratio(np.where(where, x * wt, 0.0).reshape(C, -1).sum(axis=1), wsum)


def _variances(n, s, q, sc, e2):
    """(mean, s2 (C, 1, 1), s2b (C, by, bx)) of the relative sums s, q: the block means, the
    pooled per-point variance and each block's (module doc of ``estimate``)."""
    C = len(s)
    has = n > 0
    mean = _ratio(s, n * np.ones_like(s))                        # (C, by, bx)
    dev = np.where(n > 1, np.maximum(q - s * mean, 0.0), 0.0)   # sum of squared deviations
    # Pooled over blocks with weights sc^2 (the block's F_ms squared): a relative variance
    # in which dim blocks, whose relative residuals are large and matter little, do not
    # dominate.
    wt = sc * sc
    dof = (np.maximum(n - 1, 0) * wt).reshape(C, -1).sum(axis=1)
    # Few points per block: variances estimated from few heavy-tailed residuals understate the
    # noise (measured: the first rounds crept above the network on oof_sphcu_back), so they are
    # taken (1 + SAFETY_POINTS / mean points per block) times larger, a factor that tends to 1
    safety = NOISE_SAFETY * (1.0 + SAFETY_POINTS * has.sum() / max(float(n.sum()), 1.0))
    s2 = safety * _ratio((dev * wt).reshape(C, -1).sum(axis=1), dof)
    s2 = np.maximum(s2, VAR_FLOOR)[:, None, None]
    # Per block: the pooled value as a prior (PRIOR_POINTS points' worth) beside the block's own
    # deviations, and never below its points' own path noise (e2: a dim block's relative path
    # noise is far above a bright one's).
    own = _ratio(safety * dev + PRIOR_POINTS * s2, np.maximum(n - 1, 0) + PRIOR_POINTS)
    paths = (safety * _ratio(np.asarray(e2, np.float64) / wt, n * np.ones_like(mean))
             if e2 is not None else 0.0)
    return mean, s2, np.where(has, np.maximum(np.maximum(own, paths), s2), 0.0)


def estimate(m_nn, n, s_r, q_r, mode: str = "cv_smooth", radius: int = SMOOTH_RADIUS,
             s_pt=None, q_pt=None, e2=None):
    """The table's F_ms per block and the estimate's relative error.

    m_nn (C, by, bx): the block's mean network F_ms; n (by, bx): its path-traced points;
    s_r, q_r (C, by, bx): the sums of the residual F_pt - F_nn over them and of its square;
    s_pt, q_pt: the same for F_pt itself (mode "shrink" only); e2 (C, by, bx): the sum of the
    points' squared path standard errors (a floor of each block's variance). Returns
    (F (C, by, bx) float64, info) with info {"s2": the pooled relative per-point variance per
    channel, "b2": the network's relative error variance (summed over the levels), "d2": the
    finest level's, "error": relative RMS error per block (by, bx) expected of F (None while
    fewer than MIN_DOF points lie beyond their block's first: then F is the network's),
    "error_network": that of the network alone}."""
    if mode not in ESTIMATORS:
        raise ClvolError(f"progressive estimator {mode!r}: one of {ESTIMATORS}")
    m_nn = np.asarray(m_nn, np.float64)
    n = np.asarray(n, np.float64)
    sc = block_scale(m_nn)
    C = len(m_nn)
    if mode == "shrink":
        if s_pt is None or q_pt is None:
            raise ClvolError("progressive estimator 'shrink' needs s_pt and q_pt")
        s, q = np.asarray(s_pt, np.float64) / sc, np.asarray(q_pt, np.float64) / (sc * sc)
        centre = m_nn / sc          # shrink the mean of F_pt / sc toward m_nn / sc
    else:
        s, q = np.asarray(s_r, np.float64) / sc, np.asarray(q_r, np.float64) / (sc * sc)
        centre = np.zeros_like(m_nn)
    zero = np.zeros(C)
    if float(np.maximum(n - 1, 0).sum()) < MIN_DOF and mode != "mean":
        # too few blocks with two points: a residual's spread is unknown (the paths' own
        # standard errors, from PATHS_PER_QUERY heavy-tailed paths, understate it): the
        # network alone
        return m_nn.copy(), {"s2": np.full(C, np.inf), "b2": zero, "d2": zero,
                             "error": None, "error_network": None}
    mean, s2, s2b = _variances(n, s, q, sc, e2)
    has = n > 0
    v_l = np.where(has, _ratio(s2b, n * np.ones_like(mean)), 0.0)
    if mode in ("network", "mean"):       # no paths (the baseline); no shrinkage (diagnostic)
        f = m_nn.copy() if mode == "network" else m_nn + mean * sc
        err = np.zeros(n.shape) if mode == "network" else np.sqrt(np.mean(v_l, axis=0))
        return f, {"s2": s2[:, 0, 0], "b2": zero, "d2": zero, "error": err,
                   "error_network": np.zeros(n.shape)}
    if mode in ("cv", "shrink"):
        x = mean - centre
        b2 = np.maximum(_pooled(x * x - v_l, sc * sc, has), VAR_FLOOR)[:, None, None]
        w = np.where(has, b2 / (b2 + np.where(has, v_l, 1.0)), 0.0)
        err = np.sqrt(np.where(has, w * v_l, b2))
        f = (centre + w * x) * sc if mode == "shrink" else m_nn + w * x * sc
        return f, {"s2": s2[:, 0, 0], "b2": b2[:, 0, 0], "d2": zero,
                   "error": np.sqrt(np.mean(err * err, axis=0)),
                   "error_network": np.sqrt(np.mean(np.broadcast_to(b2, err.shape), axis=0))}
    est, var, spread, tau2 = _levels(n, s, s2b, sc, radius)
    return m_nn + est * sc, {
        "s2": s2[:, 0, 0], "b2": spread, "d2": tau2,
        "error": np.sqrt(np.mean(var, axis=0)),
        "error_network": np.sqrt(np.mean(np.broadcast_to(spread[:, None, None], var.shape),
                                         axis=0))}


def _levels(n, s, s2b, sc, radius):
    """cv_smooth's shrinkage through the levels, coarse to fine: the whole image,
    neighbourhoods of 4 R and of R blocks, the block. Each level's residual mean m is shrunk
    toward the estimate of the level above, est += w (m - est), w = tau2 / (tau2 + v): v its
    noise, tau2 the pooled spread of the level's true means about the coarser level's (mean
    of (m - m_up)^2 - (v - v_up); the neighbourhoods nest, so the covariance of m and m_up
    is v_up). Returns (est, its posterior variance under that model, the spreads' sum per
    channel, the finest level's spread)."""
    C = len(s)
    wt = sc * sc
    levels = [None] + ([4 * radius, radius] if radius > 0 else []) + [0]
    est = np.zeros_like(s)
    m_up, v_up = np.zeros_like(s), np.zeros_like(s)
    var = np.zeros_like(s)             # the estimate's posterior variance (the model's)
    spread = np.zeros(C)               # sum of tau2 over the levels: the network's error
    for lev in levels:
        if lev is None:                # the whole image
            tot = float(n.sum())
            ns = np.full(n.shape, tot)
            m = np.broadcast_to(_ratio(s.reshape(C, -1).sum(axis=1),
                                       np.full(C, tot))[:, None, None], s.shape)
            nv = np.broadcast_to((n * s2b).reshape(C, -1).sum(axis=1)[:, None, None], s.shape)
        else:
            ns = box_sum(n, lev)
            m = _ratio(box_sum(s, lev), ns * np.ones_like(s))
            nv = box_sum(n * s2b, lev)
        hl = ns > 0
        v = np.where(hl, _ratio(nv, ns * ns * np.ones_like(m)), 0.0)
        d = m - m_up
        # The pooled spread is an average over about G independent neighbourhoods (1 for the
        # whole image), so its noise is ~ sqrt(2 / G) x (spread + noise): it is taken
        # SPREAD_SIGMAS of those below its estimate (a coarse level moves the image only
        # where its residual stands out of its noise; the margin -> 0 with the noise).
        groups = 1.0 if lev is None else max(float(hl.sum()) / (2 * lev + 1) ** 2, 1.0)
        margin = SPREAD_SIGMAS * np.sqrt(2.0 / groups) * _pooled(v, wt, hl)
        tau2 = np.maximum(_pooled(d * d - (v - v_up), wt, hl) - margin,
                          VAR_FLOOR)[:, None, None]
        w = np.where(hl, tau2 / (tau2 + v), 0.0)
        est = est + w * (m - est)
        var = np.where(hl, (1.0 - w) ** 2 * var + w * v, var + tau2)
        spread += tau2[:, 0, 0]
        m_up, v_up = np.where(hl, m, m_up), np.where(hl, v, v_up)
    return est, var, spread, tau2[:, 0, 0]


# --------------------------------------------------------------------------- the source

class _Paths:
    """Per block: path-traced points n, sums of the residual, of its square, of F_pt, of its
    square and of the squared path standard errors; paths."""

    def __init__(self, channels, by, bx):
        z = (channels, by, bx)
        self.n = np.zeros((by, bx))
        self.s_r, self.q_r = np.zeros(z), np.zeros(z)
        self.s_pt, self.q_pt = np.zeros(z), np.zeros(z)
        self.e2 = np.zeros(z)
        self.paths = np.zeros((by, bx))


class ProgressiveViewMs(StochasticViewMs):
    """The stochastic view, refined toward path-traced F_ms while the view is still (module
    doc)."""
    name = "progressive"
    summary = "the stochastic view refined toward path-traced F_ms while the view is still"
    what = "progressive view-space F_ms table (network + path-traced residual)"
    bundle_supported = False           # Python only (docs/embedding.md)

    def bundle_view(self, camera) -> None:
        return None
    options = (WEIGHTS_OPTION, VIEW_BLOCK_OPTION, *PROGRESSIVE_OPTIONS, DOMAIN_FALLBACK_OPTION)

    def __init__(self, weights=None, block: int | None = None, seed: int = 0,
                 rounds: int | None = None, budget: float | None = None, runtime=None):
        super().__init__(weights, block, 1, seed, runtime)
        check_progressive_options(rounds, budget)
        if rounds is not None and budget is not None:
            raise ClvolError("--ms progressive: give --time or --progressive-rounds, not both")
        self.rounds = None if rounds is None else int(rounds)
        self.budget = None if budget is None else float(budget)
        self.estimator = "cv_smooth"
        self.radius = SMOOTH_RADIUS
        self.paths_per_query = PATHS_PER_QUERY
        self.fraction = ROUND_FRACTION
        self.paths = None
        self.rounds_done = 0            # refinement rounds of this view
        self.estimate_info = None
        self._evaluations = 1           # network evaluations per point (3: colour)
        # Optional stand-in for the path tracer (tests): path_query(points, omegas, n_paths,
        # seed) -> {"Fms": (N, 3), "Fms_se": (N, 3)}, as point_query's
        self.path_query = None

    @classmethod
    def from_options(cls, o, runtime=None) -> "ProgressiveViewMs":
        o.get("domain_fallback")        # read by plan_frame for every network source
        return cls(o.get("weights"), o.get("view_block"), o.get("seed", 0),
                   o.get("progressive_rounds"), o.get("time"), runtime)

    @property
    def label(self) -> str:
        from pathlib import Path
        return (f"network multiple scattering at the camera's view, refined by path-traced "
                f"point queries ({self.block}x{self.block}-pixel blocks, "
                f"{self._paths_per_block():.0f} "
                f"paths per block so far; weights {Path(str(self.weights_path)).name})")

    def _paths_per_block(self) -> float:
        if self.paths is None or not (self.history.count > 0).any():
            return 0.0
        return float(self.paths.paths.sum() / (self.history.count > 0).sum())

    # ------------------------------------------------------------------ rounds
    def _round(self, frame, h, with_paths: bool, moved: bool = False):
        """One round: a draw per block, the network there and (``with_paths``) paths at a
        scheduled share of the points. Returns its seconds by stage."""
        t = {}
        index = self.draws
        self.draws += 1
        with Stopwatch() as sw:
            pts, dirs, depth, full = self._draw(frame, index)
        t["depths"] = sw.seconds
        if moved:
            with Stopwatch() as sw:
                self._reproject(h, frame.camera, pts, full)
            t["reproject"] = sw.seconds
        chosen = np.zeros(len(pts), bool)
        if with_paths and len(pts):
            m_nn = self._nn_mean(h)
            sc = block_scale(m_nn).mean(axis=0)[full]
            prio = sc / np.sqrt(self.paths.n[full] + 1.0)
            total = prio.sum()
            want = self.fraction * len(pts)
            p = np.minimum(1.0, _ratio(want * prio, np.full(prio.shape, total)))
            chosen = np.random.default_rng([self.seed, index, 1]).random(len(pts)) < p
        # the network at every point while its mean still gathers (STILL_SAMPLES), then only
        # where paths go (the control variate needs F_nn there)
        evaluate = np.ones(len(pts), bool) if h.count.max(initial=0) < STILL_SAMPLES else chosen
        vals, info = self._evaluate(frame, pts[evaluate], dirs[evaluate])
        t.update({k: info.get(k, 0.0) for k in ("light", "gather", "network")})
        t["points"] = int(evaluate.sum())
        self._evaluations = info.get("evaluations", 1)
        ij = np.argwhere(full)[evaluate]
        for c in range(len(h.sums)):
            np.add.at(h.sums[c], (ij[:, 0], ij[:, 1]), vals[:, c])
        np.add.at(h.count, (ij[:, 0], ij[:, 1]), 1.0)
        np.add.at(h.depth, (ij[:, 0], ij[:, 1]), depth[evaluate])
        t["paths"] = 0.0
        if chosen.any():
            from ..pathtrace import point_query
            f_nn = vals[chosen[evaluate]]
            dm = frame.device_medium
            scene = SimpleNamespace(medium=frame.medium, light=frame.light, volume=None)
            path_seed = (self.seed * 0x9E3779B1 + index) % (1 << 32)
            with Stopwatch() as sw:
                if self.path_query is not None:
                    q = self.path_query(pts[chosen], -dirs[chosen], self.paths_per_query,
                                        path_seed)
                else:
                    kw = ({"device_medium": dm, "majorant_block": dm.block} if dm is not None
                          else {})
                    q = point_query(scene, pts[chosen], -dirs[chosen], self.paths_per_query,
                                    seed=path_seed, grid=frame.grid, runtime=frame.runtime, **kw)
            t["paths"] = sw.seconds
            C = len(h.sums)
            f_pt = q["Fms"][:, :C] if C == 3 else q["Fms"].mean(axis=1, keepdims=True)
            se2 = (q["Fms_se"][:, :C] if C == 3 else
                   q["Fms_se"].mean(axis=1, keepdims=True)) ** 2
            r = f_pt - f_nn
            jj, ii = np.argwhere(full)[chosen].T
            P = self.paths
            for c in range(C):
                for arr, v in ((P.s_r, r), (P.q_r, r * r), (P.s_pt, f_pt), (P.q_pt, f_pt * f_pt),
                               (P.e2, se2)):
                    np.add.at(arr[c], (jj, ii), v[:, c])
            np.add.at(P.n, (jj, ii), 1.0)
            np.add.at(P.paths, (jj, ii), float(self.paths_per_query))
        if not np.isfinite(h.sums).all() or not np.isfinite(self.paths.s_r).all():
            raise ClvolError("--ms progressive: a non-finite F_ms (network or paths)")
        return t

    @staticmethod
    def _nn_mean(h) -> np.ndarray:
        return _ratio(h.sums, np.broadcast_to(h.count, h.sums.shape))

    def table_now(self):
        """(table (1 + C, by, bx, 1) float32, estimate info) from what is accumulated."""
        h, P = self.history, self.paths
        m_nn = self._nn_mean(h)
        f, info = estimate(m_nn, P.n, P.s_r, P.q_r, self.estimator, self.radius,
                           s_pt=P.s_pt, q_pt=P.q_pt, e2=P.e2)
        t = h.table()
        t[1:, ..., 0] = np.where(h.count > 0, f, 0.0)
        return t, info

    def prepare(self, frame) -> None:
        self.info = {}
        h, fresh, moved = self._frame_history(frame)
        cam = frame.camera
        by, bx = h.count.shape
        builds = self.net.graded_builds
        times = {"light": 0.0, "gather": 0.0, "network": 0.0, "points": 0}

        def add(t):
            for k, v in t.items():
                times[k] = times.get(k, 0.0) + v

        rounds = 0
        first = fresh or moved or h.camera is None
        if first:
            # the first frame of a view: the network only (what a stochastic frame costs)
            self.paths = _Paths(len(h.sums), by, bx)
            self.rounds_done = 0
            add(self._round(frame, h, with_paths=False, moved=moved))
            h.camera = cam
            h.still = 0
        if not first or self.budget is not None or self.rounds is not None:
            # a still view refines: --time or --progressive-rounds after the first frame too
            # (one render, as clvol render makes), else one round per render (the viewer's)
            t0 = time.perf_counter()
            while True:
                add(self._round(frame, h, with_paths=True))
                rounds += 1
                if self.budget is None:
                    if rounds >= (self.rounds or 1):
                        break
                else:
                    spent = time.perf_counter() - t0
                    if spent + spent / rounds > self.budget or rounds >= MAX_ROUNDS:
                        break
            h.still += rounds
        self.rounds_done += rounds
        table, est = self.table_now()
        self.estimate_info = est
        self.refining = True             # a still view keeps refining (never idles)
        self.info = dict(times, evaluations=self._evaluations,
                         blocks=int((h.count > 0).sum()),
                         samples=int(h.count.max(initial=0)), rounds=rounds)
        self.table = frame.runtime.upload(table)
        if self.net.graded_builds != builds:
            frame.count("graded_transmittance")
        frame.count("ms_view_table")

    @classmethod
    def plan_for(cls, medium, camera, shortcuts: bool, options):
        options.get("progressive_rounds")
        options.get("time")
        return super().plan_for(medium, camera, shortcuts, options)

    @staticmethod
    def _simulated(block, knots, bx, by, channels) -> str:
        return (f"multiple scattering (network at the camera's view, refined by path-traced "
                f"point queries while still: {block}x{block}-pixel blocks, {bx}x{by} blocks, "
                f"{channels} channel(s))")

    def header(self) -> dict:
        h = super().header()
        h.pop("raymarch.view_samples", None)
        info = self.info or {}
        est = self.estimate_info or {}
        P = self.paths
        full = self.history.count > 0 if self.history is not None else None
        per_block = (P.paths[full] if P is not None and full is not None and full.any()
                     else np.zeros(1))
        err = est.get("error")
        err_nn = est.get("error_network")
        known = err is not None and err_nn is not None and full is not None and full.any()
        resolved = known and float(np.max(est.get("b2", 0.0))) > 10 * VAR_FLOOR
        h.update({
            "raymarch.progressive_estimator": self.estimator,
            "raymarch.progressive_rounds": self.rounds_done,
            "raymarch.progressive_rounds_this_render": info.get("rounds", 0),
            "raymarch.progressive_paths_per_query": self.paths_per_query,
            "raymarch.progressive_paths_per_block": (
                f"mean {per_block.mean():.1f}, min {per_block.min():.0f}, "
                f"max {per_block.max():.0f}"),
            "raymarch.progressive_error": (
                f"{100 * np.sqrt(np.mean(err[full] ** 2)):.2f}% of F_ms, estimated RMS over "
                f"blocks (network alone: {100 * np.sqrt(np.mean(err_nn[full] ** 2)):.2f}%)"
                if resolved else
                "not resolved yet (the paths do not yet separate the network's error from "
                "their own noise: the network's F_ms)" if known else
                "unknown (too few blocks with two path-traced points yet: the network's F_ms)"),
            "seconds.progressive_paths": round(info.get("paths", 0.0), 4),
        })
        if self.budget is not None:
            h["raymarch.progressive_time"] = self.budget
        return h
