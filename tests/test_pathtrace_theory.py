"""The path tracer against theory: Chandrasekhar's semi-infinite slab (multiple scattering)
and deterministic quadrature of single scattering in a thin homogeneous box.

Tolerances: z = |estimate - theory| / standard error < 4 for image means (the SE is the
sample standard deviation over >= 2^16 paths / sqrt(n); at most 1e-4 false-alarm chance per
comparison under the normal approximation), < 4.5 per pixel where a whole image is compared
(36 pixels x 3 channels: Bonferroni). The theory side is exact to < 1e-6 relative (H
function to 1e-11, quadrature with 8 x 16 Gauss nodes per ray and 8 x 8 per pixel), and
the finite slab (40 mean free paths deep and wide, camera footprint 0.02 mfp) differs from
the semi-infinite medium by far less than the ~0.4% standard errors.
"""
import math

import numpy as np
import pytest

from clvol.kernels.pathtrace import ROW_L1, ROW_LMS, ROW_VERTICES, PathMedium, PathTracer
from clvol.scene import Camera
from media import light_of, medium_of
from reference.grid import box_intersect
from reference.pathtrace import chandrasekhar_h
from reference.phase import phase_eval


@pytest.mark.parametrize("a", [0.3, 0.8, 0.95, 0.999])
def test_h_function_zeroth_moment(a):
    """int_0^1 H(mu) dmu = (2/a)(1 - sqrt(1 - a)) (Chandrasekhar, Radiative Transfer, ch. V)."""
    x, w = np.polynomial.legendre.leggauss(200)
    x, w = 0.5 * (x + 1), 0.5 * w
    assert np.sum(w * chandrasekhar_h(a, x)) == pytest.approx(2 / a * (1 - math.sqrt(1 - a)), rel=1e-9)


def test_h_function_limits():
    assert chandrasekhar_h(1e-9, [0.0, 0.5, 1.0]) == pytest.approx(1.0, abs=1e-8)
    h = chandrasekhar_h(0.9, np.linspace(0, 1, 11))
    assert h[0] == pytest.approx(1.0) and np.all(np.diff(h) > 0)  # H(0) = 1, increasing


# (albedo, mu = view cosine, mu0 = sun cosine, view azimuth relative to the sun plane)
SLAB_CASES = [(0.5, 1.0, 1.0, 0.0), (0.9, 0.5, 0.8, 1.0), (0.99, 0.7, 0.4, 2.0), (0.8, 0.3, 0.9, 3.0)]


@pytest.mark.parametrize("a,mu,mu0,phi", SLAB_CASES)
def test_semi_infinite_slab_matches_chandrasekhar(a, mu, mu0, phi):
    """Isotropic scatterers filling z < 0 (40 mfp deep, 80 wide), sun at incidence mu0,
    viewed at cosine mu: L = E a mu0 H(mu) H(mu0) / (4 pi (mu + mu0)); order 1 alone is
    E a mu0 / (4 pi (mu + mu0))."""
    size = 40.0
    th, th0 = math.acos(mu), math.acos(mu0)
    light = (math.sin(th0), 0.0, mu0)
    eye = 20.0 * np.array([math.sin(th) * math.cos(phi), math.sin(th) * math.sin(phi), mu])
    cam = Camera(tuple(eye), (0, 0, 0), (0, 0, 1) if mu < 0.99 else (0, 1, 0), 0.05, 4, 4)
    med = PathMedium(np.ones((2, 2, 2), np.float32), np.array([-size, -size, -size]),
                 np.array([size, size, 0.0]), medium_of(1.0, (a, a, a)), light_of(light))
    rows = PathTracer(med, majorant_block=0).render_batch(cam, 1, 0, 4096).astype(np.float64)
    total = (rows[..., ROW_L1] + rows[..., ROW_LMS])[..., 0].ravel()
    single = rows[..., ROW_L1][..., 0].ravel()
    h, h0 = chandrasekhar_h(a, [mu, mu0])
    want_total = a * mu0 * h * h0 / (4 * math.pi * (mu + mu0))
    want_single = a * mu0 / (4 * math.pi * (mu + mu0))
    se_t = total.std(ddof=1) / math.sqrt(total.size)
    se_s = single.std(ddof=1) / math.sqrt(single.size)
    assert se_t < 0.01 * want_total  # the test can resolve a 4% error
    assert abs(total.mean() - want_total) < 4 * se_t, (total.mean(), want_total, se_t)
    assert abs(single.mean() - want_single) < 4 * se_s, (single.mean(), want_single, se_s)


def test_slab_check_has_power():
    """The same comparison rejects a medium whose albedo is off by 2% (0.88 vs 0.9)."""
    a_true, mu, mu0 = 0.9, 0.5, 0.8
    size = 40.0
    th0 = math.acos(mu0)
    eye = 20.0 * np.array([math.sqrt(1 - mu * mu), 0.0, mu])
    cam = Camera(tuple(eye), (0, 0, 0), (0, 0, 1), 0.05, 4, 4)
    med = PathMedium(np.ones((2, 2, 2), np.float32), np.array([-size, -size, -size]),
                 np.array([size, size, 0.0]), medium_of(1.0, (0.88,) * 3),
                 light_of((math.sin(th0), 0.0, mu0)))
    rows = PathTracer(med, majorant_block=0).render_batch(cam, 1, 0, 4096).astype(np.float64)
    total = (rows[..., ROW_L1] + rows[..., ROW_LMS])[..., 0].ravel()
    h, h0 = chandrasekhar_h(a_true, [mu, mu0])
    want = a_true * mu0 * h * h0 / (4 * math.pi * (mu + mu0))
    assert abs(total.mean() - want) > 4 * total.std(ddof=1) / math.sqrt(total.size)


# ------------------------------------------------------------------ thin box, single scattering

BMIN = np.array([-0.5, -0.4, -0.5])
BMAX = np.array([0.5, 0.5, 0.6])


def _single_scattering_quadrature(cam, sigma, albedo, lobes, light, sun, n_sub=8, n_seg=8, n_gl=16):
    """Pixel averages of int T(cam, x) sigma a E f(dot(l, w)) T(x -> sun) dt in a
    homogeneous box: Gauss-Legendre per ray (composite, the sun's exit face changes along
    the ray), midpoint sub-pixel grid (the kernel jitters uniformly over the pixel)."""
    fwd, right, up = cam.basis()
    tan_half = math.tan(math.radians(cam.fov_y) / 2)
    W, H = cam.width, cam.height
    sub = (np.arange(n_sub) + 0.5) / n_sub
    col = (np.arange(W)[:, None] + sub[None, :]).ravel()
    row = (np.arange(H)[:, None] + sub[None, :]).ravel()
    cc, rr = np.meshgrid(col, row)
    sx = (2 * cc / W - 1) * tan_half * (W / H)
    sy = (1 - 2 * rr / H) * tan_half
    d = fwd + sx[..., None] * right + sy[..., None] * up
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    d = d.reshape(-1, 3)
    o = np.broadcast_to(np.asarray(cam.origin, np.float64), d.shape)
    t0, t1 = box_intersect(o, d, BMIN, BMAX)
    assert np.all(t0 < t1)  # the camera sees only the box
    x, wq = np.polynomial.legendre.leggauss(n_gl)
    u = ((np.arange(n_seg)[:, None] + 0.5 * (x[None, :] + 1)) / n_seg).ravel()
    wu = np.tile(0.5 * wq, n_seg) / n_seg
    t = t0[:, None] + (t1 - t0)[:, None] * u[None, :]
    p = o[:, None, :] + t[..., None] * d[:, None, :]
    l = np.asarray(light)
    _, s_exit = box_intersect(p.reshape(-1, 3), np.broadcast_to(l, (p.size // 3, 3)), BMIN, BMAX)
    s_exit = s_exit.reshape(t.shape)
    f = phase_eval(d @ l, lobes)
    integrand = sigma * np.exp(-sigma * (t - t0[:, None])) * np.exp(-sigma * s_exit)
    radiance = f * ((t1 - t0) * (integrand * wu[None, :]).sum(axis=1))
    per_pixel = radiance.reshape(H, n_sub, W, n_sub).mean(axis=(1, 3))
    return per_pixel[..., None] * (np.asarray(albedo) * np.asarray(sun))[None, None, :]


@pytest.mark.parametrize("lobes", [[(0.6, 1.0)], [(0.8, 0.7), (-0.3, 0.3)]])
def test_thin_box_single_scattering_matches_quadrature(lobes):
    sigma, albedo, sun = 0.3, (0.8, 0.6, 0.4), (1.0, 0.9, 0.8)
    light = tuple(np.array([0.4, 0.8, -0.45]) / np.linalg.norm([0.4, 0.8, -0.45]))  # from behind
    cam = Camera((0.05, 0.05, 2.5), (0.0, 0.0, 0.05), (0, 1, 0), 10.0, 6, 6)
    med = PathMedium(np.ones((3, 4, 5), np.float32), BMIN, BMAX, medium_of(sigma, albedo, lobes),
                 light_of(light, sun), max_order=1)
    rows = PathTracer(med).render_batch(cam, 3, 0, 8192).astype(np.float64)
    assert np.all(rows[..., ROW_LMS] == 0) and rows[..., ROW_VERTICES].max() == 1
    est = rows[..., ROW_L1]                       # (spp, npix, 3)
    mean = est.mean(axis=0).reshape(6, 6, 3)
    se = (est.std(axis=0, ddof=1) / math.sqrt(est.shape[0])).reshape(6, 6, 3)
    want = _single_scattering_quadrature(cam, sigma, albedo, lobes, light, sun)
    z = np.abs(mean - want) / se
    assert z.max() < 4.5, (z.max(), mean[0, 0], want[0, 0])
    se_img = np.sqrt((se ** 2).sum(axis=(0, 1))) / 36
    assert np.all(np.abs(mean.mean(axis=(0, 1)) - want.mean(axis=(0, 1))) < 4 * se_img)
    assert np.all(se_img < 0.005 * want.mean(axis=(0, 1)))  # resolves a 2% error


def test_single_scattering_orientation():
    """Forward scattering (g = 0.8) with the sun behind the box is much brighter than with
    the sun behind the camera: a flipped cosine convention would swap the two."""
    cam = Camera((0.05, 0.05, 2.5), (0.0, 0.0, 0.05), (0, 1, 0), 10.0, 2, 2)
    out = {}
    for name, l in (("behind-box", (0.2, 0.3, -1.0)), ("behind-camera", (0.2, 0.3, 1.0))):
        l = tuple(np.array(l) / np.linalg.norm(l))
        med = PathMedium(np.ones((2, 2, 2), np.float32), BMIN, BMAX,
                         medium_of(0.3, (0.9,) * 3, [(0.8, 1.0)]), light_of(l), max_order=1)
        out[name] = PathTracer(med).render_batch(cam, 0, 0, 1024)[..., ROW_L1].mean()
        want = _single_scattering_quadrature(cam, 0.3, (0.9,) * 3, [(0.8, 1.0)], l, (1, 1, 1)).mean()
        assert out[name] == pytest.approx(want, rel=0.05)
    assert out["behind-box"] > 10 * out["behind-camera"]
