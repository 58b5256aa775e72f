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
    jump: bool = False  # the motion does not continue the frame before (a looped clip starting again)


class MotionSource(Protocol):
    skeleton: Skeleton
    frame_time: float

    def __iter__(self) -> Iterator[PoseFrame]: ...

    def close(self) -> None: ...


class BVHSource:
    """Frames of a BVH file, read line by line.

    pace: "realtime" sleeps to the clip's frame rate (divided by `every`); "fast" does not wait.
      The schedule starts when the first frame is delivered (opening the file and the first
      parse take a moment). A consumer up to `max_lag` seconds behind (default: one frame time)
      gets the next frame at once; one further behind (a pause, a slow first retarget) shifts
      the schedule instead: a burst of late frames would only queue up downstream (a cloth
      service a few frames behind adds their whole backlog to every frame's latency).
    loop: start again from the first frame at the end (frame index and time keep counting; that
      frame says `jump`); loop_from: from this frame instead (of the frames taken: a clip whose
      first frame is its converter's T-pose, which a session skips, loops back to the frame after).
    every: take one frame in `every` (e.g. 2 turns the 120 Hz CMU clips into 60 Hz).
    """

    def __init__(self, path: str | Path, pace: str = "fast", loop: bool = False, every: int = 1,
                 unit: float = CMU_UNIT_M, max_frames: int | None = None, max_lag: float | None = None,
                 loop_from: int = 0):
        if pace not in ("realtime", "fast"):
            raise ValueError(f"pace must be 'realtime' or 'fast', got {pace!r}")
        if every < 1:
            raise ValueError(f"every must be >= 1, got {every}")
        if loop_from < 0:
            raise ValueError(f"loop_from must be >= 0, got {loop_from}")
        self.path = Path(path)
        self.loop_from = loop_from
        self.pace, self.loop, self.every, self.unit, self.max_frames = pace, loop, every, unit, max_frames
        self._clock: float | None = None  # perf_counter() of the session's time 0, set at the first frame
        self._reader = BVHReader(self.path, unit)
        self.header = self._reader.header
        self.skeleton = self.header.skeleton
        self.frame_time = self.header.frame_time * every
        self.max_lag = self.frame_time if max_lag is None else max_lag

    def close(self) -> None:
        self._reader.close()

    def hold(self, seconds: float) -> None:
        """Shift the real-time schedule by `seconds` (the consumer paused; no burst of late frames)."""
        if self._clock is not None:
            self._clock += seconds

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __iter__(self) -> Iterator[PoseFrame]:
        n_bones = len(self.skeleton.names)
        index = 0
        self._clock = None
        jump = False
        skip = 0  # frames of the clip not taken again on this pass (loop_from)
        while True:
            start = index
            for k, values in enumerate(self._reader.rows()):
                if k % self.every or k // self.every < skip:
                    continue
                if self.max_frames is not None and index >= self.max_frames:
                    return
                rot, pos = local_pose(self.header, values, np.empty((n_bones, 3, 3)), np.empty(3))
                t = index * self.frame_time
                if self.pace == "realtime":
                    now = time.perf_counter()
                    if self._clock is None:
                        self._clock = now - t
                    delay = self._clock + t - now
                    if delay > 0:
                        time.sleep(delay)
                    elif delay < -self.max_lag:
                        self._clock -= delay  # too far behind: this frame now, the next on schedule
                yield PoseFrame(index, t, rot, pos, jump)
                index += 1
                jump = False
            if not self.loop or index == start:  # (nothing taken: an empty clip, or loop_from beyond its end)
                return
            self._reader.close()
            self._reader = BVHReader(self.path, self.unit)
            jump = True  # from the clip's last pose back to its first (loop_from's)
            skip = self.loop_from
