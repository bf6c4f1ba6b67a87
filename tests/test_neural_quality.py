"""The quality benchmark's own logic (bench/neural_quality.py): noise-floor removal on synthetic
images whose answer is known, the reference cache key, the target check, and a tiny end-to-end
run (two 16^3 scenes at 16x16 pixels, 8-spp references) that must give the whole table."""
import csv
import importlib.util
import json
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from clvol.metrics import LUMA, mrpnn_exposure, tonemap_srgb

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def nq():
    sys.path.insert(0, str(ROOT / "bench"))   # the benchmark imports bench/_common.py
    try:
        spec = importlib.util.spec_from_file_location("neural_quality",
                                                      ROOT / "bench" / "neural_quality.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        yield mod
    finally:
        sys.path.remove(str(ROOT / "bench"))


def synthetic(seed, sigma, bias=1.03, h=64, w=64):
    """A grey ramp mu in [0.2, 0.5], two half-references mu + N(0, sigma^2) per pixel and
    channel, and a noise-free test image mu * bias."""
    rng = np.random.default_rng(seed)
    mu = np.broadcast_to(np.linspace(0.2, 0.5, w)[None, :, None], (h, w, 3)).copy()
    h1 = mu + sigma * rng.standard_normal(mu.shape)
    h2 = mu + sigma * rng.standard_normal(mu.shape)
    return mu, h1, h2, mu * bias


def test_noise_floor_matches_its_known_value(nq):
    # Reference R = (h1 + h2) / 2 has per-channel noise variance sigma^2 / 2. Its tonemapped
    # luminance Y = sum_c LUMA_c s(k x_c) (s the sRGB curve) then has, to first order,
    # Var Y = sum_c LUMA_c^2 (k s'(k mu))^2 sigma^2 / 2 with s'(x) = 1.055 / 2.4 x^(1/2.4 - 1).
    mu, h1, h2, _ = synthetic(1, sigma=0.004)
    k = mrpnn_exposure(0.5 * (h1 + h2))
    ds = 1.055 / 2.4 * (k * mu[..., 0]) ** (1 / 2.4 - 1)
    var_y = np.sum(LUMA**2) * (k * ds) ** 2 * 0.004**2 / 2
    expected = 100 * math.sqrt(np.mean(var_y))
    got = nq.scores(mu, h1, h2, with_flip=False)["ref_floor_rmse100"]
    # The estimate is a mean over 4096 pixels of a scaled chi-square(1)-like term: relative
    # standard deviation sqrt(2 / 4096) = 2.2% in the MSE, 1.1% in its square root; the
    # linearisation error is (sigma / (k mu))^2 < 0.1%. 5% is > 4 standard deviations.
    assert got == pytest.approx(expected, rel=0.05)


def test_noise_is_removed_from_the_rmse(nq):
    # The reference noise is about as large as the test's real error, so the uncorrected RMSE
    # is visibly too high while the corrected one recovers the true error against mu.
    mu, h1, h2, test = synthetic(2, sigma=0.015)
    k = mrpnn_exposure(0.5 * (h1 + h2))
    true = 100 * math.sqrt(np.mean((tonemap_srgb(test, k) @ LUMA - tonemap_srgb(mu, k) @ LUMA) ** 2))
    s = nq.scores(test, h1, h2, with_flip=False)
    assert s["rmse100_raw"] > 1.15 * true            # the set-up makes the noise matter
    # Estimate's relative standard deviation in the MSE ~ sqrt(4 d^2 v + 4 v^2) / (d^2 sqrt(N))
    # with v / d^2 ~ 0.5 and N = 4096: ~2.7%, ~1.4% in the RMSE. 7% is 5 standard deviations.
    assert s["rmse100"] == pytest.approx(true, rel=0.07)
    assert s["mean"] == pytest.approx(1.03 * mu.mean() / (0.5 * (h1 + h2)).mean(), rel=1e-12)


def test_test_image_noise_is_removed_when_made_twice(nq):
    # pt_view: a noisy test made twice with independent noise. Both noises are about as large
    # as the test's bias; the corrected RMSE of the mean recovers the bias alone.
    mu, h1, h2, test = synthetic(3, sigma=0.015)
    rng = np.random.default_rng(4)
    t1 = test + 0.02 * rng.standard_normal(mu.shape)
    t2 = test + 0.02 * rng.standard_normal(mu.shape)
    k = mrpnn_exposure(0.5 * (h1 + h2))
    true = 100 * math.sqrt(np.mean((tonemap_srgb(test, k) @ LUMA - tonemap_srgb(mu, k) @ LUMA) ** 2))
    plain = nq.scores(0.5 * (t1 + t2), h1, h2, with_flip=False)
    s = nq.scores(0.5 * (t1 + t2), h1, h2, with_flip=False, test_halves=(t1, t2))
    assert plain["rmse100"] > 1.15 * true            # the test's noise matters here
    # As above, with the test's noise variance added to the reference's (v / d^2 ~ 1.3):
    # ~2% relative standard deviation in the RMSE; 10% is 5 of them.
    assert s["rmse100"] == pytest.approx(true, rel=0.10)


def test_noise_is_removed_from_the_relmse(nq):
    # relMSE's numerator is linear in the images, so the correction is exact for it; the
    # noisy reference in the denominator leaves a second-order bias of relative size
    # ~ 4 k^2 Var R / (0.03 ((k mu)^2 + 0.01)) ~ 3% here (see scores), plus ~1.5% of
    # statistical scatter; 8% covers both. Uncorrected, the noise adds ~20%.
    mu, h1, h2, test = synthetic(4, sigma=0.006)
    r = 0.5 * (h1 + h2)
    k = mrpnn_exposure(r)
    true = np.mean((k * mu * 0.03) ** 2 / ((k * mu) ** 2 + 0.01))
    raw = np.mean(k * k * (test - r) ** 2 / ((k * r) ** 2 + 0.01))
    assert raw > 1.15 * true
    assert nq.scores(test, h1, h2, with_flip=False)["relmse"] == pytest.approx(true, rel=0.08)


def test_noise_correction_clamps_at_zero(nq):
    mu, h1, h2, _ = synthetic(3, sigma=0.01)
    s = nq.scores(mu, h1, h2, with_flip=False)      # the test image is the truth itself
    assert s["rmse100"] < 0.3 * s["ref_floor_rmse100"] and s["relmse"] >= 0.0


def test_cache_key_changes_with_the_scene_and_settings(nq):
    scene = nq.bench_scene(ROOT / "examples" / "smoke.toml", 16)
    scene = scene.with_overrides({"volume.resolution": 8})
    grid = scene.volume.load()
    key = nq.reference_key(scene, grid, 64, code="c")
    assert key == nq.reference_key(scene, grid, 64, code="c")
    variants = {
        "density scale": scene.with_overrides({"medium.density_scale": 31.0}),
        "light": scene.with_overrides({"light.direction": [0.0, 1.0, 0.0]}),
        "camera size": replace(scene, camera=replace(scene.camera, width=17)),
        "phase": scene.with_overrides({"medium.phase": {"type": "hg", "g": 0.2}}),
    }
    for what, other in variants.items():
        assert nq.reference_key(other, grid, 64, code="c") != key, what
    reseeded = scene.with_overrides({"volume.seed": 5})
    assert nq.reference_key(reseeded, reseeded.volume.load(), 64, code="c") != key
    denser = replace(grid, density=grid.density * np.float32(2))   # same scene, other bytes
    assert nq.reference_key(scene, denser, 64, code="c") != key
    assert nq.reference_key(scene, grid, 32, code="c") != key
    assert nq.reference_key(scene, grid, 64, seeds=(1, 2), code="c") != key
    assert nq.reference_key(scene, grid, 64, code="d") != key      # path tracer code changed
    assert len(nq.code_hash()) == 64


def test_target_check_names_the_failing_scene(nq):
    def row(scene, method, rmse, rel=0.001, fl=0.01):
        return {"scene": scene, "method": method, "rmse100": rmse, "relmse": rel, "flip": fl}
    rows = [row("a", "network", 0.5), row("a", "wrenninge", 3.0), row("a", "single", 9.0),
            row("a", "pt_equal", 2.0),
            row("b", "network", 0.9, fl=0.07), row("b", "wrenninge", 0.8), row("b", "single", 9.0),
            row("b", "pt_equal", 2.0)]
    got = {c: (ok, d) for c, ok, d in nq.check_target(rows)}
    assert got["worst rmse100 <= 1"][0] and got["worst relmse <= 0.01"][0]
    assert not got["worst flip <= 0.05"][0] and "(b)" in got["worst flip <= 0.05"][1]
    ok, detail = got["network rmse100 <= best baseline on every scene"]
    assert not ok and detail == "b: 0.9 > wrenninge 0.8"


TINY = """
[volume]
generator = "{gen}"
seed = 1
resolution = 16
[medium]
density_scale = 20.0
albedo = {albedo}
phase = {{ type = "hg", g = 0.857 }}
[light]
direction = [0.6, 0.9, 0.3]
[camera]
origin = [0.0, 0.3, 2.4]
target = [0.0, 0.0, 0.0]
fov_y = 35.0
width = 256
height = 256
"""


@pytest.mark.slow
def test_tiny_run_writes_the_whole_table(nq, tmp_path, capsys):
    pytest.importorskip("flip_evaluator")
    scenes = []
    for gen, albedo in (("sphere", "0.95"), ("blob", "[0.8, 0.95, 0.9]")):
        p = tmp_path / f"{gen}.toml"
        p.write_text(TINY.format(gen=gen, albedo=albedo))
        scenes.append(str(p))
    argv = ["--scenes", *scenes, "--size", "16", "--ref-spp", "8", "--repeats", "1",
            "--cache", str(tmp_path / "cache")]
    assert nq.main(argv + ["--out", str(tmp_path / "t.csv")]) == 0
    out = capsys.readouterr().out
    with open(tmp_path / "t.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["scene"], r["method"]) for r in rows] == [
        (s, m) for s in ("sphere", "blob") for m in nq.METHODS]
    assert list(rows[0]) == list(nq.COLUMNS)
    for r in rows:
        for col in ("rmse100", "relmse", "flip", "mean", "seconds", "ref_floor_rmse100",
                    "ref_halves_flip"):
            assert math.isfinite(float(r[col])) and float(r[col]) >= 0, (r["method"], col)
        assert (r["spp"] != "") == (r["method"] == "pt_equal")
    assert sum(line.startswith(("PASS ", "FAIL ")) for line in out.splitlines()) == 4
    # Both references were made once and are read back, not re-rendered, on a second run.
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 2
    assert nq.main(argv + ["--refs-only"]) == 0
    out = capsys.readouterr().out
    assert out.count("cached") == 2 and "half 1/2" not in out
    # An interrupted build: one scene's file gone, its first half kept. Only half 2 is
    # rendered, and the scene's file comes back with the same first half.
    final = sorted((tmp_path / "cache").glob("sphere_*.npz"))[0]
    (h1, h2), meta = nq.load_reference(final, json.loads(str(np.load(final)["meta"]))["key"])
    nq._save_npz(final.with_name(final.stem + ".half1.npz"), h=h1,
                 meta=np.array(json.dumps({"key": meta["key"], "seconds": 1.0})))
    final.unlink()
    assert nq.main(argv + ["--refs-only"]) == 0
    out = capsys.readouterr().out
    assert "sphere: half 1/2 from" in out and "sphere: half 2/2, 4 spp" in out
    assert out.count("cached") == 1
    (again, _), _ = nq.load_reference(final, meta["key"])
    assert np.array_equal(again, h1) and not list((tmp_path / "cache").glob("*.half*.npz"))
    assert nq.main(argv + ["--out", str(tmp_path / "t.txt")]) == 2   # refused, one line


def test_pt_lattice_row_is_the_lattice_filled_by_point_queries(nq, tmp_path, capsys):
    """--pt-lattice N adds a row per scene whose image is the march over the F_ms lattice that
    the path tracer's point queries filled (not a baseline: the target check ignores it), and a
    negative count is refused."""
    pytest.importorskip("flip_evaluator")
    p = tmp_path / "sphere.toml"
    p.write_text(TINY.format(gen="sphere", albedo="0.95"))
    argv = ["--scenes", str(p), "--size", "16", "--ref-spp", "8", "--repeats", "1",
            "--cache", str(tmp_path / "cache"), "--ms-resolution", "8"]
    assert nq.main(argv + ["--pt-lattice", "-1"]) == 2
    assert nq.main(argv + ["--pt-lattice", "16", "--out", str(tmp_path / "t.csv")]) == 0
    with open(tmp_path / "t.csv", newline="") as fh:
        rows = {r["method"]: r for r in csv.DictReader(fh)}
    assert set(rows) == set(nq.METHODS) | {"pt_lattice"}
    lat = rows["pt_lattice"]
    assert lat["spp"] == "16" and math.isfinite(float(lat["rmse100"]))
    # the lattice's multiple scattering reaches the image: it differs from single scattering
    assert float(lat["mean"]) > float(rows["single"]["mean"])
