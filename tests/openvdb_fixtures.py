"""Make .vdb files with OpenVDB's own writer, for tests/test_vdb.py and bench/bench_vdb.py.

Debian's ``python3-openvdb`` is built for the system Python (``/usr/bin/python3``) and its NumPy,
not for the Python that runs clvol, so the OpenVDB code runs there, in a subprocess
(scripts/setup.sh installs it). ``vdb_tool`` (``libopenvdb-tools``) re-saves a file with another
compression codec, again with OpenVDB's own writer.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import textwrap
from pathlib import Path

SYSTEM_PYTHON = os.environ.get("CLVOL_OPENVDB_PYTHON", "/usr/bin/python3")


def openvdb_missing() -> str | None:
    """Why OpenVDB cannot write fixtures here, or None when it can."""
    if not Path(SYSTEM_PYTHON).exists():
        return f"{SYSTEM_PYTHON} not found (Debian's python3-openvdb runs there)"
    r = subprocess.run([SYSTEM_PYTHON, "-c", "import pyopenvdb"], capture_output=True, text=True)
    if r.returncode != 0:
        return (f"{SYSTEM_PYTHON} cannot import pyopenvdb (apt-get install python3-openvdb; "
                f"scripts/setup.sh does): {r.stderr.strip().splitlines()[-1:]}")
    if shutil.which("vdb_tool") is None:
        return "vdb_tool not found (apt-get install libopenvdb-tools; scripts/setup.sh does)"
    return None


def run_openvdb(code: str, cwd, args=()) -> str:
    """Run ``code`` (with ``pyopenvdb as vdb`` and ``numpy as np`` imported) in the system
    Python inside ``cwd``, with ``args`` as sys.argv[1:]; return its stdout, or raise with its
    stderr."""
    prog = "import pyopenvdb as vdb\nimport numpy as np\n" + textwrap.dedent(code)
    r = subprocess.run([SYSTEM_PYTHON, "-c", prog, *map(str, args)], cwd=str(cwd),
                       capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"OpenVDB script failed ({r.returncode}):\n{r.stderr}")
    return r.stdout


def vdb_tool_resave(src, dst, codec: str) -> None:
    """Re-save ``src`` as ``dst`` with compression ``codec`` (none, zip, blosc or active)."""
    r = subprocess.run(["vdb_tool", "-read", str(src), "-write", f"codec={codec}", str(dst)],
                       capture_output=True, text=True)
    if r.returncode != 0 or not Path(dst).is_file():
        raise RuntimeError(f"vdb_tool failed ({r.returncode}):\n{r.stdout}\n{r.stderr}")


# Helpers defined inside every fixture script. ``expect(grid, name)`` saves what OpenVDB itself
# reads back for the active box (copyToArray: x, y, z order) as name.npz, keys a, lo.
EXPECT = """
def expect(path, gridname, out):
    g = vdb.read(path, gridname)
    lo, hi = g.evalActiveVoxelBoundingBox()
    a = np.zeros([h - l + 1 for l, h in zip(lo, hi)], np.float32)
    g.copyToArray(a, ijk=lo)
    np.savez(out, a=a, lo=np.array(lo), count=g.activeVoxelCount(),
             voxel=np.array(g.transform.voxelSize()),
             origin=np.array(g.transform.indexToWorld((0, 0, 0))))
"""
