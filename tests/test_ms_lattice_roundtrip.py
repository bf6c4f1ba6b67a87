"""The F_ms lattice round trip, deterministic: fill_fms_lattice -> ray marcher ms="lattice" -> NumPy.

The only other check of the lattice against the marcher's lookup is statistical (path-traced
lattice vs path tracer, tests/test_raymarch_pathtrace.py), with tolerances wide enough to let
a half-cell shift through. Here nothing is random:

- the lattice is filled through ``fill_fms_lattice`` from an analytic affine field
  F_c(x) = a_c + b_c . x per channel (the query function evaluates it at the points it is
  given), over a box one lattice cell wider than the volume on every side, so every point of
  the volume lies between the outermost lattice centres ("away from faces": trilinear
  interpolation reproduces an affine field exactly there, no clamping);
- the points the query receives must be the documented lattice (docs/raymarch.md, "The F_ms
  slot"): cell centres lo + (i + 0.5) (hi - lo) / n in [z][y][x] order;
- the volume is a homogeneous box (sigma_t constant), marched with early termination off.
  docs/raymarch.md: multiple = albedo E int T_cam(t) sigma_t F_ms(x_t) dt over the ray's
  stretch in the box (sigma_s = albedo sigma_t, no phase factor on F_ms). Per segment the
  marcher integrates exactly against its own extinction and reads F at the segment's mean
  extinction point, which is exact for a source linear along the segment; so for this scene
  the marcher is exact up to float32 rounding, and the test compares it with a Gauss-Legendre
  quadrature (64 nodes: the integrand e^(-sigma t) (a + b t) is resolved to double precision)
  of the analytic field along each camera ray, the rays built from the documented camera
  convention (docs/conventions.md).

Tolerance: 2e-5 of the layer's maximum, the float32 bound of the marcher's twin tests
(docs/raymarch.md: measured 3e-7..3e-6 there; here 1.4e-6, the same at steps of 1, 0.5 and
0.37 voxels); a half-cell shift of the lattice changes the image by ~b . cell / 2, here 2% of
the maximum.
"""
import math

import numpy as np

from render_helpers import render_raymarch
from clvol.render.ms.lattice import fill_fms_lattice
from clvol.scene import Camera, Light, Medium, Phase, Scene, VolumeSpec
from clvol.volume.grid import DensityGrid

BOX_MIN, BOX_MAX = np.array([-0.5, -0.4, -0.3]), np.array([0.5, 0.4, 0.3])
N_VOX = (12, 10, 8)                 # density grid x, y, z (homogeneous)
SIGMA_T = 2.5                       # density 1 x density_scale
LATTICE = (10, 9, 7)                # F_ms lattice x, y, z
A = np.array([1.0, 0.7, 0.4])       # F_c(x) = A_c + B_c . x
B = np.array([[0.50, -0.30, 0.20],
              [-0.20, 0.40, 0.30],
              [0.10, 0.10, -0.35]])
ALBEDO = (0.9, 0.8, 0.7)
IRRADIANCE = (1.5, 1.0, 0.5)
TOL = 2e-5


def field(x, a=A):
    return a[None, :] + np.asarray(x, np.float64) @ B.T


def padded_box():
    """Lattice box: one lattice cell beyond the volume on every side, so the outermost
    centres lie half a cell outside the volume: lo = bmin - c, hi = bmax + c, c = (hi - lo)/n."""
    n = np.array(LATTICE, np.float64)
    c = (BOX_MAX - BOX_MIN) / (n - 2)
    return BOX_MIN - c, BOX_MAX + c


def scene():
    cam = Camera(origin=(0.35, 0.55, 1.6), target=(0.02, -0.03, 0.0), up=(0.0, 1.0, 0.0),
                 fov_y=40.0, width=20, height=16)
    return Scene(path=None, volume=VolumeSpec(file=None, generator=None),
                 medium=Medium(SIGMA_T, ALBEDO, Phase.hg(0.6)),
                 light=Light((0.3, 0.8, 0.52), IRRADIANCE), camera=cam)


def camera_rays(cam):
    """(H, W, 3) unit directions through the pixel centres, from docs/conventions.md."""
    fwd = np.subtract(cam.target, cam.origin, dtype=np.float64)
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, cam.up)
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    th = math.tan(math.radians(cam.fov_y) / 2)
    col = np.arange(cam.width) + 0.5
    row = np.arange(cam.height) + 0.5
    sx = (2 * col[None, :] / cam.width - 1) * th * cam.width / cam.height
    sy = (1 - 2 * row[:, None] / cam.height) * th
    sx, sy = np.broadcast_arrays(sx, sy)
    d = fwd + sx[..., None] * right + sy[..., None] * up
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def expected_multiple(sc, a=A):
    """albedo E int_{t0}^{t1} sigma e^(-sigma (t - t0)) F(o + t d) dt per pixel, (H, W, 3)
    (F with offsets ``a``)."""
    o = np.asarray(sc.camera.origin, np.float64)
    d = camera_rays(sc.camera)
    with np.errstate(divide="ignore"):
        ta = (BOX_MIN - o) / d
        tb = (BOX_MAX - o) / d
    t0 = np.maximum(np.minimum(ta, tb).max(-1), 0.0)
    t1 = np.maximum(ta, tb).min(-1)
    hit = t1 > t0
    x, w = np.polynomial.legendre.leggauss(64)
    half = np.where(hit, 0.5 * (t1 - t0), 0.0)
    t = 0.5 * (t0 + t1)[..., None] + half[..., None] * x           # (H, W, 64)
    pts = o + t[..., None] * d[..., None, :]
    integrand = SIGMA_T * np.exp(-SIGMA_T * (t - t0[..., None]))[..., None] * field(pts, a)
    integral = (integrand * w[:, None]).sum(-2) * half[..., None]
    return np.asarray(ALBEDO) * np.asarray(IRRADIANCE) * integral, hit


def fill(sc, seen=None):
    def query(points, omegas):
        if seen is not None:
            seen["p"], seen["w"] = np.array(points, np.float64), np.array(omegas, np.float64)
        return field(points)
    lo, hi = padded_box()
    return fill_fms_lattice(sc, LATTICE, query, bbox_min=lo, bbox_max=hi)


def test_lattice_points_are_documented_cell_centres():
    sc = scene()
    lo, hi = padded_box()
    seen = {}
    g = fill(sc, seen)
    # [z][y][x] order (x fastest), centres lo + (i + 0.5) cell
    cell = (hi - lo) / np.array(LATTICE)
    iz, iy, ix = np.meshgrid(*(np.arange(k) for k in LATTICE[::-1]), indexing="ij")
    idx = np.stack([ix, iy, iz], -1).reshape(-1, 3)
    want = lo + (idx + 0.5) * cell
    assert seen["p"].shape == want.shape
    np.testing.assert_allclose(seen["p"], want, rtol=0, atol=1e-12 * np.abs(hi - lo).max())
    # omega toward the camera at every point
    to_cam = np.asarray(sc.camera.origin) - want
    np.testing.assert_allclose(seen["w"], to_cam / np.linalg.norm(to_cam, axis=1, keepdims=True),
                               rtol=0, atol=1e-12)
    assert np.asarray(g.values).shape == (LATTICE[2], LATTICE[1], LATTICE[0], 3)


def test_marcher_reads_the_lattice_exactly():
    sc = scene()
    lo, hi = padded_box()
    g = fill(sc)
    grid = DensityGrid(density=np.ones(N_VOX[::-1], np.float32), bbox_min=BOX_MIN, bbox_max=BOX_MAX)
    res = render_raymarch(sc, ms="lattice", ms_lattice=g, grid=grid, threshold=0.0,
                          light_resolution=16)
    got = res.layers["multiple"].astype(np.float64)
    want_img, hit = expected_multiple(sc)
    assert hit.mean() > 0.5 and not hit.all(), "the view must cover the box and some background"
    err = np.abs(got - want_img)
    scale = want_img.max()
    worst = np.unravel_index(np.argmax(err), err.shape)
    assert err.max() <= TOL * scale, (
        f"multiple layer off the quadrature by {err.max() / scale:.2e} of its max at pixel "
        f"{worst}: {got[worst]:.6g} vs {want_img[worst]:.6g}")
    # Power: values at cell corners read as centres (the field seen at x - cell/2) would
    # be off by far more than the tolerance (measured 2% of the max; the error above 1.4e-6).
    cell = (hi - lo) / np.array(LATTICE)
    shifted, _ = expected_multiple(sc, A - B @ (cell / 2))
    assert np.abs(shifted - want_img).max() > 100 * TOL * scale
