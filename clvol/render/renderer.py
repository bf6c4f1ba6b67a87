"""``Renderer``: the one object an application holds to render a scene many times.

    import clvol, dataclasses
    scene = clvol.load_scene("examples/cloud.toml")
    r = clvol.Renderer(scene)                      # raymarch + network MS (the paper's method)
    img = r.render()                               # RenderResult: .total .alpha ... .header
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
import math
import sys
from collections import Counter

import numpy as np

from ..errors import ClvolError
from ..kernels.majorant import DEFAULT_BLOCK
from ..runtime import Stopwatch, get_runtime
from . import RenderResult
from .options import DEFAULT_METHOD, bind, option_label
from .raymarch import DEFAULT_STEP, DEFAULT_THRESHOLD


def _check_arg(value, cls, name):
    if value is not None and not isinstance(value, cls):
        raise ClvolError(f"Renderer.render({name}=...): expected a clvol.scene.{cls.__name__} "
                         f"(e.g. dataclasses.replace(scene.{name}, ...)), got {type(value).__name__}")
    return value


def _check_medium(m):
    s = m.density_scale
    if not (isinstance(s, (int, float)) and math.isfinite(s) and s >= 0):
        raise ClvolError(f"[medium.density_scale] = {s!r}: must be a finite number >= 0")
    a = np.asarray(m.albedo, np.float64)
    if a.shape != (3,) or not (np.all(np.isfinite(a)) and np.all(a >= 0) and np.all(a <= 1)):
        raise ClvolError(f"[medium.albedo] = {list(m.albedo)!r}: three values in [0, 1]")


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
        self.source = self.fallback = None
        self._tau1 = self.thin = None
        if self.method == "raymarch":
            self._setup_raymarch()

    def _count(self, stage: str) -> None:
        self.counts[stage] += 1

    def set_density(self, grid, emission=None) -> None:
        """Render a new density from the next frame on (module doc: what it recomputes).
        ``grid``: a clvol Grid (any shape and box); ``emission``: its EmissionGrid
        (clvol/emission.py) when the scene has ``[emission]`` (required then: the renderer
        cannot know which file the new density came from; refused otherwise)."""
        from ..volume.grid import Grid
        if not isinstance(grid, Grid):
            raise ClvolError(f"set_density: expected a clvol.volume.grid.Grid, got "
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
        self._tau1 = None
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
        from .ms.network import NetworkMs
        from .raymarch import check_march_options, make_source
        from .ms import source_class, source_classes
        o, given = self.options, self.given
        mo = o["max_order"]
        if mo is not None:
            if isinstance(mo, bool) or not isinstance(mo, (int, np.integer)) or mo < 1:
                raise ClvolError(f"option --max-order = {mo!r}: must be an integer >= 1")
            if mo > 1:
                raise ClvolError(f"option --max-order {mo} is not supported by method 'raymarch': "
                                 f"it simulates order 1 (--max-order 1) or all orders; use "
                                 f"--method pathtrace to stop at order {mo}")
            if given.get("ms", "none") != "none":
                raise ClvolError(f"option --max-order 1 asks for single scattering, but --ms "
                                 f"{given['ms']} adds multiple scattering; drop one of them")
            o["ms"] = "none"
        ms = o["ms"]
        source_class(ms)                          # an unknown name is refused here
        for name in given:
            owners = [n for n, cls in source_classes().items() if name in cls.options]
            if owners and ms not in owners:
                raise ClvolError(f"option {option_label(name)} is used only with --ms "
                                 f"{' or '.join(owners)} "
                                 f"(method 'raymarch' with --ms {ms} does not read it)")
        check_march_options(o["step"], o["threshold"], o["light_resolution"], o["supersample"],
                            o["light_interp"], o["env_directions"], o["env_resolution"])
        self.source = make_source(ms, o, self.rt)
        self.source.count = self._count
        if isinstance(self.source, NetworkMs):
            self.domain = self.source.training_domain()

    def _active_source(self, medium, grid):
        """The configured source, or the measured alternative when the medium lies outside
        the network's training domain (one warning per distinct reason)."""
        from .ms.network import THIN_OPTICAL_THICKNESS, NetworkMs, fallback_for, outside_domain
        if not isinstance(self.source, NetworkMs):
            return self.source, None
        if self._tau1 is None:                 # optical thickness at density scale 1
            from ..volume.stats import volume_stats
            self._tau1 = volume_stats(grid, 1.0)["max_optical_thickness"]
        ot = self._tau1 * medium.density_scale
        if ot < THIN_OPTICAL_THICKNESS and not self.options["no_shortcuts"]:
            self.thin = ot
            return self._other("none"), None
        self.thin = None
        out = outside_domain(self.domain, medium, ot)
        if not out:
            return self.source, None
        alt = None if self.options["no_domain_fallback"] else fallback_for(medium)
        what = ("the network is used all the same (--no-domain-fallback)"
                if self.options["no_domain_fallback"] else
                "the network is used all the same (measured better than the analytic sources "
                "there)" if alt is None else f"multiple scattering from --ms {alt} instead")
        msg = (f"scene outside the network's training domain ({'; '.join(out)}): {what} "
               f"(docs/raymarch.md)")
        if msg not in self._warned:
            print(f"clvol: warning: {msg}", file=sys.stderr)
            self._warned.add(msg)
        if alt is None:
            return self.source, msg
        return self._other(alt), msg

    def active_source(self, medium=None):
        """(source, warning): the multiple-scattering source a render of ``medium`` (default
        the scene's) uses -- the configured one, or the alternative for a medium outside the
        network's domain or optically thin -- and the domain warning, if any."""
        return self._active_source(medium or self.scene.medium, self.grid)

    def _other(self, name):
        from .raymarch import make_source
        if self.fallback is None or self.fallback.name != name:
            self.fallback = make_source(name, runtime=self.rt)
        return self.fallback

    def _render_raymarch(self, cam, light, medium) -> RenderResult:
        from .raymarch import RayMarcher, downsample, is_lit
        from .ms.base import Frame
        o = self.options
        shortcuts, skip_empty, s = not o["no_shortcuts"], not o["no_skip_empty"], o["supersample"]
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
            if s > 1:
                cam = dataclasses.replace(cam, width=cam.width * s, height=cam.height * s)
            source, warning = self._active_source(medium, grid)
            if is_lit(medium, light) or not shortcuts:
                from .ms.network import lattice_reach
                reach = lattice_reach(grid, o["step"])
                source.prepare(Frame(grid, cam, light, medium, self.rt, shortcuts, self._count,
                                     reach, rm.dm.cache, rm.density,
                                     o["step"] * float(np.min(grid.cell_size)),
                                     o["threshold"]))
            else:
                source.skip()
            with Stopwatch() as sw_light:
                if is_lit(medium, light) or not shortcuts:
                    if rm.ensure_light(light.direction):
                        self._count("light_field")
                    self.rt.finish()
            emission = self.emission
            with Stopwatch() as sw_march:
                layers, plan = rm.march(cam, light, source, step=o["step"],
                                        threshold=o["threshold"], skip_empty=skip_empty,
                                        shortcuts=shortcuts, emission=emission)
            self._count("march")
            if s > 1:
                layers = downsample(layers, s)
        step = float(o["step"])
        simulated, skipped = list(plan.simulated), list(plan.skipped)
        if emission is not None:
            simulated.append(f"emission ({emission.kind} grid {emission.name!r}: sigma_a Le, "
                             f"sigma_a = sigma_t (1 - albedo), exact along camera rays)")
            skipped.append("scattering of emitted light (the path tracer has it; measured in "
                           "docs/raymarch.md, \"Emission\")")
        header = {
            "method": "raymarch",
            "method.description": f"ray marching: exact single scattering + {source.label}",
            "simulated": "; ".join(simulated),
            "skipped": "; ".join(skipped) or "nothing",
            "seconds": round(sw_total.seconds, 4),
            "seconds.load": round(sw_load.seconds, 4),
            "seconds.light_field": round(sw_light.seconds, 4),
            "seconds.march": round(sw_march.seconds, 4),
            **({"seconds.environment": round(rm.env_seconds, 4),
                "raymarch.env_directions": rm.env_directions,
                "raymarch.env_resolution": rm.env_resolution} if plan.env_scatter else {}),
            "raymarch.ms": source.name,
            "raymarch.step_voxels": step,
            "raymarch.step": step * float(np.min(grid.cell_size)),
            "raymarch.threshold": float(o["threshold"]),
            "raymarch.skip_empty": bool(skip_empty),
            "raymarch.block": int(rm.block),
            "raymarch.light_resolution": int(rm.light_resolution) if plan.lit else 0,
            "raymarch.light_interp": o["light_interp"],
            "raymarch.supersample": int(s),
            "raymarch.channels_marched": plan.channels,
            "raymarch.shortcuts": bool(shortcuts),
            "device": self.rt.entry.label,
        }
        if warning:
            header["warning"] = warning
        if self.thin is not None and source is not self.source:
            header["skipped"] = ("; ".join(s for s in skipped if "--ms none" not in s) +
                                 f"; multiple scattering (optically thin: largest optical "
                                 f"thickness {self.thin:.3g} < 0.5, where single scattering "
                                 f"alone measured as accurate; docs/raymarch.md)").lstrip("; ")
        header.update(source.header())
        return RenderResult(layers, header)

    # ------------------------------------------------------------------ pathtrace
    def _render_pathtrace(self, cam, light, medium, seed=None) -> RenderResult:
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
    def render(self, camera=None, light=None, medium=None, seed: int | None = None,
               grid=None, emission=None) -> RenderResult:
        """Render with the scene's camera, light and medium, or the ones given (instances of
        clvol.scene.Camera, Light, Medium). Returns a RenderResult. ``grid`` (and, with
        ``[emission]``, ``emission``): a new density from this frame on (``set_density``).

        ``seed`` (path tracer only) replaces the ``seed`` option for this frame, so the passes
        of a progressive render draw independent samples from one Renderer."""
        from ..scene import Camera, Light, Medium
        cam = _check_arg(camera, Camera, "camera") or self.scene.camera
        light = _check_arg(light, Light, "light") or self.scene.light
        medium = _check_arg(medium, Medium, "medium") or self.scene.medium
        _check_medium(medium)
        if grid is not None:
            self.set_density(grid, emission)
        elif emission is not None:
            raise ClvolError("render(emission=...) goes with grid=...: a new frame's density "
                             "and its emission grid")
        if seed is not None:
            if self.method != "pathtrace":
                raise ClvolError(f"seed: render(seed=) chooses the path tracer's pass; the "
                                 f"{self.method} method takes its seed as an option "
                                 f"(Renderer(..., seed=N), read by --ms stochastic)")
            if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**32:
                raise ClvolError(f"seed: {seed!r} must be an integer in [0, 2^32)")
        if self.method == "raymarch":
            return self._render_raymarch(cam, light, medium)
        if self.method == "pathtrace":
            return self._render_pathtrace(cam, light, medium, seed)
        raise ClvolError(f"render method {self.method!r} has no Renderer support")


def render_raymarch(scene, *, ms: str = "wrenninge", octaves: int = 3, a: float = 0.5,
                    b: float = 0.5, c: float = 0.5, ms_grid=None,
                    step: float = DEFAULT_STEP, threshold: float = DEFAULT_THRESHOLD,
                    skip_empty: bool = True, block: int = DEFAULT_BLOCK,
                    light_resolution: int | None = None, light_interp: str = "transmittance",
                    supersample: int = 1, shortcuts: bool = True, grid=None,
                    runtime=None, weights=None, ms_resolution=None,
                    domain_fallback: bool = False, view_block=None, view_knots=None,
                    view_samples=None, seed=None):
    """Render ``scene`` with the ray marcher in one call (a ``Renderer`` kept for one frame).
    Returns a RenderResult with layers total, single, multiple (H, W, 3), alpha and depth
    (H, W), and the header.

    step: segment length in voxels of the density grid (smallest cell side);
    threshold: early termination transmittance (error < threshold x the largest source
    radiance along the ray); supersample: S x S rays per pixel on a regular sub-grid, box
    filtered (1 = pixel centres); grid: the loaded volume (else ``scene.volume.load()``).
    ms="network": ``weights`` (a weight file; default the shipped model) fills an F_ms
    lattice of ``ms_resolution`` points per side for this camera and light, used even outside
    the weights' training domain unless ``domain_fallback`` (the Renderer's default).
    ms="view": the same network queried at ``view_knots`` depths per ``view_block`` x
    ``view_block`` pixels of the camera's view (clvol/render/ms/view.py); ms="stochastic":
    ``view_samples`` free-flight samples per block from the stream of ``seed``.
    """
    from .ms import source_classes
    opts = dict(ms=ms, step=step, threshold=threshold, no_skip_empty=not skip_empty,
                majorant_block=block, light_resolution=light_resolution,
                light_interp=light_interp, supersample=supersample, no_shortcuts=not shortcuts)
    per_source = dict(octaves=octaves, ms_a=a, ms_b=b, ms_c=c, ms_grid=ms_grid, weights=weights,
                      ms_resolution=ms_resolution, no_domain_fallback=not domain_fallback,
                      view_block=view_block, view_knots=view_knots,
                      view_samples=view_samples, seed=seed)
    read = getattr(source_classes().get(ms), "options", ())     # those of the source asked for
    opts.update({k: v for k, v in per_source.items() if k in read})
    opts = {k: v for k, v in opts.items() if v is not None}
    return Renderer(scene, "raymarch", grid=grid, runtime=runtime, **opts).render()
