"""cl/majorant.cl + cl/include/majorant.h against reference/majorant.py, and the property the
trackers rely on: no interpolated density inside a coarse cell exceeds that cell's majorant
(STYLE.md pattern 6; a majorant below the density silently biases delta tracking).

Tolerances: the grid build is a max of float32 values, so kernel and twin agree exactly.
DDA segment ends are float32 in the kernel and float64 in the twin: within 2e-5 of the
box diagonal (a few float32 ULP of parameters of order 1, accumulated over ~20 steps).
"""
import numpy as np
import pytest

from clvol.kernels import majorant as kmaj
from reference import majorant as rmaj
from reference.grid import grid_density


def _spiky(shape, seed=0, p=0.02):
    """Mostly empty grid with isolated spikes, the worst case for a too-small footprint."""
    rs = np.random.default_rng(seed)
    d = np.where(rs.random(shape) < p, rs.uniform(1, 100, shape), 0.0)
    return d.astype(np.float32)


SHAPES_BLOCKS = [((5, 3, 7), 2), ((17, 9, 33), 8), ((1, 1, 1), 8), ((16, 16, 16), 16),
                 ((6, 4, 5), 1), ((12, 7, 10), 3)]


@pytest.mark.parametrize("shape,block", SHAPES_BLOCKS)
def test_build_matches_reference_exactly(shape, block):
    d = _spiky(shape, seed=sum(shape)) + np.random.default_rng(1).random(shape).astype(np.float32)
    got = kmaj.build_majorant(d, block)
    want = rmaj.build_majorant(d, block)
    assert got.shape == tuple(-(-n // block) for n in shape)
    np.testing.assert_array_equal(got, want)


def test_reference_footprint_by_brute_force():
    """The twin's separable max equals the literal definition for every coarse cell."""
    d = np.random.default_rng(3).random((7, 5, 9)).astype(np.float32)
    b = 3
    m = rmaj.build_majorant(d, b)
    for k, j, i in np.ndindex(m.shape):
        sl = tuple(slice(max(c * b - 1, 0), min((c + 1) * b, n - 1) + 1)
                   for c, n in zip((k, j, i), d.shape))
        assert m[k, j, i] == d[sl].max()


def _points_per_coarse_cell(shape, block, bmin, bmax, n, seed):
    """Random world points and the coarse cell whose box contains them."""
    nz, ny, nx = shape
    rs = np.random.default_rng(seed)
    p = rs.uniform(bmin, bmax, size=(n, 3))
    cell = (np.asarray(bmax) - bmin) / np.array([nx, ny, nz])
    c = np.minimum(((p - bmin) / (cell * block)).astype(int),
                   np.array([-(-nx // block), -(-ny // block), -(-nz // block)]) - 1)
    return p, c


def _violations(d, maj, block, bmin, bmax, n=200_000, seed=0):
    p, c = _points_per_coarse_cell(d.shape, block, bmin, bmax, n, seed)
    dens = grid_density(d.astype(np.float64), bmin, bmax, p)
    m = maj[c[:, 2], c[:, 1], c[:, 0]].astype(np.float64)
    return np.count_nonzero(dens > m)


@pytest.mark.parametrize("shape,block", [((9, 13, 11), 4), ((16, 16, 16), 8), ((5, 3, 7), 2)])
def test_no_interpolated_density_exceeds_its_cell_majorant(shape, block):
    d = _spiky(shape, seed=7)
    bmin, bmax = np.array([-0.3, -1.0, 0.2]), np.array([0.9, 0.5, 0.35])
    maj = kmaj.build_majorant(d, block)
    assert _violations(d, maj, block, bmin, bmax) == 0


def test_footprint_check_has_power():
    """A majorant of the block's own voxels only (no one-voxel border) must be caught."""
    d = _spiky((16, 16, 16), seed=7)
    b = 4
    own = d.reshape(4, b, 4, b, 4, b).max(axis=(1, 3, 5))
    bmin, bmax = np.zeros(3), np.ones(3)
    assert _violations(d, own, b, bmin, bmax) > 100


# ------------------------------------------------------------------------------ DDA

BMIN = np.array([-0.3, -1.0, 0.2], np.float32)
BMAX = np.array([0.9, 0.5, 0.35], np.float32)


def _rays(n, seed):
    rs = np.random.default_rng(seed)
    centre = (BMIN + BMAX) / 2
    o = centre + rs.normal(size=(n, 3)) * 1.5
    tgt = rs.uniform(BMIN, BMAX, size=(n, 3))
    d = tgt - o
    # Axis-parallel rays (zero direction components), one starting inside, one missing.
    d[0] = [1, 0, 0]; o[0] = [-1, -0.2, 0.3]
    d[1] = [0, -1, 0]; o[1] = [0.1, 2, 0.25]
    d[2] = [0, 0, 1]; o[2] = [0.11, -0.5, -3]
    o[3] = centre
    d[4] = [0, 0, 1]; o[4] = [5, 5, 0]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o.astype(np.float32), d.astype(np.float32)


def _nonzero(segs, tol):
    return [s for s in segs if s[1] - s[0] > tol]


@pytest.mark.parametrize("shape,block", [((9, 13, 11), 4), ((5, 3, 7), 2), ((4, 4, 4), 8)])
def test_dda_matches_reference(shape, block):
    d = np.random.default_rng(2).random(shape).astype(np.float32)
    maj = rmaj.build_majorant(d, block)
    o, w = _rays(300, 5)
    seg, cnt = kmaj.dda_segments(o, w, BMIN, BMAX, shape, maj, block)
    (mx, my, mz), bsize = kmaj.majorant_args(shape, BMIN, BMAX, block)
    diag = float(np.linalg.norm(BMAX - BMIN))
    tol = 2e-5 * diag
    assert cnt[4] == 0  # the missing ray
    for i in range(len(o)):
        want = rmaj.dda_segments(o[i], w[i], BMIN, BMAX, bsize[:3].astype(np.float32), maj)
        got = [tuple(s) for s in seg[i, :cnt[i]]]
        a, b = _nonzero(got, tol), _nonzero(want, tol)
        assert len(a) == len(b), (i, got, want)
        if a:
            np.testing.assert_allclose(np.array(a)[:, :2], np.array(b)[:, :2], atol=tol, rtol=0)
            np.testing.assert_array_equal(np.array(a)[:, 2], np.array(b)[:, 2])


def test_dda_segments_tile_the_ray_and_bound_the_density():
    """Segments are contiguous from box entry to exit, and density sampled anywhere in a
    segment (at the kernel's float32 positions) never exceeds the segment's majorant."""
    shape, block = (9, 13, 11), 4
    d = _spiky(shape, seed=11, p=0.05)
    maj = kmaj.build_majorant(d, block)
    o, w = _rays(400, 9)
    seg, cnt = kmaj.dda_segments(o, w, BMIN, BMAX, shape, maj, block, tmin=0.0)
    rs = np.random.default_rng(0)
    checked = 0
    for i in np.flatnonzero(cnt):
        s = seg[i, :cnt[i]].astype(np.float64)
        np.testing.assert_array_equal(s[1:, 0], s[:-1, 1])  # contiguous (same float32 values)
        assert np.all(s[:, 1] >= s[:, 0])
        t = rs.uniform(s[:, 0, None], s[:, 1, None], size=(len(s), 16))
        p = (o[i][None, None] + t[..., None] * w[i][None, None]).astype(np.float32)
        dens = grid_density(d.astype(np.float64), BMIN.astype(np.float64),
                            BMAX.astype(np.float64), p.astype(np.float64))
        assert np.all(dens <= s[:, 2, None]), i
        checked += dens.size
    assert checked > 10_000


def test_dda_tmax_clips_and_global_majorant_is_one_segment():
    shape = (6, 5, 7)
    d = np.random.default_rng(4).random(shape).astype(np.float32)
    gmaj = kmaj.build_majorant(d, max(shape))
    assert gmaj.shape == (1, 1, 1) and gmaj[0, 0, 0] == d.max()
    o = np.array([[-1.0, -0.25, 0.27]], np.float32)
    w = np.array([[1.0, 0.0, 0.0]], np.float32)
    seg, cnt = kmaj.dda_segments(o, w, BMIN, BMAX, shape, gmaj, max(shape))
    assert cnt[0] == 1
    np.testing.assert_allclose(seg[0, 0], [0.7, 1.9, d.max()], rtol=1e-6)
    seg, cnt = kmaj.dda_segments(o, w, BMIN, BMAX, shape, gmaj, max(shape), tmin=1.0, tmax=1.5)
    np.testing.assert_allclose(seg[0, 0, :2], [1.0, 1.5], rtol=1e-6)


@pytest.mark.oclgrind
@pytest.mark.rusticl
def test_majorant_tiny():
    d = np.random.default_rng(0).random((3, 2, 3)).astype(np.float32)
    np.testing.assert_array_equal(kmaj.build_majorant(d, 2), rmaj.build_majorant(d, 2))
    maj = rmaj.build_majorant(d, 2)
    o = np.array([[-1, 0.1, 0.3], [0.1, 0.1, 0.3]], np.float32)
    w = np.array([[1, 0, 0], [0, 0, 1]], np.float32)
    seg, cnt = kmaj.dda_segments(o, w, BMIN, BMAX, d.shape, maj, 2, max_seg=8)
    assert cnt[0] == 2 and cnt[1] == 1
