"""The feature contract between the template gather (cl/gather.cl) and the network.

This module is the one place the layout is written down; the gather, the NumPy
reference, the torch model, the OpenCL forward pass and the weight export all read it,
and a weight file records ``LAYOUT_VERSION`` and ``contract_dict()`` so a network is never
fed features of another layout. Change anything here -> bump ``LAYOUT_VERSION``.

Template points (seed III.B.2): a diffuse template of 8 spherical layers and a highlight
template of 4 layers toward the light. Point order is: diffuse layers 0..7, then highlight
layers 0..3, each layer's points in the order of its table (clvol/data/templates.npz).
The seed says 182 diffuse points but its per-layer counts sum to 194; we follow the counts.

Per query (one point p, view direction omega toward the camera, one colour channel):
  features  float32 [N][3][N_POINTS]     type-major: index FEATURE_TYPES
      density        log1p(optical thickness of one voxel of the layer's mip level),
                     i.e. log1p(sigma_t,i * dx_i)  (docs/conventions.md: invariant to scale x size)
      transmittance  the combined graded transmittance sum_m w_m T_m + b (rendering), in
                     the units of T (no log); training uses ``levels`` below instead.
                     Each T_m is sampled at the voxel centres of the point's *density* level
                     and interpolated trilinearly to the point with the density's weights, so
                     density and transmittance share one footprint (and one interleaved read
                     at render time, from a grid baked per level with sum_m w_m T_m + b)
      phase          log1p(volume-phase feature)  (seed eq. 5; the centre point uses the
                     plain phase function f(dot(-l, omega)))
  levels    float32 [N][N_LEVELS][N_POINTS]  every graded transmittance level T_m at every
            point, on the density level's footprint as above (training only; the model learns
            the per-level weights: the seed's 3D-CNN as a 1x1x1 convolution across levels).
            The render feature equals sum_m w_m levels[m] + b (tests/test_gather.py).
  config    float32 [N][CONFIG_DIM]        fields CONFIG_FIELDS:
      g0 g1 g2   HG lobe asymmetries (unused lobes: g 0, weight 0)
      w0 w1 w2   lobe weights (sum 1)
      g_mean     mean cosine sum w_k g_k (the one g the attention squeeze uses)
      albedo     single-scattering albedo of this colour channel
      alpha      angle between view and light, acos(dot(-l, omega)) in radians (0: looking into the sun)
Outside the medium or beyond the box, density is 0 and T is 1 (defined, not undefined).
"""
from __future__ import annotations

import numpy as np

LAYOUT_VERSION = 1

DIFFUSE_LAYER_COUNTS = (6, 8, 12, 16, 24, 32, 48, 48)
HIGHLIGHT_LAYER_COUNTS = (32, 16, 16, 8)
LAYER_COUNTS = DIFFUSE_LAYER_COUNTS + HIGHLIGHT_LAYER_COUNTS
N_DIFFUSE = sum(DIFFUSE_LAYER_COUNTS)      # 194
N_HIGHLIGHT = sum(HIGHLIGHT_LAYER_COUNTS)  # 72
N_POINTS = N_DIFFUSE + N_HIGHLIGHT         # 266

FEATURE_TYPES = ("density", "transmittance", "phase")
CONFIG_FIELDS = ("g0", "g1", "g2", "w0", "w1", "w2", "g_mean", "albedo", "alpha")
CONFIG_DIM = len(CONFIG_FIELDS)

# Graded transmittance levels for the default 256^3 base (levels 0..8 = 256^3 .. 1^3).
DEFAULT_BASE_RESOLUTION = 256
DEFAULT_LAMBDA = 0.6


# Base resolutions a network can be trained at and run with (a power of two in this range).
MIN_NETWORK_BASE, MAX_NETWORK_BASE = 2, 512


def is_power_of_two(n) -> bool:
    """``n`` is an integer (not a bool) >= 1 with a single bit set."""
    return (isinstance(n, (int, np.integer)) and not isinstance(n, (bool, np.bool_))
            and n >= 1 and (int(n) & (int(n) - 1)) == 0)


def n_levels(base_resolution: int = DEFAULT_BASE_RESOLUTION) -> int:
    """Mip levels from base^3 down to 1^3 (9 for 256, 11 for 1024): log2(base) + 1 for the
    power-of-two bases the pyramid takes."""
    return int(base_resolution).bit_length()


N_LEVELS = n_levels()


def layer_slices() -> list[slice]:
    """Point-index slice of each layer: 8 diffuse then 4 highlight."""
    out, start = [], 0
    for count in LAYER_COUNTS:
        out.append(slice(start, start + count))
        start += count
    return out


def contract_dict(base_resolution: int = DEFAULT_BASE_RESOLUTION,
                  lam: float = DEFAULT_LAMBDA, template_hash: str = "") -> dict:
    """What a weight file must match to be fed by this gather."""
    return {
        "layout_version": LAYOUT_VERSION,
        "layer_counts": list(LAYER_COUNTS),
        "feature_types": list(FEATURE_TYPES),
        "config_fields": list(CONFIG_FIELDS),
        "base_resolution": int(base_resolution),
        "n_levels": n_levels(base_resolution),
        "lambda": float(lam),
        "template_hash": template_hash,  # clvol.features.templates.load_templates().sha256
        "frame": "z = l (toward light), x = omega's part perpendicular to l, y = z x x",
        "units": {"density": "log1p(tau_voxel)", "transmittance": "T", "phase": "log1p(f*f*)",
                  "alpha": "radians"},
    }
