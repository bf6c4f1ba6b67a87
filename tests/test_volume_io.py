"""Volume file I/O: round trips on a non-cubic grid, a hand-made .vol, every malformed input.

The grid is 3 x 5 x 7 (x, y, z) with value 100 z + 10 y + x + 0.5 at voxel (x, y, z), so any
axis swap or transposition changes values and fails the comparisons.
"""
import struct

import numpy as np
import pytest

from clvol.errors import VolumeError
from clvol.volume.grid import DensityGrid
from clvol.volume.io import read_volume, write_volume

NX, NY, NZ = 3, 5, 7


def value(x, y, z):
    return 100.0 * z + 10.0 * y + x + 0.5


def labelled_density():
    d = np.empty((NZ, NY, NX), dtype=np.float32)
    for z in range(NZ):
        for y in range(NY):
            for x in range(NX):
                d[z, y, x] = value(x, y, z)
    return d


# A box exactly representable in float32, so the .vol round trip can be exact.
BMIN = (-1.0, -2.5, 0.25)
BMAX = (2.0, 3.0, 7.75)


def vol_bytes(nx=NX, ny=NY, nz=NZ, values=None, magic=b"VOL", version=3, encoding=1,
              channels=1, bbox=BMIN + BMAX, extra=b"", drop=0):
    """A .vol file assembled with struct, independent of the writer under test.

    ``values(x, y, z)`` gives each voxel; they are written x fastest, then y, then z.
    """
    values = values or value
    head = magic + bytes([version]) + struct.pack("<i", encoding) + struct.pack("<3i", nx, ny, nz)
    head += struct.pack("<i", channels) + struct.pack("<6f", *bbox)
    body = b"".join(struct.pack("<f", values(x, y, z))
                    for z in range(max(nz, 0)) for y in range(max(ny, 0)) for x in range(max(nx, 0)))
    data = head + body + extra
    return data[:len(data) - drop] if drop else data


def write(tmp_path, name, data):
    p = tmp_path / name
    p.write_bytes(data)
    return p


# --------------------------------------------------------------------------- good files

def test_handmade_vol_reads_with_the_right_axes(tmp_path):
    p = write(tmp_path, "hand.vol", vol_bytes())
    g = read_volume(p)
    assert g.resolution == (NX, NY, NZ)
    assert g.density.shape == (NZ, NY, NX)
    assert g.density.dtype == np.float32 and g.density.flags.c_contiguous
    # spot checks written out, then the whole grid
    assert g.density[0, 0, 1] == value(1, 0, 0) == 1.5
    assert g.density[6, 4, 2] == value(2, 4, 6) == 642.5
    assert g.density[3, 0, 0] == 300.5
    np.testing.assert_array_equal(g.density, labelled_density())
    np.testing.assert_array_equal(g.bbox_min, BMIN)
    np.testing.assert_array_equal(g.bbox_max, BMAX)


def test_vol_writer_matches_handmade_bytes(tmp_path):
    p = tmp_path / "w.vol"
    write_volume(p, DensityGrid(labelled_density(), np.array(BMIN), np.array(BMAX)))
    assert p.read_bytes() == vol_bytes()


@pytest.mark.parametrize("ext", [".vol", ".npz"])
def test_round_trip_with_bbox(tmp_path, ext):
    g = DensityGrid(labelled_density(), np.array(BMIN), np.array(BMAX))
    p = tmp_path / f"grid{ext}"
    write_volume(p, g)
    back = read_volume(p)
    np.testing.assert_array_equal(back.density, g.density)
    assert back.density.dtype == np.float32
    np.testing.assert_array_equal(back.bbox_min, BMIN)
    np.testing.assert_array_equal(back.bbox_max, BMAX)
    assert back.resolution == (NX, NY, NZ)


def test_round_trip_npy_default_bbox(tmp_path):
    g = DensityGrid.from_array(labelled_density())
    p = tmp_path / "grid.npy"
    write_volume(p, g)
    back = read_volume(p)
    np.testing.assert_array_equal(back.density, labelled_density())
    np.testing.assert_array_equal(back.bbox_min, [-0.5, -0.5, -0.5])
    np.testing.assert_array_equal(back.bbox_max, [0.5, 0.5, 0.5])


def test_npy_layout_is_z_y_x(tmp_path):
    # A bare array saved by NumPy is read as [z][y][x]: resolution is its shape reversed.
    p = tmp_path / "bare.npy"
    np.save(p, labelled_density())
    assert read_volume(p).resolution == (NX, NY, NZ)


def test_npz_without_bbox_gets_default(tmp_path):
    p = tmp_path / "d.npz"
    np.savez(p, density=labelled_density())
    g = read_volume(p)
    np.testing.assert_array_equal(g.bbox_min, [-0.5] * 3)
    np.testing.assert_array_equal(g.bbox_max, [0.5] * 3)


def test_float64_and_fortran_order_are_converted_exactly(tmp_path):
    d64 = np.asfortranarray(labelled_density().astype(np.float64))
    p = tmp_path / "f64.npy"
    np.save(p, d64)
    g = read_volume(p)
    assert g.density.dtype == np.float32 and g.density.flags.c_contiguous
    np.testing.assert_array_equal(g.density, labelled_density())


def test_extension_is_case_insensitive(tmp_path):
    p = write(tmp_path, "UPPER.VOL", vol_bytes())
    assert read_volume(p).resolution == (NX, NY, NZ)


# --------------------------------------------------------------------------- malformed .vol

def _nan_at_2_1_0(x, y, z):
    return float("nan") if (x, y, z) in ((0, 1, 2), (2, 4, 6)) else 1.0


def _inf_at_1_0_0(x, y, z):
    return float("inf") if (x, y, z) == (0, 0, 1) else 1.0


def _negative_at_0_3_2(x, y, z):
    return -0.25 if (x, y, z) == (2, 3, 0) else 1.0


BAD_VOL = {
    # name: (file bytes, fragments the message must contain)
    "truncated": (vol_bytes(drop=4), ["truncated", "3x5x7", "420 data bytes", "468 bytes in all",
                                      "file has 464 bytes"]),
    "extra_bytes": (vol_bytes(extra=b"\0" * 8), ["over-long", "468 bytes in all", "file has 476 bytes"]),
    "header_only_part": (vol_bytes()[:20], ["truncated", "header", "20 bytes"]),
    "empty_file": (b"", ["truncated", "0 bytes"]),
    "wrong_magic": (vol_bytes(magic=b"VOX"), ["magic", "b'VOX'"]),
    "version_2": (vol_bytes(version=2), ["version 2"]),
    "encoding_2": (vol_bytes(encoding=2), ["encoding 2", "float16", "only 1 (float32)"]),
    "channels_3": (vol_bytes(channels=3), ["3 channels", "exactly 1"]),
    "nan": (vol_bytes(values=_nan_at_2_1_0), ["2 NaN", "[z, y, x] = (2, 1, 0)"]),
    "inf": (vol_bytes(values=_inf_at_1_0_0), ["1 infinite", "[z, y, x] = (1, 0, 0)", "inf"]),
    "negative": (vol_bytes(values=_negative_at_0_3_2), ["1 negative", "[z, y, x] = (0, 3, 2)", "-0.25"]),
    "zero_size": (vol_bytes(nx=0), ["0, 5, 7", "at least one voxel"]),
    "negative_size": (vol_bytes(ny=-5), ["3, -5, 7", "at least one voxel"]),
    "bbox_inverted": (vol_bytes(bbox=(0, 0, 0, 1, -1, 1)), ["bbox_min", "must be < bbox_max", "not on y"]),
    "bbox_nan": (vol_bytes(bbox=(0, 0, float("nan"), 1, 1, 1)), ["bbox_min", "not finite"]),
}


def assert_rejected(p, fragments):
    """read_volume(p) raises a VolumeError naming the file and containing every fragment."""
    with pytest.raises(VolumeError) as err:
        read_volume(p)
    msg = str(err.value)
    assert str(p) in msg
    for frag in fragments:
        assert frag in msg, f"{frag!r} not in {msg!r}"


@pytest.mark.parametrize("case", sorted(BAD_VOL))
def test_malformed_vol_is_rejected_with_file_and_value(tmp_path, case):
    data, fragments = BAD_VOL[case]
    p = write(tmp_path, f"bad_{case}.vol", data)
    assert_rejected(p, fragments)


# --------------------------------------------------------------------------- malformed .npy / .npz

def _npy(tmp_path, name, arr):
    p = tmp_path / name
    np.save(p, arr)
    return p


@pytest.mark.parametrize("arr, fragments", [
    (np.zeros((4, 0, 3), np.float32), ["empty", "(4, 0, 3)"]),
    (np.zeros((4, 3), np.float32), ["3-D", "2-D", "(4, 3)"]),
    (np.ones((2, 2, 2), np.uint8), ["uint8", "floating-point"]),
    (np.array([[[1.0, -2.0], [-3.0, 4.0]]], np.float64), ["2 negative", "(0, 0, 1)"]),
    (np.array([[[1.0, np.nan]]], np.float32), ["1 NaN", "(0, 0, 1)"]),
    (np.array([[[1.0, -np.inf]]], np.float32), ["1 infinite", "(0, 0, 1)"]),
    (np.array([[[1.0, 1e300]]], np.float64), ["1e+300", "overflows float32"]),
])
def test_malformed_npy_is_rejected(tmp_path, arr, fragments):
    p = _npy(tmp_path, "bad.npy", arr)
    assert_rejected(p, fragments)


def test_corrupt_npy_is_a_volume_error(tmp_path):
    p = write(tmp_path, "junk.npy", b"not numpy at all")
    with pytest.raises(VolumeError, match="cannot read as .npy"):
        read_volume(p)


@pytest.mark.parametrize("arrays, fragments", [
    ({"dens": np.ones((2, 2, 2), np.float32)}, ["unknown key", "dens", "allowed"]),
    ({"density": np.ones((2, 2, 2), np.float32), "bbox_min": np.zeros(3)}, ["bbox_min but not the other"]),
    ({"density": np.ones((2, 2, 2), np.float32), "bbox_min": np.zeros(3), "bbox_max": np.zeros(3)},
     ["must be < bbox_max", "not on x, y, z"]),
    ({"density": np.ones((2, 2, 2), np.float32), "bbox_min": np.zeros(2), "bbox_max": np.ones(2)},
     ["bbox_min must hold 3 numbers", "(2,)"]),
    ({"density": np.full((2, 2, 2), -1.0, np.float32)}, ["8 negative", "(0, 0, 0)"]),
])
def test_malformed_npz_is_rejected(tmp_path, arrays, fragments):
    p = tmp_path / "bad.npz"
    np.savez(p, **arrays)
    assert_rejected(p, fragments)


def test_unknown_extension_and_missing_file(tmp_path):
    p = write(tmp_path, "cloud.nvdb", b"whatever")
    with pytest.raises(VolumeError, match=r"cloud\.nvdb.*unknown volume file extension '\.nvdb'.*\.vol"):
        read_volume(p)
    with pytest.raises(VolumeError, match="no such volume file"):
        read_volume(tmp_path / "absent.vol")
    with pytest.raises(VolumeError, match="unknown volume file extension"):
        write_volume(tmp_path / "out.raw", DensityGrid.from_array(labelled_density()))


def test_npy_refuses_to_drop_a_bbox(tmp_path):
    g = DensityGrid(labelled_density(), np.array(BMIN), np.array(BMAX))
    p = tmp_path / "lossy.npy"
    with pytest.raises(VolumeError, match="stores no bounding box"):
        write_volume(p, g)
    assert not p.exists()


# --------------------------------------------------------------------------- DensityGrid invariants

def test_grid_properties_non_cubic():
    g = DensityGrid(labelled_density(), np.array(BMIN), np.array(BMAX))
    assert g.resolution == (3, 5, 7)
    np.testing.assert_allclose(g.extent, [3.0, 5.5, 7.5])
    np.testing.assert_allclose(g.cell_size, [1.0, 1.1, 7.5 / 7])
    np.testing.assert_allclose(g.voxel_centers(0), [-0.5, 0.5, 1.5])


@pytest.mark.parametrize("density, bmin, bmax, fragment", [
    (np.ones((2, 2, 2), np.float64), BMIN, BMAX, "must be float32"),
    (np.ones((2, 2), np.float32), BMIN, BMAX, "3-D"),
    (np.ones((2, 0, 2), np.float32), BMIN, BMAX, "empty"),
    (np.ones((2, 3, 4), np.float32).transpose(2, 1, 0), BMIN, BMAX, "C-contiguous"),
    (np.full((2, 2, 2), np.nan, np.float32), BMIN, BMAX, "8 NaN"),
    (np.ones((2, 2, 2), np.float32), (0, 0, 0), (1, 1, 0), "not on z"),
    (np.ones((2, 2, 2), np.float32), (0, 0, 0), (1, np.inf, 1), "not finite"),
])
def test_grid_rejects_bad_contents(density, bmin, bmax, fragment):
    with pytest.raises(VolumeError, match=fragment):
        DensityGrid(density, bmin, bmax)
