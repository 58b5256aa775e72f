"""Per-frame coarse cloth simulation (S101): state arrays and the frame step.

    model = prepare_cloth(garment, fabric, body_rest_vertices, body_mesh)   # once
    sim = ClothSim(model, body_mesh, body_rest_vertices)                    # once per session
    x = sim.step(body_vertices, dt)                                          # every frame

A frame: body following (relative coordinates to the nearest face, distance-blended), then
`substeps` × (RK4 step, vertex collision, strain limiting), then the instability check (NaN,
speed, runaway stretch → reset to the body-following positions, counted), the contact pass
over the whole body (then a slide pass: strain limiting with the placed particles free and the
contact pass again), strain limiting with the placed particles held, the contact pass once
more for the particles that moved, the body parts each particle's substep collisions track
(`track_parts`), and the new relative coordinates.

A frame is two kernel calls, `advance_particles` (up to the instability check) and
`finish_frame` (the rest), which take the model, body, state and settings as tuples built once
(`ClothSim._arguments`): two dozen calls with up to 38 arguments each cost 10-35 µs a
garment-frame of Python and dispatch (1-2.5 % of S101; docs/history.md, thirty-ninth session).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from .coarse_layers import hold_over
from .coarsen import coarsen
from .collision import (ALL_REGIONS, FACE_TREE_STACK, PART_SLOTS, REGION_DTYPE, UNION_HITS, BodyMesh, BodyPose,
                        attach_to_body, collide_particles, face_normals, follow_body, leave_body_union, part_scratch,
                        part_seeds, part_slots, resolve_contacts, track_parts)
from .dynamics import limit_stretch, rk4_substep, spring_scratch
from .fabric import Fabric
from .garment import Garment, face_outward
from .geometry import nearest_vertices, region_masks, vertex_normals
from .jit import helper, kernel
from .model import ClothModel, SimSettings, build_cloth_model
from .winding import NO_WINDING


@kernel
def simulate_substeps(n_sub, collide_every, dt, x, v, carried, inv_mass, drag, normals, gravity_y, pairs, params,
                      si, sj, rest, spring_work, work, n_structural, max_strain, limit_passes, body_x, body_vel,
                      nbr_start, nbr_ids, tris, tri_start, tri_ids, regions, masks, nearest, part_nearest, thickness,
                      friction, contact, fixed, face_n, tested_at, clear):
    """n_sub × (RK4 integration, vertex collision, strain limiting), fused so that a frame is one
    call; collision after every collide_every-th substep and always after the last."""
    for k in range(n_sub):
        rk4_substep(x, v, carried, dt, inv_mass, drag, normals, gravity_y, pairs, params, spring_work, work)
        if (k + 1) % collide_every == 0 or k == n_sub - 1:
            collide_particles(x, v, body_x, body_vel, nbr_start, nbr_ids, tris, tri_start, tri_ids, regions,
                              masks, nearest, part_nearest, thickness, friction, contact, fixed, face_n, tested_at,
                              clear)
        # one Gauss-Seidel pass per substep, more on the last: the frame's output is what must hold
        for _ in range(1 if k < n_sub - 1 else limit_passes):
            limit_stretch(x, v, carried, inv_mass, si, sj, rest, n_structural, max_strain)


@kernel
def recover_unstable(x, v, followed, si, sj, rest, n_structural, max_speed, max_stretch, bad):
    """Reset exploded particles to their body-following positions; returns how many were reset.

    Exploded: a non-finite position or velocity, a speed above max_speed, or a structural
    spring (the first n_structural) longer than max_stretch × its rest length (both ends)."""
    n = x.shape[0]
    lim2 = max_speed * max_speed
    for i in range(n):
        s2 = v[i, 0] ** 2 + v[i, 1] ** 2 + v[i, 2] ** 2
        ok = np.isfinite(x[i, 0]) and np.isfinite(x[i, 1]) and np.isfinite(x[i, 2]) and np.isfinite(s2)
        bad[i] = 0 if (ok and s2 <= lim2) else 1
    for s in range(n_structural):
        i = si[s]
        j = sj[s]
        d2 = (x[i, 0] - x[j, 0]) ** 2 + (x[i, 1] - x[j, 1]) ** 2 + (x[i, 2] - x[j, 2]) ** 2
        if not (d2 <= (max_stretch * rest[s]) ** 2):
            bad[i] = 1
            bad[j] = 1
    count = 0
    for i in range(n):
        if bad[i]:
            count += 1
            for k in range(3):
                x[i, k] = followed[i, k]
                v[i, k] = 0.0  # at rest relative to the body, which carries it
    return count


@kernel
def mark_moved(x, before, distance, out):
    """out[i] = 1 where particle i moved more than distance from before[i], else 0."""
    d2 = distance * distance
    for i in range(x.shape[0]):
        out[i] = 1 if ((x[i, 0] - before[i, 0]) ** 2 + (x[i, 1] - before[i, 1]) ** 2
                       + (x[i, 2] - before[i, 2]) ** 2) > d2 else 0


SLIDE_RECHECK = 0.1  # x thickness: a particle that slid less is not tested again (ClothSim.settle_contacts)
# x thickness: the same for the held strain-limiting passes before the final contact pass. Not
# more: where the skinned skin intersects itself, a sub-millimetre move can make a buried sheet
# facing the other way the nearest surface, and a particle outside reads deep inside
FINAL_RECHECK = 0.1
REGION_RADIUS = 0.06  # m: a particle may attach to the body parts within this distance at rest


@kernel
def advance_particles(model, body, state, body_x, face_n, n_sub, h, inv_dt, ease, settings):
    """A frame's body following, n_sub substeps of length h and the instability check
    (`recover_unstable`) as one call (one dispatch instead of four: see `ClothSim.step`):
    returns how many particles were reset. model, body, state, settings: `ClothSim`'s argument
    tuples (`ClothSim._arguments`); inv_dt, ease: `follow_body`'s."""
    (triangles, grip, inv_mass, drag, pairs, params, si, sj, rest, region_mask, n_structural, max_strain, thickness,
     friction) = model
    tris, nbr_start, nbr_ids, tri_start, tri_ids, tri_nbrs, regions, winding_faces = body
    (x, v, nearest, part_nearest, nearest_any, face, bary, height, anchor, body_vel, carrier, follow_w, followed,
     contact, tested_at, clear, normals, bad, work, spring_work, carried) = state[0]
    collide_every, limit_passes, gravity_y, follow_near, follow_far, max_speed, max_stretch = settings[0]
    follow_body(x, v, body_x, tris, grip, face, bary, height, anchor, body_vel, carrier, carried, inv_dt, follow_near,
                follow_far, followed, face_n, follow_w, ease)
    vertex_normals(x, triangles, normals)  # for air drag
    for i in range(clear.shape[0]):
        clear[i] = -np.inf  # the body moved: every particle is tested at the first collision
    simulate_substeps(n_sub, collide_every, h, x, v, carried, inv_mass, drag, normals, gravity_y, pairs, params, si,
                      sj, rest, spring_work, work, n_structural, max_strain, limit_passes, body_x, carrier, nbr_start,
                      nbr_ids, tris, tri_start, tri_ids, regions, region_mask, nearest, part_nearest, thickness,
                      friction, contact, grip, face_n, tested_at, clear)
    # recovery before the contact pass: a reset particle's body-following place can lie in
    # another body part, and what leaves the step has been through the contact pass
    return recover_unstable(x, v, followed, si, sj, rest, n_structural, max_speed, max_stretch, bad)


@kernel
def contact_pass(model, body, state, body_x, face_n, grid, tree, radius, active):
    """`resolve_contacts` against the whole body in this pose for the active particles (uint8
    mask); marks the placed particles (placed_inv_mass) and those left with an untested push
    (unsettled). Arguments as `settle_particles`'."""
    (triangles, grip, inv_mass, drag, pairs, params, si, sj, rest, region_mask, n_structural, max_strain, thickness,
     friction) = model
    tris, nbr_start, nbr_ids, tri_start, tri_ids, tri_nbrs, regions, winding_faces = body
    (x, v, nearest, part_nearest, nearest_any, face, bary, height, anchor, body_vel, carrier, follow_w, followed,
     contact, tested_at, clear, normals, bad, work, spring_work, carried) = state[0]
    (q, stack, part, part_vertex, part_d2, placed_inv_mass, held_from, all_particles, recheck, unsettled, hit_t, hit_s,
     hit_f) = state[1]
    cell, grid_start, grid_ids, grid_x, grid_regions, grid_parts = grid
    box, child, first, count, order, parent, leaf = tree
    resolve_contacts(x, v, body_x, carrier, nbr_start, nbr_ids, tris, tri_start, tri_ids, tri_nbrs, regions,
                     nearest_any, thickness, grip, face_n, q, cell, grid_start, grid_ids, grid_x, grid_regions,
                     grid_parts, box, child, first, count, order, parent, leaf, radius, stack, part, part_vertex,
                     part_d2, inv_mass, placed_inv_mass, active, unsettled)


@kernel
def union_pass(model, body, state, body_x, face_n, tree, winding, active):
    """`leave_body_union` for the active particles (uint8 mask), out of the body as a whole;
    marks the placed particles. Returns how many it put out, and how many it tested."""
    (triangles, grip, inv_mass, drag, pairs, params, si, sj, rest, region_mask, n_structural, max_strain, thickness,
     friction) = model
    tris, nbr_start, nbr_ids, tri_start, tri_ids, tri_nbrs, regions, winding_faces = body
    (x, v, nearest, part_nearest, nearest_any, face, bary, height, anchor, body_vel, carrier, follow_w, followed,
     contact, tested_at, clear, normals, bad, work, spring_work, carried) = state[0]
    (q, stack, part, part_vertex, part_d2, placed_inv_mass, held_from, all_particles, recheck, unsettled, hit_t, hit_s,
     hit_f) = state[1]
    lo, start, ids, span, extent = winding
    box, child, first, count, order, parent, leaf = tree
    tested = 0
    for i in range(active.shape[0]):
        tested += 1 if active[i] else 0
    pushed = leave_body_union(x, v, carrier, body_x, face_n, winding_faces, lo, start, ids, span, extent, tris, box,
                              child, first, count, order, parent, leaf, stack, hit_t, hit_s, hit_f, q, thickness,
                              active, placed_inv_mass)
    return pushed, tested


@helper
def _copy_rows(src, dst):
    for i in range(src.shape[0]):
        for k in range(3):
            dst[i, k] = src[i, k]


@kernel
def settle_particles(model, body, state, body_x, face_n, grid, tree, winding, settings, union_tested):
    """After the substeps: the contact pass against the whole body, the slide pass, the
    strain-limiting passes with the placed particles held, the final contact pass and the union
    passes (see `SimSettings`), as one call (one dispatch instead of a dozen). Returns how many
    particles the union passes put out; union_tested (2,) int64: written, how many particles
    the first and the last union pass tested (-1: not run). grid, tree, winding: the body
    pose's `VertexGrid.arrays()`, `FaceTree.arrays()` and `WindingGrid.arrays()` (empty ones of
    the same types where the settings read none)."""
    (triangles, grip, inv_mass, drag, pairs, params, si, sj, rest, region_mask, n_structural, max_strain, thickness,
     friction) = model
    (x, v, nearest, part_nearest, nearest_any, face, bary, height, anchor, body_vel, carrier, follow_w, followed,
     contact, tested_at, clear, normals, bad, work, spring_work, carried) = state[0]
    (q, stack, part, part_vertex, part_d2, placed_inv_mass, held_from, all_particles, recheck, unsettled, hit_t, hit_s,
     hit_f) = state[1]
    slide_passes, contact_limit_passes, final_contact, union_passes, radius = settings[1]
    union_tested[0] = union_tested[1] = -1
    pushes = 0
    contact_pass(model, body, state, body_x, face_n, grid, tree, radius, all_particles)
    if slide_passes:
        # the pass puts a particle where the skin under it went, and skin stretches more than
        # the cloth may (hips and thighs in a stride): free strain-limiting passes let the
        # placed particles slide back towards their neighbours, and a second contact pass puts
        # out again what slid inside, and what the first pass's pushes left untested. A
        # particle that slid less than SLIDE_RECHECK x thickness from where the first pass
        # left it outside is still outside (the body has not moved); it is not tested again,
        # and, as that test would leave it, not held by the strain limiting below.
        _copy_rows(x, held_from)
        for _ in range(slide_passes):
            limit_stretch(x, v, carried, inv_mass, si, sj, rest, n_structural, max_strain)
        mark_moved(x, held_from, SLIDE_RECHECK * thickness, recheck)
        for i in range(recheck.shape[0]):
            recheck[i] |= unsettled[i]
            placed_inv_mass[i] = inv_mass[i]
        contact_pass(model, body, state, body_x, face_n, grid, tree, radius, recheck)
    if union_passes >= 2:
        pushed, tested = union_pass(model, body, state, body_x, face_n, tree, winding, all_particles)
        union_tested[0] = tested
        pushes += pushed
    # the pushes stretch the cloth around a pushed particle: pull its neighbours after it
    _copy_rows(x, held_from)
    for _ in range(contact_limit_passes):
        limit_stretch(x, v, carried, placed_inv_mass, si, sj, rest, n_structural, max_strain)
    final = final_contact and contact_limit_passes > 0
    if final:
        # pulled after a placed particle, a free one cuts the chord across a curved limb:
        # what moved far enough to have reached the body is tested once more
        mark_moved(x, held_from, FINAL_RECHECK * thickness, recheck)
        contact_pass(model, body, state, body_x, face_n, grid, tree, radius, recheck)
    if union_passes >= 1:  # last: what the ring tests above cannot see
        active = all_particles
        if union_passes >= 2:
            # the first union pass left each particle outside, or where no way out was found:
            # only one that moved since by more than FINAL_RECHECK x thickness can have gone
            # in (the final contact pass moved only such particles)
            if not final:
                mark_moved(x, held_from, FINAL_RECHECK * thickness, recheck)
            active = recheck
        pushed, tested = union_pass(model, body, state, body_x, face_n, tree, winding, active)
        union_tested[1] = tested
        pushes += pushed
    return pushes


@kernel
def finish_frame(model, body, state, body_x, face_n, grid, tree, winding, settings, union_tested):
    """`settle_particles`, then the body parts each particle's substep collisions track
    (`track_parts`) and the new relative coordinates (`attach_to_body`): the end of a frame as
    one call. Returns what settle_particles returns."""
    (triangles, grip, inv_mass, drag, pairs, params, si, sj, rest, region_mask, n_structural, max_strain, thickness,
     friction) = model
    tris, nbr_start, nbr_ids, tri_start, tri_ids, tri_nbrs, regions, winding_faces = body
    (x, v, nearest, part_nearest, nearest_any, face, bary, height, anchor, body_vel, carrier, follow_w, followed,
     contact, tested_at, clear, normals, bad, work, spring_work, carried) = state[0]
    pushes = settle_particles(model, body, state, body_x, face_n, grid, tree, winding, settings, union_tested)
    track_parts(x, body_x, regions, region_mask, nearest, nearest_any, part_nearest, REGION_RADIUS)
    attach_to_body(x, body_x, tris, tri_start, tri_ids, nearest, grip, face, bary, height, anchor, face_n)
    return pushes


def particle_regions(points: np.ndarray, body_x: np.ndarray, body: BodyMesh) -> np.ndarray:
    masks = np.zeros(len(points), dtype=REGION_DTYPE)
    region_masks(np.ascontiguousarray(points, dtype=np.float64), body_x, body.regions, REGION_RADIUS, masks)
    return masks


def resolve_intersections(points: np.ndarray, body_x: np.ndarray, body: BodyMesh, thickness: float,
                          masks: np.ndarray, iterations: int = 4) -> np.ndarray:
    """Move particles that start inside the body out to its surface plus thickness (garment setup)."""
    x = np.array(points, dtype=np.float64)
    v = np.zeros_like(x)
    nearest = np.empty(len(x), dtype=np.int32)
    nearest_vertices(x, body_x, nearest, body.regions, masks)
    part_nearest = part_seeds(x, body_x, body.regions, masks)
    contact = np.zeros(len(x), dtype=np.uint8)
    free = np.zeros(len(x), dtype=np.uint8)
    face_n = face_normals(body_x, body.triangles)
    tested_at = np.zeros_like(x)
    clear = np.full(len(x), -np.inf)
    for _ in range(iterations):
        collide_particles(x, v, body_x, v, body.nbr_start, body.nbr_ids, body.triangles, body.tri_start,
                          body.tri_ids, body.regions, masks, nearest, part_nearest, thickness, 0.0, contact, free,
                          face_n, tested_at, clear)
    return x


def prepare_cloth(garment: Garment, fabric: Fabric, body_rest: np.ndarray, body: BodyMesh,
                  settings: SimSettings | None = None, grip_waistband: bool = False) -> ClothModel:
    """Coarse model of a garment fitted on the rest body, its initial intersections resolved.

    grip_waistband: the garment's highest boundary loop grips the body (an elastic or buttoned
    waistband): those particles keep their rest-pose place on the body. The rest of the garment
    is simulated."""
    settings = settings or SimSettings()
    garment = face_outward(garment, body_rest[: body.n_vertices])  # the skin, not the helper geometry
    coarse = coarsen(garment.vertices, garment.faces, settings.target_particles)
    body_x = body.internal(body_rest)
    masks = particle_regions(coarse.vertices, body_x, body)
    resolved = resolve_intersections(coarse.vertices, body_x, body, fabric.thickness, masks)
    model = build_cloth_model(garment, fabric, settings, resolved, coarse)
    model.region_mask = masks
    if grip_waistband and model.boundary_loops:
        top = max(model.boundary_loops, key=lambda loop: model.rest_positions[loop, 1].mean())
        model.grip[top] = 1
        model.inv_mass[top] = 0.0
    return model


@dataclass
class ClothStats:
    frames: int = 0
    reset_particles: int = 0  # particles reset by the instability recovery, summed over frames
    reset_frames: int = 0  # frames in which any particle was reset
    union_pushes: int = 0  # particles put out of the body as a whole (leave_body_union), summed over frames
    last_substeps: int = 0


class ClothState:
    """Everything that changes per frame, preallocated."""

    def __init__(self, n: int, n_springs: int, n_slots: int = PART_SLOTS):
        self.x = np.zeros((n, 3))  # positions, m
        self.v = np.zeros((n, 3))  # velocities, m/s
        self.nearest = np.zeros(n, dtype=np.int32)  # nearest body vertex in the particle's body regions
        self.part_nearest = np.full((n, n_slots), -1, dtype=np.int32)  # and in each of them (see part_seeds)
        self.nearest_any = np.zeros(n, dtype=np.int32)  # nearest body vertex over the whole body
        self.q = np.zeros(3)  # contact pass scratch, and for the body parts near a particle:
        self.stack = np.zeros(FACE_TREE_STACK, dtype=np.int32)  # the face tree's traversal
        self.hit_t = np.zeros(UNION_HITS)  # the rays of leave_body_union
        self.hit_s = np.zeros(UNION_HITS, dtype=np.int32)
        self.hit_f = np.zeros(UNION_HITS, dtype=np.int32)
        self.part, self.part_vertex, self.part_d2 = part_scratch()
        self.placed_inv_mass = np.zeros(n)  # inverse masses with 0 for the particles the contact pass placed
        self.held_from = np.zeros((n, 3))  # positions before the strain-limiting passes with those held
        self.all_particles = np.ones(n, dtype=np.uint8)  # contact pass masks: every particle,
        self.recheck = np.zeros(n, dtype=np.uint8)  # those a strain-limiting pass moved far enough to test again
        self.unsettled = np.zeros(n, dtype=np.uint8)  # those the contact pass left with an untested push
        self.face = np.zeros(n, dtype=np.int32)  # body face of the relative coordinates
        self.bary = np.zeros((n, 3))  # barycentric coordinates on that face
        self.height = np.zeros(n)  # offset along the face normal, m
        self.anchor = np.zeros((n, 3))  # the attachment point on the body
        self.body_vel = np.zeros((n, 3))  # body velocity at the attachment point, m/s
        self.carrier = np.zeros((n, 3))  # part of it not transported by body following, m/s
        self.carried = np.zeros((n, 3))  # the part transported, m/s: v + carried is the world velocity
        self.follow_w = np.full(n, -1.0)  # the body following's weight last frame (-1: none yet)
        self.followed = np.zeros((n, 3))  # fully body-following positions (recovery targets)
        self.contact = np.zeros(n, dtype=np.uint8)  # in contact after the last collision
        self.tested_at = np.zeros((n, 3))  # substep collision: where each particle was last tested,
        self.clear = np.zeros(n)  # and how far in front of the body's faces it was (see collide_particles)
        self.normals = np.zeros((n, 3))  # particle normals of this frame (air drag)
        self.bad = np.zeros(n, dtype=np.uint8)
        self.work = np.zeros((9, n, 3))
        self.spring_work = spring_scratch(n_springs)


class ClothSim:
    def __init__(self, model: ClothModel, body: BodyMesh, body_vertices: np.ndarray):
        self.model = model
        self.body = body
        self.state = ClothState(model.n_particles, len(model.spring_i), part_slots(body.regions))
        self.stats = ClothStats()
        self.stage_seconds = np.zeros(2)  # integration, collision (filled when profiling)
        self.union_tested = np.zeros(2, dtype=np.int64)  # particles the last frame's union passes tested
        # (CoarseLayerModel, CoarseLayerState) of each garment this one is worn over (`cloth.coarse_layers`),
        # the inner cloth carried into the frame's pose by the owner before the step
        self.worn_over: list[tuple] = []
        self.over_moved = 0  # particles put over an inner garment's cloth in the last frame
        st = model.settings
        self.own_pose = BodyPose(body, st.needs_face_tree, st.union_passes > 0)  # when no shared pose is given
        self.pose = self.own_pose  # the body pose of the last step, for the detailed surface stage
        self._model_args, self._body_args, self._state_args, self._settings_args = self._arguments()
        self.reset(body_vertices)

    def _arguments(self) -> tuple[tuple, tuple, tuple, tuple]:
        """What the frame's kernels (`advance_particles`, `settle_particles`) take of the model,
        the body mesh, the state and the settings, as tuples built once: a frame is then two
        calls with a dozen arguments, not two dozen calls with thirty each (about 80 µs a
        garment-frame of Python and dispatch). The kernels unpack them in this order."""
        m, b, s, st = self.model, self.body, self.state, self.model.settings
        f = m.fabric
        model = (m.triangles, m.grip, m.inv_mass, m.drag, m.spring_pairs, m.spring_params, m.spring_i, m.spring_j,
                 m.rest_length, m.region_mask, int(m.n_structural), float(f.max_strain), float(f.thickness),
                 float(f.friction))
        body = (b.triangles, b.nbr_start, b.nbr_ids, b.tri_start, b.tri_ids, b.tri_nbrs, b.regions, b.winding_faces)
        state = ((s.x, s.v, s.nearest, s.part_nearest, s.nearest_any, s.face, s.bary, s.height, s.anchor, s.body_vel,
                  s.carrier, s.follow_w, s.followed, s.contact, s.tested_at, s.clear, s.normals, s.bad, s.work,
                  s.spring_work, s.carried),
                 (s.q, s.stack, s.part, s.part_vertex, s.part_d2, s.placed_inv_mass, s.held_from, s.all_particles,
                  s.recheck, s.unsettled, s.hit_t, s.hit_s, s.hit_f))
        # fixed types (an integer given for a float setting would compile the kernels again)
        settings = ((int(st.collide_every), int(st.limit_passes), -float(st.gravity), float(st.follow_near),
                     float(st.follow_far), float(st.max_speed), float(st.max_stretch)),
                    (int(st.slide_passes), int(st.contact_limit_passes), bool(st.final_contact), int(st.union_passes),
                     float(st.nearest_face_radius)))
        return model, body, state, settings

    def _pose_arguments(self, pose: BodyPose) -> tuple[tuple, tuple, tuple]:
        """(grid, tree, winding) of a body pose for `settle_particles`: empty ones of the same
        types where the settings read none (the contact pass's query is off with no tree)."""
        st = self.model.settings
        if st.union_passes and (pose.faces is None or pose.winding is None):
            raise ValueError("SimSettings.union_passes needs a body pose with the face tree and the winding grid "
                             "(BodyPose(..., face_tree=True, winding=True))")
        winding = pose.winding.arrays() if pose.winding is not None else NO_WINDING
        return pose.grid.arrays(), pose.face_tree_arrays(), winding

    @property
    def body_x(self) -> np.ndarray:
        return self.pose.x

    def reset(self, body_vertices: np.ndarray) -> None:
        """Garment at its rest positions on a body in its rest pose, at rest."""
        s, m, b = self.state, self.model, self.body
        self.pose = self.own_pose
        self.pose.update(body_vertices)
        body_x, face_n = self.pose.x, self.pose.face_n
        s.x[:] = m.rest_positions
        s.v[:] = 0.0
        s.body_vel[:] = 0.0
        s.carrier[:] = 0.0
        s.follow_w[:] = -1.0
        nearest_vertices(s.x, body_x, s.nearest, b.regions, m.region_mask)
        part_seeds(s.x, body_x, b.regions, m.region_mask, s.part_nearest)
        nearest_vertices(s.x, body_x, s.nearest_any, b.regions, np.full(m.n_particles, ALL_REGIONS, dtype=REGION_DTYPE))
        free = np.zeros_like(m.grip)
        attach_to_body(s.x, body_x, b.triangles, b.tri_start, b.tri_ids, s.nearest, free, s.face, s.bary,
                       s.height, s.anchor, face_n)
        s.followed[:] = s.x
        self.stats = ClothStats()

    def step(self, body_vertices: np.ndarray | None, dt: float, profile: bool = False,
             body_pose: BodyPose | None = None) -> np.ndarray:
        """Advance one frame of length dt against the body's new vertices; returns positions (n, 3).

        body_pose: a `BodyPose` already updated for this frame, shared by every garment on the
        body (body_vertices is then ignored); None: the simulation updates its own from
        body_vertices."""
        s, m, b, st = self.state, self.model, self.body, self.model.settings
        if body_pose is None:
            body_pose = self.own_pose
            body_pose.update(body_vertices)
        self.pose = body_pose
        body_x, face_n = body_pose.x, body_pose.face_n
        n_sub = m.substeps_for(dt)
        h = dt / n_sub
        ease = -math.expm1(-dt / st.follow_easing) if st.follow_easing > 0 else 1.0
        if profile:
            n_bad = self._advance_profiled(body_pose, n_sub, h, 1.0 / dt, ease)
        else:
            n_bad = advance_particles(self._model_args, self._body_args, self._state_args, body_x, face_n, n_sub, h,
                                      1.0 / dt, ease, self._settings_args)
        if n_bad:
            self.stats.reset_particles += n_bad
            self.stats.reset_frames += 1
            # a reset particle may be far from where its walk left off
            idx = np.flatnonzero(s.bad)
            near = np.empty(len(idx), dtype=np.int32)
            nearest_vertices(s.x[idx], body_x, near, b.regions, m.region_mask[idx])
            s.nearest[idx] = near
            s.nearest_any[idx] = near
            part_seeds(s.x, body_x, b.regions, m.region_mask, s.part_nearest, idx)
        # over the garments it is worn over before the contact passes, which have the last word (the body)
        self.over_moved = sum(hold_over(lm, ls, s, m.inv_mass) for lm, ls in self.worn_over)
        body_pose.wait_queries()  # its grids and tree may still be updated (or grown) on another thread
        grid, tree, winding = self._pose_arguments(body_pose)
        self.stats.union_pushes += finish_frame(self._model_args, self._body_args, self._state_args, body_x, face_n,
                                                grid, tree, winding, self._settings_args, self.union_tested)
        self.stats.frames += 1
        self.stats.last_substeps = n_sub
        return s.x

    def _advance_profiled(self, pose: BodyPose, n_sub: int, h: float, inv_dt: float, ease: float) -> int:
        """What `advance_particles` does, kernel by kernel, with integration (RK4 and strain
        limiting) and collision timed apart into stage_seconds (bench_cloth's columns)."""
        s, m, b, st = self.state, self.model, self.body, self.model.settings
        f = m.fabric
        body_x, face_n = pose.x, pose.face_n
        follow_body(s.x, s.v, body_x, b.triangles, m.grip, s.face, s.bary, s.height, s.anchor, s.body_vel, s.carrier,
                    s.carried, inv_dt, st.follow_near, st.follow_far, s.followed, face_n, s.follow_w, ease)
        vertex_normals(s.x, m.triangles, s.normals)
        s.clear[:] = -np.inf
        t_int = t_col = 0.0
        for k in range(n_sub):  # the same order as simulate_substeps
            t0 = time.perf_counter()
            rk4_substep(s.x, s.v, s.carried, h, m.inv_mass, m.drag, s.normals, -st.gravity, m.spring_pairs,
                        m.spring_params, s.spring_work, s.work)
            t1 = time.perf_counter()
            if (k + 1) % st.collide_every == 0 or k == n_sub - 1:
                collide_particles(s.x, s.v, body_x, s.carrier, b.nbr_start, b.nbr_ids, b.triangles, b.tri_start,
                                  b.tri_ids, b.regions, m.region_mask, s.nearest, s.part_nearest, f.thickness,
                                  f.friction, s.contact, m.grip, face_n, s.tested_at, s.clear)
            t2 = time.perf_counter()
            for _ in range(1 if k < n_sub - 1 else st.limit_passes):
                limit_stretch(s.x, s.v, s.carried, m.inv_mass, m.spring_i, m.spring_j, m.rest_length, m.n_structural,
                              f.max_strain)
            t_int += (t1 - t0) + (time.perf_counter() - t2)
            t_col += t2 - t1
        self.stage_seconds[0] = t_int
        self.stage_seconds[1] = t_col
        return recover_unstable(s.x, s.v, s.followed, m.spring_i, m.spring_j, m.rest_length, m.n_structural,
                                st.max_speed, st.max_stretch, s.bad)

    def settle_contacts(self, pose: BodyPose) -> None:
        """After the substeps: the contact pass against the whole body, the slide pass, the
        strain-limiting passes with the placed particles held, the final contact pass and the
        union passes (`settle_particles`; see `SimSettings`). union_tested: what each union
        pass tested."""
        pose.wait_queries()  # its grids and tree may still be updated (or grown) on another thread
        grid, tree, winding = self._pose_arguments(pose)
        self.stats.union_pushes += settle_particles(self._model_args, self._body_args, self._state_args, pose.x,
                                                    pose.face_n, grid, tree, winding, self._settings_args,
                                                    self.union_tested)


__all__ = ["ClothSim", "ClothState", "ClothStats", "advance_particles", "contact_pass", "finish_frame", "prepare_cloth",
           "recover_unstable", "resolve_intersections", "settle_particles", "simulate_substeps", "union_pass",
           "SimSettings"]
