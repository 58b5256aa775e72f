"""S101 collision against the body, vertex only, and body following (numba kernels).

The body is seen as arrays: skinned vertex positions (per frame) and a `BodyMesh`
(triangles and adjacency, built once). Each particle tracks its nearest body vertex by a
local walk; it is inside when it lies behind every face incident to that vertex.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from .topology import unique_edges, vertex_neighbours, vertex_triangles


@dataclass(frozen=True)
class BodyMesh:
    """Topology of the collision body: triangles and vertex adjacency (CSR)."""

    triangles: np.ndarray  # (m, 3) int32
    n_vertices: int
    nbr_start: np.ndarray  # (n + 1,) int64
    nbr_ids: np.ndarray  # int32
    tri_start: np.ndarray  # (n + 1,) int64
    tri_ids: np.ndarray  # int32
    regions: np.ndarray  # (n,) uint8: one bit per body region (torso, each arm, each leg)

    @classmethod
    def build(cls, triangles: np.ndarray, n_vertices: int, regions: np.ndarray | None = None) -> "BodyMesh":
        """regions: a bit per vertex naming its body part. A particle's nearest-vertex walk stays in
        the parts it lay near at rest, so an arm swinging past the torso cannot carry a shirt's
        side away, nor one leg the other trouser leg. None: one region."""
        triangles = np.ascontiguousarray(triangles, dtype=np.int32)
        edges, _ = unique_edges(triangles)
        ns, ni = vertex_neighbours(n_vertices, edges)
        ts, ti = vertex_triangles(n_vertices, triangles)
        if regions is None:
            regions = np.ones(n_vertices, dtype=np.uint8)
        regions = np.ascontiguousarray(regions, dtype=np.uint8)
        if regions.shape != (n_vertices,) or np.any(regions == 0):
            raise ValueError(f"regions must be ({n_vertices},) uint8 with a bit set for every vertex")
        return cls(triangles, n_vertices, ns, ni, ts, ti, regions)


@njit(cache=True)
def face_normal(body_x, tri, out):
    """Unit normal of triangle tri (3 vertex ids); returns twice its area."""
    a, b, c = tri[0], tri[1], tri[2]
    ux = body_x[b, 0] - body_x[a, 0]
    uy = body_x[b, 1] - body_x[a, 1]
    uz = body_x[b, 2] - body_x[a, 2]
    vx = body_x[c, 0] - body_x[a, 0]
    vy = body_x[c, 1] - body_x[a, 1]
    vz = body_x[c, 2] - body_x[a, 2]
    nx = uy * vz - uz * vy
    ny = uz * vx - ux * vz
    nz = ux * vy - uy * vx
    area2 = math.sqrt(nx * nx + ny * ny + nz * nz)
    inv = 1.0 / area2 if area2 > 0.0 else 0.0
    out[0] = nx * inv
    out[1] = ny * inv
    out[2] = nz * inv
    return area2


@njit(cache=True)
def walk_nearest(p, body_x, nbr_start, nbr_ids, start, regions, mask):
    """Nearest body vertex to p by a local walk from `start` (S101: repeat while a neighbour is nearer),
    through vertices of the particle's body regions only (regions[u] & mask)."""
    best = start
    bd = (body_x[best, 0] - p[0]) ** 2 + (body_x[best, 1] - p[1]) ** 2 + (body_x[best, 2] - p[2]) ** 2
    moved = True
    while moved:
        moved = False
        for k in range(nbr_start[best], nbr_start[best + 1]):
            u = nbr_ids[k]
            if not (regions[u] & mask):
                continue
            d = (body_x[u, 0] - p[0]) ** 2 + (body_x[u, 1] - p[1]) ** 2 + (body_x[u, 2] - p[2]) ** 2
            if d < bd:
                bd = d
                best = u
                moved = True
    return best


@njit(cache=True)
def deepest_plane(p, body_x, tris, tri_start, tri_ids, vertex, n, n_out, n_vertex):
    """Signed distance of p to the incident-face plane it is least behind, and that plane's normal.

    p is inside (behind every face incident to `vertex`) exactly when the result is < 0.
    n: (3,) scratch; n_vertex receives the area-weighted vertex normal (not normalised)."""
    best = -np.inf
    n_vertex[:] = 0.0
    for k in range(tri_start[vertex], tri_start[vertex + 1]):
        t = tri_ids[k]
        area2 = face_normal(body_x, tris[t], n)
        if area2 == 0.0:
            continue
        for c in range(3):
            n_vertex[c] += area2 * n[c]
        a = tris[t, 0]
        d = (p[0] - body_x[a, 0]) * n[0] + (p[1] - body_x[a, 1]) * n[1] + (p[2] - body_x[a, 2]) * n[2]
        if d > best:
            best = d
            n_out[0] = n[0]
            n_out[1] = n[1]
            n_out[2] = n[2]
    return best


@njit(cache=True)
def collide_particles(x, v, body_x, body_vel, nbr_start, nbr_ids, tris, tri_start, tri_ids, regions, masks,
                      nearest, thickness, friction, contact, fixed):
    """S101 collision: update each particle's nearest body vertex by a walk; if the particle is
    behind every face around it (closer than `thickness`), move it onto the surface plus thickness.

    Velocity relative to the body (body_vel: the body's velocity at the particle not already
    carried by body following) loses its inward normal part, and Coulomb friction removes up to
    friction * |removed normal speed| of its tangential part."""
    n = np.empty(3)
    nv = np.empty(3)
    scratch = np.empty(3)
    for i in range(x.shape[0]):
        p = x[i]
        nearest[i] = walk_nearest(p, body_x, nbr_start, nbr_ids, nearest[i], regions, masks[i])
        d = deepest_plane(p, body_x, tris, tri_start, tri_ids, nearest[i], scratch, n, nv)
        if d >= thickness or fixed[i]:
            contact[i] = 0
            continue
        contact[i] = 1
        push = thickness - d
        for k in range(3):
            p[k] += push * n[k]
        rx = v[i, 0] - body_vel[i, 0]
        ry = v[i, 1] - body_vel[i, 1]
        rz = v[i, 2] - body_vel[i, 2]
        vn = rx * n[0] + ry * n[1] + rz * n[2]
        # In a crease the push alternates between faces; the inward part along the vertex
        # normal is removed too, or a velocity into the crease would survive every push.
        nl = math.sqrt(nv[0] * nv[0] + nv[1] * nv[1] + nv[2] * nv[2])
        if nl > 0.0:
            vnv = (rx * nv[0] + ry * nv[1] + rz * nv[2]) / nl
            if vnv < 0.0:
                rx -= vnv * nv[0] / nl
                ry -= vnv * nv[1] / nl
                rz -= vnv * nv[2] / nl
                vn = min(vn, vnv)
        vplane = rx * n[0] + ry * n[1] + rz * n[2]
        if vplane < 0.0:
            rx -= vplane * n[0]
            ry -= vplane * n[1]
            rz -= vplane * n[2]
        if vn < 0.0:
            vt = math.sqrt(rx * rx + ry * ry + rz * rz)
            if vt > 0.0:
                scale = max(0.0, 1.0 - friction * (-vn) / vt)
                rx *= scale
                ry *= scale
                rz *= scale
        v[i, 0] = body_vel[i, 0] + rx
        v[i, 1] = body_vel[i, 1] + ry
        v[i, 2] = body_vel[i, 2] + rz


@njit(cache=True)
def attach_to_body(x, body_x, tris, tri_start, tri_ids, nearest, fixed, face, bary, height, anchor):
    """Store each particle's coordinates relative to its nearest body face (S101 body following).

    Among the faces around the nearest vertex, the one whose plane projection is most inside
    the triangle; barycentric coordinates of the projection, and height along the face normal.
    anchor = the projected point on the body (its motion is the body's velocity there).
    Gripped particles (fixed[i] != 0) keep the coordinates they got at the start."""
    n = np.empty(3)
    for i in range(x.shape[0]):
        vtx = nearest[i]
        lo = tri_start[vtx]
        hi = tri_start[vtx + 1] if not fixed[i] else lo
        best = -np.inf
        for k in range(lo, hi):
            t = tri_ids[k]
            if face_normal(body_x, tris[t], n) == 0.0:
                continue
            a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
            # barycentric coordinates of the projection of x onto the plane
            e1x, e1y, e1z = body_x[b, 0] - body_x[a, 0], body_x[b, 1] - body_x[a, 1], body_x[b, 2] - body_x[a, 2]
            e2x, e2y, e2z = body_x[c, 0] - body_x[a, 0], body_x[c, 1] - body_x[a, 1], body_x[c, 2] - body_x[a, 2]
            px, py, pz = x[i, 0] - body_x[a, 0], x[i, 1] - body_x[a, 1], x[i, 2] - body_x[a, 2]
            d11 = e1x * e1x + e1y * e1y + e1z * e1z
            d12 = e1x * e2x + e1y * e2y + e1z * e2z
            d22 = e2x * e2x + e2y * e2y + e2z * e2z
            dp1 = px * e1x + py * e1y + pz * e1z
            dp2 = px * e2x + py * e2y + pz * e2z
            det = d11 * d22 - d12 * d12
            if det <= 0.0:
                continue
            wb = (d22 * dp1 - d12 * dp2) / det
            wc = (d11 * dp2 - d12 * dp1) / det
            wa = 1.0 - wb - wc
            inside = min(wa, min(wb, wc))
            if inside > best:
                best = inside
                face[i] = t
                bary[i, 0] = wa
                bary[i, 1] = wb
                bary[i, 2] = wc
                height[i] = px * n[0] + py * n[1] + pz * n[2]
        t = face[i]
        for k in range(3):
            anchor[i, k] = (bary[i, 0] * body_x[tris[t, 0], k] + bary[i, 1] * body_x[tris[t, 1], k]
                            + bary[i, 2] * body_x[tris[t, 2], k])


@njit(cache=True)
def follow_body(x, body_x, tris, fixed, face, bary, height, anchor, body_vel, carrier, inv_dt, near, far,
                followed):
    """S101 body following, before a step, after the body moved (with the Decision's distance blend).

    The fully-followed position keeps the particle's face, barycentric coordinates and height;
    a particle within `near` of the body takes it, one beyond `far` keeps its own, and between
    the two the move is blended linearly (weight w). Gripped particles (fixed[i] != 0: a
    waistband) always follow fully.

    Following is a transport: the body's motion reaches the particle through this move, not
    through its velocity, which stays the particle's own motion relative to the carried frame
    (adding the body velocity as well would move it twice, once here and once in the substeps,
    against a body that stands still at its new pose during them). The part of the body's
    velocity not transported, (1 - w) * body velocity, is the `carrier` velocity collisions and
    friction measure against."""
    n = np.empty(3)
    for i in range(x.shape[0]):
        t = face[i]
        face_normal(body_x, tris[t], n)
        h = height[i]
        w = 1.0 if (h <= near or fixed[i]) else (0.0 if h >= far else (far - h) / (far - near))
        for k in range(3):
            a = (bary[i, 0] * body_x[tris[t, 0], k] + bary[i, 1] * body_x[tris[t, 1], k]
                 + bary[i, 2] * body_x[tris[t, 2], k])
            target = a + h * n[k]
            vb = (a - anchor[i, k]) * inv_dt
            followed[i, k] = target
            x[i, k] += w * (target - x[i, k])
            body_vel[i, k] = vb
            carrier[i, k] = (1.0 - w) * vb
            anchor[i, k] = a
