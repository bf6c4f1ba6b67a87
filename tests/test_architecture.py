"""The layers of docs/architecture.md, read from the import statements of clvol/ (ast, nothing
imported): kernel wrappers never import the render layer above them, and torch stays in the
two training modules."""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CLVOL = ROOT / "clvol"


def imports(path: Path) -> set[str]:
    """Absolute names of the modules ``path`` imports (relative imports resolved)."""
    package = list(path.relative_to(ROOT).with_suffix("").parts[:-1])
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            mod = ".".join(base + ([node.module] if node.module else []))
            out.add(mod)
            out.update(f"{mod}.{a.name}" for a in node.names)
    return out


def modules(folder: Path):
    return sorted(p for p in folder.rglob("*.py") if "_cl" not in p.parts)


def test_imports_resolve_relative_names():
    got = imports(CLVOL / "kernels" / "majorant.py")
    assert "clvol.errors" in got and "clvol.kernels.grid" in got and "numpy" in got


def test_kernels_do_not_import_the_render_layer():
    above = ("clvol.render", "clvol.viewer", "clvol.cli", "clvol.bundle")
    bad = {p.name: sorted(m for m in imports(p) if m.startswith(above))
           for p in modules(CLVOL / "kernels")}
    assert not {k: v for k, v in bad.items() if v}


def test_torch_only_in_the_training_modules():
    training = {CLVOL / "neural" / "model.py", CLVOL / "neural" / "train.py"}
    users = {p.relative_to(ROOT).as_posix() for p in modules(CLVOL)
             if any(m == "torch" or m.startswith("torch.") for m in imports(p))}
    assert users == {p.relative_to(ROOT).as_posix() for p in training}
