"""cl/include/rng.h (via cl/rng.cl) against reference/rng.py and Random123's known answers."""
import numpy as np
import pytest

from clvol.kernels import rng as krng
from reference import rng as rrng

# Known-answer vectors of Philox4x32-10 published with Random123 (kat_vectors).
KAT = [
    ((0, 0, 0, 0), (0, 0), (0x6627E8D5, 0xE169C58D, 0xBC57AC4C, 0x9B00DBD8)),
    ((0xFFFFFFFF,) * 4, (0xFFFFFFFF, 0xFFFFFFFF), (0x408F276D, 0x41C83B0E, 0xA20BC7C6, 0x6D5451FD)),
    ((0x243F6A88, 0x85A308D3, 0x13198A2E, 0x03707344), (0xA4093822, 0x299F31D0),
     (0xD16CFE09, 0x94FDCCEB, 0x5001E420, 0x24126EA1)),
]


@pytest.mark.parametrize("ctr,key,expect", KAT)
def test_reference_matches_random123_known_answers(ctr, key, expect):
    got = rrng.philox4x32_10(np.array([ctr], np.uint32), np.array(key, np.uint32))[0]
    assert tuple(int(x) for x in got) == expect


@pytest.mark.oclgrind
@pytest.mark.rusticl
@pytest.mark.parametrize("ctr,key,expect", KAT)
def test_kernel_matches_random123_known_answers(ctr, key, expect):
    got = krng.philox_raw(np.array([ctr], np.uint32), key)[0]
    assert tuple(int(x) for x in got) == expect


def test_kernel_bit_identical_to_reference_on_many_counters():
    rs = np.random.default_rng(1)
    ctr = rs.integers(0, 2**32, size=(1001, 4), dtype=np.uint64).astype(np.uint32)
    key = (0x12345678, 0x9ABCDEF0)
    np.testing.assert_array_equal(krng.philox_raw(ctr, key), rrng.philox4x32_10(ctr, key))


@pytest.mark.oclgrind
@pytest.mark.rusticl
def test_uniform_streams_bit_identical_and_in_unit_interval():
    seed = (7 << 32) | 12345  # both key words in use
    stream0 = (3 << 32) + 17  # stream ids beyond 32 bits
    got = krng.uniforms(seed, 37, stream0=stream0, sample=5, block=2)
    want = rrng.uniform4(seed, stream0 + np.arange(37, dtype=np.uint64), 5, 2)
    np.testing.assert_array_equal(got, want)
    assert got.min() >= 0.0 and got.max() < 1.0


def test_uniforms_look_uniform():
    # 4 x 40,000 draws in 10 bins: each bin count ~ Binomial(160000, 0.1), sd = 120.
    # A 6-sd band (720) is a false-alarm rate of ~2e-9 per bin; a broken generator
    # (e.g. a stuck bit) is off by thousands.
    u = krng.uniforms(99, 40000).ravel()
    counts = np.histogram(u, bins=10, range=(0, 1))[0]
    assert np.all(np.abs(counts - 16000) < 720), counts
    # Different samples and blocks give different streams.
    assert not np.array_equal(krng.uniforms(99, 64, sample=1), krng.uniforms(99, 64, sample=0))
    assert not np.array_equal(krng.uniforms(99, 64, block=1), krng.uniforms(99, 64, block=0))
