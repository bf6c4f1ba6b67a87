"""clvol: participating media rendered with multiple scattering on any OpenCL device.

    import clvol
    scene = clvol.load_scene("examples/cloud.toml")
    result = clvol.Renderer(scene).render()      # the paper's method: raymarch + network MS
    result.total, result.alpha, result.header

The pipeline, file by file: docs/architecture.md.
"""
__version__ = "0.1.0"

__all__ = ["__version__", "load_scene", "Renderer", "RenderResult"]


def __getattr__(name):
    # Lazy: `clvol info` and the scene tools must not import pyopencl-heavy modules.
    if name == "load_scene":
        from .scene import load_scene
        return load_scene
    if name == "Renderer":
        from .render.renderer import Renderer
        return Renderer
    if name == "RenderResult":
        from .render import RenderResult
        return RenderResult
    raise AttributeError(f"module 'clvol' has no attribute {name!r}")


def __dir__():
    # The lazy names are what a user looks for with dir(clvol) or tab completion.
    return sorted(set(globals()) | set(__all__))
