"""Host wrapper for cl/mlp.cl: the network's fused forward pass from a weight file.

    w = load_weights("net.npz", expect_contract=gather_contract(base_resolution, lam))
    net = MlpKernel(w)                                # packs the weights once, on the device
    y = net.forward(features, config)                 # y [N] (config's albedo)
    F = net.forward(features, config, channel_albedo=(0.9, 0.95, 1.0), decode=True)   # F [N][3]
    F = net.radiance(features, config, albedo_rgb)    # F [N][3], grey media: one evaluation
    net.enqueue(features_dev, config_dev, n, out_dev, ...)   # DeviceArrays in and out

``features``/``config`` are the gather's arrays or DeviceArrays (clvol/features/layout.py). With
``channel_albedo`` one evaluation per distinct non-zero channel albedo is run in the kernel
(grey: pass the config's albedo and no channel_albedo, one evaluation); albedo-0 channels give 0.
"""
from __future__ import annotations

import numpy as np

from ..errors import NetworkInputError
from ..features.weights import ALBEDO_EPS, GAMMA, SQUEEZE_DIM, TYPES, MlpWeights
from ..features.layout import CONFIG_DIM, CONFIG_FIELDS
from ..runtime import DeviceArray, get_runtime


def _pad8(x: int) -> int:
    return (int(x) + 7) // 8 * 8


def pack_params(weights: MlpWeights) -> np.ndarray:
    """The flat float32 parameter buffer cl/mlp.cl walks: normalisation constants, then each
    linear layer in execution order as W^T [n_in][pad8(n_out)] and bias [pad8(n_out)]."""
    p = weights.params
    parts = [p["feature_shift"], p["feature_scale"], p["config_shift"], p["config_scale"]]
    for name, n_in, n_out in weights.arch.linear_layers():
        wt = np.zeros((n_in, _pad8(n_out)), np.float32)
        wt[:, :n_out] = p[f"{name}.weight"].T
        b = np.zeros(_pad8(n_out), np.float32)
        b[:n_out] = p[f"{name}.bias"]
        parts += [wt.ravel(), b]
    return np.concatenate([np.asarray(a, np.float32).ravel() for a in parts])


def contract_defines() -> dict:
    """The -D options that carry the feature contract's and the weight format's numbers
    (clvol/features/layout.py, clvol/features/weights.py) into cl/include/mlp_core.h, which
    refuses to build without them."""
    if GAMMA != int(GAMMA):
        raise RuntimeError(f"bug: GAMMA = {GAMMA!r}; the kernels decode integer powers only")
    return {"CONFIG_DIM": CONFIG_DIM, "CFG_GMEAN": CONFIG_FIELDS.index("g_mean"),
            "CFG_ALBEDO": CONFIG_FIELDS.index("albedo"), "CFG_ALPHA": CONFIG_FIELDS.index("alpha"),
            "N_TYPES": len(TYPES), "SQUEEZE": SQUEEZE_DIM, "MLP_GAMMA": int(GAMMA),
            "MLP_ALBEDO_EPS": float(ALBEDO_EPS)}


def kernel_defines(arch, channels: int, decode: bool) -> dict:
    """The -D options of cl/mlp.cl (and of cl/gather_mlp.cl's network) for ``arch``."""
    maxw = max(max(_pad8(i), _pad8(o)) for _, i, o in arch.linear_layers())
    return {
        **contract_defines(),
        "N_LAYERS": len(arch.layer_counts), "N_DIFFUSE": arch.n_diffuse_layers,
        "LAYER_COUNTS": ",".join(str(c) for c in arch.layer_counts),
        "N_POINTS": arch.n_points, "SE_HIDDEN": arch.se_hidden,
        "MODULE_WIDTH": arch.module_width, "HEAD_DEPTH": len(arch.head_widths),
        "HEAD_WIDTHS": ",".join(str(w) for w in arch.head_widths),
        "MAXW": maxw, "MLP_CHANNELS": channels, "MLP_DECODE": int(bool(decode)),
        **({"MLP_ALBEDO_LOG1M": 1} if arch.albedo_input == "log1m" else {}),
    }


# Added on PoCL only (Clang builtins, measured faster there: cl/mlp.cl).
POCL_DEFINES = {"MLP_TRANSPOSE16": 1, "MLP_PREFETCH": 1}


class MlpKernel:
    """A weight file on one device, ready to evaluate gather buffers."""

    def __init__(self, weights: MlpWeights, runtime=None, defines: dict | None = None):
        """``defines``: extra -D options, overriding the defaults (a value of None removes
        one: tests use {"MLP_TRANSPOSE16": None} for the per-lane load path)."""
        self.weights = weights
        self.arch = weights.arch
        self.rt = runtime or get_runtime()
        self.params = pack_params(weights)
        self.params_device = self.rt.upload(self.params, label="network weights")
        self._kernels = {}
        self._extra = dict(defines or {})

    def defines(self, channels: int, decode: bool) -> dict:
        """The -D options of cl/mlp.cl's device functions (also cl/gather_mlp.cl's)."""
        defines = kernel_defines(self.arch, channels, decode)
        if self.rt.is_pocl:
            defines.update(POCL_DEFINES)
        defines.update(self._extra)   # runtime._define_flags skips None values
        return defines

    def kernel(self, channels: int, decode: bool):
        key = (channels, bool(decode))
        k = self._kernels.get(key)
        if k is None:
            prog = self.rt.program("mlp", defines=self.defines(channels, decode))
            k = self._kernels[key] = prog.kernel(
                "mlp_forward", [None, None, None, None, np.int32, None])
        return k

    def enqueue(self, features: DeviceArray, config: DeviceArray, n: int, out: DeviceArray,
                channel_albedo=None, decode: bool = False, wait_for=None):
        """Launch on DeviceArrays: features [n][3][P], config [n][9] -> out [n][C] float32,
        C = 3 with channel_albedo, else 1. Returns the event."""
        for name, a in (("features", features), ("config", config), ("out", out)):
            if not isinstance(a, DeviceArray):
                raise NetworkInputError(f"MlpKernel.enqueue: {name} must be a DeviceArray "
                                        f"(Runtime.upload / alloc), got {type(a).__name__}")
        channels = 1 if channel_albedo is None else 3
        alb = np.zeros(4, np.float32)
        if channel_albedo is not None:
            alb[:3] = _channel_albedo(channel_albedo)
        return launch_items(self.rt, self.kernel(channels, decode), n,
                            (features.buffer, config.buffer, self.params_device.buffer, alb,
                             np.int32(n), out.buffer),
                            wait_for=wait_for)

    def forward(self, features, config, channel_albedo=None, decode: bool = False,
                n: int | None = None) -> np.ndarray:
        """y (or F with ``decode``) as [N] (config's albedo) or [N][3] (``channel_albedo``).
        ``features``/``config`` are arrays (checked against the layout) or DeviceArrays (``n``:
        their first dimension unless given)."""
        rt = self.rt
        if isinstance(features, DeviceArray) or isinstance(config, DeviceArray):
            if not (isinstance(features, DeviceArray) and isinstance(config, DeviceArray)):
                raise NetworkInputError("MlpKernel.forward: features and config must both be "
                                        "arrays or both DeviceArrays")
            n = features.shape[0] if n is None else int(n)
            fb, cb = features, config
        else:
            features = np.asarray(features)
            config = np.asarray(config)
            n = len(features)
            want_f = (n, len(TYPES), self.arch.n_points)
            if features.shape != want_f or config.shape != (n, CONFIG_DIM):
                raise NetworkInputError(f"features {features.shape} / config {config.shape}: "
                                        f"expected {want_f} / {(n, CONFIG_DIM)} (clvol/features/layout.py)")
            fb, cb = rt.upload(features), rt.upload(config)
        channels = 1 if channel_albedo is None else 3
        if n == 0:
            return np.zeros((0,) if channels == 1 else (0, 3), np.float32)
        out = rt.alloc((n, channels))
        evt = self.enqueue(fb, cb, n, out, channel_albedo, decode)
        y = out.read(wait_for=[evt])
        return y[:, 0] if channels == 1 else y


    def radiance(self, features, config, albedo_rgb, n: int | None = None) -> np.ndarray:
        """F [N][3] (orders >= 2, unit irradiance) for a medium of RGB albedo ``albedo_rgb``:
        one evaluation per query for a grey medium (its config's albedo is replaced by the
        medium's), three for a chromatic one (equal channels share one); albedo 0 gives 0."""
        alb = _channel_albedo(albedo_rgb)
        if alb[0] == alb[1] == alb[2]:
            if isinstance(config, DeviceArray):   # the kernel's 3-channel mode dedupes equal albedos
                return self.forward(features, config, channel_albedo=alb, decode=True, n=n)
            cfg = np.array(config, np.float32, copy=True)
            cfg[:, CONFIG_FIELDS.index("albedo")] = alb[0]
            F = self.forward(features, cfg, decode=True, n=n)
            return np.repeat(F[:, None], 3, axis=1)
        return self.forward(features, config, channel_albedo=alb, decode=True, n=n)


def launch_items(rt, kernel, n: int, args, wait_for=None):
    """Launch a kernel that evaluates the network for LANES queries per work-item (the
    device's lane width ``rt.lanes``, one query per lane; mlp_forward, gather_mlp) over n
    queries. A work-item holds ~105 KB of private arrays (at 16 lanes: all 798 features of its
    16 queries, the layer buffers). PoCL's CPU driver with a NULL local size packs many
    work-items into one group and overflows its stack (segfault at 256 items); groups of one
    work-item also need no padding of the global size."""
    items = -(-int(n) // rt.lanes)
    local = (1,) if rt.entry.kind == "cpu" else None
    return rt.launch(kernel, items, args, local_size=local, pad=1 if local else 64,
                     wait_for=wait_for)


def _channel_albedo(a) -> np.ndarray:
    a = np.asarray(a, np.float32).ravel()
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.any(a < 0) or np.any(a > 1):
        raise NetworkInputError(f"channel_albedo must be 3 values in [0, 1], got {a.tolist()}")
    return a
