"""The multiple-scattering source interface, and the data every source's plan carries.

Every source answers the same questions, so the marcher (clvol/render/raymarch.py) never
tests a source's name:

- ``plan(medium, shortcuts)``: an ``MsPlan`` with the kernel -D defines it needs, the device
  data it reads (an F_ms lattice, or nothing) and what it simulates or skips (header lines);
- ``prepare(frame)``: fill its data for the frame's camera, light and medium (a no-op for
  analytic sources; the network fills its lattice here, only when the frame changed what the
  lattice depends on);
- ``header()``: its own header entries (options, weights, time split).

What a source can do, it declares here (class attributes and classmethods, each with its
answer in the source's own module), so nothing outside this package tests a source's class
or name (tests/test_architecture.py): ``multiple_scattering``, ``uses_network``,
``bundle_supported``; ``choose_for`` (the source that runs for a medium: the network's training
domain and thin-medium rules), ``lattice_reach_for`` and ``network_reach`` (the active-point
rules), ``training_domain``.

The sources, one module each in this package: analytic.py (``NoMs`` "none", ``OctavesMs``
"wrenninge"), grid.py (``LatticeMs`` "grid", a precomputed ``FmsLattice``), network.py (``NetworkMs``
"network", the paper's world lattice) and view.py (``ViewMs`` "view", ``StochasticViewMs``
"stochastic": the network where the camera sees). The package's ``__init__`` maps ``--ms``
names to classes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ...errors import ClvolError
from ...kernels.raymarch import (DEFAULT_OCTAVE_MULTIPLIER, DEFAULT_OCTAVES, DEFAULT_THRESHOLD,
                                 MAX_OCTAVES, MS_KIND_LATTICE, MS_SOURCE_DEFINES,
                                 ms_defines)


# --------------------------------------------------------------------------- data

@dataclass(frozen=True)
class Octaves:
    """Wrenninge octaves: F_ms = sum_{i=1}^{n-1} b^i f(mu; g c^i) T_light^(a^i).

    ``a`` multiplies the optical depth toward the light, ``b`` the contribution, ``c`` the
    phase eccentricity. Energy condition (Wrenninge et al.): an octave's contribution
    multiplier must not exceed its extinction multiplier, i.e. ``b <= a`` in this formula's
    letters (the paper writes it "a <= b" with the roles of the letters swapped;
    docs/raymarch.md). The defaults (clvol/kernels/raymarch.py: a = b = c) satisfy it.
    """
    n: int = DEFAULT_OCTAVES
    a: float = DEFAULT_OCTAVE_MULTIPLIER
    b: float = DEFAULT_OCTAVE_MULTIPLIER
    c: float = DEFAULT_OCTAVE_MULTIPLIER

    @property
    def energy_conserving(self) -> bool:
        return self.b <= self.a

    @classmethod
    def from_options(cls, o: dict) -> "Octaves":
        """From render options (octaves, ms_a, ms_b, ms_c); the defaults above for any missing."""
        d = cls()
        return cls(o.get("octaves", d.n), float(o.get("ms_a", d.a)), float(o.get("ms_b", d.b)),
                   float(o.get("ms_c", d.c)))

    def as_options(self) -> dict:
        return {"octaves": self.n, "ms_a": self.a, "ms_b": self.b, "ms_c": self.c}

    def check(self) -> "Octaves":
        def bad(name, value, allowed):
            return ClvolError(f"raymarch option {name} = {value!r}: {allowed}")
        if not (isinstance(self.n, (int, np.integer)) and not isinstance(self.n, bool)
                and 1 <= self.n <= MAX_OCTAVES):
            raise bad("octaves", self.n, f"must be an integer from 1 to {MAX_OCTAVES}")
        # a = 0 would make T^(a^i) = 1 behind any amount of medium: light through walls.
        for name, v, lo_open in (("ms_a", self.a, True), ("ms_b", self.b, False),
                                 ("ms_c", self.c, False)):
            ok = math.isfinite(v) and (0 < v <= 1 if lo_open else 0 <= v <= 1)
            if not ok:
                raise bad(name, v, "must be in (0, 1]" if lo_open else "must be in [0, 1]")
        return self


# --------------------------------------------------------------------------- options

@dataclass(frozen=True)
class SourceOption:
    """One render option a source reads: its CLI flags and argparse keywords (type, default,
    help ...). The sources' options are collected from the registry
    (clvol/render/ms/__init__.py ``source_options``) into the ray marcher's option table
    (clvol/render/options.py), which the CLI, the Renderer and the viewer share."""
    flags: tuple
    kwargs: dict = field(default_factory=dict, hash=False, compare=False)

    @property
    def name(self) -> str:
        """The Python keyword (argparse's ``dest``)."""
        return self.kwargs.get("dest") or self.flags[0][2:].replace("-", "_")

    @property
    def default(self):
        action = self.kwargs.get("action")
        return (action == "store_false") if action in ("store_true", "store_false") \
            else self.kwargs.get("default")


def option(*flags, **kwargs) -> SourceOption:
    """A source's option as argparse takes it: ``option("--ms-a", type=float, default=0.5,
    help=...)``."""
    return SourceOption(tuple(flags), kwargs)


# --------------------------------------------------------------------------- interface

@dataclass
class MsPlan:
    """What one source asks of the kernel for one medium and camera: decided from the options
    alone (``MsSource.plan_for``), before any data exists; the data it reads comes from the
    prepared source (``MsSource.device_data``)."""
    defines: dict
    octaves: Octaves = Octaves()            # oct_a, oct_b, oct_c kernel arguments
    simulated: list = field(default_factory=list)
    skipped: list = field(default_factory=list)

    @property
    def channels(self) -> int | None:
        """Colour planes marched for F_ms, or None when the source has no lattice or table."""
        reads_table = self.defines["MS_SOURCE"] in (MS_SOURCE_DEFINES[MS_KIND_LATTICE],
                                                    MS_SOURCE_DEFINES["view"])
        return int(self.defines["MS_CHANNELS"]) if reads_table else None


@dataclass(frozen=True)
class SourceChoice:
    """The source that runs and why it is not the configured one (None when it is)."""
    name: str
    warning: str | None = None      # outside the network's training domain
    thin: float | None = None       # the largest optical thickness, when thinness chose none
    thin_reason: str | None = None  # the header's skipped line saying why (thin media)


@dataclass
class SourceFrame:
    """What a source may read to fill its data: the volume, the frame's camera, light and
    medium, the runtime, the shortcut switch, and ``count(stage)`` (recomputation counters)."""
    grid: object
    camera: object
    light: object
    medium: object
    runtime: object
    shortcuts: bool = True
    count: object = None
    reach: float | None = None  # the plan's active-point reach (None: every lattice point)
    device_medium: object = None  # the volume on the device (clvol/kernels/medium.py): its
                                  # density, pyramids and cache (data as long as the volume)
    step: float = 0.0         # the march's segment length (world units) ...
    threshold: float = DEFAULT_THRESHOLD   # ... and its early-termination transmittance
    key: object = None        # the plan's keys["ms"]: what the source's data depends on
    programs: dict | None = None  # the plan's programs with this device's additions
                                  # (FramePlan.device_programs): the defines it builds with


class MsSource:
    """Base class: no multiple scattering. Subclasses override what they need.

    A source's class decides (``plan_for``: pure, from the options; called by
    clvol/render/plan.py ``plan_frame``); an instance executes (``prepare`` fills its data
    for a frame, ``device_data`` hands it to the marcher, ``header`` reports it)."""
    name = "none"
    label = "no multiple scattering"
    # What the source is (one answer per source, read by the plan, the renderer, the bundle):
    multiple_scattering = False   # it adds orders >= 2 (refused with --max-order 1)
    uses_network = False          # the trained network computes its F_ms (and the sky's)
    bundle_supported = False      # the C host (clvol bundle, examples/c/) implements it
    summary = "single scattering only"   # its entry in --ms's help
    # The render options it reads (flag, default, help): its own table, collected into the
    # CLI's and the Renderer's by the registry (several sources may list the same one).
    options: tuple = ()

    @classmethod
    def option(cls, name: str) -> SourceOption:
        """This source's declared option ``name``."""
        for opt in cls.options:
            if opt.name == name:
                return opt
        raise KeyError(f"--ms {cls.name} has no option {name!r}")

    @classmethod
    def read(cls, o, name: str):
        """Option ``name`` from render options ``o`` (recorded as read), or its declared
        default where ``o`` lacks it (a partial dict, as the tests pass)."""
        return o[name] if name in o else cls.option(name).default

    @classmethod
    def choose_for(cls, medium, options, volume, domain) -> SourceChoice:
        """The source that runs when this one is configured for ``medium`` (``options``: the
        render options; ``volume``: clvol/render/plan.py ``VolumeFacts`` or None; ``domain``:
        the weights' training domain or None): itself, unless the source's own rule says
        otherwise (the network's: clvol/render/ms/network.py)."""
        return SourceChoice(cls.name)

    @classmethod
    def lattice_reach_for(cls, volume, step_voxels: float) -> float | None:
        """The active-point reach of this source's own F_ms lattice over the volume (only
        points a density sample reads are filled; shortcuts on), or None: every point, or no
        lattice."""
        return None

    @classmethod
    def network_reach(cls, volume, step_voxels: float) -> float | None:
        """The network's active-voxel reach for the sky's F_ms fields (a network source), or
        None."""
        return None

    def training_domain(self) -> dict | None:
        """The validity domain of the weights this source evaluates, or None (no network)."""
        return None

    # What the C host's bundle (clvol/bundle.py) and the sky's network share
    # (clvol/render/environment.py) ask of a network source; None or empty for the others.
    lattice_points_per_launch: int | None = None   # the most lattice points one launch takes

    def bundle_view(self, camera) -> dict | None:
        """What the C host's bundle needs of a view-space source for ``camera``: its
        ``view.*`` manifest keys (``keys``) and the ``viewdepth`` program's defines
        (``viewdepth``); None for a source without a view table in the C host."""
        return None

    def network_weights(self):
        """The checked weights (clvol/features/weights.py MlpWeights) it evaluates, or None."""
        return None

    @classmethod
    def domain_rules(cls) -> dict:
        """The numbers of its ``choose_for`` rules ({rule: value}; the bundle's manifest)."""
        return {}

    @classmethod
    def outside_training_domain(cls, domain: dict, medium) -> list[str]:
        """The ways ``medium`` lies outside the weights' ``domain`` (empty: inside)."""
        return []

    @classmethod
    def active_points(cls, grid, resolution, reach: float, box=None):
        """Boolean mask over a lattice's points ([z][y][x], over ``box`` or the volume's):
        those with density within ``reach`` (the plan's ``lattice_reach``), or None."""
        return None

    @classmethod
    def network_programs(cls, medium, shortcuts: bool, weights, fused: bool | None = None):
        """(programs, pocl): {program name: -D defines} of the kernels its network runs for
        ``medium`` with ``weights`` (MlpWeights), and the defines PoCL adds to some of them;
        ({}, {}) for a source without a network. ``fused`` (None: the Python host's choice):
        gather and network in one kernel, else two (the C host's)."""
        return {}, {}

    @classmethod
    def sky_evaluator(cls, weights, grid, medium, runtime, device_medium):
        """The network evaluator of the sky's F_ms fields (``weights`` None: the shipped
        model), or None for a source without a network."""
        return None

    @classmethod
    def from_options(cls, o, runtime=None) -> "MsSource":
        """The source built from render options (a missing one takes its default); the
        options it reads count as used (clvol/render/options.py)."""
        return cls()

    @classmethod
    def plan_for(cls, medium, camera, shortcuts: bool, o) -> MsPlan:
        """The kernel defines, octaves and effects of this source for ``medium`` seen by
        ``camera`` (the marched camera) with render options ``o``."""
        return MsPlan(ms_defines("none"), skipped=[f"multiple scattering (--ms {cls.name})"])

    @classmethod
    def key_for(cls, camera, light, medium, shortcuts: bool):
        """What this source's data depends on for a frame (the plan's ``keys["ms"]``;
        clvol/render/stages.py); None for a source without data of its own."""
        return None

    def prepare(self, frame: "SourceFrame") -> None:
        """Fill this source's data for the frame (nothing to do for an analytic source)."""

    def skip(self) -> None:
        """This frame does not read the source (nothing is lit): forget per-frame state that
        its header would otherwise report as this frame's."""

    def device_data(self, medium, shortcuts: bool):
        """(planes, (box_min, box_max)): the F_ms lattice or table on the device (a
        DeviceArray) and its box, or (None, (None, None)) for a source without data."""
        return None, (None, None)

    def header(self) -> dict:
        return {}
