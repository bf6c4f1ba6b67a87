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


# docs/architecture.md, "Layers": a module imports only its own layer and the ones before it.
LAYERS = [
    ("base", ["errors", "atomic", "progress", "runtime", "__init__"]),
    ("data", ["scene", "scenefile", "envmap", "volume", "image", "metrics"]),
    ("network contract", ["neural.layout", "neural.templates", "neural.phasetable",
                          "neural.export", "neural.__init__"]),
    ("kernels", ["kernels"]),
    ("render", ["render"]),
    ("training", ["neural.dataset", "neural.distributed", "neural.labels", "neural.model",
                  "neural.train"]),
    ("applications", ["cli", "__main__", "viewer", "bundle", "goldens"]),
]


def layer_of(module: str) -> int:
    """Index in LAYERS of a clvol module ("clvol.render.network"), by its longest listed prefix."""
    name = "__init__" if module == "clvol" else module.removeprefix("clvol.")
    best = None
    for i, (_, prefixes) in enumerate(LAYERS):
        for p in prefixes:
            if (name in (p, f"{p}.__init__") or name.startswith(p + ".")
                    or f"{name}.__init__" == p) and (best is None or len(p) > best[1]):
                best = (i, len(p))
    assert best is not None, f"{module} is in no layer of docs/architecture.md"
    return best[0]


def test_every_module_imports_only_its_layer_and_those_before():
    up = []
    for path in modules(CLVOL):
        mod = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        own = layer_of(mod)
        for m in imports(path):
            # the package itself (clvol/__init__.py) resolves names lazily for users
            if (m == "clvol" or m.startswith("clvol.")) and mod != "clvol.__init__":
                try:
                    target = layer_of(m)
                except AssertionError:     # a name imported from a module: the module's layer
                    target = layer_of(m.rsplit(".", 1)[0])
                if target > own:
                    up.append(f"{mod} ({LAYERS[own][0]}) imports {m} ({LAYERS[target][0]})")
    assert not up, "\n".join(up)
