"""Host wrapper for cl/raymarch.cl (twin: reference/raymarch.py; same argument names).

Big inputs (``density``, ``majorant``, ``light``, ``ms_lattice``) may be NumPy arrays (copied
to the device on each call: tests) or ``DeviceArray`` handles of buffers already on the device
(the renderer keeps the volume and the light field resident between frames).
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from ..errors import ClvolError
from ..runtime import DeviceArray, get_runtime
from .constants import kernel_constant
from .grid import f4
from .blocks import block_defines, light_block, medium_block
from .phase import phase_defines

# The kernel's MS_SOURCE define per kind of F_ms lookup (the registry of source classes, a
# different table, is clvol/render/ms/__init__.py SOURCES: each source says which kind it
# marches as, in its ``plan_for``). The kinds are the kernel's words, named once here.
MS_KIND_NONE, MS_KIND_OCTAVES, MS_KIND_LATTICE, MS_KIND_VIEW = "none", "wrenninge", "lattice", "view"
MS_SOURCE_DEFINES = {MS_KIND_NONE: 0, MS_KIND_OCTAVES: 1, MS_KIND_LATTICE: 2, MS_KIND_VIEW: 3}
MS_TABLE_KINDS = (MS_KIND_LATTICE, MS_KIND_VIEW)   # the kinds that read a lattice or table
LIGHT_QUANTITIES = ("transmittance", "optical_depth")
# Wrenninge octaves: N, and the a, b, c multipliers (one value for all three; b <= a holds).
# clvol/render/ms/base.py Octaves and the CLI take them from here.
DEFAULT_OCTAVES = 3
DEFAULT_OCTAVE_MULTIPLIER = 0.5
DEFAULT_THRESHOLD = 1e-3   # early termination when T_cam falls below this
MAX_OCTAVES = kernel_constant("MS_MAX_OCTAVES")
MAX_VIEW_K = kernel_constant("VIEW_MAX_K")  # knots per block of the view-space table
TILE = kernel_constant("TILE")  # pixels per row of the tile one work-item marches
LOCAL_SIZE = 16  # tiles per work-group
LAYERS = (("total", 3), ("single", 3), ("multiple", 3), ("alpha", 1), ("depth", 1))


def tile_rows(lanes: int) -> int:
    """Rows of a tile: one pixel per lane (cl/raymarch.cl TILE_ROWS; LANES is the device's,
    ``Runtime.lanes``)."""
    return lanes // TILE


def _device(x, rt) -> DeviceArray:
    if isinstance(x, DeviceArray):
        return x
    return rt.upload(x)


def ms_defines(source: str, octaves: int = 1, channels: int = 1, view_k: int = 1,
               view_block: int | None = None) -> dict:
    """The -D defines of one multiple-scattering source of cl/raymarch.cl (see its header)."""
    if source not in MS_SOURCE_DEFINES:
        raise ClvolError(f"unknown multiple-scattering source {source!r}; one of "
                         f"{sorted(MS_SOURCE_DEFINES)}")
    if not 1 <= octaves <= MAX_OCTAVES:
        raise ClvolError(f"octaves must be 1..{MAX_OCTAVES}, got {octaves}")
    if channels not in (1, 3):
        raise ClvolError(f"F_ms lattice channels must be 1 or 3, got {channels}")
    d = {"MS_SOURCE": MS_SOURCE_DEFINES[source],
         "MS_OCTAVES": int(octaves) if source == MS_KIND_OCTAVES else 1,
         "MS_CHANNELS": int(channels) if source in MS_TABLE_KINDS else 1}
    if source == MS_KIND_VIEW:
        if not (1 <= view_k <= MAX_VIEW_K and view_block is not None and view_block >= 1):
            raise ClvolError(f"view table: {view_k} knots (1..{MAX_VIEW_K}), block {view_block}")
        d.update(VIEW_K=int(view_k), VIEW_BLOCK=int(view_block))
    return d


def input_defines(light_quantity: str, env_channels: int | None = None, bg_image: bool = False,
                  emission_channels: int | None = None, emission_box: bool = False) -> dict:
    """The -D defines of what the march reads besides its source (cl/raymarch.cl's header):
    LIGHT_TAU (the light field holds optical depth), ENV and ENV_CHANNELS (the sky's source
    field, 1 or 3 channels), BG_IMAGE (a per-pixel background), EMISSION, EMISSION_CHANNELS
    and EMISSION_BOX. Decided by the plan for a frame (clvol/render/plan.py ``programs``);
    ``raymarch`` (the tests' form) derives them from its arrays; ``launch`` checks that its
    inputs match them."""
    if light_quantity not in LIGHT_QUANTITIES:
        raise ClvolError(f"light_quantity {light_quantity!r}: one of {LIGHT_QUANTITIES}")
    d = {"LIGHT_TAU": int(light_quantity == "optical_depth")}
    if env_channels:
        d.update(ENV=1, ENV_CHANNELS=int(env_channels))
    if bg_image:
        d["BG_IMAGE"] = 1
    if emission_channels:
        d.update(EMISSION=1, EMISSION_CHANNELS=int(emission_channels),
                 EMISSION_BOX=int(bool(emission_box)))
    return d


def march_defines(lobes, lit: bool, skip_empty: bool, ms: dict) -> dict:
    """The -D defines that specialise cl/raymarch.cl (see its header) but its inputs'
    (``input_defines``): the phase, the slots of the blocks' declared properties, LIT,
    SKIP_EMPTY and the source's ``ms`` (``ms_defines``). The plan's (clvol/render/plan.py)
    and the tests' form below both come from here."""
    d = dict(phase_defines(lobes))
    d.update(block_defines())
    d.update(LIT=int(bool(lit)), SKIP_EMPTY=int(bool(skip_empty)))
    d.update(ms)
    return d


def raymarch_defines(lobes, lit: bool, source: str, octaves: int, channels: int,
                     skip_empty: bool, view_k: int = 1, view_block: int | None = None) -> dict:
    """``march_defines`` of one source kind, its ``ms_defines`` made here."""
    return march_defines(lobes, lit, skip_empty,
                         ms_defines(source, octaves, channels, view_k, view_block))


_SCALARS = ([None, np.int32, np.int32, np.int32, None, None, None]             # density, medium
            + [None, np.int32, np.int32, np.int32, np.int32]                     # majorant
            + [None, np.int32, None, np.float32]                                 # light field
            + [None, np.int32, np.int32, np.int32, None, None]                   # F_ms lattice
            + [None, None, None, None, np.float32, np.int32, np.int32]           # camera
            + [None] * 2                                                         # sun block, background
            + [np.float32] * 5                                                   # a, b, c, step, thr
            + [None] * 6)                                                        # outputs
_ENV_SCALARS = [None, np.int32, None, np.float32, None]       # env, en, min, size, colour (ENV)
_BG_SCALARS = [None]                                           # bg_image (BG_IMAGE)
# em, emx, emy, emz, em_min, em_max, em_colour, emission_out (EMISSION)
_EM_SCALARS = [None, np.int32, np.int32, np.int32, None, None, None, None]


ENV_PACK = 8     # floats per voxel of an RGB environment field on the device (6 used)


def env_device_layout(env) -> np.ndarray:
    """The kernel's layout of an environment field (2 C, n, n, n): one grey field (C = 1) as
    given; an RGB one (C = 3) as (n, n, n, ENV_PACK), a voxel's six values side by side and
    two zeros, so that the kernel fetches a voxel pair's six values with one 64-byte load
    instead of six lookups (cl/raymarch.cl, ``lookupL_env6``)."""
    env = np.asarray(env, np.float32)
    if env.ndim != 4 or env.shape[0] not in (2, 6) or len(set(env.shape[1:])) != 1:
        raise ClvolError(f"env must be (2 C, n, n, n) with C = 1 or 3, got {env.shape}")
    if env.shape[0] == 2:
        return np.ascontiguousarray(env)
    n = env.shape[1]
    packed = np.zeros((n, n, n, ENV_PACK), np.float32)
    packed[..., :6] = np.moveaxis(env, 0, -1)
    return packed


def raymarch(density, bbox_min, bbox_max, medium,
             majorant, block,
             light, cube_min, cube_size,
             ms_lattice, ms_bbox_min, ms_bbox_max,
             origin, forward, right, up, tan_half, width, height,
             sun, background,
             source="wrenninge", octaves=DEFAULT_OCTAVES, a=DEFAULT_OCTAVE_MULTIPLIER,
             b=DEFAULT_OCTAVE_MULTIPLIER, c=DEFAULT_OCTAVE_MULTIPLIER,
             step=None, threshold=DEFAULT_THRESHOLD, skip_empty=True, lit=True,
             light_quantity="transmittance", runtime=None, read_back=True, stats=False,
             view_block=None, env=None, env_min=(0, 0, 0), env_size=1.0,
             env_colour=(1, 1, 1), bg_image=None, emission=None, em_min=(0, 0, 0),
             em_max=(1, 1, 1), em_colour=(1, 1, 1), em_box=False):
    """Launch the ray marcher. Returns {layer: array} (float32; total/single/multiple
    (H, W, 3), alpha/depth (H, W)) and "stopped_at_bound" (int: the rays cl/raymarch.cl's
    progress bound stopped, 0 on any image that can be marched), or with ``read_back=False``
    (event, {layer: buffer}; "stats" word 0 holds the count).

    With ``stats`` the kernel also counts its work (cl/raymarch.cl, RAYMARCH_STATS) and the
    result gets "stats": uint32 (tiles, 4) (iterations, light lookups, majorant reads,
    active lane-segments per 4 x 4 tile).
    ``ms_lattice`` is (C, gz, gy, gx) with C = 1 or 3 (source "lattice"), or the view-space table
    (1 + C, by, bx, K) of blocks of ``view_block`` pixels (source "view"), else ignored (may
    be None). ``light`` may be None when ``lit`` is False. ``env`` (2 C, n, n, n), C = 1 or 3:
    the environment's source field over the cube env_min .. + env_size (builds with ENV);
    ``bg_image`` (H, W, 3): per-pixel background (builds with BG_IMAGE). ``emission``
    (C, ez, ey, ex), C = 1 or 3, over em_min .. em_max (its own box when ``em_box``), Le =
    em_colour * planes: builds with EMISSION and adds the "emission" layer. Argument meanings:
    see the twin (this function's keywords are the twin's; ``launch`` takes them grouped).
    """
    rt = runtime or get_runtime()
    if source == MS_KIND_LATTICE:
        ms = _device(ms_lattice, rt)
        if len(ms.shape) != 4 or ms.shape[0] not in (1, 3):
            raise ClvolError(f"ms_lattice must be (C, gz, gy, gx) with C = 1 or 3, got {ms.shape}")
        channels = ms.shape[0]
        view_k = 1
    elif source == MS_KIND_VIEW:
        ms = _device(ms_lattice, rt)
        if len(ms.shape) != 4 or ms.shape[0] not in (2, 4):
            raise ClvolError(f"view table must be (1 + C, by, bx, K) with C = 1 or 3, got {ms.shape}")
        channels, view_k = ms.shape[0] - 1, ms.shape[3]
        ms_bbox_min, ms_bbox_max = (0, 0, 0), (1, 1, 1)
    else:
        ms, channels, view_k = None, 1, 1
    lobes = () if medium.phase.is_isotropic else medium.phase.pairs
    defines = raymarch_defines(lobes, lit, source, octaves, channels, skip_empty, view_k,
                               view_block)
    defines.update(input_defines(
        light_quantity, env_channels=None if env is None else _env_shape(
            env if isinstance(env, DeviceArray) else env_device_layout(env))[0],
        bg_image=bg_image is not None,
        emission_channels=None if emission is None else _device(emission, rt).shape[0],
        emission_box=em_box))
    return launch(
        defines=defines,
        volume=MarchVolume(density, bbox_min, bbox_max, medium, majorant, block),
        camera=MarchCamera(origin, forward, right, up, tan_half, width, height),
        light=MarchLight(sun, background,
                         field=light if lit else None, cube_min=cube_min, cube_size=cube_size,
                         quantity=light_quantity),
        ms=MarchMs(ms, ms_bbox_min, ms_bbox_max, a, b, c),
        environment=MarchEnvironment(env, env_min, env_size, env_colour, bg_image),
        emission=None if emission is None else MarchEmission(emission, em_min, em_max,
                                                             em_colour, em_box),
        step=step, threshold=threshold, runtime=rt, read_back=read_back, stats=stats)


# ----------------------------------------------------------------------------- launch
# launch() takes the kernel's arguments in these groups (arrays may be NumPy arrays, copied to
# the device on each call, or DeviceArrays already there). The environment's and the
# emission's field names are ``raymarch``'s keywords, so a dict of those keywords splits into
# them with ``pick``.

@dataclass(frozen=True)
class MarchVolume:
    """The medium's density [nz][ny][nx] over bbox_min .. bbox_max, its optical properties
    ``medium`` (a clvol.scene.Medium, passed whole: sigma_t = density * medium.density_scale;
    packed by clvol/kernels/blocks.py medium_block) and its majorant grid of ``block``-voxel
    cells (clvol/kernels/majorant.py)."""
    density: object
    bbox_min: tuple
    bbox_max: tuple
    medium: object
    majorant: object
    block: int


@dataclass(frozen=True)
class MarchCamera:
    """A pinhole camera: origin, orthonormal basis, tan(fov_y / 2), image size in pixels."""
    origin: tuple
    forward: tuple
    right: tuple
    up: tuple
    tan_half: float
    width: int
    height: int


@dataclass(frozen=True)
class MarchLight:
    """The ``sun`` (a clvol.scene.Light, passed whole: its direction toward the light and RGB
    irradiance; packed by clvol/kernels/blocks.py light_block), the background radiance, and
    the light field: T_light (or its optical depth, by ``quantity``) over the cube cube_min ..
    + cube_size; None for an unlit build (LIT 0)."""
    sun: object
    background: tuple
    field: object = None
    cube_min: tuple = (0, 0, 0)
    cube_size: float = 1.0
    quantity: str = "transmittance"


@dataclass(frozen=True)
class MarchMs:
    """The multiple-scattering source's data: its device planes (a (C, gz, gy, gx) grid over
    bbox_min .. bbox_max, or the view table) or None, and the Wrenninge octaves' a, b, c."""
    planes: object = None
    bbox_min: tuple | None = None
    bbox_max: tuple | None = None
    a: float = DEFAULT_OCTAVE_MULTIPLIER
    b: float = DEFAULT_OCTAVE_MULTIPLIER
    c: float = DEFAULT_OCTAVE_MULTIPLIER


@dataclass(frozen=True)
class MarchEnvironment:
    """The sky's source field (ENV; ``env`` as ``raymarch`` takes it, or its device layout)
    over the cube env_min .. + env_size, coloured by env_colour, and the per-pixel background
    (BG_IMAGE); None for either leaves its code out of the program."""
    env: object = None
    env_min: tuple = (0, 0, 0)
    env_size: float = 1.0
    env_colour: tuple = (1, 1, 1)
    bg_image: object = None

    @classmethod
    def pick(cls, keywords: dict) -> "MarchEnvironment":
        """The environment's part of a dict of ``raymarch`` keywords."""
        return cls(**{f.name: keywords[f.name] for f in fields(cls) if f.name in keywords})


@dataclass(frozen=True)
class MarchEmission:
    """Emission planes (C, ez, ey, ex), C = 1 or 3, over em_min .. em_max (their own box when
    ``em_box``, else the density's), Le = em_colour * planes (EMISSION)."""
    emission: object
    em_min: tuple = (0, 0, 0)
    em_max: tuple = (1, 1, 1)
    em_colour: tuple = (1, 1, 1)
    em_box: bool = False

    @classmethod
    def pick(cls, keywords: dict) -> "MarchEmission | None":
        """The emission's part of a dict of ``raymarch`` keywords (None without "emission")."""
        if keywords.get("emission") is None:
            return None
        return cls(**{f.name: keywords[f.name] for f in fields(cls) if f.name in keywords})


class MarchOutputs:
    """The march's device outputs, owned by the caller and reused frame after frame (as
    tiny-cuda-nn's kernels write into caller-owned outputs): a buffer per layer and the stats
    words, kept while the image size, the layers and the stats mode stay the same and made
    again when one changes. The count in stats word 0 is set to zero before every launch.

        outs = MarchOutputs()                      # e.g. one per RayMarcher
        launch(..., outputs=outs)                  # frame after frame: no new buffers
    """

    def __init__(self):
        self._key = None
        self.buffers: dict | None = None
        self.n_tiles = 0
        self.allocations = 0                       # times the buffers were made

    def take(self, camera: MarchCamera, layers, stats: bool, rt) -> tuple[dict, int]:
        """(buffers, tiles) for a launch of ``camera``'s image with ``layers``."""
        key = (camera.width, camera.height, tuple(layers), bool(stats), rt.lanes)
        if key != self._key:
            self.buffers = None                    # the old buffers go before the new come
            self.buffers, self.n_tiles = _outputs(camera, layers, stats, rt)
            self._key = key
            self.allocations += 1
            return self.buffers, self.n_tiles
        rt.zero(self.buffers["stats"])
        return self.buffers, self.n_tiles


def launch(*, defines: dict, volume: MarchVolume, camera: MarchCamera, light: MarchLight,
           ms: MarchMs, environment: MarchEnvironment = MarchEnvironment(),
           emission: MarchEmission | None = None, step: float, threshold: float,
           runtime=None, read_back: bool = True, stats: bool = False,
           outputs: MarchOutputs | None = None):
    """Launch cl/raymarch.cl built with ``defines``, complete: the plan's
    (FramePlan.programs["raymarch"]), or ``raymarch_defines`` with ``input_defines``. The
    inputs are checked against them (an environment, a background image, emission planes
    exactly where the defines say so); only ``stats`` adds one (RAYMARCH_STATS: counters for
    the benchmarks, no change to the image). ``step`` in world units. ``outputs``: the
    caller's MarchOutputs to write into (default: new buffers for this launch). Returns what
    ``raymarch`` returns."""
    rt = runtime or get_runtime()
    if step is None or not step > 0:
        raise ClvolError(f"step must be > 0 (world units), got {step}")
    if defines.get("LIT") and light.field is None:
        raise ClvolError("a lit march (LIT 1) needs the light field")
    dummy = _Dummy(rt)     # one 1-float buffer for whichever input is absent
    args = (_volume_args(volume, rt) + _light_field_args(light, rt, dummy)
            + _ms_args(ms, dummy) + _camera_args(camera) + _light_args(light, ms)
            + (np.float32(step), np.float32(threshold)))
    scalars = list(_SCALARS)
    extra, layers = (), LAYERS
    env_channels = em_channels = None
    if environment.env is not None:
        env_channels, more = _env_args(environment, rt)
        extra += more
        scalars += _ENV_SCALARS
    if environment.bg_image is not None:
        extra += _bg_args(environment, camera, rt)
        scalars += _BG_SCALARS
    if emission is not None:
        em_channels, more = _emission_args(emission, rt)
        extra += more
        scalars += _EM_SCALARS
        layers = LAYERS + (("emission", 3),)
    _check_input_defines(defines, input_defines(
        light.quantity, env_channels, environment.bg_image is not None, em_channels,
        emission is not None and emission.em_box))
    if stats:
        defines = dict(defines, RAYMARCH_STATS=1)
    k = rt.program("raymarch", defines).kernel("raymarch", scalars)
    outs, n_tiles = (outputs or MarchOutputs()).take(camera, layers, stats, rt)
    args += tuple(outs[name] for name, _ in LAYERS) + (outs["stats"],) + extra
    if emission is not None:
        args += (outs["emission"],)
    # An explicit local size: with a NULL one, PoCL 3.1 picked work-groups for 512 x 512
    # images (16384 tiles) that crashed it (segfault). 16 and 64 measured alike on PoCL;
    # Oclgrind 21.10 crashes with 64.
    evt = rt.launch(k, n_tiles, args, pad=LOCAL_SIZE, local_size=(LOCAL_SIZE,))
    if not read_back:
        return evt, outs
    return _read_layers(outs, layers, camera, n_tiles if stats else 0, evt, rt)


class _Dummy:
    """A 1-float device buffer made on first use (stands in for an absent input)."""

    def __init__(self, rt):
        self.rt, self._buffer = rt, None

    @property
    def buffer(self):
        if self._buffer is None:
            self._buffer = self.rt.empty(1)
        return self._buffer


def _volume_args(v: MarchVolume, rt) -> tuple:
    """The density, its box, the medium block and the majorant grid."""
    dens, maj = _device(v.density, rt), _device(v.majorant, rt)
    (nz, ny, nx), (mz, my, mx) = dens.shape, maj.shape
    return (dens.buffer, np.int32(nx), np.int32(ny), np.int32(nz), f4(v.bbox_min),
            f4(v.bbox_max), medium_block(v.medium),
            maj.buffer, np.int32(mx), np.int32(my), np.int32(mz), np.int32(v.block))


def _light_field_args(light: MarchLight, rt, dummy: _Dummy) -> tuple:
    if light.field is None:
        buffer, n = dummy.buffer, 1
    else:
        field = _device(light.field, rt)
        n = field.shape[0]
        if field.shape != (n, n, n):
            raise ClvolError(f"light must be a cube [n][n][n], got {field.shape}")
        buffer = field.buffer
    return buffer, np.int32(n), f4(light.cube_min), np.float32(light.cube_size)


def _ms_args(ms: MarchMs, dummy: _Dummy) -> tuple:
    if ms.planes is None:   # the kernel reads no planes: any box will do
        buffer, (gz, gy, gx), gmin, gmax = dummy.buffer, (1, 1, 1), (0, 0, 0), (1, 1, 1)
    else:
        buffer, (gz, gy, gx) = ms.planes.buffer, ms.planes.shape[1:]
        gmin, gmax = ms.bbox_min, ms.bbox_max
    return buffer, np.int32(gx), np.int32(gy), np.int32(gz), f4(gmin), f4(gmax)


def _camera_args(c: MarchCamera) -> tuple:
    return (f4(c.origin), f4(c.forward), f4(c.right), f4(c.up), np.float32(c.tan_half),
            np.int32(c.width), np.int32(c.height))


def _light_args(light: MarchLight, ms: MarchMs) -> tuple:
    return (light_block(light.sun), f4(light.background),
            np.float32(ms.a), np.float32(ms.b), np.float32(ms.c))


def _check_input_defines(defines: dict, inputs: dict) -> None:
    """The defines the inputs imply (``input_defines``) must be the given ones: a plan that
    says ENV without a sky field, or a sky field the plan did not foresee, is a bug."""
    keys = ("LIGHT_TAU", "ENV", "ENV_CHANNELS", "BG_IMAGE", "EMISSION", "EMISSION_CHANNELS",
            "EMISSION_BOX")
    given = {k: defines[k] for k in keys if defines.get(k) is not None}
    if given != inputs:
        raise ClvolError(f"raymarch: the defines {given} do not match the inputs {inputs}")


def _env_shape(env) -> tuple[int, int]:
    """(channels, n) of an environment field in its device layout (``env_device_layout``,
    or a DeviceArray of it): 1 for grey planes (2, n, n, n), 3 for the packed RGB layout
    (n, n, n, ENV_PACK)."""
    shape = tuple(env.shape)
    if len(shape) == 4 and shape[0] == 2 and len(set(shape[1:])) == 1:
        return 1, shape[1]
    if len(shape) == 4 and shape[3] == ENV_PACK and len(set(shape[:3])) == 1:
        return 3, shape[0]
    raise ClvolError(f"env must be (2 C, n, n, n) with C = 1 or 3 (or its device "
                     f"layout, env_device_layout), got {shape}")


def _env_args(e: MarchEnvironment, rt) -> tuple:
    """(ENV_CHANNELS, the ENV arguments)."""
    env = e.env if isinstance(e.env, DeviceArray) else env_device_layout(e.env)
    channels, n = _env_shape(env)
    env = _device(env, rt)
    return channels, (env.buffer, np.int32(n), f4(e.env_min), np.float32(e.env_size),
                      f4(e.env_colour))


def _bg_args(e: MarchEnvironment, camera: MarchCamera, rt) -> tuple:
    bg = _device(e.bg_image, rt)
    if tuple(bg.shape) != (camera.height, camera.width, 3):
        raise ClvolError(f"bg_image must be ({camera.height}, {camera.width}, 3), got {bg.shape}")
    return (bg.buffer,)


def _emission_args(e: MarchEmission, rt) -> tuple:
    """(EMISSION_CHANNELS, the EMISSION arguments but the output layer: launch appends it)."""
    em = _device(e.emission, rt)
    if len(em.shape) != 4 or em.shape[0] not in (1, 3):
        raise ClvolError(f"emission must be (C, ez, ey, ex) with C = 1 or 3, got {em.shape}")
    ez, ey, ex = em.shape[1:]
    return em.shape[0], (em.buffer, np.int32(ex), np.int32(ey), np.int32(ez), f4(e.em_min),
                         f4(e.em_max), f4(e.em_colour))


def _outputs(camera: MarchCamera, layers, stats: bool, rt) -> tuple[dict, int]:
    """The output buffers of every layer and the stats: word 0 the count of rays the
    progress bound stopped (zeroed on the device), then with ``stats`` 4 counts per tile;
    and the number of tiles (work-items)."""
    w, h = camera.width, camera.height
    outs = {name: rt.empty((h * w * ch,)) for name, ch in layers}
    n_tiles = -(-w // TILE) * -(-h // tile_rows(rt.lanes))
    outs["stats"] = rt.empty((1 + n_tiles * 4 if stats else 1,), np.uint32, zero=True)
    return outs, n_tiles


def _read_layers(outs: dict, layers, camera: MarchCamera, stat_tiles: int, evt, rt) -> dict:
    """The layers, ``stopped_at_bound`` (the rays cl/raymarch.cl's progress bound stopped:
    an int, read with the stats) and with ``stat_tiles`` the per-tile ``stats``."""
    result = {}
    for name, ch in layers:
        shape = (camera.height, camera.width, 3) if ch == 3 else (camera.height, camera.width)
        result[name] = rt.from_device(outs[name], shape, wait_for=[evt])
    words = rt.from_device(outs["stats"], (1 + stat_tiles * 4,), np.uint32, wait_for=[evt],
                           label="march bound count")
    result["stopped_at_bound"] = int(words[0])
    if stat_tiles:
        result["stats"] = words[1:].reshape(stat_tiles, 4)
    return result
