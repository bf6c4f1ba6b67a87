"""`clvol render` output files, as a user runs it (subprocesses): an output that would be lost
or mislabelled is refused before anything renders, with one line and exit 2."""
from __future__ import annotations

import subprocess
import sys

import pytest

from scene_toml import SMALL_CLOUD, write_scene


def _render(tmp_path, *args):
    scene = write_scene(tmp_path / "s.toml", **SMALL_CLOUD)
    p = subprocess.run([sys.executable, "-m", "clvol", "render", str(scene), "--ms", "none", *args],
                       capture_output=True, text=True, cwd=tmp_path, timeout=300)
    return p.returncode, p.stderr


@pytest.mark.parametrize("args,text", [
    (["-o", "y.png", "--png"], "name it .exr"),             # the PNG would overwrite the EXR
    (["-o", "x.png"], "name it .exr"),                      # an EXR under a .png name
    (["-o", "x.exr", "--png", "z.exr"], "name it .png"),     # a PNG under an .exr name
    (["-o", "x.exr", "--png", "x.exr"], "name it .png"),
    (["-o", "x.exr", "--png", "--exposure", "nan"], "finite"),
    (["-o", "x.exr", "--png", "--exposure", "scenes"], "'image' (chosen from the image) or 'scene'"),
    (["-o", "x.exr", "--png", "--exposure=-inf"], "finite"),
    (["-o", "x.exr", "--exposure", "scene"], "give --png too"),
    (["-o", "x.exr", "--png", "missing/p.png"], "does not exist"),
    (["-o", "missing/x.exr"], "does not exist"),
])
def test_bad_outputs_are_refused_before_rendering(tmp_path, args, text):
    rc, err = _render(tmp_path, *args)
    assert rc == 2, err
    lines = [l for l in err.splitlines() if l.strip()]
    assert len(lines) == 1 and text in lines[0], err
    assert sorted(f.name for f in tmp_path.iterdir()) == ["s.toml"]      # nothing written


def test_exr_and_preview_are_both_written_once(tmp_path):
    rc, err = _render(tmp_path, "-o", "x.exr", "--png")
    assert rc == 0, err
    assert (tmp_path / "x.exr").read_bytes()[:4] == b"\x76\x2f\x31\x01"      # OpenEXR magic
    assert (tmp_path / "x.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    wrote = [l for l in err.splitlines() if l.startswith("wrote ")]
    assert [w.split()[1] for w in wrote] == ["x.exr", "x.png"]


def test_width_height_and_quiet(tmp_path):
    rc, err = _render(tmp_path, "-o", "x.exr", "--width", "7", "--height", "5", "--quiet")
    assert rc == 0, err
    from clvol.image import read_exr
    assert read_exr(tmp_path / "x.exr").rgb.shape == (5, 7, 3)
    assert err.strip().splitlines() == ["wrote x.exr"]                      # no summary
    rc, err = _render(tmp_path, "-o", "y.exr", "--width", "0")
    assert rc == 2 and "width" in err and len(err.strip().splitlines()) == 1
