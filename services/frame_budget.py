"""A live session's frame budget: the detailed surface's level of detail chosen to hold it.

The cloth step's cost grows with the detailed vertices, about as the tessellation level squared
(docs/surface.md: linear in the vertices from level 4 to 12). On a machine too slow for the
asked level (or one that other work slows down), a live session would fall behind its input and
its latency would grow without bound; a display would rather show the garments with fewer
detailed vertices, on time. `LevelGovernor` watches a session's frame times in the cloth service
(each frame's wait before its step and the step: `services.cloth_service`) and asks for a lower
level when the slow frames exceed the budget, and one more (up to the asked level) when the next
level's expected cost fits with room to spare. The cloth service carries each garment's wrinkles
over to the other level (`DetailedSurface.carry_heights_from`) and latches its new topology.

What the output depends on: the level follows the machine's timing, so a session with a budget is
not reproduced bit for bit by a replay (as with `--catch-up`); without one (the default) it is.
"""

from __future__ import annotations

import math

import numpy as np

LOWEST_LEVEL = 3  # below it a coarse face's lattice has no interior particle to wrinkle (level 3: one)


class LevelGovernor:
    """Chooses the tessellation level that holds a session's frames within `budget` seconds.

    observe(seconds) after each stepped frame (its time: the step, and the service's wait before
    it) returns the level to change to, or None. The decision looks at the `quantile` (default the
    90th percentile: the 27th of 30) of those times over the last `window` frames since the level
    last changed:
    * over the budget, and a level below left: down to the level whose vertices would fit, by the
      ratio of detailed vertices, about (L' / L)² (one level at least);
    * under the asked level, the level's expected cost there (this level's quantile times the
      ratio of detailed vertices, about ((L + 1) / L)²) within `headroom` of the budget, and
      `rise_frames` frames at this level: one level up. A rise that had to be taken back within
      two windows doubles the wait before the next (up to `max_rise_frames`): a machine that holds
      a level only on its good spells does not flicker between two.
    `changed(level)` tells it a change was made (the samples start again)."""

    def __init__(self, budget: float, top: int, bottom: int = LOWEST_LEVEL, window: int = 30,
                 quantile: float = 0.9, headroom: float = 0.8, rise_frames: int = 120,
                 max_rise_frames: int = 3600):
        if not budget > 0 or not math.isfinite(budget):
            raise ValueError(f"frame budget must be a positive number of seconds, got {budget!r}")
        if top < 1:
            raise ValueError(f"level must be >= 1, got {top}")
        if window < 1 or not 0 < quantile <= 1 or not 0 < headroom <= 1 or rise_frames < window:
            raise ValueError("LevelGovernor: window >= 1, 0 < quantile <= 1, 0 < headroom <= 1, "
                             "rise_frames >= window")
        self.budget, self.top, self.bottom = budget, top, min(bottom, top)
        self.window, self.quantile, self.headroom = window, quantile, headroom
        self.rise_frames, self.max_rise_frames = rise_frames, max_rise_frames
        self.level = top
        self._samples = np.zeros(window)  # the last `window` frame times, a ring (preallocated: read every frame)
        self._sorted = np.zeros(window)  # (scratch)
        self._k = min(window - 1, max(0, math.ceil(quantile * window) - 1))  # the quantile's rank among them
        self._frames = 0  # frames stepped at this level
        self._rise_wait = rise_frames
        self._rose = False  # the last change was a rise
        self.changes = 0

    def observe(self, seconds: float) -> int | None:
        """One stepped frame's time (s); the level to change to (None: keep this one)."""
        if not math.isfinite(seconds) or seconds < 0:
            return None
        self._samples[self._frames % self.window] = seconds
        self._frames += 1
        if self._frames < self.window:
            return None
        self._sorted[:] = self._samples
        self._sorted.partition(self._k)
        slow = float(self._sorted[self._k])
        if slow > self.budget and self.level > self.bottom:
            if self._rose and self._frames <= 2 * self.window:  # a rise taken back: wait longer next time
                self._rise_wait = min(2 * self._rise_wait, self.max_rise_frames)
            # as far down as the vertex ratio says at once (the part that does not shrink with the
            # level makes that an underestimate of the level needed: the next window goes on from there)
            return max(self.bottom, min(self.level - 1, math.floor(self.level * math.sqrt(self.budget / slow))))
        if (self.level < self.top and self._frames >= self._rise_wait
                and slow * ((self.level + 1) / self.level) ** 2 <= self.headroom * self.budget):
            return self.level + 1
        return None

    def changed(self, level: int) -> None:
        """The session now steps at `level` (asked by observe, or set otherwise: a restart)."""
        if level != self.level:
            self._rose = level > self.level
            self.changes += 1
        self.level = level
        self._frames = 0


__all__ = ["LOWEST_LEVEL", "LevelGovernor"]
