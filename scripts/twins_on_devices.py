"""Run the kernel-vs-twin test files (tests/conftest.py ``TWIN_FILES``) on OpenCL devices, one
pytest process per file and device, every kernel cache empty at its start, and print a table of
pass/fail and wall time per file.

    python scripts/twins_on_devices.py                   # every device `clvol info` lists
    python scripts/twins_on_devices.py --tiny            # only the tiny adversarial subset
    RUSTICL_ENABLE=llvmpipe python scripts/twins_on_devices.py --device rusticl --tiny
    RUSTICL_ENABLE=llvmpipe python scripts/twins_on_devices.py --device rusticl -m rusticl

``--tiny`` runs the tests marked ``oclgrind`` (the tiny-input kernel tests), ``-m EXPR`` those
pytest's marker expression selects (``rusticl``: the subset tests/test_rusticl.py runs;
pyproject.toml lists the markers).
Each process gets fresh, empty cache folders: ``POCL_CACHE_DIR``, ``MESA_SHADER_CACHE_DIR``
and ``XDG_CACHE_HOME`` (pyopencl's cache, Mesa's default one), as CI's cold machine has.
Mesa's rusticl shows its llvmpipe device only with ``RUSTICL_ENABLE=llvmpipe`` set
(docs/opencl.md, "rusticl"). Exit status 1 if any file failed or timed out.
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def twin_files() -> list[str]:
    """tests/conftest.py's TWIN_FILES (one list for the suite, this script and test_rusticl)."""
    sys.path.insert(0, str(ROOT / "tests"))
    from conftest import TWIN_FILES
    return list(TWIN_FILES)


def machine_line() -> str:
    """bench/_common.py's machine line (CPU, cores, Python, load average, date)."""
    sys.path.insert(0, str(ROOT / "bench"))
    from _common import machine
    return machine()


def device_specs() -> list[tuple[str, str]]:
    sys.path.insert(0, str(ROOT))
    from clvol.runtime import list_devices
    return [(e.spec, e.label) for e in list_devices()]


def run_file(spec: str, path: str, marker: str | None, timeout: float) -> tuple[str, float, str]:
    """(summary, seconds, output tail) of one pytest process on one file."""
    with tempfile.TemporaryDirectory(prefix="clvol-twins-") as cold:
        env = dict(os.environ)
        for var in ("POCL_CACHE_DIR", "MESA_SHADER_CACHE_DIR", "XDG_CACHE_HOME"):
            env[var] = os.path.join(cold, var.lower())
            os.makedirs(env[var])
        env.pop("PYOPENCL_CTX", None)
        env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
        cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
               "--cl-device", spec, path] + (["-m", marker] if marker else [])
        t0 = time.monotonic()
        try:
            proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True,
                                  timeout=timeout)
        except subprocess.TimeoutExpired:
            return f"TIMEOUT after {timeout:.0f} s", time.monotonic() - t0, ""
        dt = time.monotonic() - t0
        out = proc.stdout + proc.stderr
        lines = [ln for ln in proc.stdout.splitlines() if re.search(r"\d+ (passed|failed|error|skipped|deselected)", ln)]
        summary = lines[-1].strip("= ") if lines else f"exit {proc.returncode}"
        if proc.returncode not in (0, 5):   # 5: nothing collected/selected
            summary = f"FAILED ({summary})"
        return summary, dt, out[-3000:]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", action="append", metavar="SPEC",
                    help="device SPEC as `clvol info` takes it (repeatable; default: every device)")
    ap.add_argument("--tiny", action="store_true", help="only the tests marked oclgrind")
    ap.add_argument("-m", dest="marker", metavar="EXPR", help="pytest marker expression")
    ap.add_argument("--files", nargs="+", metavar="FILE", help="test files (default: TWIN_FILES)")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per file (default 900)")
    args = ap.parse_args(argv)
    specs = [(s, s) for s in args.device] if args.device else device_specs()
    files = args.files or twin_files()
    marker = args.marker or ("oclgrind" if args.tiny else None)
    bad = 0
    print(machine_line(), flush=True)
    for spec, label in specs:
        print(f"device {spec} ({label}), {'-m ' + marker if marker else 'whole files'}, "
              f"cold caches, one process a file", flush=True)
        total = 0.0
        for path in files:
            summary, dt, tail = run_file(spec, path, marker, args.timeout)
            total += dt
            print(f"  {path:<28} {dt:7.1f} s  {summary}", flush=True)
            if summary.startswith(("FAILED", "TIMEOUT")):
                bad += 1
                print("    " + tail.replace("\n", "\n    ")[-2000:], flush=True)
        print(f"  total {total:.1f} s", flush=True)
    print(f"at the end: {machine_line()}", flush=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
