"""Memory known before it is spent (clvol/render/memory.py): a frame whose image would not
fit the budget is refused up front with one line naming the size, the estimate and the limit.

Before, a 16384 x 16384 image (inside the scene file's range) on a 16^3 sphere ran 4 minutes,
reached 16.9 GB and was killed by the kernel (exit 137) with no message (issue 41). The tests
set ``CLVOL_MEMORY_LIMIT`` so that they refuse the same sizes on any machine (one with more
memory than 32 GiB would otherwise start the 16384^2 render).
"""
from __future__ import annotations

import dataclasses
import time

import pytest

import clvol
from clvol.cli import main
from clvol.errors import ClvolError
from clvol.render import memory
from clvol.scene import scene_from_dict

from scene_toml import write_scene

SPHERE = {"volume": {"generator": "sphere", "resolution": 16},
          "medium": {"preset": "cloud", "density_scale": 8.0},
          "light": {"direction": [0.0, 1.0, 0.0]},
          "camera": {"origin": [0.0, 0.0, 2.5], "target": [0.0, 0.0, 0.0], "fov_y": 35.0,
                     "width": 16384, "height": 16384}}


def test_a_16384_square_image_exits_2_in_one_line_before_rendering(tmp_path, capsys,
                                                                  monkeypatch):
    monkeypatch.setenv(memory.LIMIT_ENV, "16G")
    scene = write_scene(tmp_path / "big.toml", **SPHERE)
    t0 = time.perf_counter()
    code = main(["render", str(scene), "-o", str(tmp_path / "big.exr")])
    seconds = time.perf_counter() - t0
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1, err
    for text in ("16384 x 16384 image (raymarch)", "32.00 GiB", "128 bytes a pixel",
                 "16.00 GiB limit", "$CLVOL_MEMORY_LIMIT"):
        assert text in err, (text, err)
    assert seconds < 5.0 and not (tmp_path / "big.exr").exists()


def test_the_renderer_refuses_past_the_limit_and_renders_below(monkeypatch):
    """128 bytes a ray-marched pixel: 64^2 is 512 KiB, under a 1 MiB limit; 128^2 (2 MiB) and
    64^2 at supersample 2 are over; the path tracer's 384 bytes put 64^2 at 1.5 MiB."""
    monkeypatch.setenv(memory.LIMIT_ENV, "1M")
    scene = scene_from_dict({**SPHERE, "camera": {**SPHERE["camera"], "width": 64,
                                                  "height": 64}}, "<memory>")
    r = clvol.Renderer(scene, ms="none")
    assert r.render().total.shape == (64, 64, 3)
    big = dataclasses.replace(scene.camera, width=128, height=128)
    with pytest.raises(ClvolError, match=r"a 128 x 128 image \(raymarch\) needs about "
                                         r"0\.00 GiB .* more than the 0\.00 GiB limit"):
        r.render(camera=big)
    with pytest.raises(ClvolError, match=r"64 x 64 image at supersample 2 \(raymarch\)"):
        clvol.Renderer(scene, ms="none", supersample=2).render()
    with pytest.raises(ClvolError, match=r"64 x 64 image \(pathtrace\)"):
        clvol.Renderer(scene, "pathtrace", spp=1).render()
    assert memory.check_frame_memory("raymarch", 64, 64, 1) == 64 * 64 * 128


def test_the_default_budget_is_the_smaller_of_host_and_device(monkeypatch):
    monkeypatch.delenv(memory.LIMIT_ENV, raising=False)

    class Device:
        global_mem_size = 3 * 2**30
        max_mem_alloc_size = 2**30
    host = memory.host_memory()
    assert host and host > 2**26
    limit, where = memory.memory_limit(Device)
    assert limit == min(host, Device.global_mem_size)
    # one plane over the largest buffer: 16 bytes x 8192^2 = 1 GiB + a row
    with pytest.raises(ClvolError, match="allows in one buffer"):
        Device.global_mem_size = 2**50
        memory.check_frame_memory("raymarch", 8192, 8193, 1, Device)


@pytest.mark.parametrize("text,value", [("1024", 1024), ("8G", 8 * 2**30), ("1.5k", 1536),
                                        ("2 GiB", 2 * 2**30), ("3mb", 3 * 2**20)])
def test_limit_values(text, value):
    assert memory.parse_limit(text) == value


@pytest.mark.parametrize("text", ["lots", "-1G", "0", "nan", "G"])
def test_bad_limit_values_are_refused_in_one_line(text):
    with pytest.raises(ClvolError, match=r"\$CLVOL_MEMORY_LIMIT = .*: must be a number of "
                                         r"bytes >= 1"):
        memory.parse_limit(text)


def test_info_prints_the_devices_limits_and_the_budget(capsys, monkeypatch):
    monkeypatch.setenv(memory.LIMIT_ENV, "3G")
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    line = [x for x in out.splitlines() if x.startswith("render memory:")]
    assert len(line) == 1, out
    for text in ("host ", "per buffer", "budget 3.00 GiB ($CLVOL_MEMORY_LIMIT)", "128 (raymarch)"):
        assert text in line[0], (text, line[0])
