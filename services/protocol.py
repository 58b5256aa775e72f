"""The bus contract: versioned binary messages with a JSON header and raw little-endian arrays.

Wire layout of every message (all integers little-endian):

    offset 0   4 bytes   magic b"TRYN"
    offset 4   uint16    schema version (SCHEMA_VERSION)
    offset 6   uint32    header length H in bytes
    offset 10  H bytes   header, UTF-8 JSON object (below), space-padded so the payload starts
                         at a multiple of 8 bytes
    then       payload   the arrays in header order, each starting at a multiple of 8 bytes
                         from the start of the payload, C order, little-endian

Header fields:
    kind      one of KINDS
    session   the session name (must match the key expression's session)
    frame     frame number in the session (int >= 0; topology/session/skeleton: 0)
    time      seconds since the session's first frame (float)
    stamp_ns  wall-clock time of publication, ns since the Unix epoch (int)
    origin_ns stamp_ns of the message this one was computed from (garment: its body frame;
              body: its pose message, or its own stamp_ns) - end-to-end latency = now - origin_ns
    arrays    [{"name": str, "dtype": "<f4" | "<f8" | "<i4" | "<u4" | "<i2" | "<u2" | "|u1", "shape": [int, ...]}, ...]
    meta      free JSON object (per-kind fields, documented in README "Bus contract")

A message that breaks any rule raises MessageError naming the key expression and the problem;
services catch it, log it, count it in their stats and go on serving.
"""

from __future__ import annotations

import json
import math
import struct
import time
from dataclasses import dataclass, field

import numpy as np

MAGIC = b"TRYN"
SCHEMA_VERSION = 4
MAX_LEVEL = 16  # the finest PN tessellation level a session description may ask for
# versions this build reads. Version 1 differs only in the body message, which had to carry the
# skin's vertex normals: half its bytes, read by no service (a display computes them from the
# latched topology). Version 2 garments are float32 only; version 3 adds the compact garment
# arrays (`services.wire`), version 4 the body's vertices in the same compact form. Recordings of
# any of them still replay.
READABLE_VERSIONS = (1, 2, 3, 4)
PREFIX = struct.Struct("<4sHI")
MAX_HEADER = 1 << 20
ALIGN = 8
DTYPES = {"<f4": np.float32, "<f8": np.float64, "<i4": np.int32, "<u4": np.uint32, "<i2": np.int16,
          "<u2": np.uint16, "|u1": np.uint8}
KINDS = ("session", "skeleton", "pose", "body", "garment", "topology", "stats", "control")

# Required arrays per kind: name -> (allowed dtypes, shape pattern; None = any length, an int = exact).
SCHEMAS: dict[str, dict[str, tuple[tuple[str, ...], tuple]]] = {
    "session": {},
    "skeleton": {"parents": (("<i4",), (None,)), "heads": (("<f8", "<f4"), (None, 3)),
                 "tails": (("<f8", "<f4"), (None, 3))},
    "pose": {"local_rotations": (("<f8", "<f4"), (None, 4)), "root_position": (("<f8", "<f4"), (3,))},
    "body": {"q": (("<f8",), (None,))},  # and its vertices, as float32 or compact: FORMS
    "garment": {},  # positions and normals, as float32 or compact: FORMS
    "topology": {"triangles": (("<i4",), (None, 3))},
    "stats": {},
    "control": {},
}
# The compact form of positions (`services.wire`): a per-frame, per-axis 16-bit grid.
COMPACT_POSITIONS = {"positions_u16": (("<u2",), (None, 3)), "position_origin": (("<f4",), (3,)),
                     "position_step": (("<f4",), (3,))}
# Arrays a message may carry, validated like the required ones when present.
OPTIONAL: dict[str, dict[str, tuple[tuple[str, ...], tuple]]] = {
    "body": {"vertices": (("<f4",), (None, 3)), "normals": (("<f4",), (None, 3)),  # (version 1 always had normals)
             **COMPACT_POSITIONS},
    "garment": {"positions": (("<f4",), (None, 3)), "normals": (("<f4",), (None, 3)),
                **COMPACT_POSITIONS, "normals_oct16": (("<i2",), (None, 2))},
}
# A body carries its vertices, a garment its positions and its normals, each in exactly one of
# these forms (float32, or compact: `services.wire`).
COMPACT = ("positions_u16", "position_origin", "position_step")
FORMS = {"body": {"vertices": (("vertices",), COMPACT)},
         "garment": {"positions": (("positions",), COMPACT), "normals": (("normals",), ("normals_oct16",))}}


class MessageError(ValueError):
    """A message that breaks the bus contract; the text names the key expression and the problem."""

    def __init__(self, key: str, problem: str):
        super().__init__(f"{key}: {problem}")
        self.key, self.problem = key, problem


@dataclass
class Message:
    kind: str
    session: str
    frame: int = 0
    time: float = 0.0
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)
    stamp_ns: int = 0
    origin_ns: int = 0


def _pad(n: int) -> int:
    return (-n) % ALIGN


def encode(msg: Message, stamp_ns: int | None = None) -> bytes:
    """Serialise a message; stamp_ns defaults to now (and origin_ns, if unset, to stamp_ns)."""
    stamp = time.time_ns() if stamp_ns is None else stamp_ns
    descr, chunks = [], []
    for name, a in msg.arrays.items():
        a = np.asarray(a)
        code = a.dtype.newbyteorder("<").str
        if code not in DTYPES:
            raise MessageError(msg.kind, f"array {name!r} has unsupported dtype {a.dtype}")
        descr.append({"name": name, "dtype": code, "shape": list(a.shape)})
        raw = np.ascontiguousarray(a, dtype=np.dtype(code)).tobytes()
        chunks.append(raw + b"\0" * _pad(len(raw)))
    header = json.dumps({
        "kind": msg.kind, "session": msg.session, "frame": int(msg.frame), "time": float(msg.time),
        "stamp_ns": stamp, "origin_ns": int(msg.origin_ns or stamp), "arrays": descr, "meta": msg.meta,
    }, separators=(",", ":")).encode()
    return b"".join([PREFIX.pack(MAGIC, SCHEMA_VERSION, len(header) + _pad(PREFIX.size + len(header))),
                     header, b" " * _pad(PREFIX.size + len(header)), *chunks])


def _int(h: dict, name: str, key: str) -> int:
    v = h.get(name)
    if not isinstance(v, int) or isinstance(v, bool) or v < 0:
        raise MessageError(key, f"header field {name!r} must be an integer >= 0, got {v!r}")
    return v


def decode(data: bytes | memoryview, key: str = "?", session: str | None = None,
           kind: str | None = None) -> Message:
    """Parse and validate one message. Arrays are read-only views of `data` (no copy).

    session/kind: what the key expression says the message must be (checked against the header).
    """
    buf = memoryview(data)
    if len(buf) < PREFIX.size:
        raise MessageError(key, f"message of {len(buf)} bytes is shorter than the {PREFIX.size}-byte prefix")
    magic, version, hlen = PREFIX.unpack_from(buf, 0)
    if magic != MAGIC:
        raise MessageError(key, f"bad magic {bytes(magic)!r} (expected {MAGIC!r}): not a tryon message")
    if version not in READABLE_VERSIONS:
        raise MessageError(key, f"schema version {version} is not supported (this build reads "
                                f"{', '.join(map(str, READABLE_VERSIONS))})")
    if hlen > MAX_HEADER or PREFIX.size + hlen > len(buf):
        raise MessageError(key, f"header length {hlen} runs past the message ({len(buf)} bytes)")
    try:
        h = json.loads(bytes(buf[PREFIX.size:PREFIX.size + hlen]))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MessageError(key, f"header is not valid JSON ({exc})") from None
    if not isinstance(h, dict):
        raise MessageError(key, "header is not a JSON object")
    k = h.get("kind")
    if k not in KINDS:
        raise MessageError(key, f"unknown kind {k!r} (expected one of {', '.join(KINDS)})")
    if kind is not None and k != kind:
        raise MessageError(key, f"kind {k!r} where {kind!r} is expected")
    s = h.get("session")
    if not isinstance(s, str) or not s:
        raise MessageError(key, f"header field 'session' must be a non-empty string, got {s!r}")
    if session is not None and s != session:
        raise MessageError(key, f"header session {s!r} does not match the key's session {session!r}")
    frame, stamp, origin = _int(h, "frame", key), _int(h, "stamp_ns", key), _int(h, "origin_ns", key)
    t = h.get("time")
    if not isinstance(t, (int, float)) or isinstance(t, bool) or not np.isfinite(t):
        raise MessageError(key, f"header field 'time' must be a finite number, got {t!r}")
    meta = h.get("meta", {})
    if not isinstance(meta, dict):
        raise MessageError(key, "header field 'meta' must be a JSON object")
    descr = h.get("arrays")
    if not isinstance(descr, list):
        raise MessageError(key, "header field 'arrays' must be a list")
    arrays: dict[str, np.ndarray] = {}
    offset = PREFIX.size + hlen
    for d in descr:
        if not isinstance(d, dict) or not isinstance(d.get("name"), str):
            raise MessageError(key, f"array descriptor {d!r} has no name")
        name, code, shape = d["name"], d.get("dtype"), d.get("shape")
        if code not in DTYPES:
            raise MessageError(key, f"array {name!r}: dtype {code!r} not allowed ({', '.join(DTYPES)})")
        if (not isinstance(shape, list) or len(shape) > 4
                or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)):
            raise MessageError(key, f"array {name!r}: shape {shape!r} is not a list of up to 4 sizes >= 0")
        if name in arrays:
            raise MessageError(key, f"array {name!r} appears twice")
        dtype = np.dtype(code)
        nbytes = math.prod(shape) * dtype.itemsize  # (Python integers: a product past 2^63 does not wrap)
        if offset + nbytes > len(buf):
            raise MessageError(key, f"array {name!r} {code}{shape} needs {nbytes} bytes, "
                                    f"{len(buf) - offset} left in the message")
        arrays[name] = np.frombuffer(buf, dtype=dtype, count=nbytes // dtype.itemsize, offset=offset).reshape(shape)
        offset += nbytes + _pad(nbytes)
    if offset != len(buf):
        raise MessageError(key, f"{len(buf) - offset} bytes left over after the arrays")
    for name, (codes, pattern) in (SCHEMAS[k] | OPTIONAL.get(k, {})).items():
        a = arrays.get(name)
        if a is None:
            if name in SCHEMAS[k]:
                raise MessageError(key, f"{k} message lacks array {name!r}")
            continue
        if a.dtype.str not in codes:
            raise MessageError(key, f"array {name!r} has dtype {a.dtype.str}, expected {' or '.join(codes)}")
        if len(a.shape) != len(pattern) or any(p is not None and p != n for p, n in zip(pattern, a.shape)):
            want = "(" + ", ".join("n" if p is None else str(p) for p in pattern) + ")"
            raise MessageError(key, f"array {name!r} has shape {tuple(a.shape)}, expected {want}")
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise MessageError(key, f"array {name!r} holds NaN or infinite values")
    if k in FORMS:
        _check_forms(k, arrays, key)
    points = arrays.get("vertices" if k == "body" else "positions", arrays.get("positions_u16"))
    normals = arrays.get("normals", arrays.get("normals_oct16"))
    if normals is not None and points is not None and normals.shape[0] != points.shape[0]:
        raise MessageError(key, f"{normals.shape[0]} normals for {points.shape[0]} vertices")
    return Message(k, s, frame, float(t), arrays, meta, stamp, origin)


def _check_forms(kind: str, arrays: dict[str, np.ndarray], key: str) -> None:
    for what, forms in FORMS[kind].items():
        present = [f for f in forms if any(name in arrays for name in f)]
        if len(present) != 1:
            names = " or ".join("+".join(f) for f in forms)
            raise MessageError(key, f"{kind} message needs its {what} as {names}"
                                    + (", not both" if present else ""))
        missing = [name for name in present[0] if name not in arrays]
        if missing:
            raise MessageError(key, f"{kind} message lacks array {missing[0]!r} (with {present[0][0]!r})")
    step = arrays.get("position_step")
    if step is not None and not (step > 0).all():
        raise MessageError(key, f"array 'position_step' must be > 0, got {step.tolist()}")


def peek_header(data: bytes | memoryview) -> dict | None:
    """The JSON header of a message, unvalidated and without touching its arrays (None when
    unreadable): for passing messages on (recorder) without the cost of `decode`."""
    try:
        magic, _, hlen = PREFIX.unpack_from(data, 0)
        h = json.loads(bytes(memoryview(data)[PREFIX.size:PREFIX.size + hlen])) if magic == MAGIC else None
        return h if isinstance(h, dict) else None
    except (struct.error, UnicodeDecodeError, json.JSONDecodeError):
        return None


def peek_frame(data: bytes | memoryview) -> int | None:
    """Frame number of a message without decoding its arrays (None when unreadable)."""
    h = peek_header(data)
    return h.get("frame") if h is not None and isinstance(h.get("frame"), int) else None


def retag(data: bytes | memoryview, session: str, key: str = "?", restamp: bool = False) -> bytes:
    """The same message under another session name (restamp: published now); the arrays and every
    other field are kept bit for bit."""
    decode(data, key)  # reject what is not a valid message before touching it
    buf = memoryview(data)
    _, version, hlen = PREFIX.unpack_from(buf, 0)
    h = json.loads(bytes(buf[PREFIX.size:PREFIX.size + hlen]))
    h["session"] = session
    if restamp:
        h["stamp_ns"] = h["origin_ns"] = time.time_ns()
    header = json.dumps(h, separators=(",", ":")).encode()
    pad = _pad(PREFIX.size + len(header))
    return b"".join([PREFIX.pack(MAGIC, version, len(header) + pad), header, b" " * pad,
                     bytes(buf[PREFIX.size + hlen:])])
