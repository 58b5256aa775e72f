"""S101 collision against the body, vertex only, and body following (numba kernels).

The body is seen as arrays: skinned vertex positions (per frame) and a `BodyMesh`
(triangles and adjacency, built once). Each particle tracks its nearest body vertex by a
local walk; it is inside when it lies behind every face incident to that vertex.

The helpers take a point as three scalars (px, py, pz), not as a row view of an array: a
view in a loop with branches costs numba two atomic reference counts (see `cloth.jit`).
"""

from __future__ import annotations

import hashlib
import math
import threading
from dataclasses import dataclass

import numpy as np

from .geometry import closest_point_triangle, morton_order, nearest_vertices, plane_barycentric
from .jit import helper, kernel
from .topology import triangle_neighbours, unique_edges, vertex_cells, vertex_neighbours
from .winding import WindingGrid, closed_faces, ray_crossing, winding_number

# Body regions are bits of a 16-bit mask (BodyMesh.regions, a particle's region mask): at most 16 parts
REGION_DTYPE = np.uint16
ALL_REGIONS = 0xFFFF  # a mask that takes in every part
BODY_ORDER_CELL = 0.01  # m: the grid of the body's Morton order (BodyMesh.build), a few body edges


@dataclass(frozen=True)
class BodyMesh:
    """Topology of the collision body: triangles and vertex adjacency (CSR)."""

    triangles: np.ndarray  # (m, 3) int32
    n_vertices: int
    nbr_start: np.ndarray  # (n + 1,) int64
    nbr_ids: np.ndarray  # int32
    tri_start: np.ndarray  # (n + 1,) int64
    tri_ids: np.ndarray  # int32
    # (n,) REGION_DTYPE: one bit per body region (torso, each arm, each thigh, each lower leg), as S101
    # tells them apart: each of `build`'s limbs is one region here
    regions: np.ndarray
    tri_nbrs: np.ndarray  # (m, 3) int32: the triangle across each edge (see topology.triangle_neighbours)
    clothed_faces: np.ndarray  # (m,) bool: the faces clothes can touch (see build)
    # (k, 3) int32: the faces the winding number counts (`wound_faces`), their holes capped (`winding.closed_faces`)
    winding_faces: np.ndarray
    # (n,) int64 or None: internal vertex k is the caller's vertex vertex_order[k] (see build)
    vertex_order: np.ndarray | None = None
    # (n,) REGION_DTYPE: the body parts S103 tells apart (upper arms and forearms too); regions if no limbs
    parts: np.ndarray | None = None
    # (m,) bool: the body's faces among winding_faces (see build); None: the clothed faces
    wound_faces: np.ndarray | None = None

    def __post_init__(self):
        if self.parts is None:
            object.__setattr__(self, "parts", self.regions)
        if self.wound_faces is None:
            object.__setattr__(self, "wound_faces", self.clothed_faces)

    @classmethod
    def build(cls, triangles: np.ndarray, n_vertices: int, regions: np.ndarray | None = None,
              clothed_faces: np.ndarray | None = None, rest_vertices: np.ndarray | None = None,
              limbs: tuple[int, ...] = (), wound_faces: np.ndarray | None = None) -> "BodyMesh":
        """regions: a bit per vertex naming its body part. A particle's nearest-vertex walk stays in
        the parts it lay near at rest, so an arm swinging past the torso cannot carry a shirt's
        side away, nor one leg the other trouser leg. None: one region.
        limbs: masks of regions that the coarse cloth (S101) takes as one region, the lowest bit of
        each (`regions`), while the detailed surface (S103 and the moves out of creases) keeps
        them apart (`parts`): an upper arm and its forearm. Where a bent elbow folds the forearm
        onto the upper arm, S103's walk in another part finds a sleeve's detailed particle inside
        the forearm where the walk on the upper arm stops outside (walk clip, the blouse: vertex-
        frames deeper than 1 mm 5,803 -> 3,023). S101 keeps the arm whole: split, a sleeve particle
        met the folded forearm as another part, which pushes only from near its surface, and in
        the walk clip's crouch the forearm went through the sleeve and the sleeve came off it.
        clothed_faces: (m,) bool, the faces a garment can touch; only those go into the contact
        pass's face tree (`FaceTree`). The head, hands and toes are two thirds of a MakeHuman
        body's triangles, and boxes full of them would be searched for nothing. None: every face.
        rest_vertices: (>= n, 3), the body at rest; given, the vertices and faces are numbered
        along a Morton curve inside (`vertex_order`), so that a particle's lookups touch
        neighbouring memory (S101 1-5 % faster on the MakeHuman body, docs/history.md). Callers
        still pass body vertices in their own order (`BodyPose`, `prepare_cloth`, `ClothSim`
        convert them with `internal`); the mesh's own arrays and `BodyPose.x` are in the inner one.
        wound_faces: (m,) bool, the faces of the surface whose winding number tells inside from
        outside (`winding_faces`: these, their holes capped), a superset of the clothed faces.
        Decision: the clothed faces and the whole hands (the cloth service's `collision_body`,
        WRIST_REACH). Capped at the wrist, a point inside the hand read as outside the body, and a
        sleeve's particle inside the hand stayed there (the walk's blouse and skirt: 340 of their
        1,715 vertex-frames deeper than 1 mm lay nearest a hand's skin, fifty-ninth session); capped
        6 cm from the wrist (548 of the hands' 6,330 faces, fifty-ninth to sixty-fifth sessions), a
        point inside the fingers did (the walk's skirt under the left hand: half its vertex-frames
        deeper than 1 mm, sixty-sixth session). None: the clothed faces."""
        triangles = np.ascontiguousarray(triangles, dtype=np.int32)
        if regions is None:
            regions = np.ones(n_vertices, dtype=REGION_DTYPE)
        regions = np.asarray(regions)
        if (regions.shape != (n_vertices,) or regions.dtype.kind not in "ui" or np.any(regions <= 0)
                or np.any(regions > ALL_REGIONS)):
            raise ValueError(f"regions must be ({n_vertices},) unsigned integers of at most 16 bits, with a bit set "
                             f"for every vertex")
        regions = np.ascontiguousarray(regions, dtype=REGION_DTYPE)
        if clothed_faces is None:
            clothed_faces = np.ones(len(triangles), dtype=bool)
        clothed_faces = np.asarray(clothed_faces, dtype=bool)
        if clothed_faces.shape != (len(triangles),):
            raise ValueError(f"clothed_faces must be ({len(triangles)},) bool")
        wound_faces = clothed_faces if wound_faces is None else np.asarray(wound_faces, dtype=bool)
        if wound_faces.shape != (len(triangles),) or np.any(clothed_faces & ~wound_faces):
            raise ValueError(f"wound_faces must be ({len(triangles)},) bool, true on every clothed face")
        vertex_order = None
        if rest_vertices is not None:
            rest = np.asarray(rest_vertices, dtype=np.float64)[:n_vertices]
            if rest.shape != (n_vertices, 3):
                raise ValueError(f"rest_vertices must be (>= {n_vertices}, 3)")
            vertex_order = morton_order(rest, BODY_ORDER_CELL)
            new_index = np.empty(n_vertices, dtype=np.int64)
            new_index[vertex_order] = np.arange(n_vertices)
            triangles = new_index[triangles].astype(np.int32)
            face_order = morton_order(rest[vertex_order][triangles].mean(axis=1), BODY_ORDER_CELL)
            triangles = np.ascontiguousarray(triangles[face_order])
            regions = np.ascontiguousarray(regions[vertex_order])
            clothed_faces = clothed_faces[face_order]
            wound_faces = wound_faces[face_order]
        edges, _ = unique_edges(triangles)
        ns, ni = vertex_neighbours(n_vertices, edges)
        ts, ti = vertex_cells(n_vertices, triangles)
        limbs = np.asarray(limbs, dtype=np.int64)
        if limbs.ndim != 1 or np.any(limbs <= 0) or np.any(limbs > ALL_REGIONS):
            raise ValueError("limbs must be region masks of at most 16 bits")
        parts = regions
        if len(limbs):
            regions = regions.copy()
            for limb in limbs:
                regions[(regions & limb) != 0] = limb & -limb  # the limb's lowest bit
        return cls(triangles, n_vertices, ns, ni, ts, ti, regions, triangle_neighbours(triangles), clothed_faces,
                   closed_faces(triangles, wound_faces), vertex_order, parts, np.ascontiguousarray(wound_faces))

    def internal(self, vertices: np.ndarray) -> np.ndarray:
        """(n, 3) float64: the caller's body vertices (>= n_vertices rows, the first n the body) in
        this mesh's vertex order (a copy when reordered)."""
        x = np.asarray(vertices, dtype=np.float64)[: self.n_vertices]
        return np.ascontiguousarray(x if self.vertex_order is None else x[self.vertex_order])


@kernel
def gather_rows(src, rows, out):
    """out[k] = src[rows[k]] (3 columns): the body's vertices in the mesh's order, every pose."""
    for k in range(rows.shape[0]):
        r = rows[k]
        out[k, 0] = src[r, 0]
        out[k, 1] = src[r, 1]
        out[k, 2] = src[r, 2]


@kernel
def body_face_normals(body_x, tris, face_n):
    """face_n[t] = (unit normal, twice the area) of every body face, once per body pose.

    The body stands still during a frame's substeps and its surface stage, and every garment
    on it reads the same faces: one flat pass per pose, shared, costs less than computing
    them on demand behind a per-face check in every walk."""
    for t in range(tris.shape[0]):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
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
        face_n[t, 0] = nx * inv
        face_n[t, 1] = ny * inv
        face_n[t, 2] = nz * inv
        face_n[t, 3] = area2


@kernel
def face_tip_heights(body_x, tris, nbr_start, nbr_ids, tri_start, tri_ids, face_n, vertices, faces, vertex_tip,
                     face_tip):
    """How far each body vertex of `vertices` stands out of its ring: (x_v - mean of its
    neighbours) . n_v, n_v the area-weighted vertex normal (0 where it is lower than its ring);
    face_tip[t] for each face t of `faces`: the highest of its corners (the others are left as
    they are). A coarse body mesh (the MakeHuman thighs' edges are 2-3 cm) has vertices standing
    2-7 mm out of their rings, and more where a pose bends it, where a detailed triangle whose
    corners are all the clearance away from the body's faces still lets the vertex through
    between them (S103 tests particles). Once per pose, shared by every garment."""
    for k in range(vertices.shape[0]):
        v = vertices[k]
        nx, ny, nz = area_weighted_normal(tri_start, tri_ids, face_n, v)
        norm = math.sqrt(nx * nx + ny * ny + nz * nz)
        count = nbr_start[v + 1] - nbr_start[v]
        if norm == 0.0 or count == 0:
            vertex_tip[v] = 0.0
            continue
        mx = my = mz = 0.0
        for m in range(nbr_start[v], nbr_start[v + 1]):
            u = nbr_ids[m]
            mx += body_x[u, 0]
            my += body_x[u, 1]
            mz += body_x[u, 2]
        inv = 1.0 / count
        h = ((body_x[v, 0] - mx * inv) * nx + (body_x[v, 1] - my * inv) * ny + (body_x[v, 2] - mz * inv) * nz) / norm
        vertex_tip[v] = h if h > 0.0 else 0.0
    for k in range(faces.shape[0]):
        t = faces[k]
        a, b, c = vertex_tip[tris[t, 0]], vertex_tip[tris[t, 1]], vertex_tip[tris[t, 2]]
        m = a if a > b else b
        face_tip[t] = m if m > c else c


def face_normals(body_x: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(m, 4) float64: unit normal and twice the area of each face (allocating; see body_face_normals)."""
    out = np.zeros((len(triangles), 4))
    body_face_normals(np.ascontiguousarray(body_x, dtype=np.float64), np.ascontiguousarray(triangles, dtype=np.int32),
                      out)
    return out


@helper
def walk_nearest(px, py, pz, body_x, nbr_start, nbr_ids, start, regions, mask):
    """Nearest body vertex to p by a local walk from `start` (S101: repeat while a neighbour is nearer),
    through vertices of the particle's body regions only (regions[u] & mask). With ALL_REGIONS no
    region is read (every vertex has a bit, BodyMesh.build; S103's own-vertex walk, a sixth of its
    time), and the indices are unsigned (no wrap-around of a negative one to compute: 2 % of S103)."""
    every = mask == ALL_REGIONS
    best = start
    bd = (body_x[best, 0] - px) ** 2 + (body_x[best, 1] - py) ** 2 + (body_x[best, 2] - pz) ** 2
    moved = True
    while moved:
        moved = False
        for k in range(np.uint64(nbr_start[best]), np.uint64(nbr_start[best + 1])):
            u = np.uint64(nbr_ids[k])
            if not every and not (regions[u] & mask):
                continue
            d = (body_x[u, 0] - px) ** 2 + (body_x[u, 1] - py) ** 2 + (body_x[u, 2] - pz) ** 2
            if d < bd:
                bd = d
                best = nbr_ids[k]
                moved = True
    return best


@helper
def deepest_plane(px, py, pz, body_x, tris, tri_start, tri_ids, vertex, face_n):
    """Signed distance of p to the incident-face plane it is least behind, and that face.

    p is inside (behind every face incident to `vertex`) exactly when the distance is < 0."""
    best = -np.inf
    best_t = -1
    for k in range(np.uint64(tri_start[vertex]), np.uint64(tri_start[vertex + 1])):
        t = np.uint64(tri_ids[k])  # (unsigned: no wrap-around of a negative index)
        if face_n[t, 3] == 0.0:
            continue
        a = np.uint64(tris[t, 0])
        d = ((px - body_x[a, 0]) * face_n[t, 0] + (py - body_x[a, 1]) * face_n[t, 1]
             + (pz - body_x[a, 2]) * face_n[t, 2])
        if d > best:
            best = d
            best_t = tri_ids[k]
    return best, best_t


@helper
def behind_every_plane(px, py, pz, body_x, tris, tri_start, tri_ids, vertex, face_n):
    """Whether p lies behind the plane of every usable face incident to `vertex` (and there is
    one): `deepest_plane`'s "distance < 0", which stops at the first face p is in front of."""
    found = False
    for k in range(np.uint64(tri_start[vertex]), np.uint64(tri_start[vertex + 1])):
        t = np.uint64(tri_ids[k])  # (unsigned: no wrap-around of a negative index)
        if face_n[t, 3] == 0.0:
            continue
        a = np.uint64(tris[t, 0])
        d = ((px - body_x[a, 0]) * face_n[t, 0] + (py - body_x[a, 1]) * face_n[t, 1]
             + (pz - body_x[a, 2]) * face_n[t, 2])
        if d >= 0.0:
            return False
        found = found or d > -np.inf  # (as deepest_plane: a face at -inf or NaN is no face)
    return found


# a particle this many thicknesses in front of the faces it was last tested against, less how
# far it moved since, is not tested again in the frame (see collide_particles)
SKIP_CLEARANCE = 2.0


@kernel
def collide_particles(x, v, body_x, body_vel, nbr_start, nbr_ids, tris, tri_start, tri_ids, regions, masks,
                      nearest, part_nearest, thickness, friction, contact, fixed, face_n, tested_at, clear):
    """S101 collision: update each particle's nearest body vertex by a walk; if the particle is
    behind every face around it (closer than `thickness`), move it onto the surface plus thickness.

    A particle near several body parts (part_nearest: a seed vertex per part; the parts of its
    region mask, `part_seeds`, and those that came to it since, `track_parts`) walks in each
    part separately and is tested against the ring of each part's nearest vertex: one walk over
    them all stops at a local minimum on the part it started on (a shirt's hem in the crease
    between belly and a thigh swinging up into it: the nearest belly vertex is nearer than all
    its neighbours while the hem sinks centimetres into the thigh), and a walk in the mask's
    parts never sees an arm that hangs against a blouse's side. It is pushed out of the part it
    is least deep in, and `nearest` is the nearest vertex of its mask's parts.

    Velocity relative to the body (body_vel: the body's velocity at the particle not already
    carried by body following) loses its inward normal part, and Coulomb friction removes up to
    friction * |removed normal speed| of its tangential part.
    face_n: the body's face normals for this pose (see `body_face_normals`).
    tested_at (n, 3), clear (n,): where each particle was last tested and its distance in front
    of the faces there (-inf: test it now). The body stands still during a frame's substeps,
    and a point's distance to a plane changes by at most how far the point moved: a particle
    still farther than SKIP_CLEARANCE thicknesses from the faces it was tested against
    is not tested again (loose cloth: a skirt's hem, a blouse's back). The caller sets clear
    to -inf when the body moves (each frame). Not exact: in a crease the walk would have
    moved on to a vertex whose faces the particle is behind (on the walk clip's elegant
    outfit 275 of 3.5 million particle tests, 300 frames); the end-of-frame contact pass,
    which skips nothing, puts those out."""
    for i in range(x.shape[0]):
        px, py, pz = x[i, 0], x[i, 1], x[i, 2]  # the point as scalars (see the module docstring)
        if clear[i] > SKIP_CLEARANCE * thickness:
            moved = math.sqrt((px - tested_at[i, 0]) ** 2 + (py - tested_at[i, 1]) ** 2 + (pz - tested_at[i, 2]) ** 2)
            if clear[i] - moved > SKIP_CLEARANCE * thickness:
                contact[i] = 0
                continue
        n_parts = 0
        for k in range(part_nearest.shape[1]):
            n_parts += part_nearest[i, k] >= 0
        if n_parts < 2:
            vtx = walk_nearest(px, py, pz, body_x, nbr_start, nbr_ids, nearest[i], regions, masks[i])
            nearest[i] = vtx
            d, t = deepest_plane(px, py, pz, body_x, tris, tri_start, tri_ids, vtx, face_n)
            clear[i] = d if t >= 0 else -np.inf
        else:
            # each part's walk and ring; the push from the part the particle is least deep in
            best = np.inf
            d = -np.inf  # the push: its plane distance, face and ring vertex
            t = -1
            push_vtx = -1
            clear[i] = np.inf
            for k in range(part_nearest.shape[1]):
                if part_nearest[i, k] < 0:
                    continue
                u = walk_nearest(px, py, pz, body_x, nbr_start, nbr_ids, part_nearest[i, k], regions, 1 << k)
                part_nearest[i, k] = u
                du = (body_x[u, 0] - px) ** 2 + (body_x[u, 1] - py) ** 2 + (body_x[u, 2] - pz) ** 2
                if du < best and (masks[i] >> k) & 1:  # a part the particle follows (see track_parts)
                    best = du
                    nearest[i] = u
                dk, tk = deepest_plane(px, py, pz, body_x, tris, tri_start, tri_ids, u, face_n)
                clear[i] = min(clear[i], dk) if tk >= 0 else -np.inf
                # a part that came to the particle (not in its mask) pushes only from near its surface:
                # deeper behind its faces the skinned parts intersect (a belly folded over a thigh)
                if tk >= 0 and dk < thickness and dk > d and ((masks[i] >> k) & 1 or dk > -MAX_OTHER_PART_DEPTH):
                    d, t, push_vtx = dk, tk, u
            vtx = push_vtx if t >= 0 else nearest[i]
        tested_at[i, 0], tested_at[i, 1], tested_at[i, 2] = px, py, pz
        if d >= thickness or fixed[i] or t < 0:
            contact[i] = 0
            continue
        contact[i] = 1
        nx, ny, nz = face_n[t, 0], face_n[t, 1], face_n[t, 2]
        push = thickness - d
        x[i, 0] = px + push * nx
        x[i, 1] = py + push * ny
        x[i, 2] = pz + push * nz
        rx = v[i, 0] - body_vel[i, 0]
        ry = v[i, 1] - body_vel[i, 1]
        rz = v[i, 2] - body_vel[i, 2]
        vn = rx * nx + ry * ny + rz * nz
        # In a crease the push alternates between faces; the inward part along the vertex
        # normal (area-weighted) is removed too, or a velocity into the crease would survive every push.
        wx, wy, wz = vertex_normal(tri_start, tri_ids, face_n, vtx)
        if wx != 0.0 or wy != 0.0 or wz != 0.0:
            vnv = rx * wx + ry * wy + rz * wz
            if vnv < 0.0:
                rx -= vnv * wx
                ry -= vnv * wy
                rz -= vnv * wz
                vn = min(vn, vnv)
        vplane = rx * nx + ry * ny + rz * nz
        if vplane < 0.0:
            rx -= vplane * nx
            ry -= vplane * ny
            rz -= vplane * nz
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


PART_SLOTS = 16  # the most region bits a body has (REGION_DTYPE)


def part_slots(regions: np.ndarray) -> int:
    """part_nearest's columns for a body whose vertices have these region bits: one per bit up
    to the highest used (S101's body, with each limb merged, uses 7 of the 16; the kernels scan
    every column of every particle)."""
    present = int(np.bitwise_or.reduce(regions)) if len(regions) else 0
    return max(present.bit_length(), 1)


def part_seeds(points: np.ndarray, body_x: np.ndarray, regions: np.ndarray, masks: np.ndarray,
               out: np.ndarray | None = None, rows: np.ndarray | None = None) -> np.ndarray:
    """part_nearest for `collide_particles`: (n, part_slots(regions)) int32, column k the nearest
    vertex of region bit 1 << k for a particle whose mask has two or more parts of the body, else
    -1 (brute force: setup and recovery only). rows: fill only these rows of out."""
    rows = np.arange(len(points)) if rows is None else np.asarray(rows)
    slots = part_slots(regions)
    if out is None:
        out = np.full((len(points), slots), -1, dtype=np.int32)
    elif out.shape[1] < slots:
        raise ValueError(f"part_seeds: out has {out.shape[1]} columns, the body's regions need {slots}")
    out[rows] = -1
    present = int(np.bitwise_or.reduce(regions)) if len(regions) else 0
    masks = np.asarray(masks, dtype=np.int64)  # (any unsigned width: the bits below go up to 1 << 15)
    parts = masks[rows] & present
    several = rows[(parts & (parts - 1)) != 0]  # more than one bit
    pts = np.ascontiguousarray(points[several], dtype=np.float64)
    for k in range(out.shape[1]):
        bit = 1 << k
        has = (masks[several] & bit) != 0
        if not (present & bit) or not has.any():
            continue
        seed = np.zeros(int(has.sum()), dtype=np.int32)
        nearest_vertices(pts[has], body_x, seed, regions, np.full(len(seed), bit, dtype=REGION_DTYPE))
        out[several[has], k] = seed
    return out


@kernel
def track_parts(x, body_x, regions, masks, nearest, nearest_any, part_nearest, drop):
    """Add to a particle's collision parts (part_nearest, see `collide_particles`) the body part
    of its nearest vertex over the whole body (nearest_any, from the contact pass) when that
    part is not in its region mask, and drop such a part again once its tracked vertex is
    farther than `drop` from the particle. The substep collisions then see an arm that came
    to rest against a blouse's side, and push the cloth out of it the way it came, where the
    contact pass at the end of a frame finds it centimetres inside and puts it out of the
    arm's nearest side, the front one frame, the back the next. The following keeps to the
    mask's parts (`nearest`)."""
    d2max = drop * drop
    for i in range(x.shape[0]):
        px, py, pz = x[i, 0], x[i, 1], x[i, 2]
        for k in range(part_nearest.shape[1]):
            u = part_nearest[i, k]
            if u >= 0 and not (masks[i] >> k) & 1:
                if (body_x[u, 0] - px) ** 2 + (body_x[u, 1] - py) ** 2 + (body_x[u, 2] - pz) ** 2 > d2max:
                    part_nearest[i, k] = -1
        u = nearest_any[i]
        r = regions[u]
        if r & masks[i]:
            continue
        added = False
        for k in range(part_nearest.shape[1]):
            if (r >> k) & 1 and part_nearest[i, k] < 0:
                part_nearest[i, k] = u
                added = True
        if added:  # the mask's parts need their seeds too (a particle near one part has none yet)
            own = regions[nearest[i]] & masks[i]
            for k in range(part_nearest.shape[1]):
                if (own >> k) & 1 and part_nearest[i, k] < 0:
                    part_nearest[i, k] = nearest[i]


@kernel
def attach_to_body(x, body_x, tris, tri_start, tri_ids, nearest, fixed, face, bary, height, anchor, face_n):
    """Store each particle's coordinates relative to its nearest body face (S101 body following).

    Among the faces around the nearest vertex, the one whose plane projection is most inside
    the triangle; barycentric coordinates of the projection, and height along the face normal.
    anchor = the projected point on the body (its motion is the body's velocity there).
    Gripped particles (fixed[i] != 0) keep the coordinates they got at the start."""
    for i in range(x.shape[0]):
        vtx = nearest[i]
        lo = tri_start[vtx]
        hi = tri_start[vtx + 1] if not fixed[i] else lo
        best = -np.inf
        for k in range(lo, hi):
            t = tri_ids[k]
            if face_n[t, 3] == 0.0:
                continue
            a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
            # barycentric coordinates of the projection of x onto the plane
            wb, wc, ok = plane_barycentric(body_x, a, b, c, x[i, 0], x[i, 1], x[i, 2])
            if not ok:
                continue
            wa = 1.0 - wb - wc
            inside = min(wa, min(wb, wc))
            if inside > best:
                best = inside
                face[i] = t
                bary[i, 0] = wa
                bary[i, 1] = wb
                bary[i, 2] = wc
                px, py, pz = x[i, 0] - body_x[a, 0], x[i, 1] - body_x[a, 1], x[i, 2] - body_x[a, 2]
                height[i] = px * face_n[t, 0] + py * face_n[t, 1] + pz * face_n[t, 2]
        t = face[i]
        for k in range(3):
            anchor[i, k] = (bary[i, 0] * body_x[tris[t, 0], k] + bary[i, 1] * body_x[tris[t, 1], k]
                            + bary[i, 2] * body_x[tris[t, 2], k])


@kernel
def follow_body(x, v, body_x, tris, fixed, face, bary, height, anchor, body_vel, carrier, carried, inv_dt, near, far,
                followed, face_n, follow_w, smoothing):
    """S101 body following, before a step, after the body moved (with the Decision's distance blend).

    The fully-followed position keeps the particle's face, barycentric coordinates and height;
    a particle within `near` of the body takes it, one beyond `far` keeps its own, and between
    the two the move is blended linearly (weight w). Gripped particles (fixed[i] != 0: a
    waistband) always follow fully.

    The weight a particle is moved with eases towards that blend: w = w_last + smoothing *
    (blend - w_last) (follow_w: w_last, written; negative: none yet, the blend is taken as it
    is). Taken at once, the blend is a switch at frame rate: a particle left behind by a body
    moving away from it (a sleeve behind the swinging forearm) is farther out next frame and
    followed less, lags more, and is pulled back in by its neighbours, where it is followed
    fully again; a two-frame flutter of 5-8 cm on the elegant outfit's blouse and sleeves at
    walking pace.

    Following is a transport: the body's motion reaches the particle through this move, not
    through its velocity v, which stays the particle's own motion relative to the carried
    frame (adding the body velocity as well would move it twice, once here and once in the
    substeps, against a body that stands still at its new pose during them). Its world
    velocity is v + carried, carried = w * body velocity (written); the part of the body's
    velocity not transported, carrier = (1 - w) * body velocity, is what collisions and
    friction measure against. Decision (the world velocity kept): when w changes, v takes the
    difference, v += (w_last - w) * body velocity; otherwise a particle leaving the body's
    reach lost the body's velocity with its weight, and on the sprint of the run clip (6 m/s)
    the blouse's lower half was left behind by 10-17 cm each stride."""
    for i in range(x.shape[0]):
        t = face[i]
        h = height[i]
        w = 1.0 if (h <= near or fixed[i]) else (0.0 if h >= far else (far - h) / (far - near))
        w_last = follow_w[i]
        if w_last >= 0.0 and not fixed[i]:
            w = w_last + smoothing * (w - w_last)
        follow_w[i] = w
        change = w_last - w if w_last >= 0.0 else 0.0
        for k in range(3):
            a = (bary[i, 0] * body_x[tris[t, 0], k] + bary[i, 1] * body_x[tris[t, 1], k]
                 + bary[i, 2] * body_x[tris[t, 2], k])
            target = a + h * face_n[t, k]
            vb = (a - anchor[i, k]) * inv_dt
            followed[i, k] = target
            x[i, k] += w * (target - x[i, k])
            v[i, k] += change * vb
            body_vel[i, k] = vb
            carrier[i, k] = (1.0 - w) * vb
            carried[i, k] = w * vb
            anchor[i, k] = a


@helper
def area_weighted_normal(tri_start, tri_ids, face_n, vtx):
    """The sum of the face normals around body vertex vtx, each times twice its face's area (not unit)."""
    wx = wy = wz = 0.0
    for k in range(tri_start[vtx], tri_start[vtx + 1]):
        t = tri_ids[k]
        wx += face_n[t, 3] * face_n[t, 0]
        wy += face_n[t, 3] * face_n[t, 1]
        wz += face_n[t, 3] * face_n[t, 2]
    return wx, wy, wz


@helper
def vertex_normal(tri_start, tri_ids, face_n, vtx):
    """Area-weighted unit normal of the body at vertex vtx; (0, 0, 0) when it has no usable face."""
    wx, wy, wz = area_weighted_normal(tri_start, tri_ids, face_n, vtx)
    wl = math.sqrt(wx * wx + wy * wy + wz * wz)
    if wl == 0.0:
        return 0.0, 0.0, 0.0
    return wx / wl, wy / wl, wz / wl


@helper
def feature_normal(body_x, tris, tri_nbrs, tri_start, tri_ids, face_n, t, feature):
    """The surface normal at a closest point on face t (`closest_feature`): the face normal inside
    the face, the two faces' normals summed on an edge, the angle-weighted vertex normal at a
    corner. These pseudo-normals give the exact inside/outside sign of a closed mesh
    (Bærentzen & Aanæs 2005). (0, 0, 0) when degenerate."""
    if feature == INSIDE_FACE:
        return face_n[t, 0], face_n[t, 1], face_n[t, 2]
    nx = ny = nz = 0.0
    if feature < 3:
        nx, ny, nz = face_n[t, 0], face_n[t, 1], face_n[t, 2]
        o = tri_nbrs[t, feature]
        if o >= 0:
            nx, ny, nz = nx + face_n[o, 0], ny + face_n[o, 1], nz + face_n[o, 2]
    else:
        vtx = tris[t, feature - 3]
        for k in range(tri_start[vtx], tri_start[vtx + 1]):
            f = tri_ids[k]
            c = 0
            while tris[f, c] != vtx:
                c += 1
            u, w = tris[f, (c + 1) % 3], tris[f, (c + 2) % 3]
            ux, uy, uz = body_x[u, 0] - body_x[vtx, 0], body_x[u, 1] - body_x[vtx, 1], body_x[u, 2] - body_x[vtx, 2]
            wx, wy, wz = body_x[w, 0] - body_x[vtx, 0], body_x[w, 1] - body_x[vtx, 1], body_x[w, 2] - body_x[vtx, 2]
            lu = math.sqrt(ux * ux + uy * uy + uz * uz)
            lw = math.sqrt(wx * wx + wy * wy + wz * wz)
            if lu == 0.0 or lw == 0.0:
                continue
            angle = math.acos(min(1.0, max(-1.0, (ux * wx + uy * wy + uz * wz) / (lu * lw))))
            nx += angle * face_n[f, 0]
            ny += angle * face_n[f, 1]
            nz += angle * face_n[f, 2]
    nl = math.sqrt(nx * nx + ny * ny + nz * nz)
    if nl == 0.0:
        return 0.0, 0.0, 0.0
    return nx / nl, ny / nl, nz / nl


@helper
def signed(px, py, pz, qx, qy, qz, nx, ny, nz, d2):
    """The distance sqrt(d2) from p to its closest point q, negative when p is behind the
    surface normal (nx, ny, nz) there."""
    dist = math.sqrt(d2)
    return dist if (px - qx) * nx + (py - qy) * ny + (pz - qz) * nz >= 0.0 else -dist


@helper
def ring_signed_distance(px, py, pz, body_x, tris, tri_nbrs, tri_start, tri_ids, vtx, face_n, q):
    """Signed distance from p to the faces around body vertex vtx (negative inside).

    The exact closest point q over those faces; the sign from the surface's pseudo-normal
    there (`feature_normal`). Returns (distance, nx, ny, nz, qx, qy, qz, face): a zero normal
    when vtx has no usable face; `face` holds the closest point. q: (3,) scratch."""
    best = np.inf
    best_t = -1
    feature = INSIDE_FACE
    qx = qy = qz = 0.0
    for k in range(np.uint64(tri_start[vtx]), np.uint64(tri_start[vtx + 1])):
        t = np.uint64(tri_ids[k])  # (unsigned: no wrap-around of a negative index)
        bv, bw = closest_point_triangle(px, py, pz, body_x, tris[t, 0], tris[t, 1], tris[t, 2], q)
        d = (px - q[0]) ** 2 + (py - q[1]) ** 2 + (pz - q[2]) ** 2
        if d < best:
            best = d
            best_t = tri_ids[k]
            qx, qy, qz = q[0], q[1], q[2]
            feature = closest_feature(bv, bw)
    if best_t < 0:
        return np.inf, 0.0, 0.0, 0.0, qx, qy, qz, best_t
    nx, ny, nz = feature_normal(body_x, tris, tri_nbrs, tri_start, tri_ids, face_n, best_t, feature)
    if nx == 0.0 and ny == 0.0 and nz == 0.0:
        return np.inf, 0.0, 0.0, 0.0, qx, qy, qz, best_t
    return signed(px, py, pz, qx, qy, qz, nx, ny, nz, best), nx, ny, nz, qx, qy, qz, best_t


@helper
def in_vertex_region(px, py, pz, body_x, nbr_start, nbr_ids, vtx):
    """Whether body vertex vtx is the closest point to p on every face around it:
    (p - v).(u - v) <= 0 for every neighbour u (then each face's closest point is v)."""
    rx, ry, rz = px - body_x[vtx, 0], py - body_x[vtx, 1], pz - body_x[vtx, 2]
    for k in range(nbr_start[vtx], nbr_start[vtx + 1]):
        u = nbr_ids[k]
        if (rx * (body_x[u, 0] - body_x[vtx, 0]) + ry * (body_x[u, 1] - body_x[vtx, 1])
                + rz * (body_x[u, 2] - body_x[vtx, 2])) > 0.0:
            return False
    return True


FACE_WALK_STEPS = 48  # a face walk longer than this falls back to the vertex walk
# m: a face walk that ends on an edge or a vertex farther than this from p looks across the nearest
# faces' other edges too (Decision in `face_walk_distance`; nearer, the look cost S103 a sixth more)
LOOK_ACROSS_BEYOND = 0.004
INSIDE_FACE = -1  # closest_feature: the point lies inside the triangle


@helper
def closest_feature(v, w):
    """Where a closest point with barycentric weights (1 - v - w, v, w) lies on triangle abc:
    INSIDE_FACE, edge 0 (a, b), 1 (b, c), 2 (c, a) (the index into tri_nbrs), or vertex 3 + k
    (a, b, c)."""
    eps = 1e-9
    zu, zv, zw = 1.0 - v - w <= eps, v <= eps, w <= eps
    if zv and zw:
        return 3
    if zu and zw:
        return 4
    if zu and zv:
        return 5
    if zw:
        return 0
    if zu:
        return 1
    if zv:
        return 2
    return INSIDE_FACE


@helper
def face_walk_distance(px, py, pz, body_x, tris, tri_nbrs, tri_start, tri_ids, nbr_start, nbr_ids, regions, start,
                       face_n, q):
    """Signed distance from p to the body (negative inside) by a walk over faces from `start`.

    The exact closest point on the current face; inside the face it is a local minimum of the
    distance to the surface (in front of the face; behind it, the walk goes on to a nearer
    neighbour while there is one), on an edge the walk crosses to the face beyond while that
    gets closer. Most points end inside a face or on an edge after one or two faces, where the
    vertex walk + ring (`ring_signed_distance`) computes six. On a vertex that is the closest
    point of its whole ring (`in_vertex_region`) the distance is to the vertex; on any other
    vertex (or after a walk longer than FACE_WALK_STEPS) the ring of that vertex decides. Sign
    from the pseudo-normal of the closest feature (`feature_normal`), as in the ring.
    Decision (across the other edges, eighty-seventh session): farther than LOOK_ACROSS_BEYOND,
    a walk that ends on an edge descends from both faces of that edge, and one that ends in a
    ring from the ring's nearest face, to a nearer neighbour while there is one (`descend_faces`).
    Returns (distance, nx, ny, nz, qx, qy, qz, face): `face` is where the next walk should start.
    q: (3,) scratch."""
    # the usual case, written out first (it compiles to far less work than the general walk's
    # first round): in front of the start face, closest point inside it
    a, b, c = tris[start, 0], tris[start, 1], tris[start, 2]
    v, w = closest_point_triangle(px, py, pz, body_x, a, b, c, q)
    if closest_feature(v, w) == INSIDE_FACE:
        side = (px - q[0]) * face_n[start, 0] + (py - q[1]) * face_n[start, 1] + (pz - q[2]) * face_n[start, 2]
        if side >= 0.0:
            return side, face_n[start, 0], face_n[start, 1], face_n[start, 2], q[0], q[1], q[2], start
    t = start
    best = np.inf
    best_t = -1
    feature = INSIDE_FACE
    qx = qy = qz = 0.0
    settled = False
    for step in range(FACE_WALK_STEPS):
        if step > 0:  # the start face's closest point is in (v, w, q) already
            a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
            v, w = closest_point_triangle(px, py, pz, body_x, a, b, c, q)
        d2 = (px - q[0]) ** 2 + (py - q[1]) ** 2 + (pz - q[2]) ** 2
        settled = True  # unless the walk goes on below
        if d2 >= best:
            break  # the face beyond is no closer: the closest point is on the shared edge
        best, best_t, feature = d2, t, closest_feature(v, w)
        qx, qy, qz = q[0], q[1], q[2]
        if feature == INSIDE_FACE or feature >= 3 or tri_nbrs[t, feature] < 0:
            break  # inside the face, on a vertex, or on an open edge
        settled = False
        t = tri_nbrs[t, feature]
    if settled and feature == INSIDE_FACE and (
            (px - qx) * face_n[best_t, 0] + (py - qy) * face_n[best_t, 1] + (pz - qz) * face_n[best_t, 2]) < 0.0:
        # behind a face, a closest point inside it need not be the nearest: where the body is
        # convex a neighbouring face's plane can be nearer. Descend to the nearest neighbour
        # while one is nearer.
        best, best_t, feature, qx, qy, qz = descend_faces(px, py, pz, body_x, tris, tri_nbrs, best, best_t, feature,
                                                          qx, qy, qz, q)
    elif settled and 0 <= feature < 3 and best > LOOK_ACROSS_BEYOND ** 2:
        # Decision (across the other edges, eighty-seventh session): on an edge whose face beyond is
        # no nearer, a face across another edge of either face can be (the run's skirt over the thigh
        # read 23.1 mm from one edge of a long face, 12.8 mm from the face across the next): descend
        # from each of the two, where p is farther than LOOK_ACROSS_BEYOND (a reading that far lets
        # S106 bring the particle down by as much)
        b2, t2, f2, rx, ry, rz = descend_faces(px, py, pz, body_x, tris, tri_nbrs, best, best_t, feature, qx, qy, qz,
                                               q)
        beyond = tri_nbrs[best_t, feature]
        if t2 == best_t and beyond >= 0:
            b2, t2, f2, rx, ry, rz = descend_faces(px, py, pz, body_x, tris, tri_nbrs, best, beyond, feature, qx, qy,
                                                   qz, q)
            if t2 == beyond:
                t2 = best_t
        if t2 != best_t:
            best, best_t, feature, qx, qy, qz = b2, t2, f2, rx, ry, rz
    vertex = -1
    if settled and feature >= 3:
        vertex = tris[best_t, feature - 3]
        # the usual case on a vertex: it is the closest point of its whole ring, and the ring's
        # rule gives the sign without six more closest points
        if in_vertex_region(px, py, pz, body_x, nbr_start, nbr_ids, vertex):
            nx, ny, nz = feature_normal(body_x, tris, tri_nbrs, tri_start, tri_ids, face_n, best_t, feature)
            if nx != 0.0 or ny != 0.0 or nz != 0.0:
                return signed(px, py, pz, qx, qy, qz, nx, ny, nz, best), nx, ny, nz, qx, qy, qz, best_t
    elif not settled:
        vertex = walk_nearest(px, py, pz, body_x, nbr_start, nbr_ids, tris[best_t, 0], regions, ALL_REGIONS)
    if not settled or feature >= 3:
        d, nx, ny, nz, qx, qy, qz, t = ring_signed_distance(px, py, pz, body_x, tris, tri_nbrs, tri_start, tri_ids,
                                                             vertex, face_n, q)
        if t < 0 or abs(d) <= LOOK_ACROSS_BEYOND:
            return d, nx, ny, nz, qx, qy, qz, (t if t >= 0 else best_t)
        # (the same Decision: the faces across the ring's nearest face's edges)
        best, best_t, feature, rx, ry, rz = descend_faces(px, py, pz, body_x, tris, tri_nbrs, d * d, t, INSIDE_FACE,
                                                          qx, qy, qz, q)
        if best_t == t:
            return d, nx, ny, nz, qx, qy, qz, t
        qx, qy, qz = rx, ry, rz
        if feature >= 3:
            d, nx, ny, nz, qx, qy, qz, t = ring_signed_distance(px, py, pz, body_x, tris, tri_nbrs, tri_start,
                                                                 tri_ids, tris[best_t, feature - 3], face_n, q)
            return d, nx, ny, nz, qx, qy, qz, (t if t >= 0 else best_t)
    nx, ny, nz = feature_normal(body_x, tris, tri_nbrs, tri_start, tri_ids, face_n, best_t, feature)
    return signed(px, py, pz, qx, qy, qz, nx, ny, nz, best), nx, ny, nz, qx, qy, qz, best_t


@helper
def descend_faces(px, py, pz, body_x, tris, tri_nbrs, best, best_t, feature, qx, qy, qz, q):
    """From face best_t (p's squared distance best, at closest point q on `feature`), to the
    nearest of its neighbours while one is nearer. Returns (best, best_t, feature, q)."""
    for _ in range(FACE_WALK_STEPS):
        cur = best_t
        for e in range(3):
            o = tri_nbrs[cur, e]
            if o < 0:
                continue
            v, w = closest_point_triangle(px, py, pz, body_x, tris[o, 0], tris[o, 1], tris[o, 2], q)
            d2 = (px - q[0]) ** 2 + (py - q[1]) ** 2 + (pz - q[2]) ** 2
            if d2 < best:
                best, best_t, feature = d2, o, closest_feature(v, w)
                qx, qy, qz = q[0], q[1], q[2]
        if best_t == cur:
            break
    return best, best_t, feature, qx, qy, qz


# nearest-surface pushes per particle and frame (alternate pushes in a narrow crease between
# two body parts converge slowly)
CONTACT_ITERATIONS = 8
MAX_CONTACT_DEPTH = 0.06  # m: deeper inside, the nearest surface is as likely a limb's far side: left as it is
CREASE_COS = 0.98  # two push planes nearer parallel (or opposite) than this are not solved together
# two push planes nearer opposite than this (normals more than 127° apart) face each other
# across a slit (frames with a coarse particle deeper than 1 mm over every clip and outfit,
# tenth session: 0.98 70, 0.9 46, 0.8 21, 0.6 12; 0.3 27 on the walk and jumping jacks alone)
SLIT_COS = 0.6
MAX_CREASE_MOVE = 0.03  # m: a crease solution farther than this from the particle is not taken
NO_FACE_TREE = (np.zeros((1, 6)), np.full((1, 2), -1, np.int32), np.zeros(1, np.int32), np.zeros(1, np.int32),
                np.zeros(0, np.int32), np.full(1, -1, np.int32),
                np.full(0, -1, np.int32))  # FaceTree.arrays(), no faces
FACE_TREE_STACK = 64  # traversal scratch of `tree_nearest_face` (a tree at most this deep, less two)
MAX_OTHER_PART_DEPTH = 0.01  # m: deeper behind another part's face, the parts intersect: that push is not taken
UNION_REACH = 0.12  # m: how far along each axis `leave_body_union` looks for a way out (8 cm: deep squats stayed in)
UNION_HITS = 32  # the most faces one of its rays may cross within reach


@kernel
def resolve_contacts(x, v, body_x, body_vel, nbr_start, nbr_ids, tris, tri_start, tri_ids, tri_nbrs, regions,
                     nearest_any, thickness, fixed, face_n, q, cell, grid_start, grid_ids, grid_x, grid_regions,
                     grid_parts, fbox, fchild, ffirst, fcount, forder, fparent, fleaf, refine, stack, part, part_vertex,
                     part_d2,
                     inv_mass, placed_inv_mass, active, unsettled):
    """End-of-step contact pass against every body part (after the substeps' S101 collisions).

    The vertex test of S101 looks only at the faces around a particle's nearest vertex, in the
    body regions the particle lay near at rest; it misses a particle that a concave fold of the
    body (armpit, crotch) or another limb swung into. Here each particle finds its nearest body
    vertex over the whole body (the vertex grid, then a walk over every region), takes the
    exact closest point on the faces around it, and one inside or closer than `thickness` is
    put at that point plus thickness along the surface normal there (its pseudo-normal, see
    `ring_signed_distance`), its inward velocity relative to the body removed. In a crease
    between two body parts a push can land it behind the other part's faces: the test is
    repeated from the new position (CONTACT_ITERATIONS), and when a push would land the
    particle behind the plane of the push before it, it goes instead to the nearest point
    thickness in front of both planes (a narrow crease: alternate pushes close in by only the
    squared cosine of the planes' angle a round). Planes within CREASE_COS of parallel or
    opposite are not solved together, nor is a solution farther than MAX_CREASE_MOVE taken,
    nor a gripped particle moved off the surface by one. Planes that face each other (within
    SLIT_COS of opposite) are two body surfaces pressed together, skin on skin, with a slit
    between them narrower than twice the thickness: the particle goes midway into the slit and
    stays there, outside both (where the surfaces overlap there is no slit, and the last push
    stands). Between surfaces that near opposite the crease solution lies far out along the
    wedge, often inside a third part.
    Gripped particles (fixed) are placed too, their velocity untouched. One found deeper than
    MAX_CONTACT_DEPTH is left where it is. Where two body parts meet (an arm against the torso,
    the thighs), a face of the other part can be nearer than every vertex of it, and the ring
    of the nearest vertex says "outside" while the particle is behind that face: the ring of
    each other part's nearest vertex within one grid cell is tested too, and the most inside
    side taken, unless it is more than MAX_OTHER_PART_DEPTH inside: that deep behind a thin
    part's face the two parts intersect (linear blend skinning presses a thigh into the belly),
    and a push out of one lands in the other.
    A surface that folds (the skinned skin between the buttocks, at the groin in a stride) has
    faces of the same part nearer than every face around the nearest vertex: a result within
    `refine` of the particle is checked against every clothed body face (`FaceTree`,
    `tree_nearest_face`), and the nearest face the particle is behind (or less than thickness
    in front of) takes over. refine = 0 turns that off.
    q: (3,) scratch; cell, grid_start, grid_ids, grid_x, grid_regions, grid_parts: a
    `VertexGrid` built for this pose (`VertexGrid.arrays()`); fbox, fchild, ffirst, fcount, forder,
    fparent, fleaf: a `FaceTree` refitted to this pose (`FaceTree.arrays()`); stack: its traversal scratch
    (int32, at least `FaceTree.stack_depth`);
    part (PART_SLOTS,) REGION_DTYPE, part_vertex (PART_SLOTS,) int32, part_d2 (PART_SLOTS,): scratch for the parts.
    placed_inv_mass (n,): written, inv_mass with 0 for every particle this pass placed, so a
    strain-limiting pass after it pulls the cloth towards them and never them back inside.
    active (n,) uint8: the particles to test; the others (and their placed_inv_mass) are left
    as they are. unsettled (n,) uint8: written for the active particles, 1 where the last
    push (the CONTACT_ITERATIONS-th) was not tested again, else 0."""
    for i in range(x.shape[0]):
        if not active[i]:
            continue
        px, py, pz = x[i, 0], x[i, 1], x[i, 2]
        placed_inv_mass[i] = inv_mass[i]
        unsettled[i] = 0
        pushed = False
        pnx = pny = pnz = pd = 0.0  # the plane of the last push: pn·x >= pd
        for it in range(CONTACT_ITERATIONS):
            # walk first: its distance bounds the grid search to the few cells that could hold a nearer vertex
            vtx = walk_nearest(px, py, pz, body_x, nbr_start, nbr_ids, nearest_any[i], regions, ALL_REGIONS)
            d2 = (body_x[vtx, 0] - px) ** 2 + (body_x[vtx, 1] - py) ** 2 + (body_x[vtx, 2] - pz) ** 2
            found, d2 = grid_nearest(px, py, pz, grid_x, cell, grid_start, grid_ids, vtx, d2)
            if found != vtx:
                vtx = walk_nearest(px, py, pz, body_x, nbr_start, nbr_ids, found, regions, ALL_REGIONS)
            nearest_any[i] = vtx
            side, nx, ny, nz, qx, qy, qz, ring_face = ring_signed_distance(px, py, pz, body_x, tris, tri_nbrs,
                                                                           tri_start, tri_ids, vtx, face_n, q)
            if abs(side) < refine:
                t, b2, fv, fw = tree_nearest_face(px, py, pz, body_x, tris, face_n, fbox, fchild, ffirst, fcount,
                                                  forder, fparent, fleaf, ring_face, vtx, stack, side * side,
                                                  thickness, q)
                if t >= 0:
                    mx, my, mz = feature_normal(body_x, tris, tri_nbrs, tri_start, tri_ids, face_n, t,
                                                closest_feature(fv, fw))
                    if mx != 0.0 or my != 0.0 or mz != 0.0:
                        side = signed(px, py, pz, q[0], q[1], q[2], mx, my, mz, b2)
                        nx, ny, nz, qx, qy, qz = mx, my, mz, q[0], q[1], q[2]
            if d2 < cell * cell:
                # another body part's face can be nearer than any of its vertices, and nearer
                # than this vertex's ring (an arm against the torso, the thighs at the crotch):
                # the ring of each other part's nearest vertex too, the most inside one decides
                n_parts = grid_nearest_per_part(px, py, pz, grid_x, grid_regions, grid_parts, cell, grid_start,
                                                grid_ids, cell, regions[vtx], part, part_vertex, part_d2)
                for k in range(n_parts):
                    s2, mx, my, mz, ax, ay, az, _ = ring_signed_distance(px, py, pz, body_x, tris, tri_nbrs, tri_start,
                                                                         tri_ids, part_vertex[k], face_n, q)
                    if s2 < side and s2 > -MAX_OTHER_PART_DEPTH and (mx != 0.0 or my != 0.0 or mz != 0.0):
                        side, nx, ny, nz, qx, qy, qz = s2, mx, my, mz, ax, ay, az
            if side >= thickness * 0.999 or side < -MAX_CONTACT_DEPTH or (nx == 0.0 and ny == 0.0 and nz == 0.0):
                break
            tx = qx + thickness * nx
            ty = qy + thickness * ny
            tz = qz + thickness * nz
            d_new = nx * qx + ny * qy + nz * qz + thickness
            slit = False
            if pushed and pnx * tx + pny * ty + pnz * tz < pd:  # this push would undo the last one
                c = pnx * nx + pny * ny + pnz * nz
                if c <= -SLIT_COS:
                    # the planes face each other: a slit between two body surfaces pressed together
                    # (skin on skin) narrower than twice the thickness. The particle goes midway
                    # between them along the last push (pn·x >= pd - thickness, n·x >= d_new -
                    # thickness) and stays; where the surfaces overlap there is no outside here
                    lo = pd - thickness - (pnx * px + pny * py + pnz * pz)
                    hi = (nx * px + ny * py + nz * pz - d_new + thickness) / -c
                    if lo < hi:
                        a = 0.5 * (lo + hi)
                        tx = px + a * pnx
                        ty = py + a * pny
                        tz = pz + a * pnz
                        slit = True
                elif abs(c) < CREASE_COS and not fixed[i]:  # a gripped particle keeps to the surface
                    # a crease: the nearest point in front of both planes
                    # (on both: x = p + a pn + b n with pn·x = pd, n·x = d_new)
                    ra = pd - (pnx * px + pny * py + pnz * pz)
                    rb = d_new - (nx * px + ny * py + nz * pz)
                    det = 1.0 - c * c
                    a = (ra - c * rb) / det
                    b = (rb - c * ra) / det
                    if a * a + b * b + 2.0 * a * b * c < MAX_CREASE_MOVE * MAX_CREASE_MOVE:
                        tx = px + a * pnx + b * nx
                        ty = py + a * pny + b * ny
                        tz = pz + a * pnz + b * nz
            pushed = True
            pnx, pny, pnz, pd = nx, ny, nz, d_new
            px, py, pz = tx, ty, tz
            x[i, 0], x[i, 1], x[i, 2] = px, py, pz
            placed_inv_mass[i] = 0.0
            if it == CONTACT_ITERATIONS - 1 and not slit:
                unsettled[i] = 1
            if not fixed[i]:  # a gripped particle is placed, not moved: it has no velocity of its own
                rx = v[i, 0] - body_vel[i, 0]
                ry = v[i, 1] - body_vel[i, 1]
                rz = v[i, 2] - body_vel[i, 2]
                vn = rx * nx + ry * ny + rz * nz
                if vn < 0.0 or slit:  # in a slit, towards either side
                    v[i, 0] -= vn * nx
                    v[i, 1] -= vn * ny
                    v[i, 2] -= vn * nz
            if slit:
                break  # as far out as this place allows: a test would push it back into one side


@helper
def tree_ray_exit(px, py, pz, axis, sign, wind, reach, body_x, tris, box, child, first, count, order, stack, hit_t,
                  hit_s, hit_f):
    """How far along the ray from p along axis (0-2) towards sign (+-1) a point wrapped `wind`
    times by the body first gets out (its winding number falls to 0), the face it leaves
    through, and where the ray next crosses the body after that (inf: not within reach): the
    tree's faces the ray crosses within reach, in order along it, each -1 where the ray leaves
    through it, +1 where it enters. (inf, -1, inf): not within reach (or more crossings than
    hit_t holds).
    stack: the tree's traversal scratch; hit_t (k,) float64, hit_s, hit_f (k,) int32: scratch."""
    u = (axis + 1) % 3
    v = (axis + 2) % 3
    p = (px, py, pz)
    pu, pv, pw = p[u], p[v], p[axis]
    lo_w = pw - reach if sign < 0 else pw
    hi_w = pw + reach if sign > 0 else pw
    n = 0
    top = 0
    stack[0] = 0
    while top >= 0:
        node = stack[top]
        top -= 1
        if box[node, u] > pu or box[node, 3 + u] < pu or box[node, v] > pv or box[node, 3 + v] < pv \
                or box[node, axis] > hi_w or box[node, 3 + axis] < lo_w:
            continue
        if child[node, 0] >= 0:
            stack[top + 1] = child[node, 1]
            stack[top + 2] = child[node, 0]
            top += 2
            continue
        for e in range(first[node], first[node] + count[node]):
            h, s = ray_crossing(body_x, tris, order[e], pu, pv, u, v, axis)
            t = (h - pw) * sign
            if s == 0 or t <= 0.0 or t > reach:
                continue
            if n == hit_t.shape[0]:
                return np.inf, -1, np.inf
            k = n  # insertion: the hits in order along the ray
            while k > 0 and hit_t[k - 1] > t:
                hit_t[k] = hit_t[k - 1]
                hit_s[k] = hit_s[k - 1]
                hit_f[k] = hit_f[k - 1]
                k -= 1
            hit_t[k] = t
            hit_s[k] = s if sign > 0 else -s
            hit_f[k] = order[e]
            n += 1
    for k in range(n):
        wind -= hit_s[k]
        if wind <= 0:
            return hit_t[k], hit_f[k], (hit_t[k + 1] if k + 1 < n else np.inf)
    return np.inf, -1, np.inf


# the 20 directions between the axes (unit), where `leave_body_union` also looks for a way out
# when the axes' nearest is farther than UNION_NEAR (m)
UNION_NEAR = 0.02
DIAGONALS = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)
                      if abs(a) + abs(b) + abs(c) > 1], dtype=np.float64)
DIAGONALS /= np.linalg.norm(DIAGONALS, axis=1)[:, None]
MARCH_BISECTIONS = 10  # halvings of a winding-number march's last step (its first step / 1024 at most)
MARCH_FIRST_STEP = 0.001  # m


@helper
def outside_at(px, py, pz, dx, dy, dz, s, body_x, wfaces, wlo, wstart, wids, wspan, wextent):
    """Whether the point s along d from p is outside the body as a whole (winding number 0)."""
    return winding_number(px + s * dx, py + s * dy, pz + s * dz, body_x, wfaces, wlo, wstart, wids, wspan,
                          wextent) == 0


@helper
def march_exit(px, py, pz, dx, dy, dz, reach, body_x, wfaces, wlo, wstart, wids, wspan, wextent):
    """How far from p (inside the body) along the unit direction d the body first ends, by
    winding numbers: steps doubling from MARCH_FIRST_STEP, then bisection; inf if not within
    reach (or d is zero). Can step over a part thinner than a step: only a nearer way out is
    taken from it, and the caller checks the point it lands on."""
    if dx * dx + dy * dy + dz * dz == 0.0:
        return np.inf
    lo = 0.0
    step = MARCH_FIRST_STEP
    while lo < reach:
        hi = min(lo + step, reach)
        if outside_at(px, py, pz, dx, dy, dz, hi, body_x, wfaces, wlo, wstart, wids, wspan, wextent):
            for _ in range(MARCH_BISECTIONS):
                mid = 0.5 * (lo + hi)
                if outside_at(px, py, pz, dx, dy, dz, mid, body_x, wfaces, wlo, wstart, wids, wspan, wextent):
                    hi = mid
                else:
                    lo = mid
            return hi
        lo = hi
        step *= 2.0
    return np.inf


@kernel
def leave_body_union(x, v, body_vel, body_x, face_n, wfaces, wlo, wstart, wids, wspan, wextent, tris, box, child, first,
                     count, order, parent, leaf, stack, hit_t, hit_s, hit_f, q, thickness, active, placed_inv_mass):
    """Put out every active particle that is inside the body as a whole (its winding number,
    `winding.winding_number`), where the contact pass's ring tests cannot see it: behind a
    face of one body part that lies buried in another (a thigh pressed into the belly by the
    skinning, the shoulder cap into the chest, the calf into the thigh behind a bent knee),
    the nearest face is the buried one, and it faces the particle. The way out: straight out
    through the nearest face the particle is behind (by its plane, or less than thickness in
    front of it), to the face's closest point (also the other sheet of a fold of the skinned
    skin, which the contact pass's rings cannot see either: this replaced a face-tree query
    per contact-pass particle); else, of the six axis directions, the one on which the body
    ends nearest (within UNION_REACH), or the normal of the face it ends at, if that face's
    plane is nearer; the particle goes thickness beyond
    it, if what lies there is outside the body, and its velocity into the body (relative to the
    body's, body_vel) along that direction is removed. Where every way out is a slit narrower
    than thickness (two skins pressed together, the skinned body closed over it again within
    a few millimetres: the gluteal fold of a leg spread sideways), the particle goes to the
    middle of the nearest slit along an axis: outside, if by less than thickness.
    The axes alone often go round a limb: in the walk's deep stride the jeans' seat particles
    caught in the crease of the right hip were taken 8-12 cm out along an axis, across the
    thigh from their neighbours (1-2 cm away), and the edges to them stretched to 1.5-2.4 times
    their rest length. So where the axes' nearest way out is farther than UNION_NEAR, the 20
    directions between the axes (DIAGONALS) are ways out too, where they are nearer: found by
    winding numbers along them (`march_exit`). Only those few particles pay for it, and a near
    way out stays the axes' (taken on every move, the diagonals' shorter moves in other
    directions stretched the silk blouse's sleeves: strain p99 on the jumping jacks 11.6 →
    13.5 %, 11.8 % with the threshold).
    face_n: the pose's face normals (`body_face_normals`); wfaces, wlo ... wextent: the pose's
    `WindingGrid` (BodyMesh.winding_faces and its arrays); box ... order: the pose's `FaceTree`
    (its clothed faces), stack its scratch; hit_t, hit_s, hit_f: scratch of `tree_ray_exit`;
    q: (3,) scratch.
    placed_inv_mass: 0 written for each particle moved. Returns the number moved."""
    moved = 0
    for i in range(x.shape[0]):
        if not active[i]:
            continue
        px, py, pz = x[i, 0], x[i, 1], x[i, 2]
        wind = winding_number(px, py, pz, body_x, wfaces, wlo, wstart, wids, wspan, wextent)
        if wind <= 0:
            continue
        best = np.inf
        bx = by = bz = 0.0  # the unit direction out
        slit = np.inf  # the nearest slit's middle along an axis (no way out thickness wide)
        sx = sy = sz = 0.0
        # the nearest face the particle is behind: straight out through it, if outside beyond it
        f, d2, _, _ = tree_nearest_face(px, py, pz, body_x, tris, face_n, box, child, first, count, order, parent,
                                        leaf, -1, -1, stack, UNION_REACH * UNION_REACH, thickness, q)
        if f >= 0:
            d = math.sqrt(d2)
            if d > 1e-9:
                nx, ny, nz = (q[0] - px) / d, (q[1] - py) / d, (q[2] - pz) / d
            else:
                nx, ny, nz = face_n[f, 0], face_n[f, 1], face_n[f, 2]
            if outside_at(px, py, pz, nx, ny, nz, d + thickness, body_x, wfaces, wlo, wstart, wids, wspan, wextent):
                best, bx, by, bz = d, nx, ny, nz
        for axis in range(3):
            for sign in (-1.0, 1.0):
                t, f, t_next = tree_ray_exit(px, py, pz, axis, sign, wind, UNION_REACH, body_x, tris, box, child,
                                             first, count, order, stack, hit_t, hit_s, hit_f)
                if t == np.inf:
                    continue
                # the exit face's plane is the nearer way out where the ray meets it at a slant
                nx, ny, nz = face_n[f, 0], face_n[f, 1], face_n[f, 2]
                a = tris[f, 0]
                plane = (body_x[a, 0] - px) * nx + (body_x[a, 1] - py) * ny + (body_x[a, 2] - pz) * nz
                if 0.0 < plane < min(t, best) and outside_at(px, py, pz, nx, ny, nz, plane + thickness, body_x,
                                                               wfaces, wlo, wstart, wids, wspan, wextent):
                    best, bx, by, bz = plane, nx, ny, nz
                    continue  # nearer than the ray's own way out
                ax = sign if axis == 0 else 0.0
                ay = sign if axis == 1 else 0.0
                az = sign if axis == 2 else 0.0
                if t < best and outside_at(px, py, pz, ax, ay, az, t + thickness, body_x, wfaces, wlo, wstart, wids,
                                           wspan, wextent):
                    best, bx, by, bz = t, ax, ay, az
                elif best == np.inf and t_next < t + thickness:
                    mid = 0.5 * (t + t_next)
                    if mid < slit and outside_at(px, py, pz, ax, ay, az, mid, body_x, wfaces, wlo, wstart, wids,
                                                 wspan, wextent):
                        slit, sx, sy, sz = mid, ax, ay, az
        for k in range(DIAGONALS.shape[0] if best > UNION_NEAR else 0):
            nx, ny, nz = DIAGONALS[k, 0], DIAGONALS[k, 1], DIAGONALS[k, 2]
            t = march_exit(px, py, pz, nx, ny, nz, min(best, UNION_REACH), body_x, wfaces, wlo, wstart, wids, wspan,
                           wextent)
            if t < best and outside_at(px, py, pz, nx, ny, nz, t + thickness, body_x, wfaces, wlo, wstart, wids,
                                       wspan, wextent):
                best, bx, by, bz = t, nx, ny, nz
        if best < np.inf:
            step = best + thickness
        elif slit < np.inf:
            step, bx, by, bz = slit, sx, sy, sz
        else:
            continue
        x[i, 0] = px + step * bx
        x[i, 1] = py + step * by
        x[i, 2] = pz + step * bz
        vn = (v[i, 0] - body_vel[i, 0]) * bx + (v[i, 1] - body_vel[i, 1]) * by + (v[i, 2] - body_vel[i, 2]) * bz
        if vn < 0.0:
            v[i, 0] -= vn * bx
            v[i, 1] -= vn * by
            v[i, 2] -= vn * bz
        placed_inv_mass[i] = 0.0
        moved += 1
    return moved


class BodyPose:
    """What every garment reads from one body pose, computed once per pose and shared: the
    vertices (float64, contiguous), the face normals, the vertex grid, the face tree (of the
    faces clothes can touch, `BodyMesh.clothed_faces`), the winding grid (the body as a
    whole: `leave_body_union`) and how far each face's corners stand out (`face_tip_heights`,
    for S103).

    `update()` computes all of it but the tips. A caller that steps garments on several threads
    can split it:
    `update_surface()` (vertices, face normals: what a step needs from its start), then
    `update_queries()` (grids, face tree: needed only by the contact passes at the end of S101)
    while the garments start; `ClothSim` calls `wait_queries()` before its contact passes. The
    tips are computed by the first garment that asks for them (`face_tips()`, before its S103),
    or by a thread that would otherwise wait for the queries (`wait_queries()`): usually a
    helper's, which started before the queries' update, not the thread that updated them and
    stepped its own garment after them."""

    def __init__(self, body: BodyMesh, face_tree: bool = True, winding: bool = False, tips: bool = False):
        """face_tree: keep the face tree (the contact pass's nearest-face query and the union
        pass read it; False when no garment on the body needs it, `SimSettings.needs_face_tree`).
        winding: keep the winding grid (`leave_body_union`, when a garment on the body has
        `SimSettings.union_passes`). tips: keep the faces' tip heights (`face_tip`, for S103 when
        a detailed surface has `SurfaceSettings.tip_share`; else they stay 0)."""
        self.body = body
        self.x = np.zeros((body.n_vertices, 3))  # m
        self.face_n = np.zeros((len(body.triangles), 4))  # see body_face_normals
        self.grid = VertexGrid(body.n_vertices)
        self.vertex_tip = np.zeros(body.n_vertices)  # m: see face_tip_heights
        self.face_tip = np.zeros(len(body.triangles))  # m: S103's extra clearance per face is a share of it
        # the faces clothes can touch and their corners (the head and hands, finely meshed, keep 0)
        self._tip_faces = np.flatnonzero(body.clothed_faces if tips else np.zeros(0, bool)).astype(np.int32)
        self._tip_vertices = np.unique(body.triangles[self._tip_faces]).astype(np.int32)
        self.faces = FaceTree(body.triangles, np.flatnonzero(body.clothed_faces), body.regions) if face_tree else None
        self.winding = WindingGrid(body.winding_faces, body.n_vertices) if winding else None
        self._queries = threading.Event()  # set: grid and tree are this pose's
        self._queries_failed = False
        self._tips_lock = threading.Lock()
        self._poses = 0  # poses set by update_surface, and the one the tips are of
        self._tips_of = -1
        self._tips_wanted = False  # this pose's tips will be asked for (update_surface)

    def update(self, body_vertices: np.ndarray) -> None:
        """body_vertices: (>= n_vertices, 3); the first n_vertices are the collision body."""
        self.update_surface(body_vertices)
        self.update_queries()

    def update_surface(self, body_vertices: np.ndarray, tips: bool = True) -> None:
        """The vertices and face normals of this pose; the grid and tree are stale until
        `update_queries()`. tips: whether this pose's tips will be asked for (a detailed surface
        is stepped on it): a thread that waits for the queries then computes them meanwhile."""
        self._queries.clear()
        self._tips_wanted = tips
        self._poses += 1
        if self.body.vertex_order is None:
            self.x[:] = body_vertices[: self.body.n_vertices]
        else:
            body_vertices = np.asarray(body_vertices)
            if body_vertices.ndim != 2 or body_vertices.shape[0] < self.body.n_vertices or body_vertices.shape[1] != 3:
                raise ValueError(f"body vertices must be (>= {self.body.n_vertices}, 3), got {body_vertices.shape}")
            gather_rows(body_vertices, self.body.vertex_order, self.x)
        body_face_normals(self.x, self.body.triangles, self.face_n)

    def update_queries(self) -> None:
        """The vertex grid, the winding grid and the face tree's boxes for the pose
        `update_surface()` set."""
        self._queries_failed = True
        try:
            self.grid.update(self.x, self.body.regions, self.body.parts)
            if self.winding is not None:
                self.winding.update(self.x)
            if self.faces is not None:
                self.faces.update(self.x)
            self._queries_failed = False
        finally:  # a waiting garment is released either way, and told if this failed
            self._queries.set()

    def face_tips(self) -> np.ndarray:
        """`face_tip` for this pose (`face_tip_heights`; zeros unless built with tips=True),
        computed by the first caller, the others waiting for it (thread-safe)."""
        with self._tips_lock:
            if self._tips_of != self._poses and len(self._tip_faces):
                b = self.body
                face_tip_heights(self.x, b.triangles, b.nbr_start, b.nbr_ids, b.tri_start, b.tri_ids, self.face_n,
                                 self._tip_vertices, self._tip_faces, self.vertex_tip, self.face_tip)
            self._tips_of = self._poses
        return self.face_tip

    def wait_queries(self) -> None:
        """Block until the grid and the face tree are this pose's (`update_queries()` on another
        thread). A thread that would wait computes the tips first (`face_tips()`; S103 needs them
        later, and whichever thread asks first computes them): a helper's garment reaches its
        contact passes before the caller has updated the queries, and otherwise spent that time
        idle and then computed the tips at the start of its S103."""
        if self._tips_wanted and not self._queries.is_set():
            self.face_tips()
        self._queries.wait()
        if self._queries_failed:
            raise RuntimeError("BodyPose: the vertex grid or face tree update failed for this pose")

    def face_tree_arrays(self) -> tuple:
        """What `resolve_contacts` takes of the face tree (`FaceTree.arrays()`), or an empty
        tree of the same types when there is none (the query is then off)."""
        return self.faces.arrays() if self.faces is not None else NO_FACE_TREE


class VertexGrid:
    """The body's vertices bucketed in a hashed uniform grid, rebuilt once per body pose.

    It answers "which body vertex is nearest to this point" over the whole body, where a
    walk over the mesh can only reach vertices connected to where it starts (a thigh cannot
    walk to the other thigh). One grid serves every garment on the same body pose.
    Bucket c holds ids[start[c]:start[c + 1]]; x and regions are the vertices' positions and
    region bits in that same order (a bucket's scan reads contiguous memory), and parts[c] is
    the OR of its vertices' region bits (a block of buckets with one body part in it needs no
    scan for the others). detail_regions and detail_parts are the same for the body parts the
    detailed surface tells apart (`BodyMesh.parts`)."""

    def __init__(self, n_vertices: int, cell: float = 0.03, table_bits: int = 15):
        self.cell = cell
        self.start = np.zeros((1 << table_bits) + 1, dtype=np.int64)
        self.ids = np.zeros(n_vertices, dtype=np.int32)
        self.x = np.zeros((n_vertices, 3))
        self.regions = np.zeros(n_vertices, dtype=REGION_DTYPE)
        self.parts = np.zeros(1 << table_bits, dtype=REGION_DTYPE)
        self.detail_regions = np.zeros(n_vertices, dtype=REGION_DTYPE)
        self.detail_parts = np.zeros(1 << table_bits, dtype=REGION_DTYPE)
        self.counts = np.zeros(1 << table_bits, dtype=np.int64)
        self.slot = np.zeros(n_vertices, dtype=np.int64)  # each vertex's bucket (build scratch)

    def update(self, body_x: np.ndarray, regions: np.ndarray, parts: np.ndarray | None = None) -> None:
        """regions: (n,) REGION_DTYPE region bits of the vertices (`BodyMesh.regions`); parts: the
        detailed surface's (`BodyMesh.parts`; None: regions)."""
        build_vertex_grid(body_x, regions, regions if parts is None else parts, self.cell, self.start, self.ids,
                          self.counts, self.x, self.regions, self.parts, self.detail_regions, self.detail_parts,
                          self.slot)

    def arrays(self) -> tuple:
        """What `resolve_contacts` takes of the grid: (cell, start, ids, x, regions, parts)."""
        return self.cell, self.start, self.ids, self.x, self.regions, self.parts

    def detail_arrays(self) -> tuple:
        """The same for the detailed surface's body parts (S103: `other_part_seeds`)."""
        return self.cell, self.start, self.ids, self.x, self.detail_regions, self.detail_parts


@helper
def _cell_hash(i, j, k, mask):
    return ((i * 73856093) ^ (j * 19349663) ^ (k * 83492791)) & mask


@kernel
def build_vertex_grid(body_x, regions, detail, cell, start, ids, counts, grid_x, grid_regions, parts, detail_regions,
                      detail_parts, slot):
    """Counting sort of the body vertices by hashed cell (CSR: start, ids), with their
    positions and regions (and detail: the detailed surface's parts) copied in that order and
    each cell's OR of region bits. slot (n,): scratch, each vertex's bucket (hashed once)."""
    mask = counts.shape[0] - 1
    counts[:] = 0
    parts[:] = 0
    detail_parts[:] = 0
    n = ids.shape[0]
    for u in range(n):
        c = _cell_hash(int(math.floor(body_x[u, 0] / cell)), int(math.floor(body_x[u, 1] / cell)),
                       int(math.floor(body_x[u, 2] / cell)), mask)
        slot[u] = c
        counts[c] += 1
        parts[c] |= regions[u]
        detail_parts[c] |= detail[u]
    total = 0
    for c in range(counts.shape[0]):
        start[c] = total
        total += counts[c]
        counts[c] = 0
    start[counts.shape[0]] = total
    for u in range(n):
        c = slot[u]
        e = start[c] + counts[c]
        ids[e] = u
        grid_x[e, 0], grid_x[e, 1], grid_x[e, 2] = body_x[u, 0], body_x[u, 1], body_x[u, 2]
        grid_regions[e] = regions[u]
        detail_regions[e] = detail[u]
        counts[c] += 1


@helper
def _cell_block(px, py, pz, r, cell):
    """The grid cells (i0..i1, j0..j1, k0..k1) that the box of half-width r around p overlaps."""
    return (int(math.floor((px - r) / cell)), int(math.floor((px + r) / cell)),
            int(math.floor((py - r) / cell)), int(math.floor((py + r) / cell)),
            int(math.floor((pz - r) / cell)), int(math.floor((pz + r) / cell)))


def part_scratch() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scratch for `grid_nearest_per_part` (part, best, best_d2): one slot per region bit."""
    return (np.zeros(PART_SLOTS, dtype=REGION_DTYPE), np.zeros(PART_SLOTS, dtype=np.int32),
            np.zeros(PART_SLOTS))


@helper
def grid_nearest_per_part(px, py, pz, grid_x, grid_regions, parts, cell, start, ids, radius, own, part, best,
                          best_d2):
    """The nearest body vertex of every body part (a distinct region bit) other than `own`
    within `radius` of p. Returns how many parts were found (at most len(part)): part k is
    region bit part[k], its nearest vertex best[k] at squared distance best_d2[k]. The cells
    whose vertices are all of `own` are not scanned (on most of a garment, all of them)."""
    mask = start.shape[0] - 2
    r2 = radius * radius
    n = 0
    i0, i1, j0, j1, k0, k1 = _cell_block(px, py, pz, radius, cell)
    for i in range(i0, i1 + 1):
        for j in range(j0, j1 + 1):
            for k in range(k0, k1 + 1):
                c = _cell_hash(i, j, k, mask)
                if (parts[c] & ~own) == 0:
                    continue
                for e in range(np.uint64(start[c]), np.uint64(start[c + 1])):  # (unsigned: no wrap-around)
                    g = grid_regions[e]
                    if g == own:
                        continue
                    d = (grid_x[e, 0] - px) ** 2 + (grid_x[e, 1] - py) ** 2 + (grid_x[e, 2] - pz) ** 2
                    if d >= r2:
                        continue
                    slot = 0
                    while slot < n and part[slot] != g:
                        slot += 1
                    if slot == n:
                        if n == part.shape[0]:
                            continue
                        part[slot] = g
                        best[slot] = ids[e]
                        best_d2[slot] = d
                        n += 1
                    elif d < best_d2[slot]:
                        best[slot] = ids[e]
                        best_d2[slot] = d
    return n


@helper
def grid_nearest(px, py, pz, grid_x, cell, start, ids, best, best_d2):
    """Nearest body vertex to p within one grid cell of it, if nearer than best_d2 (returns
    (vertex, squared distance); (best, best_d2) when none is nearer). Only the cells that the
    ball of radius sqrt(best_d2) around p overlaps are visited: for a particle in contact
    that is a few cells, not 27."""
    mask = start.shape[0] - 2
    r = min(math.sqrt(best_d2), cell)
    i0, i1, j0, j1, k0, k1 = _cell_block(px, py, pz, r, cell)
    for i in range(i0, i1 + 1):
        for j in range(j0, j1 + 1):
            for k in range(k0, k1 + 1):
                c = _cell_hash(i, j, k, mask)
                for e in range(np.uint64(start[c]), np.uint64(start[c + 1])):  # (unsigned: no wrap-around)
                    d = (grid_x[e, 0] - px) ** 2 + (grid_x[e, 1] - py) ** 2 + (grid_x[e, 2] - pz) ** 2
                    if d < best_d2:
                        best_d2 = d
                        best = ids[e]
    return best, best_d2


class FaceTree:
    """A bounding-box tree over the faces clothes can touch, its shape built once from the
    first pose it sees and its boxes refitted to every pose after (one bottom-up pass).

    It answers "which face is nearest to p within r" exactly, where the ring of the nearest
    vertex holds the nearest face only when the surface does not fold: in a crease of the
    skinned skin (between the buttocks, the groin in a stride) a face of another sheet of the
    same part can be nearer than every face around the nearest vertex. The top levels split
    the faces by body part, so that a refitted box never spans an arm and the torso; below,
    median splits along the longest axis, down to LEAF_FACES faces. Nodes are in pre-order
    (a child after its parent): the refit walks them backwards."""

    LEAF_FACES = 4

    def __init__(self, triangles: np.ndarray, faces: np.ndarray, regions: np.ndarray):
        self.triangles = triangles
        self.faces = np.asarray(faces, dtype=np.int32)
        self.face_region = regions[triangles[self.faces, 0]]
        self.built = False

    def update(self, body_x: np.ndarray) -> None:
        if not self.built:
            self._build(body_x)
        refit_face_tree(body_x, self.triangles, self.order, self.child, self.first, self.count, self.box)

    # the shapes built so far, by what they were built from (every garment's simulation builds its
    # tree from the rest body: about 90 ms of Python each time): (child, first, count, order,
    # parent, leaf, stack_depth), shared by the trees built from the same (no kernel writes them:
    # the refit writes each tree's own boxes)
    _shapes: dict[bytes, tuple] = {}
    _shapes_lock = threading.Lock()
    SHAPES_KEPT = 16

    def _build(self, body_x: np.ndarray) -> None:
        h = hashlib.sha1()
        for a in (self.triangles, self.faces, self.face_region, body_x):
            a = np.ascontiguousarray(a)
            h.update(repr((a.dtype.str, a.shape)).encode())
            h.update(a.data)
        shape_key = h.digest() + self.LEAF_FACES.to_bytes(4, "little")
        with self._shapes_lock:
            shape = self._shapes.get(shape_key)
        if shape is None:
            self._build_shape(body_x)
            shape = (self.child, self.first, self.count, self.order, self.parent, self.leaf, self.stack_depth)
            with self._shapes_lock:
                while len(self._shapes) >= self.SHAPES_KEPT:
                    self._shapes.pop(next(iter(self._shapes)))
                self._shapes[shape_key] = shape
        self.child, self.first, self.count, self.order, self.parent, self.leaf, self.stack_depth = shape
        self.box = np.zeros((len(self.child), 6))  # lo xyz, hi xyz: this tree's own, refitted per pose
        self.built = True

    def _build_shape(self, body_x: np.ndarray) -> None:
        centre = body_x[self.triangles[self.faces]].mean(axis=1)
        child, first, count, order = [], [], [], []
        todo = [(-1, 0, np.arange(len(self.faces)))]  # (parent, which child, faces); pre-order
        while todo:
            parent, side, ids = todo.pop()
            node = len(child)
            child.append([-1, -1])
            first.append(0)
            count.append(0)
            if parent >= 0:
                child[parent][side] = node
            if len(ids) <= self.LEAF_FACES:
                first[node] = len(order)
                count[node] = len(ids)
                order.extend(self.faces[ids])
                continue
            reg = self.face_region[ids]
            if np.any(reg != reg[0]):
                left = reg == reg[0]  # one body part apart from the others
            else:
                c = centre[ids]
                axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
                rank = np.argsort(c[:, axis], kind="stable")
                left = np.zeros(len(ids), dtype=bool)
                left[rank[: len(ids) // 2]] = True
            # pushed right first, so the left subtree is numbered next (pre-order)
            todo.append((node, 1, ids[~left]))
            todo.append((node, 0, ids[left]))
        self.child = np.array(child, dtype=np.int32)
        self.first = np.array(first, dtype=np.int32)
        self.count = np.array(count, dtype=np.int32)
        self.order = np.array(order, dtype=np.int32)
        self.parent = np.full(len(child), -1, dtype=np.int32)
        for node, (a, b) in enumerate(self.child):
            if a >= 0:
                self.parent[a] = self.parent[b] = node
        self.leaf = np.full(len(self.triangles), -1, dtype=np.int32)  # each tree face's leaf, -1: not in the tree
        for node in np.flatnonzero(self.child[:, 0] < 0):
            self.leaf[self.order[self.first[node]:self.first[node] + self.count[node]]] = node
        self.stack_depth = self._depth() + 2
        if self.stack_depth > FACE_TREE_STACK:
            raise ValueError(f"face tree {self.stack_depth - 2} levels deep; FACE_TREE_STACK allows "
                             f"{FACE_TREE_STACK - 2}")

    def _depth(self) -> int:
        depth = np.zeros(len(self.child), dtype=np.int64)
        for node in range(len(self.child)):  # pre-order: a parent's depth is set before its children's
            for c in self.child[node]:
                if c >= 0:
                    depth[c] = depth[node] + 1
        return int(depth.max())

    def arrays(self) -> tuple:
        """What `resolve_contacts` takes of the tree: (box, child, first, count, order, parent, leaf)."""
        return self.box, self.child, self.first, self.count, self.order, self.parent, self.leaf


@kernel
def refit_face_tree(body_x, tris, order, child, first, count, box):
    """Every node's box around its faces' corners for this pose: the leaves from their faces,
    the inner nodes from their children (nodes are in pre-order: backwards, children first)."""
    for node in range(child.shape[0] - 1, -1, -1):
        if child[node, 0] < 0:
            for k in range(3):
                box[node, k] = np.inf
                box[node, 3 + k] = -np.inf
            for e in range(first[node], first[node] + count[node]):
                t = order[e]
                for c in range(3):
                    u = tris[t, c]
                    for k in range(3):
                        box[node, k] = min(box[node, k], body_x[u, k])
                        box[node, 3 + k] = max(box[node, 3 + k], body_x[u, k])
        else:
            a, b = child[node, 0], child[node, 1]
            for k in range(3):
                box[node, k] = min(box[a, k], box[b, k])
                box[node, 3 + k] = max(box[a, 3 + k], box[b, 3 + k])


@helper
def _box_d2(px, py, pz, box, node):
    """Squared distance from p to the node's box (0 inside)."""
    dx = max(box[node, 0] - px, 0.0, px - box[node, 3])
    dy = max(box[node, 1] - py, 0.0, py - box[node, 4])
    dz = max(box[node, 2] - pz, 0.0, pz - box[node, 5])
    return dx * dx + dy * dy + dz * dz


@helper
def tree_nearest_face(px, py, pz, body_x, tris, face_n, box, child, first, count, order, parent, leaf, start,
                      skip, stack, best_d2, front, q):
    """The body face nearest to p among those p is less than `front` in front of (by its plane),
    if one is nearer than sqrt(best_d2): returns (face, squared distance, v, w) with the closest
    point in q and its barycentric weights of the face's second and third corners; face -1 when
    none is. A subtree whose box is no nearer than the best so far is not entered, and a face
    p is farther in front of than `front`, or farther behind than the best distance, costs a
    plane test: a face p is well in front of cannot put p inside.
    start: a body face near p (the ring's closest), or -1. The search begins at its leaf and
    climbs to the root, searching each sibling on the way (the same answer as from the root).
    skip: a body vertex whose faces are not tested (the ring's, already measured; -1: none).
    stack: (depth,) int32 scratch."""
    best_t = -1
    bv = bw = 0.0
    qx = qy = qz = 0.0
    climb = leaf[start] if 0 <= start < leaf.shape[0] else -1
    if climb < 0:  # not a face of the tree: from the root
        climb = 0
    top = 0
    stack[0] = climb
    while True:
        while top >= 0:
            node = stack[top]
            top -= 1
            if _box_d2(px, py, pz, box, node) >= best_d2:
                continue
            if child[node, 0] >= 0:
                # not ordered by distance: nearly every query finds nothing nearer than its bound,
                # and ordering would test each child's box twice
                stack[top + 1] = child[node, 1]
                stack[top + 2] = child[node, 0]
                top += 2
                continue
            r = math.sqrt(best_d2)
            for e in range(first[node], first[node] + count[node]):
                t = order[e]
                a0 = tris[t, 0]
                if a0 == skip or tris[t, 1] == skip or tris[t, 2] == skip:
                    continue
                plane = ((px - body_x[a0, 0]) * face_n[t, 0] + (py - body_x[a0, 1]) * face_n[t, 1]
                         + (pz - body_x[a0, 2]) * face_n[t, 2])
                if plane >= front or plane <= -r:
                    continue
                v, w = closest_point_triangle(px, py, pz, body_x, tris[t, 0], tris[t, 1], tris[t, 2], q)
                d2 = (px - q[0]) ** 2 + (py - q[1]) ** 2 + (pz - q[2]) ** 2
                if d2 < best_d2:
                    best_d2, best_t, bv, bw = d2, t, v, w
                    qx, qy, qz = q[0], q[1], q[2]
                    r = math.sqrt(best_d2)
        up = parent[climb]
        if up < 0:
            break
        # the subtree below climb is done: its sibling next, then one level up
        top = 0
        stack[0] = child[up, 0] if child[up, 1] == climb else child[up, 1]
        climb = up
    q[0], q[1], q[2] = qx, qy, qz
    return best_t, best_d2, bv, bw
