"""Analytic multiple-scattering sources: none (single scattering only) and Wrenninge's
octaves, evaluated in the kernel from the light field (no data of their own)."""
from __future__ import annotations

from ...kernels.raymarch import ms_defines
from .base import MsPlan, MsSource, Octaves, option


class NoMs(MsSource):
    """Single scattering only."""
    bundle_supported = True


class OctavesMs(MsSource):
    """Wrenninge octaves evaluated in the kernel from the light field: no data of its own."""
    name = "wrenninge"
    label = "Wrenninge octaves (analytic multiple scattering)"
    summary = "analytic octaves"
    multiple_scattering = True
    bundle_supported = True
    options = (
        option("--octaves", type=int, default=Octaves.n,
               help=f"Wrenninge octaves N (default {Octaves.n})"),
        option("--ms-a", type=float, default=Octaves.a,
               help=f"octave extinction multiplier a (default {Octaves.a:g})"),
        option("--ms-b", type=float, default=Octaves.b,
               help=f"octave contribution multiplier b (default {Octaves.b:g}; keep b <= a)"),
        option("--ms-c", type=float, default=Octaves.c,
               help=f"octave eccentricity multiplier c (default {Octaves.c:g})"),
    )

    def __init__(self, octaves: Octaves = Octaves()):
        self.octaves = octaves.check()

    @classmethod
    def from_options(cls, o: dict, runtime=None) -> "OctavesMs":
        return cls(Octaves.from_options(o))

    @classmethod
    def plan_for(cls, medium, camera, shortcuts: bool, options) -> MsPlan:
        o = Octaves.from_options(options).check()
        p = MsPlan(ms_defines("wrenninge", o.n), octaves=o)
        if o.n > 1:
            p.simulated.append(f"multiple scattering (Wrenninge octaves n={o.n} a={o.a:g} "
                               f"b={o.b:g} c={o.c:g})")
        else:
            p.skipped.append("multiple scattering (Wrenninge with 1 octave: single only)")
        return p

    def header(self) -> dict:
        o = self.octaves
        return {"raymarch.octaves": o.n, "raymarch.ms_a": o.a, "raymarch.ms_b": o.b,
                "raymarch.ms_c": o.c, "raymarch.energy_condition_b_le_a": o.energy_conserving}
