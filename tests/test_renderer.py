"""The renderer against images saved before its refactor, and the Renderer API.

Golden images (tests/data/make_goldens.py): the four example scenes (copied to
tests/data/scenes/) at 48^2 through every multiple-scattering source of the ray marcher and
through the path tracer. On the device that made them the images must be bit-identical (the
refactor moves code, it does not change arithmetic). On another device the OpenCL compiler may
contract or reorder float operations differently: there we allow 1e-4 of the image's largest
value per pixel (float32 rounding through a few hundred march steps stays far below that).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parent / "data"
sys.path.insert(0, str(DATA))
import make_goldens as mg  # noqa: E402

from clvol.runtime import get_runtime  # noqa: E402


def _compare(got: dict, want: dict, prefix: str, device: str):
    same_device = device == get_runtime().entry.label
    for key, ref in want.items():
        if not key.startswith(prefix):
            continue
        layer = key[len(prefix):]
        img = got[layer]
        assert img.shape == ref.shape, key
        if same_device:
            np.testing.assert_array_equal(img, ref, err_msg=key)
        else:
            np.testing.assert_allclose(img, ref, rtol=0, atol=1e-4 * max(float(ref.max()), 1e-30),
                                       err_msg=key)


@pytest.fixture(scope="module")
def raymarch_goldens():
    with np.load(DATA / "goldens_raymarch.npz") as z:
        return {k: z[k] for k in z.files}


@pytest.mark.parametrize("ms", list(mg.RAYMARCH_SOURCES))
@pytest.mark.parametrize("name", mg.SCENES)
def test_raymarch_images_match_goldens(raymarch_goldens, name, ms):
    got = mg.render_raymarch_golden(name, ms)
    _compare(got, raymarch_goldens, f"{name}/{ms}/", str(raymarch_goldens["device"]))


@pytest.mark.parametrize("name", mg.SCENES)
def test_pathtrace_images_match_goldens(name):
    with np.load(DATA / "goldens_pathtrace.npz") as z:
        want = {k: z[k] for k in z.files}
    got = mg.render_pathtrace_golden(name)
    _compare(got, want, f"{name}/", str(want["device"]))
