"""Preview exposure: chosen from the image (the default) or from the scene's light
(``--exposure scene``, clvol.image.scene_exposure; docs/scenes.md, "Previews")."""
from __future__ import annotations

import math
import zlib
from pathlib import Path

import numpy as np
import pytest

from clvol.cli import main
from clvol.image import (AUTO_WHITE, choose_exposure, read_exr, scene_exposure, white_luminance,
                         write_exr)
from clvol.scene import Light
from scene_toml import SMALL_CLOUD, write_scene


def png_pixels(path, with_alpha: bool = False) -> np.ndarray:
    """(H, W, 3) uint8 of the 8-bit RGB or RGBA, filter-0 PNGs that clvol.image writes (the
    colour channels; with ``with_alpha``, all channels as stored: 3 or 4)."""
    data = Path(path).read_bytes()
    pos, idat, w, h, c = 8, b"", 0, 0, 3
    while pos < len(data):
        n = int.from_bytes(data[pos:pos + 4], "big")
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + n]
        if kind == b"IHDR":
            w, h = int.from_bytes(body[:4], "big"), int.from_bytes(body[4:8], "big")
            c = {2: 3, 6: 4}[body[9]]                 # colour type: RGB or RGBA
        elif kind == b"IDAT":
            idat += body
        pos += 12 + n
    rows = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(h, 1 + c * w)
    assert not rows[:, 0].any()                     # filter type 0 on every row
    px = rows[:, 1:].reshape(h, w, c)
    return px if with_alpha else px[..., :3]


def render(tmp_path, capsys, name, medium, *args, light=None):
    scene = write_scene(tmp_path / f"{name}.toml", **{
        **SMALL_CLOUD, "medium": medium, "light": light or SMALL_CLOUD["light"],
        "camera": {**SMALL_CLOUD["camera"], "width": 24, "height": 20}})
    out = tmp_path / f"{name}.exr"
    code = main(["render", str(scene), "-o", str(out), "--png", "--quiet", *args])
    err = capsys.readouterr().err
    assert code == 0, err
    line = [l for l in err.splitlines() if l.startswith(f"wrote {tmp_path / name}.png")]
    assert len(line) == 1, err
    return png_pixels(out.with_suffix(".png")), line[0], read_exr(out).header


def test_scene_exposure_shows_albedo_which_image_exposure_hides(tmp_path, capsys):
    # Same volume, density, light and camera; only the medium differs.
    smoke = {"preset": "smoke", "density_scale": 30.0}        # albedo 0.4, g 0.3
    cloud = {"preset": "cloud", "density_scale": 30.0}        # albedo 0.999, g 0.857
    s_img, s_line, _ = render(tmp_path, capsys, "smoke_i", smoke)
    c_img, c_line, _ = render(tmp_path, capsys, "cloud_i", cloud)
    assert "chosen from the image" in s_line and "chosen from the image" in c_line
    # From the image: both normalised, the albedo does not show (means within 15 %) ...
    assert abs(s_img.mean() - c_img.mean()) < 0.15 * c_img.mean(), (s_img.mean(), c_img.mean())
    s_sc, s_line, s_hdr = render(tmp_path, capsys, "smoke_s", smoke, "--exposure", "scene")
    c_sc, c_line, c_hdr = render(tmp_path, capsys, "cloud_s", cloud, "--exposure", "scene")
    # ... from the light: the same exposure for both, and the smoke is clearly darker.
    stops = math.log2(AUTO_WHITE * math.pi)                   # irradiance 1, no sky: +1.33
    for line, hdr in ((s_line, s_hdr), (c_line, c_hdr)):
        assert f"exposure {stops:+.2f} stops, from the scene's light; filmic" in line
        assert hdr["preview.exposure_from"] == "from the scene's light"
        assert float(hdr["preview.exposure"]) == pytest.approx(stops, abs=1e-4)
    assert s_sc.mean() < 0.6 * c_sc.mean(), (s_sc.mean(), c_sc.mean())
    # The cloud is neither dark nor clipped at the scene exposure.
    assert 0.5 * c_img.mean() < c_sc.mean() < 2.0 * c_img.mean()
    assert np.count_nonzero(c_sc == 255) < 0.01 * c_sc.size


def test_scene_exposure_without_light_falls_back_to_the_image(tmp_path, capsys):
    dark = {"direction": [0.5, 0.8, 0.3], "irradiance": [0.0, 0.0, 0.0]}
    _, line, hdr = render(tmp_path, capsys, "dark", {"preset": "cloud", "density_scale": 30.0},
                          "--exposure", "scene", light=dark)
    assert "chosen from the image: the scene has no light" in line
    assert hdr["preview.exposure_from"] == "chosen from the image: the scene has no light"
    _, line, hdr = render(tmp_path, capsys, "given", {"preset": "cloud", "density_scale": 30.0},
                          "--exposure", "-0.25")
    assert "exposure -0.25 stops, given; filmic" in line and hdr["preview.exposure"] == "-0.2500"


def test_white_luminance_of_sun_sky_and_map(tmp_path):
    sun = Light(direction=(0.0, 1.0, 0.0), irradiance=(2.0, 2.0, 2.0))
    assert white_luminance(sun) == pytest.approx(2.0 / math.pi)
    assert scene_exposure(sun) == pytest.approx(math.log2(AUTO_WHITE * math.pi / 2.0))
    # Luminance weights: pure green counts 0.7152.
    assert white_luminance(Light((0.0, 1.0, 0.0), irradiance=(0.0, math.pi, 0.0))) == \
        pytest.approx(0.7152)
    sky = Light((0.0, 1.0, 0.0), irradiance=(0.0, 0.0, 0.0), environment=(0.5, 0.5, 0.5))
    assert white_luminance(sky) == pytest.approx(0.5)
    # A map's solid-angle mean: bright rows at the poles count less than at the equator.
    texels = np.zeros((8, 16, 3), np.float32)
    texels[0] = 1.0                                  # the top row only
    write_exr(tmp_path / "m.exr", {"total": texels})
    c = np.cos(np.pi * np.arange(9) / 8)
    mean = (c[0] - c[1]) / 2.0                       # its share of the sphere
    mapped = Light((0.0, 1.0, 0.0), irradiance=(0.0, 0.0, 0.0),
                   environment_map=tmp_path / "m.exr", environment_scale=(3.0, 3.0, 3.0))
    assert white_luminance(mapped) == pytest.approx(3.0 * mean, rel=1e-6)
    # A uniform map equals the constant sky of the same radiance.
    write_exr(tmp_path / "u.exr", {"total": np.full((8, 16, 3), 0.5, np.float32)})
    uniform = Light((0.0, 1.0, 0.0), irradiance=(0.0, 0.0, 0.0), environment_map=tmp_path / "u.exr")
    assert white_luminance(uniform) == pytest.approx(0.5, rel=1e-6)
    none = Light((0.0, 1.0, 0.0), irradiance=(0.0, 0.0, 0.0))
    assert scene_exposure(none) is None


def test_choose_exposure_modes():
    rgb = np.full((2, 2, 3), 0.1)
    light = Light((0.0, 1.0, 0.0))
    assert choose_exposure(None, rgb, light)[1] == "chosen from the image"
    assert choose_exposure("image", rgb, light) == choose_exposure(None, rgb, light)
    assert choose_exposure("scene", rgb, light) == (scene_exposure(light), "from the scene's light")
    assert choose_exposure(1.5, rgb, light) == (1.5, "given")
    from clvol.errors import ClvolError
    for bad in ("scenes", float("nan"), float("inf")):
        with pytest.raises(ClvolError, match="finite number of stops"):
            choose_exposure(bad, rgb, light)


def test_preview_has_the_images_alpha_over_a_black_background(tmp_path, capsys):
    """The PNG preview carries the EXR's coverage as straight alpha (before: RGB only), and
    stays opaque with a sky behind the medium (the beauty already shows it)."""
    from clvol.image import tonemap_srgb8
    px, _, header = render(tmp_path, capsys, "black", SMALL_CLOUD["medium"])
    rgba = png_pixels(tmp_path / "black.png", with_alpha=True)
    img = read_exr(tmp_path / "black.exr")
    a = img.layers["alpha"].astype(np.float64)
    assert rgba.shape[2] == 4
    np.testing.assert_array_equal(rgba[..., 3], np.floor(a * 255 + 0.5).astype(np.uint8))
    assert 0 < a.max() and a.min() == 0.0                   # medium and empty background
    # straight colour: the premultiplied beauty divided by alpha, then the same tone curve
    stops = float(header["preview.exposure"])
    seen = a >= 0.5 / 255
    straight = np.where(seen[..., None], img.rgb / np.where(seen, a, 1)[..., None], 0)
    want, _ = tonemap_srgb8(straight, stops, header["preview.tone"])
    np.testing.assert_array_equal(rgba[..., :3], want)
    sky = dict(SMALL_CLOUD["light"], environment=[0.2, 0.3, 0.5])
    render(tmp_path, capsys, "sky", SMALL_CLOUD["medium"], light=sky)
    assert png_pixels(tmp_path / "sky.png", with_alpha=True).shape[2] == 3
