"""The documentation names what ships and its commands run.

- every example scene is listed in docs/scenes.md;
- every ``clvol render`` command in a code block of the README or docs/*.md runs, at 16x16
  pixels and a few samples (``runnable``), or is listed in SKIPPED with the reason.
"""
from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md"] + sorted((ROOT / "docs").glob("*.md"))

# Commands that cannot run as shown, by a substring of their text, with the reason.
SKIPPED = {
    "--ms-lattice fms.npz": "needs an F_ms lattice file (fms.npz) that the page makes in Python first",
    "examples/fire/fire.toml": "needs the frames that python examples/fire/make_fire.py makes "
                               "(tests/test_fire_example.py renders them)",
}


def test_every_example_is_named_in_docs_scenes():
    text = (ROOT / "docs" / "scenes.md").read_text()
    missing = [p.name for p in sorted((ROOT / "examples").glob("*.toml"))
               if f"examples/{p.name}" not in text]
    assert not missing, f"docs/scenes.md does not name {missing}"


def render_commands() -> list[tuple[str, str]]:
    """(page, command) for every ``clvol render`` line of a fenced code block, with its
    backslash continuations joined and its trailing comment dropped."""
    out = []
    for page in DOCS:
        for block in re.findall(r"```[a-z]*\n(.*?)```", page.read_text(), re.S):
            for cmd in re.sub(r"\\\n\s*", " ", block).splitlines():
                cmd = re.sub(r"\s+#.*$", "", cmd.strip())
                if cmd.startswith("clvol render "):
                    out.append((page.name, cmd))
    return out


def runnable(cmd: str, out_dir: Path) -> list[str]:
    """The command's arguments at a small size: a placeholder scene becomes the cloud
    example, optional [...] parts go, outputs go to ``out_dir``, 16x16 pixels, at most 2
    samples per pixel or per block, no time budget."""
    cmd = re.sub(r"\[[^\]]*\]", "", cmd).replace("SCENE.toml", "examples/cloud.toml")
    args = shlex.split(cmd)[2:]                        # after "clvol render"
    fixed = []
    i = 0
    while i < len(args):
        a = args[i]
        if a in ("-o", "--output"):
            fixed += [a, str(out_dir / Path(args[i + 1]).name)]
            i += 2
            continue
        if a in ("--spp", "--view-samples"):
            fixed += [a, "2"]
            i += 2
            continue
        if a == "--time":
            i += 2
            continue
        fixed.append(a)
        i += 1
    return ["render"] + fixed + ["--width", "16", "--height", "16", "--quiet"]


COMMANDS = render_commands()


def test_the_docs_show_render_commands():
    assert len(COMMANDS) >= 15                      # the README alone shows 6
    used = {k for k in SKIPPED for _, c in COMMANDS if k in c}
    assert used == set(SKIPPED), f"SKIPPED entries that match no command: {set(SKIPPED) - used}"


@pytest.mark.parametrize("page,cmd", COMMANDS, ids=[f"{p}:{c[13:60]}" for p, c in COMMANDS])
def test_documented_render_command_runs(page, cmd, tmp_path, monkeypatch):
    skip = [why for key, why in SKIPPED.items() if key in cmd]
    if skip:
        pytest.skip(skip[0])
    from clvol.cli import main
    monkeypatch.chdir(ROOT)                          # the pages' paths are from the root
    argv = runnable(cmd, tmp_path)
    assert main(argv) == 0, f"{page}: {cmd}\nran as: clvol {' '.join(argv)}"
    assert list(tmp_path.glob("*.exr")), f"{page}: {cmd} wrote no EXR"
