"""Atomic file writes: results, shards, checkpoints and weight files appear whole or not at all.

The data goes to a temporary file in the destination's folder (so ``os.replace`` is an atomic
rename on one file system), is flushed to disk, then renamed over the destination. A failure or
a killed process leaves at most a hidden ``.NAME.*.tmp`` file, never a truncated result; readers
that resume work (dataset shards, training checkpoints) can trust any file that has its name.
"""
from __future__ import annotations

import os
import secrets
from contextlib import contextmanager
from pathlib import Path


def temp_path_for(path: Path) -> Path:
    """A fresh hidden temporary name next to ``path``."""
    return path.parent / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp"


@contextmanager
def atomic_path(path):
    """Yield a temporary path to write (for writers that want a file name, e.g. OpenEXR);
    on success it is fsync'ed and renamed to ``path``, on any error removed."""
    path = Path(path)
    tmp = temp_path_for(path)
    try:
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        try:
            tmp.unlink()
        except FileNotFoundError:
            pass
        raise


@contextmanager
def atomic_open(path, mode: str = "wb"):
    """Like ``open(path, mode)`` for writing, but the file appears at ``path`` only whole."""
    with atomic_path(path) as tmp:
        with open(tmp, mode) as f:
            yield f
            f.flush()
