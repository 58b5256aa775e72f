"""The polling helpers of services/spin.py and the garments stepped on them (services.cloth_job)."""

import os
import queue
import threading
import time
import weakref
from types import SimpleNamespace

import numpy as np
import pytest

from cloth.collision import BodyMesh, BodyPose
from cloth.surface import SurfaceSettings
from services.cloth_job import OUTFITS, OutfitSession, load_outfit_models
from services.spin import SpinPool, SpinWorker, check_cpus, default_cpus, spin_get
from skinning.animate import BodyAnimator
from skinning.body import body_clothed_faces, body_regions
from skinning.source import BVHSource


def test_spin_get_returns_what_arrives_while_it_polls_and_times_out_when_nothing_does():
    q = queue.Queue()
    threading.Timer(0.02, q.put, args=("frame",)).start()
    t0 = time.monotonic()
    assert spin_get(q, 0.2, 1.0) == "frame"  # arrives within the polling window
    assert time.monotonic() - t0 < 0.5
    threading.Timer(0.05, q.put, args=("late",)).start()
    assert spin_get(q, 0.01, 1.0) == "late"  # after the window: the blocking get takes it
    t0 = time.monotonic()
    with pytest.raises(queue.Empty):
        spin_get(q, 0.02, 0.05)
    assert 0.04 < time.monotonic() - t0 < 0.5


@pytest.mark.parametrize("spin", [0.0, 0.05])
def test_spin_worker_runs_each_call_and_hands_back_its_result_or_error(spin):
    w = SpinWorker(spin)
    try:
        for k in range(20):
            w.submit(lambda x: x * x, k)
            assert w.result() == k * k
            if k % 5 == 0:
                time.sleep(0.08)  # past the polling window: the worker has blocked, and wakes
        for k in range(2000):  # back to back: each call runs once and its own result comes back
            w.submit(lambda x: x + 1, k)
            assert w.result() == k + 1
        w.submit(lambda x: 1 // x, 0)
        with pytest.raises(ZeroDivisionError):
            w.result()
        w.submit(lambda x: x + 1, 1)  # still serving after an error
        assert w.result() == 2
        w.submit(lambda x: x, 1)
        with pytest.raises(RuntimeError):
            w.submit(lambda x: x, 2)  # one call at a time
        assert w.result() == 1
    finally:
        w.close()
    assert not w._thread.is_alive()


@pytest.mark.parametrize("spin", [0.0, 0.05])
def test_spin_worker_keeps_nothing_of_a_call_once_its_result_is_taken(spin):
    """An ended session's state must not stay alive in the shared helper threads."""

    class State:
        def step(self, arg):
            return Result()

    class Result:
        pass

    w = SpinWorker(spin)
    try:
        state = State()
        arg = State()
        w.submit(state.step, arg)
        result = w.result()
        refs = [weakref.ref(state), weakref.ref(arg), weakref.ref(result)]
        del state, arg, result
        time.sleep(0.1)  # the worker has gone idle (blocked, or polling)
        assert [r() for r in refs] == [None, None, None]
    finally:
        w.close()


def test_spin_pool_is_held_by_one_caller_at_a_time():
    pool = SpinPool(1, 0.0)
    try:
        workers = pool.acquire()
        assert workers is not None and len(workers) == 1
        assert pool.acquire() is None  # busy: the other caller steps alone
        pool.release()
        assert pool.acquire() is workers
        pool.release()
    finally:
        pool.close()


def test_a_garment_failing_on_a_helper_is_raised_and_leaves_the_pool_idle():
    """An error in a helper's garment reaches the caller of step_cloth after the other
    garments are done, and the pool can be acquired and used again."""
    session = OutfitSession.__new__(OutfitSession)  # the stepping logic alone, on stand-in garments
    pool = SpinPool(1, 0.0)
    session._pool, session._threads, session.sims = pool, 2, [None, None]
    session.garment_seconds, session._order, session._shares = np.zeros(2), [0, 1], {1: [[0, 1]], 2: [[0], [1]]}
    session.surfaces, session.over = [], []
    session.pose = SimpleNamespace(update_surface=lambda v, tips=True: None, update_queries=lambda: None)
    calls = []

    def step(k):
        calls.append(k)
        if k == 1 and len(calls) < 3:
            raise ValueError("garment 1 failed")
        return k

    session._step_garment = step
    try:
        with pytest.raises(ValueError, match="garment 1"):
            session.step_cloth(None, 1 / 60)
        assert sorted(calls) == [0, 1]
        assert session.step_cloth(None, 1 / 60) == [0, 1]  # the pool is usable again
        assert pool.acquire() is not None
        pool.release()
    finally:
        pool.close()


def test_the_callers_thread_steps_the_cheapest_garment():
    """The caller's thread also updates the body's queries: it steps the garment whose running
    average step time is the least, the helper the other, and the shares follow the averages
    when they change order."""
    session = OutfitSession.__new__(OutfitSession)  # the stepping logic alone, on stand-in garments
    pool = SpinPool(1, 0.0)
    session._pool, session._threads, session.sims, session.surfaces, session.over = pool, 2, [None, None], [], []
    session.garment_seconds, session._order = np.array([0.004, 0.003]), [0, 1]
    session._shares = session._share_out(session._order)
    session.pose = SimpleNamespace(update_surface=lambda v, tips=True: None, update_queries=lambda: None)
    threads = {}

    def step(k):
        threads[k] = threading.get_ident()
        return k

    session._step_garment = step
    try:
        assert session.step_cloth(None, 1 / 60) == [0, 1]
        assert threads[1] == threading.get_ident() != threads[0]
        session.garment_seconds[:] = (0.002, 0.003)
        assert session.step_cloth(None, 1 / 60) == [0, 1]
        assert threads[0] == threading.get_ident() != threads[1]
        assert session._shares[1] == [[0, 1]]  # helpers busy: the caller steps both
    finally:
        pool.close()


@pytest.mark.parametrize("outfit_name", [OUTFITS[0], "female_sportsuit01"])
def test_garments_stepped_on_helper_threads_match_one_thread_bit_for_bit(body, data, outfit_name):
    """The casual and the sport outfit (two garments each, coarse and detailed) over 12
    run-clip frames: on one thread; on a helper thread beside the caller (own pool, and a
    shared polling pool); and with the shared pool held by someone else (the frame falls back
    to one thread). Each garment is handed to on_garment once a frame, done, on the thread that
    stepped it (the caller's: the one of least average step time so far), but a garment worn
    over or under another (the casual outfit's T-shirt and jeans, layered once both are done)
    on the caller's."""
    with BVHSource(data / "mocap" / "cmu_npybvh_example_75f.bvh", every=2, max_frames=14) as source:
        animator = BodyAnimator(body, source.skeleton)
        frames = [animator(f.local_rot, f.root_position).vertices.copy() for f in source][2:]
    mesh = BodyMesh.build(body.triangles, body.n_visible, body_regions(body), body_clothed_faces(body))
    outfit = load_outfit_models(body, animator, mesh, data / "garments" / outfit_name)
    shared = SpinPool(1, 0.01)
    runs = []
    try:
        for threads, pool, hold in ((1, None, False), (2, None, False), (2, shared, False), (2, shared, True)):
            session = OutfitSession(body, animator, mesh, outfit, SurfaceSettings(level=3), threads=threads, pool=pool)
            if hold:
                assert shared.acquire() is not None
            try:
                for v in frames:
                    handed = []
                    cheapest = int(np.argmin(session.garment_seconds))  # stepped on the caller's thread

                    def on_garment(k, x, session=session, handed=handed):
                        p, n = session.garment_surface(k)
                        handed.append((k, threading.get_ident(), x.copy(), p.copy()))

                    session.step_cloth(v, 1 / 60, on_garment=on_garment)
                    assert sorted(k for k, *_ in handed) == [0, 1]
                    helper_used = threads == 2 and not hold
                    assert bool(session.layered_garments) == (outfit_name == OUTFITS[0])
                    for k, ident, x, p in handed:
                        on_helper = helper_used and k != cheapest and k not in session.layered_garments
                        assert (ident != threading.get_ident()) == on_helper
                        np.testing.assert_array_equal(x, session.sims[k].state.x)
                        np.testing.assert_array_equal(p, session.detailed[k][0])
            finally:
                if hold:
                    shared.release()
                session.close()
            runs.append([p.copy() for p, _ in session.detailed] + [s.state.x.copy() for s in session.sims])
    finally:
        shared.close()
    for other in runs[1:]:
        for a, b in zip(runs[0], other):
            np.testing.assert_array_equal(a, b)


def test_a_pose_updated_in_two_parts_on_two_threads_equals_one_update(body):
    """BodyPose.update_surface, then update_queries on another thread while a garment waits
    for them (wait_queries): the same normals, grid and tree as update(); the waiting thread
    computes the face tips meanwhile (where the pose's tips are wanted), the same as face_tips()
    after update(), which computes none; a failed query update releases the waiter with an error
    instead of leaving it blocked."""
    mesh = BodyMesh.build(body.triangles, body.n_visible, body_regions(body), body_clothed_faces(body))
    rng = np.random.default_rng(3)
    poses = [body.vertices + rng.normal(0.0, 0.002, body.vertices.shape) for _ in range(2)]
    whole, split = BodyPose(mesh, tips=True), BodyPose(mesh, tips=True)
    for v in poses:
        whole.update(v)
        assert not whole.face_tip.any()  # (update() computes no tips: nobody waited)
        split.update_surface(v)
        np.testing.assert_array_equal(split.face_n, whole.face_n)
        worker = threading.Timer(0.05, split.update_queries)
        worker.start()
        split.face_tip[:] = 0.0
        split.wait_queries()  # blocks until the other thread is done, computing the tips first
        worker.join()
        assert split.face_tip.any()
        np.testing.assert_array_equal(split.face_tip, whole.face_tips())
        whole.face_tip[:] = 0.0
        split.update_surface(v, tips=False)  # a pose no detailed surface asks the tips of
        split.face_tip[:] = 0.0
        worker = threading.Timer(0.05, split.update_queries)
        worker.start()
        split.wait_queries()
        worker.join()
        assert not split.face_tip.any()
        for a, b in zip(split.grid.arrays()[1:], whole.grid.arrays()[1:]):
            np.testing.assert_array_equal(a, b)
        for a, b in zip(split.face_tree_arrays(), whole.face_tree_arrays()):
            np.testing.assert_array_equal(a, b)
    split.update_surface(poses[0])
    split.grid = None  # its update fails
    worker = threading.Thread(target=lambda: pytest.raises(AttributeError, split.update_queries))
    worker.start()
    with pytest.raises(RuntimeError, match="grid or face tree"):
        split.wait_queries()
    worker.join()


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="thread affinity is Linux-only")
def test_pool_workers_keep_to_their_cores_and_bad_core_lists_are_refused():
    cores = sorted(os.sched_getaffinity(0))
    pool = SpinPool(1, 0.0, cpus=[cores[-1]])
    try:
        worker = pool.workers[0]
        worker.submit(lambda _: os.sched_getaffinity(0), None)  # 0: the calling thread, the worker's
        assert worker.result() == {cores[-1]}
        assert os.sched_getaffinity(0) == set(cores)  # the caller is left as it was
    finally:
        pool.close()
    assert check_cpus([cores[0]]) == [cores[0]]
    for bad, problem in (([], "at least one"), ([cores[0], cores[0]], "distinct"),
                         ([max(cores) + 1], "not among this process's cores")):
        with pytest.raises(ValueError, match=problem):
            check_cpus(bad)
    with pytest.raises(ValueError, match="2 workers, 1 cores"):
        SpinPool(2, 0.0, cpus=[cores[0]])


def test_a_live_cloth_service_pins_its_threads_to_the_process_cores_by_default(monkeypatch):
    """default_cpus: every allowed core in order where there are two or more; None (unpinned)
    with one core, or where the platform cannot pin threads."""
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {3, 1}, raising=False)
    monkeypatch.setattr(os, "sched_setaffinity", lambda pid, cpus: None, raising=False)
    assert default_cpus() == [1, 3]
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {2}, raising=False)
    assert default_cpus() is None
    monkeypatch.delattr(os, "sched_setaffinity")
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    assert default_cpus() is None


def test_cloth_service_cli_rejects_bad_core_lists():
    from services.cli import main

    for value, problem in (("0,0", "distinct"), ("x", "invalid literal"), ("4096", "not among")):
        with pytest.raises(SystemExit, match=f"--pin-cores '{value}': .*{problem}"):
            main(["cloth-service", "--pin-cores", value])
