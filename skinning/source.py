"""Motion sources: poses arrive one frame at a time, from a file or (later) a live stream.

A source exposes the person's `skeleton` (rest pose, metres, canonical bone names)
and its `frame_time`, and iterates `PoseFrame`s. The rest of the system never needs
the whole clip in memory.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Protocol

import numpy as np

from .bvh import CMU_UNIT_M, BVHReader, local_pose
from .skeleton import Skeleton


@dataclass
class PoseFrame:
    index: int  # frame number in the session (keeps counting across loops)
    time: float  # seconds since the session's first frame
    local_rot: np.ndarray  # (n, 3, 3) each joint's rotation relative to its parent (rest = identity)
    root_position: np.ndarray  # (3,) metres, root joint translation


class MotionSource(Protocol):
    skeleton: Skeleton
    frame_time: float

    def __iter__(self) -> Iterator[PoseFrame]: ...

    def close(self) -> None: ...


class BVHSource:
    """Frames of a BVH file, read line by line.

    pace: "realtime" sleeps to the clip's frame rate (divided by `every`); "fast" does not wait.
    loop: start again from the first frame at the end (frame index and time keep counting).
    every: take one frame in `every` (e.g. 2 turns the 120 Hz CMU clips into 60 Hz).
    """

    def __init__(self, path: str | Path, pace: str = "fast", loop: bool = False, every: int = 1,
                 unit: float = CMU_UNIT_M, max_frames: int | None = None):
        if pace not in ("realtime", "fast"):
            raise ValueError(f"pace must be 'realtime' or 'fast', got {pace!r}")
        if every < 1:
            raise ValueError(f"every must be >= 1, got {every}")
        self.path = Path(path)
        self.pace, self.loop, self.every, self.unit, self.max_frames = pace, loop, every, unit, max_frames
        self._reader = BVHReader(self.path, unit)
        self.header = self._reader.header
        self.skeleton = self.header.skeleton
        self.frame_time = self.header.frame_time * every

    def close(self) -> None:
        self._reader.close()

    def hold(self, seconds: float) -> None:
        """Shift the real-time schedule by `seconds` (the consumer paused; no burst of late frames)."""
        self._clock = getattr(self, "_clock", time.perf_counter()) + seconds

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __iter__(self) -> Iterator[PoseFrame]:
        n_bones = len(self.skeleton.names)
        index = 0
        self._clock = time.perf_counter()
        while True:
            for k, values in enumerate(self._reader.rows()):
                if k % self.every:
                    continue
                if self.max_frames is not None and index >= self.max_frames:
                    return
                rot, pos = local_pose(self.header, values, np.empty((n_bones, 3, 3)), np.empty(3))
                t = index * self.frame_time
                if self.pace == "realtime":
                    delay = self._clock + t - time.perf_counter()
                    if delay > 0:
                        time.sleep(delay)
                yield PoseFrame(index, t, rot, pos)
                index += 1
            if not self.loop or index == 0:
                return
            self._reader.close()
            self._reader = BVHReader(self.path, self.unit)
