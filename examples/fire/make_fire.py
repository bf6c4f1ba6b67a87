"""Make the frames of the fire example: a procedural fireball that rises, grows and cools.

    python examples/fire/make_fire.py                 # 8 frames, 64^3, next to this script
    python examples/fire/make_fire.py --frames 48 --resolution 128 --out /tmp/fire

Each frame is ``fire_{frame:04d}.npz`` (frames 1..N) with two grids on the same voxels over
the box [-0.5, 0.5]^3 (docs/volumes.md, ".npz"): ``density`` (smoke and flame, 0..~1) and
``temperature`` (kelvin; 0 where nothing burns), read by examples/fire/fire.toml's
``[emission] kind = "blackbody"``. Deterministic: the same --seed gives the same files.
Nothing is downloaded.

The model (an artistic one, not a simulation): a ball of puffs centred at height
-0.25 + 0.35 t (t = 0..1 over the sequence), radius 0.14 + 0.16 t, its surface displaced by
two octaves of smooth periodic noise that is carried upward with the ball; a thinner smoke
stem below it; the temperature peaks in the ball's core at 2600 K and falls to 1700 K by
the last frame, and is 0 outside the inner 80% of the ball.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy import ndimage


def smooth_noise(n: int, scale: float, rng) -> np.ndarray:
    """Periodic noise in [0, 1] on an n^3 lattice: white noise low-passed in Fourier space
    (features about ``scale`` of the box wide)."""
    w = rng.standard_normal((n, n, n))
    k = np.fft.fftfreq(n)
    kk = k[:, None, None] ** 2 + k[None, :, None] ** 2 + k[None, None, :] ** 2
    f = np.fft.ifftn(np.fft.fftn(w) * np.exp(-kk * (scale * n) ** 2 * 2.0)).real
    f = (f - f.mean()) / (f.std() + 1e-12)
    return 0.5 + 0.18 * f


def smoothstep(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def make_frame(t: float, n: int, noise, rise: float):
    """(density, temperature) float32 [z][y][x] at sequence time t in [0, 1]."""
    c = (np.arange(n) + 0.5) / n - 0.5
    z, y, x = np.meshgrid(c, c, c, indexing="ij")
    # the noise moves up with the ball (periodic lookup, in voxels)
    shift = rise * t * n
    coords = np.stack([(z + 0.5) * n - 0.5, (y + 0.5) * n - 0.5 - shift, (x + 0.5) * n - 0.5])
    n1 = ndimage.map_coordinates(noise[0], coords, order=1, mode="grid-wrap")
    n2 = ndimage.map_coordinates(noise[1], coords, order=1, mode="grid-wrap")
    cy, r = -0.25 + rise * t, 0.14 + 0.16 * t
    d = np.sqrt(x ** 2 + (y - cy) ** 2 + z ** 2) / r
    d = d + 0.9 * (n1 - 0.5) + 0.4 * (n2 - 0.5)
    ball = smoothstep(1.0, 0.55, d)
    stem_r = 0.05 + 0.03 * t + 0.04 * (n2 - 0.5)
    stem = smoothstep(1.0, 0.4, np.sqrt(x ** 2 + z ** 2) / np.maximum(stem_r, 1e-3))
    stem = stem * smoothstep(-0.5, -0.35, y) * smoothstep(cy, cy - 0.15, y) * 0.35
    density = np.clip(ball * (0.55 + 0.9 * (n1 - 0.5)) + stem * n2, 0.0, None)
    t_max = 2600.0 - 900.0 * t
    core = smoothstep(0.8, 0.15, d) * (0.75 + 0.5 * (n2 - 0.5))
    temperature = np.where(core > 0, 900.0 + (t_max - 900.0) * core, 0.0)
    return density.astype(np.float32), np.clip(temperature, 0.0, None).astype(np.float32)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=8, help="number of frames (1..N), default 8")
    ap.add_argument("--resolution", type=int, default=64, help="voxels per side, default 64")
    ap.add_argument("--seed", type=int, default=28)
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent),
                    help="folder for fire_NNNN.npz (default: next to this script)")
    args = ap.parse_args(argv)
    if not (1 <= args.frames <= 10000 and 8 <= args.resolution <= 512):
        ap.error("--frames must be 1..10000 and --resolution 8..512")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    noise = [smooth_noise(args.resolution, 0.08, rng), smooth_noise(args.resolution, 0.03, rng)]
    for f in range(1, args.frames + 1):
        t = (f - 1) / max(args.frames - 1, 1)
        density, temperature = make_frame(t, args.resolution, noise, 0.35)
        np.savez_compressed(out / f"fire_{f:04d}.npz", density=density, temperature=temperature,
                            bbox_min=np.full(3, -0.5), bbox_max=np.full(3, 0.5))
    print(f"wrote {args.frames} frames ({args.resolution}^3) to {out}/fire_0001.npz ..")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
