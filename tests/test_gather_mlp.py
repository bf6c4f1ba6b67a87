"""cl/gather_mlp.cl (the fused render-mode gather + network, clvol/kernels/gather_mlp.py) against
the twins composed in NumPy (reference/gather_mlp.py: reference/gather.py's features ->
reference/mlp.py's forward -> decode), and against the unfused kernels (gather -> mlp_forward).

Tolerances:
- fused vs twin, on y = log(F / a^4 + 1) per channel: the feature errors the gather is allowed
  against its twin (tests/test_gather.py: 2e-5 on density and T, a float32 trilinear read vs
  float64; 2e-3 on phase at g up to 0.857, the kernel's linear read of its alpha table, 3e-3
  with lobes of |g| 0.95-0.97, whose steeper peaks the table resolves less well (measured
  2.4e-3 there; 3.4e-6 at g = 0.02); 1e-5 on the centre point's exact phase; the test first
  checks the gather kernel's features against the twin's within these, as the premise of
  the bound) pushed through the network, plus the network's own float32 bound
  (tests/test_mlp.py: 1e-5 |y| + 1e-5 max|y|). The push-through is measured on the float64
  twin at the test's own inputs: feature i moved by its tolerance alone, one at a time, and
  the |change of y| summed over the 798 features (a first-order bound for errors of either
  sign in every feature at once), doubled for the second-order terms a one-at-a-time
  measure misses. F = a^4 max(exp(y) - 1, 0) then moves by at most a^4 (exp(y + b) - exp(y))
  for a bound b on y (the clamp at 0 only shrinks differences). The bound is loose (measured
  errors 1e-5 to 2e-2 of it): it catches gross errors (a wrong feature, layout, channel or
  decode; asserted: F varies over more than 10 bounds); exactness is the next test's.
- fused vs unfused on the same device: 1e-6 of max|F| + 1 ULP-scale floor (1e-30): both run
  the same inlined device functions (cl/include/gather_core.h, mlp_core.h) on the same values
  in the same order, so they should agree to the last bit (measured: identical bits on PoCL);
  the tolerance only allows for a compiler that contracts the two programs' expressions into
  fused multiply-adds differently. The same holds for the existing kernels across the move of
  their code into those headers (checked bit for bit when it was made).

Inputs are adversarial for a fused kernel: a non-cubic volume (13 x 9 x 11 voxels, padded to a
cube) so a swap of the grid axes moves the features; query points inside the volume, on its
faces and corners, just outside the volume inside the cube, and outside the cube; omega
parallel and antiparallel to the light (the frame's fallback) and random; g near 0 and |g|
near 1 (0.02; 0.97 and -0.95 in an MHG); grey and chromatic albedo with distinct channels
(so a channel swap shows: asserted), both albedo inputs of the network (linear, log1m);
query counts that are not multiples of the 16 lanes.
"""
import numpy as np
import pytest

from clvol.errors import ClvolError
from clvol.kernels import gather as kgather
from clvol.kernels.gather import GatherError, gather
from clvol.kernels.gather_mlp import gather_mlp
from clvol.kernels.mlp import MlpKernel
from clvol.kernels.pyramid import build_pyramid
from clvol.kernels.transmittance import graded_transmittance
from clvol.features.weights import Architecture, MlpWeights, default_params, feature_contract
from clvol.scene import Medium, Phase
from clvol.volume.generators import generate
from reference import gather_mlp as rfused
from reference import mlp as rmlp

FEATURE_TOL = (2e-5, 2e-5, 2e-3)      # density, transmittance, phase (tests/test_gather.py)
PHASE_TOL_STEEP = 3e-3                # phase with |g| ~ 0.95-0.97 lobes (module docstring)
CENTRE_TOL = 1e-5                     # the centre point's phase, exact in both


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def scene(light, density_scale, base=32):
    g = generate("cloud", seed=3, resolution=(13, 9, 11))      # nx, ny, nz all different
    pyr = build_pyramid(g, base)
    return g, pyr, graded_transmittance(pyr, density_scale, unit(light))


def network(n_levels, seed, albedo_input="linear"):
    """Random He-scaled weights (tests/test_mlp.py) with the output bias raised by 3 so that
    y > 0 for most queries: with the raw init y < 0 everywhere and every decoded F is 0."""
    arch = Architecture(n_levels=n_levels, albedo_input=albedo_input)
    p = default_params(arch, np.random.default_rng(seed))
    last = f"head.{len(arch.head_widths)}.bias"
    p[last] = p[last] + np.float32(3.0)
    p["level_weights"] = np.linspace(0.3, -0.05, n_levels).astype(np.float32)   # not uniform
    p["level_bias"] = np.array([0.04], np.float32)
    return MlpWeights(arch, p, feature_contract())


def queries(grid, pyr, light, seed):
    """27 queries (one full work-item of 16 and a tail of 11)."""
    rs = np.random.default_rng(seed)
    lo, hi = np.asarray(grid.bbox_min), np.asarray(grid.bbox_max)
    inside = rs.uniform(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo), (12, 3))
    faces = np.array([[lo[0], 0, 0], [hi[0], 0.05, -0.02], [0.03, lo[1], 0], [0, hi[1], 0.1],
                      [-0.05, 0, lo[2]], hi, lo, [hi[0], lo[1], hi[2]]])
    eps = 1e-3 * (hi - lo)
    near_out = np.array([lo - eps, hi + eps, [0, hi[1] + 0.02, 0]])  # outside the volume
    cube_hi = np.asarray(pyr.cube_min) + pyr.cube_size
    far_out = np.array([cube_hi + 0.3, np.asarray(pyr.cube_min) - [0.7, 0.1, 0.4],
                        [0, 0, 5.0], [-3.0, 0.2, 0.0]])              # outside the cube
    pts = np.concatenate([inside, faces, near_out, far_out]).astype(np.float32)
    om = unit(rs.normal(size=(len(pts), 3)))
    om[0], om[1] = unit(light), -unit(light)         # the frame's fallback: omega || l
    return pts, om.astype(np.float32)


def y_bound(w, f, c, albedo, tols):
    """Bound on |y_kernel - y_twin| (module docstring): network float32 bound + twice the
    summed one-at-a-time response of the float64 twin to each feature's tolerance."""
    arch, params = w.arch, w.params
    cfg = rmlp.with_albedo(c, albedo)
    y = rmlp.forward(params, arch, f, cfg)
    n, T, P = f.shape
    tol = np.repeat(np.asarray(tols)[:, None], P, axis=1)
    tol[2, 0] = CENTRE_TOL
    rows = np.repeat(f[:, None], T * P, axis=1)                      # [n][T*P][T][P]
    idx = np.arange(T * P)
    rows.reshape(n, T * P, T * P)[:, idx, idx] += tol.ravel()
    yp = rmlp.forward(params, arch, rows.reshape(n * T * P, T, P),
                      np.repeat(cfg, T * P, axis=0)).reshape(n, T * P)
    push = np.abs(yp - y[:, None]).sum(axis=1)
    return y, 1e-5 * np.abs(y) + 1e-5 * np.abs(y).max() + 2.0 * push


def f_bound(y, b, a):
    return a ** 4 * (np.exp(y + b) - np.exp(y))


CASES = {
    # light, medium, config albedo, channel albedo, albedo input of the network
    "grey_g0": ((0.3, 0.5, 0.8), Medium(14.0, (0.8,) * 3, Phase.hg(0.02)), 0.8, None, "linear"),
    "rgb_g1": ((-0.6, 0.2, -0.75), Medium(9.0, (0.6, 0.95, 0.8),
                                            Phase.mhg([(0.97, 0.6), (-0.95, 0.4)])),
               0.6, (0.6, 0.95, 0.8), "log1m"),
}


# rgb_g1 (three channels, log1m albedo input, a steep two-lobe phase, the shipped network's
# shape) is this file's test on Mesa's rusticl (tests/test_rusticl.py): the fused kernel against
# the NumPy twins directly. test_tiny compares the fused kernel with the unfused pair on one
# device, which a fault both share would pass, and builds four programs of the full network:
# 105-147 s there against 40-60 s for this case (docs/opencl.md, "rusticl").
@pytest.mark.parametrize("case", [pytest.param(c, marks=[pytest.mark.rusticl] if c == "rgb_g1"
                                               else []) for c in CASES])
def test_fused_matches_composed_twins(case):
    light, medium, alb, channels, albedo_input = CASES[case]
    grid, pyr, gt = scene(light, medium.density_scale)
    seed = list(CASES).index(case) + 5          # each case its own draws
    w = network(pyr.n_levels, seed=seed, albedo_input=albedo_input)
    pts, om = queries(grid, pyr, light, seed=seed)
    lobes = tuple((l.g, l.weight) for l in medium.phase.lobes)
    lw, lb = w.level_weights, w.level_bias
    got = gather_mlp(MlpKernel(w), pyr, gt, pts, om, gt.light_dir, medium, alb,
                     level_weights=lw, bias=lb, channel_albedo=channels)
    assert np.all(np.isfinite(got))
    want = rfused.gather_mlp(w.params, w.arch, pyr, gt.data, pts, om, gt.light_dir, lobes,
                             medium.density_scale, alb, lw, lb, channel_albedo=channels)
    f, c = rfused.features(pyr, gt.data, pts, om, gt.light_dir, lobes, medium.density_scale,
                           alb, lw, lb)
    steep = max(abs(g) for g, _ in lobes) > 0.9
    tols = FEATURE_TOL[:2] + ((PHASE_TOL_STEEP,) if steep else FEATURE_TOL[2:])
    # premise of the bound: the gather's features (what the fused kernel computes inside)
    kf = gather(pyr, gt, pts, om, gt.light_dir, medium, alb, mode="render", level_weights=lw,
                bias=lb)["features"]
    for t in range(3):
        np.testing.assert_allclose(kf[:, t, 1:], f[:, t, 1:], atol=tols[t], rtol=0)
    np.testing.assert_allclose(kf[:, 2, 0], f[:, 2, 0], atol=CENTRE_TOL, rtol=0)
    for ch, a in enumerate([alb] if channels is None else channels):
        y, b = y_bound(w, f, c, a, tols)
        g_ch, w_ch = (got, want) if channels is None else (got[:, ch], want[:, ch])
        err = np.abs(g_ch - w_ch)
        bound = f_bound(y, b, a)
        assert np.all(err <= bound), (f"channel {ch}: max err {err.max():.3g}, "
                                      f"at bound {bound[np.argmax(err)]:.3g}")
        # power: F varies far beyond the bound, and more than half the queries have F > 0
        assert np.ptp(w_ch) > 10 * np.median(bound) and np.mean(w_ch > 0) > 0.5
    if channels is not None:
        # distinct channels: a swap of channels would be seen
        swapped = want[:, ::-1]
        assert np.max(np.abs(swapped - want)) > 10 * np.median(bound)


def random_queries(seed: int, n: int, extent: float):
    """n points uniform in [-extent, extent]^3 and unit directions, float32."""
    rs = np.random.default_rng(seed)
    return (rs.uniform(-extent, extent, (n, 3)).astype(np.float32),
            unit(rs.normal(size=(n, 3))).astype(np.float32))


def unfused(net, w, pyr, gt, pts, om, medium, albedo, channels):
    """The unfused pair on the device: gather (render, buffers) -> mlp_forward (decode)."""
    g = gather(pyr, gt, pts, om, gt.light_dir, medium, albedo, mode="render", as_buffers=True,
               level_weights=w.level_weights, bias=w.level_bias)
    return net.forward(g["features"], g["config"], channel_albedo=channels, decode=True,
                       n=g["n"])


@pytest.mark.parametrize("channels", [None, (0.0, 0.7, 0.9), (0.85, 0.85, 0.6)])
def test_fused_equals_unfused(channels, monkeypatch):
    """The fused kernel vs gather (render, device buffers) -> mlp_forward(decode) on the same
    device: 300 queries (19 work-items, a tail of 12), both render load paths, sorted and
    unsorted processing; albedo 0 and repeated channel albedos (the kernel's shortcuts)."""
    light = (0.1, -0.9, 0.35)
    medium = Medium(11.0, (0.85, 0.9, 0.6), Phase.mhg([(0.8, 0.7), (-0.3, 0.3)]))
    grid, pyr, gt = scene(light, medium.density_scale)
    w = network(pyr.n_levels, seed=7)
    net = MlpKernel(w)
    pts, om = random_queries(4, 300, 0.7)
    kw = dict(level_weights=w.level_weights, bias=w.level_bias)
    want = unfused(net, w, pyr, gt, pts, om, medium, 0.85, channels)
    assert np.ptp(want) > 0.1
    for shuffle in (True, False):
        monkeypatch.setattr(kgather, "USE_SHUFFLE", shuffle)
        for sort in (True, False):
            got = gather_mlp(net, pyr, gt, pts, om, gt.light_dir, medium, 0.85,
                             channel_albedo=channels, sort=sort, **kw)
            assert got.shape == want.shape and np.all(np.isfinite(got))
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-6 * np.abs(want).max() + 1e-30)
    if channels is not None and channels[0] == 0:
        assert np.all(got[:, 0] == 0)


def _checked_setup():
    """A small volume, its graded field and a network: the input-check tests' fixture."""
    medium = Medium(12.0, (0.9,) * 3, Phase.hg(0.5))
    _, pyr, gt = scene((0.3, 0.5, 0.8), medium.density_scale, base=16)
    w = network(pyr.n_levels, seed=1)
    return medium, pyr, gt, w, MlpKernel(w)


def test_inputs_checked():
    medium, pyr, gt, w, net = _checked_setup()
    kw = dict(level_weights=w.level_weights, bias=w.level_bias)
    out = gather_mlp(net, pyr, gt, np.zeros((0, 3)), np.zeros((0, 3)), gt.light_dir, medium, 0.9, **kw)
    assert out.shape == (0,)
    with pytest.raises(GatherError, match="unit"):
        gather_mlp(net, pyr, gt, np.zeros((2, 3)), np.ones((2, 3)), gt.light_dir, medium, 0.9, **kw)
    tiny = Architecture(layer_counts=(3, 2, 5, 2, 3), n_diffuse_layers=3, n_levels=3,
                        head_widths=(8,))
    small = MlpKernel(MlpWeights(tiny, default_params(tiny), {}))
    with pytest.raises(GatherError, match="template points"):
        gather_mlp(small, pyr, gt, np.zeros((2, 3)), unit(np.ones((2, 3))), gt.light_dir, medium, 0.9, **kw)


@pytest.mark.oclgrind
def test_tiny():
    """3 queries on a 4^3 base, grey and chromatic, against the unfused kernels (Oclgrind)."""
    light = (0.2, 0.3, 0.9)
    medium = Medium(12.0, (0.5, 0.9, 0.7), Phase.hg(0.6))
    g = generate("sphere", seed=0, resolution=4)
    pyr = build_pyramid(g, 4)
    gt = graded_transmittance(pyr, medium.density_scale, unit(light))
    w = network(pyr.n_levels, seed=3)
    net = MlpKernel(w)
    pts, om = random_queries(1, 3, 0.4)
    kw = dict(level_weights=w.level_weights, bias=w.level_bias)
    for ch in (None, (0.5, 0.9, 0.7)):
        want = unfused(net, w, pyr, gt, pts, om, medium, 0.5, ch)
        got = gather_mlp(net, pyr, gt, pts, om, gt.light_dir, medium, 0.5, channel_albedo=ch, **kw)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-6 * np.abs(want).max() + 1e-30)
        assert np.abs(want).max() > 0


@pytest.mark.parametrize("albedo", [0.9, (0.7, 0.95, 0.8)])
def test_network_source_fused_and_unfused_paths_agree(tmp_path, albedo):
    """NetworkSource.evaluate (clvol/render/ms/network.py) on its fused default and on the
    unfused pair (fused=False): the same F_ms (identical bits measured; same tolerance as
    above), and the time split says which path ran."""
    from clvol.features.weights import gather_contract, save_weights
    from clvol.render.ms import network as rnet
    w = network(5, seed=11)
    path = tmp_path / "net.npz"
    save_weights(path, w.arch, w.params, gather_contract(16, 0.6), training={"note": "test"})
    grid = generate("cloud", seed=4, resolution=(12, 16, 10))
    medium = Medium(25.0, (albedo,) * 3 if np.isscalar(albedo) else albedo, Phase.hg(0.7))
    rs = np.random.default_rng(2)
    pts = rs.uniform(grid.bbox_min, grid.bbox_max, (150, 3))
    om = unit(rs.normal(size=(150, 3)))
    light = unit((0.5, 0.8, 0.3))
    fused = rnet.NetworkSource(path, grid, medium)
    assert fused.fused is rnet.FUSED_DEFAULT
    a, ia = rnet.NetworkSource(path, grid, medium, fused=True).evaluate(pts, om, light)
    b, ib = rnet.NetworkSource(path, grid, medium, fused=False).evaluate(pts, om, light)
    assert a.shape == b.shape == ((150,) if np.isscalar(albedo) else (150, 3))
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-6 * np.abs(b).max() + 1e-30)
    assert np.abs(b).max() > 0
    assert ia["gather"] == 0.0 and ia["network"] > 0 and ib["gather"] > 0


# --------------------------------------------------------------------------- device output

LATTICE = (4, 3, 5)        # (gz, gy, gx): 60 points per plane, more than the 27 queries


@pytest.mark.parametrize("case", CASES)
def test_device_output_layout_matches_twin(case):
    """``out``/``out_index`` (the ray marcher's lattice, written on the device): channel c of
    query q lands at element out_index[q] of plane c, nothing else is written, and the values
    are the NumPy path's bits. Adversarial: the indices are a scattered, unsorted subset of a
    non-cubic lattice (so neither q, q C, the processing order nor a transposed layout lands
    them there), the plane size (60) differs from the query count (27), and the elements
    left alone hold a sentinel, not 0. Against the twin (reference/gather_mlp.py
    gather_mlp_into) within the composed-twins bound of the first test."""
    light, medium, alb, channels, albedo_input = CASES[case]
    grid, pyr, gt = scene(light, medium.density_scale)
    seed = list(CASES).index(case) + 5
    w = network(pyr.n_levels, seed=seed, albedo_input=albedo_input)
    net = MlpKernel(w)
    pts, om = queries(grid, pyr, light, seed=seed)
    n, C = len(pts), 1 if channels is None else 3
    plane = int(np.prod(LATTICE))
    rs = np.random.default_rng(seed)
    idx = rs.choice(plane, n, replace=False)
    while np.any(idx == np.arange(n)) or np.any(idx == np.arange(n) * C):   # no query at q
        idx = rs.choice(plane, n, replace=False)
    assert n != plane and not np.all(np.diff(idx) > 0)
    rt = pyr.runtime
    sentinel = np.full((C,) + LATTICE, -7.0, np.float32)
    out, flag = rt.upload(sentinel), rt.alloc(1, np.int32, zero=True)
    lw, lb = w.level_weights, w.level_bias
    kw = dict(level_weights=lw, bias=lb, channel_albedo=channels)
    ret = gather_mlp(net, pyr, gt, pts, om, gt.light_dir, medium, alb, out=out, out_index=idx,
                     nonfinite=flag, **kw)
    assert ret is out
    got = out.read()
    assert flag.read()[0] == 0
    rows = gather_mlp(net, pyr, gt, pts, om, gt.light_dir, medium, alb, **kw)   # NumPy out
    rows = rows[:, None] if rows.ndim == 1 else rows
    written = np.zeros(got.shape, bool)
    written.reshape(C, -1)[:, idx] = True
    assert np.all(got[~written] == -7.0)                               # nothing else written
    np.testing.assert_array_equal(got.reshape(C, -1)[:, idx], rows.T)  # the same bits
    lobes = tuple((l.g, l.weight) for l in medium.phase.lobes)
    want = rfused.gather_mlp_into(sentinel.copy(), idx, w.params, w.arch, pyr, gt.data, pts, om,
                                  gt.light_dir, lobes, medium.density_scale, alb, lw, lb,
                                  channel_albedo=channels)
    assert np.all(want[~written] == -7.0)
    f, c = rfused.features(pyr, gt.data, pts, om, gt.light_dir, lobes, medium.density_scale,
                           alb, lw, lb)
    steep = max(abs(g) for g, _ in lobes) > 0.9
    tols = FEATURE_TOL[:2] + ((PHASE_TOL_STEEP,) if steep else FEATURE_TOL[2:])
    for ch, a in enumerate([alb] if channels is None else channels):
        y, b = y_bound(w, f, c, a, tols)
        g_ch, w_ch = got.reshape(C, -1)[ch, idx], want.reshape(C, -1)[ch, idx]
        bound = f_bound(y, b, a)
        assert np.all(np.abs(g_ch - w_ch) <= bound), f"channel {ch}"
        # power: a layout that put query q's value at q, at q C + c, or in another plane
        # (an index or stride swap) would be seen
        assert np.ptp(w_ch) > 10 * np.median(bound)
        for other in (np.arange(n), np.arange(n) * C + ch):
            moved = want.reshape(-1)[other]
            assert np.max(np.abs(moved - w_ch)) > 10 * np.median(bound)
    if channels is not None:
        assert np.max(np.abs(want[0] - want[2])[written[0]]) > 10 * np.median(bound)


def test_device_output_inputs_checked():
    medium, pyr, gt, w, net = _checked_setup()
    rt = pyr.runtime
    pts, om = random_queries(3, 5, 0.4)
    kw = dict(level_weights=w.level_weights, bias=w.level_bias)
    args = (net, pyr, gt, pts, om, gt.light_dir, medium, 0.9)
    with pytest.raises(GatherError, match=r"1 plane\(s\)"):
        gather_mlp(*args, out=rt.alloc((3, 2, 2, 2)), out_index=np.arange(5), **kw)
    with pytest.raises(GatherError, match=r"lie in \[0, 8\)"):
        gather_mlp(*args, out=rt.alloc((1, 2, 2, 2)), out_index=np.arange(5) + 4, **kw)
    with pytest.raises(GatherError, match="5 integers"):
        gather_mlp(*args, out=rt.alloc((1, 2, 2, 2)), out_index=np.arange(4), **kw)
    with pytest.raises(GatherError, match="goes with out"):
        gather_mlp(*args, out_index=np.arange(5), **kw)


def _weights_file(tmp_path, seed=11, bias_shift=0.0):
    from clvol.features.weights import gather_contract, save_weights
    w = network(5, seed=seed)
    p = dict(w.params)
    last = f"head.{len(w.arch.head_widths)}.bias"
    p[last] = (p[last] + np.float32(bias_shift)).astype(np.float32)
    path = tmp_path / f"net{seed}_{bias_shift:g}.npz"
    save_weights(path, w.arch, p, gather_contract(16, 0.6), training={"note": "test"})
    return path


@pytest.mark.parametrize("albedo", [0.9, (0.7, 0.95, 0.8)])
def test_fill_device_equals_the_host_lattice(tmp_path, albedo):
    """NetworkSource.fill_device (the default render path: the lattice written on the device
    in the marcher's (C, gz, gy, gx) layout) holds fill's FmsLattice planes bit for bit, with and
    without an active mask (0 elsewhere), on a non-cubic lattice; into the caller's array
    when its shape fits; the unfused path through the host gives the same."""
    from clvol.render.ms import network as rnet
    path = _weights_file(tmp_path)
    grid = generate("cloud", seed=4, resolution=(12, 16, 10))
    medium = Medium(25.0, (albedo,) * 3 if np.isscalar(albedo) else albedo, Phase.hg(0.7))
    light, origin, res = unit((0.5, 0.8, 0.3)), (0.4, 0.3, 2.0), (5, 6, 7)
    src = rnet.NetworkSource(path, grid, medium)
    active = np.random.default_rng(3).random(5 * 6 * 7) < 0.6
    for act in (None, active):
        g, _ = src.fill(light, res, origin=origin, active=act)
        want = g.planes()
        lat, box, info = src.fill_device(light, res, origin=origin, active=act)
        got = lat.read()
        assert got.shape == want.shape == ((1 if np.isscalar(albedo) else 3), 7, 6, 5)
        np.testing.assert_array_equal(got, want)
        assert box == (tuple(g.bbox_min), tuple(g.bbox_max))
        assert np.ptp(want) > 0 and info["points"] == (210 if act is None else active.sum())
        if act is not None:
            assert np.all(got.reshape(got.shape[0], -1)[:, ~active] == 0)
    again, _, _ = src.fill_device(light, res, origin=(0.0, 1.0, 2.0), out=lat)
    assert again is lat
    slow = rnet.NetworkSource(path, grid, medium, fused=False)
    np.testing.assert_array_equal(slow.fill_device(light, res, origin=origin)[0].read(),
                                  src.fill_device(light, res, origin=origin)[0].read())


def test_non_finite_network_output_is_refused_on_both_paths(tmp_path):
    """No silent NaN: a network whose output overflows (y ~ 1e3: F = inf) is refused by the
    host path (isfinite on the values) and by the device path (the kernel's non-finite flag,
    the one value read back)."""
    from clvol.render.ms import network as rnet
    path = _weights_file(tmp_path, bias_shift=1000.0)
    grid = generate("cloud", seed=4, resolution=(12, 16, 10))
    medium = Medium(25.0, (0.9,) * 3, Phase.hg(0.7))
    src = rnet.NetworkSource(path, grid, medium)
    light = unit((0.5, 0.8, 0.3))
    with pytest.raises(ClvolError, match="non-finite F_ms"):
        src.fill(light, 4, origin=(0.4, 0.3, 2.0))
    with pytest.raises(ClvolError, match="non-finite F_ms"):
        src.fill_device(light, 4, origin=(0.4, 0.3, 2.0))
    ok = rnet.NetworkSource(_weights_file(tmp_path), grid, medium)
    assert np.all(np.isfinite(ok.fill_device(light, 4, origin=(0.4, 0.3, 2.0))[0].read()))
