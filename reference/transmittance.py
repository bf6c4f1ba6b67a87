"""NumPy twin of cl/transmittance.cl (float64). See that file for the equations.

Voxel units of a level: voxel (x, y, z) centred at integer (x, y, z), cube [-0.5, n - 0.5]^3,
arrays [z][y][x]. ``l`` is the unit direction toward the light; ``scale`` is
lambda^(i+1) * density_scale * voxel size, so tau = scale * integral of rho over voxel-unit length.

- ``brute``: exact integral of the trilinear field (2-point Gauss on pieces between the
  half-integer planes, where the field is cubic along a line), all voxels at once. Every ray
  starts at an integer point, so all rays share the same crossing distances m / (2 |l_a|).
- ``sweep``: the slice-by-slice algorithm, written per slice for all voxels of the slice.
- ``combine_levels``: sum_l w_l T_l(base voxel centre) + bias.
- ``transmittance_at``: trilinear lookup of a field over the cube at world points, T = 1 outside
  (how consumers read the fields).
"""
import numpy as np

from reference.grid import grid_lookup

_GAUSS = np.array([-1.0, 1.0]) / np.sqrt(3.0)


def _density_vox(d, p):
    """Trilinear (clamped) density at voxel-unit points p (..., 3), 0 outside the cube."""
    n = d.shape[0]
    inside = np.all((p >= -0.5) & (p <= n - 0.5), axis=-1)
    return np.where(inside, grid_lookup(d, p), 0.0)


def brute(d, l, scale):
    """Optical depth tau at every voxel centre of the cubic level d (n, n, n), float64."""
    d = np.asarray(d, np.float64)
    n = d.shape[0]
    l = np.asarray(l, np.float64)
    z, y, x = np.meshgrid(*(np.arange(n, dtype=np.float64),) * 3, indexing="ij")
    p = np.stack([x, y, z], axis=-1)
    t_max = min(float((n - 0.5 + 0.5) / abs(c)) for c in l if c != 0)  # >= every exit
    cuts = [np.arange(1, int(np.ceil(t_max * 2 * abs(c))) + 1) * 0.5 / abs(c)
            for c in l if c != 0]
    ts = np.unique(np.concatenate([[0.0]] + cuts))
    ts = ts[ts <= t_max + 1e-12]
    tau = np.zeros((n, n, n))
    for t0, t1 in zip(ts[:-1], ts[1:]):
        for gx in _GAUSS:
            t = 0.5 * (t0 + t1) + 0.5 * (t1 - t0) * gx
            tau += 0.5 * (t1 - t0) * _density_vox(d, p + t * l)
    return scale * tau


def sweep_geometry(l):
    l = np.asarray(l, np.float64)
    a = int(np.argmax(np.abs(l)))
    lat = [ax for ax in range(3) if ax != a]
    la = abs(l[a])
    return a, (1 if l[a] > 0 else -1), l[lat[0]] / la, l[lat[1]] / la, 1.0 / la


def _to_xyz(a, pu, pv, pa):
    if a == 2:
        return np.stack([pu, pv, pa], -1)
    if a == 1:
        return np.stack([pu, pa, pv], -1)
    return np.stack([pa, pu, pv], -1)


def _slice(d, a, k):
    """Slice k along axis a as an array indexed [v][u]."""
    if a == 2:
        return d[k, :, :]
    if a == 1:
        return d[:, k, :]
    return d[:, :, k]


def _prev_weights(q, n):
    """(i0, i1, w0, w1) for tau_prev at lateral positions q in [-0.5, n - 0.5]."""
    below, above = q < 0, q > n - 1
    i0 = np.clip(np.floor(q), 0, n - 1).astype(np.int64)
    i1 = np.minimum(i0 + 1, n - 1)
    f = q - i0
    w0 = np.where(below, np.maximum(2 * (q + 0.5), 0), np.where(above, np.maximum(2 * (n - 0.5 - q), 0), 1 - f))
    w1 = np.where(below | above, 0.0, f)
    return i0, i1, w0, w1


def sweep(d, l, scale):
    """Optical depth by the slice sweep (same algorithm as transmittance_sweep_slice)."""
    d = np.asarray(d, np.float64)
    n = d.shape[0]
    a, sa, su, sv, inv_la = sweep_geometry(l)
    v, u = np.meshgrid(np.arange(n, dtype=np.float64), np.arange(n, dtype=np.float64), indexing="ij")
    tau = np.zeros((n, n, n))
    prev = None
    for j in range(n):
        k = n - 1 - j if sa > 0 else j
        seg = 0.5 if j == 0 else 1.0
        du, dv, da = su * seg, sv * seg, sa * seg
        c = np.ones_like(u)
        with np.errstate(divide="ignore", invalid="ignore"):
            for pos, dd in ((u, du), (v, dv)):
                c = np.where(pos + dd < -0.5, np.minimum(c, (-0.5 - pos) / dd), c)
                c = np.where(pos + dd > n - 0.5, np.minimum(c, (n - 0.5 - pos) / dd), c)
        r0 = _slice(d, a, k)
        rm = grid_lookup(d, _to_xyz(a, u + 0.5 * c * du, v + 0.5 * c * dv, k + 0.5 * c * da))
        r1 = grid_lookup(d, _to_xyz(a, u + c * du, v + c * dv, k + c * da))
        cur = scale * seg * inv_la * c * (r0 + 4 * rm + r1) / 6
        if j > 0:
            u0, u1, wu0, wu1 = _prev_weights(u + du, n)
            v0, v1, wv0, wv1 = _prev_weights(v + dv, n)
            tp = (wv0 * (wu0 * prev[v0, u0] + wu1 * prev[v0, u1])
                  + wv1 * (wu0 * prev[v1, u0] + wu1 * prev[v1, u1]))
            cur = cur + np.where(c >= 1, tp, 0.0)
        _slice(tau, a, k)[...] = cur
        prev = cur
    return tau


def graded(levels, density_scale, l, lam, cube_size, method="brute"):
    """List of T_l (float64) for a list of levels [base^3, ..., 1^3]."""
    fn = brute if method == "brute" else sweep
    out = []
    for i, d in enumerate(levels):
        n = d.shape[0]
        out.append(np.exp(-fn(d, l, lam ** (i + 1) * density_scale * cube_size / n)))
    return out


def combine_levels(t_levels, weights, bias):
    """sum_l w_l T_l + bias at the base voxel centres (T_l trilinear, clamped)."""
    base = t_levels[0].shape[0]
    z, y, x = np.meshgrid(*(np.arange(base, dtype=np.float64) + 0.5,) * 3, indexing="ij")
    c = np.stack([x, y, z], -1)
    out = np.full((base,) * 3, float(bias))
    for i, (w, t) in enumerate(zip(weights, t_levels)):
        out += w * grid_lookup(np.asarray(t, np.float64), c / 2 ** i - 0.5)
    return out


def transmittance_at(field, cube_min, cube_size, points):
    """Trilinear lookup of a cube field [z][y][x] at world points (N, 3); 1 outside the cube."""
    n = field.shape[0]
    g = (np.asarray(points, np.float64) - np.asarray(cube_min)) / (cube_size / n) - 0.5
    inside = np.all((g >= -0.5) & (g <= n - 0.5), axis=-1)
    return np.where(inside, grid_lookup(np.asarray(field, np.float64), g), 1.0)
