"""EXR round trip, PNG preview (decoded here with zlib), and the sRGB curve."""
import struct
import zlib

import numpy as np
import pytest

from clvol.errors import ImageError
from clvol.image import linear_to_srgb, read_exr, to_srgb8, write_exr, write_png_preview

H, W = 3, 5  # non-square, so an axis swap fails


def _bits(a):
    return np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)


def _srgb_inverse(v):
    """Inverse IEC 61966-2-1 curve, written independently of clvol for the tests."""
    v = np.asarray(v, dtype=np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


# --------------------------------------------------------------------------- EXR

def test_exr_round_trip_layers_and_header_bit_exact(tmp_path, rng):
    total = rng.random((H, W, 3)).astype(np.float32)
    # Values a lossy or half-float path would change.
    total[0, 0] = [1e-40, -0.0, 3.0e38]
    total[2, 4] = [np.float32(0.1), 1.0 + 2.0**-23, -5.5]
    direct = rng.random((H, W, 3)).astype(np.float32) * 7.0
    alpha = rng.random((H, W)).astype(np.float32)
    depth64 = rng.random((H, W)) * 100.0  # float64 in: written as float32
    header = {"scene": "scenes/cloud.toml", "method": "pathtrace", "spp": 16,
              "seconds": 0.1, "effects": "single,multiple"}
    path = tmp_path / "out.exr"
    write_exr(path, {"total": total, "direct": direct, "alpha": alpha, "depth": depth64}, header)

    img = read_exr(path)
    assert sorted(img.layers) == ["alpha", "depth", "direct", "total"]
    assert img.layers["total"].shape == (H, W, 3) and img.layers["alpha"].shape == (H, W)
    assert all(a.dtype == np.float32 for a in img.layers.values())
    np.testing.assert_array_equal(_bits(img.layers["total"]), _bits(total))
    np.testing.assert_array_equal(_bits(img.layers["direct"]), _bits(direct))
    np.testing.assert_array_equal(_bits(img.layers["alpha"]), _bits(alpha))
    np.testing.assert_array_equal(_bits(img.layers["depth"]), _bits(depth64.astype(np.float32)))
    np.testing.assert_array_equal(_bits(img.rgb), _bits(total))
    assert img.header == {"scene": "scenes/cloud.toml", "method": "pathtrace", "spp": "16",
                          "seconds": "0.1", "effects": "single,multiple"}
    assert float(img.header["seconds"]) == 0.1  # exact, not rounded to float32


def test_exr_channel_names_follow_the_layer_convention(tmp_path, rng):
    import OpenEXR

    path = tmp_path / "names.exr"
    write_exr(path, {"": rng.random((H, W, 3)), "direct": rng.random((H, W, 3)),
                     "alpha": rng.random((H, W))}, {"spp": 4})
    f = OpenEXR.File(str(path), separate_channels=True)
    assert sorted(f.channels()) == ["A", "B", "G", "R", "direct.B", "direct.G", "direct.R"]
    assert f.header()["clvol.spp"] == "4"
    assert sorted(read_exr(path).layers) == ["alpha", "direct", "total"]


def test_alpha_and_depth_are_the_channels_compositors_read(tmp_path, rng):
    """Nuke and Blender read coverage from A and depth from Z; before, they were channels
    named alpha and depth, which compositors show as unrelated data. Read back under the layer
    names, and a file of an earlier version (channels alpha, depth) still reads the same."""
    import OpenEXR
    a, z = rng.random((H, W)), rng.random((H, W))
    write_exr(tmp_path / "n.exr", {"total": rng.random((H, W, 3)), "alpha": a, "depth": z,
                                    "single": rng.random((H, W, 3))})
    f = OpenEXR.File(str(tmp_path / "n.exr"), separate_channels=True)
    assert sorted(f.channels()) == ["A", "B", "G", "R", "Z", "single.B", "single.G", "single.R"]
    img = read_exr(tmp_path / "n.exr")
    assert sorted(img.layers) == ["alpha", "depth", "single", "total"]
    np.testing.assert_array_equal(img.layers["alpha"], a.astype(np.float32))
    np.testing.assert_array_equal(img.layers["depth"], z.astype(np.float32))
    old = {"R": a, "G": a, "B": a, "alpha": a, "depth": z}       # an earlier version's file
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {k: np.ascontiguousarray(v, np.float32) for k, v in old.items()}
                 ).write(str(tmp_path / "old.exr"))
    assert sorted(read_exr(tmp_path / "old.exr").layers) == ["alpha", "depth", "total"]
    with pytest.raises(ImageError, match="collide"):
        write_exr(tmp_path / "c.exr", {"total": rng.random((H, W, 3)), "A": a})


def test_exr_refuses_nan_and_inf_naming_layer_and_count(tmp_path, rng):
    bad = rng.random((H, W, 3)).astype(np.float32)
    bad[0, 1, 2] = np.nan
    bad[1, 1, 0] = np.inf
    bad[2, 0, 1] = -np.inf
    path = tmp_path / "bad.exr"
    with pytest.raises(ImageError, match=r"layer 'direct': 3 non-finite"):
        write_exr(path, {"total": rng.random((H, W, 3)), "direct": bad})
    assert list(tmp_path.iterdir()) == []  # nothing written, no temp file left


def test_exr_refuses_float64_overflowing_float32(tmp_path):
    a = np.full((H, W), 1e39)
    with pytest.raises(ImageError, match=r"layer 'depth': 15 non-finite"):
        write_exr(tmp_path / "o.exr", {"depth": a})


def test_exr_refuses_mismatched_sizes(tmp_path):
    with pytest.raises(ImageError, match=r"layer 'alpha' is 4x5 .*'total' is 3x5"):
        write_exr(tmp_path / "m.exr", {"total": np.zeros((3, 5, 3)), "alpha": np.zeros((4, 5))})


@pytest.mark.parametrize("layers, message", [
    ({"a.b": np.zeros((H, W, 3))}, r"layer name 'a\.b'"),
    ({"total": np.zeros((H, W))}, r"'total' must be \(H, W, 3\)"),
    ({"R": np.zeros((H, W))}, r"collide"),
    ({"": np.zeros((H, W, 3)), "total": np.zeros((H, W, 3))}, r"same layer"),
    ({"x": np.zeros((H, W, 4))}, r"layer 'x': shape \(3, 5, 4\)"),
    ({"x": np.zeros((H, W), dtype=np.int32)}, r"layer 'x': dtype int32"),
])
def test_exr_refuses_bad_layers(tmp_path, layers, message):
    with pytest.raises(ImageError, match=message):
        write_exr(tmp_path / "l.exr", layers)


def test_exr_refuses_bad_header_values(tmp_path):
    with pytest.raises(ImageError, match=r"header \[seconds\]: value nan"):
        write_exr(tmp_path / "h.exr", {"total": np.zeros((H, W, 3))}, {"seconds": float("nan")})
    with pytest.raises(ImageError, match=r"header \[obj\]: value of type list"):
        write_exr(tmp_path / "h.exr", {"total": np.zeros((H, W, 3))}, {"obj": [1]})


def test_exr_write_is_atomic_replace(tmp_path, rng):
    path = tmp_path / "r.exr"
    first = rng.random((H, W, 3)).astype(np.float32)
    write_exr(path, {"total": first})
    second = first + 1.0
    write_exr(path, {"total": second})
    np.testing.assert_array_equal(read_exr(path).rgb, second)
    # A refused write leaves the previous file untouched.
    with pytest.raises(ImageError):
        write_exr(path, {"total": np.full((H, W, 3), np.nan)})
    np.testing.assert_array_equal(read_exr(path).rgb, second)
    assert [p.name for p in tmp_path.iterdir()] == ["r.exr"]


def test_exr_missing_folder(tmp_path):
    with pytest.raises(ImageError, match=r"folder .*nope does not exist"):
        write_exr(tmp_path / "nope" / "a.exr", {"total": np.zeros((H, W, 3))})


def test_read_exr_missing_file(tmp_path):
    path = tmp_path / "missing.exr"
    with pytest.raises(ImageError, match=rf"{path}: no such file"):
        read_exr(path)


def test_read_exr_not_an_exr(tmp_path):
    path = tmp_path / "fake.exr"
    path.write_text("hello, not an image")
    with pytest.raises(ImageError, match=r"fake\.exr: not an OpenEXR file"):
        read_exr(path)


def test_read_exr_truncated(tmp_path, rng):
    good = tmp_path / "good.exr"
    write_exr(good, {"total": rng.random((40, 30, 3))})
    data = good.read_bytes()
    cut = tmp_path / "cut.exr"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ImageError, match=r"cut\.exr: cannot read EXR"):
        read_exr(cut)


def test_rgb_property_without_total_layer(tmp_path):
    path = tmp_path / "a.exr"
    write_exr(path, {"alpha": np.ones((H, W))})
    img = read_exr(path)
    with pytest.raises(ImageError, match=r"no plain R, G, B channels"):
        img.rgb


# --------------------------------------------------------------------------- sRGB

def test_srgb_known_points():
    assert to_srgb8(np.array(0.0)) == 0
    assert to_srgb8(np.array(1.0)) == 255
    # 1.055 * 0.5**(1/2.4) - 0.055 = 0.735357; * 255 = 187.516 -> 188
    assert to_srgb8(np.array(0.5)) == 188
    # Linear segment: 12.92 * 0.001 * 255 = 3.29 -> 3
    assert to_srgb8(np.array(0.001)) == 3
    # Clamped outside [0, 1].
    np.testing.assert_array_equal(to_srgb8(np.array([-1.0, 7.0])), [0, 255])


def test_srgb_curve_continuous_at_segment_boundary():
    t = 0.0031308
    below = linear_to_srgb(t)                        # linear piece: 12.92 t = 0.0404500
    above = linear_to_srgb(np.nextafter(t, 1.0))     # power piece
    assert below == pytest.approx(12.92 * t, rel=1e-15)
    # The standard's rounded constants leave a jump below 1e-7 (far below one 8-bit step, 3.9e-3).
    assert abs(above - below) < 1e-7


def test_srgb8_rounds_to_nearest():
    # Linear values whose exact sRGB value is code k + 0.4 or k + 0.6: nearest is k, k + 1
    # (floor would give k for both).
    k = np.arange(1, 254)
    np.testing.assert_array_equal(to_srgb8(_srgb_inverse((k + 0.4) / 255.0)), k)
    np.testing.assert_array_equal(to_srgb8(_srgb_inverse((k + 0.6) / 255.0)), k + 1)


def test_srgb8_refuses_nan():
    with pytest.raises(ImageError, match=r"1 non-finite"):
        to_srgb8(np.array([0.5, np.nan]))


# --------------------------------------------------------------------------- PNG

def _decode_png(data: bytes) -> np.ndarray:
    """Minimal PNG decoder for 8-bit RGB, non-interlaced, any of the 5 filter types."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, ihdr, kinds = 8, b"", None, []
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        kind = data[pos + 4:pos + 8]
        body = data[pos + 8:pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length:pos + 12 + length])
        assert crc == zlib.crc32(kind + body) & 0xFFFFFFFF, f"bad CRC in chunk {kind}"
        kinds.append(kind)
        if kind == b"IHDR":
            ihdr = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        pos += 12 + length
    assert kinds[0] == b"IHDR" and kinds[-1] == b"IEND"
    w, h, depth, colour, comp, filt, interlace = ihdr
    assert (depth, colour, comp, filt, interlace) == (8, 2, 0, 0, 0)
    raw = zlib.decompress(idat)
    stride = 3 * w
    assert len(raw) == h * (stride + 1)
    out = np.zeros((h, stride), np.int64)
    prev = np.zeros(stride, np.int64)
    for y in range(h):
        ftype = raw[y * (stride + 1)]
        line = np.frombuffer(raw, np.uint8, stride, y * (stride + 1) + 1).astype(np.int64)
        cur = np.zeros(stride, np.int64)
        for x in range(stride):
            a = cur[x - 3] if x >= 3 else 0
            b = prev[x]
            c = prev[x - 3] if x >= 3 else 0
            if ftype == 0:
                pred = 0
            elif ftype == 1:
                pred = a
            elif ftype == 2:
                pred = b
            elif ftype == 3:
                pred = (a + b) // 2
            elif ftype == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
            else:
                raise AssertionError(f"bad filter type {ftype}")
            cur[x] = (line[x] + pred) & 0xFF
        out[y] = cur
        prev = cur
    return out.reshape(h, w, 3).astype(np.uint8)


def test_png_preview_decodes_to_srgb8(tmp_path, rng):
    rgb = rng.random((4, 7, 3)) * 1.5 - 0.2  # some values clamp at both ends
    path = tmp_path / "p.png"
    write_png_preview(path, rgb, exposure=-1.0)
    pixels = _decode_png(path.read_bytes())
    assert pixels.shape == (4, 7, 3)
    np.testing.assert_array_equal(pixels, to_srgb8(rgb * 0.5))
    assert [p.name for p in tmp_path.iterdir()] == ["p.png"]


def test_png_preview_known_pixels(tmp_path):
    rgb = np.zeros((2, 3, 3))
    rgb[0, 0] = [0.5, 0.25, 0.0]     # exposure +1: 1 -> 255, 0.5 -> 188
    rgb[1, 2] = [0.25, 0.25, 4.0]   # exposure +1: 0.5 -> 188, 4 -> 8 clamps to 255
    path = tmp_path / "k.png"
    write_png_preview(path, rgb, exposure=1.0)
    px = _decode_png(path.read_bytes())
    assert px[0, 0].tolist() == [255, 188, 0]
    assert px[1, 2].tolist() == [188, 188, 255]
    assert px[0, 1].tolist() == [0, 0, 0]


def test_png_preview_refuses_nan(tmp_path):
    rgb = np.zeros((2, 2, 3))
    rgb[1, 1, 1] = np.nan
    with pytest.raises(ImageError, match=r"n\.png: 1 non-finite"):
        write_png_preview(tmp_path / "n.png", rgb)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- tone mapping

def test_filmic_curve_is_monotonic_bounded_and_rolls_off():
    from clvol.image import filmic
    x = np.concatenate([[0.0], np.geomspace(1e-6, 1e3, 2000)])
    y = filmic(x)
    assert y[0] == 0.0 and np.all(np.diff(y) >= 0.0) and y.max() <= 1.0
    # The shoulder: 4x the light gives far less than 4x the value near white, unlike a clamp.
    assert filmic(np.array([0.5]))[0] < 0.8 and filmic(np.array([2.0]))[0] < 1.0
    # Hand-checked value of the formula at x = 1: 2.54 / 3.16.
    assert abs(filmic(np.array([1.0]))[0] - 2.54 / 3.16) < 1e-12


def test_auto_exposure_maps_the_bright_percentile_of_lit_pixels():
    from clvol.image import AUTO_WHITE, auto_exposure
    rgb = np.zeros((64, 64, 3))
    rgb[:8, :8] = 0.01                       # a small grey object on black
    ev = auto_exposure(rgb)
    assert abs(0.01 * 2.0 ** ev - AUTO_WHITE) < 1e-9   # luminance weights sum to 1
    assert auto_exposure(np.zeros((4, 4, 3))) == 0.0


def test_tonemap_default_is_the_old_linear_preview_and_refuses_bad_input():
    from clvol.errors import ImageError
    from clvol.image import tonemap_srgb8
    rgb = np.random.default_rng(3).uniform(0, 2, (5, 7, 3))
    px, ev = tonemap_srgb8(rgb, 1.0, "linear")
    assert ev == 1.0 and np.array_equal(px, to_srgb8(rgb * 2.0))
    with pytest.raises(ImageError, match="tone curve"):
        tonemap_srgb8(rgb, 0.0, "aces")
    rgb[0, 0, 0] = np.nan
    with pytest.raises(ImageError, match="non-finite"):
        tonemap_srgb8(rgb, None, "filmic")
