#!/usr/bin/env python
"""Held-out error against the amount of training data: the same network trained on growing
leading fractions of the training volumes, the held-out shards the same for every point.

    python scripts/data_curve.py DATA[,DATA...] OUT [--fractions 0.0625,0.125,0.25,0.5,1]
        [--family-sets F,F;F,...] [--steps 8000] [--jobs 2] [--oof OOF_DATA]
        [-- extra scripts/train.py options]

Each point is one ``scripts/train.py DATA OUT/frac_F --train-fraction F --steps S`` run (resumable:
rerun the command after an interruption and finished or checkpointed points continue); ``--jobs``
runs that many at once, one torch thread each. Prints and writes ``OUT/curve.md``: per fraction the
training volumes, samples, label-path cost, the best and the final held-out loss (eq. 20) and the
step of the best. A curve still falling at the largest fraction says more data would pay.

With ``--oof`` (a data set of the out-of-family generators, docs/neural.md "On clouds it has never
seen") each point's exported weights are also scored by ``scripts/train.py DATA,OOF --evaluate``,
and a second table gives, per albedo bin, the ratio sum(predicted F) / sum(labels) on the unseen
in-family cloud volumes and on the out-of-family clouds: the gap's curve against data.

``--family-sets "cumulus;cumulus,stratus;..."`` adds points trained on only those training
families (all their volumes): the out-of-family error against the variety of structure seen.
Their in-family column still scores the unseen volumes of all ten training families.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from clvol.training.dataset import TRAINING_FAMILIES  # noqa: E402  (the one list of families)


def points_for(fractions, family_sets) -> list[tuple[str, str, list[str]]]:
    """(folder name, row label, scripts/train.py options) of every point of the curve."""
    pts = [(f"frac_{f:g}", f"{f:g}", ["--train-fraction", str(f)]) for f in fractions]
    for fams in family_sets:
        left_out = [f for f in TRAINING_FAMILIES if f not in fams]
        pts.append(("fams_" + "+".join(fams), ", ".join(fams),
                    ["--exclude-families", ",".join(left_out)] if left_out else []))
    return pts


def run_points(data: str, out: Path, points, steps: int, jobs: int, extra, export=False) -> None:
    todo = list(points)
    running = []
    while todo or running:
        while todo and len(running) < jobs:
            name, _, opts = todo.pop(0)
            folder = out / name
            if (folder / "report.json").exists() and json.loads(
                    (folder / "report.json").read_text())["step"] >= steps:
                continue
            folder.mkdir(parents=True, exist_ok=True)
            cmd = [sys.executable, str(ROOT / "scripts" / "train.py"), data, str(folder), *opts,
                   "--steps", str(steps), "--threads", "1",
                   "--eval-every", str(max(steps // 8, 1)), "--checkpoint-every", "500", *extra]
            if export:
                cmd += ["--export", str(folder / "w.npz")]
            log = open(folder / "train.log", "a")
            print(f"start {name}: {' '.join(cmd)}", flush=True)
            running.append((name, subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT), log))
        time.sleep(5)
        for item in list(running):
            name, proc, log = item
            if proc.poll() is not None:
                log.close()
                running.remove(item)
                if proc.returncode != 0:
                    raise SystemExit(f"{name} failed ({proc.returncode}); see {out / name / 'train.log'}")
                print(f"done {name}", flush=True)


def table(out: Path, points) -> str:
    rows = ["| point | training volumes | training samples | labels x paths | best held-out "
            "(step) | final held-out | held-out mean predictor |",
            "|---|---|---|---|---|---|---|"]
    for name, label, _ in points:
        rep = json.loads((out / name / "report.json").read_text())
        hist = [h for h in rep["history"] if "held_out" in h]
        best = min(hist, key=lambda h: h["held_out"])
        cost = rep["samples"]["train_queries"] * rep["spec"]["n_paths"]
        rows.append(f"| {label} | {rep['shards']['train_volumes']} | {rep['samples']['train']:,} | {cost:.3g} | "
                    f"{best['held_out']:.3e} ({best['step']}) | {hist[-1]['held_out']:.3e} | "
                    f"{rep['held_out_mean_predictor']:.3e} |")
    return "\n".join(rows)


def evaluate_points(data: str, oof: str, out: Path, points) -> None:
    """Score each point's weights on DATA's held-out shards and on OOF (resumable)."""
    for name, _, _ in points:
        folder = out / name
        if (folder / "evaluation.json").exists():
            continue
        cmd = [sys.executable, str(ROOT / "scripts" / "train.py"), f"{data},{oof}", str(folder),
               "--evaluate", str(folder / "w.npz")]
        print(f"evaluate {name}", flush=True)
        with open(folder / "evaluate.log", "w") as log:
            if subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT).returncode != 0:
                raise SystemExit(f"{name}: evaluation failed; see {folder / 'evaluate.log'}")


def gap_table(out: Path, points) -> str:
    """Per point and albedo bin: in-family / out-of-family ratio of sums (predicted / labels).
    The in-family side is the unseen cloud volumes of every training family, also of those a
    family-set point did not train on."""
    inf, oof = "in-family clouds (unseen volumes)", "out-of-family clouds"
    evs = [(label, name, json.loads((out / name / "evaluation.json").read_text()))
           for name, label, _ in points]
    bins = list(evs[0][2]["bias"][oof])
    rows = ["| point | training queries | " + " | ".join(f"albedo {b}" for b in bins) + " |",
            "|---|---|" + "---|" * len(bins)]
    for label, name, ev in evs:
        rep = json.loads((out / name / "report.json").read_text())
        cells = [(f"{ev['bias'][inf][b][0]:.3f}" if inf in ev["bias"] else "-") +
                 f" / {ev['bias'][oof][b][0]:.3f}" for b in bins]
        rows.append(f"| {label} | {rep['samples']['train_queries']:,} | " + " | ".join(cells) + " |")
    return ("Ratio sum(predicted F) / sum(labels): in-family clouds (unseen volumes) / "
            "out-of-family clouds\n\n" + "\n".join(rows))


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", help="data set folder(s), comma-separated, as scripts/train.py takes them")
    ap.add_argument("out", help="curve folder (one run folder per fraction)")
    ap.add_argument("--fractions", default="0.0625,0.125,0.25,0.5,1",
                    help="leading fractions of the training volumes, one point each ('' for none)")
    ap.add_argument("--family-sets", default="", metavar="F,F;F,...",
                    help="also train on only these training families, one point per ';'-separated set")
    ap.add_argument("--steps", type=int, default=8000)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--oof", default="", metavar="OOF_DATA",
                    help="out-of-family data set(s): also score every point there (needs no retraining)")
    args = ap.parse_args(argv)
    fractions = sorted(float(x) for x in args.fractions.split(",") if x)
    family_sets = [tuple(f for f in fs.split(",") if f) for fs in args.family_sets.split(";") if fs]
    unknown = sorted({f for fs in family_sets for f in fs} - set(TRAINING_FAMILIES))
    if unknown:
        print(f"error: --family-sets: {', '.join(unknown)}: not a training family "
              f"({', '.join(TRAINING_FAMILIES)})", file=sys.stderr)
        return 2
    if not (fractions or family_sets) or any(not 0 < f <= 1 for f in fractions):
        print(f"error: --fractions {args.fractions}: each must be in (0, 1]", file=sys.stderr)
        return 2
    if args.steps < 1 or args.jobs < 1:
        print("error: --steps and --jobs must be >= 1", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    points = points_for(fractions, family_sets)
    run_points(args.data, out, points, args.steps, args.jobs, extra, export=bool(args.oof))
    text = table(out, points)
    if args.oof:
        evaluate_points(args.data, args.oof, out, points)
        text += "\n\n" + gap_table(out, points)
    (out / "curve.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
