"""Time every program build and every kernel launch of one clvol command, one at a time.

    python scripts/trace_builds.py render examples/cloud.toml --width 32 --height 32 -o /tmp/c.exr

runs ``clvol <args>`` in this process with ``Runtime.program`` and ``Runtime.launch`` wrapped:
each build prints its file, defines and seconds before and after it runs (so a build that
never ends is the last "build ..." line), and each launch waits for the queue and prints the
kernel, its global size and seconds. Launch times include the wait for anything queued
before it (transfers), so they are an upper bound of the kernel's. Meant for a driver on which
a render stalls (docs/opencl.md, "rusticl"): put ``timeout`` in front and read the last line.
"""
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path[:1]:
    sys.path.insert(0, str(ROOT))

from clvol import runtime as _rt  # noqa: E402

_T0 = time.perf_counter()


def _say(msg: str) -> None:
    print(f"[{time.perf_counter() - _T0:8.2f} s] {msg}", file=sys.stderr, flush=True)


def _short(options: tuple) -> str:
    return " ".join(o for o in options
                    if o.startswith("-D") and not o.startswith("-DCLVOL_SOURCES_HASH"))


_program = _rt.Runtime.program
_launch = _rt.Runtime.launch


def program(self, stem, defines=None, extra_options=()):
    key_before = len(self._programs)
    t = time.perf_counter()
    flags = " ".join(_rt._define_flags(defines) + list(extra_options))
    announced = False
    # only a build that is not already cached is announced (the cache lookup is cheap)
    path = _rt.cl_source_dir() / f"{stem}.cl"
    src_hash = _rt._sources_hash(path)
    options = tuple(["-I", str(_rt.include_dir()), f"-DCLVOL_SOURCES_HASH=0x{src_hash}",
                     f"-DLANES={self.lanes}"] + _rt._define_flags(defines) + list(extra_options))
    if (src_hash, options, self.entry.spec) not in self._programs:
        _say(f"build {stem}.cl {flags} ...")
        announced = True
    prog = _program(self, stem, defines, extra_options)
    if announced or len(self._programs) != key_before:
        _say(f"built {stem}.cl in {time.perf_counter() - t:.2f} s")
    return prog


def launch(self, kernel, global_size, args, local_size=None, pad=_rt.DEFAULT_PAD,
           wait_for=None):
    name = kernel.function_name
    self.queue.finish()
    _say(f"launch {name} global {global_size} ...")
    t = time.perf_counter()
    evt = _launch(self, kernel, global_size, args, local_size, pad, wait_for)
    self.queue.finish()
    _say(f"ran {name} in {time.perf_counter() - t:.3f} s")
    return evt


_rt.Runtime.program = program
_rt.Runtime.launch = launch

if __name__ == "__main__":
    import faulthandler
    import os
    import signal
    # `kill -USR1 PID` prints where Python is (a stall inside a driver call shows the call)
    faulthandler.register(signal.SIGUSR1)
    if os.environ.get("TRACE_DUMP_AFTER"):   # or print it after that many seconds, repeatedly
        faulthandler.dump_traceback_later(float(os.environ["TRACE_DUMP_AFTER"]), repeat=True)
    from clvol.cli import main
    rt = _rt.get_runtime()
    _say(f"device {rt.entry.label}, lanes {rt.lanes}")
    sys.exit(main(sys.argv[1:]))
