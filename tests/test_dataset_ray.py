"""Data set generation on Ray (clvol/training/distributed.py): byte-identical to the serial path,
resumable, a killed worker's shard retried, a two-node cluster on loopback, and the serial
fallback without Ray.

One tiny spec throughout (2 cloud volumes at 12^3, 2 configurations each, 24 points, 16
paths; seed 67 draws only isotropic phases, which need no phase table: a fresh worker costs
only its OpenCL set-up): what is tested is dispatch, retries and file handling, not labels. One local Ray (2 CPUs, on
127.0.0.1) is shared by the tests of this module: starting Ray costs several seconds.
"""
from __future__ import annotations

import ipaddress
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import ray_cluster

from clvol import cli
from clvol.training import dataset as ds
from clvol.training import distributed as dist

# Tiny and cheap: two volumes of cheap families (no plume), one of them held out.
SPEC = ds.DatasetSpec(seed=67, n_volumes=2, n_heldout_volumes=1, resolution=(12, 12),
                      base_resolution=16, configs_per_volume=2, points_per_config=24, n_paths=16,
                      families=("cumulus", "blob"))
SPEC_ARGS = ["--seed", "67", "--volumes", "2", "--heldout", "1", "--resolution", "12,12",
             "--base", "16", "--configs", "2", "--points", "24", "--paths", "16",
             "--families", "cumulus,blob", "--no-progress"]
ROOT = Path(__file__).resolve().parent.parent


def shard_files(folder) -> dict:
    return {p.name: p.read_bytes() for p in sorted(Path(folder).glob("shard_*.npz"))}


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    """The serial path's data set of SPEC: {file name: bytes}."""
    out = tmp_path_factory.mktemp("serial")
    assert ds.make_dataset(SPEC, out, progress=False) == {"made": 4, "skipped": 0}
    files = shard_files(out)
    assert len(files) == SPEC.n_shards
    return files


@pytest.fixture(scope="module")
def local_ray():
    ray = dist.import_ray(local=True)    # loopback-only settings before ray is first imported
    if ray.is_initialized():
        ray.shutdown()
    ray.init(**dist.local_init_kwargs(workers=2))
    try:
        # a local Ray must stay on loopback (Ray on Linux would pick the outward address)
        assert [n["NodeManagerAddress"] for n in ray.nodes()] == ["127.0.0.1"]
        yield ray
    finally:
        ray.shutdown()


def test_ray_shards_are_the_serial_bytes_and_a_run_resumes(local_ray, serial, tmp_path):
    out = tmp_path / "data"
    ds.make_dataset(SPEC, out, progress=False, max_shards=1)       # an interrupted serial run
    written = []
    r = dist.make_dataset_ray(SPEC, out, on_shard=lambda v, c: written.append((v, c)))
    assert r == {"made": 3, "skipped": 1}
    assert sorted(written) == [(0, 1), (1, 0), (1, 1)]              # the finished one not redone
    assert shard_files(out) == serial                               # byte for byte
    assert not list(out.glob(".*.tmp"))
    log = [json.loads(line) for line in (out / ds.TIMINGS_FILE).read_text().splitlines()]
    assert sorted(x["shard"] for x in log) == sorted(serial)        # one line per write
    assert {x["node"] for x in log if "node" in x} == {"127.0.0.1"}
    assert dist.make_dataset_ray(SPEC, out) == {"made": 0, "skipped": 4}
    other = ds.DatasetSpec(**{**SPEC.to_dict(), "n_paths": 17})
    with pytest.raises(ds.DatasetError, match=r"spec.json.*\['n_paths'\]"):
        dist.make_dataset_ray(other, out)


def test_killed_worker_is_retried_without_loss_or_duplicates(local_ray, serial, tmp_path,
                                                            monkeypatch):
    marker = tmp_path / "killed"
    monkeypatch.setenv("CLVOL_FAULT_KILL_SHARD", "1,0")
    monkeypatch.setenv("CLVOL_FAULT_MARKER", str(marker))
    out = tmp_path / "data"
    written = []
    r = dist.make_dataset_ray(SPEC, out, on_shard=lambda v, c: written.append((v, c)))
    # the first attempt of shard (1, 0) really died: its process is gone
    pid = int(marker.read_text())
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)
    assert r == {"made": 4, "skipped": 0}
    assert sorted(written) == [(0, 0), (0, 1), (1, 0), (1, 1)]      # each written exactly once
    assert shard_files(out) == serial


def test_shard_killed_on_every_attempt_fails_cleanly_and_resumes(local_ray, serial, tmp_path,
                                                                 monkeypatch):
    monkeypatch.setenv("CLVOL_FAULT_KILL_SHARD", "0,1")           # no marker: every attempt
    monkeypatch.delenv("CLVOL_FAULT_MARKER", raising=False)
    out = tmp_path / "data"
    with pytest.raises(dist.DistributedError, match=r"shard \(0, 1\) failed on 2 attempt\(s\)"):
        dist.make_dataset_ray(SPEC, out, retries=1)
    assert ds.shard_name(0, 1) not in shard_files(out)
    for name, data in shard_files(out).items():                      # whatever was written is whole
        assert data == serial[name]
    monkeypatch.delenv("CLVOL_FAULT_KILL_SHARD")
    r = dist.make_dataset_ray(SPEC, out)
    assert r["made"] + r["skipped"] == 4 and r["made"] >= 1
    assert shard_files(out) == serial


def test_cli_without_ray_runs_serially_and_says_how_to_get_it(serial, tmp_path, monkeypatch,
                                                              capsys):
    monkeypatch.setattr(dist, "ray_available", lambda: False)
    out = tmp_path / "data"
    assert cli.main(["dataset", "make", str(out), *SPEC_ARGS]) == 0
    captured = capsys.readouterr()
    assert "pip install 'clvol[scale]'" in captured.err and "(serial)" in captured.out
    assert shard_files(out) == serial
    # an option that needs Ray is refused, not ignored
    assert cli.main(["dataset", "make", str(out), *SPEC_ARGS, "--address", "auto"]) == 2
    assert "need Ray" in capsys.readouterr().err
    assert cli.main(["dataset", "make", str(out), *SPEC_ARGS, "--serial", "--workers", "2"]) == 2
    assert "--serial runs in this process" in capsys.readouterr().err


def test_make_dataset_script_is_the_cli(serial, tmp_path):
    """scripts/make_dataset.py runs `clvol dataset make`: on a finished folder it checks the
    spec and skips every shard (no shard is computed, so this stays cheap)."""
    out = tmp_path / "data"
    ds.pending_shards(SPEC, out)                                    # spec.json
    for name, data in serial.items():
        (out / name).write_bytes(data)
    script = [sys.executable, str(ROOT / "scripts" / "make_dataset.py"), str(out), *SPEC_ARGS]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.run([*script, "--serial"], capture_output=True, text=True, env=env)
    assert p.returncode == 0, p.stderr
    assert "made 0 shards (0 labels), skipped 4 finished ones" in p.stdout
    p = subprocess.run([*script, "--serial", "--paths", "17"], capture_output=True, text=True,
                       env=env)
    assert p.returncode == 2 and "['n_paths']" in p.stderr


def test_progress_bar_shows_shards_labels_per_second_and_eta(monkeypatch):
    import io
    import time
    from clvol.progress import Progress
    monkeypatch.setenv("CLVOL_PROGRESS", "1")
    buf = io.StringIO()
    with Progress(4, label="dataset", unit=" shards", delay=0.0, stream=buf,
                  rate_per_unit=24, rate_unit="labels") as bar:
        time.sleep(0.15)                     # the bar redraws at most every 0.1 s
        bar.update(1)
        elapsed = bar.elapsed
    line = buf.getvalue().strip().split("\r")[-1]
    assert "1/4 shards" in line and "eta" in line
    rate = float(line.split(" labels/s")[0].split()[-1])
    # 24 labels over the elapsed time; the bar rounds to a whole label per second and
    # closes a little later than `elapsed` was read
    assert rate <= 24 / elapsed + 0.5 and rate > 0


# -- a two-node cluster on loopback (tests/ray_cluster.py) ---------------------------------------
CLUSTER = r"""
"$PY" -c '
import json, ray
ray.init(address="127.0.0.2:6379", logging_level="WARNING")
print("NODES " + json.dumps([[n["NodeManagerAddress"], n["Alive"]] for n in ray.nodes()]))
'
"$PY" -m clvol dataset make "$OUT" --address 127.0.0.2:6379 "$@"
"$PY" -m clvol dataset make "$OUT_CLIENT" --address ray://127.0.0.2:10001 "$@"
"""


@pytest.mark.skipif(not ray_cluster.unshare_works(), reason=ray_cluster.SKIP_REASON)
def test_two_node_loopback_cluster_makes_the_serial_bytes(serial, tmp_path):
    """`ray start` a head on 127.0.0.2 and a worker node on 127.0.0.3, then `clvol dataset
    make` through the GCS address and through Ray Client (ray://)."""
    pytest.importorskip("ray")
    out, out_client = tmp_path / "data", tmp_path / "data_client"
    p = ray_cluster.run(CLUSTER, *SPEC_ARGS, cwd=tmp_path, logs=tmp_path / "logs", timeout=420,
                        env={"OUT": str(out), "OUT_CLIENT": str(out_client),
                             # A bound on how long the Ray Client proxy waits for a healthy
                             # server process to answer (import ray + gRPC start-up: ~3-6 s
                             # here; the default 30 s leaves little room on two busy cores).
                             # It is not a retry: a crashed server still fails the test.
                             "RAY_CLIENT_SERVER_CHECK_CHANNEL_TIMEOUT_S": "150"})
    assert p.returncode == 0, (p.stdout + p.stderr)[-3000:]
    nodes = json.loads(next(line for line in p.stdout.splitlines()
                            if line.startswith("NODES "))[6:])
    assert sorted(nodes) == [["127.0.0.2", True], ["127.0.0.3", True]]
    assert all(ipaddress.ip_address(ip) in ipaddress.ip_network("127.0.0.0/8") for ip, _ in nodes)
    assert p.stdout.count("made 4 shards") == 2 and "(ray)" in p.stdout
    assert shard_files(out) == serial
    assert shard_files(out_client) == serial           # through Ray Client (ray://)
    log = [json.loads(line) for line in (out / ds.TIMINGS_FILE).read_text().splitlines()]
    # one CPU per node and four tasks in flight: both nodes make shards
    assert {x["node"] for x in log} == {"127.0.0.2", "127.0.0.3"}


def test_ray_client_init_failure_names_the_servers_cause_in_one_line():
    """Ray Client's failed init is "Initialization failure from server:" and the server's
    traceback; the message keeps the traceback's last line (the cause) and hints at the fix
    for the forked server that crashed (GRPC_ENABLE_FORK_SUPPORT=0 on the head)."""
    exc = ConnectionAbortedError(
        "Initialization failure from server:\nTraceback (most recent call last):\n"
        '  File "proxier.py", line 772, in Datapath\n    raise RuntimeError(\n'
        "RuntimeError: Starting Ray client server failed. See ray_client_server_23000.err for "
        "detailed logs.\n")
    msg = dist.connect_error_message("ray://127.0.0.2:10001", exc)
    assert "\n" not in msg
    assert msg.startswith("cannot start or reach Ray at ray://127.0.0.2:10001: Initialization "
                          "failure from server: RuntimeError: Starting Ray client server failed")
    assert "GRPC_ENABLE_FORK_SUPPORT=0" in msg
    # a one-line error stays as it was, with no hint
    assert (dist.connect_error_message(None, ConnectionError("no cluster"))
            == "cannot start or reach Ray at local: no cluster")
    assert dist.connect_error_message("auto", RuntimeError()) == \
        "cannot start or reach Ray at auto: RuntimeError"
