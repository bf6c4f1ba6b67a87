"""setup.cfg ships every sub-package and every data file of clvol (a non-editable install
reads only what setup.cfg lists: a package missing there imports from a checkout, not from a
wheel)."""
import configparser
import fnmatch
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _options():
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / "setup.cfg")
    packages = set(cfg["options"]["packages"].split())
    data = {k: v.replace(",", " ").split() for k, v in cfg["options.package_data"].items()}
    return packages, data


def test_every_subpackage_is_listed():
    packages, _ = _options()
    found = {".".join(p.parent.relative_to(ROOT).parts)
             for p in (ROOT / "clvol").rglob("__init__.py") if "_cl" not in p.parts}
    assert found <= packages, f"add to setup.cfg [options] packages: {sorted(found - packages)}"
    assert "clvol._cl" in packages      # cl/, mapped by package_dir


def test_every_data_file_is_shipped():
    _, data = _options()
    others = [p.relative_to(ROOT).as_posix() for p in (ROOT / "clvol").rglob("*")
              if p.is_file() and p.suffix not in (".py", ".pyc") and "_cl" not in p.parts]
    assert any(f.startswith("clvol/data/weights/") for f in others)   # the check sees them
    missing = []
    for f in others:
        pkg_dir = Path(f).parent
        while pkg_dir != Path(".") and not (ROOT / pkg_dir / "__init__.py").exists():
            pkg_dir = pkg_dir.parent
        rel = Path(f).relative_to(pkg_dir).as_posix()
        globs = data.get(".".join(pkg_dir.parts), [])
        if not any(fnmatch.fnmatch(rel, g) and rel.count("/") == g.count("/") for g in globs):
            missing.append(f)
    assert not missing, f"not in setup.cfg [options.package_data]: {missing}"
