"""The kernel-vs-twin tests on a second OpenCL implementation: Mesa's rusticl on llvmpipe
(docs/opencl.md, "rusticl"), run by the README's ``python -m pytest -q`` where rusticl is
installed (scripts/setup.sh installs it; skipped, with the reason, where it is not).

Passing on PoCL says the kernels are right on PoCL, passing under Oclgrind that they lean on no
undefined behaviour Oclgrind can see; passing here says another compiler (SPIR-V -> NIR ->
gallivm, no FP contraction, its own vectorisation of work-items) computes the twins' results
too. It found a real one: private pointers with run-time offsets, miscompiled by rusticl
(docs/opencl.md).

One subprocess, ``pytest --cl-device rusticl -m rusticl TWIN_FILES``, rather than a
parametrisation of the tests in this session: rusticl shows its device only when
``RUSTICL_ENABLE=llvmpipe`` is set before the ICD loader first asks (this session has asked
already, without it), clvol's runtime picks its device once a process, and a crash inside
llvmpipe's code (SIGBUS seen while the offsets were miscompiled) fails this test instead of
ending the suite. Mesa's shader cache and pyopencl's are empty folders, as on CI's fresh
machine, so every kernel is compiled as a first user's would be.

Which tests run there (marker ``rusticl``, at least one per kernel file of cl/; this test fails
if a file has none or one is skipped): every tiny-input test (marker ``oclgrind``) of the
twin files, except two that rusticl's first-launch compilation makes too slow for CI's budget
(CI's limit 30 min, the suite ~21.5 min without this; llvmpipe compiles each kernel at its first
launch, 50-65 s for the path tracer's and the fused network's):

- ``test_pathtrace.py``: ``test_pathtrace_tiny`` (pt_render, 2 x 2 pixels, a two-lobe phase,
  chromatic albedo, an environment) runs; its point-query half ``test_pathtrace_tiny_query``
  (pt_query, another ~52 s compile) does not;
- ``test_gather_mlp.py``: ``test_fused_matches_composed_twins[rgb_g1]`` (the fused gather +
  network kernel against the NumPy twins, three channels, 27 queries inside, on faces and
  outside the volume, the shipped network's shape) runs instead of ``test_tiny``, which
  compares the fused kernel with the unfused pair on the same device and builds four programs
  of the full network (105-147 s).

The tests' own tolerances hold (each file states its bounds; rusticl rounds a * b + c twice
where PoCL fuses it, within them). Measured cold on the 2-core machine (Mesa 22.3.6, shared,
load average 1.1-2.0): 120 s and 135 s wall, ~1.1 GB resident (docs/opencl.md, "rusticl").
"""
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from conftest import TWIN_FILES

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT_S = 900


def rusticl_icd() -> Path | None:
    """The ICD file of rusticl where the loader (ocl-icd) looks: $OCL_ICD_VENDORS (a folder or
    one file), else /etc/OpenCL/vendors; None if there is none."""
    where = Path(os.environ.get("OCL_ICD_VENDORS") or "/etc/OpenCL/vendors")
    files = [where] if where.is_file() else sorted(where.glob("*.icd")) if where.is_dir() else []
    for f in files:
        try:
            if "rusticl" in f.read_text().lower():
                return f
        except OSError:
            continue
    return None


def test_twins_on_rusticl(tmp_path):
    icd = rusticl_icd()
    if icd is None:
        pytest.skip("Mesa's rusticl is not installed (no rusticl ICD in $OCL_ICD_VENDORS or "
                    "/etc/OpenCL/vendors): scripts/setup.sh installs mesa-opencl-icd")
    env = dict(os.environ, RUSTICL_ENABLE="llvmpipe")
    for var in ("CLVOL_DEVICE", "PYOPENCL_CTX", "CLVOL_LANES"):   # rusticl's own rule: 4 lanes
        env.pop(var, None)
    for var in ("MESA_SHADER_CACHE_DIR", "XDG_CACHE_HOME", "POCL_CACHE_DIR"):
        env[var] = str(tmp_path / var.lower())
        os.makedirs(env[var])
    report = tmp_path / "rusticl.xml"
    cmd = [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "--cl-device",
           "rusticl", "-m", "rusticl", f"--junitxml={report}", *TWIN_FILES]
    try:
        proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True,
                              timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f"the twin tests on rusticl did not finish in {TIMEOUT_S} s ({icd})")
    out = f"{proc.stdout[-5000:]}\n{proc.stderr[-2000:]}"
    assert proc.returncode == 0, f"twin tests on rusticl failed ({icd}):\n{out}"
    # the session header's device line (tests/conftest.py), not any "rusticl" in the output:
    # the junit file's path alone holds that word
    header = [ln for ln in proc.stdout.splitlines() if ln.startswith("clvol OpenCL device:")]
    assert header and "rusticl" in header[0].lower(), \
        f"the session's header names another device:\n{out}"
    passed: dict[str, int] = {}
    for case in ET.parse(report).getroot().iter("testcase"):
        assert not any(c.tag in ("failure", "error", "skipped") for c in case), \
            f"{case.get('classname')}::{case.get('name')} did not pass on rusticl:\n{out}"
        path = "tests/" + case.get("classname").split(".")[-1] + ".py"
        passed[path] = passed.get(path, 0) + 1
    missing = [f for f in TWIN_FILES if not passed.get(f)]
    assert not missing, f"kernel files with no test passed on rusticl: {missing}\n{out}"
