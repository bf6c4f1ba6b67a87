"""Environment light for the ray marcher: the sky's single and multiple scattering as one
source field over the medium, read by cl/raymarch.cl (define ENV) at every march point.

Directions. The sphere is cut into K near-equal cells around a Fibonacci set of directions
w_i (solid angle Omega_i = 4 pi / K each). A constant sky L gives each cell the irradiance
E_i = L Omega_i; a lat-long map gives E_i = sum of L_texel Omega_texel over the texels whose
centre is nearest w_i (the map's integral is kept exactly: sum_i E_i = int L dw), and the
cell's solid angle Omega_i = the sum of those texels' (so a uniform map is a furnace too).

Transmittance (``EnvTransmittance``): for every w_i the exact light transmittance field
T_i(x) toward w_i (cl/transmittance.cl's sweep, optical depth accumulated along the light
rays) on a pyramid of ``resolution``^3 voxels over the medium's cube. It depends only on the
density, the density scale and the direction set: a new sky does not rebuild it.

Single scattering. In-scattered radiance per unit extinction toward the camera at x:

    S_c(x) = albedo_c sum_i E_i,c T_i(x) f_i(x),
    f_i(x) = f(w_i . u) / sum_j Omega_j f(w_j . u),   u = normalize(x - camera origin),

with f the scene's phase function with every lobe's g multiplied by (1 - 1/K), the mean
cosine of a cell of solid angle 4 pi / K (the HG lobe convolved with a lobe as wide as a
cell: HG convolved with HG(g_s) is HG(g g_s)). The normalisation makes sum_i Omega_i f_i = 1
exactly, so a cell-sized sampling of a sharp forward lobe neither gains nor loses energy.
u is the direction of the camera ray through x, so the field is exact in direction for every
pixel; an anisotropic phase therefore makes the field depend on the camera position (rebuilt
when it moves); an isotropic one (f_i = 1 / (4 pi)) does not.

Multiple scattering, by the network (the default wherever the network serves the sun; measured
in docs/raymarch.md "Environment light"). Light is additive, so the sky's multiple scattering
is the sum of the network's F_ms for each sky cell's direction, weighted by the cell's
irradiance:

    M_c(x) = albedo_c sum_j E_j,c F_ms,c(x, w_j, u),

over J cells of their own (``DEFAULT_ENV_MS_DIRECTIONS``; E_j from ``make_sky`` with J cells,
so a map's energy is kept exactly), u toward the camera: the network's queries at the field's
voxel centres within reach of the density (``SkyNetwork``), one network call per cell, the
graded transmittance toward every cell kept between camera moves.

Multiple scattering, the escape model (an approximation; the plan uses it where the network
does not run: an analytic sun source, a medium outside the network's domain, and the white
furnace, where it is exact). The sky light that does not reach x directly along w_i (the
fraction 1 - T_i) is taken to arrive at x after scattering instead, from the same direction,
diminished by a factor R:

    M_c(x) = albedo_c R_c(x) sum_i E_i,c (1 - T_i(x)) f_i(x).

In a white furnace (albedo 1, uniform sky) the exact radiance is L everywhere, so R = 1
there: single + multiple = albedo sum_i E_i f_i = L for any phase function (the furnace is
exact by construction). For albedo < 1, R comes from a one-number escape model: with
t_c(x) = sum_i E_i,c T_i(x) / sum_i E_i,c the fraction of the sky's irradiance that reaches x
unscattered, a photon is taken to reach the sky at each scattering with probability t, so
the light of all orders at x is the geometric series t sum_n (albedo (1 - t))^n, of which
orders >= 1 are t albedo (1 - t) / (1 - albedo (1 - t)); spread over the blocked fraction
1 - t this is

    R_c = (albedo_c t / (1 - albedo_c (1 - t)))^p,   p = MS_EXPONENT = 2

(1 at albedo 1 for any p; the denominator is 0 only for albedo 1 and t = 0, where the limit 1
is used). The plain series (p = 1) was measured too bright below albedo 1 (+50% on the cloud
at albedo 0.9: a photon scattered once is deeper than x on average, so it escapes less
often than t); p = 2 was fitted on the sky-only cloud at albedo 0.9 (48^3, density 64) and
checked at other albedos, densities and resolutions (docs/raymarch.md).

Background: a constant sky is the kernel's constant background; a map is looked up (nearest
texel, clvol/envmap.py) along every camera ray (``background_image``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..envmap import row_solid_angles, texel_directions
from ..errors import ClvolError
from .sphere import fibonacci_directions

DEFAULT_ENV_DIRECTIONS = 64
DEFAULT_ENV_RESOLUTION = 32
# Sky cells the network is evaluated for (docs/raymarch.md "Environment light": the error
# against the number of cells, bench/env_accuracy.py).
DEFAULT_ENV_MS_DIRECTIONS = 32
# How the sky's multiple scattering is found (the plan's ``env_ms``; --env-ms names the first
# two): the network's F_ms per sky cell, the escape model, or none (--max-order 1). Words of
# their own, not --ms source names.
ENV_MS_NETWORK, ENV_MS_ESCAPE, ENV_MS_NONE = "network", "escape", "none"
INV_4PI = 1.0 / (4.0 * math.pi)
# The escape model's R is raised to this power (fitted: docs/raymarch.md "Environment light").
MS_EXPONENT = 2.0


def sky_directions(k: int) -> np.ndarray:
    """(k, 3) float64 unit directions of a Fibonacci sphere (near-equal cells)."""
    if not (isinstance(k, (int, np.integer)) and 1 <= k <= 1024):
        raise ClvolError(f"environment directions = {k!r}: must be an integer from 1 to 1024")
    return fibonacci_directions(k)[:, [0, 2, 1]]      # the same lattice about +y (up)


def has_environment(light) -> bool:
    return light.environment is not None or getattr(light, "environment_map", None) is not None


def sky_is_uniform(light) -> bool:
    """A constant sky, or a map whose texels are all alike (its scale may be coloured)."""
    if light.environment is not None:
        return True
    t = light.environment_texels()
    return t is not None and bool(np.all(t.reshape(-1, 3) == t.reshape(-1, 3)[0]))


@dataclass(frozen=True)
class Sky:
    """The sky cut into cells: ``directions`` (K, 3), ``irradiance`` (K, C) E_i per cell
    (C = 1: in units of ``colour``; C = 3: RGB), ``colour`` (RGB, applied once per ray)."""
    directions: np.ndarray
    irradiance: np.ndarray
    colour: tuple
    channels: int
    solid_angles: np.ndarray     # (K,) Omega_i: 4 pi / K, or a map's texels' in cell i

    @property
    def total(self) -> np.ndarray:
        """(C,) sum_i E_i."""
        return self.irradiance.sum(axis=0)



def sky_key(light, k: int):
    """What the cells depend on (a cache key)."""
    m = getattr(light, "environment_map", None)
    if m is not None:
        return ("map", str(m), tuple(light.environment_scale), float(light.environment_rotation), k)
    return ("constant", tuple(light.environment), k)


def sky_channels(light, grey_albedo: bool) -> int:
    """The sky cells' colour planes (``make_sky``; the march's ENV_CHANNELS): 1 for a
    constant sky over a grey albedo, else 3."""
    return 1 if getattr(light, "environment_map", None) is None and grey_albedo else 3


def make_sky(light, k: int, grey_albedo: bool = True) -> Sky:
    """The cells of ``light``'s environment. A constant sky is grey (C = 1, coloured once per
    ray) when the albedo is grey too; otherwise (a map, or a coloured albedo, whose multiple
    scattering is not linear in the sky colour per channel) C = 3."""
    dirs = sky_directions(k)
    omega = 4.0 * math.pi / k
    m = getattr(light, "environment_map", None)
    if m is None:
        L = np.asarray(light.environment, np.float64)
        om = np.full(k, omega)
        if sky_channels(light, grey_albedo) == 1:
            return Sky(dirs, np.full((k, 1), omega), tuple(L), 1, om)
        return Sky(dirs, np.tile(L * omega, (k, 1)), (1.0, 1.0, 1.0), 3, om)
    rgb = np.asarray(light.environment_texels(), np.float64)
    h, w = rgb.shape[:2]
    td = texel_directions(h, w, light.environment_rotation).reshape(-1, 3)
    texel_omega = np.broadcast_to(row_solid_angles(h, w)[:, None], (h, w)).ravel()
    energy = (rgb * np.asarray(light.environment_scale, np.float64)).reshape(-1, 3) \
        * texel_omega[:, None]
    cell = np.empty(len(td), np.int64)
    for s in range(0, len(td), 65536):                    # nearest direction per texel
        cell[s:s + 65536] = np.argmax(td[s:s + 65536] @ dirs.T, axis=1)
    e = np.zeros((k, 3))
    np.add.at(e, cell, energy)
    om = np.bincount(cell, weights=texel_omega, minlength=k)   # sums to 4 pi
    return Sky(dirs, e, (1.0, 1.0, 1.0), 3, om)


def background_image(light, camera) -> np.ndarray:
    """(H, W, 3) float32 radiance of the map along the camera's pixel-centre rays."""
    from ..envmap import lookup
    d = camera.pixel_directions()
    return lookup(light.environment_texels(), light.environment_scale,
                  light.environment_rotation, d).astype(np.float32)


class EnvTransmittance:
    """T_i(x) toward each of ``k`` sky directions on a ``resolution``^3 pyramid over the
    medium's cube (float32 (K, n, n, n) on the host). Rebuilt when the density scale changes.
    ``device_medium``: the volume on the device; the pyramid is that medium's
    (``DeviceMedium.pyramid``, clvol/kernels/medium.py): no second copy of the density."""

    def __init__(self, grid, k: int, resolution: int, runtime, device_medium):
        self.grid, self.k, self.n, self.rt = grid, k, resolution, runtime
        self.dm = device_medium
        self.T = None
        self._scale = None
        self.builds = 0

    @property
    def pyramid(self):
        return self.dm.pyramid(self.n)

    def ensure(self, density_scale: float) -> bool:
        """Build the fields unless they are those of ``density_scale``; True when built."""
        if self.T is not None and self._scale == float(density_scale):
            return False
        from ..kernels.transmittance import light_transmittance
        pyr = self.pyramid
        dirs = sky_directions(self.k)
        T = np.empty((self.k,) + (self.n,) * 3, np.float32)
        for i, w in enumerate(dirs):
            T[i] = light_transmittance(pyr, density_scale, w)
        self.T, self._scale = T, float(density_scale)
        self.builds += 1
        return True


def phase_weights(points, origin, dirs, lobes, solid_angles) -> np.ndarray | None:
    """(K, P) float32 f_i at ``points`` (P, 3) seen from ``origin`` (the module doc: cell-
    widened lobes, normalised so sum_i Omega_i f_i = 1), or None for an isotropic phase."""
    if not lobes:
        return None
    om = np.asarray(solid_angles, np.float64)
    k = len(dirs)
    gs = 1.0 - 1.0 / k
    u = np.asarray(points, np.float64) - np.asarray(origin, np.float64)
    norm = np.linalg.norm(u, axis=1, keepdims=True)
    # A point at the camera itself sees every direction alike: any unit u will do there.
    u = np.where(norm > 0, u / np.where(norm > 0, norm, 1.0), np.array([0.0, 0.0, 1.0]))
    # float32 from here: the field is float32, and this runs per camera position.
    one_minus_mu = 1.0 - (dirs.astype(np.float32) @ u.T.astype(np.float32))   # (K, P)
    f = np.zeros_like(one_minus_mu)
    for g, wt in lobes:
        gg = g * gs
        ga = abs(gg)
        a = 1.0 - ga
        # 1 - mu' with mu' = sign(g) mu: 1 - mu, or 2 - (1 - mu) for a backward lobe.
        om_mu = one_minus_mu if gg >= 0 else 2.0 - one_minus_mu
        den = np.float32(a * a) + np.float32(2.0 * ga) * om_mu   # >= a^2 > 0 for |g| < 1
        f += np.float32(wt * a * (1.0 + ga) * INV_4PI) / (den * np.sqrt(den))
    # HG > 0 everywhere for |g| < 1 and the Omega_i sum to 4 pi, so the sum is > 0.
    return f * (1.0 / (om.astype(np.float32) @ f))[None, :]


def voxel_centres(cube_min, cube_size, n) -> np.ndarray:
    """(n^3, 3) world positions of a cube's voxel centres, [z][y][x] order."""
    c = (np.arange(n) + 0.5) * (cube_size / n)
    z, y, x = np.meshgrid(c, c, c, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=-1) + np.asarray(cube_min)


def source_field(T, sky: Sky, albedo, lobes, cube_min, cube_size, origin,
                 ms: np.ndarray | None = None, escape: bool = True) -> np.ndarray:
    """(2 C, n, n, n) float32: the single (planes 0..C-1) and multiple (C..2C-1) in-scattered
    radiance per unit extinction (module doc), from T (K, n, n, n). ``ms``: the network's
    (C, n^3) sum_j E_j F_ms (``SkyNetwork.field``) for the multiple planes instead of the escape
    model; ``escape=False`` without it: no multiple scattering (--max-order 1)."""
    k, n = T.shape[0], T.shape[1]
    C = sky.channels
    alb = np.asarray(albedo, np.float64)
    alb = np.full(C, alb[0]) if C == 1 else alb
    Tf = T.reshape(k, -1)
    E = sky.irradiance                                          # (K, C)
    fw = phase_weights(voxel_centres(cube_min, cube_size, n), origin, sky.directions, lobes,
                       sky.solid_angles)
    out = np.empty((2 * C, n ** 3), np.float32)
    reach = E.T.astype(np.float32) @ Tf                        # (C, P): sum_i E_i T_i
    total = sky.total
    if fw is None:
        single = reach * np.float32(INV_4PI)
        sky_f = np.repeat((total * INV_4PI)[:, None], Tf.shape[1], axis=1)
    else:
        E32 = E.T.astype(np.float32)
        single = E32 @ (fw * Tf)                               # (C, P): sum_i E_i f_i T_i
        sky_f = E32 @ fw                                       # (C, P): sum_i E_i f_i
    for c in range(C):
        out[c] = alb[c] * single[c]
        if ms is not None or not escape:
            out[C + c] = alb[c] * ms[c] if ms is not None else 0.0
            continue
        if not total[c] > 0:
            out[C + c] = 0.0
            continue
        t = np.clip(reach[c].astype(np.float64) / total[c], 0.0, 1.0)
        den = 1.0 - alb[c] * (1.0 - t)
        # den = 0 only at albedo 1 and t = 0, where R's limit is 1.
        R = np.where(den > 0, alb[c] * t / np.where(den > 0, den, 1.0), 1.0) ** MS_EXPONENT
        blocked = np.maximum(sky_f[c].astype(np.float64) - single[c], 0.0)  # sum E f (1 - T)
        out[C + c] = alb[c] * R * blocked
    return out.reshape((2 * C,) + (n,) * 3)


class SkyNetwork:
    """The network's share of the sky (the module doc): one NetworkSource (weights and the
    pyramid of the medium's DeviceMedium) that keeps the graded transmittance toward each of
    the sky's cells, and the field voxels it evaluates (those within reach of the density).

    Each cell's F_ms is kept with the camera position it was evaluated for: a new sky (colour,
    map, scale, rotation) re-weights them without a network call, since the J directions are
    fixed; a camera move makes them stale. ``per_frame`` > 0 refreshes at most that many stale
    cells per call, the oldest first (MRPNN's few directions per frame, accumulated); the
    others keep their last positions' values and ``pending`` counts them."""

    def __init__(self, source, weights, grid, medium, runtime, device_medium):
        # ``source``: the frame's network source class (clvol/render/ms/), which makes the
        # evaluator and owns the active-point rule
        self.source = source
        self.net = source.sky_evaluator(weights, grid, medium, runtime, device_medium)
        self._active = None
        self._cells = None        # (key, F (J, P, Cf) float32, origin per cell, order)
        self.pending = 0          # stale cells left after the last call
        self.evaluated = 0        # cells evaluated by the last call
        self.points = 0           # field voxels the network is queried at

    def active(self, cube_min, cube_size, n, reach) -> np.ndarray:
        """The field voxels the march can read where there is density (the network lattice's
        rule, the source's ``active_points``, over the field's cube); all of them for
        ``reach`` None (the plan's rule with shortcuts off)."""
        key = (tuple(cube_min), float(cube_size), n, reach)
        if reach is None:                   # shortcuts off: every voxel
            return np.ones(n ** 3, bool)
        if self._active is None or self._active[0] != key:
            lo = np.asarray(cube_min, np.float64)
            self._active = (key, self.source.active_points(self.net.grid, n, reach,
                                                           box=(lo, lo + cube_size)))
        return self._active[1]

    def field(self, cells: Sky, medium, cube_min, cube_size, n, origin, reach,
              per_frame: int = 0) -> np.ndarray:
        """(C, n^3) float32 sum_j E_j,c F_ms,c(x, w_j, toward ``origin``) at the field's voxel
        centres (0 at voxels out of reach), refreshing the stale cells (all, or ``per_frame``)."""
        act = np.flatnonzero(self.active(cube_min, cube_size, n, reach))
        self.points = len(act)
        J = len(cells.directions)
        self.net.graded_keep = J
        key = (cells.directions.tobytes(), medium.density_scale, tuple(medium.albedo),
               medium.phase, (tuple(cube_min), float(cube_size), n, reach))
        if self._cells is None or self._cells[0] != key:
            self._cells = (key, [None] * J, [None] * J, list(range(J)))
        _, F, at, order = self._cells
        origin = tuple(float(v) for v in origin)
        # a black cell adds nothing: it is evaluated once the sky lights it
        stale = [j for j in order if at[j] != origin and np.any(cells.irradiance[j] > 0)]
        todo = stale if per_frame <= 0 else stale[:per_frame]
        pts = voxel_centres(cube_min, cube_size, n) if todo else None
        for j in todo:
            F[j] = per_cell_f_ms(self.net, cells.directions[j], medium, pts, act, origin)
            at[j] = origin
            order.remove(j)
            order.append(j)                                  # now the newest
        self.evaluated, self.pending = len(todo), len(stale) - len(todo)
        out = np.zeros((cells.channels, n ** 3), np.float64)
        for j in range(J):
            if F[j] is not None and np.any(cells.irradiance[j] > 0):
                out[:, act] += cells.irradiance[j][:, None] * F[j].T
        return out.astype(np.float32)


def per_cell_f_ms(net, direction, medium, points, active, origin) -> np.ndarray:
    """(len(active), Cf) float64 F_ms at ``points[active]`` for a light toward
    ``direction``, toward ``origin`` (Cf = 1 for a grey medium, else 3)."""
    from .ms.lattice import toward
    pts = np.asarray(points, np.float64)[active]
    F, _ = net.evaluate(pts, toward(origin, pts), direction, medium)
    F = np.asarray(F, np.float64)
    return F[:, None] if F.ndim == 1 else F
