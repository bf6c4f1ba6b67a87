"""cl/mlp.cl (via clvol/kernels/mlp.py) against reference/mlp.py (float64).

Tolerance (the parity bound of docs/network.md): |y_cl - y_ref| <= 1e-5 |y_ref| + 1e-5 * max|y_ref|. The kernel is float32
with fused multiply-adds; rounding enters each layer's sums (<= 105 terms, ~20 layers deep) at
the scale of the activations, which is the output's scale, so the error is absolute at about
that scale (measured <= 1e-6 * max|y|). Decoded F = albedo^4 (exp(y) - 1) inherits it through
dF/dy = albedo^4 exp(y). Weights are He-scaled with positive biases so ReLUs stay alive (checked).
"""
import numpy as np
import pytest

from clvol.errors import NetworkInputError
from clvol.kernels.mlp import MlpKernel, pack_params
from clvol.runtime import driver_defines_for
from clvol.features.weights import Architecture, MlpWeights, default_params, feature_contract
from reference import mlp as ref

ARCH = Architecture()
LOBES = {1: [(0.857, 1.0)], 2: [(0.8, 0.7), (-0.3, 0.3)], 3: [(0.8, 0.5), (0.3, 0.3), (-0.3, 0.2)]}


def _bound(want):
    want = np.asarray(want, np.float64)
    return 1e-5 * np.abs(want) + 1e-5 * np.abs(want).max()


def _assert_y(got, want):
    err = np.abs(np.asarray(got, np.float64) - want)
    assert np.all(np.isfinite(got))
    assert np.all(err <= _bound(want)), f"max err {err.max():.3g} (max|y| {np.abs(want).max():.3g})"


@pytest.fixture(scope="module")
def weights():
    return MlpWeights(ARCH, default_params(ARCH, np.random.default_rng(21)), feature_contract())


@pytest.fixture(scope="module")
def net(weights):
    return MlpKernel(weights)


@pytest.mark.parametrize("n_lobes", [1, 2, 3])
def test_grey_matches_reference(net, weights, n_lobes):
    """One evaluation per query with the config's albedo; 203 queries (not a multiple of 16)."""
    f, c = ref.random_inputs(203, np.random.default_rng(n_lobes), lobes=LOBES[n_lobes])
    trace = {}
    want = ref.forward(weights.params, ARCH, f, c, trace=trace)
    got = net.forward(f, c)
    assert got.shape == (203,)
    _assert_y(got, want)
    fractions = np.array(list(trace.values()))
    assert fractions.mean() > 0.4 and fractions.min() > 0.0   # parity not passed by dead units
    assert np.std(want) > 0.05 * np.abs(want).max()


@pytest.mark.parametrize("albedo", [(0.92, 0.99, 0.94), (0.8, 0.9, 1.0)])
def test_chromatic_matches_reference(net, weights, albedo):
    f, c = ref.random_inputs(77, np.random.default_rng(5), lobes=LOBES[3])
    want = ref.forward_channels(weights.params, ARCH, f, c, albedo)
    got = net.forward(f, c, channel_albedo=albedo)
    assert got.shape == (77, 3)
    _assert_y(got, want)


def test_decoded_radiance_matches_reference(net, weights):
    """F per channel; albedo 0 gives 0 and equal albedos one shared evaluation."""
    f, c = ref.random_inputs(50, np.random.default_rng(8), lobes=LOBES[2])
    alb = (0.7, 0.0, 0.7)
    got = net.forward(f, c, channel_albedo=alb, decode=True)
    want = ref.radiance(weights.params, ARCH, f, c, alb)
    y = ref.forward(weights.params, ARCH, f, ref.with_albedo(c, 0.7))
    slope = 0.7 ** 4 * np.exp(y)                        # dF/dy
    bound = 1e-5 * np.abs(want[:, 0]) + slope * 1e-5 * np.abs(y).max()
    assert np.all(np.abs(got[:, 0] - want[:, 0]) <= bound)
    assert np.all(got[:, 1] == 0.0)
    assert np.array_equal(got[:, 0], got[:, 2])
    assert np.all(got[:, 0] >= 0)


def test_grey_decode_uses_config_albedo(net, weights):
    f, c = ref.random_inputs(20, np.random.default_rng(9))
    c[3, ref.ALBEDO] = 0.0                               # an albedo-0 query decodes to F = 0
    got = net.forward(f, c, decode=True)
    y = ref.forward(weights.params, ARCH, f, c)
    want = ref.decode(y, c[:, ref.ALBEDO])
    bound = 1e-5 * want + c[:, ref.ALBEDO].astype(np.float64) ** 4 * np.exp(y) * 1e-5 * np.abs(y).max()
    assert got[3] == 0.0
    assert np.all(np.abs(got - want) <= bound)


@pytest.mark.parametrize("n", [1, 16, 17])
def test_tail_sizes_and_no_write_past_n(net, weights, n):
    """Lanes past n recompute the last query but are never stored."""
    rt = net.rt
    f, c = ref.random_inputs(n, np.random.default_rng(n))
    sentinel = np.full(n + 40, -7.0, np.float32)
    out = rt.upload(sentinel)
    evt = net.enqueue(rt.upload(f), rt.upload(c), n, out)
    got = rt.from_device(out, sentinel.shape, wait_for=[evt])
    _assert_y(got[:n], ref.forward(weights.params, ARCH, f, c))
    assert np.all(got[n:] == -7.0)


def test_fed_by_device_buffers(net, weights):
    """The render path: gather buffers in, device buffer out, no host copies of features."""
    rt = net.rt
    f, c = ref.random_inputs(40, np.random.default_rng(2))
    got = net.forward(rt.upload(f), rt.upload(c), channel_albedo=(0.5, 0.6, 0.7), n=40)
    _assert_y(got, ref.forward_channels(weights.params, ARCH, f, c, (0.5, 0.6, 0.7)))


def test_load_paths_agree(weights, net):
    """Per-lane feature loads (any compiler; what Oclgrind checks) and the transposed row
    loads (PoCL) read the same values: bit-identical outputs."""
    lanes = MlpKernel(weights, defines={"MLP_TRANSPOSE16": None, "MLP_PREFETCH": None})
    f, c = ref.random_inputs(33, np.random.default_rng(4), lobes=LOBES[2])
    a = lanes.forward(f, c)
    _assert_y(a, ref.forward(weights.params, ARCH, f, c))
    if net.rt.is_pocl:
        assert np.array_equal(a, net.forward(f, c))


@pytest.mark.parametrize("form", ["array", "rusticl"])
def test_dense_forms_agree(weights, net, form):
    """The dense layers' array form (-D MLP_DENSE_ARRAY) and rusticl's whole rule (clvol/runtime.py
    DRIVER_RULES: the array form with the multiply-adds written a * b + c, -D MLP_MULADD) sum
    the same terms in the same order as the named-accumulator form: bit-identical outputs
    where the compiler fuses a * b + c (PoCL does; compared where the default form builds in
    reasonable time, i.e. off rusticl)."""
    defines = {"MLP_DENSE_ARRAY": 1} if form == "array" else driver_defines_for("rusticl")
    assert defines.get("MLP_DENSE_ARRAY")
    arr = MlpKernel(weights, defines=defines)
    f, c = ref.random_inputs(37, np.random.default_rng(5), lobes=LOBES[1])
    a = arr.forward(f, c)
    _assert_y(a, ref.forward(weights.params, ARCH, f, c))
    if not net.rt.driver_defines:
        assert np.array_equal(a, net.forward(f, c))
        alb = (0.9, 0.95, 1.0)
        assert np.array_equal(arr.forward(f, c, channel_albedo=alb, decode=True),
                              net.forward(f, c, channel_albedo=alb, decode=True))


def test_packed_layout(weights):
    """Normalisation first, then W^T padded to 8 outputs and the bias, in execution order."""
    packed = pack_params(weights)
    p = weights.params
    np.testing.assert_array_equal(packed[:3], p["feature_shift"])
    np.testing.assert_array_equal(packed[15:24], p["config_scale"])
    first = ARCH.linear_layers()[0]
    assert first == ("branches.density.diffuse.se_a.0", 8, ARCH.se_hidden)
    w = packed[24:24 + 8 * 8].reshape(8, 8)
    np.testing.assert_array_equal(w, p["branches.density.diffuse.se_a.0.weight"].T)
    expected = 24 + sum(i * ((o + 7) // 8 * 8) + (o + 7) // 8 * 8 for _, i, o in ARCH.linear_layers())
    assert packed.size == expected


def test_bad_inputs(net):
    f, c = ref.random_inputs(4, np.random.default_rng(0))
    with pytest.raises(NetworkInputError, match=r"features \(4, 3, 265\)"):
        net.forward(f[:, :, :-1], c)
    with pytest.raises(NetworkInputError, match=r"config \(4, 8\)"):
        net.forward(f, c[:, :-1])
    with pytest.raises(NetworkInputError, match=r"channel_albedo must be 3 values in \[0, 1\]"):
        net.forward(f, c, channel_albedo=(0.5, 1.5, 0.5))
    assert net.forward(f[:0], c[:0]).shape == (0,)


TINY = Architecture(layer_counts=(3, 2, 5, 2, 3), n_diffuse_layers=3, n_levels=3,
                    se_hidden=2, module_width=3, head_widths=(4,))


@pytest.mark.oclgrind
@pytest.mark.rusticl
def test_tiny_architecture():
    """A tiny network (14 template points, 3 queries): runs under Oclgrind in seconds and
    exercises both load paths (two transposed 16-blocks, then per-lane loads for the last 10)."""
    w = MlpWeights(TINY, default_params(TINY, np.random.default_rng(1)), {})
    f, c = ref.random_inputs(3, np.random.default_rng(3), arch=TINY, lobes=LOBES[3])
    net = MlpKernel(w)
    _assert_y(net.forward(f, c), ref.forward(w.params, TINY, f, c))
    got = net.forward(f, c, channel_albedo=(0.0, 0.6, 0.9), decode=True)
    want = ref.radiance(w.params, TINY, f, c, (0.0, 0.6, 0.9))
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6 * np.abs(want).max())


def test_matches_torch(weights):
    """OpenCL vs torch directly (test_model.py holds torch to the same reference)."""
    torch = pytest.importorskip("torch")
    from clvol.training.model import Model
    m = Model(ARCH)
    m.load_numpy_params(weights.params)
    f, c = ref.random_inputs(64, np.random.default_rng(12), lobes=LOBES[1])
    with torch.no_grad():
        want = m.eval()(torch.from_numpy(f), torch.from_numpy(c)).numpy().astype(np.float64)
    got = MlpKernel(weights).forward(f, c)
    # two float32 computations: twice the one-sided bound
    assert np.all(np.abs(got - want) <= 2 * _bound(want))


@pytest.mark.parametrize("albedo", [(0.8, 0.8, 0.8), (0.0, 0.6, 0.9)])
def test_radiance_grey_and_chromatic(net, weights, albedo):
    """F [N][3] as reference.mlp.radiance: grey is one evaluation broadcast to 3 channels."""
    f, c = ref.random_inputs(21, np.random.default_rng(6), lobes=LOBES[1])
    got = net.radiance(f, c, albedo)
    want = ref.radiance(weights.params, ARCH, f, c, albedo)
    assert got.shape == (21, 3)
    for ch, a in enumerate(albedo):
        if a == 0:
            assert np.all(got[:, ch] == 0)
            continue
        y = ref.forward(weights.params, ARCH, f, ref.with_albedo(c, a))
        bound = 1e-5 * want[:, ch] + a ** 4 * np.exp(y) * 1e-5 * np.abs(y).max()
        assert np.all(np.abs(got[:, ch] - want[:, ch]) <= bound)


# --------------------------------------------------------------------------- gather features

PHASES = {1: {"type": "hg", "g": 0.857},
          2: {"type": "mhg", "lobes": [{"g": 0.8, "weight": 0.7}, {"g": -0.3, "weight": 0.3}]},
          3: {"type": "mhg", "lobes": [{"g": 0.8, "weight": 0.5}, {"g": 0.3, "weight": 0.3},
                                       {"g": -0.3, "weight": 0.2}]}}


@pytest.fixture(scope="module")
def cloud():
    from clvol.kernels.pyramid import build_pyramid
    from clvol.kernels.transmittance import graded_transmittance
    from clvol.volume.generators import generate
    grid = generate("cloud", seed=2, resolution=32)
    pyr = build_pyramid(grid, base_resolution=64)
    l = np.array([0.6, 0.9, 0.3]) / np.linalg.norm([0.6, 0.9, 0.3])
    graded = graded_transmittance(pyr, 20.0, l)
    rng = np.random.default_rng(0)
    pts = rng.uniform(grid.bbox_min * 0.8, grid.bbox_max * 0.8, (90, 3))
    om = rng.normal(size=(90, 3))
    om /= np.linalg.norm(om, axis=1, keepdims=True)
    return pyr, graded, l, pts, om


@pytest.mark.parametrize("n_lobes,albedo", [(1, (0.95, 0.95, 0.95)), (2, (0.999, 0.999, 0.999)),
                                             (3, (0.99, 0.85, 0.75))])
def test_parity_on_gathered_features(cloud, n_lobes, albedo):
    """Features of a real scene (a 32^3 cloud on a 64^3 pyramid, render mode with the level
    weights from the weight file), fed to the kernel as the gather's device buffers."""
    from clvol.kernels.gather import gather
    from clvol.scene import scene_from_dict
    pyr, graded, l, pts, om = cloud
    arch = Architecture(n_levels=pyr.n_levels)
    w = MlpWeights(arch, default_params(arch, np.random.default_rng(n_lobes)), feature_contract())
    medium = scene_from_dict({
        "volume": {"generator": "cloud", "resolution": 8},
        "medium": {"density_scale": 20.0, "albedo": list(albedo), "phase": PHASES[n_lobes]},
        "light": {"direction": list(l)},
        "camera": {"origin": [0, 0, 3], "target": [0, 0, 0], "up": [0, 1, 0], "fov_y": 30,
                   "width": 4, "height": 4}}, "<test>").medium
    kw = dict(mode="render", level_weights=w.level_weights, bias=w.level_bias)
    g = gather(pyr, graded, pts, om, l, medium, albedo[0], **kw)
    assert np.ptp(g["features"][:, 0]) > 0.1 and np.ptp(g["features"][:, 2]) > 0.1  # not empty
    net = MlpKernel(w)
    bufs = gather(pyr, graded, pts, om, l, medium, albedo[0], as_buffers=True, **kw)
    if len(set(albedo)) == 1:
        got = net.forward(bufs["features"], bufs["config"], n=bufs["n"])
        want = ref.forward(w.params, arch, g["features"], g["config"])
    else:
        got = net.forward(bufs["features"], bufs["config"], channel_albedo=albedo, n=bufs["n"])
        want = ref.forward_channels(w.params, arch, g["features"], g["config"], albedo)
    _assert_y(got, want)


@pytest.mark.parametrize("albedo", [None, (1.0, 0.999, 0.9)])
def test_log1m_albedo_input_matches_reference(albedo):
    """-D MLP_ALBEDO_LOG1M (Architecture(albedo_input="log1m")): the kernel reads the albedo as
    -log(1 - a + 1e-4), as the reference does; albedo 1 is finite."""
    arch = Architecture(albedo_input="log1m")
    w = MlpWeights(arch, default_params(arch, np.random.default_rng(23)), feature_contract())
    f, c = ref.random_inputs(45, np.random.default_rng(9), lobes=LOBES[2])
    c[::3, 7] = 1.0
    if albedo is None:
        want = ref.forward(w.params, arch, f, c)
        got = MlpKernel(w).forward(f, c)
    else:
        want = ref.forward_channels(w.params, arch, f, c, albedo)
        got = MlpKernel(w).forward(f, c, channel_albedo=albedo)
    _assert_y(got, want)
    lin = ref.forward(w.params, ARCH, f, c)       # the same weights read linearly differ
    assert not np.allclose(lin, ref.forward(w.params, arch, f, c))


def test_twin_constants_and_slicing_agree_with_the_weights_module():
    """reference/mlp.py writes the encoding's gamma, the template order, the albedo input's
    offset, the feature and config layout, the point and level counts and the layer slicing
    itself (a twin shares no code with what it checks); here the two statements are held
    equal."""
    from clvol.features import layout, weights
    assert (ref.GAMMA, ref.TEMPLATES, ref.TYPES, ref.ALBEDO_EPS) == \
        (weights.GAMMA, weights.TEMPLATES, weights.TYPES, weights.ALBEDO_EPS)
    assert (ref.TYPES, ref.CONFIG_FIELDS, ref.N_POINTS, ref.N_LEVELS) == \
        (layout.FEATURE_TYPES, layout.CONFIG_FIELDS, layout.N_POINTS, layout.N_LEVELS)
    for arch in (weights.Architecture(), weights.Architecture(layer_counts=(3, 5, 2, 4),
                                                              n_diffuse_layers=3)):
        assert ref.layer_slices(arch) == arch.layer_slices()
        for t in ref.TEMPLATES:
            assert ref.template_layer_slices(arch, t) == arch.template_layer_slices(t)
