"""The zenoh bus: configuration, key expressions, and the stats every service keeps.

Key expressions of a session <s> (a name of letters, digits, '-', '_' and '.'):

    tryon/<s>/session             session description (outfit, fabrics, level, frame_time); latched
    tryon/<s>/skeleton            a live capture's skeleton (names, parents, rest joints); latched
    tryon/<s>/pose                live pose stream from a capture system (input of mocap-ingest)
    tryon/<s>/body                skinned body per frame (mocap-ingest)
    tryon/<s>/garment/<name>      each garment's detailed mesh per frame (cloth)
    tryon/<s>/topology/body       body triangles; latched
    tryon/<s>/topology/garment/<name>   garment triangles, colour, fabric; latched
    tryon/<s>/stats/<service>     counters (received, published, rejected, dropped, timings), once a second
    tryon/<s>/control             session events ({"event": "end"} when the motion source ends)
    tryon/<s>/status/cloth        {"event": "ready"} once the garments are settled into the first pose
                                  (latched), or {"event": "failed", "reason": ...} when it cannot serve
                                  (with "kept": the outfit still worn, after a change it cannot make)
    tryon/<s>/status/ingest       {"event": "outfit", "worn": ...} how an outfit change went

"Latched" messages are put once when they are made and also answered by a queryable on the same
key, so a display that joins later gets them with one `get("tryon/<s>/topology/**")`.
"""

from __future__ import annotations

import json
import logging
import os
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from .protocol import Message, MessageError, decode, encode

log = logging.getLogger("tryon.bus")
ROOT = "tryon"
CONFIG_ENV = "TRYON_ZENOH_CONFIG"
SESSION_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


def check_session_name(name: str) -> str:
    if not SESSION_RE.match(name or ""):
        raise ValueError(f"session name {name!r}: use 1-64 letters, digits, '-', '_' or '.'")
    return name


def key(session: str, *parts: str) -> str:
    return "/".join((ROOT, session, *parts))


def parse_key(key_expr: str) -> tuple[str, tuple[str, ...]]:
    """('s1', ('garment', 'top')) from 'tryon/s1/garment/top'."""
    parts = str(key_expr).split("/")
    if len(parts) < 3 or parts[0] != ROOT:
        raise MessageError(str(key_expr), "key expression is not tryon/<session>/...")
    return parts[1], tuple(parts[2:])


@dataclass
class BusConfig:
    """How this process joins the bus.

    Default: a zenoh peer with multicast scouting off that listens on a free loopback port, so
    everything in one process (or one machine, via `connect`) works with nothing started by hand.
    For several machines: `listen` on a reachable address (tcp/0.0.0.0:7447) and `connect` the
    others to it, or run `tryon router` and connect every service to it (mode "client" or "peer").
    A zenoh JSON5 config file (`config_file`, or $TRYON_ZENOH_CONFIG) is applied first.
    """

    mode: str = "peer"
    listen: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:0"])
    connect: list[str] = field(default_factory=list)
    multicast: bool = False
    config_file: str | None = None

    def zenoh_config(self) -> zenoh.Config:
        path = self.config_file or os.environ.get(CONFIG_ENV)
        if path:
            if not Path(path).is_file():
                raise FileNotFoundError(f"zenoh config {path!r} not found")
            try:
                cfg = zenoh.Config.from_file(path)
            except zenoh.ZError as exc:  # JSON5 syntax, or a key of the wrong type
                raise BusError(f"zenoh config {path!r}: {_zenoh_reason(exc)}") from None
        else:
            cfg = zenoh.Config()
        if self.mode not in ("peer", "client", "router"):
            raise ValueError(f"bus mode {self.mode!r}: expected peer, client or router")
        cfg.insert_json5("mode", json.dumps(self.mode))
        cfg.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast))
        if self.listen:
            cfg.insert_json5("listen/endpoints", json.dumps(self.listen))
        if self.connect:
            cfg.insert_json5("connect/endpoints", json.dumps(self.connect))
        return cfg

    def open(self) -> zenoh.Session:
        cfg = self.zenoh_config()
        try:
            return zenoh.open(cfg)
        except zenoh.ZError as exc:  # an endpoint in use, an address that does not resolve, ...
            where = ", ".join([f"listen {e}" for e in self.listen] + [f"connect {e}" for e in self.connect])
            raise BusError(f"the bus does not open ({self.mode}{'; ' + where if where else ''}): "
                           f"{_zenoh_reason(exc)}") from None


class BusError(ValueError):
    """The bus cannot be opened as configured (a malformed zenoh config file, an endpoint in use or
    that does not resolve): the command line reports it as a bad setting, not a traceback."""


def _zenoh_reason(exc: Exception) -> str:
    """A zenoh error's message without the Rust source locations it ends its parts with, and a
    config file's syntax or type error as "line L, column C: what"."""
    text = re.sub(r"\s+at /\S+\.rs:\d+\.?", "", str(exc))
    syntax = re.search(r"-->\s*(\d+):(\d+).*?=\s*(.*)", text, re.S)  # JSON5 syntax (a pest parser's report)
    if syntax:
        return f"line {syntax[1]}, column {syntax[2]}: {' '.join(syntax[3].split())}"
    typed = re.search(r'msg: "((?:[^"\\]|\\.)*)", location: Some\(Location \{ line: (\d+), column: (\d+)', text)
    if typed:  # a key of the wrong type (serde's report)
        return f"line {typed[2]}, column {typed[3]}: {typed[1].replace(chr(92) + chr(34), chr(34))}"
    return " ".join(text.split())


def add_bus_arguments(parser) -> None:
    g = parser.add_argument_group("bus (zenoh)")
    g.add_argument("--mode", default="peer", choices=("peer", "client", "router"), help="zenoh mode (default peer)")
    g.add_argument("--listen", action="append", metavar="ENDPOINT",
                   help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (default tcp/127.0.0.1:<free port>)")
    g.add_argument("--connect", action="append", metavar="ENDPOINT",
                   help="endpoint of another service or router to connect to, e.g. tcp/192.168.1.20:7447")
    g.add_argument("--multicast", action="store_true", help="discover peers by multicast scouting (off by default)")
    g.add_argument("--zenoh-config", help=f"zenoh JSON5 config file (default ${CONFIG_ENV})")


def bus_config_from_args(args) -> BusConfig:
    return BusConfig(mode=args.mode, listen=args.listen or (["tcp/127.0.0.1:0"] if args.mode != "client" else []),
                     connect=args.connect or [], multicast=args.multicast, config_file=args.zenoh_config)


def wait_matching(publisher: zenoh.Publisher, timeout: float) -> bool:
    """Wait up to `timeout` s until a publisher has a subscriber (one that has just connected needs
    a moment before its subscriptions are known here); True if it has one."""
    deadline = time.monotonic() + timeout
    while not publisher.matching_status.matching:
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


class Stats:
    """A service's counters for one session, published on tryon/<s>/stats/<service>."""

    def __init__(self, service: str, session: str):
        self.service, self.session = service, session
        self.counts: dict[str, int] = {"received": 0, "published": 0, "rejected": 0, "dropped": 0}
        self.rejections: dict[str, int] = {}  # key expression -> count
        self.values: dict[str, float] = {}  # latest timings etc.
        self._lock = threading.Lock()
        self._last_publish = 0.0
        self._unpublished = False  # the last put failed (logged once until one goes through)

    def add(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counts[name] = self.counts.get(name, 0) + n

    def reject(self, err: MessageError) -> None:
        log.warning("%s: rejected %s", self.service, err)
        with self._lock:
            self.counts["rejected"] += 1
            self.rejections[err.key] = self.rejections.get(err.key, 0) + 1

    def decode(self, sample, session: str, kind: str | None = None) -> Message | None:
        """The zenoh sample's message, or None once it is logged and counted as rejected."""
        try:
            return decode(sample.payload.to_bytes(), str(sample.key_expr), session, kind)
        except MessageError as err:
            self.reject(err)
            return None

    def carry(self, earlier: "Stats") -> None:
        """Count on from another Stats' counts (a session's garments replaced by another outfit's)."""
        with earlier._lock:
            counts, rejections = dict(earlier.counts), dict(earlier.rejections)
        with self._lock:
            for name, n in counts.items():
                self.counts[name] = self.counts.get(name, 0) + n
            for k, n in rejections.items():
                self.rejections[k] = self.rejections.get(k, 0) + n

    def snapshot(self) -> dict:
        with self._lock:
            return {"service": self.service, "counts": dict(self.counts), "rejections": dict(self.rejections),
                    "values": dict(self.values)}

    def publish(self, bus: zenoh.Session, force: bool = False, period: float = 1.0) -> bool:
        """Put the counters (at most once a period unless forced). Stats are best effort: where
        the bus can take no message (closed under a service that is still stopping), that is
        logged once and the service goes on. Returns whether they were put."""
        now = time.monotonic()
        if not force and now - self._last_publish < period:
            return False
        self._last_publish = now
        msg = Message("stats", self.session, meta=self.snapshot())
        try:
            bus.put(key(self.session, "stats", self.service), encode(msg))
        except zenoh.ZError as err:
            if not self._unpublished:
                log.warning("%s: stats of session %s not published: %s", self.service, self.session, err)
            self._unpublished = True
            return False
        self._unpublished = False
        return True


def put_reliably(bus: zenoh.Session, key_expr: str, payload: bytes) -> None:
    """Put a message that must not be lost (an announcement, a status, a session's end): where
    the transmission queue is full, zenoh waits for it rather than drop the message (its default
    for a put, DROP, suits stats, and garment frames a lagging display may miss)."""
    bus.put(key_expr, payload, congestion_control=zenoh.CongestionControl.BLOCK)


class Latched:
    """Messages put once and answered to later `get`s (topology, session description, skeleton);
    each put as it is latched, never dropped (`put_reliably`)."""

    def __init__(self, bus: zenoh.Session):
        self.bus = bus
        self._payloads: dict[str, bytes] = {}
        self._queryables: list = []

    def publish(self, key_expr: str, payload: bytes) -> None:
        first = key_expr not in self._payloads
        self._payloads[key_expr] = payload
        if first:  # a query may name the key or a wildcard over it: answer with the key itself
            self._queryables.append(self.bus.declare_queryable(key_expr,
                                                               lambda query, k=key_expr: self._answer(query, k)))
        put_reliably(self.bus, key_expr, payload)

    def _answer(self, query, key_expr: str) -> None:
        payload = self._payloads.get(key_expr)
        if payload is not None:  # (None: closed while the query was on its way)
            query.reply(key_expr, payload)

    def close(self) -> None:
        """Stop answering (a later `publish` answers again)."""
        for q in self._queryables:
            q.undeclare()
        self._queryables.clear()
        self._payloads.clear()


def fetch_latched(bus: zenoh.Session, selector: str, timeout: float = 2.0,
                  stats: Stats | None = None) -> dict[str, Message]:
    """Every latched message under `selector` that a queryable answers, decoded and validated."""
    out: dict[str, Message] = {}
    for reply in bus.get(selector, timeout=timeout):
        if reply.ok is None:
            continue
        k = str(reply.ok.key_expr)
        try:
            session, _ = parse_key(k)
            out[k] = decode(reply.ok.payload.to_bytes(), k, session)
        except MessageError as err:
            if stats is not None:
                stats.reject(err)
            else:
                log.warning("rejected %s", err)
    return out
