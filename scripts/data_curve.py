#!/usr/bin/env python
"""Held-out error against the amount of training data: the same network trained on growing
leading fractions of the training volumes, the held-out shards the same for every point.

    python scripts/data_curve.py DATA[,DATA...] OUT [--fractions 0.0625,0.125,0.25,0.5,1]
        [--steps 8000] [--jobs 2] [-- extra scripts/train.py options]

Each point is one ``scripts/train.py DATA OUT/frac_F --train-fraction F --steps S`` run (resumable:
rerun the command after an interruption and finished or checkpointed points continue); ``--jobs``
runs that many at once, one torch thread each. Prints and writes ``OUT/curve.md``: per fraction the
training volumes, samples, label-path cost, the best and the final held-out loss (eq. 20) and the
step of the best. A curve still falling at the largest fraction says more data would pay.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def run_points(data: str, out: Path, fractions, steps: int, jobs: int, extra) -> None:
    todo = list(fractions)
    running = []
    while todo or running:
        while todo and len(running) < jobs:
            f = todo.pop(0)
            folder = out / f"frac_{f:g}"
            if (folder / "report.json").exists() and json.loads(
                    (folder / "report.json").read_text())["step"] >= steps:
                continue
            folder.mkdir(parents=True, exist_ok=True)
            cmd = [sys.executable, str(ROOT / "scripts" / "train.py"), data, str(folder),
                   "--train-fraction", str(f), "--steps", str(steps), "--threads", "1",
                   "--eval-every", str(max(steps // 8, 1)), "--checkpoint-every", "500", *extra]
            log = open(folder / "train.log", "a")
            print(f"start fraction {f:g}: {' '.join(cmd)}", flush=True)
            running.append((f, subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT), log))
        time.sleep(5)
        for item in list(running):
            f, proc, log = item
            if proc.poll() is not None:
                log.close()
                running.remove(item)
                if proc.returncode != 0:
                    raise SystemExit(f"fraction {f:g} failed ({proc.returncode}); see "
                                     f"{out / f'frac_{f:g}' / 'train.log'}")
                print(f"done fraction {f:g}", flush=True)


def table(out: Path, fractions) -> str:
    rows = ["| fraction | training volumes | training samples | labels x paths | best held-out "
            "(step) | final held-out | held-out mean predictor |",
            "|---|---|---|---|---|---|---|"]
    for f in fractions:
        rep = json.loads((out / f"frac_{f:g}" / "report.json").read_text())
        hist = [h for h in rep["history"] if "held_out" in h]
        best = min(hist, key=lambda h: h["held_out"])
        cost = rep["samples"]["train_queries"] * rep["spec"]["n_paths"]
        rows.append(f"| {f:g} | {rep['shards']['train_volumes']} | {rep['samples']['train']:,} | {cost:.3g} | "
                    f"{best['held_out']:.3e} ({best['step']}) | {hist[-1]['held_out']:.3e} | "
                    f"{rep['held_out_mean_predictor']:.3e} |")
    return "\n".join(rows)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", help="data set folder(s), comma-separated, as scripts/train.py takes them")
    ap.add_argument("out", help="curve folder (one run folder per fraction)")
    ap.add_argument("--fractions", default="0.0625,0.125,0.25,0.5,1")
    ap.add_argument("--steps", type=int, default=8000)
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args(argv)
    fractions = sorted(float(x) for x in args.fractions.split(",") if x)
    if not fractions or any(not 0 < f <= 1 for f in fractions):
        print(f"error: --fractions {args.fractions}: each must be in (0, 1]", file=sys.stderr)
        return 2
    if args.steps < 1 or args.jobs < 1:
        print("error: --steps and --jobs must be >= 1", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    run_points(args.data, out, fractions, args.steps, args.jobs, extra)
    text = table(out, fractions)
    (out / "curve.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
