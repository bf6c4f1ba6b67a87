"""Multiple-scattering sources of the ray marcher: one object per way of getting F_ms.

Every source answers the same questions, so the marcher (clvol/render/raymarch.py) never
tests a source's name:

- ``plan(medium, shortcuts)``: an ``MsPlan`` with the kernel -D defines it needs, the device
  data it reads (an F_ms lattice, or nothing) and what it simulates or skips (header lines);
- ``prepare(frame)``: fill its data for the frame's camera, light and medium (a no-op for
  analytic sources; the network fills its lattice here, only when the frame changed what the
  lattice depends on);
- ``header()``: its own header entries (options, weights, time split).

Sources: ``NoMs`` ("none", single scattering only), ``OctavesMs`` ("wrenninge", the games'
analytic octaves), ``GridMs`` ("grid", a precomputed ``MsGrid``), ``NetworkMs``
("network", clvol/render/network.py) and ``ViewMs`` ("view", the network at the camera's
view, clvol/render/view.py). clvol/render/msregistry.py maps ``--ms`` names to classes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import ClvolError
from ..kernels.raymarch import MAX_OCTAVES, ms_defines
from ..runtime import DeviceArray


# --------------------------------------------------------------------------- data

@dataclass(frozen=True)
class Octaves:
    """Wrenninge octaves: F_ms = sum_{i=1}^{n-1} b^i f(mu; g c^i) T_light^(a^i).

    ``a`` multiplies the optical depth toward the light, ``b`` the contribution, ``c`` the
    phase eccentricity. Energy condition (Wrenninge et al.): an octave's contribution
    multiplier must not exceed its extinction multiplier, i.e. ``b <= a`` in this formula's
    letters (the paper writes it "a <= b" with the roles of the letters swapped;
    docs/raymarch.md). Defaults a = b = c = 0.5, n = 3 satisfy it.
    """
    n: int = 3
    a: float = 0.5
    b: float = 0.5
    c: float = 0.5

    @property
    def energy_conserving(self) -> bool:
        return self.b <= self.a

    @classmethod
    def from_options(cls, o: dict) -> "Octaves":
        """From render options (octaves, ms_a, ms_b, ms_c); the defaults above for any missing."""
        d = cls()
        return cls(o.get("octaves", d.n), float(o.get("ms_a", d.a)), float(o.get("ms_b", d.b)),
                   float(o.get("ms_c", d.c)))

    def as_options(self) -> dict:
        return {"octaves": self.n, "ms_a": self.a, "ms_b": self.b, "ms_c": self.c}

    def check(self) -> "Octaves":
        def bad(name, value, allowed):
            return ClvolError(f"raymarch option {name} = {value!r}: {allowed}")
        if not (isinstance(self.n, (int, np.integer)) and not isinstance(self.n, bool)
                and 1 <= self.n <= MAX_OCTAVES):
            raise bad("octaves", self.n, f"must be an integer from 1 to {MAX_OCTAVES}")
        # a = 0 would make T^(a^i) = 1 behind any amount of medium: light through walls.
        for name, v, lo_open in (("ms_a", self.a, True), ("ms_b", self.b, False),
                                 ("ms_c", self.c, False)):
            ok = math.isfinite(v) and (0 < v <= 1 if lo_open else 0 <= v <= 1)
            if not ok:
                raise bad(name, v, "must be in (0, 1]" if lo_open else "must be in [0, 1]")
        return self


@dataclass(frozen=True)
class MsGrid:
    """Precomputed F_ms (radiance per unit irradiance, orders >= 2) on a grid over a box.

    ``values``: float32 (gz, gy, gx, 3) RGB or (gz, gy, gx) grey, voxel centres at
    bbox_min + (i + 0.5) * cell like every clvol grid, read trilinearly (clamped). F_ms
    depends on the view direction: a grid made for one camera holds F_ms(x, omega(x)) with
    omega(x) = normalize(camera.origin - x) (``fill_ms_grid`` does this).
    """
    values: np.ndarray
    bbox_min: tuple
    bbox_max: tuple

    def planes(self) -> np.ndarray:
        """(C, gz, gy, gx) float32, C = 1 (grey) or 3: the kernel's layout."""
        v = np.asarray(self.values, np.float32)
        if v.ndim == 3:
            return v[None]
        return np.ascontiguousarray(np.moveaxis(v, -1, 0))


def check_ms_grid(g) -> MsGrid:
    if not isinstance(g, MsGrid):
        raise ClvolError(f"ms grid: expected a clvol.render.sources.MsGrid, got {type(g).__name__}")
    v = np.asarray(g.values)
    if not (v.ndim == 3 or (v.ndim == 4 and v.shape[3] == 3)) or min(v.shape[:3]) < 1:
        raise ClvolError(f"ms grid: values of shape {v.shape}; expected (gz, gy, gx, 3) or (gz, gy, gx)")
    if not np.isfinite(v).all() or (v < 0).any():
        raise ClvolError("ms grid: values must be finite and >= 0 (F_ms is a radiance)")
    lo, hi = np.asarray(g.bbox_min, np.float64), np.asarray(g.bbox_max, np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or not np.all(hi > lo):
        raise ClvolError(f"ms grid: bbox_min {lo.tolist()} must be below bbox_max {hi.tolist()} on every axis")
    return g


def load_ms_grid(path) -> MsGrid:
    """An ``.npz`` with arrays ``values`` ((gz, gy, gx, 3) or (gz, gy, gx)), ``bbox_min``, ``bbox_max``."""
    try:
        with np.load(path) as z:
            missing = [k for k in ("values", "bbox_min", "bbox_max") if k not in z]
            if missing:
                raise ClvolError(f"{path}: ms grid file lacks array(s) {missing}; needs values, "
                                 f"bbox_min, bbox_max")
            return check_ms_grid(MsGrid(z["values"].astype(np.float32),
                                        tuple(z["bbox_min"]), tuple(z["bbox_max"])))
    except (OSError, ValueError) as exc:
        raise ClvolError(f"{path}: cannot read ms grid ({exc})") from None


def ms_lattice(scene, resolution, bbox_min=None, bbox_max=None, origin=None):
    """(res (gx, gy, gz), lo, hi, points (N, 3), omegas (N, 3)) of an F_ms lattice: voxel
    centres over the box (default: the volume's), [z][y][x] order, omega toward the camera
    (``origin``, default the scene camera's)."""
    res = (resolution,) * 3 if np.isscalar(resolution) else tuple(resolution)
    if len(res) != 3 or min(res) < 1:
        raise ClvolError(f"ms grid resolution {resolution!r}: give n or (gx, gy, gz), each >= 1")
    if bbox_min is None or bbox_max is None:
        g = scene.volume.load()
        bbox_min, bbox_max = g.bbox_min, g.bbox_max
    lo, hi = np.asarray(bbox_min, np.float64), np.asarray(bbox_max, np.float64)
    axes = [lo[a] + (np.arange(res[a]) + 0.5) * (hi[a] - lo[a]) / res[a] for a in range(3)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    pts = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    om = np.asarray(scene.camera.origin if origin is None else origin, np.float64) - pts
    norm = np.linalg.norm(om, axis=1, keepdims=True)
    # A point at the camera has no direction toward it: any unit vector will do (+z).
    om = np.where(norm > 0, om / np.where(norm > 0, norm, 1.0), np.array([0.0, 0.0, 1.0]))
    return res, lo, hi, pts, om


def fill_ms_grid(scene, resolution, query, bbox_min=None, bbox_max=None) -> MsGrid:
    """Fill an MsGrid for the scene's camera from a point estimator of F_ms.

    ``query(points (N, 3), omegas (N, 3)) -> (N, 3)`` returns F_ms for a light of irradiance 1
    (e.g. ``lambda p, w: point_query(scene, p, w, n_paths)["Fms"]``, or the network).
    The lattice is ``resolution`` (int or (gx, gy, gz)) voxel centres over the box
    (default: the volume's box); omega at each point is toward the camera.
    """
    res, lo, hi, pts, om = ms_lattice(scene, resolution, bbox_min, bbox_max)
    vals = np.asarray(query(pts, om), np.float64).reshape(res[2], res[1], res[0], 3)
    return check_ms_grid(MsGrid(np.maximum(vals, 0.0).astype(np.float32), tuple(lo), tuple(hi)))


# --------------------------------------------------------------------------- interface

@dataclass
class MsPlan:
    """What one source asks of the kernel for one medium."""
    defines: dict
    planes: DeviceArray | None = None       # (C, gz, gy, gx) F_ms lattice, or None
    box: tuple | None = None                # (bbox_min, bbox_max) of the lattice
    octaves: Octaves = Octaves()            # oct_a, oct_b, oct_c kernel arguments
    simulated: list = field(default_factory=list)
    skipped: list = field(default_factory=list)

    @property
    def channels(self) -> int | None:
        """Colour planes marched for F_ms, or None when the source has no lattice or table."""
        return None if self.planes is None else int(self.defines["MS_CHANNELS"])


@dataclass
class Frame:
    """What a source may read to fill its data: the volume, the frame's camera, light and
    medium, the runtime, the shortcut switch, and ``count(stage)`` (recomputation counters)."""
    grid: object
    camera: object
    light: object
    medium: object
    runtime: object
    shortcuts: bool = True
    count: object = None
    reach: float = 0.0        # world distance from a density sample to the F_ms read, + 1 voxel
    cache: dict | None = None  # the DeviceMedium's cache (data that lives as long as the volume)
    density: object = None    # the density already on the device (DeviceArray), if any
    step: float = 0.0         # the march's segment length (world units) ...
    threshold: float = 1e-3   # ... and its early-termination transmittance


class MsSource:
    """Base class: no multiple scattering. Subclasses override what they need."""
    name = "none"
    label = "no multiple scattering"
    options: tuple[str, ...] = ()      # the Renderer options this source reads

    @classmethod
    def from_options(cls, o: dict, runtime=None) -> "MsSource":
        """The source built from render options (it reads those in ``options``; a missing
        one takes its default)."""
        return cls()

    def prepare(self, frame: Frame) -> None:
        """Fill this source's data for the frame (nothing to do for an analytic source)."""

    def skip(self) -> None:
        """This frame does not read the source (nothing is lit): forget per-frame state that
        its header would otherwise report as this frame's."""

    def plan(self, medium, shortcuts: bool) -> MsPlan:
        return MsPlan(ms_defines("none"), skipped=[f"multiple scattering (--ms {self.name})"])

    def header(self) -> dict:
        return {}


class NoMs(MsSource):
    """Single scattering only."""


class OctavesMs(MsSource):
    """Wrenninge octaves evaluated in the kernel from the light field: no data of its own."""
    name = "wrenninge"
    label = "Wrenninge octaves (analytic multiple scattering)"
    options = ("octaves", "ms_a", "ms_b", "ms_c")

    def __init__(self, octaves: Octaves = Octaves()):
        self.octaves = octaves.check()

    @classmethod
    def from_options(cls, o: dict, runtime=None) -> "OctavesMs":
        return cls(Octaves.from_options(o))

    def plan(self, medium, shortcuts: bool) -> MsPlan:
        o = self.octaves
        p = MsPlan(ms_defines("wrenninge", o.n), octaves=o)
        if o.n > 1:
            p.simulated.append(f"multiple scattering (Wrenninge octaves n={o.n} a={o.a:g} "
                               f"b={o.b:g} c={o.c:g})")
        else:
            p.skipped.append("multiple scattering (Wrenninge with 1 octave: single only)")
        return p

    def header(self) -> dict:
        o = self.octaves
        return {"raymarch.octaves": o.n, "raymarch.ms_a": o.a, "raymarch.ms_b": o.b,
                "raymarch.ms_c": o.c, "raymarch.energy_condition_b_le_a": o.energy_conserving}


class GridMs(MsSource):
    """An F_ms lattice read trilinearly by the kernel. Subclasses set ``self.ms_grid`` in
    ``prepare``; the lattice goes to the device once per grid and colour layout."""
    name = "grid"
    label = "precomputed F_ms grid"
    options = ("ms_grid",)
    what = "precomputed F_ms grid"

    def __init__(self, ms_grid: MsGrid | None = None, runtime=None):
        self.ms_grid = None if ms_grid is None else check_ms_grid(ms_grid)
        self.runtime = runtime
        self._uploaded = None        # (ms_grid, grey?, DeviceArray)
        self.count = None

    @classmethod
    def from_options(cls, o: dict, runtime=None) -> "GridMs":
        g = o.get("ms_grid")
        if g is None:
            raise _no_grid()
        return cls(g if hasattr(g, "values") else load_ms_grid(g), runtime)

    def planes_for(self, medium, shortcuts: bool):
        """((C, gz, gy, gx) planes on the device, grey shortcut taken?)."""
        planes = self.ms_grid.planes()
        grey_grid = planes.shape[0] == 1 or (np.array_equal(planes[0], planes[1])
                                             and np.array_equal(planes[0], planes[2]))
        grey = bool(shortcuts and grey_grid and medium.is_grey)
        up = self._uploaded
        if up is None or up[0] is not self.ms_grid or up[1] != grey:
            if grey:
                planes = np.ascontiguousarray(planes[:1])
            elif planes.shape[0] == 1:
                planes = np.ascontiguousarray(np.repeat(planes, 3, axis=0))
            from ..runtime import get_runtime
            rt = self.runtime or get_runtime()
            if self.count:
                self.count("ms_upload")
            self._uploaded = up = (self.ms_grid, grey, rt.upload(planes))
        return up[2], grey

    def plan(self, medium, shortcuts: bool) -> MsPlan:
        if self.ms_grid is None:
            raise _no_grid()
        planes, grey = self.planes_for(medium, shortcuts)
        gz, gy, gx = planes.shape[1:]
        p = MsPlan(ms_defines("grid", channels=planes.shape[0]), planes=planes,
                   box=(tuple(self.ms_grid.bbox_min), tuple(self.ms_grid.bbox_max)))
        if grey:
            p.skipped.append("colour channels 2 and 3 of the F_ms grid (grey albedo, grey grid)")
        p.simulated.append(f"multiple scattering ({self.what} {gx}x{gy}x{gz}, "
                           f"{planes.shape[0]} channel(s))")
        return p


def _no_grid() -> ClvolError:
    return ClvolError("raymarch option ms = 'grid' needs an ms grid (--ms-grid FILE.npz, "
                      "or ms_grid=MsGrid(...) in Python)")

