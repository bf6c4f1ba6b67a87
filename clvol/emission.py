"""Emission: the ``[emission]`` grid of a scene, mapped to emitted radiance ``Le`` (docs/scenes.md,
docs/conventions.md "Emission").

A medium emits ``sigma_a(x) Le(x)`` per unit length (pbrt-v4's and Mitsuba's convention):
``sigma_a = sigma_t (1 - albedo)`` is the absorption coefficient, so a non-scattering medium
(albedo 0) of optical depth tau in front of black shows ``Le (1 - e^-tau)`` and an opaque one
``Le``: ``Le`` is the radiance the medium would glow with if it were thick and black.

Mappings (``EmissionSpec.kind``):

``radiance``   Le = scale * colour * g(x), g the grid's value (one plane, colour per ray);
``blackbody``  Le = scale * rgb(T(x)), T the grid's value in kelvin, per voxel on the host,
               then interpolated trilinearly like every clvol grid (the radiance, not the
               temperature, is interpolated). ``rgb(T)`` is ``blackbody_rgb``: Planck's law
               normalised to 1 at its peak wavelength (pbrt-v4's BlackbodySpectrum), integrated
               against the CIE 1931 2-degree colour matching functions (the analytic fit of
               Wyman, Sloan and Shirley 2013, JCGT 2(2)) over 360..830 nm in 1 nm steps,
               divided by the integral of y-bar (a constant spectrum 1 has Y = 1), then XYZ to
               linear sRGB (Rec. 709 primaries, D65), negative components (outside the sRGB
               gamut, below ~1900 K) clipped to 0. Tabulated at 4096 temperatures from 0 to
               the grid's maximum rounded up to a multiple of 500 K (so a sequence's frames
               share one table) and interpolated linearly between them.

``EmissionGrid``: the planes ``values`` (C, ez, ey, ex), C = 1 or 3, over their own box
(``bbox_min``..``bbox_max``; voxel centres at ``bbox_min + (i + 1/2) cell``, trilinear, clamped
inside the box, Le = 0 outside it), the RGB ``colour`` that multiplies them, and ``own_box``:
False when the grid lies exactly on the density's grid (same shape and box), so kernels need
no box test. Bad grids (NaN, negative values, a shape that does not match the density's
without a box of its own) raise ``VolumeError`` naming the file and the grid.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import VolumeError

KINDS = ("radiance", "blackbody")
TABLE_SIZE = 4096

# --------------------------------------------------------------------------- blackbody

_H, _C, _K = 6.62607015e-34, 299792458.0, 1.380649e-23   # SI, exact since 2019
_WIEN = 2.897771955e-3                                     # m K
_LAMBDA_NM = np.arange(360.0, 831.0, 1.0)
# XYZ -> linear sRGB (IEC 61966-2-1, D65 white).
XYZ_TO_SRGB = np.array([[3.2404542, -1.5371385, -0.4985314],
                        [-0.9692660, 1.8760108, 0.0415560],
                        [0.0556434, -0.2040259, 1.0572252]])


def _lobe(lam, mu, s1, s2):
    s = np.where(lam < mu, s1, s2)
    return np.exp(-0.5 * ((lam - mu) / s) ** 2)


def cie_xyz_bar(lam_nm) -> np.ndarray:
    """(3, n): the CIE 1931 2-degree colour matching functions at wavelengths ``lam_nm``, by
    the multi-lobe Gaussian fit of Wyman, Sloan and Shirley (2013)."""
    lam = np.asarray(lam_nm, np.float64)
    x = (1.056 * _lobe(lam, 599.8, 37.9, 31.0) + 0.362 * _lobe(lam, 442.0, 16.0, 26.7)
         - 0.065 * _lobe(lam, 501.1, 20.4, 26.2))
    y = 0.821 * _lobe(lam, 568.8, 46.9, 40.5) + 0.286 * _lobe(lam, 530.9, 16.3, 31.1)
    z = 1.217 * _lobe(lam, 437.0, 11.8, 36.0) + 0.681 * _lobe(lam, 459.0, 26.0, 13.8)
    return np.stack([x, y, z])


def planck_normalised(lam_nm, temperature) -> np.ndarray:
    """Planck's spectral radiance at ``lam_nm`` divided by its value at the peak wavelength
    (Wien: 2.8978e-3 m K / T); 0 for T <= 0. Broadcasts (T along the first axis)."""
    T = np.asarray(temperature, np.float64)[..., None]
    lam = np.asarray(lam_nm, np.float64) * 1e-9

    def planck(l, t):
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            return (2 * _H * _C ** 2 / l ** 5) / np.expm1(_H * _C / (l * _K * t))
    safe = np.where(T > 0, T, 1.0)
    peak = planck(_WIEN / safe, safe)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = planck(lam, safe) / peak
    return np.where((T > 0) & np.isfinite(out), out, 0.0)


def blackbody_xyz(temperature) -> np.ndarray:
    """(..., 3) CIE XYZ of the peak-normalised blackbody (Y = 1 for a constant spectrum 1)."""
    cmf = cie_xyz_bar(_LAMBDA_NM)
    spec = planck_normalised(_LAMBDA_NM, temperature)
    return (spec @ cmf.T) / cmf[1].sum()


def blackbody_rgb(temperature) -> np.ndarray:
    """(..., 3) linear sRGB of a blackbody at ``temperature`` kelvin (module doc); >= 0."""
    rgb = blackbody_xyz(temperature) @ XYZ_TO_SRGB.T
    return np.maximum(rgb, 0.0)


@functools.lru_cache(maxsize=8)
def blackbody_table(t_max: float, n: int = TABLE_SIZE):
    """(temperatures (n,), rgb (n, 3)): ``blackbody_rgb`` at n temperatures from 0 to t_max
    (read-only arrays, cached)."""
    t = np.linspace(0.0, max(float(t_max), 1.0), n)
    rgb = blackbody_rgb(t)
    t.flags.writeable = False
    rgb.flags.writeable = False
    return t, rgb


def map_blackbody(temperature: np.ndarray) -> np.ndarray:
    """(3, ...) float32 planes of rgb(T) per voxel (the table, linear between entries)."""
    t_max = float(temperature.max()) if temperature.size else 0.0
    tt, rgb = blackbody_table(500.0 * math.ceil(max(t_max, 1.0) / 500.0))
    # The table is uniform in T: index arithmetic, not np.interp's search (8x faster).
    x = np.clip(temperature.astype(np.float64).ravel() * ((len(tt) - 1) / tt[-1]), 0.0,
                len(tt) - 1.0)
    j = np.minimum(x.astype(np.int64), len(tt) - 2)
    f = x - j
    out = np.empty((3,) + temperature.shape, np.float32)
    for c in range(3):
        out[c] = (rgb[j, c] * (1.0 - f) + rgb[j + 1, c] * f).reshape(temperature.shape)
    return out


# --------------------------------------------------------------------------- the grid

@dataclass(eq=False)
class EmissionGrid:
    """Emitted radiance Le = colour * values (module doc)."""
    values: np.ndarray          # float32 (C, ez, ey, ex), C = 1 or 3, finite, >= 0
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    colour: tuple               # RGB multiplier of the planes
    own_box: bool = False       # False: exactly on the density's grid
    kind: str = "radiance"
    name: str = ""
    device: object = None       # the planes on the device (a DeviceArray), set by the Renderer

    @property
    def channels(self) -> int:
        return int(self.values.shape[0])

    @property
    def shape(self) -> tuple:
        return tuple(int(s) for s in self.values.shape[1:])

    def max_radiance(self) -> np.ndarray:
        """Largest Le per channel (RGB)."""
        m = self.values.reshape(self.channels, -1).max(axis=1).astype(np.float64)
        m = np.broadcast_to(m, (3,)) if self.channels == 1 else m
        return m * np.asarray(self.colour, np.float64)


def check_emission_values(a: np.ndarray, source: str) -> None:
    """NaN, infinite or negative values: one VolumeError line naming the first."""
    bad = ~(np.isfinite(a) & (a >= 0))
    if bad.any():
        j = tuple(int(x) for x in np.argwhere(bad)[0])
        v = float(a[j])
        what = "NaN" if math.isnan(v) else "infinite" if math.isinf(v) else "negative"
        raise VolumeError(f"{source}: {int(bad.sum())} voxel(s) NaN, infinite or negative "
                          f"(first {what}: [z, y, x] = {list(j)} is {v!r}); emission grids "
                          f"must be finite and >= 0")


def make_emission(raw: np.ndarray, bbox_min, bbox_max, spec, density_grid,
                  source: str, own_box_given: bool) -> EmissionGrid:
    """The EmissionGrid of a raw grid (z, y, x) read from a file, checked against the density
    grid. ``own_box_given``: the file gave this grid a box of its own (a .vdb transform, or
    .npz ``<name>_bbox_min/_max``); otherwise it must have the density's shape."""
    a = np.asarray(raw)
    if a.ndim != 3 or 0 in a.shape:
        raise VolumeError(f"{source}: an emission grid must be 3-D [z][y][x] and not empty, "
                          f"got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.floating) and not np.issubdtype(a.dtype, np.integer):
        raise VolumeError(f"{source}: emission grid of dtype {a.dtype}; a real number grid is needed")
    a64 = a.astype(np.float64)
    check_emission_values(a64, source)
    dshape = tuple(density_grid.density.shape)
    lo = np.asarray(bbox_min, np.float64)
    hi = np.asarray(bbox_max, np.float64)
    if not own_box_given:
        if a.shape != dshape:
            raise VolumeError(f"{source}: shape (nz, ny, nx) = {a.shape} does not match the "
                              f"density's {dshape}; give the grid the density's shape or a box "
                              f"of its own")
        lo, hi = density_grid.bbox_min, density_grid.bbox_max
    if not (lo.shape == (3,) and hi.shape == (3,) and np.all(np.isfinite(lo))
            and np.all(np.isfinite(hi)) and np.all(lo < hi)):
        raise VolumeError(f"{source}: box {lo.tolist()}..{hi.tolist()} must be 3 finite numbers "
                          f"each, min < max")
    on_density = (a.shape == dshape and np.array_equal(lo, density_grid.bbox_min)
                  and np.array_equal(hi, density_grid.bbox_max))
    s = float(spec.scale)
    if spec.kind == "blackbody":
        if float(a64.max()) > 1e6:
            raise VolumeError(f"{source}: temperature {float(a64.max())!r} K is above 1e6 K; "
                              f"a blackbody grid holds kelvin")
        values = map_blackbody(a64)
        colour = (s, s, s)
    else:
        with np.errstate(over="ignore"):
            values = a64.astype(np.float32)[None]
        if not np.all(np.isfinite(values)):
            raise VolumeError(f"{source}: values do not fit in float32")
        colour = tuple(s * float(c) for c in spec.colour)
    return EmissionGrid(np.ascontiguousarray(values, np.float32), lo.copy(), hi.copy(), colour,
                        own_box=not on_density, kind=spec.kind, name=spec.grid)


def load_emission(spec, file: Path | None, density_grid, max_resolution: int | None = None,
                  max_bytes: int | None = None) -> EmissionGrid:
    """Read the grid ``spec.grid`` of the volume ``file`` (.vdb or .npz) and map it."""
    if file is None:
        raise VolumeError(f"[emission.grid] = {spec.grid!r}: emission grids come from the "
                          f"volume file (.vdb or .npz); a generated volume has none")
    file = Path(file)
    suffix = file.suffix.lower()
    source = f"{file}: emission grid {spec.grid!r}"
    if suffix == ".vdb":
        from .volume.vdb import VdbFile
        with VdbFile(file) as vf:
            names = [g.name for g in vf.grids]
            if spec.grid not in names:
                raise VolumeError(f"{file}: no grid named {spec.grid!r} for [emission]; the file "
                                  f"has {', '.join(repr(n) for n in names)}")
            try:
                g = vf.read(vf.choose(spec.grid), max_resolution, max_bytes)
            except VolumeError as e:
                raise VolumeError(f"{source}: {e}") from None
        return make_emission(g.density, g.bbox_min, g.bbox_max, spec, density_grid, source, True)
    if suffix == ".npz":
        try:
            with np.load(file, allow_pickle=False) as npz:
                keys = set(npz.files)
                if spec.grid not in keys:
                    raise VolumeError(f"{file}: no array named {spec.grid!r} for [emission]; "
                                      f"the file has {sorted(keys)}")
                raw = npz[spec.grid]
                lo_k, hi_k = f"{spec.grid}_bbox_min", f"{spec.grid}_bbox_max"
                if (lo_k in keys) != (hi_k in keys):
                    raise VolumeError(f"{source}: give both {lo_k} and {hi_k} or neither")
                own = lo_k in keys
                lo = npz[lo_k] if own else density_grid.bbox_min
                hi = npz[hi_k] if own else density_grid.bbox_max
        except VolumeError:
            raise
        except Exception as e:
            raise VolumeError(f"{file}: cannot read as .npz: {type(e).__name__}: {e}") from None
        return make_emission(raw, np.asarray(lo, np.float64).ravel(),
                             np.asarray(hi, np.float64).ravel(), spec, density_grid, source, own)
    raise VolumeError(f"{file}: [emission] reads grids from .vdb or .npz volume files, not "
                      f"{suffix}")
