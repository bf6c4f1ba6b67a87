"""Weight files (clvol/features/weights.py): round trip, counts, and every kind of bad file refused with a
message naming the file and the field. NumPy only (no torch, no OpenCL)."""
import json
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from clvol.errors import ClvolError
from clvol.features import layout
from clvol.features.weights import (FORMAT_VERSION, META_KEY, Architecture, WeightsError,
                                    default_params, feature_contract, gather_contract,
                                    load_weights, params_digest, read_meta, save_weights)

ARCH = Architecture()


@pytest.fixture(scope="module")
def params():
    return default_params(ARCH, np.random.default_rng(3))


@pytest.fixture
def saved(tmp_path, params):
    return save_weights(tmp_path / "net.npz", ARCH, params, gather_contract(), {"note": "test"})


def _rewrite(path, meta=None, arrays=None, drop=()):
    """Write a modified copy of a weight file (meta dict and/or arrays replaced)."""
    with np.load(path, allow_pickle=False) as z:
        data = {k: z[k] for k in z.files if k not in drop}
    if meta is not None:
        data[META_KEY] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    data.update(arrays or {})
    out = path.with_name("bad.npz")
    np.savez(out, **data)
    return out


def test_counts_within_budget():
    """The network's budget (docs/network.md): at most ~100K parameters and ~100K multiply-adds per evaluation."""
    assert ARCH.n_params() <= 100_000
    assert ARCH.n_macs()["total"] <= 100_000
    # dense multiply-adds equal the linear weights: every weight is used once per evaluation
    n_linear_weights = sum(int(np.prod(s)) for n, s in ARCH.tensor_shapes().items()
                           if n.endswith(".weight"))
    assert ARCH.n_macs()["dense"] == n_linear_weights


def test_architecture_follows_layout():
    assert ARCH.layer_counts == layout.LAYER_COUNTS
    assert ARCH.n_points == layout.N_POINTS
    assert ARCH.n_levels == layout.N_LEVELS
    shapes = ARCH.tensor_shapes()
    # 6 modules: 8 diffuse excitations each, 7 FC-1/FC-2 pairs; 4 / 3 for highlight
    for t in ("density", "transmittance", "phase"):
        assert sum(f"branches.{t}.diffuse.se_b.{k}.weight" in shapes for k in range(9)) == 8
        assert sum(f"branches.{t}.diffuse.fc1.{k}.weight" in shapes for k in range(9)) == 7
        assert sum(f"branches.{t}.highlight.se_b.{k}.weight" in shapes for k in range(9)) == 4
        # FC-1 of diffuse layer 2 maps [h_2, config] (12 + 9) to layer 3's 16 points
        assert shapes[f"branches.{t}.diffuse.fc1.2.weight"] == (16, 21)
        assert shapes[f"branches.{t}.diffuse.se_a.0.weight"] == (ARCH.se_hidden, 8)


def test_round_trip(saved, params):
    w = load_weights(saved, expect_contract=gather_contract())
    assert w.arch == ARCH
    assert set(w.params) == set(params)
    for k in params:
        np.testing.assert_array_equal(w.params[k], params[k])
        assert w.params[k].dtype == np.float32
    assert params_digest(w.params) == params_digest(params)
    # the contract carries the render-time level weights and the normalisation
    assert w.contract["level_weights"] == [float(v) for v in params["level_weights"]]
    assert w.contract["normalisation"]["config_scale"][-1] == pytest.approx(1 / np.pi)
    assert w.meta["training"] == {"note": "test"}
    assert w.meta["counts"]["params"] == ARCH.n_params()


def test_loads_without_pickle_or_torch(saved):
    with np.load(saved, allow_pickle=False) as z:
        meta = json.loads(z[META_KEY].tobytes())
    assert meta["format"] == "clvol-mlp" and meta["format_version"] == FORMAT_VERSION
    assert read_meta(saved)["architecture"]["layer_counts"] == list(layout.LAYER_COUNTS)


def test_other_version_refused(saved):
    meta = read_meta(saved)
    meta["format_version"] = FORMAT_VERSION + 1
    with pytest.raises(WeightsError, match=r"bad\.npz: \[format_version\] is 2; .*version 1 only"):
        load_weights(_rewrite(saved, meta))


def test_other_format_refused(saved):
    meta = read_meta(saved)
    meta["format"] = "something-else"
    with pytest.raises(WeightsError, match=r"\[format\] is 'something-else'"):
        load_weights(_rewrite(saved, meta))


def test_wrong_shape_refused(saved, params):
    name = "branches.phase.highlight.fc2.1.weight"
    bad = _rewrite(saved, arrays={name: np.zeros((16, 15), np.float32)})
    with pytest.raises(WeightsError, match=rf"\[{name}\] has shape \(16, 15\), the architecture needs \(16, 16\)"):
        load_weights(bad)


def test_architecture_edit_without_tensors_refused(saved):
    meta = read_meta(saved)
    meta["architecture"]["module_width"] = 16
    with pytest.raises(WeightsError, match=r"has shape .* needs"):
        load_weights(_rewrite(saved, meta))


def test_missing_and_extra_tensors_refused(saved):
    with pytest.raises(WeightsError, match=r"missing tensor\(s\) head\.0\.bias"):
        load_weights(_rewrite(saved, drop=("head.0.bias",)))
    with pytest.raises(WeightsError, match=r"unexpected tensor\(s\) extra"):
        load_weights(_rewrite(saved, arrays={"extra": np.zeros(3, np.float32)}))


def test_non_finite_refused(saved, params):
    w = params["merges.density.weight"].copy()
    w[3, 4] = np.nan
    with pytest.raises(WeightsError, match=r"\[merges\.density\.weight\] holds 1 non-finite"):
        load_weights(_rewrite(saved, arrays={"merges.density.weight": w}))


def test_layout_contract_mismatch_refused(saved):
    meta = read_meta(saved)
    meta["contract"]["config_fields"] = list(reversed(layout.CONFIG_FIELDS))
    with pytest.raises(WeightsError, match=r"feature contract mismatch: \[contract\.config_fields\]"):
        load_weights(_rewrite(saved, meta))
    meta = read_meta(saved)
    meta["contract"]["layout_version"] = layout.LAYOUT_VERSION + 1
    with pytest.raises(WeightsError, match=r"\[contract\.layout_version\] is 2 in the file"):
        load_weights(_rewrite(saved, meta))


@pytest.mark.parametrize("field,value,pattern", [
    ("lambda", 0.5, r"\[contract\.lambda\] is 0\.6 in the file, the gather produces 0\.5"),
    ("template_hash", "0123456789abcdef", r"\[contract\.template_hash\] is '[0-9a-f]+' in the file"),
    ("base_resolution", 128, r"\[contract\.base_resolution\] is 256 in the file, the gather produces 128"),
])
def test_gather_contract_mismatch_refused(saved, field, value, pattern):
    want = gather_contract()
    want[field] = value
    with pytest.raises(WeightsError, match=pattern):
        load_weights(saved, expect_contract=want)


def test_level_map_mismatch_refused(tmp_path, params):
    c = feature_contract(template_hash="abc", level_map={"diffuse": [0] * 8, "highlight_spacing": [0.1] * 4})
    path = save_weights(tmp_path / "n.npz", ARCH, params, c)
    want = dict(c, level_map={"diffuse": [1] * 8, "highlight_spacing": [0.1] * 4})
    with pytest.raises(WeightsError, match=r"\[contract\.level_map\]"):
        load_weights(path, expect_contract=want)
    assert load_weights(path, expect_contract=c).contract["template_hash"] == "abc"


def test_not_a_weight_file(tmp_path):
    with pytest.raises(WeightsError, match=r"no such weight file"):
        load_weights(tmp_path / "absent.npz")
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip file")
    with pytest.raises(WeightsError, match=r"junk\.npz: not a clvol weight file"):
        load_weights(junk)
    plain = tmp_path / "plain.npz"
    np.savez(plain, a=np.zeros(3))
    with pytest.raises(WeightsError, match=r"no __meta__ entry"):
        load_weights(plain)
    broken = tmp_path / "broken.npz"
    np.savez(broken, **{META_KEY: np.frombuffer(b"{not json", np.uint8)})
    with pytest.raises(WeightsError, match=r"\[__meta__\] is not valid JSON"):
        load_weights(broken)
    assert issubclass(WeightsError, ClvolError)


def test_zero_scale_refused(saved, params):
    with pytest.raises(WeightsError, match=r"contain 0"):
        load_weights(_rewrite(saved, arrays={"feature_scale": np.array([1, 0, 1], np.float32)}))


def test_save_is_atomic_and_checks(tmp_path, params):
    bad = dict(params)
    bad["head.0.weight"] = bad["head.0.weight"][:, :-1]
    with pytest.raises(WeightsError, match=r"\[head\.0\.weight\] has shape"):
        save_weights(tmp_path / "x.npz", ARCH, bad, feature_contract())
    assert not list(tmp_path.iterdir())   # nothing half-written
    p = save_weights(tmp_path / "x.npz", ARCH, params, feature_contract())
    assert zipfile.is_zipfile(p) and sorted(q.name for q in tmp_path.iterdir()) == ["x.npz"]


def test_loader_and_forward_need_no_torch(saved):
    """Rendering never imports torch: load a weight file and run the NumPy forward in a process
    where importing torch fails."""
    code = (
        "import sys; sys.modules['torch'] = None\n"
        "import numpy as np\n"
        "from clvol.features.weights import load_weights\n"
        "import clvol.kernels.mlp\n"
        "from reference import mlp\n"
        f"w = load_weights({str(saved)!r})\n"
        "f, c = mlp.random_inputs(3, np.random.default_rng(0))\n"
        "y = mlp.forward(w.params, w.arch, f, c)\n"
        "assert y.shape == (3,) and np.all(np.isfinite(y))\n"
        "assert 'torch' not in [m.split('.')[0] for m in sys.modules if sys.modules[m] is not None]\n"
        "print('ok')\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          cwd=str(Path(__file__).resolve().parents[1]))
    assert proc.returncode == 0 and proc.stdout.strip() == "ok", proc.stderr[-2000:]


def test_level_count_must_match_contract(tmp_path):
    arch = Architecture(n_levels=7)                       # a 64^3 pyramid
    p = default_params(arch)
    with pytest.raises(WeightsError, match=r"7 transmittance levels, the contract 9 \(base resolution 256\)"):
        save_weights(tmp_path / "x.npz", arch, p, gather_contract(256))
    w = load_weights(save_weights(tmp_path / "y.npz", arch, p, gather_contract(64)),
                     expect_contract=gather_contract(64))
    assert w.arch.n_levels == 7 and len(w.contract["level_weights"]) == 7


DOMAIN = {"albedo": [0.3, 0.999], "g": [-0.9, 0.99], "max_lobes": 3,
          "optical_thickness": [1.0, 1000.0], "resolution": [32, 128]}


def test_domain_round_trip_and_default(tmp_path, params, saved):
    from clvol.features.weights import DEFAULT_DOMAIN, weights_domain
    p = save_weights(tmp_path / "d.npz", ARCH, params, gather_contract(), domain=DOMAIN)
    w = load_weights(p, expect_contract=gather_contract())
    assert w.meta["domain"] == DOMAIN and weights_domain(w.meta) == DOMAIN
    # a file written without a domain reads as the first shipped model's
    assert "domain" not in read_meta(saved)
    assert weights_domain(read_meta(saved)) == DEFAULT_DOMAIN == {
        "albedo": [0.8, 0.999], "g": [0.0, 0.9], "max_lobes": 3}


@pytest.mark.parametrize("change, pattern", [
    ({"extra": [0, 1]}, r"exactly the keys"),
    ({"g": [0.9, -0.9]}, r"\[domain\.g\].*low <= high"),
    ({"albedo": [0.3]}, r"\[domain\.albedo\].*\[low, high\]"),
    ({"max_lobes": 4}, r"\[domain\.max_lobes\]"),
    ({"optical_thickness": [1.0, float("inf")]}, r"\[domain\.optical_thickness\]"),
])
def test_bad_domain_refused_on_save_and_load(tmp_path, params, saved, change, pattern):
    bad = dict(DOMAIN, **change)
    with pytest.raises(WeightsError, match=pattern):
        save_weights(tmp_path / "x.npz", ARCH, params, gather_contract(), domain=bad)
    assert not (tmp_path / "x.npz").exists()
    if "optical_thickness" not in change:     # (strict JSON has no inf to write into a file)
        meta = dict(read_meta(saved), domain=bad)
        with pytest.raises(WeightsError, match=pattern):
            load_weights(_rewrite(saved, meta=meta))
