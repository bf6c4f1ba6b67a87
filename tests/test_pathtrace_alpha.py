"""The path tracer's coverage layer (`alpha`, 1 - T of the camera ray, averaged over the pixel;
docs/pathtrace.md): a `RenderResult.alpha` and an EXR layer, as the ray marcher has. Before,
`img.alpha` of a path-traced render raised and its EXR had no alpha.

The check is against the path tracer itself: in a purely absorbing medium (albedo 0) lit only
by a constant sky of radiance 1, a path adds the sky when its camera ray escapes, so the
pixel's mean is T averaged over the pixel (the jittered rays) and 1 - total estimates alpha
with the image's own standard error."""
from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np

import clvol
from clvol.image import read_exr
from scene_toml import SMALL_CLOUD, write_scene


def _scene(tmp_path):
    tables = dict(SMALL_CLOUD)
    tables["medium"] = {"density_scale": 12.0, "albedo": 0.0, "phase": {"type": "isotropic"}}
    tables["light"] = {"direction": [0.5, 0.8, 0.3], "irradiance": 0.0, "environment": 1.0}
    tables["camera"] = dict(SMALL_CLOUD["camera"], width=20, height=14)
    return clvol.load_scene(write_scene(tmp_path / "s.toml", **tables))


def test_alpha_is_one_minus_the_pixels_transmittance(tmp_path):
    scene = _scene(tmp_path)
    img = clvol.Renderer(scene, "pathtrace", spp=256, seed=3).render()
    alpha, total, se = img.alpha, img.total[..., 0], img.layers["total_se"][..., 0]
    assert alpha.shape == (14, 20) and alpha.dtype == np.float32
    assert 0.3 < alpha.max() <= 1.0 and alpha.min() == 0.0          # medium and empty sky
    est = 1.0 - total.astype(np.float64)
    # Each path escapes or not: given alpha, est is a binomial mean of 256 paths with standard
    # deviation sd (the image's own SE is 0 where every path escaped, which says nothing).
    # 5 sd per pixel, plus 2e-3 for the coverage's quadrature (0.25-voxel steps, 4 x 4 rays a
    # pixel against the path tracer's uniformly jittered ones over a soft cloud).
    n = 256
    sd = np.sqrt(alpha * (1.0 - alpha) / n)
    bad = np.abs(alpha - est) > 5 * sd + 2e-3
    assert not bad.any(), (alpha[bad], est[bad], sd[bad])
    assert np.all(np.abs(se - sd)[sd > 0.01] < 0.5 * sd[sd > 0.01])   # sd is the image's SE
    z = (est - alpha)[sd > 0] / sd[sd > 0]
    assert abs(z.mean()) < 4 / np.sqrt(z.size)                      # no bias over the image
    # the viewer's next pass at the same view reads the kept coverage
    again = clvol.Renderer(scene, "pathtrace", spp=1, seed=4).render()
    np.testing.assert_array_equal(again.alpha, alpha)


def test_the_exr_of_a_path_traced_render_has_alpha(tmp_path):
    scene = _scene(tmp_path)
    scene = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=6,
                                                                  height=5))
    p = tmp_path / "pt.exr"

    r = subprocess.run([sys.executable, "-m", "clvol", "render", str(tmp_path / "s.toml"),
                        "--method", "pathtrace", "--spp", "4", "-o", str(p), "--quiet",
                        "--width", "6", "--height", "5"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    layers = read_exr(p).layers
    assert "alpha" in layers and layers["alpha"].shape == (5, 6)
    assert float(layers["alpha"].max()) > 0
