"""Cross-check against Mitsuba 3's volpath on the same scene (skipped when Mitsuba is absent).

This tells users that our conventions (grid layout and voxel centres, camera, light
direction, phase orientation, irradiance, environment) match the renderer they know. It
uses the ``scalar_rgb`` variant, which needs no LLVM (``llvm_ad_rgb`` needs libLLVM >= 17).

Tolerance: 4x4-pixel block means of a 16x16 image, per channel (48 comparisons), within 5
combined standard errors; ours from the per-pixel sample variance of 1024 spp, Mitsuba's
from the spread of 16 independent renders (t with 15 degrees of freedom: P(|t| > 5) ~ 2e-4
per comparison, ~1% for all 48). A non-cubic grid with an asymmetric box catches axis swaps.
"""
import numpy as np
import pytest

from clvol.scene import Camera, Light, Phase, Scene, VolumeSpec
from clvol.scene import Medium as SceneMedium
from clvol.volume.grid import DensityGrid

mi = pytest.importorskip("mitsuba")


@pytest.fixture(scope="module")
def mitsuba_ready():
    try:
        mi.set_variant("scalar_rgb")
        mi.render(mi.load_dict({"type": "scene", "integrator": {"type": "path"}, "sensor": {
            "type": "perspective", "film": {"type": "hdrfilm", "width": 2, "height": 2}}}))
    except Exception as exc:  # a broken install is a reason to skip, not to fail
        pytest.skip(f"Mitsuba 3 is installed but cannot render: {exc}")
    return mi


def _scene():
    rs = np.random.default_rng(5)
    density = (0.3 + rs.random((4, 5, 6))).astype(np.float32)       # [z][y][x], non-cubic
    grid = DensityGrid(density, np.array([-0.5, -0.35, -0.3]), np.array([0.55, 0.4, 0.3]))
    l = np.array([0.3, 0.5, -0.8])
    light = Light(direction=tuple(l / np.linalg.norm(l)), irradiance=(1.0, 0.9, 0.8),
                  environment=(0.1, 0.2, 0.3))
    med = SceneMedium(density_scale=3.0, albedo=(0.9, 0.6, 0.3), phase=Phase.hg(0.6))
    cam = Camera((0.3, 0.2, 2.2), (0.0, 0.0, 0.0), (0, 1, 0), 32.0, 16, 16)
    return Scene(path=None, volume=VolumeSpec(file=None, generator="box"), medium=med,
                 light=light, camera=cam), grid


def _blocks(img):
    return img.reshape(4, 4, 4, 4, 3).mean(axis=(1, 3))


@pytest.mark.slow
def test_matches_mitsuba_volpath(mitsuba_ready):
    from clvol.render.pathtrace import mitsuba_scene_dict, render_pathtrace
    scene, grid = _scene()
    ours = render_pathtrace(scene, spp=1024, seed=1, grid=grid, progress=False)
    mean_ours = _blocks(ours.layers["total"].astype(np.float64))
    se_ours = np.sqrt(_blocks(ours.layers["total_se"].astype(np.float64) ** 2) / 16)
    renders = [np.asarray(mi.render(mi.load_dict(mitsuba_scene_dict(scene, grid, 64, seed=s))))
               [..., :3].astype(np.float64) for s in range(16)]
    blocks = np.stack([_blocks(r) for r in renders])
    mean_mi = blocks.mean(axis=0)
    se_mi = blocks.std(axis=0, ddof=1) / np.sqrt(len(blocks))
    z = np.abs(mean_ours - mean_mi) / np.sqrt(se_ours ** 2 + se_mi ** 2)
    assert z.max() < 5.0, (z.max(), mean_ours[z.argmax() // 3 // 4], mean_mi.ravel()[z.argmax()])
    # The comparison resolves a few per cent: a convention error would be far larger.
    assert np.median(np.sqrt(se_ours ** 2 + se_mi ** 2) / mean_mi) < 0.02
