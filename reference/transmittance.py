"""NumPy twin of cl/transmittance.cl (float64). See that file for the equations.

Voxel units of a level: voxel (x, y, z) centred at integer (x, y, z), cube [-0.5, n - 0.5]^3,
arrays [z][y][x]. ``l`` is the unit direction toward the light; ``scale`` is
lambda^(i+1) * density_scale * voxel size, so tau = scale * integral of rho over voxel-unit length.

- ``brute``: exact integral of the trilinear field (2-point Gauss on pieces between the
  half-integer planes, where the field is cubic along a line), all voxels at once. Every ray
  starts at an integer point, so all rays share the same crossing distances m / (2 |l_a|).
- ``sweep``: the column sweep (light rays through the first slice's voxel centres, integrated
  slice by slice, then interpolated to each slice's voxels), for all voxels of a slice at once.
- ``combine_levels``: sum_l w_l T_l(base voxel centre) + bias.
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


def inside_fraction(b, e, n):
    """Fraction of the lateral segment from b to e (arrays) inside [-0.5, n - 0.5]."""
    d = e - b
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (-0.5 - b) / d, (n - 0.5 - b) / d
        t0 = np.where(d != 0, np.maximum(0.0, np.minimum(ta, tb)), 0.0)
        t1 = np.where(d != 0, np.minimum(1.0, np.maximum(ta, tb)),
                      np.where((b >= -0.5) & (b <= n - 0.5), 1.0, 0.0))
    return t0, t1


def sweep_steps(n, l):
    """Per sweep step j: (k, iu, iv, fu, fv): the slice index and the integer / fractional parts
    of j * (su, sv), the lateral drift of the light rays ("columns") after j slices."""
    a, sa, su, sv, _ = sweep_geometry(l)
    steps = []
    for j in range(n):
        k = n - 1 - j if sa > 0 else j
        iu, iv = int(np.floor(j * su)), int(np.floor(j * sv))
        steps.append((k, iu, iv, j * su - iu, j * sv - iv))
    return steps


def sweep(d, l, scale):
    """Optical depth by the column sweep (same algorithm as transmittance_sweep_block).

    Columns are the light rays through the voxel centres of the first slice (nearest the
    light), extended to a lattice; column c sits at lateral position c - j s in the slice of
    step j (s = (su, sv)). Each step adds to every column the integral along its segment from
    the previous slice (the face for j = 0) to the current one: c * Simpson(start, middle, end)
    of the field clamped at the faces, c the fraction of the segment inside the cube's side
    faces (exact when the segment is inside, or the field constant along it). Then each voxel
    of the slice takes the bilinear interpolation of its 4 surrounding columns."""
    d = np.asarray(d, np.float64)
    n = d.shape[0]
    a, sa, su, sv, inv_la = sweep_geometry(l)
    steps = sweep_steps(n, l)
    ou = -min(s[1] for s in steps)
    ov = -min(s[2] for s in steps)
    cols = np.zeros((n + 2 + ov + max(s[2] for s in steps), n + 2 + ou + max(s[1] for s in steps)))
    tau = np.zeros((n, n, n))
    w = np.arange(n + 1, dtype=np.float64)  # window-local column index
    wv, wu = np.meshgrid(w, w, indexing="ij")
    for j, (k, iu, iv, fu, fv) in enumerate(steps):
        seg = 0.5 if j == 0 else 1.0
        eu, ev = wu - fu, wv - fv                  # column positions in slice k
        bu, bv = eu + seg * su, ev + seg * sv      # ... at the start of the segment
        t0u, t1u = inside_fraction(bu, eu, n)
        t0v, t1v = inside_fraction(bv, ev, n)
        c = np.maximum(np.minimum(t1u, t1v) - np.maximum(t0u, t0v), 0.0)

        def rho(t):  # clamped (not zeroed) beyond the faces: c accounts for the outside part
            return grid_lookup(d, _to_xyz(a, bu + t * (eu - bu), bv + t * (ev - bv),
                                          k + sa * seg * (1 - t) + 0 * bu))

        win = cols[iv + ov:iv + ov + n + 1, iu + ou:iu + ou + n + 1]
        win += scale * seg * inv_la / 6 * c * (rho(0.0) + 4 * rho(0.5) + rho(1.0))
        _slice(tau, a, k)[...] = ((1 - fv) * ((1 - fu) * win[:n, :n] + fu * win[:n, 1:])
                                  + fv * ((1 - fu) * win[1:, :n] + fu * win[1:, 1:]))
    return tau


def combine_levels(t_levels, weights, bias):
    """sum_l w_l T_l + bias at the base voxel centres (T_l trilinear, clamped)."""
    base = t_levels[0].shape[0]
    z, y, x = np.meshgrid(*(np.arange(base, dtype=np.float64) + 0.5,) * 3, indexing="ij")
    c = np.stack([x, y, z], -1)
    out = np.full((base,) * 3, float(bias))
    for i, (w, t) in enumerate(zip(weights, t_levels)):
        out += w * grid_lookup(np.asarray(t, np.float64), c / 2 ** i - 0.5)
    return out
