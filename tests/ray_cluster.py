"""A two-node Ray cluster on loopback for the tests (tests/test_dataset_ray.py,
tests/test_heldout_training.py).

The cluster runs in its own network, process and mount namespaces (unshare): the only interface
is loopback, so Ray's servers cannot listen on or reach any other address; `ray stop` inside
sees (and stops) only this cluster's processes, never another Ray on the machine; and a private
/tmp/ray keeps the cluster's address file (what `--address auto` reads) and logs to itself.
``run(body, ...)`` starts a head on 127.0.0.2 (port 6379) and a worker node on 127.0.0.3, one
CPU each, then runs the shell ``body`` ($PY, $ROOT and $LOGS set); on failure Ray's logs are
copied to $LOGS/ray and their tails printed.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
ADDRESS = "127.0.0.2:6379"

_START = r"""
set -eu
"$PY" -c '
import fcntl, socket, struct                  # `ip link set lo up` without iproute2
SIOCSIFFLAGS, IFF_UP, IFF_LOOPBACK, IFF_RUNNING = 0x8914, 0x1, 0x8, 0x40
fcntl.ioctl(socket.socket(), SIOCSIFFLAGS,
            struct.pack("16sH22x", b"lo", IFF_UP | IFF_LOOPBACK | IFF_RUNNING))
'
mkdir -p /tmp/ray && mount -t tmpfs tmpfs /tmp/ray
stop() {
    rc=$?
    if [ $rc != 0 ]; then
        cp -r /tmp/ray/session_latest/logs "$LOGS/ray" 2>/dev/null || true
        tail -n 5 /tmp/ray/session_latest/logs/*.err 2>/dev/null | tail -n 60 >&2
    fi
    ray stop --force >/dev/null 2>&1 || true
    exit $rc
}
trap stop EXIT
ray start --head --node-ip-address 127.0.0.2 --port 6379 --num-cpus 1 \
    --include-dashboard false --disable-usage-stats > "$LOGS/head.log" 2>&1
ray start --address 127.0.0.2:6379 --node-ip-address 127.0.0.3 --num-cpus 1 \
    --disable-usage-stats > "$LOGS/worker.log" 2>&1
"""


def unshare_works() -> bool:
    if shutil.which("unshare") is None:
        return False
    return subprocess.run(["unshare", "--net", "--pid", "--fork", "--mount-proc", "true"],
                          capture_output=True).returncode == 0


SKIP_REASON = ("needs unshare (net+pid namespaces) to keep the cluster on loopback and its "
               "`ray stop` away from other Ray processes")


def run(body: str, *args, cwd, logs: Path, env: dict | None = None, timeout: float = 600):
    """Start the cluster, run ``body`` (bash, positional ``args``), stop the cluster."""
    e = {**os.environ, "RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0",
         # The Ray Client proxy (started by `ray start --head`) forks a server process per
         # client with a preexec_fn, so the child runs the at-fork hooks, gRPC's fork support
         # among them; it starts threads in the child before exec, which can segfault (strace:
         # the child "killed by SIGSEGV" before exec, no log; the proxy then waits out its
         # channel timeout and answers "Initialization failure from server"). It happened in 2
         # of 2 cold tries and 0 of 3 with gRPC's fork support off (the proxy only forks to
         # exec, so it needs none). docs/dataset.md says the same.
         "GRPC_ENABLE_FORK_SUPPORT": "0",
         "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
         "PY": sys.executable, "ROOT": str(ROOT), "LOGS": str(logs), **(env or {})}
    e.pop("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", None)     # a real (multi-node) cluster
    logs.mkdir(parents=True, exist_ok=True)
    return subprocess.run(["unshare", "--net", "--pid", "--fork", "--mount-proc", "bash", "-c",
                           _START + body, "cluster", *map(str, args)], env=e, cwd=cwd,
                          capture_output=True, text=True, timeout=timeout)
