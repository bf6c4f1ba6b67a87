"""Reference volumetric path tracer: the ``pathtrace`` render method and point queries.

Images (``clvol render SCENE --method pathtrace --spp N -o out.exr``): progressive sample
passes of cl/pathtrace.cl, averaged in float64 on the host. Layers:

- ``total``    background seen through the medium + single + multiple scattering;
- ``single``   order 1 (paths with one scattering vertex: sun NEE at the first vertex and,
               with an environment, environment light after one scattering; with a map,
               its NEE at the first vertex too);
- ``multiple`` orders >= 2;
- ``total_se`` standard error of ``total`` per pixel and channel (from the sample variance);
- with ``[emission]``: ``emission`` (emitted light seen without scattering) and
  ``emission_scattered`` (emitted light scattered at least once); both are in ``total``.

The header records spp, seconds, seed, what was simulated and skipped (the kernel is
specialised with -D defines for what the scene needs), and paths cut at the vertex limit.

Point queries (``point_query``): the training-label API, F(p, omega) of docs/conventions.md for a sun
of irradiance 1 and no environment, split into F_1 and F_>=2, with standard errors.

The estimator, random-number layout and Russian roulette policy are documented at the top
of cl/pathtrace.cl and in docs/pathtrace.md.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from ..errors import ClvolError
from ..kernels.majorant import DEFAULT_BLOCK, majorant_args
from ..kernels.majorant import majorant_block as resolve_block
from ..kernels.pathtrace import (ORDER_BINS, PT_OUT, ROW_BG, ROW_EM_DIRECT, ROW_EM_SCATTERED,
                                 ROW_L1, ROW_LMS, ROW_STEPS, ROW_VERTICES, PathMedium,
                                 PathTracer, truncation_counts)
from ..kernels.transmittance import check_tracking_depth
from ..progress import Progress
from ..runtime import get_runtime
from . import RenderResult

DEFAULT_SPP = 64
# Paths per launch: enough work-items to fill the device, few enough for a responsive
# progress bar and a time budget that stops close to its limit.
PATHS_PER_LAUNCH = 1 << 16


def add_arguments(group) -> None:
    group.add_argument("--spp", type=int, default=None, metavar="N",
                       help=f"samples per pixel (default {DEFAULT_SPP}, or unlimited with --time)")
    group.add_argument("--max-order", type=int, default=None, metavar="K",
                       help="highest scattering order simulated (1 = single scattering only; "
                            "default: all)")
    group.add_argument("--time", type=float, default=None, metavar="SECONDS",
                       help="wall-time budget: stop after the last sample pass that fits (ray "
                            "marcher --ms progressive: refine this long after the first frame; "
                            "the header records the rounds, --progressive-rounds N repeats them)")
    group.add_argument("--majorant-block", type=int, default=DEFAULT_BLOCK, metavar="B",
                       help=f"voxels per majorant-grid cell for delta tracking (default "
                            f"{DEFAULT_BLOCK}; 0 = one global majorant)")


def _check_int(name: str, value, lo: int, allow_none: bool = True):
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < lo:
        raise ClvolError(f"{name} = {value!r}: must be an integer >= {lo}")
    return int(value)


def _medium(scene, grid, max_order, sun, environment, env_map: bool = False,
            emission=None) -> PathMedium:
    """The path tracer's PathMedium (the kernel's inputs): the scene's medium and light, the
    light's irradiance replaced by ``sun``; ``env_map``: with the scene's environment map,
    ``emission``: an EmissionGrid (renders only)."""
    light = scene.light
    texels = light.environment_texels() if env_map else None
    return PathMedium(density=grid.density, bbox_min=grid.bbox_min, bbox_max=grid.bbox_max,
                      medium=scene.medium,
                      light=dataclasses.replace(light, irradiance=tuple(float(s) for s in sun)),
                      environment=None if environment is None else tuple(environment),
                      max_order=max_order, env_map=texels,
                      env_scale=tuple(light.environment_scale),
                      env_rotation=float(light.environment_rotation), emission=emission)


def check_walks(density_scale, grid, majorant_block) -> float:
    """Refuse, before anything is uploaded or built, an image whose paths could not end within
    the tracking bounds (clvol/kernels/transmittance.py check_tracking_depth, the one rule):
    density_scale x the largest density x a majorant cell's longest side (inside the box).
    Returns that depth."""
    shape = np.shape(grid.density)
    block = resolve_block(majorant_block, shape)
    _, bsize = majorant_args(shape, grid.bbox_min, grid.bbox_max, block)
    extent = np.asarray(grid.bbox_max, np.float64) - np.asarray(grid.bbox_min, np.float64)
    voxel = float(np.max(np.asarray(bsize, np.float64)[:3] / block))
    cell = float(np.max(np.minimum(np.asarray(bsize, np.float64)[:3], extent)))
    return check_tracking_depth(density_scale, float(np.max(grid.density, initial=0.0)), cell,
                                voxel, min(block, max(shape)))


def render_pathtrace(scene, spp: int | None = DEFAULT_SPP, seed: int = 0,
                     max_order: int | None = None, time_budget: float | None = None,
                     runtime=None, majorant_block: int = DEFAULT_BLOCK, grid=None,
                     progress: bool = True, specialise: bool = True,
                     extra_defines: dict | None = None, device_medium=None,
                     emission=None) -> RenderResult:
    """Path-trace ``scene``: ``spp`` samples per pixel (None = until ``time_budget``).

    With ``time_budget`` (seconds) the render stops before a sample pass that would end
    after the budget (judged from the passes so far; at least one pass always runs).
    ``grid`` overrides ``scene.volume.load()``; ``device_medium`` is that grid already on the
    device (clvol/kernels/majorant.py, built with ``majorant_block``). Same seed, same device: same image, bit
    for bit, whatever the budget cut (passes are fixed sample-index ranges). ``emission``: the
    scene's EmissionGrid (default: loaded from ``scene.emission``, if any).
    """
    spp, max_order, seed = _check_render_options(spp, max_order, seed, time_budget)
    t_start = time.perf_counter()
    grid = grid if grid is not None else scene.volume.load()
    if emission is None and getattr(scene, "emission", None) is not None:
        emission = scene.emission.load(scene.volume, grid)
    check_walks(scene.medium.density_scale, grid,
                device_medium.block if device_medium is not None else majorant_block)
    light = scene.light
    med = _medium(scene, grid, max_order, light.irradiance, light.environment, env_map=True,
                  emission=emission)
    med.extra_defines = dict(extra_defines or {})
    pt = PathTracer(med, majorant_block, specialise=specialise, runtime=runtime,
                    device_medium=device_medium)
    tally = _PixelTally(scene.camera, emission is not None)
    sampling_seconds = _sample(pt, scene.camera, seed, spp, time_budget, t_start, progress,
                               tally)
    n_paths = tally.done * scene.camera.width * scene.camera.height
    header = {
        "spp": tally.done, "seconds": round(time.perf_counter() - t_start, 4), "seed": seed,
        "max_order": max_order if max_order else "all",
        "simulated": "; ".join(pt.simulated), "skipped": "; ".join(pt.skipped),
        "majorant_block": pt.block if majorant_block else "global",
        "defines": " ".join(f"{k}={v}" for k, v in sorted(pt.defines.items())),
        "samples_per_second": round(n_paths / max(sampling_seconds, 1e-9), 1),
        "mean_vertices": round(tally.vertices / n_paths, 3),
        "mean_tracking_steps": round(tally.steps / n_paths, 3),
        "paths_truncated": int(tally.truncated),
        "paths_stopped_at_bound": int(tally.bound),
    }
    if time_budget is not None:
        header["time_budget"] = time_budget
    layers = tally.layers()
    layers["alpha"] = coverage(scene, grid, pt)
    header["alpha_from"] = (f"1 - T(camera ray), marched (step {COVERAGE_STEP} voxel, no early "
                       f"stop) at {COVERAGE_SS}x{COVERAGE_SS} points a pixel")
    return RenderResult(layers=layers, header=header)


# The coverage's sampling: a box filter over the pixel as the path tracer's jittered camera
# rays average it, and steps fine enough that the quadrature error is far below the image's
# noise (0.5 voxel steps, the marcher's default, already give errors below 1e-3 of alpha).
COVERAGE_SS, COVERAGE_STEP = 4, 0.25


def coverage(scene, grid, pt) -> np.ndarray:
    """alpha (H, W): 1 minus the transmittance of the camera ray to the far side of the
    volume, averaged over each pixel (COVERAGE_SS^2 rays on a regular grid). Deterministic:
    the ray marcher's unlit march (cl/raymarch.cl's alpha, the same quantity as the ray
    marcher's layer) on the path tracer's own device medium, not a noisy count of escaping
    paths, so alpha carries no Monte Carlo noise while ``total`` does (docs/pathtrace.md)."""
    from ..kernels.raymarch import (MarchCamera, MarchLight, MarchMs, MarchVolume,
                                    input_defines, launch, raymarch_defines)
    dm = pt.dm
    key = (scene.camera, float(scene.medium.density_scale))
    kept = dm.cache.get("coverage")
    if kept is not None and kept[0] == key:        # the viewer's passes: made once a view
        return kept[1]
    s = COVERAGE_SS
    cam = dataclasses.replace(scene.camera, width=scene.camera.width * s,
                              height=scene.camera.height * s)
    fwd, right, up = cam.basis()
    cell = ((np.asarray(grid.bbox_max, np.float64) - np.asarray(grid.bbox_min, np.float64))
            / np.asarray(np.shape(grid.density)[::-1], np.float64))        # x, y, z
    step = COVERAGE_STEP * float(cell.min())
    evt, outs = launch(defines=dict(raymarch_defines([], lit=False, source="none", octaves=1,
                                                     channels=1, skip_empty=True),
                                    **input_defines("transmittance")),
                       volume=MarchVolume(dm.density, grid.bbox_min, grid.bbox_max,
                                          scene.medium, dm.majorant, dm.block),
                       camera=MarchCamera(cam.origin, fwd, right, up, cam.tan_half_fov,
                                          cam.width, cam.height),
                       light=MarchLight(scene.light, (0.0, 0.0, 0.0)),
                       ms=MarchMs(), step=step, threshold=0.0, runtime=pt.rt, read_back=False)
    fine = pt.rt.from_device(outs["alpha"], (cam.height, cam.width), wait_for=[evt],
                             label="pathtrace coverage")           # the only layer read
    h, w = scene.camera.height, scene.camera.width
    alpha = fine.reshape(h, s, w, s).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)
    dm.cache["coverage"] = (key, alpha)
    return alpha


def _check_render_options(spp, max_order, seed, time_budget):
    """(spp, max_order, seed) checked; spp is DEFAULT_SPP when neither it nor a time budget
    is given."""
    spp = _check_int("--spp", spp, 1)
    max_order = _check_int("--max-order", max_order, 1)
    seed = _check_int("--seed", seed, 0, allow_none=False)
    if time_budget is not None and not (time_budget > 0):
        raise ClvolError(f"--time = {time_budget!r}: must be > 0 seconds")
    if spp is None and time_budget is None:
        spp = DEFAULT_SPP
    return spp, max_order, seed


# The tally's columns: the row's accumulated sun part (background, order 1, orders >= 2), then
# with emission its two parts (seen unscattered, scattered), as the row orders them.
_SUN = ROW_LMS.stop
_EM_DIRECT = slice(_SUN, _SUN + 3)
_EM_SCATTERED = slice(_SUN + 3, _SUN + 6)


class _PixelTally:
    """Per-pixel float64 sums over the sample passes: the row's accumulated parts, the square
    of each path's total (for the standard error), and the paths' vertex, step and truncation
    counts."""

    def __init__(self, camera, emission: bool):
        self.shape = (camera.height, camera.width, 3)
        self.emission = emission
        npix = camera.width * camera.height
        self.sums = np.zeros((npix, _EM_SCATTERED.stop if emission else _SUN))
        self.sq = np.zeros((npix, 3))
        self.vertices = self.steps = 0.0
        self.truncated = self.bound = 0     # paths cut at the vertex limit / a tracking bound
        self.done = 0

    def add(self, rows: np.ndarray, spl: int) -> None:
        """Rows (spl, npix, row) of ``spl`` samples per pixel."""
        rows64 = rows.astype(np.float64)
        total = rows64[..., ROW_BG] + rows64[..., ROW_L1] + rows64[..., ROW_LMS]
        if self.emission:
            self.sums[:, :_SUN] += rows64[..., :_SUN].sum(axis=0)
            self.sums[:, _SUN:] += rows64[..., ROW_EM_DIRECT.start:ROW_EM_SCATTERED.stop].sum(axis=0)
            total = total + rows64[..., ROW_EM_DIRECT] + rows64[..., ROW_EM_SCATTERED]
        else:
            self.sums += rows64[..., :_SUN].sum(axis=0)
        self.sq += (total * total).sum(axis=0)
        self.vertices += rows64[..., ROW_VERTICES].sum()
        self.steps += rows64[..., ROW_STEPS].sum()
        cut, bound = truncation_counts(rows)
        self.truncated += cut
        self.bound += bound
        self.done += spl

    def layers(self) -> dict:
        """The image layers (module docstring) from the means, float32 (H, W, 3)."""
        done, shape = self.done, self.shape
        mean = self.sums / done
        bg, l1, lms = mean[:, ROW_BG], mean[:, ROW_L1], mean[:, ROW_LMS]
        total = bg + l1 + lms
        if self.emission:
            total = total + mean[:, _EM_DIRECT] + mean[:, _EM_SCATTERED]
        var = np.maximum(self.sq / done - total * total, 0.0) * (done / max(done - 1, 1))
        layers = {"total": total.reshape(shape).astype(np.float32),
                  "single": l1.reshape(shape).astype(np.float32),
                  "multiple": lms.reshape(shape).astype(np.float32),
                  "total_se": np.sqrt(var / done).reshape(shape).astype(np.float32)}
        if self.emission:
            layers["emission"] = mean[:, _EM_DIRECT].reshape(shape).astype(np.float32)
            layers["emission_scattered"] = mean[:, _EM_SCATTERED].reshape(shape).astype(np.float32)
        return layers


def _sample(pt, cam, seed: int, spp, time_budget, t_start: float, progress: bool,
            tally: _PixelTally) -> float:
    """Sample passes into ``tally`` until ``spp`` samples per pixel (None: no limit) or the
    time budget; returns the seconds spent sampling. A pass is a fixed range of sample
    indices, so where the budget cuts changes nothing in the samples before it."""
    spl_max = max(1, PATHS_PER_LAUNCH // (cam.width * cam.height))
    t_sampling = time.perf_counter()
    with Progress(spp if spp is not None else time_budget, label="pathtrace",
                  unit=" spp" if spp is not None else " s") as bar:
        bar.enabled = bar.enabled and progress
        while spp is None or tally.done < spp:
            spl = spl_max if spp is None else min(spl_max, spp - tally.done)
            if time_budget is not None and tally.done > 0:
                spl = _within_budget(spl, tally.done, time_budget, t_start, t_sampling)
                if spl < 1:
                    break
            tally.add(pt.render_batch(cam, seed, tally.done, spl), spl)
            bar.update(done=tally.done if spp is not None else time.perf_counter() - t_start)
    return time.perf_counter() - t_sampling


def _within_budget(spl: int, done: int, time_budget: float, t_start: float,
                   t_sampling: float) -> int:
    """``spl``, or the samples per pixel that still fit in the budget when a pass of ``spl``
    would end after it (judged from the ``done`` so far; < 1: stop)."""
    per_sample = (time.perf_counter() - t_sampling) / done
    if time.perf_counter() - t_start + per_sample * spl > time_budget:
        return int((time_budget - (time.perf_counter() - t_start)) / per_sample)
    return spl



def point_query(scene, points, omegas, n_paths: int, seed: int = 0,
                max_order: int | None = None, grid=None, runtime=None,
                majorant_block: int = DEFAULT_BLOCK, device_medium=None) -> dict:
    """In-scattered radiance F(p, omega) for a sun of irradiance 1 (docs/conventions.md).

    points (N, 3) world positions; omegas (N, 3) unit directions toward the camera.
    The sun is the scene's light direction with irradiance 1 in every channel; the
    scene's irradiance and environment are ignored (labels are per unit sun, and the
    environment is not part of F). Returns float64 (N, 3) arrays:
      "F1", "F1_se"   order 1: f(dot(-l, omega)) T(p -> sun) (grey; ratio-tracked T),
      "Fms", "Fms_se" orders >= 2 (RGB: the albedo of later vertices is included, that of
                      p is not, as F excludes sigma_s(p)),
    plus "paths" (n_paths), "truncated" (paths cut at the vertex limit) and
    "stopped_at_bound" (paths stopped by a tracking bound, cl/pathtrace.cl). Points outside
    the box or where the density is 0 are valid (the walk starts there all the same).
    Query q's path j uses the random stream (seed, q, j): same inputs, same output.
    ``device_medium``: the grid already on the device (as in ``render_pathtrace``).
    """
    n_paths = _check_int("n_paths", n_paths, 1, allow_none=False)
    max_order = _check_int("max_order", max_order, 1)
    p = np.asarray(points, np.float64)
    w = np.asarray(omegas, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or w.shape != p.shape:
        raise ClvolError(f"point_query: points {p.shape} and omegas {w.shape} must both be (N, 3)")
    if not (np.isfinite(p).all() and np.isfinite(w).all()):
        raise ClvolError("point_query: points and omegas must be finite")
    norm = np.linalg.norm(w, axis=1)
    if len(w) and np.abs(norm - 1).max() > 1e-4:
        i = int(np.argmax(np.abs(norm - 1)))
        raise ClvolError(f"point_query: omegas must be unit vectors; omegas[{i}] has length {norm[i]:.6g}")
    rt = runtime or get_runtime()
    grid = grid if grid is not None else scene.volume.load()
    med = _medium(scene, grid, max_order, (1.0, 1.0, 1.0), None)
    pt = PathTracer(med, majorant_block, runtime=rt, device_medium=device_medium)
    nq = len(p)
    out = {k: np.zeros((nq, 3)) for k in ("F1", "F1_se", "Fms", "Fms_se")}
    out["paths"] = n_paths
    out["truncated"] = out["stopped_at_bound"] = 0
    if nq == 0:
        return out
    pbuf = rt.to_device(p.astype(np.float32))
    wbuf = rt.to_device(w.astype(np.float32))
    ppl_max = max(1, PATHS_PER_LAUNCH // nq)
    s1, q1, sm, qm = (np.zeros((nq, 3)) for _ in range(4))
    done = 0
    while done < n_paths:
        ppl = min(ppl_max, n_paths - done)
        rows = pt.query_batch(pbuf, wbuf, nq, seed, done, ppl).astype(np.float64)
        a, b = rows[..., ROW_L1], rows[..., ROW_LMS]
        s1 += a.sum(axis=0)
        q1 += (a * a).sum(axis=0)
        sm += b.sum(axis=0)
        qm += (b * b).sum(axis=0)
        cut, bound = truncation_counts(rows)
        out["truncated"] += cut
        out["stopped_at_bound"] += bound
        done += ppl
    n = float(n_paths)
    for key, s, q in (("F1", s1, q1), ("Fms", sm, qm)):
        mean = s / n
        var = np.maximum(q / n - mean * mean, 0.0) * (n / max(n - 1.0, 1.0))
        out[key] = mean
        out[key + "_se"] = np.sqrt(var / n)
    return out


# Albedos at which per-order queries report the label's standard error (the label at any
# other albedo takes the error of the nearest node in log(1 - albedo); clvol/training/labels.py).
SE_ALBEDOS = (1.0, 0.9999, 0.999, 0.997, 0.99, 0.97, 0.9, 0.7, 0.3)


def point_query_orders(scene, points, omegas, n_paths: int, seed: int = 0, grid=None,
                       runtime=None, majorant_block: int = DEFAULT_BLOCK,
                       device_medium=None) -> dict:
    """F_>=2(p, omega) for every albedo from one set of paths (docs/pathtrace.md, "Labels per
    scattering order"): the walks run at albedo 1 (grey), and each sun NEE is binned by its
    albedo exponent e (real collisions after p), so the label at a homogeneous albedo a is
    sum_b S_b a^(M_b / S_b) (clvol/training/labels.py). The scene's albedo is ignored; its
    density, phase and light direction are used, with a sun of irradiance 1.

    Returns float64 arrays: "S", "M" [N][ORDER_BINS] (per-bin means of the contributions and
    of contribution x e), "se" [N][len(SE_ALBEDOS)] (standard error of the label at each of
    SE_ALBEDOS), "F1", "F1_se" [N]; "vertices_mean" [N], "vertices_max" [N] (path lengths),
    and the counts "paths", "truncated" (paths cut at the vertex limit: their remaining
    orders are missing from the label, so a data set reports them)."""
    n_paths = _check_int("n_paths", n_paths, 2, allow_none=False)
    p = np.asarray(points, np.float64)
    w = np.asarray(omegas, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or w.shape != p.shape:
        raise ClvolError(f"point_query_orders: points {p.shape} and omegas {w.shape} must both be (N, 3)")
    rt = runtime or get_runtime()
    grid = grid if grid is not None else scene.volume.load()
    med = _medium(dataclasses.replace(scene, medium=dataclasses.replace(
        scene.medium, albedo=(1.0, 1.0, 1.0))), grid, None, (1.0, 1.0, 1.0), None)
    pt = PathTracer(med, majorant_block, runtime=rt, device_medium=device_medium)
    nq = len(p)
    nodes = np.asarray(SE_ALBEDOS, np.float64)
    S, M = np.zeros((nq, ORDER_BINS)), np.zeros((nq, ORDER_BINS))
    xs, xq = np.zeros((nq, len(nodes))), np.zeros((nq, len(nodes)))
    s1, q1 = np.zeros(nq), np.zeros(nq)
    vsum, vmax = np.zeros(nq), np.zeros(nq)
    out = {"paths": n_paths, "truncated": 0, "stopped_at_bound": 0}
    if nq:
        pbuf = rt.to_device(p.astype(np.float32))
        wbuf = rt.to_device(w.astype(np.float32))
        ppl_max = max(1, PATHS_PER_LAUNCH // nq // 4)   # rows are 22x wider than plain ones
        log_nodes = np.log(np.maximum(nodes, 1e-300))
        done = 0
        while done < n_paths:
            ppl = min(ppl_max, n_paths - done)
            rows = pt.query_batch(pbuf, wbuf, nq, seed, done, ppl, orders=True).astype(np.float64)
            sb, mb = rows[..., PT_OUT:PT_OUT + ORDER_BINS], rows[..., PT_OUT + ORDER_BINS:]
            S += sb.sum(axis=0)
            M += mb.sum(axis=0)
            # Each path's label at the nodes, for the standard error (the path's own mean
            # exponent per bin: exact where a bin holds one order, as the exact bins do).
            ebar = np.divide(mb, sb, out=np.zeros_like(mb), where=sb > 0)
            x = np.einsum("pqb,pqbn->pqn", sb, np.exp(ebar[..., None] * log_nodes))
            xs += x.sum(axis=0)
            xq += (x * x).sum(axis=0)
            l1 = rows[..., ROW_L1][..., 0]
            s1 += l1.sum(axis=0)
            q1 += (l1 * l1).sum(axis=0)
            v = rows[..., ROW_VERTICES]
            vsum += v.sum(axis=0)
            vmax = np.maximum(vmax, v.max(axis=0))
            cut, bound = truncation_counts(rows)
            out["truncated"] += cut
            out["stopped_at_bound"] += bound
            done += ppl
    n = float(n_paths)

    def se(total, sq):
        mean = total / n
        return np.sqrt(np.maximum(sq / n - mean * mean, 0.0) / (n - 1.0))
    out.update(S=S / n, M=M / n, se=se(xs, xq), F1=s1 / n, F1_se=se(s1, q1),
               vertices_mean=vsum / n, vertices_max=vmax)
    return out


def mitsuba_scene_dict(scene, grid, spp: int, seed: int = 0, max_depth: int = -1) -> dict:
    """The same scene for Mitsuba 3's ``volpath`` (cross-checks and benchmarks only).

    Call after ``mitsuba.set_variant(...)``; pass the result to ``mitsuba.load_dict``.
    Mapping: the grid [z][y][x] as a ``gridvolume`` over the box (Mitsuba's voxel-centre,
    clamped trilinear convention is ours), ``heterogeneous`` medium with ``scale`` =
    density_scale, a ``cube`` with a ``null`` BSDF as its boundary, ``directional``
    emitter with direction -l (Mitsuba gives the propagation direction), a ``constant``
    emitter for the environment, a perspective sensor with ``fov_axis`` y and a box
    filter (our jittered pixel average). Isotropic and one-lobe HG phases only.
    """
    import mitsuba as mi
    m = scene.medium
    if m.phase.is_isotropic:
        phase = {"type": "isotropic"}
    elif len(m.phase.lobes) == 1:
        phase = {"type": "hg", "g": float(m.phase.lobes[0].g)}
    else:
        raise ClvolError("mitsuba export: multi-lobe HG phases are not supported")
    T = mi.ScalarTransform4f
    lo = np.asarray(grid.bbox_min, np.float64)
    ext = np.asarray(grid.bbox_max, np.float64) - lo
    cam = scene.camera
    light = scene.light
    rgb = lambda v: {"type": "rgb", "value": [float(c) for c in v]}  # noqa: E731
    d = {
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": int(max_depth)},
        "sensor": {
            "type": "perspective", "fov": float(cam.fov_y), "fov_axis": "y",
            "to_world": T().look_at(origin=list(cam.origin), target=list(cam.target),
                                    up=list(cam.up)),
            "film": {"type": "hdrfilm", "width": cam.width, "height": cam.height,
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": int(spp), "seed": int(seed)}},
        "sun": {"type": "directional", "direction": [-float(c) for c in light.direction],
                "irradiance": rgb(light.irradiance)},
        "volume": {
            "type": "cube", "bsdf": {"type": "null"},
            "to_world": T().translate((lo + ext / 2).tolist()) @ T().scale((ext / 2).tolist()),
            "interior": {
                "type": "heterogeneous", "albedo": rgb(m.albedo), "scale": float(m.density_scale),
                "sigma_t": {"type": "gridvolume",
                            "grid": mi.VolumeGrid(np.ascontiguousarray(grid.density[..., None])),
                            "to_world": T().translate(lo.tolist()) @ T().scale(ext.tolist())},
                "phase": phase}},
    }
    if light.environment is not None:
        d["environment"] = {"type": "constant", "radiance": rgb(light.environment)}
    return d


__all__ = ["add_arguments", "render_pathtrace", "point_query", "mitsuba_scene_dict",
           "PT_OUT"]
