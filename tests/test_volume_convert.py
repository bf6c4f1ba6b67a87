"""`clvol volume convert` keeps every grid it reads or refuses with one line (docs/volumes.md,
"Converting"). Before, only the density was written: `fire_0001.npz -> .vdb` lost the
`temperature` grid, and the fire scene then failed on the converted file."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from clvol.cli import main
from clvol.errors import VolumeError
from clvol.volume.grid import DensityGrid
from clvol.volume.io import read_volume
from clvol.volume.vdb import VdbFile, read_vdb, write_vdb


def _fire_like(path, own_box: bool = True):
    """A non-cubic grid on a non-default box (nx, ny, nz all differ, so a swapped axis shows),
    a temperature on the density's box, and optionally a smoke grid on a box of its own."""
    rng = np.random.default_rng(5)
    d = rng.random((10, 12, 14), dtype=np.float32)
    d[d < 0.4] = 0                                      # inactive voxels, as in a real file
    d[:, :, -1] = 0.75                                  # active up to the box's edge
    t = (rng.random((10, 12, 14)) * 2500).astype(np.float32)
    t[:, :4] = 0                                        # a cold region
    arrays = dict(density=d, temperature=t, bbox_min=np.array([-0.7, -0.1, -0.5]) / 3,
                  bbox_max=np.array([0.7, 1.1, 0.5]) / 3)     # 1/3: not exact in binary
    if own_box:
        s = rng.random((4, 6, 8), dtype=np.float32)
        arrays.update(smoke=s, smoke_bbox_min=np.array([0.1, 0.2, 0.3]),
                      smoke_bbox_max=np.array([0.9, 0.8, 0.7]))
    np.savez(path, **arrays)
    return arrays


def _convert(src, dst):
    p = subprocess.run([sys.executable, "-m", "clvol", "volume", "convert", str(src), str(dst)],
                       capture_output=True, text=True, timeout=120)
    return p.returncode, p.stdout, p.stderr


@pytest.mark.parametrize("own_box", [True, False])
def test_npz_vdb_npz_round_trip_is_bit_equal_for_every_grid(tmp_path, own_box):
    want = _fire_like(tmp_path / "a.npz", own_box)
    rc, out, err = _convert(tmp_path / "a.npz", tmp_path / "a.vdb")
    assert rc == 0, err
    assert out.strip().endswith("(grids: density, " + ", ".join(
        sorted(k for k in want if k not in ("density", "bbox_min", "bbox_max")
               and not k.endswith(("_bbox_min", "_bbox_max")))) + ")")
    with VdbFile(tmp_path / "a.vdb") as vf:
        assert sorted(g.name for g in vf.grids) == sorted(
            k for k in want if np.ndim(want[k]) == 3)
    rc, out, err = _convert(tmp_path / "a.vdb", tmp_path / "b.npz")
    assert rc == 0, err
    with np.load(tmp_path / "b.npz") as got:
        assert sorted(got.files) == sorted(want)
        for k, v in want.items():
            assert got[k].dtype == v.dtype and got[k].shape == v.shape, k
            assert got[k].tobytes() == v.tobytes(), k            # bit-equal, boxes included


def test_npz_to_npz_keeps_every_grid(tmp_path):
    want = _fire_like(tmp_path / "a.npz")
    assert _convert(tmp_path / "a.npz", tmp_path / "b.npz")[0] == 0
    with np.load(tmp_path / "b.npz") as got:
        assert sorted(got.files) == sorted(want)
        for k, v in want.items():
            assert got[k].tobytes() == v.tobytes(), k


@pytest.mark.parametrize("ext", [".vol", ".npy"])
def test_a_one_grid_format_is_refused_in_one_line(tmp_path, ext):
    _fire_like(tmp_path / "a.npz", own_box=False)
    rc, out, err = _convert(tmp_path / "a.npz", tmp_path / f"b{ext}")
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1, err
    assert "'temperature'" in lines[0] and "convert to .npz or .vdb" in lines[0]
    assert not (tmp_path / f"b{ext}").exists()


def test_a_density_alone_still_converts_to_vol(tmp_path, capsys):
    g = DensityGrid(np.arange(24, dtype=np.float32).reshape(2, 3, 4), np.zeros(3), np.array([4., 3, 2]))
    np.savez(tmp_path / "a.npz", density=g.density, bbox_min=g.bbox_min, bbox_max=g.bbox_max)
    assert main(["volume", "convert", str(tmp_path / "a.npz"), str(tmp_path / "a.vol")]) == 0
    assert capsys.readouterr().out.strip() == f"wrote {tmp_path / 'a.vol'}"
    np.testing.assert_array_equal(read_volume(tmp_path / "a.vol").density, g.density)


def test_the_fire_scenes_emission_reads_the_converted_file_alike(tmp_path):
    """What the fire scene reads ([emission] grid = "temperature", blackbody) from the .npz
    and from its .vdb conversion: the same grid on the same box."""
    from clvol.emission import load_emission
    from clvol.scenemodel import EmissionSpec
    _fire_like(tmp_path / "a.npz", own_box=False)
    assert _convert(tmp_path / "a.npz", tmp_path / "a.vdb")[0] == 0
    spec = EmissionSpec(grid="temperature", kind="blackbody", scale=1.0)
    got = {}
    for ext in (".npz", ".vdb"):
        dens = read_volume(tmp_path / f"a{ext}")
        got[ext] = (dens, load_emission(spec, tmp_path / f"a{ext}", dens))
    (dn, en), (dv, ev) = got[".npz"], got[".vdb"]
    assert dn.density.tobytes() == dv.density.tobytes()
    assert dn.bbox_min.tobytes() == dv.bbox_min.tobytes()
    assert en.values.tobytes() == ev.values.tobytes()
    assert en.own_box == ev.own_box is False


def test_a_stored_box_is_ignored_when_filtering_and_empty_grids_read_back(tmp_path):
    """Reading at a lower max_resolution filters as for any file (active box plus border);
    a further grid of zeros (no active voxel) comes back as zeros of its shape."""
    d = np.zeros((8, 16, 24), np.float32)
    d[2:6, 3:13, 4:20] = 1.0
    g = DensityGrid(d, np.zeros(3), np.array([3.0, 2.0, 1.0]))
    zero = DensityGrid(np.zeros((8, 16, 24), np.float32), g.bbox_min, g.bbox_max)
    write_vdb(tmp_path / "z.vdb", g, extra={"cold": zero})
    assert read_vdb(tmp_path / "z.vdb").density.tobytes() == d.tobytes()
    assert read_vdb(tmp_path / "z.vdb", grid="cold").density.tobytes() == zero.density.tobytes()
    small = read_vdb(tmp_path / "z.vdb", max_resolution=12)
    assert max(small.resolution) <= 12
    assert np.sum(small.density) * np.prod(small.cell_size) == pytest.approx(
        np.sum(d) * np.prod(g.cell_size), rel=1e-6)       # the mass is kept
    with pytest.raises(VolumeError, match="cubic voxels"):
        write_vdb(tmp_path / "x.vdb", g, extra={"t": DensityGrid(np.ones((2, 3, 4), np.float32),
                                                         np.zeros(3), np.ones(3))})
