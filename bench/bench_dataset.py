"""Data set generation throughput: serial vs a local Ray, side by side in one run.

    python bench/bench_dataset.py [--reps 3] [--workers 2] [--volumes 2] [--configs 6] ...

Each repetition runs `clvol dataset make` into a fresh folder twice, once with --serial and
once on a local Ray with --workers CPUs, alternating so load changes hit both, and times the
whole command (start-up, OpenCL builds, phase tables, Ray's start included: what a user
waits for). Prints the medians of shards/s and labels/s, the summed in-shard seconds (from
timings.jsonl: work that each Ray worker repeats, such as phase tables for a new g, shows up
there), and checks the two folders hold the same bytes.
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _common

ROOT = _common.ROOT


def run(out: Path, spec_args: list[str], extra: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "clvol", "dataset", "make", str(out), *spec_args,
                    "--no-progress", *extra], cwd=ROOT, check=True, capture_output=True)
    return time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--volumes", type=int, default=2)
    ap.add_argument("--configs", type=int, default=6)
    ap.add_argument("--resolution", type=int, default=24)
    ap.add_argument("--base", type=int, default=32)
    ap.add_argument("--points", type=int, default=128)
    ap.add_argument("--paths", type=int, default=128)
    args = ap.parse_args(argv)
    spec_args = ["--seed", "0", "--volumes", str(args.volumes), "--heldout", "0",
                 "--configs", str(args.configs),
                 "--resolution", f"{args.resolution},{args.resolution}",
                 "--base", str(args.base), "--points", str(args.points), "--paths", str(args.paths)]
    n_shards = args.volumes * args.configs
    print(_common.machine())
    print(f"spec: {' '.join(spec_args)} -> {n_shards} shards, {n_shards * args.points} labels")
    times = {"serial": [], f"ray ({args.workers} workers)": []}
    work = {name: [] for name in times}
    with tempfile.TemporaryDirectory(prefix="clvol-bench-") as tmp:
        for rep in range(args.reps):
            outs = {}
            for name, extra in (("serial", ["--serial"]),
                                (f"ray ({args.workers} workers)", ["--workers", str(args.workers)])):
                out = Path(tmp) / f"{rep}-{name.split()[0]}"
                times[name].append(run(out, spec_args, extra))
                outs[name] = {p.name: p.read_bytes() for p in out.glob("shard_*.npz")}
                work[name].append(sum(json.loads(line)["total"] for line in
                                      (out / "timings.jsonl").read_text().splitlines()))
                print(f"  rep {rep}: {name:>16}: {times[name][-1]:6.1f} s, in-shard "
                      f"{work[name][-1]:6.1f} s   "
                      f"(load {_common.load_average()})", flush=True)
            a, b = outs.values()
            if a != b or len(a) != n_shards:
                print("error: serial and Ray folders differ", file=sys.stderr)
                return 1
    print(f"{'':>18} {'median s':>9} {'shards/s':>9} {'labels/s':>9} {'in-shard s':>11}")
    base = statistics.median(times["serial"])
    for name, ts in times.items():
        m = statistics.median(ts)
        print(f"{name:>18} {m:9.1f} {n_shards / m:9.3f} {n_shards * args.points / m:9.1f} "
              f"{statistics.median(work[name]):11.1f}   x{base / m:.2f} vs serial")
    print("shard bytes: identical in every repetition")
    return 0


if __name__ == "__main__":
    sys.exit(main())
