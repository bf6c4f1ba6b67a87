"""NumPy twin of cl/viewdepth.cl: where along the camera rays the view-space F_ms source puts
its network queries.

The image is cut into blocks of ``block`` x ``block`` pixels (block (i, j) covers pixel
columns i*block .. (i+1)*block - 1 and rows j*block ..). Each block sends ``rays`` x
``rays`` sample rays through the continuous pixel positions

    x = i*block + (a + 1/2) block/rays,   y = j*block + (b + 1/2) block/rays,

(a, b = 0..rays-1; pixel k's centre is at k + 1/2, as in grid.h's camera_ray). What a camera
ray gathers from a source F is int T_cam(t) sigma_t(t) F(t) dt (docs/conventions.md), so the
block's in-scattering weight at distance t is the mean over its sample rays of
T_cam(t) sigma_t(t), and its cumulative form is

    C(t) = mean_r (1 - exp(-tau_r(t))),   tau_r(t) = optical depth from the camera along ray r.

The K query depths are the quantiles C(t_i) = (i + 1/2)/K * W, W = C(end), i = 0..K-1: the
midpoints of K slabs of equal in-scattering weight.

Quadrature: all sample rays of a block advance together over segments [t_lo + k dt,
t_lo + (k+1) dt], t_lo the smallest box entry of the block's rays. A ray's share of a segment
is its overlap with the ray's own stretch in the box, with sigma_t at the overlap's midpoint
(trilinear, clamped, as the marcher). C is kept at segment ends and is linear in between
(quantiles interpolate inside the segment that crosses the level). The march stops once every
ray is past its exit or has T_cam < ``stop`` (the marcher's threshold: nothing beyond reaches
the image). A block with W < EMPTY_WEIGHT (no sample ray meets the medium) is empty: its
depths are -1 and it costs no query.

``jitter`` (by, bx, 3), values in [0, 1), moves block (i, j)'s sample rays to
x = i*block + (a + jitter[..., 0]) block/rays (y likewise with jitter[..., 1]) and the levels
to (i + z)/K with z = jitter[..., 2] clamped to [MIN_LEVEL, 1] (a level of 0 would have no
crossing segment); None is 1/2 for all three, the deterministic placement above. Uniform
random jitter with K = 1 draws the depth from the block's in-scattering weight: a free-flight
sample conditioned on meeting the medium (the stochastic source).

Returns (depths float (by, bx, K), weight W (by, bx)), float64 here; the kernel is float32.
"""
import numpy as np

from reference.grid import box_intersect, grid_lookup

EMPTY_WEIGHT = 1e-5
MIN_LEVEL = 1e-6


def block_grid(width, height, block):
    """(bx, by): blocks across and down (the last ones may be partial)."""
    return -(-width // block), -(-height // block)


def sample_rays(forward, right, up, tan_half, width, height, block, rays, jitter=None):
    """(by, bx, rays*rays, 3) unit directions of every block's sample rays."""
    bx, by = block_grid(width, height, block)
    jit = np.full((by, bx, 3), 0.5) if jitter is None else np.asarray(jitter, np.float64)
    a = np.arange(rays)
    # x[j, i, b, a] = i*block + (a + jx[j, i]) block/rays; y likewise with the row index b
    x = (np.arange(bx)[None, :, None, None] * block
         + (a[None, None, None, :] + jit[:, :, 0, None, None]) * block / rays)
    y = (np.arange(by)[:, None, None, None] * block
         + (a[None, None, :, None] + jit[:, :, 1, None, None]) * block / rays)
    x, y = np.broadcast_arrays(x, y)                                       # (by, bx, rays, rays)
    d = _rays_at(forward, right, up, tan_half, width, height, x, y)
    return d.reshape(by, bx, rays * rays, 3)


def _rays_at(forward, right, up, tan_half, width, height, x, y):
    sx = (2 * x / width - 1) * tan_half * (width / height)
    sy = (1 - 2 * y / height) * tan_half
    d = (np.asarray(forward, np.float64) + sx[..., None] * np.asarray(right, np.float64)
         + sy[..., None] * np.asarray(up, np.float64))
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def view_depths(density, bbox_min, bbox_max, density_scale, origin, forward, right, up,
                tan_half, width, height, block, rays, k, step, stop=1e-3, jitter=None):
    density = np.asarray(density, np.float64)
    nz, ny, nx = density.shape
    bmin, bmax = np.asarray(bbox_min, np.float64), np.asarray(bbox_max, np.float64)
    cell = (bmax - bmin) / np.array([nx, ny, nz], np.float64)
    o = np.asarray(origin, np.float64)
    d = sample_rays(forward, right, up, tan_half, width, height, block, rays, jitter)
    by, bx, r, _ = d.shape
    z = (np.full(by * bx, 0.5) if jitter is None else
         np.clip(np.asarray(jitter, np.float64)[..., 2].ravel(), MIN_LEVEL, 1.0))
    d = d.reshape(-1, r, 3)
    nb = len(d)
    t0, t1 = box_intersect(np.broadcast_to(o, (nb * r, 3)), d.reshape(-1, 3), bmin, bmax)
    t0, t1 = t0.reshape(nb, r), t1.reshape(nb, r)
    hit = t0 <= t1
    t_lo = np.where(hit, t0, np.inf).min(axis=1)
    t_hi = np.where(hit, t1, -np.inf).max(axis=1)
    any_hit = hit.any(axis=1)
    t_lo = np.where(any_hit, t_lo, 0.0)
    n_steps = np.where(any_hit, np.ceil((t_hi - t_lo) / step), 0).astype(np.int64)

    # One march, keeping C at every segment end (the kernel marches twice instead).
    tau = np.zeros((nb, r))
    curve = [np.zeros(nb)]
    alive = any_hit.copy()
    for s in range(int(n_steps.max()) if nb else 0):
        alive &= s < n_steps
        if not alive.any():
            break
        ta, tb = t_lo + s * step, t_lo + (s + 1) * step
        lo = np.maximum(ta[:, None], t0)
        hi = np.minimum(tb[:, None], t1)
        length = np.where(alive[:, None] & hit & (hi > lo), hi - lo, 0.0)
        with np.errstate(invalid="ignore"):             # inf - inf of missed rays, unused
            mid = np.where(length > 0, 0.5 * (lo + hi), 0.0)
        p = o + mid[..., None] * d
        sigma = density_scale * grid_lookup(density, (p - bmin) / cell - 0.5)
        tau = tau + np.where(length > 0, sigma * length, 0.0)
        curve.append(np.where(alive, (-np.expm1(-tau)).mean(axis=1), curve[-1]))
        # Every ray past its exit or below the stop transmittance: nothing further is seen.
        done = ~hit | (tb[:, None] >= t1) | (np.exp(-tau) < stop)
        alive &= ~np.all(done, axis=1)
    curve = np.stack(curve, axis=1)                                        # (nb, steps + 1)
    w = curve[:, -1]
    depths = np.full((nb, k), -1.0)
    for b in np.flatnonzero(w >= EMPTY_WEIGHT):
        c = curve[b]
        for i in range(k):
            u = (i + z[b]) / k * w[b]
            s = int(np.argmax(c[1:] >= u))          # first segment whose end reaches u
            depths[b, i] = t_lo[b] + step * (s + (u - c[s]) / (c[s + 1] - c[s]))
    return depths.reshape(by, bx, k), np.where(w >= EMPTY_WEIGHT, w, 0.0).reshape(by, bx)


def free_flight_depths(density, bbox_min, bbox_max, density_scale, origin, forward, right, up,
                       tan_half, width, height, block, step, jitter, stop=1e-3):
    """One unconditioned free flight per block (the kernel's VIEW_FREE_FLIGHT): the block's
    one jittered ray (``jitter`` as above) marched over segments [t0 + k step, ...] from its
    own box entry t0, sigma_t at each segment's midpoint; the depth where the optical depth
    reaches -log(1 - z) (z clamped to [MIN_LEVEL, 1]), interpolated linearly inside its
    segment (tau is linear there). -1 and weight 0 where the ray leaves the box first, or
    its optical depth passes -log(stop) first; weight 1 for a collision.

    Returns (depths (by, bx, 1), weight (by, bx)) like view_depths."""
    density = np.asarray(density, np.float64)
    nz, ny, nx = density.shape
    bmin, bmax = np.asarray(bbox_min, np.float64), np.asarray(bbox_max, np.float64)
    cell = (bmax - bmin) / np.array([nx, ny, nz], np.float64)
    o = np.asarray(origin, np.float64)
    d = sample_rays(forward, right, up, tan_half, width, height, block, 1, jitter)[:, :, 0]
    by, bx, _ = d.shape
    z = np.clip(np.asarray(jitter, np.float64)[..., 2], MIN_LEVEL, 1.0)
    with np.errstate(divide="ignore"):
        target = -np.log1p(-z)                              # inf for z = 1: never reached
    tau_stop = -np.log(stop) if stop > 0 else np.inf
    depths = np.full((by, bx, 1), -1.0)
    for j in range(by):
        for i in range(bx):
            t0, t1 = box_intersect(o[None], d[j, i][None], bmin, bmax)
            t0, t1 = float(t0[0]), float(t1[0])
            if not t0 <= t1:
                continue
            tau = 0.0
            for s in range(int(np.ceil((t1 - t0) / step))):
                ta = t0 + s * step
                tb = min(ta + step, t1)
                p = o + 0.5 * (ta + tb) * d[j, i]
                dtau = density_scale * float(grid_lookup(density, ((p - bmin) / cell - 0.5)[None])[0]) * (tb - ta)
                if tau + dtau >= target[j, i]:
                    depths[j, i, 0] = ta + (tb - ta) * (target[j, i] - tau) / dtau
                    break
                tau += dtau
                if tau > tau_stop:
                    break
    return depths, (depths[..., 0] >= 0).astype(np.float64)
