"""Data set generation on Ray: one shard is one Ray task (docs/dataset.md).

    make_dataset_ray(spec, "runs/data")                      # a local Ray on this machine's cores
    make_dataset_ray(spec, "runs/data", address="auto")      # the cluster this node belongs to
    generate(spec, "runs/data", serial=True)                 # clvol.training.dataset.make_dataset

A worker makes the shard and returns the bytes of its file (clvol.training.dataset.shard_bytes); only
this process (the driver) writes, atomically, so workers need no shared file system, a killed
worker's task is simply rerun by Ray (``max_retries``), and a shard is written once whatever
happens to the workers. The folder handling is the serial path's (``pending_shards``: the
spec check, stale temporary files removed, finished shards skipped), and so are the bytes:
a shard is a pure function of (spec, v, c) and the device.

Each worker process creates its own clvol OpenCL runtime on its first task (the default
device of that node, or CLVOL_DEVICE), so every node needs an OpenCL driver and clvol.

Fault injection for tests: CLVOL_FAULT_KILL_SHARD="v,c" in the driver's environment makes
the worker running shard (v, c) SIGKILL itself after computing it, before returning; with
CLVOL_FAULT_MARKER=PATH only while PATH does not exist (the killed attempt creates it, so the
retry succeeds; it holds the killed process id; PATH must be on the worker's file system).
"""
from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

from ..errors import ClvolError
from . import dataset as ds

INSTALL_HINT = "pip install 'clvol[scale]' (or pip install ray)"
DEFAULT_RETRIES = 3

# Ray on Linux replaces a loopback node address by the machine's outward one (it assumes a
# cluster); a local run must stay on 127.0.0.1. Read when ray is first imported.
_LOCAL_ENV = {"RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}


class DistributedError(ClvolError):
    """Ray missing, unreachable, or a shard task that failed on every attempt."""


def ray_available() -> bool:
    # find_spec, not import: ray's settings (_LOCAL_ENV) are read when it is first imported
    import importlib.util
    return importlib.util.find_spec("ray") is not None


def import_ray(local: bool):
    if local:
        for k, v in _LOCAL_ENV.items():
            os.environ.setdefault(k, v)
    try:
        import ray
    except ImportError:
        raise DistributedError(f"Ray is not installed: {INSTALL_HINT}") from None
    return ray


def local_init_kwargs(workers: int | None = None) -> dict:
    """ray.init arguments of a private local Ray: loopback only, no dashboard, ``workers``
    CPUs (default: all of them), and workers that import the same clvol as this process."""
    clvol_root = str(Path(__file__).resolve().parents[2])  # the folder holding clvol/
    path = os.pathsep.join(p for p in (clvol_root, os.environ.get("PYTHONPATH")) if p)
    kw = {"_node_ip_address": "127.0.0.1", "include_dashboard": False,
          "runtime_env": {"env_vars": {"PYTHONPATH": path}}, "logging_level": "WARNING",
          "log_to_driver": True}
    if workers is not None:
        kw["num_cpus"] = workers
    return kw


def connect_error_message(address: str | None, exc: BaseException) -> str:
    """One line for a failed ray.init: the exception's first line and, when Ray sends a
    traceback (Ray Client: "Initialization failure from server:" and the server's
    traceback), its last line, which names the cause."""
    lines = [x.strip() for x in str(exc).splitlines() if x.strip()]
    what = lines[0] if lines else type(exc).__name__
    if len(lines) > 1 and lines[-1] != what:
        what = f"{what.rstrip(':')}: {lines[-1]}"
    msg = f"cannot start or reach Ray at {address or 'local'}: {what}"
    if "Starting Ray client server failed" in what:
        msg += (" (on the head: run `ray start --head` with GRPC_ENABLE_FORK_SUPPORT=0 in its "
                "environment, see docs/dataset.md)")
    return msg


def _fault_switch() -> tuple | None:
    spec = os.environ.get("CLVOL_FAULT_KILL_SHARD")
    if not spec:
        return None
    try:
        v, c = (int(x) for x in spec.split(","))
    except ValueError:
        raise DistributedError(f"CLVOL_FAULT_KILL_SHARD = {spec!r}: expected 'v,c' "
                               "(two integers)") from None
    return v, c, os.environ.get("CLVOL_FAULT_MARKER")


_MAKER = None     # one per worker process: keeps its OpenCL runtime and last volume


def shard_task(spec_dict: dict, v: int, c: int, fault: tuple | None = None) -> dict:
    """Body of a Ray task (runs in a worker): shard (v, c) as file bytes."""
    import ray
    global _MAKER
    if _MAKER is None:
        _MAKER = ds.ShardMaker()
    spec = ds.DatasetSpec.from_dict(spec_dict)
    data, meta = _MAKER(spec, v, c)
    if fault is not None and (fault[0], fault[1]) == (v, c):
        marker = fault[2]
        if marker is None or not os.path.exists(marker):
            if marker is not None:
                Path(marker).write_text(str(os.getpid()))
            os.kill(os.getpid(), signal.SIGKILL)     # mid-task: the result is never returned
    return {"bytes": data, "contract": meta["contract"],
            "log": {**(meta.get("seconds") or {}), "node": ray.util.get_node_ip_address()}}


def make_dataset_ray(spec: ds.DatasetSpec, out_dir, address: str | None = None,
                     workers: int | None = None, progress: bool = True,
                     retries: int = DEFAULT_RETRIES, on_shard=None) -> dict:
    """Make every missing shard of ``spec`` in ``out_dir`` as Ray tasks. ``address``: None
    starts a private local Ray (``workers`` CPUs, default all), or "auto" / "HOST:PORT" /
    "ray://HOST:PORT" joins a running cluster; if this process already called ray.init, that
    Ray is used. Returns {"made", "skipped"} like clvol.training.dataset.make_dataset."""
    if workers is not None and address is not None:
        raise DistributedError("--workers applies to a local Ray only; a cluster's size is "
                               "set by `ray start --num-cpus` on its nodes")
    ray = import_ray(local=address is None)
    out = Path(out_dir)
    todo = ds.pending_shards(spec, out)
    started = False
    if ray.is_initialized() and workers is not None:
        raise DistributedError("workers: Ray is already running in this process; its size "
                               "was set when it was started")
    if not ray.is_initialized():
        try:
            if address is None:
                ray.init(**local_init_kwargs(workers))
            else:
                ray.init(address=address, logging_level="WARNING")
        except (ConnectionError, ValueError, RuntimeError) as exc:
            raise DistributedError(connect_error_message(address, exc)) from None
        started = True
    try:
        return _run(ray, spec, out, todo, progress, retries, on_shard)
    finally:
        if started:
            ray.shutdown()


def _run(ray, spec, out, todo, progress, retries, on_shard) -> dict:
    task = ray.remote(num_cpus=1, max_retries=retries)(shard_task)
    spec_dict = spec.to_dict()
    want = ds._code_contract(spec)
    fault = _fault_switch()
    # A bounded window of tasks in flight: results (a few MB each) wait in the object store
    # only until written, and an error stops the run without a long queue behind it.
    window = max(4, 2 * int(ray.cluster_resources().get("CPU", 1)))
    queue = list(todo)
    queue.reverse()
    running: dict = {}
    made = 0
    with ds.shard_progress(len(todo), spec, progress) as bar:
        try:
            while queue or running:
                while queue and len(running) < window:
                    v, c = queue.pop()
                    running[task.remote(spec_dict, v, c, fault)] = (v, c)
                done, _ = ray.wait(list(running), num_returns=1)
                for ref in done:
                    v, c = running.pop(ref)
                    r = _result(ray, ref, v, c, retries)
                    if r["contract"] != want:
                        raise DistributedError(
                            f"shard ({v}, {c}): the worker's clvol has code contract "
                            f"{r['contract']}, this one {want}; install the same clvol on every node")
                    ds.write_shard(out, v, c, r["bytes"], r["log"])
                    made += 1
                    bar.update(1)
                    if on_shard is not None:
                        on_shard(v, c)
        finally:
            for ref in running:     # after an error: drop the rest, keep the workers (warm)
                ray.cancel(ref)
    return {"made": made, "skipped": spec.n_shards - len(todo)}


def _result(ray, ref, v, c, retries) -> dict:
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as exc:
        cause = getattr(exc, "cause", None)
        if isinstance(cause, ClvolError):      # bad input found in the worker: say it as is
            raise cause from None
        raise DistributedError(f"shard ({v}, {c}) failed in a worker: "
                               f"{str(exc).strip().splitlines()[-1]}") from None
    except ray.exceptions.RayError as exc:
        raise DistributedError(f"shard ({v}, {c}) failed on {retries + 1} attempt(s) "
                               f"({type(exc).__name__}); see the Ray logs of the workers") from None


def generate(spec: ds.DatasetSpec, out_dir, address: str | None = None, serial: bool = False,
             workers: int | None = None, progress: bool = True, log=None, part=None) -> dict:
    """What `clvol dataset make` runs: Ray if installed (local, or ``address``), else the
    serial path with a note on how to get Ray. Adds "engine" to the returned counts.
    ``part`` (i, n) needs ``serial``: n such processes share one device and one folder."""
    if part is not None and not serial:
        raise DistributedError("--part splits the serial engine across processes: add --serial "
                               "(Ray already spreads the shards over its workers)")
    if serial:
        if address is not None or workers is not None:
            raise DistributedError("--serial runs in this process: drop --address/--workers")
        return {**ds.make_dataset(spec, out_dir, progress=progress, part=part), "engine": "serial"}
    if not ray_available():
        if address is not None or workers is not None:
            raise DistributedError(f"--address/--workers need Ray, which is not installed: "
                                   f"{INSTALL_HINT}")
        print(f"clvol: Ray is not installed, making shards serially in this process; for "
              f"all cores or a cluster: {INSTALL_HINT}", file=log or sys.stderr)
        return {**ds.make_dataset(spec, out_dir, progress=progress), "engine": "serial"}
    r = make_dataset_ray(spec, out_dir, address=address, workers=workers, progress=progress)
    return {**r, "engine": "ray"}
