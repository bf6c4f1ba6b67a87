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

from ...errors import ClvolError
from ...kernels.raymarch import ms_defines
from ...runtime import Stopwatch
from .network import DOMAIN_FALLBACK_OPTION, WEIGHTS_OPTION, NetworkMs
from .base import MsPlan, option

DEFAULT_VIEW_BLOCK = 4     # pixels per block side
DEFAULT_VIEW_KNOTS = 4     # query depths per block
# The stochastic source's default block: about this many blocks across the image's longer
# side (block = max(1, round(side / 64)): 2 at 96^2-128^2, 4 at 256^2, 8 at 512^2). Its frame
# cost scales with the blocks, and at 64 across a 256^2 camera move costs about 1.5x the plain
# march (docs/raymarch.md, "Stochastic view-space F_ms").
STOCHASTIC_BLOCKS_ACROSS = 64
VIEW_BLOCK_OPTION = option(        # read by every view-space source
    "--view-block", type=int, default=None, metavar="B",
    help=f"--ms view, stochastic and progressive: pixels per block side; each block's "
         f"queries serve its pixels (default {DEFAULT_VIEW_BLOCK} for view; for the others "
         f"about {STOCHASTIC_BLOCKS_ACROSS} blocks across the image: 2 at 128^2, 4 at 256^2)")
VIEW_RAYS = 2              # sample rays per block side for the depth quantiles (at most
                           # one per pixel: a 1-pixel block gets one ray)
# The depth pass marches at this many march steps per segment: its cost (the view_depths
# stage of bench/bench_orbit.py --ms view) falls in proportion, and a quantile needs less
# resolution along the ray than the image's integral.
VIEW_STEP_FACTOR = 2.0
MAX_VIEW_BLOCK = 64


def _is_int(v) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


def check_view_options(block, knots):
    from ...kernels.viewdepth import MAX_VIEW_K
    if not (_is_int(block) and 1 <= block <= MAX_VIEW_BLOCK):
        raise ClvolError(f"raymarch option view_block = {block!r}: an integer from 1 to "
                         f"{MAX_VIEW_BLOCK} (pixels per block side)")
    if not (_is_int(knots) and 1 <= knots <= MAX_VIEW_K):
        raise ClvolError(f"raymarch option view_knots = {knots!r}: an integer from 1 to "
                         f"{MAX_VIEW_K} (network queries per block)")


class ViewMs(NetworkMs):
    """The network at ``knots`` depths per ``block`` x ``block`` pixels of the camera's view."""
    name = "view"
    summary = "the trained network at the camera's view"
    what = "view-space F_ms table"
    bundle_supported = False           # Python only (docs/embedding.md)
    options = (
        WEIGHTS_OPTION,
        VIEW_BLOCK_OPTION,
        option("--view-knots", type=int, default=DEFAULT_VIEW_KNOTS, metavar="K",
               help=f"--ms view: network queries per block, at the quantiles of the "
                    f"camera's in-scattering weight (default {DEFAULT_VIEW_KNOTS})"),
        DOMAIN_FALLBACK_OPTION,
    )

    @classmethod
    def lattice_reach_for(cls, volume, step_voxels: float) -> None:
        return None                    # a table where the camera sees, no world lattice

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
    def from_options(cls, o, runtime=None) -> "ViewMs":
        block = cls.read(o, "view_block")
        cls.read(o, "domain_fallback")  # read by plan_frame for every network source
        return cls(cls.read(o, "weights"), DEFAULT_VIEW_BLOCK if block is None else block,
                   cls.read(o, "view_knots"), runtime)

    @property
    def label(self) -> str:
        from pathlib import Path
        return (f"network multiple scattering at the camera's view ({self.knots} queries per "
                f"{self.block}x{self.block} pixels; weights {Path(str(self.weights_path)).name})")

    def prepare(self, frame) -> None:
        from ...kernels.viewdepth import block_grid, view_depths
        if self.info:
            self.info = dict(self.info, light=0.0, gather=0.0, network=0.0, depths=0.0)
        self._ensure_network(frame)
        cam, m = frame.camera, frame.medium
        key = frame.key                 # None (no plan): what the table depends on is unknown
        if key is not None and key == self._key:
            return
        rt = frame.runtime
        fwd, right, up = cam.basis()
        builds = self.net.graded_builds
        with Stopwatch() as sw:
            dm = frame.device_medium
            density = dm.density if dm is not None else frame.grid.density
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
        vals, info = self._evaluate(frame, pts, d)
        channels = vals.shape[1]
        table = np.zeros((1 + channels,) + depths.shape, np.float32)
        table[0] = depths
        for c in range(channels):
            table[1 + c][full] = vals[:, c].reshape(-1, self.knots)
        info["depths"] = t_depths
        info["blocks"] = int(full.sum())
        self.info = info
        self.table = rt.upload(table)
        if self.net.graded_builds != builds:
            frame.count("graded_transmittance")
        frame.count("ms_view_table")
        self._key = key

    def _evaluate(self, frame, pts, dirs):
        """(F_ms float32 (n, C), info) at world points ``pts`` seen along unit ``dirs`` (n, 3)
        (omega = -dir, toward the camera): the network, or the benchmark's stand-in
        ``query``. C = 1 for a grey medium with shortcuts (one evaluation), else 3."""
        m = frame.medium
        grey = frame.shortcuts and m.is_grey
        channels = 1 if grey else 3
        info = {"light": 0.0, "gather": 0.0, "network": 0.0, "points": len(pts),
                "evaluations": 1 if grey else 3}
        if not len(pts):
            return np.zeros((0, channels), np.float32), info
        if self.query is not None:
            with Stopwatch() as sw:
                vals = np.asarray(self.query(pts, -dirs), np.float32).reshape(len(pts), 3)
            info["network"] = sw.seconds
            return vals[:, :channels], info
        vals, info = self.net.evaluate(pts, -dirs, frame.light.direction, m, frame.shortcuts)
        return vals.reshape(len(vals), -1), info

    @classmethod
    def key_for(cls, camera, light, medium, shortcuts: bool):
        """The table depends on the whole camera (its rays), the light and the medium."""
        return (tuple(camera.origin), tuple(np.concatenate(camera.basis())),
                camera.tan_half_fov, camera.width, camera.height, tuple(light.direction),
                medium.density_scale, tuple(medium.albedo), medium.phase, bool(shortcuts))

    @classmethod
    def _block_knots(cls, camera, o) -> tuple[int, int]:
        block = cls.read(o, "view_block")
        return (DEFAULT_VIEW_BLOCK if block is None else block, cls.read(o, "view_knots"))

    @classmethod
    def plan_for(cls, medium, camera, shortcuts: bool, options) -> MsPlan:
        from ...kernels.viewdepth import block_grid
        block, knots = cls._block_knots(camera, options)
        grey = bool(shortcuts and medium.is_grey)
        channels = 1 if grey else 3
        p = MsPlan(ms_defines("view", channels=channels, view_k=knots, view_block=block))
        p.programs["viewdepth"] = cls._depth_defines(block, knots)
        bx, by = block_grid(camera.width, camera.height, block)
        p.simulated.append(cls._simulated(block, knots, bx, by, channels))
        if grey:
            p.skipped.append("network evaluations for colour channels 2 and 3 (grey albedo: "
                             "one per query)")
        p.skipped.append(cls._skipped_blocks)
        return p

    @staticmethod
    def _depth_defines(block: int, knots: int) -> dict:
        """The view_depths program's defines (``prepare``'s depth pass)."""
        from ...kernels.viewdepth import view_depth_defines
        return view_depth_defines(knots, block, min(VIEW_RAYS, block))

    @staticmethod
    def _simulated(block, knots, bx, by, channels) -> str:
        return (f"multiple scattering (network at the camera's view: {knots} queries per "
                f"{block}x{block}-pixel block, {bx}x{by} blocks, {channels} channel(s))")

    _skipped_blocks = "network evaluations for pixel blocks where no sample ray meets the medium"

    def device_data(self, medium, shortcuts: bool):
        """The view table (1 + C, by, bx, K) on the device; the kernel reads it by pixel
        block, so its box is the unit box."""
        if self.table is None:
            raise ClvolError(f"--ms {self.name}: the source was not prepared for a frame")
        return self.table, ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))

    def header(self) -> dict:
        info = self.info or {}
        h = self._network_header()
        h.update({"raymarch.view_block": self.block, "raymarch.view_knots": self.knots,
                  "raymarch.view_blocks_queried": info.get("blocks", 0),
                  "seconds.view_depths": round(info.get("depths", 0.0), 4)})
        return h


# --------------------------------------------------------------------------- stochastic

DEFAULT_VIEW_SAMPLES = 1
MAX_VIEW_SAMPLES = 4096
# A still view stops drawing after this many draws per block (a thin block, whose ray often
# escapes, holds fewer samples): the table's noise then sits well below the network's own
# error (bench/accuracy_vs_time.py, stochastic rows: 16 frames already reach the curve's best).
STILL_SAMPLES = 64
# Through a camera move a block keeps at most this many samples' worth of history, so a new
# sample weighs at least 1/(MOVE_HISTORY + 1) and the table follows the view (F_ms depends
# on the direction toward the camera, which the move changed).
MOVE_HISTORY = 4
# A frame draws until its history is at least this many draws old (a new history, or one
# carried through a move after fewer draws): one draw per block leaves the first frames of a
# back-scattering cloud worse than the analytic octaves (bench/moving_frames.py: RMSE x 100
# 8.1 and 6.6 against 6.4); four bring them under it. Once the history is older, a moving
# frame draws view_samples (MOVE_HISTORY carried + the new one already reach it).
MIN_SAMPLES = 4


def auto_block(width: int, height: int) -> int:
    """The stochastic source's block for an image: about STOCHASTIC_BLOCKS_ACROSS blocks
    across its longer side."""
    return max(1, int(round(max(width, height) / STOCHASTIC_BLOCKS_ACROSS)))


def view_jitter(seed: int, draw: int, bx: int, by: int) -> np.ndarray:
    """(by, bx, 3) float32 in [0, 1): the jitter of draw ``draw`` (x, y of the block's ray,
    z its free-flight level): Philox4x32-10 (cl/include/rng.h) keyed by ``seed``, stream the
    block's index j bx + i, sample ``draw``, dimension block 0, its first three uniforms.
    libclvol draws the same numbers (capi/src/renderer.c view_jitter; docs/conventions.md,
    "Randomness")."""
    from ...kernels.rng import host_uniform4
    u = host_uniform4(seed, np.arange(bx * by), draw, 0)
    return u[:, :3].reshape(by, bx, 3)


def check_stochastic_options(samples, seed):
    if not (_is_int(samples) and 1 <= samples <= MAX_VIEW_SAMPLES):
        raise ClvolError(f"raymarch option view_samples = {samples!r}: an integer from 1 to "
                         f"{MAX_VIEW_SAMPLES} (free-flight samples per block per frame)")
    if not (_is_int(seed) and 0 <= seed < 2 ** 32):
        raise ClvolError(f"raymarch option seed = {seed!r}: an integer in [0, 2^32)")


class _History:
    """What a stochastic table has accumulated: per block the sum of F_ms over its samples,
    their count and their mean depth, for one light and medium, at one camera."""

    def __init__(self, key, channels, by, bx):
        self.key = key
        self.sums = np.zeros((channels, by, bx), np.float64)
        self.count = np.zeros((by, bx), np.float64)
        self.depth = np.zeros((by, bx), np.float64)       # sum of sample depths
        self.camera = None                                # the camera of the last draw
        self.still = 0                                    # draws since the last move
        self.age = 0              # draws the history holds per block (capped through moves)

    def table(self) -> np.ndarray:
        """(1 + C, by, bx, 1) float32: mean depth (-1 where no sample yet), mean F_ms."""
        c = self.count
        inv = np.where(c > 0, 1.0 / np.maximum(c, 1.0), 0.0)
        t = np.empty((1 + len(self.sums),) + c.shape + (1,), np.float32)
        t[0, ..., 0] = np.where(c > 0, self.depth * inv, -1.0)
        t[1:, ..., 0] = self.sums * inv
        return t


class StochasticViewMs(ViewMs):
    """MRPNN's estimator at the camera's view: each frame, one free-flight point per block of
    ``block`` x ``block`` pixels (a uniformly jittered ray, a depth drawn from its
    in-scattering weight), accumulated per block while the view is still and reprojected
    when the camera moves. The marcher reads the block means as a one-knot view table
    (MS_SOURCE 3, VIEW_K 1): F_ms constant along each ray, blended across blocks."""
    name = "stochastic"
    summary = ("the network at one free-flight point per pixel block per frame, "
               "accumulated")
    what = "stochastic view-space F_ms table"
    bundle_supported = True            # libclvol runs it too (docs/embedding.md)
    options = (
        WEIGHTS_OPTION,
        VIEW_BLOCK_OPTION,
        option("--view-samples", type=int, default=DEFAULT_VIEW_SAMPLES, metavar="N",
               help=f"--ms stochastic: free-flight samples per block drawn per frame "
                    f"(default {DEFAULT_VIEW_SAMPLES}; a still view accumulates them "
                    f"up to {STILL_SAMPLES} per block)"),
        DOMAIN_FALLBACK_OPTION,
    )

    def __init__(self, weights=None, block: int | None = None,
                 samples: int = DEFAULT_VIEW_SAMPLES, seed: int = 0, runtime=None):
        super().__init__(weights, 1 if block is None else block, 1, runtime)
        self.fixed_block = block        # None: chosen from the image size (auto_block)
        check_stochastic_options(samples, seed)
        self.samples, self.seed = int(samples), int(seed)
        self.draws = 0              # draws since construction: the RNG stream's position
        self.history = None
        self._history_grid = None   # the density the history was gathered on
        self.refining = False       # whether the next frame of this view draws more

    @classmethod
    def from_options(cls, o, runtime=None) -> "StochasticViewMs":
        cls.read(o, "domain_fallback")  # read by plan_frame for every network source
        return cls(cls.read(o, "weights"), cls.read(o, "view_block"),
                   cls.read(o, "view_samples"), o.get("seed", 0), runtime)

    @property
    def label(self) -> str:
        from pathlib import Path
        n = int(self.history.count.max()) if self.history is not None else 0
        return (f"network multiple scattering at the camera's view, stochastic (one "
                f"free-flight sample per {self.block}x{self.block} pixels per frame, up to "
                f"{n} accumulated; weights {Path(str(self.weights_path)).name})")

    def skip(self) -> None:
        self.refining = False

    def _draw(self, frame, draw: int):
        """One free-flight sample per block, the ``draw``-th of the RNG stream (jitter
        ``view_jitter(seed, draw, ...)``): (points (n, 3), dirs (n, 3), depths (n,), block
        mask (by, bx)) for the blocks whose jittered ray collides. The flight is
        unconditioned (one pass, usually ending ~1 optical depth in); a ray that escapes
        draws nothing this frame, and the collisions are distributed as the in-scattering
        weight, so the block's mean over them is still the estimator's (only thin blocks
        collect samples more slowly)."""
        from ...kernels.viewdepth import block_grid, view_depths
        cam, m = frame.camera, frame.medium
        bx, by = block_grid(cam.width, cam.height, self.block)
        jitter = view_jitter(self.seed, draw, bx, by)
        fwd, right, up = cam.basis()
        dm = frame.device_medium
        density = dm.density if dm is not None else frame.grid.density
        depths, _ = view_depths(density, frame.grid.bbox_min, frame.grid.bbox_max,
                                m.density_scale, cam.origin, fwd, right, up, cam.tan_half_fov,
                                cam.width, cam.height, self.block, 1, 1,
                                VIEW_STEP_FACTOR * frame.step, frame.threshold,
                                jitter=jitter, free_flight=True, runtime=frame.runtime)
        full = depths[..., 0] >= 0
        col = (np.arange(bx)[None, :] + jitter[..., 0]) * self.block
        row = (np.arange(by)[:, None] + jitter[..., 1]) * self.block
        dirs = cam.directions_at(col[full], row[full])
        t = depths[full, 0].astype(np.float64)
        return np.asarray(cam.origin, np.float64) + t[:, None] * dirs, dirs, t, full

    def _reproject(self, h: _History, cam, pts, full) -> None:
        """Carry the history from ``h.camera`` to ``cam`` (at most MOVE_HISTORY samples'
        worth per block). A block with a new sample takes the old block its new point
        projects into; a block without one (its ray missed this frame, as at silhouettes)
        takes an old block whose mean point projects into it; the others start empty."""
        old = h.camera
        by, bx = h.count.shape
        src = np.full((by, bx), -1, np.int64)               # flat old block index per block

        def blocks_of(camera, points):
            col, row, _ = camera.image_positions(points)
            with np.errstate(invalid="ignore"):            # NaN behind the camera
                i, j = np.floor(col / self.block), np.floor(row / self.block)
            ok = np.isfinite(i) & np.isfinite(j) & (i >= 0) & (i < bx) & (j >= 0) & (j < by)
            return ok, (np.where(ok, j, 0) * bx + np.where(ok, i, 0)).astype(np.int64)

        # forward: old blocks' mean points (old centre ray at the mean depth) into the view
        had = np.flatnonzero(h.count.ravel() > 0)
        if len(had):
            jj, ii = np.divmod(had, bx)
            d = old.directions_at((ii + 0.5) * self.block, (jj + 0.5) * self.block)
            mean_t = h.depth.ravel()[had] / h.count.ravel()[had]
            ok, dst = blocks_of(cam, np.asarray(old.origin, np.float64) + mean_t[:, None] * d)
            src.ravel()[dst[ok]] = had[ok]
        # backward, where this frame drew: the old block under each new point wins
        ok, old_block = blocks_of(old, pts)
        new_blocks = np.flatnonzero(full.ravel())
        src.ravel()[new_blocks[ok]] = old_block[ok]
        src.ravel()[new_blocks[~ok]] = -1
        take = src >= 0
        s_flat = src[take]
        count_old = h.count.ravel()[s_flat]
        keep = np.minimum(count_old, MOVE_HISTORY)
        scale = keep / np.maximum(count_old, 1.0)           # 0 where the old block was empty
        sums = np.zeros_like(h.sums)
        for c in range(len(sums)):
            sums[c][take] = h.sums[c].ravel()[s_flat] * scale
        count = np.zeros_like(h.count)
        count[take] = keep
        # The old mean depth is along the old rays: with one knot the marcher reads only
        # its sign (a block with samples), and new samples soon outweigh it.
        depth = np.zeros_like(h.depth)
        depth[take] = h.depth.ravel()[s_flat] * scale
        h.sums, h.count, h.depth = sums, count, depth
        h.still = 0

    def _block_for(self, camera) -> int:
        """The block for ``camera``'s image: the fixed one, else ``auto_block``."""
        return (auto_block(camera.width, camera.height) if self.fixed_block is None
                else self.fixed_block)

    def _frame_history(self, frame):
        """(history, fresh, moved) for this frame: the network ready, the block size chosen,
        the history started again for a new density or key (light, medium, image layout),
        and whether the camera moved since the history's last frame."""
        from ...kernels.viewdepth import block_grid
        self._ensure_network(frame)
        if self._history_grid is not frame.grid:
            self.history = None                          # a new density: start again
            self._history_grid = frame.grid
        cam = frame.camera
        grey = frame.shortcuts and frame.medium.is_grey
        self.block = self._block_for(cam)
        bx, by = block_grid(cam.width, cam.height, self.block)
        h = self.history
        fresh = h is None or frame.key is None or h.key != frame.key
        if fresh:
            h = self.history = _History(frame.key, 1 if grey else 3, by, bx)
        moved = h.camera is not None and (tuple(h.camera.origin) != tuple(cam.origin) or
                                          not np.array_equal(np.concatenate(h.camera.basis()),
                                                             np.concatenate(cam.basis())))
        return h, fresh, moved

    def prepare(self, frame) -> None:
        if self.info:
            self.info = dict(self.info, light=0.0, gather=0.0, network=0.0, depths=0.0,
                             reproject=0.0, points=0)
        h, fresh, moved = self._frame_history(frame)
        cam = frame.camera
        if not moved and h.still >= STILL_SAMPLES:
            self.refining = False
            return                                       # converged: nothing to draw
        # the history's age once carried through a move (_reproject keeps MOVE_HISTORY)
        age = min(h.age, MOVE_HISTORY) if moved else h.age
        n_draws = max(self.samples, MIN_SAMPLES - age)
        if frame.still:     # a still image: draw now what the still view would accumulate
            n_draws = max(n_draws, STILL_SAMPLES - (0 if moved or fresh else h.still))
        builds = self.net.graded_builds
        with Stopwatch() as sw:
            draws = []
            for _ in range(n_draws):
                self.draws += 1
                draws.append(self._draw(frame, self.draws - 1))
        t_depths = sw.seconds
        t_reproject = 0.0
        if moved:
            with Stopwatch() as sw:
                self._reproject(h, cam, draws[0][0], draws[0][3])
            t_reproject = sw.seconds
        pts = np.concatenate([d[0] for d in draws])
        dirs = np.concatenate([d[1] for d in draws])
        vals, info = self._evaluate(frame, pts, dirs)
        start = 0
        for p, _, t, full in draws:
            v = vals[start:start + len(p)]
            start += len(p)
            for c in range(len(h.sums)):
                h.sums[c][full] += v[:, c]
            h.count[full] += 1
            h.depth[full] += t
        h.camera = cam
        h.still += n_draws
        h.age = age + n_draws
        info.update(depths=t_depths, reproject=t_reproject, blocks=int((h.count > 0).sum()),
                    samples=int(h.count.max()))
        self.refining = h.still < STILL_SAMPLES
        self.info = info
        self.table = frame.runtime.upload(h.table())
        if self.net.graded_builds != builds:
            frame.count("graded_transmittance")
        frame.count("ms_view_table")

    def bundle_view(self, camera) -> dict:
        """The bundle's view.* keys (libclvol repeats prepare with them) and the free-flight
        draw's viewdepth defines, for ``camera``'s image size."""
        block = self._block_for(camera)
        keys = {"block": block, "block_auto": self.fixed_block is None,
                "blocks_across": STOCHASTIC_BLOCKS_ACROSS, "samples": self.samples,
                "seed": self.seed, "still_samples": STILL_SAMPLES, "min_samples": MIN_SAMPLES,
                "move_history": MOVE_HISTORY, "step_factor": VIEW_STEP_FACTOR}
        return {"keys": keys, "viewdepth": self._depth_defines(block, 1)}

    @classmethod
    def key_for(cls, camera, light, medium, shortcuts: bool):
        """The history holds for one light, medium and image layout; camera motion is
        reprojected, not a new key."""
        return (tuple(light.direction), medium.density_scale, tuple(medium.albedo),
                medium.phase, bool(shortcuts), camera.width, camera.height, camera.tan_half_fov)

    @classmethod
    def _block_knots(cls, camera, o) -> tuple[int, int]:
        block = cls.read(o, "view_block")
        return (auto_block(camera.width, camera.height) if block is None else block), 1

    @staticmethod
    def _depth_defines(block: int, knots: int) -> dict:
        """The free-flight draws' defines (``_draw``: one ray and one knot, jittered)."""
        from ...kernels.viewdepth import view_depth_defines
        return view_depth_defines(1, block, 1, jitter=True, free_flight=True)

    @staticmethod
    def _simulated(block, knots, bx, by, channels) -> str:
        return (f"multiple scattering (network at the camera's view, stochastic: one "
                f"free-flight sample per {block}x{block}-pixel block per frame, {bx}x{by} "
                f"blocks, {channels} channel(s), accumulated while the view is still)")

    _skipped_blocks = "network evaluations for pixel blocks whose sample ray misses the medium"

    def header(self) -> dict:
        h = super().header()
        h.pop("raymarch.view_knots", None)
        info = self.info or {}
        h.update({"raymarch.view_samples": self.samples, "raymarch.seed": self.seed,
                  "raymarch.view_accumulated": info.get("samples", 0),
                  # whether another frame of this view draws more (the viewer's refine rule)
                  "raymarch.view_refining": self.refining,
                  "seconds.view_reproject": round(info.get("reproject", 0.0), 4)})
        return h
