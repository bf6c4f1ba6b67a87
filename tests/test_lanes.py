"""The lane width (cl/include/lanes.h LANES) is the device's choice (clvol/runtime.py
device_lanes, docs/opencl.md "Compiler warnings"), and the image does not depend on it: lanes
are independent rays, queries, template points or sweep columns.
"""
from __future__ import annotations

import numpy as np
import pytest

from clvol.errors import DeviceError
from clvol.render.renderer import Renderer
from clvol.runtime import device_lanes, forced_lanes, get_runtime, lanes_for
from clvol.scenefile import scene_from_dict


def test_the_width_follows_a_cpus_vector_registers_and_stays_16_elsewhere():
    assert [lanes_for("cpu", w) for w in (16, 8, 4)] == [16, 8, 4]   # AVX-512, AVX(2), SSE
    assert lanes_for("cpu", 32) == 16 and lanes_for("cpu", 1) == 16 and lanes_for("cpu", 0) == 16
    assert [lanes_for(k, 4) for k in ("gpu", "accelerator", "other")] == [16, 16, 16]


def test_clvol_lanes_forces_a_width_and_refuses_others(monkeypatch):
    monkeypatch.delenv("CLVOL_LANES", raising=False)
    assert forced_lanes() is None
    for w in (4, 8, 16):
        monkeypatch.setenv("CLVOL_LANES", str(w))
        assert forced_lanes() == w and get_runtime().lanes == w
    for bad in ("2", "32", "eight"):
        monkeypatch.setenv("CLVOL_LANES", bad)
        with pytest.raises(DeviceError, match="CLVOL_LANES"):
            forced_lanes()


def _scene(method_width: int, method_height: int):
    return scene_from_dict({
        "volume": {"generator": "cloud", "seed": 3, "resolution": 32},
        "medium": {"preset": "cloud", "density_scale": 48.0, "albedo": [0.9, 0.8, 0.6]},
        "light": {"direction": [0.45, 0.4, -0.8]},
        "camera": {"origin": [0.1, 0.15, 1.6], "target": [0.0, 0.06, 0.0], "fov_y": 35.0,
                   "width": method_width, "height": method_height}}, "<test_lanes>")


def _render(monkeypatch, lanes: int, method: str, **kw) -> dict:
    monkeypatch.setenv("CLVOL_LANES", str(lanes))
    rt = get_runtime()
    assert rt.lanes == lanes and device_lanes(rt.entry) == lanes
    # 13 x 10: partial tiles at every width (4 x 4, 4 x 2, 4 x 1 pixels)
    res = Renderer(_scene(13, 10), method, runtime=rt, **kw).render()
    if method == "raymarch":     # the network's kernels ran (fused gather + network)
        assert res.header["raymarch.ms"] == "network" and res.header["raymarch.network_fused"]
    return {k: np.asarray(v) for k, v in res.layers.items()}


@pytest.mark.parametrize("method,kw", [
    ("raymarch", {"ms": "network", "ms_resolution": 8}),              # light field, gather + network, march
    ("pathtrace", {"spp": 2}),
], ids=["default", "pathtrace"])
def test_a_scene_renders_the_same_bits_at_16_8_and_4_lanes(monkeypatch, method, kw):
    want = _render(monkeypatch, 16, method, **kw)
    assert want["total"].max() > 0
    for lanes in (8, 4):
        got = _render(monkeypatch, lanes, method, **kw)
        assert set(got) == set(want)
        for name in want:
            np.testing.assert_array_equal(got[name], want[name], err_msg=f"{name} at {lanes}")


def test_clvol_info_prints_each_devices_width_with_its_code_paths(monkeypatch, capsys):
    from clvol.cli import main
    monkeypatch.delenv("CLVOL_LANES", raising=False)
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    rt = get_runtime()
    assert f"lanes: {rt.lanes} per work-item (" in out
    monkeypatch.setenv("CLVOL_LANES", "8")
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    assert "lanes: 8 per work-item (forced by $CLVOL_LANES" in out
    assert "raymarch: 4x2 pixel tile" in out and "mlp, gather_mlp: 8 queries" in out


def test_kernels_refuse_a_missing_or_unknown_width_and_wider_path_lanes(monkeypatch):
    import pyopencl as cl

    from clvol.errors import BuildError
    from clvol.runtime import include_dir
    rt = get_runtime()
    src = '#include "lanes.h"\n__kernel void k(__global float *o) { vstoreL((vL)(1.0f), 0, o); }\n'
    for opts, msg in (([], "needs -D LANES"), (["-DLANES=6"], "LANES must be 16, 8 or 4")):
        with pytest.raises(cl.RuntimeError, match=msg):
            cl.Program(rt.context, src).build(options=["-I", str(include_dir())] + opts,
                                              devices=[rt.device])
    monkeypatch.setenv("CLVOL_LANES", "8")
    with pytest.raises(BuildError, match="PT_LANES must be at most"):
        get_runtime().program("pathtrace", {"PHASE_ISOTROPIC": 1, "PHASE_LOBES": 1, "PT_LANES": 16})
