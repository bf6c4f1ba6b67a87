"""The one cache convention of a frame's recomputable stages.

A ``Stage`` holds the value of one stage (the light field, the environment's sky cells, its
source field, a map's background image) and the key it was built for. The key says what the
stage depends on, and the frame's plan states it (``FramePlan.keys``, clvol/render/plan.py):
the executing objects never invent their own. ``get(key, build)`` rebuilds only when the key
changed, and counts each rebuild under the stage's name (the Renderer's ``counts``, which the
tests hold to docs/architecture.md's recompute table). The multiple-scattering sources key
their data the same way: their frame input carries the plan's ``keys["ms"]``.
"""
from __future__ import annotations

_UNBUILT = object()


class Stage:
    """A value rebuilt only when the key of what it depends on changes."""

    def __init__(self, name: str, count=None):
        self.name = name
        self.count = count or (lambda stage: None)
        self.key = _UNBUILT
        self.value = None

    def get(self, key, build):
        """The value for ``key``: kept, or ``build()`` (counted) when the key changed."""
        if self.key is _UNBUILT or key != self.key:
            self.value = build()
            self.key = key
            self.count(self.name)
        return self.value

    @property
    def built(self) -> bool:
        return self.key is not _UNBUILT

    def drop(self) -> None:
        """Forget the value (what it depends on is gone: a new density)."""
        self.key, self.value = _UNBUILT, None
