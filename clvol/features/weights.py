"""The network's architecture description and its weight file (NumPy only, no torch).

A weight file is one ``.npz``: every parameter tensor under its torch ``state_dict`` name
(float32, torch's (out, in) shapes), plus ``__meta__``, a UTF-8 JSON document (uint8 array,
so ``np.load(allow_pickle=False)`` reads it) holding

- ``format`` / ``format_version``: "clvol-mlp" / ``FORMAT_VERSION``; other versions are refused;
- ``architecture``: ``Architecture.to_dict()`` (everything that fixes the tensor shapes);
- ``contract``: the feature contract the network was trained with (``feature_contract``):
  ``clvol.features.layout.contract_dict`` (layout version, layer counts, feature and config order, frame,
  units, base resolution, number of levels, lambda, template table hash) plus the level map,
  the phase parameterisation, the learned per-level transmittance weights and bias (the
  seed's 3D-CNN as a 1x1x1 convolution across levels, baked by the gather at render time),
  the input normalisation and the output encoding;
- ``training``: free-form notes (data, steps, loss), never checked;
- ``domain`` (optional): the validity domain of the training data, exactly the keys of
  ``DOMAIN_KEYS``: {"albedo": [lo, hi], "g": [lo, hi], "max_lobes": n,
  "optical_thickness": [lo, hi], "resolution": [lo, hi]}. A file without it is read as
  ``DEFAULT_DOMAIN`` (the domain of the first shipped model, cloud_small).

``load_weights`` refuses a file of another format version, a tensor of another shape, a
non-finite value, or a contract that differs from the one the caller's gather produces,
with a ``WeightsError`` naming the file and the dotted field.

Architecture (seed III.C; docs/network.md has the picture and the counts)
-------------------------------------------------------------------------
Per query: features x [3][P] (types density, transmittance, phase; P template points),
config c [9]. Inputs are normalised first: x_t <- (x_t - feature_shift[t]) * feature_scale[t],
c <- (c - config_shift) * config_scale.
Squeeze (per template layer k, shared by the three types' modules): the 8-vector
v_k = (mean_d, mean_T, mean_p, max_d, max_T, max_p, g_mean, alpha) over layer k's points.
Module (type t, template s with layers k = 0..K-1 of n_k points), state h_0 = x_t[layer 0]:
    a_k = [h_k, c]                                    (n_k + 9)  "fused with the configuration"
    w_k = sigmoid(E2_k relu(E1_k v_k))                (n_k + 9)  SE excitation, FC-ReLU-FC-sigmoid
    z_k = w_k * a_k
    k < K-1:  u = relu(FC1_k z_k) + x_t[layer k+1]    (n_{k+1})  FC-1 to the next layer's width, fused
              h_{k+1} = relu(FC2_k u) + x_t[layer k+1]           FC-2, fused with the current layer
    out_{t,s} = relu(OUT z_{K-1})                     (module_width)
Merge per type m_t = relu(MERGE_t [out_{t,diffuse}, out_{t,highlight}]) (module_width);
head: y = H3 relu(H2 relu(H1 [m_density, m_transmittance, m_phase, c])).
Output y = log(F / albedo^GAMMA + 1) (F: orders >= 2 for a unit light); decode
F = albedo^GAMMA * max(exp(y) - 1, 0), and F = 0 for albedo 0.
"""
from __future__ import annotations

import hashlib
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..atomic import atomic_open
from ..errors import ClvolError, WeightsError  # noqa: F401 (re-exported)
from . import layout

FORMAT = "clvol-mlp"
FORMAT_VERSION = 1
GAMMA = 4.0
TYPES = layout.FEATURE_TYPES                  # ("density", "transmittance", "phase")
TEMPLATES = ("diffuse", "highlight")
SQUEEZE_DIM = 8
META_KEY = "__meta__"

# Fixed input normalisation defaults: the angle enters in units of pi (so it lies in [0, 1]);
# everything else is already O(1). Training may replace the feature shift/scale by data
# statistics (clvol.training.train); the values travel in the weight file either way.
DEFAULT_CONFIG_SCALE = tuple(1.0 / math.pi if f == "alpha" else 1.0 for f in layout.CONFIG_FIELDS)

PHASE_PARAMETERISATION = (
    "config g0 g1 g2 w0 w1 w2: up to 3 Henyey-Greenstein lobes (unused: g 0, weight 0), weights sum "
    "to 1; g_mean = sum w_k g_k is the one g of the attention squeeze; phase features log1p(f*f*) "
    "of cone-averaged HG (docs/conventions.md)")
OUTPUT_ENCODING = "y = log(F / albedo^4 + 1), F = multiple scattering (orders >= 2) for unit irradiance"

DOMAIN_KEYS = ("albedo", "g", "max_lobes", "optical_thickness", "resolution")
# cloud_small's data (clvol/data/weights/cloud_small.md): what a file without "domain" covers.
DEFAULT_DOMAIN = {"albedo": [0.8, 0.999], "g": [0.0, 0.9], "max_lobes": 3}


# --------------------------------------------------------------------------- architecture

# Encodings of the config's albedo (Architecture.albedo_input) and the offset of "log1m".
ALBEDO_INPUTS = ("linear", "log1m")
ALBEDO_EPS = 1e-4
# The config normalisation of a "log1m" albedo: shift to a = 0.99, scale ~1/spread.
LOG1M_SHIFT, LOG1M_SCALE = 4.6, 1.0 / 3.0


@dataclass(frozen=True)
class Architecture:
    """Everything that fixes the network's tensor shapes. ``layer_counts`` is the template's
    points per layer (clvol.features.layout), the first ``n_diffuse_layers`` of them diffuse."""
    layer_counts: tuple = layout.LAYER_COUNTS
    n_diffuse_layers: int = len(layout.DIFFUSE_LAYER_COUNTS)
    config_dim: int = layout.CONFIG_DIM
    n_levels: int = layout.N_LEVELS
    se_hidden: int = 8
    module_width: int = 32
    head_widths: tuple = (64, 32)
    # How the config's albedo enters (before the config normalisation): "linear" (the files
    # before issue 21) or "log1m", -log(1 - a + ALBEDO_EPS), which spreads 0.99 .. 1 over as
    # wide a range as 0.3 .. 0.99 (F rises steeply as a -> 1; docs/network.md).
    albedo_input: str = "linear"

    def __post_init__(self):
        object.__setattr__(self, "layer_counts", tuple(int(c) for c in self.layer_counts))
        object.__setattr__(self, "head_widths", tuple(int(c) for c in self.head_widths))
        if not 1 <= self.n_diffuse_layers < len(self.layer_counts):
            raise WeightsError("need at least one diffuse and one highlight layer")
        if min(self.layer_counts) < 1 or min(self.head_widths, default=1) < 1:
            raise WeightsError("layer counts and widths must be positive")
        if self.albedo_input not in ALBEDO_INPUTS:
            raise WeightsError(f"albedo_input {self.albedo_input!r}: one of {list(ALBEDO_INPUTS)}")
        if self.config_dim != layout.CONFIG_DIM:  # the forward reads g_mean, albedo, alpha by index
            raise WeightsError(f"config_dim must be {layout.CONFIG_DIM} (clvol.features.layout.CONFIG_FIELDS)")

    @property
    def n_points(self) -> int:
        return sum(self.layer_counts)

    def template_counts(self, template: str) -> tuple:
        nd = self.n_diffuse_layers
        return self.layer_counts[:nd] if template == "diffuse" else self.layer_counts[nd:]

    def layer_slices(self) -> list[slice]:
        out, start = [], 0
        for c in self.layer_counts:
            out.append(slice(start, start + c))
            start += c
        return out

    def template_layer_slices(self, template: str) -> list[slice]:
        sl = self.layer_slices()
        return sl[:self.n_diffuse_layers] if template == "diffuse" else sl[self.n_diffuse_layers:]

    # Linear layers as (name, fan_in, fan_out), in the order the forward pass runs them.
    def linear_layers(self) -> list[tuple[str, int, int]]:
        c, r, m = self.config_dim, self.se_hidden, self.module_width
        out = []
        for t in TYPES:
            for s in TEMPLATES:
                counts = self.template_counts(s)
                pre = f"branches.{t}.{s}"
                for k, n in enumerate(counts):
                    out.append((f"{pre}.se_a.{k}", SQUEEZE_DIM, r))
                    out.append((f"{pre}.se_b.{k}", r, n + c))
                    if k + 1 < len(counts):
                        out.append((f"{pre}.fc1.{k}", n + c, counts[k + 1]))
                        out.append((f"{pre}.fc2.{k}", counts[k + 1], counts[k + 1]))
                out.append((f"{pre}.out", counts[-1] + c, m))
        for t in TYPES:
            out.append((f"merges.{t}", 2 * m, m))
        widths = (3 * m + c,) + self.head_widths + (1,)
        for j in range(len(widths) - 1):
            out.append((f"head.{j}", widths[j], widths[j + 1]))
        return out

    def tensor_shapes(self) -> dict[str, tuple]:
        """Every tensor of the weight file / torch state_dict, with its shape."""
        shapes = {
            "level_weights": (self.n_levels,), "level_bias": (1,),
            "feature_shift": (len(TYPES),), "feature_scale": (len(TYPES),),
            "config_shift": (self.config_dim,), "config_scale": (self.config_dim,),
        }
        for name, fan_in, fan_out in self.linear_layers():
            shapes[f"{name}.weight"] = (fan_out, fan_in)
            shapes[f"{name}.bias"] = (fan_out,)
        return shapes

    def n_params(self, trainable_only: bool = True) -> int:
        """Parameters (trainable: linear layers and the level weights/bias; the normalisation
        constants are buffers)."""
        skip = {"feature_shift", "feature_scale", "config_shift", "config_scale"}
        return sum(int(np.prod(s)) for n, s in self.tensor_shapes().items()
                   if not (trainable_only and n in skip))

    def n_macs(self) -> dict:
        """Multiply-adds of one evaluation (one query, one colour channel), by kind."""
        dense = sum(i * o for _, i, o in self.linear_layers())
        se_scale = 3 * sum(n + self.config_dim for n in self.layer_counts)  # w_k * a_k
        pooling = 2 * len(TYPES) * self.n_points                            # sum and max
        return {"dense": dense, "se_scale": se_scale, "pooling": pooling,
                "total": dense + se_scale + pooling}

    def to_dict(self) -> dict:
        return {"layer_counts": list(self.layer_counts), "n_diffuse_layers": self.n_diffuse_layers,
                "config_dim": self.config_dim, "n_levels": self.n_levels,
                "se_hidden": self.se_hidden, "module_width": self.module_width,
                "head_widths": list(self.head_widths), "albedo_input": self.albedo_input,
                "albedo_eps": ALBEDO_EPS, "squeeze_dim": SQUEEZE_DIM,
                "types": list(TYPES), "templates": list(TEMPLATES), "gamma": GAMMA}

    @classmethod
    def from_dict(cls, d: dict, where: str = "architecture") -> "Architecture":
        keys = ("layer_counts", "n_diffuse_layers", "config_dim", "n_levels", "se_hidden",
                "module_width", "head_widths")
        missing = [k for k in keys if k not in d]
        if missing:
            raise WeightsError(f"{where}: missing field(s) {', '.join(missing)}")
        for k, want in (("squeeze_dim", SQUEEZE_DIM), ("types", list(TYPES)),
                        ("templates", list(TEMPLATES)), ("gamma", GAMMA),
                        ("albedo_eps", ALBEDO_EPS)):
            if k in d and d[k] != want:
                raise WeightsError(f"{where}: [architecture.{k}] is {d[k]!r}; this code supports {want!r}")
        try:
            return cls(**{k: d[k] for k in keys}, albedo_input=d.get("albedo_input", "linear"))
        except (TypeError, ValueError, WeightsError) as exc:
            raise WeightsError(f"{where}: [architecture] is invalid: {exc}") from None


# --------------------------------------------------------------------------- contract

def feature_contract(base_resolution: int = layout.DEFAULT_BASE_RESOLUTION,
                     lam: float = layout.DEFAULT_LAMBDA, template_hash: str = "",
                     level_map: dict | None = None) -> dict:
    """The contract a gather produces: clvol.features.layout.contract_dict plus the level map (the mip
    level each template layer reads, from clvol.features.templates) and the phase parameterisation.
    The weight-specific parts (level weights, normalisation) are added by ``save_weights``."""
    c = layout.contract_dict(base_resolution, lam, template_hash)
    c["level_map"] = level_map
    c["phase_parameterisation"] = PHASE_PARAMETERISATION
    return c


def gather_contract(base_resolution: int = layout.DEFAULT_BASE_RESOLUTION,
                    lam: float = layout.DEFAULT_LAMBDA, templates=None) -> dict:
    """``feature_contract`` for the packaged template table (clvol.features.templates): its hash and
    level map (diffuse layers: one level each; highlight layers: spacing per unit t_enter,
    the level is chosen per query from it)."""
    from .templates import load_templates
    t = templates if templates is not None else load_templates()
    level_map = {"diffuse": [int(v) for v in t.diffuse_levels(base_resolution)],
                 "highlight_spacing": [round(float(v), 9) for v in t.highlight_spacing()]}
    c = feature_contract(base_resolution, lam, t.sha256)
    c["level_map"] = level_map
    return c


# Contract fields a loader compares with the caller's gather (weight-specific fields are not).
CONTRACT_KEYS = ("layout_version", "layer_counts", "feature_types", "config_fields",
                 "base_resolution", "n_levels", "lambda", "template_hash", "frame", "units",
                 "level_map", "phase_parameterisation")


def _contract_diff(have: dict, want: dict) -> list[str]:
    out = []
    for k in CONTRACT_KEYS:
        if k not in want:
            continue
        a, b = have.get(k, "<missing>"), want[k]
        same = (math.isclose(a, b, rel_tol=1e-9, abs_tol=0.0) if isinstance(a, float)
                and isinstance(b, (int, float)) else a == b)
        if not same:
            out.append(f"[contract.{k}] is {a!r} in the file, the gather produces {b!r}")
    return out


# --------------------------------------------------------------------------- file

@dataclass
class MlpWeights:
    """A loaded weight file: ``params`` maps state_dict names to float32 arrays."""
    arch: Architecture
    params: dict
    contract: dict
    meta: dict = field(default_factory=dict)
    path: str = ""

    @property
    def level_weights(self) -> np.ndarray:
        return self.params["level_weights"]

    @property
    def level_bias(self) -> float:
        return float(self.params["level_bias"][0])


def _check_params(params: dict, arch: Architecture, where: str) -> dict:
    shapes = arch.tensor_shapes()
    missing = [n for n in shapes if n not in params]
    extra = [n for n in params if n not in shapes]
    if missing or extra:
        msg = []
        if missing:
            msg.append(f"missing tensor(s) {', '.join(missing[:5])}" + (" ..." if len(missing) > 5 else ""))
        if extra:
            msg.append(f"unexpected tensor(s) {', '.join(extra[:5])}" + (" ..." if len(extra) > 5 else ""))
        raise WeightsError(f"{where}: {'; '.join(msg)} for the architecture it declares")
    out = {}
    for name, shape in shapes.items():
        a = np.asarray(params[name])
        if a.shape != tuple(shape):
            raise WeightsError(f"{where}: [{name}] has shape {a.shape}, the architecture needs {tuple(shape)}")
        if a.dtype.kind != "f":
            raise WeightsError(f"{where}: [{name}] has dtype {a.dtype}, expected float32")
        a = a.astype(np.float32)
        if not np.all(np.isfinite(a)):
            bad = int(np.size(a) - np.count_nonzero(np.isfinite(a)))
            raise WeightsError(f"{where}: [{name}] holds {bad} non-finite value(s)")
        out[name] = a
    if np.any(out["feature_scale"] == 0) or np.any(out["config_scale"] == 0):
        raise WeightsError(f"{where}: [feature_scale]/[config_scale] contain 0 (an input would be ignored)")
    return out


def check_domain(domain, where: str = "domain") -> dict:
    """A validity domain with exactly DOMAIN_KEYS: [lo, hi] pairs (lo <= hi, finite) and an
    integer max_lobes in 1..3; returned as plain JSON types."""
    if not isinstance(domain, dict) or set(domain) != set(DOMAIN_KEYS):
        got = sorted(domain) if isinstance(domain, dict) else domain
        raise WeightsError(f"{where}: [domain] must have exactly the keys {list(DOMAIN_KEYS)}, got {got!r}")
    out = {}
    for k in DOMAIN_KEYS:
        v = domain[k]
        if k == "max_lobes":
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 1 <= v <= 3:
                raise WeightsError(f"{where}: [domain.max_lobes] = {v!r} must be an integer in [1, 3]")
            out[k] = int(v)
            continue
        try:
            lo, hi = (float(x) for x in v)
        except (TypeError, ValueError):
            raise WeightsError(f"{where}: [domain.{k}] = {v!r} must be [low, high]") from None
        if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
            raise WeightsError(f"{where}: [domain.{k}] = {v!r} must be finite with low <= high")
        out[k] = [int(lo), int(hi)] if k == "resolution" else [lo, hi]
    return out


def weights_domain(meta: dict) -> dict:
    """The validity domain of a weight file's meta (``read_meta``): its "domain", or
    DEFAULT_DOMAIN for a file written before domains were recorded."""
    d = meta.get("domain")
    return dict(DEFAULT_DOMAIN) if d is None else check_domain(d)


def save_weights(path, arch: Architecture, params: dict, contract: dict,
                 training: dict | None = None, domain: dict | None = None) -> Path:
    """Write a weight file (atomically: a temporary file renamed into place). ``domain``: the
    training data's validity domain (``check_domain``; clvol.training.dataset.dataset_domain makes it)."""
    path = Path(path)
    params = _check_params(params, arch, str(path))
    domain = None if domain is None else check_domain(domain, str(path))
    if "n_levels" in contract and contract["n_levels"] != arch.n_levels:
        raise WeightsError(f"{path}: the network has {arch.n_levels} transmittance levels, the contract "
                           f"{contract['n_levels']} (base resolution {contract.get('base_resolution')})")
    contract = dict(contract)
    contract["level_weights"] = [float(v) for v in params["level_weights"]]
    contract["level_bias"] = float(params["level_bias"][0])
    contract["normalisation"] = {
        "features": "x_t <- (x_t - feature_shift[t]) * feature_scale[t], t in feature_types",
        "config": "c <- (c - config_shift) * config_scale",
        "feature_shift": [float(v) for v in params["feature_shift"]],
        "feature_scale": [float(v) for v in params["feature_scale"]],
        "config_shift": [float(v) for v in params["config_shift"]],
        "config_scale": [float(v) for v in params["config_scale"]],
    }
    contract["output"] = OUTPUT_ENCODING
    contract["gamma"] = GAMMA
    meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "architecture": arch.to_dict(),
            "contract": contract, "training": training or {},
            "counts": {"params": arch.n_params(), "macs": arch.n_macs()}}
    if domain is not None:
        meta["domain"] = domain
    blob = np.frombuffer(json.dumps(meta, indent=1, sort_keys=True).encode("utf-8"), np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **{META_KEY: blob}, **params)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path) as f:
        f.write(buf.getvalue())
    return path


def read_meta(path) -> dict:
    """The JSON description of a weight file (format checked, tensors not read)."""
    return _open(path)[0]


def _open(path):
    where = str(path)
    if not Path(path).is_file():
        raise WeightsError(f"{where}: no such weight file")
    try:
        npz = np.load(path, allow_pickle=False)
        files = list(npz.files)
    except Exception as exc:  # zipfile/ValueError/OSError: not an npz at all
        raise WeightsError(f"{where}: not a clvol weight file (.npz): {exc}") from None
    if META_KEY not in files:
        raise WeightsError(f"{where}: no {META_KEY} entry; not a clvol weight file")
    try:
        meta = json.loads(npz[META_KEY].tobytes().decode("utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise WeightsError(f"{where}: [{META_KEY}] is not valid JSON: {exc}") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise WeightsError(f"{where}: [format] is {meta.get('format') if isinstance(meta, dict) else meta!r}, "
                           f"expected {FORMAT!r}")
    if meta.get("format_version") != FORMAT_VERSION:
        raise WeightsError(f"{where}: [format_version] is {meta.get('format_version')!r}; this clvol reads "
                           f"version {FORMAT_VERSION} only (re-export the network)")
    for k in ("architecture", "contract"):
        if not isinstance(meta.get(k), dict):
            raise WeightsError(f"{where}: [{k}] missing or not an object")
    return meta, npz, files


def load_weights(path, expect_contract: dict | None = None) -> MlpWeights:
    """Load and check a weight file. The file's feature contract must equal this code's
    layout (clvol.features.layout: version, layer counts, feature/config order, frame, units); with
    ``expect_contract`` (``feature_contract(...)`` from the gather that will feed it) the
    base resolution, lambda, template hash and level map must match too."""
    where = str(path)
    meta, npz, files = _open(path)
    arch = Architecture.from_dict(meta["architecture"], where)
    contract = meta["contract"]
    diffs = _contract_diff(contract, layout.contract_dict(
        contract.get("base_resolution", layout.DEFAULT_BASE_RESOLUTION),
        contract.get("lambda", layout.DEFAULT_LAMBDA), contract.get("template_hash", "")))
    if expect_contract is not None:
        diffs += [d for d in _contract_diff(contract, expect_contract) if d not in diffs]
    if diffs:
        raise WeightsError(f"{where}: feature contract mismatch: " + "; ".join(diffs))
    if arch.layer_counts != tuple(contract["layer_counts"]) or arch.n_levels != contract.get("n_levels"):
        raise WeightsError(f"{where}: [architecture.layer_counts/n_levels] disagree with [contract]")
    if "domain" in meta:
        check_domain(meta["domain"], where)
    params = _check_params({n: npz[n] for n in files if n != META_KEY}, arch, where)
    return MlpWeights(arch=arch, params=params, contract=contract, meta=meta, path=where)


def params_digest(params: dict) -> str:
    """A short hash of the tensors (names, shapes, bytes) for logs and caches."""
    h = hashlib.sha256()
    for n in sorted(params):
        a = np.ascontiguousarray(params[n], np.float32)
        h.update(n.encode())
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def default_params(arch: Architecture, rng: np.random.Generator | None = None,
                   alive: bool = True) -> dict:
    """Random float32 parameters (tests, benchmarks). With ``alive`` the weights are scaled
    N(0, 2/fan_in) (He) and biases small positive, so ReLUs stay active and parity tests are
    not passed by dead units."""
    rng = rng or np.random.default_rng(0)
    p = {}
    for name, shape in arch.tensor_shapes().items():
        if name == "level_weights":
            p[name] = np.full(shape, 1.0 / shape[0], np.float32)
        elif name in ("level_bias", "feature_shift", "config_shift"):
            p[name] = np.zeros(shape, np.float32)
        elif name == "feature_scale":
            p[name] = np.ones(shape, np.float32)
        elif name == "config_scale":
            p[name] = np.asarray(DEFAULT_CONFIG_SCALE, np.float32)[:shape[0]]
        elif name.endswith(".weight"):
            std = math.sqrt((2.0 if alive else 1.0) / shape[1])
            p[name] = (rng.standard_normal(shape) * std).astype(np.float32)
        else:  # bias
            p[name] = (rng.uniform(0.0, 0.1, shape) if alive else np.zeros(shape)).astype(np.float32)
    return p
