"""NumPy twin of cl/gather.cl: the template gather (clvol/features/layout.py is the contract).

Written independently of the kernel's loop structure, in float64:
- frame, coarse level and highlight levels from this module's own definitions (from the docs);
- t_enter by slab-testing the ray p + t l against every non-empty cell of the coarse level and
  taking the largest exit parameter (no DDA);
- density and graded levels by explicit trilinear weights over the level's voxel centres
  (reference.grid.grid_lookup for the T_m values at those centres);
- phase at the exact alpha of each query from the volume phase's Legendre series (``cap_average``),
  not the kernel's alpha table nor clvol.features.phasetable's lobe tables;
- the template table read from its .npz with NumPy (``Templates``), not through clvol's loader;
- render transmittance as sum_m w_m levels[m] + b (no baked grid);
- ``baked_grid``: the twin of the bake kernels (gather_bake's definition), by direct trilinear
  lookups of every level at every level's voxel centres (the kernels split them into passes).
Arrays are the pyramid's / graded fields' concatenated float32 data (any object with
base_resolution, n_levels, cube_min, cube_size, level_offsets, data works, e.g. a stand-in).
"""
import numpy as np

from pathlib import Path

from reference.grid import grid_lookup
from reference.phase import phase_eval

TEMPLATE_FILE = Path(__file__).resolve().parents[1] / "clvol" / "data" / "templates.npz"

# Written here from docs/templates.md and docs/conventions.md, not imported from the code the
# twin checks (a shared helper's mistake would pass both).
COARSE_CELLS = 32          # t_enter's level: the finest with at most 32^3 cells
FRAME_EPS = 1e-4           # |omega x l| below this: the frame's fallback axis


def coarse_level(base_resolution):
    """The pyramid level with at most COARSE_CELLS cells a side: base / 2^level <= 32."""
    level = 0
    while (base_resolution >> level) > COARSE_CELLS:
        level += 1
    return level


def level_for_spacing(spacing_voxels, base_resolution):
    """The level whose voxel is nearest the spacing in log2: round(log2(s)) (halves up),
    clamped to the pyramid's levels 0 .. log2(base); spacing 0 reads level 0."""
    top = int(round(np.log2(base_resolution)))
    s = np.asarray(spacing_voxels, np.float64)
    out = np.zeros(s.shape, np.int64)
    pos = s > 0
    out[pos] = np.floor(np.log2(s[pos]) + 0.5)
    return np.clip(out, 0, top)


def template_frame(light_dir, omega):
    """z = l; x = omega's part perpendicular to l, normalised; y = z cross x. Where omega is
    (nearly) parallel to l, x comes from the world axis least aligned with l (lowest index on
    ties) instead (docs/conventions.md, "Template frame")."""
    l = np.broadcast_to(np.asarray(light_dir, np.float64), np.shape(omega))
    w = np.asarray(omega, np.float64)
    x = np.empty_like(w)
    for i in np.ndindex(w.shape[:-1]):
        li, wi = l[i], w[i]
        if np.linalg.norm(np.cross(wi, li)) < FRAME_EPS:
            e = np.zeros(3)
            e[int(np.argmin(np.abs(li)))] = 1.0
            v = e - np.dot(e, li) * li
        else:
            v = wi - np.dot(wi, li) * li
        x[i] = v / np.linalg.norm(v)
    return x, np.cross(l, x), l


class Templates:
    """The packaged template table read with NumPy alone (the data file is the contract;
    clvol.features.templates' loader is not used): points (frame units), layer per point,
    spacing per layer (cube units), cone half-angle per point."""

    def __init__(self, path=TEMPLATE_FILE):
        with np.load(path, allow_pickle=False) as z:
            self.points = np.asarray(z["points"], np.float64)
            self.layer = np.asarray(z["layer"], np.int64)
            self.spacing = np.asarray(z["spacing"], np.float64)
            self.half_angle = np.asarray(z["half_angle"], np.float64)
            self.n_diffuse_layers = int(z["n_diffuse_layers"])
        self.n_points = len(self.points)
        self.is_highlight = self.layer >= self.n_diffuse_layers

    def diffuse_levels(self, base_resolution):
        """Each diffuse layer reads the level whose voxel is nearest its spacing."""
        return level_for_spacing(self.spacing[:self.n_diffuse_layers] * base_resolution,
                                 base_resolution)


def cap_average(mu, beta, lobes, tol=1e-13):
    """The volume phase fbar(mu, beta): the phase function averaged over the cap of
    half-angle beta whose axis makes cosine mu with its argument (docs/templates.md).
    Evaluated from its Legendre series, independent of the lobe tables: by Funk-Hecke,
        fbar = sum_l (2l + 1) / (4 pi) g^l c_l(beta) P_l(mu),
        c_l = (P_{l-1}(cos beta) - P_{l+1}(cos beta)) / ((2l + 1)(1 - cos beta)), c_0 = 1,
    the cap average of P_l (c_l = 1 at beta = 0), summed until |g|^l < tol, per HG lobe."""
    mu = np.clip(np.asarray(mu, np.float64), -1.0, 1.0)
    beta = np.broadcast_to(np.asarray(beta, np.float64), mu.shape)
    if not lobes:
        return np.full(mu.shape, 1.0 / (4.0 * np.pi))
    x0 = np.cos(beta)
    one_minus = 2.0 * np.sin(beta / 2.0) ** 2          # 1 - cos beta without cancellation
    cap = one_minus > 0
    safe = np.where(cap, one_minus, 1.0)
    out = np.zeros(mu.shape)
    for g, w in lobes:
        n_terms = 1 if g == 0 else int(np.ceil(np.log(tol) / np.log(abs(g)))) + 1
        p_prev, p = np.ones(mu.shape), mu.copy()            # P_0, P_1 at mu
        q_prev, q = np.ones(mu.shape), x0.copy()            # P_0, P_1 at cos beta
        q_next = (3 * x0 * q - q_prev) / 2                  # P_2 at cos beta
        total = np.ones(mu.shape)                           # l = 0: c_0 P_0 = 1
        for l in range(1, n_terms + 1):
            c = np.where(cap, (q_prev - q_next) / ((2 * l + 1) * safe), 1.0)
            total += (2 * l + 1) * g ** l * c * p
            p_prev, p = p, ((2 * l + 1) * mu * p - l * p_prev) / (l + 1)
            q_prev, q = q, q_next
            q_next = ((2 * l + 3) * x0 * q - (l + 1) * q_prev) / (l + 2)
        out += w * total / (4.0 * np.pi)
    return out


def phase_features(lobes, points, half_angle, alpha):
    """log1p phase feature per query alpha and template point (seed eq. 5, docs/conventions.md):
    in the frame omega = (sin alpha, 0, -cos alpha) and light reaches p along d = -u, so
    fbar(u_z) * fbar(u_z cos alpha - u_x sin alpha); the centre point holds f(cos alpha)."""
    alpha = np.atleast_1d(np.asarray(alpha, np.float64))[:, None]
    r = np.linalg.norm(points, axis=1)
    u = points / np.where(r > 0, r, 1.0)[:, None]
    mu_in = np.broadcast_to(u[None, :, 2], (alpha.shape[0], len(u)))
    mu_out = u[None, :, 2] * np.cos(alpha) - u[None, :, 0] * np.sin(alpha)
    feat = cap_average(mu_in, half_angle[None, :], lobes) * cap_average(mu_out, half_angle[None, :],
                                                                        lobes)
    centre = r == 0
    feat[:, centre] = phase_eval(np.cos(alpha), list(lobes))
    return np.log1p(feat)


def level_array(pyr, data, level):
    n = pyr.base_resolution >> level
    off = int(pyr.level_offsets[level])
    return np.asarray(data[off:off + n ** 3], np.float64).reshape(n, n, n)


def light_entry(pyr, points, light_dir):
    """Largest t >= 0 at which p + t l leaves a non-empty coarse cell (0 if none)."""
    c = coarse_level(pyr.base_resolution)
    occ = level_array(pyr, pyr.data, c) > 0
    n = occ.shape[0]
    bs = pyr.cube_size / n
    cells = np.argwhere(occ)[:, ::-1]                      # (k, 3) as x, y, z
    lo = np.asarray(pyr.cube_min) + cells * bs
    hi = lo + bs
    p = np.asarray(points, np.float64)[:, None, :]
    l = np.asarray(light_dir, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (lo[None] - p) / l
        tb = (hi[None] - p) / l
    tmin = np.where(l == 0, np.where((p >= lo[None]) & (p <= hi[None]), -np.inf, np.inf),
                    np.minimum(ta, tb))
    tmax = np.where(l == 0, np.where((p >= lo[None]) & (p <= hi[None]), np.inf, -np.inf),
                    np.maximum(ta, tb))
    t0 = np.maximum(tmin.max(-1), 0.0)
    t1 = tmax.min(-1)
    hit = t0 < t1
    return np.where(hit, t1, 0.0).max(-1, initial=0.0) if len(cells) else np.zeros(len(points))


def _corners(g, n):
    """Trilinear corner indices (x0, x1, y0, ...) and weights, clamped like grid.h."""
    c = np.clip(g, 0, n - 1)
    i0 = c.astype(np.int64)
    i1 = np.minimum(i0 + 1, n - 1)
    return i0, i1, c - i0


def gather(pyr, graded_data, points, omegas, light_dir, lobes, density_scale, mode="train",
           level_weights=None, bias=0.0):
    """Returns dict(features [N][3][NP], levels [N][L][NP] (train), t_enter [N], level [N][NP])."""
    tpl = Templates()
    pts = np.asarray(points, np.float64)
    om = np.asarray(omegas, np.float64)
    l = np.asarray(light_dir, np.float64)
    n, L, NP = len(pts), pyr.n_levels, tpl.n_points
    x, y, z = template_frame(l, om)
    t_enter = light_entry(pyr, pts, l)
    hl = tpl.is_highlight
    scale = np.where(hl[None, :], t_enter[:, None], pyr.cube_size)             # (N, NP)
    u = tpl.points
    s = pts[:, None, :] + scale[..., None] * (u[None, :, 0:1] * x[:, None] + u[None, :, 1:2] * y[:, None]
                                              + u[None, :, 2:3] * z[:, None])
    lvl = np.empty((n, NP), np.int64)
    dl = tpl.diffuse_levels(pyr.base_resolution)
    lvl[:, ~hl] = dl[tpl.layer[~hl]]
    sp = tpl.spacing[tpl.layer[hl]] * pyr.base_resolution / pyr.cube_size   # base voxels per unit t
    lvl[:, hl] = level_for_spacing(sp[None, :] * t_enter[:, None], pyr.base_resolution)
    cmin = np.asarray(pyr.cube_min, np.float64)
    inside = np.all((s >= cmin) & (s <= cmin + pyr.cube_size), axis=-1)
    dens = np.zeros((n, NP))
    levels = np.ones((n, L, NP))
    for lv in np.unique(lvl):
        sel = lvl == lv
        nl = pyr.base_resolution >> lv
        vox = pyr.cube_size / nl
        g = (s[sel] - cmin) / vox - 0.5
        rho = grid_lookup(level_array(pyr, pyr.data, lv), g)
        dens[sel] = np.where(inside[sel], rho * density_scale * vox, 0.0)
        if mode == "train" or level_weights is not None:
            (x0, y0, z0), (x1, y1, z1), (fx, fy, fz) = [np.moveaxis(a, -1, 0) for a in _corners(g, nl)]
            for m in range(L):
                tm = level_array(pyr, graded_data, m)
                nm = pyr.base_resolution >> m

                def at(ix, iy, iz):
                    c = (np.stack([ix, iy, iz], -1) + 0.5) * (nm / nl) - 0.5
                    return grid_lookup(tm, c)
                val = ((1 - fz) * ((1 - fy) * ((1 - fx) * at(x0, y0, z0) + fx * at(x1, y0, z0))
                                   + fy * ((1 - fx) * at(x0, y1, z0) + fx * at(x1, y1, z0)))
                       + fz * ((1 - fy) * ((1 - fx) * at(x0, y0, z1) + fx * at(x1, y0, z1))
                               + fy * ((1 - fx) * at(x0, y1, z1) + fx * at(x1, y1, z1))))
                tmp = levels[:, m, :]
                tmp[sel] = np.where(inside[sel], val, 1.0)
    feats = np.zeros((n, 3, NP))
    feats[:, 0] = np.log1p(dens)
    if level_weights is not None:
        feats[:, 1] = np.einsum("l,nlj->nj", np.asarray(level_weights, np.float64), levels) + bias
    alpha = np.arccos(np.clip(-(om @ l), -1.0, 1.0))
    feats[:, 2] = phase_features(tuple(lobes or ()), tpl.points, tpl.half_angle, alpha)
    out = {"features": feats, "t_enter": t_enter, "level": lvl, "alpha": alpha}
    if mode == "train":
        out["levels"] = levels
    return out


def baked_grid(pyr, graded_data, density_scale, level_weights, bias):
    """Per level l: (tau, C) arrays (n_l, n_l, n_l), tau = rho_l * density_scale * voxel size,
    C = sum_m w_m T_m(centre of the voxel at level m's coordinates) + bias."""
    out = []
    for lv in range(pyr.n_levels):
        n = pyr.base_resolution >> lv
        c = np.arange(n) + 0.5
        zz, yy, xx = np.meshgrid(c, c, c, indexing="ij")
        acc = np.full((n, n, n), float(bias))
        for m in range(pyr.n_levels):
            nm = pyr.base_resolution >> m
            g = np.stack([xx, yy, zz], -1) * (nm / n) - 0.5
            acc += level_weights[m] * grid_lookup(level_array(pyr, graded_data, m), g)
        tau = level_array(pyr, pyr.data, lv) * density_scale * (pyr.cube_size / n)
        out.append((tau, acc))
    return out
