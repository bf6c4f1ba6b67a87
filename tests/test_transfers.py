"""Host <-> device transfers of a render, counted by the runtime (clvol/runtime.py
``Runtime.transfers``: calls and bytes per direction and label, calls per size).

The budget of the default method (raymarch + network, docs/architecture.md "Device data"):

- the density goes up once per volume (``DeviceMedium.upload``, label "density"); the
  pyramids of the light field, the network and the environment derive from it
  (``DeviceMedium.pyramid``: level 0 resampled on the host, or copied on the device when the
  grid already is that cube), so no other upload has the density's size;
- nothing comes back but the image layers, the network's 4-byte non-finite flag and the
  march's 4-byte count of rays its progress bound stopped (the header's
  ``raymarch.rays_stopped_at_bound``): the F_ms
  lattice is written by the fused kernel straight into the marcher's device lattice, and the
  pyramids' host copies are made only on request;
- a moved camera uploads nothing of the volume; ``set_density`` uploads the new density once.

Sizes are compared as well as labels, so an upload of the density under another name is
seen. The 64^3 cloud is the cube the shipped network reads (base 64): a pyramid built from
the host grid there would upload the density's very bytes a second time.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import clvol
from clvol.runtime import READBACK, UPLOAD, get_runtime
from clvol.volume.generators import generate

ROOT = Path(__file__).resolve().parents[1]
FLAG_BYTES = 4       # the network's non-finite flag (clvol/render/ms/network.py fill_device)
BOUND_BYTES = 4      # the march's count of rays its progress bound stopped (cl/raymarch.cl)


def cloud(resolution=None):
    sc = clvol.load_scene(ROOT / "examples" / "cloud.toml")
    sc = dataclasses.replace(sc, camera=dataclasses.replace(sc.camera, width=32, height=32))
    if resolution is not None:
        sc = dataclasses.replace(sc, volume=dataclasses.replace(sc.volume,
                                                                resolution=resolution))
    return sc


def render(r, **change):
    """(result, transfers of this render alone)."""
    rt = get_runtime()
    before = rt.transfers.copy()
    res = r.render(**change)
    return res, rt.transfers.since(before)


def image_bytes(res) -> int:
    return sum(a.nbytes for a in res.layers.values())


def check_frame(t, res, density_bytes, density_uploads):
    ups = t.labels(UPLOAD)
    assert t.calls(UPLOAD, "density") == density_uploads, ups
    assert t.sizes[UPLOAD, density_bytes] == density_uploads, ups     # under any label
    # nothing read back but the image layers, the non-finite flag and the march's bound
    # count (no lattice, no pyramid)
    assert t.nbytes(READBACK) == image_bytes(res) + FLAG_BYTES + BOUND_BYTES, t.report()
    assert t.calls(READBACK) == len(res.layers) + 2, t.report()
    assert t.calls(READBACK, "network non-finite flag") == 1
    assert t.calls(READBACK, "march bound count") == 1


def test_default_render_uploads_the_density_once_and_reads_back_only_the_image():
    sc = cloud()
    r = clvol.Renderer(sc)
    nbytes = r.grid.density.nbytes
    res, t = render(r)
    assert res.header["raymarch.ms"] == "network" and res.multiple.max() > 0
    check_frame(t, res, nbytes, 1)
    # the light field's and the network's pyramids: level 0 each, on the host's resampling
    assert t.calls(UPLOAD, "pyramid level 0") == 2
    moved = dataclasses.replace(sc.camera, origin=(0.2, 0.15, 1.55))
    res2, t2 = render(r, camera=moved)
    check_frame(t2, res2, nbytes, 0)
    assert t2.calls(UPLOAD, "pyramid level 0") == 0 and r.counts["ms_lattice"] == 2
    assert not np.array_equal(res.total, res2.total)
    # a new density: uploaded once, its pyramids made again from it
    g2 = generate("cloud", seed=2, resolution=96)
    before = get_runtime().transfers.copy()
    r.set_density(g2)
    res3, t3 = render(r)
    t3 = get_runtime().transfers.since(before)
    check_frame(t3, res3, g2.density.nbytes, 1)
    assert t3.calls(UPLOAD, "pyramid level 0") == 2


@pytest.mark.parametrize("light_resolution", [None, 64])
def test_a_grid_that_is_the_pyramid_cube_is_not_uploaded_again(light_resolution):
    """64^3 in a cubic box: the network's pyramid (base 64), and with light_resolution 64 the
    light field's too, take level 0 from the device density (a device copy): the density's
    bytes go up once, and no level 0 goes up for those pyramids."""
    sc = cloud(64)
    opts = {} if light_resolution is None else {"light_resolution": light_resolution}
    r = clvol.Renderer(sc, **opts)
    nbytes = r.grid.density.nbytes
    assert nbytes == 4 * 64 ** 3
    res, t = render(r)
    check_frame(t, res, nbytes, 1)
    assert t.calls(UPLOAD, "pyramid level 0") == (0 if light_resolution else 1)
    before = get_runtime().transfers.copy()
    r.set_density(generate("cloud", seed=5, resolution=64))
    res2, t2 = render(r)
    check_frame(get_runtime().transfers.since(before), res2, nbytes, 1)
