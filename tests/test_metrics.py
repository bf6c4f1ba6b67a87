"""Image metrics on images whose errors are worked out by hand."""
import json
import math
import sys

import numpy as np
import pytest

from clvol.errors import ImageError
from clvol.cli import main
from clvol.image import write_exr
from clvol.metrics import compare_images, flip, mrpnn_metric, psnr, relmse, rmse

H, W = 4, 5
N = H * W

# sRGB code of linear 0.9 (the MRPNN exposure target):
# 1.055 * 0.9**(1/2.4) - 0.055 = 0.954687; * 255 = 243.45 -> 243.
CODE_09 = 243


def const(v, shape=(H, W, 3)):
    return np.full(shape, v, dtype=np.float64)


def test_rmse_constant_images():
    assert rmse(const(1.0), const(0.5)) == 0.5


def test_relmse_constant_images():
    # (1 - 0.5)^2 / (0.5^2 + 0.01) = 0.25 / 0.26
    assert relmse(const(1.0), const(0.5)) == pytest.approx(0.25 / 0.26, rel=1e-14)


def test_relmse_dark_pixels_use_the_0_01_guard():
    ref = const(0.0)
    test = const(0.0)
    test[:2] = 0.1  # half the rows: 0.1^2 / (0 + 0.01) = 1; the rest 0
    assert relmse(test, ref) == pytest.approx(0.5, rel=1e-14)


def test_psnr_known_mse_and_peak():
    ref = const(1.0)
    ref[0, 0, 0] = 2.0           # peak = max of the reference = 2
    test = ref + 0.1             # MSE = 0.01
    assert psnr(test, ref) == pytest.approx(10 * math.log10(4 / 0.01), rel=1e-12)  # 26.02 dB
    assert psnr(test, ref, peak=1.0) == pytest.approx(20.0, rel=1e-12)


def test_psnr_identical_is_infinite_and_black_reference_refused():
    assert psnr(const(0.3), const(0.3)) == math.inf
    with pytest.raises(ImageError, match=r"positive peak; the maximum of the reference is 0\.0"):
        psnr(const(0.1), const(0.0))


def test_mrpnn_identical_is_zero():
    img = np.random.default_rng(5).random((H, W, 3))
    assert mrpnn_metric(img, img) == 0.0


def test_mrpnn_one_black_pixel():
    # Grey reference v: percentile luminance = v, so k*v = 0.9 -> code 243 in every channel.
    ref = const(0.37)
    test = ref.copy()
    test[2, 3] = 0.0             # code 0: luminance differs by 243/255 at one pixel of N
    expected = 100 * (CODE_09 / 255) / math.sqrt(N)
    assert mrpnn_metric(test, ref) == pytest.approx(expected, rel=1e-12)


def test_mrpnn_uses_luminance_weights_and_clamps():
    ref = const(0.37)
    test = ref.copy()
    test[0, 0] = [0.37, 0.0, 0.37]    # only green lost: 0.587 * 243 / 255
    test[1, 4] = [0.37, 0.37, 0.74]   # blue at 2 * 0.9 = 1.8 clamps to 255: 0.114 * 12 / 255
    expected = 100 * math.sqrt(((0.587 * CODE_09) ** 2 + (0.114 * 12) ** 2) / N) / 255
    assert mrpnn_metric(test, ref) == pytest.approx(expected, rel=1e-12)


def test_mrpnn_exposure_from_99_5th_percentile_not_max():
    # 1000 pixels: 999 at luminance 1, one outlier at 100. NumPy's linear 99.5th percentile
    # sits at rank 0.995 * 999 = 994.005 among the sorted values: 1. So k = 0.9, the 999
    # pixels map to code 243 and the outlier clamps to 255. Against a black test image:
    ref = np.ones((1000, 1, 3))
    ref[617] = 100.0
    test = np.zeros_like(ref)
    expected = 100 * math.sqrt((999 * CODE_09**2 + 255**2) / 1000) / 255
    assert mrpnn_metric(test, ref) == pytest.approx(expected, rel=1e-12)


def test_mrpnn_invariant_to_common_scale():
    rng = np.random.default_rng(7)
    ref = rng.random((H, W, 3))
    test = ref * rng.uniform(0.8, 1.2, ref.shape)
    # A power of two scales exactly in floating point, so the 8-bit codes are identical.
    assert mrpnn_metric(8 * test, 8 * ref) == mrpnn_metric(test, ref)
    assert mrpnn_metric(test, ref) > 0


def test_mrpnn_black_reference_refused():
    with pytest.raises(ImageError, match=r"99\.5th-percentile luminance is 0\.0; a black reference"):
        mrpnn_metric(const(0.5), const(0.0))
    # One lit pixel of 1000 is above the percentile (rank 994.005 falls among the zeros):
    # still no exposure.
    ref = np.zeros((1000, 1, 3))
    ref[3] = 1.0
    with pytest.raises(ImageError, match=r"luminance is 0\.0"):
        mrpnn_metric(ref, ref)


def test_shapes_must_match():
    with pytest.raises(ImageError, match=r"test \(4, 5, 3\), reference \(5, 4, 3\)"):
        rmse(const(0.0), const(0.0, (W, H, 3)))
    with pytest.raises(ImageError, match=r"shapes differ"):
        compare_images(const(0.0), const(0.0, (H, W + 1, 3)))


def test_non_finite_refused_naming_the_image():
    bad = const(0.5)
    bad[1, 1, 1] = np.nan
    bad[2, 2, 2] = np.inf
    with pytest.raises(ImageError, match=r"test image has 2 non-finite"):
        rmse(bad, const(0.5))
    with pytest.raises(ImageError, match=r"reference image has 2 non-finite"):
        compare_images(const(0.5), bad)


def test_compare_images_all_four_json_ready():
    ref = const(0.37)
    test = ref.copy()
    test[2, 3] = 0.0
    out = compare_images(test, ref, with_flip=False)
    assert sorted(out) == ["mrpnn", "psnr", "relmse", "rmse"]
    assert all(type(v) is float for v in out.values())
    assert out["rmse"] == pytest.approx(0.37 / math.sqrt(N), rel=1e-12)
    assert out["relmse"] == pytest.approx(0.37**2 / (0.37**2 + 0.01) / N, rel=1e-12)
    assert out["psnr"] == pytest.approx(10 * math.log10(0.37**2 / (0.37**2 / N)), rel=1e-12)
    assert out["mrpnn"] == pytest.approx(100 * (CODE_09 / 255) / math.sqrt(N), rel=1e-12)
    assert json.loads(json.dumps(out)) == out


# --------------------------------------------------------------------------- FLIP

def gradient_image(h=32, w=48):
    """A smooth horizontal ramp with a vertical colour tint: edges and colours FLIP can see."""
    x = np.linspace(0.05, 1.0, w)[None, :, None]
    y = np.linspace(0.5, 1.0, h)[:, None, None]
    return x * y * np.array([1.0, 0.8, 0.6])


def test_flip_identical_is_zero_and_grows_with_the_perturbation():
    pytest.importorskip("flip_evaluator")
    ref = gradient_image()
    assert flip(ref, ref) == 0.0
    small, large = flip(ref * 1.05, ref), flip(ref * 1.5, ref)
    # FLIP is a mean per-pixel error in [0, 1]; a 5% brightening is visible but small,
    # 50% much more so.
    assert 0.0 < small < large <= 1.0
    assert small < 0.1
    # The exposure comes from the reference, so a common power-of-two scale changes nothing.
    assert flip(8 * ref * 1.05, 8 * ref) == small


def test_flip_is_ldr_flip_after_the_mrpnn_exposure():
    flip_evaluator = pytest.importorskip("flip_evaluator")
    # Grey reference 0.37: exposure k = 0.9 / 0.37, so the reference becomes linear 0.9, sRGB
    # 1.055 * 0.9^(1/2.4) - 0.055; one black pixel stays 0. That is what FLIP must be given.
    ref = const(0.37)
    test = ref.copy()
    test[2, 3] = 0.0
    s09 = 1.055 * 0.9 ** (1 / 2.4) - 0.055
    r8 = np.full((H, W, 3), s09, np.float32)
    t8 = r8.copy()
    t8[2, 3] = 0.0
    expected = flip_evaluator.evaluate(r8, t8, "LDR", applyMagma=False)[1]
    assert flip(test, ref) == pytest.approx(expected, rel=1e-6)
    assert expected > 0.0


def test_flip_without_the_package_says_how_to_get_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "flip_evaluator", None)   # import raises ImportError
    with pytest.raises(ImageError, match=r"pip install 'clvol\[quality\]'"):
        flip(const(0.5), const(0.5))
    assert "flip" not in compare_images(const(0.4), const(0.5))


def _write_pair(tmp_path):
    ref = gradient_image().astype(np.float32)
    write_exr(tmp_path / "ref.exr", {"total": ref})
    write_exr(tmp_path / "test.exr", {"total": ref * np.float32(1.2)})
    return tmp_path / "test.exr", tmp_path / "ref.exr"


def test_compare_json_has_flip(tmp_path, capsys):
    pytest.importorskip("flip_evaluator")
    test, ref = _write_pair(tmp_path)
    assert main(["compare", str(test), str(ref), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["flip"] == pytest.approx(flip(read_rgb(test), read_rgb(ref)), rel=1e-12)
    assert 0.0 < out["flip"] < 1.0
    assert main(["compare", str(ref), str(ref), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["flip"] == 0.0


def test_compare_without_flip_still_prints_the_rest(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "flip_evaluator", None)
    test, ref = _write_pair(tmp_path)
    assert main(["compare", str(test), str(ref), "--json"]) == 0
    cap = capsys.readouterr()
    out = json.loads(cap.out)
    assert "flip" not in out and out["rmse"] > 0 and out["mrpnn"] > 0
    assert "pip install 'clvol[quality]'" in cap.err


def read_rgb(path):
    from clvol.image import read_exr
    return read_exr(path).rgb
