"""Output paths refused before any work, in one line (exit 2), as `clvol render` refuses a
missing folder: a bundle onto a file or into a missing folder, a {frame} field without
--frames, an image named like a folder. Each wrote something wrong before (a traceback, a
folder made from the root down, a file literally named nofr_{frame}.exr, a render of seconds
ending in an error naming an internal temporary file)."""
from __future__ import annotations

import subprocess
import sys

import pytest

from clvol.cli import main
from scene_toml import SMALL_CLOUD, write_scene


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = [l for l in err.splitlines() if l.strip()]
    assert len(lines) == 1, err
    return lines[0]


def test_bundle_onto_an_existing_file_is_refused(tmp_path, capsys):
    scene = write_scene(tmp_path / "s.toml", **SMALL_CLOUD)
    afile = tmp_path / "afile"
    afile.write_text("keep me")
    assert main(["bundle", str(scene), str(afile)]) == 2
    assert "is not a folder" in _one_line(capsys)
    assert afile.read_text() == "keep me"


def test_bundle_into_a_missing_folder_is_refused_and_creates_nothing(tmp_path, capsys):
    scene = write_scene(tmp_path / "s.toml", **SMALL_CLOUD)
    out = tmp_path / "missing" / "dir" / "x.bundle"
    assert main(["bundle", str(scene), str(out)]) == 2
    assert "does not exist" in _one_line(capsys)
    assert not (tmp_path / "missing").exists()


def _render(tmp_path, *args):
    scene = write_scene(tmp_path / "s.toml", **SMALL_CLOUD)
    p = subprocess.run([sys.executable, "-m", "clvol", "render", str(scene), "--ms", "none",
                        *args], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    return p.returncode, [l for l in p.stderr.splitlines() if l.strip()]


@pytest.mark.parametrize("args,text", [
    (["-o", "nofr_{frame}.exr"], "give --frames"),
    (["-o", "nofr_{frame:04d}.exr"], "give --frames"),
    (["-o", "x.exr", "--png", "p_{frame}.png"], "give --frames"),
    (["-o", "adir.exr"], "is a folder"),
    (["-o", "x.exr", "--png", "adir.png"], "is a folder"),
])
def test_render_outputs_refused_before_rendering(tmp_path, args, text):
    (tmp_path / "adir.exr").mkdir()
    (tmp_path / "adir.png").mkdir()
    rc, lines = _render(tmp_path, *args)
    assert rc == 2 and len(lines) == 1 and text in lines[0], lines
    assert sorted(f.name for f in tmp_path.iterdir()) == ["adir.exr", "adir.png", "s.toml"]


def test_braces_that_are_not_a_frame_field_are_a_plain_name(tmp_path):
    rc, lines = _render(tmp_path, "-o", "a{b}.exr", "--quiet")
    assert rc == 0 and (tmp_path / "a{b}.exr").is_file(), lines
