"""Image error metrics: test image against a reference, both linear RGB (H, W, 3).

All metrics are computed in float64 and returned as Python floats. Inputs must have the same
shape and be finite (ImageError otherwise, naming which image and how many bad values).

* ``rmse``  = sqrt(mean((t - r)^2)) over every pixel and channel.
* ``relmse`` = mean((t - r)^2 / (r^2 + 0.01)) over every pixel and channel (the 0.01 keeps
  dark pixels from dominating).
* ``psnr`` = 10 log10(peak^2 / MSE) in dB; ``peak`` defaults to the maximum of the reference
  over all pixels and channels. Identical images give ``math.inf`` (Python's json writes it as
  ``Infinity``).
* ``mrpnn_metric``: the metric of MRPNN (Hu et al. 2023), see its docstring; units are percent of
  the 8-bit full scale.
* ``flip``: NVIDIA's FLIP (Andersson et al. 2020, the ``flip-evaluator`` package, an optional
  dependency: ``pip install clvol[quality]``), LDR-FLIP of both images after the MRPNN exposure
  and sRGB curve; see its docstring for why LDR and not HDR-FLIP. In [0, 1], 0 = identical.
"""
from __future__ import annotations

import math

import numpy as np

from .errors import ImageError
from .image import linear_to_srgb, to_srgb8

# Rec. 601 luma weights, as MRPNN uses them (on linear values for the exposure, on 8-bit codes
# for the error).
LUMA = np.array([0.299, 0.587, 0.114])
MRPNN_PERCENTILE = 99.5
MRPNN_TARGET = 0.9


def _pair(test, ref, rgb: bool = False) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(test, dtype=np.float64)
    r = np.asarray(ref, dtype=np.float64)
    if t.shape != r.shape:
        raise ImageError(f"image shapes differ: test {t.shape}, reference {r.shape}")
    if t.size == 0:
        raise ImageError(f"empty images of shape {t.shape}")
    if rgb and (t.ndim != 3 or t.shape[2] != 3):
        raise ImageError(f"expected (H, W, 3) RGB images, got shape {t.shape}")
    for label, a in (("test", t), ("reference", r)):
        bad = int(np.count_nonzero(~np.isfinite(a)))
        if bad:
            raise ImageError(f"{label} image has {bad} non-finite value(s) (NaN/Inf) of {a.size}")
    return t, r


def _mse(t: np.ndarray, r: np.ndarray) -> float:
    return float(np.mean((t - r) ** 2))


def rmse(test, ref) -> float:
    """Root mean squared error over all pixels and channels (units of the images)."""
    t, r = _pair(test, ref)
    return math.sqrt(_mse(t, r))


def relmse(test, ref) -> float:
    """Relative MSE: mean of (t - r)^2 / (r^2 + 0.01) over all pixels and channels."""
    t, r = _pair(test, ref)
    return float(np.mean((t - r) ** 2 / (r * r + 0.01)))


def psnr(test, ref, peak: float | None = None) -> float:
    """Peak signal-to-noise ratio in dB, 10 log10(peak^2 / MSE).

    ``peak`` defaults to the maximum of ``ref`` over all pixels and channels; it must be > 0.
    Returns ``math.inf`` when the images are identical.
    """
    t, r = _pair(test, ref)
    p = float(np.max(r)) if peak is None else float(peak)
    if not (math.isfinite(p) and p > 0.0):
        what = "maximum of the reference" if peak is None else "peak"
        raise ImageError(f"PSNR needs a positive peak; the {what} is {p!r}")
    mse = _mse(t, r)
    if mse == 0.0:
        return math.inf
    return 10.0 * math.log10(p * p / mse)


def mrpnn_exposure(ref) -> float:
    """MRPNN's exposure ``k = 0.9 / P``, P the 99.5th percentile (NumPy's linear interpolation)
    of the reference's linear luminance 0.299 R + 0.587 G + 0.114 B; ImageError if P <= 0."""
    r = np.asarray(ref, dtype=np.float64)
    p = float(np.percentile(r @ LUMA, MRPNN_PERCENTILE))
    if not p > 0.0:
        raise ImageError(
            f"MRPNN metric: the reference's {MRPNN_PERCENTILE}th-percentile luminance is {p!r}; "
            "a black reference cannot set the exposure")
    return MRPNN_TARGET / p


def tonemap_srgb(img, k: float) -> np.ndarray:
    """``k * img`` clamped to [0, 1] and sRGB-encoded (float64, not rounded to 8 bits)."""
    # A huge k may overflow to Inf, which the clamp turns into 1 like any bright value.
    with np.errstate(over="ignore"):
        return linear_to_srgb(np.clip(np.asarray(img, np.float64) * k, 0.0, 1.0))


def mrpnn_metric(test, ref) -> float:
    """MRPNN's error: RMSE x 100 of the luminance of both images tonemapped to 8-bit sRGB.

    1. ``k = 0.9 / P``, with ``P`` the 99.5th percentile (NumPy's default linear interpolation)
       of the reference's linear luminance 0.299 R + 0.587 G + 0.114 B over its pixels.
    2. Both images are multiplied by ``k`` and go through ``to_srgb8`` (clamp to [0, 1],
       IEC 61966-2-1 curve, round half up to 8-bit codes q).
    3. Per pixel ``Y = (0.299 q_R + 0.587 q_G + 0.114 q_B) / 255`` (in [0, 1]).
    4. Result = 100 * sqrt(mean over pixels of (Y_test - Y_ref)^2).

    Units: percent of the 8-bit full scale; one pixel of N off by d codes in every channel
    gives ``100 * d / (255 sqrt(N))``. A reference whose percentile luminance is <= 0 (black)
    has no exposure and raises ImageError.
    """
    t, r = _pair(test, ref, rgb=True)
    k = mrpnn_exposure(r)
    # to_srgb8 clamps to 1 anyway; clamping first keeps a huge k from overflowing to Inf.
    with np.errstate(over="ignore"):
        yt = to_srgb8(np.minimum(t * k, 1.0)).astype(np.float64) @ LUMA / 255.0
        yr = to_srgb8(np.minimum(r * k, 1.0)).astype(np.float64) @ LUMA / 255.0
    return 100.0 * math.sqrt(float(np.mean((yt - yr) ** 2)))


FLIP_MISSING = ("FLIP needs the flip-evaluator package: pip install 'clvol[quality]' "
                "(or pip install flip-evaluator)")


def flip_available() -> bool:
    try:
        import flip_evaluator  # noqa: F401
    except ImportError:
        return False
    return True


def flip(test, ref) -> float:
    """Mean LDR-FLIP error of ``test`` against ``ref`` (linear RGB), in [0, 1].

    Both images are tonemapped the way ``mrpnn_metric`` sees them (the reference's MRPNN
    exposure ``k``, clamp to [0, 1], sRGB curve, no 8-bit rounding) and given to NVIDIA's
    reference implementation (``flip_evaluator.evaluate(ref, test, "LDR")``, default 67 pixels
    per degree). LDR-FLIP and not HDR-FLIP because HDR-FLIP picks its exposure range from the
    reference's median luminance: our renders of a medium on a black background have a median
    of 0, which sends the range up to ~24 stops of over-exposure, where the faint edges and
    reference noise decide the score. One fixed exposure also makes FLIP and the MRPNN error
    describe the same picture. Raises ImageError when flip-evaluator is not installed.
    """
    t, r = _pair(test, ref, rgb=True)
    try:
        import flip_evaluator
    except ImportError:
        raise ImageError(FLIP_MISSING) from None
    k = mrpnn_exposure(r)
    _, mean, _ = flip_evaluator.evaluate(tonemap_srgb(r, k).astype(np.float32),
                                         tonemap_srgb(t, k).astype(np.float32), "LDR",
                                         applyMagma=False)
    return float(mean)


def compare_images(test_rgb, ref_rgb, with_flip: bool | None = None) -> dict[str, float]:
    """The metrics as a JSON-ready dict: rmse, relmse, psnr (dB), mrpnn, and flip.

    ``with_flip``: None = FLIP when flip-evaluator is installed (else the key is left out),
    True = required (ImageError without it), False = never.
    """
    t, r = _pair(test_rgb, ref_rgb, rgb=True)
    out = {
        "rmse": rmse(t, r),
        "relmse": relmse(t, r),
        "psnr": psnr(t, r),
        "mrpnn": mrpnn_metric(t, r),
    }
    if with_flip or (with_flip is None and flip_available()):
        out["flip"] = flip(t, r)
    return out
