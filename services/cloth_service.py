"""cloth: subscribe to every session's body frames, run S101-S106 per garment, publish the meshes.

One worker thread consumes the body frames of all sessions in arrival order (each session keeps
its own simulation state). Frames are never skipped: when the service falls behind, the queue
holds the backlog and the service catches up at full speed with the same fixed time step, so the
simulation sees exactly the frames it would have seen in real time (and a replayed body stream
gives bit-identical garments).

A session starts with its announcement (tryon/<s>/session: outfit, fabric, level and the first
pose): the service fits the outfit on the rest body and settles it into that pose (pre-roll),
reports it ready, then publishes tryon/<s>/garment/<name> per frame and latches each garment's
topology. The fitting and pre-roll (about a second) run on a setup thread, so the sessions
already running keep their frame rate while a new one joins; body frames of a session still
being set up wait for it, in order. A session that starts without an announcement (its first
body frame comes first) reads the latched description and settles into that frame's pose.

Announcements, body frames and control messages come on three subscribers, each with a thread
of its own (zenoh-python's callbacks): each key's messages keep their order, the three keys'
do not among each other. A session announced again (an outfit change, a looped clip starting
over) names the last frame its ingest published before (`after_frame`); the announcement waits
until that frame is in (DEFER_SECONDS at most), so those frames are stepped with the garments
they were meant for, and whatever came for the session meanwhile waits behind it. The other
way round, each body frame names the announcement it follows (`run`; a replay sends frames
without waiting for "ready"): a frame of an announcement not yet here waits for it
(ANNOUNCEMENT_SECONDS at most: an announcement is sent so that it is never dropped, so it is
late, never lost).
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numba
import numpy as np
import zenoh

from cloth.fabric import fabric_choice
from cloth.geometry import vertex_normals
from cloth.pn import load_resample_heights
from cloth.surface import SurfaceSettings
from skinning.animate import BodyAnimator
from skinning.body import Body

from .bus import Latched, Stats, fetch_latched, key, parse_key, put_reliably
from .cloth_job import GARMENT_COLORS, Outfit, OutfitSession, build_outfit, collision_body, find_outfit
from .frame_budget import LevelGovernor
from .frame_order import FrameOrder
from .heap import freeze_heap, reclaim_heap
from .model_cache import ModelCache, object_digest
from .protocol import MAX_LEVEL, Message, MessageError, decode, encode
from .spin import SpinPool, check_cpus, pin_to_cpu, spin_get
from .wire import CompactMesh, body_vertices, vertex_count

log = logging.getLogger("tryon.cloth")


@dataclass
class Hold:
    """A session's messages held until what they wait for is in (`ClothService.DEFER_SECONDS` or
    `ANNOUNCEMENT_SECONDS` at most): an announcement that came ahead of the body frames before it
    waits for frame `frame` (its `after_frame`; -1: none), body frames that came ahead of their
    announcement wait for announcement `run` (-1: none); what comes for the session meanwhile
    waits behind them."""

    frame: int
    run: int
    deadline: float
    messages: list[tuple[str, bytes, bool]]

    def lets_through(self, msg: Message) -> bool:
        """Whether msg is what the hold waits for (not held behind it)."""
        return (msg.kind == "body" and msg.frame <= self.frame) or (msg.kind == "session" and self.run >= 0)


def run_of(desc: dict) -> int:
    """Which of its session's announcements a description is (`run`; 0 if it does not say)."""
    run = desc.get("run", 0)
    return run if isinstance(run, int) and not isinstance(run, bool) else 0


def _yielding_thread() -> None:
    """A thread whose work no frame waits for: it yields the cores to the serving threads (a
    lower scheduling priority, where the system allows it) and runs numba's parallel kernels
    (the animator's skinning) on itself alone."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 10)
    except (AttributeError, OSError):
        pass
    numba.set_num_threads(1)


@dataclass(frozen=True)
class OutfitSpec:
    outfit: str
    fabric: str | None = None  # a preset for every garment, or garment=preset pairs (`fabric_choice`); None: defaults
    level: int | None = 6  # PN tessellation level; None: coarse cloth only

    @staticmethod
    def from_description(d: dict, default: "OutfitSpec", key_expr: str) -> "OutfitSpec":
        outfit = d.get("outfit", default.outfit)
        fabric = d.get("fabric", default.fabric)
        level = d.get("level", default.level)
        if not isinstance(outfit, str) or not outfit:
            raise MessageError(key_expr, f"session 'outfit' must be a name, got {outfit!r}")
        if fabric is not None and not isinstance(fabric, str):
            raise MessageError(key_expr, f"session 'fabric' must be a preset name, garment=preset pairs or null, "
                                            f"got {fabric!r}")
        if level is not None and (isinstance(level, bool) or not isinstance(level, int) or not 1 <= level <= MAX_LEVEL):
            raise MessageError(key_expr, f"session 'level' must be an integer 1-{MAX_LEVEL} or null, got {level!r}")
        return OutfitSpec(outfit, fabric, level)


class GarmentSession:
    """One session's cloth: its own simulation state, publishers and stats."""

    def __init__(self, service: "ClothService", session: str, spec: OutfitSpec, frame_time: float):
        self.service, self.session, self.spec, self.dt = service, session, spec, frame_time
        outfit, surface_models, layers = service.outfit_models(spec)
        self.sim = OutfitSession(service.body, service.animator, service.body_mesh, outfit,
                                 surface_models=surface_models, pool=service.garment_pool, layers=layers)
        self.names = [m.name for m in outfit.models]
        self.stats = Stats(ClothService.SERVICE, session)
        self.stats.values["garments"] = len(self.names)
        bus = service.bus
        self.latched = Latched(bus)
        # a display that lags must not hold the cloth back: garment frames are dropped for it
        self.publishers = [bus.declare_publisher(key(session, "garment", n),
                                                 congestion_control=zenoh.CongestionControl.DROP)
                           for n in self.names]
        self._coarse_normals = [np.empty((m.n_particles, 3)) for m in outfit.models]
        self.level = spec.level  # the detailed surfaces' level now (a frame budget may lower it)
        # the level that holds the frame budget (`services.frame_budget`; None: the announced level, always)
        self.governor = (LevelGovernor(service.frame_budget, spec.level, **service.governor_settings)
                         if service.frame_budget is not None and spec.level is not None else None)
        self._level_job: tuple[int, Future] | None = None  # another level's models being built
        self._least_wait = np.inf  # ns: the least a body frame waited from its stamp to its step (on_body)
        if self.governor is not None:
            load_resample_heights()  # (set up here, not at the first change of level, which a frame waits for)
            # the levels below, built here too (0.8-1.2 s each for the casual outfit, read back from the model
            # cache after): a machine slow enough to need them leaves the low-priority background thread
            # little time, and the stream waits for this setup, not for a change of level
            for level in range(spec.level - 1, self.governor.bottom - 1, -1):
                service.outfit_models(replace(spec, level=level))
        self.stats.values["level"] = spec.level
        self.body_x = np.empty((service.body.n_visible, 3))
        self.order = FrameOrder()  # of the body frames stepped
        self.seen_frame = -1  # the newest body frame that reached it, stepped or rejected
        self.run = 0  # which of the session's announcements its garments are from (`run` in the description)
        self.started = False
        self.skin_contact = True
        self.announced_ns = 0  # stamp of the announcement it was set up from (0: none)
        self.start_q: np.ndarray | None = None  # the pose the garments were settled into,
        self.start_state = None  # and their state then (cloth.snapshot.StateSnapshot)
        self._loop_job: Future | None = None  # ... or that state being settled in the background
        self.closing = threading.Event()  # closed (a background settling for it stops)
        self.end_frame: int | None = None  # set by the session's end message
        self.skipped_since = 0  # frames stepped without their surface since the last published one
        self._msg: Message | None = None  # the body frame being stepped (read by _publish_garment)
        self._first = False  # ... and whether it is the session's first
        self.last_seen = time.monotonic()
        self._prepare_output()
        self.latch(ready=False)

    def _prepare_output(self) -> None:
        """The wire buffers (reused every frame) and the latched topology of the garments at this level."""
        models = self.sim.outfit.models
        if self.sim.surfaces:
            n_out = [sf.model.n_vertices for sf in self.sim.surfaces]
        else:
            n_out = [m.n_particles for m in models]
        float32 = self.service.float32_meshes
        self._p32 = [np.empty((n, 3), np.float32) for n in n_out] if float32 else None
        self._n32 = [np.empty((n, 3), np.float32) for n in n_out] if float32 else None
        self._compact = None if float32 else [CompactMesh(n) for n in n_out]
        self._topology = []
        for k, (n, m) in enumerate(zip(self.names, models)):
            tris = self.sim.surfaces[k].model.tess.triangles if self.sim.surfaces else m.triangles
            topo = Message("topology", self.session,
                           arrays={"triangles": np.ascontiguousarray(tris, dtype=np.int32)},
                           meta={"what": "garment", "garment": n, "fabric": m.fabric.name,
                                 "color": list(GARMENT_COLORS[k % len(GARMENT_COLORS)]),
                                 "level": self.level, "n_vertices": int(tris.max()) + 1})
            self._topology.append((key(self.session, "topology", "garment", n), encode(topo)))

    def _set_level(self, surface_models: list, layers: list) -> None:
        """Go on at another level (its surface models and layer pairs): each garment's wrinkles
        carried over (`OutfitSession.change_level`), its new topology latched before the first
        frame that has it (a display that sees a frame of another size reads the topology again)."""
        before = self.level
        self.sim.change_level(surface_models, layers)
        self.level = self.sim.level
        self._prepare_output()
        self.latch(ready=False)
        if self.governor is not None:
            self.governor.changed(self.level)
        self.stats.values["level"] = self.level
        self.stats.add("level_changes")
        log.info("cloth: session %s: level %s -> %s (frame budget %s ms)", self.session, before, self.level,
                 None if self.governor is None else round(self.governor.budget * 1000, 2))

    def _take_level(self) -> None:
        """Another level, once its models are built (on the service's background thread)."""
        want, job = self._level_job
        if not job.done():
            return
        self._level_job = None
        try:
            _, surface_models, layers = job.result()
        except Exception:  # noqa: BLE001 - the session keeps its level
            log.exception("cloth: session %s: building level %d failed; it stays at level %s", self.session, want,
                          self.level)
            self.governor = None
            return
        self._set_level(surface_models, layers)

    def _back_to_announced_level(self) -> None:
        """The announced level's surfaces again (the ones it was settled with: a snapshot of its
        start restores onto them)."""
        self._level_job = None
        if self.level != self.spec.level:  # (its models are the session's own: no wait on the background's build)
            self._set_level(*self.sim.models_at(self.spec.level))

    def latch(self, ready: bool = True) -> None:
        """Latch each garment's topology, and (ready) the session's status: ready, as set up."""
        for k, payload in self._topology:
            self.latched.publish(k, payload)
        if ready:
            self._report_ready()

    def unlatch(self) -> None:
        """No longer answer for the session's topology and status (another outfit is being set up
        for it; `latch` answers again)."""
        self.latched.close()

    def preroll(self, q: np.ndarray, loop_q: np.ndarray | None = None) -> None:
        """Settle the garments from the rest pose into pose q, then tell the session we are ready.
        The settled garments are kept (`restart`); loop_q: the ones settled into that pose
        instead (the pose a looped clip comes back to, announced with an outfit change). Those are
        settled after the session is ready, on the service's background thread, while its frames
        stream (`ClothService.settle_later`): the change's pause holds one pre-roll, not two."""
        t0 = time.perf_counter()
        q = np.array(q, dtype=np.float64)
        with self.service.animator_lock:  # the service's one animator poses the blend
            self.sim.preroll(q, self.dt, contact=self.skin_contact)
        if loop_q is not None and not np.array_equal(loop_q, q):
            self.start_q, self.start_state = loop_q, None
            self._loop_job = self.service.settle_later(self, loop_q)
        else:
            self.start_q, self.start_state = q, self.sim.snapshot()
        self.stats.values["preroll_s"] = round(time.perf_counter() - t0, 3)
        self.started = True
        self._report_ready()

    def _start_state(self):
        """The garments as settled into start_q (None: not available), once the background
        settling of a loop pose is done (waited for here if it is not)."""
        self._back_to_announced_level()  # (the snapshot is of its states)
        job, self._loop_job = self._loop_job, None
        if job is not None:
            try:
                snapshot = job.result()
            except Exception:  # noqa: BLE001 - the loop then fits and settles the garments afresh
                log.exception("cloth: session %s: settling the garments into the loop's pose failed", self.session)
                snapshot = None
            if snapshot is None:
                self.start_q = None
            else:  # settled in another session of the same models: its values into this one's arrays
                self.start_state = snapshot.onto(*self.sim.states())
        return self.start_state

    def _report_ready(self) -> None:
        # announced_ns: which announcement this answers (an ingest that changed the outfit waits
        # for the new one's, while the old one's may still be latched)
        ready = Message("control", self.session, meta={"event": "ready", "from": "cloth", "garments": self.names,
                                                       "outfit": self.spec.outfit, "announced_ns": self.announced_ns})
        self.latched.publish(key(self.session, "status", "cloth"), encode(ready))

    def starts_again_as_before(self, desc: dict) -> bool:
        """Whether an announcement of this session asks for the garments exactly as they were
        settled at its start: the same outfit, fabric, level, frame time and skin contact, and
        the same first pose bit for bit (a looped clip starting again; services.ingest)."""
        if self._start_state() is None:
            return False
        try:
            spec = OutfitSpec.from_description(desc, self.service.default, key(self.session, "session"))
        except MessageError:
            return False  # (the setup that follows names what is wrong)
        q = desc.get("first_q")
        return (spec == self.spec and desc.get("frame_time", 1 / 60) == self.dt
                and desc.get("skin_contact", True) == self.skin_contact and isinstance(q, list)
                and len(q) == len(self.start_q) and all(isinstance(v, (int, float)) for v in q)
                and np.array_equal(np.array(q, dtype=np.float64), self.start_q))

    def restart(self, announced_ns: int, run: int) -> None:
        """The garments back as they were settled at the session's start (`starts_again_as_before`),
        at once: what fitting and settling them again would give, bit for bit, without the
        second's pause."""
        self._start_state().restore()
        self.announced_ns, self.run = announced_ns, run
        self.skipped_since = 0
        self.stats.add("restarts")
        self._report_ready()

    def start_from_description(self, desc: dict, key_expr: str) -> None:
        contact = desc.get("skin_contact", True)
        if not isinstance(contact, bool):
            raise MessageError(key_expr, f"'skin_contact' must be true or false, got {contact!r}")
        self.skin_contact = contact  # the pre-roll's blend is skinned as the ingest skins the frames
        q = desc.get("first_q")
        if q is None:
            return  # no first pose announced: the first body frame starts the session
        nq = self.service.animator.character.model.nq
        loop_q = desc.get("loop_q")
        for name, v in (("first_q", q), ("loop_q", loop_q)):
            if name == "loop_q" and v is None:
                continue  # (optional)
            if not isinstance(v, list) or len(v) != nq or not all(isinstance(a, (int, float)) for a in v):
                raise MessageError(key_expr, f"'{name}' must list the character's {nq} configuration values")
        self.preroll(np.array(q, dtype=np.float64), None if loop_q is None else np.array(loop_q, dtype=np.float64))

    def on_body(self, msg: Message, key_expr: str, publish: bool = True) -> None:
        """Step the cloth to this body frame. publish=False (catching up): S101 only, no surface and
        no garment message; the next published frame's surface step spans the skipped frames."""
        svc = self.service
        q = msg.arrays["q"]
        if vertex_count(msg.arrays) != svc.body.n_visible:
            raise MessageError(key_expr, f"body has {vertex_count(msg.arrays)} vertices, this service's body has "
                                         f"{svc.body.n_visible}")
        if q.shape[0] != svc.animator.character.model.nq:
            raise MessageError(key_expr, f"q has {q.shape[0]} values, the character needs "
                                         f"{svc.animator.character.model.nq}")
        last = self.order.last
        jumped_from = self.order.take(msg.frame, key_expr)
        if jumped_from is not None:
            log.warning("cloth: %s: %d frames in a row came behind frame %d, a stray: the session goes on from "
                        "frame %d", key_expr, FrameOrder.RESYNC_FRAMES, jumped_from, msg.frame)
            self.stats.add("resyncs")
            self.seen_frame = msg.frame
        elif last >= 0 and msg.frame != last + 1:
            self.stats.add("gaps")
        body_vertices(msg.arrays, out=self.body_x)  # (compact: decoded straight into it)
        first = not self.started
        if first:  # joined without the announcement: settle the garments into this first pose
            self.preroll(q)
        if self._level_job is not None and publish:
            self._take_level()
        self._msg, self._first = msg, first
        # how long the frame waited before its step, as far as the clocks tell (the least wait seen is
        # the trip, with any offset between the ingest's clock and this one's): a frame budget counts the
        # wait beyond it, so frames queued behind slow steps (or another session's) lower the level too
        waited = time.time_ns() - msg.stamp_ns
        self._least_wait = min(self._least_wait, waited)
        t0 = time.perf_counter()
        try:
            # each garment is published from the thread that stepped it, as soon as it is done
            self.sim.step_cloth(self.body_x, self.dt, surface=publish, surface_dt=self.dt * (self.skipped_since + 1),
                                on_garment=self._publish_garment if publish else None)
        finally:
            self._msg = None
        step_ms = (time.perf_counter() - t0) * 1000
        self.stats.add("received")
        if not publish:
            self.skipped_since += 1
            self.stats.add("skipped")
            return
        self.skipped_since = 0
        if self.governor is not None and self._level_job is None and not first:
            want = self.governor.observe(step_ms / 1000 + (waited - self._least_wait) / 1e9)
            if want is not None:
                self._level_job = (want, svc.models_later(replace(self.spec, level=want)))
        self.stats.values.update(step_ms=round(step_ms, 3), backlog=svc.backlog(),
                                 latency_ms=round((time.time_ns() - msg.stamp_ns) / 1e6, 3))
        self.stats.publish(svc.bus)

    def _publish_garment(self, k: int, positions: np.ndarray) -> None:
        """Garment k of the body frame being stepped, encoded and published (on the thread that
        stepped it; each garment has its own buffers and publisher)."""
        msg, sim = self._msg, self.sim
        if sim.surfaces:
            p, n = sim.garment_surface(k)
        else:
            p = positions
            n = self._coarse_normals[k]
            vertex_normals(p, sim.outfit.models[k].triangles, n)
        meta = {"garment": self.names[k], "s101_ms": round(float(sim.cloth_seconds[k]) * 1000, 4),
                "resets": int(sim.sims[k].stats.reset_particles), "level": self.level}
        if self._first:
            meta["preroll_s"] = self.stats.values["preroll_s"]
        if sim.surfaces:
            pn, col, deform = (float(x) * 1000 for x in sim.surface_seconds[k])
            meta.update(pn_ms=round(pn, 4), collision_ms=round(col, 4), deformation_ms=round(deform, 4))
            if k in sim.layered_garments:  # kept over (under) the garment under (over) it once both were done
                meta["layer_ms"] = round(sim.layer_seconds * 1000, 4)
        if self._compact is not None:
            arrays = self._compact[k].encode(p, n)
        else:
            self._p32[k][:] = p
            self._n32[k][:] = n
            arrays = {"positions": self._p32[k], "normals": self._n32[k]}
        out = Message("garment", self.session, msg.frame, msg.time, arrays, meta, origin_ns=msg.stamp_ns)
        self.publishers[k].put(encode(out))
        self.stats.add("published")

    def close(self) -> None:
        self.closing.set()
        if self._loop_job is not None and not self._loop_job.cancel():
            self._loop_job.exception()  # (running: it stops at its next step)
        self._loop_job = None
        self.sim.close()
        self.stats.publish(self.service.bus, force=True)
        for p in self.publishers:
            p.undeclare()
        self.latched.close()


class ClothService:
    """Serves every session seen on tryon/*/body (see the module docstring)."""

    SERVICE = "cloth"
    # how long an announcement waits for the frames its ingest published before it (`handle`): a
    # body frame may have been dropped on the way (congestion control DROP)
    DEFER_SECONDS = 2.0
    # how long frames wait for the announcement they follow: announcements go with congestion
    # control BLOCK, so one not here yet is late (its key's samples come on another thread,
    # which a machine starved for CPU can leave behind by more than DEFER_SECONDS: seen once,
    # a looped replay's test beside two acceptance runs; docs/history.md, sixty-third session)
    ANNOUNCEMENT_SECONDS = 5.0

    def __init__(self, bus: zenoh.Session, body: Body, data: Path, default: OutfitSpec,
                 queue_frames: int = 1024, idle_seconds: float = 60.0, sessions: str = "*",
                 catch_up: bool = False, spin: float = 0.0, cpus: list[int] | None = None,
                 float32_meshes: bool = False, model_cache: ModelCache | None = None,
                 frame_budget: float | None = None):
        """catch_up: when a session's body frames queue up, step the coarse cloth through every one
        of them but build and publish the detailed surface only for the newest (live displays stay
        current; the output then depends on timing). Off: every frame is published, in order, and
        the output is deterministic (replays reproduce it bit for bit).
        spin: seconds after a frame that this service's threads poll for the next one before they
        block (`services.spin`: on a virtual machine an idle core wakes about 1 ms late; the
        cores stay busy while sessions stream).
        cpus: cores to keep the threads to, one each (`services.spin.pin_to_cpu`): the serving
        thread on the first, a garment helper on each of the others; None: one helper per core
        beyond the first, unpinned.
        float32_meshes: publish garment positions and normals as float32 (24 bytes a vertex)
        rather than compact (`services.wire`: a 16-bit grid and octahedral normals, 10 bytes).
        model_cache: where outfit models built before are read back (`services.model_cache`;
        default: $TRYON_CACHE's folder, ~/.cache/tryon).
        frame_budget: seconds a session's frame may spend here, its wait behind earlier frames and
        its step (their 90th percentile over half a second): a session over it goes on at a lower
        tessellation level, and back up when the higher one fits (`services.frame_budget`; the
        output then depends on timing). None: each session keeps its announced level."""
        self.bus, self.body, self.data, self.default = bus, body, Path(data), default
        self.model_cache = model_cache if model_cache is not None else ModelCache.from_env()
        self._body_digest: str | None = None
        self.float32_meshes = float32_meshes
        self.frame_budget = frame_budget
        self.governor_settings: dict = {}  # the sessions' LevelGovernor keywords beyond the budget (window, ...)
        self.catch_up = catch_up
        self.spin = spin
        # helper threads for the garments, shared by the sessions: one per core beyond this
        # thread's, or one per given core beyond the first
        self.cpus = check_cpus(cpus) if cpus else None
        if self.cpus is None:
            self.garment_pool = SpinPool(max(0, (os.cpu_count() or 1) - 1), spin)
        else:
            self.garment_pool = SpinPool(len(self.cpus) - 1, spin, cpus=self.cpus[1:])
        self._last_work = 0.0  # monotonic time the serving thread last handled a message
        self.idle_seconds = idle_seconds
        self.animator = BodyAnimator(body)
        self.body_mesh = collision_body(body)
        self.sessions: dict[str, GarmentSession] = {}
        self.failed: dict[str, str] = {}  # session -> why it cannot be served
        self.ended: dict[str, int] = {}  # session -> stamp_ns of its end message
        self.closed_stats: dict[str, dict] = {}  # final stats of the sessions that ended
        self.stats = Stats(self.SERVICE, "_service")  # rejections of messages with no usable session
        self._models: dict[OutfitSpec, tuple[Outfit, list | None]] = {}
        self._models_lock = threading.Lock()
        self.animator_lock = threading.Lock()  # the one animator: pre-rolls and fitting pose the body with it
        # sessions being fitted and settled on the setup thread: (its result, messages held for it)
        self._setup = ThreadPoolExecutor(1, thread_name_prefix="session-setup")
        # work for the sessions that no frame waits for (`settle_later`)
        self._background = ThreadPoolExecutor(1, thread_name_prefix="cloth-background", initializer=_yielding_thread)
        self._preparing: dict[str, tuple[Future, list[tuple[str, bytes, bool]]]] = {}
        # a session whose outfit is being changed (or whose motion jumped): its garments as they
        # were and the new announcement's stamp, kept until the new ones are ready, and kept on if
        # they cannot be
        self._replaced: dict[str, tuple[GarmentSession, int]] = {}
        # each key's samples come in order, on a thread of their own, not the keys' among each
        # other: a session's messages that came ahead of what they follow, held until it is in
        self._held: dict[str, Hold] = {}
        self._queue: queue.Queue = queue.Queue(maxsize=queue_frames)
        self._subs = [bus.declare_subscriber(key(sessions, k), self._queue.put) for k in ("session", "body", "control")]
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.frames_done = 0
        self.done = threading.Condition()

    def settle_later(self, gs: GarmentSession, q: np.ndarray) -> Future:
        """Settle a fresh copy of session gs's garments into pose q on the background thread, as
        `OutfitSession.preroll` settles gs's own; the future's result is the settled state
        (`OutfitSession.snapshot`; None if gs closed first), for `StateSnapshot.onto` gs's."""
        return self._background.submit(self._settle, gs, np.array(q, dtype=np.float64))

    def models_later(self, spec: OutfitSpec) -> Future:
        """`outfit_models(spec)` built on the background thread (another level for a session
        holding its frame budget, while its frames stream)."""
        return self._background.submit(self.outfit_models, spec)

    def _settle(self, gs: GarmentSession, q: np.ndarray):
        outfit, surface_models, layers = self.outfit_models(gs.spec)
        fresh = OutfitSession(self.body, self.animator, self.body_mesh, outfit, surface_models=surface_models,
                              threads=1, layers=layers)
        t0 = time.perf_counter()
        with self.animator_lock:
            done = fresh.preroll(q, gs.dt, contact=gs.skin_contact, stop=gs.closing.is_set)
        log.info("cloth: session %s: garments settled into the loop's pose in %.2f s (background)%s", gs.session,
                 time.perf_counter() - t0, "" if done else ", abandoned: the session closed")
        return fresh.snapshot() if done else None

    # -- models shared by sessions with the same outfit, fabric and level (built once) --
    def outfit_models(self, spec: OutfitSpec):
        with self._models_lock:
            return self._outfit_models(spec)

    def _outfit_models(self, spec: OutfitSpec):
        if spec not in self._models:
            outfit_dir = find_outfit(self.data, spec.outfit)
            fabrics = fabric_choice(spec.fabric) if spec.fabric else None
            if self._body_digest is None and self.model_cache.folder is not None:
                self._body_digest = object_digest(self.body)
            with self.animator_lock:  # (fitting poses the rest body: not while a pre-roll reads the animator)
                self._models[spec] = build_outfit(self.body, self.animator, self.body_mesh, outfit_dir, fabrics,
                                                  surface=None if spec.level is None else
                                                  SurfaceSettings(level=spec.level),
                                                  cache=self.model_cache, body_digest=self._body_digest)
        return self._models[spec]

    def backlog(self) -> int:
        return self._queue.qsize()

    def start(self) -> "ClothService":
        freeze_heap()  # the body, the libraries: alive as long as the service
        self._thread = threading.Thread(target=self.serve, name="cloth-service", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 10.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        self.close()

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self._subs.clear()
        self._setup.shutdown(wait=True)
        for fut, _ in self._preparing.values():
            if fut.exception() is None:
                fut.result().close()
        self._preparing.clear()
        for gs, _ in self._replaced.values():
            gs.close()
        self._replaced.clear()
        for gs in self.sessions.values():
            gs.close()
        self.sessions.clear()
        self._background.shutdown(wait=True, cancel_futures=True)
        self.garment_pool.close()

    def serve(self) -> None:
        """Consume body frames until stop(); every error is logged and counted, never fatal."""
        if self.cpus is not None:
            pin_to_cpu(self.cpus[0])
        while not self._stop.is_set():
            self._finish_setups()
            try:
                spin = max(0.0, self.spin - (time.monotonic() - self._last_work))
                batch = [spin_get(self._queue, spin, 0.01 if self._preparing or self._held else 0.2)]
            except queue.Empty:
                self._release_held()
                self._drop_idle()
                continue
            if self.catch_up:  # everything already waiting: only each session's newest frame is published
                while True:
                    try:
                        batch.append(self._queue.get_nowait())
                    except queue.Empty:
                        break
            newest: dict[str, int] = {}
            for i, sample in enumerate(batch):
                k = str(sample.key_expr)
                if k.endswith("/body"):
                    newest[k] = i
            for i, sample in enumerate(batch):
                k = str(sample.key_expr)
                self._handle_counted(k, sample.payload.to_bytes(), newest.get(k, i) == i)
                if self._held:
                    self._release_held()
            self._last_work = time.monotonic()

    def _handle_counted(self, key_expr: str, payload: bytes, publish: bool, wait: bool = True) -> None:
        """handle() one message and count it done, unless it waits for its session's setup."""
        try:
            held = self.handle(key_expr, payload, publish=publish, wait=wait)
        except Exception:  # noqa: BLE001 - a bug in one session must not stop the others
            log.exception("cloth: failed on %s", key_expr)
            self.stats.add("errors")
            held = False
        if not held:
            self._count_done()

    def _count_done(self) -> None:
        with self.done:
            self.frames_done += 1
            self.done.notify_all()

    def _finish_setups(self) -> None:
        """Start serving the sessions whose setup has finished, with the messages held for them."""
        for session, (fut, held) in list(self._preparing.items()):
            if not fut.done():
                continue
            del self._preparing[session]
            err = fut.exception()
            old, announced_ns = self._replaced.pop(session, (None, 0))
            if err is None:
                self.sessions[session] = fut.result()
                if old is not None:  # the session's counts go on (it has not ended: no closed_stats)
                    self.sessions[session].stats.carry(old.stats)
                    old.close()
                freeze_heap()  # the session's models and state: alive until it ends
            else:
                if not isinstance(err, (MessageError, FileNotFoundError, ValueError)):
                    log.error("cloth: setting up session %s failed", session, exc_info=err)
                    self.stats.add("errors")
                if old is not None:
                    self._keep(session, old, announced_ns, err)
                else:
                    self._fail(session, key(session, "session"), err)
            self._count_done()  # the announcement
            bodies = [j for j, (k, _, _) in enumerate(held) if k.endswith("/body")]
            for j, (k, payload, publish) in enumerate(held):
                # catching up: of the frames that waited, only the newest gets its surface published
                newest = not k.endswith("/body") or not self.catch_up or j == bodies[-1]
                self._handle_counted(k, payload, publish and newest)

    def _fail(self, session: str, key_expr: str, err: BaseException) -> None:
        """The session cannot be served: remember why, count it, and tell its ingest (which stops
        waiting for "ready") on tryon/<s>/status/cloth."""
        self.failed[session] = f"session cannot be served: {err}"
        self.stats.reject(MessageError(key_expr, self.failed[session]))
        msg = Message("control", session, meta={"event": "failed", "from": "cloth", "reason": self.failed[session]})
        put_reliably(self.bus, key(session, "status", "cloth"), encode(msg))

    def _keep(self, session: str, old: "GarmentSession", announced_ns: int, err: BaseException) -> None:
        """The garments an announcement asked for cannot be served (an outfit this machine's data
        lacks or cannot read, a pose it cannot settle into): the session keeps the ones it wore,
        from where they were, and its ingest, told so on tryon/<s>/status/cloth, announces them
        again."""
        reason = f"the garments asked for cannot be served: {err}; {old.spec.outfit} stays on"
        old.stats.reject(MessageError(key(session, "session"), reason))
        old.stats.add("failed_changes")
        self.sessions[session] = old
        old.latch()
        msg = Message("control", session, meta={"event": "failed", "from": "cloth", "reason": reason,
                                                "kept": old.spec.outfit, "announced_ns": announced_ns})
        put_reliably(self.bus, key(session, "status", "cloth"), encode(msg))

    def _set_up(self, session: str, key_expr: str, desc: dict, stamp_ns: int) -> "GarmentSession":
        """On the setup thread: fit the outfit and settle it into the announced first pose."""
        gs = self._new_session(session, key_expr, desc)
        gs.announced_ns, gs.run = stamp_ns, run_of(desc)
        try:
            gs.start_from_description(desc, key_expr)
        except BaseException:
            gs.close()
            raise
        return gs

    def handle(self, key_expr: str, payload: bytes, publish: bool = True, wait: bool = True) -> bool:
        """Act on one message. Returns True when it is held until its session's setup finishes,
        or until what it follows is in (`Hold`; it is handled again then). wait=False: it waited
        already, as long as a Hold waits, and goes on without."""
        try:
            session, rest = parse_key(key_expr)
            msg = decode(payload, key_expr, session, rest[0] if rest[0] in ("session", "body", "control") else None)
        except MessageError as err:
            gs = self.sessions.get(parse_key(key_expr)[0]) if key_expr.startswith("tryon/") else None
            (gs.stats if gs else self.stats).reject(err)
            return False
        if session in self._preparing:  # (announced again while being set up: handled after it, in order)
            self._preparing[session][1].append((key_expr, payload, publish))
            return True
        hold = self._held.get(session)
        if hold is not None and not hold.lets_through(msg):
            hold.messages.append((key_expr, payload, publish))
            return True
        if msg.kind == "control":
            if msg.meta.get("event") == "end" and msg.meta.get("from") == "ingest":
                last = msg.meta.get("last_frame", -1)
                self.ended[session] = msg.stamp_ns
                gs = self.sessions.get(session)
                if gs is not None:  # frames still on their way (other key, other order) finish it
                    gs.end_frame = last if isinstance(last, int) else -1
                    self._close_if_done(session)
            return False
        if msg.kind == "session":  # announced: fit and settle the outfit before the first body frame
            if msg.stamp_ns <= self.ended.get(session, -1):
                return False
            old = self.sessions.get(session)
            if old is not None:
                if msg.stamp_ns <= old.announced_ns:
                    return False  # the announcement it was set up from
                after = msg.meta.get("after_frame")
                if wait and isinstance(after, int) and after > old.seen_frame:
                    # frames its ingest published before this are still on their way (the body key's
                    # samples come on another thread): they are stepped first, with these garments
                    return self._hold(session, after, -1, key_expr, payload, publish)
                if "restart_frame" in msg.meta and old.starts_again_as_before(msg.meta):
                    # a looped clip back at its first pose: the garments as they were settled there
                    log.info("cloth: session %s starts its garments again (%s) from frame %s, as settled at its "
                             "start", session, msg.meta.get("restart_reason"), msg.meta["restart_frame"])
                    old.restart(msg.stamp_ns, run_of(msg.meta))
                    return False
                # announced anew: its ingest changed the outfit or its motion jumped (a looped clip
                # starting again; services.ingest), or its last run
                # never ended (its ingest stopped without an end message) and a new run under the
                # same name starts. Either way the garments start again, from the announced pose.
                self.sessions.pop(session)
                if "restart_frame" in msg.meta:
                    log.info("cloth: session %s starts its garments again (%s, outfit %s -> %s) from frame %s",
                             session, msg.meta.get("restart_reason"), old.spec.outfit, msg.meta.get("outfit"),
                             msg.meta["restart_frame"])
                    # the new garments' topology and status are the ones to answer with; the old
                    # ones are kept (not stepped: the ingest waits) in case the new cannot be served
                    old.unlatch()
                    self._replaced[session] = (old, msg.stamp_ns)
                else:
                    log.warning("cloth: session %s announced again; its earlier run is closed", session)
                    self.closed_stats[session] = old.stats.snapshot()
                    old.close()
            self.failed.pop(session, None)
            self._preparing[session] = (self._setup.submit(self._set_up, session, key_expr, msg.meta, msg.stamp_ns),
                                        [])
            return True  # counted when the setup is done
        gs = self.sessions.get(session)
        if gs is None and msg.stamp_ns <= self.ended.get(session, -1):
            self.stats.reject(MessageError(key_expr, f"frame {msg.frame} arrives after the session's end"))
            return False
        run = msg.meta.get("run")
        run = run if isinstance(run, int) and not isinstance(run, bool) else None
        if wait and gs is not None and run is not None and run > gs.run:
            # a frame of an announcement still on its way (the session key's samples come on another
            # thread): it waits for it, and so does what comes after it
            return self._hold(session, -1, run, key_expr, payload, publish)
        joined = gs is None
        if joined:
            if session in self.failed:
                self.stats.reject(MessageError(key_expr, self.failed[session]))
                return False
            latched = next(iter(fetch_latched(self.bus, key(session, "session"), timeout=2.0,
                                              stats=self.stats).values()), None)
            desc = latched.meta if latched is not None else {}
            if wait and run is not None and run != run_of(desc):
                # the latched description is another announcement's than this frame's (a replay
                # ahead of the frames, or the frame ahead of its announcement): it waits for its own
                return self._hold(session, -1, run, key_expr, payload, publish)
            try:
                gs = self._new_session(session, key_expr, desc, latched)
            except (MessageError, FileNotFoundError, ValueError) as err:
                self._fail(session, key_expr, err)
                return False
            if run is not None:  # (joined after waiting for its announcement: its frames go on)
                gs.run = max(gs.run, run)
            self.sessions[session] = gs
        gs.last_seen = time.monotonic()
        gs.seen_frame = max(gs.seen_frame, msg.frame)
        try:
            gs.on_body(msg, key_expr, publish)
        except MessageError as err:
            gs.stats.reject(err)
            gs.stats.publish(self.bus)
        if joined:
            freeze_heap()  # set up and settled into this frame: alive until the session ends
        self._close_if_done(session)
        return False

    def _hold(self, session: str, frame: int, run: int, key_expr: str, payload: bytes, publish: bool) -> bool:
        """Hold this message of the session until `frame` or announcement `run` is in (`Hold`),
        with the messages another hold of it held (the frames that came for this announcement)."""
        before = self._held.pop(session, None)
        self._held[session] = Hold(frame, run, time.monotonic() + self._wait_seconds(frame),
                                   [(key_expr, payload, publish)] + (before.messages if before else []))
        return True

    def _wait_seconds(self, frame: int) -> float:
        """How long a `Hold` waits: for frame `frame` (>= 0) DEFER_SECONDS, for an announcement
        ANNOUNCEMENT_SECONDS."""
        return self.DEFER_SECONDS if frame >= 0 else self.ANNOUNCEMENT_SECONDS

    def _release_held(self) -> None:
        """Handle the messages of each `Hold` whose frame or announcement is in (or after
        DEFER_SECONDS, ANNOUNCEMENT_SECONDS for an announcement: then the first, which waited, goes
        on without, and it is counted)."""
        now = time.monotonic()
        for session, hold in list(self._held.items()):
            gs = self.sessions.get(session)
            if hold.frame >= 0:
                came = gs is None or gs.seen_frame >= hold.frame
            else:
                came = session in self._preparing or (gs is not None and gs.run >= hold.run)
            if not came and now < hold.deadline:
                continue
            del self._held[session]
            if not came:
                what = (f"frames up to {hold.frame}, published before its announcement" if hold.frame >= 0 else
                        f"its announcement {hold.run}, which frames came for")
                log.warning("cloth: session %s: %s, did not come in %.0f s; going on without", session, what,
                            self._wait_seconds(hold.frame))
                if gs is not None:
                    gs.stats.add("missed_frames" if hold.frame >= 0 else "unannounced_frames")
                    gs.run = max(gs.run, hold.run)
            for i, (k, payload, publish) in enumerate(hold.messages):
                self._handle_counted(k, payload, publish, wait=came or i > 0)

    def _close_if_done(self, session: str) -> None:
        gs = self.sessions.get(session)
        if gs is not None and gs.end_frame is not None and gs.order.last >= gs.end_frame:
            log.info("cloth: session %s ended after frame %d", session, gs.order.last)
            self.closed_stats[session] = gs.stats.snapshot()
            self.sessions.pop(session).close()
            self._reclaim_if_idle()

    def _new_session(self, session: str, key_expr: str, desc: dict,
                     latched: Message | None = None) -> GarmentSession:
        """The session's garments for description desc (announced, or latched: its message)."""
        if not desc:
            log.warning("cloth: session %s has no description on %s; using the defaults", session,
                        key(session, "session"))
        spec = OutfitSpec.from_description(desc, self.default, key(session, "session"))
        ft = desc.get("frame_time", 1 / 60)
        if not isinstance(ft, (int, float)) or not 0 < ft < 1:
            raise MessageError(key(session, "session"), f"'frame_time' must be seconds in (0, 1), got {ft!r}")
        log.info("cloth: session %s: outfit %s, fabric %s, level %s, dt %.4f s", session, spec.outfit,
                 spec.fabric or "presets", spec.level, ft)
        gs = GarmentSession(self, session, spec, float(ft))
        if latched is not None:
            # joined from a body frame, set up from the latched announcement: that announcement,
            # arriving after the frame (another key, another thread), is the one it was set up from
            gs.announced_ns, gs.run = latched.stamp_ns, run_of(desc)
            contact = desc.get("skin_contact", True)
            gs.skin_contact = contact if isinstance(contact, bool) else True
        return gs

    def _drop_idle(self) -> None:
        now = time.monotonic()
        for s in [s for s, gs in self.sessions.items() if now - gs.last_seen > self.idle_seconds]:
            log.info("cloth: session %s idle for %.0f s, dropped", s, self.idle_seconds)
            self.sessions.pop(s).close()
            self._reclaim_if_idle()

    def _reclaim_if_idle(self) -> None:
        """With no session left to serve (none being set up either), collect what the ended
        ones left in reference cycles (see services.heap)."""
        if not self.sessions and not self._preparing:
            reclaim_heap()

    def wait_processed(self, n: int, timeout: float | None = None) -> bool:
        """Block until n messages have been handled (flow control for offline runs)."""
        with self.done:
            return self.done.wait_for(lambda: self.frames_done >= n, timeout)
