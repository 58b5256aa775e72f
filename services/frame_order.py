"""The order of one stream's frames: a session's body frames at the cloth service, a capture's
poses at the ingest.

Each frame must come after the last one taken. Zenoh keeps the order of one key's samples, so a
frame at or before it is a stray (a duplicate, a second publisher on the key) and is rejected.
Frames may skip numbers (a paused capture resumes later in its numbering), so there is no bound
on how far ahead the next one may be, and a frame numbered far ahead (a second publisher, a
corrupt counter) would have every real frame after it rejected. A stream does not go back, and
a stray does not go on: `RESYNC_FRAMES` frames in a row behind the last one taken, each after
the one before (not every frame need reach a consumer that takes the newest), are the stream
going on from there, and the last of them is taken.
"""

from __future__ import annotations

from .protocol import MessageError


class FrameOrder:
    RESYNC_FRAMES = 3

    def __init__(self) -> None:
        self.last = -1  # the last frame taken
        self._behind = 0  # frames in a row behind `last`, each after the one before
        self._behind_last = -1

    def take(self, frame: int, key_expr: str) -> int | None:
        """Take `frame` as the stream's next, or raise MessageError naming key_expr where it is
        a stray. Returns the frame the order jumped back from where this frame is the one that
        shows the stream going on behind it (None otherwise)."""
        if frame > self.last:
            self.last, self._behind = frame, 0
            return None
        self._behind = self._behind + 1 if self._behind and frame > self._behind_last else 1
        self._behind_last = frame
        if self._behind < self.RESYNC_FRAMES:
            raise MessageError(key_expr, f"frame {frame} arrives after frame {self.last}")
        jumped_from, self.last, self._behind = self.last, frame, 0
        return jumped_from
