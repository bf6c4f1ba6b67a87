"""Test-session options shared by every test file.

``--cl-device SPEC`` (or ``$CLVOL_DEVICE``) runs the tests on one chosen OpenCL device: SPEC is
what ``clvol info`` and ``--device`` take (``P:D``, ``gpu``, ``cpu`` or a name substring, e.g.
``rusticl``). The kernel tests reach the device through ``clvol.runtime.get_runtime()``, which
reads ``$CLVOL_DEVICE`` (docs/opencl.md), so the option sets that variable for the session and
every kernel-vs-twin test runs on that device. The header line names the device.

Run the kernel-vs-twin tests on every device there is (one pytest process per file and
device, kernel caches empty, a table of results and times)::

    python scripts/twins_on_devices.py            # --tiny: only the tiny adversarial subset
    RUSTICL_ENABLE=llvmpipe python scripts/twins_on_devices.py --device rusticl --tiny

``TWIN_FILES`` is the list of those test files: ``tests/test_<stem>.py`` for each kernel
``cl/<stem>.cl`` that has one. tests/test_rusticl.py runs their subset marked ``rusticl`` on
Mesa's rusticl within the default run.
"""
from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TWIN_FILES = sorted(f"tests/test_{p.stem}.py" for p in (ROOT / "cl").glob("*.cl")
                    if (ROOT / "tests" / f"test_{p.stem}.py").is_file())


def pytest_addoption(parser):
    parser.addoption(
        "--cl-device", default=None, metavar="SPEC",
        help="OpenCL device for the kernel tests (P:D, gpu, cpu or a name substring, as "
             "'clvol info' lists them); sets $CLVOL_DEVICE for the session")


def pytest_configure(config):
    spec = config.getoption("--cl-device")
    if spec:
        os.environ["CLVOL_DEVICE"] = spec
        os.environ.pop("PYOPENCL_CTX", None)


def pytest_report_header(config):
    try:
        from clvol.runtime import choose_device, device_lanes
        entry, why = choose_device()
        return [f"clvol OpenCL device: {entry.spec} {entry.label} ({why}); "
                f"{entry.platform.version.strip()}; lanes {device_lanes(entry)} "
                f"($CLVOL_LANES forces 16, 8 or 4)"]
    except Exception as exc:  # noqa: BLE001 - a header must not stop the session
        return [f"clvol OpenCL device: none ({str(exc).splitlines()[0]})"]
