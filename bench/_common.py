"""What every benchmark prints about the machine it ran on (imported as ``_common``:
benchmarks run as ``python bench/<name>.py``, which puts bench/ on sys.path)."""
import os
import platform
import time
from pathlib import Path


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def load_average() -> str:
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def machine(rt=None) -> str:
    """One line: CPU, cores, OpenCL device and platform version, load average, date."""
    parts = [f"CPU: {cpu_model()}", f"{os.cpu_count()} logical cores",
             f"Python {platform.python_version()}"]
    if rt is not None:
        parts += [f"device: {rt.entry.label}", f"platform: {rt.entry.platform.version.strip()}"]
    parts += [f"load average: {load_average()}", time.strftime("%Y-%m-%d %H:%M")]
    return "; ".join(parts)
