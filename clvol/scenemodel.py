"""The parts of a scene: volume, medium, light and camera, the limits on them and the material
presets.

The classes here are frozen dataclasses that the renderers read. The whole ``Scene``, which
holds one of each, is clvol/scenefile.py's (it is made and copied through the file parser:
``load_scene``, ``scene_from_dict``, ``Scene.with_overrides``; format in docs/scenes.md).
Users import every name from clvol/scene.py; this module imports neither of the other two.

``Camera.pixel_directions`` is *the* camera convention of the project (docs/conventions.md):
column 0 is the left edge, row 0 the top, right = normalize(cross(forward, up)).
OpenCL kernels copy that formula.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import ClvolError, VolumeError

# --------------------------------------------------------------------------- limits

HG_G_LIMIT = 0.99          # |g| above this makes HG peaks too narrow for our tables (docs/conventions.md)
MHG_MAX_LOBES = 3
MHG_WEIGHT_TOL = 1e-4      # lobe weights must sum to 1 within this, then are renormalised
MAX_IMAGE_SIZE = 16384
VOLUME_SUFFIXES = (".vol", ".npy", ".npz", ".vdb")
MAX_VDB_RESOLUTION = 16384   # [volume.max_resolution]: voxels on the longest axis, border included
# A vector whose length is already 1 (or weights already summing to 1) within this is left
# alone, so that writing a scene and reading it back gives bit-identical values.
_ALREADY_UNIT = 1e-12


# --------------------------------------------------------------------------- data model

@dataclass(frozen=True)
class Lobe:
    """One Henyey-Greenstein lobe: asymmetry ``g`` and mixture ``weight``."""
    g: float
    weight: float


@dataclass(frozen=True)
class Phase:
    """A phase function: ``isotropic``, ``hg`` (one lobe) or ``mhg`` (weighted HG lobes).

    ``lobes`` always holds the lobes, so code that evaluates the phase function can
    ignore ``type``: isotropic is ``(Lobe(0.0, 1.0),)`` and hg is ``(Lobe(g, 1.0),)``.
    """
    type: str
    lobes: tuple[Lobe, ...]

    @classmethod
    def isotropic(cls) -> "Phase":
        return cls("isotropic", (Lobe(0.0, 1.0),))

    @classmethod
    def hg(cls, g: float) -> "Phase":
        return cls("hg", (Lobe(float(g), 1.0),))

    @classmethod
    def mhg(cls, lobes) -> "Phase":
        """``lobes``: iterable of ``Lobe`` or ``(g, weight)`` pairs, weights summing to 1."""
        return cls("mhg", tuple(l if isinstance(l, Lobe) else Lobe(float(l[0]), float(l[1]))
                                for l in lobes))

    @property
    def mean_cosine(self) -> float:
        """Mean cosine ``sum(w_k g_k)``: the one number that stands for the phase (docs/conventions.md)."""
        return float(sum(l.weight * l.g for l in self.lobes))

    @property
    def pairs(self) -> tuple[tuple[float, float], ...]:
        """The lobes as (g, weight) pairs of floats, the form the kernels' wrappers take."""
        return tuple((float(lo.g), float(lo.weight)) for lo in self.lobes)

    @property
    def is_isotropic(self) -> bool:
        return self.type == "isotropic" or all(l.g == 0.0 for l in self.lobes)


@dataclass(frozen=True)
class VolumeSpec:
    """Where the density grid comes from: a file, or a procedural generator."""
    file: Path | None
    generator: str | None
    seed: int = 0
    resolution: tuple[int, int, int] | int | None = None
    params: dict = field(default_factory=dict)
    bbox_min: tuple[float, float, float] | None = None
    bbox_max: tuple[float, float, float] | None = None
    grid: str | None = None                 # .vdb only: which grid
    max_resolution: int | None = None       # .vdb only: box-filter while reading
    frame: int | None = None                # a sequence (file with {frame}): the frame to load

    @property
    def is_sequence(self) -> bool:
        """The file name is a pattern with a ``{frame}`` field (docs/scenes.md, "Sequences")."""
        return self.file is not None and is_frame_pattern(self.file.name)

    def frame_file(self, frame: int | None = None) -> Path | None:
        """The file of ``frame`` (default ``self.frame``); the file itself for a non-sequence."""
        if not self.is_sequence:
            return self.file
        n = self.frame if frame is None else frame
        if n is None:
            raise VolumeError(f"{self.file}: the volume is a sequence; pick a frame "
                              f"(clvol render --frames N, or [volume] frame = N)")
        return self.file.with_name(self.file.name.format(frame=int(n)))

    def for_frame(self, frame: int) -> "VolumeSpec":
        """This volume at ``frame`` (a sequence), or itself (a single file)."""
        return dataclasses.replace(self, frame=int(frame)) if self.is_sequence else self

    def load(self, max_bytes: int | None = None):
        """Read the file or run the generator; apply the bbox override. Returns a ``DensityGrid``.

        A .vdb grid whose dense array would exceed ``max_bytes`` (default: the OpenCL device's
        largest buffer, when a device is available) is refused with the ``max_resolution`` that
        would fit, before anything large is allocated. A sequence loads ``frame``.
        """
        if self.file is not None:
            from .volume.io import read_volume
            file = self.frame_file()
            if not file.is_file():
                raise VolumeError(f"{file}: volume file not found")
            if file.suffix.lower() == ".vdb":
                if max_bytes is None:
                    max_bytes = _device_buffer_limit()
                grid = read_volume(file, grid=self.grid, max_resolution=self.max_resolution,
                                   max_bytes=max_bytes)
            else:
                grid = read_volume(file)
        else:
            from .volume.generators import generate
            res = self.resolution if self.resolution is not None else 64
            grid = generate(self.generator, seed=self.seed, resolution=res, **self.params)
        if self.bbox_min is None:
            return grid
        bmin = np.asarray(self.bbox_min, dtype=np.float64)
        bmax = np.asarray(self.bbox_max, dtype=np.float64)
        if dataclasses.is_dataclass(grid):
            return dataclasses.replace(grid, bbox_min=bmin, bbox_max=bmax)
        return type(grid)(density=grid.density, bbox_min=bmin, bbox_max=bmax)


def is_frame_pattern(name: str) -> bool:
    """``name`` holds a ``{frame...}`` replacement field (a volume sequence)."""
    return "{" in name


@dataclass(frozen=True)
class EmissionSpec:
    """``[emission]``: the grid ``grid`` of the volume file, mapped to emitted radiance by
    ``kind`` ("radiance": scale * colour * value; "blackbody": scale * rgb(value in kelvin));
    clvol/emission.py."""
    grid: str
    kind: str
    scale: float = 1.0
    colour: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def load(self, volume: "VolumeSpec", density_grid, max_bytes: int | None = None):
        """The EmissionGrid of ``volume``'s file (its frame, for a sequence)."""
        from .emission import load_emission
        file = volume.frame_file() if volume.file is not None else None
        if file is not None and file.suffix.lower() == ".vdb" and max_bytes is None:
            max_bytes = _device_buffer_limit()
        return load_emission(self, file, density_grid, volume.max_resolution, max_bytes)


def _device_buffer_limit() -> int | None:
    """CL_DEVICE_MAX_MEM_ALLOC_SIZE of the configured OpenCL device, or None without one."""
    from .errors import ClvolError
    try:
        from .runtime import get_runtime
        return int(get_runtime().device.max_mem_alloc_size)
    except (ClvolError, ImportError):
        return None     # no device: the render reports that itself


@dataclass(frozen=True)
class Property:
    """What a declared scene property is, read from its declaration alone by the scene file's
    reader and writer (clvol/scenefile.py) and, with ``kernel``, by the block packers
    (clvol/kernels/blocks.py), which give it the next free slot of the medium's or the light's
    block and the kernels a ``-D MEDIUM_SLOT_<NAME>`` (or ``LIGHT_SLOT_<NAME>``) to read it by
    (cl/include/blocks.h).
    ``kind``: "number" (one float) or "rgb" (a number for grey, or 3 numbers); the range
    ``lo`` .. ``hi`` (None: unbounded; ``*_open``: the bound itself refused, numbers only)."""
    kind: str
    help: str
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    kernel: bool = False

    def __post_init__(self):
        if self.kind not in ("number", "rgb"):
            raise TypeError(f"a declared property's kind is 'number' or 'rgb', not {self.kind!r}")
        if self.kind == "rgb" and (self.lo_open or self.hi_open):
            raise TypeError("an RGB property's bounds are closed (the file's RGB check has no "
                            "open bounds)")


def declared(default, help: str, kind: str = "number", **limits):
    """A dataclass field of ``Medium``, ``Light`` or ``Camera`` with its ``Property`` (the one
    place a new property is written):

        single_scale: float = declared(1.0, "factor on single scattering", lo=0.0, kernel=True)

    The scene file reads it from its table (optional: ``default`` when absent), writes it
    back, checks its kind and range with the file's one-line messages; with ``kernel`` (a
    Medium's or a Light's) the kernels read it from the medium or light block
    (clvol/kernels/blocks.py; docs/architecture.md, "Add a scene field")."""
    return field(default=default, metadata={"property": Property(kind, help, **limits)})


def declared_properties(cls) -> tuple[tuple[str, "Property", object], ...]:
    """``(name, Property, default)`` of each declared field of the dataclass ``cls``, in
    declaration order."""
    return tuple((f.name, f.metadata["property"], f.default) for f in dataclasses.fields(cls)
                 if "property" in f.metadata)


@dataclass(frozen=True)
class Medium:
    """``sigma_t = density * density_scale``; RGB ``albedo``; ``phase``; the preset it came
    from; then the declared properties (``declared``), each with its default."""
    density_scale: float
    albedo: tuple[float, float, float]
    phase: Phase
    preset: str | None = None

    @property
    def is_grey(self) -> bool:
        return self.albedo[0] == self.albedo[1] == self.albedo[2]


@dataclass(frozen=True)
class Light:
    """A distant light. ``direction`` is a unit vector pointing *toward* the light.

    The sky is either ``environment`` (constant radiance, RGB) or ``environment_map`` (a
    lat-long EXR, absolute path, validated when the scene is loaded; convention in
    clvol/envmap.py and docs/conventions.md) times ``environment_scale`` (RGB), turned by
    ``environment_rotation`` degrees about the world up axis +y; or neither."""
    direction: tuple[float, float, float]
    irradiance: tuple[float, float, float] = (1.0, 1.0, 1.0)
    environment: tuple[float, float, float] | None = None
    environment_map: Path | None = None
    environment_scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    environment_rotation: float = 0.0

    def environment_texels(self):
        """The map's (H, W, 3) float32 texels (unscaled; cached, read-only), or None."""
        if self.environment_map is None:
            return None
        from .envmap import load_map
        return load_map(self.environment_map)

    def sky_mean(self) -> np.ndarray:
        """Mean radiance (float64, [3]) of the sky over the sphere: the constant
        ``environment``, or the map's solid-angle mean times ``environment_scale``; zeros
        for no sky."""
        if self.environment is not None:
            return np.asarray(self.environment, dtype=np.float64)
        if self.environment_map is not None:
            from .envmap import mean_radiance
            return mean_radiance(self.environment_texels()) * \
                np.asarray(self.environment_scale, dtype=np.float64)
        return np.zeros(3)


@dataclass(frozen=True)
class Camera:
    """A pinhole camera; ``fov_y`` is the full vertical field of view in degrees."""
    origin: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float]
    fov_y: float
    width: int
    height: int

    @property
    def tan_half_fov(self) -> float:
        """tan(fov_y / 2): the image plane's half-height at distance 1."""
        return math.tan(math.radians(self.fov_y) / 2.0)

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(forward, right, up)``: orthonormal float64 vectors of the image plane.

        forward = normalize(target - origin), right = normalize(cross(forward, up)),
        up = cross(right, forward) (the ``up`` field only picks the roll).
        """
        fwd = _unit(np.subtract(self.target, self.origin, dtype=np.float64))
        right = _unit(np.cross(fwd, _in_range(np.asarray(self.up, dtype=np.float64))))
        return fwd, right, np.cross(right, fwd)

    def pixel_directions(self, jitter: np.ndarray | None = None) -> np.ndarray:
        """Unit directions (H, W, 3) float64 from the origin through each pixel.

        Through the pixel centres, or through ``centre + jitter`` where ``jitter`` has
        shape broadcastable to (H, W, 2), in pixels, ``[..., 0]`` along a row (to the
        right) and ``[..., 1]`` down a column, each in [-0.5, 0.5]. With
        ``sx = 2 (col + 0.5) / W - 1`` and ``sy = 1 - 2 (row + 0.5) / H``::

            d = normalize(forward + sx tan(fov_y/2) (W/H) right + sy tan(fov_y/2) up)
        """
        h, w = self.height, self.width
        col = np.arange(w, dtype=np.float64)[None, :] + 0.5
        row = np.arange(h, dtype=np.float64)[:, None] + 0.5
        if jitter is not None:
            j = np.asarray(jitter, dtype=np.float64)
            try:
                j = np.broadcast_to(j, (h, w, 2))
            except ValueError:
                raise ClvolError(f"jitter of shape {np.shape(jitter)} does not broadcast "
                                 f"to (height, width, 2) = ({h}, {w}, 2)") from None
            if not (np.all(j >= -0.5) and np.all(j <= 0.5)):   # also catches NaN
                raise ClvolError("jitter must be in [-0.5, 0.5] pixels")
            col = col + j[..., 0]
            row = row + j[..., 1]
        return self.directions_at(col, row)

    def directions_at(self, col, row) -> np.ndarray:
        """Unit directions (..., 3) float64 through continuous image positions in pixels
        (pixel k's centre is at k + 0.5; ``col`` to the right, ``row`` down), broadcast."""
        h, w = self.height, self.width
        tan_half = self.tan_half_fov
        sx = (2.0 * np.asarray(col, np.float64) / w - 1.0) * tan_half * (w / h)
        sy = (1.0 - 2.0 * np.asarray(row, np.float64) / h) * tan_half
        sx, sy = np.broadcast_arrays(sx, sy)
        fwd, right, up = self.basis()
        d = fwd + sx[..., None] * right + sy[..., None] * up
        # |d| >= 1 since forward is orthogonal to right and up: no division by zero.
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def image_positions(self, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(col, row, z) of world points (..., 3): the continuous image position that
        ``directions_at`` maps onto each point's direction, and its distance z along the
        forward axis; col and row are NaN where z <= 0 (behind the camera)."""
        fwd, right, up = self.basis()
        v = np.asarray(points, np.float64) - np.asarray(self.origin, np.float64)
        z = v @ fwd
        ahead = z > 0
        zs = np.where(ahead, z, 1.0)          # no division by a zero or negative depth
        tan_half, w, h = self.tan_half_fov, self.width, self.height
        col = ((v @ right) / zs / (tan_half * (w / h)) + 1.0) * (0.5 * w)
        row = (1.0 - (v @ up) / zs / tan_half) * (0.5 * h)
        return np.where(ahead, col, np.nan), np.where(ahead, row, np.nan), z


def _in_range(v: np.ndarray) -> np.ndarray:
    """``v`` itself, or scaled by its largest component where its squares would underflow or
    overflow: the scene file accepts vectors as short as 1e-300 (issue 41's fuzzing: up =
    (0, -2e-259, 1e-285) gave a NaN basis and a march that never ended). Ordinary vectors
    pass untouched, so their images stay bit-identical."""
    with np.errstate(over="ignore", under="ignore"):
        n = np.linalg.norm(v)
    return v if 1e-150 < n < 1e150 else v / np.max(np.abs(v))


def _unit(v: np.ndarray) -> np.ndarray:
    v = _in_range(v)
    return v / np.linalg.norm(v)


# Only the medium and the light have blocks the kernels read declared properties from.
if any(p.kernel for _, p, _ in declared_properties(Camera)):
    raise TypeError("Camera: kernel=True is for Medium's and Light's properties (their kernel "
                    "blocks); the camera reaches the kernels as arguments")


# --------------------------------------------------------------------------- presets

# Artistic defaults from docs/conventions.md, not measured data. A preset gives albedo and phase;
# density_scale depends on the world size of the volume and is always given by the user.
PRESETS: dict[str, tuple[tuple[float, float, float], Phase]] = {
    "cloud": ((0.999, 0.999, 0.999), Phase.hg(0.857)),
    "fog": ((0.95, 0.95, 0.95), Phase.hg(0.7)),
    "smoke": ((0.4, 0.4, 0.4), Phase.hg(0.3)),
    "milk": ((0.999, 0.999, 0.999), Phase.mhg([(0.8, 0.7), (-0.3, 0.3)])),
    "jade": ((0.92, 0.99, 0.94), Phase.mhg([(0.6, 0.8), (-0.2, 0.2)])),
    "wax": ((0.99, 0.97, 0.93), Phase.mhg([(0.4, 0.8), (-0.1, 0.2)])),
    "skin": ((0.99, 0.85, 0.75), Phase.mhg([(0.8, 0.5), (0.3, 0.3), (-0.3, 0.2)])),
}
