"""Training data (clvol/dataset.py) and resumable training runs (clvol/train.py).

Tiny specs throughout (12^3 volumes, 16^3 pyramid, 24 points, 16 paths): what is tested is
determinism, resumability and the file handling, not the labels' accuracy (the path tracer's
tests cover that).
"""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from clvol import dataset as ds

TINY = dict(n_volumes=2, n_solids=1, resolution=12, base_resolution=16, configs_per_volume=2,
            points_per_config=24, n_paths=16)


def test_shard_is_deterministic_and_records_its_parameters():
    spec = ds.DatasetSpec(seed=3, **TINY)
    a = ds.make_shard(spec, 1, 1)
    b = ds.make_shard(spec, 1, 1)
    for k in ds.ARRAYS:
        assert a["arrays"][k].tobytes() == b["arrays"][k].tobytes(), k
    other = ds.make_shard(ds.DatasetSpec(seed=4, **TINY), 1, 1)
    assert not np.array_equal(other["arrays"]["points"], a["arrays"]["points"])
    m = a["meta"]
    assert m["spec"]["seed"] == 3 and m["volume_index"] == 1 and m["config_index"] == 1
    assert m["volume"]["generator"] in ("blob", "sphere")         # volume 1 is the solid
    assert 1 <= len(m["config"]["lobes"]) <= 3 and "query_seed" in m
    arr = a["arrays"]
    n, L = spec.points_per_config, int(np.log2(spec.base_resolution)) + 1
    assert arr["features"].shape == (n, 3, 266) and arr["levels"].shape == (n, L, 266)
    assert np.all(arr["Fms"] >= 0) and np.all(arr["Fms_se"] >= 0)
    # points: density-weighted ones inside the box where the density is > 0, uniform ones in the box
    assert np.all(arr["points"] >= -0.5) and np.all(arr["points"] <= 0.5)
    np.testing.assert_allclose(np.linalg.norm(arr["omegas"], axis=1), 1.0, atol=1e-6)


class Killed(Exception):
    pass


def test_interrupted_run_resumes_without_redoing_shards(tmp_path):
    spec = ds.DatasetSpec(seed=0, **TINY)
    out = tmp_path / "data"

    def kill_after_first(v, c):
        raise Killed()
    with pytest.raises(Killed):
        ds.make_dataset(spec, out, progress=False, on_shard=kill_after_first)
    first = out / ds.shard_name(0, 0)
    assert sorted(p.name for p in out.glob("shard_*.npz")) == [first.name]
    before = first.read_bytes()
    # a run killed while writing leaves a temporary file: never read as a shard, removed on resume
    partial = out / ".shard_000_001-abc.tmp"
    partial.write_bytes(b"PK\x03\x04 truncated")
    assert [s.path.name for s in ds.load_shards(out)] == [first.name]
    made = []
    r = ds.make_dataset(spec, out, progress=False, on_shard=lambda v, c: made.append((v, c)))
    assert r == {"made": 3, "skipped": 1}
    assert made == [(0, 1), (1, 0), (1, 1)]                   # the finished shard was not redone
    assert first.read_bytes() == before and not partial.exists()
    assert len(ds.load_shards(out)) == 4
    # a resumed shard is the same as one made in a fresh run
    fresh = ds.make_shard(spec, 1, 0)
    got = ds.read_shard(out / ds.shard_name(1, 0))
    assert got.arrays["Fms"].tobytes() == fresh["arrays"]["Fms"].tobytes()
    assert ds.make_dataset(spec, out, progress=False) == {"made": 0, "skipped": 4}


def test_folder_of_another_spec_is_refused(tmp_path):
    out = tmp_path / "data"
    ds.make_dataset(ds.DatasetSpec(seed=0, **TINY), out, progress=False, max_shards=0)
    with pytest.raises(ds.DatasetError, match=r"spec.json.*\['seed'\]"):
        ds.make_dataset(ds.DatasetSpec(seed=1, **TINY), out, progress=False, max_shards=0)
    with pytest.raises(ds.DatasetError, match=r"\[n_solids\] = 5"):
        ds.DatasetSpec(n_volumes=2, n_solids=5)
    bad = out / "shard_009_009.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ds.DatasetError, match="shard_009_009.npz: cannot read shard"):
        ds.load_shards(out)


def _synthetic_samples(n=64, L=5, seed=0):
    from clvol.train import Samples
    rng = np.random.default_rng(seed)
    f = rng.uniform(0, 1, (n, 3, 266)).astype(np.float32)
    lv = rng.uniform(0, 1, (n, L, 266)).astype(np.float32)
    c = np.zeros((n, 9), np.float32)
    c[:, 0], c[:, 3], c[:, 6], c[:, 7], c[:, 8] = 0.8, 1.0, 0.8, 0.95, rng.uniform(0, 3, n)
    y = (0.5 * f[:, 0].mean(axis=1) + 0.1 * c[:, 8]).astype(np.float32)
    return Samples(f, c, y, np.ones(n, np.float32), np.zeros(n, np.float32), lv, np.zeros(n, int))


def test_checkpoint_resume_gives_the_same_state(tmp_path):
    """6 steps in one go == 3 steps, checkpoint to disk, a new Trainer restored, 3 more steps:
    every tensor of model and optimiser bit-identical (same thread count, CPU)."""
    import torch
    from clvol import train as tr
    data = _synthetic_samples()
    cfg = tr.RunConfig(steps=6, batch=16, lr=1e-3, seed=5, eval_every=0, checkpoint_every=3)
    straight = tr.Trainer(data, cfg)
    straight.run(6)
    ckpt = tmp_path / "ckpt.pt"
    first = tr.Trainer(data, cfg)
    first.run(3, checkpoint=ckpt)
    assert first.step == 3 and ckpt.exists()
    resumed = tr.Trainer(data, cfg)
    resumed.load_state_dict(torch.load(ckpt, weights_only=False))
    assert resumed.step == 3
    resumed.run(6, checkpoint=ckpt)
    a, b = straight.state_dict(), resumed.state_dict()
    for k, v in a["model"].items():
        assert torch.equal(v, b["model"][k]), k
    for sa, sb in zip(a["opt"]["state"].values(), b["opt"]["state"].values()):
        assert torch.equal(sa["exp_avg"], sb["exp_avg"]) and torch.equal(sa["exp_avg_sq"], sb["exp_avg_sq"])
    assert torch.equal(a["gen"], b["gen"])
    # a power check: a different seed does not give the same weights
    other = tr.Trainer(data, tr.RunConfig(steps=6, batch=16, lr=1e-3, seed=6, eval_every=0))
    other.run(6)
    assert not all(torch.equal(v, other.state_dict()["model"][k]) for k, v in a["model"].items())
    # a checkpoint of other settings is refused
    with pytest.raises(ValueError, match=r"other run settings \(\['lr'\]\)"):
        tr.Trainer(data, tr.RunConfig(steps=6, batch=16, lr=2e-3, seed=5, eval_every=0,
                                      checkpoint_every=3)).load_state_dict(torch.load(ckpt, weights_only=False))
    assert not any(p.name.endswith(".tmp") for p in tmp_path.iterdir())


def test_train_script_end_to_end(tmp_path):
    """make_dataset -> scripts/train.py (held-out split, checkpoint, resume, export) -> the weight
    file loads with the gather's contract for the data set's base resolution."""
    import subprocess
    import sys
    from clvol.export import gather_contract, load_weights
    spec = ds.DatasetSpec(seed=1, **dict(TINY, n_volumes=3, n_solids=1))
    data = tmp_path / "data"
    ds.make_dataset(spec, data, progress=False)
    run = tmp_path / "run"
    w = tmp_path / "w.npz"
    args = [sys.executable, "scripts/train.py", str(data), str(run), "--steps", "4", "--batch", "8",
            "--eval-every", "2", "--checkpoint-every", "2", "--holdout-volumes", "0",
            "--export", str(w)]
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    p = subprocess.run(args + ["--until", "2"], cwd=root, capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert not w.exists()                      # not finished: nothing exported
    p = subprocess.run(args, cwd=root, capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert "resumed from" in p.stdout and "held_out" in p.stdout
    rep = json.loads((run / "report.json").read_text())
    assert rep["step"] == 4 and rep["shards"]["held_out"] > 0
    # held out: all of volume 0 and of the first solid (volume 2), and the last configuration
    assert {n for n in rep["shards"]["held_out_names"]} == {
        "shard_000_000.npz", "shard_000_001.npz", "shard_002_000.npz", "shard_002_001.npz",
        "shard_001_001.npz"}
    wts = load_weights(w, expect_contract=gather_contract(spec.base_resolution, spec.lam))
    assert wts.arch.n_levels == 5 and wts.meta["training"]["step"] == 4
