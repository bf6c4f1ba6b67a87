"""Host wrapper for cl/phase.cl: evaluate and sample the scene's phase function.

``lobes`` is a sequence of (g, weight) pairs (clvol.scene.Phase.lobes work too);
None or empty means isotropic (compiled with PHASE_ISOTROPIC).
"""
import numpy as np

from ..errors import ClvolError
from ..runtime import get_runtime


def phase_defines(lobes) -> dict:
    """The -D defines that specialise phase.h for these lobes."""
    if not lobes:
        return {"PHASE_ISOTROPIC": 1, "PHASE_LOBES": 1}
    if not 1 <= len(lobes) <= 3:
        raise ClvolError(f"1 to 3 phase lobes supported, got {len(lobes)}")
    return {"PHASE_LOBES": len(lobes)}


def lobe_vectors(lobes) -> tuple[np.ndarray, np.ndarray]:
    """(lobe_g, lobe_w) as the float4 kernel arguments."""
    g = np.zeros(4, np.float32)
    w = np.zeros(4, np.float32)
    for k, lobe in enumerate(lobes or [(0.0, 1.0)]):
        gk, wk = (lobe.g, lobe.weight) if hasattr(lobe, "g") else lobe
        g[k], w[k] = gk, wk
    return g, w


def _prog(lobes, runtime):
    rt = runtime or get_runtime()
    return rt, rt.program("phase", defines=phase_defines(lobes))


def phase_eval(mu: np.ndarray, lobes, runtime=None) -> np.ndarray:
    rt, prog = _prog(lobes, runtime)
    mu = np.ascontiguousarray(mu, np.float32).ravel()
    g, w = lobe_vectors(lobes)
    k = prog.kernel("phase_eval_many", [None, None, None, np.int32, None])
    out = rt.empty(mu.size)
    rt.launch(k, mu.size, (rt.to_device(mu), g, w, np.int32(mu.size), out))
    return rt.from_device(out, mu.shape)


def phase_sample(w_in: np.ndarray, u: np.ndarray, lobes, runtime=None) -> np.ndarray:
    rt, prog = _prog(lobes, runtime)
    w_in = np.ascontiguousarray(w_in, np.float32).reshape(-1, 3)
    u = np.ascontiguousarray(u, np.float32).reshape(-1, 3)
    n = len(w_in)
    g, wt = lobe_vectors(lobes)
    k = prog.kernel("phase_sample_many", [None, None, None, None, np.int32, None])
    out = rt.empty((n, 3))
    rt.launch(k, n, (rt.to_device(w_in), rt.to_device(u), g, wt, np.int32(n), out))
    return rt.from_device(out, (n, 3))
