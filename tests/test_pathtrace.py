"""cl/pathtrace.cl against reference/pathtrace.py, exact cases, specialisation and the API.

How the tests decide (tolerances and why):
- Same random stream, path by path: the kernel built with a global majorant (block >= grid)
  makes the twin's decisions; per path the counters (vertices, tracking steps, truncation)
  must be equal and every output within 1e-4 relative + 1e-6 absolute (float32 kernel vs
  float64 twin: a few hundred float32 operations per path, ~1e-6 relative each). A path
  may diverge when a uniform falls within rounding of a threshold (~1e-7 per decision),
  so we require >= 97% of paths to agree; a 1% bias injected into the kernel (-D
  PT_TEST_BIAS) must fail it on every path
  that receives sun light (power check).
- Statistical, independent streams: z = |mean_a - mean_b| / sqrt(se_a^2 + se_b^2) < 4.0
  (about 20 comparisons in this file: family-wise false alarm ~1e-3); standard errors from
  per-pixel sample variances of >= 2048 spp (see the twin test for its 16-spp side).
- White furnace, missed rays, empty grid, albedo 0: exact per path (no tolerance): with
  albedo 1 the throughput is exactly 1 and each path adds the environment exactly once.
"""
import numpy as np
import pytest

from clvol.errors import ClvolError
from clvol.kernels.pathtrace import (ROW_BG, ROW_L1, ROW_LMS, ROW_STEPS, ROW_TRUNCATED,
                                     ROW_VERTICES, PathMedium, PathTracer)
from clvol.scene import Camera
from reference import pathtrace as rpt
from reference.phase import phase_eval
from media import light_of, medium_of
from scene_toml import CAMERA, write_scene

BMIN = np.array([-0.5, -0.4, -0.5])
BMAX = np.array([0.5, 0.5, 0.6])
CAM = Camera((0.15, 0.1, 2.2), (0, 0, 0.05), (0, 1, 0), 34.0, 8, 8)
SKIN = [(0.8, 0.5), (0.3, 0.3), (-0.3, 0.2)]


def _unit(v):
    v = np.asarray(v, np.float64)
    return tuple(v / np.linalg.norm(v))


def _smooth(shape=(6, 5, 7), seed=0):
    return (0.2 + np.random.default_rng(seed).random(shape)).astype(np.float32)


def _spiky(shape=(9, 8, 7), seed=1, p=0.05, peak=50.0):
    rs = np.random.default_rng(seed)
    return np.where(rs.random(shape) < p, peak, 0.02).astype(np.float32)


def make_medium(density=None, scale=3.0, albedo=(0.9, 0.9, 0.9), lobes=(), light=(0.3, 0.8, 0.5),
                sun=(1.0, 1.0, 1.0), env=None, max_order=None, env_map=None,
                env_scale=(1.0, 1.0, 1.0), env_rotation=0.0, **extra):
    density = _smooth() if density is None else density
    return PathMedium(density=density, bbox_min=BMIN, bbox_max=BMAX,
                  medium=medium_of(scale, albedo, lobes), light=light_of(_unit(light), sun),
                  environment=env, max_order=max_order, extra_defines=dict(extra),
                  env_map=env_map, env_scale=tuple(env_scale), env_rotation=env_rotation)


def twin(med: PathMedium) -> rpt.Params:
    return rpt.Params(density=med.density, bbox_min=med.bbox_min, bbox_max=med.bbox_max,
                      medium=med.medium,
                      light=med.light, environment=med.environment,
                      max_order=med.max_order or 0, env_map=med.env_map,
                      env_scale=med.env_scale, env_rotation=med.env_rotation)


def _sky_16x8(seed=5):
    """A 16 x 8 map with distinct texels per channel (tests/test_envmap.py has more)."""
    rs = np.random.default_rng(seed)
    return (0.2 + rs.random((8, 16, 3)) * np.array([1.0, 0.6, 1.8])).astype(np.float32)


def agreement(k, r, rtol=1e-4, atol=1e-6) -> float:
    """Fraction of paths on which kernel rows k and twin rows r agree (see module doc)."""
    counters = np.all(k[..., 9:] == r[..., 9:], axis=-1)
    close = np.all(np.abs(k[..., :9] - r[..., :9]) <= atol + rtol * np.abs(r[..., :9]), axis=-1)
    return float(np.mean(counters & close))


# ------------------------------------------------------------------ same stream, path by path

SAME_STREAM = {
    "iso-grey": dict(lobes=[], albedo=(0.9, 0.9, 0.9)),
    "hg-rgb-env": dict(lobes=[(0.8, 1.0)], albedo=(0.95, 0.7, 0.4), env=(0.2, 0.3, 0.5)),
    "mhg3-order2": dict(lobes=SKIN, albedo=(0.99, 0.85, 0.75), max_order=2),
    "hg-back-single": dict(lobes=[(-0.5, 1.0)], max_order=1, env=(0.1, 0.1, 0.1)),
    "spiky-milk": dict(density=_spiky(), scale=1.0, lobes=[(0.8, 0.7), (-0.3, 0.3)],
                       albedo=(0.999, 0.999, 0.999)),
    "hg-rgb-envmap": dict(lobes=[(0.7, 1.0)], albedo=(0.95, 0.7, 0.4), env_map=_sky_16x8(),
                          env_scale=(1.0, 2.0, 0.5), env_rotation=37.0),
}


@pytest.mark.parametrize("name", SAME_STREAM)
def test_render_same_stream_matches_twin_path_by_path(name):
    med = make_medium(**SAME_STREAM[name])
    k = PathTracer(med, majorant_block=0).render_batch(CAM, seed=7, sample0=3, spl=2)
    r = rpt.render_paths(twin(med), CAM, seed=7, samples=[3, 4])
    assert np.count_nonzero(r[..., ROW_VERTICES]) > 40  # most paths do scatter
    assert agreement(k, r) >= 0.97


def test_query_same_stream_matches_twin_path_by_path():
    med = make_medium(lobes=[(0.6, 0.8), (-0.2, 0.2)], albedo=(0.92, 0.99, 0.94))
    rs = np.random.default_rng(3)
    p = rs.uniform(BMIN - 0.2, BMAX + 0.2, size=(24, 3))   # some outside the box
    w = rs.normal(size=(24, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    rt_pt = PathTracer(med, majorant_block=0)
    k = rt_pt.query_batch(rt_pt.rt.to_device(p.astype(np.float32)),
                          rt_pt.rt.to_device(w.astype(np.float32)), 24, seed=2, sample0=0, ppl=4)
    # The twin starts from the float32 positions the kernel sees.
    r = rpt.query_paths(twin(med), p.astype(np.float32), w.astype(np.float32), seed=2,
                        samples=range(4))
    assert agreement(k, r) >= 0.97


def test_injected_one_percent_bias_fails_the_same_stream_comparison():
    med = make_medium(lobes=[(0.5, 1.0)], PT_TEST_BIAS=1.01)
    k = PathTracer(med, majorant_block=0).render_batch(CAM, seed=7, sample0=0, spl=2)
    r = rpt.render_paths(twin(med), CAM, seed=7, samples=[0, 1])
    lit = np.any(r[..., ROW_L1] + r[..., ROW_LMS] > 0, axis=-1)
    assert lit.mean() > 0.4
    # Every lit path (one receiving sun light) must be flagged, not only most of them.
    assert agreement(k, r) <= 1.0 - lit.mean() + 0.01
    assert agreement(k, r) < 0.97
    # ... and the unbiased build passes on the very same paths.
    unbiased = PathTracer(make_medium(lobes=[(0.5, 1.0)]), majorant_block=0)
    assert agreement(unbiased.render_batch(CAM, seed=7, sample0=0, spl=2), r) >= 0.97


# ------------------------------------------------------------------ statistical, independent streams

def _image_mean_and_se(rows):
    """Mean over pixels and samples of each of total, single, multiple, with its standard
    error from the per-pixel sample variances (pixels differ in distribution)."""
    parts = {"total": rows[..., ROW_BG] + rows[..., ROW_L1] + rows[..., ROW_LMS],
             "single": rows[..., ROW_L1], "multiple": rows[..., ROW_LMS]}
    out = {}
    spp, npix = rows.shape[:2]
    for key, v in parts.items():
        v = v.astype(np.float64)
        mean = v.mean(axis=(0, 1))
        se = np.sqrt(v.var(axis=0, ddof=1).sum(axis=0) / (npix * npix * spp))
        out[key] = (mean, se)
    return out


def _z(a, b):
    (ma, sa), (mb, sb) = a, b
    return np.abs(ma - mb) / np.sqrt(sa ** 2 + sb ** 2 + 1e-300)


STATISTICAL = {
    "hg-rgb-env-grid": dict(lobes=[(0.7, 1.0)], albedo=(0.9, 0.7, 0.5), env=(0.3, 0.2, 0.1)),
    "mhg2-order2-grid": dict(lobes=[(0.8, 0.7), (-0.3, 0.3)], max_order=2, albedo=(0.8, 0.85, 0.9)),
    "iso-spiky-grid": dict(density=_spiky(), scale=1.0, lobes=[]),
    "mhg3-single-env-grid": dict(lobes=SKIN, max_order=1, albedo=(0.99, 0.85, 0.75), env=(0.2, 0.2, 0.3)),
}
SMALL_CAM = Camera((0.1, 0.05, 2.0), (0, 0, 0.05), (0, 1, 0), 22.0, 4, 4)


@pytest.mark.parametrize("name", STATISTICAL)
def test_kernel_with_majorant_grid_matches_twin_statistically(name):
    """Kernel (majorant grid, block 2, its own seed) against the twin (global majorant)."""
    med = make_medium(**STATISTICAL[name])
    k = PathTracer(med, majorant_block=2).render_batch(SMALL_CAM, seed=101, sample0=0, spl=4096)
    r = rpt.render_paths(twin(med), SMALL_CAM, seed=202, samples=range(16))
    mk, mr = _image_mean_and_se(k), _image_mean_and_se(r)
    for key in mk:
        if key == "multiple" and med.max_order == 1:
            continue
        # The twin's 16 spp are too few to estimate its own variance (order-2 light is
        # heavy-tailed: 256 paths underestimated it 10x in a trial), so under the null
        # hypothesis (same distribution) its standard error is taken from the kernel's
        # per-path variance (4096 spp) scaled to 16 spp.
        se_twin = mk[key][1] * np.sqrt(k.shape[0] / r.shape[0])
        assert np.all(_z(mk[key], (mr[key][0], se_twin)) < 4.0), (key, mk[key], mr[key], se_twin)


def test_majorant_grid_and_global_majorant_agree_statistically():
    """Same estimator, different majorants: a majorant below the density anywhere (or a
    DDA that mis-assigns cells) would bias the grid version. 2^15 paths each."""
    density = np.zeros((12, 10, 11), np.float32)
    density[:4, :4, :4] = _spiky((4, 4, 4), seed=4, p=0.3, peak=30.0)   # a dense corner
    density[6:, 5:, 6:] = 0.5                                            # a thin region
    med = make_medium(density=density, scale=1.0,
                      lobes=[(0.6, 1.0)], albedo=(0.95, 0.8, 0.6), env=(0.2, 0.2, 0.2))
    a = PathTracer(med, majorant_block=2).render_batch(SMALL_CAM, 11, 0, 2048)
    b = PathTracer(med, majorant_block=0).render_batch(SMALL_CAM, 12, 0, 2048)
    ma, mb = _image_mean_and_se(a), _image_mean_and_se(b)
    for key in ma:
        assert np.all(_z(ma[key], mb[key]) < 4.0), (key, ma[key], mb[key])
    # The grid pays fewer tentative collisions in this sparse medium (why it exists).
    assert a[..., ROW_STEPS].mean() < 0.5 * b[..., ROW_STEPS].mean()


def test_russian_roulette_adds_no_bias():
    """RR from vertex 1 on (aggressive) against RR effectively off: same expectation."""
    base = dict(lobes=[(0.5, 1.0)], albedo=(0.85, 0.7, 0.95), scale=6.0)
    early = PathTracer(make_medium(**base, PT_RR_START=1), 0).render_batch(SMALL_CAM, 21, 0, 4096)
    never = PathTracer(make_medium(**base, PT_RR_START=1 << 30), 0).render_batch(SMALL_CAM, 22, 0, 4096)
    me, mn = _image_mean_and_se(early), _image_mean_and_se(never)
    for key in me:
        assert np.all(_z(me[key], mn[key]) < 4.0), (key, me[key], mn[key])
    assert early[..., ROW_VERTICES].mean() < 0.9 * never[..., ROW_VERTICES].mean()


# ------------------------------------------------------------------ exact cases

def _totals(rows):
    return rows[..., ROW_BG] + rows[..., ROW_L1] + rows[..., ROW_LMS]


@pytest.mark.parametrize("grid,scale", [("dense", 40.0), ("sparse", 8.0), ("spiky", 4.0)])
@pytest.mark.parametrize("specialise", [True, False])
def test_white_furnace_is_exact_per_path(grid, scale, specialise):
    density = {"dense": np.ones((5, 4, 6), np.float32),
               "sparse": np.where(_smooth((8, 8, 8), 5) > 1.0, 1.0, 0.0).astype(np.float32),
               "spiky": _spiky((9, 8, 7), seed=2, p=0.1, peak=100.0)}[grid]
    env = (0.5, 0.25, 1.0)
    med = make_medium(density=density, scale=scale, albedo=(1.0, 1.0, 1.0), lobes=[(0.7, 1.0)],
                      sun=(0.0, 0.0, 0.0), env=env)
    rows = PathTracer(med, majorant_block=2, specialise=specialise).render_batch(CAM, 3, 0, 4)
    assert np.all(rows[..., ROW_TRUNCATED] == 0)
    assert rows[..., ROW_VERTICES].max() > (50 if grid == "dense" else 1)  # paths did scatter
    np.testing.assert_array_equal(_totals(rows), np.broadcast_to(np.float32(env), rows.shape[:2] + (3,)))


def test_rays_missing_the_box_return_the_background_exactly():
    away = Camera((0.0, 0.0, 2.0), (0, 0, 4.0), (0, 1, 0), 30.0, 4, 4)
    med = make_medium(env=(0.3, 0.6, 0.9), lobes=[(0.5, 1.0)])
    rows = PathTracer(med).render_batch(away, 0, 0, 3)
    np.testing.assert_array_equal(rows[..., ROW_BG], np.broadcast_to(np.float32([0.3, 0.6, 0.9]), rows.shape[:2] + (3,)))
    assert np.all(rows[..., 3:] == 0)


def test_empty_grid_is_the_empty_scene():
    med = make_medium(density=np.zeros((4, 5, 3), np.float32), env=(0.3, 0.6, 0.9),
                      albedo=(0.9, 0.5, 0.1), lobes=[(0.3, 1.0)])
    rows = PathTracer(med).render_batch(CAM, 0, 0, 3)
    assert np.all(rows[..., ROW_L1] == 0) and np.all(rows[..., ROW_LMS] == 0)
    np.testing.assert_array_equal(rows[..., ROW_BG], np.broadcast_to(np.float32([0.3, 0.6, 0.9]), rows.shape[:2] + (3,)))


def test_albedo_zero_gives_only_the_attenuated_background():
    """Homogeneous slab seen head-on through its depth D: background * exp(-sigma D)."""
    cam = Camera((0.0, 0.0, 30.0), (0, 0, 0), (0, 1, 0), 0.2, 4, 4)  # near-parallel rays
    sigma = 1.5
    med = make_medium(density=np.ones((3, 3, 3), np.float32), scale=sigma, albedo=(0, 0, 0),
                      env=(1.0, 0.5, 0.25), lobes=[(0.5, 1.0)])
    rows = PathTracer(med).render_batch(cam, 0, 0, 4096)
    assert np.all(rows[..., ROW_L1] == 0) and np.all(rows[..., ROW_LMS] == 0)
    seen = rows[..., ROW_BG][..., 0].astype(np.float64)
    assert set(np.unique(seen)) <= {0.0, 1.0}
    expected = np.exp(-sigma * (BMAX[2] - BMIN[2]))
    se = np.sqrt(expected * (1 - expected) / seen.size)
    assert abs(seen.mean() - expected) < 4 * se
    np.testing.assert_array_equal(rows[..., ROW_BG][..., 1], 0.5 * rows[..., ROW_BG][..., 0])


@pytest.mark.parametrize("scale", [1e-4, 1e-2, 1.0, 1e2, 1e4])
def test_extreme_density_scales_are_finite_and_non_negative(scale):
    med = make_medium(scale=scale, lobes=[(0.9, 1.0)], albedo=(0.9, 0.6, 0.3), env=(0.2, 0.2, 0.2))
    pt = PathTracer(med)
    rows = pt.render_batch(Camera((0.1, 0.05, 2.0), (0, 0, 0.05), (0, 1, 0), 22.0, 4, 4), 0, 0, 8)
    assert np.all(np.isfinite(rows)) and np.all(rows >= 0)
    assert np.all(rows[..., ROW_TRUNCATED] == 0)
    p = np.array([[0.0, 0.0, 0.0], [0.4, -0.3, 0.5], [3.0, 3.0, 3.0]], np.float32)
    w = np.array([[0, 0, 1], [1, 0, 0], [0, -1, 0]], np.float32)
    q = pt.query_batch(pt.rt.to_device(p), pt.rt.to_device(w), 3, 0, 0, 16)
    assert np.all(np.isfinite(q)) and np.all(q >= 0)


# ------------------------------------------------------------------ specialisation, determinism

SPECIALISED = {
    "grey-iso-noenv": dict(lobes=[], albedo=(0.9, 0.9, 0.9)),
    "single-only": dict(lobes=[(0.6, 1.0)], max_order=1, albedo=(0.9, 0.5, 0.2)),
    "no-sun-env": dict(lobes=[(0.3, 1.0)], sun=(0, 0, 0), env=(0.4, 0.5, 0.6)),
    "mhg2-rgb-env": dict(lobes=[(0.8, 0.7), (-0.3, 0.3)], albedo=(0.9, 0.8, 0.7), env=(0.1, 0.2, 0.3)),
}


@pytest.mark.parametrize("name", SPECIALISED)
def test_specialised_build_equals_general_build(name):
    med = make_medium(**SPECIALISED[name])
    spec = PathTracer(med, specialise=True)
    gen = PathTracer(med, specialise=False)
    assert spec.defines != gen.defines
    a = spec.render_batch(CAM, 5, 0, 4)
    b = gen.render_batch(CAM, 5, 0, 4)
    np.testing.assert_array_equal(a[..., 9:], b[..., 9:])
    np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-9)


def test_lane_width_does_not_change_paths():
    """Paths run PT_LANES to a work-item and lanes take new paths as theirs end; each path
    keeps its own stream and output row, so 4, 8 or 16 lanes give the same rows (counters
    exact, values to float rounding: the lane maths is the same per lane). Widths up to the
    device's (cl/include/lanes.h LANES: $CLVOL_LANES lowers it)."""
    from clvol.runtime import get_runtime
    widths = [n for n in (4, 8, 16) if n <= get_runtime().lanes]
    med = dict(lobes=SKIN, albedo=(0.99, 0.85, 0.75), env=(0.1, 0.1, 0.1))
    rows = {n: PathTracer(make_medium(**med, PT_LANES=n)).render_batch(CAM, 4, 0, 3)
            for n in widths}
    p = np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 0.4], [2.0, 0.0, 0.0]], np.float32)
    w = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]], np.float32)
    queries = {}
    for n in widths:
        pt = PathTracer(make_medium(**med, PT_LANES=n))
        queries[n] = pt.query_batch(pt.rt.to_device(p), pt.rt.to_device(w), 3, 4, 0, 5)
    assert rows[4][..., ROW_VERTICES].max() > 3   # long paths: lanes refill at different times
    for n in widths[1:]:
        for a, b in ((rows[n], rows[4]), (queries[n], queries[4])):
            np.testing.assert_array_equal(a[..., 9:], b[..., 9:])
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)


def test_max_order_splits_orders():
    base = dict(lobes=[(0.5, 1.0)], albedo=(0.9, 0.8, 0.7))
    full = PathTracer(make_medium(**base)).render_batch(CAM, 9, 0, 4)
    one = PathTracer(make_medium(**base, max_order=1)).render_batch(CAM, 9, 0, 4)
    two = PathTracer(make_medium(**base, max_order=2)).render_batch(CAM, 9, 0, 4)
    # Vertex 1's NEE happens before any later decision: identical order-1 light.
    np.testing.assert_array_equal(full[..., ROW_L1], one[..., ROW_L1])
    np.testing.assert_array_equal(full[..., ROW_L1], two[..., ROW_L1])
    assert np.all(one[..., ROW_LMS] == 0) and np.all(one[..., ROW_VERTICES] <= 1)
    assert np.all(two[..., ROW_VERTICES] <= 2) and two[..., ROW_LMS].sum() > 0
    assert full[..., ROW_VERTICES].max() > 2


def test_same_seed_is_bit_identical_and_seeds_differ():
    med = make_medium(lobes=SKIN, albedo=(0.99, 0.85, 0.75), env=(0.1, 0.1, 0.1))
    a = PathTracer(med).render_batch(CAM, 42, 0, 4)
    b = PathTracer(med).render_batch(CAM, 42, 0, 4)
    c = PathTracer(med).render_batch(CAM, 43, 0, 4)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


# ------------------------------------------------------------------ public API

def _scene(**medium_kw):
    from clvol.scene import Light, Phase, Scene, VolumeSpec
    from clvol.scene import Medium as SceneMedium
    from clvol.volume.grid import DensityGrid
    grid = DensityGrid(_smooth(), BMIN, BMAX)
    phase = medium_kw.pop("phase", Phase.hg(0.6))
    med = SceneMedium(density_scale=medium_kw.pop("density_scale", 3.0),
                      albedo=medium_kw.pop("albedo", (0.9, 0.8, 0.7)), phase=phase)
    light = Light(direction=_unit((0.3, 0.8, 0.5)), irradiance=(2.0, 2.0, 2.0),
                  environment=medium_kw.pop("environment", None))
    scene = Scene(path=None, volume=VolumeSpec(file=None, generator="box"), medium=med,
                  light=light, camera=SMALL_CAM)
    return scene, grid


def test_render_pathtrace_layers_header_and_budget():
    from clvol.render.pathtrace import render_pathtrace
    scene, grid = _scene(environment=(0.1, 0.2, 0.3))
    res = render_pathtrace(scene, spp=8, seed=3, grid=grid, progress=False)
    L = res.layers
    assert set(L) == {"total", "single", "multiple", "total_se", "alpha"}
    for k, v in L.items():
        shape = (4, 4) if k == "alpha" else (4, 4, 3)       # coverage: one channel
        assert v.shape == shape and v.dtype == np.float32 and np.all(np.isfinite(v))
    assert np.all((L["alpha"] >= 0) & (L["alpha"] <= 1))
    h = res.header
    assert h["spp"] == 8 and h["seconds"] > 0 and "environment" in h["simulated"]
    assert "PT_ENV=1" in h["defines"] and h["paths_truncated"] == 0
    again = render_pathtrace(scene, spp=8, seed=3, grid=grid, progress=False)
    assert np.array_equal(L["total"], again.layers["total"])
    # Background + single + multiple = total, each a non-negative mean.
    assert np.all(L["single"] >= 0) and np.all(L["multiple"] >= 0)
    assert np.all(L["total"] >= L["single"] + L["multiple"] - 1e-6)
    budget = render_pathtrace(scene, spp=None, time_budget=0.5, seed=3, grid=grid, progress=False)
    n = budget.header["spp"]
    assert n >= 1 and budget.header["seconds"] < 5.0
    fixed = render_pathtrace(scene, spp=n, seed=3, grid=grid, progress=False)
    np.testing.assert_allclose(budget.layers["total"], fixed.layers["total"], rtol=1e-6)


def test_render_rejects_bad_options():
    from clvol.render.pathtrace import render_pathtrace
    scene, grid = _scene()
    for kw in (dict(spp=0), dict(max_order=0), dict(spp=None, time_budget=-1.0), dict(seed=-1)):
        with pytest.raises(ClvolError):
            render_pathtrace(scene, grid=grid, progress=False, **kw)


def test_point_query_outside_points_and_errors():
    from clvol.render.pathtrace import point_query
    scene, grid = _scene(environment=(5.0, 5.0, 5.0))
    l = np.asarray(scene.light.direction)
    p = np.array([[0.0, 0.0, 0.0], 3.0 * l, [0.1, 0.1, 0.1]])   # centre, far toward the sun, inside
    w = np.array([_unit((0, 0, 1)), _unit((1, 1, 0)), _unit((-1, 0, 0))])
    out = point_query(scene, p, w, n_paths=256, seed=1, grid=grid)
    assert set(out) >= {"F1", "F1_se", "Fms", "Fms_se"}
    for key in ("F1", "F1_se", "Fms", "Fms_se"):
        assert out[key].shape == (3, 3) and np.all(np.isfinite(out[key])) and np.all(out[key] >= 0)
    # Toward the sun from outside the box nothing attenuates: F1 = f(dot(-l, omega)) exactly
    # (per unit irradiance: the scene's irradiance 2 and environment 5 are ignored).
    f = phase_eval(np.array(np.dot(-l, w[1])), [(0.6, 1.0)])
    np.testing.assert_allclose(out["F1"][1], f, rtol=1e-5)
    assert np.all(out["F1_se"][1] == 0)
    assert np.all(out["Fms"][0] > 0) and np.all(out["Fms_se"][0] > 0)
    assert np.all(out["F1"][:, 0] == out["F1"][:, 1])  # F1 is grey
    again = point_query(scene, p, w, n_paths=256, seed=1, grid=grid)
    assert np.array_equal(out["Fms"], again["Fms"])
    single = point_query(scene, p, w, n_paths=64, seed=1, grid=grid, max_order=1)
    assert np.all(single["Fms"] == 0)
    with pytest.raises(ClvolError, match="unit"):
        point_query(scene, p, 2 * w, n_paths=4, grid=grid)
    with pytest.raises(ClvolError):
        point_query(scene, p[:2], w, n_paths=4, grid=grid)
    with pytest.raises(ClvolError):
        point_query(scene, p, w, n_paths=0, grid=grid)


def test_cli_render_writes_layers_and_header(tmp_path):
    from clvol.cli import main
    from clvol.image import read_exr
    scene = write_scene(tmp_path / "s.toml", volume={"generator": "sphere", "resolution": 8},
                        medium={"density_scale": 4.0, "albedo": [0.9, 0.8, 0.7],
                                "phase": {"type": "hg", "g": 0.5}},
                        light={"direction": [0.0, 1.0, 0.0]},
                        camera={**CAMERA, "origin": [0.0, 0.0, 3.0], "up": [0.0, 1.0, 0.0],
                                "fov_y": 30.0, "width": 6, "height": 4})
    out = tmp_path / "o.exr"
    assert main(["render", str(scene), "--method", "pathtrace", "--spp", "4", "--max-order", "3",
                 "-o", str(out)]) == 0
    img = read_exr(out)
    assert img.rgb.shape == (4, 6, 3)
    assert {"single", "multiple"} <= set(img.layers)
    assert img.header["spp"] == "4" and img.header["max_order"] == "3"
    assert "simulated" in img.header and "skipped" in img.header


def _tiny_tracer():
    d = _smooth((3, 2, 3))
    med = make_medium(density=d, lobes=[(0.5, 0.7), (-0.2, 0.3)], albedo=(0.9, 0.8, 0.7),
                      env=(0.1, 0.1, 0.1), max_order=3)
    return med, PathTracer(med, majorant_block=0)


@pytest.mark.oclgrind
@pytest.mark.rusticl
def test_pathtrace_tiny():
    """pt_render on a 2 x 2 camera, 1 path a pixel, against the twin's paths. The point-query
    kernel's half is the next test: on Mesa's rusticl (tests/test_rusticl.py) each kernel's
    first launch compiles for 50-65 s, and this one is the subset's."""
    med, pt = _tiny_tracer()
    cam = Camera((0.1, 0.0, 2.0), (0, 0, 0), (0, 1, 0), 30.0, 2, 2)
    assert agreement(pt.render_batch(cam, 1, 0, 1), rpt.render_paths(twin(med), cam, 1, [0])) == 1.0


@pytest.mark.oclgrind
def test_pathtrace_tiny_query():
    med, pt = _tiny_tracer()
    p = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]], np.float32)
    w = np.array([[0, 0, 1], [0, 1, 0]], np.float32)
    k = pt.query_batch(pt.rt.to_device(p), pt.rt.to_device(w), 2, 1, 0, 1)
    assert agreement(k, rpt.query_paths(twin(med), p, w, 1, [0])) == 1.0


def test_shared_device_medium_gives_the_same_rows_and_refuses_a_mismatch():
    from clvol.kernels.medium import DeviceMedium
    med = make_medium(lobes=[(0.5, 1.0)])
    dm = DeviceMedium.upload(med, 2)
    own = PathTracer(med, majorant_block=2).render_batch(CAM, 5, 0, 2)
    shared = PathTracer(med, majorant_block=2, device_medium=dm)
    assert shared.dm is dm
    np.testing.assert_array_equal(shared.render_batch(CAM, 5, 0, 2), own)
    with pytest.raises(ClvolError, match="majorant block"):
        PathTracer(med, majorant_block=0, device_medium=dm)
    with pytest.raises(ClvolError, match="shape"):
        PathTracer(make_medium(density=_spiky()), majorant_block=2, device_medium=dm)
    with pytest.raises(ClvolError, match="3-D"):
        PathTracer(make_medium(density=np.ones((4, 4), np.float32)))


def test_gpu_launch_shape_gives_the_same_rows(monkeypatch):
    """A GPU's launch (many work-items in groups of 64, more than there are paths) takes the
    same paths from the counter as a CPU's: bit-identical rows, render and point queries."""
    from clvol.kernels import pathtrace as kpt
    med = make_medium(lobes=[(0.5, 1.0)], max_order=3)
    p = np.array([[0.0, 0.0, 0.0], [0.1, -0.2, 0.05], [2.0, 0.0, 0.0]], np.float32)
    w = np.array([[0, 0, 1], [0, 1, 0], [1, 0, 0]], np.float32)

    def rows(kind):
        monkeypatch.setattr(kpt, "launch_shape",
                            lambda _k, cus, n, lanes, real=kpt.launch_shape: real(kind, cus, n,
                                                                                 lanes))
        pt = PathTracer(med, majorant_block=2)
        return (pt.render_batch(CAM, 5, 0, 3),
                pt.query_batch(pt.rt.to_device(p), pt.rt.to_device(w), 3, 5, 0, 7))

    assert kpt.launch_shape("gpu", 132, 100_000, 8) == (12544, (64,))
    assert kpt.launch_shape("cpu", 2, 100_000, 8) == (8, (1,))
    for a, b in zip(rows("cpu"), rows("gpu")):
        np.testing.assert_array_equal(a, b)
