"""Tests for the planted bugs that survived issue 41's audit (docs/testing.md, "The issue-41
survivors"; replant them with ``python scripts/plant_bugs.py --bugs furnace-any lit-all
blackbody-hot vdb-affine-translation sky-newest-first``).

Each test states its rule from the documentation, not from the code it checks:

- the white furnace (docs/raymarch.md): the escape model replaces the network for the sky
  only at albedo 1 in *every* channel under a uniform sky; every earlier furnace test used
  (1, 1, 1), so ``any`` passed them;
- lit (docs/conventions.md, the pixel integral): the sun scatters toward the camera in every
  channel where albedo * irradiance > 0; one zero channel must not switch the others off;
- the blackbody (docs/conventions.md, "Emission"): rgb(T) recomputed here from the stated
  definition with its own constants and colour-matching fit;
- OpenVDB's AffineMap and UnitaryMap (16 doubles, row vectors: the translation is the last
  row): no fixture wrote one, so dropping the translation passed;
- the network sky's refresh (docs/raymarch.md, --env-ms-per-frame): the oldest cell first, so
  under continuous motion every cell is refreshed in turn.
"""
from __future__ import annotations

import dataclasses
import struct

import numpy as np
import pytest

import clvol
from clvol.scene import scene_from_dict

SCENE = {"volume": {"generator": "sphere", "seed": 1, "resolution": 16},
         "medium": {"density_scale": 30.0, "albedo": 0.9, "phase": {"type": "hg", "g": 0.5}},
         "light": {"direction": [0.4, 0.8, 0.3], "irradiance": [1, 1, 1]},
         "camera": {"origin": [0, 0, 2.5], "target": [0, 0, 0], "up": [0, 1, 0],
                    "fov_y": 30.0, "width": 20, "height": 16}}


def _scene(medium=None, light=None):
    d = {k: dict(v) for k, v in SCENE.items()}
    d["medium"].update(medium or {})
    d["light"].update(light or {})
    return scene_from_dict(d, "<survivors>")


def _plan(scene, **given):
    from clvol.features.weights import weights_domain
    from clvol.render.ms.network import load_network_weights, shipped_weights
    from clvol.render.options import bind
    from clvol.render.plan import VolumeFacts, plan_frame
    domain = weights_domain(load_network_weights(shipped_weights()).meta)
    return plan_frame(scene, bind("raymarch", given), VolumeFacts(scene.volume.load()), domain)


# ----------------------------------------------------------------- the white furnace

@pytest.mark.parametrize("albedo", [(1.0, 0.95, 0.9), (0.9, 1.0, 1.0), (1.0, 1.0, 0.999)])
def test_the_sky_keeps_the_network_unless_every_channel_has_albedo_one(albedo):
    sky = {"environment": [0.3, 0.5, 0.9]}
    p = _plan(_scene({"albedo": list(albedo)}, sky))
    assert p.env_scatter and p.env_ms == "network", (albedo, p.env_ms)
    white = _plan(_scene({"albedo": [1.0, 1.0, 1.0]}, sky))
    assert white.env_ms == "escape"


# ----------------------------------------------------------------- lit with one zero channel

@pytest.mark.parametrize("medium,light", [
    ({"albedo": [0.8, 0.0, 0.8]}, {}),                           # a zero albedo channel
    ({"albedo": 0.8}, {"irradiance": [1.0, 0.0, 1.0]}),           # a zero sun channel
])
def test_one_zero_channel_leaves_the_others_lit(medium, light):
    """Single scattering alone (--ms none) of a sphere lit from above: the channels with
    albedo * irradiance > 0 scatter (their single layer is positive where the sphere is
    seen), the zero channel does not; the plan says lit."""
    scene = _scene(medium, light)
    img = clvol.Renderer(scene, ms="none").render()
    single = img.layers["single"]
    seen = img.alpha > 0.1
    assert seen.sum() > 20
    for c in (0, 2):
        assert single[..., c][seen].min() >= 0 and single[..., c][seen].mean() > 1e-3, c
    assert single[..., 1].max() == 0.0
    assert _plan(scene, ms="none").lit


# ----------------------------------------------------------------- the blackbody

def _rgb_by_definition(T: float) -> np.ndarray:
    """docs/conventions.md "Emission", written out again: Planck's law normalised to 1 at its
    peak wavelength (Wien's displacement b = 2.897771955e-3 m K), against the CIE 1931
    2-degree functions (Wyman, Sloan and Shirley 2013, the multi-lobe fit) over 360..830 nm in
    1 nm steps, divided by the integral of y-bar, then XYZ to linear sRGB (D65), clipped at 0."""
    h, c, k = 6.62607015e-34, 2.99792458e8, 1.380649e-23
    lam = np.arange(360, 831, dtype=np.float64)

    def planck(l_m):
        return 2 * h * c * c / l_m ** 5 / np.expm1(h * c / (l_m * k * T))

    spec = planck(lam * 1e-9) / planck(2.897771955e-3 / T)

    def g(mu, s1, s2):
        return np.exp(-0.5 * ((lam - mu) / np.where(lam < mu, s1, s2)) ** 2)
    xb = 1.056 * g(599.8, 37.9, 31.0) + 0.362 * g(442.0, 16.0, 26.7) - 0.065 * g(501.1, 20.4, 26.2)
    yb = 0.821 * g(568.8, 46.9, 40.5) + 0.286 * g(530.9, 16.3, 31.1)
    zb = 1.217 * g(437.0, 11.8, 36.0) + 0.681 * g(459.0, 26.0, 13.8)
    xyz = np.array([np.sum(spec * xb), np.sum(spec * yb), np.sum(spec * zb)]) / np.sum(yb)
    m = np.array([[3.2404542, -1.5371385, -0.4985314], [-0.9692660, 1.8760108, 0.0415560],
                  [0.0556434, -0.2040259, 1.0572252]])
    return np.maximum(m @ xyz, 0.0)


def test_map_blackbody_gives_the_documented_colour_of_each_temperature():
    """Per channel within 1e-3 of the temperature's largest channel. What the bound covers:
    float32 storage (6e-8 relative) and the table's linear interpolation (4096 entries to
    10,000 K, steps of 2.4 K): measured 5.5e-4 at 800 K (rgb ~ exp(-c/T) curves most
    there), 2e-5 at 1500 K, under 4e-7 from 2856 K up. A temperature 1% high moves the
    colour by 1.2-26% of the largest channel at these temperatures (3.0% at 2856 K): 12x
    the bound or more."""
    from clvol.emission import map_blackbody
    temps = np.array([800.0, 1500.0, 2856.0, 4000.0, 6504.0, 10000.0])
    got = map_blackbody(temps.reshape(1, 2, 3)).reshape(3, -1).T
    for T, rgb in zip(temps, got):
        want = _rgb_by_definition(T)
        np.testing.assert_allclose(rgb, want, rtol=0, atol=1e-3 * want.max(), err_msg=f"{T} K")
    # the check has power: 1% hotter is far outside the bound at 2856 K
    shift = np.abs(_rgb_by_definition(2856.0 * 1.01) - _rgb_by_definition(2856.0))
    assert shift.max() > 20 * 1e-3 * _rgb_by_definition(2856.0).max()


# ----------------------------------------------------------------- vdb affine maps

def _as_affine(data: bytes, h: float, t, kind: str) -> bytes:
    """clvol's .vdb (a UniformScaleTranslateMap: its name, translation, scale and voxel size,
    three cached inverses) rewritten with the same transform as an ``kind`` map: OpenVDB's
    Mat4d, 16 doubles, row vectors (world = [i j k 1] M, the translation in the last row).
    The grid's block and end offsets move by the size change."""
    name = b"UniformScaleTranslateMap"
    start = data.index(struct.pack("<I", len(name)) + name)
    end = start + 4 + len(name) + 6 * 24
    m = np.diag([h, h, h, 1.0])
    m[3, :3] = t
    new = struct.pack("<I", len(kind)) + kind.encode() + struct.pack("<16d", *m.ravel())
    delta = len(new) - (end - start)
    pos = next(p for p in range(len(data) - 24)
               if struct.unpack_from("<q", data, p)[0] == p + 24 and p < start)
    grid_pos, block_pos, end_pos = struct.unpack_from("<3q", data, pos)
    out = bytearray(data[:start] + new + data[end:])
    struct.pack_into("<3q", out, pos, grid_pos, block_pos + delta, end_pos + delta)
    return bytes(out)


@pytest.mark.parametrize("kind,h", [("AffineMap", 0.1), ("UnitaryMap", 1.0)])
def test_affine_and_unitary_maps_keep_their_translation(tmp_path, kind, h):
    from clvol.volume.grid import Grid
    from clvol.volume.vdb import read_vdb, write_vdb
    rng = np.random.default_rng(3)
    d = (0.1 + rng.random((5, 4, 6))).astype(np.float32)        # (nz, ny, nx)
    lo = np.array([0.35, -1.25, 2.05])
    g = Grid(d, lo, lo + h * np.array([6, 4, 5]))
    write_vdb(tmp_path / "st.vdb", g)
    plain = read_vdb(tmp_path / "st.vdb")
    raw = (tmp_path / "st.vdb").read_bytes()
    name = b"UniformScaleTranslateMap"
    t = struct.unpack_from("<3d", raw, raw.index(struct.pack("<I", len(name)) + name) + 4
                           + len(name))                     # the writer's translation
    assert np.all(np.abs(t) > 0.01)                          # dropping it moves the box
    (tmp_path / "aff.vdb").write_bytes(_as_affine(raw, h, t, kind))
    got = read_vdb(tmp_path / "aff.vdb")
    np.testing.assert_array_equal(got.density, plain.density)
    np.testing.assert_allclose(got.bbox_min, plain.bbox_min, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.bbox_max, plain.bbox_max, rtol=0, atol=1e-12)
    # and the box is where the grid was written: clvol's own files keep their dense box in the
    # grid metadata (no border voxel), which the reader takes only where the transform agrees
    np.testing.assert_allclose(got.bbox_min, lo, atol=1e-9)
    np.testing.assert_allclose(got.bbox_max, g.bbox_max, atol=1e-9)


# ----------------------------------------------------------------- the sky's refresh order

def test_the_network_sky_refreshes_the_oldest_cell_under_continuous_motion(monkeypatch):
    """--env-ms-per-frame 1 with the camera moving every frame (the viewer's setting): each
    frame refreshes one cell, the one refreshed longest ago, so three cells go round in turn
    (6 frames: each twice). Newest-first refreshes one cell every frame and the others never."""
    from clvol.render import environment as E
    sky = {"environment": [0.3, 0.5, 0.9], "irradiance": 0.0}
    scene = dataclasses.replace(_scene({"albedo": 0.9}, sky),
                                camera=dataclasses.replace(_scene().camera, width=8, height=8))
    seen = []
    real = E.per_cell_f_ms

    def record(net, direction, *a, **k):
        seen.append(tuple(np.round(np.asarray(direction, np.float64), 9)))
        return real(net, direction, *a, **k)
    monkeypatch.setattr(E, "per_cell_f_ms", record)
    r = clvol.Renderer(scene, env_ms_directions=3, env_ms_per_frame=1)
    r.render()
    seen.clear()
    for i in range(6):
        a = 0.2 * (i + 1)
        cam = dataclasses.replace(scene.camera, origin=(2.5 * np.sin(a), 0.0, 2.5 * np.cos(a)))
        h = r.render(camera=cam).header
        assert h["raymarch.env_ms_cells_evaluated"] == 1
    assert len(seen) == 6 and len(set(seen)) == 3, seen
    assert seen[:3] == seen[3:], seen                  # round robin
