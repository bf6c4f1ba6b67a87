"""The network evaluated where the camera sees: the view-space F_ms source (``--ms view``).

Instead of a world lattice, the network is queried on the camera rays. The image is cut into
blocks of ``block`` x ``block`` pixels; for each block cl/viewdepth.cl marches a few sample
rays and puts ``knots`` query depths at the quantiles of the block's in-scattering weight
T_cam sigma_t (where the camera ray gathers its light). The queries lie on the block's centre
ray, omega toward the camera; the marcher (cl/raymarch.cl, MS_SOURCE 3) blends the four
nearest blocks' knots for each pixel and interpolates F_ms along the ray between them.

Deterministic: the same camera, light and medium give the same image. Empty blocks (no
sample ray meets the medium) cost no query. The table depends on the whole camera (position,
orientation, field of view, image size), the light and the medium; ``prepare`` rebuilds it
only when one of those changed. It has no world lattice: nothing caps the resolution of F_ms
across the image but the block size (docs/raymarch.md, "View-space F_ms").
"""
from __future__ import annotations

import numpy as np

from ..errors import ClvolError
from ..kernels.raymarch import ms_defines
from ..runtime import Stopwatch
from .network import NetworkMs
from .sources import MsPlan, register

DEFAULT_VIEW_BLOCK = 4     # pixels per block side
DEFAULT_VIEW_KNOTS = 4     # query depths per block
VIEW_RAYS = 2              # sample rays per block side for the depth quantiles (at most
                           # one per pixel: a 1-pixel block gets one ray)
# The depth pass marches at this many march steps per segment: its cost (the view_depths
# stage of bench/bench_orbit.py --ms view) falls in proportion, and a quantile needs less
# resolution along the ray than the image's integral.
VIEW_STEP_FACTOR = 2.0
MAX_VIEW_BLOCK = 64


def check_view_options(block, knots):
    from ..kernels.viewdepth import MAX_VIEW_K

    def is_int(v):
        return isinstance(v, (int, np.integer)) and not isinstance(v, bool)
    if not (is_int(block) and 1 <= block <= MAX_VIEW_BLOCK):
        raise ClvolError(f"raymarch option view_block = {block!r}: an integer from 1 to "
                         f"{MAX_VIEW_BLOCK} (pixels per block side)")
    if not (is_int(knots) and 1 <= knots <= MAX_VIEW_K):
        raise ClvolError(f"raymarch option view_knots = {knots!r}: an integer from 1 to "
                         f"{MAX_VIEW_K} (network queries per block)")


@register
class ViewMs(NetworkMs):
    """The network at ``knots`` depths per ``block`` x ``block`` pixels of the camera's view."""
    name = "view"
    options = ("weights", "view_block", "view_knots", "no_domain_fallback")
    what = "view-space F_ms table"

    def __init__(self, weights=None, block: int = DEFAULT_VIEW_BLOCK,
                 knots: int = DEFAULT_VIEW_KNOTS, runtime=None):
        check_view_options(block, knots)
        self.block, self.knots = int(block), int(knots)
        self.runtime = runtime
        self._init_network(weights)
        self.table = None           # DeviceArray (1 + C, by, bx, K)
        self.count = None
        # Optional stand-in for the network: query(points (N, 3), omegas (N, 3)) -> F_ms
        # (N, 3) for irradiance 1 (the benchmark's path-traced queries measure what the
        # table itself leaves, whatever the network; bench/neural_quality.py --pt-view).
        self.query = None

    @classmethod
    def from_options(cls, o: dict, runtime=None) -> "ViewMs":
        return cls(o.get("weights"), o.get("view_block", DEFAULT_VIEW_BLOCK),
                   o.get("view_knots", DEFAULT_VIEW_KNOTS), runtime)

    @property
    def label(self) -> str:
        from pathlib import Path
        return (f"network multiple scattering at the camera's view ({self.knots} queries per "
                f"{self.block}x{self.block} pixels; weights {Path(str(self.weights_path)).name})")

    def prepare(self, frame) -> None:
        from ..kernels.viewdepth import block_grid, view_depths
        if self.info:
            self.info = dict(self.info, light=0.0, gather=0.0, network=0.0, depths=0.0)
        self._ensure_network(frame)
        cam, m = frame.camera, frame.medium
        key = (tuple(cam.origin), tuple(np.concatenate(cam.basis())), cam.tan_half_fov,
               cam.width, cam.height, tuple(frame.light.direction), m.density_scale,
               tuple(m.albedo), m.phase, bool(frame.shortcuts))
        if key == self._key:
            return
        rt = frame.runtime
        fwd, right, up = cam.basis()
        builds = self.net.graded_builds
        with Stopwatch() as sw:
            density = frame.density if frame.density is not None else frame.grid.density
            depths, _ = view_depths(density, frame.grid.bbox_min, frame.grid.bbox_max,
                                    m.density_scale, cam.origin, fwd, right, up,
                                    cam.tan_half_fov, cam.width, cam.height, self.block,
                                    min(VIEW_RAYS, self.block), self.knots,
                                    VIEW_STEP_FACTOR * frame.step,
                                    frame.threshold,
                                    runtime=rt)
        t_depths = sw.seconds
        # the queries lie on each block's centre ray (x = i block + block / 2, in pixels)
        bx, by = block_grid(cam.width, cam.height, self.block)
        dirs = cam.directions_at((np.arange(bx) + 0.5) * self.block,
                                 ((np.arange(by) + 0.5) * self.block)[:, None])   # (by, bx, 3)
        full = depths[..., 0] >= 0                                   # (by, bx)
        d = np.repeat(dirs[full], self.knots, axis=0)                # (n * K, 3)
        pts = np.asarray(cam.origin, np.float64) + depths[full].reshape(-1, 1) * d
        grey = frame.shortcuts and m.is_grey
        channels = 1 if grey else 3
        table = np.zeros((1 + channels,) + depths.shape, np.float32)
        table[0] = depths
        if len(pts) and self.query is not None:
            with Stopwatch() as sw:
                vals = np.asarray(self.query(pts, -d), np.float32).reshape(len(pts), 3)
            info = {"light": 0.0, "gather": 0.0, "network": sw.seconds, "points": len(pts),
                    "evaluations": 1 if grey else 3}
        if len(pts) and self.query is None:
            vals, info = self.net.evaluate(pts, -d, frame.light.direction, m, frame.shortcuts)
        if len(pts):
            vals = vals.reshape(len(vals), -1)                       # (n * K, C)
            for c in range(channels):
                table[1 + c][full] = vals[:, c].reshape(-1, self.knots)
        else:
            info = {"light": 0.0, "gather": 0.0, "network": 0.0, "points": 0,
                    "evaluations": 1 if grey else 3}
        info["depths"] = t_depths
        info["blocks"] = int(full.sum())
        self.info = info
        self.table = rt.upload(table)
        if self.net.graded_builds != builds:
            frame.count("graded_transmittance")
        frame.count("ms_view_table")
        self._key = key

    def plan(self, medium, shortcuts: bool) -> MsPlan:
        if self.table is None:
            raise ClvolError("--ms view: the source was not prepared for a frame")
        channels = self.table.shape[0] - 1
        p = MsPlan(ms_defines("view", channels=channels, view_k=self.knots,
                              view_block=self.block),
                   planes=self.table, box=((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)))
        by, bx = self.table.shape[1:3]
        p.simulated.append(f"multiple scattering (network at the camera's view: {self.knots} "
                           f"queries per {self.block}x{self.block}-pixel block, {bx}x{by} "
                           f"blocks, {channels} channel(s))")
        if medium.is_grey and shortcuts:
            p.skipped.append("network evaluations for colour channels 2 and 3 (grey albedo: "
                             "one per query)")
        p.skipped.append("network evaluations for pixel blocks where no sample ray meets the "
                         "medium")
        return p

    def header(self) -> dict:
        info = self.info or {}
        h = self._network_header()
        h.update({"raymarch.view_block": self.block, "raymarch.view_knots": self.knots,
                  "raymarch.view_blocks_queried": info.get("blocks", 0),
                  "seconds.view_depths": round(info.get("depths", 0.0), 4)})
        return h
