"""NumPy twin of cl/majorant.cl and cl/include/majorant.h: majorant grid and its DDA.

The majorant grid has ceil(n / block) coarse cells per axis, [z][y][x]. Coarse cell i covers
fine cells [i*block, (i+1)*block) (world box bmin + i*bsize .. bmin + (i+1)*bsize with
bsize = cell * block) and holds the maximum of the fine voxels [i*block - 1, (i+1)*block],
clamped to the grid: every voxel the clamped trilinear lookup can blend for a point of
that box (and half a voxel beyond it on each side). Raw densities; scale by density_scale.
"""
import numpy as np


def _axis_block_max(a: np.ndarray, axis: int, block: int) -> np.ndarray:
    """Max over windows [i*block - 1, (i+1)*block] (clamped) along one axis."""
    n = a.shape[axis]
    m = -(-n // block)
    parts = []
    for i in range(m):
        lo, hi = max(i * block - 1, 0), min((i + 1) * block, n - 1)
        parts.append(np.take(a, np.arange(lo, hi + 1), axis=axis).max(axis=axis, keepdims=True))
    return np.concatenate(parts, axis=axis)


def build_majorant(density: np.ndarray, block: int = 8) -> np.ndarray:
    """float32 [ceil(nz/b)][ceil(ny/b)][ceil(nx/b)]; a box max is separable, so per axis."""
    out = np.asarray(density, np.float32)
    for axis in range(3):
        out = _axis_block_max(out, axis, block)
    return out


def dda_segments(o, d, bmin, bmax, bsize, maj, tmin=0.0, tmax=np.inf):
    """List of (t_a, t_b, majorant) segments of one ray o + t d, t in [tmin, tmax], in
    float64. Same walk as majorant.h (entry cell by clamped floor, axis with the nearest
    boundary advances, ties one axis at a time)."""
    from reference.grid import box_intersect
    o, d = np.asarray(o, np.float64), np.asarray(d, np.float64)
    bmin, bmax, bsize = (np.asarray(v, np.float64) for v in (bmin, bmax, bsize))
    mres = np.array(maj.shape[::-1])
    t0, t1 = box_intersect(o[None], d[None], bmin, bmax, tmin)
    t0, t1 = float(t0[0]), min(float(t1[0]), tmax)
    if not t0 < t1:
        return []
    cell = np.clip((o + t0 * d - bmin) / bsize, 0, mres - 1).astype(np.int64)
    step = np.sign(d).astype(np.int64)
    with np.errstate(divide="ignore"):
        t_next = np.where(d > 0, (bmin + (cell + 1) * bsize - o) / d,
                          np.where(d < 0, (bmin + cell * bsize - o) / d, np.inf))
        t_delta = np.where(d != 0, bsize / np.abs(d), np.inf)
    segs, t = [], t0
    while True:
        tb = min(t_next.min(), t1)
        segs.append((t, tb, float(maj[cell[2], cell[1], cell[0]])))
        if tb >= t1:
            return segs
        t = tb
        a = int(np.argmin(t_next))  # first minimum: x before y before z, as the kernel
        cell[a] += step[a]
        t_next[a] += t_delta[a]
        if not 0 <= cell[a] < mres[a]:
            return segs
