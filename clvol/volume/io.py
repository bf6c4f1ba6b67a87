"""Reading and writing density grids: Mitsuba ``.vol``, NumPy ``.npy`` and ``.npz``, and
reading OpenVDB ``.vdb`` (clvol/volume/vdb.py).

Formats (docs/volumes.md has the full description):

``.vol`` (Mitsuba grid volume, little-endian), a 48-byte header then the data::

    offset  size  field
    0       3     magic b"VOL"
    3       1     version, must be 3
    4       4     int32 encoding, must be 1 (float32)
    8       12    int32 xres, yres, zres (each >= 1)
    20      4     int32 channels, must be 1 (a scalar density)
    24      24    float32 bbox xmin, ymin, zmin, xmax, ymax, zmax
    48      4*n   float32 data, x fastest, then y, then z (n = xres*yres*zres)

``.npy``: one 3-D float array indexed [z][y][x]; the box is the default [-0.5, 0.5]^3.
``.npz``: key ``density`` (as .npy) and optionally both ``bbox_min`` and ``bbox_max`` (3 numbers);
further 3-D arrays are grids for ``[emission]`` (clvol/emission.py), each optionally with its
own ``<name>_bbox_min`` and ``<name>_bbox_max``.

Every malformed input raises ``VolumeError`` whose message starts with the file name and
quotes what was found. Nothing is clipped; float64 data is rounded to float32 only when
every value is finite and fits.
"""
from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np

from ..errors import VolumeError
from .grid import DEFAULT_BBOX_MAX, DEFAULT_BBOX_MIN, DensityGrid, check_bbox, density_to_float32

VOL_MAGIC = b"VOL"
VOL_VERSION = 3
VOL_ENCODING_FLOAT32 = 1
# Mitsuba's encoding ids, named in the error message when a file uses one we do not read.
_VOL_ENCODING_NAMES = {1: "float32", 2: "float16", 3: "uint8", 4: "quantized directions"}
# magic(3s) version(B) encoding(i) xres yres zres(3i) channels(i) bbox(6f), little-endian.
_VOL_HEADER = struct.Struct("<3sBiiiii6f")
VOL_HEADER_SIZE = _VOL_HEADER.size  # 48

SUPPORTED_EXTENSIONS = (".vol", ".npy", ".npz", ".vdb")
_NPZ_KEYS = ("density", "bbox_min", "bbox_max")


def _extension(path: Path) -> str:
    ext = path.suffix.lower()
    if ext not in SUPPORTED_EXTENSIONS:
        raise VolumeError(
            f"{path}: unknown volume file extension {path.suffix!r}; supported: "
            f"{', '.join(SUPPORTED_EXTENSIONS)}")
    return ext


def read_volume(path: str | os.PathLike, grid: str | None = None,
                max_resolution: int | None = None, max_bytes: int | None = None) -> DensityGrid:
    """Read a density grid from a ``.vol``, ``.npy``, ``.npz`` or ``.vdb`` file (by extension).

    ``grid``, ``max_resolution`` and ``max_bytes`` apply to ``.vdb`` only (see ``read_vdb``);
    given for another format they are refused, not ignored.
    """
    path = Path(path)
    ext = _extension(path)
    if not path.is_file():
        raise VolumeError(f"{path}: no such volume file")
    if ext == ".vdb":
        from .vdb import read_vdb
        return read_vdb(path, grid=grid, max_resolution=max_resolution, max_bytes=max_bytes)
    for name, value in (("grid", grid), ("max_resolution", max_resolution)):
        if value is not None:
            raise VolumeError(f"{path}: {name} applies to .vdb files only, not {ext}")
    if ext == ".vol":
        return _read_vol(path)
    if ext == ".npy":
        return _read_npy(path)
    return _read_npz(path)


def write_volume(path: str | os.PathLike, grid: DensityGrid) -> None:
    """Write ``grid`` to a ``.vol``, ``.npy`` or ``.npz`` file (chosen by extension).

    ``.npy`` has no room for the box, so a grid whose box is not the default [-0.5, 0.5]^3
    is refused there rather than silently losing it. ``.vol`` stores the box as float32:
    each bound is rounded to float32 (about 7 significant digits).
    """
    path = Path(path)
    ext = _extension(path)
    grid.validate(f"{path} (writing)")
    if ext == ".vol":
        _write_vol(path, grid)
    elif ext == ".vdb":
        from .vdb import write_vdb
        write_vdb(path, grid)
    elif ext == ".npy":
        if not (np.array_equal(grid.bbox_min, DEFAULT_BBOX_MIN)
                and np.array_equal(grid.bbox_max, DEFAULT_BBOX_MAX)):
            raise VolumeError(
                f"{path}: a .npy file stores no bounding box, and this grid's box "
                f"{grid.bbox_min.tolist()}..{grid.bbox_max.tolist()} is not the default "
                f"[-0.5, 0.5]^3; write .npz or .vol instead")
        with open(path, "wb") as f:   # a file object stops np.save from renaming the file
            np.save(f, grid.density, allow_pickle=False)
    else:
        with open(path, "wb") as f:
            np.savez_compressed(f, density=grid.density, bbox_min=grid.bbox_min,
                                bbox_max=grid.bbox_max)


# --------------------------------------------------------------------------- .vol

def _read_vol(path: Path) -> DensityGrid:
    with open(path, "rb") as f:
        file_size = os.fstat(f.fileno()).st_size
        header = f.read(VOL_HEADER_SIZE)
        if len(header) >= 3 and header[:3] != VOL_MAGIC:
            raise VolumeError(
                f"{path}: not a Mitsuba .vol file: magic bytes are {header[:3]!r}, expected b'VOL'")
        if len(header) < VOL_HEADER_SIZE:
            raise VolumeError(
                f"{path}: truncated .vol header: file has {file_size} bytes, the header alone "
                f"needs {VOL_HEADER_SIZE}")
        _, version, encoding, nx, ny, nz, channels, *bbox = _VOL_HEADER.unpack(header)
        if version != VOL_VERSION:
            raise VolumeError(f"{path}: unsupported .vol version {version}; only version 3 is read")
        if encoding != VOL_ENCODING_FLOAT32:
            name = _VOL_ENCODING_NAMES.get(encoding, "unknown")
            raise VolumeError(
                f"{path}: unsupported .vol encoding {encoding} ({name}); only 1 (float32) is read")
        if nx <= 0 or ny <= 0 or nz <= 0:
            raise VolumeError(
                f"{path}: .vol resolution xres, yres, zres = {nx}, {ny}, {nz}: a grid needs at "
                f"least one voxel on every axis")
        if channels != 1:
            raise VolumeError(
                f"{path}: .vol has {channels} channels; a density grid needs exactly 1")
        n = nx * ny * nz  # Python ints: no overflow even for absurd headers
        expected = VOL_HEADER_SIZE + 4 * n
        if file_size != expected:
            what = "truncated" if file_size < expected else "over-long"
            raise VolumeError(
                f"{path}: {what} .vol file: header says {nx}x{ny}x{nz} float32 voxels "
                f"({4 * n} data bytes, {expected} bytes in all), file has {file_size} bytes")
        data = np.fromfile(f, dtype="<f4", count=n)
    bbox_min, bbox_max = check_bbox(bbox[:3], bbox[3:], f"{path}: .vol header")
    density = density_to_float32(data.reshape(nz, ny, nx), str(path))
    return DensityGrid(density, bbox_min, bbox_max)


def _write_vol(path: Path, grid: DensityGrid) -> None:
    nx, ny, nz = grid.resolution
    bbox = np.concatenate([grid.bbox_min, grid.bbox_max])
    f32_max = float(np.finfo(np.float32).max)
    if np.abs(bbox).max() > f32_max:
        raise VolumeError(f"{path}: bounding box {bbox.tolist()} does not fit in float32 (.vol)")
    bbox32 = bbox.astype(np.float32)
    if not (bbox32[:3] < bbox32[3:]).all():
        raise VolumeError(
            f"{path}: bounding box {bbox.tolist()} collapses to min >= max when rounded to "
            f"float32 for .vol; use .npz")
    header = _VOL_HEADER.pack(VOL_MAGIC, VOL_VERSION, VOL_ENCODING_FLOAT32, nx, ny, nz, 1,
                              *(float(v) for v in bbox32))
    with open(path, "wb") as f:
        f.write(header)
        f.write(grid.density.astype("<f4", copy=False).tobytes(order="C"))


# --------------------------------------------------------------------------- .npy / .npz

def _unreadable(path, kind: str, e: Exception) -> VolumeError:
    """The one-line error for a file NumPy could not read as ``kind`` (.npy, .npz)."""
    return VolumeError(f"{path}: cannot read as {kind}: {type(e).__name__}: "
                       f"{str(e).splitlines()[0] if str(e) else ''}")


def _read_npy(path: Path) -> DensityGrid:
    try:
        arr = np.load(path, allow_pickle=False)
    except MemoryError:
        raise
    except Exception as e:
        # numpy parses the header as a Python literal: a corrupt one raises SyntaxError or
        # tokenize errors besides ValueError (found by tests/test_fuzz.py)
        raise _unreadable(path, ".npy", e) from None
    return DensityGrid(density_to_float32(arr, str(path)), np.array(DEFAULT_BBOX_MIN),
                np.array(DEFAULT_BBOX_MAX))


def _read_npz(path: Path) -> DensityGrid:
    try:
        npz = np.load(path, allow_pickle=False)
    except MemoryError:
        raise
    except Exception as e:            # see below: a corrupt archive raises many types
        raise _unreadable(path, ".npz", e) from None
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise VolumeError(f"{path}: not a .npz archive (it holds a bare .npy array); rename it .npy")
    try:
        with npz:
            keys = set(npz.files)
            unknown = sorted(keys - set(_NPZ_KEYS))
            if "density" not in keys and unknown:
                raise VolumeError(
                    f"{path}: .npz has no 'density' array; unknown key(s) {unknown}; allowed: "
                    f"{', '.join(_NPZ_KEYS)}, and further grids for [emission] beside a density")
            # Further grids beside the density (read by [emission], clvol/emission.py): 3-D
            # arrays, each with an optional box <name>_bbox_min / <name>_bbox_max.
            grids = {k for k in unknown if npz[k].ndim == 3}
            boxes = {f"{g}_{b}" for g in grids for b in ("bbox_min", "bbox_max")}
            unknown = sorted(set(unknown) - grids - boxes)
            if unknown:
                raise VolumeError(
                    f"{path}: unknown key(s) {unknown} in .npz; allowed: {', '.join(_NPZ_KEYS)}, "
                    f"further 3-D grids and their <name>_bbox_min / <name>_bbox_max")
            if "density" not in keys:
                raise VolumeError(f"{path}: .npz has no 'density' array (keys: {sorted(keys)})")
            has_bbox = ("bbox_min" in keys, "bbox_max" in keys)
            if has_bbox[0] != has_bbox[1]:
                present = "bbox_min" if has_bbox[0] else "bbox_max"
                raise VolumeError(
                    f"{path}: .npz has {present} but not the other; give both bbox_min and "
                    f"bbox_max or neither (default [-0.5, 0.5]^3)")
            density = npz["density"]
            if has_bbox[0]:
                bbox_min, bbox_max = npz["bbox_min"], npz["bbox_max"]
            else:
                bbox_min, bbox_max = DEFAULT_BBOX_MIN, DEFAULT_BBOX_MAX
    except (VolumeError, MemoryError):
        raise
    except Exception as e:
        # zipfile and zlib raise many types for a corrupt archive (zlib.error,
        # NotImplementedError, RuntimeError for "encrypted" members; tests/test_fuzz.py found
        # each): all of them mean "not a readable .npz"
        raise _unreadable(path, ".npz", e) from None
    lo, hi = check_bbox(bbox_min, bbox_max, str(path))
    return DensityGrid(density_to_float32(density, str(path)), lo, hi)


# --------------------------------------------------------------------------- every grid

def read_volume_grids(path: str | os.PathLike, grid: str | None = None,
                      max_resolution: int | None = None) -> tuple[DensityGrid, dict[str, DensityGrid]]:
    """The density (as ``read_volume``) and every further grid of the file, for
    ``clvol volume convert``, which keeps them all or refuses (docs/volumes.md).

    ``.npz``: each further 3-D array, on its own ``<name>_bbox_min/_max`` or else the
    density's box (then it must have the density's shape); ``.vdb``: every other grid, read
    as the density is (a scalar fog grid: one that cannot be is refused with its reason);
    ``.vol`` and ``.npy`` hold none. Further grids' values are checked and stored as the
    density's are (float, finite, >= 0, float32)."""
    path = Path(path)
    density = read_volume(path, grid=grid, max_resolution=max_resolution)
    ext = _extension(path)
    extras: dict[str, DensityGrid] = {}
    if ext == ".npz":
        with np.load(path, allow_pickle=False) as npz:
            keys = set(npz.files)
            for name in sorted(keys - set(_NPZ_KEYS)):
                a = npz[name]
                if a.ndim != 3:
                    continue            # a box of a grid (read_volume checked the keys)
                lo_k, hi_k = f"{name}_bbox_min", f"{name}_bbox_max"
                if (lo_k in keys) != (hi_k in keys):
                    raise VolumeError(f"{path}: grid {name!r}: give both {lo_k} and {hi_k} "
                                      f"or neither")
                if lo_k in keys:
                    lo, hi = npz[lo_k], npz[hi_k]
                elif a.shape != density.density.shape:
                    raise VolumeError(f"{path}: grid {name!r} of shape {a.shape} has no box of "
                                      f"its own and not the density's shape "
                                      f"{density.density.shape}")
                else:
                    lo, hi = density.bbox_min, density.bbox_max
                extras[name] = _as_grid(a, lo, hi, f"{path}: grid {name!r}")
    elif ext == ".vdb":
        from .vdb import VdbFile
        with VdbFile(path) as vf:
            chosen = vf.choose(grid)
            for g in vf.grids:
                if g is chosen:
                    continue
                if g.name in extras or g.name == "density":
                    raise VolumeError(f"{path}: a second grid named {g.name!r}; clvol volume "
                                      f"convert keeps every grid and names them uniquely")
                try:
                    extras[g.name] = vf.read(g, max_resolution)
                except VolumeError as e:
                    raise VolumeError(f"{e}; clvol volume convert keeps every grid of a file "
                                      f"or converts none (this one cannot be kept)") from None
    return density, extras


def _as_grid(a: np.ndarray, lo, hi, source: str) -> DensityGrid:
    """A further grid under the density's rules (float, finite, >= 0, float64 rounded to
    float32 only when it fits), so that every format clvol writes can hold it."""
    return DensityGrid(density_to_float32(a, source), *check_bbox(lo, hi, source))


def write_volume_grids(path: str | os.PathLike, density: DensityGrid, extras: dict[str, DensityGrid],
                       source: str = "the input") -> None:
    """Write the density and every further grid (``read_volume_grids``): ``.npz`` and
    ``.vdb`` hold them all (bit-equal on reading back); ``.vol`` and ``.npy`` hold one, so a
    file with further grids is refused there, naming them, rather than losing them."""
    path = Path(path)
    ext = _extension(path)
    if extras and ext in (".vol", ".npy"):
        names = ", ".join(repr(n) for n in extras)
        raise VolumeError(f"{path}: {source} has grid(s) {names} beside the density, and a "
                          f"{ext} file holds one grid; convert to .npz or .vdb to keep them")
    if not extras:
        write_volume(path, density)
        return
    density.validate(f"{path} (writing)")
    if ext == ".vdb":
        from .vdb import write_vdb
        write_vdb(path, density, extra=extras)
        return
    arrays = {"density": density.density, "bbox_min": density.bbox_min,
              "bbox_max": density.bbox_max}
    for name, g in extras.items():
        arrays[name] = g.density
        on_density = (g.density.shape == density.density.shape
                      and np.array_equal(g.bbox_min, density.bbox_min)
                      and np.array_equal(g.bbox_max, density.bbox_max))
        if not on_density:
            arrays[f"{name}_bbox_min"], arrays[f"{name}_bbox_max"] = g.bbox_min, g.bbox_max
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)
