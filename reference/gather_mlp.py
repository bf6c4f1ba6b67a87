"""NumPy twin of cl/gather_mlp.cl (the fused render-mode gather + network): reference/gather.py's
render-mode features and reference/mlp.py's config rows, forward pass and decode, composed.
Nothing of its own beyond the composition (the two twins are the yardsticks)."""

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
