"""Every shipped example loads and renders with each method, small, with no NaN/Inf, nothing
negative, and the medium actually visible (the examples are framed to fill the image).
examples/fire/fire.toml reads frames that examples/fire/make_fire.py makes: the test makes
them small (16^3, 6 frames, ~1 s) in a temporary folder and renders the scene file as shipped."""
import dataclasses
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import clvol

ROOT = Path(__file__).resolve().parents[1]
FIRE = ROOT / "examples" / "fire" / "fire.toml"
EXAMPLES = sorted((ROOT / "examples").glob("*.toml")) + [FIRE]


@pytest.fixture(scope="module")
def fire_scene(tmp_path_factory):
    """fire.toml beside its frames (it renders frame 6 of the sequence)."""
    out = tmp_path_factory.mktemp("fire")
    subprocess.run([sys.executable, str(FIRE.parent / "make_fire.py"), "--frames", "6",
                    "--resolution", "16", "--out", str(out)], check=True, capture_output=True)
    shutil.copy(FIRE, out / "fire.toml")
    return out / "fire.toml"


def test_examples_are_shipped():
    names = {p.stem for p in EXAMPLES}
    assert {"cloud", "cloud_large", "jade", "milk", "smoke", "wax", "fire"} <= names


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.stem)
@pytest.mark.parametrize("options", [{}, {"method": "raymarch", "ms": "wrenninge"},
                                     {"method": "pathtrace", "spp": 2}],
                         ids=["default", "wrenninge", "pathtrace"])
def test_example_renders_finite_and_fills_the_frame(path, options, request):
    if path == FIRE:
        path = request.getfixturevalue("fire_scene")
    scene = clvol.load_scene(path)
    scene = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=24, height=24))
    result = clvol.Renderer(scene, **options).render()
    rgb = result.layers["total"]
    assert rgb.shape == (24, 24, 3)
    assert np.isfinite(rgb).all() and (rgb >= 0).all()
    alpha = result.layers.get("alpha")
    if alpha is not None:
        assert np.all((alpha >= 0) & (alpha <= 1))
        # Framed on the medium: at least 30% of the pixels see it (the thin smoke plume is the
        # sparsest example; the solids and clouds cover 40-70%). The fireball is framed with
        # room to rise and grow: 25-28% at 16^3-64^3 (measured), so 20% for it.
        least = 0.2 if path.name == "fire.toml" else 0.3
        assert np.mean(alpha > 0.05) > least, np.mean(alpha > 0.05)
    assert rgb.mean() > 0
    if scene.emission is not None:                     # the fire glows: emission reaches the image
        assert result.layers["emission"].max() > 0


def test_silver_lining_example_has_bright_edges_in_both_methods():
    """examples/cloud_silver.toml: the sun behind the cloud, 21 degrees from the line of sight.
    Thin edges (alpha 0.05-0.5 in the real-time image) must be brighter than the thick core
    (alpha > 0.95), in the real-time image and in the path tracer's, and the two ratios must
    agree. Measured at 128^2: 1.57 (real time) and 1.70 (path tracer, 64 spp); with the
    cloud.toml light (39 degrees) 0.36 and 0.33. Here 64^2, 32 spp: the edge mask holds 158
    pixels and the ratio measured 1.82 (real time) and 1.96 / 2.00 / 2.09 (path tracer, seeds
    5 / 4 / 3: the noise moves it by a few per cent), so 1.2 and a 25% agreement are far from
    both the noise and the no-lining case."""
    path = Path(__file__).resolve().parents[1] / "examples" / "cloud_silver.toml"
    scene = clvol.load_scene(path)
    scene = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=64, height=64))
    grid = scene.volume.load()
    rt = clvol.Renderer(scene, grid=grid).render()
    pt = clvol.Renderer(scene, "pathtrace", grid=grid, spp=32, seed=3).render()
    alpha = rt.layers["alpha"]
    edge, core = (alpha > 0.05) & (alpha < 0.5), alpha > 0.95
    assert edge.sum() > 50 and core.sum() > 500

    def ratio(res):
        lum = res.layers["total"].mean(axis=2)
        return lum[edge].mean() / lum[core].mean()
    r_rt, r_pt = ratio(rt), ratio(pt)
    assert r_rt > 1.2 and r_pt > 1.2, (r_rt, r_pt)
    assert abs(r_rt / r_pt - 1) < 0.25, (r_rt, r_pt)
