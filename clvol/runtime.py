"""OpenCL runtime: device choice, program building from ``cl/``, kernel launches.

One ``Runtime`` holds a context and an in-order queue on one device. Kernel host
wrappers (``clvol/kernels/<stem>.py``) get it from ``get_runtime()`` and do::

    rt = get_runtime()
    prog = rt.program("raymarch", defines={"GREY": 1})
    k = prog.kernel("raymarch", [None, None, np.int32, np.float32])   # built once, reused
    rt.launch(k, n_items, (buf_in, buf_out, np.int32(n), np.float32(step)))

Device choice (first that applies): the ``device`` argument, ``$CLVOL_DEVICE``,
``$PYOPENCL_CTX``, the first GPU, the first CPU, any device. A spec is
``"P"`` or ``"P:D"`` (platform and device indices, as ``clvol info`` lists them),
``"gpu"``/``"cpu"``/``"accelerator"``, or a case-insensitive substring of
"platform name / device name".

Programs are built with ``-I cl/include``, the caller's ``-D`` defines, the device's lane
width ``-D LANES`` (``device_lanes``; ``Runtime.lanes`` for launch sizes) and a hash of
every source they could include, so no driver-side cache can serve a stale header.
They are cached in-process on (source hash, options, device).

Device data follows one convention:

- an array kept on the device is a ``DeviceArray`` (buffer, shape, dtype), made by
  ``Runtime.upload`` or ``Runtime.alloc`` and read with ``.read()``;
- every launch goes through ``Runtime.launch`` (profiling sees all of them);
- every host->device upload and device->host readback goes through ``Runtime.to_device`` /
  ``Runtime.upload`` and ``Runtime.from_device`` / ``DeviceArray.read``, which count it in
  ``Runtime.transfers`` (calls and bytes per direction and label: the caller's ``label``, or
  the calling function's name); tests/test_transfers.py holds a render to its budget;
- data derived from an object and kept for reuse lives in that object's ``cache`` dict
  (``Pyramid.cache``, ``DeviceMedium.cache``) and dies with it; host-only tables that are pure
  functions of small arguments use ``functools.lru_cache``.
"""
from __future__ import annotations

import atexit
import functools
import hashlib
import importlib.resources
import os
import sys
import time
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyopencl as cl

from .errors import BuildError, DeviceError

# PoCL runs a NULL-local-size launch with a prime global size on one core
# (docs/opencl.md), so global sizes are padded to a multiple of this by default.
DEFAULT_PAD = 64


@functools.lru_cache(maxsize=None)
def cl_source_dir() -> Path:
    """Folder holding the ``.cl`` sources (``cl/`` in a checkout, ``clvol/_cl`` installed);
    where the package lies does not change in a process, and every launch asks.

    A clvol imported from a checkout takes the ``cl/`` beside it: ``clvol._cl`` is mapped
    by setup.cfg's ``package_dir`` only in an installed copy, so from a checkout it would
    resolve to whatever clvol is installed (another worktree's kernels, or none: running
    from a checkout with clvol installed by ``pip install --target`` elsewhere on the path
    found no ``clvol._cl`` at all)."""
    checkout = Path(__file__).resolve().parents[1] / "cl"
    if (checkout / "include").is_dir() and (checkout / "raymarch.cl").is_file():
        return checkout
    return Path(str(importlib.resources.files("clvol._cl")))


def include_dir() -> Path:
    return cl_source_dir() / "include"


def padded(n: int, multiple: int = DEFAULT_PAD) -> int:
    """Smallest multiple of ``multiple`` that is >= n (and >= multiple)."""
    n = max(int(n), 1)
    return ((n + multiple - 1) // multiple) * multiple


# --------------------------------------------------------------------------- devices

@dataclass(frozen=True)
class DeviceEntry:
    platform_index: int
    device_index: int
    platform: "cl.Platform"
    device: "cl.Device"

    @property
    def spec(self) -> str:
        return f"{self.platform_index}:{self.device_index}"

    @property
    def kind(self) -> str:
        t = self.device.type
        if t & cl.device_type.GPU:
            return "gpu"
        if t & cl.device_type.CPU:
            return "cpu"
        if t & cl.device_type.ACCELERATOR:
            return "accelerator"
        return "other"

    @property
    def label(self) -> str:
        return f"{self.platform.name.strip()} / {self.device.name.strip()}"


def list_devices() -> list[DeviceEntry]:
    try:
        platforms = cl.get_platforms()
    except cl.Error:  # the ICD loader reports "no platforms" as an error
        platforms = []
    out = []
    for pi, p in enumerate(platforms):
        try:
            devices = p.get_devices()
        except cl.Error:
            devices = []
        for di, d in enumerate(devices):
            out.append(DeviceEntry(pi, di, p, d))
    return out


def _match(spec: str, entries: list[DeviceEntry], origin: str) -> DeviceEntry:
    s = spec.strip()
    parts = s.split(":")
    if all(p.strip().isdigit() for p in parts) and 1 <= len(parts) <= 2:
        pi = int(parts[0])
        di = int(parts[1]) if len(parts) == 2 else 0
        for e in entries:
            if e.platform_index == pi and e.device_index == di:
                return e
    elif s.lower() in ("gpu", "cpu", "accelerator"):
        for e in entries:
            if e.kind == s.lower():
                return e
    else:
        for e in entries:
            if s.lower() in e.label.lower():
                return e
    have = "; ".join(f"{e.spec} = {e.label} ({e.kind})" for e in entries) or "none"
    raise DeviceError(
        f"{origin}={spec!r} matches no OpenCL device; use 'P:D', 'gpu', 'cpu' or a name "
        f"substring. Devices: {have}")


def choose_device(device: str | None = None) -> tuple[DeviceEntry, str]:
    """Return the chosen device and the reason it was chosen."""
    entries = list_devices()
    if not entries:
        raise DeviceError(
            "no OpenCL platform found; on Debian/Ubuntu install the CPU runtime with "
            "'apt-get install pocl-opencl-icd' (scripts/setup.sh does this)")
    for origin, spec in (("--device", device),
                         ("CLVOL_DEVICE", os.environ.get("CLVOL_DEVICE")),
                         ("PYOPENCL_CTX", os.environ.get("PYOPENCL_CTX"))):
        if spec:
            return _match(spec, entries, origin), f"{origin}={spec}"
    for kind in ("gpu", "cpu"):
        found = [e for e in entries if e.kind == kind]
        if found:
            e = min(found, key=lambda e: default_last(e.platform.name))   # the first of the best
            return e, f"default: first {kind.upper()}" + (
                "" if e is found[0] else f" not of {found[0].platform.name.strip()!r} "
                "(runtime.DEFAULT_LAST)")
    return entries[0], "default: first device"


def device_details(e: DeviceEntry) -> list[str]:
    """What ``clvol info`` prints under a device: its type, compute units and clock, memory,
    preferred and native float vector widths, driver."""
    d = e.device

    def q(name, default="?"):
        try:
            return getattr(d, name)
        except (cl.Error, AttributeError):   # a driver may not answer every query
            return default

    return [f"type {e.kind}, {q('max_compute_units')} compute units at {q('max_clock_frequency')} "
            f"MHz, max work-group {q('max_work_group_size')}",
            f"memory {q('global_mem_size', 0) / 2**30:.1f} GiB global (one buffer up to "
            f"{q('max_mem_alloc_size', 0) / 2**30:.1f} GiB), {q('local_mem_size', 0) / 1024:.0f} "
            f"KiB local",
            f"float vector width preferred {q('preferred_vector_width_float')}, native "
            f"{q('native_vector_width_float')}; driver {str(q('driver_version')).strip()}, "
            f"{str(q('version')).strip()}"]


def describe_devices(device: str | None = None, details: bool = True) -> str:
    """Human-readable listing for ``clvol info`` (with ``details``: each device's type,
    compute units, memory, vector widths and driver)."""
    entries = list_devices()
    lines = []
    try:
        chosen, why = choose_device(device)
    except DeviceError as exc:
        chosen, why = None, str(exc)
    last_p = None
    for e in entries:
        if e.platform_index != last_p:
            lines.append(f"platform {e.platform_index}: {e.platform.name.strip()} "
                         f"({e.platform.version.strip()})")
            last_p = e.platform_index
        mark = "*" if chosen is not None and e.spec == chosen.spec else " "
        d = e.device
        lines.append(
            f" {mark} {e.spec}  {e.kind:<4} {d.name.strip()}  "
            f"{d.max_compute_units} CUs, {d.global_mem_size / 2**30:.1f} GiB, "
            f"OpenCL C {d.opencl_c_version.strip()}")
        if details:
            lines += [f"        {ln}" for ln in device_details(e)]
    if not entries:
        lines.append("no OpenCL platforms found")
    lines.append(f"chosen: {chosen.spec + ' ' + chosen.label if chosen else 'none'} ({why})")
    lines.append("select with --device P:D|gpu|cpu|NAME, or $CLVOL_DEVICE / $PYOPENCL_CTX")
    return "\n".join(lines)


# --------------------------------------------------------------------------- lanes

LANE_WIDTHS = (16, 8, 4)


def lanes_for(kind: str, native_float_width: int) -> int:
    """Vector lanes per work-item (cl/include/lanes.h LANES) for a device: a CPU's native float
    vector width (512-bit registers: 16, 256: 8, 128: 4), since a call passing a wider vector
    changes the CPU's calling convention (clang's -Wpsabi, docs/opencl.md); 16 elsewhere (a
    GPU scalarises the lanes, and a CPU that reports no SIMD width is not one PoCL targets)."""
    w = int(native_float_width or 0)
    if kind == "cpu" and w in (4, 8):
        return w
    return 16


def forced_lanes() -> int | None:
    """``$CLVOL_LANES`` (16, 8 or 4) if set: run the kernels at that width on any device (the
    tests compare widths on one machine)."""
    v = os.environ.get("CLVOL_LANES", "").strip()
    if not v:
        return None
    if not v.isdigit() or int(v) not in LANE_WIDTHS:
        raise DeviceError(
            f"CLVOL_LANES={v!r}: expected one of {', '.join(map(str, LANE_WIDTHS))}")
    return int(v)


def device_lanes(e: DeviceEntry) -> int:
    """The lane width the kernels are built with on this device: ``$CLVOL_LANES``, else its
    driver's rule (DRIVER_RULES: 4 on rusticl), else ``lanes_for`` its type and native float
    vector width. The one place it is decided."""
    return _lanes_and_why(e)[0]


def _lanes_and_why(e: DeviceEntry) -> tuple[int, str]:
    forced = forced_lanes()
    if forced is not None:
        return forced, "forced by $CLVOL_LANES"
    drv = driver_lanes_for(e.platform.name)
    if drv is not None:
        return drv, f"the driver rule of platform {e.platform.name!r}, clvol/runtime.py DRIVER_RULES"
    try:
        width = int(e.device.native_vector_width_float)
    except (cl.Error, AttributeError):
        width = 0
    why = (f"the CPU's native float vector width {width}" if e.kind == "cpu"
           else f"16 on a {e.kind}")
    return lanes_for(e.kind, width), why


def describe_lanes(e: DeviceEntry) -> str:
    """``clvol info``'s line: the width and why."""
    lanes, why = _lanes_and_why(e)
    return f"lanes: {lanes} per work-item ({why}; -D LANES of every program)"


# --------------------------------------------------------------------------- driver workarounds

# (substring of the platform name, matched case-insensitively; -D defines every program gets
# there; the lane width there, None for the device rule of lanes_for). libclvol repeats this
# table (capi/src/util.c DRIVER_RULES: clvol_driver_defines, clvol_driver_lanes);
# tests/test_capi.py holds the two to the same answers on a table of platform names.
DRIVER_RULES: tuple = (
    # Mesa's rusticl (22.3.6, llvmpipe; docs/opencl.md, "rusticl"), cl/include/mlp_core.h:
    # MLP_DENSE_ARRAY: the dense layers with their accumulators in an array (the same fma
    # chains in the same order: bit-identical sums). rusticl's NIR passes, run at
    # clCreateKernel, took 2.3 s for one dense() of the default form (16 and 8 named
    # accumulators, a pointer induction) on 8 inputs and 8 outputs, and had not finished the
    # network's after 300 s at ~4 GB; with the array form mlp_forward is created in 8.6 s and
    # gather_mlp in 6.6 s at 16 lanes.
    # MLP_MULADD: the multiply-adds written a * b + c instead of fma(). fma() of float is a
    # software fma there (exact; presumably libclc's), inlined at every call: a loop of fma
    # ran 17x slower than one of a * b + c (scripts/rusticl_probe.py fma), and llvmpipe
    # compiles all of it at the first launch. PoCL contracts a * b + c into the same fma
    # (bit-identical; tests/test_mlp.py::test_dense_forms_agree); rusticl does not contract,
    # so its sums round twice (within the twins' tolerance).
    # 4 lanes: llvmpipe runs work-items as SIMD lanes already; explicit vector lanes only
    # multiply the code it compiles at the first launch (the network's mlp_forward: 13-18 s
    # at 4 lanes, not done in 230 s at 16: scripts/rusticl_probe.py mlp). Lanes are
    # independent: bit-identical at 16, 8 and 4.
    ("rusticl", {"MLP_DENSE_ARRAY": 1, "MLP_MULADD": 1}, 4),
)


# Platforms whose devices the default choice takes after any other device of the same type:
# Mesa's Clover (mesa.icd, which mesa-opencl-icd installs beside rusticl's ICD; scripts/setup.sh
# installs it) shows no device on a machine without a GPU, but exposes an AMD or Intel GPU
# through Mesa's Gallium drivers: an OpenCL 1.1 implementation clvol is not tested on, which
# would otherwise be the default render's device wherever the ICD loader lists it before the
# GPU vendor's platform. --device / $CLVOL_DEVICE still pick it. libclvol: capi/src/util.c
# clvol_default_last (tests/test_capi.py holds the two to the same answers).
DEFAULT_LAST = ("clover",)


def default_last(platform_name: str) -> bool:
    """Whether the default device choice takes this platform's devices last (DEFAULT_LAST)."""
    name = (platform_name or "").lower()
    return any(m in name for m in DEFAULT_LAST)


def _driver_rules(platform_name: str):
    name = (platform_name or "").lower()
    return [r for r in DRIVER_RULES if r[0] in name]


def driver_defines_for(platform_name: str) -> dict:
    """The driver workarounds of a platform of this name (DRIVER_RULES; empty if none)."""
    out: dict = {}
    for _, defines, _ in _driver_rules(platform_name):
        out.update(defines)
    return out


def driver_lanes_for(platform_name: str) -> int | None:
    """The lane width DRIVER_RULES gives a platform of this name (None: the device rule)."""
    lanes = [r[2] for r in _driver_rules(platform_name) if r[2]]
    return lanes[-1] if lanes else None


def driver_defines(e: DeviceEntry) -> dict:
    """``-D`` defines every program gets on this device to work around its driver
    (DRIVER_RULES by its platform's name); empty on PoCL and Oclgrind (their code is the
    default one)."""
    return driver_defines_for(e.platform.name)


def describe_workarounds(e: DeviceEntry) -> list[str]:
    """``clvol info``'s line for the driver workarounds this device gets (driver_defines)."""
    d = driver_defines(e)
    if not d:
        return []
    return [f"driver workarounds: {' '.join('-D' + k for k in sorted(d))} on every program "
            f"(rusticl: the network's kernels otherwise stall in clCreateKernel and at their first launch)"]


# --------------------------------------------------------------------------- programs

def first_build_error(log: str) -> str:
    """The first error line of a compiler log (clang's ``file:line:col: error: ...``,
    NVIDIA's ``<kernel>:line:col: error: ...``), else its first non-empty line."""
    lines = [ln.strip() for ln in (log or "").splitlines() if ln.strip()]
    for ln in lines:
        if "error" in ln.lower():
            return ln[:300]
    return lines[0][:300] if lines else "(empty build log)"


class Program:
    """A built program; hands out Kernel objects that are created once and reused."""

    def __init__(self, runtime: "Runtime", stem: str, program: "cl.Program", options: tuple):
        self.runtime = runtime
        self.stem = stem
        self.options = options
        self._program = program
        self._kernels: dict[str, cl.Kernel] = {}

    def kernel(self, name: str, scalar_dtypes: list | None = None) -> "cl.Kernel":
        """The kernel ``name``; ``scalar_dtypes`` as for ``Kernel.set_scalar_arg_dtypes``
        (None for buffers, a NumPy dtype for scalars) is applied on first use."""
        k = self._kernels.get(name)
        if k is None:
            try:
                k = cl.Kernel(self._program, name)
            except cl.Error as exc:
                raise BuildError(f"{self.stem}.cl has no kernel {name!r}: {exc}") from exc
            if scalar_dtypes is not None:
                k.set_scalar_arg_dtypes(scalar_dtypes)
            self._kernels[name] = k
        return k


_HASHES: dict[tuple, str] = {}


def _sources_hash(stem_path: Path) -> str:
    """A hash of the source and every header. Reading them costs ~0.8 ms a launch on every
    frame, so the hash is kept per (file, size, mtime) signature: an edited file still
    changes the signature and is read again."""
    files = [stem_path] + _headers()
    sig = tuple((str(f), st.st_size, st.st_mtime_ns) for f in files for st in (f.stat(),))
    cached = _HASHES.get(sig)
    if cached is not None:
        return cached
    h = hashlib.sha256(stem_path.read_bytes())
    for hdr in files[1:]:
        h.update(hdr.name.encode())
        h.update(hdr.read_bytes())
    _HASHES[sig] = h.hexdigest()[:16]
    return _HASHES[sig]


_HEADERS: dict = {}


def _headers() -> list[Path]:
    """The include folder's headers, listed again only when the folder changed (its mtime:
    a header added or removed); an edited header is caught by _sources_hash's stat."""
    inc = include_dir()
    key = (str(inc), inc.stat().st_mtime_ns)
    if key not in _HEADERS:
        _HEADERS.clear()
        _HEADERS[key] = sorted(inc.glob("*.h"))
    return _HEADERS[key]


def _define_flags(defines: dict | None) -> list[str]:
    flags = []
    for key, value in sorted((defines or {}).items()):
        if value is None or value is False:
            continue
        if value is True:
            flags.append(f"-D{key}=1")
        elif isinstance(value, float):
            flags.append(f"-D{key}={value!r}f")
        else:
            flags.append(f"-D{key}={value}")
    return flags


def compiler_output_shown() -> bool:
    """Whether pyopencl's CompilerWarning ("Non-empty compiler output encountered", or with
    PYOPENCL_COMPILER_OUTPUT=1 the log itself) reaches the user: only when asked for, by
    pyopencl's own PYOPENCL_COMPILER_OUTPUT=1 or the CLI's --verbose (which sets it). The
    kernels build without warnings (tests/test_kernel_warnings.py); a build log on another
    driver (notes, remarks) would otherwise print on every first render, --quiet or not."""
    from pytools import strtobool
    try:
        return bool(strtobool(os.environ.get("PYOPENCL_COMPILER_OUTPUT", "False")))
    except ValueError:
        return False


UPLOAD, READBACK = "upload", "readback"


def _call_site() -> str:
    """``module.function`` of the nearest caller outside this module (a transfer's default
    label)."""
    f = sys._getframe(1)
    while f is not None and f.f_globals.get("__name__") == __name__:
        f = f.f_back
    if f is None:
        return "?"
    return f"{f.f_globals.get('__name__', '?')}.{f.f_code.co_name}"


class Transfers:
    """Host<->device copies made through one ``Runtime``: calls and bytes per
    (direction, label), direction ``UPLOAD`` (host -> device) or ``READBACK`` (device ->
    host); ``sizes`` counts calls per (direction, bytes), so a copy of a given array's size is
    seen whatever its label. ``since(earlier)`` is what happened after a ``copy()``."""

    def __init__(self):
        self.count: Counter = Counter()
        self.bytes: Counter = Counter()
        self.sizes: Counter = Counter()

    def record(self, direction: str, label: str, nbytes: int) -> None:
        self.count[direction, label] += 1
        self.bytes[direction, label] += int(nbytes)
        self.sizes[direction, int(nbytes)] += 1

    def copy(self) -> "Transfers":
        t = Transfers()
        t.count, t.bytes, t.sizes = Counter(self.count), Counter(self.bytes), Counter(self.sizes)
        return t

    def since(self, earlier: "Transfers") -> "Transfers":
        t = Transfers()
        t.count, t.bytes = self.count - earlier.count, self.bytes - earlier.bytes
        t.sizes = self.sizes - earlier.sizes
        return t

    def calls(self, direction: str, label: str | None = None) -> int:
        """Calls in ``direction`` (with ``label``, or all)."""
        return sum(n for (d, lab), n in self.count.items()
                   if d == direction and (label is None or lab == label))

    def nbytes(self, direction: str, label: str | None = None) -> int:
        return sum(n for (d, lab), n in self.bytes.items()
                   if d == direction and (label is None or lab == label))

    def labels(self, direction: str) -> dict:
        """{label: calls} in ``direction``."""
        return {lab: n for (d, lab), n in self.count.items() if d == direction}

    def report(self) -> str:
        rows = [f"{d:<8} {lab:<56} {self.count[d, lab]:>5} calls {self.bytes[d, lab]:>12} bytes"
                for d, lab in sorted(self.count)]
        return "\n".join(rows) if rows else "(no transfers)"


def _finish_quietly(queue) -> None:
    try:
        queue.finish()
    except Exception:  # noqa: BLE001 - at exit a released context is not an error to report
        pass


class Runtime:
    """A context and an in-order queue on one device, plus the program cache and the
    transfer counters (``transfers``)."""

    def __init__(self, device: str | None = None, profiling: bool = False):
        entry, why = choose_device(device)
        self.entry = entry
        self.device = entry.device
        self.reason = why
        self.lanes = device_lanes(entry)   # -D LANES of every program (cl/include/lanes.h)
        self.driver_defines = driver_defines(entry)   # workarounds, on every program
        self.profiling = profiling
        self.context = cl.Context([self.device])
        props = cl.command_queue_properties.PROFILING_ENABLE if profiling else 0
        self.queue = cl.CommandQueue(self.context, properties=props)
        # Drain the queue before the interpreter exits: a process that ended on an error with
        # an upload still queued crashed in PoCL's teardown (SIGSEGV after its last line, about
        # 1 run in 5 of tests/test_bounded.py's "density 1e30 everywhere" child, cold cache).
        atexit.register(_finish_quietly, self.queue)
        self._programs: dict[tuple, Program] = {}
        self._events: list[tuple[str, cl.Event]] = []
        self.kernel_seconds: dict[str, float] = {}
        self.kernel_launches: dict[str, int] = {}
        self.transfers = Transfers()

    @property
    def is_oclgrind(self) -> bool:
        return "oclgrind" in self.entry.platform.name.lower()

    @property
    def is_pocl(self) -> bool:
        return "portable computing language" in self.entry.platform.name.lower()

    # -- programs
    def program(self, stem: str, defines: dict | None = None,
                extra_options: tuple[str, ...] = ()) -> Program:
        """Build (or fetch from cache) ``cl/<stem>.cl`` with the given ``-D`` defines and the
        device's ``-D LANES``."""
        path = cl_source_dir() / f"{stem}.cl"
        if not path.is_file():
            raise BuildError(f"no OpenCL source {path}")
        src_hash = _sources_hash(path)
        options = tuple(["-I", str(include_dir()), f"-DCLVOL_SOURCES_HASH=0x{src_hash}",
                         f"-DLANES={self.lanes}"]
                        + _define_flags(dict(self.driver_defines, **(defines or {})))
                        + list(extra_options))
        key = (src_hash, options, self.entry.spec)
        prog = self._programs.get(key)
        if prog is None:
            program = cl.Program(self.context, path.read_text())
            try:
                with warnings.catch_warnings():
                    if not compiler_output_shown():
                        warnings.simplefilter("ignore", cl.CompilerWarning)
                    program.build(options=list(options), devices=[self.device])
            except cl.Error as exc:
                try:
                    log = program.get_build_info(self.device, cl.program_build_info.LOG)
                except cl.Error:
                    log = str(exc)
                raise BuildError(
                    f"{path.name} failed to build on {self.entry.label} with options "
                    f"{' '.join(options)}:\n{(log or str(exc)).strip()}", stem=stem,
                    device=self.entry.label, first_error=first_build_error(log or str(exc))
                ) from None
            prog = Program(self, stem, program, options)
            self._programs[key] = prog
        return prog

    # -- buffers
    def to_device(self, array: np.ndarray, writable: bool = False,
                  label: str | None = None) -> "cl.Buffer":
        """Copy a host array into a new buffer (C-contiguous; at least 1 byte). Counted in
        ``transfers`` under ``label`` (default: the caller's function)."""
        a = np.ascontiguousarray(array)
        flags = (cl.mem_flags.READ_WRITE if writable else cl.mem_flags.READ_ONLY)
        if a.nbytes == 0:  # zero-size buffers are invalid in OpenCL
            return cl.Buffer(self.context, flags, size=max(a.itemsize, 4))
        self.transfers.record(UPLOAD, label or _call_site(), a.nbytes)
        return cl.Buffer(self.context, flags | cl.mem_flags.COPY_HOST_PTR, hostbuf=a)

    def empty(self, shape, dtype=np.float32, zero: bool = False) -> "cl.Buffer":
        """A new device buffer; zero-filled on request.

        Under Oclgrind it is always written from the host: Oclgrind's uninitialised-value
        check does not carry what one launch stored over to the next, so a buffer written only
        by kernels would be reported when a later kernel reads it."""
        nbytes = max(int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize, 4)
        buf = cl.Buffer(self.context, cl.mem_flags.READ_WRITE, size=nbytes)
        if zero or self.is_oclgrind:
            self.zero(buf)
        return buf

    def upload(self, array, dtype=np.float32, label: str | None = None) -> "DeviceArray":
        """A C-ordered copy of ``array`` on the device (counted under ``label``)."""
        a = np.ascontiguousarray(array, dtype)
        return DeviceArray(self.to_device(a, label=label or _call_site()), a.shape, a.dtype,
                           self)

    def alloc(self, shape, dtype=np.float32, zero: bool = False) -> "DeviceArray":
        """A new device array (contents undefined unless ``zero``)."""
        shape = (int(shape),) if np.isscalar(shape) else tuple(int(n) for n in shape)
        return DeviceArray(self.empty(shape, dtype, zero), shape, np.dtype(dtype), self)

    def from_device(self, buf, shape, dtype=np.float32, wait_for=None,
                    label: str | None = None) -> np.ndarray:
        """A host copy of the first ``shape`` elements of ``buf`` (a cl.Buffer or a
        DeviceArray), counted in ``transfers`` under ``label`` (default: the caller)."""
        if isinstance(buf, DeviceArray):
            buf = buf.buffer
        out = np.empty(shape, dtype=dtype)
        if out.nbytes:
            self.transfers.record(READBACK, label or _call_site(), out.nbytes)
            cl.enqueue_copy(self.queue, out, buf, wait_for=wait_for)
        return out

    def write(self, dst: "DeviceArray", array, offset: int = 0,
              label: str | None = None) -> "cl.Event":
        """Copy a host array into ``dst`` from element ``offset`` on (counted as an upload)."""
        a = np.ascontiguousarray(array, dst.dtype)
        if offset < 0 or offset + a.size > dst.size:
            raise ValueError(f"write of {a.size} elements at {offset} past a DeviceArray of "
                             f"{dst.size}")
        if not a.nbytes:
            return None
        return self._write_bytes(dst.buffer, a.reshape(-1).view(np.uint8),
                                 int(offset) * np.dtype(dst.dtype).itemsize,
                                 label or _call_site())

    def _write_bytes(self, buf, data: np.ndarray, byte_offset: int, label: str):
        """Host bytes into ``buf`` at ``byte_offset``. Under Oclgrind the whole buffer is
        written: its uninitialised-value check loses track of a buffer written in part
        (clEnqueueWriteBuffer or CopyBuffer of less than the buffer; measured: mip_reduce
        reported level 0 written alone into a zeroed pyramid), so the rest is read back and
        written with it (counted under "(Oclgrind) whole-buffer write")."""
        if self.is_oclgrind and data.nbytes != buf.size:
            whole = np.empty(buf.size, np.uint8)
            self.transfers.record(READBACK, "(Oclgrind) whole-buffer write", whole.nbytes)
            cl.enqueue_copy(self.queue, whole, buf)
            whole[byte_offset:byte_offset + data.nbytes] = data
            data, byte_offset = whole, 0
        self.transfers.record(UPLOAD, label, data.nbytes)
        return cl.enqueue_copy(self.queue, buf, data, dst_offset=int(byte_offset))

    def zero(self, dst) -> "cl.Event":
        """Fill ``dst`` (a DeviceArray or a cl.Buffer) with zero bytes on the device (no host
        transfer); under Oclgrind from the host, as ``empty`` does."""
        buf = dst.buffer if isinstance(dst, DeviceArray) else dst
        if self.is_oclgrind:
            self.transfers.record(UPLOAD, "zeros (Oclgrind)", buf.size)
            return cl.enqueue_copy(self.queue, buf, np.zeros(buf.size, np.uint8))
        return cl.enqueue_fill_buffer(self.queue, buf, np.uint8(0), 0, buf.size)

    def copy(self, dst: "DeviceArray", src: "DeviceArray", nbytes: int | None = None,
             dst_offset: int = 0, src_offset: int = 0) -> "cl.Event":
        """Device-to-device copy of ``nbytes`` (default all of ``src``; offsets in bytes):
        no host transfer."""
        n = src.nbytes if nbytes is None else int(nbytes)
        if self.is_oclgrind and n != dst.buffer.size:   # see _write_bytes: through the host
            data = np.empty(src.buffer.size, np.uint8)
            self.transfers.record(READBACK, "(Oclgrind) whole-buffer write", data.nbytes)
            cl.enqueue_copy(self.queue, data, src.buffer)
            return self._write_bytes(dst.buffer, data[int(src_offset):int(src_offset) + n],
                                     int(dst_offset), "(Oclgrind) whole-buffer write")
        return cl.enqueue_copy(self.queue, dst.buffer, src.buffer, byte_count=n,
                               dst_offset=int(dst_offset), src_offset=int(src_offset))

    # -- launches
    def launch(self, kernel: "cl.Kernel", global_size, args, local_size=None,
               pad: int = DEFAULT_PAD, wait_for=None) -> "cl.Event":
        """Enqueue ``kernel``. The first global dimension is padded to a multiple of
        ``pad`` (kernels guard with their own element count); others are used as given.
        ``args=None`` launches with the arguments already set on the kernel (``set_args`` /
        ``set_arg``: a loop of launches that changes one argument)."""
        gs = (global_size,) if np.isscalar(global_size) else tuple(global_size)
        gs = (padded(gs[0], pad),) + tuple(max(int(g), 1) for g in gs[1:])
        if args is None:
            evt = cl.enqueue_nd_range_kernel(self.queue, kernel, gs, local_size, wait_for=wait_for)
        else:
            evt = kernel(self.queue, gs, local_size, *args, wait_for=wait_for)
        if self.profiling:
            self._events.append((kernel.function_name, evt))
        return evt

    def finish(self) -> None:
        self.queue.finish()
        if self.profiling:
            for name, evt in self._events:
                secs = (evt.profile.end - evt.profile.start) * 1e-9
                self.kernel_seconds[name] = self.kernel_seconds.get(name, 0.0) + secs
                self.kernel_launches[name] = self.kernel_launches.get(name, 0) + 1
            self._events.clear()

    def timing_report(self) -> str:
        """Per-kernel device time collected with ``profiling=True``."""
        self.finish()
        rows = [f"{n:<32} {self.kernel_launches[n]:>6} launches {s * 1e3:10.3f} ms"
                for n, s in sorted(self.kernel_seconds.items(), key=lambda kv: -kv[1])]
        return "\n".join(rows) if rows else "(no profiled launches)"


@dataclass(frozen=True, eq=False)
class DeviceArray:
    """A C-ordered array living in ``buffer`` on ``runtime``'s device: the one handle device
    data travels in between modules (a raw ``cl.Buffer`` stays inside the function that hands
    it to pyopencl)."""
    buffer: "cl.Buffer"
    shape: tuple
    dtype: np.dtype = np.dtype(np.float32)
    runtime: "Runtime | None" = None

    @classmethod
    def upload(cls, array, runtime=None, label: str | None = None) -> "DeviceArray":
        return (runtime or get_runtime()).upload(array, label=label or _call_site())

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))

    @property
    def nbytes(self) -> int:
        return self.size * np.dtype(self.dtype).itemsize

    def reshape(self, *shape) -> "DeviceArray":
        """The same buffer seen with another shape of the same size."""
        shape = tuple(shape[0]) if len(shape) == 1 and not np.isscalar(shape[0]) else shape
        shape = tuple(int(n) for n in shape)
        if int(np.prod(shape, dtype=np.int64)) != self.size:
            raise ValueError(f"cannot view a DeviceArray of shape {self.shape} as {shape}")
        return DeviceArray(self.buffer, shape, self.dtype, self.runtime)

    def read(self, wait_for=None, label: str | None = None) -> np.ndarray:
        return (self.runtime or get_runtime()).from_device(
            self.buffer, self.shape, self.dtype, wait_for=wait_for, label=label or _call_site())


_RUNTIMES: dict[tuple, Runtime] = {}
_DEFAULTS = {"device": None, "profiling": False}


def configure(device: str | None = None, profiling: bool | None = None) -> None:
    """Process-wide defaults for ``get_runtime()`` calls that give no arguments (the CLI's
    ``--device`` and ``--profile`` reach every render method this way)."""
    if device is not None:
        _DEFAULTS["device"] = device
    if profiling is not None:
        _DEFAULTS["profiling"] = bool(profiling)


def get_runtime(device: str | None = None, profiling: bool | None = None) -> Runtime:
    """The process-wide runtime for a device spec (resolved as ``choose_device`` does;
    unspecified arguments take the ``configure`` defaults)."""
    device = device if device is not None else _DEFAULTS["device"]
    profiling = profiling if profiling is not None else _DEFAULTS["profiling"]
    entry, _ = choose_device(device)
    key = (entry.spec, profiling, device_lanes(entry))
    rt = _RUNTIMES.get(key)
    if rt is None:
        rt = _RUNTIMES[key] = Runtime(device, profiling)
    return rt


class Stopwatch:
    """Wall-clock timing of host-side steps (``with Stopwatch() as sw: ...; sw.seconds``)."""

    def __enter__(self):
        self._t0 = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.seconds = time.perf_counter() - self._t0
