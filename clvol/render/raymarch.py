"""The ray-marching render method: exact single scattering plus a multiple-scattering source.

    clvol render examples/cloud.toml -o cloud.exr            # raymarch + network (the default)

``RayMarcher`` keeps a volume on the device for many frames (``DeviceMedium``: density and
majorant) and the exact light field toward the light (``set_light``: the light-change cost);
``march(camera, light, source)`` renders a camera with a multiple-scattering source from
clvol/render/ms/. ``Plan`` decides what the kernel simulates for a medium and a light,
and which shortcuts it takes (with reasons, for the header). The stateful ``Renderer``
(clvol/render/renderer.py) drives all of it; its ``render_raymarch`` is the one-call form.

``shortcuts=False`` forces the general kernel (all lobes evaluated, three colour planes, light
lookups even at albedo 0): the tests check that every shortcut gives the same image. The
method, its accuracy and its speed are described in docs/raymarch.md.
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import ClvolError
from ..kernels.majorant import DEFAULT_BLOCK
from ..kernels.medium import DeviceMedium
from ..kernels.pyramid import MAX_BASE_RESOLUTION
from ..kernels.raymarch import DEFAULT_THRESHOLD, LIGHT_QUANTITIES, MarchOutputs, launch
from ..features.layout import is_power_of_two
from ..runtime import get_runtime
from .ms.base import MsSource
from .plan import MAX_LIGHT_RESOLUTION, light_key, light_resolution_for, plan_frame
from .stages import Stage

# Segment length in voxels of the density grid. Half a voxel, because at one voxel the
# single scattering alone left RMSE x100 0.54-0.85 against the path tracer on dense scenes
# (every bench scene has 0.5-0.94 optical depths per voxel) and 0.19-0.33 at half a voxel
# with the 4x light field below (docs/raymarch.md, "Step and light field").
DEFAULT_STEP = 0.5
DEFAULT_SUPERSAMPLE = 1
MAX_SUPERSAMPLE = 8


def check_march_options(step, threshold, light_resolution, supersample, light_interp,
                        env=None):
    """Refuse bad ray-marcher options when the Renderer is made, not at its first frame (the
    environment options included: a scene without a sky never reads them, but a bad value is
    still a mistake worth one line now)."""
    def bad(name, value, allowed):
        return ClvolError(f"raymarch option {name} = {value!r}: {allowed}")
    if not (isinstance(step, (int, float)) and math.isfinite(step) and 0.01 <= step <= 64):
        raise bad("step", step, "must be in [0.01, 64] voxels")
    if not (isinstance(threshold, (int, float)) and math.isfinite(threshold) and 0 <= threshold < 1):
        raise bad("threshold", threshold, "must be in [0, 1) (0 disables early termination)")
    if light_resolution is not None and not (  # the light field's pyramid base
            is_power_of_two(light_resolution) and light_resolution <= MAX_BASE_RESOLUTION):
        raise bad("light_resolution", light_resolution,
                  f"must be a power of two from 1 to {MAX_BASE_RESOLUTION}")
    if not (isinstance(supersample, (int, np.integer)) and 1 <= supersample <= MAX_SUPERSAMPLE):
        raise bad("supersample", supersample, f"must be an integer from 1 to {MAX_SUPERSAMPLE}")
    if light_interp not in LIGHT_QUANTITIES:
        raise bad("light_interp", light_interp, f"choose one of {list(LIGHT_QUANTITIES)}")
    check_env_options(**(env or {}))


def check_env_options(env_directions, env_resolution, env_ms_directions=None, env_ms=None,
                      env_ms_per_frame=0) -> None:
    """The environment source's sky directions (1..1024) and field resolution (a power of two
    from 4 to 256); None: the default."""
    from .environment import ENV_MS_ESCAPE, ENV_MS_NETWORK, sky_directions
    if env_directions is not None:
        sky_directions(env_directions)                    # refuses a bad count
    if env_ms not in (None, ENV_MS_NETWORK, ENV_MS_ESCAPE):
        raise ClvolError(f"raymarch option env_ms = {env_ms!r}: choose network or escape")
    pf = env_ms_per_frame
    if isinstance(pf, bool) or not isinstance(pf, (int, np.integer)) or not 0 <= pf <= 256:
        raise ClvolError(f"raymarch option env_ms_per_frame = {pf!r}: an integer from 0 "
                         f"(every sky cell at once) to 256")
    if env_ms_directions is not None and not (
            isinstance(env_ms_directions, (int, np.integer)) and
            not isinstance(env_ms_directions, bool) and 1 <= env_ms_directions <= 256):
        raise ClvolError(f"raymarch option env_ms_directions = {env_ms_directions!r}: must be "
                         f"an integer from 1 to 256")
    if env_resolution is not None and not (
            isinstance(env_resolution, (int, np.integer)) and not isinstance(env_resolution, bool)
            and is_power_of_two(int(env_resolution)) and 4 <= env_resolution <= 256):
        raise ClvolError(f"raymarch option env_resolution = {env_resolution!r}: must be a "
                         f"power of two from 4 to 256")


class RayMarcher:
    """A volume kept on the device for many frames: density, majorant grid, light field.

    ``grid``: clvol DensityGrid; ``medium``: clvol Medium (``set_medium`` changes it). The volume's
    device data is its DeviceMedium's (clvol/kernels/medium.py): the light field (T_light, or
    its optical depth with light_interp="optical_depth", on the pyramid's cube) is asked of it
    by ``set_light`` (the light-change cost) and kept until the light direction or the density
    scale changes. ``light_builds`` counts them.
    """

    def __init__(self, grid, medium, runtime=None, block: int = DEFAULT_BLOCK,
                 light_resolution: int | None = None, light_interp: str = "transmittance",
                 device_medium: DeviceMedium | None = None, env_directions: int | None = None,
                 env_resolution: int | None = None):
        self.rt = runtime or get_runtime()
        self.grid = grid
        self.medium = medium
        self.light_resolution = light_resolution_for(light_resolution, grid.resolution)
        if light_interp not in LIGHT_QUANTITIES:
            raise ClvolError(f"raymarch option light_interp = {light_interp!r}: choose one of "
                             f"{list(LIGHT_QUANTITIES)}")
        self.light_interp = light_interp
        self.dm = device_medium or DeviceMedium.upload(grid, block, self.rt)
        self.block = self.dm.block
        self.density, self.majorant = self.dm.density, self.dm.majorant
        self.light_builds = 0
        self.outputs = MarchOutputs()    # the march's output buffers, kept frame to frame
        from .environment import DEFAULT_ENV_DIRECTIONS, DEFAULT_ENV_RESOLUTION
        check_env_options(env_directions, env_resolution)
        self.env_directions = int(env_directions or DEFAULT_ENV_DIRECTIONS)
        self.env_resolution = int(env_resolution or DEFAULT_ENV_RESOLUTION)
        self._env_T = None
        # Called with a stage name ("light_field", "env_transmittance", "env_sky",
        # "env_field", "env_background") each time one is recomputed (the Renderer counts).
        self.count = lambda stage: None
        # The stages, keyed by what the plan says they depend on (clvol/render/stages.py).
        counted = lambda stage: self.count(stage)                      # noqa: E731
        self._light = Stage("light_field", counted)
        self._env_sky = Stage("env_sky", counted)
        self._env_field = Stage("env_field", counted)
        self._env_ms_sky = Stage("env_ms_sky", counted)   # the network's J cells
        self._env_net = None       # environment.SkyNetwork, made on the first network sky
        self._bg = Stage("env_background", counted)
        self.env_seconds = 0.0     # host time of the last frame's environment precomputation
        self.rays_stopped_at_bound = 0   # the last read-back march's (cl/raymarch.cl bound)

    @property
    def pyramid(self):
        """Density resampled to the light field's cube (the DeviceMedium's, built once)."""
        return self.dm.pyramid(self.light_resolution)

    def set_medium(self, medium) -> None:
        self.medium = medium

    def set_volume(self, grid, device_medium: DeviceMedium, light_resolution=None) -> None:
        """A new density (Renderer.set_density): what depends on it (the light field, the
        environment's transmittance and source field) is dropped and rebuilt on the next
        march; the sky cells and the background image, which do not, are kept."""
        self.grid = grid
        self.dm = device_medium
        self.block = self.dm.block
        self.density, self.majorant = self.dm.density, self.dm.majorant
        self.light_resolution = light_resolution_for(light_resolution, grid.resolution)
        self._light.drop()
        self._env_T = None
        self._env_field.drop()
        self._env_net = None

    def set_light(self, light_dir) -> bool:
        """Make the light field the one for a light toward ``light_dir`` now (the benchmarks'
        light change: the DeviceMedium computes it unless it already holds it). Returns True
        when it was computed."""
        self._light.drop()
        return self.ensure_light(light_dir)

    def _compute_light(self, key):
        l, scale = key
        builds = self.dm.light_builds
        field = self.dm.light_field(np.asarray(l), scale, self.light_interp,
                                    self.light_resolution)
        self.light_builds += self.dm.light_builds != builds
        return field

    @property
    def light_field(self):
        return self._light.value

    @property
    def light_dir(self):
        return np.asarray(self._light.key[0]) if self._light.built else None

    def ensure_light(self, light_dir) -> bool:
        """The light field for this light and the medium's density scale (the stage's key,
        clvol/render/plan.py ``light_key``), computed only when that changed. Returns True
        when it was computed."""
        return self.ensure_light_for(light_key(light_dir, self.medium.density_scale))

    def ensure_light_for(self, key) -> bool:
        """The light field for the plan's ``keys["light_field"]`` (direction, density
        scale), computed only when the key changed; True when it was computed."""
        builds = self.light_builds
        self._light.get(key, lambda: self._compute_light(key))
        return self.light_builds != builds

    def march(self, camera, light, plan, source: MsSource, *, read_back: bool = True,
              stats: bool = False, emission=None):
        """Render ``camera`` (the plan's marched camera) lit by ``light`` as ``plan`` (a
        FramePlan, clvol/render/plan.py) says, reading the data of ``source`` (the plan's
        source, prepared for this frame). ``emission``: an EmissionGrid (clvol/emission.py;
        its ``device`` planes when set). Returns (layers, plan), or with ``read_back=False``
        (event, buffers, plan): the buffers are ``self.outputs``'s, which the next march
        writes again, so read them before it."""
        if plan.lit:
            self.ensure_light_for(plan.keys["light_field"])
        from ..runtime import Stopwatch
        with Stopwatch() as sw:
            env_kw = self.environment(camera, light, plan)
            self.rt.finish()
        self.env_seconds = sw.seconds
        g = self.grid
        fwd, right, up = camera.basis()
        cube_min = self.pyramid.cube_min if plan.lit else np.zeros(3)
        cube_size = self.pyramid.cube_size if plan.lit else 1.0
        planes, box = (source.device_data(self.medium, plan.shortcuts)
                       if plan.lit and plan.ms.channels is not None else (None, (None, None)))
        o = plan.ms.octaves
        if emission is not None:
            env_kw.update(emission=emission.device if emission.device is not None
                          else emission.values, em_min=emission.bbox_min,
                          em_max=emission.bbox_max, em_colour=emission.colour,
                          em_box=emission.own_box)
        from ..kernels.raymarch import (MarchCamera, MarchEmission, MarchEnvironment,
                                        MarchLight, MarchMs, MarchVolume)
        res = launch(
            defines=plan.programs["raymarch"],
            volume=MarchVolume(self.density, g.bbox_min, g.bbox_max, self.medium,
                               self.majorant, self.block),
            camera=MarchCamera(camera.origin, fwd, right, up, camera.tan_half_fov,
                               camera.width, camera.height),
            light=MarchLight(light, plan.background,
                             field=self.light_field if plan.lit else None,
                             cube_min=cube_min, cube_size=cube_size,
                             quantity=self.light_interp),
            ms=MarchMs(planes, *box, a=o.a, b=o.b, c=o.c),
            environment=MarchEnvironment.pick(env_kw), emission=MarchEmission.pick(env_kw),
            step=plan.step, threshold=plan.threshold, runtime=self.rt,
            read_back=read_back, stats=stats, outputs=self.outputs)
        if read_back:
            # the rays cl/raymarch.cl's progress bound stopped (the header's
            # raymarch.rays_stopped_at_bound); the layers stay images only
            self.rays_stopped_at_bound = res.pop("stopped_at_bound")
            return res, plan
        return res + (plan,)

    def march_with(self, camera, light, ms: str = "wrenninge", *, read_back: bool = True,
                   stats: bool = False, **options):
        """One frame with a source that needs no preparation (none, wrenninge, grid), planned
        from raymarch ``options`` (``ms_lattice=``, ``octaves=``, ``step=`` ...; the others
        default): the benchmarks' and tests' short form of plan_frame + march."""
        from ..scene import Scene
        from .options import bind
        from .plan import VolumeFacts
        o = bind("raymarch", dict(options, ms=ms))
        scene = Scene(path=None, volume=None, medium=self.medium, light=light, camera=camera)
        # the volume's facts, as the Renderer gives them: without them the plan cannot turn the
        # step from voxels into world units (it marched 1-world-unit steps, 10-40x too coarse)
        plan = plan_frame(scene, o, VolumeFacts(self.grid))
        source = make_source(ms, o, self.rt)
        return self.march(plan.camera, light, plan, source, read_back=read_back, stats=stats)

    # ------------------------------------------------------------------ environment
    def environment(self, camera, light, plan) -> dict:
        """The environment's kernel arguments for this frame (``launch``'s env, env_min,
        env_size, env_colour, bg_image), rebuilding only what changed:

            env_transmittance   density scale (or first use): K sweeps on the env pyramid
            env_sky             the sky (constant colour, map, its scale or rotation)
            env_field           any of those, the albedo, the phase, or (anisotropic phase
                                only) the camera position
            env_background      a map scene's camera or map
        """
        from . import environment as E
        from ..kernels.raymarch import env_device_layout
        out, keys = {}, plan.keys
        if plan.env_background == "map":
            out["bg_image"] = self._bg.get(keys["env_background"], lambda: self.rt.upload(
                E.background_image(light, camera)))
        if not plan.env_scatter:
            return out
        if self._env_T is None:
            self._env_T = E.EnvTransmittance(self.grid, self.env_directions, self.env_resolution,
                                             self.rt, self.dm)
        if self._env_T.ensure(self.medium.density_scale):
            self.count("env_transmittance")
        sky = self._env_sky.get(keys["env_sky"], lambda: E.make_sky(
            light, self.env_directions, self.medium.is_grey))
        pyr = self._env_T.pyramid
        alb = tuple(float(a) for a in self.medium.albedo)

        def field():
            ms = self._env_network_ms(camera, light, plan, pyr)
            return self.rt.upload(env_device_layout(E.source_field(
                self._env_T.T, sky, alb, plan.lobes, pyr.cube_min, pyr.cube_size,
                camera.origin, ms=ms, escape=plan.env_ms == "escape")))
        if self._env_net is not None:
            self._env_net.evaluated = 0        # this frame's count (0 unless the field is made)
            if self._env_net.pending:
                self._env_field.drop()  # cells left stale by the last frame: refresh more now
        out.update(env=self._env_field.get(keys["env_field"], field), env_min=pyr.cube_min,
                   env_size=pyr.cube_size, env_colour=sky.colour)
        return out

    def _env_network_ms(self, camera, light, plan, pyr):
        """The network's (C, n^3) sky multiple scattering for this camera position
        (environment.py ``SkyNetwork``), or None where the plan says otherwise."""
        from . import environment as E
        if plan.env_ms != E.ENV_MS_NETWORK:
            return None
        if self._env_net is None or self._env_net.net.grid is not self.grid:
            from .ms import source_class
            self._env_net = E.SkyNetwork(source_class(plan.source), plan.env_weights or None,
                                         self.grid, self.medium, self.rt, self.dm)
            self.count("env_network_setup")
        programs = plan.device_programs(self.rt.is_pocl)
        sky = "sky_gather_mlp" if "sky_gather_mlp" in programs else "gather_mlp"
        self._env_net.net.programs = {"gather_mlp": programs[sky]} if sky in programs else None
        cells = self._env_ms_sky.get(plan.keys["env_ms_sky"], lambda: E.make_sky(
            light, plan.env_ms_directions, self.medium.is_grey))
        return self._env_net.field(cells, self.medium, pyr.cube_min, pyr.cube_size,
                                   self.env_resolution, camera.origin, plan.env_reach,
                                   plan.env_ms_per_frame)

    def env_header(self, plan) -> dict:
        """This frame's network sky entries: cells evaluated, and whether some are still
        stale (a caller that renders the same view again refines it)."""
        from . import environment as E
        if plan.env_ms != E.ENV_MS_NETWORK or self._env_net is None:
            return {}
        return {"raymarch.env_ms_points": self._env_net.points,
                "raymarch.env_ms_cells_evaluated": self._env_net.evaluated,
                "raymarch.env_refining": self._env_net.pending > 0}


def make_source(ms: str, options: dict | None = None, runtime=None) -> MsSource:
    """The source named ``ms`` (``--ms``), built from render ``options`` by the source itself
    (``MsSource.from_options``)."""
    from .ms import source_class
    return source_class(ms).from_options(options or {}, runtime)


def downsample(layers: dict, s: int) -> dict:
    """Box-filter S x S blocks of sub-pixel samples into pixels; depth is averaged with
    alpha weights (the mean distance of the extinction events in the whole pixel)."""
    def box(x):
        h, w = x.shape[0] // s, x.shape[1] // s
        return x.reshape((h, s, w, s) + x.shape[2:]).mean(axis=(1, 3), dtype=np.float64)
    out = {k: box(v).astype(np.float32) for k, v in layers.items() if k != "depth"}
    a = box(layers["alpha"])
    ad = box(layers["alpha"].astype(np.float64) * layers["depth"])
    out["depth"] = np.where(a > 0, ad / np.where(a > 0, a, 1.0), 0.0).astype(np.float32)
    return out



# --------------------------------------------------------------------------- CLI options

def add_arguments(group) -> None:
    """The ray marcher's options: its multiple-scattering source's, then the march's."""
    _source_arguments(group)
    _march_arguments(group)


def _source_arguments(group) -> None:
    """Each multiple-scattering source's own options (clvol/render/ms/, ``source_options``)."""
    from .ms import source_options
    for opt in source_options():
        group.add_argument(*opt.flags, **opt.kwargs)


def _march_arguments(group) -> None:
    from .environment import (DEFAULT_ENV_DIRECTIONS, DEFAULT_ENV_MS_DIRECTIONS,
                              DEFAULT_ENV_RESOLUTION)
    group.add_argument("--max-order", type=int, default=None, metavar="K",
                       help="highest scattering order: 1 = single scattering only (the ray "
                            "marcher then uses --ms none); the ray marcher has no other limit")
    group.add_argument("--majorant-block", type=int, default=DEFAULT_BLOCK, metavar="B",
                       help=f"voxels per majorant-grid cell (default {DEFAULT_BLOCK}; 0 = one "
                            f"global majorant)")
    group.add_argument("--step", type=float, default=DEFAULT_STEP,
                       help=f"march step in voxels (default {DEFAULT_STEP:g})")
    group.add_argument("--threshold", type=float, default=DEFAULT_THRESHOLD,
                       help=f"stop a ray when its transmittance falls below this "
                            f"(default {DEFAULT_THRESHOLD:g}; 0 = never)")
    group.add_argument("--light-resolution", type=int, default=None,
                       help="light field resolution (power of two; default: four times the "
                            f"grid size rounded up to a power of two, at most {MAX_LIGHT_RESOLUTION})")
    group.add_argument("--light-interp", choices=list(LIGHT_QUANTITIES), default="transmittance",
                       help="what is blended trilinearly between light-field voxels: T "
                            "(default) or the optical depth (docs/raymarch.md)")
    group.add_argument("--env-directions", type=int, default=None, metavar="K",
                       help="environment light: sky directions (cells) whose transmittance "
                            f"fields light the medium (default {DEFAULT_ENV_DIRECTIONS}; "
                            f"docs/raymarch.md)")
    group.add_argument("--env-resolution", type=int, default=None, metavar="N",
                       help=f"environment light: voxels per side of each direction's "
                            f"transmittance field (power of two; default "
                            f"{DEFAULT_ENV_RESOLUTION})")
    group.add_argument("--env-ms", choices=["network", "escape"], default=None,
                       help="environment light's multiple scattering: the network for "
                            "--env-ms-directions sky cells (default wherever the network "
                            "serves the sun) or the escape model (cheaper, less accurate; "
                            "docs/raymarch.md)")
    group.add_argument("--env-ms-directions", type=int, default=None, metavar="J",
                       help=f"environment light: sky cells the network is evaluated for "
                            f"(default {DEFAULT_ENV_MS_DIRECTIONS}; each is one network call "
                            f"per camera position)")
    group.add_argument("--env-ms-per-frame", type=int, default=0, metavar="M",
                       help="environment light: after a camera move, evaluate the network "
                            "for at most M sky cells per frame, the others keeping earlier "
                            "positions' values until their turn (default 0 = all at once)")
    group.add_argument("--supersample", type=int, default=DEFAULT_SUPERSAMPLE,
                       help=f"S x S rays per pixel (default {DEFAULT_SUPERSAMPLE})")
    group.add_argument("--no-skip-empty", dest="skip_empty", action="store_false",
                       help="march through empty majorant blocks too (same image, slower)")
    group.add_argument("--no-shortcuts", dest="shortcuts", action="store_false",
                       help="run the general kernel even where the scene allows a shortcut "
                            "(same image, slower; for testing)")

