"""Data-parallel training on a Ray cluster (Ray Train's TorchTrainer): the same model, the same
checkpoint file and the same resume as ``scripts/train.py`` (clvol/training/train.py ``Trainer``).

    python scripts/train.py DATA OUT --ray [--address HOST:PORT] [--workers N] [--gpu] ...

How it works (docs/dataset.md, "Training on Ray"):

- ``N`` workers (one CPU each, or one GPU each with ``--gpu``), each a ``Trainer`` whose model is
  wrapped by ``ray.train.torch.prepare_model`` (DistributedDataParallel: gradients averaged over
  the workers every step, the model's buffers (the feature normalisation) broadcast from rank 0).
- Worker r reads the training shards ``r::N`` (the data folders must be readable at the same path
  on every node: one machine, or a shared file system) and draws batches of ``batch / N`` from its
  own generator (seed + r), so one step sees ``batch`` samples, as one process would.
- Rank 0 reports a Ray checkpoint every ``checkpoint_every`` steps: a folder holding
  ``checkpoint.pt``, the very file ``scripts/train.py`` writes, kept under ``OUT/ray``. The driver
  copies the newest one to ``OUT/checkpoint.pt`` at the end. A rerun starts from the newest of
  that file and the checkpoints under ``OUT/ray`` (a driver killed before its copy loses
  nothing), sent to the workers as bytes, so they need no shared file system for it.
- Rank 0 also evaluates the held-out monitor set, as one process does.

Unlike one process, a resumed Ray run is not bit-identical to an uninterrupted one (the workers'
floating-point reductions are not ordered); one-process training stays the reference.
"""
from __future__ import annotations

import io
import os
import shutil
import tempfile
from pathlib import Path

CHECKPOINT_FILE = "checkpoint.pt"
RAY_DIR = "ray"


def _worker_loop(config: dict) -> None:
    """One data-parallel worker (runs inside a Ray Train worker process)."""
    import ray.train
    import torch
    from ray.train.torch import prepare_model

    from . import train as tr
    from .dataset import load_shards
    from ..features.weights import Architecture

    torch.set_num_threads(1)
    ctx = ray.train.get_context()
    rank, world = ctx.get_world_rank(), ctx.get_world_size()
    cfg = tr.RunConfig(**{**config["run"], "holdout_volumes": tuple(config["run"]["holdout_volumes"]),
                          "batch": max(1, config["run"]["batch"] // world)})
    folders = [load_shards(d) for d in config["data"]]
    excluded = set(config["excluded"])
    fam = (lambda s: s.meta.get("volume", {}).get("family"))
    train_sh = [s for f in folders for s in tr.split_shards(f, cfg)[0] if fam(s) not in excluded]
    mine = train_sh[rank::world]
    samples = tr.shard_samples(mine, cfg.floor, albedo_draws=config["albedo_draws"], seed=cfg.seed,
                               image_weight=cfg.image_weight)
    arch = Architecture.from_dict(config["architecture"])
    device = "cpu"
    if config["gpu"]:
        device = ray.train.torch.get_device()
    trainer = tr.Trainer(samples, cfg, arch, device=str(device), generator_seed=cfg.seed + rank)
    ckpt = ray.train.get_checkpoint()
    if config.get("resume") is not None:      # the driver's newest checkpoint, as bytes
        trainer.load_state_dict(torch.load(io.BytesIO(config["resume"]), weights_only=False,
                                           map_location=str(device)))
    elif ckpt is not None:                    # Ray restarting the workers within this run
        with ckpt.as_directory() as d:
            trainer.load_state_dict(torch.load(Path(d) / CHECKPOINT_FILE, weights_only=False,
                                               map_location=str(device)))
    elif config.get("init") is not None:
        trainer.model.load_numpy_params(config["init"])
    trainer.net = prepare_model(trainer.model, move_to_device=False)
    held = None
    if rank == 0 and config["held"]:
        held_sh = [s for f in folders for s in tr.split_shards(f, cfg)[1]]
        held_sh += [s for f in folders for s in tr.split_shards(f, cfg)[0] if fam(s) in excluded]
        held_sh = held_sh[::max(1, -(-len(held_sh) // config["held"]))]
        held = tr.shard_samples(held_sh, cfg.floor, albedo_draws=config["albedo_draws"] and 2,
                                seed=cfg.seed + 1)

    def report(t: "tr.Trainer") -> None:
        last = t.history["eval"][-1] if t.history["eval"] else {}
        metrics = {"step": t.step, **{k: v for k, v in last.items() if isinstance(v, float)}}
        if rank == 0:
            with tempfile.TemporaryDirectory() as d:
                tr.save_checkpoint(Path(d) / CHECKPOINT_FILE, t.state_dict())
                ray.train.report(metrics, checkpoint=ray.train.Checkpoint.from_directory(d))
        else:
            ray.train.report(metrics)

    trainer.run(config["until"], checkpoint=None, held=held,
                log=print if rank == 0 else None, on_checkpoint=report)


def newest_checkpoint(out: Path):
    """(path, step) of the newest checkpoint.pt among OUT/checkpoint.pt and Ray's copies under
    OUT/ray; (None, -1) if there is none."""
    import torch
    best, step = None, -1
    for p in [out / CHECKPOINT_FILE, *sorted((out / RAY_DIR).rglob(CHECKPOINT_FILE))]:
        if p.is_file():
            try:
                s = int(torch.load(p, weights_only=False, map_location="cpu")["step"])
            except Exception:          # a damaged or foreign file is not a resume point
                continue
            if s > step:
                best, step = p, s
    return best, step


def train_on_ray(data: list[str], out: Path, cfg, arch, *, albedo_draws: int = 0,
                 excluded=(), init_params: dict | None = None, until: int | None = None,
                 workers: int = 2, address: str | None = None, gpu: bool = False,
                 held_shards: int = 400, log=print):
    """Run the data-parallel training to step ``until`` (default cfg.steps); returns the final
    state dict (the checkpoint's contents) and writes OUT/checkpoint.pt."""
    import torch

    from .distributed import connect_error_message, import_ray, local_init_kwargs
    ray = import_ray(local=address is None)    # a local Ray stays on loopback (docs/dataset.md)
    from ray.train import RunConfig, ScalingConfig
    from ray.train.torch import TorchTrainer

    out = Path(out).resolve()
    if not ray.is_initialized():
        kw = {"address": address} if address else local_init_kwargs(workers)
        # the workers' own logs (Ray Train's per-report lines) stay in Ray's log folder; the
        # driver prints the run's evaluation rows from the final checkpoint
        kw.update(logging_level="ERROR", log_to_driver=False)
        try:
            ray.init(**kw)
        except Exception as exc:      # one line, as `clvol dataset make` says it
            raise RuntimeError(connect_error_message(address, exc)) from None
    resume, step = newest_checkpoint(out)
    if resume is not None:
        log(f"resuming from {resume} at step {step}")
    # sent to the workers as bytes (through Ray's object store): no shared file system needed
    config = {"data": [str(Path(d).resolve()) for d in data], "run": cfg.to_dict(),
              "architecture": arch.to_dict(), "albedo_draws": albedo_draws,
              "excluded": list(excluded), "init": init_params, "gpu": gpu,
              "until": int(until or cfg.steps), "held": held_shards,
              "resume": resume.read_bytes() if resume is not None else None}
    trainer = TorchTrainer(
        _worker_loop, train_loop_config=config,
        scaling_config=ScalingConfig(num_workers=workers, use_gpu=gpu),
        run_config=RunConfig(name="train", storage_path=str(out / RAY_DIR)))
    result = trainer.fit()
    if result.checkpoint is None:
        raise RuntimeError("the Ray training reported no checkpoint")
    with result.checkpoint.as_directory() as d:
        src = Path(d) / CHECKPOINT_FILE
        tmp = out / (CHECKPOINT_FILE + ".tmp")
        shutil.copy2(src, tmp)
        os.replace(tmp, out / CHECKPOINT_FILE)
    return torch.load(out / CHECKPOINT_FILE, weights_only=False, map_location="cpu")
