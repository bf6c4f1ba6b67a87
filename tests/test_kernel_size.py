"""Kernels a reader can hold (issue 37 item 5): no function of any kernel source or header in cl/
is longer than LIMIT body lines. The long kernels (raymarch, pt_events,
transmittance_sweep_block) were split into named stage functions; this keeps a new stage from
growing back inside them. Read as text (nothing built): a function starts at
column 0 with its name and an opening parenthesis, its body is the lines between its opening
brace and the next ``}`` at column 0 (the files' layout)."""
import re
from pathlib import Path

import pytest

CL = Path(__file__).resolve().parents[1] / "cl"
LIMIT = 120
SOURCES = sorted(p.relative_to(CL).as_posix() for p in CL.rglob("*") if p.suffix in (".cl", ".h"))
_HEADER = re.compile(r"^(?:__kernel\s+)?[A-Za-z_]\w*(?:\s+\w+)*[\s*]+([A-Za-z_]\w*)\s*\(")


def function_bodies(text: str) -> dict[str, int]:
    """{name: body lines} of every function defined in a .cl source."""
    lines = text.splitlines()
    out, i = {}, 0
    while i < len(lines):
        m = _HEADER.match(lines[i])
        if not m or lines[i].startswith(("typedef", "return")):
            i += 1
            continue
        j = i
        while j < len(lines) and not lines[j].rstrip().endswith("{") and not lines[j].rstrip().endswith(";"):
            j += 1
        if j == len(lines) or lines[j].rstrip().endswith(";"):   # a declaration
            i = j + 1
            continue
        end = next(k for k in range(j + 1, len(lines)) if lines[k].startswith("}"))
        out[m.group(1)] = end - j - 1
        i = end + 1
    return out


def test_the_reader_finds_the_kernels_and_their_helpers():
    bodies = function_bodies((CL / "raymarch.cl").read_text())
    assert {"raymarch", "lookupL", "store_lanes"} <= set(bodies)
    assert all(n > 0 for n in bodies.values())
    sample = "__kernel void k(\n    int a)\n{\n    a;\n    a;\n}\nfloat f(int x) {\n    x;\n}\n"
    assert function_bodies(sample) == {"k": 2, "f": 1}


@pytest.mark.parametrize("name", SOURCES)
def test_no_function_of_a_kernel_source_is_longer_than_the_limit(name):
    bodies = function_bodies((CL / name).read_text())
    long = {f: n for f, n in bodies.items() if n > LIMIT}
    assert not long, f"cl/{name}: functions over {LIMIT} body lines: {long}"
