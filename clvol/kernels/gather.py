"""Host wrapper for cl/gather.cl: the template gather that feeds the network (clvol/features/layout.py).

    pyr = build_pyramid(grid, 256)
    gt = graded_transmittance(pyr, medium.density_scale, light.direction)
    out = gather(pyr, gt, points, omegas, light.direction, medium, channel_albedo=0.9,
                 mode="train")                       # features, levels, config
    out = gather(pyr, gt, points, omegas, light.direction, medium, 0.9, mode="render",
                 level_weights=w, bias=b)            # features (combined T), config

    dev = gather(..., mode="render", level_weights=w, bias=b, as_buffers=True, reuse=dev)
                                # DeviceArrays for the OpenCL network (dev = None at first)

Render mode bakes, once per (graded fields, weights, bias), a float2 grid per level holding
(optical thickness of a voxel, sum_l w_l T_l + b) at that level's voxel centres, interleaved so
one trilinear read serves both features (``bake_render_grid``; cached). Queries run sorted by
coarse cell (``query_order``; results unchanged). Train mode returns every
level T_l sampled at the centres of the point's density level and interpolated with the same
trilinear weights, so sum_l w_l levels[:, l] + b equals the render feature (to rounding).
Phase features come from a per-frame table over alpha (clvol/features/phasetable.py) built once per phase.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import pyopencl as cl

from ..errors import ClvolError
from ..features import layout
from ..features.phasetable import N_ALPHA, phase_feature_table, volume_phase
from ..features.templates import load_templates
from ..runtime import DeviceArray
from .constants import kernel_constant
from .grid import f4
from .phase import lobe_vectors, phase_defines
from .pyramid import Pyramid
from .transmittance import GradedT, check_level_weights

MODES = ("train", "render")
MAX_COARSE = 32   # t_enter is found on the pyramid level with at most 32^3 cells


class GatherError(ClvolError):
    """Bad input to the gather (shapes, directions, mismatched fields, weights)."""


def coarse_level(base_resolution: int) -> int:
    """Pyramid level used as the coarse occupancy grid for t_enter (<= 32^3 cells)."""
    return max(0, layout.n_levels(base_resolution) - 1 - int(np.log2(MAX_COARSE)))


def _lobes(medium):
    return medium.phase.pairs


@lru_cache(maxsize=8)
def phase_table(lobes: tuple, n_alpha: int = N_ALPHA) -> np.ndarray:
    """log1p phase features [n_alpha][NP] over alpha = linspace(0, pi, n_alpha)."""
    tpl = load_templates()
    return phase_feature_table(volume_phase(lobes), tpl.points, tpl.half_angle, n_alpha)


@lru_cache(maxsize=8)
def _phase_table_padded(lobes: tuple, n_alpha: int = N_ALPHA) -> np.ndarray:
    t = phase_table(lobes, n_alpha)
    out = np.zeros((t.shape[0], n_pad(t.shape[1])), np.float32)
    out[:, :t.shape[1]] = t
    return out


CHUNK = 16   # template points per chunk at the widest LANES (cl/include/gather_core.h NPAD)


def n_pad(n_points: int = layout.N_POINTS) -> int:
    """Template points rounded up to whole chunks of 16 (the kernel's table row length, the
    same for every lane width: 16 is a multiple of each)."""
    return -(-n_points // CHUNK) * CHUNK


def template_arrays(base_resolution: int):
    """(tpl float [3][NPAD] x, y, z rows, pinfo int [NPAD], hl_spacing float [4] per unit
    t_enter) for the kernel. Padding lanes are diffuse level-0 points at u = 0 (never stored)."""
    tpl = load_templates()
    npad = n_pad(tpl.n_points)
    pts = np.zeros((3, npad), np.float32)
    pts[:, :tpl.n_points] = tpl.points.T
    levels = tpl.diffuse_levels(base_resolution)
    info = np.zeros(npad, np.int32)
    info[:tpl.n_points] = np.where(tpl.is_highlight, -(tpl.layer - tpl.n_diffuse_layers + 1),
                                   levels[np.minimum(tpl.layer, tpl.n_diffuse_layers - 1)])
    hl = tpl.highlight_spacing().astype(np.float32)    # x t_enter (world) / base voxel in the kernel
    return pts, info, hl


@dataclass(eq=False)
class BakedGrid:
    """float2 (tau, C) per voxel of every level, offsets x 2 of the pyramid's, + BAKE_PAD floats
    of zeros (the kernel's row loads on the 1-voxel level read up to 3 voxels past it), in
    ``device`` (a flat DeviceArray). One per pyramid at a time: the next bake for the same
    pyramid overwrites it."""
    device: DeviceArray
    weights: tuple
    bias: float
    c_out: float


GATHER_LOCAL = 64         # work-items per group of the gather on CPU devices (see its launch)
MIN_ROW_LEVEL = 16        # levels at least this wide are baked by rows of 16 (bake_rows)
BAKE_SPAN = kernel_constant("BAKE_SPAN")   # voxels of a row per bake_rows work-item
MAX_RENDER_FLOATS = 2**31 - 1   # the render kernel indexes the (tau, C) pairs with int
BAKE_PAD = 8


def _check_weights(level_weights, bias, n_levels):
    return check_level_weights(level_weights, bias, n_levels, "level_weights", GatherError)


def _taufac(pyramid: Pyramid, density_scale: float) -> np.ndarray:
    return np.array([density_scale * pyramid.voxel_size(l) for l in range(pyramid.n_levels)],
                    np.float32)


def _reused(pyramid: Pyramid, name: str, nfloats: int):
    """A device buffer of at least ``nfloats`` kept on the pyramid and reused by later calls:
    a fresh buffer costs a page fault per 4 KiB on its first write, as much CPU time as the
    gather itself for the features of 65,536 queries (docs/templates.md)."""
    buf = pyramid.cache.get(name)
    if buf is None or buf.size < max(nfloats, 1):
        pyramid.cache.pop(name, None)
        buf = pyramid.cache[name] = pyramid.runtime.alloc(max(nfloats, 1))
    return buf


def _static(pyramid: Pyramid) -> dict:
    """Device copies (DeviceArrays) of the per-pyramid tables (level offsets, templates),
    made once."""
    st = pyramid.cache.get("gather")
    if st is None:
        rt = pyramid.runtime
        tpl, info, hl = template_arrays(pyramid.base_resolution)
        st = pyramid.cache["gather"] = {
            "loff": rt.upload(pyramid.level_offsets, np.int32),
            "tpl": rt.upload(tpl), "pinfo": rt.upload(info, np.int32), "hl": rt.upload(hl)}
    return st


def static_args(pyramid: Pyramid) -> tuple:
    """The kernels' (loff, tpl, pinfo, hl) buffer arguments."""
    st = _static(pyramid)
    return st["loff"].buffer, st["tpl"].buffer, st["pinfo"].buffer, st["hl"].buffer


def _xpass_layout(pyramid: Pyramid, lvl: int) -> tuple[np.ndarray, int]:
    """Offsets of the x-interpolated rows X_m (m > lvl) of the coarser levels at level lvl's
    x centres in the bake's scratch buffer, and its size: nm^2 rows of n_lvl each."""
    L, n = pyramid.n_levels, pyramid.resolution(lvl)
    xoff = np.zeros(L, np.int32)
    size = 0
    for m in range(lvl + 1, L):
        xoff[m] = size
        size += pyramid.resolution(m) ** 2 * n
    return xoff, size


def bake_render_grid(pyramid: Pyramid, graded: GradedT, density_scale: float, level_weights,
                     bias: float = 0.0) -> BakedGrid:
    """The render-time grid: for every voxel of every level, (rho * density_scale * voxel
    size, sum_m w_m T_m(centre) + bias). The last bake is kept in ``pyramid.cache`` and
    returned again for the same graded fields, scale, weights and bias."""
    w, b = _check_weights(level_weights, bias, pyramid.n_levels)
    key = (float(density_scale), w.tobytes(), b)
    hit = pyramid.cache.get("gather_bake")
    if hit is not None and hit[0] is graded and hit[1] == key:
        return hit[2]
    rt = pyramid.runtime
    total = int(pyramid.size)
    if 2 * total + BAKE_PAD > MAX_RENDER_FLOATS:
        raise GatherError(f"render mode supports pyramids up to 2^30 voxels in all (base 512); "
                          f"base_resolution = {pyramid.base_resolution} has {total}")
    L, n0 = pyramid.n_levels, pyramid.base_resolution
    # One light at a time per pyramid: the previous bake's buffer is overwritten (a fresh one
    # would cost a page fault per 4 KiB on first write).
    baked_dev = pyramid.cache.get("gather_baked")
    if baked_dev is None:
        baked_dev = pyramid.cache["gather_baked"] = rt.alloc(2 * total + BAKE_PAD)
        if not rt.is_oclgrind:          # (Oclgrind: rt.alloc already zero-filled it)
            cl.enqueue_fill_buffer(rt.queue, baked_dev.buffer, np.float32(0.0), 4 * 2 * total,
                                   4 * BAKE_PAD)
    out = baked_dev.buffer
    loff = _static(pyramid)["loff"].buffer
    dens, graded_buf = pyramid.device.buffer, graded.device.buffer
    prog = rt.program("gather")
    taufac = _taufac(pyramid, density_scale)
    wbuf = rt.to_device(w.astype(np.float32))
    row_levels = [l for l in range(L) if pyramid.resolution(l) >= MIN_ROW_LEVEL]
    if row_levels:
        kx = prog.kernel("bake_xpass", [None, np.int32, np.int32, np.int32, np.int32, None, np.int32])
        kr = prog.kernel("bake_rows", [None, None, None, None, None, np.int32, np.int32, np.int32,
                                       np.int32, np.float32, None, np.float32, None])
        scratch_size = max(_xpass_layout(pyramid, l)[1] for l in row_levels)
        scratch = pyramid.cache.get("gather_xpass")
        if scratch is None or scratch.size < max(scratch_size, 1):
            scratch = pyramid.cache["gather_xpass"] = rt.alloc(max(scratch_size, 1))
        scratch = scratch.buffer
        for lvl in row_levels:
            n = pyramid.resolution(lvl)
            log2n = n.bit_length() - 1
            xoff, _ = _xpass_layout(pyramid, lvl)
            for m in range(lvl + 1, L):
                nm = pyramid.resolution(m)
                rt.launch(kx, nm * nm * n, (graded_buf, np.int32(pyramid.level_offsets[m]),
                                            np.int32(nm), np.int32(n), np.int32(log2n), scratch,
                                            np.int32(xoff[m])))
            rt.launch(kr, n ** 3 // min(n, BAKE_SPAN), (dens, graded_buf, scratch, loff,
                                         rt.to_device(xoff),
                                         np.int32(L), np.int32(n0), np.int32(lvl), np.int32(log2n),
                                         taufac[lvl], wbuf, np.float32(b), out))
    first = len(row_levels)
    if first < L:
        ks = prog.kernel("bake_small", [None, None, None, np.int32, np.int32, np.int32, None, None,
                                        np.float32, None])
        rt.launch(ks, total - int(pyramid.level_offsets[first]),
                  (dens, graded_buf, loff, np.int32(L), np.int32(n0),
                   np.int32(first), rt.to_device(taufac), wbuf, np.float32(b), out))
    baked = BakedGrid(baked_dev, tuple(w), b, float(np.float32(w.sum() + b)))
    pyramid.cache["gather_bake"] = (graded, key, baked)   # one light at a time per pyramid
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
    """[N][CONFIG_DIM] per clvol.features.layout.CONFIG_FIELDS."""
    n = len(omegas)
    lobes = _lobes(medium)
    at = layout.CONFIG_FIELDS.index
    cfg = np.zeros((n, layout.CONFIG_DIM), np.float32)
    for k, (g, w) in enumerate(lobes):
        cfg[:, at(f"g{k}")], cfg[:, at(f"w{k}")] = g, w
    cfg[:, at("g_mean")] = sum(g * w for g, w in lobes)
    alb = np.broadcast_to(np.asarray(channel_albedo, np.float64), (n,))
    if not (np.all(np.isfinite(alb)) and np.all(alb >= 0) and np.all(alb <= 1)):
        raise GatherError(f"channel_albedo must be in [0, 1], got {np.asarray(channel_albedo)!r}")
    cfg[:, at("albedo")] = alb
    mu = np.clip(-(np.asarray(omegas, np.float64) @ np.asarray(light_dir, np.float64)), -1.0, 1.0)
    cfg[:, at("alpha")] = np.arccos(mu)
    return cfg


SORT_BITS = 5     # queries run ordered by the Morton code of their cell in a 32^3 grid of the cube
# Register transposes of the render lookups with Clang's __builtin_shufflevector (cl/gather.cl,
# GATHER_SHUFFLE), used on PoCL; False forces the portable per-lane loads (tests compare both).
USE_SHUFFLE = True


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """Bits b of v (< 2^SORT_BITS) moved to bit 3 b."""
    out = np.zeros_like(v)
    for b in range(SORT_BITS):
        out |= ((v >> b) & 1) << (3 * b)
    return out


def query_order(pyramid: Pyramid, points: np.ndarray) -> np.ndarray:
    """A processing order for the queries: by the Morton code of their cell in a 32^3 grid over
    the cube (points outside are clamped onto it). Consecutive queries then read nearby voxels
    and share cache lines and pages (faster on random queries in a cloud: docs/templates.md). A
    16-bit key, so NumPy's stable sort is a radix sort."""
    cells = 1 << SORT_BITS
    g = (np.asarray(points, np.float64) - pyramid.cube_min) * (cells / pyramid.cube_size)
    c = np.clip(g, 0, cells - 1).astype(np.uint16)
    key = _spread_bits(c[:, 0]) | (_spread_bits(c[:, 1]) << 1) | (_spread_bits(c[:, 2]) << 2)
    return np.argsort(key, kind="stable").astype(np.int32)


# Added on PoCL only (Clang builtins, measured faster there: cl/gather.cl).
POCL_DEFINES = {"GATHER_SHUFFLE": 1} if USE_SHUFFLE else {}


def program_defines(base_resolution: int, lobes: tuple, render: bool) -> dict:
    """The -D options of cl/gather.cl's device functions (also cl/gather_mlp.cl's) on every
    device (``POCL_DEFINES`` are PoCL's additions): the plan's and the bundle's."""
    defines = dict(phase_defines(lobes), NP=layout.N_POINTS,
                   COARSE_LEVEL=coarse_level(base_resolution))
    if render:
        defines["GATHER_RENDER"] = 1
    return defines


def gather_defines(pyramid: Pyramid, lobes: tuple, render: bool) -> dict:
    """``program_defines`` with the device's additions (``POCL_DEFINES`` on PoCL)."""
    defines = program_defines(pyramid.base_resolution, lobes, render)
    if pyramid.runtime.is_pocl:
        defines.update(POCL_DEFINES)
    return defines


def gather(pyramid: Pyramid, graded: GradedT, points, omegas, light_dir, medium, channel_albedo,
           mode: str = "train", level_weights=None, bias: float = 0.0,
           return_t_enter: bool = False, as_buffers: bool = False, sort: bool = True,
           reuse: dict | None = None) -> dict:
    """Features for N queries (clvol/features/layout.py): ``features`` float32 [N][3][NP], ``levels``
    [N][L][NP] (train mode only), ``config`` [N][CONFIG_DIM] (and ``t_enter`` [N] on request).

    ``points`` world positions (N, 3); ``omegas`` unit directions toward the camera; ``light_dir``
    unit toward the light (the one ``graded`` was made for); ``medium`` a clvol.scene.Medium;
    ``channel_albedo`` scalar or (N,) in [0, 1]. Train mode fills features[:, 1] with
    sum_l w_l levels[:, l] + bias when ``level_weights`` is given, else with 0 (the model
    combines ``levels`` itself). Render mode needs ``level_weights``.

    ``as_buffers=True`` (render mode) returns DeviceArrays instead of arrays, for the
    network's OpenCL forward (clvol/kernels/mlp.py: ``MlpKernel.forward(features, config,
    ...)``): ``features`` (n, 3, NP), ``config`` (n, 9) and ``t_enter`` (n,), plus ``n``;
    nothing is read back (~200 MiB for 65,536 queries). Pass a previous such result as
    ``reuse`` to have its buffers overwritten instead of new ones allocated (new buffers cost
    a page fault per 4 KiB on their first write).

    ``sort`` (default): the kernel visits the queries in ``query_order`` (results are the same
    and in the caller's order; only speed changes). ``sort=False`` visits them as given, for
    callers whose queries are already coherent."""
    pts, om, l = _check_inputs(pyramid, graded, points, omegas, light_dir, medium, mode)
    render = mode == "render"
    _check_mode(pyramid, graded, render, level_weights, as_buffers)
    n = len(pts)
    cfg = config_vectors(medium, channel_albedo, om, l)
    grids = _mode_inputs(pyramid, graded, medium, level_weights, bias, render, n)
    feats, tenter = _feature_buffers(pyramid, n, as_buffers, reuse)
    if n:
        order = query_order(pyramid, pts) if sort else np.arange(n, dtype=np.int32)
        _launch(pyramid, graded, _lobes(medium), render, pts, om, l, order, grids, feats, tenter)
    if as_buffers:
        return {"features": feats, "config": pyramid.runtime.upload(cfg), "t_enter": tenter,
                "n": n}
    out = _read_features(pyramid, feats, grids, n, render, level_weights, bias)
    out["config"] = cfg
    if return_t_enter:
        out["t_enter"] = pyramid.runtime.from_device(tenter, (n,))
    return out


def _check_mode(pyramid, graded, render: bool, level_weights, as_buffers: bool) -> None:
    if pyramid.n_levels != graded.n_levels:
        raise GatherError("graded fields and pyramid disagree on the number of levels")
    if render and level_weights is None:
        raise GatherError("mode='render' needs level_weights (one per graded level) and bias")
    if as_buffers and not render:
        raise GatherError("as_buffers=True is for mode='render' (training reads host arrays)")


@dataclass
class _ModeInputs:
    """The kernel arguments that differ by mode: render reads the baked grid (and C outside
    the cube); train reads the raw levels with their tau factors and writes every level."""
    baked: object
    c_out: float
    taufac: object
    levels: object


def _mode_inputs(pyramid, graded, medium, level_weights, bias, render: bool, n: int) -> _ModeInputs:
    rt = pyramid.runtime
    if render:
        baked = bake_render_grid(pyramid, graded, medium.density_scale, level_weights, bias)
        unused = rt.empty(1)
        return _ModeInputs(baked.device.buffer, baked.c_out, taufac=unused, levels=unused)
    # levels: not kept on the pyramid (9x the features, and training is compute-bound)
    return _ModeInputs(rt.empty(1), 0.0, rt.to_device(_taufac(pyramid, medium.density_scale)),
                       rt.empty(n * pyramid.n_levels * layout.N_POINTS))


def _feature_buffers(pyramid, n: int, as_buffers: bool, reuse: dict | None):
    """(features, t_enter) DeviceArrays: the caller's previous ones when they fit (``reuse``,
    as_buffers), new ones for the caller, or the pyramid's own (read back, then reused by the
    next call)."""
    rt, NP = pyramid.runtime, layout.N_POINTS
    if not as_buffers:
        return (_reused(pyramid, "gather_features", n * 3 * NP),
                _reused(pyramid, "gather_t_enter", n))
    old_f, old_t = (reuse or {}).get("features"), (reuse or {}).get("t_enter")
    fits = (isinstance(old_f, DeviceArray) and isinstance(old_t, DeviceArray)
            and old_f.buffer.size >= 4 * max(n * 3 * NP, 1)
            and old_t.buffer.size >= 4 * max(n, 1))
    if fits:
        return (DeviceArray(old_f.buffer, (n, 3, NP), old_f.dtype, rt),
                DeviceArray(old_t.buffer, (n,), old_t.dtype, rt))
    return rt.alloc((n, 3, NP)), rt.alloc(n)


_GATHER_ARGS = [None, None, None, None, np.int32, np.int32, None, np.float32, None, None, None,
                None, None, np.int32, None, None, None, None, None, np.float32, None, np.int32,
                None, None, None]


def _launch(pyramid, graded, lobes, render: bool, pts, om, l, order, grids: _ModeInputs,
            feats, tenter) -> None:
    rt = pyramid.runtime
    k = rt.program("gather", defines=gather_defines(pyramid, lobes, render)).kernel(
        "gather", _GATHER_ARGS)
    loff, tpl, pinfo, hl = static_args(pyramid)
    ptab = _phase_table_padded(lobes)
    lg, lw = lobe_vectors(lobes)
    args = (pyramid.device.buffer, graded.device.buffer, grids.baked, loff,
            np.int32(pyramid.n_levels),
            np.int32(pyramid.base_resolution), f4(pyramid.cube_min),
            np.float32(pyramid.cube_size), grids.taufac, tpl, pinfo, hl,
            rt.to_device(ptab), np.int32(ptab.shape[0]), rt.to_device(pts), rt.to_device(om),
            f4(l), lg, lw, np.float32(grids.c_out), rt.to_device(order), np.int32(len(pts)),
            feats.buffer, grids.levels, tenter.buffer)
    # A fixed local size: with a NULL one PoCL picks a group size from the global size and
    # compiles the kernel anew for each size it picks (~0.4 s each on the 2-core CPU), which a
    # query count that changes every frame (the view-space source) hit each frame.
    rt.launch(k, len(pts), args, local_size=(GATHER_LOCAL,) if rt.entry.kind == "cpu" else None,
              pad=GATHER_LOCAL)


def _read_features(pyramid, feats, grids: _ModeInputs, n: int, render: bool, level_weights,
                   bias) -> dict:
    """The features (and, in train mode, the levels, combined into the transmittance
    feature when ``level_weights`` is given) as host arrays."""
    rt, L, NP = pyramid.runtime, pyramid.n_levels, layout.N_POINTS
    out = {"features": rt.from_device(feats, (n, 3, NP))}
    if not render:
        out["levels"] = rt.from_device(grids.levels, (n, L, NP))
        if level_weights is not None:
            w, b = _check_weights(level_weights, bias, L)
            out["features"][:, 1, :] = (np.einsum("l,nlj->nj", w, out["levels"]) + b).astype(np.float32)
    return out
