"""Training helpers for the network (torch; not imported by rendering).

Samples are (query, colour channel) pairs: a query's gathered features and levels, its config
with that channel's albedo, and that channel's label F (orders >= 2, unit sun) with its Monte
Carlo standard error. A grey medium gives one sample per query, a chromatic one up to three;
channels of albedo 0 are dropped (nothing to predict, and eq. 20 would divide 0 by 0).

Loss: seed eq. 20, the squared error in y = log(F / albedo^4 + 1), with two changes for noisy
labels (``encode_labels``):

- bias correction. A path-traced F_hat with standard error s has E[log(F_hat + a^4)] ~
  log(F + a^4) - var_y / 2 with var_y = (s / (F_hat + a^4))^2 (second-order delta method), so a
  network fitted to log(F_hat) learns values low by half the labels' relative variance. The
  target is y + var_y / 2 instead.
- inverse-variance weights w = 1 / (var_y + floor^2), normalised to mean 1 over the data set:
  noisy labels count less, and ``floor`` (the error we expect of the network itself, default
  0.05 in y) keeps near-exact labels from dominating. With no standard errors, or floor = inf,
  this is plain eq. 20.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from . import layout
from .export import GAMMA, TYPES
from .model import Model

ALBEDO = layout.CONFIG_FIELDS.index("albedo")
T_INDEX = TYPES.index("transmittance")


def encode_labels(F, se, albedo, gamma: float = GAMMA, floor: float = 0.05):
    """(target y, var_y, weight) for labels F >= 0 with standard errors se (or None) at
    albedo > 0. See the module docstring."""
    F = np.asarray(F, np.float64)
    a4 = np.asarray(albedo, np.float64) ** gamma
    if np.any(a4 <= 0):
        raise ValueError("encode_labels: albedo must be > 0 (drop albedo-0 channels first)")
    y = np.log1p(np.maximum(F, 0.0) / a4)
    if se is None:
        var = np.zeros_like(y)
    else:
        var = (np.asarray(se, np.float64) / (np.maximum(F, 0.0) + a4)) ** 2
    w = 1.0 / (var + floor ** 2) if math.isfinite(floor) else np.ones_like(y)
    return y + 0.5 * var, var, w / w.mean()


@dataclass
class Samples:
    """Training samples as float32 arrays: features [S][3][P], levels [S][L][P] or None,
    config [S][9], target y [S], weight [S], var_y [S], and key [S] (an int naming the
    configuration the sample came from, for per-configuration baselines)."""
    features: np.ndarray
    config: np.ndarray
    y: np.ndarray
    weight: np.ndarray
    var: np.ndarray
    levels: np.ndarray | None = None
    key: np.ndarray | None = None

    def __len__(self):
        return len(self.y)

    def subset(self, idx) -> "Samples":
        pick = (lambda a: None if a is None else a[idx])
        return Samples(self.features[idx], self.config[idx], self.y[idx], self.weight[idx],
                       self.var[idx], pick(self.levels), pick(self.key))


def make_samples(features, config, F, F_se, albedo_rgb, levels=None, key=None,
                 floor: float = 0.05) -> Samples:
    """Expand per-query RGB labels F, F_se [N][3] into per-channel samples. Channels of equal
    albedo are one sample (their labels averaged: the same estimate for a grey medium);
    channels of albedo 0 are dropped."""
    albedo_rgb = np.asarray(albedo_rgb, np.float64).reshape(3)
    F = np.asarray(F, np.float64).reshape(-1, 3)
    se = None if F_se is None else np.asarray(F_se, np.float64).reshape(-1, 3)
    n = len(F)
    parts = []
    for a in np.unique(albedo_rgb[albedo_rgb > 0]):
        ch = albedo_rgb == a
        Fa = F[:, ch].mean(axis=1)
        # channels of one albedo come from the same paths: fully correlated, so the mean's
        # error is their rms error (not rms / sqrt(count))
        sea = None if se is None else np.sqrt((se[:, ch] ** 2).mean(axis=1))
        y, var, _ = encode_labels(Fa, sea, np.full(n, a), floor=floor)
        cfg = np.array(config, np.float32, copy=True)
        cfg[:, ALBEDO] = a
        parts.append((y, var, cfg))
    if not parts:
        raise ValueError("make_samples: every channel has albedo 0")
    idx = np.tile(np.arange(n), len(parts))
    y = np.concatenate([p[0] for p in parts])
    var = np.concatenate([p[1] for p in parts])
    w = 1.0 / (var + floor ** 2) if math.isfinite(floor) else np.ones_like(y)
    return Samples(features=np.asarray(features, np.float32)[idx],
                   config=np.concatenate([p[2] for p in parts]),
                   y=y.astype(np.float32), weight=(w / w.mean()).astype(np.float32),
                   var=var.astype(np.float32),
                   levels=None if levels is None else np.asarray(levels, np.float32)[idx],
                   key=None if key is None else np.asarray(key)[idx])


def concat_samples(items) -> Samples:
    items = list(items)
    cat = (lambda name: None if getattr(items[0], name) is None
           else np.concatenate([getattr(s, name) for s in items]))
    s = Samples(*(cat(n) for n in ("features", "config", "y", "weight", "var")),
                levels=cat("levels"), key=cat("key"))
    s.weight = (s.weight / s.weight.mean()).astype(np.float32)
    return s


def weighted_loss(y_hat: torch.Tensor, y: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Seed eq. 20 (mean squared error in the normalised log space), optionally weighted."""
    err = (y_hat - y) ** 2
    if weight is None:
        return err.mean()
    return (weight * err).sum() / weight.sum()


def set_normalisation(model: Model, samples: Samples) -> None:
    """Feature shift/scale per type from the training data (mean and 1/std; the transmittance
    statistics are of the initial level combination when levels are given)."""
    f = samples.features.astype(np.float64)
    if samples.levels is not None:
        with torch.no_grad():
            w = model.level_weights.detach().double().numpy()
            b = float(model.level_bias.detach())
        f = f.copy()
        f[:, T_INDEX] = np.einsum("nlp,l->np", samples.levels.astype(np.float64), w) + b
    mean = f.mean(axis=(0, 2))
    std = f.std(axis=(0, 2))
    with torch.no_grad():
        model.feature_shift.copy_(torch.tensor(mean, dtype=torch.float32))
        model.feature_scale.copy_(torch.tensor(1.0 / np.maximum(std, 1e-3), dtype=torch.float32))


def _tensors(s: Samples, idx=None):
    pick = (lambda a: None if a is None else torch.from_numpy(np.ascontiguousarray(a if idx is None else a[idx])))
    return pick(s.features), pick(s.config), pick(s.levels), pick(s.y), pick(s.weight)


def evaluate(model: Model, s: Samples, batch: int = 4096, weighted: bool = False) -> float:
    """Loss on a sample set (eq. 20; weighted with ``weighted``)."""
    model.eval()
    total, norm = 0.0, 0.0
    with torch.no_grad():
        for i in range(0, len(s), batch):
            f, c, lv, y, w = _tensors(s, slice(i, i + batch))
            err = (model(f, c, lv) - y) ** 2
            ww = w if weighted else torch.ones_like(y)
            total += float((ww * err).sum())
            norm += float(ww.sum())
    return total / max(norm, 1e-30)


def predict(model: Model, s: Samples, batch: int = 4096) -> np.ndarray:
    model.eval()
    out = []
    with torch.no_grad():
        for i in range(0, len(s), batch):
            f, c, lv, _, _ = _tensors(s, slice(i, i + batch))
            out.append(model(f, c, lv).numpy())
    return np.concatenate(out) if out else np.zeros(0, np.float32)


def fit(model: Model, train: Samples, steps: int, batch: int = 256, lr: float = 2e-3,
        seed: int = 0, weighted: bool = True, log_every: int = 0, weight_decay: float = 0.0):
    """Adam on eq. 20 (noise-weighted with ``weighted``), cosine learning-rate decay.
    Returns the per-step training losses."""
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(model.parameters(), lr=lr, weight_decay=weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(steps, 1))
    losses = []
    n = len(train)
    for step in range(steps):
        model.train()
        idx = torch.randint(0, n, (min(batch, n),), generator=gen).numpy()
        f, c, lv, y, w = _tensors(train, idx)
        loss = weighted_loss(model(f, c, lv), y, w if weighted else None)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
        if log_every and (step % log_every == 0 or step == steps - 1):
            print(f"step {step:6d} loss {losses[-1]:.5f}")
    return losses


def per_key_mean(train: Samples, test: Samples) -> np.ndarray:
    """The baseline predictor: for each test sample, the (weighted) mean training target of
    its configuration key (the global mean for keys not seen in training)."""
    out = np.full(len(test), float(np.average(train.y, weights=train.weight)))
    for k in np.unique(test.key):
        m = train.key == k
        if m.any():
            out[test.key == k] = np.average(train.y[m], weights=train.weight[m])
    return out
