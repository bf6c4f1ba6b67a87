"""volume_stats on grids whose numbers are worked out by hand in the test."""
import numpy as np
import pytest

from clvol.errors import VolumeError
from clvol.volume.grid import DensityGrid
from clvol.volume.stats import format_stats, volume_stats


def test_constant_grid():
    # 4 x 6 x 8 voxels (x, y, z) over a 2 x 3 x 1 box: cells 0.5 x 0.5 x 0.125.
    c, scale = 0.25, 8.0
    g = DensityGrid(np.full((8, 6, 4), c, np.float32), np.zeros(3), np.array([2.0, 3.0, 1.0]))
    s = volume_stats(g, density_scale=scale)
    assert s["resolution"] == (4, 6, 8)
    assert s["voxel_size"] == [0.5, 0.5, 0.125]
    assert s["bbox_min"] == [0.0, 0.0, 0.0] and s["bbox_max"] == [2.0, 3.0, 1.0]
    assert (s["min"], s["max"]) == (0.25, 0.25)
    assert s["mean"] == pytest.approx(0.25, rel=1e-12)
    assert s["occupied_fraction"] == 1.0
    # The longest side is y (3 units): tau = 0.25 * 3 * 8 = 6.
    assert s["max_optical_thickness"] == pytest.approx(6.0, rel=1e-12)
    assert s["max_optical_thickness_axis"] == "y"
    # Voxel edge = cube root of 0.5 * 0.5 * 0.125 = 0.03125 -> 0.31498...
    edge = 0.03125 ** (1 / 3)
    assert s["mean_voxel_optical_thickness"] == pytest.approx(0.25 * 8.0 * edge, rel=1e-12)
    assert s["mean_occupied_voxel_optical_thickness"] == pytest.approx(0.25 * 8.0 * edge, rel=1e-12)


def test_single_row_picks_the_right_axis():
    # Zero grid, 4 x 3 x 5 (x, y, z), with density 1, 2, 3, 4 along x in row (y=1, z=2).
    # Box 2 x 0.75 x 10: cells 0.5 (x), 0.25 (y), 2.0 (z).
    d = np.zeros((5, 3, 4), np.float32)
    d[2, 1, :] = [1, 2, 3, 4]
    g = DensityGrid(d, np.zeros(3), np.array([2.0, 0.75, 10.0]))
    s = volume_stats(g, density_scale=0.5)
    # along x: (1+2+3+4) * 0.5 = 5; along y: 4 * 0.25 = 1; along z: 4 * 2 = 8 (the max).
    assert s["max_optical_thickness"] == pytest.approx(8.0 * 0.5, rel=1e-12)
    assert s["max_optical_thickness_axis"] == "z"
    assert s["occupied_fraction"] == pytest.approx(4 / 60)
    assert (s["min"], s["max"]) == (0.0, 4.0)
    assert s["mean"] == pytest.approx(10 / 60)
    edge = (0.5 * 0.25 * 2.0) ** (1 / 3)
    assert s["mean_voxel_optical_thickness"] == pytest.approx(10 / 60 * 0.5 * edge)
    assert s["mean_occupied_voxel_optical_thickness"] == pytest.approx(2.5 * 0.5 * edge)

    # Make the x row dominate: cells along z shrink to 0.2 (box z = 1): x gives 5, z gives 0.8.
    g2 = DensityGrid(d, np.zeros(3), np.array([2.0, 0.75, 1.0]))
    s2 = volume_stats(g2, density_scale=1.0)
    assert s2["max_optical_thickness"] == pytest.approx(5.0, rel=1e-12)
    assert s2["max_optical_thickness_axis"] == "x"


def test_sum_times_cell_is_the_clamped_linear_integral():
    # The docstring's claim: with interpolation between voxel centres, clamped over the end
    # half-cells, the integral along a row equals sum(density) * cell. Check it against a
    # fine midpoint-rule integral of np.interp (which clamps at the ends, like the renderer).
    # Midpoint error on a piecewise linear function with 200,000 steps is ~1e-10 here.
    vals = np.array([0.0, 3.0, 1.0, 0.5, 2.0, 0.0, 4.0], np.float32)
    length = 1.75
    # y and z are one thin voxel (0.01), so the x row holds the maximum.
    g = DensityGrid(vals.reshape(1, 1, -1).copy(), np.zeros(3), np.array([length, 0.01, 0.01]))
    cell = length / vals.size
    centres = (np.arange(vals.size) + 0.5) * cell
    n = 200_000
    t = (np.arange(n) + 0.5) * (length / n)
    integral = np.interp(t, centres, vals.astype(np.float64)).sum() * (length / n)
    s = volume_stats(g)
    assert s["max_optical_thickness_axis"] == "x"
    assert s["max_optical_thickness"] == pytest.approx(integral, rel=1e-8)


def test_empty_grid_has_zero_occupied_thickness():
    g = DensityGrid(np.zeros((2, 2, 2), np.float32), np.zeros(3), np.ones(3))
    s = volume_stats(g, 3.0)
    assert s["occupied_fraction"] == 0.0
    assert s["max_optical_thickness"] == 0.0
    assert s["mean_occupied_voxel_optical_thickness"] == 0.0


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_bad_density_scale(bad):
    g = DensityGrid(np.ones((2, 2, 2), np.float32), np.zeros(3), np.ones(3))
    with pytest.raises(VolumeError, match="density_scale"):
        volume_stats(g, bad)


def test_format_stats_shows_the_numbers():
    d = np.zeros((5, 3, 4), np.float32)
    d[2, 1, :] = [1, 2, 3, 4]
    g = DensityGrid(d, np.zeros(3), np.array([2.0, 0.75, 10.0]))
    text = format_stats(volume_stats(g, density_scale=0.5))
    assert "4 x 3 x 5 (x, y, z), 60 voxels" in text
    assert "max 4" in text
    assert "6.67% of voxels" in text
    assert "4 (along z)" in text
    assert "density_scale 0.5" in text
    assert len(text.splitlines()) == 7
