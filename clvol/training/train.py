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
import time
from dataclasses import dataclass

import numpy as np
import torch

from ..errors import ClvolError
from ..features import layout
from ..features.weights import GAMMA, TYPES
from .model import Model

ALBEDO = layout.CONFIG_FIELDS.index("albedo")
T_INDEX = TYPES.index("transmittance")


def _loss_weights(var, floor: float) -> np.ndarray:
    """Inverse-variance weights 1 / (var + floor^2) normalised to mean 1; uniform for an
    infinite floor (docs/network.md)."""
    w = 1.0 / (var + floor ** 2) if math.isfinite(floor) else np.ones_like(var)
    return (w / w.mean()).astype(np.float32)


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
    return y + 0.5 * var, var, _loss_weights(var, floor)


@dataclass
class Samples:
    """Training samples as float32 arrays: features [Q][3][P], levels [Q][L][P] or None,
    config [S][9], target y [S], weight [S], var_y [S], key [S] (an int naming the
    configuration the sample came from, for per-configuration baselines), and row [S] or None.

    A chromatic query gives up to three samples that share its features and levels, so these
    are stored once per query and sample i reads row ``row[i]`` (None: row i). Without the
    indirection a million-label data set would hold every feature block up to three times."""
    features: np.ndarray
    config: np.ndarray
    y: np.ndarray
    weight: np.ndarray
    var: np.ndarray
    levels: np.ndarray | None = None
    key: np.ndarray | None = None
    row: np.ndarray | None = None

    def __len__(self):
        return len(self.y)

    def rows(self, idx=slice(None)) -> np.ndarray:
        """Feature rows of samples ``idx``."""
        return np.arange(len(self.y))[idx] if self.row is None else self.row[idx]

    def subset(self, idx) -> "Samples":
        return Samples(self.features, self.config[idx], self.y[idx], self.weight[idx],
                       self.var[idx], self.levels, None if self.key is None else self.key[idx],
                       row=self.rows(idx))

    def row_counts(self) -> np.ndarray:
        """How many samples read each feature row."""
        return np.bincount(self.rows(), minlength=len(self.features))


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
    return Samples(features=np.asarray(features, np.float32),
                   config=np.concatenate([p[2] for p in parts]),
                   y=y.astype(np.float32), weight=_loss_weights(var, floor),
                   var=var.astype(np.float32),
                   levels=None if levels is None else np.asarray(levels, np.float32),
                   key=None if key is None else np.asarray(key)[idx], row=idx.astype(np.int64))


def concat_samples(items, n_rows: int | None = None) -> Samples:
    """One sample set from several. Feature rows are copied once into preallocated arrays; with
    ``n_rows`` (the total feature rows) ``items`` may be a generator, consumed one item at a
    time, so each item's features (e.g. read from a shard file) are dropped once copied."""
    if n_rows is None:
        items = list(items)
        n_rows = sum(len(s.features) for s in items)
    features = levels = None
    light, start = [], 0      # the items without their feature rows
    for s in items:
        n = len(s.features)
        if features is None:
            features = np.empty((n_rows,) + s.features.shape[1:], np.float32)
            levels = (None if s.levels is None
                      else np.empty((n_rows,) + s.levels.shape[1:], np.float32))
        features[start:start + n] = s.features
        if levels is not None:
            levels[start:start + n] = s.levels
        light.append(Samples(None, s.config, s.y, s.weight, s.var, None, s.key,
                             row=s.rows() + start))
        start += n
    if features is None or start != n_rows:
        raise ValueError(f"concat_samples: {start} feature rows given, {n_rows} expected")
    cat = (lambda name: None if getattr(light[0], name) is None
           else np.concatenate([getattr(s, name) for s in light]))
    out = Samples(features, *(cat(n) for n in ("config", "y", "weight", "var")),
                  levels=levels, key=cat("key"), row=cat("row"))
    out.weight = (out.weight / out.weight.mean()).astype(np.float32)
    return out


def weigh_as_image(s: Samples, power: float) -> Samples:
    """Multiply the loss weights by (F + a^gamma) / its configuration's mean, to ``power``.

    The loss is a squared error in y = log1p(F / a^gamma), so an error e in y is a linear error
    of about (F + a^gamma) e. An image is a sum of linear radiance over the points a camera sees:
    power 2 weighs each sample's log error as its linear share of its configuration's image
    (docs/neural.md, "Weighted as the image weighs points"); power 0 leaves the weights as they
    are. Per-configuration means keep one bright configuration from taking over the loss."""
    if power == 0 or len(s) == 0:
        return s
    a_g = np.asarray(s.config[:, ALBEDO], np.float64) ** GAMMA
    lin = np.exp(np.asarray(s.y, np.float64) - 0.5 * np.asarray(s.var, np.float64)) * a_g
    key = np.zeros(len(s), np.int64) if s.key is None else np.asarray(s.key)
    _, inv = np.unique(key, return_inverse=True)
    mean = np.bincount(inv, weights=lin) / np.bincount(inv)
    w = np.asarray(s.weight, np.float64) * (lin / mean[inv]) ** power
    s.weight = (w / w.mean()).astype(np.float32)
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
    # Statistics over samples (a row counts as often as samples read it), accumulated per type
    # in float64 over blocks of rows so no float64 copy of the whole feature array is made.
    counts = samples.row_counts().astype(np.float64)
    if samples.levels is not None:
        with torch.no_grad():
            w = model.level_weights.detach().double().numpy()
            b = float(model.level_bias.detach())
    n_types = samples.features.shape[1]
    s1, s2 = np.zeros(n_types), np.zeros(n_types)
    for i in range(0, len(counts), 8192):
        f = samples.features[i:i + 8192].astype(np.float64)
        if samples.levels is not None:
            f[:, T_INDEX] = np.einsum("nlp,l->np", samples.levels[i:i + 8192].astype(np.float64), w) + b
        c = counts[i:i + 8192]
        s1 += np.einsum("n,ntp->t", c, f)
        s2 += np.einsum("n,ntp->t", c, f * f)
    total = counts.sum() * samples.features.shape[2]
    mean = s1 / total
    std = np.sqrt(np.maximum(s2 / total - mean * mean, 0.0))
    with torch.no_grad():
        model.feature_shift.copy_(torch.tensor(mean, dtype=torch.float32))
        model.feature_scale.copy_(torch.tensor(1.0 / np.maximum(std, 1e-3), dtype=torch.float32))


def _tensors(s: Samples, idx=slice(None), device=None):
    pick = (lambda a, i: None if a is None else
            torch.from_numpy(np.ascontiguousarray(a[i])).to(device or "cpu"))
    rows = s.rows(idx)
    return (pick(s.features, rows), pick(s.config, idx), pick(s.levels, rows), pick(s.y, idx),
            pick(s.weight, idx))


def _device(model: Model):
    return next(model.parameters()).device


def evaluate(model: Model, s: Samples, batch: int = 4096, weighted: bool = False) -> float:
    """Loss on a sample set (eq. 20; weighted with ``weighted``)."""
    model.eval()
    total, norm = 0.0, 0.0
    with torch.no_grad():
        for i in range(0, len(s), batch):
            f, c, lv, y, w = _tensors(s, slice(i, i + batch), _device(model))
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
            f, c, lv, _, _ = _tensors(s, slice(i, i + batch), _device(model))
            out.append(model(f, c, lv).cpu().numpy())
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


# --------------------------------------------------------------------------- training runs
# A run on a clvol.training.dataset folder: held-out split by volume and configuration, checkpoints
# written atomically and resumed exactly, export with the gather's contract.

CHECKPOINT = "checkpoint.pt"


@dataclass(frozen=True)
class RunConfig:
    """What determines a training run (a resumed run must use the same)."""
    steps: int = 6000
    batch: int = 256
    lr: float = 2e-3
    weight_decay: float = 0.0
    seed: int = 0
    floor: float = 0.05
    image_weight: float = 0.0         # power of the image-brightness weight (weigh_as_image); 0: off
    holdout_volumes: tuple = ()       # extra whole volumes never trained on (split_shards)
    holdout_config: int = -1          # this configuration index of every volume is held out too
    train_fraction: float = 1.0       # train on the first fraction of each data set's training volumes
    eval_every: int = 500
    checkpoint_every: int = 250

    def to_dict(self) -> dict:
        from dataclasses import asdict
        d = asdict(self)
        d["holdout_volumes"] = list(self.holdout_volumes)
        return d


def split_shards(shards, cfg: RunConfig):
    """(train shards, held-out shards). Held out are all configurations of the held-out volumes
    and configuration ``cfg.holdout_config`` (negative: from the end) of every other volume, so
    held-out points come from volumes or light/view/phase/albedo draws training never saw.

    Held-out volumes: those of ``cfg.holdout_volumes``, plus, for a version-2 data set, its
    held-out stream (``n_heldout_volumes``, generator seeds training never sees), or, for a
    version-1 one, volume 1 (when no others are named) and the first solid."""
    spec = shards[0].meta["spec"]
    n_cfg = spec["configs_per_volume"]
    hv = set(int(v) for v in cfg.holdout_volumes)
    if "n_heldout_volumes" in spec:
        hv |= set(range(spec["n_volumes"] - spec["n_heldout_volumes"], spec["n_volumes"]))
    else:   # version 1: volume 1 (a cloud) unless others are named, and the first solid
        hv |= set() if cfg.holdout_volumes else {1}
        if spec.get("n_solids", 0) > 0:
            hv.add(spec["n_volumes"] - spec["n_solids"])
    hc = cfg.holdout_config % n_cfg
    from .dataset import OUT_OF_FAMILY
    # out-of-family volumes are never trained on, whatever the split (they measure generalisation)
    oof = {s.volume for s in shards if s.meta.get("volume", {}).get("family") in OUT_OF_FAMILY}
    hv |= oof
    held = [s for s in shards if s.volume in hv or s.config_index == hc]
    train = [s for s in shards if not (s.volume in hv or s.config_index == hc)]
    if not train and held and {s.volume for s in held} <= oof:
        return [], held        # an evaluation-only set: every volume out of family
    if not 0.0 < cfg.train_fraction <= 1.0:
        raise ClvolError(f"train_fraction {cfg.train_fraction}: must be in (0, 1]")
    if cfg.train_fraction < 1.0:
        # whole volumes, the first ones (families cycle through volume indices, so every
        # family keeps its share); the held-out shards stay the same for every fraction
        vols = sorted({s.volume for s in train})
        keep = set(vols[:max(1, round(cfg.train_fraction * len(vols)))])
        train = [s for s in train if s.volume in keep]
    if not train and not held:
        raise ClvolError(f"held-out split of {len(shards)} shards leaves {len(train)} for training "
                         f"and {len(held)} held out (held-out volumes {sorted(hv)}, configuration "
                         f"{hc}): nothing to train on or to evaluate")
    return train, held


# Albedos drawn for per-order labels (``albedo_draws``): the data sets' law for a range that
# reaches 1 (clvol/training/dataset.py: log-uniform in 1 - a up to 1 - ALBEDO_GAP, a share
# ALBEDO_ONE exactly 1), vectorised, from DRAW_LOW.
DRAW_LOW = 0.3


def draw_albedos(rng: np.random.Generator, n: int) -> np.ndarray:
    from .dataset import ALBEDO_GAP, ALBEDO_ONE
    a = 1.0 - np.exp(rng.uniform(np.log(ALBEDO_GAP), np.log(1.0 - DRAW_LOW), n))
    return np.where(rng.uniform(size=n) < ALBEDO_ONE, 1.0, a)



def order_samples(arrays, albedo, key=None, floor: float = 0.05) -> Samples:
    """Samples of one per-order shard at the albedos ``albedo`` [N][K] (K per query; any value
    in (0, 1]): labels and standard errors relabelled from the bins (clvol/training/labels.py)."""
    from ..render.pathtrace import SE_ALBEDOS
    from .labels import label_at, se_at
    albedo = np.asarray(albedo, np.float64)
    n, k = albedo.shape
    S, M, se_nodes = (np.asarray(arrays[x], np.float64) for x in ("S", "M", "se"))
    F = np.concatenate([label_at(S, M, albedo[:, j]) for j in range(k)])
    se = np.concatenate([se_at(se_nodes, SE_ALBEDOS, albedo[:, j]) for j in range(k)])
    a = albedo.T.ravel()
    y, var, _ = encode_labels(F, se, a, floor=floor)
    cfg = np.tile(np.asarray(arrays["config"], np.float32), (k, 1))
    cfg[:, ALBEDO] = a
    idx = np.tile(np.arange(n), k)
    return Samples(features=np.asarray(arrays["features"], np.float32), config=cfg,
                   y=y.astype(np.float32), weight=_loss_weights(var, floor),
                   var=var.astype(np.float32), levels=np.asarray(arrays["levels"], np.float32),
                   key=None if key is None else np.tile(np.asarray(key), k),
                   row=idx.astype(np.int64))


def shard_samples(shards, floor: float = 0.05, albedo_draws: int = 0, albedos=None,
                  seed: int = 0, image_weight: float = 0.0) -> Samples:
    """Samples of a list of clvol.training.dataset.Shard, key = the shard's position in the data
    set (volume * configs + configuration). Shards are read one at a time and their feature
    rows copied once (``concat_samples`` with ``n_rows``).

    By default one sample per (query, distinct non-zero albedo of the configuration). Shards
    with per-order labels can instead be labelled at ``albedo_draws`` albedos per query, drawn
    by ``draw_albedos`` from a stream keyed by (seed, volume, configuration), or at every
    albedo of the list ``albedos`` (evaluation); other shards keep their own albedo."""
    labels = [s.arrays["Fms"] for s in shards]

    def parts():
        for s, F in zip(shards, labels):
            a = s.arrays
            key = np.full(len(F), s.volume * s.meta["spec"]["configs_per_volume"] + s.config_index)
            if s.meta["spec"].get("per_order_labels") and (albedo_draws or albedos is not None):
                if albedos is not None:
                    alb = np.tile(np.asarray(albedos, np.float64), (len(F), 1))
                else:
                    rng = np.random.default_rng([seed, s.volume, s.config_index])
                    alb = draw_albedos(rng, len(F) * albedo_draws).reshape(len(F), albedo_draws)
                yield order_samples(a, alb, key=key, floor=floor)
            else:
                yield make_samples(a["features"], a["config"], F, a["Fms_se"], s.albedo,
                                   levels=a["levels"], key=key, floor=floor)
    out = concat_samples(parts(), n_rows=sum(len(F) for F in labels))
    return weigh_as_image(out, image_weight)


def save_checkpoint(path, state: dict) -> None:
    """torch.save through clvol.atomic (a killed run leaves the previous checkpoint whole)."""
    from ..atomic import atomic_open
    with atomic_open(path, "wb") as f:
        torch.save(state, f)


class Trainer:
    """Adam + cosine decay on the noise-weighted eq. 20 loss, in resumable steps.

    Everything that changes during training (model, optimiser and scheduler state, the batch
    generator's state, the step, the loss history) is in ``state_dict()``; a run restored from a
    checkpoint continues exactly as the uninterrupted run would have (tests/test_dataset.py)."""

    def __init__(self, train: Samples, cfg: RunConfig, arch=None, device: str = "cpu",
                 generator_seed: int | None = None):
        from ..features.weights import Architecture
        self.cfg = cfg
        self.device = torch.device(device)
        self.train = train
        torch.manual_seed(cfg.seed)
        L = train.levels.shape[1] if train.levels is not None else layout.N_LEVELS
        self.model = Model(arch or Architecture(n_levels=L))
        set_normalisation(self.model, train)
        self.model.to(self.device)      # after the normalisation (computed in NumPy on the host)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        self.sched = torch.optim.lr_scheduler.CosineAnnealingLR(self.opt, T_max=max(cfg.steps, 1))
        # a data-parallel worker draws its own batches (clvol/training/raytrain.py: seed + rank)
        self.gen = torch.Generator().manual_seed(cfg.seed if generator_seed is None else generator_seed)
        self.net = self.model     # what the steps run: the model, or a DDP wrapper of it
        self.step = 0
        self.history = {"train": [], "eval": []}

    def state_dict(self) -> dict:
        return {"model": self.model.state_dict(), "opt": self.opt.state_dict(),
                "sched": self.sched.state_dict(), "gen": self.gen.get_state(), "step": self.step,
                "history": self.history, "config": self.cfg.to_dict(),
                "architecture": self.model.arch.to_dict()}

    def load_state_dict(self, st: dict) -> None:
        # settings added since a checkpoint was written count as their defaults
        have_cfg = {**RunConfig().to_dict(), **st["config"]}
        if have_cfg != self.cfg.to_dict():
            diff = sorted(k for k in have_cfg if have_cfg[k] != self.cfg.to_dict().get(k))
            raise ValueError(f"checkpoint was made with other run settings ({diff}); use the same "
                             f"settings or another output folder")
        have = st.get("architecture", self.model.arch.to_dict())   # older checkpoints: not recorded
        if have != self.model.arch.to_dict():
            diff = sorted(k for k in have if have[k] != self.model.arch.to_dict().get(k))
            raise ValueError(f"checkpoint was made with another architecture ({diff}); use the same "
                             f"settings or another output folder")
        self.model.load_state_dict({k: v.to(self.device) for k, v in st["model"].items()})
        self.opt.load_state_dict(st["opt"])
        self.sched.load_state_dict(st["sched"])
        self.gen.set_state(st["gen"])
        self.step = int(st["step"])
        self.history = st["history"]

    def run(self, until: int, checkpoint=None, held: Samples | None = None, log=print,
            on_checkpoint=None, deadline: float | None = None) -> None:
        """Train to step ``until`` (<= cfg.steps), writing ``checkpoint`` every
        cfg.checkpoint_every steps and at the end, evaluating ``held`` every cfg.eval_every.
        ``on_checkpoint(trainer)`` is called at each of those steps (after the write, if any).
        ``deadline`` (time.perf_counter): the step that reaches it is the last one, evaluated
        and checkpointed as a last step is (a time-boxed run; rerun to go on)."""
        until = min(int(until), self.cfg.steps)
        n = len(self.train)
        window = []
        t0 = time.perf_counter()
        done_before = self.history["eval"][-1].get("seconds", 0.0) if self.history["eval"] else 0.0
        while self.step < until:
            self.net.train()
            idx = torch.randint(0, n, (min(self.cfg.batch, n),), generator=self.gen).numpy()
            f, c, lv, y, w = _tensors(self.train, idx, self.device)
            loss = weighted_loss(self.net(f, c, lv), y, w)
            self.opt.zero_grad()
            loss.backward()
            self.opt.step()
            self.sched.step()
            self.step += 1
            window.append(float(loss.detach()))
            if deadline is not None and time.perf_counter() >= deadline:
                until = self.step
            last = self.step == until
            if self.cfg.eval_every and (self.step % self.cfg.eval_every == 0 or last):
                row = {"step": self.step, "train": float(np.mean(window)),
                       # wall seconds of training so far, over resumed sessions too
                       "seconds": round(done_before + time.perf_counter() - t0, 1)}
                window = []
                if held is not None:
                    row["held_out"] = evaluate(self.model, held)
                    row["held_out_weighted"] = evaluate(self.model, held, weighted=True)
                self.history["eval"].append(row)
                if log:
                    log("  ".join(f"{k} {v:.5f}" if isinstance(v, float) else f"{k} {v}"
                                  for k, v in row.items()))
            if self.step % self.cfg.checkpoint_every == 0 or last:
                if checkpoint is not None:
                    save_checkpoint(checkpoint, self.state_dict())
                if on_checkpoint is not None:
                    on_checkpoint(self)


def mean_predictor_loss(train: Samples, held: Samples) -> float:
    """Held-out eq. 20 loss of the constant predictor (the training set's weighted mean y)."""
    m = float(np.average(train.y, weights=train.weight))
    return float(np.mean((held.y.astype(np.float64) - m) ** 2))
