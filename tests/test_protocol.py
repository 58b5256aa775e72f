"""The bus contract: encoding, validation of malformed messages, retagging, pose quaternions."""

import json
import struct

import numpy as np
import pytest

from services.bus import check_session_name, key, parse_key
from services.ingest import matrices_to_quaternions, quaternions_to_matrices
from services.protocol import (MAGIC, MAX_LEVEL, PREFIX, SCHEMA_VERSION, Message, MessageError, decode, encode,
                               peek_frame, retag)

KEY = "tryon/s1/body"


def body_message(n=5, frame=7):
    rng = np.random.default_rng(0)
    return Message("body", "s1", frame, 0.125,
                   {"vertices": rng.normal(size=(n, 3)).astype(np.float32),
                    "normals": rng.normal(size=(n, 3)).astype(np.float32),
                    "q": rng.normal(size=10)}, {"ik_ms": 1.5})


def with_header(data: bytes, **changes) -> bytes:
    """The same message with header fields changed (payload kept)."""
    _, version, hlen = PREFIX.unpack_from(data, 0)
    h = json.loads(data[PREFIX.size:PREFIX.size + hlen])
    h.update(changes)
    header = json.dumps(h).encode()
    header += b" " * ((-(PREFIX.size + len(header))) % 8)
    return PREFIX.pack(MAGIC, version, len(header)) + header + data[PREFIX.size + hlen:]


def test_round_trip_keeps_every_bit_and_aligns_arrays():
    m = body_message()
    data = encode(m, stamp_ns=123)
    d = decode(data, KEY, "s1", "body")
    assert (d.kind, d.session, d.frame, d.time, d.meta, d.stamp_ns, d.origin_ns) == \
        ("body", "s1", 7, 0.125, {"ik_ms": 1.5}, 123, 123)
    for name, a in m.arrays.items():
        assert d.arrays[name].dtype == a.dtype and d.arrays[name].tobytes() == a.tobytes()
    _, _, hlen = PREFIX.unpack_from(data, 0)
    assert (PREFIX.size + hlen) % 8 == 0
    assert peek_frame(data) == 7


@pytest.mark.parametrize("mutate, problem", [
    (lambda d: d[:6], "shorter than"),
    (lambda d: b"XXXX" + d[4:], "bad magic"),
    (lambda d: struct.pack("<4sH", MAGIC, SCHEMA_VERSION + 1) + d[6:], f"schema version {SCHEMA_VERSION + 1}"),
    (lambda d: d[:PREFIX.size] + b"}" + d[PREFIX.size + 1:], "not valid JSON"),
    (lambda d: d[:-8], "needs"),
    (lambda d: d + b"\0" * 16, "left over"),
    (lambda d: with_header(d, kind="nonsense"), "unknown kind"),
    (lambda d: with_header(d, kind="garment"), "'body' is expected"),
    (lambda d: with_header(d, session="other"), "does not match the key's session"),
    (lambda d: with_header(d, frame=-1), "'frame'"),
    (lambda d: with_header(d, time="soon"), "'time'"),
])
def test_malformed_messages_are_rejected_with_key_and_problem(mutate, problem):
    data = encode(body_message())
    with pytest.raises(MessageError) as e:
        decode(mutate(data), KEY, "s1", "body")
    assert KEY in str(e.value) and problem in str(e.value)


@pytest.mark.parametrize("arrays, problem", [
    ({"vertices": np.zeros((4, 3), np.float32), "normals": np.zeros((4, 3), np.float32)}, "lacks array 'q'"),
    ({"vertices": np.zeros((4, 2), np.float32), "normals": np.zeros((4, 3), np.float32), "q": np.zeros(3)},
     "shape (4, 2), expected (n, 3)"),
    ({"vertices": np.zeros((4, 3)), "normals": np.zeros((4, 3), np.float32), "q": np.zeros(3)},
     "dtype <f8, expected <f4"),
    ({"vertices": np.full((4, 3), np.nan, np.float32), "normals": np.zeros((4, 3), np.float32), "q": np.zeros(3)},
     "NaN"),
    ({"vertices": np.zeros((4, 3), np.float32), "normals": np.zeros((4, 2), np.float32), "q": np.zeros(3)},
     "'normals' has shape (4, 2)"),
    ({"vertices": np.zeros((4, 3), np.float32), "normals": np.zeros((5, 3), np.float32), "q": np.zeros(3)},
     "5 normals for 4 vertices"),
])
def test_schema_violations_are_rejected(arrays, problem):
    data = encode(Message("body", "s1", 1, 0.0, arrays))
    with pytest.raises(MessageError, match="tryon/s1/body") as e:
        decode(data, KEY, "s1")
    assert problem in str(e.value)


def with_array_shape(data: bytes, name: str, shape: list) -> bytes:
    """The same message with one array descriptor's shape changed (payload kept)."""
    _, _, hlen = PREFIX.unpack_from(data, 0)
    arrays = json.loads(data[PREFIX.size:PREFIX.size + hlen])["arrays"]
    for d in arrays:
        if d["name"] == name:
            d["shape"] = shape
    return with_header(data, arrays=arrays)


@pytest.mark.parametrize("shape", [[2**32, 2**32], [2**62, 4], [2**21, 2**21, 2**21, 4], [2**63, 3]])
def test_an_array_whose_size_overflows_64_bits_is_rejected(shape):
    """Sizes whose product wraps round in 64-bit integers (2^64 elements: 0) were taken for an
    empty array, and numpy's reshape then failed with a plain ValueError, which the services do
    not count as a rejection."""
    data = with_array_shape(encode(body_message()), "vertices", shape)
    with pytest.raises(MessageError) as e:
        decode(data, KEY, "s1", "body")
    assert KEY in str(e.value) and "'vertices'" in str(e.value) and "needs" in str(e.value)


def test_unsupported_dtype_is_refused_when_encoding():
    with pytest.raises(MessageError, match="unsupported dtype"):
        encode(Message("stats", "s1", arrays={"x": np.zeros(3, np.complex64)}))


def test_retag_changes_only_the_session():
    data = encode(body_message(), stamp_ns=55)
    out = decode(retag(data, "s2"), "tryon/s2/body", "s2", "body")
    ref = decode(data)
    assert out.session == "s2" and out.stamp_ns == 55 and out.frame == ref.frame
    assert all(out.arrays[k].tobytes() == ref.arrays[k].tobytes() for k in ref.arrays)
    assert decode(retag(data, "s2", restamp=True)).stamp_ns > 55


def test_keys_and_session_names():
    assert key("s1", "garment", "top") == "tryon/s1/garment/top"
    assert parse_key("tryon/s1/garment/top") == ("s1", ("garment", "top"))
    with pytest.raises(MessageError):
        parse_key("other/s1/body")
    for bad in ("", "a/b", "a*", "x" * 65):
        with pytest.raises(ValueError, match="session name"):
            check_session_name(bad)


def test_pose_quaternions_known_rotation_and_round_trip():
    s = np.sqrt(0.5)
    m = quaternions_to_matrices(np.array([[0.0, 0.0, s, s]]), np.empty((1, 3, 3)))  # 90 deg about z
    np.testing.assert_allclose(m[0] @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    rng = np.random.default_rng(1)
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    r = quaternions_to_matrices(q, np.empty((50, 3, 3)))
    np.testing.assert_allclose(quaternions_to_matrices(matrices_to_quaternions(r), np.empty((50, 3, 3))), r, atol=1e-12)


def test_body_normals_are_optional_and_version_1_is_still_read():
    """Schema 2's body message carries no normals (a display computes them); one with them, as
    every version 1 body message had, is read and checked as before, so old recordings replay."""
    m = body_message()
    bare = Message("body", "s1", 7, 0.125, {"vertices": m.arrays["vertices"], "q": m.arrays["q"]})
    d = decode(encode(bare), KEY, "s1", "body")
    assert set(d.arrays) == {"vertices", "q"}
    v1 = bytearray(encode(m))
    v1[4:6] = (1).to_bytes(2, "little")
    d = decode(bytes(v1), KEY, "s1", "body")
    assert d.arrays["normals"].tobytes() == m.arrays["normals"].tobytes()
    assert SCHEMA_VERSION >= 2


def test_a_display_shades_a_mesh_sent_without_normals():
    """VertexNormals: a tent of two faces of equal area folded along the x axis: each face's
    normal at its own corner, their normalised mean on the ridge; a topology whose indices run
    past its vertices is refused."""
    from services.viewer import VertexNormals, triangles_problem
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 1], [0, 1, -1]], np.float32)  # ridge 0-1
    tris = np.array([[0, 1, 2], [1, 0, 3]], np.int32)
    n = VertexNormals(tris, 4)(x)
    r = 1 / np.sqrt(2)
    assert np.allclose(n, [[0, -1, 0], [0, -1, 0], [0, -r, r], [0, -r, -r]])
    assert triangles_problem(tris, 4) is None
    assert "outside 0..2" in triangles_problem(tris, 3)
    assert "n_vertices" in triangles_problem(tris, "4")


@pytest.mark.parametrize("level", [0, MAX_LEVEL + 1, True, 6.0, "6"])
def test_a_session_description_with_a_level_out_of_range_is_refused(level):
    from services.cloth_service import OutfitSpec

    default = OutfitSpec("female_casualsuit01")
    says = rf"tryon/s/session: session 'level' must be an integer 1-{MAX_LEVEL} or null"
    with pytest.raises(MessageError, match=says):
        OutfitSpec.from_description({"level": level}, default, "tryon/s/session")
    assert OutfitSpec.from_description({"level": None}, default, "tryon/s/session").level is None
    assert OutfitSpec.from_description({}, default, "tryon/s/session").level == 6


def test_a_stray_frame_far_ahead_does_not_hold_the_stream_out():
    """FrameOrder: frames taken in order, gaps allowed; one at or before the last taken is
    rejected naming the key. A stray numbered far ahead is taken (nothing tells it from a stream
    resuming after a pause), and then RESYNC_FRAMES frames in a row behind it, each after the one
    before, show the stream going on: the last of them is taken, and the order follows it."""
    from services.frame_order import FrameOrder

    order = FrameOrder()
    assert FrameOrder.RESYNC_FRAMES == 3
    assert [order.take(f, KEY) for f in (0, 1, 5)] == [None, None, None]  # (a gap: a paused capture)
    with pytest.raises(MessageError, match=rf"{KEY}: frame 5 arrives after frame 5"):
        order.take(5, KEY)
    assert order.take(10**6, KEY) is None  # the stray
    for f in (6, 7):
        with pytest.raises(MessageError, match="arrives after frame 1000000"):
            order.take(f, KEY)
    assert order.take(8, KEY) == 10**6 and order.last == 8
    assert order.take(9, KEY) is None and order.last == 9

    # strays behind a stream that goes on are rejected every time: the stream's frames between
    # them, or a stray's repeats, break the run
    order = FrameOrder()
    for f in range(100, 110):
        assert order.take(f, KEY) is None
        for stray in (f - 50, f - 50):
            with pytest.raises(MessageError):
                order.take(stray, KEY)
    assert order.last == 109
