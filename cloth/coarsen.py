"""Coarse model of a garment: a few hundred particles, quad-dominant, boundaries kept.

Why our own code and not a decimation library: the libraries that install cleanly
here (pyfqmr, fast-simplification) minimise the quadric error, which is what a render
mesh wants, but a particle cloth wants *even* edge lengths (the shortest spring sets
the explicit time step) and needs every hem, cuff and collar loop to survive; with
border preservation off pyfqmr closed a T-shirt cuff, with it on it kept all 158
border vertices of the blouse. So: shortest-edge-first collapses (uniform edges),
boundary edges collapse only along their own loop and never below `min_loop`
vertices, links and face orientation are checked on every collapse, and the
resulting triangles are paired back into quads where the pair is a good quad.

Result: `CoarseMesh(vertices, faces (m, 4) with -1 padding, fine_triangle, fine_bary)`;
the last two map each vertex of the authored garment onto the coarse triangulation
(rest pose), so authored detail (UVs, seams) can be carried onto the cloth later.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

from .geometry import morton_order, nearest_triangles
from .topology import boundary_loops, triangulate


@dataclass
class CoarseMesh:
    vertices: np.ndarray  # (n, 3) float64, metres
    faces: np.ndarray  # (m, 4) int32, quads and triangles (-1 in the last slot)
    fine_triangle: np.ndarray  # (n_fine,) int32 index into triangulate(faces)
    fine_bary: np.ndarray  # (n_fine, 3) float64

    @property
    def n_quads(self) -> int:
        return int(np.count_nonzero(self.faces[:, 3] >= 0))

    @property
    def n_triangles(self) -> int:
        return int(np.count_nonzero(self.faces[:, 3] < 0))


def _cross(u, v) -> np.ndarray:
    """u × v of two 3-vectors: what np.cross computes (the same products and differences, so the
    same bits) without its general-shape handling, which took most of a garment's coarsening
    (32,000 calls: 1.1 of 1.8 s per outfit)."""
    u0, u1, u2 = float(u[0]), float(u[1]), float(u[2])
    v0, v1, v2 = float(v[0]), float(v[1]), float(v[2])
    return np.array((u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0))


def _normal(p0, p1, p2):
    n = _cross(p1 - p0, p2 - p0)
    return n, float(np.linalg.norm(n))


def _quality(p0, p1, p2) -> float:
    """4√3·area / Σ edge² : 1 for equilateral, 0 for degenerate."""
    n = np.linalg.norm(_cross(p1 - p0, p2 - p0))
    s = np.dot(p1 - p0, p1 - p0) + np.dot(p2 - p1, p2 - p1) + np.dot(p0 - p2, p0 - p2)
    return 0.0 if s == 0 else 2.0 * np.sqrt(3.0) * n / s


class _Collapser:
    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, min_loop: int):
        self.pos = vertices.astype(np.float64).copy()
        self.tris = triangles.astype(np.int64).copy()
        self.alive_tri = np.ones(len(triangles), dtype=bool)
        self.alive = np.zeros(len(vertices), dtype=bool)
        self.alive[triangles.ravel()] = True
        self.vtris = [set() for _ in range(len(vertices))]
        for t, tri in enumerate(self.tris):
            for v in tri:
                self.vtris[v].add(t)
        self.loop = np.full(len(vertices), -1, dtype=np.int64)
        loops = boundary_loops(triangles)
        self.loop_size = [len(lp) for lp in loops]
        self.pinned = np.zeros(len(vertices), dtype=bool)
        for k, lp in enumerate(loops):
            self.pinned[lp[self.loop[lp] >= 0]] = True  # a vertex on two loops (pinch) never moves
            self.loop[lp] = k
        self.min_loop = min_loop
        self.version = np.zeros(len(vertices), dtype=np.int64)
        self.heap: list = []
        self.n_alive = int(self.alive.sum())

    def neighbours(self, v: int) -> set:
        out = set()
        for t in self.vtris[v]:
            out.update(int(x) for x in self.tris[t])
        out.discard(v)
        return out

    def push_edges(self, v: int) -> None:
        for u in self.neighbours(v):
            length = float(np.linalg.norm(self.pos[u] - self.pos[v]))
            a, b = (v, u) if v < u else (u, v)
            heapq.heappush(self.heap, (length, a, b, self.version[a], self.version[b]))

    def try_collapse(self, a: int, b: int) -> bool:
        shared = self.vtris[a] & self.vtris[b]
        if not shared or self.pinned[a] or self.pinned[b]:
            return False
        ba, bb = self.loop[a] >= 0, self.loop[b] >= 0
        if len(shared) == 1:  # boundary edge: shorten its loop, but keep the loop
            if self.loop_size[self.loop[a]] <= self.min_loop:
                return False
            target = 0.5 * (self.pos[a] + self.pos[b])
        elif len(shared) == 2:
            if ba and bb:
                return False  # an interior edge between two boundary vertices would pinch the cloth
            target = self.pos[a] if ba else self.pos[b] if bb else 0.5 * (self.pos[a] + self.pos[b])
        else:
            return False
        opposite = set()
        for t in shared:
            opposite.update(int(x) for x in self.tris[t])
        opposite -= {a, b}
        if (self.neighbours(a) & self.neighbours(b)) != opposite:
            return False  # link condition: the collapse would fold the surface
        for t in (self.vtris[a] | self.vtris[b]) - shared:
            tri = self.tris[t]
            before = [self.pos[x] for x in tri]
            after = [target if x in (a, b) else self.pos[x] for x in tri]
            n0, l0 = _normal(*before)
            n1, l1 = _normal(*after)
            if l1 < 1e-12 or np.dot(n0, n1) < 0.5 * l0 * l1 or _quality(*after) < 0.15:
                return False
        # commit: b merges into a
        for t in shared:
            self.alive_tri[t] = False
            for x in self.tris[t]:
                self.vtris[x].discard(t)
        for t in self.vtris[b]:
            self.tris[t][self.tris[t] == b] = a
            self.vtris[a].add(t)
        self.vtris[b] = set()
        if len(shared) == 1:
            self.loop_size[self.loop[a]] -= 1
        elif bb:
            self.loop[a] = self.loop[b]
        self.pos[a] = target
        self.alive[b] = False
        self.n_alive -= 1
        self.version[a] += 1
        self.version[b] += 1
        self.push_edges(a)
        return True

    def run(self, target: int) -> None:
        for v in np.flatnonzero(self.alive):
            self.push_edges(int(v))
        while self.n_alive > target and self.heap:
            _, a, b, va, vb = heapq.heappop(self.heap)
            if not (self.alive[a] and self.alive[b]) or va != self.version[a] or vb != self.version[b]:
                continue
            self.try_collapse(a, b)


def _corner_cosines(p: np.ndarray) -> np.ndarray:
    """|cos| of the four corner angles of quad p (4, 3)."""
    out = np.empty(4)
    for k in range(4):
        u = p[k - 1] - p[k]
        w = p[(k + 1) % 4] - p[k]
        out[k] = abs(np.dot(u, w)) / (np.linalg.norm(u) * np.linalg.norm(w) + 1e-30)
    return out


def pair_into_quads(vertices: np.ndarray, triangles: np.ndarray, max_cos: float = 0.7,
                    min_planarity: float = 0.8) -> np.ndarray:
    """Greedily merge triangle pairs into quads, best-shaped first. Returns (m, 4) faces, -1 padded.

    A pair is merged when every corner of the quad is within acos(max_cos) of a right angle
    and the two triangles' normals agree to min_planarity."""
    edge_owner: dict[tuple[int, int], list[int]] = {}
    for t, tri in enumerate(triangles):
        for k in range(3):
            a, b = int(tri[k]), int(tri[(k + 1) % 3])
            edge_owner.setdefault((min(a, b), max(a, b)), []).append(t)
    normals = np.cross(vertices[triangles[:, 1]] - vertices[triangles[:, 0]],
                       vertices[triangles[:, 2]] - vertices[triangles[:, 0]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True) + 1e-30
    candidates = []
    for (a, b), owners in edge_owner.items():
        if len(owners) != 2:
            continue
        t1, t2 = owners
        if np.dot(normals[t1], normals[t2]) < min_planarity:
            continue
        tri1 = list(triangles[t1])
        k = tri1.index(a)
        if tri1[(k + 1) % 3] != b:  # orient so that t1 runs a -> b
            a, b = b, a
            k = tri1.index(a)
        c = tri1[(k + 2) % 3]
        d = [x for x in triangles[t2] if x != a and x != b][0]
        quad = np.array([a, d, b, c])
        cos = _corner_cosines(vertices[quad])
        if cos.max() <= max_cos:
            candidates.append((cos.max(), t1, t2, quad))
    candidates.sort(key=lambda c: c[0])
    used = np.zeros(len(triangles), dtype=bool)
    faces = []
    for _, t1, t2, quad in candidates:
        if used[t1] or used[t2]:
            continue
        used[t1] = used[t2] = True
        faces.append(quad)
    for t in np.flatnonzero(~used):
        faces.append(np.array([*triangles[t], -1]))
    return np.asarray(faces, dtype=np.int32).reshape(-1, 4)


ORDER_CELL = 0.02  # m: the grid of `spatial_order`'s Morton keys, about half a coarse edge


def spatial_order(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same mesh with its vertices and faces numbered along a Morton curve.

    The per-particle body lookups (the collision's walks, the contact pass, the surface's
    penetration test) touch the body around each particle in turn; particles near each other
    read some of the same body vertices, faces and tree nodes, which this order finds still in
    cache. The authored order put consecutive particles 10-34 cm apart (the jeans alternate
    legs), this one 4-6 cm (the first contact pass 4-5 % faster; docs/history.md)."""
    order = morton_order(vertices, ORDER_CELL)
    vertices = vertices[order]
    new_index = np.empty(len(order), dtype=np.int64)
    new_index[order] = np.arange(len(order))
    faces = np.where(faces >= 0, new_index[np.maximum(faces, 0)], -1).astype(faces.dtype)
    real = faces >= 0
    centre = (np.where(real[..., None], vertices[np.maximum(faces, 0)], 0.0).sum(axis=1)
              / real.sum(axis=1, keepdims=True))
    return vertices, faces[morton_order(centre, ORDER_CELL)]


def coarsen(vertices: np.ndarray, faces: np.ndarray, target_particles: int = 360,
            min_loop: int = 8) -> CoarseMesh:
    """Coarse model of a garment mesh (tri/quad faces, -1 padded) with about `target_particles` particles."""
    tris, _ = triangulate(faces, vertices)
    col = _Collapser(vertices, tris, min_loop)
    col.run(target_particles)
    keep = np.flatnonzero(col.alive)
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[keep] = np.arange(len(keep))
    coarse_v = col.pos[keep]
    coarse_t = remap[col.tris[col.alive_tri]]
    quads = pair_into_quads(coarse_v, coarse_t)
    coarse_v, quads = spatial_order(coarse_v, quads)
    coarse_tris, _ = triangulate(quads, coarse_v)
    fine_tri = np.empty(len(vertices), dtype=np.int32)
    fine_bary = np.empty((len(vertices), 3))
    nearest_triangles(np.ascontiguousarray(vertices, dtype=np.float64), coarse_v, coarse_tris, fine_tri, fine_bary)
    return CoarseMesh(coarse_v, quads, fine_tri, fine_bary)
