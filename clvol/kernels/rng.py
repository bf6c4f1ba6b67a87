"""Host wrapper for cl/rng.cl (Philox4x32-10 streams; see cl/include/rng.h)."""
import numpy as np

from ..runtime import get_runtime


def philox_raw(ctr: np.ndarray, key=(0, 0), runtime=None) -> np.ndarray:
    """Raw Philox4x32-10 of (n, 4) uint32 counters."""
    rt = runtime or get_runtime()
    ctr = np.ascontiguousarray(ctr, dtype=np.uint32).reshape(-1, 4)
    n = len(ctr)
    k = rt.program("rng").kernel("philox_raw", [None, np.uint32, np.uint32, np.int32, None])
    out = rt.empty((n, 4), np.uint32)
    rt.launch(k, n, (rt.to_device(ctr), np.uint32(key[0]), np.uint32(key[1]), np.int32(n), out))
    return rt.from_device(out, (n, 4), np.uint32)


def uniforms(seed: int, n: int, stream0: int = 0, sample: int = 0, block: int = 0,
             runtime=None) -> np.ndarray:
    """(n, 4) float32 uniforms for streams stream0..stream0+n-1."""
    rt = runtime or get_runtime()
    k = rt.program("rng").kernel(
        "rng_uniforms", [np.uint64, np.uint64, np.uint32, np.uint32, np.int32, None])
    out = rt.empty((n, 4), np.float32)
    rt.launch(k, n, (np.uint64(seed), np.uint64(stream0), np.uint32(sample), np.uint32(block),
                     np.int32(n), out))
    return rt.from_device(out, (n, 4), np.float32)
