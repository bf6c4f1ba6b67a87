"""NumPy twin of cl/pathtrace.cl: the same estimator, one path at a time, in float64.

Plain on purpose: a path is a Python loop over events; the medium uses one *global*
majorant (the kernel's majorant grid is an optimisation the tests hold against this).
Uniforms come from reference.rng.uniform4 in the kernel's order, so with the kernel built
on a global majorant (majorant block >= grid size) both follow the same path decisions up
to float rounding (kernel float32, twin float64). See cl/pathtrace.cl for the estimator,
the conventions (light toward l, omega toward the camera, cosines between propagation
directions) and the draw order; per-path rows use the kernel's layout:

    (background rgb, order-1 rgb, orders>=2 rgb, vertices, tracking steps, truncated)

and, with emission (``Params.emission``, kernel define PT_EMISSION), two more RGB triples:
the emission seen unscattered and the emission scattered at least once. The medium emits
sigma_a Le, sigma_a = sigma_t (1 - albedo); at every real collision x the path adds
beta (1 - albedo) Le(x) before beta takes the albedo (a collision estimator: collisions
have density sigma_t T along a flight, so the expectation is int T sigma_a Le dt). Le is
em_colour times the planes (C, ez, ey, ex) over em_min .. em_max (trilinear between voxel
centres, clamped; 0 outside that box).

Environment maps (cl/pathtrace.cl PT_ENVMAP): the twin builds its own sampling tables
(``EnvMap``, float64) from the texels, scale and rotation, by the convention stated there
and in docs/conventions.md; nothing of clvol/envmap.py is imported.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from reference.grid import box_intersect, camera_rays, grid_density
from reference.phase import phase_eval, phase_sample
from reference.rng import uniform4

RR_START = 8
MAX_VERTICES = 100_000
T_RR = 0.1
PT_OUT = 12
# Per-order rows: exponents 1..31 one bin each, then 8 equal bins per octave up to 2^17 - 1.
ORDER_EXACT, ORDER_SUB, ORDER_TOP_OCTAVE = 32, 8, 16
ORDER_BINS = ORDER_EXACT - 1 + (ORDER_TOP_OCTAVE + 1 - 5) * ORDER_SUB


def order_bin(e: int) -> int:
    """Bin of albedo exponent e >= 1 (the number of real collisions after the query point)."""
    if e < ORDER_EXACT:
        return e - 1
    o = e.bit_length() - 1
    width = (1 << o) // ORDER_SUB
    return min(ORDER_EXACT - 1 + (o - 5) * ORDER_SUB + (e - (1 << o)) // width, ORDER_BINS - 1)


@dataclass
class Params:
    """The medium and lights as the kernel sees them: ``medium``, the optical properties read
    by name (density_scale, RGB albedo, phase.lobes each with .g and .weight), unpacked here
    into ``density_scale``, ``albedo`` and ``lobes`` ((g, weight) pairs); ``light``, the sun
    read by name (direction toward it, RGB irradiance), unpacked into ``light_dir`` and
    ``sun``; ``environment`` None = none, ``max_order`` 0 = unlimited."""
    density: np.ndarray
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    medium: object
    light: object
    environment: tuple | None = None
    max_order: int = 0
    rr_start: int = RR_START
    max_vertices: int = MAX_VERTICES
    env_map: np.ndarray | None = None
    env_scale: tuple = (1.0, 1.0, 1.0)
    env_rotation: float = 0.0      # degrees about +y
    emission: np.ndarray | None = None     # (C, ez, ey, ex), C = 1 or 3
    em_min: tuple = (0.0, 0.0, 0.0)
    em_max: tuple = (1.0, 1.0, 1.0)
    em_colour: tuple = (1.0, 1.0, 1.0)

    def __post_init__(self):
        self.density = np.asarray(self.density, np.float64)
        self.bbox_min = np.asarray(self.bbox_min, np.float64)
        self.bbox_max = np.asarray(self.bbox_max, np.float64)
        self.density_scale = float(self.medium.density_scale)
        self.albedo = np.asarray(self.medium.albedo, np.float64)
        self.sun = np.asarray(self.light.irradiance, np.float64)
        self.light_dir = np.asarray(self.light.direction, np.float64)
        self.sigma_maj = float(self.density.max()) * self.density_scale
        self.lobes = [(lo.g, lo.weight) for lo in self.medium.phase.lobes]
        self.env = (None if self.environment is None or max(self.environment) <= 0
                    else np.asarray(self.environment, np.float64))
        if self.emission is not None:
            self.emission = np.asarray(self.emission, np.float64)
            self.em_min = np.asarray(self.em_min, np.float64)
            self.em_max = np.asarray(self.em_max, np.float64)
            self.em_colour = np.asarray(self.em_colour, np.float64)
        self.envmap = None
        if self.env_map is not None:
            em = EnvMap(self.env_map, self.env_scale, self.env_rotation)
            self.envmap = em if em.total > 0 else None   # a black map: no light


LUMA = np.array([0.2126, 0.7152, 0.0722])   # Rec. 709


class EnvMap:
    """A lat-long map: row i covers theta = acos(y) in [i pi/H, (i+1) pi/H] from +y, column
    j covers phi_map in [j 2pi/W, (j+1) 2pi/W], phi_map = atan2(-z, x) - rotation. Texel
    (i, j) is drawn with probability lum_ij Omega_i / total (Omega_i its solid angle), then
    a direction uniform in cos(theta) and phi inside it: pdf(d) = lum(texel(d)) / total."""

    def __init__(self, texels, scale, rotation_deg):
        a = np.asarray(texels, np.float64) * np.asarray(scale, np.float64)
        self.rgb = a
        self.h, self.w = a.shape[:2]
        self.rot = math.radians(rotation_deg)
        self.lum = a @ LUMA
        c = np.cos(np.pi * np.arange(self.h + 1) / self.h)
        self.cos_edges = c
        weight = self.lum * ((2 * np.pi / self.w) * (c[:-1] - c[1:]))[:, None]
        row = weight.sum(axis=1)
        self.total = float(row.sum())
        self.marg = np.concatenate([[0.0], np.cumsum(row)]) / max(self.total, 1e-300)
        self.marg[-1] = 1.0
        self.cond = np.zeros((self.h, self.w + 1))
        for i in range(self.h):
            self.cond[i, 1:] = (np.cumsum(weight[i]) / row[i] if row[i] > 0
                                else np.arange(1, self.w + 1) / self.w)
            self.cond[i, -1] = 1.0

    @staticmethod
    def _find(cdf, u: float) -> int:
        """Largest i < len(cdf) - 1 with cdf[i] <= u."""
        return min(int(np.searchsorted(cdf, u, side="right")) - 1, len(cdf) - 2)

    def sample(self, u0: float, u1: float):
        """(direction, rgb, pdf per solid angle) for uniforms u0 (row), u1 (column)."""
        i = self._find(self.marg, u0)
        fv = (u0 - self.marg[i]) / (self.marg[i + 1] - self.marg[i])
        c = self.cond[i]
        j = self._find(c, u1)
        fu = (u1 - c[j]) / (c[j + 1] - c[j])
        ct = self.cos_edges[i] + fv * (self.cos_edges[i + 1] - self.cos_edges[i])
        st = math.sqrt(max(0.0, 1.0 - ct * ct))
        phi = 2 * math.pi * (j + fu) / self.w + self.rot
        d = np.array([st * math.cos(phi), ct, -st * math.sin(phi)])
        return d, self.rgb[i, j], self.lum[i, j] / self.total

    def lookup(self, d):
        """(rgb, pdf) of the texel along unit direction d."""
        u = ((math.atan2(-d[2], d[0]) - self.rot) / (2 * math.pi)) % 1.0
        v = math.acos(min(1.0, max(-1.0, d[1]))) / math.pi
        j, i = min(int(u * self.w), self.w - 1), min(int(v * self.h), self.h - 1)
        return self.rgb[i, j], self.lum[i, j] / self.total


class Stream:
    """The kernel's pt_rng: uniforms of (seed, stream, sample), 4 per block, in order."""
    CHUNK = 32  # blocks fetched per uniform4 call (speed only; values are per block)

    def __init__(self, seed: int, stream: int, sample: int):
        self.seed, self.stream, self.sample = seed, stream, sample
        self._u = np.empty(0)
        self._i = 0

    def next(self) -> float:
        if self._i == len(self._u):
            first = len(self._u) // 4
            blocks = np.arange(first, first + self.CHUNK, dtype=np.uint32)
            new = uniform4(self.seed, self.stream, self.sample, blocks).astype(np.float64)
            self._u = np.concatenate([self._u, new.ravel()])
        u = float(self._u[self._i])
        self._i += 1
        return u


class Counters:
    def __init__(self):
        self.vertices = 0
        self.steps = 0
        self.truncated = 0


def sigma(P: Params, p) -> float:
    return float(grid_density(P.density, P.bbox_min, P.bbox_max, np.asarray(p)[None])[0]) \
        * P.density_scale


def emitted(P: Params, p) -> np.ndarray:
    """(1 - albedo) Le(p): what a collision at p with throughput 1 adds (RGB)."""
    le = np.array([float(grid_density(P.emission[c], P.em_min, P.em_max, np.asarray(p)[None])[0])
                   for c in range(P.emission.shape[0])])
    return (1.0 - P.albedo) * P.em_colour * le


def tentative_collisions(P: Params, x, w, rs: Stream, c: Counters):
    """The tentative collision points along x + t w at the global majorant's rate (one
    exponential draw each, counted in c.steps), until the ray leaves the box. Delta and ratio
    tracking draw their own numbers between two points."""
    t0, t1 = box_intersect(x[None], w[None], P.bbox_min, P.bbox_max, 0.0)
    t0, t1 = float(t0[0]), float(t1[0])
    if not t0 <= t1:
        return
    t, sm = t0, P.sigma_maj
    while True:
        tau = -math.log(1.0 - rs.next())
        if not (sm > 0 and sm * (t1 - t) >= tau):
            return
        t = min(t + tau / sm, t1)
        c.steps += 1
        yield x + t * w


def free_flight(P: Params, x, w, rs: Stream, c: Counters):
    """Delta tracking with the global majorant: the real collision point or None."""
    for p in tentative_collisions(P, x, w, rs, c):
        if rs.next() * P.sigma_maj < sigma(P, p):
            return p
    return None


def transmittance(P: Params, x, w, rs: Stream, c: Counters) -> float:
    """Ratio tracking with roulette below T_RR (survive with probability T / T_RR)."""
    T = 1.0
    for p in tentative_collisions(P, x, w, rs, c):
        T *= max(0.0, 1.0 - sigma(P, p) / P.sigma_maj)
        if T < T_RR:
            if rs.next() * T_RR >= T:
                return 0.0
            T = T_RR
    return T


def walk(P: Params, x, w, beta, k: int, rs: Stream, c: Counters, single_only=False,
         orders=None, emit=None):
    """Continue a path at vertex k; returns (order-1 rgb, orders>=2 rgb). ``orders``: an
    array [2][ORDER_BINS] that receives each sun NEE of vertex k >= 2 (channel 0) in bin
    order_bin(k - 1), and its value times k - 1 in the second row. ``emit``: an RGB array
    that receives the emission of the later collisions (with P.emission)."""
    l1, lms = np.zeros(3), np.zeros(3)
    beta = np.asarray(beta, np.float64)
    em = P.envmap

    def add(contrib):
        nonlocal l1, lms
        if k == 1:
            l1 = l1 + contrib
        else:
            lms = lms + contrib
    while True:
        if beta.max() <= 0:
            break
        c.vertices += 1
        if P.sun.max() > 0:
            f = float(phase_eval(np.array(np.dot(P.light_dir, w)), P.lobes))
            T = transmittance(P, x, P.light_dir, rs, c)
            contrib = beta * P.sun * (f * T)
            if k == 1:
                l1 += contrib
            else:
                lms += contrib
                if orders is not None:
                    b = order_bin(k - 1)
                    orders[0, b] += contrib[0]
                    orders[1, b] += contrib[0] * (k - 1)
        last = single_only or k == P.max_order
        if em is not None:
            # Map NEE, power heuristic against phase sampling (weight 1 at the last vertex).
            d, rgb, pe = em.sample(rs.next(), rs.next())
            if pe > 0:
                f = float(phase_eval(np.array(np.dot(d, w)), P.lobes))
                s = f / pe if last else f * pe / (pe * pe + f * f)
                T = transmittance(P, x, d, rs, c)
                add(beta * rgb * (s * T))
        if last:
            break
        if k >= P.max_vertices:
            c.truncated = 1
            break
        if k >= P.rr_start:
            q = min(1.0, beta.max())
            if rs.next() >= q:
                break
            beta = beta / q
        u = np.array([rs.next(), rs.next(), rs.next()])
        w_old = w
        w = phase_sample(w[None], P.lobes, u[None])[0]
        hit = free_flight(P, x, w, rs, c)
        if hit is None:
            if P.env is not None:
                add(beta * P.env)
            if em is not None:
                rgb, pe = em.lookup(w)
                pf = float(phase_eval(np.array(np.dot(w_old, w)), P.lobes))
                den = pf * pf + pe * pe
                add(beta * rgb * (pf * pf / den if den > 0 else 0.0))
            break
        x = hit
        if emit is not None:
            emit += beta * emitted(P, x)
        beta = beta * P.albedo
        k += 1
    return l1, lms


def _row(bg, l1, lms, c: Counters, emission=None) -> np.ndarray:
    row = np.concatenate([bg, l1, lms, [c.vertices, c.steps, c.truncated]])
    return row if emission is None else np.concatenate([row, *emission])


def render_paths(P: Params, camera, seed: int, samples, pixels=None) -> np.ndarray:
    """Rows (len(samples), len(pixels), PT_OUT), like PathTracer.render_batch.
    ``camera`` is a clvol.scene.Camera; ``pixels`` flat indices (default: all)."""
    w_img, h_img = camera.width, camera.height
    pixels = np.arange(w_img * h_img) if pixels is None else np.asarray(pixels)
    fwd, right, up = camera.basis()
    tan_half = math.tan(math.radians(camera.fov_y) / 2)
    origin = np.asarray(camera.origin, np.float64)
    out = np.zeros((len(samples), len(pixels), PT_OUT + (6 if P.emission is not None else 0)))
    for si, s in enumerate(samples):
        # The first two uniforms of each pixel's stream jitter its ray (kernel: col + u).
        u = uniform4(seed, np.arange(w_img * h_img, dtype=np.uint64), s, 0).astype(np.float64)
        jitter = u[:, :2].reshape(h_img, w_img, 2) - 0.5
        dirs = camera_rays(fwd, right, up, tan_half, w_img, h_img, jitter).reshape(-1, 3)
        for pi, pix in enumerate(pixels):
            rs = Stream(seed, int(pix), int(s))
            rs.next(), rs.next()
            c = Counters()
            w = dirs[pix]
            hit = free_flight(P, origin, w, rs, c)
            bg = np.zeros(3)
            l1 = lms = np.zeros(3)
            em = None if P.emission is None else (np.zeros(3), np.zeros(3))
            if hit is None:
                if P.env is not None:
                    bg = P.env.copy()
                if P.envmap is not None:
                    bg = P.envmap.lookup(w)[0].copy()
            else:
                if em is not None:
                    em[0][:] = emitted(P, hit)
                l1, lms = walk(P, hit, w, P.albedo, 1, rs, c,
                               emit=None if em is None else em[1])
            out[si, pi] = _row(bg, l1, lms, c, em)
    return out


def query_paths(P: Params, points, omegas, seed: int, samples, orders: bool = False) -> np.ndarray:
    """Rows (len(samples), n_queries, PT_OUT) like PathTracer.query_batch: the walk starts
    at p as vertex 1 with w = -omega and beta = 1 (F for a sun of irradiance P.sun). With
    ``orders``, each row is followed by its ORDER_BINS per-order sums and first moments."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    omegas = np.asarray(omegas, np.float64).reshape(-1, 3)
    width = PT_OUT + (2 * ORDER_BINS if orders else 0)
    out = np.zeros((len(samples), len(points), width))
    for si, s in enumerate(samples):
        for q in range(len(points)):
            rs = Stream(seed, q, int(s))
            c = Counters()
            bins = np.zeros((2, ORDER_BINS)) if orders else None
            l1, lms = walk(P, points[q], -omegas[q], np.ones(3), 1, rs, c, orders=bins)
            out[si, q, :PT_OUT] = _row(np.zeros(3), l1, lms, c)
            if orders:
                out[si, q, PT_OUT:] = bins.ravel()
    return out


def chandrasekhar_h(albedo: float, mu, n_nodes: int = 256, tol: float = 1e-13):
    """Chandrasekhar's H function for isotropic scattering with single-scattering albedo a,
    from  1/H(mu) = sqrt(1 - a) + (a/2) int_0^1 mu' H(mu') / (mu + mu') dmu'  (the form
    that converges by plain iteration), Gauss-Legendre on [0, 1], evaluated at ``mu`` by
    the same formula (Nystrom). Theory for tests: a semi-infinite medium lit at incidence
    cosine mu0 by irradiance E reflects L(mu) = E a mu0 H(mu) H(mu0) / (4 pi (mu + mu0)).
    0 <= a < 1 (at a = 1 this form has no sqrt(1 - a) anchor and plain iteration stalls).
    """
    if not 0.0 <= albedo < 1.0:
        raise ValueError(f"chandrasekhar_h: albedo {albedo} must be in [0, 1)")
    x, wq = np.polynomial.legendre.leggauss(n_nodes)
    x, wq = 0.5 * (x + 1.0), 0.5 * wq
    h = np.ones_like(x)
    s = math.sqrt(1.0 - albedo)
    kernel = 0.5 * albedo * (wq * x)[None, :] / (x[:, None] + x[None, :])
    for _ in range(100_000):
        new = 1.0 / (s + kernel @ h)
        if np.max(np.abs(new - h)) < tol:
            h = new
            break
        h = new
    mu = np.atleast_1d(np.asarray(mu, np.float64))
    hm = 1.0 / (s + 0.5 * albedo * ((wq * x * h)[None, :] / (mu[:, None] + x[None, :])).sum(1))
    return hm
