"""A small progress bar for long steps (no dependency).

It draws on stderr only when stderr is a terminal or ``CLVOL_PROGRESS=1``, and only once
the step has run for ``delay`` seconds, so short steps and test logs stay quiet.
"""
from __future__ import annotations

import os
import sys
import time


class Progress:
    def __init__(self, total: float, label: str = "", unit: str = "", delay: float = 1.0,
                 stream=None, rate_per_unit: float = 0.0, rate_unit: str = ""):
        # rate_per_unit > 0 adds a throughput column: e.g. labels per second when one unit
        # (a shard) holds rate_per_unit labels.
        self.rate_per_unit = rate_per_unit
        self.rate_unit = rate_unit
        self.total = max(float(total), 1e-12)
        self.label = label
        self.unit = unit
        self.delay = delay
        self.stream = stream if stream is not None else sys.stderr
        forced = os.environ.get("CLVOL_PROGRESS")
        self.enabled = (forced == "1") if forced in ("0", "1") else self.stream.isatty()
        self.done = 0.0
        self._t0 = time.perf_counter()
        self._last_draw = 0.0
        self._drawn = False

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self._t0

    def update(self, amount: float = 1.0, done: float | None = None) -> None:
        self.done = done if done is not None else self.done + amount
        now = self.elapsed
        if self.enabled and now >= self.delay and now - self._last_draw >= 0.1:
            self._draw(now)

    def _draw(self, now: float) -> None:
        frac = min(self.done / self.total, 1.0)
        width = 30
        fill = int(frac * width)
        eta = (now / frac - now) if frac > 0 else float("nan")
        rate = (f" {self.done * self.rate_per_unit / max(now, 1e-9):8.0f} {self.rate_unit}/s"
                if self.rate_per_unit > 0 else "")
        self.stream.write(f"\r{self.label} [{'#' * fill}{'.' * (width - fill)}] "
                          f"{frac * 100:5.1f}% {self.done:g}/{self.total:g}{self.unit}{rate} "
                          f"{now:6.1f}s eta {eta:6.1f}s")
        self.stream.flush()
        self._last_draw = now
        self._drawn = True

    def close(self) -> None:
        if self._drawn:
            self._draw(self.elapsed)
            self.stream.write("\n")
            self.stream.flush()
