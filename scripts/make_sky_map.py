"""Write the small procedural sky map shipped with examples/cloud_sky.toml.

    python scripts/make_sky_map.py [-o examples/sky_64x32.exr]

A lat-long map (convention: docs/conventions.md "Environment maps"): 64 x 32 texels, linear
RGB. Above the horizon a blue sky brightening toward a white horizon, with a warm glow around
the direction (phi = 60 deg from +x toward -z, 30 deg above the horizon); below the horizon a
dim grey-brown ground. Deterministic (no random numbers): the same file every time.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from clvol.envmap import texel_directions  # noqa: E402
from clvol.image import write_exr  # noqa: E402

W, H = 64, 32
ZENITH = np.array([0.10, 0.25, 0.65])
HORIZON = np.array([0.65, 0.75, 0.90])
GROUND = np.array([0.12, 0.10, 0.08])
GLOW = np.array([1.6, 1.1, 0.6])
GLOW_DIR = (np.cos(np.radians(30)) * np.cos(np.radians(60)), np.sin(np.radians(30)),
            -np.cos(np.radians(30)) * np.sin(np.radians(60)))


def sky(h: int = H, w: int = W) -> np.ndarray:
    d = texel_directions(h, w)
    y = d[..., 1:2]
    up = np.clip(y, 0.0, 1.0)
    rgb = np.where(y > 0, HORIZON + (ZENITH - HORIZON) * np.sqrt(up), GROUND)
    c = np.clip(d @ np.asarray(GLOW_DIR), 0.0, 1.0)[..., None]
    rgb = rgb + GLOW * c ** 16 * (y > 0)
    return rgb.astype(np.float32)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", default=str(Path(__file__).resolve().parents[1] / "examples"
                                      / "sky_64x32.exr"))
    out = Path(ap.parse_args().o)
    write_exr(out, {"total": sky()})
    print(f"wrote {out} ({out.stat().st_size} bytes)")


if __name__ == "__main__":
    main()
