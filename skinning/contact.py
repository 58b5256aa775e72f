"""Skin contact: where linear blend skinning makes the body cut through itself, the two skins meet
halfway instead.

Linear blend skinning keeps no volume at a bent joint: behind a bent knee the calf's skin sinks
into the thigh and the thigh's into the calf, a raised thigh sinks into the belly, the upper arm
into the chest. Between the two sheets lies a lens that is inside both parts, and a garment there
has no outside to go to. Each skin vertex inside the lens is moved back into its own part by half
the lens's thickness along its normal, so that both sheets end on one contact surface, as skin
pressed on skin does (the contact surface of implicit skinning, Vaillant et al. 2013, here from
one ray per vertex).

A vertex is in the lens when the first face its inward ray (along -normal) leaves a part through
lies within `reach` and was far from the vertex in the rest pose (more than the ray's length plus
`margin`): the far side of the vertex's own limb, which the ray leaves through otherwise, was as
far away at rest as it is now. Only the clothed skin takes part (not the head, hands or toes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from .body import Body, body_clothed_faces
from .skin import MeshNormals

_HASH_BITS = 15


@dataclass(frozen=True)
class ContactSettings:
    reach: float = 0.06  # m, the thickest lens corrected (deeper: the far side is as likely)
    margin: float = 0.01  # m, how much farther than the ray's length the face must have been at rest
    across: float = 0.5  # ... and at least acos(across) off the vertex's inward normal
    cell: float = 0.02  # m, the face grid's cell
    sample: float = 0.025  # m, spacing at rest of the vertices a ray is cast from in every pose
    smooth_passes: int = 2  # rounds that fill the vertices a lens's rays missed and fade the moves over its rim

    def __post_init__(self):
        for key in ("reach", "margin", "cell", "sample"):
            if not getattr(self, key) > 0:
                raise ValueError(f"ContactSettings.{key} must be > 0, got {getattr(self, key)!r}")
        if not isinstance(self.smooth_passes, int) or self.smooth_passes < 0:
            raise ValueError(f"ContactSettings.smooth_passes must be an integer >= 0, got {self.smooth_passes!r}")
        if not -1.0 < self.across <= 1.0:
            raise ValueError(f"ContactSettings.across must be in (-1, 1], got {self.across!r}")


@njit(cache=True, nogil=True)
def _cell_hash(i, j, k, mask):
    return ((i * 73856093) ^ (j * 19349663) ^ (k * 83492791)) & mask


@njit(cache=True, nogil=True)
def far_at_rest(rest, rest_normals, rest_centroid, v, f, t, margin, across):
    """Whether face f was elsewhere at rest than across v's own limb: farther from v than t +
    margin, and more than acos(across) off v's inward normal. The far side of v's own limb, which
    its inward ray leaves through when v is in no lens, lay straight across at rest too."""
    cx = rest_centroid[f, 0] - rest[v, 0]
    cy = rest_centroid[f, 1] - rest[v, 1]
    cz = rest_centroid[f, 2] - rest[v, 2]
    d2 = cx * cx + cy * cy + cz * cz
    if d2 <= (t + margin) ** 2:
        return False
    inward = -(cx * rest_normals[v, 0] + cy * rest_normals[v, 1] + cz * rest_normals[v, 2])
    return inward < across * np.sqrt(d2)


@njit(cache=True, nogil=True)
def build_face_grid(x, tris, inv_cell, mask, lo, hi, start, ids, count):
    """Every face into each hashed cell its bounding box overlaps (counting sort into start/ids;
    lo/hi (m, 3) receive the boxes' cell ranges). Returns the entries needed (> len(ids): grow)."""
    start[:] = 0
    for t in range(tris.shape[0]):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        for d in range(3):
            lo[t, d] = int(np.floor(min(x[a, d], x[b, d], x[c, d]) * inv_cell))
            hi[t, d] = int(np.floor(max(x[a, d], x[b, d], x[c, d]) * inv_cell))
        for i in range(lo[t, 0], hi[t, 0] + 1):
            for j in range(lo[t, 1], hi[t, 1] + 1):
                for k in range(lo[t, 2], hi[t, 2] + 1):
                    start[_cell_hash(i, j, k, mask) + 1] += 1
    for h in range(mask + 1):
        start[h + 1] += start[h]
    n = start[mask + 1]
    if n > ids.shape[0]:
        return n
    count[:] = 0
    for t in range(tris.shape[0]):
        for i in range(lo[t, 0], hi[t, 0] + 1):
            for j in range(lo[t, 1], hi[t, 1] + 1):
                for k in range(lo[t, 2], hi[t, 2] + 1):
                    h = _cell_hash(i, j, k, mask)
                    ids[start[h] + count[h]] = t
                    count[h] += 1
    return n


@njit(cache=True, nogil=True)
def first_exit(px, py, pz, dx, dy, dz, reach, v, x, tris, inv_cell, mask, start, ids, rest, rest_normals,
               rest_centroid, margin, across):
    """The ray p + t d (d unit) from skin vertex v, t in (0, reach], against the faces of `tris`
    but those around v: (t of the first face it leaves a part through (its outward normal along
    d), or reach; that face, or -1; whether it crossed a face before, either way, that was farther
    from v at rest than t + margin and not across its limb: `far_at_rest`)."""
    best = -1
    best_t = reach
    far_t = np.inf
    cell = 1.0 / inv_cell
    i = int(np.floor(px * inv_cell))
    j = int(np.floor(py * inv_cell))
    k = int(np.floor(pz * inv_cell))
    # Amanatides-Woo walk through the cells the ray crosses
    si = 1 if dx > 0 else -1
    sj = 1 if dy > 0 else -1
    sk = 1 if dz > 0 else -1
    big = 1e30
    tdx = cell / abs(dx) if dx != 0 else big
    tdy = cell / abs(dy) if dy != 0 else big
    tdz = cell / abs(dz) if dz != 0 else big
    tx = ((i + max(si, 0)) * cell - px) / dx if dx != 0 else big
    ty = ((j + max(sj, 0)) * cell - py) / dy if dy != 0 else big
    tz = ((k + max(sk, 0)) * cell - pz) / dz if dz != 0 else big
    t_enter = 0.0
    while t_enter <= best_t:  # beyond the first exit lies the far side of its own part or the outside
        h = _cell_hash(i, j, k, mask)
        for s in range(start[h], start[h + 1]):
            f = ids[s]
            a, b, c = tris[f, 0], tris[f, 1], tris[f, 2]
            if a == v or b == v or c == v:
                continue
            # Moller-Trumbore; det < 0 <=> d . (e1 x e2) > 0: the ray leaves through the face
            e1x = x[b, 0] - x[a, 0]
            e1y = x[b, 1] - x[a, 1]
            e1z = x[b, 2] - x[a, 2]
            e2x = x[c, 0] - x[a, 0]
            e2y = x[c, 1] - x[a, 1]
            e2z = x[c, 2] - x[a, 2]
            qx = dy * e2z - dz * e2y
            qy = dz * e2x - dx * e2z
            qz = dx * e2y - dy * e2x
            det = e1x * qx + e1y * qy + e1z * qz
            if abs(det) < 1e-14:
                continue
            inv = 1.0 / det
            sx = px - x[a, 0]
            sy = py - x[a, 1]
            sz = pz - x[a, 2]
            u = (sx * qx + sy * qy + sz * qz) * inv
            if u < 0.0 or u > 1.0:
                continue
            rx = sy * e1z - sz * e1y
            ry = sz * e1x - sx * e1z
            rz = sx * e1y - sy * e1x
            w = (dx * rx + dy * ry + dz * rz) * inv
            if w < 0.0 or u + w > 1.0:
                continue
            t = (e2x * rx + e2y * ry + e2z * rz) * inv
            if not 0.0 < t <= reach:
                continue
            if t < far_t and far_at_rest(rest, rest_normals, rest_centroid, v, f, t, margin, across):
                far_t = t
            if det < 0.0 and t < best_t:
                best_t = t
                best = f
        if tx <= ty and tx <= tz:
            t_enter = tx
            tx += tdx
            i += si
        elif ty <= tz:
            t_enter = ty
            ty += tdy
            j += sj
        else:
            t_enter = tz
            tz += tdz
            k += sk
    return best_t, best, far_t <= best_t


@njit(cache=True, nogil=True, parallel=True)
def lens_depths(x, normals, verts, which, tris, rest, rest_normals, rest_centroid, reach, margin, across, inv_cell, mask, start, ids, depth,
                trigger):
    """For verts[which[i]]: depth, how far the skin there has sunk into another part along -normal
    (the first face its inward ray leaves a part through, if that face was far at rest; else 0),
    and trigger, whether the ray met any face that was far at rest (a lens may be near)."""
    for i in prange(which.shape[0]):
        k = which[i]
        v = verts[k]
        t, f, far = first_exit(x[v, 0], x[v, 1], x[v, 2], -normals[v, 0], -normals[v, 1], -normals[v, 2], reach, v,
                               x, tris, inv_cell, mask, start, ids, rest, rest_normals, rest_centroid, margin, across)
        depth[k] = t if f >= 0 and far_at_rest(rest, rest_normals, rest_centroid, v, f, t, margin, across) else 0.0
        trigger[k] = far


@njit(cache=True, nogil=True)
def around_triggered(seeds, trigger, nbr_start, nbr_ids, done, out):
    """The vertices near the seeds whose rays met a face far at rest, each once, seeds left out
    (done: seeds marked True on entry, left so). Returns how many are in out."""
    n = 0
    for s in range(seeds.shape[0]):
        if not trigger[seeds[s]]:
            continue
        for q in range(nbr_start[s], nbr_start[s + 1]):
            k = nbr_ids[q]
            if not done[k]:
                done[k] = True
                out[n] = k
                n += 1
    for q in range(n):
        done[out[q]] = False
    return n


@njit(cache=True, nogil=True)
def meet_halfway(x, normals, verts, depth, ring_start, ring_ids, passes, move, spare):
    """Each vertex in a lens back into its own part by half the lens, so both sheets meet; then
    `passes` rounds in which every other vertex takes its ring's mean move: a vertex whose ray
    missed the lens no longer stands out of the moved skin around it, and the moves fade out over
    the lens's rim. Returns how many vertices moved."""
    n = verts.shape[0]
    for k in range(n):
        h = -0.5 * depth[k]
        v = verts[k]
        move[k, 0] = h * normals[v, 0]
        move[k, 1] = h * normals[v, 1]
        move[k, 2] = h * normals[v, 2]
    for _ in range(passes):
        for k in range(n):
            if depth[k] > 0.0:
                spare[k, 0] = move[k, 0]
                spare[k, 1] = move[k, 1]
                spare[k, 2] = move[k, 2]
                continue
            mx = 0.0
            my = 0.0
            mz = 0.0
            for q in range(ring_start[k], ring_start[k + 1]):
                j = ring_ids[q]
                mx += move[j, 0]
                my += move[j, 1]
                mz += move[j, 2]
            c = 1.0 / max(1, ring_start[k + 1] - ring_start[k])
            spare[k, 0] = mx * c
            spare[k, 1] = my * c
            spare[k, 2] = mz * c
        move[:] = spare
    moved = 0
    for k in range(n):
        if move[k, 0] != 0.0 or move[k, 1] != 0.0 or move[k, 2] != 0.0:
            v = verts[k]
            x[v, 0] += move[k, 0]
            x[v, 1] += move[k, 1]
            x[v, 2] += move[k, 2]
            moved += 1
    return moved


def vertex_rings(tris: np.ndarray, verts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each vertex's edge neighbours, as positions in `verts` (compressed rows)."""
    pos = np.full(int(verts.max()) + 1, -1, dtype=np.int64)
    pos[verts] = np.arange(len(verts))
    t = pos[tris]
    edges = np.unique(np.sort(np.vstack([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1), axis=0)
    both = np.vstack([edges, edges[:, ::-1]])
    both = both[np.argsort(both[:, 0], kind="stable")]
    start = np.zeros(len(verts) + 1, dtype=np.int64)
    start[1:] = np.cumsum(np.bincount(both[:, 0], minlength=len(verts)))
    return start, np.ascontiguousarray(both[:, 1])


def seed_vertices(rest: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Seeds a ray is cast from every pose: one vertex per cube of `spacing` at rest; and each
    seed's neighbours, every vertex within 2 x spacing of it at rest (compressed rows), so that
    every vertex is some seed's neighbour. Positions index `rest`."""
    _, first = np.unique(np.floor(rest / spacing).astype(np.int64), axis=0, return_index=True)
    seeds = np.sort(first)
    r2 = (2.0 * spacing) ** 2
    rows = []
    for chunk in np.array_split(seeds, max(1, len(seeds) // 256)):
        d2 = ((rest[chunk, None, :] - rest[None, :, :]) ** 2).sum(axis=2)
        rows.extend(np.flatnonzero(row <= r2) for row in d2)
    start = np.zeros(len(seeds) + 1, dtype=np.int64)
    start[1:] = np.cumsum([len(r) for r in rows])
    return seeds.astype(np.int64), start, np.concatenate(rows).astype(np.int64)


class SkinContact:
    """Brings the skin of one body to a contact surface where it cuts through itself; built once
    per body, called on each skinned pose (vertices modified in place)."""

    def __init__(self, rest_vertices: np.ndarray, triangles: np.ndarray, settings: ContactSettings | None = None):
        """rest_vertices (n, 3) m; triangles (m, 3): the closed or open skin that takes part
        (outward winding); the vertices they use are the ones moved."""
        self.settings = s = settings or ContactSettings()
        self.tris = np.ascontiguousarray(triangles, dtype=np.int64)
        self.verts = np.unique(self.tris)
        self.rest = np.ascontiguousarray(rest_vertices, dtype=np.float64)
        self.rest_centroid = self.rest[self.tris].mean(axis=1)
        self._normals = MeshNormals(self.tris, len(self.rest))
        self.rest_normals = self._normals(self.rest, np.zeros((len(self.rest), 3)))
        self.seeds, self.nbr_start, self.nbr_ids = seed_vertices(self.rest[self.verts], s.sample)
        self.ring_start, self.ring_ids = vertex_rings(self.tris, self.verts)
        self._move = np.zeros((len(self.verts), 3))
        self._spare = np.zeros((len(self.verts), 3))
        self.normals = np.zeros((len(self.rest), 3))
        self.depth = np.zeros(len(self.verts))  # m, last pose's lens depth per vertex of `verts`
        self._trigger = np.zeros(len(self.verts), dtype=np.bool_)
        self._done = np.zeros(len(self.verts), dtype=np.bool_)
        self._done[self.seeds] = True
        self._around = np.empty(len(self.verts), dtype=np.int64)
        self._mask = (1 << _HASH_BITS) - 1
        self._start = np.zeros(self._mask + 2, dtype=np.int64)
        self._count = np.zeros(self._mask + 1, dtype=np.int64)
        self._lo = np.empty((len(self.tris), 3), dtype=np.int64)
        self._hi = np.empty((len(self.tris), 3), dtype=np.int64)
        self._ids = np.zeros(8 * len(self.tris), dtype=np.int64)
        self.moved = 0  # vertices moved in the last pose

    @classmethod
    def for_body(cls, body: Body, settings: ContactSettings | None = None) -> "SkinContact":
        """The clothed skin (not the head, hands or toes) of a MakeHuman body."""
        return cls(body.vertices[: body.n_visible], body.triangles[body_clothed_faces(body)], settings)

    def __call__(self, vertices: np.ndarray) -> int:
        """Move the skinned vertices ((>= n, 3) float64, metres) in lenses onto the contact
        surface; returns how many moved."""
        s = self.settings
        x = vertices
        self._normals(x, self.normals)
        inv_cell = 1.0 / s.cell
        grid = (x, self.tris, inv_cell, self._mask, self._lo, self._hi, self._start)
        n = build_face_grid(*grid, self._ids, self._count)
        if n > len(self._ids):
            self._ids = np.zeros(2 * n, dtype=np.int64)
            build_face_grid(*grid, self._ids, self._count)
        self.depth[:] = 0.0
        rays = (x, self.normals, self.verts)
        query = (self.tris, self.rest, self.rest_normals, self.rest_centroid, s.reach, s.margin, s.across, inv_cell, self._mask, self._start,
                 self._ids, self.depth, self._trigger)
        lens_depths(*rays, self.seeds, *query)
        k = around_triggered(self.seeds, self._trigger, self.nbr_start, self.nbr_ids, self._done, self._around)
        lens_depths(*rays, self._around[:k], *query)
        self.rays = len(self.seeds) + k
        self.moved = meet_halfway(x, self.normals, self.verts, self.depth, self.ring_start, self.ring_ids,
                                  s.smooth_passes, self._move, self._spare)
        return self.moved
