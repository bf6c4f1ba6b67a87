"""Summary numbers for a density grid (``clvol volume info``).

Optical thickness along an axis-aligned line through a row of voxel centres: with trilinear
interpolation clamped at the edges (docs/conventions.md), the density along the row is piecewise linear
between centres and constant over the half cells at both ends, so its integral over the box is
exactly ``sum(density) * cell``. ``max_optical_thickness`` is the largest such value over all
rows along x, y and z, times ``density_scale``: how opaque the grid is at its thickest.
"""
from __future__ import annotations

import numpy as np

from ..errors import VolumeError
from .grid import DensityGrid


def volume_stats(grid: DensityGrid, density_scale: float = 1.0) -> dict:
    """Numbers describing ``grid``; optical quantities use sigma_t = density * density_scale.

    Keys: resolution (nx, ny, nz), bbox_min, bbox_max, voxel_size (x, y, z), density_scale,
    min, max, mean (density), occupied_fraction (voxels with density > 0),
    max_optical_thickness, max_optical_thickness_axis ('x', 'y' or 'z'),
    mean_voxel_optical_thickness (mean over all voxels of density * scale * voxel edge) and
    mean_occupied_voxel_optical_thickness (the same over voxels with density > 0; 0 if none).
    For non-cubic voxels the voxel edge is the cube root of the voxel volume.
    """
    scale = float(density_scale)
    if not (np.isfinite(scale) and scale >= 0):
        raise VolumeError(f"density_scale = {density_scale!r} must be a finite number >= 0")
    d = grid.density
    cell = grid.cell_size
    # float64 accumulation: a float32 running sum over 256^3 voxels loses digits.
    total = float(d.sum(dtype=np.float64))
    occupied = int(np.count_nonzero(d))
    mean = total / d.size
    best, best_axis = -1.0, "x"
    for axis_name, array_axis, c in (("x", 2, cell[0]), ("y", 1, cell[1]), ("z", 0, cell[2])):
        tau = float(d.sum(axis=array_axis, dtype=np.float64).max()) * c * scale
        if tau > best:
            best, best_axis = tau, axis_name
    edge = float(np.prod(cell)) ** (1.0 / 3.0)
    return {
        "resolution": grid.resolution,
        "bbox_min": grid.bbox_min.tolist(),
        "bbox_max": grid.bbox_max.tolist(),
        "voxel_size": cell.tolist(),
        "density_scale": scale,
        "min": float(d.min()),
        "max": float(d.max()),
        "mean": mean,
        "occupied_fraction": occupied / d.size,
        "max_optical_thickness": best,
        "max_optical_thickness_axis": best_axis,
        "mean_voxel_optical_thickness": mean * scale * edge,
        "mean_occupied_voxel_optical_thickness": (total / occupied * scale * edge) if occupied else 0.0,
    }


def format_stats(stats: dict) -> str:
    """The dict from ``volume_stats`` as aligned ``name: value`` lines."""
    def vec(v):
        return "(" + ", ".join(f"{x:.6g}" for x in v) + ")"
    nx, ny, nz = stats["resolution"]
    s = stats["density_scale"]
    lines = [
        ("resolution", f"{nx} x {ny} x {nz} (x, y, z), {nx * ny * nz} voxels"),
        ("bbox", f"{vec(stats['bbox_min'])} .. {vec(stats['bbox_max'])}"),
        ("voxel size", vec(stats["voxel_size"])),
        ("density", f"min {stats['min']:.6g}, max {stats['max']:.6g}, mean {stats['mean']:.6g}"),
        ("occupied", f"{100 * stats['occupied_fraction']:.2f}% of voxels have density > 0"),
        (f"max optical thickness (density_scale {s:g})",
         f"{stats['max_optical_thickness']:.6g} (along {stats['max_optical_thickness_axis']})"),
        ("mean voxel optical thickness",
         f"{stats['mean_voxel_optical_thickness']:.6g} (all voxels), "
         f"{stats['mean_occupied_voxel_optical_thickness']:.6g} (occupied voxels)"),
    ]
    width = max(len(k) for k, _ in lines)
    return "\n".join(f"  {k:<{width}} : {v}" for k, v in lines)
