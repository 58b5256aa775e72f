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


def pin_to_cpu(cpu: int) -> None:
    """Keep the calling thread on one core (Linux: the affinity of a thread, not its process).

    A pinned garment thread is never moved onto the other garment's core, where the two would
    share it until the load balancer parts them: on this project's 2-core machine, with the
    service's two threads pinned apart, the 60 Hz latency's p99 came to 8.1-9.3 ms against
    8.7-10.1 ms unpinned (three alternating pairs of runs, ninth session). `check_cpus` says
    beforehand whether the platform and the cores allow it."""
    os.sched_setaffinity(0, {cpu})


def check_cpus(cpus) -> list[int]:
    """cpus as a list of distinct cores this process may run on; ValueError naming the problem."""
    cpus = list(cpus)
    if not hasattr(os, "sched_getaffinity"):
        raise ValueError("pinning threads to cores needs os.sched_setaffinity (Linux)")
    allowed = os.sched_getaffinity(0)
    if not cpus or len(set(cpus)) != len(cpus):
        raise ValueError(f"cores to pin to must be distinct and at least one, got {cpus}")
    bad = [c for c in cpus if c not in allowed]
    if bad:
        raise ValueError(f"cores {bad} are not among this process's cores {sorted(allowed)}")
    return cpus


def default_cpus() -> list[int] | None:
    """The cores a live cloth service keeps its threads to by default: every core this process
    may run on, in order, where there are two or more and threads can be pinned (Linux); else
    None (unpinned). Unpinned, the scheduler put both garment threads of a frame on one core now
    and then, one waiting out the other's whole step: about 4 ms of run-queue wait (read from
    /proc/thread-self/schedstat) in the frames that made the 60 Hz p99 (sixteenth session)."""
    if not hasattr(os, "sched_getaffinity") or not hasattr(os, "sched_setaffinity"):
        return None
    cpus = sorted(os.sched_getaffinity(0))
    return cpus if len(cpus) >= 2 else None


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

    def __init__(self, spin: float, name: str = "spin-worker", cpu: int | None = None):
        """cpu: the core the thread keeps to (`pin_to_cpu`), or None: wherever the scheduler puts it."""
        self.spin = spin
        self.cpu = cpu
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
        if self.cpu is not None:
            pin_to_cpu(self.cpu)
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

    def __init__(self, workers: int, spin: float, name: str = "garment", cpus: list[int] | None = None):
        """cpus: one core per worker to keep to (see `pin_to_cpu`), or None."""
        if cpus is not None and len(cpus) != workers:
            raise ValueError(f"SpinPool: {workers} workers, {len(cpus)} cores to pin them to")
        self.workers = [SpinWorker(spin, name=f"{name}-{r + 1}", cpu=None if cpus is None else cpus[r])
                        for r in range(workers)]
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
