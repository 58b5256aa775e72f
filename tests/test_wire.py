"""Compact meshes on the bus (services.wire): the 16-bit position grid, octahedral normals, and the
two forms of the garment and body messages in the bus contract."""

import numpy as np
import pytest

from services.protocol import PREFIX, Message, MessageError, decode, encode
from services.wire import GRID, CompactMesh, CompactPositions, body_vertices, garment_mesh, vertex_count

KEY = "tryon/s1/garment/top"


def unit_vectors(n, seed=0):
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1)[:, None]


def angle_deg(a, b):
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), (a * b).sum(1)))


def test_positions_come_back_within_half_a_grid_step_and_the_extremes_exactly():
    rng = np.random.default_rng(1)
    p = rng.uniform((-0.3, 0.1, -0.2), (0.4, 1.6, 0.25), (5000, 3))
    c = CompactMesh(len(p))
    arrays = c.encode(p, unit_vectors(len(p)))
    extent = p.max(0) - p.min(0)
    np.testing.assert_allclose(arrays["position_step"], extent / GRID, rtol=1e-6)
    assert arrays["positions_u16"].min(0).tolist() == [0, 0, 0]
    assert arrays["positions_u16"].max(0).tolist() == [GRID] * 3
    back, _ = garment_mesh(arrays)
    ulp = np.spacing(np.float32(np.abs(p).max()))  # the decoding's float32 product and sum round too
    assert (np.abs(back - p) <= arrays["position_step"] / 2 + 2 * ulp).all()  # the nearest grid step
    assert np.abs(back - p).max() < 12e-6  # 1.5 m tall: a 23 µm grid


def test_a_flat_axis_gets_step_one_and_reads_back_exactly():
    p = np.zeros((4, 3))
    p[:, 0] = [0.0, 0.25, 0.5, 1.0]
    p[:, 1] = 0.75  # flat: one value on that axis
    arrays = CompactMesh(4).encode(p, np.tile([0.0, 0.0, 1.0], (4, 1)))
    assert arrays["position_step"][1] == 1.0 and (arrays["positions_u16"][:, 1] == 0).all()
    assert arrays["positions_u16"][:, 0].tolist() == [0, 16384, 32768, GRID]  # 0.25 * 65535 = 16383.75
    np.testing.assert_array_equal(garment_mesh(arrays)[0][:, 1], 0.75)


def test_octahedral_normals_keep_the_axes_exactly_and_any_direction_within_0_004_degrees():
    axes = np.vstack([np.eye(3), -np.eye(3)])
    diagonals = np.array([[sx, sy, sz] for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)]) / np.sqrt(3)
    equator = np.array([[np.cos(a), np.sin(a), 0.0] for a in np.linspace(0, 2 * np.pi, 37)])  # the fold, z = 0
    n = np.vstack([axes, diagonals, equator, unit_vectors(20000)])
    c = CompactMesh(len(n))
    arrays = c.encode(np.zeros((len(n), 3)), n)
    _, back = garment_mesh(arrays)
    np.testing.assert_array_equal(back[:6], axes)
    assert angle_deg(back, n).max() < 0.004
    np.testing.assert_allclose(np.linalg.norm(back, axis=1), 1.0, atol=1e-6)
    # +z at the octahedron's centre, +x on its rim; the lower half folded outside the upper's
    # diamond, so -z lands on the corner
    assert arrays["normals_oct16"][[2, 0, 5]].tolist() == [[0, 0], [32767, 0], [32767, 32767]]


def test_a_zero_normal_reads_back_as_up_and_a_nan_position_is_refused():
    c = CompactMesh(2)
    _, n = garment_mesh(c.encode(np.zeros((2, 3)), np.zeros((2, 3))))
    np.testing.assert_array_equal(n, [[0, 0, 1], [0, 0, 1]])
    p = np.zeros((2, 3))
    p[1, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        c.encode(p, np.zeros((2, 3)))


def compact_message(n=50):
    rng = np.random.default_rng(2)
    arrays = CompactMesh(n).encode(rng.uniform(-1, 1, (n, 3)), unit_vectors(n))
    return Message("garment", "s1", 3, 0.05, {k: v.copy() for k, v in arrays.items()}, {"garment": "top"})


def test_a_compact_garment_message_is_10_bytes_a_vertex_and_round_trips():
    n = 11000
    m = compact_message(n)
    data = encode(m)
    d = decode(data, KEY, "s1", "garment")
    assert all(d.arrays[k].tobytes() == a.tobytes() for k, a in m.arrays.items())
    _, _, hlen = PREFIX.unpack_from(data, 0)
    assert len(data) - PREFIX.size - hlen == 6 * n + 4 * n + 32  # + origin and step, each padded to 16
    f32 = Message("garment", "s1", 3, 0.05, dict(zip(("positions", "normals"), garment_mesh(d.arrays))))
    assert len(encode(f32)) - len(data) > 13 * n  # 24 bytes a vertex as float32


@pytest.mark.parametrize("change, problem", [
    (lambda a: a.pop("normals_oct16"), "needs its normals as normals or normals_oct16"),
    (lambda a: a.update(normals=np.zeros((50, 3), np.float32)), "normals or normals_oct16, not both"),
    (lambda a: a.pop("position_origin"), "lacks array 'position_origin'"),
    (lambda a: a.update(positions=np.zeros((50, 3), np.float32)), "positions or positions_u16+"),
    (lambda a: a["position_step"].__setitem__(1, 0.0), "'position_step' must be > 0"),
    (lambda a: a.update(position_step=np.ones(3)), "dtype <f8, expected <f4"),
    (lambda a: a.update(normals_oct16=np.zeros((49, 2), np.int16)), "49 normals for 50 vertices"),
    (lambda a: a.update(positions_u16=np.zeros((50, 3), np.int16)), "'positions_u16' has dtype <i2"),
])
def test_a_malformed_compact_garment_is_rejected_naming_the_array(change, problem):
    m = compact_message()
    change(m.arrays)
    with pytest.raises(MessageError) as e:
        decode(encode(m), KEY, "s1", "garment")
    assert KEY in str(e.value) and problem in str(e.value)


def test_a_float32_garment_is_still_read():
    n = unit_vectors(7)
    p = np.arange(21, dtype=np.float32).reshape(7, 3)
    d = decode(encode(Message("garment", "s1", 0, 0.0, {"positions": p, "normals": n.astype(np.float32)})), KEY)
    back_p, back_n = garment_mesh(d.arrays)
    np.testing.assert_array_equal(back_p, p)
    np.testing.assert_array_equal(back_n, n.astype(np.float32))


def test_a_compact_body_is_6_bytes_a_vertex_and_decodes_within_half_a_step_into_any_buffer():
    """A body 1.8 m tall of 13,380 vertices: 80 kB of vertices, each within half its axis's grid
    step (at most 14 µm); decoded into a float64 buffer it holds the same values as decoded to
    float32 (the cloth service decodes straight into its float64 body)."""
    rng = np.random.default_rng(3)
    v = rng.uniform([-0.3, 0.0, -0.2], [0.3, 1.8, 0.2], size=(13380, 3))
    q = np.array([0.1, 0.9, 0.0, 0.0, 0.0, 0.0, 1.0])
    compact = CompactPositions(len(v))
    m = Message("body", "s1", 5, 0.08, dict(compact.encode(v), q=q))
    data = encode(m)
    d = decode(data, "tryon/s1/body", "s1", "body")
    assert vertex_count(d.arrays) == len(v)
    _, _, hlen = PREFIX.unpack_from(data, 0)
    assert len(data) - PREFIX.size - hlen == 6 * len(v) + 32 + 56  # + origin, step and q
    back = body_vertices(d.arrays)
    assert back.dtype == np.float32
    step = d.arrays["position_step"].astype(np.float64)
    assert step.max() < 28e-6
    assert np.all(np.abs(back - v) <= 0.5 * step + 1e-6)
    out = np.empty((len(v), 3))
    assert body_vertices(d.arrays, out=out) is out
    np.testing.assert_array_equal(out, back.astype(np.float64))
    f32 = decode(encode(Message("body", "s1", 5, 0.08, {"vertices": v.astype(np.float32), "q": q})))
    assert body_vertices(f32.arrays) is f32.arrays["vertices"]  # float32 bodies are still read
    np.testing.assert_array_equal(body_vertices(f32.arrays, out=out), v.astype(np.float32))
    with pytest.raises(ValueError, match="NaN"):
        compact.encode(np.full((len(v), 3), np.nan))


@pytest.mark.parametrize("arrays, problem", [
    ({"q": np.zeros(3)}, "body message needs its vertices as vertices or positions_u16+"),
    ({"vertices": np.zeros((4, 3), np.float32), "positions_u16": np.zeros((4, 3), np.uint16), "q": np.zeros(3)},
     "not both"),
    ({"positions_u16": np.zeros((4, 3), np.uint16), "position_origin": np.zeros(3, np.float32), "q": np.zeros(3)},
     "lacks array 'position_step'"),
])
def test_a_body_without_exactly_one_form_of_its_vertices_is_rejected(arrays, problem):
    with pytest.raises(MessageError) as e:
        decode(encode(Message("body", "s1", 0, 0.0, arrays)), "tryon/s1/body")
    assert "tryon/s1/body" in str(e.value) and problem in str(e.value)
