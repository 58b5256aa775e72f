"""Waiting without falling asleep: helpers that poll for a while before they block.

A thread that blocks until the next 60 Hz frame leaves its core idle for about 10 ms, and on a
virtual machine an idle virtual CPU is descheduled: waking it again took about 1 ms here
(p99 3 ms; 55 µs when it had not been idle), and a garment stepped on it started that much
later. So a thread that expects work soon polls for it, for `spin` seconds after its last work,
and only then blocks. OpenMP runtimes do the same (Intel's spins 200 ms by default).

Between polls it calls `sched_yield()` (which releases the GIL): the scheduler then runs
whatever else is runnable on that core first. `time.sleep(0)` did not: the scheduler treated
the poller as one more busy thread, and when it shared a core with a garment's thread the
garment waited out the poller's time slices, 3-4 ms in one garment-step of ten (measured as
the garment thread's run-queue wait, `/proc/self/task/<id>/schedstat`; p99 latency at 60 Hz
12 ms, 9 ms with `sched_yield`).
"""

from __future__ import annotations

import os
import queue
import threading
import time
from typing import Any, Callable

LIVE_SPIN = 0.02  # s: how long a live service polls after a frame (covers the 16.7 ms of 60 Hz)

_yield = getattr(os, "sched_yield", None) or (lambda: time.sleep(0))  # sched_yield: Unix only


def spin_get(q: queue.Queue, spin: float, timeout: float) -> Any:
    """q.get(timeout=timeout), polling the first `spin` seconds of the wait (raises queue.Empty)."""
    if spin > 0.0:
        end = time.monotonic() + min(spin, timeout)
        while True:
            try:
                return q.get_nowait()
            except queue.Empty:
                if time.monotonic() >= end:
                    break
                _yield()
        timeout = max(0.0, timeout - spin)
    return q.get(timeout=timeout)


class SpinWorker:
    """One helper thread that runs the calls given to it, one at a time, polling for the next
    one for `spin` seconds after each before it blocks. `submit(fn, arg)` then `result()`:
    the caller runs its own share of the work in between."""

    def __init__(self, spin: float, name: str = "spin-worker"):
        self.spin = spin
        self._job: tuple[int, Callable, Any] | None = None  # (sequence number, fn, arg): read in one go
        self._seq = 0
        self._pending = False
        self._result: Any = None
        self._error: BaseException | None = None
        self._done = threading.Event()
        self._wake = threading.Event()
        self._stop = False
        self._last = time.monotonic()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, fn: Callable, arg: Any) -> None:
        if self._pending:
            raise RuntimeError("SpinWorker: submit() before the last result() was taken")
        self._pending = True
        self._done.clear()
        self._seq += 1
        self._job = (self._seq, fn, arg)
        self._wake.set()

    def result(self) -> Any:
        """Wait (polling, then blocking) for the submitted call; re-raises its exception."""
        end = time.monotonic() + self.spin
        while not self._done.is_set() and time.monotonic() < end:
            _yield()
        self._done.wait()
        self._pending = False
        # nothing of the call stays referenced here: an ended session's models and state are freed
        self._job = None
        result, self._result = self._result, None
        if self._error is not None:
            err, self._error = self._error, None
            raise err
        return result

    def close(self) -> None:
        self._stop = True
        self._wake.set()
        self._thread.join(5.0)

    def _run(self) -> None:
        ran = 0  # the sequence number of the last call run: each runs once
        while not self._stop:
            job = self._job
            if job is None or job[0] == ran:
                job = None  # not held while idle
                if time.monotonic() - self._last < self.spin:
                    _yield()
                else:
                    self._wake.wait()
                    self._wake.clear()
                continue
            ran, fn, arg = job
            job = None
            try:
                self._result = fn(arg)
            except BaseException as err:  # noqa: BLE001 - handed to the caller of result()
                self._error = err
            fn = arg = None
            self._last = time.monotonic()
            self._done.set()


class SpinPool:
    """Helper threads shared by whoever holds the pool: `acquire()` gives the workers (or None
    while another thread holds them), `release()` hands them back."""

    def __init__(self, workers: int, spin: float, name: str = "garment"):
        self.workers = [SpinWorker(spin, name=f"{name}-{r + 1}") for r in range(workers)]
        self._lock = threading.Lock()

    def acquire(self) -> list[SpinWorker] | None:
        return self.workers if self._lock.acquire(blocking=False) else None

    def release(self) -> None:
        self._lock.release()

    def close(self) -> None:
        with self._lock:
            for w in self.workers:
                w.close()
            self.workers = []
