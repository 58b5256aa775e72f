"""Hand clearance: a hand the retargeted motion sinks into the character's body is turned out of it.

The character is broader than most captured people, so a hand the person rests on her hip, or
lets hang against her thigh, lands inside the character's hip or thigh: on the CMU walk the whole
left hand (1,500 of its 1,595 vertices) lies inside the hip for a third of the clip. The arm
clearance (`retarget.keep_arm_clear`) keeps the elbow and the wrist a few degrees out from a
hanging arm's line, but the hand on the hip bends in from the wrist.

Here the body is skinned once with the retargeted pose; then each hand's points (its vertices,
one per `sample` cube at rest) are tested against the clothed skin of the body's other parts
(torso and legs; not the arms, nor the head: a hand on the face is no garment's business). A
point is `margin` in front of the skin when its offset from the nearest of those vertices,
along that vertex's normal, is at least `margin`. If a point is not, the whole arm turns
outwards about the chest's forward axis, through the shoulder joint, as the arm clearance turns
it, by the smallest angle (found by bisection) that puts every point in front. A turn about
that axis keeps the elbow's and the wrist's angles: the hand keeps its shape and rests on the
hip, a garment's thickness away from the skin. The turn is 0 until the hand comes within
`margin` of the skin and grows continuously with the depth. A hand that needs more than
`max_turn_deg` is held there on purpose (on the belly, at the neck) and is left alone; the turn
fades out from two thirds of that, so that it stays continuous.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from .body import ARM_REGIONS, UNCLOTHED_BONES, Body, body_regions
from .ik_kernels import smooth_fade
from .skeleton import Skeleton
from .skin import MeshNormals

HAND_BONES = {"left": ("LeftHand", "LeftFingerBase", "LeftHandFinger1", "LThumb"),
              "right": ("RightHand", "RightFingerBase", "RightHandFinger1", "RThumb")}
ARM_BONES = {"left": "LeftArm", "right": "RightArm"}


@dataclass(frozen=True)
class HandSettings:
    margin: float = 0.006  # m kept between a hand and the skin of the body's other parts
    # the largest turn: a hand that needs more is left where it is (the turn fades out from 2/3 of this)
    max_turn_deg: float = 45.0
    sample: float = 0.01  # m, spacing at rest of the hand points tested
    near: float = 0.08  # m: a hand point farther than this from every body vertex is clear
    bisections: int = 10  # halvings of the turn's interval (45 deg -> 0.04 deg)

    def __post_init__(self):
        for key in ("margin", "sample", "near"):
            if not getattr(self, key) > 0:
                raise ValueError(f"HandSettings.{key} must be > 0, got {getattr(self, key)!r}")
        if not 0 < self.max_turn_deg <= 90:
            raise ValueError(f"HandSettings.max_turn_deg must be in (0, 90], got {self.max_turn_deg!r}")
        if not isinstance(self.bisections, int) or self.bisections < 1:
            raise ValueError(f"HandSettings.bisections must be an integer >= 1, got {self.bisections!r}")


@njit(cache=True, nogil=True)
def turned(p, s, axis, angle, out):
    """out = p rotated by `angle` (rad) about the unit `axis` through s (Rodrigues)."""
    c, sn = np.cos(angle), np.sin(angle)
    rx, ry, rz = p[0] - s[0], p[1] - s[1], p[2] - s[2]
    dot = axis[0] * rx + axis[1] * ry + axis[2] * rz
    cx = axis[1] * rz - axis[2] * ry
    cy = axis[2] * rx - axis[0] * rz
    cz = axis[0] * ry - axis[1] * rx
    out[0] = s[0] + rx * c + cx * sn + axis[0] * dot * (1.0 - c)
    out[1] = s[1] + ry * c + cy * sn + axis[1] * dot * (1.0 - c)
    out[2] = s[2] + rz * c + cz * sn + axis[2] * dot * (1.0 - c)


@njit(cache=True, nogil=True)
def axis_angle_matrix(axis, angle, out):
    """out (3, 3): the rotation by `angle` (rad) about the unit `axis`."""
    c, sn = np.cos(angle), np.sin(angle)
    for i in range(3):
        for j in range(3):
            out[i, j] = axis[i] * axis[j] * (1.0 - c)
        out[i, i] += c
    out[0, 1] -= axis[2] * sn
    out[1, 0] += axis[2] * sn
    out[0, 2] += axis[1] * sn
    out[2, 0] -= axis[1] * sn
    out[1, 2] -= axis[0] * sn
    out[2, 1] += axis[0] * sn


@njit(cache=True, nogil=True)
def near_body(x, body_ids, centre, radius, out):
    """Positions in body_ids of the vertices within `radius` of `centre`, into out; returns how many."""
    n = 0
    r2 = radius * radius
    for k in range(len(body_ids)):
        v = body_ids[k]
        dx, dy, dz = x[v, 0] - centre[0], x[v, 1] - centre[1], x[v, 2] - centre[2]
        if dx * dx + dy * dy + dz * dz < r2:
            out[n] = k
            n += 1
    return n


@njit(cache=True, nogil=True)
def hand_clearance_at(x, points, s, axis, angle, body_ids, body_normals, cand, margin, near, p):
    """min over the hand points, turned by `angle` about `axis` through s, of (the point's offset
    from its nearest candidate body vertex along that vertex's normal) - margin; a point with no
    candidate within `near` counts as clear (+near). cand: positions in body_ids; p: (3,) scratch."""
    worst = near
    near2 = near * near
    for i in range(len(points)):
        turned(x[points[i]], s, axis, angle, p)
        best = near2
        k_best = -1
        for j in range(len(cand)):
            v = body_ids[cand[j]]
            dx, dy, dz = p[0] - x[v, 0], p[1] - x[v, 1], p[2] - x[v, 2]
            d2 = dx * dx + dy * dy + dz * dz
            if d2 < best:
                best = d2
                k_best = cand[j]
        if k_best < 0:
            continue
        v = body_ids[k_best]
        n = body_normals[k_best]
        d = (p[0] - x[v, 0]) * n[0] + (p[1] - x[v, 1]) * n[1] + (p[2] - x[v, 2]) * n[2] - margin
        if d < worst:
            worst = d
    return worst


@njit(cache=True, nogil=True)
def posed_normals(rest_normals, dominant, rotations, cand, n, out):
    """Normals of the candidate body vertices: each rest normal turned by its dominant bone."""
    for j in range(n):
        k = cand[j]
        r = rotations[dominant[k]]
        a = rest_normals[k]
        out[k, 0] = r[0, 0] * a[0] + r[0, 1] * a[1] + r[0, 2] * a[2]
        out[k, 1] = r[1, 0] * a[0] + r[1, 1] * a[1] + r[1, 2] * a[2]
        out[k, 2] = r[2, 0] * a[0] + r[2, 1] * a[1] + r[2, 2] * a[2]


@njit(cache=True, nogil=True)
def clearance_near(angle, centre, x, points, s, axis, radius, body_ids, rest_normals, dominant, rotations, body_normals,
                   cand, margin, near, p):
    """`hand_clearance_at` the turn `angle`, against the body vertices within `radius` of the
    hand's centre turned by it (`centre`), their normals posed first."""
    n = near_body(x, body_ids, centre, radius, cand)
    posed_normals(rest_normals, dominant, rotations, cand, n, body_normals)
    return hand_clearance_at(x, points, s, axis, angle, body_ids, body_normals, cand[:n], margin, near, p)


@njit(cache=True, nogil=True)
def hand_turn(x, points, s, axis, max_turn, bisections, body_ids, rest_normals, dominant, rotations, body_normals,
              cand, margin, near, scratch):
    """The smallest turn t (rad) about the unit `axis` through the shoulder s that puts every hand
    point (x[points]) `margin` in front of the body's skin, faded out as t goes from 2/3 of
    max_turn to max_turn; 0 where no turn up to max_turn does (a hand held there on purpose).
    The candidates are the body vertices (x[body_ids]) within reach + near of the hand's centre,
    turned with the hand at each angle tried (reach: its farthest point from its centre).
    scratch: (3, 3)."""
    centre, moved, p = scratch[0], scratch[1], scratch[2]
    centre[:] = 0.0
    for i in range(len(points)):
        for a in range(3):
            centre[a] += x[points[i], a] / len(points)
    reach = 0.0
    for i in range(len(points)):
        d2 = 0.0
        for a in range(3):
            d2 += (x[points[i], a] - centre[a]) ** 2
        reach = max(reach, np.sqrt(d2))
    args = (x, points, s, axis, reach + near, body_ids, rest_normals, dominant, rotations, body_normals, cand, margin,
            near, p)
    if clearance_near(0.0, centre, *args) >= 0.0:
        return 0.0
    turned(centre, s, axis, max_turn, moved)
    if clearance_near(max_turn, moved, *args) < 0.0:
        return 0.0  # no turn up to max_turn clears it: a hand placed on purpose (at the neck, on the belly)
    lo, hi = 0.0, max_turn
    for _ in range(bisections):
        mid = 0.5 * (lo + hi)
        turned(centre, s, axis, mid, moved)
        if clearance_near(mid, moved, *args) >= 0.0:
            hi = mid
        else:
            lo = mid
    # fade out between 2/3 of max_turn and max_turn: continuous into the hands left alone
    return hi * smooth_fade(hi, 2.0 * max_turn / 3.0, max_turn)


class HandClearance:
    """Per body: which vertices are each hand's points and which are the other parts' skin.
    `turn` gives, for one skinned pose, the turn an arm needs."""

    def __init__(self, rest_vertices: np.ndarray, rest_normals: np.ndarray, weight_bones: np.ndarray,
                 weight_values: np.ndarray, n_visible: int, regions: np.ndarray, arm_regions: int,
                 skeleton: Skeleton, settings: HandSettings | None = None):
        """rest_vertices, rest_normals: (>= n_visible, 3) the rest body and its unit vertex
        normals; weight_bones, weight_values: (n, k) skinning weights; regions: (n_visible,)
        region bits of the visible vertices, arm_regions the bits of the arms (their skin, and the
        head's and the toes' (`UNCLOTHED_BONES`), is not the body a hand is kept out of);
        skeleton: the character's (bone names, parents and rest joints)."""
        self.settings = s = settings or HandSettings()
        vis = np.arange(n_visible)
        dominant = weight_bones[vis, np.argmax(weight_values[vis], axis=1)].astype(np.int64)
        bare = np.isin(dominant, [i for i, b in enumerate(skeleton.names) if b in UNCLOTHED_BONES])
        self.body_ids = np.flatnonzero(((regions & arm_regions) == 0) & ~bare).astype(np.int64)
        self.dominant = np.ascontiguousarray(dominant[self.body_ids])
        self.rest_normals = np.ascontiguousarray(rest_normals[self.body_ids], dtype=np.float64)
        self.body_normals = np.zeros((len(self.body_ids), 3))
        self.cand = np.empty(len(self.body_ids), dtype=np.int64)
        self.hands = []
        bone_names = list(skeleton.names)
        for slot, side in enumerate(("left", "right")):
            bones = [bone_names.index(b) for b in HAND_BONES[side] if b in bone_names]
            if not bones or ARM_BONES[side] not in bone_names:
                continue
            ids = vis[np.isin(dominant, bones)]
            if not len(ids):
                continue
            rest = np.asarray(rest_vertices, dtype=np.float64)[ids]
            _, first = np.unique(np.floor(rest / s.sample).astype(np.int64), axis=0, return_index=True)
            points = ids[np.sort(first)].astype(np.int64)
            arm = bone_names.index(ARM_BONES[side])
            parent = int(skeleton.parents[arm])
            self.hands.append(dict(slot=slot, arm=arm, parent=parent, chest=int(skeleton.parents[parent]),
                                   outward=float(np.sign(skeleton.heads[arm, 0])), points=points))
        self._scratch = np.empty((3, 3))

    @classmethod
    def for_body(cls, body: Body, settings: HandSettings | None = None) -> "HandClearance":
        """Both hands of a MakeHuman body, kept out of its torso and legs."""
        rest = np.ascontiguousarray(body.vertices[: body.n_visible], dtype=np.float64)
        normals = MeshNormals(body.triangles, body.n_visible)(rest, np.zeros_like(rest))
        return cls(rest, normals, body.weight_bones, body.weight_values, body.n_visible, body_regions(body),
                   ARM_REGIONS, body.skeleton, settings)

    def turn(self, hand: dict, vertices: np.ndarray, rotations: np.ndarray, shoulder: np.ndarray,
             axis: np.ndarray) -> float:
        """The turn (rad) one hand needs in a skinned pose: vertices (>= n_visible, 3), rotations
        (bones, 3, 3) the pose's global bone rotations, shoulder (3,) the arm's joint, axis (3,)
        the unit axis the arm turns about (outwards for a positive turn)."""
        s = self.settings
        return hand_turn(vertices, hand["points"], shoulder, axis, np.deg2rad(s.max_turn_deg), s.bisections,
                         self.body_ids, self.rest_normals, self.dominant, rotations, self.body_normals, self.cand,
                         s.margin, s.near, self._scratch)


__all__ = ["HandClearance", "HandSettings", "axis_angle_matrix", "hand_clearance_at", "hand_turn", "turned"]
