"""Single scattering of the path tracer against closed forms, at a precision that sees a 1%
extinction bias on shadow rays.

The path tracer's twin (reference/pathtrace.py) replays it path by path, so a misunderstanding
copied into both passes; the theory tests outside the twin were too noisy to see a 1-2% bias
in the shadow-ray extinction. Here ``point_query(max_order=1)`` (F1 = f(dot(-l, omega)) T(p ->
sun), docs/pathtrace.md: grey, ratio-tracked T, the albedo of p is *not* included, as F
excludes sigma_s(p)) is compared with

1. a homogeneous box: T = exp(-sigma_t d), d the distance from p to the box along l (a slab
   test here; for l = +z simply z_max - p_z);
2. a heterogeneous box whose density is a linear ramp in z at the voxel centres: trilinear
   interpolation is then exactly that ramp between the first and last centres and constant
   (clamped) beyond, so the optical depth along p + t l is the exact integral of a piecewise
   linear function of z (trapezoids on its breakpoints), over (z_exit - p_z) / l_z.

The phase factor f is HG from its textbook formula. Each point gets 2^20 paths; the estimate
must lie within 4 of its standard errors (sample variance over the paths) of the closed form.
With a homogeneous majorant the ratio-tracking estimate is 0 or 1, so its relative standard
error is sqrt((1 - T) / (T n)): 0.09-0.25% here. A 1% bias in the shadow-ray extinction moves
F1 by a factor e^(-0.01 tau), i.e. by 0.6-2% at these optical depths (tau 0.6-2), 7-10
standard errors per point (measured; asserted below as the test's power: the expected shift
pooled over the six points, sum / sqrt(6), must exceed 8 standard errors; measured 19-23).
Measured z of the estimates: within +-1.7 (pooled within +-1.1).
"""
import numpy as np
import pytest

from clvol.render.pathtrace import point_query
from clvol.scene import Camera, Light, Medium, Phase, Scene, VolumeSpec
from clvol.volume.grid import DensityGrid

N_PATHS = 1 << 20
G = 0.6
Z_LIMIT = 4.0
BOX_MIN, BOX_MAX = np.array([-0.5, -0.5, -0.5]), np.array([0.5, 0.5, 0.5])


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def hg(mu, g=G):
    return (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * np.asarray(mu)) ** 1.5)


def scene(light, density_scale):
    return Scene(path=None, volume=VolumeSpec(file=None, generator=None),
                 medium=Medium(density_scale, (0.9, 0.8, 0.7), Phase.hg(G)),
                 light=Light(tuple(unit(light))),
                 camera=Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 30.0, 4, 4))


def exit_distance(p, l):
    """Distance from interior points p (N, 3) along unit l to the box boundary."""
    with np.errstate(divide="ignore"):
        t = np.where(l > 0, (BOX_MAX - p) / l, np.where(l < 0, (BOX_MIN - p) / l, np.inf))
    return t.min(axis=1)


POINTS = np.array([[0.0, 0.0, 0.0], [0.1, -0.2, -0.3], [-0.3, 0.3, 0.2], [0.2, 0.1, -0.45],
                   [-0.05, 0.4, -0.2], [0.35, -0.35, 0.05]])
OMEGAS = unit([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.2, -0.3, 1.0], [0.6, 0.0, 0.8],
               [-0.5, -0.5, -0.7], [0.0, 0.0, -1.0]])


def check(name, est, se, want):
    z = (est - want) / se
    msg = "; ".join(f"{name} point {i}: F1 {e:.6g} vs {w:.6g} (z = {zz:+.1f})"
                    for i, (e, w, zz) in enumerate(zip(est, want, z)))
    assert np.all(np.abs(z) < Z_LIMIT), msg
    return z


@pytest.mark.parametrize("light", [(0.0, 0.0, 1.0), (0.3, -0.45, 0.85)], ids=["axis+z", "oblique"])
def test_single_scattering_homogeneous_box(light):
    sigma = 2.0
    sc = scene(light, sigma)
    l = np.asarray(sc.light.direction)
    grid = DensityGrid(density=np.ones((8, 8, 8), np.float32), bbox_min=BOX_MIN, bbox_max=BOX_MAX)
    out = point_query(sc, POINTS, OMEGAS, N_PATHS, seed=7, max_order=1, grid=grid)
    assert out["truncated"] == 0
    d = exit_distance(POINTS, l)
    if l[2] == 1.0:
        np.testing.assert_allclose(d, 0.5 - POINTS[:, 2], rtol=0, atol=1e-15)
    tau = sigma * d
    assert tau.min() > 0.5 and tau.max() < 2.6
    want = hg(-(OMEGAS @ l)) * np.exp(-tau)
    f1, se = out["F1"], out["F1_se"]
    np.testing.assert_array_equal(f1[:, 0], f1[:, 1])        # grey: no albedo in F1
    np.testing.assert_array_equal(f1[:, 0], f1[:, 2])
    z = check("homogeneous", f1[:, 0], se[:, 0], want)
    # the precision the power below relies on (binary ratio-tracking estimate: 0.09-0.25%)
    assert np.all(se[:, 0] < 3e-3 * f1[:, 0])
    # Power: a 1% extinction bias would shift F1 by want (1 - e^(-0.01 tau)); pooled over the
    # points that is far beyond the allowance (an expected pooled z of 8+).
    shift = want * -np.expm1(-0.01 * tau) / se[:, 0]
    assert shift.sum() / np.sqrt(len(shift)) > 8.0
    assert abs(z.sum() / np.sqrt(len(z))) < Z_LIMIT


def ramp_optical_depth(p, l, zc, rho, density_scale):
    """Exact optical depth from p along unit l to the box, for a density that is the linear
    interpolation of rho at centres zc in z and constant beyond them (clamped)."""
    d = exit_distance(p, l)
    out = np.empty(len(p))
    for i, (pz, di) in enumerate(zip(p[:, 2], d)):
        z0, z1 = sorted((pz, pz + di * l[2]))
        br = np.unique(np.clip(np.concatenate([[z0, z1], zc]), z0, z1))
        val = np.interp(br, zc, rho)                      # clamps outside [zc0, zc-1] too
        integral_z = np.sum(0.5 * (val[1:] + val[:-1]) * np.diff(br))
        out[i] = density_scale * integral_z / abs(l[2])
    return out


def test_ratio_tracking_linear_ramp():
    """Heterogeneous field (density 0.2 .. 2.0 along z, constant in x and y), default majorant
    grid (blocks of 8 voxels: the majorant is above the density, so ratio tracking really
    multiplies ratios): F1 / f = T within 4 standard errors of exp(-closed-form tau)."""
    n = 16
    zc = BOX_MIN[2] + (np.arange(n) + 0.5) * (BOX_MAX[2] - BOX_MIN[2]) / n
    rho = 0.2 + 1.8 * (np.arange(n) + 0.5) / n
    dens = np.broadcast_to(rho[:, None, None], (n, n, n)).astype(np.float32)
    scale = 1.5
    sc = scene((0.25, 0.2, 0.95), scale)
    l = np.asarray(sc.light.direction)
    grid = DensityGrid(density=np.ascontiguousarray(dens), bbox_min=BOX_MIN, bbox_max=BOX_MAX)
    out = point_query(sc, POINTS, OMEGAS, N_PATHS, seed=8, max_order=1, grid=grid)
    tau = ramp_optical_depth(POINTS, l, zc, rho.astype(np.float32).astype(np.float64), scale)
    assert tau.min() > 0.3 and tau.max() < 3.0
    want = hg(-(OMEGAS @ l)) * np.exp(-tau)
    z = check("ramp", out["F1"][:, 0], out["F1_se"][:, 0], want)
    assert abs(z.sum() / np.sqrt(len(z))) < Z_LIMIT
    shift = want * -np.expm1(-0.01 * tau) / out["F1_se"][:, 0]
    assert shift.sum() / np.sqrt(len(shift)) > 8.0
