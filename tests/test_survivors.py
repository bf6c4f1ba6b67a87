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
  under continuous motion every cell is refreshed in turn;
- the stochastic source's points on the rays cl/viewdepth.cl marched (reference/viewdepth.py),
  the pyramid's device copy only for a cube (reference/pyramid.py), the labels' chord exact
  where a bin holds only its end exponents, and the view table's bilinear block blend with
  F_ms that differs per block (``--bugs view-jitter-swap pyramid-copy-unchecked chord-width
  block-blend-swap``).
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
    from clvol.volume.grid import DensityGrid
    from clvol.volume.vdb import read_vdb, write_vdb
    rng = np.random.default_rng(3)
    d = (0.1 + rng.random((5, 4, 6))).astype(np.float32)        # (nz, ny, nx)
    lo = np.array([0.35, -1.25, 2.05])
    g = DensityGrid(d, lo, lo + h * np.array([6, 4, 5]))
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


# ----------------------------------------------------------------- the stochastic source's rays

def test_stochastic_points_lie_on_the_rays_the_depth_kernel_marched():
    """--ms stochastic: each block's free-flight point is origin + t d, where d is the block's
    jittered ray as cl/viewdepth.cl places it (reference/viewdepth.py: x = i block + jx block,
    y = j block + jy block, jitter the first three uniforms of Philox stream j bx + i, sample
    draw (reference/rng.py uniform4, docs/conventions.md "Randomness") as (by, bx, 3)) and t
    the free flight along that same ray (the twin's free_flight_depths). Directions within
    1e-5 (float64 host vs float64 twin from one float32 jitter); points within 2e-5 of the
    depth span + 1e-5 (test_viewdepth.py's kernel-vs-twin bound for the depth). Blocks of 4
    pixels on a 26 x 19 image: the x/y jitter swapped moves a ray by up to 4 pixels (0.08
    rad here), and the point by ~0.1 world units, 1000x the bound."""
    from clvol.render.renderer import Renderer
    from reference.viewdepth import free_flight_depths, sample_rays
    from scene_toml import look_at
    d = {"volume": {"generator": "cloud", "seed": 3, "resolution": 24},
         "medium": {"preset": "cloud", "density_scale": 30.0},
         "light": {"direction": [0.6, 0.9, 0.3], "irradiance": [1.5, 1.5, 1.5]},
         "camera": {"origin": [0.0, 0.3, 2.4], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0],
                    "fov_y": 30.0, "width": 26, "height": 19}}
    scene = scene_from_dict(d, "<jitter>")
    seen, frames = [], []

    def query(p, omega):
        seen.append((np.array(p, np.float64), -np.array(omega, np.float64)))
        return np.full((len(p), 3), 0.1)
    r = Renderer(scene, "raymarch", ms="stochastic", view_block=4, view_samples=1, seed=11)
    r.source.query = query
    real = r.source._draw
    r.source._draw = lambda frame, draw: (frames.append(frame), real(frame, draw))[1]
    r.render()
    # a new history draws MIN_SAMPLES at once (one network call); the first draw's points
    # come first (the test checks those: draw 0's jitter)
    from clvol.render.ms.view import MIN_SAMPLES
    assert len(seen) == 1 and len(frames) == MIN_SAMPLES
    pts, dirs = seen[0]
    frame, cam = frames[0], scene.camera
    bx, by = -(-cam.width // 4), -(-cam.height // 4)
    from reference.rng import uniform4
    jitter = uniform4(11, np.arange(bx * by), 0, 0)[:, :3].reshape(by, bx, 3)
    assert np.abs(jitter[..., 0] - jitter[..., 1]).max() > 0.5       # a swap shows
    f, rt, u = look_at(cam.origin, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    tan_half = np.tan(np.radians(cam.fov_y) / 2)
    want_d = sample_rays(f, rt, u, tan_half, cam.width, cam.height, 4, 1, jitter)[:, :, 0]
    g = scene.volume.load()
    depth, _ = free_flight_depths(g.density, g.bbox_min, g.bbox_max, scene.medium.density_scale,
                                  cam.origin, f, rt, u, tan_half, cam.width, cam.height, 4,
                                  2.0 * frame.step, jitter, stop=frame.threshold)
    hit = depth[..., 0] >= 0
    assert hit.sum() >= 6 and len(pts) >= hit.sum(), (hit.sum(), len(pts))
    pts, dirs = pts[:hit.sum()], dirs[:hit.sum()]
    np.testing.assert_allclose(dirs, want_d[hit], rtol=0, atol=1e-5)
    t = depth[hit, 0]
    want_p = np.asarray(cam.origin)[None] + t[:, None] * want_d[hit]
    np.testing.assert_allclose(pts, want_p, rtol=0, atol=2e-5 * max(np.ptp(t), 1.0) + 1e-5)


# ----------------------------------------------------------------- the pyramid's device copy

@pytest.mark.parametrize("bmax", [(1.0, 2.0, 1.5), (1.0, 1.0, 1.0)])
def test_a_base_sized_grid_on_the_device_is_copied_only_when_its_box_is_a_cube(bmax):
    """docs (clvol/kernels/pyramid.py step 3): level 0 is copied on the device from the
    density a DeviceMedium holds only when the grid is already a base^3 *cube*. An 8^3 grid
    in a 1 x 2 x 1.5 box has base^3 voxels but is padded to a cube 2 on a side (its voxels are
    not the cube's): level 0 must be reference/pyramid.py's padded resample, whether the
    density is passed on the device or not (1e-6 of the largest density, tests/test_pyramid.py's
    bound). Copying it unchanged puts medium in the padding (y outside the box) and stretches
    x and z: errors of the order of the density itself. The cubic box is the copy itself."""
    from clvol.kernels.pyramid import build_pyramid
    from clvol.runtime import get_runtime
    from clvol.volume.grid import DensityGrid
    from reference.pyramid import resample_to_cube
    d = (0.2 + np.random.default_rng(4).random((8, 8, 8))).astype(np.float32)
    g = DensityGrid.from_array(d, (0.0, 0.0, 0.0), bmax)
    rt = get_runtime()
    want, cube_min, size = resample_to_cube(d, (0.0, 0.0, 0.0), bmax, 8)
    for density in (None, rt.upload(d)):
        p = build_pyramid(g, 8, rt, density=density)
        np.testing.assert_allclose(p.cube_min, cube_min, rtol=0, atol=1e-12)
        np.testing.assert_allclose(p.level(0), want, rtol=0, atol=1e-6 * want.max())
        if bmax == (1.0, 1.0, 1.0):
            np.testing.assert_array_equal(p.level(0), d)


# ----------------------------------------------------------------- the labels' upper bound

@pytest.mark.parametrize("albedo", [0.3, 0.9, 0.99, 0.999])
def test_the_chord_bound_is_exact_when_a_bin_holds_only_its_end_exponents(albedo):
    """docs/pathtrace.md, "Labels per scattering order": the upper bound of a bin is the chord
    of a^e over the bin's exponents [lo, hi] read at M/S. The chord is tight: a bin whose
    contributions sit only at its two ends (weight p at lo, 1 - p at hi) has exactly that
    chord value, sum p a^lo + (1 - p) a^hi, and one-exponent bins are exact both ways. The
    bins come from the twin's own rule (reference/pathtrace.py order_bin, inverted here by
    scanning e over 1 .. 2^17 - 1); relative bound 1e-12 (float64 sums of 127 terms). Tests that only check
    the bracketing pass a chord over a bin one exponent too wide (still above the sum)."""
    from clvol.training.labels import label_bounds
    from reference.pathtrace import ORDER_BINS, ORDER_TOP_OCTAVE, order_bin
    ends = {}
    for e in range(1, 2 << ORDER_TOP_OCTAVE):          # up to the top octave's last exponent
        b = order_bin(e)
        lo, hi = ends.get(b, (e, e))
        ends[b] = (min(lo, e), max(hi, e))
    assert sorted(ends) == list(range(ORDER_BINS))
    rng = np.random.default_rng(8)
    n = 5
    S, M = np.zeros((n, ORDER_BINS)), np.zeros((n, ORDER_BINS))
    exact = np.zeros(n)
    wide = [b for b, (lo, hi) in ends.items() if hi > lo]
    assert len(wide) > 50
    for q in range(n):
        for b, (lo, hi) in ends.items():
            c_lo, c_hi = rng.random(2) * (1.0 if hi > lo else 0.0) + [0.01, 0.0]
            if q == 0 and b not in wide[:3]:
                c_lo = c_hi = 0.0                  # one query with three wide bins alone
            S[q, b] = c_lo + c_hi
            M[q, b] = c_lo * lo + c_hi * hi
            exact[q] += c_lo * albedo ** lo + c_hi * albedo ** hi
    lower, upper = label_bounds(S, M, albedo)
    np.testing.assert_allclose(upper, exact, rtol=1e-12, atol=0)
    assert np.all(lower <= exact * (1 + 1e-12))
    single = np.zeros_like(S)
    for b, (lo, hi) in ends.items():
        if hi == lo:
            single[:, b] = S[:, b]
    lo1, up1 = label_bounds(single, single * [ends[b][0] for b in range(ORDER_BINS)], albedo)
    np.testing.assert_allclose(lo1, up1, rtol=1e-12, atol=0)


# ----------------------------------------------------------------- the view table's block blend

@pytest.mark.parametrize("ms", ["stochastic", "view"])
def test_each_pixel_blends_its_four_nearest_blocks_bilinearly(ms):
    """cl/raymarch.cl's view table (docs in its header, MS_SOURCE 3): a pixel's knots are the
    bilinear blend of the four nearest non-empty blocks' knots, between block centres
    ((i + 1/2) B), clamped at the image's edge blocks, the weights of empty blocks (depth -1)
    dropped and the rest renormalised. The blocks get different F_ms here (a stand-in query
    F = 0.05 + 0.3 x - 0.2 y + 0.1 z of the world point, blocks of 4 pixels, 26 x 19 pixels),
    and F is constant along each ray (the stochastic source's one knot; for --ms view a
    query of the block only, so every knot of a block has one value): the multiple layer
    is albedo E alpha F_blend(pixel), with F_blend computed here from the table the kernel
    was given. Bound: 2e-5 of the layer's maximum (float32 march; the constant-source test
    measures 1e-5). The blend's x and y weights swapped moves pixels by ~10% of it."""
    from clvol.render.renderer import Renderer
    d = {"volume": {"generator": "cloud", "seed": 3, "resolution": 24},
         "medium": {"preset": "cloud", "density_scale": 30.0},
         "light": {"direction": [0.6, 0.9, 0.3], "irradiance": [1.5, 1.5, 1.5]},
         "camera": {"origin": [0.0, 0.3, 2.4], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0],
                    "fov_y": 30.0, "width": 26, "height": 19}}
    scene = scene_from_dict(d, "<blend>")
    cam = scene.camera
    o = np.asarray(cam.origin, np.float64)
    B = 4
    bx, by = -(-cam.width // B), -(-cam.height // B)

    def f_world(p):
        return 0.05 + 0.3 * p[:, 0] - 0.2 * p[:, 1] + 0.1 * p[:, 2]
    if ms == "stochastic":
        def query(p, omega):
            return f_world(p)[:, None].repeat(3, 1)
        r = Renderer(scene, "raymarch", ms="stochastic", view_block=B, view_samples=1, seed=3)
    else:
        from scene_toml import look_at
        f, rt, u = look_at(cam.origin, (0.0, 0.0, 0.0))
        th = np.tan(np.radians(cam.fov_y) / 2)

        def query(p, omega):
            # the block of the ray through p (image position by the pinhole's definition)
            v = p - o
            x = ((v @ rt) / (v @ f) / (th * cam.width / cam.height) + 1) * cam.width / 2
            y = (1 - (v @ u) / (v @ f) / th) * cam.height / 2
            i = np.clip(np.floor(x / B), 0, bx - 1)
            j = np.clip(np.floor(y / B), 0, by - 1)
            return (0.05 + 0.04 * i + 0.07 * j)[:, None].repeat(3, 1)
        r = Renderer(scene, "raymarch", ms="view", view_block=B, view_knots=3)
    r.source.query = query
    res = r.render()
    table = np.asarray(r.source.table.read(), np.float64)      # what the kernel was given
    table = table.reshape(-1, by, bx, table.shape[-1])
    depth0, F = table[0, ..., 0], table[1, ..., 0]
    if ms == "view":
        assert np.all(np.ptp(table[1], axis=-1)[depth0 >= 0] < 1e-6)     # one value a block
    assert np.ptp(F[depth0 >= 0]) > 0.05
    px = np.arange(cam.width) + 0.5
    py = np.arange(cam.height) + 0.5
    uu = np.clip(px / B - 0.5, 0, bx - 1)
    vv = np.clip(py / B - 0.5, 0, by - 1)
    i0, j0 = np.floor(uu).astype(int), np.floor(vv).astype(int)
    i1, j1 = np.minimum(i0 + 1, bx - 1), np.minimum(j0 + 1, by - 1)
    fu, fv = uu - i0, vv - j0
    want_f = np.zeros((cam.height, cam.width))
    for y in range(cam.height):
        for x in range(cam.width):
            num = den = 0.0
            for jj, ii, w in ((j0[y], i0[x], (1 - fu[x]) * (1 - fv[y])),
                              (j0[y], i1[x], fu[x] * (1 - fv[y])),
                              (j1[y], i0[x], (1 - fu[x]) * fv[y]),
                              (j1[y], i1[x], fu[x] * fv[y])):
                if depth0[jj, ii] >= 0:
                    num, den = num + w * F[jj, ii], den + w
            want_f[y, x] = num / den if den > 0 else 0.0
    alb = np.asarray(scene.medium.albedo)
    want = res.layers["alpha"][..., None] * alb * 1.5 * want_f[..., None]
    got = res.layers["multiple"]
    assert (res.layers["alpha"] > 0.05).sum() > 100
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-5 * np.abs(want).max())
