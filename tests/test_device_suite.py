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


def test_device_suite_pathtrace_traffic(tmp_path):
    """The path tracer's rows carry their bytes per sample and the bandwidth bounds
    (bench/pt_traffic.py), the twin's replay taking the kernel's steps on the same paths."""
    out = tmp_path / "suite"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    proc = subprocess.run(
        [sys.executable, "bench/device_suite.py", "--quick", "--out", str(out), "--twins", "none",
         "--only", "path tracer", "--budget-s", "240"],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=400)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    rows = json.loads((out / "device_suite.json").read_text())["timings"]["path tracer"]
    assert len(rows) == 2
    for r in rows:
        assert r["steps/sample"] > 0 and r["vertices/sample"] > 0
        words, sectors = (float(v) for v in r["B/sample (words / 32-B sectors)"].split(" / "))
        assert 0 < words < sectors
        assert float(r["BW bound H200 M/s (words / sectors)"].split(" / ")[0]) > 0
        # the replay follows the kernel's paths (float rounding may part a rare one)
        same = r["majorant reads/sample (twin replay)"].split(", ")[1].split("%")[0]
        assert int(same) >= 80
    assert "B/sample" in (out / "device_suite.md").read_text()
