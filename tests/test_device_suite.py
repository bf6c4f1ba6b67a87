"""bench/device_suite.py runs end to end on this machine's device at a tiny size (the CI's
check that the one-call GPU suite works before a GPU is lent): one twin file through pytest
--cl-device, two timings, the JSON and markdown written."""
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_device_suite_quick(tmp_path):
    out = tmp_path / "suite"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    proc = subprocess.run(
        [sys.executable, "bench/device_suite.py", "--quick", "--out", str(out), "--jobs", "1",
         "--twin-files", "tests/test_rng.py", "--only", "transmittance", "gather",
         "--budget-s", "240"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=400)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    rep = json.loads((out / "device_suite.json").read_text())
    assert rep["twins"]["tests/test_rng.py"]["status"] == "passed"
    assert rep["twins"]["tests/test_rng.py"]["passed"] >= 2
    assert set(rep["timings"]) == {"transmittance", "gather"}
    assert all(r["wall ms"] > 0 for r in rep["timings"]["transmittance"])
    assert rep["machine"]["device"]["compute_units"] >= 1
    md = (out / "device_suite.md").read_text()
    assert "## Kernel vs twin" in md and "### gather" in md
    assert (out / "twins.log").read_text().count("=====") == 1
