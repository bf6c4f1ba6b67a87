"""Host wrapper for cl/gather_mlp.cl: the render-mode gather and the network in one kernel.

    net = MlpKernel(weights)
    F = gather_mlp(net, pyr, graded, points, omegas, light_dir, medium, albedo,
                   level_weights=w, bias=b)                        # F [N], config albedo
    F = gather_mlp(..., channel_albedo=(0.9, 0.95, 1.0))          # F [N][3], one per channel
    gather_mlp(..., out=lattice, out_index=idx, nonfinite=flag)   # into a device lattice

The inputs are those of ``gather(..., mode="render")`` (clvol/kernels/gather.py; ``albedo``
is its ``channel_albedo``, the config's albedo) and of ``MlpKernel.forward(...,
channel_albedo=None or RGB, decode=True)``, and the result is the same: F decoded, [N] or
[N][3] (tests/test_gather_mlp.py). The features never leave the kernel's private memory
(no ~200 MiB per 65,536 queries written and read back); the bake of the combined
transmittance grid is the gather's (``bake_render_grid``, cached per pyramid). With ``out``
the results go straight into a caller-owned device array of planes (the ray marcher's F_ms
lattice) and nothing is read back.
"""
from __future__ import annotations

import numpy as np

from ..features import layout
from ..runtime import DeviceArray
from .gather import (GatherError, _check_inputs, _lobes, _phase_table_padded, bake_render_grid,
                     config_vectors, gather_defines, query_order, static_args)
from .grid import f4
from .mlp import MlpKernel, _channel_albedo, launch_items
from .phase import lobe_vectors


def gather_mlp(net: MlpKernel, pyramid, graded, points, omegas, light_dir, medium, albedo,
               level_weights, bias: float = 0.0, channel_albedo=None, sort: bool = True,
               out: DeviceArray | None = None, out_index=None,
               nonfinite: DeviceArray | None = None, defines: dict | None = None):
    """F (decoded, >= 0 up to the network's sign) at N queries: [N] with ``albedo`` (scalar or
    (N,)) in the config, or [N][3] with ``channel_albedo`` (one evaluation per distinct
    non-zero channel albedo; albedo-0 channels give 0). ``sort``: process the queries in
    ``query_order`` (faster; results in the caller's order either way).

    Device out (the ray marcher's F_ms lattice, NetworkSource.fill_device): ``out`` a
    caller-owned float32 DeviceArray of C planes, shape (C, ...) with C = 1 without
    ``channel_albedo`` and 3 with it, and ``out_index`` (N,) distinct ints in [0, plane size):
    channel c of query q goes to element ``out_index[q]`` of plane c. Nothing else of ``out``
    is written, nothing is read back, and ``out`` is returned. ``nonfinite``: a (1,) int32
    DeviceArray into which the kernel ORs 1 when a value it writes is not finite (the caller
    zeroes it before and reads it after); the NumPy path's caller checks the array it gets.
    ``defines``: the program's -D defines as the frame's plan lists them (FramePlan.programs
    "gather_mlp" with the device's additions); None: formed here from the kernels' own
    functions."""
    if net.arch.n_points != layout.N_POINTS:
        raise GatherError(f"the network reads {net.arch.n_points} template points, the gather "
                          f"writes {layout.N_POINTS}")
    if net.rt is not pyramid.runtime:
        raise GatherError("the network and the pyramid must live on the same runtime")
    pts, om, l = _check_inputs(pyramid, graded, points, omegas, light_dir, medium, "render")
    rt = pyramid.runtime
    n = len(pts)
    channels = 1 if channel_albedo is None else 3
    if out is not None:
        index, stride = _device_layout(out, out_index, n, channels)
    elif out_index is not None:
        raise GatherError("out_index goes with out (a caller-owned DeviceArray of planes)")
    alb = np.zeros(4, np.float32)
    if channel_albedo is not None:
        alb[:3] = _channel_albedo(channel_albedo)
    lobes = _lobes(medium)
    cfg = config_vectors(medium, albedo, om, l)
    baked = bake_render_grid(pyramid, graded, medium.density_scale, level_weights, bias)
    if n == 0:
        return out if out is not None else np.zeros((0,) if channels == 1 else (0, 3), np.float32)
    if out is None:              # NumPy out: [n][C] rows, read back below
        host_out = rt.alloc((n, channels))
        index, stride = np.arange(n, dtype=np.int32) * channels, 1
    if defines is None:          # no plan (tests, benchmarks): the kernels' own functions
        defines = dict(gather_defines(pyramid, lobes, render=True), **net.defines(channels, True))
    elif int(defines.get("MLP_CHANNELS", 0)) != channels:
        raise GatherError(f"gather_mlp: the planned program has MLP_CHANNELS "
                          f"{defines.get('MLP_CHANNELS')}, the call {channels}")
    k = rt.program("gather_mlp", defines=defines).kernel(
        "gather_mlp", [None, None, None, np.int32, np.int32, None, np.float32, None, None, None,
                       None, np.int32, None, None, None, None, None, np.float32, None, None,
                       None, None, np.int32, None, np.int32, None, None])
    loff, tpl, pinfo, hl = static_args(pyramid)
    ptab = _phase_table_padded(lobes)
    lg, lw = lobe_vectors(lobes)
    order = query_order(pyramid, pts) if sort else np.arange(n, dtype=np.int32)
    flag = nonfinite if nonfinite is not None else rt.alloc(1, np.int32, zero=True)
    dst = out if out is not None else host_out
    evt = launch_items(rt, k, n, (
        pyramid.device.buffer, baked.device.buffer, loff, np.int32(pyramid.n_levels),
        np.int32(pyramid.base_resolution), f4(pyramid.cube_min), np.float32(pyramid.cube_size),
        tpl, pinfo, hl, rt.to_device(ptab), np.int32(ptab.shape[0]),
        rt.to_device(pts), rt.to_device(om), f4(l), lg, lw, np.float32(baked.c_out),
        rt.to_device(order), rt.to_device(cfg), net.params_device.buffer, alb, np.int32(n),
        rt.to_device(index), np.int32(stride), dst.buffer, flag.buffer))
    if out is not None:
        return out
    F = host_out.read(wait_for=[evt])
    return F[:, 0] if channels == 1 else F


def _device_layout(out, out_index, n: int, channels: int):
    """(int32 element index of each query's channel 0, channel stride) in ``out``'s planes,
    or GatherError naming what does not fit."""
    if not isinstance(out, DeviceArray) or np.dtype(out.dtype) != np.float32:
        raise GatherError(f"out must be a float32 DeviceArray, got {type(out).__name__}")
    if len(out.shape) < 2 or out.shape[0] != channels:
        raise GatherError(f"out must be {channels} plane(s) (C, ...), got shape {out.shape}")
    plane = out.size // channels
    if out.size >= 2 ** 31:
        raise GatherError(f"out has {out.size} elements; the kernel indexes them with int")
    if out_index is None:
        raise GatherError("out needs out_index: each query's element in a plane")
    idx = np.asarray(out_index)
    if idx.shape != (n,) or not np.issubdtype(idx.dtype, np.integer):
        raise GatherError(f"out_index must be {n} integers (one per query), got "
                          f"{idx.dtype} {idx.shape}")
    if n and (idx.min() < 0 or idx.max() >= plane):
        raise GatherError(f"out_index must lie in [0, {plane}) (a plane of out), got "
                          f"[{idx.min()}, {idx.max()}]")
    return np.ascontiguousarray(idx, np.int32), plane
