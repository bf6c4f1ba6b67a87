"""Render options bound to the methods (and multiple-scattering sources) that use them.

Each render method declares its options in ``add_arguments(group)`` (argparse); this module
records them per method, so the CLI and ``Renderer`` share one table:
``method_options(method)`` gives {name: default}, and ``bind(method, given)`` returns the
full option set or refuses, naming the option and the method, an option the method does not
use (as pbrt-v4's ReportUnused does). Names are the CLI's with dashes as underscores.
"""
from __future__ import annotations

import argparse
from functools import lru_cache

from ..errors import ClvolError

# Options defined by the CLI for every method but used only by some.
SHARED = {"seed": (("--seed",), dict(type=int, default=0,
                                     help="random seed (same seed, same image): the path "
                                          "tracer, and the ray marcher with --ms stochastic"),
                   ("pathtrace", "raymarch"))}
DEFAULT_METHOD = "raymarch"


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def option_label(name: str) -> str:
    """How a message names an option for both of its spellings: ``spp (--spp)`` (the
    Renderer keyword, then the CLI flag)."""
    return f"{name} ({flag(name)})"


class _Recorder:
    """Stands in for an argparse group: records each option's flags and keywords."""

    def __init__(self):
        self.options: dict[str, tuple[tuple, dict]] = {}

    def add_argument(self, *flags, **kw):
        dest = kw.get("dest") or next(f for f in flags if f.startswith("--"))[2:].replace("-", "_")
        self.options[dest] = (flags, kw)


@lru_cache(maxsize=None)
def _declared(method: str) -> dict:
    from . import method_module
    rec = _Recorder()
    mod = method_module(method)
    if hasattr(mod, "add_arguments"):
        mod.add_arguments(rec)
    for name, (flags, kw, methods) in SHARED.items():
        if method in methods:
            rec.options[name] = (flags, kw)
    return rec.options


def _default(kw: dict):
    if kw.get("action") == "store_true":
        return False
    return kw.get("default")


def method_options(method: str) -> dict:
    """{option name: default} of a render method."""
    return {k: _default(kw) for k, (_, kw) in _declared(method).items()}


def bind(method: str, given: dict) -> dict:
    """The method's options with ``given`` applied; ClvolError for an option it does not use."""
    from . import METHODS
    known = method_options(method)
    for name in given:
        if name not in known:
            users = [m for m in METHODS if name in method_options(m)]
            if users:
                raise ClvolError(f"option {option_label(name)} is not used by method {method!r} "
                                 f"(it is an option of {', '.join(users)})")
            import difflib
            close = difflib.get_close_matches(name, list(known), n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise ClvolError(f"unknown render option {name!r}: {hint}(method {method!r} takes "
                             f"{', '.join(sorted(known))})")
    out = dict(known)
    out.update(given)
    return out


def add_cli_arguments(parser, methods) -> None:
    """Every method's options on the ``render`` parser, each once, defaulting to "not given"
    (argparse.SUPPRESS) so that ``given_options(args)`` sees only what the user typed."""
    seen = set()
    for name, (flags, kw, _) in SHARED.items():
        parser.add_argument(*flags, **dict(kw, default=argparse.SUPPRESS))
        seen.add(name)
    for method in methods:
        group = parser.add_argument_group(f"{method} options")
        for name, (flags, kw) in _declared(method).items():
            if name in seen:
                continue
            seen.add(name)
            group.add_argument(*flags, **dict(kw, default=argparse.SUPPRESS))


def given_options(args, methods) -> dict:
    names = set(SHARED)
    for m in methods:
        names |= set(_declared(m))
    return {k: getattr(args, k) for k in sorted(names) if hasattr(args, k)}
