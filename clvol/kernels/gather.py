"""Host wrapper for cl/gather.cl: the template gather that feeds the network (clvol/layout.py).

    pyr = build_pyramid(grid, 256)
    gt = graded_transmittance(pyr, medium.density_scale, light.direction)
    out = gather(pyr, gt, points, omegas, light.direction, medium, channel_albedo=0.9,
                 mode="train")                       # features, levels, config
    out = gather(pyr, gt, points, omegas, light.direction, medium, 0.9, mode="render",
                 level_weights=w, bias=b)            # features (combined T), config

Render mode bakes, once per (graded fields, weights, bias), a float2 grid per level holding
(optical thickness of a voxel, sum_l w_l T_l + b) at that level's voxel centres, interleaved so
one trilinear read serves both features (``bake_render_grid``; cached). Train mode returns every
level T_l sampled at the centres of the point's density level and interpolated with the same
trilinear weights, so sum_l w_l levels[:, l] + b equals the render feature (to rounding).
Phase features come from a per-frame table over alpha (clvol/phasetable.py) built once per phase.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .. import layout
from ..errors import ClvolError
from ..phasetable import N_ALPHA, phase_feature_table, volume_phase
from ..templates import load_templates
from .grid import f4
from .phase import lobe_vectors, phase_defines
from .pyramid import Pyramid
from .transmittance import GradedT

MODES = ("train", "render")
MAX_COARSE = 32   # t_enter is found on the pyramid level with at most 32^3 cells


class GatherError(ClvolError):
    """Bad input to the gather (shapes, directions, mismatched fields, weights)."""


def coarse_level(base_resolution: int) -> int:
    """Pyramid level used as the coarse occupancy grid for t_enter (<= 32^3 cells)."""
    n_levels = int(np.log2(base_resolution)) + 1
    return max(0, n_levels - 1 - int(np.log2(MAX_COARSE)))


def _lobes(medium):
    return tuple((float(l.g), float(l.weight)) for l in medium.phase.lobes)


@lru_cache(maxsize=8)
def phase_table(lobes: tuple, n_alpha: int = N_ALPHA) -> np.ndarray:
    tpl = load_templates()
    return phase_feature_table(volume_phase(lobes), tpl.points, tpl.half_angle, n_alpha)


def template_arrays(base_resolution: int):
    """(tpl float4 [NP], pinfo int [NP], hl_spacing float [4] per unit t_enter) for the kernel."""
    tpl = load_templates()
    pts = np.zeros((tpl.n_points, 4), np.float32)
    pts[:, :3] = tpl.points
    levels = tpl.diffuse_levels(base_resolution)
    info = np.where(tpl.is_highlight, -(tpl.layer - tpl.n_diffuse_layers + 1),
                    levels[np.minimum(tpl.layer, tpl.n_diffuse_layers - 1)]).astype(np.int32)
    hl = tpl.highlight_spacing().astype(np.float32)    # x t_enter (world) / base voxel in the kernel
    return pts, info, hl


@dataclass(eq=False)
class BakedGrid:
    """float2 (tau, C) per voxel of every level, offsets x 2 of the pyramid's."""
    buffer: object
    weights: tuple
    bias: float
    c_out: float


_BAKED: dict = {}


def _check_weights(level_weights, bias, n_levels):
    w = np.asarray(level_weights, np.float64)
    if w.shape != (n_levels,) or not np.all(np.isfinite(w)):
        raise GatherError(f"level_weights must be {n_levels} finite numbers (one per graded level), "
                          f"got {np.asarray(level_weights).tolist()!r}")
    if not np.isfinite(float(bias)):
        raise GatherError(f"bias = {bias!r} must be finite")
    return w, float(bias)


def _taufac(pyramid: Pyramid, density_scale: float) -> np.ndarray:
    return np.array([density_scale * pyramid.voxel_size(l) for l in range(pyramid.n_levels)],
                    np.float32)


def bake_render_grid(pyramid: Pyramid, graded: GradedT, density_scale: float, level_weights,
                     bias: float = 0.0) -> BakedGrid:
    """The render-time grid (cached per graded fields, scale, weights and bias)."""
    w, b = _check_weights(level_weights, bias, pyramid.n_levels)
    key = (id(graded), float(density_scale), w.tobytes(), b)
    hit = _BAKED.get(key)
    if hit is not None and hit[0] is graded:
        return hit[1]
    rt = pyramid.runtime
    total = int(pyramid.data.size)
    out = rt.empty(2 * total)
    k = rt.program("gather").kernel("gather_bake", [None, None, None, np.int32, np.int32, None,
                                                    None, np.float32, np.int32, None])
    rt.launch(k, total, (pyramid.buffer, graded.buffer,
                         rt.to_device(pyramid.level_offsets.astype(np.int32)),
                         np.int32(pyramid.n_levels), np.int32(pyramid.base_resolution),
                         rt.to_device(_taufac(pyramid, density_scale)),
                         rt.to_device(w.astype(np.float32)), np.float32(b), np.int32(total), out))
    baked = BakedGrid(out, tuple(w), b, float(np.float32(w.sum() + b)))
    _BAKED.clear()                 # one light at a time: keep the memory bounded
    _BAKED[key] = (graded, baked)
    return baked


def _check_inputs(pyramid, graded, points, omegas, light_dir, medium, mode):
    if not isinstance(pyramid, Pyramid):
        raise GatherError(f"gather needs a Pyramid, got {type(pyramid).__name__}")
    if not isinstance(graded, GradedT) or graded.pyramid is not pyramid:
        raise GatherError("graded must be the GradedT made from this pyramid")
    if graded.quantity != "transmittance":
        raise GatherError(f"graded fields hold {graded.quantity!r}; the gather reads T "
                          f"(graded_transmittance(..., quantity='transmittance'))")
    if mode not in MODES:
        raise GatherError(f"mode = {mode!r}; allowed: {', '.join(MODES)}")
    pts = np.asarray(points, np.float32)
    om = np.asarray(omegas, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or om.shape != pts.shape:
        raise GatherError(f"points and omegas must both be (N, 3), got {pts.shape} and {om.shape}")
    if not (np.all(np.isfinite(pts)) and np.all(np.isfinite(om))):
        raise GatherError("points and omegas must be finite")
    norms = np.linalg.norm(om, axis=1)
    if len(om) and not np.all(np.abs(norms - 1.0) < 1e-4):
        bad = int(np.argmax(np.abs(norms - 1.0)))
        raise GatherError(f"omegas must be unit vectors; omegas[{bad}] has length {norms[bad]:.6g}")
    l = np.asarray(light_dir, np.float64)
    if l.shape != (3,) or not np.all(np.isfinite(l)) or not abs(np.linalg.norm(l) - 1.0) < 1e-4:
        raise GatherError(f"light_dir = {np.asarray(light_dir).tolist()!r} must be a unit 3-vector "
                          f"toward the light")
    if np.max(np.abs(graded.light_dir - l)) > 1e-5:
        raise GatherError(f"light_dir {l.tolist()} differs from the one the graded fields were made "
                          f"for {np.asarray(graded.light_dir).tolist()}")
    if not np.isclose(graded.density_scale, medium.density_scale, rtol=1e-6, atol=0):
        raise GatherError(f"[medium.density_scale] = {medium.density_scale} but the graded fields "
                          f"were made with {graded.density_scale}")
    return pts, om.astype(np.float32), l


def config_vectors(medium, channel_albedo, omegas, light_dir) -> np.ndarray:
    """[N][CONFIG_DIM] per clvol.layout.CONFIG_FIELDS."""
    n = len(omegas)
    lobes = _lobes(medium)
    cfg = np.zeros((n, layout.CONFIG_DIM), np.float32)
    for k, (g, w) in enumerate(lobes):
        cfg[:, k], cfg[:, 3 + k] = g, w
    cfg[:, 6] = sum(g * w for g, w in lobes)
    alb = np.broadcast_to(np.asarray(channel_albedo, np.float64), (n,))
    if not (np.all(np.isfinite(alb)) and np.all(alb >= 0) and np.all(alb <= 1)):
        raise GatherError(f"channel_albedo must be in [0, 1], got {np.asarray(channel_albedo)!r}")
    cfg[:, 7] = alb
    mu = np.clip(-(np.asarray(omegas, np.float64) @ np.asarray(light_dir, np.float64)), -1.0, 1.0)
    cfg[:, 8] = np.arccos(mu)
    return cfg


def gather(pyramid: Pyramid, graded: GradedT, points, omegas, light_dir, medium, channel_albedo,
           mode: str = "train", level_weights=None, bias: float = 0.0,
           return_t_enter: bool = False) -> dict:
    """Features for N queries (clvol/layout.py): ``features`` float32 [N][3][NP], ``levels``
    [N][L][NP] (train mode only), ``config`` [N][CONFIG_DIM] (and ``t_enter`` [N] on request).

    ``points`` world positions (N, 3); ``omegas`` unit directions toward the camera; ``light_dir``
    unit toward the light (the one ``graded`` was made for); ``medium`` a clvol.scene.Medium;
    ``channel_albedo`` scalar or (N,) in [0, 1]. Train mode fills features[:, 1] with
    sum_l w_l levels[:, l] + bias when ``level_weights`` is given, else with 0 (the model
    combines ``levels`` itself). Render mode needs ``level_weights``."""
    pts, om, l = _check_inputs(pyramid, graded, points, omegas, light_dir, medium, mode)
    rt = pyramid.runtime
    n, L, NP = len(pts), pyramid.n_levels, layout.N_POINTS
    if L != graded.n_levels:
        raise GatherError("graded fields and pyramid disagree on the number of levels")
    render = mode == "render"
    if render and level_weights is None:
        raise GatherError("mode='render' needs level_weights (one per graded level) and bias")
    lobes = _lobes(medium)
    defines = dict(phase_defines(lobes), NP=NP, COARSE_LEVEL=coarse_level(pyramid.base_resolution))
    if render:
        defines["GATHER_RENDER"] = 1
    prog = rt.program("gather", defines=defines)
    k = prog.kernel("gather", [None, None, None, None, np.int32, np.int32, None, np.float32,
                               None, None, None, None, None, np.int32, None, None, None, None,
                               None, np.float32, np.int32, None, None, None])
    tpl, info, hl = template_arrays(pyramid.base_resolution)
    ptab = phase_table(lobes)
    lg, lw = lobe_vectors(lobes)
    c_out = 0.0
    if render:
        baked = bake_render_grid(pyramid, graded, medium.density_scale, level_weights, bias)
        baked_buf, c_out = baked.buffer, baked.c_out
    else:
        baked_buf = rt.empty(2)
    feats = rt.empty(n * 3 * NP)
    levels = rt.empty(n * L * NP if not render else 1)
    tenter = rt.empty(n)
    if n:
        rt.launch(k, n, (pyramid.buffer, graded.buffer, baked_buf,
                         rt.to_device(pyramid.level_offsets.astype(np.int32)), np.int32(L),
                         np.int32(pyramid.base_resolution), f4(pyramid.cube_min),
                         np.float32(pyramid.cube_size),
                         rt.to_device(_taufac(pyramid, medium.density_scale)), rt.to_device(tpl),
                         rt.to_device(info), rt.to_device(hl), rt.to_device(ptab),
                         np.int32(ptab.shape[0]), rt.to_device(pts), rt.to_device(om), f4(l),
                         lg, lw, np.float32(c_out), np.int32(n), feats, levels, tenter))
    out = {"features": rt.from_device(feats, (n, 3, NP)),
           "config": config_vectors(medium, channel_albedo, om, l)}
    if not render:
        out["levels"] = rt.from_device(levels, (n, L, NP))
        if level_weights is not None:
            w, b = _check_weights(level_weights, bias, L)
            out["features"][:, 1, :] = (np.einsum("l,nlj->nj", w, out["levels"]) + b).astype(np.float32)
    if return_t_enter:
        out["t_enter"] = rt.from_device(tenter, (n,))
    return out
