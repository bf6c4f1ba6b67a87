#!/usr/bin/env python
"""Train the network on a clvol data set and export a weight file (clvol/training/train.py, clvol/training/dataset.py).

    python scripts/train.py runs/data runs/train [--steps 6000] [--batch 256] [--lr 2e-3]
        [--seed 0] [--threads 1] [--export clvol/data/weights/full_albedo.npz]
        [--module-width 32] [--head-widths 64,32] [--se-hidden 8]

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

import numpy as np


def main(argv=None) -> int:
    import torch
    started = time.perf_counter()      # --time-budget counts from here (loading included)

    from clvol.errors import ClvolError
    from clvol.training import train as tr
    from clvol.training.dataset import load_shards

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", help="data set folder (scripts/make_dataset.py), or several, comma-separated "
                                 "(each split into training and held-out shards by its own spec)")
    ap.add_argument("out", help="run folder (checkpoint, report)")
    d = tr.RunConfig()
    ap.add_argument("--steps", type=int, default=d.steps)
    ap.add_argument("--batch", type=int, default=d.batch)
    ap.add_argument("--lr", type=float, default=d.lr)
    ap.add_argument("--seed", type=int, default=d.seed)
    ap.add_argument("--floor", type=float, default=d.floor)
    ap.add_argument("--image-weight", type=float, default=d.image_weight, metavar="P",
                    help="weigh each training sample's error by its share of its "
                         "configuration's linear brightness, to the power P (0: off; 2: as an "
                         "image weighs it; docs/neural.md)")
    ap.add_argument("--holdout-volumes", default=",".join(map(str, d.holdout_volumes)))
    ap.add_argument("--train-fraction", type=float, default=d.train_fraction,
                    help="train on the first fraction of each data set's training volumes "
                         "(the held-out shards stay the same): the error-against-data curve")
    ap.add_argument("--eval-every", type=int, default=d.eval_every)
    ap.add_argument("--checkpoint-every", type=int, default=d.checkpoint_every)
    ap.add_argument("--threads", type=int, default=1,
                    help="torch threads (default 1: the machine is shared; results depend on it)")
    ap.add_argument("--until", type=int, default=None, help="stop at this step (resume later)")
    ap.add_argument("--time-budget", type=float, default=None, metavar="S",
                    help="stop S seconds after the start, data loading included (checkpointed; "
                         "rerun to go on), and export what was reached, saying so in the weight "
                         "file's notes")
    from clvol.features.weights import Architecture
    da = Architecture()
    ap.add_argument("--module-width", type=int, default=da.module_width,
                    help="width of each module's output and of the per-type merges")
    ap.add_argument("--head-widths", default=",".join(map(str, da.head_widths)),
                    help="hidden widths of the head MLP, comma-separated")
    ap.add_argument("--se-hidden", type=int, default=da.se_hidden,
                    help="hidden width of the squeeze-and-excitation layers")
    ap.add_argument("--albedo-input", default=da.albedo_input, choices=["linear", "log1m"],
                    help="how the network reads the albedo (docs/network.md)")
    ap.add_argument("--albedo-draws", type=int, default=0, metavar="K",
                    help="per-order data sets: label every training query at K albedos drawn "
                         "in 0.3..1 (0: the configuration's albedo only)")
    ap.add_argument("--init", metavar="WEIGHTS.npz", default=None,
                    help="start from this weight file's parameters (same architecture)")
    ap.add_argument("--export", default=None, help="weight file to write at the end")
    ap.add_argument("--evaluate", metavar="WEIGHTS.npz", default=None,
                    help="no training: held-out losses of a weight file, per held-out group, "
                         "in-family and out-of-family rows (also OUT/evaluation.json)")
    ap.add_argument("--exclude-families", default="", metavar="F[,F...]",
                    help="train without these families: their shards are held out and reported "
                         "as out-of-family (leave-one-family-out, scripts/lofo.py)")
    ap.add_argument("--device", default="cpu",
                    help="torch device of the training (cpu, cuda); the data stays on the host")
    rg = ap.add_argument_group("data-parallel training on Ray Train (docs/dataset.md)")
    rg.add_argument("--ray", action="store_true",
                    help="train with N data-parallel workers (Ray Train's TorchTrainer)")
    rg.add_argument("--address", default=None, metavar="auto|HOST:PORT",
                    help="with --ray: a running cluster (default: a local Ray)")
    rg.add_argument("--workers", type=int, default=2, metavar="N", help="with --ray: workers")
    rg.add_argument("--gpu", action="store_true", help="with --ray: one GPU per worker")
    args = ap.parse_args(argv)
    if not args.ray and (args.address or args.gpu):
        ap.error("--address and --gpu are options of --ray")
    if args.ray and (args.evaluate or args.workers < 1):
        ap.error("--ray trains (not with --evaluate) with --workers >= 1")
    torch.set_num_threads(args.threads)
    cfg = tr.RunConfig(steps=args.steps, batch=args.batch, lr=args.lr, seed=args.seed,
                       floor=args.floor, image_weight=args.image_weight,
                       holdout_volumes=tuple(int(v) for v in args.holdout_volumes.split(",") if v),
                       train_fraction=args.train_fraction, eval_every=args.eval_every,
                       checkpoint_every=args.checkpoint_every)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    try:
        folders = [load_shards(d) for d in args.data.split(",") if d]
    except ClvolError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    shards = [s for f in folders for s in f]
    c0 = shards[0].meta["contract"]
    for f in folders[1:]:
        if f[0].meta["contract"] != c0:
            print(f"error: {f[0].path.parent}: [contract] differs from {shards[0].path.parent}'s "
                  f"(other base resolution, lambda or templates)", file=sys.stderr)
            return 2
    try:
        splits = [tr.split_shards(f, cfg) for f in folders]
    except ClvolError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    excluded = tuple(f for f in args.exclude_families.split(",") if f)
    fam = (lambda sh: sh.meta.get("volume", {}).get("family"))
    train_sh = [s for t, _ in splits for s in t if fam(s) not in excluded]
    held_sh = [s for _, h in splits for s in h] + [s for t, _ in splits for s in t if fam(s) in excluded]
    if not train_sh and not args.evaluate:
        print("error: no training shards (every volume is held out or out of family)", file=sys.stderr)
        return 2
    if not held_sh:
        print("error: no held-out shards (a data set with --heldout volumes, or more "
              "configurations per volume, gives some)", file=sys.stderr)
        return 2
    if args.ray:
        return train_ray(args, folders, train_sh, held_sh, cfg, out, excluded)
    # --evaluate needs the training samples only for the mean predictor: a bounded subset
    # (every k-th shard) keeps evaluating a large data set's weights cheap
    use = train_sh[::max(1, len(train_sh) // EVAL_TRAIN_SHARDS)] if args.evaluate else train_sh
    train = tr.shard_samples(use, cfg.floor, albedo_draws=args.albedo_draws, seed=cfg.seed,
                             image_weight=cfg.image_weight)
    # the held-out loss printed during training is a monitor: a bounded subset of the held-out
    # shards (every k-th); --evaluate reports on all of them by group
    mon = held_sh if args.evaluate else thin_to_queries(held_sh, MONITOR_QUERIES)
    held = tr.shard_samples(mon, cfg.floor, albedo_draws=args.albedo_draws and 2,
                            seed=cfg.seed + 1)
    spec = shards[0].meta["spec"]
    print(f"data: {len(shards)} shards ({len(train_sh)} train, {len(held_sh)} held out), "
          f"{len(train)} / {len(held)} samples; base {spec['base_resolution']}, {spec['n_paths']} paths")
    base_loss = tr.mean_predictor_loss(train, held) if len(train) else float("nan")
    noise = float(np.mean(held.var))
    print(f"held-out loss of the mean predictor {base_loss:.5f}; label noise (mean var_y) {noise:.5f}")
    if args.evaluate:
        try:
            return evaluate_weights(args.evaluate, train, held_sh, cfg, base_loss, out, excluded,
                                    device=args.device)
        except ClvolError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    try:
        arch = _architecture(args, train.levels.shape[1])
    except ValueError as exc:
        print(f"error: architecture: {exc}", file=sys.stderr)
        return 2
    print(f"architecture: module width {arch.module_width}, head {arch.head_widths}, SE hidden "
          f"{arch.se_hidden}: {arch.n_params()} parameters, {arch.n_macs()['total']} multiply-adds "
          f"per evaluation")
    trainer = tr.Trainer(train, cfg, arch, device=args.device)
    if args.init:
        from clvol.features.weights import load_weights
        w0 = load_weights(args.init)
        same = (lambda d: {k: v for k, v in d.items() if k != "albedo_input"})
        if same(w0.arch.to_dict()) != same(arch.to_dict()):
            print(f"error: --init {args.init}: another architecture", file=sys.stderr)
            return 2
        shift, scale = (getattr(trainer.model, n).clone() for n in ("config_shift", "config_scale"))
        trainer.model.load_numpy_params(w0.params)
        if w0.arch.albedo_input != arch.albedo_input:   # keep this encoding's normalisation
            import torch as _t
            with _t.no_grad():
                trainer.model.config_shift[tr.ALBEDO] = shift[tr.ALBEDO]
                trainer.model.config_scale[tr.ALBEDO] = scale[tr.ALBEDO]
        print(f"initialised from {args.init}")
    ckpt = out / tr.CHECKPOINT
    if ckpt.exists():
        try:
            trainer.load_state_dict(torch.load(ckpt, weights_only=False, map_location=args.device))
        except ValueError as exc:
            print(f"error: {ckpt}: {exc}", file=sys.stderr)
            return 2
        print(f"resumed from {ckpt} at step {trainer.step}")
    t0 = time.perf_counter()
    deadline = started + args.time_budget if args.time_budget else None
    trainer.run(args.until or cfg.steps, checkpoint=ckpt, held=held, deadline=deadline)
    secs = time.perf_counter() - t0
    budget_stop = trainer.step < (args.until or cfg.steps)
    if budget_stop:
        print(f"stopped by --time-budget {args.time_budget:g} s at step {trainer.step} of {cfg.steps}")
    final = trainer.history["eval"][-1] if trainer.history["eval"] else {}
    report = {"data": str(args.data), "spec": spec, "run": cfg.to_dict(), "threads": args.threads,
              "device": args.device, "excluded_families": list(excluded),
              "albedo_draws": args.albedo_draws, "init": args.init,
              "architecture": arch.to_dict(), "macs": arch.n_macs(), "params": arch.n_params(),
              "shards": {"train": len(train_sh), "held_out": len(held_sh),
                         "train_volumes": len({(str(s.path.parent), s.volume) for s in train_sh}),
                         "held_out_names": [s.path.name for s in held_sh]},
              "samples": {"train": len(train), "held_out": len(held),
                          "train_queries": len(train.features)},
              "step": trainer.step, "seconds_this_session": round(secs, 1),
              "held_out_mean_predictor": base_loss, "held_out_label_noise": noise,
              "final": final, "history": trainer.history["eval"]}
    (out / "report.json").write_text(json.dumps(report, indent=1))
    report["stopped_by_time_budget"] = budget_stop
    (out / "report.json").write_text(json.dumps(report, indent=1))
    if args.export and (trainer.step >= cfg.steps or budget_stop):
        notes = {k: report[k] for k in ("spec", "run", "samples", "step", "held_out_mean_predictor",
                                         "held_out_label_noise", "final")}
        notes["seconds_training"] = final.get("seconds")
        if budget_stop:       # the cosine schedule did not reach its end
            notes["stopped_by_time_budget"] = f"step {trainer.step} of {cfg.steps}"
        export(trainer.model.cpu(), args.export, folders, notes)
    return 0


def export(model, path, folders, notes) -> None:
    """Write ``model``'s weight file with the contract of the gather that made the data and the
    union of the data sets' domains."""
    from clvol.training.dataset import dataset_domain
    from clvol.features.weights import gather_contract
    spec = folders[0][0].meta["spec"]
    model.export(path, gather_contract(spec["base_resolution"], spec["lam"]), training=notes,
                 domain=union_domain([dataset_domain(f[0].meta["spec"]) for f in folders]))
    print(f"exported {path}")


def _architecture(args, n_levels):
    from clvol.features.weights import Architecture
    return Architecture(n_levels=n_levels, module_width=args.module_width,
                        head_widths=tuple(int(w) for w in args.head_widths.split(",") if w),
                        se_hidden=args.se_hidden, albedo_input=args.albedo_input)


def train_ray(args, folders, train_sh, held_sh, cfg, out, excluded) -> int:
    """--ray: the same run on Ray Train's data-parallel workers (clvol/training/raytrain.py); the
    same checkpoint file, report and export as one process."""
    import json
    import time
    from clvol.features.weights import load_weights
    from clvol.training.model import Model
    from clvol.training.raytrain import train_on_ray
    try:
        import ray.train  # noqa: F401
    except ImportError as exc:
        print(f"error: --ray needs Ray Train: pip install -e '.[scale]' ({exc})", file=sys.stderr)
        return 2
    arch = _architecture(args, np.asarray(train_sh[0].arrays["levels"]).shape[1])
    init = None
    if args.init:
        w0 = load_weights(args.init)
        if w0.arch.to_dict() != arch.to_dict():
            print(f"error: --init {args.init}: another architecture (or albedo input)", file=sys.stderr)
            return 2
        init = w0.params
    t0 = time.perf_counter()
    state = train_on_ray(args.data.split(","), out, cfg, arch, albedo_draws=args.albedo_draws,
                         excluded=excluded, init_params=init, until=args.until,
                         workers=args.workers, address=args.address, gpu=args.gpu)
    secs = time.perf_counter() - t0
    spec = folders[0][0].meta["spec"]
    final = state["history"]["eval"][-1] if state["history"]["eval"] else {}
    report = {"data": str(args.data), "spec": spec, "run": cfg.to_dict(), "engine": "ray",
              "workers": args.workers, "gpu": args.gpu, "excluded_families": list(excluded),
              "albedo_draws": args.albedo_draws, "init": args.init, "architecture": arch.to_dict(),
              "step": state["step"], "seconds_this_session": round(secs, 1), "final": final,
              "history": state["history"]["eval"]}
    (out / "report.json").write_text(json.dumps(report, indent=1))
    for row in state["history"]["eval"]:
        print("  ".join(f"{k} {v:.5f}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()))
    print(f"ray: {args.workers} workers, step {state['step']}, {secs:.1f} s")
    if args.export and state["step"] >= cfg.steps:
        model = Model(arch)
        model.load_state_dict(state["model"])
        export(model, args.export, folders,
               {k: report[k] for k in ("spec", "run", "step", "final", "engine", "workers")})
    return 0


def union_domain(domains):
    """The smallest domain holding every data set's (None if any is a version-1 data set, whose
    domain the weight file's default describes)."""
    if not domains or any(d is None for d in domains):
        return None
    out = {"max_lobes": max(d["max_lobes"] for d in domains)}
    for k in ("albedo", "g", "optical_thickness", "resolution"):
        out[k] = [min(d[k][0] for d in domains), max(d[k][1] for d in domains)]
    return out


# --evaluate: at most about this many training shards for the mean predictor, and this many
# queries per out-of-family family (every k-th shard: a leave-one-family-out run holds a whole
# training family out, far more than an evaluation needs); the monitor set printed during
# training: at most about MONITOR_QUERIES held-out queries.
EVAL_TRAIN_SHARDS = 200
MONITOR_QUERIES = 40_000
EVAL_FAMILY_QUERIES = 30_000


def thin_to_queries(shards, n_queries):
    """Every k-th shard, k the smallest that keeps at most about ``n_queries`` queries."""
    if not shards:
        return shards
    per = max(1, int(shards[0].meta["spec"]["points_per_config"]))
    return shards[::max(1, -(-len(shards) * per // n_queries))]


def evaluate_weights(path, train, held_sh, cfg, base_loss, out=None, excluded=(),
                     device="cpu") -> int:
    """Held-out eq. 20 loss of a weight file, split into unseen volumes and unseen configurations
    of seen volumes, with the mean predictor's loss and the labels' noise, and the median
    relative error of the decoded F against the labels. Volumes are in family (a training
    family's held-out stream) or out of family (clvol.training.dataset.OUT_OF_FAMILY, and the
    ``excluded`` families of a leave-one-family-out run); the albedo bias is reported for both
    and their difference (the generalisation gap). Writes OUT/evaluation.json."""
    from collections import Counter

    from clvol.training import train as tr
    from clvol.training.dataset import OUT_OF_FAMILY
    from clvol.features.weights import load_weights
    from clvol.training.model import Model
    model = Model.from_weights(load_weights(path)).to(device)
    vid = (lambda s: (str(s.path.parent), s.volume))
    fam = (lambda s: s.meta["volume"].get("family", ""))
    outside = set(OUT_OF_FAMILY) | set(excluded)
    thin = []
    for f in sorted({fam(s) for s in held_sh if fam(s) in outside}):
        thin += thin_to_queries([s for s in held_sh if fam(s) == f], EVAL_FAMILY_QUERIES)
    held_sh = [s for s in held_sh if fam(s) not in outside] + thin
    # a seen volume has one held-out shard (its held-out configuration), an unseen one several
    count = Counter(map(vid, held_sh))
    is_seen = (lambda s: count[vid(s)] == 1 and fam(s) not in outside)
    keep = set(map(id, thin_to_queries([s for s in held_sh if is_seen(s)], EVAL_FAMILY_QUERIES)))
    held_sh = [s for s in held_sh if not is_seen(s) or id(s) in keep]
    count = Counter(map(vid, held_sh))
    hv = {k for k, n in count.items() if n > 1}
    hv |= {vid(s) for s in held_sh if fam(s) in outside}
    in_fam = [s for s in held_sh if vid(s) in hv and fam(s) not in outside]
    out_fam = [s for s in held_sh if fam(s) in outside]
    groups = {"all held out": held_sh,
              "in family: unseen volumes": in_fam,
              "unseen configurations of seen volumes": [s for s in held_sh if vid(s) not in hv],
              "out of family": out_fam}
    for f in sorted({fam(s) for s in held_sh} - {""}):     # version-2 data: unseen volumes per family
        tag = "out of family" if f in outside else "in family"
        groups[f"  {tag}: {f}"] = [s for s in held_sh if vid(s) in hv and fam(s) == f]
    m = float(np.average(train.y, weights=train.weight)) if len(train) else float("nan")
    report = {"weights": str(path), "excluded_families": list(excluded), "groups": {}, "bias": {}}
    for name, shards in groups.items():
        if not shards:
            continue
        h = tr.shard_samples(shards, cfg.floor)
        y = tr.predict(model, h).astype(np.float64)
        a4 = h.config[:, tr.ALBEDO].astype(np.float64) ** 4
        F_hat, F_lab = a4 * np.expm1(y), a4 * np.expm1(h.y.astype(np.float64))
        rel = np.abs(F_hat - F_lab) / np.maximum(F_lab, 1e-12)
        row = {"shards": len(shards), "samples": len(h), "loss": float(np.mean((y - h.y) ** 2)),
               "mean_predictor": float(np.mean((m - h.y) ** 2)), "label_noise": float(np.mean(h.var)),
               "median_rel_error": float(np.median(rel))}
        report["groups"][name.strip()] = row
        print(f"{name:44s} {len(shards):4d} shards {len(h):7d} samples  loss {row['loss']:.3e}"
              f"  mean predictor {row['mean_predictor']:.3e}  label noise {row['label_noise']:.3e}"
              f"  median |F - label| / label {row['median_rel_error']:.3f}")
    # Bias by albedo: the labels are unbiased in the mean (path-traced), the loss is in log
    # space, so sum(predicted F) / sum(label F) shows a systematic under- or over-prediction.
    # Per-order data: every held-out query at every albedo of EVAL_ALBEDOS.
    clouds = (lambda sh: [s for s in sh if fam(s) not in SOLIDS])
    parts = {"in-family clouds (unseen volumes)": clouds(in_fam),
             "in-family solids (unseen volumes)": [s for s in in_fam if fam(s) in SOLIDS],
             "out-of-family clouds": clouds(out_fam),
             "out-of-family solids": [s for s in out_fam if fam(s) in SOLIDS]}
    boots = {}
    for name, shards in parts.items():
        if shards:
            report["bias"][name], boots[name] = print_albedo_bias(model, shards, cfg.floor, name)
    a, b = "out-of-family clouds", "in-family clouds (unseen volumes)"
    if a in boots and b in boots:
        print("generalisation gap (out-of-family minus in-family ratio; 95% bootstrap interval):")
        report["gap"] = {}
        for k in boots[a]:
            if k in boots[b]:
                d = boots[a][k] - boots[b][k]
                gap = report["bias"][a][k][0] - report["bias"][b][k][0]
                lo_ci, hi_ci = np.percentile(d, 2.5), np.percentile(d, 97.5)
                report["gap"][k] = (gap, float(lo_ci), float(hi_ci))
                print(f"  albedo {k}: {gap:+.3f} ({lo_ci:+.3f} .. {hi_ci:+.3f})")
    for name in (a, b):
        shards = parts.get(name)
        if shards and all(s.meta["spec"].get("per_order_labels") for s in shards):
            report.setdefault("albedo_response", {})[name] = albedo_response(model, shards, name)
    if out is not None:
        import json
        (Path(out) / "evaluation.json").write_text(json.dumps(report, indent=1))
    return 0


# Albedos of the albedo-response table (issue "the network on clouds it has never seen").
RESPONSE_ALBEDOS = (0.8, 0.9, 0.96, 0.99, 1.0)


def albedo_response(model, shards, name) -> dict:
    """The network against the path-traced labels at the same points, at RESPONSE_ALBEDOS:
    sum ratio per albedo, and the albedo response d log F / d log a near 1 (the labels': their
    mean albedo exponent, sum M / sum S at albedo 1; the network's: from its F at 0.99 and 1)."""
    import numpy as np
    from clvol.training import train as tr
    h = tr.shard_samples(shards, 0.05, albedos=RESPONSE_ALBEDOS)
    y = tr.predict(model, h).astype(np.float64)
    alb = h.config[:, tr.ALBEDO].astype(np.float64)
    F_hat = alb ** 4 * np.expm1(y)
    F_lab = alb ** 4 * np.expm1(h.y.astype(np.float64) - 0.5 * h.var)
    out = {"ratio": {}}
    sums = {}
    for a in RESPONSE_ALBEDOS:
        k = np.isclose(alb, a)
        sums[a] = (F_hat[k].sum(), F_lab[k].sum())
        out["ratio"][str(a)] = float(sums[a][0] / max(sums[a][1], 1e-30))
    S = np.concatenate([np.asarray(s.arrays["S"], np.float64) for s in shards])
    M = np.concatenate([np.asarray(s.arrays["M"], np.float64) for s in shards])
    out["label_mean_exponent"] = float(M.sum() / max(S.sum(), 1e-30))
    out["label_slope_099_1"] = float(np.log(sums[1.0][1] / sums[0.99][1]) / -np.log(0.99))
    out["network_slope_099_1"] = float(np.log(sums[1.0][0] / sums[0.99][0]) / -np.log(0.99))
    print(f"{name}: albedo response, network / labels at " +
          ", ".join(f"{a}: {out['ratio'][str(a)]:.3f}" for a in RESPONSE_ALBEDOS) +
          f"; d log F / d log a over 0.99..1: labels {out['label_slope_099_1']:.1f}, network "
          f"{out['network_slope_099_1']:.1f} (labels' mean exponent at 1: {out['label_mean_exponent']:.1f})")
    return out


SOLIDS = ("sphere", "blob", "torus", "box", "union")
# Evaluation albedos of per-order data, and the bins the bias is reported in.
EVAL_ALBEDOS = (0.3, 0.5, 0.7, 0.8, 0.85, 0.92, 0.95, 0.98, 0.993, 0.995, 0.998, 0.9995, 0.9999, 1.0)
ALBEDO_BINS = ((0.0, 0.9), (0.9, 0.97), (0.97, 0.99), (0.99, 0.997), (0.997, 0.999),
               (0.999, 1.0001))


def print_albedo_bias(model, shards, floor, name) -> dict:
    """Print and return sum(predicted F) / sum(label F) per albedo bin with a 95% bootstrap
    interval over configurations (a configuration's points are correlated), and the bootstrap
    draws (for the gap between two groups)."""
    import numpy as np
    from clvol.training import train as tr
    per_order = all(s.meta["spec"].get("per_order_labels") for s in shards)
    h = tr.shard_samples(shards, floor, albedos=EVAL_ALBEDOS if per_order else None)
    y = tr.predict(model, h).astype(np.float64)
    alb = h.config[:, tr.ALBEDO].astype(np.float64)
    F_hat = alb ** 4 * np.expm1(y)
    F_lab = alb ** 4 * np.expm1(h.y.astype(np.float64) - 0.5 * h.var)
    print(f"{name}, sum of predicted F / sum of labels, by albedo "
          f"({'at ' + ' '.join(map(str, EVAL_ALBEDOS)) if per_order else 'the configurations'}; "
          f"95% interval: bootstrap over configurations):")
    rng = np.random.default_rng(0)
    out, boots = {}, {}
    for lo, hi in ALBEDO_BINS:
        k = np.flatnonzero((alb >= lo) & (alb < hi))
        if not len(k):
            continue
        groups = [k[h.key[k] == u] for u in np.unique(h.key[k])]
        ratio = (lambda idx: F_hat[idx].sum() / max(F_lab[idx].sum(), 1e-30))
        boot = [ratio(np.concatenate([groups[i] for i in rng.integers(0, len(groups), len(groups))]))
                for _ in range(1000)]
        lo_ci, hi_ci = np.percentile(boot, 2.5), np.percentile(boot, 97.5)
        out[f"[{lo:g}, {min(hi, 1.0):g}]"] = (float(ratio(k)), float(lo_ci), float(hi_ci))
        boots[f"[{lo:g}, {min(hi, 1.0):g}]"] = np.asarray(boot)
        print(f"  albedo [{lo:g}, {min(hi, 1.0):g}{']' if hi > 1 else ')'}: {len(k):7d} samples  "
              f"ratio {ratio(k):.3f}  ({lo_ci:.3f}-{hi_ci:.3f} over {len(groups)} configurations)")
    return out, boots


if __name__ == "__main__":
    sys.exit(main())
