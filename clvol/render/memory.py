"""What a frame's image costs in memory, known before it is spent (issue 41).

A render whose per-pixel working set would exceed the budget is refused up front, with one
line naming the size, the estimate and the limit, instead of running for minutes and being
killed by the kernel (a 16384^2 image reached 16.9 GB and exit 137 with no message).

**Estimate.** Bytes per marched pixel (``supersample^2`` per image pixel for the ray
marcher), host and device together: the output layers on the device, their host copies and
the temporaries of downsampling and assembling the result. Measured as the growth of peak RSS
for one 1024^2 frame after a 8^2 warm-up frame (16^3 cloud; PoCL's device memory is host
memory, so RSS holds both): ray marcher 81-109 bytes (``--ms network`` and ``none``: 11
float32 planes on the device and on the host), path tracer 312 (float64 accumulators of the
mean and the variance per layer). The constants below are those plus about a fifth.
The volume, its pyramid and light field are not counted here: they do not grow with the image
(the .vdb reader refuses a grid larger than a device buffer itself).

**Budget.** ``CLVOL_MEMORY_LIMIT`` (bytes, or with a K, M, G or T suffix, powers of 1024)
when set; else the smaller of the machine's physical memory and the OpenCL device's global
memory (``clvol info`` prints both). A single image plane must also fit the device's largest
buffer (``CL_DEVICE_MAX_MEM_ALLOC_SIZE``).
"""
from __future__ import annotations

import os

from ..errors import ClvolError

BYTES_PER_PIXEL = {"raymarch": 128, "pathtrace": 384}
PLANE_BYTES_PER_PIXEL = 16      # the largest single buffer: an RGB(A) float32 plane
LIMIT_ENV = "CLVOL_MEMORY_LIMIT"
_SUFFIX = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def host_memory() -> int | None:
    """The machine's physical memory in bytes (None where the OS does not say)."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None


def parse_limit(text: str) -> int:
    """``CLVOL_MEMORY_LIMIT``'s value in bytes: an integer with an optional K/M/G/T suffix."""
    t = text.strip().upper().removesuffix("B").removesuffix("I")
    unit = t[-1:] if t[-1:] in _SUFFIX and t[-1:] else ""
    num = t[:-1] if unit else t
    try:
        value = float(num) * _SUFFIX[unit]
    except ValueError:
        value = float("nan")
    if not (value >= 1):                       # also NaN
        raise ClvolError(f"${LIMIT_ENV} = {text!r}: must be a number of bytes >= 1, "
                         f"optionally with a K, M, G or T suffix (e.g. 8G)")
    return int(value)


def memory_limit(device=None) -> tuple[int | None, str]:
    """(bytes, where the number comes from) of the render budget; (None, why) without one."""
    env = os.environ.get(LIMIT_ENV)
    if env is not None and env.strip():
        return parse_limit(env), f"${LIMIT_ENV}"
    options = []
    host = host_memory()
    if host:
        options.append((host, "the machine's memory"))
    if device is not None:
        options.append((int(device.global_mem_size), "the OpenCL device's global memory"))
    if not options:
        return None, "unknown"
    return min(options)


def gib(n: float) -> str:
    return f"{n / 2**30:.2f} GiB"


def check_frame_memory(method: str, width: int, height: int, supersample: int,
                       device=None) -> int:
    """Refuse (ClvolError, one line) a frame whose image would not fit the budget; return
    the estimate in bytes."""
    pixels = int(width) * int(height) * int(supersample) ** 2
    need = pixels * BYTES_PER_PIXEL[method]
    limit, where = memory_limit(device)
    ss = f" at supersample {supersample}" if supersample > 1 else ""
    size = f"a {width} x {height} image{ss} ({method})"
    if limit is not None and need > limit:
        raise ClvolError(f"{size} needs about {gib(need)} of memory ({BYTES_PER_PIXEL[method]} "
                         f"bytes a pixel, host and device), more than the {gib(limit)} limit "
                         f"({where}; ${LIMIT_ENV} sets another); render a smaller image")
    if device is not None:
        plane = pixels * PLANE_BYTES_PER_PIXEL
        if plane > int(device.max_mem_alloc_size):
            raise ClvolError(f"{size}: one image plane needs {gib(plane)}, more than the "
                             f"{gib(device.max_mem_alloc_size)} the OpenCL device allows in one "
                             f"buffer; render a smaller image")
    return need


def describe_limits(device) -> str:
    """``clvol info``'s line on the render budget of ``device``."""
    limit, where = memory_limit(device)
    host = host_memory()
    parts = [f"host {gib(host)}" if host else "host unknown",
             f"device {gib(device.global_mem_size)}, {gib(device.max_mem_alloc_size)} per buffer"]
    budget = f"{gib(limit)} ({where})" if limit else "none"
    return (f"render memory: {'; '.join(parts)}; budget {budget}: at most "
            f"{BYTES_PER_PIXEL['raymarch']} (raymarch) or {BYTES_PER_PIXEL['pathtrace']} "
            f"(pathtrace) bytes a pixel")
