"""Image files: linear float32 EXR for results, tonemapped 8-bit PNG for previews.

EXR layout (one scanline part, ZIP compression, lossless, every channel FLOAT)
-----------------------------------------------------------------------------
``write_exr(path, layers)`` takes a dict ``layer name -> array``:

* ``""`` or ``"total"`` (H, W, 3): the beauty image, written as the plain ``R``, ``G``, ``B``
  channels so every viewer shows it.
* any other name with an (H, W, 3) array: channels ``name.R``, ``name.G``, ``name.B``
  (the OpenEXR layer convention; viewers list it as layer ``name``).
* ``alpha`` and ``depth`` (H, W): the channels ``A`` and ``Z``, the names compositors read
  as the beauty's coverage and depth (Nuke's rgba.alpha and depth.Z, Blender's Alpha and Depth
  sockets). With a black background the beauty is premultiplied by ``A`` (over a plate:
  ``RGB + (1 - A) plate``); with a sky the beauty already holds the sky seen through.
* any other name with an (H, W) array: one channel named ``name`` exactly (no ``.Y``
  suffix, so tools do not show it as a luminance layer).

``read_exr`` inverts this: ``R``, ``G``, ``B`` -> layer ``"total"``; ``A`` -> ``"alpha"`` and
``Z`` -> ``"depth"`` (files of earlier versions name those channels ``alpha`` and ``depth``,
read as they are); ``name.R/G/B`` -> (H, W, 3) layer ``name``; every other channel -> an
(H, W) layer under its full channel name. HALF and UINT channels of foreign files are
converted to float32.

Layer names are letters, digits, ``_`` and ``-`` (no ``.``, which would make ``a.b.R`` ambiguous).

Metadata: ``header`` values (str, int or float) are stored as *string* attributes named
``clvol.<key>``; floats are written with ``repr`` so they read back exactly (a typed float
attribute would be rounded to float32). ``read_exr(...).header`` returns our keys without the
prefix, values as strings. Other attributes of the file are not returned.

Writes are atomic: the file is written under a temporary name in the destination folder and
moved into place with ``os.replace``, so a crash never leaves a half-written result.

sRGB
----
``linear_to_srgb`` is the piecewise IEC 61966-2-1 curve; ``to_srgb8`` clamps to [0, 1], applies it
and rounds half up (``floor(255 v + 0.5)``) to uint8. It is the only sRGB code in clvol: the PNG
preview and the MRPNN metric (``clvol.metrics``) both use it.
"""
from __future__ import annotations

import math
import re
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .atomic import atomic_open, atomic_path
from .errors import ImageError

HEADER_PREFIX = "clvol."
_TOTAL_NAMES = ("", "total")
# Single-channel layers written under the channel names compositors read (module docstring).
_CHANNEL_OF = {"alpha": "A", "depth": "Z"}
_LAYER_OF = {c: n for n, c in _CHANNEL_OF.items()}
_LAYER_NAME = re.compile(r"^[A-Za-z0-9_\-]+$")
_HEADER_KEY = re.compile(r"^[A-Za-z0-9_\-.]+$")
_EXR_MAGIC = b"\x76\x2f\x31\x01"
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


# --------------------------------------------------------------------------- sRGB

def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 transfer curve on values in [0, 1] (float64 out).

    ``12.92 x`` for ``x <= 0.0031308``, else ``1.055 x^(1/2.4) - 0.055``. The two pieces meet
    at the threshold to within 1e-7 (the standard's rounded constants). No clamping here.
    """
    x = np.asarray(x, dtype=np.float64)
    # np.maximum keeps the power away from negative inputs in the branch not taken.
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1.0 / 2.4) - 0.055)


def to_srgb8(rgb: np.ndarray) -> np.ndarray:
    """Linear values (any shape) -> uint8 sRGB codes: clamp to [0, 1], sRGB curve, round half up.

    Clamping is the tonemap (a preview/metric shows [0, 1] of the scaled image); NaN or Inf
    cannot be clamped meaningfully and raise ImageError.
    """
    a = np.asarray(rgb, dtype=np.float64)
    bad = int(np.count_nonzero(~np.isfinite(a)))
    if bad:
        raise ImageError(f"cannot convert to sRGB: {bad} non-finite value(s) (NaN/Inf) in the image")
    v = linear_to_srgb(np.clip(a, 0.0, 1.0))
    # Round half up: floor(255 v + 0.5). v <= 1 so the result is <= 255.
    return np.floor(v * 255.0 + 0.5).astype(np.uint8)


# --------------------------------------------------------------------------- atomic writes

def _check_folder(path: Path) -> None:
    if not path.parent.is_dir():
        raise ImageError(f"{path}: cannot write, folder {path.parent} does not exist")


# --------------------------------------------------------------------------- EXR

@dataclass
class ExrImage:
    """An EXR read back: ``layers`` as float32 arrays, ``header`` our ``clvol.*`` metadata as strings."""

    path: Path
    layers: dict[str, np.ndarray]
    header: dict[str, str] = field(default_factory=dict)

    @property
    def rgb(self) -> np.ndarray:
        """The total (beauty) layer, (H, W, 3) float32."""
        if "total" not in self.layers:
            raise ImageError(
                f"{self.path}: no plain R, G, B channels (layers found: {sorted(self.layers)})")
        return self.layers["total"]


def _layer_float32(name: str, arr) -> np.ndarray:
    label = "total" if name in _TOTAL_NAMES else name
    a = np.asarray(arr)
    if not np.issubdtype(a.dtype, np.floating):
        raise ImageError(f"layer '{label}': dtype {a.dtype} is not a float type")
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] != 3):
        raise ImageError(f"layer '{label}': shape {a.shape}, expected (H, W, 3) RGB or (H, W)")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ImageError(f"layer '{label}': empty image of shape {a.shape}")
    with np.errstate(over="ignore"):  # overflow is reported below as a non-finite count
        a32 = a.astype(np.float32)
    bad = int(np.count_nonzero(~np.isfinite(a32)))
    if bad:
        # A renderer bug must not be saved silently; float64 values beyond the float32 range
        # land here too.
        raise ImageError(
            f"layer '{label}': {bad} non-finite value(s) (NaN/Inf, or beyond the float32 range) "
            f"of {a32.size}; refusing to write")
    return a32


def _header_attributes(header) -> dict[str, str]:
    out: dict[str, str] = {}
    for key, value in (header or {}).items():
        if not isinstance(key, str) or not _HEADER_KEY.match(key):
            raise ImageError(
                f"header key {key!r}: use letters, digits, '_', '-' or '.'")
        if isinstance(value, str):
            text = value
        elif isinstance(value, (bool, np.bool_)):
            text = str(bool(value))
        elif isinstance(value, (int, np.integer)):
            text = str(int(value))
        elif isinstance(value, (float, np.floating)):
            if not math.isfinite(float(value)):
                raise ImageError(f"header [{key}]: value {value!r} is not finite")
            text = repr(float(value))  # repr round-trips a float64 exactly
        else:
            raise ImageError(
                f"header [{key}]: value of type {type(value).__name__}, expected str, int or float")
        out[HEADER_PREFIX + key] = text
    return out


def write_exr(path, layers: dict[str, np.ndarray],
              header: dict[str, str | int | float] | None = None) -> None:
    """Write ``layers`` as a linear float32 EXR (layout in the module docstring), atomically.

    Raises ImageError for NaN/Inf (naming the layer and the count), mismatched layer sizes,
    bad names, a missing folder, or a failed write.
    """
    import OpenEXR

    path = Path(path)
    if not layers:
        raise ImageError(f"{path}: no layers to write")
    if all(n in layers for n in _TOTAL_NAMES):
        raise ImageError(f"{path}: layers '' and 'total' are the same layer; give only one")

    channels: dict[str, np.ndarray] = {}
    size = None
    for name, arr in layers.items():
        if not isinstance(name, str) or (name not in _TOTAL_NAMES and not _LAYER_NAME.match(name)):
            raise ImageError(
                f"{path}: layer name {name!r}: use letters, digits, '_' or '-' (or '' / 'total')")
        a = _layer_float32(name, arr)
        label = "total" if name in _TOTAL_NAMES else name
        if size is None:
            size = (label, a.shape[:2])
        elif a.shape[:2] != size[1]:
            raise ImageError(
                f"{path}: layer '{label}' is {a.shape[0]}x{a.shape[1]} (HxW) but layer "
                f"'{size[0]}' is {size[1][0]}x{size[1][1]}; all layers must share one size")
        if a.ndim == 2:
            if name in _TOTAL_NAMES:
                raise ImageError(f"{path}: layer 'total' must be (H, W, 3) RGB, got shape {a.shape}")
            if name in ("R", "G", "B", "A", "Z"):
                raise ImageError(
                    f"{path}: single-channel layer {name!r} would collide with the channels of "
                    f"the total, alpha or depth layers")
            names = [_CHANNEL_OF.get(name, name)]
        else:
            names = ["R", "G", "B"] if name in _TOTAL_NAMES else [f"{name}.{c}" for c in "RGB"]
        for i, ch in enumerate(names):
            # OpenEXR's binding ignores numpy strides: every channel must be C-contiguous.
            channels[ch] = np.ascontiguousarray(a if a.ndim == 2 else a[:, :, i])

    attrs = _header_attributes(header)
    exr_header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    exr_header.update(attrs)

    _check_folder(path)
    try:
        with atomic_path(path) as tmp:
            # The binding replaces the dict's arrays by Channel objects: pass only our own dicts.
            OpenEXR.File(exr_header, channels).write(str(tmp))
    except Exception as e:  # the binding raises RuntimeError/TypeError with its own text
        raise ImageError(f"{path}: cannot write EXR ({e})") from e


def read_exr(path) -> ExrImage:
    """Read an EXR written by ``write_exr`` (or any single-part scanline/tiled float EXR).

    Only the first part of a multi-part file is read. Raises ImageError naming the file when
    it is missing, not an EXR, damaged, or has sub-sampled channels.
    """
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: no such file")
    try:
        with open(path, "rb") as fh:
            magic = fh.read(4)
    except OSError as e:
        raise ImageError(f"{path}: cannot read ({e.strerror or e})") from e
    # Checked here so a wrong file gets a clear message (the library only says "unable to open").
    if magic != _EXR_MAGIC:
        raise ImageError(f"{path}: not an OpenEXR file (first bytes {magic!r}, expected {_EXR_MAGIC!r})")
    try:
        f = OpenEXR.File(str(path), separate_channels=True)
        hdr = f.header()
        chans = f.channels()
    except Exception as e:
        raise ImageError(f"{path}: cannot read EXR, damaged or truncated? ({e})") from e

    planes: dict[str, np.ndarray] = {}
    for name, ch in chans.items():
        if ch.xSampling != 1 or ch.ySampling != 1:
            raise ImageError(f"{path}: channel {name!r} is sub-sampled; not supported")
        planes[name] = np.asarray(ch.pixels).astype(np.float32, copy=False)

    layers: dict[str, np.ndarray] = {}
    used: set[str] = set()
    groups = {n.rpartition(".")[0] for n in planes}
    for prefix in sorted(groups):
        rgb = [f"{prefix}.{c}" if prefix else c for c in "RGB"]
        if all(c in planes for c in rgb):
            layers["total" if prefix == "" else prefix] = np.stack([planes[c] for c in rgb], axis=-1)
            used.update(rgb)
    for name in sorted(set(planes) - used):
        layer = _LAYER_OF.get(name, name)
        if layer != name and layer in planes:     # a foreign file with both: keep each name
            layer = name
        if layer in layers:
            raise ImageError(f"{path}: channel {name!r} collides with the RGB layer of the same name")
        layers[layer] = planes[name]

    header = {k[len(HEADER_PREFIX):]: (v if isinstance(v, str) else str(v))
              for k, v in hdr.items() if k.startswith(HEADER_PREFIX)}
    return ExrImage(path=path, layers=layers, header=header)


# --------------------------------------------------------------------------- PFM

def read_pfm(path) -> ExrImage:
    """Read a PFM (Portable Float Map: ``PF`` colour or ``Pf`` grey, float32, rows bottom to
    top), as the C demo examples/c/clvol-render writes it, into the same shape ``read_exr``
    returns: layer ``"total"`` (H, W, 3) float32, top row first; a grey map is repeated over
    R, G, B. Raises ImageError naming the file when it is missing or damaged."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: no such file")
    data = path.read_bytes()
    try:
        kind, dims, scale, body = data.split(b"\n", 3)
        w, h = (int(v) for v in dims.split())
        scale = float(scale)
    except ValueError:
        raise ImageError(f"{path}: not a PFM file (expected 'PF' or 'Pf', width height, "
                         f"scale lines)") from None
    if kind.strip() not in (b"PF", b"Pf") or w < 1 or h < 1 or not math.isfinite(scale) or scale == 0:
        raise ImageError(f"{path}: not a PFM file (header {kind!r} {dims!r} {scale!r})")
    channels = 3 if kind.strip() == b"PF" else 1
    if len(body) != 4 * w * h * channels:
        raise ImageError(f"{path}: {len(body)} bytes of pixels, expected {4 * w * h * channels} "
                         f"for {w} x {h} x {channels} float32 (truncated?)")
    img = np.frombuffer(body, "<f4" if scale < 0 else ">f4").reshape(h, w, channels)[::-1]
    img = np.ascontiguousarray(np.repeat(img, 3, axis=2) if channels == 1 else img, np.float32)
    return ExrImage(path=path, layers={"total": img})


def read_image(path) -> ExrImage:
    """An EXR (``read_exr``) or a PFM (``read_pfm``), told apart by their first bytes."""
    path = Path(path)
    if path.is_file():
        with open(path, "rb") as fh:
            magic = fh.read(2)
        if magic in (b"PF", b"Pf"):
            return read_pfm(path)
    return read_exr(path)


# --------------------------------------------------------------------------- PNG

def _png_chunk(kind: bytes, data: bytes) -> bytes:
    # Length, type, data, CRC-32 over type + data (PNG spec 5.3).
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def encode_png_rgb8(pixels: np.ndarray) -> bytes:
    """(H, W, 3) uint8 -> PNG bytes: 8-bit RGB, no interlace, filter type 0 on every row;
    (H, W, 4) -> 8-bit RGBA (colour type 6: straight, not premultiplied, alpha)."""
    p = np.asarray(pixels)
    if (p.dtype != np.uint8 or p.ndim != 3 or p.shape[2] not in (3, 4) or p.shape[0] == 0
            or p.shape[1] == 0):
        raise ImageError(f"PNG pixels must be (H, W, 3) or (H, W, 4) uint8, got {p.shape} {p.dtype}")
    h, w, c = p.shape
    # Every scanline starts with its filter-type byte (0 = None).
    raw = np.concatenate([np.zeros((h, 1), np.uint8), np.ascontiguousarray(p).reshape(h, c * w)], axis=1)
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2 if c == 3 else 6, 0, 0, 0)   # depth 8, RGB(A)
    return (_PNG_SIGNATURE
            + _png_chunk(b"IHDR", ihdr)
            + _png_chunk(b"sRGB", b"\x00")  # the data is sRGB-encoded (perceptual intent)
            + _png_chunk(b"IDAT", zlib.compress(raw.tobytes(), 6))
            + _png_chunk(b"IEND", b""))


# --------------------------------------------------------------------------- tone mapping

TONE_CURVES = ("filmic", "linear")
# Auto exposure maps this percentile of the lit pixels' luminance to AUTO_WHITE.
AUTO_PERCENTILE = 99.0
AUTO_WHITE = 0.8
REC709_LUMA = np.array([0.2126, 0.7152, 0.0722])


def auto_exposure(rgb: np.ndarray) -> float:
    """Exposure in stops that maps the ``AUTO_PERCENTILE`` luminance of the non-black pixels
    to ``AUTO_WHITE`` (so a small object on black is exposed for itself, not for the
    background). 0 for an all-black image."""
    a = np.asarray(rgb, dtype=np.float64)
    lum = a.reshape(-1, 3) @ REC709_LUMA
    lit = lum[lum > 0.0]
    if lit.size == 0:
        return 0.0
    level = float(np.percentile(lit, AUTO_PERCENTILE))
    if not (math.isfinite(level) and level > 0.0):
        return 0.0
    return float(np.clip(math.log2(AUTO_WHITE / level), -30.0, 30.0))


EXPOSURE_MODES = ("image", "scene")


def white_luminance(light) -> float:
    """Luminance of the scene's reference white: the radiance of a white Lambertian surface
    facing the sun under the sky, ``Y(irradiance) / pi + Y(mean sky radiance)``.

    ``light`` is a ``clvol.scene.Light``. The sky is ``Light.sky_mean()``: its constant
    ``environment``, or its ``environment_map``'s solid-angle mean times
    ``environment_scale``; none counts 0. (Under a
    constant sky of radiance L a white surface sees irradiance pi L and sends back L; the mean
    over the sphere is exact for a white sphere lit by any map.) Y: Rec. 709 luminance."""
    sun = float(np.dot(np.asarray(light.irradiance, dtype=np.float64), REC709_LUMA)) / math.pi
    return sun + float(light.sky_mean() @ REC709_LUMA)


def scene_exposure(light) -> float | None:
    """Scene-referred exposure in stops, from the light only (never the image): maps the
    reference white (``white_luminance``) to ``AUTO_WHITE``, the level auto exposure gives the
    image's bright pixels: ``log2(AUTO_WHITE / white_luminance(light))``. So two scenes under
    the same light get the same exposure and a dark medium looks dark. Irradiance 1, no sky:
    ``log2(0.8 pi)`` = +1.33 stops. None when the scene has no light (white luminance 0)."""
    white = white_luminance(light)
    if not (math.isfinite(white) and white > 0.0):
        return None
    return float(np.clip(math.log2(AUTO_WHITE / white), -30.0, 30.0))


def choose_exposure(exposure, rgb: np.ndarray, light=None) -> tuple[float, str]:
    """``(stops, how)`` of a preview: ``exposure`` is a number of stops (how = "given"),
    "image" or None (``auto_exposure``: "chosen from the image") or "scene"
    (``scene_exposure(light)``: "from the scene's light"; a scene without light falls back
    to the image: "chosen from the image: the scene has no light")."""
    if exposure is None or exposure == "image":
        return auto_exposure(rgb), "chosen from the image"
    if exposure == "scene":
        stops = scene_exposure(light) if light is not None else None
        if stops is None:
            return auto_exposure(rgb), "chosen from the image: the scene has no light"
        return stops, "from the scene's light"
    if isinstance(exposure, str) or not math.isfinite(float(exposure)):
        raise ImageError(f"exposure {exposure!r}: give a finite number of stops, "
                         f"{' or '.join(repr(m) for m in EXPOSURE_MODES)}")
    return float(exposure), "given"


def filmic(x: np.ndarray) -> np.ndarray:
    """A filmic shoulder on linear values >= 0: ``x (2.51 x + 0.03) / (x (2.43 x + 0.59) + 0.14)``
    (Narkowicz's fit of the ACES reference rendering transform). Smooth, monotonic, 0 -> 0,
    reaches 1 near x = 11, so highlights roll off instead of clipping. Output in [0, 1]."""
    x = np.maximum(np.asarray(x, dtype=np.float64), 0.0)
    # The denominator is >= 0.14 for x >= 0: no division by zero.
    return np.clip(x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0)


def tonemap_srgb8(rgb: np.ndarray, exposure: float | None = 0.0,
                  curve: str = "linear") -> tuple[np.ndarray, float]:
    """Linear (H, W, 3) -> (uint8 sRGB pixels, exposure used in stops).

    ``exposure=None`` picks it from the image (``auto_exposure``). ``curve``: "linear" clamps
    to [0, 1] (``to_srgb8``), "filmic" applies ``filmic`` first. Non-finite pixels raise."""
    if curve not in TONE_CURVES:
        raise ImageError(f"tone curve {curve!r}: choose one of {', '.join(TONE_CURVES)}")
    a = np.asarray(rgb, dtype=np.float64)
    bad = int(np.count_nonzero(~np.isfinite(a)))
    if bad:
        raise ImageError(f"{bad} non-finite value(s) (NaN/Inf) in the image")
    if exposure is None:
        exposure = auto_exposure(a)
    if not math.isfinite(float(exposure)):
        raise ImageError(f"exposure {exposure!r} is not finite")
    scaled = a * 2.0 ** float(exposure)
    return to_srgb8(filmic(scaled) if curve == "filmic" else scaled), float(exposure)


def write_png_preview(path, rgb: np.ndarray, exposure: float | None = 0.0,
                      curve: str = "linear", alpha: np.ndarray | None = None) -> float:
    """Tonemapped 8-bit sRGB preview of a linear (H, W, 3) image, written atomically.

    Pixel = ``to_srgb8(rgb * 2**exposure)`` for the linear curve (clamp to [0, 1], sRGB
    curve, round half up), or through ``filmic`` first; ``exposure=None`` chooses it from
    the image. Returns the exposure used.

    ``alpha`` (H, W) in [0, 1]: an RGBA preview of an image premultiplied by it (a medium over
    a black background). PNG alpha is straight, so the colour is divided by alpha before the
    tone curve (the exposure is still the whole image's); where alpha rounds to 0 in 8 bits
    the colour is 0 (invisible, and the division would only amplify noise).
    """
    path = Path(path)
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ImageError(f"{path}: preview image must be (H, W, 3) RGB, got shape {a.shape}")
    if exposure is not None and not math.isfinite(float(exposure)):
        raise ImageError(f"{path}: exposure {exposure!r} is not finite")
    bad = int(np.count_nonzero(~np.isfinite(a)))
    if bad:
        raise ImageError(f"{path}: {bad} non-finite value(s) (NaN/Inf) in the image; refusing to write")
    if exposure is None:
        exposure = auto_exposure(np.asarray(a, np.float64))   # from the premultiplied image
    if alpha is not None:
        al = np.asarray(alpha, np.float64)
        if al.shape != a.shape[:2] or not np.all(np.isfinite(al)):
            raise ImageError(f"{path}: alpha must be a finite (H, W) = {a.shape[:2]} array, "
                             f"got shape {al.shape}")
        al = np.clip(al, 0.0, 1.0)
        seen = al >= 0.5 / 255.0
        a = np.where(seen[..., None], np.asarray(a, np.float64) / np.where(seen, al, 1.0)[..., None], 0.0)
    pixels, used = tonemap_srgb8(a, exposure, curve)
    if alpha is not None:
        a8 = np.floor(al * 255.0 + 0.5).astype(np.uint8)
        pixels = np.concatenate([pixels, a8[..., None]], axis=-1)
    data = encode_png_rgb8(pixels)
    _check_folder(path)
    try:
        with atomic_open(path) as f:
            f.write(data)
    except OSError as e:
        raise ImageError(f"{path}: cannot write ({e.strerror or e})") from e
    return used
