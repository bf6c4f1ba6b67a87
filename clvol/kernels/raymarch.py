"""Host wrapper for cl/raymarch.cl (twin: reference/raymarch.py; same argument names).

Big inputs (``density``, ``majorant``, ``light``, ``ms_grid``) may be NumPy arrays (copied
to the device on each call: tests) or ``DeviceArray`` handles of buffers already on the device
(the renderer keeps the volume and the light field resident between frames).
"""
from __future__ import annotations

import numpy as np

from ..errors import ClvolError
from ..runtime import DeviceArray, get_runtime
from .constants import kernel_constant
from .grid import f4
from .phase import lobe_vectors, phase_defines

# The kernel's MS_SOURCE define per source kind (the registry of source classes, a different
# table, is clvol/render/ms/__init__.py SOURCES).
MS_SOURCE_DEFINES = {"none": 0, "wrenninge": 1, "grid": 2, "view": 3}
LIGHT_QUANTITIES = ("transmittance", "optical_depth")
MAX_OCTAVES = kernel_constant("MS_MAX_OCTAVES")
MAX_VIEW_K = kernel_constant("VIEW_MAX_K")  # knots per block of the view-space table
TILE = kernel_constant("TILE")  # pixels per side of the tile one work-item marches (16 lanes)
LOCAL_SIZE = 16  # tiles per work-group
LAYERS = (("total", 3), ("single", 3), ("multiple", 3), ("alpha", 1), ("depth", 1))


def _device(x, rt) -> DeviceArray:
    if isinstance(x, DeviceArray):
        return x
    return rt.upload(x)


def ms_defines(source: str, octaves: int = 1, channels: int = 1, view_k: int = 1,
               view_block: int = 4) -> dict:
    """The -D defines of one multiple-scattering source of cl/raymarch.cl (see its header)."""
    if source not in MS_SOURCE_DEFINES:
        raise ClvolError(f"unknown multiple-scattering source {source!r}; one of "
                         f"{sorted(MS_SOURCE_DEFINES)}")
    if not 1 <= octaves <= MAX_OCTAVES:
        raise ClvolError(f"octaves must be 1..{MAX_OCTAVES}, got {octaves}")
    if channels not in (1, 3):
        raise ClvolError(f"ms grid channels must be 1 or 3, got {channels}")
    d = {"MS_SOURCE": MS_SOURCE_DEFINES[source],
         "MS_OCTAVES": int(octaves) if source == "wrenninge" else 1,
         "MS_CHANNELS": int(channels) if source in ("grid", "view") else 1}
    if source == "view":
        if not (1 <= view_k <= MAX_VIEW_K and view_block >= 1):
            raise ClvolError(f"view table: {view_k} knots (1..{MAX_VIEW_K}), block {view_block}")
        d.update(VIEW_K=int(view_k), VIEW_BLOCK=int(view_block))
    return d


def raymarch_defines(lobes, lit: bool, source: str, octaves: int, channels: int,
                     skip_empty: bool, view_k: int = 1, view_block: int = 4) -> dict:
    """The -D defines that specialise cl/raymarch.cl (see its header)."""
    d = dict(phase_defines(lobes))
    d.update(LIT=int(bool(lit)), SKIP_EMPTY=int(bool(skip_empty)))
    d.update(ms_defines(source, octaves, channels, view_k, view_block))
    return d


_SCALARS = ([None, np.int32, np.int32, np.int32, None, None, np.float32]       # density
            + [None, np.int32, np.int32, np.int32, np.int32]                     # majorant
            + [None, np.int32, None, np.float32]                                 # light field
            + [None, np.int32, np.int32, np.int32, None, None]                   # ms grid
            + [None, None, None, None, np.float32, np.int32, np.int32]           # camera
            + [None] * 6                                                         # light, medium
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
    instead of six lookups (cl/raymarch.cl, ``lookup16_env6``)."""
    env = np.asarray(env, np.float32)
    if env.ndim != 4 or env.shape[0] not in (2, 6) or len(set(env.shape[1:])) != 1:
        raise ClvolError(f"env must be (2 C, n, n, n) with C = 1 or 3, got {env.shape}")
    if env.shape[0] == 2:
        return np.ascontiguousarray(env)
    n = env.shape[1]
    packed = np.zeros((n, n, n, ENV_PACK), np.float32)
    packed[..., :6] = np.moveaxis(env, 0, -1)
    return packed


def raymarch(density, bbox_min, bbox_max, density_scale,
             majorant, block,
             light, cube_min, cube_size,
             ms_grid, ms_bbox_min, ms_bbox_max,
             origin, forward, right, up, tan_half, width, height,
             light_dir, irradiance, albedo, lobes, background,
             source="wrenninge", octaves=3, a=0.5, b=0.5, c=0.5,
             step=None, threshold=1e-3, skip_empty=True, lit=True,
             light_quantity="transmittance", runtime=None, read_back=True, stats=False,
             view_block=4, env=None, env_min=(0, 0, 0), env_size=1.0,
             env_colour=(1, 1, 1), bg_image=None, emission=None, em_min=(0, 0, 0),
             em_max=(1, 1, 1), em_colour=(1, 1, 1), em_box=False):
    """Launch the ray marcher. Returns {layer: array} (float32; total/single/multiple
    (H, W, 3), alpha/depth (H, W)), or with ``read_back=False`` (event, {layer: buffer}).

    With ``stats`` the kernel also counts its work (cl/raymarch.cl, RAYMARCH_STATS) and the
    result gets "stats": uint32 (tiles, 4) (iterations, light lookups, majorant reads,
    active lane-segments per 4 x 4 tile).
    ``ms_grid`` is (C, gz, gy, gx) with C = 1 or 3 (source "grid"), or the view-space table
    (1 + C, by, bx, K) of blocks of ``view_block`` pixels (source "view"), else ignored (may
    be None). ``light`` may be None when ``lit`` is False. ``env`` (2 C, n, n, n), C = 1 or 3:
    the environment's source field over the cube env_min .. + env_size (builds with ENV);
    ``bg_image`` (H, W, 3): per-pixel background (builds with BG_IMAGE). ``emission``
    (C, ez, ey, ex), C = 1 or 3, over em_min .. em_max (its own box when ``em_box``), Le =
    em_colour * planes: builds with EMISSION and adds the "emission" layer. Argument meanings:
    see the twin.
    """
    rt = runtime or get_runtime()
    if source == "grid":
        ms = _device(ms_grid, rt)
        if len(ms.shape) != 4 or ms.shape[0] not in (1, 3):
            raise ClvolError(f"ms_grid must be (C, gz, gy, gx) with C = 1 or 3, got {ms.shape}")
        channels = ms.shape[0]
        view_k = 1
    elif source == "view":
        ms = _device(ms_grid, rt)
        if len(ms.shape) != 4 or ms.shape[0] not in (2, 4):
            raise ClvolError(f"view table must be (1 + C, by, bx, K) with C = 1 or 3, got {ms.shape}")
        channels, view_k = ms.shape[0] - 1, ms.shape[3]
        ms_bbox_min, ms_bbox_max = (0, 0, 0), (1, 1, 1)
    else:
        ms, channels, view_k = None, 1, 1
    defines = raymarch_defines(lobes, lit, source, octaves, channels, skip_empty, view_k,
                               view_block)
    return launch(defines, density, bbox_min, bbox_max, density_scale, majorant, block,
                  light, cube_min, cube_size, ms, ms_bbox_min, ms_bbox_max,
                  origin, forward, right, up, tan_half, width, height,
                  light_dir, irradiance, albedo, lobes, background, a=a, b=b, c=c, step=step,
                  threshold=threshold, lit=lit, light_quantity=light_quantity, runtime=rt,
                  read_back=read_back, stats=stats, env=env, env_min=env_min,
                  env_size=env_size, env_colour=env_colour, bg_image=bg_image,
                  emission=emission, em_min=em_min, em_max=em_max, em_colour=em_colour,
                  em_box=em_box)


def launch(defines, density, bbox_min, bbox_max, density_scale, majorant, block,
           light, cube_min, cube_size, ms_grid, ms_bbox_min, ms_bbox_max,
           origin, forward, right, up, tan_half, width, height,
           light_dir, irradiance, albedo, lobes, background, *, a=0.5, b=0.5, c=0.5,
           step=None, threshold=1e-3, lit=True, light_quantity="transmittance", runtime=None,
           read_back=True, stats=False, env=None, env_min=(0, 0, 0), env_size=1.0,
           env_colour=(1, 1, 1), bg_image=None, emission=None, em_min=(0, 0, 0),
           em_max=(1, 1, 1), em_colour=(1, 1, 1), em_box=False):
    """Launch cl/raymarch.cl built with ``defines`` (``raymarch_defines``, or the phase, LIT,
    SKIP_EMPTY and a multiple-scattering source's own). ``ms_grid``: a (C, gz, gy, gx)
    DeviceArray or None. ``env`` / ``bg_image`` (see ``raymarch``) add the ENV / BG_IMAGE
    defines; without them the defines (and the program) are those of a scene without an
    environment. Returns what ``raymarch`` returns."""
    rt = runtime or get_runtime()
    if step is None or not step > 0:
        raise ClvolError(f"step must be > 0 (world units), got {step}")
    dens = _device(density, rt)
    maj = _device(majorant, rt)
    nz, ny, nx = dens.shape
    mz, my, mx = maj.shape
    dummy = None
    if lit:
        light = _device(light, rt)
        ln = light.shape[0]
        if light.shape != (ln, ln, ln):
            raise ClvolError(f"light must be a cube [n][n][n], got {light.shape}")
    else:
        dummy = dummy or rt.empty(1)
        light, ln = DeviceArray(dummy, (1, 1, 1)), 1
    if ms_grid is not None:
        ms = ms_grid
        gz, gy, gx = ms.shape[1:]
        gmin, gmax = ms_bbox_min, ms_bbox_max
    else:
        dummy = dummy or rt.empty(1)
        ms, (gz, gy, gx) = DeviceArray(dummy, (1, 1, 1, 1)), (1, 1, 1)
        gmin, gmax = (0, 0, 0), (1, 1, 1)
    defines = dict(defines)
    if stats:
        defines["RAYMARCH_STATS"] = 1
    if env is not None:
        if not isinstance(env, DeviceArray):
            env = env_device_layout(env)
        env = _device(env, rt)
        shape = tuple(env.shape)
        if len(shape) == 4 and shape[0] == 2 and len(set(shape[1:])) == 1:
            env_channels, en = 1, shape[1]
        elif len(shape) == 4 and shape[3] == ENV_PACK and len(set(shape[:3])) == 1:
            env_channels, en = 3, shape[0]
        else:
            raise ClvolError(f"env must be (2 C, n, n, n) with C = 1 or 3 (or its device "
                             f"layout, env_device_layout), got {shape}")
        defines.update(ENV=1, ENV_CHANNELS=env_channels)
    if bg_image is not None:
        bg_image = _device(bg_image, rt)
        if tuple(bg_image.shape) != (height, width, 3):
            raise ClvolError(f"bg_image must be ({height}, {width}, 3), got {bg_image.shape}")
        defines["BG_IMAGE"] = 1
    layers = LAYERS
    if emission is not None:
        emission = _device(emission, rt)
        if len(emission.shape) != 4 or emission.shape[0] not in (1, 3):
            raise ClvolError(f"emission must be (C, ez, ey, ex) with C = 1 or 3, got "
                             f"{emission.shape}")
        defines.update(EMISSION=1, EMISSION_CHANNELS=emission.shape[0],
                       EMISSION_BOX=int(bool(em_box)))
        layers = LAYERS + (("emission", 3),)
    if light_quantity not in LIGHT_QUANTITIES:
        raise ClvolError(f"light_quantity {light_quantity!r}: one of {LIGHT_QUANTITIES}")
    defines["LIGHT_TAU"] = int(light_quantity == "optical_depth")
    prog = rt.program("raymarch", defines)
    k = prog.kernel("raymarch", _SCALARS + (_ENV_SCALARS if env is not None else [])
                    + (_BG_SCALARS if bg_image is not None else [])
                    + (_EM_SCALARS if emission is not None else []))
    g, w = lobe_vectors(lobes)
    outs = {name: rt.empty((height * width * ch,)) for name, ch in layers}
    n_tiles = -(-width // TILE) * -(-height // TILE)
    outs["stats"] = rt.empty((n_tiles * 4 if stats else 1,), np.uint32)
    args = (dens.buffer, np.int32(nx), np.int32(ny), np.int32(nz), f4(bbox_min), f4(bbox_max),
            np.float32(density_scale),
            maj.buffer, np.int32(mx), np.int32(my), np.int32(mz), np.int32(block),
            light.buffer, np.int32(ln), f4(cube_min), np.float32(cube_size),
            ms.buffer, np.int32(gx), np.int32(gy), np.int32(gz), f4(gmin), f4(gmax),
            f4(origin), f4(forward), f4(right), f4(up), np.float32(tan_half),
            np.int32(width), np.int32(height),
            f4(light_dir), f4(irradiance), f4(albedo), g, w, f4(background),
            np.float32(a), np.float32(b), np.float32(c), np.float32(step),
            np.float32(threshold),
            outs["total"], outs["single"], outs["multiple"], outs["alpha"], outs["depth"],
            outs["stats"])
    if env is not None:
        args += (env.buffer, np.int32(en), f4(env_min), np.float32(env_size), f4(env_colour))
    if bg_image is not None:
        args += (bg_image.buffer,)
    if emission is not None:
        ez, ey, ex = emission.shape[1:]
        args += (emission.buffer, np.int32(ex), np.int32(ey), np.int32(ez), f4(em_min),
                 f4(em_max), f4(em_colour), outs["emission"])
    # An explicit local size: with a NULL one, PoCL 3.1 picked work-groups for 512 x 512
    # images (16384 tiles) that crashed it (segfault). 16 and 64 measured alike on PoCL;
    # Oclgrind 21.10 crashes with 64.
    evt = rt.launch(k, n_tiles, args, pad=LOCAL_SIZE, local_size=(LOCAL_SIZE,))
    if not read_back:
        return evt, outs
    result = {}
    for name, ch in layers:
        shape = (height, width, 3) if ch == 3 else (height, width)
        result[name] = rt.from_device(outs[name], shape, wait_for=[evt])
    if stats:
        result["stats"] = rt.from_device(outs["stats"], (n_tiles, 4), np.uint32)
    return result
