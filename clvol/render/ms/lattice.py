"""A precomputed F_ms lattice (``FmsLattice``) and the source that marches one (``LatticeMs``, ``--ms
lattice``); the network's source (network.py) is a LatticeMs whose lattice the network fills."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import ClvolError
from ...kernels.raymarch import MS_KIND_LATTICE, ms_defines
from .base import MsPlan, MsSource, option


@dataclass(frozen=True)
class FmsLattice:
    """Precomputed F_ms (radiance per unit irradiance, orders >= 2) on a grid over a box.

    ``values``: float32 (gz, gy, gx, 3) RGB or (gz, gy, gx) grey, voxel centres at
    bbox_min + (i + 0.5) * cell like every clvol grid, read trilinearly (clamped). F_ms
    depends on the view direction: a grid made for one camera holds F_ms(x, omega(x)) with
    omega(x) = normalize(camera.origin - x) (``fill_fms_lattice`` does this).
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


def check_fms_lattice(g) -> FmsLattice:
    if not isinstance(g, FmsLattice):
        raise ClvolError(f"F_ms lattice: expected a clvol.render.ms.lattice.FmsLattice, got {type(g).__name__}")
    v = np.asarray(g.values)
    if not (v.ndim == 3 or (v.ndim == 4 and v.shape[3] == 3)) or min(v.shape[:3]) < 1:
        raise ClvolError(f"F_ms lattice: values of shape {v.shape}; expected (gz, gy, gx, 3) or (gz, gy, gx)")
    if not np.isfinite(v).all() or (v < 0).any():
        raise ClvolError("F_ms lattice: values must be finite and >= 0 (F_ms is a radiance)")
    lo, hi = np.asarray(g.bbox_min, np.float64), np.asarray(g.bbox_max, np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or not np.all(hi > lo):
        raise ClvolError(f"F_ms lattice: bbox_min {lo.tolist()} must be below bbox_max {hi.tolist()} on every axis")
    return g


def load_fms_lattice(path) -> FmsLattice:
    """An ``.npz`` with arrays ``values`` ((gz, gy, gx, 3) or (gz, gy, gx)), ``bbox_min``, ``bbox_max``."""
    try:
        with np.load(path) as z:
            missing = [k for k in ("values", "bbox_min", "bbox_max") if k not in z]
            if missing:
                raise ClvolError(f"{path}: F_ms lattice file lacks array(s) {missing}; needs values, "
                                 f"bbox_min, bbox_max")
            return check_fms_lattice(FmsLattice(z["values"].astype(np.float32),
                                        tuple(z["bbox_min"]), tuple(z["bbox_max"])))
    except (OSError, ValueError) as exc:
        raise ClvolError(f"{path}: cannot read F_ms lattice ({exc})") from None


def ms_lattice(scene, resolution, bbox_min=None, bbox_max=None, origin=None):
    """(res (gx, gy, gz), lo, hi, points (N, 3), omegas (N, 3)) of an F_ms lattice: voxel
    centres over the box (default: the volume's), [z][y][x] order, omega toward the camera
    (``origin``, default the scene camera's)."""
    res = (resolution,) * 3 if np.isscalar(resolution) else tuple(resolution)
    if len(res) != 3 or min(res) < 1:
        raise ClvolError(f"F_ms lattice resolution {resolution!r}: give n or (gx, gy, gz), each >= 1")
    if bbox_min is None or bbox_max is None:
        g = scene.volume.load()
        bbox_min, bbox_max = g.bbox_min, g.bbox_max
    lo, hi = np.asarray(bbox_min, np.float64), np.asarray(bbox_max, np.float64)
    axes = [lo[a] + (np.arange(res[a]) + 0.5) * (hi[a] - lo[a]) / res[a] for a in range(3)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    pts = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    om = toward(scene.camera.origin if origin is None else origin, pts)
    return res, lo, hi, pts, om


def toward(origin, points) -> np.ndarray:
    """(N, 3) unit directions from ``points`` toward ``origin`` (omega, toward the camera)."""
    om = np.asarray(origin, np.float64) - np.asarray(points, np.float64)
    norm = np.linalg.norm(om, axis=1, keepdims=True)
    # A point at the camera has no direction toward it: any unit vector will do (+z).
    return np.where(norm > 0, om / np.where(norm > 0, norm, 1.0), np.array([0.0, 0.0, 1.0]))


def fill_fms_lattice(scene, resolution, query, bbox_min=None, bbox_max=None) -> FmsLattice:
    """Fill an FmsLattice for the scene's camera from a point estimator of F_ms.

    ``query(points (N, 3), omegas (N, 3)) -> (N, 3)`` returns F_ms for a light of irradiance 1
    (e.g. ``lambda p, w: point_query(scene, p, w, n_paths)["Fms"]``, or the network).
    The lattice is ``resolution`` (int or (gx, gy, gz)) voxel centres over the box
    (default: the volume's box); omega at each point is toward the camera.
    """
    res, lo, hi, pts, om = ms_lattice(scene, resolution, bbox_min, bbox_max)
    vals = np.asarray(query(pts, om), np.float64).reshape(res[2], res[1], res[0], 3)
    return check_fms_lattice(FmsLattice(np.maximum(vals, 0.0).astype(np.float32), tuple(lo), tuple(hi)))


class LatticeMs(MsSource):
    """An F_ms lattice read trilinearly by the kernel. Subclasses set ``self.ms_lattice`` in
    ``prepare``; the lattice goes to the device once per grid and colour layout."""
    name = "lattice"
    label = "precomputed F_ms lattice"
    summary = "precomputed F_ms, --ms-lattice"
    multiple_scattering = True
    options = (option("--ms-lattice", metavar="FILE.npz",
                      help="precomputed F_ms lattice (arrays values, bbox_min, bbox_max) for "
                           "--ms lattice"),)
    what = "precomputed F_ms lattice"

    def __init__(self, ms_lattice: FmsLattice | None = None, runtime=None):
        self.ms_lattice = None if ms_lattice is None else check_fms_lattice(ms_lattice)
        self.runtime = runtime
        self._uploaded = None        # (ms_lattice, grey?, DeviceArray)
        self.count = None

    @classmethod
    def from_options(cls, o, runtime=None) -> "LatticeMs":
        return cls(options_lattice(o), runtime)

    @staticmethod
    def _grey(planes, medium, shortcuts: bool) -> bool:
        """The grey shortcut: one plane marched for a grey medium and a grey lattice."""
        grey_lattice = planes.shape[0] == 1 or (np.array_equal(planes[0], planes[1])
                                             and np.array_equal(planes[0], planes[2]))
        return bool(shortcuts and grey_lattice and medium.is_grey)

    @classmethod
    def plan_for(cls, medium, camera, shortcuts: bool, options) -> MsPlan:
        planes = options_lattice(options).planes()
        return cls._grid_plan(cls._grey(planes, medium, shortcuts), planes.shape[1:])

    @classmethod
    def _grid_plan(cls, grey: bool, shape) -> MsPlan:
        gz, gy, gx = shape
        channels = 1 if grey else 3
        p = MsPlan(ms_defines(MS_KIND_LATTICE, channels=channels))
        if grey:
            p.skipped.append("colour channels 2 and 3 of the F_ms lattice (grey albedo, grey lattice)")
        p.simulated.append(f"multiple scattering ({cls.what} {gx}x{gy}x{gz}, "
                           f"{channels} channel(s))")
        return p

    def device_data(self, medium, shortcuts: bool):
        """The lattice's planes on the device in the plan's colour layout (uploaded once per
        grid and layout) and its box."""
        if self.ms_lattice is None:
            raise _no_lattice()
        planes = self.ms_lattice.planes()
        grey = self._grey(planes, medium, shortcuts)
        up = self._uploaded
        if up is None or up[0] is not self.ms_lattice or up[1] != grey:
            if grey:
                planes = np.ascontiguousarray(planes[:1])
            elif planes.shape[0] == 1:
                planes = np.ascontiguousarray(np.repeat(planes, 3, axis=0))
            from ...runtime import get_runtime
            rt = self.runtime or get_runtime()
            if self.count:
                self.count("ms_upload")
            self._uploaded = up = (self.ms_lattice, grey, rt.upload(planes, label="F_ms lattice"))
        return up[2], (tuple(self.ms_lattice.bbox_min), tuple(self.ms_lattice.bbox_max))


def options_lattice(o) -> FmsLattice:
    """The ``ms_lattice`` option as an FmsLattice (a given FmsLattice, or read from its .npz file)."""
    g = o.get("ms_lattice")
    if g is None:
        raise _no_lattice()
    return g if isinstance(g, FmsLattice) else load_fms_lattice(g)


def _no_lattice() -> ClvolError:
    return ClvolError("raymarch option ms = 'lattice' needs an F_ms lattice (--ms-lattice FILE.npz, "
                      "or ms_lattice=FmsLattice(...) in Python)")
