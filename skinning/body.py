"""The character's body: MakeHuman base mesh, its CMU skeleton and skin weights.

Everything internal is metres, Y up, character facing +Z (MakeHuman files are
decimetres with the same axes). All 19,158 vertices of base.obj are kept in file
order: garments are fitted to helper vertices, and every index file refers to
that order. Only the `body` group is visible and used for collision/drawing.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .data import data_dir
from .obj import MeshFormatError, read_obj, split_polygons
from .skeleton import CMU_BONES, Skeleton, bone_tails, cmu_parents

MAKEHUMAN_UNIT_M = 0.1  # 1 MakeHuman unit = 1 decimetre


@dataclass(frozen=True)
class Body:
    vertices: np.ndarray  # (n, 3) float64, rest pose, metres: all base.obj vertices, file order
    n_visible: int  # vertices [0, n_visible) form the visible skin
    triangles: np.ndarray  # (m, 3) int32, visible skin, quads split along the shorter diagonal
    skeleton: Skeleton  # character skeleton, rest pose, metres
    weight_bones: np.ndarray  # (n, K) int32 bone index per influence (padding: bone 0, weight 0)
    weight_values: np.ndarray  # (n, K) float64, each row sums to 1
    floor_y: float  # lowest visible vertex at rest: the soles

    @property
    def visible_vertices(self) -> np.ndarray:
        return self.vertices[: self.n_visible]


def _group_centroid(mesh, name: str, path: Path) -> np.ndarray:
    if name not in mesh.group_names:
        raise MeshFormatError(f"{path}: joint cube group {name!r} not found")
    return mesh.vertices[mesh.group_vertex_ids(name)].mean(axis=0)


def _rig_point(spec: dict, mesh, obj_path: Path, rig_path: Path, where: str) -> np.ndarray:
    strategy = spec.get("strategy")
    if strategy == "CUBE":
        return _group_centroid(mesh, spec["cube_name"], obj_path)
    if strategy == "MEAN":
        ids = np.asarray(spec["vertex_indices"], dtype=np.int64)
        if ids.size == 0 or ids.min() < 0 or ids.max() >= len(mesh.vertices):
            raise MeshFormatError(f"{rig_path}: {where}: vertex_indices out of range")
        return mesh.vertices[ids].mean(axis=0)
    if strategy == "VERTEX":
        return mesh.vertices[int(spec["vertex_index"])]
    raise MeshFormatError(f"{rig_path}: {where}: unknown strategy {strategy!r}")


def load_weights(path: Path, names: tuple[str, ...], n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Read an MPFB2/MakeHuman weights JSON into padded (n, K) arrays, rows normalised."""
    try:
        doc = json.loads(path.read_text())
        table = doc["weights"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise MeshFormatError(f"{path}: not a weights file: {exc}") from exc
    per_vertex: list[list[tuple[int, float]]] = [[] for _ in range(n_vertices)]
    for bone, pairs in table.items():
        if bone not in names:
            raise MeshFormatError(f"{path}: bone {bone!r} is not in the skeleton")
        for vid, w in pairs:
            vid = int(vid)
            if not 0 <= vid < n_vertices:
                raise MeshFormatError(f"{path}: bone {bone!r}: vertex {vid} out of range (< {n_vertices})")
            if w > 0:
                per_vertex[vid].append((names.index(bone), float(w)))
    k = max(1, max(len(p) for p in per_vertex))
    bones = np.zeros((n_vertices, k), dtype=np.int32)
    values = np.zeros((n_vertices, k), dtype=np.float64)
    for v, pairs in enumerate(per_vertex):
        if not pairs:
            raise MeshFormatError(f"{path}: vertex {v} has no weight")
        for j, (b, w) in enumerate(pairs):
            bones[v, j] = b
            values[v, j] = w
    values /= values.sum(axis=1, keepdims=True)
    return bones, values


def load_body(data: str | Path | None = None) -> Body:
    """Load the MakeHuman body with the 31-bone CMU skeleton from `<data>/body/`."""
    root = data_dir(data) / "body"
    obj_path = root / "base.obj"
    rig_path = root / "mpfb2_rig.cmu_mb.json"
    mesh = read_obj(obj_path)
    try:
        rig = json.loads(rig_path.read_text())
    except (OSError, ValueError) as exc:
        raise MeshFormatError(f"{rig_path}: cannot read rig: {exc}") from exc

    heads = np.zeros((len(CMU_BONES), 3))
    for b, name in enumerate(CMU_BONES):
        if name not in rig:
            raise MeshFormatError(f"{rig_path}: bone {name!r} missing")
        heads[b] = _rig_point(rig[name]["head"], mesh, obj_path, rig_path, f"{name}.head")
    ends = {b: _rig_point(rig[n]["tail"], mesh, obj_path, rig_path, f"{n}.tail") for b, n in enumerate(CMU_BONES)}
    parents = cmu_parents()
    scale = MAKEHUMAN_UNIT_M
    heads *= scale
    ends = {b: p * scale for b, p in ends.items()}
    skeleton = Skeleton(CMU_BONES, parents, heads, bone_tails(CMU_BONES, parents, heads, ends))

    vertices = mesh.vertices * scale
    body_faces = mesh.group_faces("body")
    n_visible = int(max(max(f) for f in body_faces)) + 1
    triangles = split_polygons(body_faces, vertices)
    bones, values = load_weights(root / "mpfb2_weights.cmu_mb.json", CMU_BONES, len(vertices))
    return Body(
        vertices=vertices,
        n_visible=n_visible,
        triangles=triangles,
        skeleton=skeleton,
        weight_bones=bones,
        weight_values=values,
        floor_y=float(vertices[:n_visible, 1].min()),
    )


# Each region is a body part the cloth's collision walks over on its own; where two regions
# meet (the hip crease, the armpit, behind the knee) a particle near both is tested against
# each. The legs are split at the knee: behind a bent knee the thigh's and the calf's skins
# form a crease, and a walk over one leg stops on the thigh while a detailed cloth vertex
# is inside the calf (walk, jeans: detailed vertex-frames deeper than 1 mm 29,563 -> 22,940).
# The arms are split at the elbow for the same reason: in the walk's crouch, a hand at the face,
# the forearm folds onto the upper arm inside the sleeve (docs/surface.md).
# And the feet at the ankle: in a squat the flexed ankle folds the top of the foot into the
# shin, under a trouser leg's hem, where a walk over the shin stops outside it.
# One bit each, in 16-bit masks (REGION_DTYPE).
BODY_REGIONS = {
    "torso": 1,
    "left_upper_arm": 2,
    "right_upper_arm": 4,
    "left_thigh": 8,
    "right_thigh": 16,
    "left_lower_leg": 32,
    "right_lower_leg": 64,
    "left_forearm": 128,  # with the hand
    "right_forearm": 256,
    "left_foot": 512,  # with the toes
    "right_foot": 1024,
}
REGION_DTYPE = np.uint16
# each arm's regions, upper arm and forearm (with the hand): one sleeve covers both
# (`cloth.collision.BodyMesh.build`'s limbs)
ARM_LIMBS = (BODY_REGIONS["left_upper_arm"] | BODY_REGIONS["left_forearm"],
             BODY_REGIONS["right_upper_arm"] | BODY_REGIONS["right_forearm"])
ARM_REGIONS = ARM_LIMBS[0] | ARM_LIMBS[1]
# each leg's lower leg and foot: one trouser leg covers both, and S101 walks them as one region
LEG_LIMBS = (BODY_REGIONS["left_lower_leg"] | BODY_REGIONS["left_foot"],
             BODY_REGIONS["right_lower_leg"] | BODY_REGIONS["right_foot"])
_REGION_BONES = {
    "left_upper_arm": ("LeftArm",),
    "right_upper_arm": ("RightArm",),
    "left_forearm": ("LeftForeArm", "LeftHand", "LeftFingerBase", "LeftHandFinger1", "LThumb"),
    "right_forearm": ("RightForeArm", "RightHand", "RightFingerBase", "RightHandFinger1", "RThumb"),
    "left_thigh": ("LeftUpLeg",),
    "right_thigh": ("RightUpLeg",),
    "left_lower_leg": ("LeftLeg",),
    "right_lower_leg": ("RightLeg",),
    "left_foot": ("LeftFoot", "LeftToeBase"),
    "right_foot": ("RightFoot", "RightToeBase"),
}


# bones whose skin no garment covers: the head and face, the hands, the toes (small, many
# triangles: 17,000 of the body's 26,756)
HAND_BONES = ("LeftHand", "LeftFingerBase", "LeftHandFinger1", "LThumb", "RightHand", "RightFingerBase",
              "RightHandFinger1", "RThumb")
UNCLOTHED_BONES = ("Head", *HAND_BONES, "LeftToeBase", "RightToeBase")


def body_clothed_faces(body: Body) -> np.ndarray:
    """(n_triangles,) bool: the faces a garment can cover, i.e. not all three corners dominated by
    a bone of the head, the hands or the toes."""
    return ~_faces_of(body, UNCLOTHED_BONES)


def body_hand_faces(body: Body, reach: float | None = None) -> np.ndarray:
    """(n_triangles,) bool: the faces of the hands, i.e. all three corners dominated by a bone of
    a hand (HAND_BONES); given `reach` (m), only those whose corners all lie within it of the
    wrist (the corners the hand's faces share with the clothed ones) on the body at rest."""
    hand = _faces_of(body, HAND_BONES)
    if reach is None:
        return hand
    wrist = np.intersect1d(body.triangles[hand], body.triangles[body_clothed_faces(body)])
    x = np.asarray(body.vertices[: body.n_visible], dtype=np.float64)
    corners = np.unique(body.triangles[hand])
    near = np.zeros(body.n_visible, dtype=bool)
    if len(wrist):
        d2 = ((x[corners][:, None, :] - x[wrist][None, :, :]) ** 2).sum(axis=2).min(axis=1)
        near[corners] = d2 < reach * reach
    return hand & near[body.triangles].all(axis=1)


def _faces_of(body: Body, bones: tuple[str, ...]) -> np.ndarray:
    """(n_triangles,) bool: the faces all three of whose corners are dominated by one of `bones`."""
    names = body.skeleton.names
    wanted = np.zeros(len(names), dtype=bool)
    wanted[[names.index(b) for b in bones if b in names]] = True
    vis = np.arange(body.n_visible)
    dominant = body.weight_bones[vis, np.argmax(body.weight_values[vis], axis=1)]
    return wanted[dominant][body.triangles].all(axis=1)


def body_regions(body: Body) -> np.ndarray:
    """(n_visible,) REGION_DTYPE region bit per visible vertex (BODY_REGIONS), from its dominant bone."""
    names = body.skeleton.names
    bone_region = np.full(len(names), BODY_REGIONS["torso"], dtype=REGION_DTYPE)
    for region, bones in _REGION_BONES.items():
        for b in bones:
            if b in names:
                bone_region[names.index(b)] = BODY_REGIONS[region]
    vis = np.arange(body.n_visible)
    dominant = body.weight_bones[vis, np.argmax(body.weight_values[vis], axis=1)]
    return bone_region[dominant]
