"""Lat-long HDR environment maps: reading, validation, the direction convention and the
path tracer's sampling tables.

Convention (docs/conventions.md, "Environment maps"; world up is +y, right-handed axes):
a map of H rows and W = 2 H columns, row 0 at the top. A world direction d = (x, y, z)
has polar angle theta = acos(y) from up (+y) and azimuth phi = atan2(-z, x) in [0, 2 pi),
measured from +x toward -z (counter-clockwise seen from above, the right-hand sense about
+y). With the map turned by ``rotation`` degrees about +y (same sense), the map's own
azimuth is phi_map = phi - rotation, and

    u = phi_map / (2 pi) in [0, 1)   column j = floor(u W)
    v = theta / pi       in [0, 1]   row    i = floor(v H)   (clamped to H - 1)

Texel (i, j) is constant radiance over its patch theta in [i pi / H, (i+1) pi / H], phi_map
in [j 2 pi / W, (j+1) 2 pi / W] (no filtering), of solid angle
Omega_i = (2 pi / W) (cos(i pi / H) - cos((i+1) pi / H)). So column 0 starts at +x, column
W/4 looks along -z, W/2 along -x, 3W/4 along +z; row 0 touches +y, the last row -y.

Sampling (cl/pathtrace.cl PT_ENVMAP, twin reference/pathtrace.py, docs/pathtrace.md):
texel (i, j) is drawn with probability P_ij = lum_ij Omega_i / sum_kl lum_kl Omega_k
(lum = Rec. 709 luminance of the scaled texel) through a marginal CDF over rows and a
conditional CDF over the columns of each row, then a direction uniform in solid angle
inside it (uniform in cos(theta) and phi), so the density per solid angle is
pdf(d) = lum(texel(d)) / sum_kl lum_kl Omega_k: constant on each texel, exactly
proportional to the map's luminance.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import ImageError
from .image import REC709_LUMA   # Rec. 709 luminance, as the auto exposure

MAX_ROWS = 8192                   # a 16384 x 8192 map is 1.6 GB of float32 RGBA: refuse above


def read_map(path) -> np.ndarray:
    """(H, W, 3) float32 linear RGB of a lat-long EXR, validated; ImageError (one line,
    naming the file and what is wrong) for: not an EXR, no R, G, B channels, an aspect
    other than 2:1, NaN, infinite or negative texels."""
    from .image import read_exr
    path = Path(path)
    img = read_exr(path)   # ImageError: missing, not an OpenEXR file, damaged
    rgb = img.layers.get("total")
    if rgb is None or rgb.ndim != 3:
        raise ImageError(f"{path}: an environment map needs R, G, B channels (found "
                         f"{', '.join(sorted(img.layers)) or 'none'})")
    h, w = rgb.shape[:2]
    if w != 2 * h:
        raise ImageError(f"{path}: a lat-long environment map must be twice as wide as high "
                         f"(2:1), got {w} x {h}")
    if h > MAX_ROWS:
        raise ImageError(f"{path}: environment map of {w} x {h} texels is too large (at most "
                         f"{2 * MAX_ROWS} x {MAX_ROWS})")
    bad = ~np.isfinite(rgb)
    if bad.any():
        i, j, c = np.argwhere(bad)[0]
        raise ImageError(f"{path}: texel (row {i}, column {j}) channel {'RGB'[c]} is "
                         f"{rgb[i, j, c]} ({int(bad.any(-1).sum())} texels not finite); texels "
                         f"must be finite and >= 0")
    neg = rgb < 0
    if neg.any():
        i, j, c = np.argwhere(neg)[0]
        raise ImageError(f"{path}: texel (row {i}, column {j}) channel {'RGB'[c]} is "
                         f"{float(rgb[i, j, c]):g} ({int(neg.any(-1).sum())} texels negative); "
                         f"texels must be >= 0")
    return np.ascontiguousarray(rgb, np.float32)


def has_map_shape(path) -> bool:
    """Whether ``path`` is an EXR whose data window is 2:1, from its header alone (no texels
    read): a cheap first filter for folders of images (the viewer's map menu), before
    read_map's full checks."""
    import OpenEXR
    try:
        lo, hi = OpenEXR.File(str(path), header_only=True).header()["dataWindow"]
    except Exception:          # not an EXR, damaged, no data window: not a candidate
        return False
    w, h = int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)
    return w == 2 * h and 0 < h <= MAX_ROWS


@functools.lru_cache(maxsize=4)
def _read_cached(path: str, mtime_ns: int, size: int) -> np.ndarray:
    a = read_map(path)
    a.setflags(write=False)
    return a


def load_map(path) -> np.ndarray:
    """read_map, cached per (path, modification time, size): renders of the same scene do
    not read the file again. The array is read-only."""
    p = Path(path)
    try:
        st = p.stat()
    except OSError:
        return read_map(p)   # raises the one-line error
    return _read_cached(str(p), st.st_mtime_ns, st.st_size)


def row_solid_angles(h: int, w: int) -> np.ndarray:
    """Omega_i of one texel of each row (float64, [h])."""
    c = np.cos(np.pi * np.arange(h + 1) / h)
    return (2.0 * np.pi / w) * (c[:-1] - c[1:])


def mean_radiance(texels) -> np.ndarray:
    """Solid-angle mean (float64, [3]) of a lat-long map's (H, W, 3) texels over the sphere."""
    def build():
        t = np.asarray(texels)
        h, w = t.shape[:2]
        return np.einsum("hwc,h->c", t, row_solid_angles(h, w).astype(t.dtype),
                         dtype=np.float64) / (4.0 * math.pi)
    return _per_map("mean", texels, (), build).copy()


def direction_to_texel(d, rotation_deg: float, h: int, w: int):
    """(row, column) int arrays of unit directions d (..., 3) (the module's convention)."""
    d = np.asarray(d, np.float64)
    phi = np.arctan2(-d[..., 2], d[..., 0]) - math.radians(rotation_deg)
    u = np.mod(phi / (2.0 * np.pi), 1.0)
    v = np.arccos(np.clip(d[..., 1], -1.0, 1.0)) / np.pi
    j = np.minimum((u * w).astype(np.int64), w - 1)
    i = np.minimum((v * h).astype(np.int64), h - 1)
    return i, j


def texel_directions(h: int, w: int, rotation_deg: float = 0.0) -> np.ndarray:
    """(h, w, 3) unit world directions of the texel centres (centre in theta and phi)."""
    theta = np.pi * (np.arange(h) + 0.5) / h
    phi = 2.0 * np.pi * (np.arange(w) + 0.5) / w + math.radians(rotation_deg)
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    return np.stack(np.broadcast_arrays(st * np.cos(phi)[None], ct, -st * np.sin(phi)[None]),
                    axis=-1)


@dataclass
class Tables:
    """What cl/pathtrace.cl's PT_ENVMAP reads: ``rgbl`` [H][W][4] float32 (scaled R, G, B and
    luminance), ``marginal`` [H+1] and ``conditional`` [H][W+1] float32 CDFs (first 0, last
    exactly 1; a row of zero weight gets a uniform conditional CDF, never drawn),
    ``inv_total`` = 1 / sum lum Omega (pdf(d) = lum(texel(d)) * inv_total), ``rotation``
    in radians. ``total`` 0 means a black map: nothing to simulate (no tables used)."""
    h: int
    w: int
    rgbl: np.ndarray
    marginal: np.ndarray
    conditional: np.ndarray
    total: float
    inv_total: float
    rotation: float


# What was last derived from a read-only map (load_map's), with the map itself (kept alive,
# so that its id stays its own): every path-tracer pass of the viewer, and every frame
# exposed from the light, asks again for the same map's tables and mean.
_LAST: dict = {}


def _per_map(name: str, rgb, key: tuple, build):
    hit = _LAST.get(name)
    if hit is not None and hit[0] is rgb and hit[1] == key:
        return hit[2]
    value = build()
    if isinstance(rgb, np.ndarray) and not rgb.flags.writeable:
        _LAST[name] = (rgb, key, value)
    return value


def build_tables(rgb, scale=(1.0, 1.0, 1.0), rotation_deg: float = 0.0) -> Tables:
    """The sampling tables of a map (H, W, 3) times ``scale`` (RGB), turned by
    ``rotation_deg``. CDFs are summed in float64 and stored as float32. A read-only map with
    the same scale and rotation as the last call reuses its tables."""
    key = (tuple(float(v) for v in np.broadcast_to(scale, (3,))), float(rotation_deg))
    return _per_map("tables", rgb, key, lambda: _build_tables(rgb, scale, rotation_deg))


def _build_tables(rgb, scale, rotation_deg: float) -> Tables:
    a = np.asarray(rgb, np.float64) * np.asarray(scale, np.float64)[None, None, :]
    h, w = a.shape[:2]
    lum = a @ REC709_LUMA
    weight = lum * row_solid_angles(h, w)[:, None]          # lum_ij Omega_i >= 0
    row = weight.sum(axis=1)
    total = float(row.sum())
    cond = np.empty((h, w + 1))
    cond[:, 0] = 0.0
    for i in range(h):
        if row[i] > 0:
            cond[i, 1:] = np.cumsum(weight[i]) / row[i]
        else:
            cond[i, 1:] = np.arange(1, w + 1) / w
        cond[i, w] = 1.0
    marg = np.zeros(h + 1)
    if total > 0:
        marg[1:] = np.cumsum(row) / total
    else:
        marg[1:] = np.arange(1, h + 1) / h
    marg[h] = 1.0
    rgbl = np.concatenate([a, lum[..., None]], axis=-1).astype(np.float32)
    return Tables(h=h, w=w, rgbl=np.ascontiguousarray(rgbl),
                  marginal=marg.astype(np.float32), conditional=cond.astype(np.float32),
                  total=total, inv_total=1.0 / total if total > 0 else 0.0,
                  rotation=math.radians(rotation_deg))


def lookup(rgb, scale, rotation_deg: float, d) -> np.ndarray:
    """Radiance (..., 3) float64 of the scaled map along unit directions d (nearest texel)."""
    a = np.asarray(rgb)
    i, j = direction_to_texel(d, rotation_deg, a.shape[0], a.shape[1])
    return a[i, j].astype(np.float64) * np.asarray(scale, np.float64)
