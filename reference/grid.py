"""NumPy twin of cl/include/grid.h: trilinear grid lookups, ray/box intersection, camera rays.

Grids are density[z][y][x]; voxel centres at bmin + (i + 0.5) * cell; trilinear between
centres, clamped at the edges; 0 outside the box (docs/conventions.md).
"""
import numpy as np


def grid_lookup(d, g):
    """Trilinear lookup at continuous voxel coordinates g (..., 3) = (p - bmin)/cell - 0.5."""
    nz, ny, nx = d.shape
    g = np.asarray(g)
    x = np.clip(g[..., 0], 0, nx - 1)
    y = np.clip(g[..., 1], 0, ny - 1)
    z = np.clip(g[..., 2], 0, nz - 1)
    x0, y0, z0 = x.astype(np.int64), y.astype(np.int64), z.astype(np.int64)
    x1, y1, z1 = np.minimum(x0 + 1, nx - 1), np.minimum(y0 + 1, ny - 1), np.minimum(z0 + 1, nz - 1)
    fx, fy, fz = x - x0, y - y0, z - z0

    def lerp(a, b, t):
        return a + (b - a) * t

    c00 = lerp(d[z0, y0, x0], d[z0, y0, x1], fx)
    c01 = lerp(d[z0, y1, x0], d[z0, y1, x1], fx)
    c10 = lerp(d[z1, y0, x0], d[z1, y0, x1], fx)
    c11 = lerp(d[z1, y1, x0], d[z1, y1, x1], fx)
    return lerp(lerp(c00, c01, fy), lerp(c10, c11, fy), fz)


def grid_density(d, bmin, bmax, p):
    p = np.asarray(p)
    bmin, bmax = np.asarray(bmin, p.dtype), np.asarray(bmax, p.dtype)
    cell = (bmax - bmin) / np.array(d.shape[::-1], p.dtype)
    inside = np.all((p >= bmin) & (p <= bmax), axis=-1)
    return np.where(inside, grid_lookup(d, (p - bmin) / cell - 0.5), 0.0)


def box_intersect(o, d, bmin, bmax, tmin=0.0):
    """(t0, t1) per ray, (inf, -inf) for a miss (same rules as grid.h)."""
    o, d = np.atleast_2d(o).astype(np.float64), np.atleast_2d(d).astype(np.float64)
    lo = np.full(len(o), float(tmin))
    hi = np.full(len(o), np.inf)
    miss = np.zeros(len(o), bool)
    for a in range(3):
        zero = d[:, a] == 0
        miss |= zero & ((o[:, a] < bmin[a]) | (o[:, a] > bmax[a]))
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (bmin[a] - o[:, a]) / d[:, a]
            tb = (bmax[a] - o[:, a]) / d[:, a]
        lo = np.where(zero, lo, np.maximum(lo, np.minimum(ta, tb)))
        hi = np.where(zero, hi, np.minimum(hi, np.maximum(ta, tb)))
    miss |= lo > hi
    return np.where(miss, np.inf, lo), np.where(miss, -np.inf, hi)


def camera_rays(forward, right, up, tan_half, width, height, jitter=None):
    """(H, W, 3) unit directions through pixel centres (+ jitter in pixels)."""
    col, row = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    if jitter is not None:
        col, row = col + jitter[..., 0], row + jitter[..., 1]
    sx = (2 * col / width - 1) * tan_half * (width / height)
    sy = (1 - 2 * row / height) * tan_half
    d = (np.asarray(forward) + sx[..., None] * np.asarray(right) + sy[..., None] * np.asarray(up))
    return d / np.linalg.norm(d, axis=-1, keepdims=True)
