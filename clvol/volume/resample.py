"""Box-filter downsampling that is fed piece by piece, so a sparse volume can be reduced while it
is read, without the full-resolution dense array ever existing (docs/volumes.md, "Large volumes").

Fine voxels are addressed by integer index (x, y, z). Coarse cell ``c`` averages the ``f^3`` fine
voxels with indices ``base + c*f .. base + c*f + f - 1`` on every axis: an integer factor and an
aligned partition, so every fine voxel lands in exactly one cell and the mass
``sum(coarse) * (f*h)^3 = sum(fine) * h^3`` is kept up to float rounding.
"""
from __future__ import annotations

import numpy as np

_SLAB = 32   # fine voxels per slab along x in add_block (rounded to whole coarse cells)


class BoxAccumulator:
    """Sums of fine voxels per coarse cell over ``shape`` = (mx, my, mz) cells.

    ``add_block`` and ``add_constant`` may be called in any order and may overlap (values add);
    anything outside the fine range ``keep_lo .. keep_hi - 1`` (default: all the cells cover) is
    dropped, so the cells beyond it stay exactly 0.
    ``density()`` returns the averages as float32 [z][y][x] (the array is reused, not copied).
    """

    def __init__(self, base, shape, factor: int, keep_lo=None, keep_hi=None):
        self.base = np.asarray(base, dtype=np.int64)
        self.shape = tuple(int(n) for n in shape)
        self.f = int(factor)
        if self.f < 1 or min(self.shape) < 1:
            raise ValueError(f"BoxAccumulator: factor {factor} and shape {shape} must be >= 1")
        end = self.base + np.asarray(self.shape, np.int64) * self.f   # exclusive, fine index
        self.lo = self.base if keep_lo is None else np.maximum(self.base, np.asarray(keep_lo))
        self.end = end if keep_hi is None else np.minimum(end, np.asarray(keep_hi))
        mx, my, mz = self.shape
        # float32 sums: a cell receives at most a few partial sums (one per block it straddles),
        # each already summed in float64, so the rounding stays at a few ulps.
        self._sum = np.zeros((mz, my, mx), dtype=np.float32)

    def add_block(self, block_xyz: np.ndarray, origin) -> None:
        """Add a dense block indexed [x][y][z] whose voxel [0, 0, 0] has fine index ``origin``."""
        o = np.asarray(origin, dtype=np.int64)
        n = np.asarray(block_xyz.shape, dtype=np.int64)
        lo = np.maximum(o, self.lo)
        hi = np.minimum(o + n, self.end)
        if np.any(hi <= lo):
            return
        b = block_xyz[lo[0] - o[0]:hi[0] - o[0], lo[1] - o[1]:hi[1] - o[1],
                      lo[2] - o[2]:hi[2] - o[2]]
        f = self.f
        if f == 1:
            c0 = lo - self.base
            c1 = c0 + np.asarray(b.shape)
            self._sum[c0[2]:c1[2], c0[1]:c1[1], c0[0]:c1[0]] += b.transpose(2, 1, 0)
            return
        # In slabs of whole coarse cells along x, so the temporaries stay a fraction of the
        # block (memory is the point of reading this way).
        step = max(1, _SLAB // f)
        cx0 = (lo[0] - self.base[0]) // f
        cx1 = (hi[0] - 1 - self.base[0]) // f + 1
        for ca in range(int(cx0), int(cx1), step):
            x0 = max(lo[0], self.base[0] + ca * f)
            x1 = min(hi[0], self.base[0] + (ca + step) * f)
            self._add_cells(b[x0 - lo[0]:x1 - lo[0]], np.array([x0, lo[1], lo[2]]))

    def _add_cells(self, b: np.ndarray, lo: np.ndarray) -> None:
        f = self.f
        rel = lo - self.base
        c0 = rel // f
        # Pad the block out to whole coarse cells, then sum each f^3 group.
        pre = rel - c0 * f
        ncell = -(-(pre + np.asarray(b.shape)) // f)
        padded = np.zeros(tuple(ncell * f), dtype=b.dtype)
        padded[pre[0]:pre[0] + b.shape[0], pre[1]:pre[1] + b.shape[1],
               pre[2]:pre[2] + b.shape[2]] = b
        # One axis at a time as f strided slices added together (fast elementwise adds rather
        # than reductions over short axes); float64 from the second axis on, so a cell's sum
        # of f^3 values is rounded about as often as a float32 sum of f values.
        sums = _sum_groups(padded, 2, f)
        sums = _sum_groups(sums.astype(np.float64), 1, f)
        sums = _sum_groups(sums, 0, f)
        c1 = c0 + ncell
        self._sum[c0[2]:c1[2], c0[1]:c1[1], c0[0]:c1[0]] += sums.transpose(2, 1, 0)

    def add_constant(self, lo, hi, value: float) -> None:
        """Add ``value`` at every fine voxel of the box ``lo .. hi - 1`` (a tile), in O(cells)."""
        lo = np.maximum(np.asarray(lo, np.int64), self.lo)
        hi = np.minimum(np.asarray(hi, np.int64), self.end)
        if np.any(hi <= lo) or value == 0:
            return
        f = self.f
        counts = []
        for a in range(3):
            c0 = (lo[a] - self.base[a]) // f
            c1 = (hi[a] - 1 - self.base[a]) // f + 1
            cell_lo = self.base[a] + np.arange(c0, c1) * f
            # Fine voxels of the box inside each coarse cell, per axis: the count is separable.
            counts.append((c0, c1, np.minimum(cell_lo + f, hi[a]) - np.maximum(cell_lo, lo[a])))
        (x0, x1, cx), (y0, y1, cy), (z0, z1, cz) = counts
        block = (float(value) * cz[:, None, None] * cy[None, :, None] * cx[None, None, :])
        self._sum[z0:z1, y0:y1, x0:x1] += block.astype(np.float32)

    def density(self) -> np.ndarray:
        """The cell averages (sum / f^3), float32 [z][y][x]."""
        if self.f > 1:
            self._sum /= np.float32(self.f ** 3)
        return self._sum


def _sum_groups(a: np.ndarray, axis: int, f: int) -> np.ndarray:
    """Sums of consecutive groups of ``f`` along ``axis`` (its length is a multiple of f)."""
    idx = [slice(None)] * 3
    idx[axis] = slice(0, None, f)
    out = a[tuple(idx)].copy()
    for k in range(1, f):
        idx[axis] = slice(k, None, f)
        out += a[tuple(idx)]
    return out


def box_factor(extent, max_resolution: int | None, border: int = 1) -> int:
    """Smallest integer factor f with ceil(extent / f) + 2*border <= max_resolution on every axis
    (1 when ``max_resolution`` is None or already met)."""
    ext = np.asarray(extent, dtype=np.int64)
    if max_resolution is None:
        return 1
    room = int(max_resolution) - 2 * border
    if room < 1:
        raise ValueError(f"max_resolution {max_resolution} leaves no room inside a {border}-voxel "
                         f"border")
    return max(1, int(-(-int(ext.max()) // room)))
