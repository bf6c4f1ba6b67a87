"""``plan_frame``: the one place that decides what a ray-marched frame simulates, and how.

    plan = plan_frame(scene, options, volume=VolumeFacts(grid), domain=weights_domain)

A ``FramePlan`` holds every decision of a frame: the multiple-scattering source that runs
(the configured one, or the measured alternative for a medium outside the network's training
domain or optically thin; ``--max-order 1`` means none), whether anything is lit, the phase
lobes the kernel evaluates, the colour planes it marches, the environment's share, the
network's active-point rule, the kernel's ``-D`` defines and the effects simulated or skipped,
each with its reason. Deciding is cheap and has no side effects (no device, no file read
beyond a precomputed grid named by path); everything that runs reads the plan:

- ``Renderer`` (renderer.py) executes it: it prepares the plan's source and marches with
  the plan's defines; its caches key on what the plan says the stage depends on;
- ``clvol bundle`` (clvol/bundle.py) serialises it for the C library;
- the EXR header is written from it (``FramePlan.header``) plus the stages' timings.

The plan asks each source what it is (clvol/render/ms/base.py): ``choose_for`` (the network's
domain fallback and thin-medium shortcut live in its own module, with their measurements),
``uses_network``, ``lattice_reach_for``, ``network_reach``; it never tests a source's class
or name.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..kernels.raymarch import march_defines
from .ms import source_class
from .ms.analytic import NoMs
from .ms.base import MsPlan, SourceChoice
from .environment import ENV_MS_NETWORK


class VolumeFacts:
    """What the plan needs to know of the volume, once per density: its resolution and
    cells, and (computed on first use: only the network sources ask) its largest optical
    thickness along an axis at density scale 1; with ``emission`` (the scene's EmissionGrid,
    clvol/emission.py) its colour planes and whether it has a box of its own."""

    def __init__(self, grid, emission=None):
        self.resolution = tuple(int(n) for n in grid.resolution)
        self.cell = float(np.min(grid.cell_size))        # the smallest voxel side
        self.grid = grid
        self._ot = None
        self.emission_channels = None if emission is None else int(emission.channels)
        self.emission_box = bool(emission is not None and emission.own_box)

    @property
    def max_optical_thickness(self) -> float:
        if self._ot is None:
            from ..volume.stats import volume_stats
            self._ot = float(volume_stats(self.grid, 1.0)["max_optical_thickness"])
        return self._ot


def is_lit(medium, light) -> bool:
    """Anything scatters the sun toward the camera: some channel has albedo * irradiance > 0."""
    return bool(np.any(np.asarray(medium.albedo) * np.asarray(light.irradiance) > 0))


def choose_source(configured: str, medium, options, volume: VolumeFacts | None,
                  domain: dict | None) -> SourceChoice:
    """The multiple-scattering source for ``medium``: none for ``--max-order 1``; otherwise
    what the configured source's ``choose_for`` says (itself, or for the network sources single
    scattering alone in an optically thin medium and the measured fallback outside the
    weights' training domain: clvol/render/ms/network.py)."""
    if options["max_order"] == 1:
        return SourceChoice(NoMs.name)
    return source_class(configured).choose_for(medium, options, volume, domain)


@dataclass(frozen=True)
class FramePlan:
    """Every decision of one ray-marched frame (``plan_frame``)."""
    configured_source: str          # the --ms option
    source: str                     # the source that runs (``choose_source``)
    warning: str | None             # outside the training domain, if so
    thin: float | None              # optically thin: the largest optical thickness
    lit: bool                       # the sun's light field and the source are used
    shortcuts: bool
    skip_empty: bool
    camera: object                  # the marched camera (supersampled: S x the pixels)
    lobes: tuple                    # (g, weight) per lobe the kernel evaluates (none: isotropic)
    ms: MsPlan                      # the source's kernel defines, octaves, effects
    defines: dict                   # cl/raymarch.cl's -D defines of the source and phase
    programs: dict                  # program name -> -D defines, every program of the frame
    programs_pocl: dict             # program name -> the defines PoCL adds (Clang builtins)
    channels: int                   # colour planes marched for F_ms
    background: tuple               # constant radiance behind the medium
    env_scatter: bool               # the environment lights the medium
    env_background: str             # "none", "constant" or "map"
    env_directions: int
    env_resolution: int
    env_ms: str                     # the sky's multiple scattering: network, escape or none
    env_ms_directions: int          # sky cells the network is evaluated for (network only)
    env_ms_per_frame: int           # at most this many cells refreshed per frame (0: all)
    env_weights: object             # the network's weight file (network only; None: shipped)
    env_reach: float | None         # the network's active-voxel rule (None: every voxel)
    step_voxels: float
    step: float                     # world units
    threshold: float
    light_resolution: int           # the light field's side (0: the volume is not known)
    light_interp: str
    supersample: int
    lattice_reach: float | None     # the network's active-point rule (None: every point)
    emission: bool
    simulated: tuple
    skipped: tuple
    keys: dict                      # stage -> what it depends on (clvol/render/stages.py)

    def device_programs(self, pocl: bool) -> dict:
        """``programs`` as a device builds them: with ``programs_pocl`` added on PoCL."""
        if not pocl:
            return self.programs
        return {name: dict(d, **self.programs_pocl.get(name, {}))
                for name, d in self.programs.items()}

    def header(self, label: str) -> dict:
        """The header entries that state this plan (``label``: the source's description)."""
        return {
            "method": "raymarch",
            "method.description": f"ray marching: exact single scattering + {label}",
            "simulated": "; ".join(self.simulated),
            "skipped": "; ".join(self.skipped) or "nothing",
            **({"raymarch.env_directions": self.env_directions,
                "raymarch.env_resolution": self.env_resolution,
                "raymarch.env_ms": self.env_ms} if self.env_scatter else {}),
            **({"raymarch.env_ms_directions": self.env_ms_directions}
               if self.env_scatter and self.env_ms == ENV_MS_NETWORK else {}),
            "raymarch.ms": self.source,
            "raymarch.step_voxels": self.step_voxels,
            "raymarch.step": self.step,
            "raymarch.threshold": self.threshold,
            "raymarch.skip_empty": self.skip_empty,
            "raymarch.light_resolution": self.light_resolution if self.lit else 0,
            "raymarch.light_interp": self.light_interp,
            "raymarch.supersample": self.supersample,
            "raymarch.channels_marched": self.channels,
            "raymarch.shortcuts": self.shortcuts,
            **({"warning": self.warning} if self.warning else {}),
        }


MAX_LIGHT_RESOLUTION = 256    # the light field's largest side (its pyramid's base)

# The program names whose OpenCL source is another's (the others are named after their
# cl/<name>.cl): the sweeps' widths and the gather's bake; "sky_" + a name is the sky's own
# build of a network program where it differs from the sun's (``_programs``).
PROGRAM_SOURCES = {"transmittance_w1": "transmittance", "transmittance_wL": "transmittance",
                   "gather_bake": "gather"}
SKY_PREFIX = "sky_"


def program_source(name: str) -> str:
    """The cl/<stem>.cl a program of ``FramePlan.programs`` is built from."""
    name = name.removeprefix(SKY_PREFIX)
    return PROGRAM_SOURCES.get(name, name)


def auto_light_resolution(resolution, cap: int = MAX_LIGHT_RESOLUTION) -> int:
    """The light field's default resolution: four times the grid's largest side rounded up
    to a power of two, at most ``cap``. The voxelised light field is the ray marcher's main
    bias against exact single scattering (docs/raymarch.md measures it at 1x, 2x and 4x): a
    64^3 grid gets 256^3, grids from 96^3 up the cap."""
    n = 4 * max(resolution)
    return min(1 << max(0, (n - 1).bit_length()), cap)


def light_resolution_for(option, resolution) -> int:
    """The light field's resolution: the ``light_resolution`` option, or for None the
    default for a grid of ``resolution`` (``auto_light_resolution``)."""
    return int(option or auto_light_resolution(resolution))


def plan_frame(scene, options, volume: VolumeFacts | None = None,
               domain: dict | None = None, weights=None) -> FramePlan:
    """The plan of one ray-marched frame of ``scene`` (its camera, light and medium) with the
    method's ``options`` (a mapping with the raymarch options, clvol/render/options.py).
    ``volume``: the density's facts (None: thinness and the domain are not judged, as for a
    source that never reads them); ``domain``: the network's training domain from its weight
    file (None for other sources); ``weights``: that file's MlpWeights (the network's
    programs; None: they are not planned)."""
    o = options
    medium, light, camera = scene.medium, scene.light, scene.camera
    shortcuts, skip_empty, s = bool(o["shortcuts"]), bool(o["skip_empty"]), int(o["supersample"])
    if s > 1:
        camera = dataclasses.replace(camera, width=camera.width * s, height=camera.height * s)
    choice = choose_source(o["ms"], medium, o, volume, domain)
    lit = is_lit(medium, light) or not shortcuts
    sim, skip = [], []
    lobes = _sun_and_phase(medium, light, lit, shortcuts, sim, skip)
    cls = source_class(choice.name) if lit else NoMs
    ms = cls.plan_for(medium, camera, shortcuts, o)
    if lit:
        _ms_effects(ms, choice, sim, skip)
    env = _environment(medium, light, o, shortcuts, choice, sim, skip)
    env["env_reach"] = (source_class(choice.name).network_reach(volume, o["step"])
                        if env["env_ms"] == ENV_MS_NETWORK and shortcuts and volume is not None
                        else None)
    _emission_effects(getattr(scene, "emission", None), sim, skip)

    defines = march_defines(list(lobes), lit, skip_empty, ms.defines)
    # resolved for an unlit frame too (the bundle's C host may light it later); the header
    # and the programs count it only where it is used
    light_res = (light_resolution_for(o["light_resolution"], volume.resolution)
                 if volume is not None else 0)
    # the network's lattice skips points no density sample reads (shortcuts on)
    reach = (cls.lattice_reach_for(volume, o["step"]) if lit and shortcuts and volume is not None
             else None)
    programs, pocl = _programs(scene, o, defines, lit, light_res, env, volume,
                               cls if lit else None, source_class(choice.name), weights)
    if lit:
        programs.update(ms.programs)      # the source's own (the view sources' depth pass)
    return FramePlan(
        configured_source=o["ms"], source=choice.name, warning=choice.warning,
        thin=choice.thin, lit=lit, shortcuts=shortcuts, skip_empty=skip_empty, camera=camera,
        lobes=lobes, ms=ms, defines=defines, programs=programs, programs_pocl=pocl,
        channels=ms.channels or 1, **env,
        step_voxels=float(o["step"]),
        step=float(o["step"]) * (volume.cell if volume is not None else 1.0),
        threshold=float(o["threshold"]), light_resolution=light_res,
        light_interp=o["light_interp"], supersample=s, lattice_reach=reach,
        emission=getattr(scene, "emission", None) is not None, simulated=tuple(sim),
        skipped=tuple(skip), keys=_stage_keys(cls, camera, light, medium, shortcuts, lobes, env))


def _programs(scene, o, defines, lit, light_res, env, volume, lit_source, chosen,
              weights) -> tuple[dict, dict]:
    """(programs, programs_pocl): every program the frame builds, by name, with its -D
    defines: the majorant's and the march's always; the light field's pyramid and sweeps
    when lit; the network's (its source's ``network_programs``) where it serves the sun or
    the sky. ``programs_pocl``: what PoCL adds to some of them."""
    from ..kernels.raymarch import input_defines
    from ..kernels.transmittance import sweep_programs
    from .environment import sky_channels
    medium, light = scene.medium, scene.light
    emission = getattr(scene, "emission", None) is not None and volume is not None
    march = dict(defines, **input_defines(
        o["light_interp"],
        env_channels=sky_channels(light, medium.is_grey) if env["env_scatter"] else None,
        bg_image=env["env_background"] == "map",
        emission_channels=volume.emission_channels if emission else None,
        emission_box=emission and volume.emission_box))
    programs, pocl = {"majorant": {}}, {}
    if lit and light_res:
        programs.update(pyramid={}, transmittance={}, **sweep_programs([light_res]))
    if weights is not None:
        for cls, shortcuts in ((lit_source, bool(o["shortcuts"])),
                               (chosen if env["env_ms"] == ENV_MS_NETWORK else None, True)):
            if cls is None:
                continue
            more, more_pocl = cls.network_programs(medium, shortcuts, weights)
            for name, d in more.items():
                if name.startswith("transmittance_w") and name in programs:
                    continue                        # a sweep width both need: one program
                key = name if programs.get(name, d) == d else SKY_PREFIX + name
                programs[key] = d
                if name in more_pocl:
                    pocl[key] = more_pocl[name]
    programs["raymarch"] = march
    return programs, pocl


def light_key(light_dir, density_scale) -> tuple:
    """What the light field depends on: the unit direction toward the light and the density
    scale (the volume and the field's resolution are the marcher's own)."""
    from ..kernels.transmittance import check_light_dir
    return tuple(check_light_dir(light_dir)), float(density_scale)


def _stage_keys(cls, camera, light, medium, shortcuts, lobes, env) -> dict:
    """Each recomputable stage's key: what its value depends on, for this frame."""
    from .environment import sky_key
    keys = {"light_field": light_key(light.direction, medium.density_scale),
            "ms": cls.key_for(camera, light, medium, shortcuts)}
    if env["env_background"] == "map":
        keys["env_background"] = (sky_key(light, 0), camera)
    if env["env_scatter"]:
        sky = (sky_key(light, env["env_directions"]), medium.is_grey)
        keys["env_sky"] = sky
        net = env["env_ms"] == ENV_MS_NETWORK
        if net:                                   # the network's own J cells
            keys["env_ms_sky"] = (sky_key(light, env["env_ms_directions"]), medium.is_grey)
        # the phase toward the camera enters the field only for an anisotropic phase; the
        # network's F_ms always depends on the direction toward the camera
        keys["env_field"] = (sky, float(medium.density_scale),
                             tuple(float(a) for a in medium.albedo), lobes,
                             tuple(camera.origin) if lobes or net else None, env["env_ms"],
                             (keys["env_ms_sky"], str(env["env_weights"]), medium.phase,
                              env["env_reach"]) if net else None)
    return keys


def _sun_and_phase(medium, light, lit, shortcuts, sim, skip) -> tuple:
    """The sun's effects, and the phase lobes the kernel evaluates (none: isotropic)."""
    from .environment import has_environment
    env_on = has_environment(light)
    if lit:
        sim.append("single scattering" + (" of the sun light" if env_on else ""))
    else:
        skip.append(("sun light scattering" if env_on else "single and multiple scattering")
                    + " (albedo * irradiance = 0: no light field, no source)")
    if shortcuts and medium.phase.is_isotropic:
        skip.append("phase evaluation (isotropic: constant 1/(4 pi))")
        return ()
    return medium.phase.pairs


def _ms_effects(ms: MsPlan, choice: SourceChoice, sim, skip) -> None:
    """The source's effects; an optically thin medium says why it has none."""
    sim += ms.simulated
    skip += [x for x in ms.skipped if not (choice.thin is not None and "--ms none" in x)]
    if choice.thin is not None:
        skip.append(choice.thin_reason)
    if ms.channels is None:
        skip.append("per-channel marching (albedo and irradiance are constant over the "
                    "medium: one colour-free march, colour applied once per ray)")


def _environment(medium, light, o, shortcuts, choice, sim, skip) -> dict:
    """The sky's share of the frame: whether it lights the medium, how its multiple
    scattering is found (``_env_ms``), what is behind it."""
    from .environment import DEFAULT_ENV_DIRECTIONS, DEFAULT_ENV_RESOLUTION, has_environment
    env_on = has_environment(light)
    dirs = int(o["env_directions"] or DEFAULT_ENV_DIRECTIONS)
    res = int(o["env_resolution"] or DEFAULT_ENV_RESOLUTION)
    env_map = getattr(light, "environment_map", None) is not None
    sky_dark = env_on and not np.any(light.sky_mean() > 0)    # a black constant or map
    scatter = env_on and ((any(a > 0 for a in medium.albedo) and not sky_dark) or not shortcuts)
    env_ms, ms_dirs = ("none", 0)
    if scatter:
        what = "the map's" if env_map else "the sky's"
        sim.append(f"environment single scattering ({what} light from {dirs} "
                   f"directions, each cell's irradiance with the transmittance toward it "
                   f"({res}^3 fields from the density pyramid) and the phase "
                   f"function along each camera ray)")
        env_ms, ms_dirs = _env_ms(medium, light, o, choice, res, sim, skip)
    elif env_on:
        skip.append("environment in-scattering (" + ("a black sky" if sky_dark else
                    "albedo 0: nothing scatters") + ")")
    if light.environment is not None:
        sim.append("background (environment radiance behind the medium)")
    if env_map:
        sim.append("background (the environment map along each camera ray)")
    sim.append("extinction along camera rays")
    return dict(
        background=tuple(light.environment) if light.environment is not None else (0.0,) * 3,
        env_scatter=scatter,
        env_background="map" if env_map else "constant" if light.environment is not None
        else "none",
        env_directions=dirs, env_resolution=res, env_ms=env_ms, env_ms_directions=ms_dirs,
        env_ms_per_frame=int(o["env_ms_per_frame"] or 0) if env_ms == ENV_MS_NETWORK else 0,
        env_weights=o["weights"] if env_ms == ENV_MS_NETWORK else None)


def _env_ms(medium, light, o, choice, res, sim, skip) -> tuple:
    """(how the sky's multiple scattering is found, network sky cells): the network where it
    serves the sun (the --ms source chosen for this medium is a network source) unless
    --env-ms escape; the escape model otherwise, and in a white furnace (albedo 1 under a
    uniform sky), where it is exact; none at --max-order 1."""
    from .environment import DEFAULT_ENV_MS_DIRECTIONS, sky_is_uniform
    if o["max_order"] == 1:
        skip.append("environment multiple scattering (--max-order 1)")
        return "none", 0
    furnace = all(a == 1.0 for a in medium.albedo) and sky_is_uniform(light)
    if ((o["env_ms"] or ENV_MS_NETWORK) == ENV_MS_NETWORK
            and source_class(choice.name).uses_network and not furnace):
        j = int(o["env_ms_directions"] or DEFAULT_ENV_MS_DIRECTIONS)
        sim.append(f"environment multiple scattering (the network's F_ms for {j} sky "
                   f"directions, each weighted by its cell's irradiance, at the {res}^3 "
                   f"field's voxels toward the camera)")
        return ENV_MS_NETWORK, j
    why = ("exact here: albedo 1 under a uniform sky" if furnace else
           "--env-ms escape" if o["env_ms"] == "escape" else
           f"the network does not serve the sun here (--ms {choice.name})")
    sim.append("environment multiple scattering (approximation: the sky light "
               "blocked toward each direction arrives scattered, scaled by an escape "
               f"model's (albedo t / (1 - albedo (1 - t)))^2; {why}; measured error in "
               "docs/raymarch.md)")
    return "escape", 0


def _emission_effects(emission, sim, skip) -> None:
    if emission is None:
        return
    sim.append(f"emission ({emission.kind} grid {emission.grid!r}: sigma_a Le, sigma_a = "
               f"sigma_t (1 - albedo), exact along camera rays)")
    skip.append("scattering of emitted light (the path tracer has it; measured in "
                "docs/raymarch.md, \"Emission\")")
