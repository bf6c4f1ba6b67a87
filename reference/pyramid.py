"""NumPy twin of cl/pyramid.cl and of the host resampling in clvol/kernels/pyramid.py.

- ``resample_to_cube``: pad a grid's box to its centred cube (zero density), resample to base^3
  as cell means of the source field, per axis read as piecewise constant (box) when the base
  cell is >= the source cell and as the clamped linear interpolant otherwise. Written
  independently of the wrapper: the 1-D weights come from Gauss quadrature of the basis
  functions on pieces between their breakpoints, not from closed-form antiderivatives.
  Dense matrices: for small test grids only.
- ``mip_chain``: level l+1 = 2x2x2 mean of level l, summed in the kernel's order.
"""
import numpy as np

_GAUSS = np.array([-1.0, 1.0]) / np.sqrt(3.0)  # 2-point Gauss-Legendre on [-1, 1]: exact for cubics


def basis(g, i, n, linear):
    """Source voxel i's basis function at source voxel coordinate g (box [-0.5, n-0.5])."""
    g = np.asarray(g, np.float64)
    inside = (g >= -0.5) & (g <= n - 0.5)
    if linear:
        e = np.zeros(n)
        e[i] = 1.0
        v = np.interp(np.clip(g, 0, n - 1), np.arange(n), e)  # clamped linear interpolant
    else:
        v = (np.abs(g - i) <= 0.5).astype(np.float64)
    return np.where(inside, v, 0.0)


def resample_matrix(n_src, src_lo, src_hi, n_dst, dst_lo, dst_hi):
    src_cell = (src_hi - src_lo) / n_src
    dst_cell = (dst_hi - dst_lo) / n_dst
    linear = dst_cell < src_cell * (1 - 1e-12)
    a = np.zeros((n_dst, n_src))
    for k in range(n_dst):
        lo = (dst_lo + k * dst_cell - src_lo) / src_cell - 0.5
        hi = (dst_lo + (k + 1) * dst_cell - src_lo) / src_cell - 0.5
        # Every basis function is polynomial between half-integer breakpoints.
        brk = np.arange(np.ceil(2 * lo), np.floor(2 * hi) + 1) / 2
        pts = np.unique(np.concatenate([[lo], brk, [hi]]))
        for p0, p1 in zip(pts[:-1], pts[1:]):
            xs = 0.5 * (p0 + p1) + 0.5 * (p1 - p0) * _GAUSS
            for i in range(n_src):
                a[k, i] += 0.5 * (p1 - p0) * basis(xs, i, n_src, linear).sum()
        a[k] /= hi - lo
    return a


def resample_to_cube(density, bbox_min, bbox_max, base):
    """(base^3 float64 [z][y][x], cube_min, cube_size)."""
    bbox_min, bbox_max = np.asarray(bbox_min, float), np.asarray(bbox_max, float)
    size = float(np.max(bbox_max - bbox_min))
    cube_min = 0.5 * (bbox_min + bbox_max) - 0.5 * size
    nz, ny, nx = density.shape
    res = (nx, ny, nz)
    m = [resample_matrix(res[a], bbox_min[a], bbox_max[a], base, cube_min[a], cube_min[a] + size)
         for a in range(3)]
    out = np.einsum("zk,yj,xi,kji->zyx", m[2], m[1], m[0], density.astype(np.float64))
    return out, cube_min, size


def mip_chain(level0):
    """List of levels [base^3, (base/2)^3, ..., 1^3], float32, each the 2x2x2 mean of the last."""
    levels = [np.asarray(level0, np.float32)]
    while levels[-1].shape[0] > 1:
        s = levels[-1]
        c = [[[s[k::2, j::2, i::2] for i in (0, 1)] for j in (0, 1)] for k in (0, 1)]
        a = (c[0][0][0] + c[0][0][1]) + (c[0][1][0] + c[0][1][1])
        b = (c[1][0][0] + c[1][0][1]) + (c[1][1][0] + c[1][1][1])
        levels.append(((a + b) * np.float32(0.125)).astype(np.float32))
    return levels
