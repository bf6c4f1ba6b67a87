"""The network in torch (training only; rendering uses clvol/features/weights.py + cl/mlp.cl, no torch).

Seed III.C: six modules {density, transmittance, phase} x {diffuse, highlight} of one structure,
each walking its template layers with squeeze-and-excitation attention, FC-1 to the next layer's
width and FC-2 fusion; diffuse and highlight merged per type by an FC layer; the three types and the
configuration merged by a small MLP head. The architecture is written out in clvol/features/weights.py and
executed in NumPy by reference/mlp.py; parameter names here are the weight file's tensor names.

Inputs (clvol/features/layout.py): features [N][3][P], config [N][9] and, in training, levels [N][L][P]:
the transmittance feature is then sum_l level_weights[l] T_l + level_bias, learned here (the seed's
"3D-CNN" is a 1x1x1 convolution across levels) and baked by the gather at render time.
Output y [N] = log(F / albedo^4 + 1) (seed eq. 20).
"""
from __future__ import annotations

import numpy as np
import torch
from torch import nn

from ..features import layout
from ..features.weights import (ALBEDO_EPS, DEFAULT_CONFIG_SCALE, LOG1M_SCALE, LOG1M_SHIFT, SQUEEZE_DIM,
                               TEMPLATES, TYPES, Architecture, MlpWeights, save_weights)

G_MEAN = layout.CONFIG_FIELDS.index("g_mean")
ALBEDO = layout.CONFIG_FIELDS.index("albedo")
ALPHA = layout.CONFIG_FIELDS.index("alpha")
T_INDEX = TYPES.index("transmittance")


class Chain(nn.Module):
    """One module: the layer walk of one feature type over one template."""

    def __init__(self, counts: tuple, config_dim: int, se_hidden: int, width: int):
        super().__init__()
        c = config_dim
        self.counts = counts
        self.se_a = nn.ModuleList(nn.Linear(SQUEEZE_DIM, se_hidden) for _ in counts)
        self.se_b = nn.ModuleList(nn.Linear(se_hidden, n + c) for n in counts)
        self.fc1 = nn.ModuleList(nn.Linear(n + c, m) for n, m in zip(counts[:-1], counts[1:]))
        self.fc2 = nn.ModuleList(nn.Linear(m, m) for m in counts[1:])
        self.out = nn.Linear(counts[-1] + c, width)

    def forward(self, xs: list, c: torch.Tensor, vs: list) -> torch.Tensor:
        """xs: this type's features per layer [N][n_k]; c: config [N][9]; vs: squeeze [N][8] per layer."""
        h = xs[0]
        for k in range(len(self.counts)):
            a = torch.cat([h, c], dim=1)
            w = torch.sigmoid(self.se_b[k](torch.relu(self.se_a[k](vs[k]))))
            z = w * a
            if k + 1 < len(self.counts):
                u = torch.relu(self.fc1[k](z)) + xs[k + 1]
                h = torch.relu(self.fc2[k](u)) + xs[k + 1]
        return torch.relu(self.out(z))


class Model(nn.Module):
    def __init__(self, arch: Architecture | None = None):
        super().__init__()
        self.arch = arch = arch or Architecture()
        L = arch.n_levels
        self.level_weights = nn.Parameter(torch.full((L,), 1.0 / L))
        self.level_bias = nn.Parameter(torch.zeros(1))
        self.register_buffer("feature_shift", torch.zeros(len(TYPES)))
        self.register_buffer("feature_scale", torch.ones(len(TYPES)))
        self.register_buffer("config_shift", torch.zeros(arch.config_dim))
        self.register_buffer("config_scale", torch.tensor(DEFAULT_CONFIG_SCALE, dtype=torch.float32))
        if arch.albedo_input == "log1m":
            with torch.no_grad():
                self.config_shift[ALBEDO] = LOG1M_SHIFT
                self.config_scale[ALBEDO] = LOG1M_SCALE
        m = arch.module_width
        self.branches = nn.ModuleDict({
            t: nn.ModuleDict({s: Chain(arch.template_counts(s), arch.config_dim, arch.se_hidden, m)
                              for s in TEMPLATES}) for t in TYPES})
        self.merges = nn.ModuleDict({t: nn.Linear(2 * m, m) for t in TYPES})
        widths = (3 * m + arch.config_dim,) + arch.head_widths + (1,)
        self.head = nn.ModuleList(nn.Linear(a, b) for a, b in zip(widths[:-1], widths[1:]))
        self._slices = arch.layer_slices()

    def forward(self, features: torch.Tensor, config: torch.Tensor,
                levels: torch.Tensor | None = None) -> torch.Tensor:
        if levels is not None:
            t = torch.einsum("nlp,l->np", levels, self.level_weights) + self.level_bias
            features = torch.cat([features[:, :T_INDEX], t[:, None], features[:, T_INDEX + 1:]], dim=1)
        # (x - shift) * scale as one fused pass over the large feature tensor
        scale = self.feature_scale[None, :, None]
        x = torch.addcmul(-self.feature_shift[None, :, None] * scale, features, scale)
        if self.arch.albedo_input == "log1m":
            a = -torch.log1p(ALBEDO_EPS - config[:, ALBEDO:ALBEDO + 1])
            config = torch.cat([config[:, :ALBEDO], a, config[:, ALBEDO + 1:]], dim=1)
        c = (config - self.config_shift) * self.config_scale
        gc = c[:, [G_MEAN, ALPHA]]
        parts = [x[:, :, sl] for sl in self._slices]
        vs = [torch.cat([p.mean(dim=2), p.amax(dim=2), gc], dim=1) for p in parts]
        nd = self.arch.n_diffuse_layers
        merged = []
        for ti, t in enumerate(TYPES):
            xs = [p[:, ti] for p in parts]
            outs = [self.branches[t]["diffuse"](xs[:nd], c, vs[:nd]),
                    self.branches[t]["highlight"](xs[nd:], c, vs[nd:])]
            merged.append(torch.relu(self.merges[t](torch.cat(outs, dim=1))))
        h = torch.cat(merged + [c], dim=1)
        for j, lin in enumerate(self.head):
            h = lin(h)
            if j + 1 < len(self.head):
                h = torch.relu(h)
        return h[:, 0]

    # -- parameters <-> weight files
    def numpy_params(self) -> dict:
        return {k: v.detach().cpu().numpy().astype(np.float32) for k, v in self.state_dict().items()}

    def load_numpy_params(self, params: dict) -> None:
        self.load_state_dict({k: torch.as_tensor(np.asarray(v, np.float32)) for k, v in params.items()})

    @classmethod
    def from_weights(cls, w: MlpWeights) -> "Model":
        m = cls(w.arch)
        m.load_numpy_params(w.params)
        return m

    def export(self, path, contract: dict, training: dict | None = None, domain: dict | None = None):
        """Write the weight file (clvol/features/weights.py) with the contract of the gather that made the
        training features: ``clvol.features.weights.gather_contract(base_resolution, lam)`` for the
        packaged templates (there is no default: a wrong one would pass the loader's check),
        and the training data's validity ``domain`` (clvol.training.dataset.dataset_domain)."""
        return save_weights(path, self.arch, self.numpy_params(), contract, training, domain)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
