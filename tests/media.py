"""``medium_of``: a clvol.scene.Medium from the loose values the kernel tests pick (the
kernels, their wrappers and their twins take the medium whole)."""
from clvol.scene import Medium, Phase


def medium_of(scale, albedo=(0.9, 0.9, 0.9), lobes=()) -> Medium:
    """``lobes``: (g, weight) pairs; none: the isotropic phase."""
    phase = Phase.mhg(lobes) if len(lobes) else Phase.isotropic()
    return Medium(density_scale=float(scale), albedo=tuple(float(a) for a in albedo),
                  phase=phase)
