"""Render options: one table per method, one ``Options`` object per Renderer.

Each render method declares its options once, in ``add_arguments(group)`` (argparse: names,
types, defaults, help); this module records them per method, so the CLI and ``Renderer``
share that one table and the same defaults: ``method_options(method)`` gives {name:
default}, and ``bind(method, given)`` returns an ``Options``. Python names are positive
(``shortcuts=False``); the CLI's flag for a default-on switch is its negation
(``--no-shortcuts``, argparse ``dest="shortcuts"``, ``store_false``).

An option unknown to the method is refused at once. An option the method knows but never
reads for this configuration (``weights`` with ``--ms none``) is found Mitsuba's way: the
``Options`` records what was read, and the Renderer refuses what the method and its source
never read (``Options.unused``), not by a second declared table.
"""
from __future__ import annotations

import argparse
from collections.abc import Mapping
from functools import lru_cache

from ..errors import ClvolError

# Options defined by the CLI for every method but used only by some.
SHARED = {"seed": (("--seed",), dict(type=int, default=0,
                                     help="random seed (same seed, same image): the path "
                                          "tracer, and the ray marcher with --ms stochastic"),
                   ("pathtrace", "raymarch"))}
DEFAULT_METHOD = "raymarch"


def flag(name: str) -> str:
    """The CLI spelling of an option (a default-on switch is given as its negation)."""
    flags = _flags_of(name)
    return flags[0] if flags else "--" + name.replace("_", "-")


def _flags_of(name: str) -> tuple:
    from . import METHODS
    for method in METHODS:
        try:
            decl = _declared(method)
        except ClvolError:
            continue
        if name in decl:
            return tuple(f for f in decl[name][0] if f.startswith("--"))
    return SHARED[name][0] if name in SHARED else ()


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
    if kw.get("action") == "store_false":
        return True
    return kw.get("default")


def method_options(method: str) -> dict:
    """{option name: default} of a render method."""
    return {k: _default(kw) for k, (_, kw) in _declared(method).items()}


class Options(Mapping):
    """A method's options: its declared defaults with the caller's values, and a record of
    which were read. Read like a dict (``o["step"]``, ``o.get("seed")``) or by attribute
    (``o.step``); ``unused()`` lists the given options nothing read."""

    def __init__(self, method: str, values: dict, given):
        self.method = method
        self._values = dict(values)
        self.given = frozenset(given)
        self.read: set = set()

    def __getitem__(self, name):
        value = self._values[name]
        self.read.add(name)
        return value

    def __getattr__(self, name):
        if name.startswith("_"):
            raise AttributeError(name)
        try:
            return self[name]
        except KeyError:
            raise AttributeError(f"{self.method} has no option {name!r}") from None

    def __iter__(self):
        return iter(self._values)

    def __len__(self) -> int:
        return len(self._values)

    def set(self, name: str, value) -> None:
        """Replace a value (the Renderer normalises one: a grid file read, max_order's ms)."""
        if name not in self._values:
            raise KeyError(name)
        self._values[name] = value

    def unused(self) -> list[str]:
        """The options the caller gave that nothing has read."""
        return sorted(self.given - self.read)

    def __repr__(self) -> str:
        return f"Options({self.method!r}, {self._values!r})"


def bind(method: str, given: dict) -> Options:
    """The method's options with ``given`` applied; ClvolError for an option it does not
    know (unused ones are refused after the method read what it needs: ``Options.unused``)."""
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
    return Options(method, out, given)


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
