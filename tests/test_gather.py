"""cl/gather.cl against reference/gather.py, the render/train consistency, edge cases, and
the template's invariance under rotations (clvol/features/layout.py is the contract under test).

Tolerances (absolute; features are log1p values or T in [0, 1]):
- density log1p(tau) and T levels: 2e-5, float32 trilinear lookups and frame arithmetic in the
  kernel vs float64 in the twin (values are O(1); ~100 ULP of slack for the chained lerps);
- phase: 2e-3, the kernel's linear interpolation over its alpha table (the bound measured in
  tests/test_phasetable.py); the centre point is exact in both (1e-5);
- t_enter: 1e-5 of the cube edge (float32 DDA vs float64 slab tests);
- baked render grid vs its twin (reference.gather.baked_grid): 2e-6 on C, a float32 sum of
  L terms w_m T_m with |w_m| <= 0.6 and T_m in [0, 1], each lerp rounded (~10 ULP of 1), and
  1e-6 relative on tau (one product);
- render vs train features: 2e-6 on T, 1e-6 on density (the same lookups, summed before
  instead of after the lerps); the PoCL shuffle path vs the portable loads, sorted vs unsorted
  processing, device buffers vs arrays: identical bits.
"""
import numpy as np
import pytest

from clvol.kernels import gather as kgather
from clvol.kernels.gather import GatherError, gather
from clvol.kernels.pyramid import build_pyramid
from clvol.kernels.transmittance import graded_transmittance
from clvol.features import layout
from clvol.scene import Medium, Phase
from clvol.volume.generators import generate
from clvol.volume.grid import DensityGrid
from reference import gather as rgather

LOBES = ((0.857, 1.0),)
MEDIUM = Medium(12.0, (0.9, 0.95, 1.0), Phase.hg(0.857))
MHG = Medium(12.0, (0.9, 0.95, 1.0), Phase.mhg([(0.857, 0.7), (-0.3, 0.3)]))


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def setup(density, base, light, scale=MEDIUM.density_scale, bmin=(-0.5, -0.5, -0.5), bmax=None):
    density = np.asarray(density, np.float32)
    if bmax is None:
        nz, ny, nx = density.shape
        bmax = np.asarray(bmin) + np.array([nx, ny, nz]) / max(density.shape)
    grid = DensityGrid(density=density, bbox_min=np.asarray(bmin, float), bbox_max=np.asarray(bmax, float))
    pyr = build_pyramid(grid, base)
    return pyr, graded_transmittance(pyr, scale, unit(light))


def queries(n, seed, spread=0.7):
    rs = np.random.default_rng(seed)
    pts = rs.uniform(-spread, spread, (n, 3)).astype(np.float32)
    return pts, unit(rs.normal(size=(n, 3))).astype(np.float32)


def compare(pyr, gt, pts, om, medium=MEDIUM, lobes=LOBES):
    l = gt.light_dir
    got = gather(pyr, gt, pts, om, l, medium, 0.9, mode="train", return_t_enter=True)
    want = rgather.gather(pyr, gt.data, pts, om, l, lobes, medium.density_scale)
    np.testing.assert_allclose(got["t_enter"], want["t_enter"], atol=1e-5 * pyr.cube_size, rtol=0)
    f, wf = got["features"], want["features"]
    np.testing.assert_allclose(f[:, 0], wf[:, 0], atol=2e-5, rtol=0)
    np.testing.assert_allclose(got["levels"], want["levels"], atol=2e-5, rtol=0)
    np.testing.assert_allclose(f[:, 2, 0], wf[:, 2, 0], atol=1e-5, rtol=1e-5)
    np.testing.assert_allclose(f[:, 2], wf[:, 2], atol=2e-3, rtol=0)
    assert np.all(f[:, 1] == 0)              # train mode without weights
    return got, want


LIGHTS = {
    "oblique": (0.3, 0.5, 0.8),
    "axis+z": (0.0, 0.0, 1.0),
    "axis-x": (-1.0, 0.0, 0.0),
    "grazing": (1.0, 1e-3, -2e-3),           # nearly parallel to the y and z faces
}


@pytest.mark.parametrize("light", LIGHTS)
def test_kernel_matches_reference_odd_grid(light):
    # non-cubic odd grid, padded to a cube; a third of the queries outside the cube
    g = generate("cloud", seed=3, resolution=(13, 9, 11))
    pyr, gt = setup(g.density, 16, LIGHTS[light], bmin=g.bbox_min, bmax=g.bbox_max)
    pts, om = queries(45, seed=len(light))
    got, want = compare(pyr, gt, pts, om)
    assert np.any(got["t_enter"] > 0) and np.any(got["features"][:, 0] > 0)


def test_mhg_and_omega_parallel_to_light():
    g = generate("blob", seed=1, resolution=16)
    light = unit((0.2, -0.4, 0.9))
    pyr, gt = setup(g.density, 16, light, bmin=g.bbox_min, bmax=g.bbox_max)
    pts, om = queries(20, seed=9, spread=0.3)
    om[:5] = light                  # looking away from the sun: frame fallback
    om[5:10] = -light               # looking into the sun (alpha = 0)
    compare(pyr, gt, pts, om, medium=MHG, lobes=((0.857, 0.7), (-0.3, 0.3)))


def test_render_mode_equals_weighted_levels():
    g = generate("cloud", seed=5, resolution=(12, 10, 14))
    pyr, gt = setup(g.density, 16, (0.1, 0.9, -0.3), bmin=g.bbox_min, bmax=g.bbox_max)
    pts, om = queries(40, seed=2)
    w = np.linspace(-0.2, 0.6, pyr.n_levels)
    train = gather(pyr, gt, pts, om, gt.light_dir, MEDIUM, 0.9, mode="train", level_weights=w, bias=0.1)
    render = gather(pyr, gt, pts, om, gt.light_dir, MEDIUM, 0.9, mode="render", level_weights=w, bias=0.1)
    assert "levels" not in render
    # the baked grid is the same linear combination, summed before instead of after the lerps
    np.testing.assert_allclose(render["features"][:, 1], train["features"][:, 1], atol=2e-6)
    np.testing.assert_allclose(render["features"][:, 0], train["features"][:, 0], atol=1e-6)
    np.testing.assert_array_equal(render["features"][:, 2], train["features"][:, 2])
    want = rgather.gather(pyr, gt.data, pts, om, gt.light_dir, LOBES, MEDIUM.density_scale,
                          mode="render", level_weights=w, bias=0.1)
    np.testing.assert_allclose(render["features"][:, 1], want["features"][:, 1], atol=2e-5)


def test_outside_queries_defined():
    g = generate("sphere", seed=0, resolution=8)
    pyr, gt = setup(g.density, 8, (0, 1, 0), bmin=g.bbox_min, bmax=g.bbox_max)
    pts = np.array([[5.0, 5.0, 5.0], [-40.0, 0.0, 0.0]], np.float32)
    om = unit(np.array([[0, 0, 1.0], [1.0, 0, 0]])).astype(np.float32)
    w = np.full(pyr.n_levels, 0.25)
    out = gather(pyr, gt, pts, om, gt.light_dir, MEDIUM, 0.5, mode="train", return_t_enter=True)
    assert np.all(out["features"][:, 0] == 0) and np.all(out["levels"] == 1) and np.all(out["t_enter"] == 0)
    assert np.all(np.isfinite(out["features"]))
    r = gather(pyr, gt, pts, om, gt.light_dir, MEDIUM, 0.5, mode="render", level_weights=w, bias=-0.5)
    np.testing.assert_allclose(r["features"][:, 1], w.sum() - 0.5, rtol=1e-6)


def test_empty_grid_and_one_voxel():
    pyr, gt = setup(np.zeros((5, 6, 7)), 8, (0.3, 0.3, 0.9))
    pts, om = queries(10, seed=4, spread=0.4)
    got, _ = compare(pyr, gt, pts, om)
    assert np.all(got["t_enter"] == 0) and np.all(got["features"][:, 0] == 0)
    assert np.all(got["levels"] == 1)
    pyr1, gt1 = setup(np.ones((1, 1, 1)), 1, (0, 0, 1))          # a single voxel, base 1
    got1, _ = compare(pyr1, gt1, *queries(10, seed=6, spread=0.45))
    assert np.all(got1["features"][:, 0][:, 0] > 0)


def test_config_vector():
    g = generate("blob", seed=2, resolution=8)
    pyr, gt = setup(g.density, 8, (0, 0, 1), bmin=g.bbox_min, bmax=g.bbox_max)
    om = unit(np.array([[0, 0, -1.0], [1.0, 0, 0], [0, 0, 1.0]])).astype(np.float32)
    out = gather(pyr, gt, np.zeros((3, 3), np.float32), om, gt.light_dir, MHG,
                 np.array([0.9, 0.95, 1.0]), mode="train")
    cfg = out["config"]
    assert cfg.shape == (3, layout.CONFIG_DIM)
    f = dict(zip(layout.CONFIG_FIELDS, cfg.T))
    np.testing.assert_allclose(f["g0"], 0.857)
    np.testing.assert_allclose(f["g1"], -0.3)
    np.testing.assert_allclose(f["g2"], 0.0)
    np.testing.assert_allclose(f["w0"] + f["w1"] + f["w2"], 1.0, rtol=1e-6)
    np.testing.assert_allclose(f["g_mean"], 0.857 * 0.7 - 0.3 * 0.3, rtol=1e-6)
    np.testing.assert_allclose(f["albedo"], [0.9, 0.95, 1.0])
    np.testing.assert_allclose(f["alpha"], [0.0, np.pi / 2, np.pi], atol=1e-6)


def test_bad_inputs():
    g = generate("blob", seed=2, resolution=8)
    pyr, gt = setup(g.density, 8, (0, 0, 1), bmin=g.bbox_min, bmax=g.bbox_max)
    pts, om = queries(3, 0)
    with pytest.raises(GatherError, match="unit"):
        gather(pyr, gt, pts, om * 2, gt.light_dir, MEDIUM, 0.9)
    with pytest.raises(GatherError, match="differs"):
        gather(pyr, gt, pts, om, (1.0, 0, 0), MEDIUM, 0.9)
    with pytest.raises(GatherError, match="level_weights"):
        gather(pyr, gt, pts, om, gt.light_dir, MEDIUM, 0.9, mode="render")
    with pytest.raises(GatherError, match="density_scale"):
        gather(pyr, gt, pts, om, gt.light_dir, Medium(1.0, (1, 1, 1), Phase.hg(0.5)), 0.9)
    with pytest.raises(GatherError, match="channel_albedo"):
        gather(pyr, gt, pts, om, gt.light_dir, MEDIUM, 1.5)
    empty = gather(pyr, gt, np.zeros((0, 3)), np.zeros((0, 3)), gt.light_dir, MEDIUM, 0.9)
    assert empty["features"].shape == (0, 3, layout.N_POINTS)


def _rot_z90(v):
    v = np.asarray(v)
    return np.stack([-v[..., 1], v[..., 0], v[..., 2]], -1)


def test_invariant_under_90_degree_rotation():
    """Rotate grid, light, view and points by 90 degrees about z (the cube maps onto itself):
    every feature is unchanged up to float rounding (same tolerances as the kernel test, T
    levels 1e-4: the graded sweep runs along a different axis after the rotation)."""
    n = 16
    d = generate("cloud", seed=8, resolution=n).density
    d_rot = np.ascontiguousarray(np.transpose(d, (0, 2, 1))[:, :, ::-1])   # D'[k, i, n-1-j] = D[k, j, i]
    light = unit((0.4, -0.2, 0.7))
    pts, om = queries(30, seed=11, spread=0.45)
    pyr, gt = setup(d, n, light)
    pyr_r, gt_r = setup(d_rot, n, _rot_z90(light))
    a = gather(pyr, gt, pts, om, gt.light_dir, MEDIUM, 0.9, return_t_enter=True)
    b = gather(pyr_r, gt_r, _rot_z90(pts).astype(np.float32), _rot_z90(om).astype(np.float32),
               gt_r.light_dir, MEDIUM, 0.9, return_t_enter=True)
    np.testing.assert_allclose(b["t_enter"], a["t_enter"], atol=1e-5)
    np.testing.assert_allclose(b["features"][:, 0], a["features"][:, 0], atol=2e-5)
    np.testing.assert_allclose(b["features"][:, 2], a["features"][:, 2], atol=1e-5)
    np.testing.assert_allclose(b["levels"], a["levels"], atol=1e-4)
    # power check: the same grid with the un-rotated light gives clearly different features
    assert np.max(np.abs(b["features"][:, 0] - gather(pyr, gt, _rot_z90(pts).astype(np.float32),
                  _rot_z90(om).astype(np.float32), gt.light_dir, MEDIUM, 0.9)["features"][:, 0])) > 0.05


def _blob_grid(n, rot):
    """A smooth, compactly supported anisotropic bump 4 (1 - q^2)^3 (zero well inside the cube,
    so the cube's faces, which do not rotate, play no part), sampled at voxel centres of
    [-0.5, 0.5]^3 and rotated by rot."""
    c = (np.arange(n) + 0.5) / n - 0.5
    z, y, x = np.meshgrid(c, c, c, indexing="ij")
    p = np.stack([x, y, z], -1) @ rot            # rot^T applied to each position
    q = p - np.array([0.03, -0.02, 0.01])
    q2 = (q[..., 0] / 0.36) ** 2 + (q[..., 1] / 0.24) ** 2 + (q[..., 2] / 0.3) ** 2
    return 4.0 * np.clip(1.0 - q2, 0.0, None) ** 3


def test_rotation_of_analytic_field_within_tolerance():
    """Rotate a smooth field, light, view and points by an arbitrary rotation: features change
    only by resampling error, which grows with the mip level (a 32^3 base: layer 7 reads an 8^3
    level, the coarse graded T levels are a few voxels wide). Tolerances, about 1.5x the
    measured worst: log1p density 0.01 on layers 0-5 and 0.15 on all; T levels 0.15 (median
    0.02); phase 1e-5 (alpha is unchanged); t_enter one coarse cell diagonal. The power check
    (a view direction that did not follow the rotation changes density features by ~1.0)
    shows the tolerances still catch a frame error."""
    rs = np.random.default_rng(12)
    rot, _ = np.linalg.qr(rs.normal(size=(3, 3)))
    rot *= np.sign(np.linalg.det(rot))
    n = 32
    light = unit((0.3, 0.5, 0.8))
    pts, om = queries(40, seed=13, spread=0.12)
    pyr, gt = setup(_blob_grid(n, np.eye(3)), n, light, scale=6.0)
    pyr_r, gt_r = setup(_blob_grid(n, rot), n, rot @ light, scale=6.0)
    med = Medium(6.0, (0.9, 0.9, 0.9), Phase.hg(0.857))
    a = gather(pyr, gt, pts, om, gt.light_dir, med, 0.9, return_t_enter=True)
    pr, omr = (pts @ rot.T).astype(np.float32), (om @ rot.T).astype(np.float32)
    b = gather(pyr_r, gt_r, pr, omr, gt_r.light_dir, med, 0.9, return_t_enter=True)
    fine = np.arange(layout.N_POINTS) < sum(layout.LAYER_COUNTS[:6])   # layers 0-5: levels 0-1 here
    np.testing.assert_allclose(b["features"][:, 0, fine], a["features"][:, 0, fine], atol=0.01)
    np.testing.assert_allclose(b["features"][:, 0], a["features"][:, 0], atol=0.15)
    np.testing.assert_allclose(b["levels"], a["levels"], atol=0.15)
    assert np.median(np.abs(b["levels"] - a["levels"])) < 0.02
    np.testing.assert_allclose(b["features"][:, 2], a["features"][:, 2], atol=1e-5)
    np.testing.assert_allclose(b["t_enter"], a["t_enter"], atol=2.0 / 32 * np.sqrt(3))  # a coarse cell
    wrong = gather(pyr_r, gt_r, pr, (om @ rot).astype(np.float32), gt_r.light_dir, med, 0.9)
    assert np.max(np.abs(wrong["features"][:, 0] - a["features"][:, 0])) > 0.1


@pytest.mark.oclgrind
@pytest.mark.rusticl
def test_tiny():
    pyr, gt = setup(generate("sphere", seed=0, resolution=4).density, 4, (0.2, 0.3, 0.9))
    compare(pyr, gt, *queries(3, seed=1, spread=0.4))


# --------------------------------------------------------------------------- render path

def test_bake_matches_twin_every_level():
    """The separable bake (x pass + rows for levels >= 16 wide, incl. the finer-level 2x2x2
    means; direct lookups below) against direct lookups at every voxel of every level, on a
    non-cubic grid padded to a 64^3 base (levels 0-2 by rows: each has coarser and finer
    levels) and a light that makes every level differ."""
    g = generate("cloud", seed=4, resolution=(21, 17, 26))
    pyr, gt = setup(g.density, 64, (0.45, -0.3, 0.84), bmin=g.bbox_min, bmax=g.bbox_max)
    w = np.linspace(-0.3, 0.6, pyr.n_levels)
    baked = kgather.bake_render_grid(pyr, gt, MEDIUM.density_scale, w, 0.07)
    flat = baked.device.read()
    want = rgather.baked_grid(pyr, gt.data, MEDIUM.density_scale, w, 0.07)
    for lv, (tau, comb) in enumerate(want):
        n = pyr.resolution(lv)
        off = 2 * int(pyr.level_offsets[lv])
        got = flat[off:off + 2 * n ** 3].reshape(n, n, n, 2)
        np.testing.assert_allclose(got[..., 0], tau, rtol=1e-6, atol=0, err_msg=f"tau, level {lv}")
        np.testing.assert_allclose(got[..., 1], comb, atol=2e-6, rtol=0, err_msg=f"C, level {lv}")
    assert np.ptp(want[0][1]) > 0.1                      # power: C varies across the grid
    np.testing.assert_array_equal(flat[2 * pyr.size:], 0.0)   # the padding the kernel reads
    assert float(np.float32(w.sum() + 0.07)) == baked.c_out



def test_bake_is_kept_per_pyramid_until_its_inputs_change():
    """The last bake lives in its pyramid's cache: the same inputs return it without a launch,
    another bias re-bakes (into the same buffer), and a second pyramid keeps its own."""
    g = generate("sphere", seed=0, resolution=16)
    pyr, gt = setup(g.density, 16, (0.2, 0.3, 0.9))
    pyr2, gt2 = setup(g.density, 16, (0.9, 0.3, 0.2))
    w = np.linspace(0.1, 0.3, pyr.n_levels)
    a = kgather.bake_render_grid(pyr, gt, MEDIUM.density_scale, w, 0.1)
    b2 = kgather.bake_render_grid(pyr2, gt2, MEDIUM.density_scale, w, 0.1)
    assert kgather.bake_render_grid(pyr, gt, MEDIUM.density_scale, w, 0.1) is a   # not evicted
    assert kgather.bake_render_grid(pyr2, gt2, MEDIUM.density_scale, w, 0.1) is b2
    c = kgather.bake_render_grid(pyr, gt, MEDIUM.density_scale, w, 0.2)
    assert c is not a and c.c_out == pytest.approx(a.c_out + 0.1)
    n = pyr.size
    comb = c.device.read()[1:2 * n:2]
    want = rgather.baked_grid(pyr, gt.data, MEDIUM.density_scale, w, 0.2)
    np.testing.assert_allclose(comb[:want[0][1].size], want[0][1].ravel(), atol=2e-6)

def _render_vs_train(pyr, gt, pts, om, w, b):
    train = gather(pyr, gt, pts, om, gt.light_dir, MEDIUM, 0.9, mode="train", level_weights=w, bias=b)
    render = gather(pyr, gt, pts, om, gt.light_dir, MEDIUM, 0.9, mode="render", level_weights=w, bias=b)
    np.testing.assert_allclose(render["features"][:, 1], train["features"][:, 1], atol=2e-6)
    np.testing.assert_allclose(render["features"][:, 0], train["features"][:, 0], atol=1e-6)
    np.testing.assert_array_equal(render["features"][:, 2], train["features"][:, 2])
    want = rgather.gather(pyr, gt.data, pts, om, gt.light_dir, LOBES, MEDIUM.density_scale,
                          mode="render", level_weights=w, bias=b)
    np.testing.assert_allclose(render["features"][:, 1], want["features"][:, 1], atol=2e-5)
    np.testing.assert_allclose(render["features"][:, 0], want["features"][:, 0], atol=2e-5)
    return render


def test_render_on_faces_and_64_base():
    """Render mode on a 64^3 base (levels baked by rows), with queries on the cube's faces,
    edges and corners (the kernel's corners stop at n - 2 and weigh the last voxel by 1 there)
    and outside it; against train mode and the twin."""
    g = generate("cloud", seed=6, resolution=(19, 23, 16))
    pyr, gt = setup(g.density, 64, (-0.2, 0.7, 0.5), bmin=g.bbox_min, bmax=g.bbox_max)
    pts, om = queries(48, seed=21, spread=0.6)
    lo, hi = pyr.cube_min, pyr.cube_max
    pts[:8] = np.array([[lo[0], 0, 0], [hi[0], 0, 0], [0, lo[1], 0], [0, hi[1], 0],
                        [0, 0, hi[2]], hi, lo, [hi[0], lo[1], hi[2]]], np.float32)
    w = np.linspace(0.3, -0.1, pyr.n_levels)
    r = _render_vs_train(pyr, gt, pts, om, w, -0.05)
    assert np.any(r["features"][:, 0] > 0.5)


def test_render_paths_and_order_give_identical_bits(monkeypatch):
    """The PoCL register-transpose path vs the portable per-lane loads, and the sorted vs the
    given processing order: the same values read and combined, so the same bits."""
    g = generate("cloud", seed=3, resolution=(13, 9, 11))
    pyr, gt = setup(g.density, 32, LIGHTS["oblique"], bmin=g.bbox_min, bmax=g.bbox_max)
    pts, om = queries(70, seed=5)
    w = np.linspace(-0.2, 0.6, pyr.n_levels)

    def run(**kw):
        return gather(pyr, gt, pts, om, gt.light_dir, MEDIUM, 0.9, mode="render",
                      level_weights=w, bias=0.1, return_t_enter=True, **kw)
    a = run()
    np.testing.assert_array_equal(run(sort=False)["features"], a["features"])
    np.testing.assert_array_equal(run(sort=False)["t_enter"], a["t_enter"])
    monkeypatch.setattr(kgather, "USE_SHUFFLE", False)
    np.testing.assert_array_equal(run()["features"], a["features"])
    order = kgather.query_order(pyr, pts)
    assert sorted(order.tolist()) == list(range(len(pts))) and np.any(order != np.arange(len(pts)))


def test_as_buffers_and_reuse():
    g = generate("blob", seed=1, resolution=16)
    pyr, gt = setup(g.density, 16, (0.2, -0.4, 0.9), bmin=g.bbox_min, bmax=g.bbox_max)
    pts, om = queries(33, seed=8, spread=0.4)
    w = np.full(pyr.n_levels, 0.2)
    kw = dict(mode="render", level_weights=w, bias=0.0)
    host = gather(pyr, gt, pts, om, gt.light_dir, MEDIUM, 0.9, return_t_enter=True, **kw)
    dev = gather(pyr, gt, pts, om, gt.light_dir, MEDIUM, 0.9, as_buffers=True, **kw)
    rt = pyr.runtime
    assert dev["n"] == len(pts)
    np.testing.assert_array_equal(rt.from_device(dev["features"], host["features"].shape), host["features"])
    np.testing.assert_array_equal(rt.from_device(dev["config"], host["config"].shape), host["config"])
    np.testing.assert_array_equal(rt.from_device(dev["t_enter"], (len(pts),)), host["t_enter"])
    # a smaller batch into the same buffers; a larger one gets new buffers
    again = gather(pyr, gt, pts[:20], om[:20], gt.light_dir, MEDIUM, 0.9, as_buffers=True,
                   reuse=dev, **kw)
    assert again["features"].buffer is dev["features"].buffer
    assert again["features"].shape == (20, 3, layout.N_POINTS)
    np.testing.assert_array_equal(rt.from_device(again["features"], (20, 3, layout.N_POINTS)),
                                  host["features"][:20])
    big = np.concatenate([pts, pts])
    more = gather(pyr, gt, big, np.concatenate([om, om]), gt.light_dir, MEDIUM, 0.9,
                  as_buffers=True, reuse=dev, **kw)
    assert more["features"].buffer is not dev["features"].buffer
    with pytest.raises(GatherError, match="as_buffers"):
        gather(pyr, gt, pts, om, gt.light_dir, MEDIUM, 0.9, mode="train", as_buffers=True)


@pytest.mark.oclgrind
@pytest.mark.rusticl
def test_tiny_render():
    pyr, gt = setup(generate("sphere", seed=0, resolution=4).density, 4, (0.2, 0.3, 0.9))
    pts, om = queries(3, seed=1, spread=0.4)
    _render_vs_train(pyr, gt, pts, om, np.linspace(-0.2, 0.6, pyr.n_levels), 0.1)


def test_twin_template_table_and_volume_phase_agree_with_clvols():
    """reference/gather.py reads the template .npz and evaluates the volume phase itself
    (Legendre series). Same table as clvol's loader; the lobe tables within their stated
    error bound (clvol.features.phasetable.ERROR_BOUND, 1% relative; measured 0.17% at g 0.857)."""
    from clvol.features import phasetable
    from clvol.features.templates import load_templates
    t, mine = load_templates(), rgather.Templates()
    np.testing.assert_array_equal(mine.points, t.points)
    np.testing.assert_array_equal(mine.is_highlight, t.is_highlight)
    for base in (32, 64, 256):
        np.testing.assert_array_equal(mine.diffuse_levels(base), t.diffuse_levels(base))
    rng = np.random.default_rng(3)
    mu, beta = rng.uniform(-1, 1, 2000), rng.uniform(0, 0.6, 2000)
    for lobes in (((0.857, 1.0),), ((0.857, 0.7), (-0.3, 0.3)), ((0.99, 1.0),)):
        exact = rgather.cap_average(mu, beta, lobes)
        table = phasetable.volume_phase(lobes).eval(mu, beta)
        assert np.abs(table / exact - 1).max() <= phasetable.ERROR_BOUND
