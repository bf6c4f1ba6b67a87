#!/usr/bin/env python
"""Leave-one-family-out at small scale: for each training family F, train a model from scratch
without F, then evaluate it on F (out of family for that model) and on the unseen volumes of the
other families (in family), per albedo bin, with the gap and its 95% bootstrap interval
(scripts/train.py --exclude-families / --evaluate). A run with nothing left out ("none") is the
reference. Resumable: a family whose OUT/F/evaluation.json exists is skipped.

    python scripts/lofo.py DATA[,DATA...] OUT [--families cumulus,...] [--steps 1500] [--jobs 2]
        [--oof OOF_DATA] [-- extra scripts/train.py options]

Writes OUT/lofo.md (the table of docs/neural.md) and OUT/lofo.json.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

HERE = Path(__file__).resolve().parent


def run_family(family: str, data: str, out: Path, steps: int, extra: list[str], oof: str = "") -> dict:
    """Train without ``family`` ("none": nothing left out), evaluate, return evaluation.json."""
    d = out / family
    ev = d / "evaluation.json"
    if ev.exists():
        return json.loads(ev.read_text())
    ex = [] if family == "none" else ["--exclude-families", family]
    train = [sys.executable, str(HERE / "train.py"), data, str(d)]
    w = d / "w.npz"
    if not w.exists():
        p = subprocess.run(train + ["--steps", str(steps), "--eval-every", str(steps), *ex, *extra,
                                    "--export", str(w)], capture_output=True, text=True)
        (out / f"{family}.train.log").write_text(p.stdout + p.stderr)
        if p.returncode != 0:
            raise RuntimeError(f"{family}: training failed: {p.stderr.strip().splitlines()[-1:]}")
    # the reference run ("none") is also scored on the out-of-family generators' set
    ev_data = data + ("," + oof if family == "none" and oof else "")
    p = subprocess.run([sys.executable, str(HERE / "train.py"), ev_data, str(d), "--evaluate", str(w),
                        *ex], capture_output=True, text=True)
    (out / f"{family}.eval.log").write_text(p.stdout + p.stderr)
    if p.returncode != 0:
        raise RuntimeError(f"{family}: evaluation failed: {p.stderr.strip().splitlines()[-1:]}")
    return json.loads(ev.read_text())


def table(results: dict) -> str:
    """Markdown: per left-out family, its ratio (sum predicted / sum labels) per albedo bin, the
    in-family ratio of the same model, and the gap with its interval."""
    bins = None
    lines = []
    for fam, ev in results.items():
        groups = ev["groups"]
        if fam == "none":
            src = "out-of-family clouds"       # the generators no training set uses
        else:
            solid = fam in ("sphere", "blob", "torus", "box", "union")
            src = "out-of-family solids" if solid else "out-of-family clouds"
        ref = ("in-family solids (unseen volumes)" if src.endswith("solids")
               else "in-family clouds (unseen volumes)")
        if src not in ev["bias"] or ref not in ev["bias"]:
            continue
        bins = bins or list(ev["bias"][src])
        cells = []
        for k in bins:
            o, i = ev["bias"][src][k][0], ev["bias"][ref][k][0]
            g = ev.get("gap", {}).get(k) if src == "out-of-family clouds" else None
            gap = f"{o - i:+.3f}" + (f" ({g[1]:+.3f}..{g[2]:+.3f})" if g else "")
            cells.append(f"{o:.3f} / {i:.3f} / {gap}")
        what = "nubis + sphere_cumulus (none left out)" if fam == "none" else fam
        lines.append(f"| {what} | {groups.get('out of family', {}).get('shards', 0)} | " +
                     " | ".join(cells) + " |")
    head = ("| left out | shards | " + " | ".join(f"albedo {k}" for k in (bins or [])) + " |\n|" +
            "---|" * (2 + len(bins or [])) + "\n")
    note = ("\nEach cell: out-of-family ratio / in-family ratio (unseen volumes of the families "
            "trained on, same kind: clouds or solids) / gap; the 95% bootstrap interval of the gap "
            "over configurations where both sides are clouds.\n")
    return head + "\n".join(lines) + "\n" + note


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = []
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1:]
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data")
    ap.add_argument("out")
    ap.add_argument("--families", default="none,cumulus,flat_cumulus,stratus,plume,noise,"
                                           "sphere,blob,torus,box,union")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--oof", default="", help="an out-of-family data set (nubis, sphere_cumulus) "
                                             "the reference run is also scored on")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    fams = [f for f in args.families.split(",") if f]
    with ThreadPoolExecutor(args.jobs) as pool:
        futs = {f: pool.submit(run_family, f, args.data, out, args.steps, extra, args.oof) for f in fams}
        results = {}
        for f in fams:
            try:
                results[f] = futs[f].result()
            except RuntimeError as exc:
                print(f"lofo: {exc}", file=sys.stderr)
    (out / "lofo.json").write_text(json.dumps(results, indent=1))
    md = table(results)
    (out / "lofo.md").write_text(md)
    print(md)
    return 0 if len(results) == len(fams) else 1


if __name__ == "__main__":
    sys.exit(main())
