"""Inside the body, exactly: the winding number of a closed surface that may cut through itself.

A skinned body is watertight but not a simple surface: linear blend skinning presses a raised
thigh into the belly, the shoulder cap into the chest at the armpit, the calf into the thigh
behind a bent knee. There a face of one part is buried in the other, and the side of the
nearest face (what the S101 ring test reads) says "outside" for a point enclosed by the other
part's skin. The winding number counts how many times the surface wraps a point: 0 outside,
1 inside, 2 where two parts overlap. It is the signed count of the surface's crossings on a
ray from the point, here along +z: +1 where the ray leaves through a face, -1 where it enters.

    faces = closed_faces(triangles, keep)   # once: the faces kept, their holes capped
    grid = WindingGrid(faces, n_vertices)
    grid.update(body_x)                     # once per pose (a column grid over the faces)
    winding_number(px, py, pz, body_x, faces, *grid.arrays())   # an int

The rays run along +z, through the body's thin side: across a standing body's walls, where a
vertical ray would run along them and meet every face of a leg (a query 4.8 µs up, 0.3-0.9
along z, on the MakeHuman body). Clothes never reach the head,
hands and toes (two thirds of the MakeHuman body's faces): `closed_faces` leaves out the faces
it is not given and caps the holes that leaves (at the neck and toes; at the wrists too
without the hands) with a fan of the boundary's own vertices. The capped surface is closed, so
its winding number is exact everywhere outside the capped-off parts, where it differs from the
whole body's only inside them. The cloth keeps the hands (`BodyMesh.wound_faces`): a sleeve's
cuff and a skirt under a hand meet them.

The grid is dense over the body's x-y extent: each column of `cell` x `cell` lists the faces
whose x-y box overlaps it (a counting sort, two passes over the faces) with each face's box
(its span along the ray and across it, single precision, widened a little), so a query reads
one column and tests each face in it once. On a closed
surface the crossings of a whole line sum to 0: a query counts on the side of the point
where less of the column lies (the crossings beyond it, or minus those before it), skipping
faces wholly on the other side by their span; a point near the skin has the body's far wall
on the other side (the clothed MakeHuman body, 9,574 faces with the caps, ~37 faces a
column near the skin: 0.22 µs per query near the skin, against 0.51 µs over the whole
column; ~220-280 µs per pose; 15,862 faces with the hands, 351 → 597 µs per pose on a slower
day of the same machine). Since the seventy-fifth session a face whose box the line misses
is skipped too, and the skips are decided without a branch (`winding_number`): with the hands,
~23 entries a column near the skin, of which one or two are crossed, 176 → 108 ns a query
near the skin; the build 600 → 620-650 µs a pose, each column's extent taken from its entries
after the fill. A point exactly on an edge or vertex as the
ray sees it is counted by one face of the two by the top-left rule, from the edge's lower
vertex index, so the two faces get bitwise opposite edge values: no ray slips between faces,
none counts twice.
"""

from __future__ import annotations

import math

import numpy as np

from .jit import helper, kernel
from .topology import boundary_loops

U, V, W = 0, 1, 2  # the columns lie across x and y; the rays run along +z, through the body's thin side
WINDING_CELL = 0.02  # m: the columns' side (a few body edges)
MAX_COLUMNS = 1 << 16  # a body spread wider than this many columns gets wider columns
SPAN = 6  # per column entry (float32): its face's low and high coordinate along the ray, then across it on u, then on v


@kernel
def build_winding_grid(body_x, tris, cell, lo, start, ids, span, vertex_column, face_columns, extent):
    """Bucket every face into the columns its box across the ray overlaps (CSR: start, ids),
    over the vertices' extent. lo (5,) float64, written: the grid's corner (u0, v0), its columns
    along u and along v, and their side: cell, widened until the columns fit in len(start) - 2.
    span (SPAN, len(ids)) float32, written: each entry's face's lowest and highest coordinate along
    the ray, then across it on u and on v (widened a little: `_down`, `_up`), one row each (a
    query compares a run of entries at once); extent
    (len(start) - 1, 2) float64, written: the lowest and highest along the ray over each column's
    entries (`winding_number` reads them to skip whole columns, and to choose a side).
    vertex_column (n_vertices, 2), face_columns (n_faces, 4) int32: scratch. Returns the entries
    needed (one more than the columns hold: see below); when that exceeds len(ids) nothing is
    filled (grow ids and call again).

    A face lies in one to four columns nearly always (the body's faces are about half a column
    across). Such a face writes all four of its 2 x 2 block, without a branch: the columns it
    is not in are replaced by a spare column past the grid's (index columns), whose count it
    adds 0 to and whose one entry, past every column's, it overwrites. A loop over a face's own
    columns, one or two per axis, mispredicted its ends: the rebuild of the cloth's winding
    surface (10,146 faces) took 377-386 µs a pose against 276-298 µs now (sixtieth session,
    warm caches, the same machine and minutes). The entries and their order are the same either
    way (face order in each column), and so is every winding number."""
    u0 = v0 = np.inf
    u1 = v1 = -np.inf
    for a in range(body_x.shape[0]):
        u0 = min(u0, body_x[a, U])
        u1 = max(u1, body_x[a, U])
        v0 = min(v0, body_x[a, V])
        v1 = max(v1, body_x[a, V])
    nu = nv = 0
    while True:
        nu = int((u1 - u0) / cell) + 1
        nv = int((v1 - v0) / cell) + 1
        if nu * nv < start.shape[0] - 1:  # (and the spare column)
            break
        cell *= 1.5
    lo[0], lo[1], lo[2], lo[3], lo[4] = u0, v0, nu, nv, cell
    inv = 1.0 / cell
    for a in range(body_x.shape[0]):  # a face's columns span its corners' (floor is monotone)
        vertex_column[a, 0] = min(int((body_x[a, U] - u0) * inv), nu - 1)
        vertex_column[a, 1] = min(int((body_x[a, V] - v0) * inv), nv - 1)
    n = nu * nv
    spare = n
    start[: n + 2] = 0
    for t in range(tris.shape[0]):  # count
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        i0 = min(vertex_column[a, 0], min(vertex_column[b, 0], vertex_column[c, 0]))
        i1 = max(vertex_column[a, 0], max(vertex_column[b, 0], vertex_column[c, 0]))
        k0 = min(vertex_column[a, 1], min(vertex_column[b, 1], vertex_column[c, 1]))
        k1 = max(vertex_column[a, 1], max(vertex_column[b, 1], vertex_column[c, 1]))
        face_columns[t, 0], face_columns[t, 1], face_columns[t, 2], face_columns[t, 3] = i0, i1, k0, k1
        if i1 - i0 <= 1 and k1 - k0 <= 1:
            wi, wk = i1 - i0, k1 - k0
            c00 = i0 * nv + k0
            start[c00 + 1] += 1
            start[spare + wk * (c00 + 1 - spare) + 1] += wk
            start[spare + wi * (c00 + nv - spare) + 1] += wi
            start[spare + wi * wk * (c00 + nv + 1 - spare) + 1] += wi * wk
            continue
        for i in range(i0, i1 + 1):
            for k in range(k0, k1 + 1):
                start[i * nv + k + 1] += 1
    for c in range(n):
        start[c + 1] += start[c]
    total = start[n]  # the spare column's one entry: ids[total] (its count stays 0)
    if total + 1 > ids.shape[0]:
        return total + 1
    for t in range(tris.shape[0]):  # fill: start[c] runs up to the next column's start
        a, b, d = tris[t, 0], tris[t, 1], tris[t, 2]
        w0 = min(body_x[a, W], min(body_x[b, W], body_x[d, W]))
        w1 = max(body_x[a, W], max(body_x[b, W], body_x[d, W]))
        u0 = min(body_x[a, U], min(body_x[b, U], body_x[d, U]))
        u1 = max(body_x[a, U], max(body_x[b, U], body_x[d, U]))
        v0 = min(body_x[a, V], min(body_x[b, V], body_x[d, V]))
        v1 = max(body_x[a, V], max(body_x[b, V], body_x[d, V]))
        # the entry's box in single precision, widened: a skip on it stays exact
        b0, b1, b2, b3, b4, b5 = _down(w0), _up(w1), _down(u0), _up(u1), _down(v0), _up(v1)
        i0, i1, k0, k1 = face_columns[t, 0], face_columns[t, 1], face_columns[t, 2], face_columns[t, 3]
        if i1 - i0 <= 1 and k1 - k0 <= 1:
            wi, wk = i1 - i0, k1 - k0
            c00 = i0 * nv + k0
            _put(t, c00, 1, b0, b1, b2, b3, b4, b5, start, ids, span)
            _put(t, spare + wk * (c00 + 1 - spare), wk, b0, b1, b2, b3, b4, b5, start, ids, span)
            _put(t, spare + wi * (c00 + nv - spare), wi, b0, b1, b2, b3, b4, b5, start, ids, span)
            _put(t, spare + wi * wk * (c00 + nv + 1 - spare), wi * wk, b0, b1, b2, b3, b4, b5, start, ids, span)
            continue
        for i in range(i0, i1 + 1):
            for k in range(k0, k1 + 1):
                _put(t, i * nv + k, 1, b0, b1, b2, b3, b4, b5, start, ids, span)
    for c in range(n, 0, -1):  # back to each column's first entry
        start[c] = start[c - 1]
    start[0] = 0
    for c in range(n):  # each column's extent along the ray, from its entries (in order: one pass over them)
        lo_w, hi_w = np.inf, -np.inf
        for e in range(start[c], start[c + 1]):
            lo_w = min(lo_w, span[0, e])
            hi_w = max(hi_w, span[1, e])
        extent[c, 0] = lo_w
        extent[c, 1] = hi_w
    return total + 1


# the widening of an entry's single-precision box: more than float32's rounding error (half an
# ulp, under 6e-8 of the value) anywhere, so the box holds the face (a skip on it stays exact)
BOX_SLACK = 1e-6  # m
BOX_SLACK_RELATIVE = 1.2e-7


@helper
def _down(x):
    """x in single precision, below x."""
    return np.float32(x - (BOX_SLACK + abs(x) * BOX_SLACK_RELATIVE))


@helper
def _up(x):
    """x in single precision, above x."""
    return np.float32(x + (BOX_SLACK + abs(x) * BOX_SLACK_RELATIVE))


@helper
def _put(t, c, taken, b0, b1, b2, b3, b4, b5, start, ids, span):
    """Face t into column c's next entry, which is kept if `taken` (1) and overwritten by the
    next one put there if not (0: the spare column): b0 ... b5 its box (float32, widened a
    little) along the ray, then across it on u and on v, each low, high."""
    e = start[c]
    ids[e] = t
    span[0, e] = b0
    span[1, e] = b1
    span[2, e] = b2
    span[3, e] = b3
    span[4, e] = b4
    span[5, e] = b5
    start[c] = e + taken


@helper
def edge_side(x, a, b, pu, pv, u, v):
    """Twice the signed area of (a, b, p) across a ray along the third axis (u, v: the axes
    across it), computed from the lower vertex index, so that the two faces on an edge get
    exactly opposite values."""
    lo, hi = min(a, b), max(a, b)
    s = (x[hi, u] - x[lo, u]) * (pv - x[lo, v]) - (x[hi, v] - x[lo, v]) * (pu - x[lo, u])
    return s if a == lo else -s


@helper
def owns_edge(x, a, b, flip, u, v):
    """Top-left rule: which of the two faces on an edge counts a point exactly on it (the edge
    a -> b as the face, turned counter-clockwise across the ray, runs along it)."""
    du = x[b, u] - x[a, u]
    dv = x[b, v] - x[a, v]
    if flip:
        du, dv = -du, -dv
    return dv > 0.0 or (dv == 0.0 and du < 0.0)


@helper
def ray_crossing(x, tris, t, pu, pv, u, v, w):
    """Where the line along axis w through (pu, pv) (its coordinates on axes u, v; (u, v, w) a
    cyclic order of (0, 1, 2)) crosses face t: (its coordinate along w, +1 where the face's
    normal points along +w: a ray along +w leaves there, -1 against), or (0, 0) where it misses
    (or sees the face edge-on)."""
    a, b, d = tris[t, 0], tris[t, 1], tris[t, 2]
    area = (x[b, u] - x[a, u]) * (x[d, v] - x[a, v]) - (x[b, v] - x[a, v]) * (x[d, u] - x[a, u])
    if area == 0.0:
        return 0.0, 0  # edge-on: its neighbours count the crossing
    flip = area < 0.0  # (u, v, w) right-handed: area is twice the normal's w component
    wa = edge_side(x, b, d, pu, pv, u, v)  # opposite a
    wb = edge_side(x, d, a, pu, pv, u, v)
    wc = edge_side(x, a, b, pu, pv, u, v)
    if flip:
        wa, wb, wc = -wa, -wb, -wc
    if wa < 0.0 or wb < 0.0 or wc < 0.0:
        return 0.0, 0
    if (wa == 0.0 and not owns_edge(x, b, d, flip, u, v)) or (wb == 0.0 and not owns_edge(x, d, a, flip, u, v)) \
            or (wc == 0.0 and not owns_edge(x, a, b, flip, u, v)):
        return 0.0, 0
    h = (wa * x[a, w] + wb * x[b, w] + wc * x[d, w]) / (wa + wb + wc)
    return h, (-1 if flip else 1)


# the index of a 64-bit word's lowest set bit: de Bruijn's multiply (Leiserson, Prokop and Randall 1998)
DE_BRUIJN = np.uint64(0x03F79D71B4CB0A89)
DE_BRUIJN_BITS = np.array([0, 47, 1, 56, 48, 27, 2, 60, 57, 49, 41, 37, 28, 16, 3, 61, 54, 58, 35, 52, 50, 42, 21, 44,
                           38, 32, 29, 23, 17, 11, 4, 62, 46, 55, 26, 59, 40, 36, 15, 53, 34, 51, 20, 43, 31, 22, 10,
                           45, 25, 39, 14, 33, 19, 30, 9, 24, 13, 18, 8, 12, 7, 6, 5, 63], dtype=np.int64)
_ONE = np.uint64(1)
_SHIFT = np.uint64(58)


@helper
def lowest_bit(mask):
    """The index of the lowest set bit of mask (uint64, not 0)."""
    return DE_BRUIJN_BITS[((mask ^ (mask - _ONE)) * DE_BRUIJN) >> _SHIFT]


@helper
def winding_number(px, py, pz, body_x, tris, lo, start, ids, span, extent):
    """How many times the body's surface wraps p: the signed crossings of the ray from p (see
    module). lo, start, ids, span, extent: a `WindingGrid` of this pose (`WindingGrid.arrays()`).

    The crossings of the whole line sum to 0 on a closed surface, so those beyond p along +w
    sum to minus those before it: the count runs on the side of p with less of the column's
    extent, where fewer faces lie (a point near the skin has the body's far wall on the other
    side). A face wholly on the other side, or whose box across the ray the line misses, is
    skipped on its entry alone (a line outside a face's closed box cannot cross it). Those
    tests run branch-free over up to 64 entries into a bit mask, and only the faces left (one
    or two of a column's ~23 near the skin) are crossed: a query 176 -> 108 ns a point near the
    skin (seventy-fifth session; a branch per entry mispredicted about half of them). The tests
    compare in single precision, p rounded to it (the boxes are widened by more than that
    rounding, so a skipped face still cannot be crossed), over the boxes' rows with unsigned
    indices (numba's wrap-around of a negative index hid the contiguous loads from LLVM's
    vectoriser, which gathered them): 16 entries an instruction, a query over the particles of a
    garment 122 -> 70 ns on average (seventy-sixth session)."""
    p = (px, py, pz)
    i = math.floor((p[U] - lo[0]) / lo[4])
    k = math.floor((p[V] - lo[1]) / lo[4])
    if i < 0 or k < 0 or i >= lo[2] or k >= lo[3]:
        return 0  # beside the body
    c = int(i) * int(lo[3]) + int(k)
    pu, pv, pw = p[U], p[V], p[W]
    # in front of every face of the column the ray meets none; behind them all it meets every
    # crossing of the whole line, which sum to 0 on a closed surface (cloth in front of or
    # behind the body: most queries)
    if pw >= extent[c, 1] or pw < extent[c, 0]:
        return 0
    beyond = 2.0 * pw >= extent[c, 0] + extent[c, 1]  # nearer the far end: the crossings beyond p
    fu, fv, fw = np.float32(pu), np.float32(pv), np.float32(pw)
    w_lo, w_hi, u_lo, u_hi, v_lo, v_hi = span[0], span[1], span[2], span[3], span[4], span[5]
    w = 0
    for e0 in range(start[c], start[c + 1], 64):
        mask = np.uint64(0)
        first = np.uint64(e0)
        end = np.uint64(min(e0 + 64, start[c + 1]))
        if beyond:  # (two loops: the side is not chosen per entry)
            for e in range(first, end):
                hit = (w_hi[e] > fw) & (u_lo[e] <= fu) & (fu <= u_hi[e]) & (v_lo[e] <= fv) & (fv <= v_hi[e])
                mask |= np.uint64(hit) << (e - first)
        else:
            for e in range(first, end):
                hit = (w_lo[e] < fw) & (u_lo[e] <= fu) & (fu <= u_hi[e]) & (v_lo[e] <= fv) & (fv <= v_hi[e])
                mask |= np.uint64(hit) << (e - first)
        while mask != np.uint64(0):
            e = e0 + lowest_bit(mask)
            mask &= mask - _ONE
            h, s = ray_crossing(body_x, tris, ids[e], pu, pv, U, V, W)
            if s != 0:
                if beyond:
                    w += s if h > pw else 0
                else:  # the crossings before p, counted against
                    w -= s if h < pw else 0
    return w


@kernel
def winding_numbers(points, body_x, tris, lo, start, ids, span, extent, out):
    """out[s] = `winding_number` of points[s] (k, 3), for a batch."""
    for s in range(points.shape[0]):
        out[s] = winding_number(points[s, 0], points[s, 1], points[s, 2], body_x, tris, lo, start, ids, span,
                                extent)


def closed_faces(triangles: np.ndarray, keep: np.ndarray | None = None) -> np.ndarray:
    """(k, 3) int32: the faces of a closed, consistently oriented surface that are kept, and a
    fan over each hole their removal opens (from the hole's first vertex, wound against the
    kept faces' boundary edges, so every edge is used once each way). keep: (m,) bool; None:
    every face."""
    faces = np.asarray(triangles, dtype=np.int32)
    if keep is not None:
        faces = faces[np.asarray(keep, dtype=bool)]
    caps = [np.stack([np.full(len(loop) - 2, loop[0]), loop[2:], loop[1:-1]], axis=1)
            for loop in boundary_loops(faces) if len(loop) >= 3]
    return np.ascontiguousarray(np.concatenate([faces, *caps]).astype(np.int32))


class WindingGrid:
    """The column grid of one pose for `winding_number` (see module). Arrays are kept and
    reused; the entries grow (once) when a pose needs more."""

    def __init__(self, triangles: np.ndarray, n_vertices: int, cell: float = WINDING_CELL,
                 max_columns: int = MAX_COLUMNS):
        self.tris = np.ascontiguousarray(triangles, dtype=np.int32)
        if len(self.tris) and (self.tris.min() < 0 or self.tris.max() >= n_vertices):
            raise ValueError(f"WindingGrid: face corners must index the {n_vertices} vertices")
        self.cell = cell
        self.lo = np.zeros(5)
        self.start = np.zeros(max_columns + 1, dtype=np.int32)
        self.ids = np.zeros(4 * len(triangles), dtype=np.int32)
        self.span = np.zeros((SPAN, len(self.ids)), dtype=np.float32)
        self.vertex_column = np.zeros((n_vertices, 2), dtype=np.int32)
        self.face_columns = np.zeros((len(triangles), 4), dtype=np.int32)
        self.extent = np.zeros((max_columns, 2))

    def update(self, body_x: np.ndarray) -> None:
        """body_x: (n_vertices, 3) float64, this pose."""
        if body_x.shape != self.vertex_column.shape[:1] + (3,):
            raise ValueError(f"WindingGrid: body vertices must be ({len(self.vertex_column)}, 3), got {body_x.shape}")
        while True:
            need = build_winding_grid(body_x, self.tris, self.cell, self.lo, self.start, self.ids, self.span,
                                      self.vertex_column, self.face_columns, self.extent)
            if need <= len(self.ids):
                break
            self.ids = np.zeros(int(need * 1.25), dtype=np.int32)
            self.span = np.zeros((SPAN, len(self.ids)), dtype=np.float32)

    def arrays(self) -> tuple:
        """(lo, start, ids, span, extent): what `winding_number` takes."""
        return self.lo, self.start, self.ids, self.span, self.extent


# `WindingGrid.arrays()` of no grid: what a kernel that takes one is given where none is kept
NO_WINDING = (np.zeros(5), np.zeros(1, np.int32), np.zeros(0, np.int32), np.zeros((SPAN, 0), np.float32), np.zeros((0, 2)))


__all__ = ["NO_WINDING", "SPAN", "WindingGrid", "lowest_bit", "build_winding_grid", "closed_faces", "edge_side", "owns_edge", "ray_crossing",
           "winding_number", "winding_numbers"]
