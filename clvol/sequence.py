"""Volume sequences: ``clvol render SCENE --frames 1-48 -o out_{frame:04d}.exr``.

A scene whose ``[volume] file`` names a ``{frame}`` field (``fire_{frame:04d}.npz``,
docs/scenes.md "Sequences") is rendered frame by frame with one ``Renderer``: each frame's
density (and emission grid) replaces the last through ``Renderer.set_density``, which
recomputes only what the density invalidates. A second thread reads and prepares the next
frame (file read, checks, float32 conversion, the emission mapping) while the device renders
the current one (``prefetch=True``; ``False`` is the strict serial order, for the benchmark).

A frame that cannot be read (missing file, bad grid) stops the sequence with its one-line
error (exit 2) after every earlier frame has been written; nothing written is removed.
"""
from __future__ import annotations

import re
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from .errors import ClvolError

MAX_FRAMES = 100_000
_RANGE = re.compile(r"^\s*(\d+)\s*(?:-\s*(\d+)\s*)?$")


def parse_frames(text: str) -> list[int]:
    """``--frames``: "7", "1-48", "1,5,9" or a mix ("1-3,10"); frames are integers >= 0,
    ranges inclusive and increasing, no frame twice."""
    frames: list[int] = []
    for part in str(text).split(","):
        m = _RANGE.match(part)
        if not m:
            raise ClvolError(f"--frames {text}: expected frame numbers and ranges like 1-48 or "
                             f"1,5,9 (got {part.strip()!r})")
        a = int(m.group(1))
        b = int(m.group(2)) if m.group(2) is not None else a
        if b < a:
            raise ClvolError(f"--frames {text}: range {a}-{b} runs backwards")
        if len(frames) + (b - a + 1) > MAX_FRAMES:
            raise ClvolError(f"--frames {text}: more than {MAX_FRAMES} frames")
        frames.extend(range(a, b + 1))
    dup = [f for f, n in Counter(frames).items() if n > 1]
    if dup:
        raise ClvolError(f"--frames {text}: frame {dup[0]} is listed twice")
    return frames


def frame_path(pattern: str, frame: int) -> str:
    """``pattern`` with its ``{frame}`` field filled in."""
    try:
        return pattern.format(frame=frame)
    except Exception as e:      # KeyError, IndexError, ValueError, AttributeError, TypeError
        raise ClvolError(f"-o {pattern}: an output pattern takes one field, {{frame}} (e.g. "
                         f"out_{{frame:04d}}.exr): {type(e).__name__}: {e}") from None


def check_output_pattern(pattern: str, frames: list[int]) -> None:
    """Several frames need a ``{frame}`` field in -o that gives each its own file."""
    names = {frame_path(pattern, f) for f in frames[:2] + frames[-1:]}
    if len(frames) > 1 and len(names) < min(len(frames), 3):
        raise ClvolError(f"-o {pattern}: {len(frames)} frames would write one file; put "
                         f"{{frame}} in the name, e.g. out_{{frame:04d}}.exr")


def available_frames(volume) -> list[int]:
    """The frames of a sequence volume whose files exist (sorted); [] for a single file."""
    if volume.file is None or not volume.is_sequence:
        return []
    name = volume.file.name
    regex = re.compile("^" + re.sub(r"\\\{frame[^}]*\\\}", r"(\\d+)", re.escape(name)) + "$")
    out = []
    folder = volume.file.parent
    if not folder.is_dir():
        return []
    for p in folder.iterdir():
        m = regex.match(p.name)
        if m and all(g == m.group(1) for g in m.groups()):
            n = int(m.group(1))
            if name.format(frame=n) == p.name:
                out.append(n)
    return sorted(out)


@dataclass
class LoadedFrame:
    frame: int
    grid: object
    emission: object
    file: Path
    seconds: float          # reading and preparing it (on whichever thread did it)


def load_frame(scene, frame: int) -> LoadedFrame:
    """Read and prepare one frame of ``scene``'s sequence: its density DensityGrid and, with
    ``[emission]``, its EmissionGrid (mapped on the host)."""
    t0 = time.perf_counter()
    volume = scene.volume.for_frame(frame)
    grid = volume.load()
    emission = scene.emission.load(volume, grid) if scene.emission is not None else None
    return LoadedFrame(frame, grid, emission, volume.frame_file(),
                       time.perf_counter() - t0)


@dataclass
class SequenceStats:
    frames: list = field(default_factory=list)   # per frame: dict of seconds
    wall: float = 0.0


def render_sequence(scene, renderer, frames: list[int], on_frame, prefetch: bool = True,
                    progress=None) -> SequenceStats:
    """Render ``frames`` of ``scene`` with ``renderer`` (a Renderer of that scene), calling
    ``on_frame(frame, result, loaded)`` after each (it writes the files). With ``prefetch``
    the next frame is read on a second thread while this one renders. A frame that fails to
    load raises its error when its turn comes (earlier frames are done)."""
    stats = SequenceStats()
    t_start = time.perf_counter()
    pool = ThreadPoolExecutor(max_workers=1) if prefetch else None
    try:
        pending = pool.submit(load_frame, scene, frames[0]) if pool else None
        for i, n in enumerate(frames):
            t0 = time.perf_counter()
            if pool:
                loaded = pending.result()
                if i + 1 < len(frames):
                    pending = pool.submit(load_frame, scene, frames[i + 1])
            else:
                loaded = load_frame(scene, n)
            t_wait = time.perf_counter() - t0
            t1 = time.perf_counter()
            result = renderer.render(grid=loaded.grid, emission=loaded.emission)
            t2 = time.perf_counter()
            on_frame(n, result, loaded)
            t3 = time.perf_counter()
            stats.frames.append({"frame": n, "load": loaded.seconds, "wait": t_wait,
                                 "render": t2 - t1, "write": t3 - t2})
            if progress is not None:
                progress.update(done=i + 1)
    finally:
        if pool:
            pool.shutdown(wait=True, cancel_futures=True)
    stats.wall = time.perf_counter() - t_start
    return stats
