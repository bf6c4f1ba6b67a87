"""Procedural generators: registry, determinism, shapes, geometry of the solids, bad parameters."""
import math

import numpy as np
import pytest

from clvol.errors import VolumeError
from clvol.volume.generators import GENERATORS, generate

NAMES = sorted(GENERATORS)
SEEDED = [n for n in NAMES if GENERATORS[n].uses_seed]
FIXED = [n for n in NAMES if not GENERATORS[n].uses_seed]
RES = (20, 12, 16)   # non-cubic (nx, ny, nz)


def test_required_generators_exist():
    assert {"cloud", "smoke", "sphere", "box", "torus", "blob"} <= set(NAMES)
    assert {"cloud", "smoke", "blob"} <= set(SEEDED)


@pytest.mark.parametrize("name", NAMES)
def test_registry_entries_are_well_formed(name):
    info = GENERATORS[name]
    assert info.name == name
    assert info.doc and "\n\n" not in info.doc
    assert info.parameters
    for key, p in info.parameters.items():
        assert p.doc, key
        assert p.lo <= p.default <= p.hi, key
        assert isinstance(p.lo, type(p.default)) or not p.is_int, key


@pytest.mark.parametrize("name", NAMES)
def test_shape_bbox_and_values_non_cubic(name):
    g = generate(name, seed=1, resolution=RES)
    d = g.density
    assert d.shape == (16, 12, 20)
    assert g.resolution == RES
    assert d.dtype == np.float32 and d.flags.c_contiguous
    assert np.isfinite(d).all() and d.min() >= 0
    # Cubic voxels, longest axis (x) spans [-0.5, 0.5].
    np.testing.assert_allclose(g.cell_size, [1 / 20] * 3)
    np.testing.assert_allclose(g.bbox_min, [-0.5, -0.3, -0.4])
    np.testing.assert_allclose(g.bbox_max, [0.5, 0.3, 0.4])


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("seed", [0, 7])
def test_defaults_are_neither_empty_nor_full(name, seed):
    # Default shapes fill a few % to about half of the box and peak at "unit-ish" density.
    d = generate(name, seed=seed, resolution=24).density
    occupied = float(np.mean(d > 0))
    assert 0.02 < occupied < 0.6, occupied
    assert 0.5 <= float(d.max()) <= 2.0
    # Nothing touches the faces of the box for the default shapes (no flat walls).
    for face in (d[0], d[-1], d[:, 0], d[:, -1], d[:, :, 0], d[:, :, -1]):
        assert face.max() < 0.05 * d.max()


@pytest.mark.parametrize("name", SEEDED)
def test_seeded_generators_are_deterministic_and_seed_dependent(name):
    a = generate(name, seed=3, resolution=RES)
    b = generate(name, seed=3, resolution=RES)
    c = generate(name, seed=4, resolution=RES)
    assert np.array_equal(a.density, b.density)          # bit-identical
    diff = np.abs(a.density - c.density).mean()
    assert diff > 0.02 * a.density.mean(), diff           # genuinely different, not a few ulps


@pytest.mark.parametrize("name", FIXED)
def test_unseeded_shapes_ignore_the_seed(name):
    assert np.array_equal(generate(name, 0, RES).density, generate(name, 99, RES).density)


@pytest.mark.parametrize("name", ["cloud", "smoke", "blob"])
@pytest.mark.parametrize("seed", [0, 1])
def test_noise_is_placed_in_world_units(name, seed):
    # The same seed at twice the resolution, averaged back down 2x2x2, is close to the coarse
    # grid; another seed is not. If the noise were laid out in voxels, the doubled grid would
    # look like an unrelated seed and the ratio below would be ~1. Measured: <= 0.55 (cloud,
    # the finest detail), 0.36 (smoke), 0.05 (blob).
    def down(a):
        z, y, x = a.shape
        return a.reshape(z // 2, 2, y // 2, 2, x // 2, 2).mean(axis=(1, 3, 5))
    coarse = generate(name, seed, (16, 12, 20)).density.astype(np.float64)
    fine = down(generate(name, seed, (32, 24, 40)).density.astype(np.float64))
    other = down(generate(name, seed + 10, (32, 24, 40)).density.astype(np.float64))
    ratio = np.sqrt(np.mean((coarse - fine) ** 2) / np.mean((coarse - other) ** 2))
    assert ratio < 0.7, ratio


def _extremes(info):
    """(key, value, extra params) for each parameter at its lo and hi, with the other
    parameters moved where a cross-parameter rule requires it."""
    for key, p in info.parameters.items():
        for v in (p.lo, p.hi):
            extra = {}
            if info.name == "cloud" and key == "top" and v < 0.5:
                extra = {"base": 0.0}
            if info.name == "cloud" and key == "base" and v > 0.5:
                extra = {"top": 1.0}
            if info.name == "box" and key in ("width", "height", "depth") and v < 0.1:
                extra = {"rounding": 0.0}
            if info.name == "box" and key == "rounding" and v > 0.1:
                extra = {"width": 1.0, "height": 1.0, "depth": 1.0}
            yield key, v, extra


@pytest.mark.parametrize("name", NAMES)
def test_every_parameter_at_its_bounds_gives_a_valid_grid(name):
    info = GENERATORS[name]
    for key, v, extra in _extremes(info):
        g = generate(name, seed=2, resolution=(9, 8, 7), **{key: v}, **extra)
        assert np.isfinite(g.density).all() and g.density.min() >= 0, (key, v)


# --------------------------------------------------------------------------- geometry

def _soft_volume(area, s_min, half_width):
    """Volume of {density} for a soft surface: integral of (1 - smoothstep(-h, h, s)) * A(s) ds,
    A(s) the area of the level set at signed distance s (trapezoid rule, 200k steps)."""
    s = np.linspace(s_min, half_width, 200_001)
    t = np.clip((s + half_width) / (2 * half_width), 0, 1)
    f = 1 - t * t * (3 - 2 * t)
    return float(np.trapezoid(f * area(s), s))


def _grid_volume(g):
    return float(g.density.sum(dtype=np.float64)) * float(np.prod(g.cell_size))


def test_sphere_volume_matches_its_soft_surface():
    # Density integrates to the volume of the soft sphere (computed in 1-D above). The
    # remaining error is sampling of the soft edge at voxel centres: measured <= 0.04% at
    # 32^3 over 8 radii; allowed 0.2%. A radius off by one voxel would be ~10% off.
    r, res = 0.3317, 32
    g = generate("sphere", resolution=res, radius=r)
    h = 0.75 / res   # default edge 1.5 voxels
    expected = _soft_volume(lambda s: 4 * math.pi * (r + s) ** 2, -r, h)
    assert _grid_volume(g) == pytest.approx(expected, rel=2e-3)


def test_torus_volume_matches_its_soft_surface():
    # Same idea, A(s) = 4 pi^2 R (r + s). Measured <= 0.12% at 32^3; allowed 0.5%.
    big, small, res = 0.28, 0.1093, 32
    g = generate("torus", resolution=res, major=big, minor=small)
    h = 0.75 / res
    expected = _soft_volume(lambda s: 4 * math.pi ** 2 * big * (small + s), -small, h)
    assert _grid_volume(g) == pytest.approx(expected, rel=5e-3)


def test_sphere_soft_edge_is_about_one_voxel():
    res, r, edge = 31, 0.3, 1.5
    g = generate("sphere", resolution=res, radius=r, edge=edge)
    z, y, x = np.meshgrid(g.voxel_centers(2), g.voxel_centers(1), g.voxel_centers(0), indexing="ij")
    dist = (np.sqrt(x * x + y * y + z * z) - r) * res      # signed distance in voxels
    d = g.density
    assert np.all(d[dist < -edge / 2] == 1.0)
    assert np.all(d[dist > edge / 2] == 0.0)
    ramp = d[np.abs(dist) < edge / 2 - 0.05]
    assert ramp.size > 0 and np.all((ramp > 0) & (ramp < 1))
    # smoothstep is symmetric: density 1/2 exactly on the surface
    near = np.abs(dist) < 0.02
    np.testing.assert_allclose(d[near], 0.5 - 0.75 * dist[near] / (edge / 2), atol=1e-3)


def test_box_sides_follow_width_height_depth_on_their_axes():
    # Walk outward from the centre along each axis and find where density crosses 1/2
    # (linear interpolation between voxel centres): it must be at width/2, height/2, depth/2.
    # Interpolating a sampled smoothstep misplaces the crossing by <= 0.08 voxel (measured
    # over 10 sizes); allowed 0.15 voxel. A swapped axis would be several voxels off.
    res = (33, 31, 29)
    w, h, dep = 0.54, 0.37, 0.6
    g = generate("box", resolution=res, width=w, height=h, depth=dep, rounding=0.02)
    d = g.density
    nz, ny, nx = d.shape
    vox = g.cell_size[0]

    def crossing(profile, centres):
        i = int(np.flatnonzero(profile >= 0.5).max())
        f0, f1 = float(profile[i]), float(profile[i + 1])
        return centres[i] + (f0 - 0.5) / (f0 - f1) * (centres[i + 1] - centres[i])

    assert abs(crossing(d[nz // 2, ny // 2, :], g.voxel_centers(0)) - w / 2) < 0.15 * vox
    assert abs(crossing(d[nz // 2, :, nx // 2], g.voxel_centers(1)) - h / 2) < 0.15 * vox
    assert abs(crossing(d[:, ny // 2, nx // 2], g.voxel_centers(2)) - dep / 2) < 0.15 * vox


def test_torus_lies_in_the_xz_plane():
    g = generate("torus", resolution=(32, 16, 32), major=0.3, minor=0.08)
    d = g.density
    # Through the hole (the y axis) there is nothing; on the ring at x = 0.3 there is.
    ix = np.argmin(np.abs(g.voxel_centers(0) - 0.3))
    assert d[:, :, 15:17][15:17].max() == 0.0
    assert d[15:17, :, ix].max() == 1.0


def test_cloud_has_a_flat_base_at_its_base_height():
    base, res = 0.3, 40
    g = generate("cloud", seed=0, resolution=res, base=base, top=0.95)
    d = g.density
    rows = d.max(axis=(0, 2))                                # max over x, z per y layer
    frac_y = (np.arange(res) + 0.5) / res
    assert rows[frac_y < base].max() == 0.0                  # nothing below the base
    lowest = int(np.flatnonzero(rows > 0).min())
    assert frac_y[lowest] - base < 2.0 / res                 # starts within 2 voxels of it
    # Flat: two voxels above the base, the layer is already widely covered.
    layer = d[:, lowest + 2, :]
    assert np.mean(layer > 0.5) > 0.25


def test_smoke_widens_with_height():
    g = generate("smoke", seed=0, resolution=32)
    d = g.density.astype(np.float64)
    x = g.voxel_centers(0)[None, None, :]
    z = g.voxel_centers(2)[:, None, None]
    r2 = x * x + z * z

    def rms_radius(y0, y1):
        sl = d[:, y0:y1, :]
        return math.sqrt(float((sl * r2[:, :, :]).sum() / sl.sum()))
    low, high = rms_radius(3, 10), rms_radius(20, 28)
    assert high > 1.5 * low, (low, high)


def test_cloud_at_128_is_sane():
    # The one larger run: a production-size grid generates and stays well formed.
    g = generate("cloud", seed=11, resolution=128)
    d = g.density
    assert d.shape == (128, 128, 128)
    assert np.isfinite(d).all() and d.min() >= 0 and d.max() == pytest.approx(1.0)
    assert 0.05 < float(np.mean(d > 0)) < 0.5


# --------------------------------------------------------------------------- bad input

@pytest.mark.parametrize("call, fragments", [
    (lambda: generate("clowd"), ["unknown generator 'clowd'", "cloud", "smoke", "sphere"]),
    (lambda: generate("cloud", coverge=0.5), ["unknown parameter(s) coverge", "coverage [0.0, 1.0]"]),
    (lambda: generate("cloud", coverage=1.5), ["coverage = 1.5", "out of range [0.0, 1.0]"]),
    (lambda: generate("cloud", coverage=float("nan")), ["coverage = nan", "out of range"]),
    (lambda: generate("cloud", octaves=2.5), ["octaves = 2.5", "integer", "[1, 8]"]),
    (lambda: generate("cloud", octaves=9), ["octaves = 9", "out of range [1, 8]"]),
    (lambda: generate("cloud", coverage=True), ["coverage = True", "must be a number"]),
    (lambda: generate("sphere", radius="big"), ["radius = 'big'", "must be a number"]),
    (lambda: generate("cloud", base=0.6, top=0.65), ["top = 0.65", "base + 0.1"]),
    (lambda: generate("box", width=0.1, rounding=0.2), ["rounding = 0.2", "half the smallest side"]),
    (lambda: generate("cloud", seed=-1), ["seed", ">= 0", "-1"]),
    (lambda: generate("cloud", seed=1.5), ["seed", "1.5"]),
    (lambda: generate("cloud", resolution=0), ["resolution (0, 0, 0)", "[1, 2048]"]),
    (lambda: generate("cloud", resolution=(8, 8)), ["resolution", "(8, 8)"]),
    (lambda: generate("cloud", resolution=16.0), ["resolution", "16.0"]),
    (lambda: generate("cloud", resolution=(1024, 1024, 1024)), ["1073741824 voxels", "limit"]),
])
def test_bad_arguments_are_rejected_with_a_clear_message(call, fragments):
    with pytest.raises(VolumeError) as err:
        call()
    msg = str(err.value)
    for frag in fragments:
        assert frag in msg, f"{frag!r} not in {msg!r}"


def test_integral_valued_float_is_accepted_for_an_int_parameter():
    # JSON/TOML may give 3.0 for an integer; it is exactly an integer, so it is accepted.
    a = generate("cloud", resolution=8, octaves=3.0)
    b = generate("cloud", resolution=8, octaves=3)
    assert np.array_equal(a.density, b.density)


@pytest.mark.parametrize("name", NAMES)
def test_docs_list_every_parameter_with_its_default_and_range(name):
    # docs/volumes.md has one section per generator with a row per parameter; keep them in sync.
    from pathlib import Path
    text = (Path(__file__).resolve().parents[1] / "docs" / "volumes.md").read_text()
    section = text.split(f"### `{name}`", 1)[1].split("\n### ", 1)[0]
    for key, p in GENERATORS[name].parameters.items():
        assert f"| `{key}` | {p.default} | [{p.lo}, {p.hi}] |" in section, key
