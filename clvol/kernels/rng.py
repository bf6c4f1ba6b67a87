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


# The same Philox4x32-10 on the host (NumPy), for draws the host makes itself: the
# stochastic view source's jitter (clvol/render/ms/view.py view_jitter), which libclvol
# (capi/src/renderer.c philox4x32_10) reproduces bit for bit. Convention: cl/include/rng.h.
_M0, _M1 = np.uint64(0xD2511F53), np.uint64(0xCD9E8D57)
_W0, _W1 = 0x9E3779B9, 0xBB67AE85
_LO = np.uint64(0xFFFFFFFF)


def host_uniform4(seed: int, stream, sample: int, block: int) -> np.ndarray:
    """(n, 4) float32 uniforms in [0, 1) of rng.h's ``rng_uniform4(seed, stream, sample,
    block)`` for each stream of ``stream`` (int array, n); computed with NumPy."""
    stream = np.asarray(stream, np.uint64).ravel()
    c = [stream & _LO, stream >> np.uint64(32),
         np.full(stream.shape, int(sample) & 0xFFFFFFFF, np.uint64),
         np.full(stream.shape, int(block) & 0xFFFFFFFF, np.uint64)]
    k0, k1 = int(seed) & 0xFFFFFFFF, (int(seed) >> 32) & 0xFFFFFFFF
    for _ in range(10):
        p0, p1 = _M0 * c[0], _M1 * c[2]          # < 2^64: exact in uint64
        c = [(p1 >> np.uint64(32)) ^ c[1] ^ np.uint64(k0), p1 & _LO,
             (p0 >> np.uint64(32)) ^ c[3] ^ np.uint64(k1), p0 & _LO]
        k0, k1 = (k0 + _W0) & 0xFFFFFFFF, (k1 + _W1) & 0xFFFFFFFF
    bits = np.stack(c, axis=-1)
    return (bits >> np.uint64(8)).astype(np.float32) * np.float32(1.0 / 16777216.0)
