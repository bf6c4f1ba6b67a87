"""Write the golden images that tests/test_renderer.py holds the renderer against.

    python tests/data/make_goldens.py            # raymarch goldens (goldens_raymarch.npz)
    python tests/data/make_goldens.py --pathtrace  # path-tracer goldens (goldens_pathtrace.npz)

The scenes are copies of examples/*.toml (tests/data/scenes/) rendered at GOLDEN_SIZE^2 so
that reframing an example does not change a golden. Run it only when an image is meant to
change, and say why in the commit. The device name is recorded: bit-identity is checked
only on the device that made the goldens.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
SCENES = ("cloud", "jade", "milk", "smoke")
GOLDEN_SIZE = 48
PT_SPP = 4
PT_SEED = 7
# ms source -> extra options of the raymarch method
RAYMARCH_SOURCES = {"none": {}, "wrenninge": {}, "lattice": {}, "network": {}}
LAYERS = ("total", "multiple", "alpha", "depth")


def golden_scene(name: str):
    from clvol.scene import load_scene
    sc = load_scene(HERE / "scenes" / f"{name}.toml")
    cam = dataclasses.replace(sc.camera, width=GOLDEN_SIZE, height=GOLDEN_SIZE)
    return dataclasses.replace(sc, camera=cam)


def golden_fms_lattice(scene):
    """A deterministic, view-independent F_ms lattice (an analytic field, no estimator): the
    "lattice" source's golden needs an input that does not depend on any other code path."""
    from clvol.render.ms.lattice import FmsLattice
    g = scene.volume.load()
    n = 8
    ax = (np.arange(n) + 0.5) / n
    z, y, x = np.meshgrid(ax, ax, ax, indexing="ij")
    vals = np.stack([0.05 + 0.1 * x * y, 0.04 + 0.1 * y * z, 0.03 + 0.1 * z * x], -1)
    return FmsLattice(vals.astype(np.float32), tuple(g.bbox_min), tuple(g.bbox_max))


GOLDEN_WEIGHTS = str(Path(__file__).resolve().parents[2] / "clvol" / "data" / "weights" / "cloud_small.npz")


def render_raymarch_golden(name: str, ms: str) -> dict:
    from clvol.render.renderer import Renderer
    sc = golden_scene(name)
    kw = {"none": {}, "wrenninge": {}, "lattice": {"ms_lattice": golden_fms_lattice(sc)},
          # a fixed weight file, not the shipped default: these goldens hold the pipeline,
          # and a better default model must not change them
          "network": {"domain_fallback": False, "weights": GOLDEN_WEIGHTS}}[ms]
    res = Renderer(sc, "raymarch", ms=ms, **kw).render()
    return {k: res.layers[k] for k in LAYERS}


def render_pathtrace_golden(name: str) -> dict:
    from clvol.render.pathtrace import render_pathtrace
    res = render_pathtrace(golden_scene(name), spp=PT_SPP, seed=PT_SEED, progress=False)
    return {"total": res.layers["total"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--pathtrace", action="store_true")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(HERE.parent.parent))
    from clvol.runtime import get_runtime
    arrays = {"device": np.array(get_runtime().entry.label)}
    if args.pathtrace:
        for name in SCENES:
            for k, v in render_pathtrace_golden(name).items():
                arrays[f"{name}/{k}"] = v
        out = HERE / "goldens_pathtrace.npz"
    else:
        for name in SCENES:
            for ms in RAYMARCH_SOURCES:
                for k, v in render_raymarch_golden(name, ms).items():
                    arrays[f"{name}/{ms}/{k}"] = v
        out = HERE / "goldens_raymarch.npz"
    np.savez_compressed(out, **arrays)
    print(f"wrote {out} ({out.stat().st_size} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
