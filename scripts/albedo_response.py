#!/usr/bin/env python
"""The network's albedo response at the points a camera sees, against path-traced labels.

    python scripts/albedo_response.py SCENE.toml [SCENE.toml ...] [--weights W.npz] [--pixels 24]
        [--paths 256] [--tau 1.0]

For each scene: one point per pixel of a --pixels^2 grid of camera rays, at optical depth --tau
from the camera along the ray (what the image is made of: single scattering is weighted by the
transmittance to the camera); omega toward the camera. At those points the path tracer's
per-order labels (one set of albedo-1 paths, docs/pathtrace.md) give F at any albedo, and the
network predicts F from the train-mode gather (what the data sets store), for a unit sun. Printed,
per albedo 0.8 / 0.9 / 0.96 / 0.99 / 1: sum of predicted F over sum of labels; the response
d log F / d log a over 0.99..1 of both; and the same split by the labels' mean albedo exponent
(low- and high-order halves), and what the network's inputs say about the sun there: the median
optical depth from the point to the sun, and per graded transmittance level (finest first) the
median of the innermost template layer's mean T (the six points around the query; ``levels``):
what the network's transmittance inputs tell it of the sun's distance. The same quantities for the data sets' own point distribution
come from `scripts/train.py DATA X --evaluate W` (docs/neural.md).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ALBEDOS = (0.8, 0.9, 0.96, 0.99, 1.0)


def visible_points(scene, grid, n: int, tau: float):
    """[m][3] points at optical depth ``tau`` along a n x n grid of camera rays (rays that never
    reach it are skipped) and their directions toward the camera."""
    from clvol.training.dataset import depth_points
    cam = scene.camera
    o = np.asarray(cam.origin, np.float64)
    f = np.asarray(cam.target, np.float64) - o
    f /= np.linalg.norm(f)
    r = np.cross(f, np.asarray(cam.up, np.float64))
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    h = np.tan(np.radians(cam.fov_y) / 2)
    s = (2 * (np.arange(n) + 0.5) / n - 1) * h
    sx, sy = np.meshgrid(s * cam.width / cam.height, -s)
    dirs = f + sx.reshape(-1, 1) * r + sy.reshape(-1, 1) * u
    pts, hit = depth_points(grid, scene.medium.density_scale, o, dirs, tau)
    pts = pts[hit]
    om = o - pts
    om /= np.linalg.norm(om, axis=1, keepdims=True)
    return pts, om


def sun_depth(grid, density_scale: float, pts, to_light) -> np.ndarray:
    """[m] optical depth from each point toward the light (``to_light``: the scene's
    ``light.direction``, which points toward the light) to the box's edge, by clvol.training.dataset.depth_points' march: the depth of a
    far target at a huge optical depth is what the march has summed when it leaves the box."""
    from clvol.training.dataset import VISIBLE_STEPS
    lo, hi = np.asarray(grid.bbox_min, np.float64), np.asarray(grid.bbox_max, np.float64)
    d = grid.density.astype(np.float64) * density_scale
    shape = np.array(d.shape[::-1])
    cell = (hi - lo) / shape
    to_sun = np.asarray(to_light, np.float64)
    to_sun /= np.linalg.norm(to_sun)
    with np.errstate(divide="ignore"):
        t0, t1 = (lo - pts) / to_sun, (hi - pts) / to_sun
    tf = np.nanmin(np.maximum(t0, t1), axis=1).clip(0)
    dt = tf / VISIBLE_STEPS
    ts = (np.arange(VISIBLE_STEPS)[None, :] + 0.5) * dt[:, None]
    p = pts[:, None, :] + ts[..., None] * to_sun
    k = np.clip(((p - lo) / cell).astype(np.int64), 0, shape - 1)
    return (d[k[..., 2], k[..., 1], k[..., 0]] * dt[:, None]).sum(1)


def scene_points(scene_path: Path, pixels: int, paths: int, seed: int, base: int = 64,
                 lam: float = 0.6, tau: float = 1.0) -> dict:
    """The visible points of one scene with their labels: {"name", "points", "samples" (the
    train-mode samples at every albedo of ALBEDOS), "score": y -> per-group results} where
    ``score`` takes a model's predicted y for ``samples`` (``base``, ``lam``: the gather's
    contract, the model's)."""
    from clvol.features import layout
    from clvol.kernels.gather import gather
    from clvol.kernels.pyramid import build_pyramid
    from clvol.kernels.transmittance import graded_transmittance
    from clvol.render.pathtrace import point_query_orders
    from clvol.scene import load_scene
    from clvol.training import train as tr

    scene = load_scene(scene_path)
    # a unit sun, as the labels and the network's F are defined
    scene = dataclasses.replace(scene, light=dataclasses.replace(scene.light, irradiance=(1.0, 1.0, 1.0)))
    grid = scene.volume.load()
    pts, om = visible_points(scene, grid, pixels, tau)
    o = point_query_orders(scene, pts, om, paths, seed=seed, grid=grid)
    pyramid = build_pyramid(grid, base)
    l = np.asarray(scene.light.direction, np.float64)
    graded = graded_transmittance(pyramid, scene.medium.density_scale, l, lam=lam)
    g = gather(pyramid, graded, pts, om, l, scene.medium, scene.medium.albedo[0], mode="train")
    arrays = {"features": g["features"], "levels": g["levels"], "config": g["config"],
              "S": o["S"], "M": o["M"], "se": o["se"]}
    S, M = np.asarray(o["S"], np.float64), np.asarray(o["M"], np.float64)
    ebar = np.divide(M.sum(1), S.sum(1), out=np.zeros(len(S)), where=S.sum(1) > 0)
    h = tr.order_samples(arrays, np.tile(np.asarray(ALBEDOS), (len(pts), 1)))
    a = h.config[:, tr.ALBEDO].astype(np.float64)
    F_lab = a ** 4 * np.expm1(h.y.astype(np.float64) - 0.5 * h.var)
    rows = np.asarray(h.row)
    tau_sun = sun_depth(grid, scene.medium.density_scale, pts, l)
    # the innermost template layer (the 6 points around the query): far layers reach outside
    # the medium, where T is 1 by definition
    inner = layout.layer_slices()[0]
    t_inner = np.asarray(g["levels"], np.float64)[:, :, inner].mean(axis=2)     # [m][levels]
    lit = S.sum(1) > 0
    med = float(np.median(ebar[lit])) if lit.any() else 0.0
    groups = (("all", lit), (f"low order (mean exponent < {med:.0f})", lit & (ebar < med)),
              (f"high order (mean exponent >= {med:.0f})", lit & (ebar >= med)))

    def score(y) -> dict:
        F_hat = a ** 4 * np.maximum(np.expm1(np.asarray(y, np.float64)), 0.0)   # the decode's clamp
        out = {}
        for name, keep in groups:
            k = keep[rows]
            sums = {x: (F_hat[k & np.isclose(a, x)].sum(), F_lab[k & np.isclose(a, x)].sum())
                    for x in ALBEDOS}
            slope = (lambda i: np.log(sums[1.0][i] / max(sums[0.99][i], 1e-30)) / -np.log(0.99))
            out[name] = {"ratio": {x: sums[x][0] / max(sums[x][1], 1e-30) for x in ALBEDOS},
                         "label_slope": slope(1), "network_slope": slope(0),
                         "points": int(keep.sum()),
                         "tau_sun": float(np.median(tau_sun[keep])) if keep.any() else 0.0,
                         "t_levels": (np.median(t_inner[keep], axis=0) if keep.any()
                                      else np.zeros(t_inner.shape[1])).tolist()}
        return out
    return {"name": scene_path.stem, "points": int(len(pts)), "samples": h, "score": score}


def response(scene_path: Path, weights: Path, pixels: int, paths: int, tau: float, seed: int) -> dict:
    from clvol.features.weights import load_weights
    from clvol.training import train as tr
    from clvol.training.model import Model
    w = load_weights(weights)
    c = w.meta.get("contract", {})
    sp = scene_points(scene_path, pixels, paths, seed, base=int(c.get("base_resolution", 64)),
                      lam=float(c.get("lambda", 0.6)), tau=tau)
    y = tr.predict(Model.from_weights(w), sp["samples"])
    return {"scene": sp["name"], "points": sp["points"], "groups": sp["score"](y)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--weights", default=str(ROOT / "clvol" / "data" / "weights" / "full_albedo.npz"))
    ap.add_argument("--pixels", type=int, default=24)
    ap.add_argument("--paths", type=int, default=256)
    ap.add_argument("--tau", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    print(f"weights {args.weights}; {args.pixels}^2 camera rays, points at optical depth {args.tau} "
          f"from the camera; {args.paths} paths per label")
    print("| scene | points | group | " + " | ".join(f"a = {x}" for x in ALBEDOS) +
          " | d log F / d log a (0.99..1): labels / network | optical depth to the sun | inner T per level, finest first |")
    print("|---|---|---|" + "---|" * len(ALBEDOS) + "---|---|---|")
    for s in args.scenes:
        r = response(Path(s), Path(args.weights), args.pixels, args.paths, args.tau, args.seed)
        for name, gr in r["groups"].items():
            print(f"| {r['scene']} | {gr['points']} | {name} | " +
                  " | ".join(f"{gr['ratio'][x]:.3f}" for x in ALBEDOS) +
                  f" | {gr['label_slope']:.1f} / {gr['network_slope']:.1f} | {gr['tau_sun']:.1f}"
                  " | " + " ".join(f"{t:.0e}" for t in gr["t_levels"]) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
