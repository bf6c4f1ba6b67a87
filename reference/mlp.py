"""NumPy twin of cl/mlp.cl and of clvol.training.model.Model: the network's forward pass.

Inputs follow the feature contract (docs/network.md): features float32 [N][3][P] (density, transmittance, phase; P = 266
template points, diffuse layers then highlight layers), config float32 [N][9]
(g0 g1 g2 w0 w1 w2 g_mean albedo alpha). In training, ``levels`` [N][L][P] replaces the
transmittance feature by sum_l level_weights[l] * levels[:, l] + level_bias (the seed's 3D-CNN);
at render time the gather has already done that sum with the exported weights.

The architecture (seed III.C with the FC-ReLU-FC-sigmoid excitation of docs/conventions.md) is written out in
clvol/features/weights.py's docstring; this file is its executable statement, in float64 by default so it can
serve as the yardstick for the float32 torch and OpenCL versions.

Output y = log(F / albedo^4 + 1) per query (seed eq. 20's normalised log space); ``decode`` turns
it into F = albedo^4 * max(exp(y) - 1, 0). ``radiance`` evaluates per colour channel with that
channel's albedo (one evaluation for a grey medium, three for a chromatic one; albedo 0 -> F = 0
without evaluating).
"""
from __future__ import annotations

import numpy as np

# Written here from the seed, docs/network.md and docs/templates.md, not imported from clvol
# (a twin shares no code with what it checks, the feature contract included): the output
# encoding's gamma (seed eq. 20), the template order of the modules, the albedo input's
# offset, the feature and config layout, the default point and level counts.
# tests/test_mlp.py holds each equal to clvol's statement. ``arch`` is read as data only (its
# fields: layer_counts, n_diffuse_layers, head_widths, albedo_input); the slicing is derived.
GAMMA = 4.0
TEMPLATES = ("diffuse", "highlight")
TYPES = ("density", "transmittance", "phase")
CONFIG_FIELDS = ("g0", "g1", "g2", "w0", "w1", "w2", "g_mean", "albedo", "alpha")
ALBEDO_EPS = 1e-4
G_MEAN = CONFIG_FIELDS.index("g_mean")
ALBEDO = CONFIG_FIELDS.index("albedo")
ALPHA = CONFIG_FIELDS.index("alpha")
N_POINTS = sum((6, 8, 12, 16, 24, 32, 48, 48)) + sum((32, 16, 16, 8))   # diffuse + highlight
N_LEVELS = 9                      # graded transmittance levels of a 256^3 base: 256^3 .. 1^3


def _relu(x):
    return np.maximum(x, 0)


def _sigmoid(x):
    # exp of -|x| never overflows; same value as 1 / (1 + exp(-x)).
    e = np.exp(-np.abs(x))
    return np.where(x >= 0, 1 / (1 + e), e / (1 + e))


class _Net:
    def __init__(self, params, arch, dtype, trace):
        self.p = {k: np.asarray(v, dtype) for k, v in params.items()}
        self.arch, self.dtype, self.trace = arch, dtype, trace

    def linear(self, name, x, relu=True):
        y = x @ self.p[f"{name}.weight"].T + self.p[f"{name}.bias"]
        if relu:
            y = _relu(y)
            if self.trace is not None:
                self.trace[name] = float(np.mean(y > 0))
        return y


def combine_levels(params, levels, dtype=np.float64):
    """sum_l level_weights[l] * levels[:, l, :] + level_bias  ->  [N][P]."""
    w = np.asarray(params["level_weights"], dtype)
    b = np.asarray(params["level_bias"], dtype)[0]
    return np.einsum("nlp,l->np", np.asarray(levels, dtype), w) + b


def layer_slices(arch) -> list:
    """Point ranges of the template layers, in order (diffuse layers first)."""
    ends = np.cumsum([0] + [int(n) for n in arch.layer_counts])
    return [slice(int(a), int(b)) for a, b in zip(ends[:-1], ends[1:])]


def template_layer_slices(arch, template) -> list:
    sl, nd = layer_slices(arch), int(arch.n_diffuse_layers)
    return sl[:nd] if template == "diffuse" else sl[nd:]


def squeeze(x, c, arch):
    """The seed's v_k per template layer: [N][n_layers][8] = (mean_d, mean_T, mean_p, max_d,
    max_T, max_p, g_mean, alpha) of the normalised inputs."""
    v = []
    for sl in layer_slices(arch):
        part = x[:, :, sl]
        v.append(np.concatenate([part.mean(axis=2), part.max(axis=2),
                                 c[:, [G_MEAN]], c[:, [ALPHA]]], axis=1))
    return np.stack(v, axis=1)


def forward(params: dict, arch, features, config, levels=None,
            dtype=np.float64, trace: dict | None = None) -> np.ndarray:
    """y [N] for features [N][3][P], config [N][9] (and optionally levels [N][L][P]).
    ``trace``, if a dict, receives the fraction of positive outputs of every ReLU layer."""
    net = _Net(params, arch, dtype, trace)
    p = net.p
    x = np.array(features, dtype)
    if levels is not None:
        x[:, TYPES.index("transmittance"), :] = combine_levels(params, levels, dtype)
    c = np.array(config, dtype)
    if arch.albedo_input == "log1m":      # -log(1 - a + 1e-4): docs/network.md
        c[:, ALBEDO] = -np.log1p(ALBEDO_EPS - c[:, ALBEDO])
    x = (x - p["feature_shift"][None, :, None]) * p["feature_scale"][None, :, None]
    c = (c - p["config_shift"]) * p["config_scale"]
    v = squeeze(x, c, arch)
    merged = []
    for ti, t in enumerate(TYPES):
        outs = []
        for s in TEMPLATES:
            pre = f"branches.{t}.{s}"
            slices = template_layer_slices(arch, s)
            first = 0 if s == "diffuse" else arch.n_diffuse_layers
            h = x[:, ti, slices[0]]
            for k, sl in enumerate(slices):
                a = np.concatenate([h, c], axis=1)
                w = _sigmoid(net.linear(f"{pre}.se_b.{k}", net.linear(f"{pre}.se_a.{k}", v[:, first + k]),
                                        relu=False))
                z = w * a
                if k + 1 < len(slices):
                    nxt = x[:, ti, slices[k + 1]]
                    u = net.linear(f"{pre}.fc1.{k}", z) + nxt
                    h = net.linear(f"{pre}.fc2.{k}", u) + nxt
            outs.append(net.linear(f"{pre}.out", z))
        merged.append(net.linear(f"merges.{t}", np.concatenate(outs, axis=1)))
    hid = np.concatenate(merged + [c], axis=1)
    n_head = len(arch.head_widths) + 1
    for j in range(n_head):
        hid = net.linear(f"head.{j}", hid, relu=j + 1 < n_head)
    return hid[:, 0]


def with_albedo(config, albedo):
    """A copy of config [N][9] with the albedo field replaced (scalar or [N])."""
    c = np.array(config, copy=True)
    c[:, ALBEDO] = albedo
    return c


def forward_channels(params, arch, features, config, channel_albedo, dtype=np.float64) -> np.ndarray:
    """y [N][C]: one evaluation per channel with config's albedo replaced by channel_albedo[c]."""
    return np.stack([forward(params, arch, features, with_albedo(config, a), dtype=dtype)
                     for a in np.atleast_1d(channel_albedo)], axis=1)


def encode(F, albedo, gamma: float = GAMMA):
    """y = log(F / albedo^gamma + 1) (seed eq. 20); albedo must be > 0."""
    F, a = np.asarray(F, np.float64), np.asarray(albedo, np.float64)
    return np.log1p(F / a ** gamma)


def decode(y, albedo, gamma: float = GAMMA):
    """F = albedo^gamma * max(exp(y) - 1, 0); 0 where albedo is 0."""
    y, a = np.asarray(y, np.float64), np.asarray(albedo, np.float64)
    return a ** gamma * np.maximum(np.expm1(y), 0.0)


def radiance(params, arch, features, config, channel_albedo, dtype=np.float64) -> np.ndarray:
    """F [N][3] (orders >= 2, unit irradiance) for an RGB albedo: one evaluation per distinct
    non-zero channel albedo (grey: one), channels of albedo 0 are 0."""
    alb = np.asarray(channel_albedo, np.float64).reshape(3)
    out = np.zeros((len(config), 3))
    for a in np.unique(alb[alb > 0]):
        F = decode(forward(params, arch, features, with_albedo(config, a), dtype=dtype), a)
        out[:, alb == a] = F[:, None]
    return out


def config_rows(lobes, albedo, alpha) -> np.ndarray:
    """Config [N][9] for one phase function (list of (g, weight), 1-3 lobes), albedo [N] or
    scalar and alpha [N] (radians), as the gather writes it."""
    alpha = np.atleast_1d(np.asarray(alpha, np.float64))
    n = len(alpha)
    c = np.zeros((n, len(CONFIG_FIELDS)), np.float32)
    for k, (g, w) in enumerate(lobes):
        c[:, k], c[:, 3 + k] = g, w
    c[:, G_MEAN] = sum(g * w for g, w in lobes)
    c[:, ALBEDO] = albedo
    c[:, ALPHA] = alpha
    return c


def random_inputs(n: int, rng: np.random.Generator, arch=None,
                  lobes=((0.857, 1.0),), albedo=None, levels: bool = False):
    """Random inputs in the ranges real features take: density log1p(tau) in [0, 3], T in
    [0, 1], phase log1p(f f*) in [0, 4]; alpha uniform in [0, pi]; albedo uniform in [0.3, 1]
    unless given. Returns (features, config) or (features, config, levels). Without ``arch``,
    the layout's point and level counts."""
    P = N_POINTS if arch is None else sum(int(k) for k in arch.layer_counts)
    n_levels = N_LEVELS if arch is None else int(arch.n_levels)
    f = np.empty((n, 3, P), np.float32)
    # spatially smooth-ish: a per-query level plus per-point variation, so layers differ
    f[:, 0] = np.clip(rng.uniform(0, 2, (n, 1)) + rng.normal(0, 0.5, (n, P)), 0, 3)
    f[:, 1] = rng.uniform(0, 1, (n, 1)) ** 2 * rng.uniform(0.5, 1, (n, P))
    f[:, 2] = rng.uniform(0, 4, (n, P)) * rng.uniform(0, 1, (n, 1))
    a = rng.uniform(0.3, 1.0, n) if albedo is None else albedo
    c = config_rows(lobes, a, rng.uniform(0, np.pi, n))
    if not levels:
        return f, c
    lv = np.clip(f[:, 1][:, None, :] * rng.uniform(0.7, 1.3, (n, n_levels, P)), 0, 1).astype(np.float32)
    return f, c, lv
