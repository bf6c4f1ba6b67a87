"""Procedural density grids: clouds, smoke and smooth solids for translucent materials.

``generate(name, seed=0, resolution=64, **params) -> DensityGrid``; ``GENERATORS`` describes every
generator and its parameters (default, inclusive range, meaning). docs/volumes.md lists them.

Conventions
- +y is up (clouds have their flat base at low y, smoke rises along +y).
- The box is [-0.5, 0.5]^3 for a cubic resolution; for a non-cubic one the voxels stay cubic and
  the longest axis spans [-0.5, 0.5] (a 64x32x64 grid fills [-0.5,0.5] x [-0.25,0.25] x [-0.5,0.5]).
- Lengths given as parameters are world units of that box, except where a parameter says it is
  a fraction of the box or a number of voxels.
- Noise features are placed in world units, so a larger resolution gives the same shape, sharper:
  the same seed at 64^3 and 128^3 gives the same cloud.
- Determinism: every random draw comes from ``numpy.random.Generator(PCG64([seed, stream]))``
  with a fixed stream number per noise layer; no global state. The same call gives a
  bit-identical array (float32 arithmetic in a fixed order, no BLAS).

How the noise is made cheap: all noise is evaluated on the grid of voxel centres, which is a
tensor product of three 1-D coordinate lists. Lattice noise is a sum of lattice values times
per-axis weights, so it is evaluated one axis at a time (2 taps per axis), O(voxels) per octave
whatever the frequency. Gradient (Perlin) noise splits the same way: the dot product
g . (x - corner) is a sum of three terms, each separable. Worley (cellular) noise is evaluated
on a coarser sample grid (4 samples per cell) and interpolated linearly.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from statistics import NormalDist
from typing import Callable

import numpy as np

from ..errors import VolumeError
from .grid import DensityGrid

# Largest grid a generator will make (512 MiB of float32); generation needs several such arrays.
MAX_VOXELS = 512 ** 3
MAX_AXIS = 2048


# --------------------------------------------------------------------------- descriptions

@dataclass(frozen=True)
class Param:
    """One generator parameter: default value and inclusive bounds [lo, hi].

    An int default makes the parameter integer-valued (floats are refused for it).
    """
    default: float | int
    lo: float | int
    hi: float | int
    doc: str

    @property
    def is_int(self) -> bool:
        return isinstance(self.default, int)


@dataclass(frozen=True)
class GeneratorInfo:
    name: str
    doc: str
    parameters: dict[str, Param]
    func: Callable = field(repr=False, compare=False)
    uses_seed: bool = True  # False: a deterministic shape; the seed is accepted and ignored


# --------------------------------------------------------------------------- domain

class _Domain:
    """Voxel-centre coordinates of the grid being generated, per axis (x, y, z)."""

    def __init__(self, res: tuple[int, int, int]):
        self.res = res                                       # (nx, ny, nz)
        self.voxel = 1.0 / max(res)                          # cubic voxels, longest side = 1
        self.extent = np.array(res, dtype=np.float64) * self.voxel
        self.bbox_min = -0.5 * self.extent
        self.bbox_max = 0.5 * self.extent
        # rel[a]: distance of each voxel centre from bbox_min along axis a (>= 0), float64.
        self.rel = [(np.arange(n, dtype=np.float64) + 0.5) * self.voxel for n in res]
        # world[a]: world coordinate of each voxel centre; frac[a]: position in [0, 1] across the box.
        self.world = [self.rel[a] + self.bbox_min[a] for a in range(3)]
        self.frac = [self.rel[a] / self.extent[a] for a in range(3)]

    def axis(self, values: np.ndarray, a: int) -> np.ndarray:
        """A 1-D per-axis array as float32, shaped to broadcast over (nz, ny, nx)."""
        return _along(np.asarray(values, dtype=np.float32), a)

    def empty(self) -> np.ndarray:
        nx, ny, nz = self.res
        return np.zeros((nz, ny, nx), dtype=np.float32)


def _along(values: np.ndarray, a: int) -> np.ndarray:
    """Reshape 1-D values along axis a (0 = x, 1 = y, 2 = z) to broadcast over (nz, ny, nx)."""
    shape = [1, 1, 1]
    shape[2 - a] = -1
    return values.reshape(shape)


def _rng(seed: int, stream: int) -> np.random.Generator:
    # One independent stream per noise layer, so changing e.g. the octave count of one layer
    # does not reshuffle the others.
    return np.random.Generator(np.random.PCG64([seed, stream]))


# --------------------------------------------------------------------------- separable lattice noise

def _apply_axis(arr: np.ndarray, axis: int, i0: np.ndarray, w0: np.ndarray, w1: np.ndarray) -> np.ndarray:
    """out[.., k, ..] = w0[k] * arr[.., i0[k], ..] + w1[k] * arr[.., i0[k] + 1, ..] along ``axis``."""
    shape = [1] * arr.ndim
    shape[axis] = -1
    out = np.take(arr, i0, axis=axis)
    out *= w0.reshape(shape)
    out += np.take(arr, i0 + 1, axis=axis) * w1.reshape(shape)
    return out


def _fade(f: np.ndarray) -> np.ndarray:
    """Perlin's quintic 6f^5 - 15f^4 + 10f^3 (C2 across lattice cells)."""
    return f * f * f * (f * (f * 6.0 - 15.0) + 10.0)


def _perlin(dom: _Domain, rng: np.random.Generator, period: float) -> np.ndarray:
    """3-D gradient noise with lattice spacing ``period`` (world units); values within about +-1.

    The lattice is a function of the box extent and the rng only, not of the resolution.
    """
    offset = rng.random(3)
    sizes, taps = [], []
    for a in range(3):
        u = dom.rel[a] / period + offset[a]
        i0 = np.floor(u).astype(np.intp)
        f = u - i0
        s = _fade(f)
        # value weights (1-s, s); gradient weights (1-s)*f and s*(f-1): the displacement
        # from corner 0 is f, from corner 1 is f - 1.
        taps.append(dict(i0=i0, a=((1 - s).astype(np.float32), s.astype(np.float32)),
                         b=(((1 - s) * f).astype(np.float32), (s * (f - 1)).astype(np.float32))))
        sizes.append(int(math.floor(dom.extent[a] / period + offset[a])) + 2)
    lx, ly, lz = sizes
    g = rng.standard_normal((3, lz, ly, lx), dtype=np.float32)
    g /= np.maximum(np.sqrt((g * g).sum(axis=0)), 1e-12)   # unit gradients
    tx, ty, tz = taps

    def ax(arr, t, kind, axis):
        return _apply_axis(arr, axis, t["i0"], *t[kind])

    # Term for gradient component c uses the gradient kernel 'b' along axis c, values 'a' elsewhere.
    # Grouped so only two passes run over the full-size array (the z passes).
    gx_x = ax(g[0], tx, "b", 2)
    gy_x = ax(g[1], tx, "a", 2)
    gz_x = ax(g[2], tx, "a", 2)
    xy = ax(gx_x, ty, "a", 1)
    xy += ax(gy_x, ty, "b", 1)
    zz = ax(gz_x, ty, "a", 1)
    out = ax(xy, tz, "a", 0)
    out += ax(zz, tz, "b", 0)
    return out


# Octaves whose lattice spacing is below this many voxels are skipped: the grid cannot
# represent them (they would only alias), and their lattices would be huge.
MIN_PERIOD_VOXELS = 2.0


def _fbm(dom: _Domain, seed: int, stream: int, period: float, octaves: int,
         gain: float = 0.5, lacunarity: float = 2.0) -> np.ndarray:
    """Fractal sum of gradient noise, normalised by the amplitude sum (values within about +-1).

    The normalisation counts every requested octave, so skipping octaves too fine for the grid
    removes detail without changing the amplitude of the rest.
    """
    total = dom.empty()
    amp, norm = 1.0, 0.0
    for o in range(octaves):
        p = period / lacunarity ** o
        if p >= MIN_PERIOD_VOXELS * dom.voxel:
            total += np.float32(amp) * _perlin(dom, _rng(seed, stream * 64 + o), p)
        norm += amp
        amp *= gain
    total *= np.float32(1.0 / norm)
    return total


def _worley_f1(dom: _Domain, rng: np.random.Generator, cell: float) -> np.ndarray:
    """Distance to the nearest feature point, in units of ``cell`` (one jittered point per cell).

    Evaluated exactly (27 neighbour cells) on a sample grid with spacing cell/4, or on the voxel
    centres when voxels are coarser than that, then interpolated linearly to the voxel centres.
    """
    offset = rng.random(3)
    spacing = cell / 4.0
    direct = spacing <= dom.voxel
    samples, sizes = [], []
    for a in range(3):
        if direct:
            s = dom.rel[a]
        else:
            s = np.arange(int(math.ceil(dom.extent[a] / spacing)) + 1, dtype=np.float64) * spacing
        samples.append(s)
        sizes.append(int(math.floor(s[-1] / cell + offset[a])) + 1)
    lx, ly, lz = sizes
    # Feature point of cell (i, j, k) at (i, j, k) + jitter; one ring of padding cells so every
    # sample sees its 27 neighbours (array index = cell index + 1).
    jitter = rng.random((3, lz + 2, ly + 2, lx + 2), dtype=np.float32)
    u = [(samples[a] / cell + offset[a]) for a in range(3)]
    ci = [np.floor(u[a]).astype(np.intp) for a in range(3)]
    frac = [(u[a] - ci[a]).astype(np.float32) for a in range(3)]   # position within its cell
    shape = (len(samples[2]), len(samples[1]), len(samples[0]))
    best = np.full(shape, np.inf, dtype=np.float32)
    for oz, oy, ox in itertools.product((-1, 0, 1), repeat=3):
        iz, iy, ix = ci[2] + oz + 1, ci[1] + oy + 1, ci[0] + ox + 1
        d2 = None
        for a, o in ((0, ox), (1, oy), (2, oz)):
            j = jitter[a].take(iz, axis=0).take(iy, axis=1).take(ix, axis=2)
            # displacement from the sample to the feature point, in cell units
            d = j + (np.float32(o) - _along(frac[a], a))
            d *= d
            d2 = d if d2 is None else d2 + d
        np.minimum(best, d2, out=best)
    f1 = np.sqrt(best)
    if direct:
        return f1
    for a in range(3):
        # linear interpolation from the sample grid to the voxel centres along axis a
        t = dom.rel[a] / spacing
        i0 = np.minimum(np.floor(t).astype(np.intp), len(samples[a]) - 2)
        w1 = (t - i0).astype(np.float32)
        f1 = _apply_axis(f1, 2 - a, i0, 1 - w1, w1)
    return f1


def _worley_fbm(dom: _Domain, seed: int, stream: int, cell: float, octaves: int) -> np.ndarray:
    """Billowy cellular noise in [0, 1]: fractal sum of (1 - F1), high at the cell centres."""
    total = dom.empty()
    amp, norm = 1.0, 0.0
    for o in range(octaves):
        c = cell / 2.0 ** o
        if c >= MIN_PERIOD_VOXELS * dom.voxel:
            f1 = _worley_f1(dom, _rng(seed, stream * 64 + o), c)
            total += np.float32(amp) * np.clip(1.0 - f1, 0.0, 1.0)
        else:
            total += np.float32(amp * 0.5)   # the mean of a cell layer too fine to resolve
        norm += amp
        amp *= 0.5
    total *= np.float32(1.0 / norm)
    return total


# --------------------------------------------------------------------------- shaping helpers

def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    """Hermite step from 0 at e0 to 1 at e1 (e1 < e0 gives a falling step)."""
    t = np.clip((x - np.float32(e0)) * np.float32(1.0 / (e1 - e0)), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _box_taper(dom: _Domain, margin: float = 0.04) -> np.ndarray:
    """1 inside, falling smoothly to 0 over the outer ``margin`` (fraction of the box) on every face.

    Keeps clouds and smoke from ending in a flat wall at the box faces: the outermost voxel
    layer (centre half a voxel from the face) is exactly 0.
    """
    out = np.float32(1.0)
    for a in range(3):
        dist = np.minimum(dom.rel[a], dom.extent[a] - dom.rel[a])   # to the nearer face
        lo = 0.5 * dom.voxel + 1e-9 * dom.extent[a]
        w = _smoothstep(lo, lo + margin * dom.extent[a], dist)
        out = out * dom.axis(w, a)
    return out


def _solid_density(dom: _Domain, sdf: np.ndarray, density: float, edge: float) -> np.ndarray:
    """Density from a signed distance (world units, < 0 inside): a smoothstep ``edge`` voxels wide."""
    half = 0.5 * edge * dom.voxel
    return (np.float32(density) * _smoothstep(half, -half, sdf)).astype(np.float32)


def _centred(dom: _Domain):
    """Voxel-centre coordinates relative to the box centre, broadcastable (x, y, z)."""
    return tuple(dom.axis(dom.world[a], a) for a in range(3))


# --------------------------------------------------------------------------- generators

# Amplitude of the (unit-deviation) billow noise against the envelope, which falls from 1 on the
# axis to 0 at its edge; chosen by eye from renders of the optical depth.
_CLOUD_BILLOW = 0.45


def _cloud(dom: _Domain, seed: int, *, coverage, base, top, width, scale, octaves, worley,
           detail, density) -> np.ndarray:
    if top < base + 0.1:
        raise VolumeError(
            f"generator 'cloud': top = {top!r} must be at least base + 0.1 = {base + 0.1!r}")
    # Envelope `shape`: a column over the lowest 20% of the cloud's height, capped by a
    # half-ellipsoid above; > 0 inside, 1 on the axis at the base, 0 on the surface.
    qx = dom.axis(2 * dom.frac[0] - 1, 0)
    qz = dom.axis(2 * dom.frac[2] - 1, 2)
    h = (dom.frac[1] - base) / (top - base)                  # 0 at the base, 1 at the top
    cap = np.maximum(h - 0.2, 0.0) / 0.8
    # slightly narrower at the base than in the body, as the bulges above overhang it
    rad = width * (0.85 + 0.15 * _smoothstep(0.0, 0.25, h))
    r2 = qx * qx + qz * qz
    shape = dom.axis(1.0 - cap * cap, 1) - r2 * dom.axis(1.0 / (rad * rad), 1)

    # Billow noise: gradient fBm mixed with cellular (Worley) billows. Billows grow towards
    # the top (cumulus towers) and are weak at the flat base.
    # Both noises normalised to zero mean and unit-ish standard deviation (measured: the fBm
    # has std ~0.11, the cellular fBm mean ~0.48 and std ~0.10).
    grad = _fbm(dom, seed, 1, scale, octaves) * np.float32(1 / 0.11)
    cells = (_worley_fbm(dom, seed, 2, scale, 3) - np.float32(0.48)) * np.float32(1 / 0.10)
    noise = np.float32(1.0 - worley) * grad + np.float32(worley) * cells
    amp = dom.axis(_CLOUD_BILLOW * (0.35 + 0.65 * np.clip(h, 0.0, 1.0)), 1)
    f = shape + amp * noise

    # coverage 0.5 puts the surface near the envelope; more coverage grows the cloud.
    threshold = 1.0 - 2.0 * coverage
    d = _smoothstep(threshold, threshold + 0.3, f)
    # Flat base: a sharp rise over the lowest 4% of the cloud's height.
    d *= dom.axis(_smoothstep(0.0, 0.04, h), 1)
    if detail > 0:
        # Erode the soft edges with fine noise; the saturated interior (d = 1) is kept.
        # ero <= detail <= 0.95, so the division below is by at least 0.05.
        ero = np.float32(detail) * np.clip(0.5 + 0.5 * _fbm(dom, seed, 3, scale / 4.0, 3), 0.0, 1.0)
        d = np.clip((d - ero) / (1.0 - ero), 0.0, 1.0)
    d *= _box_taper(dom)
    return np.float32(density) * d


def _smoke(dom: _Domain, seed: int, *, radius, spread, turbulence, scale, octaves, fade, drift,
           density) -> np.ndarray:
    x, y, z = _centred(dom)
    y_src = dom.bbox_min[1] + 0.08 * dom.extent[1]          # source a little above the floor
    s0 = y - np.float32(y_src)                               # height above the source
    r_here = np.float32(radius) + np.float32(spread) * np.maximum(s0, 0.0)
    # Noise advection: displace the lookup by a vector fBm scaled by the local plume radius,
    # laminar at the source and fully turbulent a few radii up.
    onset = _smoothstep(0.0, 0.3 * dom.extent[1], s0)
    # 1 / 0.11 brings the fBm to unit standard deviation (measured), so `turbulence` is the
    # typical displacement in plume radii.
    amp = np.float32(turbulence / 0.11) * r_here * onset
    px = x + amp * _fbm(dom, seed, 1, scale, octaves)
    py = y + amp * _fbm(dom, seed, 2, scale, octaves)
    pz = z + amp * _fbm(dom, seed, 3, scale, octaves)
    s = py - np.float32(y_src)
    r = np.float32(radius) + np.float32(spread) * np.maximum(s, 0.0)
    dx = px - np.float32(drift) * np.maximum(s, 0.0)        # wind drift along +x
    q2 = (dx * dx + pz * pz) / (r * r)
    profile = np.clip(1.0 - q2, 0.0, 1.0) ** 2
    # Thinning as the plume widens (fade 2 conserves mass), a soft start at the source.
    d = profile * (np.float32(radius) / r) ** np.float32(fade)
    d *= _smoothstep(-radius, radius, s)
    # Puffs: modulate by turbulence at the displaced point's neighbourhood.
    # (capped at 1.5 so the peak stays within 1.5 x `density`)
    puffs = np.clip(1.0 + (0.5 / 0.11) * _fbm(dom, seed, 4, scale * 0.5, octaves), 0.0, 1.5)
    d *= puffs
    d *= _box_taper(dom)
    return (np.float32(density) * d).astype(np.float32)


def _sphere(dom: _Domain, seed: int, *, radius, density, edge) -> np.ndarray:
    x, y, z = _centred(dom)
    sdf = np.sqrt(x * x + y * y + z * z) - np.float32(radius)
    return _solid_density(dom, sdf, density, edge)


def _box(dom: _Domain, seed: int, *, width, height, depth, rounding, density, edge) -> np.ndarray:
    smallest = min(width, height, depth)
    if rounding > 0.5 * smallest:
        raise VolumeError(
            f"generator 'box': rounding = {rounding!r} is more than half the smallest side "
            f"({0.5 * smallest!r})")
    x, y, z = _centred(dom)
    half = np.array([width, height, depth]) / 2.0 - rounding
    qx = np.abs(x) - np.float32(half[0])
    qy = np.abs(y) - np.float32(half[1])
    qz = np.abs(z) - np.float32(half[2])
    ox, oy, oz = np.maximum(qx, 0), np.maximum(qy, 0), np.maximum(qz, 0)
    outside = np.sqrt(ox * ox + oy * oy + oz * oz)
    inside = np.minimum(np.maximum(np.maximum(qx, qy), qz), 0.0)
    return _solid_density(dom, outside + inside - np.float32(rounding), density, edge)


def _torus(dom: _Domain, seed: int, *, major, minor, density, edge) -> np.ndarray:
    x, y, z = _centred(dom)
    ring = np.sqrt(x * x + z * z) - np.float32(major)       # lies in the xz plane, axis +y
    sdf = np.sqrt(ring * ring + y * y) - np.float32(minor)
    return _solid_density(dom, sdf, density, edge)


def _blob(dom: _Domain, seed: int, *, count, radius, blend, wobble, density, edge) -> np.ndarray:
    rng = _rng(seed, 0)
    # Balls of radius 0.6..1.2 x `radius`, each one attached to a random earlier one so that
    # they overlap (centre distance 0.7 x the sum of radii): the lump is always connected.
    radii = radius * rng.uniform(0.6, 1.2, count)
    centres = np.zeros((count, 3))
    for i in range(1, count):
        j = int(rng.integers(i))
        d = rng.standard_normal(3)
        d /= max(float(np.linalg.norm(d)), 1e-12)
        centres[i] = centres[j] + d * 0.7 * (radii[i] + radii[j])
    # Centre the lump's bounding box on the box centre.
    centres -= 0.5 * ((centres - radii[:, None]).min(axis=0) + (centres + radii[:, None]).max(axis=0))
    x, y, z = _centred(dom)

    def ball_distance(i):
        c = centres[i]
        dx, dy, dz = x - np.float32(c[0]), y - np.float32(c[1]), z - np.float32(c[2])
        return np.sqrt(dx * dx + dy * dy + dz * dz) - np.float32(radii[i])

    # Smooth union of the balls: -blend * log(sum exp(-d_i / blend)), shifted by the minimum
    # so no exp underflows to a log(0). Distances are recomputed in the second pass rather
    # than kept, so memory stays a few grids whatever the ball count.
    dmin = ball_distance(0)
    for i in range(1, count):
        np.minimum(dmin, ball_distance(i), out=dmin)
    acc = dom.empty()
    for i in range(count):
        acc += np.exp((dmin - ball_distance(i)) * np.float32(1.0 / blend))
    sdf = dmin - np.float32(blend) * np.log(acc)             # acc >= 1, so the log is finite
    if wobble > 0:
        # Low-frequency surface perturbation (features about 3 ball radii across).
        sdf += np.float32(wobble) * _fbm(dom, seed, 1, 3.0 * radius, 2)
    return _solid_density(dom, sdf, density, edge)


def _stratus(dom: _Domain, seed: int, *, layers, thickness, coverage, scale, octaves, detail,
             density) -> np.ndarray:
    """Horizontal sheets across the box: each layer a vertical tent profile (1 at its mid-height,
    0 at half its thickness away), carved by fBm that is flattened (stretched 3x along x and z)
    so the sheets break into wide patches rather than towers."""
    rng = _rng(seed, 0)
    # Layer mid-heights spread over the box height, the lowest at 0.2-0.4, others above it.
    mids = np.sort(rng.uniform(0.2, 0.8, layers))
    thick = thickness * rng.uniform(0.7, 1.3, layers)
    fy = dom.frac[1]
    prof = np.zeros_like(fy)
    for m, t in zip(mids, thick):
        prof = np.maximum(prof, 1.0 - np.abs(fy - m) / (0.5 * t))
    prof = dom.axis(np.clip(prof, 0.0, 1.0), 1)
    # Flattened noise: a horizontal period 3x the vertical one, from two octave sets.
    wide = _fbm(dom, seed, 1, 3.0 * scale, octaves) * np.float32(1 / 0.11)
    fine = _fbm(dom, seed, 2, scale, max(octaves - 1, 1)) * np.float32(1 / 0.11)
    noise = np.float32(0.7) * wide + np.float32(0.3) * fine
    f = prof + np.float32(0.35) * noise
    threshold = 1.0 - 1.6 * coverage
    d = _smoothstep(threshold, threshold + 0.35, f)
    if detail > 0:
        ero = np.float32(detail) * np.clip(0.5 + 0.5 * _fbm(dom, seed, 3, scale / 4.0, 3), 0.0, 1.0)
        d = np.clip((d - ero) / (1.0 - ero), 0.0, 1.0)
    d *= _box_taper(dom, 0.08)
    return (np.float32(density) * d).astype(np.float32)


def _noise(dom: _Domain, seed: int, *, scale, octaves, gain, coverage, softness, density) -> np.ndarray:
    """Thresholded fractal (fBm) noise filling the box: heterogeneous media with no envelope."""
    n = _fbm(dom, seed, 1, scale, octaves, gain=gain)
    # Normalise by the field's own deviation so `coverage` means about the same at any gain
    # and octave count; the threshold is the (1 - coverage) quantile of a normal field.
    n = (n - n.mean(dtype=np.float64)) / max(float(n.std(dtype=np.float64)), 1e-6)
    thr = NormalDist().inv_cdf(min(max(1.0 - coverage, 1e-3), 1.0 - 1e-3))
    d = _smoothstep(thr - 0.5 * softness, thr + 0.5 * softness, n.astype(np.float32))
    d *= _box_taper(dom, 0.06)
    return (np.float32(density) * d).astype(np.float32)


def _union(dom: _Domain, seed: int, *, count, size, blend, density, edge) -> np.ndarray:
    """Union of random primitives (spheres, rounded boxes, tori, capsules), each at a random
    position with a random principal axis; hard union (min) for blend 0, else a polynomial
    smooth minimum of width ``blend``."""
    rng = _rng(seed, 0)
    x, y, z = _centred(dom)
    sdf = None
    for i in range(count):
        kind = int(rng.integers(4))
        c = rng.uniform(-0.5 + 1.2 * size, 0.5 - 1.2 * size, 3) if size < 0.4 else np.zeros(3)
        axis = int(rng.integers(3))
        s = size * rng.uniform(0.6, 1.0)
        p = [x - np.float32(c[0]), y - np.float32(c[1]), z - np.float32(c[2])]
        # rotate the frame so the primitive's main axis is `axis` (cyclic permutation)
        p = p[axis:] + p[:axis]
        if kind == 0:      # sphere
            d = np.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]) - np.float32(s)
        elif kind == 1:    # rounded box, sides 0.8-2 x s
            half = s * rng.uniform(0.4, 1.0, 3)
            r = np.float32(0.3 * half.min())
            q = [np.abs(p[a]) - np.float32(half[a] - r) for a in range(3)]
            o = [np.maximum(qa, 0) for qa in q]
            d = (np.sqrt(o[0] * o[0] + o[1] * o[1] + o[2] * o[2])
                 + np.minimum(np.maximum(np.maximum(q[0], q[1]), q[2]), 0.0) - r)
        elif kind == 2:    # torus around the first axis
            minor = s * rng.uniform(0.2, 0.4)
            ring = np.sqrt(p[1] * p[1] + p[2] * p[2]) - np.float32(s - minor)
            d = np.sqrt(ring * ring + p[0] * p[0]) - np.float32(minor)
        else:              # capsule along the first axis
            rad = s * rng.uniform(0.25, 0.5)
            h = np.float32(s - rad)
            a0 = np.clip(p[0], -h, h)
            dx = p[0] - a0
            d = np.sqrt(dx * dx + p[1] * p[1] + p[2] * p[2]) - np.float32(rad)
        if sdf is None:
            sdf = d
        elif blend > 0:
            k = np.float32(blend)
            hmix = np.clip(0.5 + 0.5 * (d - sdf) / k, 0.0, 1.0)
            sdf = sdf * hmix + d * (1 - hmix) - k * hmix * (1 - hmix)
        else:
            sdf = np.minimum(sdf, d)
    return _solid_density(dom, sdf, density, edge)


# The two generators below exist to MEASURE generalisation: the data sets keep their families
# (clvol/training/dataset.py OUT_OF_FAMILY) out of every training set. They follow published
# descriptions rather than our own cloud generator, so their density structure differs: soft,
# graded interiors (Perlin-Worley) and pyroclastic, displaced surfaces (sphere unions).

def _remap(x, lo0, hi0, lo1, hi1):
    """Linear remap of x from [lo0, hi0] to [lo1, hi1] (the Nubis talks' workhorse); lo0 and
    hi0 may be arrays. The span is kept away from zero."""
    return lo1 + (x - lo0) * (hi1 - lo1) / np.maximum(hi0 - lo0, np.float32(1e-4))


def _perlin_worley(dom: _Domain, seed: int, *, coverage, cloud_type, scale, erosion, width,
                   density) -> np.ndarray:
    """A cloud after Schneider's Nubis (SIGGRAPH 2015/2017 Advances talks): low-frequency
    Perlin-Worley noise (gradient fBm dilated by cellular fBm), shaped by a height gradient
    chosen by the cloud type (stratus ... cumulus), cut by a coverage footprint, then eroded by
    high-frequency cellular noise that is wispy at the base and billowy above. Unlike
    ``cloud``, density is not saturated: it grows gradually into the interior."""
    h = dom.frac[1]
    # height gradient: a trapezoid whose top rises with the type (stratus low and thin,
    # cumulus tall); the base is a quick rise, as in the talks' three blended gradients
    top = 0.3 + 0.65 * cloud_type
    grad = _smoothstep(0.05, 0.05 + 0.1 * (0.4 + cloud_type), h) * _smoothstep(top, top - 0.25 * (0.4 + cloud_type), h)
    grad = dom.axis(np.clip(grad, 0.0, 1.0), 1)
    # footprint (the weather map of one cloud): radial falloff in x-z, wobbled by 2-D-ish noise
    qx = dom.axis(2 * dom.frac[0] - 1, 0)
    qz = dom.axis(2 * dom.frac[2] - 1, 2)
    wob = _fbm(dom, seed, 4, 2.0 * scale, 2) * np.float32(1 / 0.11)
    foot = np.clip(1.0 - np.sqrt(qx * qx + qz * qz) / np.float32(width) + np.float32(0.12) * wob, 0.0, 1.0)
    cov = np.float32(coverage) * np.sqrt(foot)
    # Perlin-Worley: perlin in [0, 1], dilated by the inverted Worley fBm
    perlin = np.clip(0.5 + 0.5 * _fbm(dom, seed, 1, scale, 4) * np.float32(1 / 0.3), 0.0, 1.0)
    w1 = _worley_fbm(dom, seed, 2, scale, 1)
    w2 = _worley_fbm(dom, seed, 3, scale / 2.0, 1)
    w3 = _worley_fbm(dom, seed, 5, scale / 4.0, 1)
    wfbm = np.float32(0.625) * w1 + np.float32(0.25) * w2 + np.float32(0.125) * w3
    base = np.clip(_remap(perlin, -(1.0 - wfbm), 1.0, 0.0, 1.0), 0.0, 1.0)
    base = np.clip(_remap(base * grad, 1.0 - cov, 1.0, 0.0, 1.0), 0.0, 1.0) * cov
    # erosion: high-frequency cellular fBm, wispy (inverted) near the base, billowy above
    hf = _worley_fbm(dom, seed, 6, scale / 4.0, 3)
    mix = dom.axis(np.clip(h * 6.0, 0.0, 1.0), 1)
    detail = hf * mix + (1.0 - hf) * (1.0 - mix)
    d = np.clip(_remap(base, np.float32(erosion) * detail * np.float32(0.35), 1.0, 0.0, 1.0), 0.0, 1.0)
    d *= _box_taper(dom)
    peak = float(d.max())
    return (np.float32(density / peak if peak > 0 else 0.0) * d).astype(np.float32)


def _sphere_cumulus(dom: _Domain, seed: int, *, count, size, displacement, erosion, base,
                    density) -> np.ndarray:
    """A cumulus modelled as a union of spheres (a wide cluster on a flat base, smaller ones
    stacked above, as in the classic particle/implicit cloud modelling), its signed distance
    displaced outward by billowed fBm (|gradient noise|: pyroclastic puffs), a flat base, and
    its soft edge eroded by finer billowed noise."""
    rng = _rng(seed, 0)
    x, y, z = _centred(dom)
    y0 = float(dom.bbox_min[1] + base * dom.extent[1])     # the flat base
    sdf = None
    for i in range(count):
        tier = i / max(count - 1, 1)                         # 0: bottom ring, 1: top
        r = size * (1.0 - 0.45 * tier) * rng.uniform(0.75, 1.15)
        spread = (0.42 - 0.25 * tier) * rng.uniform(0.3, 1.0)
        ang = rng.uniform(0.0, 2.0 * np.pi)
        cx, cz = spread * np.cos(ang), spread * np.sin(ang)
        cy = y0 + 0.6 * r + tier * rng.uniform(0.25, 0.55) * dom.extent[1]
        cy = min(cy, float(dom.bbox_max[1]) - 1.05 * r)
        d = np.sqrt((x - np.float32(cx)) ** 2 + (y - np.float32(cy)) ** 2 + (z - np.float32(cz)) ** 2) - np.float32(r)
        sdf = d if sdf is None else np.minimum(sdf, d)
    billow = np.abs(_fbm(dom, seed, 1, 1.5 * size, 4)) * np.float32(1 / 0.11)
    sdf = sdf - np.float32(displacement * size * 0.5) * billow
    # soft edge a few percent of the cloud's size, density ramping in over it
    edge = np.float32(0.12 * size)
    d = _smoothstep(float(edge), float(-edge), sdf)
    d *= dom.axis(_smoothstep(y0 - 0.01, y0 + 0.03, dom.world[1]), 1)   # flat base
    if erosion > 0:
        fine = np.abs(_fbm(dom, seed, 2, 0.4 * size, 3)) * np.float32(1 / 0.11)
        ero = np.clip(np.float32(erosion) * np.float32(0.5) * fine, 0.0, 0.95)
        d = np.clip((d - ero) / (1.0 - ero), 0.0, 1.0)
    d *= _box_taper(dom)
    return (np.float32(density) * d).astype(np.float32)


_DENSITY = Param(1.0, 1e-3, 1e3, "peak density (extinction = density x density_scale)")
_EDGE = Param(1.5, 0.25, 16.0, "width of the soft surface in voxels (smoothstep of the signed distance)")

GENERATORS: dict[str, GeneratorInfo] = {g.name: g for g in [
    GeneratorInfo(
        "cloud",
        "A single cumulus cloud: a column capped by a dome, carved by gradient-noise fBm mixed "
        "with Worley cellular billows (stronger towards the top), with a flat base, edges eroded "
        "by fine noise, and density saturating at `density` inside.",
        {
            "coverage": Param(0.5, 0.0, 1.0, "how much of the envelope is filled; 0.5 fills it, 1 overflows it, 0 is almost empty"),
            "base": Param(0.15, 0.0, 0.8, "height of the flat base, as a fraction of the box height"),
            "top": Param(0.9, 0.1, 1.0, "height of the top, as a fraction of the box height (>= base + 0.1)"),
            "width": Param(0.75, 0.1, 1.0, "radius of the envelope, as a fraction of the box's half-width in x and z"),
            "scale": Param(0.25, 0.02, 1.0, "size of the largest billows (lattice spacing of the first octave), world units"),
            "octaves": Param(5, 1, 8, "octaves of gradient noise (each half the size of the previous)"),
            "worley": Param(0.6, 0.0, 1.0, "weight of cellular (billowy) noise against gradient noise"),
            "detail": Param(0.35, 0.0, 0.95, "erosion of the soft edges by fine noise (0 = none)"),
            "density": _DENSITY,
        },
        _cloud),
    GeneratorInfo(
        "smoke",
        "A rising plume: a round source near the floor whose radius grows linearly with height "
        "and whose density thins as it spreads; the shape is advected by vector gradient noise "
        "(laminar at the source, turbulent higher up) and broken into puffs by a second noise.",
        {
            "radius": Param(0.05, 0.01, 0.3, "radius of the source, world units"),
            "spread": Param(0.3, 0.0, 1.5, "growth of the radius per unit of height"),
            "turbulence": Param(0.45, 0.0, 2.0, "noise displacement, in units of the local plume radius"),
            "scale": Param(0.2, 0.02, 1.0, "size of the largest eddies, world units"),
            "octaves": Param(4, 1, 8, "octaves of the displacement noise"),
            "fade": Param(1.0, 0.0, 3.0, "density falls as (source radius / radius)^fade; 2 conserves mass"),
            "drift": Param(0.0, -1.0, 1.0, "sideways drift along +x per unit of height (wind)"),
            "density": Param(1.0, 1e-3, 1e3, "density on the axis at the source; puffs vary it "
                             "between 0 and 1.5 x this"),
        },
        _smoke),
    GeneratorInfo(
        "sphere",
        "A sphere at the box centre with a soft surface.",
        {"radius": Param(0.35, 0.01, 1.0, "radius, world units"), "density": _DENSITY, "edge": _EDGE},
        _sphere, uses_seed=False),
    GeneratorInfo(
        "box",
        "An axis-aligned box with rounded edges and corners at the box centre, with a soft surface.",
        {
            "width": Param(0.6, 0.02, 1.0, "side length along x, world units"),
            "height": Param(0.6, 0.02, 1.0, "side length along y, world units"),
            "depth": Param(0.6, 0.02, 1.0, "side length along z, world units"),
            "rounding": Param(0.08, 0.0, 0.5, "radius of the rounded edges (<= half the smallest side)"),
            "density": _DENSITY,
            "edge": _EDGE,
        },
        _box, uses_seed=False),
    GeneratorInfo(
        "torus",
        "A torus around the y axis (lying in the xz plane) at the box centre, with a soft surface.",
        {
            "major": Param(0.28, 0.01, 0.5, "distance from the centre to the middle of the tube, world units"),
            "minor": Param(0.1, 0.005, 0.5, "radius of the tube, world units"),
            "density": _DENSITY,
            "edge": _EDGE,
        },
        _torus, uses_seed=False),
    GeneratorInfo(
        "blob",
        "An organic lump: a smooth union of overlapping balls (metaballs) in a random connected "
        "cluster centred in the box, its surface perturbed by low-frequency gradient noise, with a "
        "soft surface.",
        {
            "count": Param(7, 1, 32, "number of balls (the lump grows with it)"),
            "radius": Param(0.13, 0.02, 0.5, "typical ball radius (each is 0.6-1.2 times this), world units"),
            "blend": Param(0.04, 0.005, 0.3, "width of the smooth union between balls, world units"),
            "wobble": Param(0.03, 0.0, 0.2, "amplitude of the noise perturbing the surface, world units"),
            "density": _DENSITY,
            "edge": _EDGE,
        },
        _blob),
    GeneratorInfo(
        "stratus",
        "Layered stratus: one to three horizontal sheets across the box, each a soft slab broken "
        "into wide patches by horizontally stretched fBm, edges eroded by fine noise.",
        {
            "layers": Param(2, 1, 3, "number of sheets (mid-heights drawn from the seed, 0.2-0.8 of the box height)"),
            "thickness": Param(0.15, 0.03, 0.5, "typical sheet thickness, fraction of the box height (each 0.7-1.3 x this)"),
            "coverage": Param(0.6, 0.0, 1.0, "how much of each sheet is filled (0 almost empty, 1 solid)"),
            "scale": Param(0.15, 0.02, 1.0, "vertical size of the patches, world units (3x wider horizontally)"),
            "octaves": Param(4, 1, 8, "octaves of gradient noise"),
            "detail": Param(0.25, 0.0, 0.95, "erosion of the soft edges by fine noise (0 = none)"),
            "density": _DENSITY,
        },
        _stratus),
    GeneratorInfo(
        "noise",
        "Fractal noise: gradient-noise fBm over the whole box, thresholded at a quantile so that "
        "about `coverage` of the box is filled, with a soft transition and a taper at the faces.",
        {
            "scale": Param(0.3, 0.02, 1.0, "size of the largest features (first octave's lattice spacing), world units"),
            "octaves": Param(5, 1, 8, "octaves of gradient noise"),
            "gain": Param(0.5, 0.2, 0.8, "amplitude ratio of successive octaves (higher = rougher)"),
            "coverage": Param(0.35, 0.02, 0.98, "fraction of the box above the threshold, before the face taper"),
            "softness": Param(0.8, 0.05, 4.0, "width of the transition, in standard deviations of the noise"),
            "density": _DENSITY,
        },
        _noise),
    GeneratorInfo(
        "union",
        "An SDF union of random primitives (spheres, rounded boxes, tori, capsules) at random "
        "positions and axes, hard (min) or smoothly blended, with a soft surface.",
        {
            "count": Param(4, 1, 12, "number of primitives"),
            "size": Param(0.18, 0.03, 0.45, "typical primitive radius / half-size (each 0.6-1 x this), world units"),
            "blend": Param(0.0, 0.0, 0.2, "width of the smooth union, world units (0 = hard union)"),
            "density": _DENSITY,
            "edge": _EDGE,
        },
        _union),
    GeneratorInfo(
        "perlin_worley",
        "A cloud after the Nubis talks (Schneider): low-frequency Perlin-Worley noise shaped by a "
        "height gradient of the cloud type, cut by a coverage footprint and eroded by cellular noise "
        "(wispy at the base, billowy above); graded, unsaturated interior. Kept out of training: "
        "it measures generalisation (docs/neural.md).",
        {
            "coverage": Param(0.7, 0.05, 1.0, "coverage at the footprint's centre (the weather map's value)"),
            "cloud_type": Param(0.8, 0.0, 1.0, "height gradient: 0 stratus (low, thin) .. 1 cumulus (tall)"),
            "scale": Param(0.35, 0.05, 1.0, "size of the largest Perlin-Worley features, world units"),
            "erosion": Param(0.6, 0.0, 1.0, "strength of the high-frequency erosion"),
            "width": Param(0.85, 0.2, 1.0, "footprint radius, fraction of the box's half-width"),
            "density": Param(1.0, 1e-3, 1e3, "peak density (the field is normalised to this)"),
        },
        _perlin_worley),
    GeneratorInfo(
        "sphere_cumulus",
        "A cumulus as a union of spheres (a wide cluster on a flat base, smaller ones stacked "
        "above) displaced by billowed fBm (pyroclastic puffs), with its soft edge eroded by finer "
        "billowed noise. Kept out of training: it measures generalisation (docs/neural.md).",
        {
            "count": Param(9, 2, 24, "number of spheres"),
            "size": Param(0.2, 0.05, 0.35, "radius of the base spheres, world units (upper ones smaller)"),
            "displacement": Param(0.5, 0.0, 1.5, "outward displacement by billowed noise, in sphere radii / 2"),
            "erosion": Param(0.3, 0.0, 1.0, "erosion of the soft edge by finer billowed noise"),
            "base": Param(0.15, 0.0, 0.5, "height of the flat base, fraction of the box height"),
            "density": _DENSITY,
        },
        _sphere_cumulus),
]}


# --------------------------------------------------------------------------- entry point

def _check_resolution(resolution) -> tuple[int, int, int]:
    def is_int(v):
        return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))
    if is_int(resolution):
        res = (int(resolution),) * 3
    elif isinstance(resolution, (tuple, list)) and len(resolution) == 3 and all(map(is_int, resolution)):
        res = tuple(int(v) for v in resolution)
    else:
        raise VolumeError(
            f"resolution must be an integer or three integers (nx, ny, nz), got {resolution!r}")
    if min(res) < 1 or max(res) > MAX_AXIS:
        raise VolumeError(f"resolution {res} (nx, ny, nz): every axis must be in [1, {MAX_AXIS}]")
    if res[0] * res[1] * res[2] > MAX_VOXELS:
        raise VolumeError(
            f"resolution {res} (nx, ny, nz) has {res[0] * res[1] * res[2]} voxels; the limit is "
            f"{MAX_VOXELS} (512^3)")
    return res


def _check_params(info: GeneratorInfo, params: dict) -> dict:
    allowed = ", ".join(f"{k} [{p.lo}, {p.hi}]" for k, p in info.parameters.items())
    unknown = sorted(set(params) - set(info.parameters))
    if unknown:
        raise VolumeError(
            f"generator {info.name!r}: unknown parameter(s) {', '.join(unknown)}; allowed: {allowed}")
    values = {}
    for key, p in info.parameters.items():
        v = params.get(key, p.default)
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise VolumeError(
                f"generator {info.name!r}: parameter {key} = {v!r} must be a number in [{p.lo}, {p.hi}]")
        if p.is_int:
            if not (isinstance(v, (int, np.integer)) or float(v).is_integer()):
                raise VolumeError(
                    f"generator {info.name!r}: parameter {key} = {v!r} must be an integer in "
                    f"[{p.lo}, {p.hi}]")
            v = int(v)
        else:
            v = float(v)
        if not (p.lo <= v <= p.hi):   # also rejects NaN
            raise VolumeError(
                f"generator {info.name!r}: parameter {key} = {v!r} is out of range [{p.lo}, {p.hi}]")
        values[key] = v
    return values


def generate(name: str, seed: int = 0, resolution: int | tuple[int, int, int] = 64, **params) -> DensityGrid:
    """Make a density grid with generator ``name`` (see GENERATORS) at ``resolution`` (nx, ny, nz).

    Raises VolumeError for an unknown generator or parameter, a value out of range, or a bad
    seed/resolution. Same arguments -> bit-identical grid.
    """
    info = GENERATORS.get(name)
    if info is None:
        raise VolumeError(f"unknown generator {name!r}; available: {', '.join(GENERATORS)}")
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise VolumeError(f"generator {name!r}: seed must be an integer >= 0, got {seed!r}")
    res = _check_resolution(resolution)
    values = _check_params(info, params)
    dom = _Domain(res)
    density = info.func(dom, int(seed), **values)
    density = np.ascontiguousarray(np.broadcast_to(density, dom.empty().shape), dtype=np.float32)
    # The shaping keeps values finite and >= 0; DensityGrid re-checks, so a bug cannot pass silently.
    return DensityGrid(density, dom.bbox_min.copy(), dom.bbox_max.copy())


def restructure(grid: DensityGrid, seed: int, *, gamma: float, modulation: float, scale: float) -> DensityGrid:
    """Domain randomisation of a generated grid's density structure (training data sets,
    clvol/training/dataset.py ``augment``): a remap d -> peak * (d / peak)^gamma (gamma > 1 grades
    saturated interiors and thins soft edges, gamma < 1 saturates them) times a low-frequency
    modulation 1 + modulation * fBm (heterogeneous interiors: our generators' clouds and solids are
    homogeneous inside, real clouds are not). Same arguments -> bit-identical grid."""
    d = grid.density.astype(np.float32)
    peak = float(d.max())
    if peak <= 0:
        return grid
    nz, ny, nx = d.shape
    dom = _Domain((nx, ny, nz))
    out = np.float32(peak) * np.power(d * np.float32(1.0 / peak), np.float32(gamma))
    if modulation > 0:
        n = _fbm(dom, seed, 7, scale, 3) * np.float32(1 / 0.11)
        out *= np.clip(1.0 + np.float32(modulation) * n, 0.05, 3.0)
    return DensityGrid(np.ascontiguousarray(out, dtype=np.float32), grid.bbox_min.copy(), grid.bbox_max.copy())
