"""mocap-ingest: a motion source (BVH file or live pose stream) -> retarget -> skin -> tryon/<s>/body.

Live pose stream (what a capture system publishes; see README "Bus contract"):
  tryon/<s>/skeleton  kind "skeleton", latched: meta {"names": [...], "frame_time": s};
                      arrays parents <i4 (n,), heads <f8 (n,3) rest joint positions in metres
                      (Y up, floor y = 0), tails <f8 (n,3) far end of each bone.
                      Names: the character's (CMU's, skinning/skeleton.py CMU_BONES) for the
                      bones that drive it, which rotations are copied by; any others may come too.
  tryon/<s>/pose      kind "pose" per frame: local_rotations <f8|<f4 (n,4) unit quaternions
                      (x, y, z, w), each joint relative to its parent, identity = rest pose;
                      root_position <f8|<f4 (3,) metres. frame numbers increase.
  tryon/<s>/control   {"event": "end", "from": "capture"} ends the stream.

Changing clothes during a session: a `get` on tryon/<s>/outfit whose payload is a control message
with meta {"outfit": name, "fabric": preset, "garment=preset,..." or null, "level": 1-16 or null} (fabric and level
optional: the session's stay) is answered at once, {"accepted": true} or {"accepted": false,
"reason": ...}. An accepted change takes effect at the next frame: the ingest announces the
session again with the new outfit and that frame's pose (`first_q`; `restart_frame`,
`restart_reason`; `after_frame`, the last frame published before it; `run`, one more than the
announcement's before, which each body frame names), and waits, as at the
start, until a cloth service has fitted the new outfit and settled it into that pose; the cloth
service replaces the session's garments from that frame on.
If it cannot (its data lacks the outfit), it keeps the garments the session wore and says so, and
the ingest latches the description as it was. How it went is put on tryon/<s>/status/ingest
({"event": "outfit", "worn": bool, "frame", "reason", "kept"}), which `request_outfit(wait=)` waits for.
A looped clip starting again is announced the same way, with the same outfit: the body jumps back
to where the clip began, and a loose garment would be left where it was. `request_outfit`
sends one (`tryon outfit`).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import zenoh

from skinning.animate import STAGES, BodyAnimator
from skinning.body import Body
from skinning.bvh import plain_name
from skinning.contact import ContactSettings
from skinning.retarget import IKSettings, missing_bones
from skinning.skeleton import CMU_BONES, Skeleton, spine_by_place
from skinning.source import PoseFrame

from .bus import Latched, Stats, fetch_latched, key, put_reliably, wait_matching
from .frame_order import FrameOrder
from .heap import freeze_heap
from .protocol import Message, MessageError, decode, encode
from .wire import CompactPositions

log = logging.getLogger("tryon.ingest")


# a pose quaternion shorter than this names no rotation (normalised, it would be noise or NaN)
MIN_QUATERNION_NORM = 1e-6


def quaternions_to_matrices(q: np.ndarray, out: np.ndarray) -> np.ndarray:
    """(n, 4) quaternions (x, y, z, w), normalised here, -> (n, 3, 3) rotation matrices."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    out[:, 0, 0] = 1 - 2 * (y * y + z * z)
    out[:, 0, 1] = 2 * (x * y - z * w)
    out[:, 0, 2] = 2 * (x * z + y * w)
    out[:, 1, 0] = 2 * (x * y + z * w)
    out[:, 1, 1] = 1 - 2 * (x * x + z * z)
    out[:, 1, 2] = 2 * (y * z - x * w)
    out[:, 2, 0] = 2 * (x * z - y * w)
    out[:, 2, 1] = 2 * (y * z + x * w)
    out[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def matrices_to_quaternions(m: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotation matrices -> (n, 4) quaternions (x, y, z, w) (for capture publishers)."""
    out = np.empty((len(m), 4))
    for i, r in enumerate(m):
        t = np.trace(r)
        if t > 0:
            s = 2.0 * np.sqrt(1.0 + t)
            out[i] = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
        else:
            k = int(np.argmax(np.diag(r)))
            a, b = (k + 1) % 3, (k + 2) % 3
            s = 2.0 * np.sqrt(max(1e-300, 1.0 + r[k, k] - r[a, a] - r[b, b]))
            v = np.empty(3)
            v[k] = 0.25 * s
            v[a] = (r[a, k] + r[k, a]) / s
            v[b] = (r[b, k] + r[k, b]) / s
            out[i, :3] = v
            out[i, 3] = (r[b, a] - r[a, b]) / s
    return out


def skeleton_message(session: str, skeleton: Skeleton, frame_time: float) -> Message:
    return Message("skeleton", session, arrays={"parents": skeleton.parents.astype(np.int32),
                                                "heads": skeleton.heads, "tails": skeleton.tails},
                   meta={"names": list(skeleton.names), "frame_time": frame_time})


def skeleton_from_message(msg: Message, key_expr: str) -> tuple[Skeleton, float]:
    names = msg.meta.get("names")
    n = len(msg.arrays["parents"])
    if n == 0:
        raise MessageError(key_expr, "a skeleton needs at least one bone")
    if not isinstance(names, list) or len(names) != n or not all(isinstance(s, str) for s in names):
        raise MessageError(key_expr, f"meta 'names' must list {n} bone names")
    names = [plain_name(s) for s in names]  # (as a BVH's: a namespace prefix left off)
    twice = sorted({s for s in names if names.count(s) > 1})
    if twice:
        raise MessageError(key_expr, f"meta 'names' names {', '.join(map(repr, twice))} more than once")
    missing = missing_bones(names)
    if missing:
        raise MessageError(key_expr, f"skeleton lacks the bones the retargeting needs: {', '.join(missing)} "
                                     f"(CMU names; a capture system publishes its pelvis and legs under them)")
    parents = msg.arrays["parents"]
    if msg.arrays["heads"].shape[0] != n or msg.arrays["tails"].shape[0] != n:
        raise MessageError(key_expr, f"heads/tails must have {n} rows, one per bone")
    if parents[0] != -1 or any(not (-1 <= p < b) for b, p in enumerate(parents[1:], 1)):
        raise MessageError(key_expr, "parents must list the root first (-1) and every parent before its children")
    ft = msg.meta.get("frame_time")
    if not isinstance(ft, (int, float)) or not 0 < ft < 1:
        raise MessageError(key_expr, f"meta 'frame_time' must be seconds in (0, 1), got {ft!r}")
    if not all(s in CMU_BONES for s in names):  # (another skeleton's spine by its place, as a BVH's)
        names = spine_by_place(names, parents)
    sk = Skeleton(tuple(names), parents.astype(np.int32), msg.arrays["heads"].astype(np.float64),
                  msg.arrays["tails"].astype(np.float64))
    return sk, float(ft)


class BusPoseSource:
    """A live pose stream on tryon/<s>/pose as a motion source (see the module docstring).

    Iteration ends on a control "end" message, after `idle_timeout` seconds without a pose, or
    when `stop` is set. Malformed poses are rejected, counted in `stats` and skipped."""

    def __init__(self, bus: zenoh.Session, session: str, stats: Stats, wait_skeleton: float = 10.0,
                 idle_timeout: float = 5.0, stop: threading.Event | None = None):
        self.bus, self.session, self.stats, self.idle_timeout = bus, session, stats, idle_timeout
        self.stop = stop or threading.Event()
        self._q: queue.Queue = queue.Queue()
        self._subs = [bus.declare_subscriber(key(session, "pose"), self._q.put),
                      bus.declare_subscriber(key(session, "control"), self._q.put)]
        deadline = time.monotonic() + wait_skeleton
        self.skeleton = None
        while self.skeleton is None:
            found = fetch_latched(bus, key(session, "skeleton"), timeout=1.0, stats=stats)
            for k, msg in found.items():
                try:
                    self.skeleton, self.frame_time = skeleton_from_message(msg, k)
                except MessageError as err:
                    stats.reject(err)
            if self.skeleton is None and time.monotonic() > deadline:
                raise TimeoutError(f"no valid skeleton on {key(session, 'skeleton')} within {wait_skeleton:.0f} s")
        n = len(self.skeleton.names)
        self._rot = np.empty((n, 3, 3))
        self._pos = np.empty(3)
        self.origin_ns = 0

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self._subs.clear()

    def hold(self, seconds: float) -> None:
        """After a pause: poses that queued meanwhile are stale; keep only the newest."""
        stale = []
        while True:
            try:
                stale.append(self._q.get_nowait())
            except queue.Empty:
                break
        poses = [s for s in stale if str(s.key_expr).endswith("/pose")]
        for s in [s for s in stale if not str(s.key_expr).endswith("/pose")] + poses[-1:]:
            self._q.put(s)
        self.stats.add("dropped", max(0, len(poses) - 1))

    def _next_sample(self):
        """The next pose or control sample; None after idle_timeout or once `stop` is set."""
        deadline = time.monotonic() + self.idle_timeout
        while not self.stop.is_set():
            try:
                return self._q.get(timeout=min(0.1, max(0.0, deadline - time.monotonic())))
            except queue.Empty:
                if time.monotonic() >= deadline:
                    return None
        return None

    def __iter__(self) -> Iterator[PoseFrame]:
        n = len(self.skeleton.names)
        order = FrameOrder()
        end_at = None  # the capture's last frame, once its end message is in
        while end_at is None or order.last < end_at:
            sample = self._next_sample()
            if sample is None:
                return
            k = str(sample.key_expr)
            try:
                msg = decode(sample.payload.to_bytes(), k, self.session)
                if msg.kind == "control":
                    if msg.meta.get("event") == "end" and msg.meta.get("from") == "capture":
                        end_at = msg.meta.get("last_frame", -1)  # poses may still be on their way
                        end_at = end_at if isinstance(end_at, int) else -1
                    continue
                if msg.kind != "pose":
                    raise MessageError(k, f"kind {msg.kind!r} where 'pose' is expected")
                rot = msg.arrays["local_rotations"]
                if rot.shape[0] != n:
                    raise MessageError(k, f"local_rotations has {rot.shape[0]} rows, the skeleton has {n} bones")
                q = rot.astype(np.float64)
                norm = np.linalg.norm(q, axis=1)
                if not (norm > MIN_QUATERNION_NORM).all():
                    row = int(np.argmin(norm))
                    raise MessageError(k, f"local_rotations row {row} ({self.skeleton.names[row]}) is no rotation: "
                                          f"quaternion of norm {norm[row]:.3g}")
                jumped_from = order.take(msg.frame, k)
            except MessageError as err:
                self.stats.reject(err)
                continue
            if jumped_from is not None:
                log.warning("ingest: %s: %d poses in a row came behind frame %d, a stray: the stream goes on from "
                            "frame %d", k, FrameOrder.RESYNC_FRAMES, jumped_from, msg.frame)
                self.stats.add("resyncs")
            self.stats.add("received")
            quaternions_to_matrices(q, self._rot)
            self._pos[:] = msg.arrays["root_position"]
            self.origin_ns = msg.origin_ns
            # (where the order went back, the motion does not continue the pose before: a capture
            # restarted, or the pose before was a stray; the ingest starts the garments again there)
            yield PoseFrame(msg.frame, msg.time, self._rot, self._pos, jump=jumped_from is not None)


class IngestService:
    """Retarget + skin each pose of `source` and publish tryon/<s>/body.

    description: the session's description, latched on tryon/<s>/session (outfit, fabrics, level...).
    ik: retargeting settings (default IKSettings()); contact: the skin contact (None: off), said
    in the description as skin_contact so that the cloth poses its pre-roll the same way.
    check_outfit(change): raises (ValueError, FileNotFoundError) naming what a requested outfit
    change gets wrong, e.g. an outfit this machine's data does not have (None: the types only);
    change_wait: how long the stream waits for the changed outfit to be ready (module docstring;
    not at all while no cloth service has reported the session ready).
    restart_on_jump: announce the session again where the motion jumps (a looped clip starting
    again), so the garments start again from that pose (module docstring).
    float32_meshes: publish the body's vertices as float32, not on the compact 16-bit grid
    (`services.wire`: 6 bytes a vertex instead of 12)."""

    SERVICE = "ingest"

    def __init__(self, bus: zenoh.Session, session: str, body: Body, source, description: dict,
                 ik: IKSettings | None = None, contact: ContactSettings | None = ContactSettings(),
                 check_outfit: Callable[[dict], None] | None = None, change_wait: float = 30.0,
                 restart_on_jump: bool = True, float32_meshes: bool = False):
        self.bus, self.session, self.body, self.source = bus, session, body, source
        self.stats = getattr(source, "stats", None) or Stats(self.SERVICE, session)
        # displays shade it themselves
        self.animator = BodyAnimator(body, source.skeleton, ik=ik, normals=False, contact=contact, helpers=False)
        self.latched = Latched(bus)
        self.description = dict(description, frame_time=source.frame_time, body_vertices=body.n_visible,
                                arm_clearance_deg=self.animator.retargeter.ik.arm_clearance_deg,
                                hand_clearance=self.animator.retargeter.ik.hand_clearance is not None,
                                run=0,  # which announcement: 0, then one more at each announcement again
                                skin_contact=contact is not None)
        self.publisher = bus.declare_publisher(key(session, "body"), congestion_control=zenoh.CongestionControl.BLOCK,
                                               reliability=zenoh.Reliability.RELIABLE)
        self.frames = 0
        self.last_index = -1  # index of the last frame published
        self._announced = False
        self._ready = threading.Event()  # a cloth service reported the session ready, or failed
        self.cloth_failed: str | None = None  # why a cloth service cannot serve the session
        self.cloth_kept: str | None = None  # the outfit it kept on when it could not serve another
        self._description_payload = b""  # the latched description, as latched
        self._status = bus.declare_subscriber(key(session, "status", "*"), self._on_status)
        self._verts = np.empty((body.n_visible, 3), np.float32) if float32_meshes else None
        self._compact = None if float32_meshes else CompactPositions(body.n_visible)
        self._ready_since = 0  # a "ready" counts when it answers an announcement stamped this late or later
        self._cloth_seen = False  # a cloth service has reported this session ready at least once
        self.check_outfit, self.change_wait, self.restart_on_jump = check_outfit, change_wait, restart_on_jump
        self._change: dict | None = None  # an accepted outfit change, applied at the next frame
        self._change_lock = threading.Lock()
        self.restarts = 0  # announcements after the first (outfit changes, jumps in the motion)
        self._loop_q: list[float] | None = None  # the pose a looped source comes back to (the first one)
        self._changes = bus.declare_queryable(key(session, "outfit"), self._on_outfit_request)

    def announce(self) -> None:
        """Latch the session description and the body's topology (once)."""
        if self._announced:
            return
        self._announced = True
        self._publish_description()
        topo = Message("topology", self.session, arrays={"triangles": self.body.triangles.astype(np.int32)},
                       meta={"what": "body", "n_vertices": self.body.n_visible, "color": [0.86, 0.69, 0.58]})
        self.latched.publish(key(self.session, "topology", "body"), encode(topo))

    def _publish_description(self) -> int:
        """Latch the session description (again, after a change); returns its stamp."""
        stamp = time.time_ns()
        self._description_payload = encode(Message("session", self.session, meta=self.description), stamp_ns=stamp)
        self.latched.publish(key(self.session, "session"), self._description_payload)
        return stamp

    def _on_outfit_request(self, query) -> None:
        """A request to change the session's outfit (module docstring): checked, answered, and
        kept for the next frame."""
        k = key(self.session, "outfit")
        try:
            if query.payload is None:
                raise MessageError(k, "an outfit request carries a control message naming the 'outfit'")
            msg = decode(query.payload.to_bytes(), k, self.session, "control")
            change = {f: msg.meta[f] for f in ("outfit", "fabric", "level") if f in msg.meta}
            if "outfit" not in change:
                raise MessageError(k, "an outfit request names the 'outfit'")
            from .cloth_service import OutfitSpec  # the cloth service's own checks of a description
            OutfitSpec.from_description(dict(self.description, **change), OutfitSpec(""), k)
            if self.check_outfit is not None:
                try:
                    self.check_outfit(change)
                except (ValueError, FileNotFoundError) as err:
                    raise MessageError(k, str(err)) from None
        except MessageError as err:
            self.stats.reject(err)  # (logged there)
            reply = {"event": "outfit", "accepted": False, "reason": str(err)}
        else:
            with self._change_lock:
                self._change = change
            log.info("ingest: session %s changes outfit to %s at its next frame", self.session, change["outfit"])
            reply = dict(change, event="outfit", accepted=True, after_frame=self.last_index)
        query.reply(k, encode(Message("control", self.session, max(0, self.last_index), meta=reply)))

    def _announce_again(self, index: int, q: np.ndarray) -> None:
        """Announce the session again from frame `index` in pose q, with the accepted outfit
        change if there is one (else as it was: the motion jumped there), and wait for a cloth
        service to have the garments fitted and settled into that pose."""
        with self._change_lock:
            change, self._change = self._change, None
        before, before_payload = dict(self.description), self._description_payload
        # after_frame: the last frame published before it, which a cloth service steps first (the
        # body frames come on another key, and zenoh keeps each key's order, not the keys' among
        # each other: an announcement can reach it ahead of the frames before it)
        self.description.update(change or {}, first_q=[float(v) for v in q], restart_frame=index,
                                restart_reason="outfit change" if change else "motion jump",
                                after_frame=self.last_index, run=self.description.get("run", 0) + 1)
        # a looped source comes back to its first pose: the cloth service settles the new garments
        # into that one too, now (in the pause of the change), to put them back there at each loop
        self.description.pop("loop_q", None)
        if change and self._loop_q is not None:
            self.description["loop_q"] = self._loop_q
        self._ready.clear()
        self.cloth_failed = self.cloth_kept = None
        self._ready_since = self._publish_description()
        self.restarts += 1
        if not self._cloth_seen:  # no cloth service has answered this session: nothing to wait for
            if change:
                self._report_change(change, index, False, "no cloth service serves this session (yet)")
            return
        t0 = time.monotonic()
        if self.wait_ready(self.change_wait):
            if change:
                self._report_change(change, index, True)
        elif self.cloth_kept is not None:
            # the cloth service kept the garments it had on: so does the description, latched as it
            # was (its stamp tells a cloth service it has it already)
            log.error("ingest: session %s: %s", self.session, self.cloth_failed)
            self.stats.add("failed_changes")
            if change:
                self._report_change(change, index, False, self.cloth_failed, kept=self.cloth_kept)
            self.description, self._description_payload = before, before_payload
            self.latched.publish(key(self.session, "session"), before_payload)
            self.cloth_failed = None
        else:
            log.warning("ingest: no cloth service reported %s ready again in %.0f s%s", self.session,
                        self.change_wait, f": {self.cloth_failed}" if self.cloth_failed else "")
            if change:
                self._report_change(change, index, False, self.cloth_failed
                                    or f"no cloth service reported it ready in {self.change_wait:.0f} s")
        waited = time.monotonic() - t0
        if waited > 0.1 and hasattr(self.source, "hold"):
            self.source.hold(waited)

    def _report_change(self, change: dict, index: int, worn: bool, reason: str = "", kept: str | None = None) -> None:
        """Tell whoever asked for an outfit change how it went, on tryon/<s>/status/ingest
        (`request_outfit` waits for it): worn from frame `index` on, or not and why (kept: the
        outfit the session still wears)."""
        meta = dict(change, event="outfit", worn=worn, frame=index)
        if not worn:
            meta["reason"] = reason
        if kept is not None:
            meta["kept"] = kept
        put_reliably(self.bus, key(self.session, "status", self.SERVICE),
                     encode(Message("control", self.session, index, meta=meta)))

    def publish(self, frame: PoseFrame, origin_ns: int = 0, out=None) -> None:
        """Retarget + skin one pose (unless `out`, its BodyFrame, is given) and publish the body."""
        out = self.animator(frame.local_rot, frame.root_position) if out is None else out
        if self._compact is not None:
            try:
                arrays = dict(self._compact.encode(out.vertices[: self.body.n_visible]), q=out.retarget.q)
            except ValueError as err:  # a skinned body with NaN: not published, counted, the stream goes on
                log.error("ingest: frame %d of %s not published: body %s", frame.index, self.session, err)
                self.stats.add("errors")
                return
        else:
            self._verts[:] = out.vertices[: self.body.n_visible]
            arrays = {"vertices": self._verts, "q": out.retarget.q}
        st = self.animator.stage_seconds
        meta = {f"{s}_ms": round(float(st[i]) * 1000, 4) for i, s in enumerate(STAGES) if s != "normals"}
        meta["ankle_error_mm"] = round(float(out.retarget.ankle_position_error.max()) * 1000, 4)
        meta["run"] = self.description["run"]  # the announcement it follows (a cloth service waits for one it lacks)
        msg = Message("body", self.session, frame.index, frame.time, arrays, meta, origin_ns=origin_ns)
        self.publisher.put(encode(msg))
        self.frames += 1
        self.last_index = frame.index
        self.stats.add("published")
        self.stats.values.update(meta)
        self.stats.publish(self.bus)

    def wait_for_subscribers(self, timeout: float) -> bool:
        """Wait (up to timeout s) until something subscribes to the body stream, e.g. a cloth service
        that connects a moment later; frames put before then would reach no one."""
        return wait_matching(self.publisher, timeout)

    def wait_ready(self, timeout: float) -> bool:
        """Wait up to `timeout` s for a cloth service to report this session ready (garments fitted
        and settled into the first pose), so the body stream does not queue up behind the pre-roll.
        False when it timed out or a cloth service reported that it cannot serve the session (then
        `cloth_failed` says why): waiting longer would not help."""
        deadline = time.monotonic() + timeout
        while not self._ready.is_set():
            found = fetch_latched(self.bus, key(self.session, "status", "*"), timeout=0.5)
            if any(self._answers(m) for m in found.values()):
                self._cloth_seen = True
                return True
            if time.monotonic() > deadline:
                return False
            self._ready.wait(0.05)
        return self.cloth_failed is None

    def _on_status(self, sample) -> None:
        msg = self.stats.decode(sample, self.session, "control")
        if msg is None:
            return
        if msg.meta.get("event") == "failed":
            kept = msg.meta.get("kept")
            if kept is not None and msg.meta.get("announced_ns") != self._ready_since:
                return  # (another announcement's)
            self.cloth_failed = str(msg.meta.get("reason", "no reason given"))
            self.cloth_kept = str(kept) if kept is not None else None
            self._cloth_seen = True  # (a cloth service serves the bus: a change is worth waiting for)
            self._ready.set()
        elif self._answers(msg):
            self.cloth_failed = None
            self._cloth_seen = True
            self._ready.set()

    def _answers(self, msg: Message) -> bool:
        """A cloth service's "ready" for the latest announcement (after an outfit change, not the
        one before it, which may still be latched)."""
        return msg.meta.get("event") == "ready" and msg.meta.get("announced_ns", 0) >= self._ready_since

    def run(self, start_frame: int = 0, before_frame: Callable[[int], bool] | None = None,
            stop: threading.Event | None = None, wait_subscribers: float = 0.0, wait_ready: float = 0.0) -> int:
        """Publish every frame of the source; before_frame(index) may wait (flow control) or return
        False to stop. Ends with a control "end" message. Returns the number of frames published.

        The first pose is retargeted before the session is announced: its configuration goes into the
        description (`first_q`), so a cloth service can fit and settle the garments into it before the
        first body frame (`wait_ready` s at most); `wait_subscribers`: wait for a body subscriber."""
        try:
            for frame in self.source:
                if stop is not None and stop.is_set():
                    break
                if frame.index < start_frame:
                    continue
                if before_frame is not None and before_frame(frame.index) is False:
                    break
                if frame.jump and self.animator.retargeter is not None:
                    # the motion does not continue the last frame: the IK starts afresh, as at the
                    # session's first frame (a looped clip's first pose is then the same bit for
                    # bit, and a cloth service restores the garments it settled there)
                    self.animator.retargeter.reset()
                out = self.animator(frame.local_rot, frame.root_position)
                if not self._announced:
                    with self._change_lock:  # a change asked for before the first frame: the first announcement's
                        change, self._change = self._change, None
                    self.description.update(change or {}, first_q=[float(v) for v in out.retarget.q])
                    if getattr(self.source, "loop", False) and getattr(self.source, "loop_from", 0) == frame.index:
                        self._loop_q = self.description["first_q"]  # where each loop starts again
                    self.announce()
                    t0 = time.monotonic()
                    if wait_subscribers > 0 and not self.wait_for_subscribers(wait_subscribers):
                        log.warning("ingest: nothing subscribes to %s", key(self.session, "body"))
                    if wait_ready > 0 and not self.wait_ready(wait_ready):
                        if self.cloth_failed is not None:
                            log.error("ingest: the cloth service cannot serve %s: %s", self.session,
                                      self.cloth_failed)
                        else:
                            log.warning("ingest: no cloth service reported %s ready in %.0f s", self.session,
                                        wait_ready)
                    # the waits paused the source: a paced file shifts its schedule by them, a live
                    # stream drops the poses that went stale (a burst of late frames would queue up
                    # at the cloth service); a paced file also shifts itself when it falls further
                    # behind than its max_lag (a slow first retarget)
                    waited = time.monotonic() - t0
                    if waited > 0.1 and hasattr(self.source, "hold"):
                        self.source.hold(waited)
                    freeze_heap()  # set up: what is alive now lives as long as the stream
                elif self._change is not None or (self.restart_on_jump and frame.jump):
                    # another outfit, or a jump (a looped clip starting again, where a loose garment
                    # left behind would never catch up): the garments start again from this pose
                    self._announce_again(frame.index, out.retarget.q)
                self.publish(frame, getattr(self.source, "origin_ns", 0), out)
        finally:
            self.end()
        return self.frames

    def end(self) -> None:
        put_reliably(self.bus, key(self.session, "control"),
                     encode(Message("control", self.session, self.frames,
                                    meta={"event": "end", "from": "ingest", "frames": self.frames,
                                          "last_frame": self.last_index})))
        self.stats.publish(self.bus, force=True)

    def close(self) -> None:
        self._changes.undeclare()
        self._status.undeclare()
        self.publisher.undeclare()
        self.latched.close()


def request_outfit(bus: zenoh.Session, session: str, outfit: str, fabric: str | None = None,
                   level: int | None = None, set_level: bool = False, timeout: float = 5.0,
                   wait: float = 0.0) -> dict:
    """Ask the ingest of a running session to change its outfit (module docstring). fabric None:
    the session's; level: set only with set_level (None there: coarse cloth only). Returns the
    ingest's answer ({"accepted": bool, "reason": ...}); ValueError when no ingest answers.
    wait > 0: an accepted change is also waited for (up to `wait` s) until the garments are on:
    the answer then says "worn" (bool; with "frame", the first frame that wears them) and,
    if not, the "reason" and the outfit the session still wears ("kept"); "worn" is None when
    the wait ran out."""
    meta: dict = {"outfit": outfit}
    if fabric is not None:
        meta["fabric"] = fabric
    if set_level:
        meta["level"] = level
    k = key(session, "outfit")
    outcomes: queue.Queue = queue.Queue()
    listen = bus.declare_subscriber(key(session, "status", IngestService.SERVICE), outcomes.put) if wait > 0 else None
    try:
        answer = _ask_outfit(bus, session, k, meta, timeout)
        if listen is None or not answer.get("accepted"):
            return answer
        deadline = time.monotonic() + wait
        while True:
            try:
                sample = outcomes.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                return dict(answer, worn=None, reason=f"not worn after {wait:.0f} s")
            try:
                got = decode(sample.payload.to_bytes(), str(sample.key_expr), session, "control").meta
            except MessageError:
                continue
            if got.get("event") != "outfit" or not isinstance(got.get("frame"), int):
                continue
            if got["frame"] <= answer.get("after_frame", -1):
                continue  # an earlier change's
            if got.get("outfit") != outfit:  # another request came after this one, before the frame
                return dict(answer, worn=False, frame=got["frame"],
                            reason=f"replaced by a request for {got.get('outfit')!r}")
            return dict(answer, **{f: got[f] for f in ("worn", "frame", "reason", "kept") if f in got})
    finally:
        if listen is not None:
            listen.undeclare()


def _ask_outfit(bus: zenoh.Session, session: str, k: str, meta: dict, timeout: float) -> dict:
    deadline = time.monotonic() + timeout
    while True:  # a process that has just joined the bus learns of the ingest's queryable a moment later
        for reply in bus.get(k, payload=encode(Message("control", session, meta=meta)),
                             timeout=max(0.1, deadline - time.monotonic())):
            if reply.ok is not None:
                return decode(reply.ok.payload.to_bytes(), k, session, "control").meta
        if time.monotonic() >= deadline:
            raise ValueError(f"no ingest answered on {k} within {timeout:.0f} s (is session {session!r} running?)")
        time.sleep(0.1)


def publish_capture(bus: zenoh.Session, session: str, source, start_frame: int = 0,
                    stop: threading.Event | None = None, wait_subscribers: float = 0.0) -> int:
    """Play a motion source onto the bus as a live capture system would (skeleton + pose stream):
    the reference publisher for capture vendors, and the live input of the tests."""
    latched = Latched(bus)
    latched.publish(key(session, "skeleton"), encode(skeleton_message(session, source.skeleton, source.frame_time)))
    pub = bus.declare_publisher(key(session, "pose"), congestion_control=zenoh.CongestionControl.BLOCK)
    wait_matching(pub, wait_subscribers)
    n, last = 0, -1
    try:
        for frame in source:
            if stop is not None and stop.is_set():
                break
            if frame.index < start_frame:
                continue
            last = frame.index
            msg = Message("pose", session, frame.index, frame.time,
                          {"local_rotations": matrices_to_quaternions(frame.local_rot),
                           "root_position": frame.root_position.copy()})
            pub.put(encode(msg))
            n += 1
    finally:
        put_reliably(bus, key(session, "control"),
                     encode(Message("control", session, n, meta={"event": "end", "from": "capture",
                                                                 "last_frame": last})))
        pub.undeclare()
        time.sleep(0.2)  # let late skeleton queries be answered before the queryable goes
        latched.close()
    return n

