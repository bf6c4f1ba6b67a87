"""The layers of docs/architecture.md, read from the import statements of clvol/ (ast, nothing
imported): no import climbs a layer, no files import each other in a circle, torch stays in
the training package and the feature contract needs no device. Also read with ast: no function
of clvol/ is longer than 80 lines unless its docstring says why."""
import ast
import sys
from pathlib import Path

import pytest

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


def test_no_import_circles_inside_clvol():
    """No file imports itself through others: the graph of every import in clvol/ (lazy ones in
    functions included) has no strongly connected component of more than one module."""
    found = import_circles(import_graph())
    assert not found, "import circles in clvol/: " + "; ".join(" <-> ".join(c) for c in found)


# --------------------------------------------------------------------------- layers

# docs/architecture.md, "Layers", bottom first: a module imports only modules of its own layer
# and of the layers before it (no arrow climbs). Each entry is a module or a package (all of its
# modules); the root "clvol" (no dot) is its own __init__.py only.
LAYERS: list[tuple[str, set[str]]] = [
    ("base", {"clvol.errors", "clvol.atomic", "clvol.progress"}),
    ("features", {"clvol.features"}),
    ("device", {"clvol.runtime"}),
    ("data", {"clvol.scenemodel", "clvol.scenefile", "clvol.scene", "clvol.envmap",
              "clvol.emission", "clvol.volume", "clvol.image", "clvol.metrics"}),
    ("kernels", {"clvol.kernels"}),
    ("render", {"clvol.render"}),
    ("training", {"clvol.training"}),
    ("applications", {"clvol", "clvol.__main__", "clvol.cli", "clvol.viewer", "clvol.bundle",
                      "clvol.goldens", "clvol.sequence"}),
]


def layer_of(module: str, layers=LAYERS) -> int:
    """Index in ``layers`` of a module ("clvol.render.ms.network"): the one layer with an entry
    that is the module or a package above it (a root package, with no dot, only itself)."""
    hits = {i for i, (_, entries) in enumerate(layers) for e in entries
            if module == e or ("." in e and module.startswith(e + "."))}
    assert len(hits) == 1, f"{module} is in {len(hits)} layers of docs/architecture.md, not one"
    return hits.pop()


def climbing_arrows(graph: dict[str, set[str]], layers=LAYERS) -> list[str]:
    """Every import arrow of ``graph`` into a higher layer than its own."""
    return [f"{a} ({layers[layer_of(a, layers)][0]}) imports {b} ({layers[layer_of(b, layers)][0]})"
            for a in sorted(graph) for b in sorted(graph[a])
            if layer_of(b, layers) > layer_of(a, layers)]


def test_climbing_arrows_are_found():
    layers = [("low", {"p.low"}), ("high", {"p", "p.high"})]
    graph = {"p.low.a": {"p.low.b", "p.high"}, "p.low.b": set(), "p.high": {"p.low.a"},
             "p": {"p.high", "p.low.b"}}
    assert climbing_arrows(graph, layers) == ["p.low.a (low) imports p.high (high)"]
    with pytest.raises(AssertionError, match="in 0 layers"):
        layer_of("q.a", layers)
    with pytest.raises(AssertionError, match="in 2 layers"):
        layer_of("p.low.a", layers + [("again", {"p.low.a"})])


def test_every_module_is_in_one_layer():
    for name in import_graph():
        layer_of(name)


def test_no_arrow_climbs():
    """Every import of clvol/ (lazy ones in functions too) goes to the importer's own layer or
    one below it: the kernels read the feature contract, training sits above the renderer."""
    up = climbing_arrows(import_graph())
    assert not up, "imports that climb a layer:\n" + "\n".join(up)


def test_torch_only_in_the_training_package():
    """torch in the training package only, and there in the model and the trainers (data sets
    are made without it: `clvol dataset` needs no torch)."""
    users = {p.relative_to(ROOT).as_posix() for p in modules(CLVOL)
             if any(m == "torch" or m.startswith("torch.") for m in imports(p))}
    assert users == {"clvol/training/model.py", "clvol/training/train.py",
                     "clvol/training/raytrain.py"}


def test_the_feature_contract_needs_only_numpy_and_scipy():
    """clvol/features/ imports the standard library, NumPy, SciPy and clvol's base layer only
    (no torch, no pyopencl, no ray): whoever reads a weight file or the contract needs no device."""
    allowed = {"numpy", "scipy", "clvol"} | set(sys.stdlib_module_names)
    bad = {p.name: sorted(m for m in imports(p) if m.split(".")[0] not in allowed)
           for p in modules(CLVOL / "features")}
    assert not {k: v for k, v in bad.items() if v}


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


# --------------------------------------------------------------------------- sources decide

MS = CLVOL / "render" / "ms"


def _ms_classes() -> dict:
    """Every class defined in clvol/render/ms/: name -> (base names, its own ``name = "..."``)."""
    out = {}
    for p in modules(MS):
        for node in ast.walk(ast.parse(p.read_text(), str(p))):
            if isinstance(node, ast.ClassDef):
                own = [s.value.value for s in node.body if isinstance(s, ast.Assign)
                       and isinstance(s.value, ast.Constant) and isinstance(s.value.value, str)
                       and any(isinstance(t, ast.Name) and t.id == "name" for t in s.targets)]
                bases = [b.id if isinstance(b, ast.Name) else getattr(b, "attr", "")
                         for b in node.bases]
                out[node.name] = (bases, own[0] if own else None)
    return out


def registered_source_names() -> set[str]:
    """The ``--ms`` names of the registry (clvol/render/ms/__init__.py ``SOURCES``): the classes
    its table lists, each class's ``name`` read from it or the nearest base that sets one."""
    classes = _ms_classes()

    def name_of(cls):
        bases, own = classes[cls]
        return own if own is not None else next(
            (n for b in bases if b in classes for n in [name_of(b)] if n), None)
    tree = ast.parse((MS / "__init__.py").read_text())
    table = next(n for n in ast.walk(tree) if isinstance(n, (ast.Assign, ast.AnnAssign))
                 and getattr(n.targets[0] if isinstance(n, ast.Assign) else n.target,
                             "id", None) == "SOURCES")
    listed = [e.id for n in ast.walk(table.value) if isinstance(n, ast.Tuple)
              for e in n.elts if isinstance(e, ast.Name) and e.id in classes]
    return {name_of(c) for c in listed}


def _strings(node) -> list:
    """The string constants of ``node``, or of the tuple, list or set it is."""
    items = node.elts if isinstance(node, (ast.Tuple, ast.List, ast.Set)) else [node]
    return [i.value for i in items if isinstance(i, ast.Constant) and isinstance(i.value, str)]


def source_checks(path: Path, classes, names) -> list[str]:
    """"file:line: what" for each class check against a clvol/render/ms/ class and each
    comparison with a string naming a registered source, in ``path``: either side of ==, !=,
    is, is not; an element of the right side of in, not in (``"grid" in table`` asks about a
    key, not a source)."""
    where = path.relative_to(ROOT) if ROOT in path.parents else path.name
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                and node.func.id in ("isinstance", "issubclass") and len(node.args) == 2):
            arg = node.args[1]
            items = arg.elts if isinstance(arg, ast.Tuple) else [arg]
            hit = [h for i in items for h in [getattr(i, "id", getattr(i, "attr", None))]
                   if h in classes]
            if hit:
                out.append(f"{where}:{node.lineno}: {node.func.id}(..., {hit[0]})")
        elif isinstance(node, ast.Compare):
            sides = [node.left, *node.comparators]
            hit = [s for k, op in enumerate(node.ops)
                   for side, tuple_ok in ((sides[k], False), (sides[k + 1], True))
                   if isinstance(op, (ast.Eq, ast.NotEq, ast.Is, ast.IsNot))
                   or (tuple_ok and isinstance(op, (ast.In, ast.NotIn)))
                   for s in (_strings(side) if tuple_ok or not isinstance(
                       side, (ast.Tuple, ast.List, ast.Set)) else []) if s in names]
            if hit:
                out.append(f"{where}:{node.lineno}: compares {hit[0]!r}")
    return out


def test_source_names_are_read_from_the_registry():
    assert registered_source_names() == {"none", "wrenninge", "lattice", "network", "view",
                                         "stochastic", "progressive"}


def test_source_checks_are_found(tmp_path):
    p = tmp_path / "planted.py"
    p.write_text("def f(s, cls, plan, t):\n"
                 "    if isinstance(s, NetworkMs) or issubclass(cls, (int, m.ViewMs)):\n"
                 "        return plan.source == 'network' or plan.source in ('view', 'x')\n"
                 "    if 'stochastic' != plan.source or plan.ms not in ['none']:\n"
                 "        return 1\n"
                 "    return s.uses_network and plan.kind == 'other' and 'grid' in t\n")
    got = [h.split(": ", 1)[1] for h in source_checks(p, _ms_classes(),
                                                     registered_source_names())]
    assert sorted(got) == sorted([
        "isinstance(..., NetworkMs)", "issubclass(..., ViewMs)", "compares 'network'",
        "compares 'view'", "compares 'stochastic'", "compares 'none'"])


def test_no_class_or_name_check_on_a_source_outside_its_package():
    """A source declares what it can do (clvol/render/ms/base.py: ``uses_network``,
    ``bundle_supported``, ``choose_for``, ...), so nothing outside clvol/render/ms/ asks which
    source it is: no isinstance/issubclass against a class of clvol/render/ms/ and no
    comparison with a registered ``--ms`` name ("none", "network", ...)."""
    classes, names = _ms_classes(), registered_source_names()
    bad = [hit for p in modules(CLVOL) if MS not in p.parents
           for hit in source_checks(p, classes, names)]
    assert not bad, "\n".join(bad)
