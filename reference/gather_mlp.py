"""NumPy twin of cl/gather_mlp.cl (the fused render-mode gather + network): reference/gather.py's
render-mode features and reference/mlp.py's config rows, forward pass and decode, composed.
Nothing of its own beyond the composition (the two twins are the yardsticks) and the device
output layout (``gather_mlp_into``: F scattered into caller-owned planes, as the kernel's
out_index and channel_stride arguments place it)."""

import numpy as np

from reference import gather as rgather
from reference import mlp as rmlp


def features(pyr, graded_data, points, omegas, light_dir, lobes, density_scale, albedo,
             level_weights, bias):
    """(features [N][3][NP], config [N][9]) as the kernel computes them internally."""
    g = rgather.gather(pyr, graded_data, points, omegas, light_dir, lobes, density_scale,
                       mode="render", level_weights=level_weights, bias=bias)
    return g["features"], rmlp.config_rows(lobes, albedo, g["alpha"])


def gather_mlp(params, arch, pyr, graded_data, points, omegas, light_dir, lobes, density_scale,
               albedo, level_weights, bias, channel_albedo=None):
    """Decoded F: [N] with the config's ``albedo`` (scalar or [N]), or [N][3] with
    ``channel_albedo`` (reference.mlp.radiance)."""
    f, c = features(pyr, graded_data, points, omegas, light_dir, lobes, density_scale, albedo,
                    level_weights, bias)
    if channel_albedo is None:
        return rmlp.decode(rmlp.forward(params, arch, f, c), c[:, rmlp.ALBEDO])
    return rmlp.radiance(params, arch, f, c, channel_albedo)


def gather_mlp_into(out, out_index, params, arch, pyr, graded_data, points, omegas, light_dir,
                    lobes, density_scale, albedo, level_weights, bias, channel_albedo=None):
    """The kernel's device output: ``out`` holds C planes (shape (C, ...), C = 1 without
    ``channel_albedo``, else 3); channel c of query q is stored at element ``out_index[q]`` of
    plane c, i.e. at flat index out_index[q] + c * (out.size // C) (the kernel's out_index and
    channel_stride), and nothing else of ``out`` changes. Returns ``out`` (written in place)."""
    F = gather_mlp(params, arch, pyr, graded_data, points, omegas, light_dir, lobes,
                   density_scale, albedo, level_weights, bias, channel_albedo)
    F = F[:, None] if F.ndim == 1 else F
    C = F.shape[1]
    if out.shape[0] != C or not out.flags.c_contiguous:
        raise ValueError(f"out must be C-contiguous with {C} planes, got {out.shape}")
    stride = out.size // C
    flat = out.reshape(-1)                       # a view: out is C-contiguous
    for c in range(C):
        flat[np.asarray(out_index) + c * stride] = F[:, c]
    return out
