"""Each named default is written once (issue 37): its constant is assigned in one module and
everything else that carries it (keyword defaults, dataclass fields, CLI option defaults,
help texts) names the constant instead of repeating its value.

The test reads every module of clvol/ (ast, no import of what it checks) and looks, for each
default in NAMED, for its literal value where a copy would hide: a second module-level
assignment of the name, a parameter or dataclass field of the names that carry it with the
literal as its default, an option (``add_argument``/``option`` with its flag) whose
``default=`` is the literal, and an option's help text that states "default <value>" in
literal text rather than formatting the constant.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CLVOL = ROOT / "clvol"

# (home module, constant, names of the parameters / fields / options that carry it)
NAMED = [
    ("clvol/features/layout.py", "DEFAULT_LAMBDA", ("lam", "lambda_")),
    ("clvol/kernels/raymarch.py", "DEFAULT_OCTAVES", ("octaves", "n")),
    ("clvol/kernels/raymarch.py", "DEFAULT_OCTAVE_MULTIPLIER", ("a", "b", "c", "ms_a", "ms_b",
                                                                "ms_c")),
    ("clvol/kernels/raymarch.py", "DEFAULT_THRESHOLD", ("threshold",)),
    ("clvol/render/raymarch.py", "DEFAULT_STEP", ("step",)),
    ("clvol/render/raymarch.py", "DEFAULT_SUPERSAMPLE", ("supersample",)),
    ("clvol/render/plan.py", "MAX_LIGHT_RESOLUTION", ("cap", "light_resolution")),
    ("clvol/render/environment.py", "DEFAULT_ENV_DIRECTIONS", ("env_directions",)),
    ("clvol/render/environment.py", "DEFAULT_ENV_RESOLUTION", ("env_resolution",)),
    ("clvol/render/environment.py", "DEFAULT_ENV_MS_DIRECTIONS", ("env_ms_directions",)),
    ("clvol/render/ms/network.py", "DEFAULT_NETWORK_RESOLUTION", ("ms_resolution",
                                                                  "resolution")),
    ("clvol/render/ms/view.py", "DEFAULT_VIEW_BLOCK", ("view_block", "block")),
    ("clvol/render/ms/view.py", "DEFAULT_VIEW_KNOTS", ("view_knots", "knots")),
    ("clvol/render/ms/view.py", "DEFAULT_VIEW_SAMPLES", ("view_samples", "samples")),
]


def modules():
    return sorted(p for p in CLVOL.rglob("*.py") if "data" not in p.relative_to(CLVOL).parts)


def home_value(home: str, name: str):
    tree = ast.parse((ROOT / home).read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == name
                                                for t in node.targets):
            return ast.literal_eval(node.value)
    raise AssertionError(f"{home} does not assign {name}")


def _is_value(node, value) -> bool:
    if not isinstance(node, ast.Constant) or isinstance(node.value, (bool, str)):
        return False
    return type(node.value) in (int, float) and node.value == value


def _flag_names(call: ast.Call) -> set:
    """The option names a CLI declaration (``add_argument``/``option``) stands for."""
    out = set()
    for a in call.args:
        if isinstance(a, ast.Constant) and isinstance(a.value, str) and a.value.startswith("--"):
            out.add(a.value[2:].replace("-", "_").removeprefix("no_"))
    for k in call.keywords:
        if k.arg == "dest" and isinstance(k.value, ast.Constant):
            out.add(k.value.value)
    return out


def _literal_text(node) -> str:
    """The literal parts of a string or f-string (the formatted fields left out)."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    if isinstance(node, ast.JoinedStr):
        return "\x00".join(v.value for v in node.values if isinstance(v, ast.Constant))
    if isinstance(node, ast.BinOp):
        return _literal_text(node.left) + "\x00" + _literal_text(node.right)
    return ""


def _spellings(value) -> list[str]:
    return sorted({str(value), f"{value:g}"} | ({f"{value:.0e}".replace("e-0", "e-")}
                                                if isinstance(value, float) else set()))


def copies(path: Path, home: str, name: str, carriers: tuple, value) -> list[str]:
    """Where ``path`` writes ``value`` again instead of naming ``name``."""
    rel = path.relative_to(ROOT).as_posix()
    tree = ast.parse(path.read_text())
    out = []
    if rel != home:
        for node in tree.body:
            if isinstance(node, (ast.Assign, ast.AnnAssign)):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                if any(isinstance(t, ast.Name) and t.id == name for t in targets):
                    out.append(f"{rel}:{node.lineno}: assigns {name} again")
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            a = node.args
            pos = a.posonlyargs + a.args
            pairs = list(zip(pos[len(pos) - len(a.defaults):], a.defaults))
            pairs += [(k, d) for k, d in zip(a.kwonlyargs, a.kw_defaults) if d is not None]
            out += [f"{rel}:{d.lineno}: {node.name}({arg.arg}={d.value!r}) repeats {name}"
                    for arg, d in pairs if arg.arg in carriers and _is_value(d, value)]
        elif isinstance(node, ast.ClassDef):
            for st in node.body:
                if (isinstance(st, ast.AnnAssign) and isinstance(st.target, ast.Name)
                        and st.target.id in carriers and _is_value(st.value, value)):
                    out.append(f"{rel}:{st.lineno}: {node.name}.{st.target.id} = "
                               f"{st.value.value!r} repeats {name}")
        elif isinstance(node, ast.Call) and _flag_names(node) & set(carriers):
            for k in node.keywords:
                if k.arg == "default" and _is_value(k.value, value):
                    out.append(f"{rel}:{node.lineno}: option default {k.value.value!r} "
                               f"repeats {name}")
                if k.arg == "help":
                    text = _literal_text(k.value)
                    for s in _spellings(value):
                        if f"default {s}" in text or f"default: {s}" in text:
                            out.append(f"{rel}:{node.lineno}: help says \"default {s}\" by "
                                       f"hand (format {name})")
    return out


@pytest.mark.parametrize("home, name, carriers", NAMED, ids=[n[1] for n in NAMED])
def test_each_named_default_is_written_once(home, name, carriers):
    value = home_value(home, name)
    bad = [hit for p in modules() for hit in copies(p, home, name, carriers, value)]
    assert not bad, "\n".join(bad)


# --------------------------------------------------------------------------- one default

def test_every_front_door_defaults_to_the_same_source(tmp_path):
    """Issue 39: the CLI, clvol.Renderer, the viewer and clvol bundle (hence libclvol) start
    from one multiple-scattering source, the registry's DEFAULT_SOURCE, with the same options:
    the bundle's manifest records the source and view options a Renderer plans with."""
    import clvol
    from clvol.cli import build_parser
    from clvol.render.ms import DEFAULT_SOURCE, source_class
    from clvol.viewer.state import METHODS as VIEWER_METHODS
    assert DEFAULT_SOURCE == "stochastic"
    assert source_class(DEFAULT_SOURCE).bundle_supported     # libclvol renders it
    # the CLI's --ms default for clvol render and clvol bundle
    ap = build_parser()
    scene = str(ROOT / "examples" / "cloud.toml")
    # (clvol render leaves an option it was not given unset: the Renderer's default applies)
    assert getattr(ap.parse_args(["render", scene, "-o", "x.exr"]), "ms", DEFAULT_SOURCE) \
        == DEFAULT_SOURCE
    assert ap.parse_args(["bundle", scene, str(tmp_path / "b")]).ms == DEFAULT_SOURCE
    # the Renderer
    r = clvol.Renderer(clvol.load_scene(scene))
    assert r.source.name == DEFAULT_SOURCE
    # the viewer's menu: its first entry is the default
    label, opts = next(iter(VIEWER_METHODS.items()))
    assert label == DEFAULT_SOURCE and opts.get("ms") == DEFAULT_SOURCE
    # the bundle (libclvol's input) as written by clvol bundle with no --ms
    from clvol.cli import main
    assert main(["bundle", scene, str(tmp_path / "b"), "--width", "32", "--height", "32"]) == 0
    lines = (tmp_path / "b" / "manifest.txt").read_text().splitlines()
    manifest = dict(ln.split("#")[0].split("=", 1) for ln in lines if "=" in ln.split("#")[0])
    manifest = {k.strip(): v.strip() for k, v in manifest.items()}
    sources = {k: v for k, v in manifest.items() if k.endswith("source") or k == "ms"}
    assert DEFAULT_SOURCE in sources.values(), sources
