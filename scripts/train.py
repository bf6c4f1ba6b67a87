#!/usr/bin/env python
"""Train the network on a clvol data set and export a weight file (clvol/train.py, clvol/dataset.py).

    python scripts/train.py runs/data runs/train [--steps 6000] [--batch 256] [--lr 2e-3]
        [--seed 0] [--threads 1] [--export clvol/data/weights/cloud_small.npz]

Resumable: OUT/checkpoint.pt is written atomically every --checkpoint-every steps; rerunning the
same command continues from it (same settings required). Prints the training loss and the
held-out loss (volumes and configurations never trained on) against the mean predictor, and
writes OUT/report.json. Exports with the contract of the gather that made the features.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def main(argv=None) -> int:
    import numpy as np
    import torch

    from clvol import train as tr
    from clvol.dataset import load_shards
    from clvol.errors import ClvolError
    from clvol.export import gather_contract

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", help="data set folder (scripts/make_dataset.py)")
    ap.add_argument("out", help="run folder (checkpoint, report)")
    d = tr.RunConfig()
    ap.add_argument("--steps", type=int, default=d.steps)
    ap.add_argument("--batch", type=int, default=d.batch)
    ap.add_argument("--lr", type=float, default=d.lr)
    ap.add_argument("--seed", type=int, default=d.seed)
    ap.add_argument("--floor", type=float, default=d.floor)
    ap.add_argument("--holdout-volumes", default=",".join(map(str, d.holdout_volumes)))
    ap.add_argument("--eval-every", type=int, default=d.eval_every)
    ap.add_argument("--checkpoint-every", type=int, default=d.checkpoint_every)
    ap.add_argument("--threads", type=int, default=1,
                    help="torch threads (default 1: the machine is shared; results depend on it)")
    ap.add_argument("--until", type=int, default=None, help="stop at this step (resume later)")
    ap.add_argument("--export", default=None, help="weight file to write at the end")
    ap.add_argument("--evaluate", metavar="WEIGHTS.npz", default=None,
                    help="no training: held-out losses of a weight file, per held-out group")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    cfg = tr.RunConfig(steps=args.steps, batch=args.batch, lr=args.lr, seed=args.seed,
                       floor=args.floor,
                       holdout_volumes=tuple(int(v) for v in args.holdout_volumes.split(",") if v),
                       eval_every=args.eval_every, checkpoint_every=args.checkpoint_every)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    try:
        shards = load_shards(args.data)
    except ClvolError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    train_sh, held_sh = tr.split_shards(shards, cfg)
    train = tr.shard_samples(train_sh, cfg.floor)
    held = tr.shard_samples(held_sh, cfg.floor)
    spec = shards[0].meta["spec"]
    print(f"data: {len(shards)} shards ({len(train_sh)} train, {len(held_sh)} held out), "
          f"{len(train)} / {len(held)} samples; base {spec['base_resolution']}, {spec['n_paths']} paths")
    base_loss = tr.mean_predictor_loss(train, held)
    noise = float(np.mean(held.var))
    print(f"held-out loss of the mean predictor {base_loss:.5f}; label noise (mean var_y) {noise:.5f}")
    if args.evaluate:
        return evaluate_weights(args.evaluate, train, held_sh, cfg, base_loss)
    trainer = tr.Trainer(train, cfg)
    ckpt = out / tr.CHECKPOINT
    if ckpt.exists():
        try:
            trainer.load_state_dict(torch.load(ckpt, weights_only=False))
        except ValueError as exc:
            print(f"error: {ckpt}: {exc}", file=sys.stderr)
            return 2
        print(f"resumed from {ckpt} at step {trainer.step}")
    t0 = time.perf_counter()
    trainer.run(args.until or cfg.steps, checkpoint=ckpt, held=held)
    secs = time.perf_counter() - t0
    final = trainer.history["eval"][-1] if trainer.history["eval"] else {}
    report = {"data": str(args.data), "spec": spec, "run": cfg.to_dict(), "threads": args.threads,
              "shards": {"train": len(train_sh), "held_out": len(held_sh),
                         "held_out_names": [s.path.name for s in held_sh]},
              "samples": {"train": len(train), "held_out": len(held)},
              "step": trainer.step, "seconds_this_session": round(secs, 1),
              "held_out_mean_predictor": base_loss, "held_out_label_noise": noise,
              "final": final, "history": trainer.history["eval"]}
    (out / "report.json").write_text(json.dumps(report, indent=1))
    if args.export and trainer.step >= cfg.steps:
        contract = gather_contract(spec["base_resolution"], spec["lam"])
        notes = {k: report[k] for k in ("spec", "run", "samples", "step", "held_out_mean_predictor",
                                         "held_out_label_noise", "final")}
        from clvol.dataset import dataset_domain
        trainer.model.export(args.export, contract, training=notes, domain=dataset_domain(spec))
        print(f"exported {args.export}")
    return 0


def evaluate_weights(path, train, held_sh, cfg, base_loss) -> int:
    """Held-out eq. 20 loss of a weight file, split into unseen volumes and unseen configurations
    of seen volumes, with the mean predictor's loss and the labels' noise, and the median
    relative error of the decoded F against the labels."""
    import numpy as np
    from clvol import train as tr
    from clvol.export import load_weights
    from clvol.model import Model
    model = Model.from_weights(load_weights(path))
    hv = {s.volume for s in held_sh if sum(t.volume == s.volume for t in held_sh) > 1}
    groups = {"all held out": held_sh,
              "unseen volumes": [s for s in held_sh if s.volume in hv],
              "unseen configurations of seen volumes": [s for s in held_sh if s.volume not in hv]}
    m = float(np.average(train.y, weights=train.weight))
    for name, shards in groups.items():
        if not shards:
            continue
        h = tr.shard_samples(shards, cfg.floor)
        y = tr.predict(model, h).astype(np.float64)
        a4 = h.config[:, tr.ALBEDO].astype(np.float64) ** 4
        F_hat, F_lab = a4 * np.expm1(y), a4 * np.expm1(h.y.astype(np.float64))
        rel = np.abs(F_hat - F_lab) / np.maximum(F_lab, 1e-12)
        print(f"{name:40s} {len(shards):4d} shards {len(h):7d} samples  loss {np.mean((y - h.y) ** 2):.3e}"
              f"  mean predictor {np.mean((m - h.y) ** 2):.3e}  label noise {np.mean(h.var):.3e}"
              f"  median |F - label| / label {np.median(rel):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
