"""Direction sets on the unit sphere: an even spread (Fibonacci lattice) and barycentric
interpolation between such directions. Used by the network's directional cache
(clvol/render/ms/network.py) and the environment's sky directions (environment.py)."""
from __future__ import annotations

import functools
import math

import numpy as np


def spherical_barycentric(dirs: np.ndarray, omegas: np.ndarray):
    """For each unit vector in ``omegas`` (N, 3): the three ``dirs`` of the triangle of their
    convex hull that it passes through, and barycentric weights (N, 3) summing to 1 (exact at
    the directions, linear in between on the triangle's plane)."""
    tri = _hull(np.ascontiguousarray(dirs, np.float64).tobytes(), len(dirs))
    inv = np.linalg.inv(np.transpose(dirs[tri], (0, 2, 1)))  # b = inv @ omega per triangle
    b = (omegas @ inv.reshape(-1, 3).T).reshape(len(omegas), -1, 3)
    t = np.argmax(b.min(axis=2), axis=1)
    w = np.maximum(b[np.arange(len(omegas)), t], 0.0)
    return tri[t], w / w.sum(axis=1, keepdims=True)


@functools.lru_cache(maxsize=8)
def _hull(key: bytes, n: int) -> np.ndarray:
    from scipy.spatial import ConvexHull
    return ConvexHull(np.frombuffer(key).reshape(n, 3)).simplices


def fibonacci_directions(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
