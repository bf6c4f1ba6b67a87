#!/usr/bin/env python
"""Held-out error against labelling cost: how many paths per label and labels per configuration
are worth their cost (docs/neural.md, "Labels by measurement").

    python scripts/label_curve.py DATA OUT [--points 32,64,128] [--paths 32,64,128]
        [--steps 1500] [--threads 1] [--seed 0]

From one data set (scripts/make_dataset.py) made with N paths per label and K labels per
configuration, every (paths p <= N, labels k <= K) cell trains the same network for the same
steps on the training shards with
- k labels per configuration: a seeded random subset of each shard's points;
- p paths per label: the stored N-path label plus Gaussian noise of variance se^2 (N/p - 1), and
  standard error se sqrt(N/p) (the central-limit model of a p-path mean; a label's own se is
  the N-path estimate, so this is an emulation, not new path tracing),
and is scored on all held-out shards at their full labels: the eq. 20 loss in y, and that loss
minus the held-out labels' own noise (mean var_y), the part a better network or more data could
remove. Labelling cost = p x k x training configurations (path-traced walks). Resumable: each
finished cell is kept in OUT/curve.json.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def emulate(shards, k: int, p: int, seed: int, floor: float):
    """Training samples with k labels per configuration at p paths (see the module docstring)."""
    from clvol.training import train as tr
    parts = []
    for s in shards:
        a = s.arrays
        n_have = int(s.meta["spec"]["n_paths"])
        rng = np.random.default_rng([seed, s.volume, s.config_index, k, p])
        idx = np.sort(rng.choice(len(a["Fms"]), min(k, len(a["Fms"])), replace=False))
        F, se = a["Fms"][idx].astype(np.float64), a["Fms_se"][idx].astype(np.float64)
        if p < n_have:
            extra = np.sqrt(n_have / p - 1.0)
            # one normal draw per label, shared by the channels: they come from the same paths
            F = np.maximum(F + se * extra * rng.standard_normal((len(idx), 1)), 0.0)
            se = se * np.sqrt(n_have / p)
        n_cfg = s.meta["spec"]["configs_per_volume"]
        key = np.full(len(idx), s.volume * n_cfg + s.config_index)
        parts.append(tr.make_samples(a["features"][idx], a["config"][idx], F, se, s.albedo,
                                     levels=a["levels"][idx], key=key, floor=floor))
    return tr.concat_samples(parts)


def main(argv=None) -> int:
    import torch
    from clvol.errors import ClvolError
    from clvol.training import train as tr
    from clvol.training.dataset import load_shards
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data")
    ap.add_argument("out")
    ap.add_argument("--points", default="32,64,128", help="labels per configuration to try")
    ap.add_argument("--paths", default="32,64,128", help="paths per label to try (<= the data's)")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    try:
        shards = load_shards(args.data)
    except ClvolError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    spec = shards[0].meta["spec"]
    ks = [int(x) for x in args.points.split(",")]
    ps = [int(x) for x in args.paths.split(",")]
    if max(ks) > spec["points_per_config"] or max(ps) > spec["n_paths"]:
        print(f"error: --points <= {spec['points_per_config']} and --paths <= {spec['n_paths']} "
              f"(the data set's)", file=sys.stderr)
        return 2
    cfg = tr.RunConfig(steps=args.steps, batch=args.batch, seed=args.seed, eval_every=args.steps,
                       checkpoint_every=args.steps)
    train_sh, held_sh = tr.split_shards(shards, cfg)
    held = tr.shard_samples(held_sh, cfg.floor)
    noise = float(np.mean(held.var))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "curve.json"
    done = json.loads(path.read_text()) if path.exists() else {"rows": []}
    have = {(r["paths"], r["labels_per_config"]) for r in done["rows"]}
    done.update(data=str(args.data), steps=args.steps, batch=args.batch, seed=args.seed,
                threads=args.threads, train_configs=len(train_sh), held_out_shards=len(held_sh),
                held_out_samples=len(held), held_out_label_noise=noise, data_paths=spec["n_paths"])
    print(f"{len(train_sh)} training configurations, {len(held_sh)} held-out shards "
          f"({len(held)} samples, label noise {noise:.2e}); {args.steps} steps per cell")
    for p in ps:
        for k in ks:
            if (p, k) in have:
                continue
            t0 = time.perf_counter()
            train = emulate(train_sh, k, p, args.seed, cfg.floor)
            trainer = tr.Trainer(train, cfg)
            trainer.run(args.steps, held=held, log=None)
            loss = trainer.history["eval"][-1]["held_out"]
            row = {"paths": p, "labels_per_config": k, "cost_paths": p * k * len(train_sh),
                   "train_samples": len(train), "held_out_loss": loss,
                   "held_out_loss_minus_noise": loss - noise,
                   "seconds": round(time.perf_counter() - t0, 1)}
            done["rows"].append(row)
            path.write_text(json.dumps(done, indent=1))
            print(f"paths {p:4d} labels/config {k:4d} cost {row['cost_paths']:9d}  held-out "
                  f"{loss:.3e} (minus noise {loss - noise:.3e})  {row['seconds']} s", flush=True)
    rows = sorted(done["rows"], key=lambda r: r["cost_paths"])
    print("\n| paths/label | labels/config | cost (paths) | held-out loss | minus label noise |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['paths']} | {r['labels_per_config']} | {r['cost_paths']:,} | "
              f"{r['held_out_loss']:.3e} | {r['held_out_loss_minus_noise']:.3e} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
