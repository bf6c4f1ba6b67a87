#!/usr/bin/env python
"""Does an optical-depth transmittance input fix the albedo response at deep points? A training-
side experiment (the renderer's gather bakes linear T; this changes only what the model reads).

    python scripts/depth_input.py DATA[,DATA...] OUT --scenes S.toml [S.toml ...]
        [--steps 3000] [--pixels 24] [--paths 128] [-- train options]

Two models of the base size are trained from scratch on the same samples, seeds and steps: ``linear`` reads the graded transmittance levels T_m as the renderer does today;
``depth`` reads min(-log T_m, DEPTH_CLAMP) / DEPTH_CLAMP at every level (0: transparent, 1:
DEPTH_CLAMP optical depths or more). Each is scored on the held-out shards (eq. 20 loss) and
at the points each scene's camera sees (scripts/albedo_response.py: path-traced per-order
labels, the ratio sum(network) / sum(labels) per albedo, split by the labels' mean albedo
exponent). docs/neural.md, "An optical-depth input", has a run.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))

# optical depths beyond which a level reads as opaque: e^-30 ~ 1e-13, below any T that decides F
DEPTH_CLAMP = 30.0


def as_depth(levels: np.ndarray) -> np.ndarray:
    """Levels T in [0, 1] -> clamped optical depth scaled to [0, 1] (float32)."""
    tau = -np.log(np.clip(levels.astype(np.float64), np.exp(-DEPTH_CLAMP), 1.0))
    return (tau / DEPTH_CLAMP).astype(np.float32)


def with_levels(s, levels):
    from clvol.training.train import Samples
    return Samples(s.features, s.config, s.y, s.weight, s.var, levels, s.key, s.row)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data")
    ap.add_argument("out")
    ap.add_argument("--scenes", nargs="+", required=True)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--albedo-draws", type=int, default=4)
    ap.add_argument("--pixels", type=int, default=24)
    ap.add_argument("--paths", type=int, default=128)
    ap.add_argument("--seeds", default="0", help="training seeds, comma-separated (each arm "
                    "is trained once per seed; the labels are made once)")
    args = ap.parse_args(argv)

    import torch
    from albedo_response import ALBEDOS, scene_points
    from clvol.features.weights import Architecture
    from clvol.training import train as tr
    from clvol.training.dataset import load_shards
    torch.set_num_threads(1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    seeds = [int(x) for x in args.seeds.split(",") if x]
    cfg = tr.RunConfig(steps=args.steps, batch=args.batch, seed=seeds[0], floor=float("inf"),
                       eval_every=args.steps, checkpoint_every=args.steps)
    folders = [load_shards(d) for d in args.data.split(",") if d]
    splits = [tr.split_shards(f, cfg) for f in folders]
    train = tr.shard_samples([s for t, _ in splits for s in t], cfg.floor,
                             albedo_draws=args.albedo_draws, seed=cfg.seed)
    held = tr.shard_samples([s for _, h in splits for s in h][::4], cfg.floor,
                            albedo_draws=2, seed=cfg.seed + 1)
    print(f"{len(train)} training samples, {len(held)} held-out samples; {args.steps} steps", flush=True)

    # the visible points of each scene, with labels (the expensive part: once for both arms)
    scenes = [scene_points(Path(s), args.pixels, args.paths, seed=1) for s in args.scenes]

    rows = {}
    for seed in seeds:
        run = dataclasses.replace(cfg, seed=seed)
        for arm in ("linear", "depth"):
            enc = (lambda lv: lv) if arm == "linear" else as_depth
            tr_s, he_s = with_levels(train, enc(train.levels)), with_levels(held, enc(held.levels))
            trainer = tr.Trainer(tr_s, run, Architecture(n_levels=train.levels.shape[1],
                                                         albedo_input="log1m"))
            trainer.run(args.steps, checkpoint=out / f"{arm}_{seed}.pt", held=he_s, log=None)
            loss = tr.evaluate(trainer.model, he_s)
            print(f"seed {seed}, {arm}: held-out loss {loss:.3e}", flush=True)
            rows[arm, seed] = [sc["score"](tr.predict(trainer.model, with_levels(
                sc["samples"], enc(sc["samples"].levels))).astype(np.float64)) for sc in scenes]
    print("\n| scene | points | group | model | seed | " + " | ".join(f"a = {x}" for x in ALBEDOS) + " |")
    print("|---|---|---|---|---|" + "---|" * len(ALBEDOS))
    for i, sc in enumerate(scenes):
        for name in rows["linear", seeds[0]][i]:
            for arm in ("linear", "depth"):
                for seed in seeds:
                    g = rows[arm, seed][i][name]
                    print(f"| {sc['name']} | {g['points']} | {name} | {arm} | {seed} | " +
                          " | ".join(f"{g['ratio'][x]:.3f}" for x in ALBEDOS) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
