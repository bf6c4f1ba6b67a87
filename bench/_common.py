"""What every benchmark shares (imported as ``_common``: benchmarks run as
``python bench/<name>.py``, which puts bench/ on sys.path): the machine line they print,
their common options, and ``ROOT``, the checkout, which importing this module puts first on
sys.path so a benchmark measures this checkout's clvol (and can import reference/) whatever
clvol is installed."""
import argparse
import dataclasses
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path[:1]:
    sys.path.insert(0, str(ROOT))


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


def parser(doc: str, size: int | None = None, spp: int | None = None) -> argparse.ArgumentParser:
    """A benchmark's command line: the first line of its docstring as the description, and the
    common --size (image side) and --spp (reference samples per pixel) with the defaults given."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    if size is not None:
        ap.add_argument("--size", type=int, default=size,
                        help=f"image width and height in pixels (default {size})")
    if spp is not None:
        ap.add_argument("--spp", type=int, default=spp,
                        help=f"path-traced reference samples per pixel (default {spp})")
    return ap


def square(scene, size: int):
    """``scene`` seen by a size x size camera."""
    return dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=size,
                                                                 height=size))


def rms(x) -> float:
    """Root mean square: of an image difference (RMSE), or of a standard-error layer."""
    return float(np.sqrt(np.mean(np.square(x))))


def cpu_seconds() -> float:
    """CPU time of this process so far, every thread (PoCL's included): less sensitive to
    other processes' load than the wall clock on a shared machine."""
    import resource
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def rot_y(v, deg: float):
    """``v`` turned by ``deg`` degrees about +y (an orbit step about the world's up axis)."""
    import math
    a = math.radians(deg)
    x, y, z = v
    return (x * math.cos(a) + z * math.sin(a), y, -x * math.sin(a) + z * math.cos(a))

