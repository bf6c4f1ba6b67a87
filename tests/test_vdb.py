"""OpenVDB input (clvol/volume/vdb.py) against files that OpenVDB itself wrote.

The fixtures are made once per run by Debian's python3-openvdb (10.0.1, run by the system Python)
and re-saved with other codecs by its vdb_tool; what OpenVDB reads back from each file
(``copyToArray`` over the active box) is the expected answer. Without OpenVDB the module skips,
except under CI (CI=true), where scripts/setup.sh installs it, so it fails instead.
"""
from __future__ import annotations

import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from clvol.cli import main
from clvol.errors import SceneError, VolumeError
from clvol.scene import load_scene
from clvol.volume.io import read_volume, write_volume
from clvol.volume.vdb import VdbFile, read_vdb, write_vdb
from reference.grid import grid_density
from tests.openvdb_fixtures import EXPECT, openvdb_missing, run_openvdb, vdb_tool_resave

ROOT = Path(__file__).resolve().parents[1]

FIXTURES = EXPECT + """
rng = np.random.default_rng(7)
def linear(h, t=(0.0, 0.0, 0.0)):
    return vdb.createLinearTransform([[h, 0, 0, 0], [0, h, 0, 0], [0, 0, h, 0], [*t, 1]])

# float: a 5x7x9 (x, y, z) box of values in [0.05, 1) at a negative-origin index box,
# voxel 0.1, index (0, 0, 0) at world (0.3, -0.2, 0.1).
a = (0.05 + 0.95 * rng.random((5, 7, 9))).astype(np.float32)
g = vdb.FloatGrid(); g.copyFromArray(a, ijk=(-3, 2, -17)); g.name = "density"
g.transform = linear(0.1, (0.3, -0.2, 0.1))
vdb.write("float.vdb", grids=[g]); expect("float.vdb", "density", "float.npz")

h = g.deepCopy(); h.saveFloatAsHalf = True
vdb.write("half.vdb", grids=[h]); expect("half.vdb", "density", "half.npz")

# several grids in one file: the density is neither first nor the only float grid.
t = vdb.FloatGrid(); t.copyFromArray(2 * a[:3], ijk=(0, 0, 0)); t.name = "temperature"
v = vdb.Vec3SGrid(); v.copyFromArray(rng.random((4, 4, 4, 3)).astype(np.float32)); v.name = "vel"
d = vdb.FloatGrid(); d.copyFromArray(a[:, :4, :2], ijk=(10, -20, 30)); d.name = "density"
d.transform = linear(0.25)
vdb.write("multi.vdb", grids=[t, v, d])
expect("multi.vdb", "density", "multi_density.npz")
expect("multi.vdb", "temperature", "multi_temperature.npz")
s = t.deepCopy(); s.name = "smoke"
vdb.write("smoke.vdb", grids=[v, s])                    # one scalar grid, not named density
b = t.deepCopy(); b.name = "b"; t2 = t.deepCopy(); t2.name = "a"
vdb.write("two.vdb", grids=[t2, b])                     # two scalar grids, neither is density

# a sparse cloud: three soft balls far apart (negative and positive indices, so several root
# children), a 128^3 constant tile (an upper-node tile) and a 16^3 one (lower-node tiles).
n, lo = 190, -40
x = np.arange(lo, lo + n)
X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
c = np.zeros((n, n, n), np.float32)
for (cx, cy, cz), r in [((-20, 10, 30), 14.0), ((100, 120, 140), 9.0), ((60, -30, 0), 6.5)]:
    dist = np.sqrt((X - cx) ** 2 + (Y - cy) ** 2 + (Z - cz) ** 2)
    c = np.maximum(c, np.clip(1 - dist / r, 0, None).astype(np.float32))
sp = vdb.FloatGrid(); sp.copyFromArray(c, ijk=(lo, lo, lo)); sp.name = "density"
sp.fill((0, 0, 0), (127, 127, 127), 0.25, True)
sp.fill((-16, -16, 64), (-1, -1, 79), 0.6, True)
sp.transform = linear(0.01)
vdb.write("sparse.vdb", grids=[sp]); expect("sparse.vdb", "density", "sparse.npz")

# what clvol must refuse
vec = vdb.Vec3SGrid(); vec.copyFromArray(rng.random((3, 3, 3, 3)).astype(np.float32))
vec.name = "density"; vdb.write("vector.vdb", grids=[vec])
for name, m in [("nonuniform", [[0.1, 0, 0, 0], [0, 0.2, 0, 0], [0, 0, 0.1, 0], [0, 0, 0, 1]]),
                ("rotated", [[0, 0.1, 0, 0], [-0.1, 0, 0, 0], [0, 0, 0.1, 0], [0, 0, 0, 1]])]:
    q = g.deepCopy(); q.transform = vdb.createLinearTransform(m)
    vdb.write(name + ".vdb", grids=[q])
q = g.deepCopy()
q.transform = vdb.createFrustumTransform(xyzMin=(0, 0, 0), xyzMax=(10, 10, 10), taper=0.5,
                                         depth=2.0)
vdb.write("frustum.vdb", grids=[q])
inst = g.copy(); inst.name = "copy"                     # shares g's tree: saved as an instance
vdb.write("instance.vdb", grids=[g, inst])
neg = a.copy(); neg[2, 3, 4] = -0.5
q = vdb.FloatGrid(); q.copyFromArray(neg, ijk=(-3, 2, -17)); q.name = "density"
vdb.write("negative.vdb", grids=[q])
ls = vdb.createLevelSetSphere(radius=3.0, voxelSize=0.5); ls.name = "density"
vdb.write("levelset.vdb", grids=[ls])
"""


@pytest.fixture(scope="module")
def vdbdir(tmp_path_factory):
    missing = openvdb_missing()
    if missing:
        if os.environ.get("CI"):
            pytest.fail(f"OpenVDB is required in CI (scripts/setup.sh installs it): {missing}")
        pytest.skip(missing)
    d = tmp_path_factory.mktemp("vdb")
    run_openvdb(FIXTURES, d)
    for codec in ("zip", "none", "active"):
        vdb_tool_resave(d / "float.vdb", d / f"float_{codec}.vdb", codec)
    return d


def expected(d: Path, name: str):
    """(array [z][y][x], index min (x, y, z), voxel size, world of index 0, active count)."""
    e = np.load(d / f"{name}.npz")
    return (e["a"].transpose(2, 1, 0), e["lo"].astype(np.int64), float(e["voxel"][0]),
            e["origin"].astype(np.float64), int(e["count"]))


def cli(args, capsys):
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


# --------------------------------------------------------------------------- values and boxes

@pytest.mark.parametrize("fname, ename", [
    ("float.vdb", "float"), ("float_zip.vdb", "float"), ("float_none.vdb", "float"),
    ("float_active.vdb", "float"), ("half.vdb", "half")])
def test_values_and_box_match_openvdb(vdbdir, fname, ename):
    """Blosc (OpenVDB's default), zip, no compression, active-mask only, and half floats: the
    interior of the dense grid equals what OpenVDB reads, bit for bit, and the border is 0."""
    a, lo, h, origin, count = expected(vdbdir, ename)
    grid = read_vdb(vdbdir / fname)
    d = grid.density
    assert d.shape == tuple(n + 2 for n in a.shape)
    np.testing.assert_array_equal(d[1:-1, 1:-1, 1:-1], a)
    border = d.copy()
    border[1:-1, 1:-1, 1:-1] = 0
    assert not border.any()
    # Voxel centres where OpenVDB's transform puts them (clvol's voxel 1 is index lo).
    for axis in range(3):
        np.testing.assert_allclose(grid.voxel_centers(axis)[1], origin[axis] + h * lo[axis],
                                   rtol=0, atol=1e-12)
    np.testing.assert_allclose(grid.cell_size, h, rtol=1e-12)
    with VdbFile(vdbdir / fname) as vf:
        assert vf.grids[0].active_voxels == count


def test_half_values_are_float16(vdbdir):
    """The half file holds float16-rounded values (so the half path really ran) that differ
    from the float file's by at most float16's rounding (relative 2^-11)."""
    full = read_vdb(vdbdir / "float.vdb").density
    half = read_vdb(vdbdir / "half.vdb").density
    assert np.array_equal(half, half.astype(np.float16).astype(np.float32))
    assert not np.array_equal(full, half)
    np.testing.assert_allclose(half, full, rtol=2.0 ** -11, atol=0)


def test_sparse_cloud_with_tiles(vdbdir):
    a, lo, h, origin, count = expected(vdbdir, "sparse")
    with VdbFile(vdbdir / "sparse.vdb") as vf:
        g = vf.grids[0]
        # The file really has root children on both sides of 0 and tiles at both levels.
        assert len(g.uppers) >= 2
        assert any((~u.child & u.active).any() for u in g.uppers)
        assert any((~low.child & low.active).any() for u in g.uppers for low in u.lowers)
        assert any(len(low.tile_slots) for u in g.uppers for low in u.lowers)
        assert g.active_voxels == count
        grid = vf.read(g)
    np.testing.assert_array_equal(grid.density[1:-1, 1:-1, 1:-1], a)


def test_max_resolution_box_filter_keeps_mass(vdbdir):
    """Downsampling while reading equals an independent box filter of OpenVDB's dense array
    (padded with one coarse cell of zeros), and keeps the mass: sum * cell volume."""
    a, lo, h, origin, count = expected(vdbdir, "sparse")
    grid = read_vdb(vdbdir / "sparse.vdb", max_resolution=40)
    nz, ny, nx = grid.density.shape
    assert max(nx, ny, nz) <= 40
    f = int(round(grid.cell_size[0] / h))
    assert f > 1
    # Independent: pad [z][y][x] by f zeros before and enough after, then mean over f^3 blocks.
    padded = np.zeros((nz * f, ny * f, nx * f), np.float64)
    padded[f:f + a.shape[0], f:f + a.shape[1], f:f + a.shape[2]] = a
    want = padded.reshape(nz, f, ny, f, nx, f).mean(axis=(1, 3, 5))
    # float32 partial sums of float64 block sums: a few ulps of the largest value.
    np.testing.assert_allclose(grid.density, want, rtol=0, atol=1e-6)
    mass_fine = a.astype(np.float64).sum() * h ** 3
    mass = grid.density.astype(np.float64).sum() * np.prod(grid.cell_size)
    assert mass == pytest.approx(mass_fine, rel=1e-6)
    # The coarse box starts one coarse cell before the active box, as at full resolution.
    np.testing.assert_allclose(grid.bbox_min, origin + h * (lo - f - 0.5), atol=1e-12)


def test_trilinear_falls_to_background_at_the_active_edge(vdbdir):
    """Sampling the dense grid the renderer's way (reference/grid.py, twin of cl/include/grid.h)
    gives OpenVDB's trilinear value (BoxSampler: between voxel centres, background 0 outside the
    active voxels) inside, across and beyond every face of the active box: no clamp to the last
    active voxel. Tolerance 2e-6: float64 twin arithmetic on float32 data near 1."""
    a, lo, h, origin, count = expected(vdbdir, "float")
    grid = read_vdb(vdbdir / "float.vdb")
    ext = np.array(a.shape[::-1])                       # (nx, ny, nz) of the active box

    def openvdb_trilinear(p):
        u = (p - origin) / h - lo                       # index coordinates relative to lo
        i0 = np.floor(u).astype(np.int64)
        t = u - i0
        out = np.zeros(len(p))
        for corner in np.ndindex(2, 2, 2):
            c = i0 + corner
            inside = np.all((c >= 0) & (c < ext), axis=1)
            v = np.zeros(len(p))
            v[inside] = a[c[inside, 2], c[inside, 1], c[inside, 0]]
            w = np.prod(np.where(corner, t, 1 - t), axis=1)
            out += w * v
        return out

    rng = np.random.default_rng(3)
    first = origin + h * lo                             # centre of the first active voxel
    last = origin + h * (lo + ext - 1)
    pts = []
    for axis in range(3):
        for s in np.linspace(-1.6, 1.6, 33):            # across both faces on this axis
            for side, edge in ((-1, first), (1, last)):
                p = first + rng.random(3) * (last - first)
                p[axis] = edge[axis] + side * s * h
                pts.append(p)
    pts.append(first)
    pts += list(first + rng.random((200, 3)) * (last - first))
    pts = np.array(pts)
    got = grid_density(grid.density.astype(np.float64), grid.bbox_min, grid.bbox_max, pts)
    np.testing.assert_allclose(got, openvdb_trilinear(pts), rtol=0, atol=2e-6)
    # Half a voxel past the last active centre the density is half the edge value, not all of it.
    p = last.copy()
    p[0] += 0.5 * h
    edge = openvdb_trilinear(last[None])[0]
    assert grid_density(grid.density.astype(np.float64), grid.bbox_min, grid.bbox_max,
                        p[None])[0] == pytest.approx(0.5 * edge, abs=2e-6)


# --------------------------------------------------------------------------- grid choice

def test_grid_choice(vdbdir):
    dens, *_ = expected(vdbdir, "multi_density")
    temp, *_ = expected(vdbdir, "multi_temperature")
    np.testing.assert_array_equal(read_vdb(vdbdir / "multi.vdb").density[1:-1, 1:-1, 1:-1], dens)
    np.testing.assert_array_equal(
        read_vdb(vdbdir / "multi.vdb", grid="temperature").density[1:-1, 1:-1, 1:-1], temp)
    # an instanced grid next to it does not stop the density from loading
    a, *_ = expected(vdbdir, "float")
    np.testing.assert_array_equal(read_vdb(vdbdir / "instance.vdb").density[1:-1, 1:-1, 1:-1], a)
    # the only scalar grid, whatever its name
    np.testing.assert_array_equal(read_vdb(vdbdir / "smoke.vdb").density[1:-1, 1:-1, 1:-1], temp)


@pytest.mark.parametrize("fname, grid, words", [
    ("two.vdb", None, ["cannot choose", "'a' (float)", "'b' (float)", "[volume] grid"]),
    ("multi.vdb", "nope", ["no grid named 'nope'", "'temperature' (float)", "'vel' (vec3s)"]),
    ("multi.vdb", "vel", ["'vel' is a vector grid"]),
    ("instance.vdb", "copy", ["an instance of grid 'density'", "not read"]),
])
def test_grid_choice_refusals(vdbdir, fname, grid, words):
    with pytest.raises(VolumeError) as e:
        read_vdb(vdbdir / fname, grid=grid)
    for w in words:
        assert w in str(e.value)


# --------------------------------------------------------------------------- malformed input

def _grid_pos(path: Path) -> int:
    """File offset of the first grid (where its compression flags are), from the descriptor."""
    b = path.read_bytes()
    pos = 8 + 12 + 1 + 36
    (nmeta,) = struct.unpack_from("<I", b, pos)
    pos += 4
    for _ in range(nmeta):                       # name, type, value: three length-prefixed
        for _ in range(3):
            (n,) = struct.unpack_from("<I", b, pos)
            pos += 4 + n
    pos += 4                                     # grid count
    for _ in range(3):                           # unique name, type, instance parent
        (n,) = struct.unpack_from("<I", b, pos)
        pos += 4 + n
    return struct.unpack_from("<q", b, pos)[0]


@pytest.mark.parametrize("case, words", [
    ("truncated_header", ["truncated .vdb file"]),
    ("truncated_topology", ["truncated .vdb file"]),
    ("truncated_buffers", ["truncated .vdb file", "the end of grid 'density' is at byte"]),
    ("vector", ["'density' is a vector grid (vec3s)"]),
    ("unknown_compression", ["unknown compression flags 0x10"]),
    ("not_vdb", ["not an OpenVDB file"]),
    ("nonuniform", ["not uniform", "cubic voxels"]),
    ("rotated", ["rotates or shears"]),
    ("frustum", ["NonlinearFrustumMap is not a linear transform"]),
    ("levelset", ["level set"]),
    ("negative", ["NaN, infinite or negative", "first at index (-1, 5, -13) = -0.5"]),
])
def test_malformed_files_exit_2_with_one_line(vdbdir, tmp_path, capsys, case, words):
    src = (vdbdir / "float.vdb").read_bytes()
    bad = tmp_path / f"{case}.vdb"
    if case == "truncated_header":
        bad.write_bytes(src[:30])
    elif case == "truncated_topology":
        bad.write_bytes(src[:_grid_pos(vdbdir / "float.vdb") + 300])
    elif case == "truncated_buffers":
        bad.write_bytes(src[:-40])
    elif case == "unknown_compression":
        b = bytearray(src)
        pos = _grid_pos(vdbdir / "float.vdb")
        assert struct.unpack_from("<I", b, pos)[0] == 0x6      # blosc + active mask
        struct.pack_into("<I", b, pos, 0x10)
        bad.write_bytes(bytes(b))
    elif case == "not_vdb":
        bad.write_text("[volume]\nfile = 'cloud.vdb'\n")
    else:
        bad.write_bytes((vdbdir / f"{case}.vdb").read_bytes())
    code, out, err = cli(["volume", "convert", bad, tmp_path / "out.npz"], capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"clvol: error: {bad}")
    for w in words:
        assert w in lines[0]
    assert not (tmp_path / "out.npz").exists()


def test_malformed_file_exit_status_from_a_subprocess(vdbdir, tmp_path):
    """The real command line: status 2 and one line on stderr, no traceback."""
    bad = tmp_path / "cut.vdb"
    bad.write_bytes((vdbdir / "float.vdb").read_bytes()[:-40])
    r = subprocess.run([sys.executable, "-m", "clvol", "volume", "convert", str(bad),
                        str(tmp_path / "x.npz")], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 2
    assert len(r.stderr.strip().splitlines()) == 1 and "truncated .vdb file" in r.stderr


def test_device_buffer_limit_is_a_clear_message(vdbdir):
    """A grid too big for one device buffer is refused before it is read, with a max_resolution
    that fits; that value then loads within the limit."""
    limit = 200_000                                     # bytes; the full grid needs ~17 MB
    with pytest.raises(VolumeError) as e:
        read_vdb(vdbdir / "sparse.vdb", max_bytes=limit)
    msg = str(e.value)
    assert "more than the" in msg and "max_resolution = " in msg
    r = int(msg.split("max_resolution = ")[1].split()[0])
    grid = read_vdb(vdbdir / "sparse.vdb", max_resolution=r, max_bytes=limit)
    assert grid.density.nbytes <= limit
    assert max(grid.resolution) == r


# --------------------------------------------------------------------------- CLI

def test_volume_info_lists_every_grid(vdbdir, capsys):
    code, out, err = cli(["volume", "info", vdbdir / "multi.vdb"], capsys)
    assert code == 0, err
    a, lo, h, origin, count = expected(vdbdir, "multi_density")
    _, tlo, _, _, tcount = expected(vdbdir, "multi_temperature")
    assert "3 grid(s)" in out
    assert "grid 'temperature': float" in out and f"active voxels: {tcount}" in out
    assert "grid 'vel': vec3s" in out and "active voxels: 64" in out
    assert "grid 'density': float" in out and f"active voxels: {count}" in out
    hi = lo + np.array(a.shape[::-1]) - 1
    assert f"index bbox: ({lo[0]}, {lo[1]}, {lo[2]}) .. ({hi[0]}, {hi[1]}, {hi[2]})" in out
    wlo, whi = origin + h * (lo - 0.5), origin + h * (hi + 0.5)
    assert "world bbox: (" + ", ".join(f"{v:.6g}" for v in wlo) + ") .. (" \
        + ", ".join(f"{v:.6g}" for v in whi) + ")" in out
    assert "voxel size: (0.25, 0.25, 0.25)" in out


def test_volume_info_warns_of_a_grid_that_cannot_be_rendered(vdbdir, capsys):
    """A level set is listed with the reason a scene would refuse it (before: listed as any
    grid, the refusal came only at render time); a fog grid gets no such line."""
    code, out, err = cli(["volume", "info", vdbdir / "levelset.vdb"], capsys)
    assert code == 0, err
    line = [l for l in out.splitlines() if "cannot be rendered" in l]
    assert len(line) == 1 and "level set" in line[0], out
    code, out, err = cli(["volume", "info", vdbdir / "float.vdb"], capsys)
    assert code == 0 and "cannot be rendered" not in out


def test_convert_vdb_to_npz_and_back(vdbdir, tmp_path, capsys):
    """vdb -> npz keeps the grid and box; npz -> vdb is read back by OpenVDB itself with the
    same values at the same world positions."""
    npz = tmp_path / "c.npz"
    assert cli(["volume", "convert", vdbdir / "sparse.vdb", npz], capsys)[0] == 0
    a = read_vdb(vdbdir / "sparse.vdb")
    b = read_volume(npz)
    np.testing.assert_array_equal(a.density, b.density)
    np.testing.assert_array_equal(a.bbox_min, b.bbox_min)
    out = tmp_path / "back.vdb"
    assert cli(["volume", "convert", npz, out], capsys)[0] == 0
    run_openvdb(EXPECT + f"expect({str(out)!r}, 'density', 'back.npz')\n", tmp_path)
    e, lo, h, origin, count = expected(tmp_path, "back")
    want, wlo, wh, worigin, wcount = expected(vdbdir, "sparse")
    np.testing.assert_array_equal(e, want)
    assert count == int(np.count_nonzero(want))
    assert h == pytest.approx(wh, rel=1e-12)
    np.testing.assert_allclose(origin + h * lo, worigin + wh * wlo, rtol=0, atol=1e-12)
    # and clvol reads its own file back to the same grid
    c = read_volume(out)
    np.testing.assert_array_equal(c.density, a.density)
    np.testing.assert_allclose(c.bbox_min, a.bbox_min, rtol=0, atol=1e-12)


def test_convert_keeps_every_grid_and_openvdb_reads_them(vdbdir, tmp_path, capsys):
    """npz (density + temperature) -> vdb: OpenVDB itself reads both grids with the values
    written (before, the temperature was dropped); a .vdb with a grid clvol cannot keep (the
    vec3s 'vel' of multi.vdb) is refused in one line rather than converted without it."""
    rng = np.random.default_rng(2)
    d = rng.random((6, 7, 9), dtype=np.float32)
    t = np.where(d > 0.5, 1500.0 * d, 0).astype(np.float32)
    np.savez(tmp_path / "f.npz", density=d, temperature=t, bbox_min=np.zeros(3),
             bbox_max=np.array([0.9, 0.7, 0.6]))                    # cubic voxels of 0.1
    assert cli(["volume", "convert", tmp_path / "f.npz", tmp_path / "f.vdb"], capsys)[0] == 0
    run_openvdb(EXPECT + f"expect({str(tmp_path / 'f.vdb')!r}, 'density', 'd.npz')\n"
                f"expect({str(tmp_path / 'f.vdb')!r}, 'temperature', 't.npz')\n", tmp_path)
    for name, want in (("d", d), ("t", t)):
        e, lo, _, _, count = expected(tmp_path, name)
        assert count == np.count_nonzero(want)
        hi = lo + np.array(e.shape[::-1])
        np.testing.assert_array_equal(e, want[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]])
    code, out, err = cli(["volume", "convert", vdbdir / "multi.vdb", tmp_path / "m.npz"], capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "'vel'" in lines[0] and "keeps every grid" in lines[0]
    assert not (tmp_path / "m.npz").exists()


def test_write_vdb_refuses_non_cubic_voxels(tmp_path):
    from clvol.volume.grid import DensityGrid
    g = DensityGrid(np.ones((2, 3, 4), np.float32), np.zeros(3), np.array([1.0, 1.0, 1.0]))
    with pytest.raises(VolumeError, match="cubic voxels"):
        write_vdb(tmp_path / "x.vdb", g)


# --------------------------------------------------------------------------- scenes

SCENE = """
[volume]
{volume}

[medium]
density_scale = 12.0
albedo = 0.9
phase = {{ type = "hg", g = 0.4 }}

[light]
direction = [0.5, 0.8, 0.3]
environment = 0.1

[camera]
origin = [{cx}, {cy}, {cz}]
target = [{tx}, {ty}, {tz}]
fov_y = 40.0
width = 20
height = 16
"""


def _write_scene(path: Path, volume: str, grid) -> Path:
    centre = 0.5 * (grid.bbox_min + grid.bbox_max)
    cam = centre + np.array([0.2, 0.3, 2.0])
    path.write_text(SCENE.format(volume=volume, cx=cam[0], cy=cam[1], cz=cam[2], tx=centre[0],
                                 ty=centre[1], tz=centre[2]))
    return path


def _fmt(v) -> str:
    return "[" + ", ".join(repr(float(x)) for x in v) + "]"


@pytest.mark.parametrize("method, extra", [("raymarch", []),
                                           ("pathtrace", ["--seed", "1", "--spp", "4"])])
def test_vdb_scene_renders_like_npy_with_the_same_box(vdbdir, tmp_path, capsys, method, extra):
    """The .vdb scene and a .npy of OpenVDB's own values with the equivalent box give the same
    image (identical inputs to the renderer, so identical pixels)."""
    from clvol.image import read_exr
    grid = read_vdb(vdbdir / "float.vdb")
    a, lo, h, origin, count = expected(vdbdir, "float")
    np.save(tmp_path / "d.npy", np.pad(a, 1))
    bmin, bmax = origin + h * (lo - 1.5), origin + h * (lo + np.array(a.shape[::-1]) + 0.5)
    s1 = _write_scene(tmp_path / "vdb.toml", f'file = "{vdbdir / "float.vdb"}"', grid)
    s2 = _write_scene(tmp_path / "npy.toml", f'file = "d.npy"\nbbox_min = {_fmt(bmin)}\n'
                      f'bbox_max = {_fmt(bmax)}', grid)
    imgs = []
    for s in (s1, s2):
        out = tmp_path / f"{s.stem}_{method}.exr"
        code, _, err = cli(["render", s, "--method", method, "-o", out] + extra, capsys)
        assert code == 0, err
        imgs.append(read_exr(out).rgb)
    assert imgs[0].max() > 0.01                          # the volume is in view and lit
    np.testing.assert_array_equal(imgs[0], imgs[1])


def test_scene_fields(vdbdir, tmp_path):
    grid = read_vdb(vdbdir / "multi.vdb", grid="temperature")
    f = vdbdir / "multi.vdb"
    s = load_scene(_write_scene(tmp_path / "a.toml", f'file = "{f}"\ngrid = "temperature"\n'
                                f'max_resolution = 8', grid))
    assert s.volume.grid == "temperature" and s.volume.max_resolution == 8
    g = s.volume.load()
    assert max(g.resolution) <= 8
    # bbox overrides the file's placement
    s = load_scene(_write_scene(tmp_path / "b.toml", f'file = "{f}"\nbbox_min = [0, 0, 0]\n'
                                f'bbox_max = [1, 2, 3]', grid))
    g = s.volume.load()
    np.testing.assert_array_equal(g.bbox_max, [1, 2, 3])
    np.testing.assert_array_equal(g.density, read_vdb(f).density)
    # round trip through the scene writer keeps the new fields
    from clvol.scene import dumps_scene, scene_from_dict
    s = load_scene(tmp_path / "a.toml")
    assert scene_from_dict(s.to_dict()).volume == s.volume
    assert "max_resolution = 8" in dumps_scene(s)


@pytest.mark.parametrize("volume, words", [
    ('file = "{npy}"\ngrid = "density"', ["[volume.grid]", "applies to .vdb files only"]),
    ('file = "{npy}"\nmax_resolution = 64', ["[volume.max_resolution]", ".vdb files only"]),
    ('file = "{vdb}"\nmax_resolution = 2', ["[volume.max_resolution] = 2", "4..16384"]),
    ('file = "{vdb}"\nmax_resolution = 64.0', ["[volume.max_resolution]", "integer"]),
    ('file = "{vdb}"\ngrid = ""', ["[volume.grid]", "non-empty"]),
    ('generator = "sphere"\nmax_resolution = 64', ["[volume.max_resolution]", "unknown key"]),
])
def test_scene_field_errors(vdbdir, tmp_path, volume, words):
    np.save(tmp_path / "d.npy", np.ones((2, 2, 2), np.float32))
    grid = read_vdb(vdbdir / "float.vdb")
    text = volume.format(npy=tmp_path / "d.npy", vdb=vdbdir / "float.vdb")
    with pytest.raises(SceneError) as e:
        load_scene(_write_scene(tmp_path / "s.toml", text, grid))
    for w in words:
        assert w in str(e.value)


def test_read_volume_refuses_vdb_options_for_other_formats(tmp_path):
    np.save(tmp_path / "d.npy", np.ones((2, 2, 2), np.float32))
    with pytest.raises(VolumeError, match="max_resolution applies to .vdb files only"):
        read_volume(tmp_path / "d.npy", max_resolution=8)
    write_volume(tmp_path / "d.npz", read_volume(tmp_path / "d.npy"))


def test_scene_load_checks_the_device_buffer_limit(vdbdir, tmp_path):
    """VolumeSpec.load refuses a grid above max_bytes, and by default takes the limit from
    the OpenCL device (CL_DEVICE_MAX_MEM_ALLOC_SIZE)."""
    from clvol.runtime import get_runtime
    from clvol.scenemodel import _device_buffer_limit
    assert _device_buffer_limit() == int(get_runtime().device.max_mem_alloc_size)
    grid = read_vdb(vdbdir / "sparse.vdb")
    s = load_scene(_write_scene(tmp_path / "s.toml", f'file = "{vdbdir / "sparse.vdb"}"', grid))
    with pytest.raises(VolumeError, match=r"more than the .* GiB the OpenCL device allows"):
        s.volume.load(max_bytes=grid.density.nbytes - 1)
    assert s.volume.load(max_bytes=grid.density.nbytes).density.shape == grid.density.shape


def test_volume_info_refuses_density_scale_for_vdb(vdbdir, capsys):
    code, out, err = cli(["volume", "info", vdbdir / "float.vdb", "--density-scale", "8"], capsys)
    assert code == 2 and "--density-scale is for the statistics of a dense grid" in err


# --------------------------------------------------------------------------- box filter

@pytest.mark.parametrize("f", [1, 2, 3, 5, 7])
def test_box_accumulator_matches_a_dense_box_filter(f):
    """Blocks and constant tiles at random offsets, overlapping and crossing the kept range,
    summed piece by piece, equal a box filter of the dense sum (clipped to the kept range).
    Tolerance 1e-5 absolute on values <= 3: float32 sums of float64 partial sums."""
    from clvol.volume.resample import BoxAccumulator
    rng = np.random.default_rng(f)
    base = np.array([-7, 3, -20])
    shape = np.array([6, 5, 7])
    keep_lo, keep_hi = base + f, base + shape * f - f + 1     # as the reader: one empty cell
    acc = BoxAccumulator(base, shape, f, keep_lo=keep_lo, keep_hi=keep_hi)
    span = shape * f
    dense = np.zeros(tuple(span), np.float64)                 # [x][y][z] from base
    for _ in range(6):
        n = rng.integers(1, 40, 3)
        o = base + rng.integers(-10, span.max(), 3)
        b = rng.random(tuple(n)).astype(np.float32)
        acc.add_block(b, o)
        lo, hi = np.maximum(o, base), np.minimum(o + n, base + span)
        if np.all(hi > lo):
            dense[tuple(slice(a - bb, c - bb) for a, c, bb in zip(lo, hi, base))] += \
                b[tuple(slice(a - oo, c - oo) for a, c, oo in zip(lo, hi, o))]
    for _ in range(3):
        lo = base + rng.integers(-5, span.max(), 3)
        hi = lo + rng.integers(1, 30, 3)
        v = float(rng.random())
        acc.add_constant(lo, hi, v)
        a, c = np.maximum(lo, base), np.minimum(hi, base + span)
        if np.all(c > a):
            dense[tuple(slice(x - bb, y - bb) for x, y, bb in zip(a, c, base))] += v
    mask = np.zeros_like(dense, bool)
    mask[tuple(slice(a - bb, c - bb) for a, c, bb in zip(keep_lo, keep_hi, base))] = True
    dense[~mask] = 0
    want = dense.reshape(shape[0], f, shape[1], f, shape[2], f).mean(axis=(1, 3, 5))
    np.testing.assert_allclose(acc.density(), want.transpose(2, 1, 0), rtol=0, atol=1e-5)
