"""recorder / replay: every bus message of a session to an MCAP file, and back onto the bus.

MCAP (https://mcap.dev) is the standard container for pub/sub recordings (ROS 2, Foxglove): an
indexed, chunked, compressed log of timestamped messages on named channels, readable by
`mcap` tools and Foxglove Studio. One channel per key expression; each MCAP message is the
tryon message exactly as it was on the bus (message_encoding "tryon/2", schemaless - the
format is self-describing, see services/protocol.py); log_time is when the recorder received
it, publish_time the sender's stamp_ns.

The file is written as <file>.part and renamed only once MCAP's summary and footer are
written, so a recording that is interrupted never looks complete. When its disk runs low
(`services.diskspace`), or a write fails, the recording is finished there, complete, and the
session goes on without it (`stopped` says why).
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import zenoh
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from .bus import Latched, Stats, check_session_name, key, parse_key, wait_matching
from .diskspace import DEFAULT_MIN_FREE, SpaceGuard
from .outputs import output_file
from .protocol import READABLE_VERSIONS, SCHEMA_VERSION, MessageError, peek_header, retag

log = logging.getLogger("tryon.recorder")
MESSAGE_ENCODING = f"tryon/{SCHEMA_VERSION}"
READABLE_ENCODINGS = tuple(f"tryon/{v}" for v in READABLE_VERSIONS)  # older recordings replay too
LATCHED = ("session", "topology", "skeleton")  # kinds of key served to late joiners


class Recorder:
    SERVICE = "recorder"

    def __init__(self, bus: zenoh.Session, session: str, path: str | Path, min_free: int = DEFAULT_MIN_FREE):
        """min_free: bytes to leave free on the file's disk; the recording is finished when fewer are."""
        self.bus, self.session, self.path = bus, session, Path(path)
        output_file(self.path)  # (a folder named: refused before the first message, not at the rename)
        self._space = SpaceGuard(self.path.parent, min_free)
        self.stopped: str | None = None  # why the recording was finished before close()
        self._finished = False
        self.part = self.path.with_name(self.path.name + ".part")
        self.stats = Stats(self.SERVICE, session)
        self._file = open(self.part, "wb")
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library="tryon recorder")
        self._writer.add_metadata("tryon", {"session": session, "schema_version": str(SCHEMA_VERSION),
                                            "message_encoding": MESSAGE_ENCODING})
        self._channels: dict[str, int] = {}
        self._lock = threading.Lock()
        self._last_log = 0
        self.messages = 0
        self._closed = False
        self._sub = bus.declare_subscriber(key(session, "**"), self._on_sample)
        for reply in bus.get(key(session, "**"), timeout=1.0):
            if reply.ok is not None:
                self.write(str(reply.ok.key_expr), reply.ok.payload.to_bytes())

    def _on_sample(self, sample) -> None:
        k = str(sample.key_expr)
        if parse_key(k)[1][:1] == ("stats",) and k.endswith("/" + self.SERVICE):
            return  # not our own counters
        self.write(k, sample.payload.to_bytes())

    def write(self, key_expr: str, payload: bytes) -> None:
        """Record one message as it was on the bus (malformed ones too: a recording is evidence)."""
        h = peek_header(payload)  # the header is enough; malformed messages are kept with no publish time
        stamp = h.get("stamp_ns") if h is not None and isinstance(h.get("stamp_ns"), int) else 0
        with self._lock:
            if self._closed:
                return
            ch = self._channels.get(key_expr)
            if ch is None:
                ch = self._channels[key_expr] = self._writer.register_channel(key_expr, MESSAGE_ENCODING, 0)
            now = max(time.time_ns(), self._last_log + 1)  # strictly increasing: replay keeps the order
            self._last_log = now
            try:
                self._writer.add_message(ch, log_time=now, data=payload, publish_time=stamp, sequence=self.messages)
            except OSError as err:
                self.stats.add("errors")
                self._stop(f"writing failed: {err}")
                return
            self.messages += 1
            free = self._space.low()
            if free is not None:
                self._stop(self._space.why(free))
        self.stats.add("received")

    def _stop(self, why: str) -> None:
        """(Under the lock.) Finish the file now, as close() does, and record nothing more."""
        self._closed = True
        self.stopped = why
        self.stats.values["stopped"] = why
        log.warning("recorder: %s finished after %d messages: %s; the session goes on unrecorded", self.path,
                    self.messages, why)
        self._finish()

    def _finish(self) -> None:
        if self._finished:
            return
        self._finished = True
        try:
            self._writer.finish()
            self._file.close()
        except OSError as err:
            log.error("recorder: %s could not be finished (%s); what was written stays in %s", self.path, err,
                      self.part)
            try:
                self._file.close()
            except OSError:
                pass
            return
        self.part.replace(self.path)

    def close(self) -> Path:
        """Finish the MCAP file (summary, footer) and give it its final name."""
        with self._lock:
            already = self._closed
            self._closed = True
        if already and self._sub is None:
            return self.path
        if self._sub is not None:
            self._sub.undeclare()  # outside the lock: a callback in flight may be waiting for it
        with self._lock:
            self._finish()
        self._sub = None
        log.info("recorder: %d messages -> %s", self.messages, self.path)
        return self.path


def read_recording(path: str | Path, kinds: set[str] | None = None):
    """(key, payload, log_time_ns) of every message in a tryon MCAP file, in recorded order."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"recording {path} not found")
    with open(path, "rb") as f:
        try:
            reader = make_reader(f)
            for _, channel, message in reader.iter_messages(log_time_order=True):
                if channel.message_encoding not in READABLE_ENCODINGS:
                    raise ValueError(f"{path}: channel {channel.topic!r} has encoding "
                                     f"{channel.message_encoding!r}, expected one of {', '.join(READABLE_ENCODINGS)}")
                if kinds is not None:
                    try:
                        part = parse_key(channel.topic)[1][0]
                    except MessageError:
                        continue
                    if part not in kinds:
                        continue
                yield channel.topic, message.data, message.log_time
        except ValueError:
            raise
        except Exception as exc:  # the mcap library's errors: truncated or corrupt file
            raise ValueError(f"{path}: not a readable MCAP recording ({type(exc).__name__}: {exc})") from exc


def replay(bus: zenoh.Session, path: str | Path, session: str | None = None, speed: float = 1.0,
           kinds: set[str] | None = None, stop: threading.Event | None = None, linger: float = 0.0,
           wait_subscribers: float = 0.0) -> int:
    """Publish a recording onto the bus; returns the number of messages published.

    session: publish under this session name instead of the recorded one (payload arrays unchanged).
    speed: 1 = original pace, 2 = twice as fast, 0 = as fast as possible.
    kinds: only these key kinds (e.g. {"session", "topology", "body"} to feed a fresh cloth service).
    Latched kinds (session, topology, skeleton) are also answered to queries while the replay runs,
    and for `linger` seconds after it: those recorded before the first frame at once, a later
    one (the session announced again, a new garment's topology) where it was recorded.
    wait_subscribers: wait up to this long for a subscriber on each key before its first message
    (a service that has just connected)."""
    if session is not None:
        check_session_name(session)
    latched = Latched(bus)

    skipped = 0

    def rename(k: str, payload: bytes) -> tuple[str, bytes] | None:
        nonlocal skipped
        try:
            old, parts = parse_key(k)
            s = session or old
            return key(s, *parts), retag(payload, s, k, restamp=True)
        except MessageError as err:  # a malformed message that was recorded as it came
            log.warning("replay: skipped %s", err)
            skipped += 1
            return None

    publishers: dict[str, zenoh.Publisher] = {}
    n, t0, start = 0, None, time.perf_counter()
    try:
        for k, payload, log_time in read_recording(path, kinds):
            if stop is not None and stop.is_set():
                break
            is_latched = parse_key(k)[1][0] in LATCHED
            if is_latched and t0 is None:
                # the latched messages before the first frame, at once: a service that starts on
                # the first frame can query them
                if (renamed := rename(k, payload)) is not None:
                    latched.publish(*renamed)
                continue
            t0 = log_time if t0 is None else t0
            if speed > 0:
                delay = start + (log_time - t0) / 1e9 / speed - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
            renamed = rename(k, payload)
            if renamed is None:
                continue
            k2, p2 = renamed
            if is_latched:  # a later one (the session announced again, a new garment's topology): at its time
                latched.publish(k2, p2)
                continue
            pub = publishers.get(k2)
            if pub is None:
                pub = publishers[k2] = bus.declare_publisher(k2, congestion_control=zenoh.CongestionControl.BLOCK)
                wait_matching(pub, wait_subscribers)
            pub.put(p2)
            n += 1
        if linger > 0:
            time.sleep(linger)
    finally:
        for p in publishers.values():
            p.undeclare()
        latched.close()
    return n
