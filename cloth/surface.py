"""The detailed surface of a garment (SPEC.md S102-S106), built on its coarse cloth.

    surface_model = build_surface_model(cloth_model, SurfaceSettings(level=6))   # once
    surface = DetailedSurface(surface_model)                                      # per session
    p, n = surface.step(x, nearest_any, body_x, body_mesh, face_n, dt)

One frame: S102 PN triangles → S103 penetration avoidance → S104 normal force → S105 length
displacement → S106 deformation (its steps scaled to each compressed edge's deficit), constraints,
the folds drawn across the compression, and shading normals. Δh carries to the next frame.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from .collision import FACE_TREE_STACK, NO_FACE_TREE, BodyMesh, VertexGrid, part_scratch
from .creases import (EXIT_AROUND_REACH, EXIT_DIRECTIONS, EXIT_FACE_REACH, EXIT_FACING, EXIT_LOWERED_NEAR, EXIT_NEAR,
                      EXIT_NEAR_ALONG, EXIT_REACH, EXIT_TURNED, NO_DIRECTIONS, leave_creases, lowered_after_lift,
                      out_along_normals)
from .dynamics import spring_forces, spring_scratch
from .model import ClothModel, check_fields
from .pn import Tessellation, build_tessellation, pn_surface, resample_heights
from .snapshot import StateSnapshot
from .topology import vertex_cells, vertex_neighbours
from .winding import NO_WINDING
from .wrinkles import (MAX_PART_SEEDS, apply_constraints, avoid_penetration, coarse_edge_forces, cover_body_tips,
                       deformation_heights, elastic_forces, fold_across, fold_lines, fold_quads, length_displacement,
                       match_required_length, normal_force, offset_along_normals, other_part_seeds, penetration_floor,
                       quad_lattice, shading_normals)


CLEARANCE = 0.001  # m: S103's clearance at level 6 (SurfaceSettings.lift_clearance)


@dataclass(frozen=True)
class SurfaceSettings:
    level: int = 6  # PN tessellation level L: L² detailed triangles per coarse triangle
    # m: S103 lifts a detailed particle this far out of the body. None: CLEARANCE at level 6 and above, and
    # below it grown with the detailed triangles' size (`lift_clearance`, Decision: the triangles' sag)
    clearance: float | None = None
    # S103 counts this share of how far the nearest body face's corners stand out of their rings
    # off a particle's distance (`wrinkles.tip_allowance`): a coarse body's vertices stand 2-7 mm
    # out, and came through the detailed triangles between particles the clearance away (0: off)
    tip_share: float = 0.25
    # and a body vertex standing out of its ring that lies in front of the detailed triangle over it, or
    # within the clearance, raises that triangle's corners until it is the clearance under it (Decision,
    # `wrinkles.cover_body_tips`; needs the pose's vertex tips)
    cover_tips: bool = True
    contact_margin: float = 0.0075  # m: S103 tests a finer particle only near a particle this close
    # m: S103 tests a coarse face, and its first subdivision, only if a corner is this close
    # (wider than contact_margin: a face whose corners stand off a convex part can cut into it)
    face_margin: float = 0.01
    # and from as far again as the largest |Δh| among the face's particles (Decision, `wrinkles.avoid_penetration`'s
    # heights' reach)
    height_reach: bool = True
    # S103 also walks in the other body parts near a coarse face (an arm by the torso under a
    # sleeve): finds particles inside them that a walk from the torso misses, for about 0.4 ms
    # per garment-frame
    other_parts: bool = True
    # S103's walk starts again from the particle's own nearest body vertex (a walk from the last frame's)
    # where that is nearer than the walk's answer (Decision, `wrinkles._detail_signed_distance`'s own vertex)
    own_vertex: bool = True
    # S103 walks again from a tested parent's last face where a particle reads farther than the parent's reading
    # plus their distance apart (Decision, `wrinkles.avoid_penetration`'s Lipschitz check)
    recheck: bool = True
    penetration_iterations: int = 4  # S103 lifts per particle (one suffices on a flat body)
    # S103: where the linear lifts fail (n_i along the body, a particle caught in a crease), search
    # for a lift by doubling and bisection (`wrinkles._lift_out`). Off (fifty-second session): such a
    # particle keeps its height and `creases.leave_creases` moves it out, to the nearest point
    # outside (fewer vertices left deeper than 1 mm, fewer edges too long, and 0.4-0.5 ms less on
    # the walk's crouch; docs/history.md). Turn it on with creases=False
    lift_search: bool = False
    max_lift: float = 0.02  # m: S103 lifts a particle at most this far per frame
    max_height: float = 0.03  # m: Δh is clamped to this (wrinkles and lifts together) before the
    # S106 neighbour-distance rounds, which may raise a particle beyond it to keep an edge within d_max
    constraint_passes: int = 4  # S106 maximum-neighbour-distance rounds
    # S106 step 2: the steps on a compressed coarse edge are scaled to give back its deficit
    max_step_scale: float = 8.0  # the largest factor (beyond it the force clamp binds anyway)
    length_tolerance: float = 1e-3  # of the rest length: the arc length matched this closely
    length_iterations: int = 4  # arc-length evaluations per compressed coarse edge, at most
    # S106 step 5: a wrinkle on a compressed coarse edge widens into a fold to keep the maximum
    # neighbour distance (its neighbours rise), rather than coming down (Decision)
    widen_folds: bool = True
    # S106 step 6 as drawn: a compressed coarse edge's wrinkle is carried into its faces as a fold
    # running across the compression (Decision, `wrinkles.fold_across`); the carried Δh is the same
    # either way
    fold_across: bool = True
    # the folds run straight across each coarse quad to its opposite edge, where two facing wrinkles
    # of parallel edges join (False: every face's to its opposite corners, as in a lone triangle)
    fold_quads: bool = True
    # S103 as drawn: a particle left inside the body where two body parts overlap goes to the
    # nearest point outside both (Decision, `creases.leave_creases`; its Δh is unchanged)
    creases: bool = True
    crease_rounds: int = 2  # measurements and moves per such particle (a curved crease)
    # and the neighbours of a particle moved out of a crease are measured from its two faces, moved if
    # inside, and so on
    crease_spread: bool = True
    # then a particle near another body part (or found inside by S103, or behind another part's surface by
    # its walk there) that the body's winding number puts inside goes out along ±n_i, where the body ends
    # nearest (Decision, `creases.out_along_normals`)
    exit_normals: bool = True
    # and the neighbours of a particle the winding number puts inside are asked too, and theirs while they
    # are inside (Decision, `creases.out_along_normals`' spread)
    exit_spread: bool = True
    # and a particle found inside the frame before is asked again (Decision, `creases.out_along_normals`' memory)
    exit_memory: bool = True
    # and where no way out along ±n_i or through the nearest face is found, the nearest among the axes and
    # diagonals (Decision, `creases.out_along_normals`' around)
    exit_around: bool = True
    # m: how far along those it looks (Decision, `creases.out_along_normals`' around, 3 cm)
    exit_around_reach: float = EXIT_AROUND_REACH
    # and a particle S103 lifted that S106 lowered again by more than the clearance (Decision,
    # `creases.out_along_normals`' lowered after a lift)
    exit_lowered: bool = True
    # and a particle with another body part within 2 cm, whatever its normal's facing (Decision,
    # `creases.out_along_normals`' another part within a centimetre, `creases.EXIT_NEAR_ALONG`)
    exit_near_along: bool = True
    # and a particle whose normal faces into the body (n_i . n_body below 0), wherever the other parts are
    # (Decision, `creases.out_along_normals`' turned in)
    exit_turned: bool = True
    # and the coarse vertices too, moved along ±n_i or the way around within 1 cm (Decision,
    # `creases.out_along_normals`' coarse vertices)
    exit_coarse: bool = True
    # and a particle S106 lowered to within EXIT_LOWERED_NEAR of the body by S103's reading (Decision,
    # `creases.lowered_after_lift`'s lowered near the body)
    exit_lowered_near: bool = True
    # and a particle S103 lowered that S106 raised again by more than the clearance (Decision,
    # `creases.lowered_after_lift`'s raised after a lowering)
    exit_raised: bool = True

    def __post_init__(self):
        """A setting out of its range is named here, not met as a NaN or an index error in a kernel."""
        check_fields(self, integers={"level": 1, "penetration_iterations": 1, "constraint_passes": 1,
                                     "length_iterations": 1, "crease_rounds": 1},
                     non_negative=("tip_share", "face_margin") + (() if self.clearance is None else ("clearance",)),
                     positive=("contact_margin", "max_lift", "max_height", "length_tolerance", "exit_around_reach"))
        if not 1 <= self.max_step_scale < math.inf:
            raise ValueError(f"SurfaceSettings.max_step_scale must be >= 1 (the patent's step) and finite, "
                             f"got {self.max_step_scale!r}")

    @property
    def lift_clearance(self) -> float:
        """m, how far out of the body S103 lifts a detailed particle: `clearance`, or where that is None,
        CLEARANCE at level 6 and above and CLEARANCE x 6 / level below it (2 mm at level 3).

        Decision (the triangles' sag): S103 keeps the particles out of the body, not the triangles
        between them, and over a curved body a triangle's middle lies nearer to it than its corners
        by about its circumradius² / 2R (R: the body's radius of curvature there), four times as
        much at level 3 as at level 6. At 1 mm, level 3's triangles let the skin through in specks
        over the knees, shins and chest. Walk, casual outfit (T-shirt / jeans), triangles a frame
        with their centroid more than 0.5 mm inside the body: level 3 1.1 / 5.1 at 1 mm, 0.6 / 3.9
        at 2 mm, 0.5 / 3.2 at 4 mm; level 4 1.1 / 5.5 at 1 mm, 0.7 / 5.0 at 1.5 mm. The clearance
        grows with the size, not the sag: at 4 mm (the sag's share) level 3 had three times the
        edges too long (0.25 / 0.47 % against 0.08 / 0.16 %) and the jeans gave back 0.87 of
        their compressed length (0.98), as lifts along diverging normals part neighbours; at 2 mm
        0.10 / 0.21 % and 0.96. CLEARANCE (1 mm) was chosen at level 6: 2 mm there left more
        vertices deeper than 1 mm and more edges too long (docs/tried.md)."""
        if self.clearance is not None:
            return self.clearance
        return CLEARANCE * max(1.0, 6.0 / self.level)


@dataclass
class SurfaceModel:
    """What does not change: the tessellation, rest arc lengths, neighbour limits, material."""

    tess: Tessellation
    settings: SurfaceSettings
    cloth: ClothModel
    edge_rest: np.ndarray  # (E,) m: detailed arc length along each coarse edge at rest (S105 L_rest,e)
    edge_rest_coarse: np.ndarray  # (E,) m: straight length of each coarse edge at rest
    d_edges: np.ndarray  # (D, 2) int32 detailed mesh edges
    d_max: np.ndarray  # (D,) m: maximum neighbour distance per detailed edge
    edge_seg_max: np.ndarray  # (E, L) m: the same for each segment along each coarse edge
    d_edge_start: np.ndarray  # (N + 1,) int64: CSR of each detailed vertex's edges (into d_edges)
    d_edge_ids: np.ndarray  # int32
    k_out_plane: float
    h_normal: float
    transfer_exponent: float
    height_allowance: float  # (d_max² - rest²) / d_max² = 1 - 1/ratio²: S106 step 5 on stretched edges
    fold_src: np.ndarray  # (3, P, 2) int32: `wrinkles.fold_lines`, the folds across the compression
    fold_weight: np.ndarray  # (3, P, 2) float64
    fold_groups: np.ndarray  # (G, 2) int32: `wrinkles.fold_quads`, the faces drawn together (a quad's halves)
    fold_corner: np.ndarray  # (T,) int8
    fold_quad_edges: np.ndarray  # (T, 5) int32
    fold_quad_flip: np.ndarray  # (T, 5) uint8
    fold_quad_points: np.ndarray  # (3, Q) int32: `wrinkles.quad_lattice`
    fold_quad_rs: np.ndarray  # (3, Q, 2) int32
    d_tri_start: np.ndarray  # (N + 1,) int64: CSR of each detailed vertex's triangles (into tess.triangles)
    d_tri_ids: np.ndarray  # int32
    d_nbr_start: np.ndarray  # (N + 1,) int64: CSR of each detailed vertex's neighbours along the detailed edges
    d_nbr_ids: np.ndarray  # int32

    @property
    def n_vertices(self) -> int:
        return self.tess.n_vertices


def rest_surface(tess: Tessellation, rest_positions: np.ndarray) -> np.ndarray:
    """(N, 3) a garment's detailed surface at rest: PN over its rest particles, no heights (setup only)."""
    x = np.ascontiguousarray(rest_positions, dtype=np.float64)
    p, normals = np.zeros((tess.n_vertices, 3)), np.zeros((tess.n_vertices, 3))
    T = len(tess.coarse_triangles)
    pn_surface(tess, x, np.zeros((len(x), 3)), np.zeros((T, 10, 3)), np.zeros((T, 6, 3)), p, normals)
    return p


def build_surface_model(cloth: ClothModel, settings: SurfaceSettings | None = None) -> SurfaceModel:
    settings = settings or SurfaceSettings()
    n = cloth.n_particles
    tess = build_tessellation(cloth.triangles, n, settings.level)
    x = np.ascontiguousarray(cloth.rest_positions, dtype=np.float64)
    p_rest = rest_surface(tess, x)
    seg = np.linalg.norm(np.diff(p_rest[tess.edge_ids], axis=1), axis=2)
    edge_rest = seg.sum(axis=1)
    d_edges = tess.detail_edges
    rest_len = np.linalg.norm(p_rest[d_edges[:, 0]] - p_rest[d_edges[:, 1]], axis=1)
    f = cloth.fabric
    straight = np.linalg.norm(x[tess.coarse_edges[:, 0]] - x[tess.coarse_edges[:, 1]], axis=1)
    es, ei = vertex_cells(tess.n_vertices, d_edges)
    faces = cloth.faces if settings.fold_quads else np.full((0, 4), -1, dtype=np.int32)
    return SurfaceModel(tess, settings, cloth, edge_rest, straight, d_edges, f.max_neighbour_ratio * rest_len,
                        f.max_neighbour_ratio * seg, es, ei, f.k_out_plane, f.h_normal, f.transfer_exponent,
                        1.0 - 1.0 / f.max_neighbour_ratio**2, *fold_lines(tess.lattice, tess.level),
                        *fold_quads(tess.coarse_triangles, faces, tess.coarse_edges),
                        *quad_lattice(tess.lattice, tess.level), *vertex_cells(tess.n_vertices, tess.triangles),
                        *vertex_neighbours(tess.n_vertices, d_edges))


class SurfaceState:
    """Per-frame arrays of the detailed surface, preallocated."""

    def __init__(self, m: SurfaceModel):
        N, n, E, T = m.n_vertices, m.tess.n_coarse, len(m.tess.coarse_edges), len(m.tess.coarse_triangles)
        L1 = m.tess.level + 1
        self.p_smoothed = np.zeros((N, 3))  # S102 reference positions, m
        self.n_pn = np.zeros((N, 3))  # S102 PN normals
        self.p = np.zeros((N, 3))  # final positions, m
        self.normals = np.zeros((N, 3))  # S106 shading normals
        self.dh = np.zeros(N)  # Δh, carried to the next frame (Δh_last_frame)
        self.height = np.zeros(N)  # the drawn heights: Δh, or more in a fold across the compression
        self.fold_raised = np.zeros((2, 2 * len(m.tess.lattice)), dtype=np.int32)  # fold_across scratch
        self.fold_wrinkle = np.zeros((E, L1))  # fold_across: each compressed coarse edge's wrinkle along it
        self.fold_peak = np.zeros(E)  # and its highest
        self.dh_pen = np.zeros(N)  # S103 Δh_penetration
        self.sd = np.zeros(N)  # S103 signed distance of tested particles (inf: untested)
        self.facing = np.zeros(N)  # S103: n_i . n_body at each tested particle's closest body point
        self.other = np.zeros(N)  # S103: distance to the nearest other body part walked to (inf: none)
        self.behind = np.zeros(N, dtype=np.uint8)  # S103: 1 where a walk in another part found it behind that part
        self.lifted = np.zeros(N)  # S103: the heights after its lifts, m
        self.lowered = np.zeros(N, dtype=np.uint8)  # 1 where S106 lowered a particle S103 lifted (out_along_normals)
        self.body_face = np.full(N, -1, dtype=np.int32)  # S103: body face each particle's last walk ended on,
        self.part_face = np.full(N, -1, dtype=np.int32)  # and its last walk in another body part
        # S103: each particle's nearest body vertex by its last vertex walk (-1: none yet; empty: not kept)
        self.near_vertex = np.full(N if m.settings.own_vertex else 0, -1, dtype=np.int32)
        self.part_seeds = np.zeros((n, MAX_PART_SEEDS), dtype=np.int32)  # S103: other body parts near each
        self.seed_reach = np.zeros((n, MAX_PART_SEEDS))  # coarse particle (other_part_seeds)
        self.seed_count = np.zeros(n, dtype=np.int32)
        K = 3 * (MAX_PART_SEEDS + 1)  # S103 scratch: the body parts near a coarse face (part_groups)
        self.corners = np.zeros(3, dtype=np.int32)
        self.parts = np.zeros((K, 2), dtype=np.int32)
        self.reach = np.zeros(K)
        self.groups = np.zeros((K, 3), dtype=np.int32)
        self.group_reach = np.zeros((K, 3))
        self.part, self.part_vertex, self.part_d2 = part_scratch()  # other_part_seeds scratch
        self.floor = np.zeros(N)  # S106: the lowest and highest heights S103 allows
        self.ceiling = np.zeros(N)
        self.body_floor = np.zeros(N)  # S103: the lowest height the body allows (penetration_floor; cloth.layers)
        self.ef = np.zeros((N, 3))  # S104 elastic force, N
        self.vf = np.zeros(N)  # S104 normal force, N
        self.required = np.zeros(N)  # S105 ΔL_required,i, m
        self.edge_required = np.zeros(E)  # S105 ΔLE_required,e, m
        self.edge_deficit = np.zeros(E)  # S105: L_rest,e minus the reference surface's arc length, m
        self.edge_scale = np.zeros(E)  # S106 step 2: each compressed coarse edge's step factor
        self.flat_edge = np.zeros(E, dtype=np.uint8)  # S106 scratch: coarse edges inside a stretched region
        self.vertex_required = np.zeros(n)
        self.vertex_compressed = np.zeros(n)  # S105 scratch: compressed coarse edges per coarse vertex
        self.dh_def = np.zeros(N)  # S106 Δh_deformation
        self.expected = np.zeros(N)  # S106 ΔL_expected
        self.moved = np.zeros((2, N), dtype=np.int32)  # S106 constraint rounds: who moved in the last one
        self.stamp = np.zeros(N, dtype=np.int32)
        self.start_h = np.zeros(N)  # S106 constraint rounds: each listed particle's height before the round moved it
        self.fold = np.zeros(N, dtype=np.uint8)  # S106 constraint rounds: particles of a fold being widened
        self.coarse_normals = np.zeros((n, 3))
        self.coarse_force = np.zeros((n, 3))
        self.zero_v = np.zeros((n, 3))
        self.spring_work = spring_scratch(len(m.cloth.spring_i))
        self.edge_force = np.zeros((E, 2, 3))
        self.ctrl = np.zeros((T, 10, 3))
        self.nctrl = np.zeros((T, 6, 3))
        self.pn_scratch = np.zeros((7, m.tess.cubic.shape[1]))
        self.n_deform = np.zeros((N, 3))
        Q = len(m.tess.chain_ids)
        self.segments = np.zeros((3, Q), dtype=np.float32)  # S104 scratch: the chains' segments
        self.rates = np.zeros(Q, dtype=np.float32)  # S104 transfer rates along the chains
        self.edge_heights = np.zeros(L1)  # S106 step 2 scratch: the heights along one coarse edge
        self.f1 = np.zeros(3)
        self.fn = np.zeros(3)
        self.q = np.zeros(3)
        self.plane_a = np.zeros(6)  # leave_creases scratch
        self.plane_b = np.zeros(6)
        self.creased_ids = np.zeros(N, dtype=np.int32)  # leave_creases: the particles it moved (first
        self.crease_moves = np.zeros((N, 3))  # DetailedSurface.creased of them) and their moves, m
        self.crease_faces = np.zeros((N, 2), dtype=np.int32)  # leave_creases: the faces their walks ended on
        self.exit_ids = np.zeros(N, dtype=np.int32)  # out_along_normals: the particles it moved (first
        self.exit_moves = np.zeros((N, 3))  # DetailedSurface.exited of them) and their moves, m
        self.crease_seen = np.zeros(N, dtype=np.uint8)
        self.exit_seen = np.zeros(N, dtype=np.uint8)  # out_along_normals' spread: the particles asked,
        self.exit_inside = np.zeros(N, dtype=np.int32)  # and those found inside
        self.exit_was_inside = np.zeros(N, dtype=np.uint8)  # out_along_normals: 1 where it found the particle inside
        self.tree_stack = np.zeros(FACE_TREE_STACK, dtype=np.int32)  # out_along_normals' face-tree query scratch
        self.no_tips = np.zeros(0)  # S103 without the body's tip heights (DetailedSurface.step's face_tip None)
        # cover_body_tips: each body vertex's nearest tested particle (-1 between frames), the vertices listed
        self.tip_owner = np.zeros(0, dtype=np.int32)
        self.tip_owned = np.zeros(0, dtype=np.int32)


class DetailedSurface:
    def __init__(self, model: SurfaceModel):
        self.model = model
        self.state = SurfaceState(model)
        self.stage_seconds = np.zeros(3)  # PN, collision (S103), deformation (S104-S106)
        self.tested = 0  # particles S103 tested in the last frame
        self.creased = 0  # particles moved out of a crease in the last frame (`creases.leave_creases`)
        self.exited = 0  # particles moved out along ±n_i in the last frame (`creases.out_along_normals`)
        self.covered = 0  # body vertices whose detailed triangle S103 raised over them in the last frame

    def carry_heights_from(self, other: "DetailedSurface", afresh: bool = True) -> None:
        """Take over another level's surface of the same garment (a session changing its level of
        detail): its Δh, resampled onto this level's particles (`pn.resample_heights`), so the
        wrinkles stay where they were; the rest of the state (S103's walks, the moves out of the
        body) starts afresh, as on a session's first frame. In place: the state's arrays stay the
        ones a snapshot of it holds (`cloth.snapshot`), so a surface used before can be taken up again.
        afresh False: the state is fresh already (a surface just built), only Δh is set (5 ms less
        on the casual outfit at level 5)."""
        o, t = other.model.tess, self.model.tess
        if (o.n_coarse != t.n_coarse or o.coarse_triangles.shape != t.coarse_triangles.shape
                or not np.array_equal(o.coarse_triangles, t.coarse_triangles)):
            raise ValueError("carry_heights_from: the two surfaces are not over the same coarse triangles")
        if afresh:
            StateSnapshot(SurfaceState(self.model)).onto(self.state).restore()  # into the same arrays
        resample_heights(o.face_ids, o.level, t.owner_face, t.owner_weights, other.state.dh, self.state.dh)

    def step(self, x: np.ndarray, coarse_nearest: np.ndarray | None, body_x: np.ndarray | None,
             body: BodyMesh | None, face_n: np.ndarray | None, dt: float,
             grid: VertexGrid | None = None, face_tip: np.ndarray | None = None,
             winding: tuple | None = None, tree: tuple | None = None,
             vertex_tip: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """One frame of S102-S106 from the coarse positions x (n, 3); returns (positions, normals)
        of the detailed mesh (views of the state arrays, valid until the next step).

        body_x: the body's vertices in the body mesh's order (`BodyPose.x`, see BodyMesh.build);
        coarse_nearest: each coarse particle's nearest body vertex (the S103 walk seeds);
        face_n: the body's face normals for this pose (see collision.body_face_normals);
        grid: the body's vertex grid for this pose, through which S103 finds the other body
        parts near each coarse particle (None: S103 walks from the nearest vertex only);
        face_tip: how far each body face's corners stand out of their rings (`BodyPose.face_tip`;
        None: not at all); winding: the pose's winding grid (`WindingGrid.arrays()` over
        body.winding_faces), through which the moves out of creases leave a particle outside the
        body as a whole where it is (None: the tangent planes alone decide); tree: the pose's face
        tree (`FaceTree.arrays()` over the clothed faces), through whose nearest face a particle
        inside goes out where no way along ±n_i is near (None: it stays); vertex_tip: how far each
        body vertex stands out of its ring (`BodyPose.vertex_tip`, valid once `face_tips()` has run;
        None: no triangle is raised over the body's tips, `wrinkles.cover_body_tips`)."""
        m, s, t, st = self.model, self.state, self.model.tess, self.model.settings
        c = m.cloth
        clearance = st.lift_clearance
        t0 = time.perf_counter()
        # S102: reference surface, then the last frame's heights
        pn_surface(t, x, s.coarse_normals, s.ctrl, s.nctrl, s.p_smoothed, s.n_pn, s.pn_scratch)
        offset_along_normals(s.p_smoothed, s.n_pn, s.dh, s.p)
        t1 = time.perf_counter()
        # S103: penetration avoidance (body None: no body, nothing to avoid)
        if body is None:
            s.sd[:] = np.inf
            s.dh_pen[:] = 0.0
            s.behind[:] = 0
            self.tested = 0
        else:
            find_parts = grid is not None and st.other_parts
            if not find_parts:
                s.seed_count[:] = 0
            else:
                other_part_seeds(x, coarse_nearest, body_x, body.parts, *grid.detail_arrays(), s.part, s.part_vertex,
                                 s.part_d2, s.part_seeds, s.seed_reach, s.seed_count)
            if face_tip is None:
                if len(s.no_tips) != len(body.triangles):
                    s.no_tips = np.zeros(len(body.triangles))
                face_tip = s.no_tips
            self.tested = avoid_penetration(s.p, s.n_pn, s.dh, s.dh_pen, s.sd, s.facing, s.other, s.behind,
                                            t.face_ids, t.order, t.parents, s.ctrl, x, coarse_nearest, find_parts,
                                            s.part_seeds, s.seed_reach, s.seed_count, s.corners, s.parts, s.reach,
                                            s.groups, s.group_reach, body_x, body.nbr_start, body.nbr_ids, body.parts,
                                            body.triangles, body.tri_start, body.tri_ids, body.tri_nbrs, s.body_face,
                                            s.part_face, s.near_vertex, face_n, s.q, face_tip, st.tip_share,
                                            clearance, st.contact_margin, st.face_margin, st.penetration_iterations,
                                            st.max_lift, st.max_height, st.lift_search, st.height_reach,
                                            st.recheck)
        s.lifted[:] = s.dh
        penetration_floor(s.dh, s.sd, s.facing, s.other, s.dh_pen, clearance, st.contact_margin - clearance,
                          st.max_height, s.floor, s.ceiling, s.body_floor)
        self.covered = 0
        if body is not None and vertex_tip is not None and st.cover_tips and st.own_vertex:  # (S103's Decision)
            if len(s.tip_owner) != len(body_x):
                s.tip_owner = np.full(len(body_x), -1, dtype=np.int32)
                s.tip_owned = np.zeros(len(body_x), dtype=np.int32)
            self.covered = cover_body_tips(s.p, s.n_pn, s.dh, s.dh_pen, s.lifted, s.floor, s.ceiling, s.body_floor,
                                           s.sd, s.facing, s.other, s.body_face, s.part_face, s.near_vertex, body_x,
                                           body.triangles, body.tri_nbrs, body.tri_start, body.tri_ids, body.nbr_start,
                                           body.nbr_ids, body.parts, face_n, s.q, vertex_tip, t.triangles,
                                           m.d_tri_start, m.d_tri_ids, m.d_nbr_start, m.d_nbr_ids,
                                           s.tip_owner, s.tip_owned, clearance, st.max_height,
                                           body.winding_faces, *(NO_WINDING if winding is None else winding),
                                           winding is not None)
        t2 = time.perf_counter()
        # S104: elastic forces (coarse springs, reaction sign) spread over the surface, normal force
        s.coarse_force[:] = 0.0
        spring_forces(x, s.zero_v, c.spring_pairs, c.spring_params, s.spring_work, s.coarse_force)
        np.negative(s.coarse_force, out=s.coarse_force)
        coarse_edge_forces(x, t.coarse_edges, m.edge_rest_coarse, c.fabric.stretch_stiffness,
                           c.fabric.compression_stiffness, s.edge_force)
        elastic_forces(s.p, s.coarse_force, s.edge_force, t.edge_ids, t.line_start, t.chain_ids, m.transfer_exponent,
                       s.segments, s.rates, s.f1, s.fn, s.ef)
        normal_force(s.p, s.ef, m.d_edges, s.vf)
        # S105: length displacement
        length_displacement(s.p, s.p_smoothed, t.edge_ids, m.edge_rest, t.coarse_triangles, t.owner_face,
                            t.owner_weights, s.edge_required, s.edge_deficit, s.vertex_required, s.vertex_compressed,
                            s.required)
        # S106: deformation, constraints, positions, shading normals
        deformation_heights(s.vf, s.dh, s.required, m.d_edges, t.n_coarse, m.k_out_plane, dt, s.expected, s.dh_def)
        match_required_length(s.p_smoothed, s.n_pn, s.dh, s.dh_def, s.floor, s.vf, m.k_out_plane, dt, s.ceiling,
                              t.edge_ids, s.edge_required, m.edge_rest, m.edge_seg_max, m.height_allowance, t.face_ids,
                              t.face_edges, t.interior_local, st.max_step_scale, st.length_tolerance,
                              st.length_iterations, s.edge_scale, s.edge_heights)
        s.dh += s.dh_def
        apply_constraints(s.p_smoothed, s.n_pn, s.dh, s.floor, s.ceiling, t.face_ids, t.face_edges, s.edge_required,
                          s.edge_deficit, t.edge_ids, t.interior_local, m.d_edges, m.d_max, m.height_allowance,
                          m.d_edge_start, m.d_edge_ids, st.constraint_passes, st.max_height, s.flat_edge, s.moved,
                          s.stamp, s.start_h, st.widen_folds, s.fold, s.p)
        if st.fold_across:
            fold_across(s.p_smoothed, s.n_pn, s.dh, s.floor, s.ceiling, t.face_ids, t.face_edges, t.edge_ids,
                        s.edge_required, t.interior_local, m.fold_src, m.fold_weight, m.fold_groups, m.fold_corner,
                        m.fold_quad_edges, m.fold_quad_flip, m.fold_quad_points, m.fold_quad_rs, m.d_edges, m.d_max,
                        m.d_edge_start, m.d_edge_ids, m.height_allowance, s.fold_wrinkle, s.fold_peak, s.fold_raised,
                        s.height, s.p)
        else:
            s.height[:] = s.dh
        self.creased = self.exited = 0
        t4 = time.perf_counter()
        if body is not None and st.creases:  # (S103's Decision, counted with its time)
            self.creased = leave_creases(s.p, s.sd, s.body_face, s.part_face, body_x, body.triangles, body.tri_nbrs,
                                         body.tri_start, body.tri_ids, body.nbr_start, body.nbr_ids, body.parts,
                                         face_n, s.q, s.plane_a, s.plane_b, clearance, st.crease_rounds,
                                         t.n_coarse, st.crease_spread, m.d_edges, m.d_edge_start, m.d_edge_ids,
                                         s.crease_seen, s.creased_ids, s.crease_moves, s.crease_faces,
                                         body.wound_faces, body.winding_faces,
                                         *(NO_WINDING if winding is None else winding),
                                         winding is not None)
        if body is not None and winding is not None and st.exit_normals:  # (the same Decision's time)
            # (off: lowered by more than infinity, none)
            lowered_after_lift(s.dh_pen, s.lifted, s.height, clearance if st.exit_lowered else np.inf, s.lowered,
                               s.sd, EXIT_LOWERED_NEAR if st.exit_lowered_near else -np.inf,
                               clearance if st.exit_raised else np.inf)
            self.exited = out_along_normals(s.p, s.n_pn, s.sd, s.other, s.facing, s.behind, s.lowered, t.n_coarse,
                                            EXIT_NEAR, EXIT_FACING, EXIT_NEAR_ALONG if st.exit_near_along else 0.0,
                                            EXIT_TURNED if st.exit_turned else -np.inf,
                                            EXIT_REACH, clearance, body_x,
                                            body.winding_faces, *winding,
                                            s.exit_ids, s.exit_moves, 0.0 if tree is None else EXIT_FACE_REACH,
                                            body.triangles, face_n, *(NO_FACE_TREE if tree is None else tree),
                                            s.tree_stack, s.q, s.body_face, st.exit_spread, m.d_edges,
                                            m.d_edge_start, m.d_edge_ids, s.exit_seen, s.exit_inside,
                                            s.exit_was_inside, st.exit_memory,
                                            EXIT_DIRECTIONS if st.exit_around else NO_DIRECTIONS,
                                            st.exit_around_reach, st.exit_coarse)
        t5 = time.perf_counter()
        shading_normals(s.p, t.triangles, s.n_pn, s.height, m.h_normal, s.n_deform, s.normals)
        t3 = time.perf_counter()
        self.stage_seconds[:] = (t1 - t0, t2 - t1 + t5 - t4, t3 - t2 - (t5 - t4))
        return s.p, s.normals


__all__ = ["DetailedSurface", "SurfaceModel", "SurfaceSettings", "SurfaceState", "build_surface_model", "rest_surface"]
