"""Density pyramid: cube padding, resampling to base^3, mip chain (cl/pyramid.cl) against
reference/pyramid.py and hand-computed cases.

Tolerances: the mip kernel adds the 8 children in the twin's order in float32, so it matches
bit for bit. The host resampling (closed-form weights, float64 sums, float32 result) and the
twin (Gauss quadrature of the basis functions, float64) agree within 1e-6 relative to the
largest density (a few float32 ULP). Mass is conserved within 1e-5 relative (float32 sums of
up to 512 values per level, compared in float64).
"""
from types import SimpleNamespace

import numpy as np
import pytest

from clvol.errors import ClvolError
from clvol.kernels import pyramid as kp
from clvol.volume.grid import DensityGrid
from reference import pyramid as rp


def _grid(shape, bmin=(0, 0, 0), bmax=(1, 1, 1), seed=0):
    d = np.random.default_rng(seed).random(shape).astype(np.float32)
    return DensityGrid.from_array(d, bmin, bmax)


CASES = {  # (nz, ny, nx), bbox_min, bbox_max, base
    "odd non-cubic box": ((3, 5, 7), (-1, 0, 0), (1, 0.5, 3), 8),
    "one voxel": ((1, 1, 1), (0, 0, 0), (1, 1, 1), 4),
    "upsample, non-cubic": ((5, 4, 3), (0, 0, 0), (1, 2, 1.5), 16),
    "downsample, factor 3.x": ((13, 11, 9), (0, 0, 0), (1, 1, 1), 4),
    "same size cube": ((8, 8, 8), (0, 0, 0), (1, 1, 1), 8),
}


@pytest.mark.parametrize("name", CASES)
def test_pyramid_matches_reference(name):
    shape, bmin, bmax, base = CASES[name]
    g = _grid(shape, bmin, bmax)
    p = kp.build_pyramid(g, base)
    want, cube_min, cube_size = rp.resample_to_cube(g.density, bmin, bmax, base)
    np.testing.assert_allclose(p.cube_min, cube_min, rtol=0, atol=1e-12)
    assert p.cube_size == cube_size
    assert p.n_levels == int(np.log2(base)) + 1
    assert list(p.level_offsets) == [sum((base >> m) ** 3 for m in range(l)) for l in range(p.n_levels)]
    np.testing.assert_allclose(p.level(0), want, rtol=0, atol=1e-6 * want.max())
    # The mip chain is bit-identical to the twin's, level by level, from the same level 0.
    for l, lv in enumerate(rp.mip_chain(p.level(0))):
        np.testing.assert_array_equal(p.level(l), lv)


@pytest.mark.parametrize("name", CASES)
def test_mass_is_conserved_on_every_level(name):
    shape, bmin, bmax, base = CASES[name]
    g = _grid(shape, bmin, bmax, seed=1)
    p = kp.build_pyramid(g, base)
    mass = g.density.astype(np.float64).sum() * np.prod(g.cell_size)
    for l in range(p.n_levels):
        got = p.level(l).astype(np.float64).sum() * p.voxel_size(l) ** 3
        assert abs(got / mass - 1) < 1e-5, (l, got, mass)
    assert p.level(p.n_levels - 1).shape == (1, 1, 1)


def test_non_cubic_box_is_padded_centred_not_stretched():
    """A 2 x 1 x 1 box of constant density: the cube is 2 on a side, the medium fills x and the
    middle half of y and z; stretching would fill the cube, off-centre padding would shift it."""
    g = DensityGrid.from_array(np.ones((4, 4, 8), np.float32), (-1, 3, 10), (1, 4, 11))
    p = kp.build_pyramid(g, 8)
    np.testing.assert_allclose(p.cube_min, [-1, 2.5, 9.5])
    assert p.cube_size == 2.0
    d = p.level(0)  # voxel 0.25: y, z voxels 2..5 lie inside the box, 0, 1, 6, 7 outside
    inside = np.zeros(8, bool)
    inside[2:6] = True
    np.testing.assert_allclose(d[np.ix_(inside, inside, np.ones(8, bool))], 1.0, rtol=1e-6)
    assert d[~inside].max() == 0 and d[:, ~inside].max() == 0


def test_upsampling_averages_the_linear_interpolant():
    """Two voxels [0, 1] along x over [0, 1]: the clamped linear field is 0 on [0, 1/4], rises
    linearly to 1 on [1/4, 3/4] and stays 1 on [3/4, 1]; its means over the quarter cells are,
    by hand, 0, 0.25, 0.75 and 1."""
    d = np.broadcast_to(np.array([0, 1], np.float32), (2, 2, 2)).copy()
    p = kp.build_pyramid(DensityGrid.from_array(d), 4)
    np.testing.assert_allclose(p.level(0)[1, 2], [0, 0.25, 0.75, 1.0], atol=1e-7)


def test_integer_downsampling_is_the_block_mean():
    g = _grid((16, 16, 16), seed=2)
    p = kp.build_pyramid(g, 4)
    want = g.density.astype(np.float64).reshape(4, 4, 4, 4, 4, 4).mean(axis=(1, 3, 5))
    np.testing.assert_allclose(p.level(0), want, rtol=1e-6)


def test_base_sized_cube_is_copied_unchanged():
    g = _grid((8, 8, 8), seed=3)
    np.testing.assert_array_equal(kp.build_pyramid(g, 8).level(0), g.density)


@pytest.mark.parametrize("bad", [0, 3, 100, 2048, 256.0, True, "256"])
def test_bad_base_resolution_is_refused(bad):
    with pytest.raises(ClvolError, match=r"base_resolution = .* power of two from 1 to 1024"):
        kp.check_base_resolution(bad)


def test_base_too_large_for_the_device_says_what_fits():
    fake = SimpleNamespace(device=SimpleNamespace(max_mem_alloc_size=2 ** 30),
                           entry=SimpleNamespace(label="fake device"))
    with pytest.raises(ClvolError, match=r"1024 needs one 4\.57 GiB buffer .* base_resolution <= 512"):
        kp.check_base_resolution(1024, fake)


def test_build_pyramid_needs_a_grid():
    with pytest.raises(ClvolError, match="needs a clvol DensityGrid, got ndarray"):
        kp.build_pyramid(np.zeros((2, 2, 2), np.float32), 4)


@pytest.mark.oclgrind
@pytest.mark.rusticl
def test_pyramid_tiny():
    g = _grid((2, 3, 1), (0, 0, 0), (1, 1.5, 0.5), seed=4)
    p = kp.build_pyramid(g, 4)
    for l, lv in enumerate(rp.mip_chain(p.level(0))):
        np.testing.assert_array_equal(p.level(l), lv)
