"""examples/fire: the shipped generator makes a sequence that the example scene renders, by
both methods, one frame and several (small: 16^3 frames written to a temporary folder)."""
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

import clvol
from clvol.cli import main

FIRE = Path(__file__).resolve().parents[1] / "examples" / "fire"


def _make(tmp_path, frames=3, res=16):
    proc = subprocess.run([sys.executable, str(FIRE / "make_fire.py"), "--frames", str(frames),
                           "--resolution", str(res), "--out", str(tmp_path)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    shutil.copy(FIRE / "fire.toml", tmp_path / "fire.toml")
    text = (tmp_path / "fire.toml").read_text().replace("frame = 6", "frame = 2")
    (tmp_path / "fire.toml").write_text(text)
    return tmp_path / "fire.toml"


def test_generator_is_deterministic_and_has_both_grids(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for d in (a, b):
        subprocess.run([sys.executable, str(FIRE / "make_fire.py"), "--frames", "2",
                        "--resolution", "12", "--out", str(d)], check=True, capture_output=True)
    za, zb = np.load(a / "fire_0002.npz"), np.load(b / "fire_0002.npz")
    np.testing.assert_array_equal(za["temperature"], zb["temperature"])
    assert za["density"].shape == za["temperature"].shape == (12, 12, 12)
    assert za["temperature"].max() > 1500 and za["density"].min() >= 0


def test_fire_example_renders_with_both_methods(tmp_path):
    scene = clvol.load_scene(_make(tmp_path))
    scene = scene.with_overrides({"camera.width": 16, "camera.height": 16})
    for opts in ({}, {"method": "pathtrace", "spp": 2}):
        res = clvol.Renderer(scene, **opts).render()
        rgb = res.layers["total"]
        assert np.isfinite(rgb).all() and (rgb >= 0).all()
        assert res.layers["emission"].max() > 0
        e = res.layers["emission"].reshape(-1, 3).sum(axis=0)
        assert e[0] > e[2]                         # fire glows red-orange, not blue
    code = main(["render", str(tmp_path / "fire.toml"), "--frames", "1-3", "--ms", "none",
                 "--width", "16", "--height", "16", "-o", str(tmp_path / "f_{frame}.exr"),
                 "--quiet"])
    assert code == 0 and len(list(tmp_path.glob("f_*.exr"))) == 3
