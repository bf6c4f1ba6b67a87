"""NumPy twin of cl/raymarch.cl: the ray marcher (exact single scattering + a pluggable
multiple-scattering source), one ray per pixel centre, all rays marched together.

Pixel equation (docs/conventions.md), omega = -d toward the camera, l toward the light:

    L = int_0^D T_cam(t) sigma_s(x_t) E (F_1 + F_ms)(x_t, omega) dt + T_cam(D) L_background

Quadrature (energy-conserving, Hillaire 2016): the ray's stretch inside the box [t0, t1] is cut
into segments [t_a, t_b] = [t0 + k dt, min(t0 + (k + 1) dt, t1)], k = 0, 1, ...; on each, the
extinction sigma_t is taken at the midpoint and the segment is integrated exactly against its
own extinction for a source F that is constant, or varies linearly, along it:

    int_{t_a}^{t_b} T_cam(t) sigma_t F(t) dt = T_cam(t_a) (1 - exp(-tau)) F(t_s),
    tau = sigma_t (t_b - t_a),   t_s = t_a + frac(tau) (t_b - t_a),
    frac(tau) = 1/tau - e^-tau / (1 - e^-tau)   (series 1/2 - tau/12 + tau^3/720 below 0.05),

t_s being the mean position of the segment's extinction events (the midpoint for a thin
segment, ~1/tau of the way in for an opaque one). A source read at the midpoint instead is
wrong by a factor e^(sigma dt / 2 ...) in optically thick segments: at 3 optical depths per
voxel, steps of one voxel were 8% off the converged image that way, 2% with t_s
(tests/test_raymarch.py, docs/raymarch.md).

Because albedo and E are constant over the medium, sigma_s E F = albedo E (sigma_t F): the march
accumulates colour-free sums and multiplies by albedo * E once per ray. 1 - exp(-tau) is
computed as -expm1(-tau) (no cancellation for thin segments); no division by sigma_t occurs.

Sources (``source``):
    "none"       F_ms = 0                                       (single scattering only)
    "wrenninge"  F_ms = sum_{i=1}^{N-1} b^i f(mu; g c^i) T_light^(a^i)   (Wrenninge octaves;
                 every lobe's g is scaled by c^i)
    "lattice"       F_ms = trilinear lookup in a precomputed RGB (or grey) grid of F_ms values
    "view"       F_ms from the view-space table (1 + C, by, bx, K): per block of view_block^2
                 pixels, K distances along the camera rays (plane 0; -1 marks an empty block)
                 and F_ms there (planes 1..C). A pixel's knots blend the four nearest blocks'
                 knots index by index, bilinearly between block centres ((i + 1/2) view_block
                 in pixels, clamped at the image edge), over the non-empty blocks only
                 (weights renormalised; no such block: F_ms = 0). F_ms(t) is the piecewise-
                 linear interpolant of the pixel's knots, constant before the first and after
                 the last, written v_0 + sum_k (v_{k+1} - v_k) clamp((t - d_k) / (d_{k+1} - d_k),
                 0, 1) with the span floored at 1e-30 (equal knots: a step)
F_1 = f(mu) T_light with mu = dot(-l, omega) = dot(l, d), T_light read trilinearly (clamped) from
the exact light transmittance field (lambda = 1) on the pyramid's cube. The field holds T_light
(``light_quantity="transmittance"``, the default) or its optical depth tau_l
(``"optical_depth"``, T_light = exp(-tau_l)). The two readings differ between voxel centres:
blending tau is exact along the light in a homogeneous medium (where a linear blend of T is
too bright: 54% half-way at 2 optical depths per voxel) but too dark across shadow edges
(exp of a mean <= mean of exp); on the shipped examples blending T was measured closer to the
path tracer (docs/raymarch.md). Octaves use T_light^(a^i) = exp(-a^i tau_l), tau_l = -log T_light.

Empty space (``skip_empty``): if the midpoint of the current segment lies in a coarse
majorant block whose majorant is 0 (majorant.h: then the trilinear density is exactly 0
anywhere in the block and half a voxel around it), the march jumps to the first segment whose
(untruncated) midpoint lies at or past the block's exit (up to SKIP_PASSES jumps before each
evaluated segment). Every skipped segment has zero
density, so its contribution is exactly 0 and its factor exp(-0) exactly 1: skipping changes
no bit of the image.

Early termination: a ray stops once T_cam < ``threshold``. The light it would still have
gathered is at most T_cam * max(albedo E (F_1 + F_ms), L_background) <= threshold * that
maximum, so the absolute error of a pixel is below ``threshold`` times the largest source
radiance along it (per channel). The background term T_cam * L_background is added with the
T_cam reached (exit or stop).

AOVs: ``single``, ``multiple`` (RGB), ``total`` = single + multiple + T_cam L_background,
``alpha`` = 1 - T_cam(exit), accumulated as sum T_cam(t_a)(1 - exp(-tau)) (exact in exact
arithmetic and free of the cancellation of 1 - T for thin media), and ``depth`` = the mean
distance from the camera of the first extinction event given that one happens inside the box:

    depth = int t T_cam(t) sigma_t(t) dt / int T_cam(t) sigma_t(t) dt   (0 where alpha = 0),

integrated per segment exactly for a constant sigma_t: its share T_cam(t_a)(1 - e^-tau) times
its mean position t_s.

Environment (``env``, kernel define ENV): a field (2 C, n, n, n), C = 1 or 3, over the cube
env_min .. env_min + env_size, read trilinearly (clamped) at every segment's source point t_s
like the light field: planes 0..C-1 are the environment's single-scattered radiance per unit
extinction (albedo, phase and transmittance toward the sky folded in by
clvol/render/environment.py), planes C..2C-1 its multiple-scattering approximation. Their
march integrals, times ``env_colour`` (RGB; the sky's colour when C = 1), are added to
``single`` and ``multiple``. The lookup happens whether or not the sun lights the medium
(``lit``). ``bg_image`` (H, W, 3), when given, replaces the constant background per pixel
(kernel define BG_IMAGE: an environment map seen along each camera ray).

Emission (``emission``, kernel define EMISSION; docs/conventions.md "Emission"): planes
(C, ez, ey, ex), C = 1 or 3, over em_min .. em_max, Le = em_colour * planes, read trilinearly
(clamped) at every segment's source point t_s; with ``em_box`` Le is 0 outside that box. The
medium emits sigma_a Le with sigma_a = sigma_t (1 - albedo), so a segment adds exactly

    int T_cam sigma_t (1 - albedo) Le dt = T_cam(t_a) (1 - e^-tau) (1 - albedo) Le(t_s)

(for Le constant or linear along the segment, as for the in-scattering source); the sum goes
to the ``emission`` layer and into ``total``. Emitted light that scatters is not simulated
here (the path tracer has it).

Everything runs in float64 on the float32 inputs; the kernel runs in float32 (tolerances in
tests/test_raymarch.py).
"""
import numpy as np

from reference.grid import box_intersect, camera_rays, grid_lookup
from reference.phase import phase_eval

SERIES_BELOW = 0.05
SKIP_PASSES = 4  # skips per march iteration (as the kernel; any number gives the same image)


def mean_fraction(tau):
    """1/tau - e^-tau / (1 - e^-tau): the mean position, as a fraction of the segment's length,
    of the extinction events in a segment of optical depth tau (see module doc)."""
    tau = np.asarray(tau, np.float64)
    series = 0.5 - tau * (1.0 / 12.0 - tau * tau / 720.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        direct = 1.0 / tau - np.exp(-tau) / -np.expm1(-tau)
    return np.where(tau < SERIES_BELOW, series, direct)


def _lookup(values, lo, cell, p):
    """Trilinear clamped lookup of a [z][y][x] grid whose cell 0 starts at lo."""
    return grid_lookup(values, (p - lo) / cell - 0.5)


def octave_weights(mu, lobes, octaves, b, c):
    """(N-1, ...) weights b^i f(mu; g c^i) of the Wrenninge octaves i = 1..N-1."""
    out = []
    for i in range(1, octaves):
        scaled = [(g * c ** i, w) for g, w in lobes] if lobes else lobes
        out.append(b ** i * phase_eval(mu, scaled))
    return np.array(out).reshape((octaves - 1,) + np.shape(mu))


def raymarch(density, bbox_min, bbox_max, medium,
             majorant, block,
             light, cube_min, cube_size,
             ms_lattice, ms_bbox_min, ms_bbox_max,
             origin, forward, right, up, tan_half, width, height,
             sun, background,
             source="wrenninge", octaves=3, a=0.5, b=0.5, c=0.5,
             step=None, threshold=1e-3, skip_empty=True, lit=True,
             light_quantity="transmittance", view_block=4, env=None, env_min=(0, 0, 0),
             env_size=1.0, env_colour=(1, 1, 1), bg_image=None, emission=None,
             em_min=(0, 0, 0), em_max=(1, 1, 1), em_colour=(1, 1, 1), em_box=False):
    """Render one image. Returns a dict of float64 arrays: total, single, multiple (H, W, 3),
    alpha, depth (H, W); with ``emission``, also emission (H, W, 3); and "stopped_at_bound",
    the number of rays the progress bound stopped (an int).

    density      [nz][ny][nx] raw density over bbox_min..bbox_max
    medium       the optical properties, read by name: density_scale (sigma_t = density *
                 density_scale), RGB albedo, phase.lobes (each with .g and .weight)
    majorant     [mz][my][mx] per-block majorant (majorant.h), block = fine voxels per block
    light        [n][n][n] the exact light transmittance field (lambda = 1) over the cube
                 cube_min .. cube_min + cube_size: T_light, or its optical depth with
                 light_quantity="optical_depth"
    ms_lattice      (C, gz, gy, gx), C = 1 or 3, F_ms over ms_bbox_min..ms_bbox_max ("lattice" source)
    camera       origin, basis (forward, right, up), tan(fov_y / 2), width x height
    sun          the distant light, read by name: direction (unit, toward the light) and
                 irradiance E (RGB); background: RGB
    step         segment length in world units; threshold: early-termination transmittance
    lit          False when albedo * E is 0: no light lookups (F_1 and F_ms are not needed)
    """
    f64 = np.float64
    density_scale, albedo = medium.density_scale, medium.albedo
    lobes = [(lo.g, lo.weight) for lo in medium.phase.lobes]
    density = np.asarray(density)
    nz, ny, nx = density.shape
    bmin, bmax = np.asarray(bbox_min, f64), np.asarray(bbox_max, f64)
    cell = (bmax - bmin) / np.array([nx, ny, nz], f64)
    bsize = cell * block
    mres = np.array(majorant.shape[::-1])
    o = np.asarray(origin, f64)
    d = camera_rays(np.asarray(forward, f64), np.asarray(right, f64), np.asarray(up, f64),
                    float(tan_half), width, height).reshape(-1, 3)
    n_rays = len(d)
    l = np.asarray(sun.direction, f64)
    mu = d @ l                                    # dot(-l, omega) with omega = -d
    f0 = phase_eval(mu, lobes)
    if source == "wrenninge" and octaves > 1:
        ow = octave_weights(mu, lobes, octaves, b, c)
        oa = np.array([a ** i for i in range(1, octaves)])
    light_cell = float(cube_size) / light.shape[0]
    if source == "lattice":
        ms_lattice = np.asarray(ms_lattice)
        gmin, gmax = np.asarray(ms_bbox_min, f64), np.asarray(ms_bbox_max, f64)
        gcell = (gmax - gmin) / np.array(ms_lattice.shape[1:][::-1], f64)

    if source == "view":
        vd, vv = view_knots(np.asarray(ms_lattice, f64), view_block, width, height)
    t0, t1 = box_intersect(np.broadcast_to(o, d.shape), d, bmin, bmax, tmin=0.0)
    k = np.zeros(n_rays)
    T = np.ones(n_rays)
    S = np.zeros(n_rays)
    M = np.zeros((n_rays, ms_lattice.shape[0] if source == "lattice" else
                  ms_lattice.shape[0] - 1 if source == "view" else 1))
    A = np.zeros(n_rays)
    D = np.zeros(n_rays)
    if env is not None:
        env = np.asarray(env)
        env_c = env.shape[0] // 2
        env_cell = float(env_size) / env.shape[1]
        emin = np.asarray(env_min, f64)
        ES = np.zeros((n_rays, env_c))
        EM = np.zeros((n_rays, env_c))
    if emission is not None:
        emission = np.asarray(emission)
        em_c = emission.shape[0]
        em_lo, em_hi = np.asarray(em_min, f64), np.asarray(em_max, f64)
        em_cell = (em_hi - em_lo) / np.array(emission.shape[1:][::-1], f64)
        EE = np.zeros((n_rays, em_c))
    hit = t0 <= t1
    dt = float(step)
    # The kernel's progress bound, in float32 as the kernel computes it: a ray stops where its
    # next segment would not start past the current one (float32 t0 + (k + 1) dt == t0 + k
    # dt: k past 2^24, or dt below t's rounding, a camera far from a small box); elsewhere it
    # never holds. Those rays are counted ("stopped_at_bound").
    f32 = np.float32
    t0_32, dt_32 = t0.astype(f32), f32(dt)
    stopped = np.zeros(n_rays, bool)

    while True:
        ta = np.where(hit, t0 + k * dt, np.inf)
        go = hit & (ta < t1) & (T >= threshold)
        with np.errstate(invalid="ignore", over="ignore"):
            progress = (t0_32 + (k + 1).astype(f32) * dt_32) > (t0_32 + k.astype(f32) * dt_32)
        active = go & progress
        if not active.any():
            stopped = go & ~progress
            break
        for _ in range(SKIP_PASSES if skip_empty else 0):
            # Untruncated midpoint of the current segment (0 for idle rays: stays finite).
            tq = np.where(active, ta + 0.5 * dt, 0.0)
            p = o + tq[:, None] * d
            cb = np.clip(np.floor((p - bmin) / bsize), 0, mres - 1).astype(np.int64)
            empty = active & (majorant[cb[:, 2], cb[:, 1], cb[:, 0]] == 0)
            if not empty.any():
                break
            face = bmin + (cb + (d > 0)) * bsize
            with np.errstate(divide="ignore", invalid="ignore"):
                t_axis = np.where(d != 0, (face - o) / d, np.inf)
            k_star = np.ceil((t_axis.min(axis=1) - t0) / dt - 0.5)
            k = np.where(empty, np.maximum(k + 1, k_star), k)
            ta = np.where(hit, t0 + k * dt, np.inf)
            active &= ta < t1
        tb = np.minimum(ta + dt, t1)
        length = np.where(active, tb - ta, 0.0)
        ta = np.where(active, ta, 0.0)
        p = o + (ta + 0.5 * length)[:, None] * d
        sigma = density_scale * _lookup(density, bmin, cell, p)
        tau = sigma * length
        a_seg = -np.expm1(-tau)
        w = T * a_seg
        ts = ta + mean_fraction(tau) * length          # the source's sample point
        ps = o + ts[:, None] * d
        if lit:
            lf = _lookup(light, np.asarray(cube_min, f64), light_cell, ps)
            with np.errstate(divide="ignore"):
                tau_l = lf if light_quantity == "optical_depth" else -np.log(lf)
            S += w * (np.exp(-lf) if light_quantity == "optical_depth" else lf)
            if source == "wrenninge" and octaves > 1:
                M[:, 0] += w * (ow * np.exp(-oa[:, None] * tau_l[None, :])).sum(axis=0)
            elif source == "lattice":
                for ch in range(ms_lattice.shape[0]):
                    M[:, ch] += w * _lookup(ms_lattice[ch], gmin, gcell, ps)
            elif source == "view":
                M += w[:, None] * view_interp(vd, vv, ts)
        if env is not None:
            for ch in range(env_c):
                ES[:, ch] += w * _lookup(env[ch], emin, env_cell, ps)
                EM[:, ch] += w * _lookup(env[env_c + ch], emin, env_cell, ps)
        if emission is not None:
            we = w
            if em_box:
                we = np.where(np.all((ps >= em_lo) & (ps <= em_hi), axis=1), w, 0.0)
            for ch in range(em_c):
                EE[:, ch] += we * _lookup(emission[ch], em_lo, em_cell, ps)
        A += w
        D += w * ts
        T = T * np.exp(-tau)
        k = k + active

    ae = np.asarray(albedo, f64) * np.asarray(sun.irradiance, f64)
    single_rgb = (f0 * S)[:, None] * ae if lit else np.zeros((n_rays, 3))
    multiple = M * ae if (lit and source != "none") else np.zeros((n_rays, 3))
    if env is not None:
        ec = np.asarray(env_colour, f64)
        single_rgb = single_rgb + ES * ec
        multiple = multiple + EM * ec
    bg = (np.asarray(background, f64) if bg_image is None else
          np.asarray(bg_image, f64).reshape(-1, 3))
    total = single_rgb + multiple + T[:, None] * bg
    if emission is not None:
        emitted = EE * ((1.0 - np.asarray(albedo, f64)) * np.asarray(em_colour, f64))
        total = total + emitted
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(A > 0, D / A, 0.0)
    shape = (height, width)
    out = {"total": total.reshape(shape + (3,)), "single": single_rgb.reshape(shape + (3,)),
           "multiple": multiple.reshape(shape + (3,)), "alpha": A.reshape(shape),
           "depth": depth.reshape(shape)}
    if emission is not None:
        out["emission"] = emitted.reshape(shape + (3,))
    out["stopped_at_bound"] = int(np.count_nonzero(stopped))
    return out


def view_knots(table, block, width, height):
    """Per pixel (row-major): knot depths (P, K) and F_ms (P, C, K) from the view table
    (1 + C, by, bx, K) (see "view" above)."""
    _, by, bx, k = table.shape
    col, row = np.meshgrid(np.arange(width), np.arange(height))
    u = np.clip((col.ravel() + 0.5) / block - 0.5, 0, bx - 1)
    v = np.clip((row.ravel() + 0.5) / block - 0.5, 0, by - 1)
    i0, j0 = u.astype(np.int64), v.astype(np.int64)
    i1, j1 = np.minimum(i0 + 1, bx - 1), np.minimum(j0 + 1, by - 1)
    fu, fv = u - i0, v - j0
    blocks = [(j0, i0, (1 - fu) * (1 - fv)), (j0, i1, fu * (1 - fv)),
              (j1, i0, (1 - fu) * fv), (j1, i1, fu * fv)]
    ws = [np.where(table[0, jj, ii, 0] < 0, 0.0, wq) for jj, ii, wq in blocks]
    total = sum(ws)
    inv = np.where(total > 0, 1.0 / np.where(total > 0, total, 1.0), 0.0)
    knots = sum((wq * inv)[:, None, None] * table[:, jj, ii, :].transpose(1, 0, 2)
                for (jj, ii, _), wq in zip(blocks, ws))                    # (P, 1 + C, K)
    return knots[:, 0, :], knots[:, 1:, :]


def view_interp(vd, vv, t):
    """F_ms (P, C) at distance t (P,) from per-pixel knots vd (P, K), vv (P, C, K)."""
    f = vv[:, :, 0].copy()
    for k in range(vd.shape[1] - 1):
        ramp = np.clip((t - vd[:, k]) / np.maximum(vd[:, k + 1] - vd[:, k], 1e-30), 0.0, 1.0)
        f += (vv[:, :, k + 1] - vv[:, :, k]) * ramp[:, None]
    return f
