"""``Renderer``: the one object an application holds to render a scene many times.

    import clvol, dataclasses
    scene = clvol.load_scene("examples/cloud.toml")
    r = clvol.Renderer(scene)                      # raymarch + network MS at the view (default)
    img = r.render()                               # a real-time frame: .total .alpha ... .header
    still = r.render(still=True)                   # a still image (what clvol render makes)
    cam = dataclasses.replace(scene.camera, origin=(1.0, 0.3, 2.2))
    img = r.render(camera=cam)                     # recomputes only what the camera changes

Options are the CLI's option names with dashes as underscores (``Renderer(scene, "raymarch",
ms="none")`` is the plain single-scattering march); an option the method does not use is
refused (clvol/render/options.py). Device state (the volume and its majorant, the light
field, the network's pyramid and lattice) is kept between calls and rebuilt only when a
change invalidates it:

    volume, device_medium   once per Renderer (both methods read the same DeviceMedium)
    light_field             light direction or density scale changed
    graded_transmittance    the same, for the network's pyramid
    ms_lattice              camera position, light direction or medium changed (network)
    ms_view_table           a frame that draws (stochastic, the default: the camera moved or
                            the view is still refining; clvol/render/ms/view.py)
    env_transmittance       density scale changed (transmittance toward the sky directions)
    env_sky                 the environment (constant sky, map, scale, rotation) changed
    env_field               the same, the albedo or phase, or with an anisotropic phase
                            the camera position (clvol/render/environment.py)
    env_background          a map scene's camera or map changed
    emission                the scene's [emission] grid read and mapped (with the volume)
    emission_upload         its planes put on the device (once per volume)
    march                   every call

``counts`` counts each stage's recomputations (tests check them).

A new density (``set_density(grid, emission)`` or ``render(grid=..., emission=...)``: the next
frame of a sequence) recomputes what depends on it and nothing else:

    device_medium           the density and its majorant uploaded again
    light_field, graded_transmittance, ms_lattice (or the view table), env_transmittance,
    env_field               rebuilt on the next frame (they read the density)
    network_pyramid         the network's density pyramid (its weights and kernels stay)
    emission_upload         the new emission planes (when the scene has [emission])
    kept                    compiled kernels, the network's weights, env_sky,
                            env_background, the options and the source objects
"""
from __future__ import annotations

import dataclasses
import sys
from collections import Counter

import numpy as np

from ..errors import ClvolError
from ..runtime import Stopwatch, get_runtime
from . import RenderResult
from .options import DEFAULT_METHOD, bind, option_label



def _checked(name: str, value, scene_value):
    """The ``camera``, ``light`` or ``medium`` of a frame, validated by the scene file's rules
    (clvol/scenefile.py ``check_part``: the same fields, ranges and messages) whether given
    to ``render`` or taken from the scene (which may have been made with dataclasses.replace)."""
    from ..scenefile import check_part
    if value is None:
        return check_part(name, scene_value, "Renderer(scene)")
    return check_part(name, value, f"Renderer.render({name}=...)")


class Renderer:
    """A scene and a render method with its options, and the device state they need."""

    def __init__(self, scene, method: str | None = None, *, grid=None, runtime=None,
                 device: str | None = None, **options):
        self.method = method or DEFAULT_METHOD
        self.given = dict(options)
        self.options = bind(self.method, self.given)
        self.scene = scene
        self.rt = runtime or get_runtime(device)
        self.counts: Counter = Counter()
        self._grid = grid
        self._marcher = None
        self._device_medium = None
        self._emission = None
        self._warned: set = set()
        self.source = None
        self._sources: dict = {}
        self.domain = None
        self.weights = None
        self._facts = self._facts_grid = None
        if self.method not in self._METHODS:
            raise ClvolError(f"render method {self.method!r} has no Renderer support; "
                             f"choose one of {sorted(self._METHODS)}")
        setup = self._METHODS[self.method][0]
        if setup is not None:
            getattr(self, setup)()

    def _count(self, stage: str) -> None:
        self.counts[stage] += 1

    def set_density(self, grid, emission=None) -> None:
        """Render a new density from the next frame on (module doc: what it recomputes).
        ``grid``: a clvol DensityGrid (any shape and box); ``emission``: its EmissionGrid
        (clvol/emission.py) when the scene has ``[emission]`` (required then: the renderer
        cannot know which file the new density came from; refused otherwise)."""
        from ..volume.grid import DensityGrid
        if not isinstance(grid, DensityGrid):
            raise ClvolError(f"set_density: expected a clvol.volume.grid.DensityGrid, got "
                             f"{type(grid).__name__}")
        has_em = getattr(self.scene, "emission", None) is not None
        if has_em and emission is None:
            raise ClvolError("set_density: the scene has [emission]: give the new frame's "
                             "emission grid too (scene.emission.load(volume, grid))")
        if emission is not None and not has_em:
            raise ClvolError("set_density: emission given, but the scene has no [emission]")
        self._grid = grid
        self._emission = emission
        self._device_medium = None
        if self._marcher is not None:
            self._marcher.set_volume(grid, self.device_medium, self.options["light_resolution"])

    @property
    def grid(self):
        """The volume (loaded on first use)."""
        if self._grid is None:
            self._grid = self.scene.volume.load()
            self._count("volume")
        return self._grid

    @property
    def emission(self):
        """The scene's EmissionGrid with its planes on the device (clvol/emission.py), or None
        for a scene without ``[emission]`` (read on first use, with the volume)."""
        spec = getattr(self.scene, "emission", None)
        if spec is None:
            return None
        if self._emission is None:
            self._emission = spec.load(self.scene.volume, self.grid)
            self._count("emission")
        if self._emission.device is None:
            self._emission.device = self.rt.upload(self._emission.values)
            self._count("emission_upload")
        return self._emission

    @property
    def device_medium(self):
        """The volume on the device with its majorant (uploaded on first use, shared by
        every frame and method)."""
        if self._device_medium is None:
            from ..kernels.medium import DeviceMedium
            self._device_medium = DeviceMedium.upload(self.grid, self.options["majorant_block"],
                                                      self.rt)
            self._count("device_medium")
        return self._device_medium

    # ------------------------------------------------------------------ raymarch
    def _setup_raymarch(self) -> None:
        """Validate the options, build the configured source (it reads its options), and
        refuse what nothing read (clvol/render/options.py)."""
        from .ms import source_class
        from .raymarch import check_march_options, make_source
        o, given = self.options, self.given
        mo = o["max_order"]
        if mo is not None:
            if isinstance(mo, bool) or not isinstance(mo, (int, np.integer)) or mo < 1:
                raise ClvolError(f"option --max-order = {mo!r}: must be an integer >= 1")
            if mo > 1:
                raise ClvolError(f"option --max-order {mo} is not supported by method 'raymarch': "
                                 f"it simulates order 1 (--max-order 1) or all orders; use "
                                 f"--method pathtrace to stop at order {mo}")
            if given.get("ms") is not None and source_class(given["ms"]).multiple_scattering:
                raise ClvolError(f"option --max-order 1 asks for single scattering, but --ms "
                                 f"{given['ms']} adds multiple scattering; drop one of them")
        source_class(o["ms"])                     # an unknown name is refused here
        # the environment's options are read (and checked) for every scene: one with no sky
        # never uses them, but a bad value is still a mistake worth one line now
        env = {k: o[k] for k in ("env_directions", "env_resolution", "env_ms_directions",
                                 "env_ms", "env_ms_per_frame")}
        check_march_options(o["step"], o["threshold"], o["light_resolution"], o["supersample"],
                            o["light_interp"], env)
        for always in ("shortcuts", "skip_empty", "majorant_block"):
            o[always]
        self.source = make_source(o["ms"], o, self.rt)
        self.source.count = self._count
        if "ms_lattice" in o.read:      # a grid source read its file: the plans take the FmsLattice
            o.set("ms_lattice", self.source.ms_lattice)
        self._sources = {self.source.name: self.source}
        self.domain = self.source.training_domain()     # None: a source without a network
        self.weights = self.source.network_weights()    # the same file's MlpWeights, or None
        unused = o.unused()
        if unused:
            raise ClvolError(_unused_message(unused[0], o["ms"]))

    def plan(self, camera=None, light=None, medium=None):
        """The FramePlan of a frame (clvol/render/plan.py ``plan_frame``) with the scene's
        camera, light and medium or those given; a domain warning is printed once per
        distinct reason."""
        from .plan import plan_frame
        scene = dataclasses.replace(self.scene, camera=_checked("camera", camera, self.scene.camera),
                                    light=_checked("light", light, self.scene.light),
                                    medium=_checked("medium", medium, self.scene.medium))
        if self._facts is None or self._facts_grid is not self.grid:
            from .plan import VolumeFacts
            self._facts, self._facts_grid = VolumeFacts(self.grid, self.emission), self.grid
        plan = plan_frame(scene, self.options, self._facts, self.domain, self.weights)
        if plan.warning and plan.warning not in self._warned:
            print(f"clvol: warning: {plan.warning}", file=sys.stderr)
            self._warned.add(plan.warning)
        return plan

    def active_source(self, medium=None):
        """(source, warning): the multiple-scattering source a render of ``medium`` (default
        the scene's) uses -- the configured one, or the alternative the plan chose for a
        medium outside the network's domain or optically thin -- and the domain warning."""
        plan = self.plan(medium=medium)
        return self._source(plan.source), plan.warning

    def _source(self, name):
        """The source object that executes the plan's source (the configured one, or a
        fallback built with its defaults and kept)."""
        if name not in self._sources:
            from .raymarch import make_source
            self._sources[name] = make_source(name, runtime=self.rt)
            self._sources[name].count = self._count
        return self._sources[name]

    def _raymarch_supersample(self) -> int:
        return self.options["supersample"]

    def _no_supersample(self) -> int:
        return 1

    def _render_raymarch(self, cam, light, medium, seed=None, still=False) -> RenderResult:
        if seed is not None:
            raise ClvolError(f"seed: render(seed=) chooses the path tracer's pass; the "
                             f"raymarch method takes its seed as an option "
                             f"(Renderer(..., seed=N), read by --ms stochastic)")
        from .ms.base import SourceFrame
        from .raymarch import RayMarcher, downsample
        o = self.options
        with Stopwatch() as sw_total:
            with Stopwatch() as sw_load:
                grid = self.grid
            if self._marcher is None:
                self._marcher = RayMarcher(grid, medium, self.rt, o["majorant_block"],
                                           o["light_resolution"], o["light_interp"],
                                           device_medium=self.device_medium,
                                           env_directions=o["env_directions"],
                                           env_resolution=o["env_resolution"])
                self._marcher.count = self._count
            rm = self._marcher
            rm.set_medium(medium)
            plan = self.plan(cam, light, medium)
            source = self._source(plan.source)
            if plan.lit:
                source.prepare(SourceFrame(grid, plan.camera, light, medium, self.rt,
                                           plan.shortcuts, self._count, plan.lattice_reach,
                                           rm.dm, plan.step, plan.threshold,
                                           plan.keys["ms"],
                                           plan.device_programs(self.rt.is_pocl),
                                           still=still))
            else:
                source.skip()
            with Stopwatch() as sw_light:
                if plan.lit:
                    rm.ensure_light_for(plan.keys["light_field"])   # counted by its stage
                self.rt.finish()
            emission = self.emission
            with Stopwatch() as sw_march:
                layers, _ = rm.march(plan.camera, light, plan, source, emission=emission)
            self._count("march")
            if plan.supersample > 1:
                layers = downsample(layers, plan.supersample)
        header = plan.header(source.label)
        header.update({
            "seconds": round(sw_total.seconds, 4),
            "seconds.load": round(sw_load.seconds, 4),
            "seconds.light_field": round(sw_light.seconds, 4),
            "seconds.march": round(sw_march.seconds, 4),
            **({"seconds.environment": round(rm.env_seconds, 4)} if plan.env_scatter else {}),
            "raymarch.block": int(rm.block),
            "device": self.rt.entry.label,
        })
        # rays cl/raymarch.cl's progress bound stopped, counted by the kernel (marched rays:
        # with supersampling, sub-pixel rays); 0 on every image that can be marched
        header["raymarch.rays_stopped_at_bound"] = int(rm.rays_stopped_at_bound)
        header.update(source.header())
        header.update(rm.env_header(plan))
        return RenderResult(layers, header)

    # ------------------------------------------------------------------ pathtrace
    def _render_pathtrace(self, cam, light, medium, seed=None, still=False) -> RenderResult:
        # every path-traced image is a still one: ``still`` changes nothing here
        from .pathtrace import render_pathtrace
        o = self.options
        scene = dataclasses.replace(self.scene, camera=cam, light=light, medium=medium)
        res = render_pathtrace(scene, spp=o["spp"], seed=o["seed"] if seed is None else seed,
                               max_order=o["max_order"], time_budget=o["time"], runtime=self.rt,
                               majorant_block=o["majorant_block"], grid=self.grid,
                               device_medium=self.device_medium, emission=self.emission)
        self._count("pathtrace")
        res.header = {"method": "pathtrace",
                      "method.description": "volumetric path tracing (reference)", **res.header}
        return res

    # ------------------------------------------------------------------ API
    def _check_optical_range(self, medium) -> None:
        """Both methods keep optical depths in float32: density_scale times the largest
        density over the box's diagonal must stay below MAX_OPTICAL_DEPTH = 1e37 (the light
        field's own rule, clvol/kernels/transmittance.py; libclvol's CLVOL_MAX_OPTICAL_DEPTH),
        else inf * 0 makes NaN (the API fuzz found density_scale = 3.4e38 rendering a NaN
        alpha through the path tracer and an unlit march)."""
        g = self.grid
        if getattr(self, "_max_density_of", None) is not g:
            self._max_density = float(np.max(g.density, initial=0.0))
            self._max_density_of = g
        from ..kernels.transmittance import check_optical_range
        check_optical_range(medium.density_scale, self._max_density,
                            float(np.linalg.norm(g.extent)), name="medium.density_scale")

    def render(self, camera=None, light=None, medium=None, seed: int | None = None,
               grid=None, emission=None, still: bool = False) -> RenderResult:
        """Render with the scene's camera, light and medium, or the ones given (instances of
        clvol.scene.Camera, Light, Medium) for this frame only: the next plain ``render()``
        uses the scene's again. ``grid`` (and, with ``[emission]``, ``emission``): a new
        density from this frame on (``set_density``), kept until the next one (README,
        "What persists between calls").

        ``seed`` (path tracer only) replaces the ``seed`` option for this frame, so the passes
        of a progressive render draw independent samples from one Renderer.

        ``still``: this frame is a still image, not one of a moving sequence (``clvol render``
        passes True): an accumulating source (``--ms stochastic``) draws at once what its
        still view would gather over frames (docs/raymarch.md, "One default"); the image is
        the same for the same seed. False (a real-time frame) draws ``view_samples``."""
        cam = _checked("camera", camera, self.scene.camera)
        light = _checked("light", light, self.scene.light)
        medium = _checked("medium", medium, self.scene.medium)
        from .memory import check_frame_memory
        check_frame_memory(self.method, cam.width, cam.height,
                           getattr(self, self._METHODS[self.method][2])(), self.rt.device)
        if grid is not None:
            self.set_density(grid, emission)
        elif emission is not None:
            raise ClvolError("render(emission=...) goes with grid=...: a new frame's density "
                             "and its emission grid")
        self._check_optical_range(medium)
        if not isinstance(still, bool):
            raise ClvolError(f"still: {still!r} must be True or False")
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)
                                 or not 0 <= seed < 2**32):
            raise ClvolError(f"seed: {seed!r} must be an integer in [0, 2^32)")
        return getattr(self, self._METHODS[self.method][1])(cam, light, medium, seed, still)

    # method -> (set-up run once by __init__, or None; the frame; the supersampling factor):
    # the one table the Renderer dispatches through (METHODS in clvol/render/__init__.py
    # names the methods for the CLI; test_renderer holds the two to the same names)
    _METHODS = {"raymarch": ("_setup_raymarch", "_render_raymarch", "_raymarch_supersample"),
                "pathtrace": (None, "_render_pathtrace", "_no_supersample")}


def source_reads(ms: str) -> set:
    """The options the source ``ms`` reads, found by letting it build itself from the
    defaults and recording what it read (a grid source without a grid still reads
    ``ms_lattice`` before it refuses)."""
    from .ms import source_class
    from .options import bind
    probe = bind("raymarch", {})
    try:
        source_class(ms).from_options(probe, None)
    except ClvolError:
        pass
    return set(probe.read)


def _unused_message(name: str, ms: str) -> str:
    """Why a raymarch option is refused: the sources that would read it."""
    from .ms import source_classes
    owners = [n for n in source_classes() if name in source_reads(n)]
    if owners:
        return (f"option {option_label(name)} is used only with --ms {' or '.join(owners)} "
                f"(method 'raymarch' with --ms {ms} does not read it)")
    return f"option {option_label(name)} is not read by method 'raymarch' with --ms {ms}"
