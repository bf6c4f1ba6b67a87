"""The numbers a kernel's code fixes and the host needs too, read from the one place they are
written: ``cl/include/constants.h`` (its comment says what each one is).

    TILE = kernel_constant("TILE")        # clvol/kernels/raymarch.py

The header holds only include guards, comments and ``#define NAME integer`` lines, so it is read
here without a preprocessor; any other line is an error (a value the host could not read would
otherwise be a value the host silently does not know). tests/test_constants.py checks that a
built program sees the values read here.
"""
from __future__ import annotations

import functools
import re

from ..errors import BuildError
from ..runtime import include_dir

HEADER = "constants.h"

_DEFINE = re.compile(r"#define\s+([A-Z][A-Z0-9_]*)\s+(-?\d+)")
_GUARD = {"#ifndef CLVOL_CONSTANTS_H", "#define CLVOL_CONSTANTS_H", "#endif"}


def parse_constants(text: str) -> dict[str, int]:
    """NAME -> value of every ``#define NAME integer`` line of the header's ``text``."""
    text = re.sub(r"/\*.*?\*/", " ", text, flags=re.DOTALL)
    values: dict[str, int] = {}
    for line in (" ".join(l.split()) for l in text.splitlines()):
        if not line or line in _GUARD:
            continue
        m = _DEFINE.fullmatch(line)
        if m is None:
            raise BuildError(f"cl/include/{HEADER}: {line!r} is not '#define NAME integer' "
                             f"(the Python host reads this file without a preprocessor)")
        if m[1] in values:
            raise BuildError(f"cl/include/{HEADER}: {m[1]} is defined twice")
        values[m[1]] = int(m[2])
    return values


@functools.lru_cache(maxsize=1)
def kernel_constants() -> dict[str, int]:
    """Every constant of ``cl/include/constants.h``."""
    return parse_constants((include_dir() / HEADER).read_text())


def kernel_constant(name: str) -> int:
    """The value of ``#define name`` in ``cl/include/constants.h``."""
    values = kernel_constants()
    if name not in values:
        raise BuildError(f"cl/include/{HEADER} defines no {name} (it has {', '.join(values)})")
    return values[name]
