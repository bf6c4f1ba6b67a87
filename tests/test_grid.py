"""cl/include/grid.h (via cl/grid.cl) against reference/grid.py and the docs/conventions.md conventions.

Tolerances: a trilinear lookup is 7 lerps of float32 values in [0, 1]; kernel and float64
twin agree within 2e-6 absolute (~16 ULP of 1.0; the kernel's position -> voxel arithmetic
is float32). Box intersections agree within 1e-5 relative (float32 vs float64 slabs).
"""
import numpy as np
import pytest

from clvol.kernels import grid as kgrid
from reference import grid as rgrid


def _grid(shape=(5, 3, 7), seed=0):
    return np.random.default_rng(seed).random(shape).astype(np.float32)


def test_mitsuba_row_convention():
    """docs/conventions.md: a 4-voxel row [0,1,2,3] over x in [0,1] is 0 at x=0.125, 1 at 0.375, 3 at 1."""
    d = np.arange(4, dtype=np.float32).reshape(1, 1, 4)
    pts = np.array([[0.125, 0.5, 0.5], [0.375, 0.5, 0.5], [1.0, 0.5, 0.5], [0.0, 0.5, 0.5],
                    [0.25, 0.5, 0.5]], np.float32)
    got = kgrid.grid_density(d, (0, 0, 0), (1, 1, 1), pts)
    np.testing.assert_allclose(got, [0, 1, 3, 0, 0.5], atol=1e-6)
    np.testing.assert_allclose(rgrid.grid_density(d, (0, 0, 0), (1, 1, 1), pts.astype(float)),
                               [0, 1, 3, 0, 0.5], atol=1e-12)


def test_axes_are_not_swapped_on_non_cubic_grid():
    """density[z][y][x]: a grid that varies only along x must vary only with p.x."""
    nz, ny, nx = 3, 5, 7
    d = np.broadcast_to(np.arange(nx, dtype=np.float32), (nz, ny, nx)).copy()
    bmin, bmax = np.zeros(3), np.array([7.0, 5.0, 3.0])  # unit voxels
    p = np.array([[2.5, 0.5, 0.5], [2.5, 4.5, 2.5]], np.float32)  # same x, other y/z
    np.testing.assert_allclose(kgrid.grid_density(d, bmin, bmax, p), [2, 2], atol=1e-6)


@pytest.mark.parametrize("shape", [(1, 1, 1), (5, 3, 7), (2, 9, 1)])
def test_kernel_matches_reference_random_points(shape):
    d = _grid(shape)
    # The kernel gets the box in float32; give the twin the very same numbers.
    bmin = np.array([-0.3, -1.0, 0.2], np.float32).astype(np.float64)
    bmax = np.array([0.9, 0.5, 0.35], np.float32).astype(np.float64)
    rs = np.random.default_rng(1)
    p = rs.uniform(bmin - 0.1, bmax + 0.1, size=(3001, 3))
    # Exactly on faces and corners, and just outside.
    p[:4] = [bmin, bmax, [bmin[0], bmax[1], bmin[2]], bmax + [1e-6, 0, 0]]
    p = p.astype(np.float32)
    got = kgrid.grid_density(d, bmin, bmax, p)
    want = rgrid.grid_density(d, bmin, bmax, p.astype(np.float64))
    np.testing.assert_allclose(got, want, atol=2e-6, rtol=0)
    assert got[3] == 0.0  # outside the box is empty


@pytest.mark.oclgrind
@pytest.mark.rusticl
def test_grid_tiny():
    d = _grid((2, 3, 2))
    p = np.array([[0.1, 0.2, 0.3], [0.9, 0.9, 0.1], [1.2, 0, 0]], np.float32)
    np.testing.assert_allclose(kgrid.grid_density(d, (0, 0, 0), (1, 1, 1), p),
                               rgrid.grid_density(d, (0, 0, 0), (1, 1, 1), p.astype(float)), atol=2e-6)


def test_box_intersection_cases():
    bmin, bmax = np.array([-1.0, -1.0, -1.0]), np.array([1.0, 2.0, 1.0])
    o = np.array([[0, 0, -5], [0, 0, 0], [3, 0, 0], [1, 0, -5], [0, 5, 0], [0, 0, -5],
                  [-1, -1, -1], [2, 2, 2]], np.float32)
    d = np.array([[0, 0, 1], [1, 0, 0], [1, 0, 0], [0, 0, 1], [0, -1, 0], [0, 1, 0],
                  [1, 0, 0], [-1, -1, -1]], np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t0, t1 = kgrid.box_intersect(o, d, bmin, bmax)
    r0, r1 = rgrid.box_intersect(o, d, bmin, bmax)
    # hit from outside; origin inside (t0 = tmin); miss behind; grazing face x = 1 (hit);
    # from above along -y; parallel outside (miss); corner along an edge; diagonal through a corner.
    expect_hit = [True, True, False, True, True, False, True, True]
    assert list(t0 <= t1) == expect_hit
    assert list(r0 <= r1) == expect_hit
    hit = np.array(expect_hit)
    np.testing.assert_allclose(t0[hit], r0[hit], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(t1[hit], r1[hit], rtol=1e-5, atol=1e-6)
    assert (t0[0], t1[0]) == (4.0, 6.0) and (t0[1], t1[1]) == (0.0, 1.0)


def test_box_intersection_random_rays():
    rs = np.random.default_rng(3)
    o = rs.uniform(-2, 2, (2000, 3)).astype(np.float32)
    d = rs.normal(size=(2000, 3))
    d[::7, 0] = 0  # axis-parallel components
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    bmin, bmax = np.array([-0.5, -0.7, -0.2]), np.array([0.5, 0.3, 0.9])
    t0, t1 = kgrid.box_intersect(o, d, bmin, bmax)
    r0, r1 = rgrid.box_intersect(o, d, bmin, bmax)
    hit_k, hit_r = t0 <= t1, r0 <= r1
    # Hit/miss can only disagree for rays that graze within float32 rounding of an edge.
    assert np.sum(hit_k != hit_r) <= 2
    both = hit_k & hit_r
    np.testing.assert_allclose(t0[both], r0[both], rtol=1e-5, atol=2e-6)
    np.testing.assert_allclose(t1[both], r1[both], rtol=1e-5, atol=2e-6)


def test_camera_rays_match_scene_camera():
    from clvol.scene import Camera
    cam = Camera(origin=(0.3, 0.2, 2.2), target=(0.0, -0.1, 0.0), up=(0.0, 1.0, 0.0),
                 fov_y=35.0, width=7, height=5)
    got = kgrid.camera_rays(cam)
    want = cam.pixel_directions()
    np.testing.assert_allclose(got, want, atol=2e-6)
    forward, right, up = cam.basis()
    assert np.allclose(got[2, 3], forward, atol=1e-6)  # centre pixel of an odd image
    assert got[2, 0] @ right < 0 and got[0, 3] @ up > 0  # column 0 left, row 0 top
