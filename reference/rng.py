"""NumPy twin of cl/include/rng.h: Philox4x32-10 and clvol's counter convention.

key = (seed & 0xffffffff, seed >> 32); counter = (stream lo, stream hi, sample, block);
uniforms are the top 24 bits of each word times 2**-24, in [0, 1).
"""
import numpy as np

M0, M1 = np.uint64(0xD2511F53), np.uint64(0xCD9E8D57)
W0, W1 = np.uint32(0x9E3779B9), np.uint32(0xBB67AE85)
_MASK = np.uint64(0xFFFFFFFF)


def philox4x32_10(ctr: np.ndarray, key) -> np.ndarray:
    """ctr: (..., 4) uint32; key: (2,) uint32. Returns (..., 4) uint32."""
    c = [np.asarray(ctr[..., j], dtype=np.uint64) for j in range(4)]
    k0, k1 = np.uint32(key[0]), np.uint32(key[1])
    with np.errstate(over="ignore"):
        for r in range(10):
            p0 = M0 * c[0]
            p1 = M1 * c[2]
            hi0, lo0 = p0 >> np.uint64(32), p0 & _MASK
            hi1, lo1 = p1 >> np.uint64(32), p1 & _MASK
            c = [hi1 ^ c[1] ^ np.uint64(k0), lo1, hi0 ^ c[3] ^ np.uint64(k1), lo0]
            k0, k1 = np.uint32(k0 + W0), np.uint32(k1 + W1)
    return np.stack([x.astype(np.uint32) for x in c], axis=-1)


def uniform4(seed: int, stream, sample, block) -> np.ndarray:
    """(..., 4) float32 uniforms in [0, 1), broadcasting stream/sample/block."""
    stream = np.asarray(stream, dtype=np.uint64)
    sample, block = np.broadcast_arrays(np.asarray(sample, np.uint32), np.asarray(block, np.uint32))
    stream, sample, block = np.broadcast_arrays(stream, sample, block)
    ctr = np.stack([(stream & _MASK).astype(np.uint32), (stream >> np.uint64(32)).astype(np.uint32),
                    sample.astype(np.uint32), block.astype(np.uint32)], axis=-1)
    key = (np.uint32(seed & 0xFFFFFFFF), np.uint32((seed >> 32) & 0xFFFFFFFF))
    bits = philox4x32_10(ctr, key)
    return ((bits >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / 16777216.0))
