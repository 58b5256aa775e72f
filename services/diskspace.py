"""What a session's recordings leave free on their disk.

A live session's recordings grow for as long as it runs: on the walk clip at 60 Hz, about
20 MB/s of bus recording (MCAP) and 55 MB/s of rerun recording (.rrd, float32 meshes). A
recording that filled its disk would stop mid-write, half-written, and take the disk from
everything else on the machine. So each recording watches the free space of its folder's disk
(at most once a second) and, when less than `DEFAULT_MIN_FREE` (or what the user sets) is
left, finishes its file there, complete and readable, says so, and the session streams on.
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

DEFAULT_MIN_FREE = 10**9  # bytes a recording leaves free on its disk (1 GB)


class SpaceGuard:
    """`low()`: the bytes free on `folder`'s disk when fewer than `min_free` are (else None),
    looked up at most once every `every` seconds."""

    def __init__(self, folder: str | Path, min_free: int = DEFAULT_MIN_FREE, every: float = 1.0):
        if min_free < 0:
            raise ValueError(f"the space to keep free must be >= 0 bytes, got {min_free}")
        self.folder, self.min_free, self.every = Path(folder), int(min_free), every
        self._next = 0.0
        self.free: int | None = None  # at the last look

    def low(self) -> int | None:
        now = time.monotonic()
        if now >= self._next:
            self._next = now + self.every
            try:
                self.free = shutil.disk_usage(self.folder).free
            except OSError:
                self.free = None  # (the folder is gone: the write itself will say so)
        return self.free if self.free is not None and self.free < self.min_free else None

    def why(self, free: int) -> str:
        return (f"{free / 1e6:.0f} MB left free on the disk of {self.folder} "
                f"(recordings keep {self.min_free / 1e9:.2f} GB free)")


__all__ = ["DEFAULT_MIN_FREE", "SpaceGuard"]
