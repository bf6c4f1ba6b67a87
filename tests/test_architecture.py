"""The layers of docs/architecture.md, read from the import statements of clvol/ (ast, nothing
imported): kernel wrappers never import the render layer above them, and torch stays in the
two training modules. Also read with ast: no function of clvol/ is longer than 80 lines unless
its docstring says why."""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CLVOL = ROOT / "clvol"


def import_statements(path: Path):
    """(module, names) for every import statement of ``path``, anywhere in it, relative
    imports resolved: ``import a.b`` gives ("a.b", []), ``from .x import y, z`` ("pkg.x",
    ["y", "z"])."""
    package = list(path.relative_to(ROOT).with_suffix("").parts[:-1])
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, []
        elif isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            yield ".".join(base + ([node.module] if node.module else [])), \
                [a.name for a in node.names]


def imports(path: Path) -> set[str]:
    """Absolute names of the modules ``path`` imports (relative imports resolved), and of
    the names it takes from them."""
    out = set()
    for mod, names in import_statements(path):
        out.add(mod)
        out.update(f"{mod}.{n}" for n in names)
    return out


def modules(folder: Path):
    return sorted(p for p in folder.rglob("*.py") if "_cl" not in p.parts)


def test_imports_resolve_relative_names():
    got = imports(CLVOL / "kernels" / "majorant.py")
    assert "clvol.errors" in got and "clvol.kernels.grid" in got and "numpy" in got


def test_twins_import_nothing_from_clvol():
    """reference/ is the independent statement of every kernel: it imports nothing from
    clvol (not even the feature contract; tests hold its own constants equal to clvol's)."""
    bad = {p.name: sorted(m for m in imports(p) if m == "clvol" or m.startswith("clvol."))
           for p in modules(ROOT / "reference")}
    assert not {k: v for k, v in bad.items() if v}


def test_kernels_do_not_import_the_render_layer():
    above = ("clvol.render", "clvol.viewer", "clvol.cli", "clvol.bundle")
    bad = {p.name: sorted(m for m in imports(p) if m.startswith(above))
           for p in modules(CLVOL / "kernels")}
    assert not {k: v for k, v in bad.items() if v}


def test_torch_only_in_the_training_modules():
    training = {CLVOL / "neural" / "model.py", CLVOL / "neural" / "train.py",
                CLVOL / "neural" / "raytrain.py"}
    users = {p.relative_to(ROOT).as_posix() for p in modules(CLVOL)
             if any(m == "torch" or m.startswith("torch.") for m in imports(p))}
    assert users == {p.relative_to(ROOT).as_posix() for p in training}


# docs/architecture.md, "Layers": a module imports only its own layer and the ones before it.
LAYERS = [
    ("base", ["errors", "atomic", "progress", "runtime", "__init__"]),
    ("data", ["scenemodel", "scenefile", "scene", "envmap", "emission", "volume", "image",
              "metrics"]),
    ("network contract", ["neural.layout", "neural.templates", "neural.phasetable",
                          "neural.export", "neural.__init__"]),
    ("kernels", ["kernels"]),
    ("render", ["render"]),
    ("training", ["neural.dataset", "neural.distributed", "neural.labels", "neural.model",
                  "neural.train", "neural.raytrain"]),
    ("applications", ["cli", "__main__", "viewer", "bundle", "goldens", "sequence"]),
]


def layer_of(module: str) -> int:
    """Index in LAYERS of a clvol module ("clvol.render.ms.network"), by its longest listed prefix."""
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


# --------------------------------------------------------------------------- import circles

def module_name(path: Path) -> str:
    """"clvol.render.ms.network" for clvol/render/ms/network.py, "clvol.render" for its __init__.py."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph() -> dict[str, set[str]]:
    """Module -> the clvol modules it imports, anywhere in its source: at the top, in a function
    (a lazy import is an edge all the same: it is the usual way a circle is hidden) or under
    TYPE_CHECKING. ``from clvol.x import y`` is an edge to clvol.x.y when that is a module, else
    to clvol.x. The packages above a module are not edges of their own."""
    known = {module_name(p): p for p in modules(CLVOL)}
    graph = {}
    for name, path in known.items():
        targets = set()
        for mod, names in import_statements(path):
            targets.update([f"{mod}.{n}" if f"{mod}.{n}" in known else mod for n in names]
                           or [mod])
        edges = set()
        for m in targets:
            while m and m not in known:       # a name inside a module: the module
                m = m.rpartition(".")[0]
            if m and m != name:
                edges.add(m)
        graph[name] = edges
    return graph


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted: every
    module of one lies on a circle through the others."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(out)


def test_import_circles_are_found():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": {"e"}}
    assert import_circles(graph) == [["a", "b", "c"]]
    assert import_circles({"a": {"b"}, "b": set()}) == []


def test_import_graph_counts_function_level_imports():
    # clvol/render/renderer.py imports the ray marcher inside a method only
    assert "clvol.render.raymarch" in import_graph()["clvol.render.renderer"]


# Circles left on purpose, each with its reason: a circle not listed here fails the test below,
# and so does a listed one that is gone (take it off the list). None today.
KNOWN_CIRCLES: dict[tuple[str, ...], str] = {}


def test_no_import_circles_inside_clvol():
    found = {tuple(c) for c in import_circles(import_graph())}
    new = sorted(found - set(KNOWN_CIRCLES))
    assert not new, "import circles in clvol/: " + "; ".join(" <-> ".join(c) for c in new)
    assert not set(KNOWN_CIRCLES) - found, "listed in KNOWN_CIRCLES but gone: remove them"


# --------------------------------------------------------------------------- function length

MAX_FUNCTION_LINES = 80     # from the def line to the last line of the body
REASON = "Long because"     # a longer function says why in its docstring, with these words

# Longer functions left without a reason, each to be split: a listed one that is short (or
# has its reason) by now fails the test below too: take it off the list.
LONG_FUNCTIONS_TO_SPLIT: set[str] = set()


def long_functions(path: Path, name: str, limit: int = MAX_FUNCTION_LINES) -> dict[str, int]:
    """"name::Class.function" -> lines of every function (methods and nested functions too)
    of the module at ``path`` longer than ``limit`` lines whose docstring gives no reason."""
    out = {}

    def visit(node, prefix):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                qual = f"{prefix}{child.name}"
                if not isinstance(child, ast.ClassDef):
                    lines = child.end_lineno - child.lineno + 1
                    if lines > limit and REASON not in (ast.get_docstring(child) or ""):
                        out[f"{name}::{qual}"] = lines
                visit(child, qual + ".")
            else:
                visit(child, prefix)

    visit(ast.parse(path.read_text(), str(path)), "")
    return out


def test_long_functions_are_found(tmp_path):
    def body(indent, n):
        return "".join(f"{' ' * indent}x{i} = {i}\n" for i in range(n))
    (tmp_path / "m.py").write_text(
        "def ok():\n" + body(4, 79)                                    # 80 lines: allowed
        + "class C:\n    def long(self):\n" + body(8, 80)             # 81 lines
        + "def told():\n    \"\"\"Long because a reason.\"\"\"\n" + body(4, 90)
        + "def outer():\n    def inner():\n" + body(8, 80) + "    return inner\n")
    assert long_functions(tmp_path / "m.py", "m.py") == \
        {"m.py::C.long": 81, "m.py::outer": 83, "m.py::outer.inner": 81}


def test_no_function_is_longer_than_80_lines_without_a_reason():
    """A function does one thing whose steps have names (issue 23): past 80 lines it is split,
    or its docstring says why not ("Long because ...")."""
    found = {}
    for path in modules(CLVOL):
        found.update(long_functions(path, path.relative_to(ROOT).as_posix()))
    new = {k: v for k, v in found.items() if k not in LONG_FUNCTIONS_TO_SPLIT}
    assert not new, "split these, or say why in their docstring ('Long because ...'): " + \
        ", ".join(f"{k} ({v} lines)" for k, v in sorted(new.items()))
    assert not LONG_FUNCTIONS_TO_SPLIT - set(found), \
        "listed in LONG_FUNCTIONS_TO_SPLIT but short now: remove them"
