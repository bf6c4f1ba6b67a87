"""Reading OpenVDB ``.vdb`` files with NumPy (docs/volumes.md, "OpenVDB").

Why our own reader: OpenVDB's Python binding is built for the system Python and its NumPy 1.x
(from our Python it imports, then crashes on the first array copy), and it can only copy a grid
to a full-resolution dense array. Reading the format ourselves needs only ``zlib`` and the
``blosc`` wheel, and lets ``max_resolution`` box-filter each 128^3 node as it is read. The tests
check it against files OpenVDB itself writes.

The parts of the format read here (file versions 222-225; OpenVDB 10 writes 224; little-endian;
``string`` = uint32 length + bytes)::

    header      int64 magic 0x56444220, uint32 file version, uint32 library major, minor,
                uint8 has-grid-offsets, 36-byte uuid text, file metadata, int32 grid count
    metadata    uint32 count, then per item: string name, string type, uint32 size, bytes
    descriptor  string unique name (name + "\\x1e" + n for repeats), string tree type
                ("Tree_float_5_4_3", "_HalfFloat" appended when stored as half),
                string instance parent, int64 grid, block and end offsets
    grid        uint32 compression flags (1 zip, 2 active mask, 4 blosc), grid metadata,
                transform (string map type + doubles), int32 buffer count (1), topology, buffers
    topology    root: background, uint32 tile and child counts, tiles (3 int32, value, bool),
                children (3 int32 origin + upper node); upper/lower internal node: child mask,
                value mask, compressed values (32^3 / 16^3 of them), then its children in
                mask order; leaf: its value mask (8^3 bits)
    buffers     per leaf, depth first (root children sorted by origin): value mask again,
                compressed values (8^3)

Compressed values (``io::readCompressedValues``): one metadata byte saying which inactive values
were left out (and how to restore them: background, -background, one or two stored values picked
by a stored selection mask), then the values (only the active ones when mask compression is on
and the byte is not 6), as raw bytes, or an int64 size and a zlib or blosc chunk (a size <= 0
means -size raw bytes). Half-float grids store these values as float16; the background, tiles
and restored inactive values stay full size. Masks are uint64 words, bit ``n`` of a node is
word ``n // 64`` bit ``n % 64``, and ``n = (x << 2L) | (y << L) | z`` for a node of side
``2**L`` (z fastest). A value at index ``ijk`` sits at world ``voxel_size * ijk + translation``.
"""
from __future__ import annotations

import math
import os
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import VolumeError
from .grid import DensityGrid
from .resample import BoxAccumulator, box_factor

VDB_MAGIC = 0x56444220
MIN_FILE_VERSION = 222      # per-grid compression flags and mask-compressed internal nodes
MAX_FILE_VERSION = 225      # the newest format (native half grids); the layout read is unchanged
COMPRESS_ZIP, COMPRESS_ACTIVE_MASK, COMPRESS_BLOSC = 0x1, 0x2, 0x4
_KNOWN_COMPRESSION = COMPRESS_ZIP | COMPRESS_ACTIVE_MASK | COMPRESS_BLOSC
HALF_SUFFIX = "_HalfFloat"
# The only tree layout OpenVDB writes for its standard grids: root -> 32^3 -> 16^3 -> 8^3.
LOG2_UPPER, LOG2_LOWER, LOG2_LEAF = 5, 4, 3
LEAF_DIM = 1 << LOG2_LEAF                                   # 8 voxels
LOWER_SPAN = LEAF_DIM << LOG2_LOWER                         # 128 voxels
UPPER_SPAN = LOWER_SPAN << LOG2_UPPER                       # 4096 voxels
_SLAB_LEAVES = 4            # leaf columns per block handed to the box filter (32 voxels)
# value type name -> (NumPy scalar type, components); scalars are what a density can be.
_VALUE_TYPES = {"float": ("<f4", 1), "double": ("<f8", 1), "half": ("<f2", 1),
                "vec3s": ("<f4", 3), "vec3d": ("<f8", 3), "vec3i": ("<i4", 3),
                "int32": ("<i4", 1), "int64": ("<i8", 1)}
SCALAR_TYPES = ("float", "double", "half")
# Grid metadata clvol writes (a JSON string: "shape" [nx, ny, nz], "bbox_min", "bbox_max"):
# the dense array and box the grid was written from, so that reading it back gives them
# again (clvol volume convert's round trips; docs/volumes.md). Other readers ignore it.
STORED_BOX_KEY = "clvol_dense_box"
_TREE_PREFIX = "Tree_"
_TREE_SUFFIX = "_5_4_3"


# --------------------------------------------------------------------------- byte reading

class _Stream:
    """Bounds-checked little-endian reads: a short read is a truncated file, named as such."""

    def __init__(self, f, path: Path):
        self.f = f
        self.path = path
        self.size = os.fstat(f.fileno()).st_size

    def tell(self) -> int:
        return self.f.tell()

    def seek(self, pos: int, what: str) -> None:
        if not 0 <= pos <= self.size:
            raise VolumeError(f"{self.path}: truncated .vdb file: {what} is at byte {pos}, "
                              f"past the end of the file ({self.size} bytes)")
        self.f.seek(pos)

    def read(self, n: int, what: str) -> bytes:
        if n < 0:
            raise VolumeError(f"{self.path}: corrupt .vdb file: {what} has size {n}")
        b = self.f.read(n)
        if len(b) != n:
            pos = self.f.tell() - len(b)
            raise VolumeError(f"{self.path}: truncated .vdb file: {what} needs {n} bytes at byte "
                              f"{pos}, the file has {self.size} bytes")
        return b

    def unpack(self, fmt: str, what: str):
        s = struct.Struct("<" + fmt)
        return s.unpack(self.read(s.size, what))

    def u32(self, what: str) -> int:
        return self.unpack("I", what)[0]

    def string(self, what: str) -> str:
        n = self.u32(what)
        if n > 1 << 20:   # names and type names are short; a huge length is a corrupt file
            raise VolumeError(f"{self.path}: corrupt .vdb file: {what} claims {n} bytes")
        return self.read(n, what).decode("utf-8", errors="replace")

    def array(self, dtype, count: int, what: str) -> np.ndarray:
        dt = np.dtype(dtype)
        return np.frombuffer(self.read(dt.itemsize * count, what), dtype=dt)


def _parse_stored_box(text: str | None) -> dict | None:
    """clvol's dense-box metadata, or None when absent or not well formed (then the grid is
    read as any other: the active box plus a border)."""
    if text is None:
        return None
    import json
    try:
        d = json.loads(text)
        shape = [int(v) for v in d["shape"]]
        lo = [float(v) for v in d["bbox_min"]]
        hi = [float(v) for v in d["bbox_max"]]
    except (ValueError, KeyError, TypeError):
        return None
    if not (len(shape) == len(lo) == len(hi) == 3 and min(shape) >= 1
            and all(math.isfinite(a) and math.isfinite(b) and a < b for a, b in zip(lo, hi))):
        return None
    return {"shape": shape, "bbox_min": lo, "bbox_max": hi}


def _skip_metadata(s: _Stream, what: str) -> dict:
    """Read a metadata map; keep the string and small numeric items (for ``class`` etc.)."""
    out = {}
    for _ in range(s.u32(f"{what} count")):
        name = s.string(f"{what} name")
        type_name = s.string(f"{what} type of {name!r}")
        size = s.u32(f"{what} size of {name!r}")
        data = s.read(size, f"{what} {name!r}")
        if type_name == "string":
            out[name] = data.decode("utf-8", errors="replace")
    return out


# --------------------------------------------------------------------------- data model

@dataclass
class _Lower:
    """An internal node of 16^3 slots, each a leaf (8^3 voxels) or a constant tile.

    Kept compact (masks as words, only the tiles that differ from the background), because a
    large cloud has one per 128^3 voxels and all of them are held while the leaves are read."""
    origin: np.ndarray          # int64 (3,) index of voxel [0, 0, 0], x, y, z
    child_words: np.ndarray     # uint64 (64,): slot holds a leaf
    active_words: np.ndarray    # uint64 (64,): value mask (active tiles)
    tile_slots: np.ndarray      # slots of tiles whose value is not the background (scalar grids)
    tile_values: np.ndarray     # their values
    n_leaves: int
    # Active voxels of its leaves: count and inclusive index box (None if none). The leaves'
    # masks are not kept: the buffers repeat each one in front of its values.
    leaf_active: int
    leaf_min: np.ndarray | None
    leaf_max: np.ndarray | None

    @property
    def child(self) -> np.ndarray:
        return _bits(self.child_words)

    @property
    def active(self) -> np.ndarray:
        return _bits(self.active_words)


@dataclass
class _Upper:
    """An internal node of 32^3 slots, each a lower node or a constant 128^3 tile."""
    origin: np.ndarray
    child: np.ndarray           # bool (32768,)
    active: np.ndarray
    values: np.ndarray
    lowers: list = field(default_factory=list)


@dataclass
class VdbGrid:
    """One grid of a .vdb file: its descriptor, transform and topology (no voxel values)."""
    name: str
    value_type: str             # "float", "double", "half", "vec3s", ... (the tree's type)
    half: bool                  # values stored as float16 ("save float as half")
    grid_class: str             # "fog volume", "level set", "unknown", ...
    compression: int
    voxel_size: np.ndarray      # float64 (3,), x, y, z
    translation: np.ndarray     # float64 (3,): world position of index (0, 0, 0)
    transform_problem: str | None   # why this grid cannot become a clvol box, or None
    background: object
    root_tiles: list            # (origin (3,), value, active)
    uppers: list
    buffers_pos: int            # file offset of the leaf buffers
    active_voxels: int
    index_min: np.ndarray | None    # inclusive index box of the active voxels, or None if empty
    index_max: np.ndarray | None
    instance_of: str = ""       # the grid whose tree this one shares, if any
    stored_box: dict | None = None  # clvol's dense shape and box, when clvol wrote the grid

    @property
    def is_scalar(self) -> bool:
        return self.value_type in SCALAR_TYPES

    @property
    def type_label(self) -> str:
        return self.value_type + (" (stored as half)" if self.half else "")

    def world_box(self) -> tuple[np.ndarray, np.ndarray] | None:
        """World box of the active voxels' cells (faces half a voxel beyond the centres)."""
        if self.index_min is None:
            return None
        lo = (self.index_min - 0.5) * self.voxel_size + self.translation
        hi = (self.index_max + 0.5) * self.voxel_size + self.translation
        return lo, hi


# --------------------------------------------------------------------------- values

def _bits(mask_words: np.ndarray) -> np.ndarray:
    """uint64 mask words -> bool array of their bits, bit n = word n // 64, bit n % 64."""
    return np.unpackbits(np.ascontiguousarray(mask_words, dtype="<u8").view(np.uint8),
                         bitorder="little").view(bool)


class _Values:
    """Reads ``io::readCompressedValues`` blocks for one grid."""

    def __init__(self, s: _Stream, grid_name: str, value_type: str, half: bool,
                 compression: int, background):
        scalar, ncomp = _VALUE_TYPES[value_type]
        self.s = s
        self.name = grid_name
        self.full = np.dtype(scalar)                      # in-memory value (one component)
        self.stored = np.dtype("<f2") if (half and self.full.kind == "f") else self.full
        self.ncomp = ncomp
        self.half = half and self.full.kind == "f"
        self.compression = compression
        self.background = background
        if compression & COMPRESS_BLOSC:
            try:
                import blosc
            except ImportError:
                raise VolumeError(
                    f"{s.path}: grid {grid_name!r} is blosc-compressed and the 'blosc' package "
                    f"is not installed (pip install blosc; scripts/setup.sh does)") from None
            self._blosc = blosc

    def _chunk(self, nbytes: int, what: str) -> bytes:
        s, c = self.s, self.compression
        if not c & (COMPRESS_BLOSC | COMPRESS_ZIP):
            return s.read(nbytes, what)
        (size,) = s.unpack("q", f"{what} chunk size")
        if size <= 0:
            if -size != nbytes:
                raise VolumeError(f"{s.path}: corrupt .vdb file: {what} holds {-size} raw bytes, "
                                  f"expected {nbytes}")
            return s.read(-size, what)
        packed = s.read(size, what)
        try:
            raw = (self._blosc.decompress(packed) if c & COMPRESS_BLOSC
                   else zlib.decompress(packed))
        except Exception as e:   # blosc and zlib raise their own types for a damaged chunk
            kind = "blosc" if c & COMPRESS_BLOSC else "zlib"
            raise VolumeError(f"{s.path}: corrupt .vdb file: {what} is not a valid {kind} "
                              f"chunk ({e})") from None
        if len(raw) != nbytes:
            raise VolumeError(f"{s.path}: corrupt .vdb file: {what} decompresses to {len(raw)} "
                              f"bytes, expected {nbytes}")
        return raw

    def read_raw(self, count: int, mask: np.ndarray, what: str):
        """Read one block without expanding it: (meta, inactive0, inactive1, selection or None,
        stored values (n, ncomp) in the full dtype, whether only the active ones were stored)."""
        s, nc = self.s, self.ncomp
        (meta,) = s.unpack("b", f"{what} metadata byte")
        if not 0 <= meta <= 6:
            raise VolumeError(f"{s.path}: corrupt .vdb file: {what} has metadata byte {meta} "
                              f"(0..6 expected)")
        bg = self.background
        in1 = bg
        in0 = bg if meta == 0 else -bg
        if meta in (2, 4, 5):
            in0 = s.array(self.full, nc, f"{what} inactive value")
            in0 = in0[0] if nc == 1 else in0
            if meta == 5:
                in1 = s.array(self.full, nc, f"{what} inactive value")
                in1 = in1[0] if nc == 1 else in1
        sel = None
        if meta in (3, 4, 5):
            sel = _bits(s.array("<u8", count // 64, f"{what} selection mask"))
        active_only = bool(self.compression & COMPRESS_ACTIVE_MASK) and meta != 6
        n = int(np.count_nonzero(mask)) if active_only else count
        if self.half and n == 0:     # OpenVDB writes nothing at all for an empty half block
            vals = np.zeros((0, nc), self.full)
        else:
            raw = self._chunk(n * nc * self.stored.itemsize, f"{what} values")
            vals = np.frombuffer(raw, dtype=self.stored).reshape(n, nc)   # read-only view
            if self.stored != self.full:
                vals = vals.astype(self.full)
        return in0, in1, sel, vals, active_only

    def read(self, count: int, mask: np.ndarray, what: str) -> np.ndarray:
        """Read and expand one block of ``count`` values (shape (count,) or (count, ncomp))."""
        in0, in1, sel, vals, active_only = self.read_raw(count, mask, what)
        out = np.empty((count, self.ncomp), self.full)
        out[:] = in0
        if sel is not None:
            out[sel] = in1
        if active_only:
            out[mask] = vals
        else:
            out[:] = vals
        return out[:, 0] if self.ncomp == 1 else out


# --------------------------------------------------------------------------- file structure

def _parse_tree_type(path: Path, unique_name: str, tree_type: str) -> tuple[str, bool]:
    half = tree_type.endswith(HALF_SUFFIX)
    t = tree_type[:-len(HALF_SUFFIX)] if half else tree_type
    if t.startswith(_TREE_PREFIX) and t.endswith(_TREE_SUFFIX):
        value = t[len(_TREE_PREFIX):-len(_TREE_SUFFIX)]
        if value in _VALUE_TYPES:
            return value, half
    return t, half   # an unknown type: listed by name, never read


def _read_transform(s: _Stream, what: str):
    """(voxel_size (3,), translation (3,), problem or None) from a serialised map."""
    kind = s.string(f"{what} map type")
    vec = lambda label: np.array(s.unpack("3d", f"{what} {label}"))  # noqa: E731
    if kind in ("UniformScaleMap", "ScaleMap"):
        scale = vec("scale")
        s.read(4 * 24, f"{what} cached inverses")
        trans = np.zeros(3)
    elif kind in ("UniformScaleTranslateMap", "ScaleTranslateMap"):
        trans = vec("translation")
        scale = vec("scale")
        s.read(4 * 24, f"{what} cached inverses")
    elif kind == "TranslationMap":
        trans, scale = vec("translation"), np.ones(3)
    elif kind in ("AffineMap", "UnitaryMap"):
        m = np.array(s.unpack("16d", f"{what} matrix")).reshape(4, 4)
        # Row vectors: world = [i j k 1] @ m, so the translation is the last row.
        scale, trans = np.diag(m)[:3].copy(), m[3, :3].copy()
        off = m[:3, :3] - np.diag(scale)
        if np.abs(off).max() > 1e-9 * np.abs(scale).max():
            return scale, trans, (f"{kind} rotates or shears the grid; clvol's box is "
                                  f"axis-aligned")
    elif kind == "NonlinearFrustumMap":
        # bbox (6 doubles), taper, depth, then the frustum's own linear map: read to skip it.
        s.read(8 * 8, f"{what} frustum")
        _read_transform(s, what)
        return np.ones(3), np.zeros(3), f"{kind} is not a linear transform"
    else:   # no other map types exist; their size is unknown, so the grid cannot be read on
        raise VolumeError(f"{s.path}: {what} has unknown map type {kind!r}")
    if not (np.isfinite(scale).all() and np.isfinite(trans).all()) or (scale <= 0).any():
        return scale, trans, f"voxel size {scale.tolist()} must be finite and > 0"
    # Stored voxel sizes of a uniform map are equal; 1e-6 allows a float32 round trip.
    if np.abs(scale - scale.mean()).max() > 1e-6 * scale.mean():
        return scale, trans, (f"voxel size {scale.tolist()} is not uniform; clvol needs cubic "
                              f"voxels")
    return scale, trans, None


def _read_topology(s: _Stream, g: dict, vals: _Values | None, path: Path):
    """Root, internal nodes and leaf masks. Tile values are kept for scalar grids only."""
    what = f"grid {g['name']!r}"
    keep = vals is not None and vals.ncomp == 1
    (buffer_count,) = s.unpack("i", f"{what} buffer count")
    if buffer_count != 1:
        raise VolumeError(f"{path}: grid {g['name']!r} has {buffer_count} buffers per leaf; "
                          f"only 1 is read")
    dt = np.dtype(_VALUE_TYPES[g["value_type"]][0])
    nc = _VALUE_TYPES[g["value_type"]][1]
    bg = s.array(dt, nc, f"{what} background")
    background = bg[0] if nc == 1 else bg
    vals.background = background
    n_tiles, n_children = s.unpack("II", f"{what} root tile and child counts")
    tiles = []
    for _ in range(n_tiles):
        origin = np.array(s.unpack("3i", f"{what} root tile origin"), np.int64)
        v = s.array(dt, nc, f"{what} root tile value")
        (active,) = s.unpack("?", f"{what} root tile flag")
        tiles.append((origin, v[0] if nc == 1 else v, active))
    uppers = []
    for _ in range(n_children):
        origin = np.array(s.unpack("3i", f"{what} root child origin"), np.int64)
        uppers.append(_read_internal(s, vals, origin, LOG2_UPPER, what, keep))
    return background, tiles, uppers


def _read_internal(s: _Stream, vals: _Values, origin, log2: int, what: str, keep: bool):
    n = 1 << (3 * log2)
    child_words = s.array("<u8", n // 64, f"{what} child mask")
    active_words = s.array("<u8", n // 64, f"{what} value mask")
    child, active = _bits(child_words), _bits(active_words)
    values = vals.read(n, active, f"{what} node values")
    values = values if keep else None
    idx = np.flatnonzero(child)
    local = np.stack([idx >> (2 * log2), (idx >> log2) & ((1 << log2) - 1),
                      idx & ((1 << log2) - 1)], axis=1)
    if log2 == LOG2_UPPER:
        node = _Upper(origin, child, active, values)
        for off in local:
            node.lowers.append(_read_internal(s, vals, origin + off * LOWER_SPAN, LOG2_LOWER,
                                              what, keep))
        return node
    masks = s.array("<u8", 8 * len(idx), f"{what} leaf masks").reshape(len(idx), 8)
    count, lo, hi = _leaf_extent(masks, _slot_origins(origin, idx, LOG2_LOWER, LEAF_DIM))
    if keep:
        tiles = np.flatnonzero(~child & (values != vals.background))
        tile_values = values[tiles]
    else:
        tiles, tile_values = np.zeros(0, np.int64), np.zeros(0)
    return _Lower(origin, child_words, active_words, tiles, tile_values, len(idx), count, lo, hi)


def _slot_origins(node_origin, idx: np.ndarray, log2: int, span: int) -> np.ndarray:
    local = np.stack([idx >> (2 * log2), (idx >> log2) & ((1 << log2) - 1),
                      idx & ((1 << log2) - 1)], axis=1)
    return node_origin + local * span


def _leaf_extent(masks: np.ndarray, origins: np.ndarray):
    """(active count, index min, index max) of leaves with value masks ``masks`` (k, 8) uint64
    at ``origins`` (k, 3); (0, None, None) when none is active."""
    if len(masks) == 0:
        return 0, None, None
    bits = _bits(masks).reshape(-1, 8, 8, 8)                     # [leaf][x][y][z]
    count = int(np.count_nonzero(bits))
    if count == 0:
        return 0, None, None
    lo, hi = np.zeros(3, np.int64), np.zeros(3, np.int64)
    for axis, other in ((0, (2, 3)), (1, (1, 3)), (2, (1, 2))):
        along = bits.any(axis=other)                               # (k, 8)
        has = along.any(axis=1)
        first = np.argmax(along, axis=1)
        last = 7 - np.argmax(along[:, ::-1], axis=1)
        lo[axis] = int((origins[has, axis] + first[has]).min())
        hi[axis] = int((origins[has, axis] + last[has]).max())
    return count, lo, hi


def _active_extent(tiles, uppers):
    """(active voxel count, index min (3,), index max (3,)) or (0, None, None)."""
    count = 0
    lo = np.full(3, np.iinfo(np.int64).max)
    hi = np.full(3, np.iinfo(np.int64).min)

    def grow(a, b):
        nonlocal lo, hi
        lo = np.minimum(lo, a)
        hi = np.maximum(hi, b)

    for origin, _, active in tiles:
        if active:
            count += UPPER_SPAN ** 3
            grow(origin, origin + UPPER_SPAN - 1)
    for up in uppers:
        t = np.flatnonzero(up.active & ~up.child)
        if len(t):
            count += len(t) * LOWER_SPAN ** 3
            o = _slot_origins(up.origin, t, LOG2_UPPER, LOWER_SPAN)
            grow(o.min(0), o.max(0) + LOWER_SPAN - 1)
        for low in up.lowers:
            t = np.flatnonzero(low.active & ~low.child)
            if len(t):
                count += len(t) * LEAF_DIM ** 3
                o = _slot_origins(low.origin, t, LOG2_LOWER, LEAF_DIM)
                grow(o.min(0), o.max(0) + LEAF_DIM - 1)
            if low.leaf_active:
                count += low.leaf_active
                grow(low.leaf_min, low.leaf_max)
    if count == 0:
        return 0, None, None
    return count, lo, hi


class VdbFile:
    """The grids of a .vdb file (descriptors, transforms, topology), read on construction."""

    def __init__(self, path):
        self.path = Path(path)
        self.grids: list[VdbGrid] = []
        try:
            self._f = open(self.path, "rb")
        except OSError as e:
            raise VolumeError(f"{self.path}: cannot open: {e.strerror or e}") from None
        try:
            self._read()
        except BaseException:
            self._f.close()
            raise

    def close(self) -> None:
        self._f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _read(self) -> None:
        s = self.s = _Stream(self._f, self.path)
        head = self._f.read(8)
        if len(head) < 8 or struct.unpack("<q", head)[0] != VDB_MAGIC:
            raise VolumeError(f"{self.path}: not an OpenVDB file: the first 8 bytes are "
                              f"{head!r}, expected the magic number 0x56444220 "
                              f"(b' BDV\\0\\0\\0\\0')")
        self.version, major, minor = s.unpack("III", "header version")
        self.library = (major, minor)
        if not MIN_FILE_VERSION <= self.version <= MAX_FILE_VERSION:
            raise VolumeError(
                f"{self.path}: OpenVDB file format version {self.version} (library "
                f"{major}.{minor}) "
                f"is not read; versions {MIN_FILE_VERSION}-{MAX_FILE_VERSION} are; re-save it "
                f"with a current OpenVDB")
        (has_offsets,) = s.unpack("?", "header flags")
        s.read(36, "header uuid")
        if not has_offsets:
            raise VolumeError(f"{self.path}: written as a stream without grid offsets; re-save "
                              f"it as a file with OpenVDB")
        _skip_metadata(s, "file metadata")
        (count,) = s.unpack("i", "grid count")
        if not 0 <= count <= 1 << 16:
            raise VolumeError(f"{self.path}: corrupt .vdb file: grid count {count}")
        descriptors = []
        for i in range(count):
            unique = s.string(f"grid {i} name")
            tree_type = s.string(f"grid {i} type")
            parent = s.string(f"grid {i} instance parent")
            grid_pos, block_pos, end_pos = s.unpack("qqq", f"grid {i} offsets")
            descriptors.append((unique, tree_type, parent, grid_pos, block_pos, end_pos))
            s.seek(end_pos, f"the end of grid {unique.split(chr(0x1e))[0]!r}")
        for unique, tree_type, parent, grid_pos, block_pos, end_pos in descriptors:
            self.grids.append(self._read_grid(unique, tree_type, parent, grid_pos, block_pos))

    def _read_grid(self, unique, tree_type, parent, grid_pos, block_pos) -> VdbGrid:
        s, path = self.s, self.path
        name = unique.split("\x1e")[0]
        value_type, half = _parse_tree_type(path, unique, tree_type)
        base = dict(name=name, value_type=value_type, half=half, grid_class="unknown",
                    compression=0, voxel_size=np.ones(3), translation=np.zeros(3),
                    transform_problem=None, background=None, root_tiles=[], uppers=[],
                    buffers_pos=-1, active_voxels=0, index_min=None, index_max=None)
        what = f"grid {name!r}"
        s.seek(grid_pos, what)
        (comp,) = s.unpack("I", f"{what} compression flags")
        if comp & ~_KNOWN_COMPRESSION:
            raise VolumeError(
                f"{path}: grid {name!r} uses unknown compression flags {comp:#x}; known: "
                f"0x1 zip, 0x2 active mask, 0x4 blosc")
        base["compression"] = comp
        meta = _skip_metadata(s, f"{what} metadata")
        base["grid_class"] = meta.get("class", "unknown")
        base["stored_box"] = _parse_stored_box(meta.get(STORED_BOX_KEY))
        (base["voxel_size"], base["translation"],
         base["transform_problem"]) = _read_transform(s, f"{what} transform")
        if parent:      # its tree is another grid's: listed, never read
            base["transform_problem"] = (f"an instance of grid {parent!r} (it shares that "
                                         f"grid's tree); instanced grids are not read")
            return VdbGrid(**base, instance_of=parent)
        if value_type not in _VALUE_TYPES:
            return VdbGrid(**base)      # listed by name and type, never read
        vals = _Values(s, name, value_type, half, comp, None)
        bg, tiles, uppers = _read_topology(s, base, vals, path)
        count, lo, hi = _active_extent(tiles, uppers)
        base.update(background=bg, root_tiles=tiles, uppers=uppers, buffers_pos=s.tell(),
                    active_voxels=count, index_min=lo, index_max=hi)
        if block_pos != base["buffers_pos"]:
            raise VolumeError(f"{path}: corrupt .vdb file: grid {name!r} topology ends at byte "
                              f"{base['buffers_pos']}, its descriptor says {block_pos}")
        return VdbGrid(**base)

    # ------------------------------------------------------------------ choosing a grid

    def choose(self, name: str | None = None) -> VdbGrid:
        """The grid named ``name``; by default ``density``, else the only scalar float grid."""
        listing = ", ".join(f"{g.name!r} ({g.type_label})" for g in self.grids) or "none"
        if name is not None:
            found = [g for g in self.grids if g.name == name]
            if not found:
                raise VolumeError(f"{self.path}: no grid named {name!r}; grids: {listing}")
            if len(found) > 1:
                raise VolumeError(f"{self.path}: {len(found)} grids are named {name!r}; clvol "
                                  f"cannot tell them apart")
            return found[0]
        found = [g for g in self.grids if g.name == "density"]
        if len(found) == 1:
            return found[0]
        scalar = [g for g in self.grids if g.is_scalar]
        if len(scalar) == 1 and not found:
            return scalar[0]
        raise VolumeError(f"{self.path}: cannot choose a density grid (no single grid named "
                          f"'density', and {len(scalar)} scalar float grids); set [volume] grid "
                          f"= \"name\"; grids: {listing}")

    # ------------------------------------------------------------------ dense grid

    def stored_layout(self, g: VdbGrid, max_resolution: int | None = None):
        """The dense shape (nx, ny, nz) clvol wrote ``g`` from (index 0 .. n - 1), when its
        metadata says so, every active voxel lies inside and no box filter is asked for;
        else None. Reading it back gives the array that was written (``write_vdb``)."""
        sb = g.stored_box
        if sb is None:
            return None
        n = np.asarray(sb["shape"], np.int64)
        if g.index_min is not None and (np.any(g.index_min < 0) or np.any(g.index_max >= n)):
            return None
        if box_factor(n, max_resolution, border=0) != 1:
            return None
        return n

    def dense_layout(self, g: VdbGrid, max_resolution: int | None = None):
        """(factor, base (3,), shape (mx, my, mz)) of the dense grid ``read`` builds: the
        stored layout of a grid clvol wrote (``stored_layout``), else the active index box plus
        one cell of background on every side, box-filtered by ``factor``."""
        stored = self.stored_layout(g, max_resolution)
        if stored is not None:
            return 1, np.zeros(3, np.int64), stored
        n = g.index_max - g.index_min + 1
        f = box_factor(n, max_resolution)
        shape = -(-n // f) + 2
        return f, g.index_min - f, shape

    def read(self, g: VdbGrid, max_resolution: int | None = None,
             max_bytes: int | None = None) -> DensityGrid:
        """The dense density grid of ``g`` (see docs/volumes.md for the box and the border)."""
        path = self.path
        stored = self.stored_layout(g, max_resolution)
        self._check_density_grid(g, allow_empty=stored is not None)
        f, base, shape = self.dense_layout(g, max_resolution)
        nbytes = 4 * int(np.prod(shape, dtype=np.int64))
        if max_bytes is not None and nbytes > max_bytes:
            raise VolumeError(self._too_big(g, shape, nbytes, max_bytes, max_resolution))
        if g.index_min is None:         # a stored grid of zeros (allowed above)
            return self._stored_grid(g, np.zeros(tuple(shape[::-1]), np.float32), shape)
        acc = BoxAccumulator(base, shape, f, keep_lo=g.index_min, keep_hi=g.index_max + 1)
        bg = float(g.background)
        for origin, value, _ in g.root_tiles:
            if value != bg:
                acc.add_constant(origin, origin + UPPER_SPAN, self._tile(g, value, origin))
        vals = _Values(self.s, g.name, g.value_type, g.half, g.compression, g.background)
        self.s.seek(g.buffers_pos, f"grid {g.name!r} buffers")
        # OpenVDB reads the root's children in sorted origin order (x, then y, then z).
        for up in sorted(g.uppers, key=lambda u: tuple(u.origin)):
            tiles = np.flatnonzero(~up.child & (up.values != bg))
            for o, v in zip(_slot_origins(up.origin, tiles, LOG2_UPPER, LOWER_SPAN),
                            up.values[tiles]):
                acc.add_constant(o, o + LOWER_SPAN, self._tile(g, v, o))
            for low in up.lowers:
                for block, origin in self._lower_blocks(g, vals, low, bg):
                    acc.add_block(block, origin)
        density = acc.density()
        if stored is not None:
            return self._stored_grid(g, density, shape)
        vs = g.voxel_size[0] * f
        lo = (base - 0.5) * g.voxel_size + g.translation
        hi = lo + np.asarray(shape) * vs
        return DensityGrid(density, lo, hi)

    def _stored_grid(self, g: VdbGrid, density: np.ndarray, shape) -> DensityGrid:
        """A grid clvol wrote, with the box it was written with: the float64 bounds are kept
        in the metadata because the transform's round trip (translation = min + h / 2, then
        back) can move them by an ulp. The transform still rules where the two disagree by
        more (the file was edited elsewhere)."""
        lo = -0.5 * g.voxel_size + g.translation
        hi = lo + np.asarray(shape) * g.voxel_size[0]
        slo = np.asarray(g.stored_box["bbox_min"], np.float64)
        shi = np.asarray(g.stored_box["bbox_max"], np.float64)
        tol = 1e-6 * float(g.voxel_size[0])
        if np.all(np.abs(slo - lo) <= tol) and np.all(np.abs(shi - hi) <= tol):
            lo, hi = slo, shi
        return DensityGrid(density, lo, hi)

    def _check_density_grid(self, g: VdbGrid, allow_empty: bool = False) -> None:
        path, name = self.path, g.name
        if g.value_type.startswith("vec3"):
            raise VolumeError(f"{path}: grid {name!r} is a vector grid ({g.type_label}); a "
                              f"density needs a scalar float grid")
        if not g.is_scalar:
            raise VolumeError(f"{path}: grid {name!r} has type {g.value_type}; a density needs "
                              f"a scalar float grid (float, double or half)")
        if g.grid_class == "level set":
            raise VolumeError(f"{path}: grid {name!r} is a level set (signed distances), not a "
                              f"density; convert it to a fog volume first")
        if g.transform_problem:
            raise VolumeError(f"{path}: grid {name!r}: {g.transform_problem}")
        if float(g.background) != 0.0:
            raise VolumeError(f"{path}: grid {name!r} has background value "
                              f"{float(g.background)!r}; a density grid needs background 0 "
                              f"(clvol's medium is empty outside its box)")
        if g.index_min is None and not allow_empty:
            raise VolumeError(f"{path}: grid {name!r} has no active voxels")

    def _tile(self, g: VdbGrid, value, origin) -> float:
        v = float(value)
        if not (math.isfinite(v) and v >= 0):
            raise VolumeError(f"{self.path}: grid {g.name!r}: tile at index "
                              f"{tuple(int(x) for x in origin)} has density {v!r}; densities "
                              f"must be finite and >= 0")
        return v

    def _lower_blocks(self, g: VdbGrid, vals: _Values, low: _Lower, bg: float):
        """Read the leaves of one lower node; yield dense blocks [x][y][z] and their origins,
        one per slab of ``_SLAB_LEAVES`` leaf columns along x (leaves arrive in x order), so
        only a slab, not the node's 128^3 block, is held at a time."""
        what = f"grid {g.name!r} leaf"
        ci = np.flatnonzero(low.child)
        slots = np.concatenate([ci, low.tile_slots])
        if len(slots) == 0:
            return
        # The blocks span the slots that hold a leaf or a non-background tile.
        loc = np.stack([slots >> 8, (slots >> 4) & 15, slots & 15], axis=1)
        l0, l1 = loc.min(0), loc.max(0) + 1
        # float32 for float and half grids (exact), float64 for double ones.
        dtype = np.float64 if vals.full.itemsize == 8 else np.float32
        t = low.tile_slots
        tx, ty, tz = t >> 8, ((t >> 4) & 15) - l0[1], (t & 15) - l0[2]
        cx, cy, cz = ci >> 8, ((ci >> 4) & 15) - l0[1], (ci & 15) - l0[2]
        row = np.empty(512, dtype)
        s = self.s
        i = 0
        for x0 in range(int(l0[0]), int(l1[0]), _SLAB_LEAVES):
            x1 = min(x0 + _SLAB_LEAVES, int(l1[0]))
            nl = (x1 - x0, *(l1[1:] - l0[1:]))
            block = np.full((nl[0], 8, nl[1], 8, nl[2], 8), bg, dtype)
            sel_t = (tx >= x0) & (tx < x1)
            block[tx[sel_t] - x0, :, ty[sel_t], :, tz[sel_t], :] = \
                low.tile_values[sel_t][:, None, None, None]
            while i < len(ci) and cx[i] < x1:
                mask = _bits(s.array("<u8", 8, f"{what} value mask"))
                in0, in1, sel, v, active_only = vals.read_raw(512, mask, what)
                row[:] = in0
                if sel is not None:
                    row[sel] = in1
                if active_only:
                    row[mask] = v[:, 0]
                else:
                    row[:] = v[:, 0]
                block[cx[i] - x0, :, cy[i], :, cz[i], :] = row.reshape(8, 8, 8)
                i += 1
            block = block.reshape(nl[0] * 8, nl[1] * 8, nl[2] * 8)
            origin = low.origin + np.array([x0, l0[1], l0[2]]) * LEAF_DIM
            if not (np.isfinite(block).all() and block.min() >= 0):
                bad = ~(np.isfinite(block) & (block >= 0))
                j = np.argwhere(bad)[0]
                raise VolumeError(
                    f"{self.path}: grid {g.name!r}: {int(bad.sum())} voxel(s) of the node at "
                    f"{tuple(int(x) for x in low.origin)} are NaN, infinite or negative; first "
                    f"at index {tuple(int(x) for x in origin + j)} = {float(block[tuple(j)])!r}")
            yield block, origin

    def _too_big(self, g, shape, nbytes, max_bytes, max_resolution) -> str:
        # The largest max_resolution whose grid fits: try factors until the buffer fits.
        n = g.index_max - g.index_min + 1
        f = 1
        while True:
            m = -(-n // f) + 2
            if 4 * int(np.prod(m)) <= max_bytes:
                break
            f += 1
        nx, ny, nz = (int(v) for v in shape)
        have = f"max_resolution = {max_resolution}" if max_resolution else "full resolution"
        return (f"{self.path}: grid {g.name!r} at {have} is a {nx}x{ny}x{nz} dense grid "
                f"({nbytes / 2**30:.2f} GiB), more than the {max_bytes / 2**30:.2f} GiB the "
                f"OpenCL device allows in one buffer; set [volume] max_resolution = "
                f"{int(m.max())} (or lower) to box-filter it while reading")


def read_vdb(path, grid: str | None = None, max_resolution: int | None = None,
             max_bytes: int | None = None) -> DensityGrid:
    """Read one scalar grid of a .vdb file as a dense ``DensityGrid`` (docs/volumes.md, "OpenVDB").

    grid: its name (default: ``density``, else the only scalar float grid).
    max_resolution: box-filter by an integer factor while reading so that no axis exceeds it.
    max_bytes: refuse (with the ``max_resolution`` that would fit) a larger dense array.
    """
    with VdbFile(path) as vf:
        return vf.read(vf.choose(grid), max_resolution, max_bytes)


# --------------------------------------------------------------------------- writing

# The layout written below is OpenVDB 10's (file version 224); the library version fields say
# which OpenVDB's reader rules apply to the file, so they name that release too.
_WRITE_VERSION, _WRITE_LIBRARY = 224, (10, 0)


def _mask_bytes(bits: np.ndarray) -> bytes:
    return np.packbits(bits.astype(bool), bitorder="little").tobytes()


def _zip_chunk(raw: bytes) -> bytes:
    """An int64 size and a zlib chunk, or a negative size and the raw bytes when zlib does not
    make them smaller (as OpenVDB's ``zipToStream``)."""
    packed = zlib.compress(raw, 6)
    if len(packed) < len(raw):
        return struct.pack("<q", len(packed)) + packed
    return struct.pack("<q", -len(raw)) + raw


def _string(s: str) -> bytes:
    b = s.encode("utf-8")
    return struct.pack("<I", len(b)) + b


def write_vdb(path, grid: DensityGrid, name: str = "density",
              extra: dict[str, DensityGrid] | None = None) -> None:
    """Write ``grid`` as a .vdb file (float, zip + active-mask compression), as the grid
    ``name``, then each grid of ``extra`` under its key (``[emission]`` grids beside a density).

    Voxels with a value > 0 are active, the background is 0; voxel ``[z][y][x]`` gets index
    ``(x, y, z)`` and the transform puts its centre where clvol has it. The voxels must be cubic
    (OpenVDB transforms with different sizes per axis are what clvol refuses to read). Each
    grid's metadata keeps its dense shape and float64 box (``STORED_BOX_KEY``), so clvol reads
    back the very array and box it wrote.
    """
    import uuid
    path = Path(path)
    grids = [(name, grid)] + list((extra or {}).items())
    names = [n for n, _ in grids]
    if len(set(names)) != len(names):
        raise VolumeError(f"{path}: two grids named {sorted(n for n in names if names.count(n) > 1)[0]!r}")
    for n, g in grids:
        cell = g.cell_size
        if np.abs(cell - cell.mean()).max() > 1e-9 * cell.mean():
            raise VolumeError(f"{path}: .vdb needs cubic voxels; grid {n!r} has voxel size "
                              f"{cell.tolist()} (x, y, z); resample it or change its box")
    header = (struct.pack("<qIII", VDB_MAGIC, _WRITE_VERSION, *_WRITE_LIBRARY) + b"\x01"
              + str(uuid.uuid4()).encode() + struct.pack("<I", 0)
              + struct.pack("<i", len(grids)))
    parts, pos = [header], len(header)
    for n, g in grids:
        body_head, buffers = _grid_body(g, n)
        desc = _string(n) + _string("Tree_float_5_4_3") + _string("")
        grid_pos = pos + len(desc) + 24
        block_pos = grid_pos + len(body_head)
        end_pos = block_pos + len(buffers)
        parts += [desc + struct.pack("<3q", grid_pos, block_pos, end_pos), body_head, buffers]
        pos = end_pos
    from ..atomic import atomic_open
    with atomic_open(path) as f:
        for part in parts:
            f.write(part)


def _grid_body(grid: DensityGrid, name: str) -> tuple[bytes, bytes]:
    """(compression, metadata, transform and topology; leaf buffers) of one float grid."""
    import json
    h = float(grid.cell_size.mean())
    t = grid.bbox_min + 0.5 * h                     # world position of index (0, 0, 0)
    nz, ny, nx = grid.density.shape
    pad = [(0, -n % LEAF_DIM) for n in (nz, ny, nx)]
    d = np.pad(grid.density, pad)
    bz, by, bx = (n // LEAF_DIM for n in d.shape)
    # leaves[bx, by, bz, x, y, z]: one row of 512 values per 8^3 block, in OpenVDB's leaf order.
    leaves = d.reshape(bz, 8, by, 8, bx, 8).transpose(4, 2, 0, 5, 3, 1).reshape(-1, 512)
    block = np.stack(np.meshgrid(np.arange(bx), np.arange(by), np.arange(bz), indexing="ij"),
                     axis=-1).reshape(-1, 3)
    keep = np.flatnonzero((leaves != 0).any(axis=1))
    leaves, block = leaves[keep], block[keep]
    # Tree position of each leaf: upper node, lower slot, leaf slot (both in x, y, z order).
    upper = block // (1 << (LOG2_UPPER + LOG2_LOWER))
    lower = (block >> LOG2_LOWER) & ((1 << LOG2_UPPER) - 1)
    slot = block & ((1 << LOG2_LOWER) - 1)
    order = np.lexsort((slot[:, 2], slot[:, 1], slot[:, 0], lower[:, 2], lower[:, 1],
                        lower[:, 0], upper[:, 2], upper[:, 1], upper[:, 0]))
    leaves, upper, lower, slot = leaves[order], upper[order], lower[order], slot[order]
    empty_values = b"\x00" + struct.pack("<q", 0)       # all tiles inactive background: none stored

    topo, bufs = [], []
    groups = {}
    for i, (u, lo_) in enumerate(zip(map(tuple, upper), map(tuple, lower))):
        groups.setdefault(u, {}).setdefault(lo_, []).append(i)
    topo.append(struct.pack("<f", 0.0) + struct.pack("<II", 0, len(groups)))
    for u, lows in groups.items():                       # dict order = sorted order here
        topo.append(struct.pack("<3i", *(int(c) * UPPER_SPAN for c in u)))
        child = np.zeros(1 << (3 * LOG2_UPPER), bool)
        for lo_ in lows:
            child[(lo_[0] << 10) | (lo_[1] << 5) | lo_[2]] = True
        topo += [_mask_bytes(child), _mask_bytes(np.zeros_like(child)), empty_values]
        for lo_, idx in lows.items():
            child = np.zeros(1 << (3 * LOG2_LOWER), bool)
            s = slot[idx]
            child[(s[:, 0] << 8) | (s[:, 1] << 4) | s[:, 2]] = True
            topo += [_mask_bytes(child), _mask_bytes(np.zeros_like(child)), empty_values]
            for i in idx:
                mask = leaves[i] != 0
                mb = _mask_bytes(mask)
                topo.append(mb)
                vals = leaves[i][mask].astype("<f4").tobytes()
                bufs.append(mb + b"\x00" + _zip_chunk(vals))
    # translation, scale, voxel size, then the cached 1/scale, 1/scale^2, 1/(2 scale)
    xform = (_string("UniformScaleTranslateMap") + struct.pack("<3d", *t)
             + struct.pack("<3d", h, h, h) * 2 + struct.pack("<3d", *([1 / h] * 3))
             + struct.pack("<3d", *([1 / (h * h)] * 3)) + struct.pack("<3d", *([0.5 / h] * 3)))
    # json writes floats with repr: the float64 bounds come back exactly
    box = json.dumps({"shape": [nx, ny, nz], "bbox_min": grid.bbox_min.tolist(),
                      "bbox_max": grid.bbox_max.tolist()})
    meta = (struct.pack("<I", 3) + _string("class") + _string("string") + _string("fog volume")
            + _string("name") + _string("string") + _string(name)
            + _string(STORED_BOX_KEY) + _string("string") + _string(box))
    body_head = (struct.pack("<I", COMPRESS_ZIP | COMPRESS_ACTIVE_MASK) + meta + xform
                 + struct.pack("<i", 1) + b"".join(topo))
    return body_head, b"".join(bufs)


def format_vdb_info(path) -> str:
    """What ``clvol volume info x.vdb`` prints: every grid with its type, active voxel count,
    index and world boxes of the active voxels, and voxel size (topology only, no values)."""
    def vec(v, fmt="{:.6g}"):
        return "(" + ", ".join(fmt.format(float(x)) for x in v) + ")"

    with VdbFile(path) as vf:
        lines = [f"{vf.path}: OpenVDB file version {vf.version} (library "
                 f"{vf.library[0]}.{vf.library[1]}), {len(vf.grids)} grid(s)"]
        for g in vf.grids:
            lines.append(f"  grid {g.name!r}: {g.type_label}, class {g.grid_class}")
            if g.value_type not in _VALUE_TYPES:
                lines.append("    (tree type not read by clvol)")
                continue
            if g.instance_of:
                lines.append(f"    shares the tree of grid {g.instance_of!r}")
            else:
                lines.append(f"    active voxels: {g.active_voxels}")
            if g.index_min is not None:
                lo, hi = g.world_box()
                if g.transform_problem:     # the world box below would be meaningless
                    lines.append(f"    index bbox: {vec(g.index_min, '{:.0f}')} .. "
                                 f"{vec(g.index_max, '{:.0f}')} (inclusive)")
                    lines.append(f"    not readable as a density: {g.transform_problem}")
                    continue
                lines.append(f"    index bbox: {vec(g.index_min, '{:.0f}')} .. "
                             f"{vec(g.index_max, '{:.0f}')} (inclusive)")
                lines.append(f"    world bbox: {vec(lo)} .. {vec(hi)} (active cells)")
                if g.is_scalar:
                    n = [int(v) for v in vf.dense_layout(g)[2]]
                    gib = 4 * n[0] * n[1] * n[2] / 2**30
                    how = ("as clvol wrote it" if vf.stored_layout(g) is not None
                           else "with its 1-voxel border")
                    lines.append(f"    clvol dense grid: {n[0]} x {n[1]} x {n[2]} voxels {how} "
                                 f"({gib:.3g} GiB float32 at full resolution)")
            lines.append(f"    voxel size: {vec(g.voxel_size)}, index (0, 0, 0) at world "
                         f"{vec(g.translation)}")
            if g.transform_problem:
                lines.append(f"    not readable as a density: {g.transform_problem}")
            elif g.is_scalar and not g.instance_of:
                # what a scene naming this grid would be refused for (a level set, a
                # background other than 0, no active voxel), said before anyone tries
                try:
                    vf._check_density_grid(g, allow_empty=vf.stored_layout(g) is not None)
                except VolumeError as e:
                    why = str(e).split(f"grid {g.name!r} ", 1)[-1]
                    lines.append(f"    cannot be rendered as a density: {why}")
    return "\n".join(lines)
