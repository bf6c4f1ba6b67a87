"""The documentation names what ships: every example scene is listed in docs/scenes.md."""
from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_example_is_named_in_docs_scenes():
    text = (ROOT / "docs" / "scenes.md").read_text()
    missing = [p.name for p in sorted((ROOT / "examples").glob("*.toml"))
               if f"examples/{p.name}" not in text]
    assert not missing, f"docs/scenes.md does not name {missing}"
