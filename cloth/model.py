"""A garment's coarse cloth model: what does not change during a session (built once).

Particles, faces, springs with rest lengths and stiffnesses, masses, the fabric, the
substep count, and the map from the authored garment onto the coarse mesh.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .coarsen import CoarseMesh, coarsen
from .collision import ALL_REGIONS, REGION_DTYPE
from .dynamics import spring_table, stable_time_step
from .fabric import Fabric
from .garment import Garment
from .topology import boundary_loops, triangulate, unique_edges

STRUCTURAL, SHEAR, BENDING = 0, 1, 2


def check_fields(settings, integers: dict[str, int] | None = None, non_negative: tuple = (),
                 positive: tuple = ()) -> None:
    """Raise a ValueError naming `Class.field` for a settings field out of its range: integers
    {field: the lowest allowed}; non_negative and positive: finite numbers >= 0 and > 0 (NaN is
    out of range)."""
    name = type(settings).__name__
    for key, low in (integers or {}).items():
        value = getattr(settings, key)
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"{name}.{key} must be an integer >= {low}, got {value!r}")
    for keys, strict in ((non_negative, False), (positive, True)):
        for key in keys:
            value = getattr(settings, key)
            number = isinstance(value, (int, float, np.number)) and not isinstance(value, bool)
            if not (number and (0 < value if strict else 0 <= value) and value < math.inf):
                raise ValueError(f"{name}.{key} must be {'>' if strict else '>='} 0 and finite, got {value!r}")


@dataclass(frozen=True)
class SimSettings:
    frame_rate: float = 60.0  # frames per second the substep count is chosen for
    substeps: int | None = None  # None: the fewest stable ones for the fabric (see stable_time_step)
    collide_every: int = 1  # vertex collision after every n-th substep, and always after the last
    gravity: float = 9.81  # m/s², along -Y
    follow_near: float = 0.01  # m: particles this close to the body follow it fully
    # m: particles farther away do not follow it. 6 cm, not 4: the gentler blend flutters less
    # (the walk, 300 frames: frame-to-frame second difference above 5 cm on the elegant
    # outfit's blouse 97 → 67 particle-frames, T-shirt's p99 14.3 → 12.8 mm; with follow_easing)
    follow_far: float = 0.06
    # s: time constant at which a particle's following weight eases towards the distance blend
    # (collision.follow_body); 0: taken at once. 24 ms: half way in a 60 Hz frame
    follow_easing: float = 0.024
    max_speed: float = 30.0  # m/s: a faster particle is treated as exploded
    max_stretch: float = 3.0  # a structural spring longer than this times rest marks an explosion
    # strain-limiting passes after the last substep (one after each other substep), and after the contact
    # pass with its placed particles held. 8 and 6 (seventy-fourth session, again in the seventy-ninth) give
    # every row's strain p99 0.0-1.6 points lower (11 of the 18 clip x garment rows within 10 %, 10 with
    # these) for 4-6 % more S101 and larger largest strains on some rows; 16 and 12 no lower than 8 and 6:
    # what is left is held by the contact (docs/cloth.md)
    limit_passes: int = 4
    # free strain-limiting passes after the contact pass, then a second one for what slid (0: neither)
    slide_passes: int = 1
    contact_limit_passes: int = 2
    final_contact: bool = True  # after those, the contact pass again for the particles they moved
    # m: a contact-pass result nearer than this is checked against every clothed body face
    # (collision.FaceTree: the other sheet of a fold); 0: off. Off by default since the union
    # pass goes out through the nearest face the particle is behind: a particle behind a fold's
    # other sheet is inside the body as a whole, and the union pass finds it by its winding
    # number and puts it out through that sheet, for a tree query per inside particle instead
    # of one per particle in contact (the first contact pass 560 -> 280 µs per garment-frame;
    # acceptance, 18 rows: no frame with a particle deeper than 1 mm, as before). 8 cm where
    # it is on: where skinning sinks a limb into the skin under the cloth a particle can lie
    # 2-6 cm inside with the nearest vertex's ring saying "outside" by up to 7 cm
    nearest_face_radius: float = 0.0
    # which contact stages run `collision.leave_body_union` (out of the body as a whole, where a
    # face buried in another part hides the inside from the ring tests; builds the face tree):
    # 0 none, 1 after the last contact pass, 2 also before the contact strain-limiting passes.
    # On since the body's skin contact (skinning.contact) keeps the skin from sinking into
    # itself at bent joints: what is left inside is shallow and the pushes no longer stretch the
    # cloth (acceptance, 18 rows: frames with a particle > 1 mm inside 3,099 -> 674, strain p99
    # within the cloth's noise). Without the skin contact the particles came back inside every
    # frame, 2-8 cm deep in the folds, and each push stretched the cloth (docs/history.md).
    union_passes: int = 2
    target_particles: int = 320  # coarse model size (SPEC.md table: 322-430)

    def __post_init__(self):
        """A setting out of its range is named here, not met as a NaN or a stalled loop in a kernel."""
        sub = self.substeps
        if sub is not None and (isinstance(sub, bool) or not isinstance(sub, (int, np.integer)) or sub < 1):
            raise ValueError(f"SimSettings.substeps must be None or an integer >= 1, got {sub!r}")
        check_fields(self, integers={"collide_every": 1, "limit_passes": 0, "slide_passes": 0,
                                     "contact_limit_passes": 0, "target_particles": 4},
                     positive=("frame_rate", "max_speed"),
                     non_negative=("follow_near", "follow_easing", "nearest_face_radius"))
        if not self.follow_near < self.follow_far < math.inf:
            raise ValueError(f"SimSettings.follow_far must be > follow_near ({self.follow_near!r} m) and finite, "
                             f"got {self.follow_far!r}")
        if not 1 < self.max_stretch < math.inf:
            raise ValueError(f"SimSettings.max_stretch must be > 1 (a ratio to the rest length), "
                             f"got {self.max_stretch!r}")
        if not math.isfinite(self.gravity):
            raise ValueError(f"SimSettings.gravity must be finite, got {self.gravity!r}")
        if self.union_passes not in (0, 1, 2):
            raise ValueError(f"SimSettings.union_passes must be 0, 1 or 2, got {self.union_passes!r}")

    @property
    def needs_face_tree(self) -> bool:
        """Whether the body pose must keep the face tree (the contact pass's fold query or the
        union pass reads it)."""
        return self.nearest_face_radius > 0 or self.union_passes > 0


@dataclass
class ClothModel:
    name: str
    fabric: Fabric
    settings: SimSettings
    rest_positions: np.ndarray  # (n, 3) float64 m, rest pose, intersections resolved
    faces: np.ndarray  # (m, 4) int32 quads and triangles (-1 padded)
    triangles: np.ndarray  # (t, 3) int32: quads split along the shorter diagonal at rest
    mass: np.ndarray  # (n,) kg
    inv_mass: np.ndarray  # (n,)
    drag: np.ndarray  # (n,) N·s/m = air_drag * area per particle
    spring_i: np.ndarray  # (s,) int32
    spring_j: np.ndarray  # (s,) int32
    spring_kind: np.ndarray  # (s,) int8: STRUCTURAL, SHEAR, BENDING
    rest_length: np.ndarray  # (s,)
    k_stretch: np.ndarray  # (s,) N/m
    k_compress: np.ndarray  # (s,) N/m
    c_stretch: np.ndarray  # (s,) N·s/m
    c_compress: np.ndarray  # (s,) N·s/m
    spring_pairs: np.ndarray  # (s, 2) int32: the force kernel's packed copy (see dynamics.spring_table)
    spring_params: np.ndarray  # (s, 5)
    substeps: int
    stable_dt: float
    n_structural: int  # the structural springs come first in the spring arrays (strain limiting)
    grip: np.ndarray  # (n,) uint8: 1 for particles that grip the body (a waistband), kinematic
    region_mask: np.ndarray  # (n,) REGION_DTYPE: body regions each particle may touch (BodyMesh.regions bits)
    boundary_loops: list[np.ndarray] = field(default_factory=list)
    coarse: CoarseMesh | None = None  # authored-garment map (fine_triangle, fine_bary)

    @property
    def n_particles(self) -> int:
        return len(self.rest_positions)

    def substeps_for(self, dt: float) -> int:
        """Configured substeps, or more if a longer frame would be unstable."""
        return max(self.substeps, math.ceil(dt / self.stable_dt - 1e-9))


def _bending_pairs(triangles: np.ndarray, quad_diagonals: set) -> np.ndarray:
    """For every interior edge of the triangulation, the two vertices opposite it (not a quad's diagonal)."""
    owner: dict[tuple[int, int], list[int]] = {}
    for tri in triangles:
        for k in range(3):
            a, b, c = int(tri[k]), int(tri[(k + 1) % 3]), int(tri[(k + 2) % 3])
            owner.setdefault((min(a, b), max(a, b)), []).append(c)
    pairs = [(min(o), max(o)) for e, o in owner.items() if len(o) == 2 and e not in quad_diagonals and o[0] != o[1]]
    return np.unique(np.asarray(pairs, dtype=np.int64).reshape(-1, 2), axis=0)


def _areas(vertices, faces):
    """Per-face area (quads as two triangles) and per-vertex share (face area / corner count)."""
    tris, src = triangulate(faces, vertices)
    t = vertices[tris]
    ta = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
    face_area = np.bincount(src, ta, minlength=len(faces))
    corners = (faces >= 0).sum(axis=1)
    vert_area = np.zeros(len(vertices))
    for k in range(4):
        ok = faces[:, k] >= 0
        np.add.at(vert_area, faces[ok, k], face_area[ok] / corners[ok])
    return face_area, vert_area


def build_springs(vertices: np.ndarray, faces: np.ndarray, fabric: Fabric):
    """Structural (every polygon edge), shear (both quad diagonals) and bending springs.

    Stiffness per spring from the fabric's 2D moduli (N/m): k = E * A_e / L², where A_e is the
    area the spring stands for (twice the share of its faces' areas per edge); a regular grid of
    squares gets k = E. Damping c = 2 ζ sqrt(k m_ij) with the pair's reduced mass."""
    edges, _ = unique_edges(faces)
    face_area, vert_area = _areas(vertices, faces)
    n_edges_face = (faces >= 0).sum(axis=1)
    edge_area: dict[tuple[int, int], float] = {}
    for f, face in enumerate(faces):
        ring = face[face >= 0]
        for a, b in zip(ring, np.roll(ring, -1)):
            key = (int(min(a, b)), int(max(a, b)))
            edge_area[key] = edge_area.get(key, 0.0) + 2.0 * face_area[f] / n_edges_face[f]
    quads = faces[faces[:, 3] >= 0]
    diag = np.concatenate([quads[:, [0, 2]], quads[:, [1, 3]]])
    diag = np.sort(diag, axis=1)
    diag_area = np.concatenate([face_area[faces[:, 3] >= 0]] * 2)
    tris, _ = triangulate(faces, vertices)
    bend = _bending_pairs(tris, {(int(a), int(b)) for a, b in diag})

    def length(p):
        return np.linalg.norm(vertices[p[:, 0]] - vertices[p[:, 1]], axis=1)

    l_e, l_d, l_b = length(edges), length(diag), length(bend)
    a_e = np.array([edge_area[(int(a), int(b))] for a, b in edges])
    # The area factors are clipped: a sliver face would otherwise make one spring far stiffer
    # than the rest, and the stiffest spring sets the explicit time step.
    f_e = np.clip(a_e / l_e**2, 0.5, 1.5)
    k_e = fabric.stretch_stiffness * f_e
    kc_e = fabric.compression_stiffness * f_e
    k_d = fabric.shear_stiffness * np.clip(diag_area / l_d**2, 0.25, 0.75)
    k_b = np.full(len(bend), fabric.bending_stiffness)
    pairs = np.concatenate([edges, diag, bend]).astype(np.int32)
    kind = np.concatenate([np.full(len(edges), STRUCTURAL), np.full(len(diag), SHEAR),
                           np.full(len(bend), BENDING)]).astype(np.int8)
    rest = np.concatenate([l_e, l_d, l_b])
    ks = np.concatenate([k_e, k_d, k_b])
    kc = np.concatenate([kc_e, k_d, k_b])
    # Lumped mass per particle, floored at half the median: a particle at a sharp hem corner
    # has little area, and the lightest particle would otherwise set the time step.
    mass = fabric.density * np.maximum(vert_area, 0.5 * np.median(vert_area))
    m_red = mass[pairs[:, 0]] * mass[pairs[:, 1]] / (mass[pairs[:, 0]] + mass[pairs[:, 1]])
    cs = 2.0 * fabric.damping_ratio * np.sqrt(ks * m_red)
    cc = 2.0 * fabric.damping_ratio * np.sqrt(kc * m_red)
    return pairs, kind, rest, ks, kc, cs, cc, mass, vert_area


def build_cloth_model(garment: Garment, fabric: Fabric, settings: SimSettings | None = None,
                      rest_positions: np.ndarray | None = None, coarse: CoarseMesh | None = None) -> ClothModel:
    """Coarsen a garment and build its springs.

    rest_positions: the coarse particles with the body's intersections already resolved
    (see `ClothSim.fit`); rest lengths are measured on them."""
    settings = settings or SimSettings()
    coarse = coarse or coarsen(garment.vertices, garment.faces, settings.target_particles)
    verts = coarse.vertices if rest_positions is None else np.asarray(rest_positions, dtype=np.float64)
    faces = coarse.faces
    pairs, kind, rest, ks, kc, cs, cc, mass, area = build_springs(verts, faces, fabric)
    if np.any(rest <= 0) or np.any(mass <= 0):
        raise ValueError(f"{garment.name}: degenerate coarse mesh (zero-length spring or zero-area particle)")
    inv_mass = 1.0 / mass
    si, sj = pairs[:, 0].copy(), pairs[:, 1].copy()
    dt = stable_time_step(verts, inv_mass, si, sj, ks, fabric.max_strain, fabric.damping_ratio)
    substeps = settings.substeps or max(1, math.ceil(1.0 / settings.frame_rate / dt))
    tris, _ = triangulate(faces, verts)
    pairs_packed, params_packed = spring_table(si, sj, rest, ks, kc, cs, cc)
    return ClothModel(
        name=garment.name, fabric=fabric, settings=settings, rest_positions=verts.copy(), faces=faces,
        triangles=tris, mass=mass, inv_mass=inv_mass, drag=fabric.air_drag * area, spring_i=si, spring_j=sj,
        spring_kind=kind, rest_length=rest, k_stretch=ks, k_compress=kc, c_stretch=cs, c_compress=cc,
        spring_pairs=pairs_packed, spring_params=params_packed,
        substeps=substeps, stable_dt=dt, n_structural=int(np.sum(kind == STRUCTURAL)),
        grip=np.zeros(len(verts), dtype=np.uint8),
        region_mask=np.full(len(verts), ALL_REGIONS, dtype=REGION_DTYPE), boundary_loops=boundary_loops(faces),
        coarse=coarse,
    )
