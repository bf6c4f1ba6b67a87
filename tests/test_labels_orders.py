"""Labels at every albedo from one set of paths (cl/pathtrace.cl -D PT_ORDER_BINS,
clvol.render.pathtrace.point_query_orders, clvol/training/labels.py).

How the tests decide:
- Kernel against twin, same random stream, path by path: as tests/test_pathtrace.py (>= 97%
  of paths agree within 1e-4 relative + 1e-6 absolute on every output, bins included).
- Relabelling against direct tracing, independent streams: z = |sum_q F_orders - sum_q
  F_direct| / sqrt(sum_q se_orders^2 + sum_q se_direct^2) < 4 per albedo (5 comparisons:
  a false alarm has probability ~3e-4); queries have independent streams, so the sums'
  variances add. The power check: a 10% scaling of the relabelled sums must fail it.
- Storage bounds: exact per-order contributions are binned by the twin's own bin rule, and
  labels.label_bounds must bracket the exact sum (no tolerance beyond float rounding).
"""
import numpy as np
import pytest

from clvol.kernels.pathtrace import ORDER_BINS, PT_OUT, PathTracer, order_bin_ranges
from clvol.training import labels
from reference import pathtrace as rpt
from test_pathtrace import BMAX, BMIN, agreement, make_medium, twin


def _queries(n, seed):
    rs = np.random.default_rng(seed)
    p = rs.uniform(BMIN, BMAX, size=(n, 3))
    w = rs.normal(size=(n, 3))
    return p, w / np.linalg.norm(w, axis=1, keepdims=True)


@pytest.mark.parametrize("albedo,scale", [(1.0, 14.0), (0.97, 40.0)])
def test_order_bins_match_twin_path_by_path(albedo, scale):
    # dense enough that paths reach the octave bins (exponents >= 32)
    med = make_medium(lobes=[(0.7, 0.8), (-0.3, 0.2)], albedo=(albedo,) * 3, scale=scale)
    p, w = _queries(12, 4)
    pt = PathTracer(med, majorant_block=0)
    k = pt.query_batch(pt.rt.to_device(p.astype(np.float32)), pt.rt.to_device(w.astype(np.float32)),
                       12, seed=9, sample0=2, ppl=3, orders=True)
    r = rpt.query_paths(twin(med), p.astype(np.float32), w.astype(np.float32), seed=9,
                        samples=range(2, 5), orders=True)
    assert k.shape == r.shape == (3, 12, PT_OUT + 2 * ORDER_BINS)
    assert r[..., 9].max() > 40                      # some path reached a geometric bin
    assert agreement(k[..., :PT_OUT], r[..., :PT_OUT]) >= 0.97
    kb, rb = k[..., PT_OUT:], r[..., PT_OUT:]
    close = np.all(np.abs(kb - rb) <= 1e-6 + 1e-4 * np.abs(rb), axis=-1)
    assert close.mean() >= 0.97
    # the bins hold exactly the orders >= 2 of the row (channel 0)
    np.testing.assert_allclose(k[..., PT_OUT:PT_OUT + ORDER_BINS].sum(-1), k[..., 6],
                               rtol=1e-5, atol=1e-7)


def test_host_bin_ranges_invert_the_twins_bin_rule():
    ranges = order_bin_ranges()
    assert ranges.shape == (ORDER_BINS, 2) and ranges[0, 0] == 1
    assert np.all(ranges[1:, 0] == ranges[:-1, 1] + 1)          # contiguous, no gaps
    for e in list(range(1, 300)) + [511, 512, 513, 1000, 4095, 4096, 99_999, 100_000, 131_071]:
        b = rpt.order_bin(e)
        assert ranges[b, 0] <= e <= ranges[b, 1], e


def _scene(albedo, tmp_path, scale=12.0):
    from clvol.scene import scene_from_dict
    rs = np.random.default_rng(5)
    dens = (0.05 + rs.random((10, 9, 8)) ** 2).astype(np.float32)
    path = tmp_path / "d.npy"
    np.save(path, dens)
    return scene_from_dict({
        "volume": {"file": str(path), "bbox_min": [-0.5, -0.4, -0.5], "bbox_max": [0.5, 0.5, 0.6]},
        "medium": {"density_scale": scale, "albedo": list(albedo),
                   "phase": {"type": "mhg", "lobes": [{"g": 0.8, "weight": 0.7},
                                                      {"g": -0.4, "weight": 0.3}]}},
        "light": {"direction": [0.3, 0.8, 0.5], "irradiance": [1.0, 1.0, 1.0]},
        "camera": {"origin": [0, 0, 2.5], "target": [0, 0, 0], "up": [0, 1, 0], "fov_y": 30.0,
                   "width": 8, "height": 8}}, "<test>")


def test_relabelled_orders_agree_with_direct_tracing(tmp_path):
    from clvol.render.pathtrace import SE_ALBEDOS, point_query, point_query_orders
    p, w = _queries(64, 6)
    # the scene's albedo is ignored by point_query_orders (it traces at albedo 1)
    o = point_query_orders(_scene((0.5, 0.5, 0.5), tmp_path), p, w, 1024, seed=3)
    assert o["truncated"] == 0 and o["vertices_max"].max() > 40
    direct = point_query(_scene((0.9, 0.99, 0.999), tmp_path), p, w, 1024, seed=4)
    z = []
    for ch, a in enumerate((0.9, 0.99, 0.999)):
        f = labels.label_at(o["S"], o["M"], a)
        se = labels.se_at(o["se"], SE_ALBEDOS, a)
        err = np.sqrt((se ** 2).sum() + (direct["Fms_se"][:, ch] ** 2).sum())
        z.append(abs(f.sum() - direct["Fms"][:, ch].sum()) / err)
        # power: a 10% error in the relabelled sums would be caught (the sums' standard
        # error is ~2% of their value: heavy-tailed long paths)
        assert abs(1.10 * f.sum() - direct["Fms"][:, ch].sum()) / err > 4.0
    assert max(z) < 4.0, z
    # albedo 1 and a low albedo against direct tracing too (grey)
    for a in (1.0, 0.6):
        d = point_query(_scene((a, a, a), tmp_path), p, w, 1024, seed=5)
        f = labels.label_at(o["S"], o["M"], a)
        se = labels.se_at(o["se"], SE_ALBEDOS, a)
        err = np.sqrt((se ** 2).sum() + (d["Fms_se"][:, 0] ** 2).sum())
        assert abs(f.sum() - d["Fms"][:, 0].sum()) / err < 4.0, a
    # the standard errors at the nodes are those of direct labels of the same path count
    # (same estimator, other streams): their ratio is near 1 where labels are not tiny
    ratio = labels.se_at(o["se"], SE_ALBEDOS, 0.99).sum() / direct["Fms_se"][:, 1].sum()
    assert 0.8 < ratio < 1.25, ratio


def test_storage_bounds_bracket_the_exact_label():
    rs = np.random.default_rng(11)
    ranges = order_bin_ranges()
    for trial in range(20):
        # exact per-order contributions C_e with a long tail (as deep paths at albedo 1 give)
        n = int(rs.integers(50, 5000))
        e = np.unique(np.concatenate([np.arange(1, 40), rs.integers(1, n, 300)]))
        C = rs.random(len(e)) * np.exp(-e / rs.uniform(5, n))
        S = np.zeros((1, ORDER_BINS))
        M = np.zeros((1, ORDER_BINS))
        for ei, ci in zip(e, C):
            b = rpt.order_bin(int(ei))           # the twin's rule, not the host's ranges
            S[0, b] += ci
            M[0, b] += ci * ei
        for a in (1.0, 0.9999, 0.999, 0.99, 0.9, 0.5, 0.0):
            exact = float((C * np.power(a, e.astype(np.float64))).sum())
            lo, hi = labels.label_bounds(S, M, a)
            assert lo[0] <= exact * (1 + 1e-12) + 1e-300, (trial, a)
            assert exact <= hi[0] * (1 + 1e-12) + 1e-300, (trial, a)
            np.testing.assert_allclose(labels.label_at(S, M, a), lo)
            if a == 1.0:
                assert lo[0] == pytest.approx(exact, rel=1e-12)
    assert ranges[-1, 1] >= 100_000     # every exponent below the vertex limit has a bin


def test_energy_above_counts_the_tail_bins():
    S = np.zeros((2, ORDER_BINS))
    S[0, 0] = 3.0                       # e = 1
    S[0, rpt.order_bin(600)] = 1.0      # e = 600
    S[1, 5] = 2.0
    np.testing.assert_allclose(labels.energy_above(S, 512), [0.25, 0.0])
    np.testing.assert_allclose(labels.energy_above(np.zeros((1, ORDER_BINS)), 512), [0.0])
