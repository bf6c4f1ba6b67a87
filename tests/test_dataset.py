"""Training data (clvol/training/dataset.py) and resumable training runs (clvol/training/train.py).

Tiny specs throughout (12^3 volumes, 16^3 pyramid, 24 points, 16 paths): what is tested is
determinism, resumability and the file handling, not the labels' accuracy (the path tracer's
tests cover that).
"""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from clvol.errors import ClvolError
from clvol.training import dataset as ds

TINY = dict(n_volumes=2, n_heldout_volumes=1, resolution=12, base_resolution=16,
            configs_per_volume=2, points_per_config=24, n_paths=16, families=("cumulus", "blob"))


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
    # volume 1 is the held-out one: first of its stream, so the first family
    assert m["volume"]["family"] == "cumulus" and m["heldout_volume"] is True
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
    with pytest.raises(ds.DatasetError, match=r"\[n_heldout_volumes\] = 5"):
        ds.DatasetSpec(n_volumes=2, n_heldout_volumes=5)
    with pytest.raises(ds.DatasetError, match=r"\[g\] = \(0.5, 0.2\)"):
        ds.DatasetSpec(g=(0.5, 0.2))
    with pytest.raises(ds.DatasetError, match=r"\[families\]"):
        ds.DatasetSpec(families=("cumulus", "teapot"))
    bad = out / "shard_009_009.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ds.DatasetError, match="shard_009_009.npz: cannot read shard"):
        ds.load_shards(out)


def test_configurations_cover_the_domain():
    """Draws of the default spec span what the spec says: g from < -0.5 to > 0.95 (backward and
    strongly forward lobes), 1-3 lobes, per-channel albedo from < 0.5 to > 0.99 with chromatic
    ones, target optical thickness over 3 decades, lights from below and grazing, every family,
    and resolutions 32-128. 400 configurations: each check fails with probability < 1e-6 if the
    sampler draws what its code says (e.g. P(no g < -0.5 in 400 first lobes) ~ 0.8^400)."""
    spec = ds.DatasetSpec(seed=0, n_volumes=50, n_heldout_volumes=10, configs_per_volume=8)
    grid = ds.make_volume(spec, 5)          # the density scale needs a grid; the draws do not
    cps = [ds.config_params(spec, v, c, grid) for v in range(50) for c in range(8)]
    gs = [g for cp in cps for g, _ in cp["lobes"]]
    assert min(gs) >= spec.g[0] and max(gs) <= spec.g[1]
    assert min(gs) < -0.8 and max(gs) > 0.97
    assert {len(cp["lobes"]) for cp in cps} == {1, 2, 3}
    assert all(abs(sum(w for _, w in cp["lobes"]) - 1) < 1e-12 for cp in cps)
    alb = np.array([cp["albedo"] for cp in cps])
    assert alb.min() >= spec.albedo[0] and alb.max() <= spec.albedo[1]
    assert alb.min() < 0.5 and alb.max() > 0.99 and np.mean(alb.max(1) - alb.min(1) > 0.05) > 0.3
    tau = np.array([cp["optical_thickness"] for cp in cps])
    assert tau.min() >= 1.0 and tau.max() <= 1000.0 and tau.min() < 3 and tau.max() > 300
    light = np.array([cp["light"] for cp in cps])
    np.testing.assert_allclose(np.linalg.norm(light, axis=1), 1.0, atol=1e-9)
    assert np.mean(light[:, 1] < -0.5) > 0.05 and np.mean(np.abs(light[:, 1]) < 0.15) > 0.2
    vps = [ds.volume_params(spec, v) for v in range(50)]
    assert {vp["family"] for vp in vps} == set(ds.TRAINING_FAMILIES)
    assert {vp["resolution"] for vp in vps} == set(ds.RESOLUTIONS)


def test_density_scale_gives_the_target_optical_thickness():
    spec = ds.DatasetSpec(seed=0, resolution=(32, 32))
    for v in (0, 6):
        grid = ds.make_volume(spec, v)
        cp = ds.config_params(spec, v, 0, grid)
        # unit_optical_thickness: mean column integral over occupied columns, 3 axes
        d = grid.density.astype(np.float64) * cp["density_scale"]
        h = float(grid.cell_size[0])
        taus = [np.mean(col[col > 0]) for col in (d.sum(axis=a) * h for a in range(3))]
        assert np.mean(taus) == pytest.approx(cp["optical_thickness"], rel=1e-4)


def test_heldout_volumes_come_from_their_own_stream():
    """Held-out volume i is the same whatever the number of training volumes (its draws are keyed
    by its held-out index), and no held-out generator seed equals a training one."""
    a = ds.DatasetSpec(seed=2, n_volumes=25, n_heldout_volumes=5)
    b = ds.DatasetSpec(seed=2, n_volumes=45, n_heldout_volumes=5)
    for i in range(5):
        assert ds.volume_params(a, 20 + i) == ds.volume_params(b, 40 + i)
        assert a.is_heldout(20 + i) and not a.is_heldout(19)
    train_seeds = {ds.volume_params(b, v)["seed"] for v in range(40)}
    held_seeds = {ds.volume_params(b, v)["seed"] for v in range(40, 45)}
    assert not train_seeds & held_seeds
    assert {ds.volume_params(b, v)["family"] for v in range(40, 45)} == set(ds.FAMILIES[:5])


def test_version_1_shards_still_load(tmp_path):
    """A shard written by the first data set version (cloud_small's data) reads and splits as
    before: volume 1 and the first solid held out, plus the last configuration."""
    from clvol.training import train as tr
    spec = ds.DatasetSpec(seed=0, **TINY)
    sh = ds.make_shard(spec, 0, 0)
    v1 = {"seed": 0, "n_volumes": 3, "n_solids": 1, "resolution": 12, "base_resolution": 16,
          "lam": spec.lam, "configs_per_volume": 2, "points_per_config": 24, "uniform_fraction": 0.2,
          "n_paths": 16, "cloud_density_scale": [16.0, 96.0], "solid_density_scale": [20.0, 200.0]}
    (tmp_path / ds.SPEC_FILE).write_text(json.dumps({"format": ds.DATASET_FORMAT, "format_version": 1,
                                                      "spec": v1}))
    for v in range(3):
        for c in range(2):
            meta = dict(sh["meta"], format_version=1, spec=v1, volume_index=v, config_index=c)
            ds.write_shard(tmp_path, v, c, ds.shard_bytes(sh["arrays"], meta))
    shards = ds.load_shards(tmp_path)
    train, held = tr.split_shards(shards, tr.RunConfig())
    assert sorted(s.path.name for s in train) == ["shard_000_000.npz"]
    assert ds.dataset_domain(v1) is None


def test_shard_samples_read_each_file_once_per_array_and_match_eager_samples(tmp_path):
    """The streaming loader (lazy shard arrays, one preallocated copy of the feature rows) gives
    exactly the samples of loading every shard eagerly and concatenating; train_fraction keeps
    whole leading training volumes and leaves the held-out shards unchanged."""
    from clvol.training import train as tr
    spec = ds.DatasetSpec(seed=5, **dict(TINY, n_volumes=4, n_heldout_volumes=1))
    ds.make_dataset(spec, tmp_path, progress=False)
    shards = ds.load_shards(tmp_path)
    assert not isinstance(shards[0].arrays, dict)          # nothing read until asked for
    got = tr.shard_samples(shards)
    eager = tr.concat_samples(
        tr.make_samples(s.arrays["features"], s.arrays["config"], s.arrays["Fms"], s.arrays["Fms_se"],
                        s.albedo, levels=s.arrays["levels"], key=np.zeros(len(s.arrays["Fms"])))
        for s in shards)
    assert len(got.features) == sum(len(s.arrays["Fms"]) for s in shards)
    for a, b in zip(tr._tensors(got), tr._tensors(eager)):
        assert np.array_equal(a.numpy(), b.numpy())
    full_train, full_held = tr.split_shards(shards, tr.RunConfig())
    part_train, part_held = tr.split_shards(shards, tr.RunConfig(train_fraction=0.5))
    assert [s.path for s in part_held] == [s.path for s in full_held]
    assert {s.volume for s in full_train} == {0, 1, 2} and {s.volume for s in part_train} == {0, 1}
    with pytest.raises(ClvolError, match="train_fraction"):
        tr.split_shards(shards, tr.RunConfig(train_fraction=0.0))


def _synthetic_samples(n=64, L=5, seed=0):
    from clvol.training.train import Samples
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
    from clvol.training import train as tr
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
    from clvol.features.weights import gather_contract, load_weights
    spec = ds.DatasetSpec(seed=1, **dict(TINY, n_volumes=3, n_heldout_volumes=1))
    data = tmp_path / "data"
    ds.make_dataset(spec, data, progress=False)
    run = tmp_path / "run"
    w = tmp_path / "w.npz"
    args = [sys.executable, "scripts/train.py", str(data), str(run), "--steps", "4", "--batch", "8",
            "--eval-every", "2", "--checkpoint-every", "2", "--holdout-volumes", "0",
            "--export", str(w)]
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=root)    # this checkout's clvol, not an installed one
    p = subprocess.run(args + ["--until", "2"], cwd=root, capture_output=True, text=True, env=env)
    assert p.returncode == 0, p.stderr
    assert not w.exists()                      # not finished: nothing exported
    p = subprocess.run(args, cwd=root, capture_output=True, text=True, env=env)
    assert p.returncode == 0, p.stderr
    assert "resumed from" in p.stdout and "held_out" in p.stdout
    rep = json.loads((run / "report.json").read_text())
    assert rep["step"] == 4 and rep["shards"]["held_out"] > 0
    # held out: all of volume 0 (named) and of the held-out stream (volume 2), and the last configuration
    assert {n for n in rep["shards"]["held_out_names"]} == {
        "shard_000_000.npz", "shard_000_001.npz", "shard_002_000.npz", "shard_002_001.npz",
        "shard_001_001.npz"}
    wts = load_weights(w, expect_contract=gather_contract(spec.base_resolution, spec.lam))
    assert wts.arch.n_levels == 5 and wts.meta["training"]["step"] == 4
    # the weight file records the data set's validity domain
    assert wts.meta["domain"] == {"albedo": list(spec.albedo), "g": list(spec.g),
                                  "max_lobes": spec.max_lobes,
                                  "optical_thickness": list(spec.optical_thickness),
                                  "resolution": list(spec.resolution)}
    # --evaluate: per-group held-out losses and the bias of predicted F by albedo
    p = subprocess.run([sys.executable, "scripts/train.py", str(data), str(tmp_path / "ev"),
                        "--holdout-volumes", "0", "--evaluate", str(w)],
                       cwd=root, capture_output=True, text=True, env=env)
    assert p.returncode == 0, p.stderr
    assert "unseen volumes" in p.stdout and "sum of predicted F / sum of labels" in p.stdout
    rows = [line.split("ratio ")[1].replace("(", "").replace("-", " ").split()[:3]
            for line in p.stdout.splitlines() if line.startswith("  albedo [")]
    assert rows
    for r, lo, hi in (map(float, row) for row in rows):
        assert np.isfinite(r) and 0 <= lo <= hi, (r, lo, hi)


def test_escape_depth_and_point_placement():
    """escape_depth on a uniform slab equals the distance to the nearer face times the
    extinction; in an optically thick sphere most density-weighted points lie within a few
    mean free paths of the surface, but a few are deeper."""
    from clvol.volume.grid import DensityGrid
    d = np.ones((4, 6, 8), np.float32)
    g = DensityGrid(d, np.array([0.0, 0.0, 0.0]), np.array([8.0, 6.0, 4.0]))    # 1-unit voxels
    e = ds.escape_depth(g, 2.0)
    z, y, x = np.meshgrid(np.arange(4), np.arange(6), np.arange(8), indexing="ij")
    dist = np.minimum.reduce([x + 0.5, 7.5 - x, y + 0.5, 5.5 - y, z + 0.5, 3.5 - z])
    np.testing.assert_allclose(e, 2.0 * dist)
    spec = ds.DatasetSpec(seed=0, resolution=(48, 48), families=("sphere",), points_per_config=400,
                          uniform_fraction=0.0, n_volumes=2, n_heldout_volumes=1)
    grid = ds.make_volume(spec, 0)
    c = next(c for c in range(50) if ds.config_params(spec, 0, c, grid)["optical_thickness"] > 200)
    cp = ds.config_params(spec, 0, c, grid)
    radius = ds.volume_params(spec, 0)["params"]["radius"]
    pts = ds.sample_points(ds.DatasetSpec(**{**spec.to_dict(), "families": ("sphere",)}), grid, 0, c)
    mfp = 1.0 / (cp["density_scale"] * 1.0)        # sphere density 1 inside
    depth = radius - np.linalg.norm(pts, axis=1)
    assert np.mean(depth < 12 * mfp + 1.5 / 48) > 0.8      # near the surface (edge ~1.5 voxels)
    assert np.mean(depth > 0.3 * radius) > 0.005           # but not only there (~5% expected)


def test_data_curve_script_trains_each_fraction_on_fewer_volumes(tmp_path):
    """scripts/data_curve.py: one run per fraction (fewer training volumes and samples for the
    smaller one, the same held-out shards), a table row for each, and a rerun that finds every
    point finished trains nothing."""
    import subprocess
    import sys
    spec = ds.DatasetSpec(seed=2, **dict(TINY, n_volumes=5, n_heldout_volumes=1))
    data = tmp_path / "data"
    ds.make_dataset(spec, data, progress=False)
    out = tmp_path / "curve"
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=root)
    args = [sys.executable, "scripts/data_curve.py", str(data), str(out), "--fractions", "0.5,1",
            "--steps", "4", "--jobs", "2", "--", "--batch", "8"]
    p = subprocess.run(args, cwd=root, capture_output=True, text=True, env=env)
    assert p.returncode == 0, p.stderr + p.stdout
    half, full = (json.loads((out / f"frac_{f}" / "report.json").read_text()) for f in ("0.5", "1"))
    assert (half["shards"]["train_volumes"], full["shards"]["train_volumes"]) == (2, 4)
    assert half["samples"]["train"] < full["samples"]["train"]
    assert half["shards"]["held_out_names"] == full["shards"]["held_out_names"]
    rows = [r for r in (out / "curve.md").read_text().splitlines() if r.startswith("| 0.5") or r.startswith("| 1 ")]
    assert len(rows) == 2
    p = subprocess.run(args, cwd=root, capture_output=True, text=True, env=env)
    assert p.returncode == 0 and "start fraction" not in p.stdout


def test_per_order_shards_label_any_albedo_and_train(tmp_path):
    """per_order_labels: the shard stores the bins, its Fms is the relabelled label at the
    configuration's albedo, draws reach albedo 1, and scripts/train.py trains on drawn
    albedos with the log1m input and reports the [0.999, 1] bin."""
    import subprocess
    import sys
    from clvol.training import train as tr
    from clvol.training.labels import label_at
    spec = ds.DatasetSpec(seed=2, **dict(TINY, n_volumes=3, n_heldout_volumes=1,
                                         albedo=(0.3, 1.0), per_order_labels=True))
    data = tmp_path / "data"
    ds.make_dataset(spec, data, progress=False)
    shards = ds.load_shards(data)
    s = shards[0]
    a = s.arrays
    assert a["S"].shape == (24, 127) and a["M"].shape == (24, 127) and a["se"].shape == (24, 9)
    alb = s.albedo
    np.testing.assert_allclose(a["Fms"][:, 0], label_at(a["S"], a["M"], alb[0]), rtol=1e-5)
    assert s.meta["vertices_mean"] >= 1 and "vertices_max" in s.meta
    # draws: reproducible, in (0.3 - eps, 1], some exactly 1
    d1 = tr.draw_albedos(np.random.default_rng(1), 4000)
    assert np.array_equal(d1, tr.draw_albedos(np.random.default_rng(1), 4000))
    assert d1.min() >= 0.3 - 1e-9 and d1.max() == 1.0 and 0.1 < np.mean(d1 == 1.0) < 0.2
    assert np.mean(d1 > 0.99) > 0.4                      # log-uniform in 1 - a: many near 1
    smp = tr.shard_samples(shards[:2], albedo_draws=3, seed=5)
    assert len(smp) == 2 * 24 * 3 and len(smp.features) == 2 * 24
    again = tr.shard_samples(shards[:2], albedo_draws=3, seed=5)
    assert np.array_equal(smp.y, again.y) and np.array_equal(smp.config, again.config)
    # a config albedo draw of 1.0 is possible with hi = 1 (ALBEDO_ONE of the draws)
    draws = [ds._draw_albedo(np.random.default_rng(i), 0.3, 1.0) for i in range(200)]
    assert 1.0 in draws and min(draws) >= 0.3 and max(d for d in draws if d < 1) <= 1 - 1e-4
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=root)
    w = tmp_path / "w.npz"
    p = subprocess.run([sys.executable, "scripts/train.py", str(data), str(tmp_path / "run"),
                        "--steps", "3", "--batch", "8", "--eval-every", "3", "--albedo-draws", "2",
                        "--albedo-input", "log1m", "--export", str(w)],
                       cwd=root, capture_output=True, text=True, env=env)
    assert p.returncode == 0, p.stderr
    p = subprocess.run([sys.executable, "scripts/train.py", str(data), str(tmp_path / "ev"),
                        "--evaluate", str(w)], cwd=root, capture_output=True, text=True, env=env)
    assert p.returncode == 0, p.stderr
    assert "albedo [0.999, 1]" in p.stdout
