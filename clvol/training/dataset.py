"""Training data for the network: procedural volumes, random configurations, path-traced labels.

    spec = DatasetSpec(seed=0, n_volumes=40, n_heldout_volumes=10, configs_per_volume=8)
    make_dataset(spec, "runs/data")          # resumable: finished shards are skipped
    shards = load_shards("runs/data")        # list of Shard (arrays + meta)

A data set is a folder of shards, one per (volume v, configuration c), named
``shard_{v:03d}_{c:03d}.npz``, plus ``spec.json`` (the ``DatasetSpec`` that made it). A shard
holds, for ``points_per_config`` query points of one volume under one configuration (sun
direction, camera position, phase, albedo, optical thickness -> density scale):

    points   float32 [n][3]        world positions (density-weighted inside the medium + uniform)
    omegas   float32 [n][3]        unit, toward the configuration's camera (as the renderer's lattice)
    features float32 [n][3][P]     train-mode gather (clvol/features/layout.py; features[:, 1] is 0: the
    levels   float32 [n][L][P]     model combines ``levels`` itself)
    config   float32 [n][9]        the gather's config (albedo of channel 0; training sets each channel's)
    Fms, Fms_se, F1  float64 [n][3]  labels from clvol.render.pathtrace.point_query (unit sun, orders >= 2)
    __meta__ uint8                 UTF-8 JSON: spec, shard indices, volume, medium, light, camera,
                                   query seed, code contract (layout version, template hash)

The file is a pure function of (spec, v, c) and the device: fixed zip timestamps, and the
wall-clock timings go to ``timings.jsonl`` in the folder instead (one JSON line per shard).

Robust to a session ending at any moment: a shard is written to a temporary file
(``.shard_*.tmp``, clvol/atomic.py) and renamed into place (``os.replace`` is atomic on one file
system), so a ``shard_*.npz`` is always complete; the loader reads only ``shard_*.npz``, and a
rerun deletes stale temporary files and skips finished shards (one writer per folder at a time). Everything random
is keyed by (spec.seed, v, c): the same spec gives the same shards bit for bit on the same
device, in any order and after any interruption, serially or on Ray (clvol/training/distributed.py:
workers return the bytes, this process writes them).
"""
from __future__ import annotations

import io
import json
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from ..atomic import atomic_open
from ..errors import ClvolError
from ..features import layout

DATASET_FORMAT = "clvol-dataset"
# Version 2: the whole material domain (volume families, resolutions, optical thickness, g < 0,
# low albedo, held-out volume stream). Version-1 shards (the cloud_small data) still load for
# training and evaluation (same arrays); only version-2 specs are made.
DATASET_VERSION = 2
READABLE_VERSIONS = (1, 2)
SPEC_FILE = "spec.json"
META_KEY = "__meta__"
ARRAYS = ("points", "omegas", "features", "levels", "config", "Fms", "Fms_se", "F1")
# With per_order_labels: the per-order bins of clvol.render.pathtrace.point_query_orders
# (S, M [n][ORDER_BINS]: the label at any albedo; se [n][len(SE_ALBEDOS)]: its standard error
# at SE_ALBEDOS), from paths traced at albedo 1. Fms and Fms_se are then the relabelled
# label at the configuration's albedo (clvol/training/labels.py).
ORDER_ARRAYS = ("S", "M", "se")

# Volume families, each a generator with a random parameter draw (``volume_params``). Volumes
# cycle through ``spec.families`` so every family is equally represented, held-out ones too.
FAMILIES = ("cumulus", "flat_cumulus", "stratus", "plume", "noise",
            "sphere", "blob", "torus", "box", "union", "nubis", "sphere_cumulus")
SOLID_FAMILIES = ("sphere", "blob", "torus", "box", "union")
# Out-of-family clouds: generators written from published descriptions that no training set
# may use (clvol/training/train.py split_shards holds every shard of theirs out). They measure how
# the network does on density structure it never saw: the training families above come from
# our own generators, so a held-out volume of theirs cannot show that gap (docs/neural.md).
OUT_OF_FAMILY = ("nubis", "sphere_cumulus")
# The default spec's families: every family a model may train on.
TRAINING_FAMILIES = tuple(f for f in FAMILIES if f not in OUT_OF_FAMILY)
RESOLUTIONS = (32, 48, 64, 96, 128)


class DatasetError(ClvolError):
    """A data set folder that does not match the requested spec, or a damaged shard."""


@dataclass(frozen=True)
class DatasetSpec:
    """Everything that determines a data set.

    Volumes 0..n_volumes-1; the last ``n_heldout_volumes`` are drawn from a separate random
    stream (their generator seeds and configurations never come from the training volumes'
    stream), so a held-out volume is one training never sees by construction. Volume v is of
    family ``families[i % len(families)]`` with i its index within its part (training or
    held out)."""
    seed: int = 0
    n_volumes: int = 30
    n_heldout_volumes: int = 10
    families: tuple = TRAINING_FAMILIES
    resolution: tuple = (32, 128)       # voxels per side, drawn per volume from RESOLUTIONS in range
    base_resolution: int = 64           # pyramid base of the gather (goes into the weight contract)
    lam: float = layout.DEFAULT_LAMBDA
    configs_per_volume: int = 8
    # From the measured curve (docs/neural.md, "Labels by measurement"): at equal cost more
    # labels per configuration beat more paths per label; paths stay at 128 because the curve's
    # fewer-path cells are emulated with Gaussian noise, which cannot show the low bias of
    # skewed few-path labels (docs/neural.md).
    points_per_config: int = 128
    uniform_fraction: float = 0.2       # of the points drawn uniformly in the box (rest by density)
    n_paths: int = 128                  # paths per point query (label standard error ~1/sqrt)
    optical_thickness: tuple = (1.0, 1000.0)   # log-uniform target (``unit_optical_thickness``)
    albedo: tuple = (0.3, 0.999)        # per channel
    g: tuple = (-0.9, 0.99)             # HG g of every lobe
    max_lobes: int = 3
    # Labels from one set of albedo-1 paths, binned by scattering order (docs/pathtrace.md):
    # training may then label every query at any albedo, 1.0 included.
    per_order_labels: bool = False
    # Domain randomisation of density structure: this fraction of the volumes gets a density
    # remap and a low-frequency modulation (clvol.volume.generators.restructure), drawn from a
    # stream of its own so the other draws of a spec are unchanged (0: none, as before).
    augment: float = 0.0
    # This fraction of the density-drawn points is instead drawn where the configuration's
    # camera looks: along a ray from the camera through a uniform point of the box, at an
    # optical depth log-uniform in VISIBLE_TAU from the camera (what images are made of,
    # deep high-order regions of thick clouds included; docs/neural.md). 0: none, as before.
    visible_fraction: float = 0.0

    def __post_init__(self):
        def bad(name, value, allowed):
            return DatasetError(f"dataset spec [{name}] = {value!r}: {allowed}")
        for name in ("n_volumes", "configs_per_volume", "points_per_config", "n_paths", "max_lobes"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise bad(name, v, "must be an integer >= 1")
        if not (isinstance(self.n_heldout_volumes, int) and 0 <= self.n_heldout_volumes < self.n_volumes):
            raise bad("n_heldout_volumes", self.n_heldout_volumes,
                      f"must be an integer in [0, n_volumes - 1 = {self.n_volumes - 1}]")
        if not isinstance(self.per_order_labels, bool):
            raise bad("per_order_labels", self.per_order_labels, "must be true or false")
        if self.max_lobes > 3:
            raise bad("max_lobes", self.max_lobes, "must be 1, 2 or 3 (the config has 3 lobe slots)")
        fam = tuple(self.families)
        if not fam or any(f not in FAMILIES for f in fam):
            raise bad("families", fam, f"must be a non-empty list of {list(FAMILIES)}")
        object.__setattr__(self, "families", fam)
        b = self.base_resolution
        if not (isinstance(b, int) and 2 <= b <= 512 and b & (b - 1) == 0):
            raise bad("base_resolution", b, "must be a power of two from 2 to 512")
        if not (isinstance(self.augment, (int, float)) and 0.0 <= self.augment <= 1.0):
            raise bad("augment", self.augment, "must be a fraction in [0, 1]")
        if not (isinstance(self.visible_fraction, (int, float)) and 0.0 <= self.visible_fraction <= 1.0):
            raise bad("visible_fraction", self.visible_fraction, "must be a fraction in [0, 1]")
        if self.visible_fraction + self.uniform_fraction > 1.0:
            raise bad("visible_fraction", self.visible_fraction,
                      f"plus uniform_fraction {self.uniform_fraction} must be at most 1")
        if not 0.0 <= self.uniform_fraction <= 1.0:
            raise bad("uniform_fraction", self.uniform_fraction, "must be in [0, 1]")
        if not 0.0 < self.lam <= 1.0:
            raise bad("lam", self.lam, "must be in (0, 1]")
        ranges = {"resolution": (4, 512), "optical_thickness": (1e-3, 1e5), "albedo": (1e-3, 1.0),
                  "g": (-0.99, 0.99)}
        for name, (lo_ok, hi_ok) in ranges.items():
            r = getattr(self, name)
            if isinstance(r, (int, float)) and name == "resolution":
                r = (int(r), int(r))       # one fixed resolution
            try:
                lo, hi = (float(x) for x in r)
            except (TypeError, ValueError):
                raise bad(name, r, "must be (low, high)") from None
            if not (lo_ok <= lo <= hi <= hi_ok):
                raise bad(name, r, f"must be (low, high) with {lo_ok} <= low <= high <= {hi_ok}")
            object.__setattr__(self, name, tuple(int(x) if name == "resolution" else float(x) for x in r))

    def to_dict(self) -> dict:
        d = asdict(self)
        for k in ("families", "resolution", "optical_thickness", "albedo", "g"):
            d[k] = list(getattr(self, k))
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "DatasetSpec":
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise DatasetError(f"dataset spec: unknown field(s) {unknown}; allowed: {sorted(names)} "
                               f"(a version-1 spec? its shards still load, but it cannot be remade)")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})

    @property
    def n_shards(self) -> int:
        return self.n_volumes * self.configs_per_volume

    @property
    def n_train_volumes(self) -> int:
        return self.n_volumes - self.n_heldout_volumes

    def is_heldout(self, v: int) -> bool:
        return v >= self.n_train_volumes

    def family(self, v: int) -> str:
        i = v - self.n_train_volumes if self.is_heldout(v) else v
        return self.families[i % len(self.families)]

    def is_solid(self, v: int) -> bool:
        return self.family(v) in SOLID_FAMILIES


def dataset_domain(spec: dict) -> dict | None:
    """The validity domain a model trained on this data set has (clvol.features.weights's ``domain``), from
    a spec dict (``DatasetSpec.to_dict()`` or a shard's meta["spec"]); None for a version-1 spec
    (clvol.features.weights.DEFAULT_DOMAIN describes that data)."""
    if "optical_thickness" not in spec:
        return None
    return {"albedo": [float(x) for x in spec["albedo"]], "g": [float(x) for x in spec["g"]],
            "max_lobes": int(spec["max_lobes"]),
            "optical_thickness": [float(x) for x in spec["optical_thickness"]],
            "resolution": [int(x) for x in spec["resolution"]]}


def shard_name(v: int, c: int) -> str:
    return f"shard_{v:03d}_{c:03d}.npz"


def _rng(spec: DatasetSpec, *key) -> np.random.Generator:
    # One independent stream per (seed, purpose, indices): shards never share random numbers and
    # do not depend on the order they are made in.
    return np.random.default_rng([spec.seed, *key])


def _vkey(spec: DatasetSpec, v: int) -> tuple:
    """Random-stream key of volume v: held-out volumes use their own purpose numbers (100+), so
    no generator seed, shape or configuration of theirs can coincide with a training volume's."""
    return (100, v - spec.n_train_volumes) if spec.is_heldout(v) else (0, v)


def _unit(rng) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _u(rng, lo, hi, nd=4) -> float:
    return round(float(rng.uniform(lo, hi)), nd)


def volume_params(spec: DatasetSpec, v: int) -> dict:
    """The generator call for volume v: {"family", "generator", "seed", "resolution", "params"}."""
    base, idx = _vkey(spec, v)
    rng = _rng(spec, base + 1, idx)
    gseed = int(rng.integers(0, 2**31 - 1))
    res = [r for r in RESOLUTIONS if spec.resolution[0] <= r <= spec.resolution[1]] or [spec.resolution[0]]
    resolution = int(res[int(rng.integers(len(res)))])
    fam = spec.family(v)
    if fam == "cumulus":          # billowy towers
        gen, prm = "cloud", {"coverage": _u(rng, 0.45, 0.75), "scale": _u(rng, 0.18, 0.4),
                             "worley": _u(rng, 0.6, 0.95), "detail": _u(rng, 0.1, 0.45),
                             "base": _u(rng, 0.05, 0.25), "top": _u(rng, 0.75, 1.0),
                             "width": _u(rng, 0.55, 0.9)}
    elif fam == "flat_cumulus":   # wide, flat-based, shallow
        base_h = _u(rng, 0.25, 0.45)
        gen, prm = "cloud", {"coverage": _u(rng, 0.4, 0.65), "scale": _u(rng, 0.12, 0.3),
                             "worley": _u(rng, 0.2, 0.6), "detail": _u(rng, 0.1, 0.5),
                             "base": base_h, "top": round(min(base_h + rng.uniform(0.2, 0.45), 1.0), 4),
                             "width": _u(rng, 0.75, 1.0)}
    elif fam == "stratus":
        gen, prm = "stratus", {"layers": int(rng.integers(1, 4)), "thickness": _u(rng, 0.06, 0.3),
                               "coverage": _u(rng, 0.4, 0.85), "scale": _u(rng, 0.08, 0.3),
                               "detail": _u(rng, 0.0, 0.5)}
    elif fam == "plume":          # wispy smoke
        gen, prm = "smoke", {"radius": _u(rng, 0.03, 0.1), "spread": _u(rng, 0.15, 0.6),
                             "turbulence": _u(rng, 0.5, 1.5), "scale": _u(rng, 0.1, 0.35),
                             "fade": _u(rng, 0.5, 2.0), "drift": _u(rng, -0.5, 0.5)}
    elif fam == "noise":
        gen, prm = "noise", {"scale": _u(rng, 0.1, 0.5), "gain": _u(rng, 0.35, 0.65),
                             "coverage": _u(rng, 0.1, 0.6), "softness": _u(rng, 0.2, 2.0)}
    elif fam == "sphere":
        gen, prm = "sphere", {"radius": _u(rng, 0.2, 0.45), "edge": _u(rng, 0.25, 1.5)}
    elif fam == "blob":
        gen, prm = "blob", {"count": int(rng.integers(3, 11)), "radius": _u(rng, 0.08, 0.16),
                            "wobble": _u(rng, 0.0, 0.05), "edge": _u(rng, 0.25, 1.5)}
    elif fam == "torus":
        minor = _u(rng, 0.05, 0.15)
        gen, prm = "torus", {"major": round(minor + rng.uniform(0.08, 0.3 - minor + 0.08), 4),
                             "minor": minor, "edge": _u(rng, 0.25, 1.5)}
    elif fam == "box":
        w, h, d = (_u(rng, 0.3, 0.8) for _ in range(3))
        gen, prm = "box", {"width": w, "height": h, "depth": d,
                           "rounding": round(0.5 * min(w, h, d) * rng.uniform(0.0, 0.8), 4),
                           "edge": _u(rng, 0.25, 1.5)}
    elif fam == "nubis":          # out of family: Perlin-Worley after the Nubis talks
        gen, prm = "perlin_worley", {"coverage": _u(rng, 0.55, 0.95), "cloud_type": _u(rng, 0.3, 1.0),
                                     "scale": _u(rng, 0.2, 0.5), "erosion": _u(rng, 0.2, 0.9),
                                     "width": _u(rng, 0.6, 0.95)}
    elif fam == "sphere_cumulus":  # out of family: displaced sphere unions
        gen, prm = "sphere_cumulus", {"count": int(rng.integers(5, 15)), "size": _u(rng, 0.12, 0.24),
                                      "displacement": _u(rng, 0.2, 1.0), "erosion": _u(rng, 0.0, 0.6),
                                      "base": _u(rng, 0.05, 0.3)}
    else:                         # union
        gen, prm = "union", {"count": int(rng.integers(2, 7)), "size": _u(rng, 0.1, 0.22),
                             "blend": _u(rng, 0.0, 0.06) if rng.uniform() < 0.5 else 0.0,
                             "edge": _u(rng, 0.25, 1.5)}
    out = {"family": fam, "generator": gen, "seed": gseed, "resolution": resolution, "params": prm}
    arng = _rng(spec, base + 5, idx)       # a stream of its own: the draws above are unchanged
    if spec.augment > 0 and arng.uniform() < spec.augment:
        out["restructure"] = {"gamma": round(float(np.exp(arng.uniform(np.log(0.5), np.log(2.5)))), 4),
                              "modulation": _u(arng, 0.0, 0.7), "scale": _u(arng, 0.08, 0.4)}
    return out


def make_volume(spec: DatasetSpec, v: int):
    from ..volume.generators import generate
    from ..volume.generators import restructure
    p = volume_params(spec, v)
    grid = generate(p["generator"], seed=p["seed"], resolution=p["resolution"], **p["params"])
    if "restructure" in p:
        grid = restructure(grid, p["seed"], **p["restructure"])
    return grid


def unit_optical_thickness(grid) -> float:
    """Optical thickness of the volume at density_scale 1: the mean, over the three axes, of the
    column integrals of density (world units) over the columns that hold any density. A data
    set draws a target optical thickness and sets density_scale = target / this."""
    d = grid.density.astype(np.float64)
    cs = np.asarray(grid.cell_size, np.float64)      # (x, y, z); density is [z][y][x]
    out = []
    for axis, h in ((2, cs[0]), (1, cs[1]), (0, cs[2])):
        col = d.sum(axis=axis) * h
        nz = col[col > 0]
        if nz.size:
            out.append(float(nz.mean()))
    return float(np.mean(out)) if out else 0.0


# Albedo 1 cannot be reached by a draw log-uniform in 1 - albedo: with hi = 1 the draw stops at
# 1 - ALBEDO_GAP and a share ALBEDO_ONE of the draws is exactly 1.
ALBEDO_GAP, ALBEDO_ONE = 1e-4, 0.15


def _draw_albedo(rng, lo: float, hi: float) -> float:
    # log-uniform in 1 - albedo: as many draws in 0.99-0.999 (clouds) as in 0.9-0.99 or below
    if hi >= 1.0:
        if rng.uniform() < ALBEDO_ONE or lo >= 1.0:
            return 1.0
        hi = 1.0 - ALBEDO_GAP
    return float(1.0 - np.exp(rng.uniform(np.log(1.0 - hi), np.log(1.0 - lo))))


def config_params(spec: DatasetSpec, v: int, c: int, grid=None) -> dict:
    """Configuration c of volume v: light and camera directions, phase lobes, albedo, target
    optical thickness and the density scale that gives it (JSON-ready). ``grid``: volume v's,
    if the caller has it (the density scale depends on it)."""
    base, idx = _vkey(spec, v)
    rng = _rng(spec, base + 2, idx, c)
    light = _unit(rng)
    if rng.uniform() < 0.25:      # grazing: within ~9 degrees of horizontal (flat bases, sheets)
        az = rng.uniform(0.0, 2.0 * np.pi)
        ly = rng.uniform(-0.15, 0.15)
        r = np.sqrt(1.0 - ly * ly)
        light = np.array([r * np.cos(az), ly, r * np.sin(az)])
    cam_dir = _unit(rng)
    cam_dist = float(rng.uniform(1.8, 3.0))
    glo, ghi = spec.g
    n_lobes = min(int(rng.choice([1, 2, 3], p=[0.5, 0.3, 0.2])), spec.max_lobes)
    # first lobe: a third of the time strongly forward (clouds, 0.75..g_hi), else anywhere
    g0 = rng.uniform(max(glo, 0.75), ghi) if (rng.uniform() < 0.35 and ghi > 0.75) else rng.uniform(glo, ghi)
    gs = [g0] + [rng.uniform(glo, min(ghi, 0.9)) for _ in range(n_lobes - 1)]
    ws = rng.dirichlet(np.full(n_lobes, 2.0)) if n_lobes > 1 else np.ones(1)
    lobes = [(round(float(g), 4), float(w)) for g, w in zip(gs, ws)]
    s = sum(w for _, w in lobes)
    lobes = [(g, w / s) for g, w in lobes]
    alo, ahi = spec.albedo
    kind = rng.uniform()
    if kind < 0.4:                # grey
        a = _draw_albedo(rng, alo, ahi)
        albedo = (a, a, a)
    elif kind < 0.7:              # tinted (like the MRPNN protocol's (0.8, 0.9, 1))
        a = _draw_albedo(rng, alo, ahi)
        albedo = tuple(float(np.clip(a * rng.uniform(0.8, 1.0), alo, ahi)) for _ in range(3))
    else:                         # independent per channel
        albedo = tuple(_draw_albedo(rng, alo, ahi) for _ in range(3))
    albedo = tuple(round(x, 4) for x in albedo)
    tlo, thi = spec.optical_thickness
    tau = float(np.exp(rng.uniform(np.log(tlo), np.log(thi))))
    grid = grid if grid is not None else make_volume(spec, v)
    unit = unit_optical_thickness(grid)
    scale = tau / unit if unit > 0 else tau
    return {"light": light.tolist(), "camera_dir": cam_dir.tolist(), "camera_distance": cam_dist,
            "lobes": [list(x) for x in lobes], "albedo": list(albedo),
            "optical_thickness": round(tau, 4), "density_scale": float(f"{scale:.6g}")}


def scene_for(spec: DatasetSpec, v: int, c: int, grid=None):
    """The clvol Scene of shard (v, c) (its camera is only a placeholder: labels need the
    sun and the medium)."""
    from ..scene import scene_from_dict
    vp, cp = volume_params(spec, v), config_params(spec, v, c, grid)
    lobes = cp["lobes"]
    phase = ({"type": "hg", "g": lobes[0][0]} if len(lobes) == 1 else
             {"type": "mhg", "lobes": [{"g": g, "weight": w} for g, w in lobes]})
    origin = (np.asarray(cp["camera_dir"]) * cp["camera_distance"]).tolist()
    return scene_from_dict({
        "volume": {"generator": vp["generator"], "seed": vp["seed"], "resolution": vp["resolution"],
                   **({"params": vp["params"]} if vp["params"] else {})},
        "medium": {"density_scale": cp["density_scale"], "albedo": list(cp["albedo"]), "phase": phase},
        "light": {"direction": cp["light"], "irradiance": [1.0, 1.0, 1.0]},
        "camera": {"origin": origin, "target": [0.0, 0.0, 0.0], "up": _up_for(origin),
                   "fov_y": 30.0, "width": 8, "height": 8},
    }, f"<dataset shard {v},{c}>")


def _up_for(origin) -> list:
    o = np.asarray(origin, np.float64)
    return [0.0, 1.0, 0.0] if abs(o[1]) < 0.99 * np.linalg.norm(o) else [1.0, 0.0, 0.0]


def escape_depth(grid, density_scale: float) -> np.ndarray:
    """Optical depth from each voxel centre to the box along the cheapest of the six axis
    directions, [z][y][x] float64 (an upper bound on the depth to the nearest way out)."""
    d = grid.density.astype(np.float64) * float(density_scale)
    best = np.full(d.shape, np.inf)
    for axis, h in ((2, grid.cell_size[0]), (1, grid.cell_size[1]), (0, grid.cell_size[2])):
        fwd = np.cumsum(d, axis=axis) * float(h)
        back = np.flip(np.cumsum(np.flip(d, axis), axis=axis), axis) * float(h)
        half = 0.5 * d * float(h)                  # from the voxel centre, not its far face
        np.minimum(best, fwd - half, out=best)
        np.minimum(best, back - half, out=best)
    return best


# Density-weighted points are also weighted by exp(-escape depth / ESCAPE_SCALE) + ESCAPE_FLOOR:
# deep inside an optically thick medium F is ~0 and no camera sees it, so most points go within
# a few mean free paths of a way out, and a few stay inside (the lattice has such points too).
ESCAPE_SCALE = 4.0
ESCAPE_FLOOR = 0.002


def sample_points(spec: DatasetSpec, grid, v: int, c: int) -> np.ndarray:
    """points_per_config world points: voxel picks with probability ~ density x (exp(-escape
    depth / ESCAPE_SCALE) + ESCAPE_FLOOR), jittered within the voxel, plus a
    ``uniform_fraction`` drawn uniformly in the box (empty space near the medium is on the
    renderer's lattice too)."""
    base, idx = _vkey(spec, v)
    rng = _rng(spec, base + 3, idx, c)
    n = spec.points_per_config
    n_uni = int(round(spec.uniform_fraction * n))
    scale = config_params(spec, v, c, grid)["density_scale"]
    dens = grid.density.astype(np.float64)
    w = (dens * (np.exp(-escape_depth(grid, scale) / ESCAPE_SCALE) + ESCAPE_FLOOR)).ravel()
    lo, hi = np.asarray(grid.bbox_min, np.float64), np.asarray(grid.bbox_max, np.float64)
    total = w.sum()
    if total <= 0:           # an empty volume: all uniform
        n_uni = n
    idx_v = rng.choice(w.size, n - n_uni, p=w / total) if n > n_uni else np.zeros(0, int)
    nz, ny, nx = grid.density.shape
    zyx = np.stack(np.unravel_index(idx_v, (nz, ny, nx)), axis=1)
    inside = lo + (zyx[:, ::-1] + rng.uniform(0, 1, (len(idx_v), 3))) * np.asarray(grid.cell_size)
    uni = lo + rng.uniform(0, 1, (n_uni, 3)) * (hi - lo)
    n_vis = int(round(spec.visible_fraction * n)) if total > 0 else 0
    if n_vis:
        # a stream of its own: the draws above are those of a spec without visible points
        cp = config_params(spec, v, c, grid)
        origin = np.asarray(cp["camera_dir"], np.float64) * cp["camera_distance"]
        vis = visible_points(grid, scale, origin, n_vis, _rng(spec, base + 6, idx, c))
        inside[:len(vis)] = vis          # rays that reach no depth keep their density draw
    return np.concatenate([inside, uni]).astype(np.float32)


VISIBLE_TAU = (0.3, 4.0)
VISIBLE_STEPS = 2048    # ~60 per voxel at 32^3: one step of a dense voxel stays a small optical depth


def visible_points(grid, density_scale: float, origin, n: int, rng) -> np.ndarray:
    """Up to n points where a camera at ``origin`` looks into the medium: on rays through
    uniform points of the box, at optical depth log-uniform in VISIBLE_TAU from the camera.
    Rays that never reach their depth are dropped (fewer than n may come back)."""
    lo, hi = np.asarray(grid.bbox_min, np.float64), np.asarray(grid.bbox_max, np.float64)
    m = 4 * n                                        # candidates: many rays miss thin media
    tgt = lo + rng.uniform(0, 1, (m, 3)) * (hi - lo)
    tau = np.exp(rng.uniform(*np.log(VISIBLE_TAU), m))
    jitter = rng.uniform(0, 1, m)
    pts, hit = depth_points(grid, density_scale, origin, tgt - origin, tau, jitter)
    return pts[hit][:n]


def depth_points(grid, density_scale: float, origin, dirs, tau, jitter=0.5):
    """(points [m][3], reached [m]): along each ray from ``origin`` in direction ``dirs`` [m][3],
    the point at optical depth ``tau`` (scalar or [m]) from ``origin``: nearest-voxel density,
    VISIBLE_STEPS steps along the ray's chord of the box (``jitter`` in [0, 1): the steps'
    offset), interpolated within the crossing step. Rays that miss the box or never reach
    ``tau`` are not reached (their point is meaningless)."""
    lo, hi = np.asarray(grid.bbox_min, np.float64), np.asarray(grid.bbox_max, np.float64)
    d = grid.density.astype(np.float64) * density_scale
    shape = np.array(d.shape[::-1])
    cell = (hi - lo) / shape
    origin = np.asarray(origin, np.float64)
    dirs = np.asarray(dirs, np.float64)
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    m = len(dirs)
    tau = np.broadcast_to(np.asarray(tau, np.float64), (m,))
    jitter = np.broadcast_to(np.asarray(jitter, np.float64), (m,))
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (lo - origin) / dirs, (hi - origin) / dirs
    tn = np.nanmax(np.minimum(t0, t1), axis=1).clip(0)
    tf = np.nanmin(np.maximum(t0, t1), axis=1)
    dt = np.maximum(tf - tn, 0) / VISIBLE_STEPS
    ts = tn[:, None] + (np.arange(VISIBLE_STEPS)[None, :] + jitter[:, None]) * dt[:, None]
    p = origin + ts[..., None] * dirs[:, None, :]
    k = np.clip(((p - lo) / cell).astype(np.int64), 0, shape - 1)
    inc = d[k[..., 2], k[..., 1], k[..., 0]] * dt[:, None]    # step j covers ts[j] +- dt/2
    cum = np.cumsum(inc, axis=1)
    hit = cum[:, -1] >= tau
    j = np.argmax(cum >= tau[:, None], axis=1)
    r = np.arange(m)
    # within the crossing step, where the optical depth reaches tau (density constant there)
    f = (tau - (cum[r, j] - inc[r, j])) / np.maximum(inc[r, j], 1e-30)
    t = ts[r, j] + (np.clip(f, 0, 1) - 0.5) * dt
    return origin + t[:, None] * dirs, hit


def _code_contract(spec: DatasetSpec) -> dict:
    from ..features.templates import load_templates
    return {"layout_version": layout.LAYOUT_VERSION, "template_hash": load_templates().sha256,
            "base_resolution": spec.base_resolution, "lambda": spec.lam,
            "n_levels": layout.n_levels(spec.base_resolution)}


def make_shard(spec: DatasetSpec, v: int, c: int, grid=None, pyramid=None, runtime=None) -> dict:
    """Arrays and meta of shard (v, c) (nothing written). ``grid``/``pyramid``: volume v's, if
    the caller already has them (they are a pure function of (spec, v))."""
    from ..kernels.gather import gather
    from ..kernels.pyramid import build_pyramid
    from ..kernels.transmittance import graded_transmittance
    from ..render.pathtrace import SE_ALBEDOS, point_query, point_query_orders
    from .labels import label_at, se_at
    t0 = time.perf_counter()
    grid = grid if grid is not None else make_volume(spec, v)
    scene = scene_for(spec, v, c, grid)
    pyramid = pyramid if pyramid is not None else build_pyramid(grid, spec.base_resolution, runtime)
    pts = sample_points(spec, grid, v, c)
    om = np.asarray(scene.camera.origin, np.float64) - pts
    om /= np.linalg.norm(om, axis=1, keepdims=True)
    base, idx = _vkey(spec, v)
    qseed = int(_rng(spec, base + 4, idx, c).integers(0, 2**31 - 1))
    order_arrays, path_stats = {}, {}
    if spec.per_order_labels:
        o = point_query_orders(scene, pts, om, spec.n_paths, seed=qseed, grid=grid, runtime=runtime)
        alb = np.asarray(scene.medium.albedo, np.float64)
        lab = {"Fms": np.stack([label_at(o["S"], o["M"], a) for a in alb], axis=1),
               "Fms_se": np.stack([se_at(o["se"], SE_ALBEDOS, a) for a in alb], axis=1),
               "F1": np.repeat(o["F1"][:, None], 3, axis=1), "truncated": o["truncated"],
               "stopped_at_bound": o["stopped_at_bound"]}
        order_arrays = {"S": o["S"].astype(np.float32), "M": o["M"].astype(np.float32),
                        "se": o["se"].astype(np.float32)}
        path_stats = {"vertices_mean": float(o["vertices_mean"].mean()),
                      "vertices_max": int(o["vertices_max"].max())}
    else:
        lab = point_query(scene, pts, om, spec.n_paths, seed=qseed, grid=grid, runtime=runtime)
    t_labels = time.perf_counter() - t0
    l = np.asarray(scene.light.direction, np.float64)
    graded = graded_transmittance(pyramid, scene.medium.density_scale, l, lam=spec.lam)
    g = gather(pyramid, graded, pts, om, l, scene.medium, scene.medium.albedo[0], mode="train")
    arrays = {"points": pts, "omegas": om.astype(np.float32), "features": g["features"],
              "levels": g["levels"], "config": g["config"], "Fms": lab["Fms"],
              "Fms_se": lab["Fms_se"], "F1": lab["F1"], **order_arrays}
    for k, a in arrays.items():
        if not np.all(np.isfinite(a)):
            raise DatasetError(f"shard ({v}, {c}): non-finite values in {k}")
    meta = {"format": DATASET_FORMAT, "format_version": DATASET_VERSION, "spec": spec.to_dict(),
            "volume_index": v, "config_index": c, "heldout_volume": spec.is_heldout(v),
            "volume": volume_params(spec, v),
            "config": config_params(spec, v, c, grid), "camera_origin": list(scene.camera.origin),
            "query_seed": qseed, "paths_truncated": int(lab["truncated"]),
            "paths_stopped_at_bound": int(lab["stopped_at_bound"]), **path_stats,
            "contract": _code_contract(spec),
            "seconds": {"labels": round(t_labels, 3), "total": round(time.perf_counter() - t0, 3)},
            "label_median_rel_se": float(np.median(lab["Fms_se"][:, 0] /
                                                   np.maximum(lab["Fms"][:, 0], 1e-30)))}
    return {"arrays": arrays, "meta": meta}


# A fixed zip timestamp (the earliest zip can hold): np.savez stamps each member with the
# current time, so two runs would differ in a few header bytes.
_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


def shard_bytes(arrays: dict, meta: dict) -> bytes:
    """The .npz file of a shard as bytes (what a remote worker sends back to the driver).

    A pure function of the arrays and meta: zip members in a fixed order with a fixed
    timestamp, and the meta's wall-clock ``seconds`` left out (they go to the folder's
    ``timings.jsonl``), so the same spec gives the same bytes serially, on Ray, or resumed.
    np.load reads it like any np.savez file."""
    import zipfile
    meta = {k: v for k, v in meta.items() if k != "seconds"}
    members = {META_KEY: np.frombuffer(json.dumps(meta, sort_keys=True).encode("utf-8"), np.uint8),
               **arrays}
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for key, a in members.items():
            info = zipfile.ZipInfo(key + ".npy", date_time=_ZIP_EPOCH)
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(a), allow_pickle=False)
    return buf.getvalue()


def _write_json_atomic(path: Path, obj) -> None:
    with atomic_open(path, "w") as f:
        json.dump(obj, f, indent=1, sort_keys=True)


def check_spec_file(out_dir: Path, spec: DatasetSpec) -> None:
    """Create spec.json, or refuse a folder made with another spec (mixing would be silent)."""
    path = out_dir / SPEC_FILE
    want = {"format": DATASET_FORMAT, "format_version": DATASET_VERSION, "spec": spec.to_dict()}
    if path.exists():
        try:
            have = json.loads(path.read_text())
        except ValueError as exc:
            raise DatasetError(f"{path}: not valid JSON ({exc})") from None
        try:   # fields added later take their defaults in an older folder's spec
            have["spec"] = DatasetSpec.from_dict(have.get("spec", {})).to_dict()
        except (DatasetError, TypeError):
            pass
        if have != want:
            diff = [k for k in set(have.get("spec", {})) | set(want["spec"])
                    if have.get("spec", {}).get(k) != want["spec"].get(k)]
            raise DatasetError(f"{path}: the folder holds a data set of another spec (fields "
                               f"{sorted(diff) or ['format']} differ); use another folder or the same spec")
    else:
        _write_json_atomic(path, want)


def check_part(part) -> tuple[int, int] | None:
    """``part`` = (i, n): this process makes the volumes v with v % n == i (None: all)."""
    if part is None:
        return None
    try:
        i, n = (int(x) for x in part)
    except (TypeError, ValueError):
        raise DatasetError(f"part {part!r}: expected I/N with 0 <= I < N") from None
    if not 0 <= i < n:
        raise DatasetError(f"part {i}/{n}: expected I/N with 0 <= I < N")
    return i, n


def pending_shards(spec: DatasetSpec, out_dir, part=None) -> list[tuple[int, int]]:
    """Prepare ``out_dir`` for a (resumed) run and list the shards still to make: checks or
    creates spec.json, removes temporary files of a run killed mid-write, skips finished
    shards. With ``part`` (i, n) only volumes v % n == i, and temporary files are left alone:
    the other parts may be writing theirs into the same folder (the loader never reads them)."""
    part = check_part(part)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    check_spec_file(out, spec)
    if part is None:
        for stale in out.glob(".shard_*.tmp"):     # a previous run killed mid-write
            stale.unlink()
    return [(v, c) for v in range(spec.n_volumes) for c in range(spec.configs_per_volume)
            if (part is None or v % part[1] == part[0]) and not (out / shard_name(v, c)).exists()]


class ShardMaker:
    """Makes shards one after another in one process, keeping the last volume's grid and
    pyramid (they depend on (spec, v) only). Used by the serial loop and by each Ray worker."""

    def __init__(self, runtime=None):
        self.runtime = runtime
        self._volume = (None, None, None)

    def __call__(self, spec: DatasetSpec, v: int, c: int) -> tuple[bytes, dict]:
        """(the shard file's bytes, its meta including the timings the file leaves out)."""
        from ..kernels.pyramid import build_pyramid
        key = (json.dumps(spec.to_dict(), sort_keys=True), v)
        if self._volume[0] != key:
            grid = make_volume(spec, v)
            self._volume = (key, grid, build_pyramid(grid, spec.base_resolution, self.runtime))
        shard = make_shard(spec, v, c, self._volume[1], self._volume[2], self.runtime)
        return shard_bytes(shard["arrays"], shard["meta"]), shard["meta"]


TIMINGS_FILE = "timings.jsonl"


def write_shard(out_dir, v: int, c: int, data: bytes, log: dict | None = None) -> None:
    """The driver's write of one finished shard: the bytes atomically, then one line of
    ``log`` (timings, the node that made it) to timings.jsonl, for labelling-cost
    measurements; the loader never reads it."""
    out = Path(out_dir)
    with atomic_open(out / shard_name(v, c), "wb") as f:
        f.write(data)
    if log:
        with open(out / TIMINGS_FILE, "a") as f:
            f.write(json.dumps({"shard": shard_name(v, c), **log}, sort_keys=True) + "\n")


def shard_progress(n_shards: int, spec: DatasetSpec, progress: bool):
    """The progress bar of a data set run: shards done/total, labels per second, ETA."""
    from ..progress import Progress
    return Progress(n_shards, label="dataset", unit=" shards", delay=0.0 if progress else 1e30,
                    rate_per_unit=spec.points_per_config, rate_unit="labels")


def make_dataset(spec: DatasetSpec, out_dir, runtime=None, progress: bool = True,
                 max_shards: int | None = None, on_shard=None, part=None) -> dict:
    """Make every missing shard of ``spec`` in ``out_dir``, serially in this process (Ray:
    clvol/training/distributed.py). Returns {"made", "skipped"} counts. ``max_shards``: stop after
    making this many (tests); ``on_shard(v, c)`` is called after each shard is written.
    ``part`` (i, n): only volumes v % n == i, so n processes can share one folder (one
    device, several host processes: docs/dataset.md)."""
    out = Path(out_dir)
    todo = pending_shards(spec, out, part)
    made = 0
    maker = ShardMaker(runtime)
    with shard_progress(len(todo), spec, progress) as bar:
        for v, c in todo:
            if max_shards is not None and made >= max_shards:
                break
            data, meta = maker(spec, v, c)
            write_shard(out, v, c, data, meta.get("seconds"))
            made += 1
            bar.update(1)
            if on_shard is not None:
                on_shard(v, c)
    mine = spec.n_shards if part is None else sum(
        spec.configs_per_volume for v in range(spec.n_volumes) if v % part[1] == part[0])
    return {"made": made, "skipped": mine - len(todo)}


class ShardArrays(Mapping):
    """A shard's arrays, read from its file when asked for (a training set of thousands of
    shards would not fit in memory twice: the trainer copies each array once, then drops it)."""

    def __init__(self, path: Path):
        self.path = path

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in ARRAYS + ORDER_ARRAYS:
            raise KeyError(name)
        try:
            with np.load(self.path, allow_pickle=False) as z:
                return z[name]
        except Exception as exc:
            raise DatasetError(f"{self.path}: cannot read array {name!r} "
                               f"({type(exc).__name__}: {exc})") from None

    def __iter__(self):
        return iter(ARRAYS)

    def __len__(self) -> int:
        return len(ARRAYS)


@dataclass
class Shard:
    path: Path
    arrays: Mapping
    meta: dict

    @property
    def volume(self) -> int:
        return int(self.meta["volume_index"])

    @property
    def config_index(self) -> int:
        return int(self.meta["config_index"])

    @property
    def albedo(self) -> tuple:
        return tuple(self.meta["config"]["albedo"])


def read_shard(path) -> Shard:
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(z[META_KEY].tobytes().decode("utf-8"))
            missing = [k for k in ARRAYS if k not in z.files]
            if missing:
                raise DatasetError(f"{path}: shard lacks array(s) {missing}")
    except DatasetError:
        raise
    except Exception as exc:
        raise DatasetError(f"{path}: cannot read shard ({type(exc).__name__}: {exc})") from None
    if meta.get("format") != DATASET_FORMAT or meta.get("format_version") not in READABLE_VERSIONS:
        raise DatasetError(f"{path}: [format] {meta.get('format')!r} version "
                           f"{meta.get('format_version')!r}; expected {DATASET_FORMAT!r} "
                           f"{' or '.join(map(str, READABLE_VERSIONS))}")
    return Shard(path, ShardArrays(path), meta)


def load_shards(data_dir) -> list[Shard]:
    """Every finished shard of a data set folder (``shard_*.npz`` only; temporary files of an
    interrupted run are never read), in name order, all made with one spec and one contract."""
    d = Path(data_dir)
    if not (d / SPEC_FILE).exists():
        raise DatasetError(f"{d}: no {SPEC_FILE}; not a clvol data set folder")
    shards = [read_shard(p) for p in sorted(d.glob("shard_*.npz"))]
    if not shards:
        raise DatasetError(f"{d}: no finished shards")
    c0 = shards[0].meta["contract"]
    for s in shards[1:]:
        if s.meta["contract"] != c0:
            raise DatasetError(f"{s.path}: [contract] {s.meta['contract']} differs from "
                               f"{shards[0].path}'s {c0}")
    return shards
