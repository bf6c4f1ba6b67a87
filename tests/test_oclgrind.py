"""Every kernel's tiny-input test (``@pytest.mark.oclgrind``) run again on Oclgrind, a strict
OpenCL simulator that reports out-of-bounds accesses, uninitialised values and data races.

Passing on PoCL says a kernel is right on PoCL; passing here says it does not lean on
undefined behaviour that another driver would expose. The suite needs ``oclgrind``
(scripts/setup.sh installs it); its absence is a failure, not a skip, so CI cannot pass
without running this.
"""
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
OCLGRIND = shutil.which("oclgrind")


def _run_under_oclgrind(args, log, timeout):
    if OCLGRIND is None:
        pytest.fail("oclgrind is not installed: run scripts/setup.sh (apt-get install oclgrind)")
    env = dict(os.environ)
    for var in ("CLVOL_DEVICE", "PYOPENCL_CTX"):  # Oclgrind's device is the only one there
        env.pop(var, None)
    cmd = [OCLGRIND, "--data-races", "--uninitialized", "--log", str(log), sys.executable, *args]
    return subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)


def test_oclgrind_reports_an_out_of_bounds_read(tmp_path):
    """Power check: the harness must see a real bug (an off-by-one read)."""
    script = tmp_path / "oob.py"
    script.write_text(textwrap.dedent("""
        import numpy as np, pyopencl as cl
        ctx = cl.create_some_context(interactive=False); q = cl.CommandQueue(ctx)
        prg = cl.Program(ctx, '''__kernel void k(__global const float *a, __global float *b) {
            int i = get_global_id(0); b[i] = a[i + 1]; }''').build()
        a = cl.Buffer(ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                      hostbuf=np.zeros(16, np.float32))
        b = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, 64)
        cl.Kernel(prg, "k")(q, (16,), None, a, b); q.finish()
    """))
    log = tmp_path / "oob.log"
    _run_under_oclgrind([str(script)], log, timeout=120)
    assert "Invalid read" in log.read_text()


def test_kernels_clean_under_oclgrind(tmp_path):
    log = tmp_path / "oclgrind.log"
    proc = _run_under_oclgrind(
        ["-m", "pytest", "-q", "-m", "oclgrind", "-p", "no:cacheprovider", "tests"],
        log, timeout=900)
    report = log.read_text() if log.exists() else ""
    assert proc.returncode == 0, f"oclgrind subset failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-2000:]}"
    assert "passed" in proc.stdout and " 0 passed" not in proc.stdout, proc.stdout[-2000:]
    assert report.strip() == "", f"Oclgrind reported errors:\n{report[:6000]}"
