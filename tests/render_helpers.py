"""``render_raymarch``: the tests' one-call ray march with the keyword spellings and defaults
the tests were written against (analytic Wrenninge octaves unless ``ms`` is given; the
network forced even outside its training domain). Applications use ``clvol.Renderer``,
whose defaults are the CLI's."""
from __future__ import annotations

from clvol.kernels.majorant import DEFAULT_BLOCK
from clvol.render.raymarch import DEFAULT_STEP, DEFAULT_THRESHOLD
from clvol.render.renderer import Renderer, source_reads
from clvol.render.ms import source_classes


def render_raymarch(scene, *, ms: str = "wrenninge", octaves: int = 3, a: float = 0.5,
                    b: float = 0.5, c: float = 0.5, ms_lattice=None,
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
    opts = dict(ms=ms, step=step, threshold=threshold, skip_empty=skip_empty,
                majorant_block=block, light_resolution=light_resolution,
                light_interp=light_interp, supersample=supersample, shortcuts=shortcuts)
    per_source = dict(octaves=octaves, ms_a=a, ms_b=b, ms_c=c, ms_lattice=ms_lattice, weights=weights,
                      ms_resolution=ms_resolution, domain_fallback=domain_fallback,
                      view_block=view_block, view_knots=view_knots,
                      view_samples=view_samples, seed=seed)
    read = source_reads(ms) if ms in source_classes() else set()   # the source asked for
    opts.update({k: v for k, v in per_source.items() if k in read})
    opts = {k: v for k, v in opts.items() if v is not None}
    return Renderer(scene, "raymarch", grid=grid, runtime=runtime, **opts).render()
