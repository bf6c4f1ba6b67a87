"""The clvol command line: subcommands, exit status 2 with one line for bad input."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from clvol.cli import main
from clvol.image import write_exr
from scene_toml import CAMERA, write_scene


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_help_runs_as_a_module():
    proc = subprocess.run([sys.executable, "-m", "clvol", "--help"], capture_output=True, text=True)
    assert proc.returncode == 0
    for cmd in ("info", "volume", "render", "compare"):
        assert cmd in proc.stdout


def test_info_lists_the_chosen_device(capsys):
    code, out, _ = run(capsys, "info")
    assert code == 0 and "chosen:" in out and "platform 0" in out


def test_info_bad_device_is_exit_2_one_line(capsys):
    code, _, err = run(capsys, "info", "--device", "7:7")
    # info reports the problem in its listing instead of failing
    assert code == 0
    code, _, err = run(capsys, "render", "nonexistent.toml", "-o", "x.exr")
    assert code == 2 and err.count("\n") == 1 and err.startswith("clvol: error:")


def test_volume_generate_info_convert(tmp_path, capsys):
    vol = tmp_path / "c.vol"
    code, out, _ = run(capsys, "volume", "generate", "sphere", "--resolution", "9", "11", "13",
                       "-o", vol, "--seed", "3")
    assert code == 0 and vol.exists()
    code, out, _ = run(capsys, "volume", "info", vol, "--density-scale", "10")
    assert code == 0 and "9" in out and "13" in out
    npz = tmp_path / "c.npz"
    code, _, _ = run(capsys, "volume", "convert", vol, npz)
    assert code == 0
    from clvol.volume.io import read_volume
    a, b = read_volume(vol), read_volume(npz)
    np.testing.assert_array_equal(a.density, b.density)
    assert a.density.shape == (13, 11, 9)


def test_volume_generate_list_and_bad_param(tmp_path, capsys):
    code, out, _ = run(capsys, "volume", "generate", "--list")
    assert code == 0 and "cloud" in out and "smoke" in out
    code, _, err = run(capsys, "volume", "generate", "cloud", "-o", tmp_path / "x.vol",
                       "--param", "no_such_param=1")
    assert code == 2 and "no_such_param" in err and err.count("\n") == 1


def test_volume_info_rejects_malformed_file(tmp_path, capsys):
    bad = tmp_path / "bad.vol"
    bad.write_bytes(b"XYZ" + bytes(60))
    code, _, err = run(capsys, "volume", "info", bad)
    assert code == 2 and "bad.vol" in err


def test_compare_prints_metrics_and_json(tmp_path, capsys):
    ref = np.full((4, 6, 3), 0.5, np.float32)
    test = ref.copy()
    test[0, 0] = 1.0
    write_exr(tmp_path / "ref.exr", {"total": ref})
    write_exr(tmp_path / "test.exr", {"total": test})
    code, out, _ = run(capsys, "compare", tmp_path / "test.exr", tmp_path / "ref.exr", "--json")
    assert code == 0
    result = json.loads(out)
    # One pixel of 24 off by 0.5 in every channel: RMSE = sqrt(0.25 / 24).
    assert result["rmse"] == pytest.approx(np.sqrt(0.25 / 24), rel=1e-6)
    code, out, _ = run(capsys, "compare", tmp_path / "ref.exr", tmp_path / "ref.exr", "--json")
    assert json.loads(out)["psnr"] is None  # inf is not JSON: written as null
    code, out, _ = run(capsys, "compare", tmp_path / "test.exr", tmp_path / "ref.exr")
    assert code == 0 and "mrpnn" in out


def test_compare_missing_file_is_exit_2(tmp_path, capsys):
    code, _, err = run(capsys, "compare", tmp_path / "a.exr", tmp_path / "b.exr")
    assert code == 2 and "a.exr" in err


def test_render_bad_scene_is_exit_2_with_field(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text("[volume]\ngenerator = 'sphere'\n[medium]\ndensity_scale = -1\n")
    code, _, err = run(capsys, "render", scene, "-o", tmp_path / "o.exr")
    assert code == 2 and "s.toml" in err and err.count("\n") == 1


def test_render_writes_exr_png_and_header(tmp_path, capsys):
    scene = write_scene(tmp_path / "s.toml", volume={"generator": "sphere", "resolution": 12},
                        medium={"preset": "milk", "density_scale": 8.0},
                        light={"direction": [0.3, 1.0, 0.4]},
                        camera={**CAMERA, "origin": [0.0, 0.2, 2.2], "width": 9, "height": 7})
    out = tmp_path / "o.exr"
    code, _, err = run(capsys, "render", scene, "--method", "raymarch", "-o", out, "--png")
    assert code == 0, err
    from clvol.image import read_exr
    img = read_exr(out)
    assert img.rgb.shape == (7, 9, 3) and np.all(np.isfinite(img.rgb)) and img.rgb.max() > 0
    assert img.header["scene"] == str(scene) and img.header["method"] == "raymarch"
    assert (tmp_path / "o.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_render_profile_and_device_options(tmp_path, capsys):
    from clvol import runtime
    scene = write_scene(tmp_path / "s.toml", volume={"generator": "sphere", "resolution": 10},
                        medium={"preset": "smoke", "density_scale": 8.0},
                        light={"direction": [0.0, 1.0, 0.0]},
                        camera={**CAMERA, "width": 8, "height": 8})
    spec = runtime.list_devices()[0].spec
    try:
        code, _, err = run(capsys, "render", scene, "--method", "raymarch", "-o",
                           tmp_path / "o.exr", "--profile", "--device", spec)
        assert code == 0, err
        assert "device time per kernel" in err and "raymarch" in err
        code, _, err = run(capsys, "render", scene, "-o", tmp_path / "o.exr", "--device", "9:9")
        assert code == 2 and "9:9" in err
    finally:
        runtime._DEFAULTS.update(device=None, profiling=False)  # undo the CLI's configure()


def test_rendering_never_imports_torch(tmp_path):
    """torch is for training only: the CLI and both renderers must work without it."""
    code = (
        "import sys\n"
        "from clvol.cli import main\n"
        f"assert main(['render', {str(tmp_path / 's.toml')!r}, '-o', {str(tmp_path / 'o.exr')!r}]) == 0\n"
        f"assert main(['render', {str(tmp_path / 's.toml')!r}, '--method', 'pathtrace', '--spp', '1',"
        f" '-o', {str(tmp_path / 'p.exr')!r}]) == 0\n"
        "import clvol.features.weights, clvol.kernels.mlp, clvol.kernels.gather\n"
        "assert 'torch' not in sys.modules, 'torch was imported'\n")
    write_scene(tmp_path / "s.toml", volume={"generator": "sphere", "resolution": 8},
                medium={"preset": "cloud", "density_scale": 8.0},
                light={"direction": [0.0, 1.0, 0.0]}, camera={**CAMERA, "width": 6, "height": 5})
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]


def test_png_preview_exposure_is_auto_unless_given_and_needs_png(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text((Path(__file__).parent / "data" / "scenes" / "milk.toml").read_text()
                     .replace("width = 256", "width = 16").replace("height = 256", "height = 16"))
    out = tmp_path / "a.exr"
    code, _, err = run(capsys, "render", scene, "-o", out, "--exposure", "1")
    assert code == 2 and "--exposure sets the PNG preview" in err
    code, _, err = run(capsys, "render", scene, "-o", out, "--png", "--ms", "none")
    assert code == 0 and "chosen from the image; filmic" in err
    code, _, err = run(capsys, "render", scene, "-o", out, "--png", "--exposure", "1.5",
                       "--tone", "linear", "--ms", "none")
    assert code == 0 and "exposure +1.50 stops, given; linear" in err


def _write_pfm(path, rgb, big_endian=False):
    h, w, _ = rgb.shape
    data = np.ascontiguousarray(rgb[::-1], ">f4" if big_endian else "<f4")   # bottom row first
    path.write_bytes(f"PF\n{w} {h}\n{1.0 if big_endian else -1.0}\n".encode() + data.tobytes())


def test_compare_reads_the_c_demos_pfm(tmp_path, capsys):
    """examples/c/clvol-render writes PFM: compare reads it against an EXR (rows flipped back
    to top first, both byte orders) and refuses a truncated one."""
    ref = np.random.default_rng(1).random((5, 7, 3)).astype(np.float32)
    write_exr(tmp_path / "ref.exr", {"total": ref})
    for big in (False, True):
        _write_pfm(tmp_path / "same.pfm", ref, big)
        code, out, _ = run(capsys, "compare", tmp_path / "same.pfm", tmp_path / "ref.exr", "--json")
        assert code == 0 and json.loads(out)["rmse"] == 0.0
    flipped = ref[::-1].copy()                       # a reader that forgot the flip fails here
    _write_pfm(tmp_path / "flip.pfm", flipped)
    code, out, _ = run(capsys, "compare", tmp_path / "flip.pfm", tmp_path / "ref.exr", "--json")
    assert code == 0 and json.loads(out)["rmse"] > 0.01
    bad = tmp_path / "cut.pfm"
    bad.write_bytes((tmp_path / "same.pfm").read_bytes()[:-4])
    code, _, err = run(capsys, "compare", bad, tmp_path / "ref.exr")
    assert code == 2 and "cut.pfm" in err and "truncated" in err


def test_set_overrides_scene_fields_as_the_file_would(tmp_path, capsys):
    """--set TABLE.FIELD=VALUE (a TOML value) replaces a field of the scene file for this run,
    through the file's own checks: the image takes the new size, a table value (the phase)
    and an RGB work, the bundle writes the new density scale; a value out of range, a
    malformed item and a clash with --width are each one line, exit 2."""
    scene = write_scene(tmp_path / "s.toml", volume={"generator": "sphere", "resolution": 12},
                        medium={"preset": "milk", "density_scale": 8.0},
                        light={"direction": [0.3, 1.0, 0.4]},
                        camera={**CAMERA, "origin": [0.0, 0.2, 2.2], "width": 9, "height": 7})
    out = tmp_path / "o.exr"
    code, _, err = run(capsys, "render", scene, "--method", "raymarch", "--ms", "none", "-o",
                       out, "--set", "camera.width=5", "--set", "camera.height=4",
                       "--set", 'medium.phase={ type = "hg", g = 0.5 }',
                       "--set", "light.irradiance=[2.0, 1.0, 0.5]")
    assert code == 0, err
    from clvol.image import read_exr
    assert read_exr(out).rgb.shape == (4, 5, 3)
    code, _, err = run(capsys, "bundle", scene, tmp_path / "B", "--set", "medium.density_scale=12")
    assert code == 0, err
    assert "\nmedium.density_scale = 12.0\n" in (tmp_path / "B" / "manifest.txt").read_text()
    for argv, fragment in (
            (["--set", "medium.density_scale=-1"], "[medium.density_scale] = -1: must be >= 0"),
            (["--set", "medium.albedo"], "must be TABLE.FIELD=VALUE"),
            (["--set", "light.irradiance=[1, 2"], "is not a TOML value"),
            (["--set", "camera.width=5", "--width", "6"], "give one of them")):
        code, _, err = run(capsys, "render", scene, "-o", out, *argv)
        assert code == 2 and fragment in err and err.count("\n") == 1, err
