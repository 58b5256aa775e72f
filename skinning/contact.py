"""Skin contact: where linear blend skinning makes the body cut through itself, the two skins meet
halfway instead.

Linear blend skinning keeps no volume at a bent joint: behind a bent knee the calf's skin sinks
into the thigh and the thigh's into the calf, a raised thigh sinks into the belly, the upper arm
into the chest. Between the two sheets lies a lens that is inside both parts, and a garment there
has no outside to go to. Each skin vertex inside the lens is moved back into its own part by half
the lens's thickness along its normal, so that both sheets end on one contact surface, as skin
pressed on skin does (the contact surface of implicit skinning, Vaillant et al. 2013, here from
one ray per vertex).

Decision (the gap): each sheet goes `ContactSettings.gap` farther back than halfway, so the
two skins end 2 x gap apart rather than on one surface. Meeting at their vertices, the two
sheets' faces still cut through each other between them by a millimetre or two, and a garment
caught there (the jeans at the hip crease in a stride, a sleeve at the armpit) had no outside
to go to: its detailed particles, tested by an independent signed distance, lay up to 3 cm
inside the body (fifty-fourth session: over the walk's first 250 frames at 60 Hz, the casual
outfit's T-shirt and jeans 791 / 4,021 vertex-frames deeper than 1 mm; with a 1.5 mm gap 513 /
2,269, with 3 mm 424 / 1,626, and fewer detailed edges too long). Skin pressed on skin over a
garment does not touch either: the cloth lies between.

A vertex is in the lens when the first face its inward ray (along -normal) leaves a part through
lies within `reach` and was elsewhere at rest than across the vertex's own limb (`far_at_rest`):
the far side of its own limb, which the ray leaves through otherwise, lay straight across at
rest too. Rays from seeds spread over the skin find the lenses (or their rims); the lenses are
then flooded ring by ring. Only the clothed skin takes part
(not the head, hands or toes).

Decision (rounds, fifty-seventh session): halfway along each sheet's own normal meets only where
the two sheets face each other squarely. At a bent elbow or knee, or where an arm lies slanted
on the thigh, the normals are not opposite and the sheets still cross after one round (the walk's
crouch, frames 176-198 at 60 Hz: 273 clothed skin vertices more than 2 mm inside another part
over the twelve frames). So each vertex of a lens measures its lens again from where the round
left it (`recast_lenses`): its ray, along its new normal, against the faces around the face it
left the other part through (not the whole grid, which would have to be rebuilt: 0.7 ms a
round), and goes back half of what is left (`ContactSettings.rounds`, 3: 273 → 138 vertices, for
about 0.1 ms a pose more).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import get_num_threads, get_thread_id, njit, prange
from numba.core.options import DefaultOptions

from .body import Body, body_clothed_faces
from .skin import MeshNormals, _face_normal, _vertex_normal, vertex_faces, vertex_normals_at

# the lens test inlined by LLVM where numba offers it (a first run compiles far faster than with
# numba's own inlining; the same machine code), by numba otherwise
_INLINE = {"forceinline": True} if hasattr(DefaultOptions, "forceinline") else {"inline": "always"}
_HASH_BITS = 15
MIN_T = 1e-9  # m
PARALLEL_RAYS = 256  # a flood ring with fewer rays is cast on one thread


@dataclass(frozen=True)
class ContactSettings:
    # m, the thickest lens corrected: a deep squat presses the calf 6-9 cm into the thigh (a ray that
    # leaves its own limb's far side is not a lens: `far_at_rest`)
    reach: float = 0.09
    margin: float = 0.01  # m, how much farther than the ray's length the face must have been at rest
    across: float = 0.3  # ... and at least acos(across) off the vertex's inward normal
    cell: float = 0.02  # m, the face grid's cell
    sample: float = 0.035  # m, spacing at rest of the seeds, the vertices a ray is cast from in every pose
    smooth_passes: int = 2  # rounds that fill the vertices a lens's rays missed and fade the moves over its rim
    # m, how much farther than halfway each sheet goes back into its own part: the two skins end
    # 2 x gap apart (see module)
    gap: float = 0.003
    # measurements of the lenses: the first from the seeds over the whole skin, each later one from
    # the last one's lens vertices against the faces near where their rays left the other part
    rounds: int = 3

    def __post_init__(self):
        for key in ("reach", "margin", "cell", "sample"):
            if not getattr(self, key) > 0:
                raise ValueError(f"ContactSettings.{key} must be > 0, got {getattr(self, key)!r}")
        if not isinstance(self.rounds, int) or self.rounds < 1:
            raise ValueError(f"ContactSettings.rounds must be an integer >= 1, got {self.rounds!r}")
        if not isinstance(self.smooth_passes, int) or self.smooth_passes < 0:
            raise ValueError(f"ContactSettings.smooth_passes must be an integer >= 0, got {self.smooth_passes!r}")
        if not 0.0 <= self.gap < self.reach:
            raise ValueError(f"ContactSettings.gap must be >= 0 and below reach, got {self.gap!r}")
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
def face_boxes(x, tris, inv_cell, mask, corners, lo, hi, counts):
    """Per face: its corners side by side (corners (m, 9), one load per face in the ray tests)
    and the cell range of its bounding box (lo/hi (m, 3) int32); and the counting sort's first
    pass of `build_face_grid`: counts (mask + 1,) int32, the faces in each hashed cell, counted
    here while the face's range is at hand (one pass over the faces less: the grid's build was a
    third of the skin contact's time, ninety-second session)."""
    counts[:] = 0
    for t in range(tris.shape[0]):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        for d in range(3):
            corners[t, d] = x[a, d]
            corners[t, 3 + d] = x[b, d]
            corners[t, 6 + d] = x[c, d]
            lo[t, d] = int(np.floor(min(x[a, d], x[b, d], x[c, d]) * inv_cell))
            hi[t, d] = int(np.floor(max(x[a, d], x[b, d], x[c, d]) * inv_cell))
        for i in range(np.int64(lo[t, 0]), np.int64(hi[t, 0]) + 1):
            for j in range(np.int64(lo[t, 1]), np.int64(hi[t, 1]) + 1):
                for k in range(np.int64(lo[t, 2]), np.int64(hi[t, 2]) + 1):
                    counts[_cell_hash(i, j, k, mask)] += 1


@njit(cache=True, nogil=True)
def build_face_grid(lo, hi, mask, start, ids, counts):
    """Every face into each hashed cell its bounding box overlaps (`face_boxes`, which counted
    them into counts): a counting sort into start/ids (int32), each cell's faces in face order;
    counts becomes scratch. Returns the entries needed (> len(ids): grow ids, and count again
    with `face_boxes`). On the calling thread: split over two threads it took as long (450
    against 370-430 µs a pose: waking the other thread twice)."""
    m = lo.shape[0]
    n = 0
    for h in range(mask + 1):  # counts become the cell's next slot
        start[h] = n
        c = counts[h]
        counts[h] = n
        n += c
    start[mask + 1] = n
    if n > ids.shape[0]:
        return n
    for t in range(m):
        for i in range(np.int64(lo[t, 0]), np.int64(hi[t, 0]) + 1):
            for j in range(np.int64(lo[t, 1]), np.int64(hi[t, 1]) + 1):
                for k in range(np.int64(lo[t, 2]), np.int64(hi[t, 2]) + 1):
                    h = _cell_hash(i, j, k, mask)
                    ids[counts[h]] = t
                    counts[h] += 1
    return n


@njit(cache=True, nogil=True, inline="always")
def _ray_face(px, py, pz, dx, dy, dz, ax, ay, az, bx, by, bz, cx, cy, cz, reach):
    """Where the ray p + t d crosses triangle abc within (MIN_T, reach] (Moller-Trumbore): (t, det),
    t inf where it does not; det < 0 <=> d . (e1 x e2) > 0: the ray leaves a part through the face
    there. The barycentric tests are scaled by |det|: no division for the faces the ray misses."""
    e1x, e1y, e1z = bx - ax, by - ay, bz - az
    e2x, e2y, e2z = cx - ax, cy - ay, cz - az
    qx = dy * e2z - dz * e2y
    qy = dz * e2x - dx * e2z
    qz = dx * e2y - dy * e2x
    det = e1x * qx + e1y * qy + e1z * qz
    sign = 1.0 if det > 0.0 else -1.0
    adet = det * sign
    if adet < 1e-14:
        return np.inf, det
    sx, sy, sz = px - ax, py - ay, pz - az
    u = (sx * qx + sy * qy + sz * qz) * sign
    if u < 0.0 or u > adet:
        return np.inf, det
    rx = sy * e1z - sz * e1y
    ry = sz * e1x - sx * e1z
    rz = sx * e1y - sy * e1x
    w = (dx * rx + dy * ry + dz * rz) * sign
    if w < 0.0 or u + w > adet:
        return np.inf, det
    t = (e2x * rx + e2y * ry + e2z * rz) * sign
    if not MIN_T * adet < t <= reach * adet:  # (a ray from a skin vertex meets the faces around it at t = 0)
        return np.inf, det
    return t / adet, det


@njit(cache=True, nogil=True)
def first_exit(px, py, pz, dx, dy, dz, reach, v, corners, stamp, ray, inv_cell, mask, start, ids, rest, rest_normals,
               rest_centroid, margin, across):
    """The ray p + t d (d unit) from skin vertex v, t in (0, reach], against the faces (corners
    (m, 9)) but those around v (t = 0 there): (t of the first face it leaves a part through (its
    outward normal along d), or reach; that face, or -1; whether it crossed a face before, either
    way, that was elsewhere at rest: `far_at_rest`). stamp (m,): the ray that last tested each
    face, set to `ray` for the faces this one tests (a face in several cells is tested once)."""
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
            if stamp[f] == ray:  # in an earlier cell of this ray too
                continue
            stamp[f] = ray
            t, det = _ray_face(px, py, pz, dx, dy, dz, corners[f, 0], corners[f, 1], corners[f, 2], corners[f, 3],
                               corners[f, 4], corners[f, 5], corners[f, 6], corners[f, 7], corners[f, 8], reach)
            if t == np.inf:
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


@njit(cache=True, nogil=True, **_INLINE)
def _lens_depth(i, x, normals, verts, which, corners, stamp, first_ray, rest, rest_normals, rest_centroid, reach,
                margin, across, inv_cell, mask, start, ids, depth, trigger, hit):
    k = which[i]
    v = verts[k]
    t, f, far = first_exit(x[v, 0], x[v, 1], x[v, 2], -normals[v, 0], -normals[v, 1], -normals[v, 2], reach, v,
                           corners, stamp, first_ray + k, inv_cell, mask, start, ids, rest, rest_normals,
                           rest_centroid, margin, across)
    depth[k] = t if f >= 0 and far_at_rest(rest, rest_normals, rest_centroid, v, f, t, margin, across) else 0.0
    hit[k] = f
    trigger[k] = far


@njit(cache=True, nogil=True, parallel=True)
def lens_depths(x, normals, verts, which, corners, stamps, first_ray, rest, rest_normals, rest_centroid, reach,
                margin, across, inv_cell, mask, start, ids, depth, trigger, hit):
    """For verts[which[i]]: depth, how far the skin there has sunk into another part along -normal
    (the first face its inward ray leaves a part through, if that face was far at rest; else 0),
    and trigger, whether the ray met any face that was far at rest (a lens may be near)."""
    for i in prange(which.shape[0]):
        _lens_depth(i, x, normals, verts, which, corners, stamps[get_thread_id()], first_ray, rest, rest_normals,
                    rest_centroid, reach, margin, across, inv_cell, mask, start, ids, depth, trigger, hit)


@njit(cache=True, nogil=True)
def lens_depths_serial(x, normals, verts, which, corners, stamps, first_ray, rest, rest_normals, rest_centroid, reach,
                       margin, across, inv_cell, mask, start, ids, depth, trigger, hit):
    """`lens_depths` on the calling thread: for the flood fill's rings (tens of rays), where
    waking the other threads costs more than the rays (on the CI machine a ring took 3.5 times
    as long in parallel)."""
    for i in range(which.shape[0]):
        _lens_depth(i, x, normals, verts, which, corners, stamps[0], first_ray, rest, rest_normals, rest_centroid,
                    reach, margin, across, inv_cell, mask, start, ids, depth, trigger, hit)


@njit(cache=True, nogil=True)
def first_front(seeds, depth, trigger, ring_start, ring_ids, seen, out):
    """Where the flood fill of the lenses starts: the ring neighbours of every seed whose ray met
    a lens or a face far at rest. seen: False on entry; marks the seeds and what is put in out.
    Returns how many are in out."""
    for q in range(seeds.shape[0]):
        seen[seeds[q]] = True
    return next_front(seeds, depth, trigger, ring_start, ring_ids, seen, out)


@njit(cache=True, nogil=True)
def next_front(front, depth, trigger, ring_start, ring_ids, seen, out):
    """The unseen ring neighbours of the front's vertices whose rays met a lens or a face far at
    rest (marked seen). Returns how many are in out."""
    n = 0
    for q in range(front.shape[0]):
        k = front[q]
        if depth[k] > 0.0 or trigger[k]:
            n = _push_ring(k, ring_start, ring_ids, seen, out, n)
    return n


@njit(cache=True, nogil=True)
def _push_ring(k, ring_start, ring_ids, seen, out, n):
    for q in range(ring_start[k], ring_start[k + 1]):
        j = ring_ids[q]
        if not seen[j]:
            seen[j] = True
            out[n] = j
            n += 1
    return n


@njit(cache=True, nogil=True)
def _exit_through(px, py, pz, dx, dy, dz, x, tris, f, reach):
    """t where the ray p + t d leaves a part through face f (its outward normal along d), within
    (0, reach]; inf where it does not."""
    a, b, c = tris[f, 0], tris[f, 1], tris[f, 2]
    t, det = _ray_face(px, py, pz, dx, dy, dz, x[a, 0], x[a, 1], x[a, 2], x[b, 0], x[b, 1], x[b, 2], x[c, 0], x[c, 1],
                       x[c, 2], reach)
    return t if det < 0.0 else np.inf


@njit(cache=True, nogil=True)
def recast_lenses(x, normals, verts, lens, hit, tris, adj_start, adj_faces, faces, stamp, first_ray, rest,
                  rest_normals, rest_centroid, reach, margin, across, depth):
    """Measure the lenses again after a round moved them (`ContactSettings.rounds`): each vertex of
    `lens` (positions in verts) casts its ray again, along its normal as the round left it, against
    the faces around the face it left the other part through (hit; its corners' faces and theirs)
    rather than every face; depth: 0 elsewhere. stamp (m,) int64: the ray that last tested each
    face (ray q is first_ray + q: ids never used before); faces (m, 3): scratch."""
    depth[:] = 0.0
    for q in range(lens.shape[0]):  # the normals there, from the faces around
        v = verts[lens[q]]
        for a in range(adj_start[v], adj_start[v + 1]):
            _face_normal(x, tris, adj_faces[a], faces)
    for q in range(lens.shape[0]):
        _vertex_normal(verts[lens[q]], adj_start, adj_faces, faces, normals)
    for q in range(lens.shape[0]):
        k = lens[q]
        v = verts[k]
        f0 = hit[k]
        px, py, pz = x[v, 0], x[v, 1], x[v, 2]
        dx, dy, dz = -normals[v, 0], -normals[v, 1], -normals[v, 2]
        best, best_f = reach, -1
        for c in range(3):  # the faces around f0's corners, and around their corners
            for a in range(adj_start[tris[f0, c]], adj_start[tris[f0, c] + 1]):
                g = adj_faces[a]
                for e in range(3):
                    u = tris[g, e]
                    for b in range(adj_start[u], adj_start[u + 1]):
                        f = adj_faces[b]
                        if stamp[f] == first_ray + q:
                            continue
                        stamp[f] = first_ray + q
                        t = _exit_through(px, py, pz, dx, dy, dz, x, tris, f, reach)
                        if t < best:
                            best, best_f = t, f
        if best_f >= 0 and far_at_rest(rest, rest_normals, rest_centroid, v, best_f, best, margin, across):
            depth[k] = best
            hit[k] = best_f


@njit(cache=True, nogil=True)
def meet_halfway(x, normals, verts, depth, ring_start, ring_ids, passes, move, spare, listed, mark, touched, gap):
    """Each vertex in a lens back into its own part by half the lens and `gap` more, so both
    sheets end on either side of one contact surface, 2 x gap apart; then
    `passes` rounds in which every other vertex takes its ring's mean move: a vertex whose ray
    missed the lens no longer stands out of the moved skin around it, and the moves fade out over
    the lens's rim. Only the lenses and the `passes` rings around them are visited (nothing
    farther can move). move, spare (n, 3): zero on entry and on return; listed (n,) int64 and
    mark (n,) bool: scratch, False on entry and on return; touched (n,) bool: set for each vertex
    moved. Returns how many vertices moved."""
    n = 0
    for k in range(verts.shape[0]):
        if depth[k] > 0.0:
            v = verts[k]
            h = -(0.5 * depth[k] + gap)
            move[k, 0] = h * normals[v, 0]
            move[k, 1] = h * normals[v, 1]
            move[k, 2] = h * normals[v, 2]
            mark[k] = True
            listed[n] = k
            n += 1
    lo = 0
    for _ in range(passes):  # the rings the rounds below can reach
        hi = n
        for q in range(lo, hi):
            n = _push_ring(listed[q], ring_start, ring_ids, mark, listed, n)
        lo = hi
    for _ in range(passes):
        for q in range(n):
            k = listed[q]
            if depth[k] > 0.0:
                spare[k, 0] = move[k, 0]
                spare[k, 1] = move[k, 1]
                spare[k, 2] = move[k, 2]
                continue
            mx = 0.0
            my = 0.0
            mz = 0.0
            for r in range(ring_start[k], ring_start[k + 1]):  # (the ring's unlisted vertices' moves are 0)
                j = ring_ids[r]
                mx += move[j, 0]
                my += move[j, 1]
                mz += move[j, 2]
            c = 1.0 / max(1, ring_start[k + 1] - ring_start[k])
            spare[k, 0] = mx * c
            spare[k, 1] = my * c
            spare[k, 2] = mz * c
        for q in range(n):
            k = listed[q]
            move[k, 0] = spare[k, 0]
            move[k, 1] = spare[k, 1]
            move[k, 2] = spare[k, 2]
    moved = 0
    for q in range(n):
        k = listed[q]
        if move[k, 0] != 0.0 or move[k, 1] != 0.0 or move[k, 2] != 0.0:
            v = verts[k]
            x[v, 0] += move[k, 0]
            x[v, 1] += move[k, 1]
            x[v, 2] += move[k, 2]
            moved += 1
            touched[k] = True
        for d in range(3):
            move[k, d] = 0.0
            spare[k, d] = 0.0
        mark[k] = False
    return moved


@njit(cache=True, nogil=True)
def lens_vertices(depth, out):
    """The positions of the vertices in a lens (depth > 0) into out; returns how many."""
    n = 0
    for k in range(depth.shape[0]):
        if depth[k] > 0.0:
            out[n] = k
            n += 1
    return n


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


def seed_vertices(rest: np.ndarray, spacing: float) -> np.ndarray:
    """The vertices a ray is cast from in every pose: one per cube of `spacing` at rest, in
    the cubes' order (rays cast one after the other read faces near each other). Positions
    index `rest`."""
    _, first = np.unique(np.floor(rest / spacing).astype(np.int64), axis=0, return_index=True)
    return first.astype(np.int64)


class SkinContact:
    """Brings the skin of one body to a contact surface where it cuts through itself; built once
    per body, called on each skinned pose (vertices modified in place)."""

    def __init__(self, rest_vertices: np.ndarray, triangles: np.ndarray, settings: ContactSettings | None = None):
        """rest_vertices (n, 3) m; triangles (m, 3): the closed or open skin that takes part
        (outward winding); the vertices they use are the ones moved."""
        self.settings = s = settings or ContactSettings()
        rest = np.asarray(rest_vertices, dtype=np.float64)
        # faces that share a cell lie side by side in memory: a ray's tests in a cell read few lines
        cells = np.floor(rest[triangles].mean(axis=1) / s.cell).astype(np.int64)
        self.tris = np.ascontiguousarray(triangles[np.lexsort(cells.T)], dtype=np.int64)
        self.verts = np.unique(self.tris)
        self.rest = np.ascontiguousarray(rest_vertices, dtype=np.float64)
        self.rest_centroid = self.rest[self.tris].mean(axis=1)
        self._adj_start, self._adj_faces = vertex_faces(self.tris, len(self.rest))
        self._faces = np.empty((len(self.tris), 3))
        self.rest_normals = MeshNormals(self.tris, len(self.rest))(self.rest, np.zeros((len(self.rest), 3)))
        self.seeds = seed_vertices(self.rest[self.verts], s.sample)
        self.ring_start, self.ring_ids = vertex_rings(self.tris, self.verts)
        self._move = np.zeros((len(self.verts), 3))
        self._spare = np.zeros((len(self.verts), 3))
        self.normals = np.zeros((len(self.rest), 3))
        self.depth = np.zeros(len(self.verts))  # m, last pose's lens depth per vertex of `verts`
        self._lens = np.zeros(len(self.verts), dtype=np.int64)
        self._hit = np.full(len(self.verts), -1, dtype=np.int64)
        self._stamp1 = np.full(len(self.tris), -1, dtype=np.int64)
        self._recast_rays = 0  # rays re-cast so far: the next one's id in _stamp1
        self._mark = np.zeros(len(self.verts), dtype=np.bool_)
        self._touched = np.zeros(len(self.verts), dtype=np.bool_)
        self._trigger = np.zeros(len(self.verts), dtype=np.bool_)
        self._seen = np.zeros(len(self.verts), dtype=np.bool_)
        self._front = np.empty(len(self.verts), dtype=np.int64)
        self._next = np.empty(len(self.verts), dtype=np.int64)
        self._mask = (1 << _HASH_BITS) - 1
        self._start = np.zeros(self._mask + 2, dtype=np.int32)
        self._count = np.zeros(self._mask + 1, dtype=np.int32)
        self._corners = np.empty((len(self.tris), 9))
        # per thread, the ray that last tested each face (first ray of the pose + the vertex's
        # position in verts): a face in several cells of a ray is tested once
        self._rays = 0
        self._stamps = np.full((get_num_threads(), len(self.tris)), -1, dtype=np.int64)
        self._lo = np.empty((len(self.tris), 3), dtype=np.int32)
        self._hi = np.empty((len(self.tris), 3), dtype=np.int32)
        self._ids = np.zeros(8 * len(self.tris), dtype=np.int32)
        self.moved = 0  # vertices moved in the last pose
        self.rays = 0  # rays cast in the last pose

    @classmethod
    def for_body(cls, body: Body, settings: ContactSettings | None = None) -> "SkinContact":
        """The clothed skin (not the head, hands or toes) of a MakeHuman body."""
        return cls(body.vertices[: body.n_visible], body.triangles[body_clothed_faces(body)], settings)

    def __call__(self, vertices: np.ndarray) -> int:
        """Move the skinned vertices ((>= n, 3) float64, metres) in lenses onto the contact
        surface; returns how many moved."""
        self._touched[:] = False
        self.rays = 0
        self._first_round(vertices)
        for _ in range(1, self.settings.rounds):
            n = lens_vertices(self.depth, self._lens)
            if n == 0:
                break
            self._recast(vertices, self._lens[:n])
        self.moved = int(np.count_nonzero(self._touched))
        return self.moved

    def _recast(self, x: np.ndarray, lens: np.ndarray) -> None:
        """A later round: the lens vertices of the round before measured again, and moved."""
        s = self.settings
        recast_lenses(x, self.normals, self.verts, lens, self._hit, self.tris, self._adj_start, self._adj_faces,
                      self._faces, self._stamp1, self._recast_rays, self.rest, self.rest_normals, self.rest_centroid,
                      s.reach, s.margin, s.across, self.depth)
        self._recast_rays += len(lens)
        self.rays += len(lens)
        meet_halfway(x, self.normals, self.verts, self.depth, self.ring_start, self.ring_ids, s.smooth_passes,
                     self._move, self._spare, self._lens, self._mark, self._touched, s.gap)

    def _first_round(self, vertices: np.ndarray) -> None:
        """Rays from the seeds over the whole skin, the lenses flooded, and moved."""
        s = self.settings
        x = vertices
        # the clothed vertices' only, on this thread: 95 µs a pose against 240 in parallel over the whole body
        vertex_normals_at(x, self.tris, self._adj_start, self._adj_faces, self._faces, self.verts, self.normals)
        inv_cell = 1.0 / s.cell
        boxes = (x, self.tris, inv_cell, self._mask, self._corners, self._lo, self._hi, self._count)
        face_boxes(*boxes)
        grid = (self._lo, self._hi, self._mask, self._start)
        n = build_face_grid(*grid, self._ids, self._count)
        if n > len(self._ids):
            self._ids = np.zeros(2 * n, dtype=np.int32)
            face_boxes(*boxes)
            build_face_grid(*grid, self._ids, self._count)
        self.depth[:] = 0.0
        self._seen[:] = False
        if self._stamps.shape[0] < get_num_threads():
            self._stamps = np.full((get_num_threads(), len(self.tris)), -1, dtype=np.int64)
        rays = (x, self.normals, self.verts)
        at_rest = (self.rest, self.rest_normals, self.rest_centroid)
        after = (s.margin, s.across, inv_cell, self._mask, self._start, self._ids, self.depth, self._trigger,
                 self._hit)
        # rays from the seeds find the lenses (or their rims), then the lenses are flooded ring by
        # ring, as far as the rays meet a lens or a face far at rest
        self._rays += len(self.verts)  # ray ids never seen before in the stamps
        lens_depths(*rays, self.seeds, self._corners, self._stamps, self._rays, *at_rest, s.reach, *after)
        ring = (self.ring_start, self.ring_ids, self._seen)
        n = first_front(self.seeds, self.depth, self._trigger, *ring, self._front)
        self.rays += len(self.seeds)
        front, spare = self._front, self._next
        while n:
            self._rays += len(self.verts)
            cast = lens_depths if n >= PARALLEL_RAYS else lens_depths_serial
            cast(*rays, front[:n], self._corners, self._stamps, self._rays, *at_rest, s.reach, *after)
            self.rays += n
            n = next_front(front[:n], self.depth, self._trigger, *ring, spare)
            front, spare = spare, front
        meet_halfway(x, self.normals, self.verts, self.depth, self.ring_start, self.ring_ids, s.smooth_passes,
                     self._move, self._spare, self._lens, self._mark, self._touched, s.gap)
