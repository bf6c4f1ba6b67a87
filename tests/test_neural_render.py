"""The network as the ray marcher's multiple-scattering source (clvol/render/ms/network.py, ms="network").

A tiny random-weight network (the real architecture, He-scaled weights, last layer scaled down so
y stays O(1)) on a 16^3 cloud with a 16^3 pyramid: training is not the point here, the wiring is
(gather in render mode with the file's level weights -> OpenCL MLP -> F_ms lattice in [z][y][x]
order -> march). Tolerances:
- lattice vs the float64 NumPy reference (reference/mlp.py) on the same gathered features:
  docs/network.md's parity bound in y, |y - y_ref| <= 1e-5 |y_ref| + 1e-5 max|y_ref|, carried to
  F = a^4 (e^y - 1) as |dF| <= a^4 e^y |dy| (x 2 for the float32 decode);
- grey shortcut (one evaluation, one plane) vs the 3-channel path: the same network on the same
  features, built as different kernels (1 vs 3 channels), so equal within float32 rounding of
  the decode (2e-6 relative), and images within 2e-6 relative (docs/raymarch.md's bound for
  shortcut vs general kernel).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from clvol.errors import ClvolError, WeightsError
from clvol.features.weights import Architecture, default_params, gather_contract, save_weights
from clvol.scene import scene_from_dict
from scene_toml import SMALL_CLOUD, write_scene

BASE = 16


def _params(seed=0):
    arch = Architecture(n_levels=int(np.log2(BASE)) + 1)
    p = default_params(arch, np.random.default_rng(seed))
    last = f"head.{len(arch.head_widths)}"
    p[f"{last}.weight"] = (p[f"{last}.weight"] * 0.05).astype(np.float32)
    p[f"{last}.bias"] = np.full_like(p[f"{last}.bias"], 0.3)
    p["level_weights"] = np.linspace(0.05, 0.3, arch.n_levels).astype(np.float32)
    p["level_bias"] = np.array([0.02], np.float32)
    return arch, p


@pytest.fixture(scope="module")
def weights_file(tmp_path_factory):
    arch, p = _params()
    path = tmp_path_factory.mktemp("net") / "tiny.npz"
    save_weights(path, arch, p, gather_contract(BASE, 0.6), training={"note": "random, tests"})
    return path


def _scene(albedo=0.95, lobes=None):
    phase = ({"type": "hg", "g": 0.857} if lobes is None else
             {"type": "mhg", "lobes": [{"g": g, "weight": w} for g, w in lobes]})
    return scene_from_dict({
        "volume": {"generator": "cloud", "seed": 4, "resolution": 16},
        "medium": {"density_scale": 30.0, "albedo": albedo, "phase": phase},
        "light": {"direction": [0.5, 0.8, 0.3], "irradiance": [1.0, 0.9, 0.8]},
        "camera": {"origin": [0.3, 0.4, 2.2], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0],
                   "fov_y": 35.0, "width": 16, "height": 12},
    }, "<neural test>")


@pytest.mark.parametrize("albedo,lobes", [(0.95, None), ([0.9, 0.95, 0.99], [(0.7, 0.6), (-0.3, 0.4)])])
def test_network_source_renders(weights_file, albedo, lobes):
    from render_helpers import render_raymarch
    res = render_raymarch(_scene(albedo, lobes), ms="network", weights=str(weights_file),
                          ms_resolution=8)
    for name in ("total", "single", "multiple"):
        img = res.layers[name]
        assert np.all(np.isfinite(img)) and np.all(img >= 0), name
    assert res.layers["multiple"].max() > 0          # the network's source reaches the image
    h = res.header
    assert "network-filled F_ms lattice 8x8x8" in h["simulated"]
    # fused (the default): the gather's time is the network's, with no stage of its own
    # (before, seconds.gather read 0.0 in every header)
    assert h["raymarch.network_fused"] is True and "seconds.gather" not in h
    for k in ("seconds.network", "seconds.march"):
        assert h[k] > 0
    grey = not isinstance(albedo, list)
    assert h["raymarch.network_evaluations_per_point"] == (1 if grey else 3)
    assert ("one per lattice point" in h["skipped"]) == grey


def test_grey_shortcut_equals_three_channels(weights_file):
    from clvol.render.ms.network import NetworkSource
    from render_helpers import render_raymarch
    sc = _scene(0.95)
    grid = sc.volume.load()
    src = NetworkSource(weights_file, grid, sc.medium)
    g1, i1 = src.fill(sc.light.direction, 8, grey_shortcut=True, origin=sc.camera.origin)
    g3, i3 = src.fill(sc.light.direction, 8, grey_shortcut=False, origin=sc.camera.origin)
    assert g1.values.shape == (8, 8, 8) and g3.values.shape == (8, 8, 8, 3)
    assert i1["evaluations"] == 1
    for c in range(3):
        np.testing.assert_allclose(g3.values[..., c], g1.values, rtol=2e-6, atol=0)
    a = render_raymarch(sc, ms="network", weights=str(weights_file), ms_resolution=8)
    b = render_raymarch(sc, ms="network", weights=str(weights_file), ms_resolution=8,
                        shortcuts=False)
    assert a.header["raymarch.channels_marched"] == 1 and b.header["raymarch.channels_marched"] == 3
    for name in ("total", "multiple"):
        scale = float(np.abs(b.layers[name]).max())
        np.testing.assert_allclose(a.layers[name], b.layers[name], rtol=0, atol=2e-6 * scale)


def test_lattice_matches_numpy_reference(weights_file):
    """Each lattice value F[k][j][i] equals the NumPy network evaluated on the gathered features
    of lattice point (i, j, k) (voxel centre, omega toward the camera): checks the point order,
    the baked level weights and the channel handling on an anisotropic lattice (5 x 6 x 7)."""
    import reference.mlp as ref
    from clvol.kernels.gather import gather
    from clvol.features.weights import load_weights
    from clvol.render.ms.network import NetworkSource
    from clvol.render.ms.lattice import ms_lattice
    sc = _scene([0.9, 0.95, 0.0], [(0.7, 0.6), (-0.3, 0.4)])
    grid = sc.volume.load()
    src = NetworkSource(weights_file, grid, sc.medium)
    msg, info = src.fill(sc.light.direction, (5, 6, 7), origin=sc.camera.origin)
    assert msg.values.shape == (7, 6, 5, 3) and info["evaluations"] == 2
    res, lo, hi, pts, om = ms_lattice(sc, (5, 6, 7), grid.bbox_min, grid.bbox_max)
    w = load_weights(weights_file)
    l = np.asarray(sc.light.direction)
    g = gather(src.pyramid, src.graded(l), pts, om, l, sc.medium, 0.9, mode="render",
               level_weights=w.level_weights, bias=w.level_bias)
    got = msg.values.reshape(-1, 3).astype(np.float64)
    assert np.all(got[:, 2] == 0)                     # albedo-0 channel: no evaluation, F = 0
    for c, a in ((0, 0.9), (1, 0.95)):
        y_ref = ref.forward(w.params, w.arch, g["features"], ref.with_albedo(g["config"], a))
        F_ref = ref.decode(y_ref, a)
        dy = 1e-5 * np.abs(y_ref) + 1e-5 * np.abs(y_ref).max()
        bound = 2 * a ** 4 * np.exp(y_ref) * dy + 1e-7 * np.abs(F_ref)
        err = np.abs(got[:, c] - F_ref)
        assert np.all(err <= bound), f"channel {c}: worst err/bound {np.max(err / bound):.3g}"
        assert F_ref.max() > 0 and np.std(F_ref) > 0     # a non-trivial comparison


def test_mismatched_weights_refused(weights_file, tmp_path):
    from render_helpers import render_raymarch
    arch, p = _params()
    bad = gather_contract(BASE, 0.6)
    bad["template_hash"] = "0" * 64
    path = tmp_path / "other_templates.npz"
    save_weights(path, arch, p, bad)
    with pytest.raises(WeightsError, match=r"other_templates.npz.*\[contract.template_hash\]"):
        render_raymarch(_scene(), ms="network", weights=str(path), ms_resolution=4)
    levels = gather_contract(BASE, 0.6)
    levels["level_map"] = dict(levels["level_map"], diffuse=[0] * 8)
    save_weights(path, arch, p, levels)
    with pytest.raises(WeightsError, match=r"\[contract.level_map\]"):
        render_raymarch(_scene(), ms="network", weights=str(path), ms_resolution=4)
    with pytest.raises(ClvolError, match="ms_resolution = 1"):
        render_raymarch(_scene(), ms="network", weights=str(weights_file), ms_resolution=1)
    with pytest.raises(WeightsError, match="no such weight file"):
        render_raymarch(_scene(), ms="network", weights=str(tmp_path / "missing.npz"))


def test_cli_network_source(weights_file, tmp_path):
    """clvol render --ms network --weights FILE writes an EXR whose header has the time split."""
    from clvol.cli import main
    from clvol.image import read_exr
    scene_path = write_scene(tmp_path / "s.toml", **SMALL_CLOUD)
    out = tmp_path / "o.exr"
    rc = main(["render", str(scene_path), "--method", "raymarch", "--ms", "network",
               "--weights", str(weights_file), "--ms-resolution", "6", "-o", str(out)])
    assert rc == 0
    img = read_exr(out)
    assert np.all(np.isfinite(img.layers["total"]))
    assert float(img.header["seconds.network"]) >= 0 and "network" in img.header["simulated"]
    # No --weights: the shipped model (clvol/data/weights/full_albedo.npz) is used.
    assert main(["render", str(scene_path), "--method", "raymarch", "--ms", "network",
                 "--ms-resolution", "6", "-o", str(out)]) == 0
    assert "network" in read_exr(out).header["simulated"]
    # A weight file that does not exist: a clear error, exit 2.
    assert main(["render", str(scene_path), "--method", "raymarch", "--ms", "network",
                 "--weights", str(tmp_path / "missing.npz"), "-o", str(out)]) == 2


@pytest.mark.parametrize("name,steps", [("cloud_small", 16000), ("core_domain", 30000),
                                        ("full_albedo", 16000)])
def test_shipped_weights_match_this_gather(name, steps):
    """Every shipped weight file must load against the packaged templates and layout (a
    template or layout change without retraining fails here, not at render time)."""
    from pathlib import Path
    from clvol.render.ms.network import load_network_weights
    path = Path(__file__).resolve().parents[1] / "clvol" / "data" / "weights" / f"{name}.npz"
    w = load_network_weights(path)
    assert w.contract["base_resolution"] == 64 and w.arch.n_levels == 7
    assert np.all(np.isfinite(w.level_weights)) and w.meta["training"]["step"] == steps


def test_default_model_is_full_albedo_with_the_whole_domain():
    """The default model covers what the quality benchmark tests: back-scattering (g -0.9),
    albedo 0.4 and albedo 1 are inside its recorded domain, so the renderer uses it there
    without a warning; it reads the albedo as -log(1 - a + 1e-4) (docs/network.md)."""
    from clvol.features.weights import weights_domain
    from clvol.render.ms.network import load_network_weights, shipped_weights
    assert shipped_weights().name == "full_albedo.npz"
    w = load_network_weights(shipped_weights())
    d = weights_domain(w.meta)
    assert d["g"] == [-0.9, 0.99] and d["albedo"] == [0.3, 1.0] and d["max_lobes"] == 3
    assert d["optical_thickness"] == [1.0, 1000.0]
    assert w.arch.albedo_input == "log1m"


def test_shipped_domain_model_matches_this_gather_and_records_its_domain():
    """clvol/data/weights/domain_small.npz loads against the packaged templates and layout, and
    its meta["domain"] is the whole-domain data sets' (exactly the keys the renderer reads)."""
    from pathlib import Path
    from clvol.features.weights import DOMAIN_KEYS, weights_domain
    from clvol.render.ms.network import load_network_weights
    path = Path(__file__).resolve().parents[1] / "clvol" / "data" / "weights" / "domain_small.npz"
    w = load_network_weights(path)
    assert w.contract["base_resolution"] == 64 and w.arch.n_levels == 7
    assert tuple(sorted(w.meta["domain"])) == tuple(sorted(DOMAIN_KEYS))
    assert weights_domain(w.meta) == {"albedo": [0.3, 0.999], "g": [-0.9, 0.99], "max_lobes": 3,
                                      "optical_thickness": [1.0, 1000.0], "resolution": [32, 128]}
    assert w.meta["training"]["step"] == 12000


def test_network_source_is_registered_whatever_is_imported_first():
    """The Renderer and the CLI's --ms choices read clvol/render/ms/__init__.py; in a fresh process
    where nothing imported clvol/render/ms/network.py yet, "network" (and its options, e.g.
    ms_resolution) must be there all the same (it once was not, and ms_resolution was dropped)."""
    import os
    import subprocess
    import sys
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    code = ("from clvol.render.renderer import Renderer\n"
            "from clvol.render.ms import source_classes\n"
            "assert 'network' in source_classes()\n"
            "from clvol.scene import scene_from_dict\n"
            "sc = scene_from_dict({'volume': {'generator': 'sphere', 'seed': 1, 'resolution': 12},\n"
            "    'medium': {'density_scale': 20.0, 'albedo': 0.9, 'phase': {'type': 'hg', 'g': 0.5}},\n"
            "    'light': {'direction': [0.5, 0.8, 0.3], 'irradiance': [1, 1, 1]},\n"
            "    'camera': {'origin': [0, 0, 2.5], 'target': [0, 0, 0], 'up': [0, 1, 0],\n"
            "               'fov_y': 30.0, 'width': 8, 'height': 8}}, '<t>')\n"
            "h = Renderer(sc, ms='network', ms_resolution=6).render().header\n"
            "assert 'lattice 6x6x6' in h['simulated'], h['simulated']\n")
    p = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True,
                       env=dict(os.environ, PYTHONPATH=root))
    assert p.returncode == 0, p.stderr
