"""``medium_of``, ``light_of``: a clvol.scene.Medium or Light from the loose values the kernel
tests pick (the kernels, their wrappers and their twins take the medium and the light whole)."""
from clvol.scene import Light, Medium, Phase


def medium_of(scale, albedo=(0.9, 0.9, 0.9), lobes=()) -> Medium:
    """``lobes``: (g, weight) pairs; none: the isotropic phase."""
    phase = Phase.mhg(lobes) if len(lobes) else Phase.isotropic()
    return Medium(density_scale=float(scale), albedo=tuple(float(a) for a in albedo),
                  phase=phase)


def light_of(direction, irradiance=(1.0, 1.0, 1.0)) -> Light:
    """The distant light the kernels take whole: ``direction`` toward it (as given: the tests
    pass unit vectors), RGB ``irradiance``."""
    return Light(direction=tuple(float(v) for v in direction),
                 irradiance=tuple(float(v) for v in irradiance))
