"""The network's out-of-domain fallback rule as a table, just either side of each threshold
(docs/raymarch.md, "Validity domain": mean cosine below -0.8 takes Wrenninge octaves at albedo
>= 0.9 and single scattering below; anything else keeps the network). The expected column is
written from the docs, not from the constants in clvol/render/ms/network.py, so that moving a
threshold fails here.

Also: the lambda of the graded transmittance agrees across the kernel wrapper, the feature
layout and every shipped weight file (the gather and the network must see the same fields).
"""
from __future__ import annotations

from pathlib import Path

import pytest

from clvol.render.ms.network import fallback_for
from clvol.scene import Medium, Phase

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("g, albedo, expected", [
    (-0.79, 0.95, None),          # not backward enough: the network
    (-0.80, 0.95, None),          # the limit itself keeps the network
    (-0.81, 0.95, "wrenninge"),
    (-0.81, 0.91, "wrenninge"),
    (-0.81, 0.90, "wrenninge"),   # the albedo limit itself takes the octaves
    (-0.81, 0.89, "none"),
    (-0.75, 0.50, None),
    (-0.85, 0.85, "none"),
    (-0.95, 0.999, "wrenninge"),
])
def test_fallback_table(g, albedo, expected):
    m = Medium(density_scale=10.0, albedo=(albedo, albedo, albedo), phase=Phase.hg(g))
    assert fallback_for(m) == expected


def test_fallback_reads_the_lowest_non_zero_channel():
    m = Medium(density_scale=10.0, albedo=(0.95, 0.89, 0.0), phase=Phase.hg(-0.85))
    assert fallback_for(m) == "none"                # 0.89 < 0.9; the zero channel is ignored


def test_lambda_agrees_across_wrapper_layout_and_weight_files():
    from clvol.kernels import transmittance
    from clvol.features import layout
    from clvol.features.weights import read_meta
    assert transmittance.DEFAULT_LAMBDA == layout.DEFAULT_LAMBDA == 0.6      # the seed's value
    files = sorted((ROOT / "clvol" / "data" / "weights").glob("*.npz"))
    assert len(files) >= 3
    for f in files:
        assert read_meta(f)["contract"]["lambda"] == pytest.approx(0.6, abs=1e-12), f.name
