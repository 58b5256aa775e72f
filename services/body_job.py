"""The body job: stream a clip, retarget and skin every frame, time the stages, render snapshots."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cloth.winding import WindingGrid, closed_faces, winding_numbers
from skinning.animate import STAGES, BodyAnimator
from skinning.body import BODY_REGIONS, Body, body_clothed_faces, body_regions
from skinning.contact import ContactSettings
from skinning.retarget import IKSettings
from skinning.source import BVHSource

# Frames worth looking at in the shipped clips (data README, "Useful frame ranges").
SHOWCASE_FRAMES = {
    "cmu_13_29_jumping_jacks": [0, 70, 200, 1000, 2500, 3960, 4340],
    "cmu_131_01_walk_3dsmax": [0, 300, 420, 560, 700, 900],
    "cmu_npybvh_example_75f": [0, 20, 40, 60],
}
SKIN = (0.86, 0.69, 0.58)


def showcase_frames(clip_stem: str, every: int = 1, first: int = 0) -> list[int]:
    """A clip's showcase frames (source frame numbers at the clip's rate) as session frame
    numbers when one frame in `every` is taken, none before `first`."""
    frames = SHOWCASE_FRAMES.get(clip_stem, [0, 100, 200, 300])
    return [max(f // every, first) for f in frames if f % every == 0]


class SelfContact:
    """How much of the clothed skin lies inside another part of the body in a pose: where linear
    blend skinning makes the body cut through itself (an arm through the torso, a thigh into the
    belly, the calf into the thigh behind a bent knee), the cloth has no outside to go to.

    A clothed vertex is inside another part when the point `depth` inwards along its normal,
    inside its own part, has a winding number of 2 or more for the clothed skin (holes at the
    neck, wrists and ankles capped); skin pressed on skin (the skin contact) is not counted, nor
    are the vertices of faces next to a cap (flat where the skin under it is not). Counts per
    body region (BODY_REGIONS order)."""

    def __init__(self, body: Body, depth: float = 0.002):
        keep = body_clothed_faces(body)
        self.grid = WindingGrid(closed_faces(body.triangles, keep), body.n_visible)
        clothed = body.triangles[keep]
        by_cap = np.isin(clothed, body.triangles[~keep]).any(axis=1)
        self.vertices = np.setdiff1d(clothed, clothed[by_cap]).astype(np.int64)
        regions = body_regions(body)[self.vertices]
        self.region_index = np.searchsorted(np.array(sorted(BODY_REGIONS.values())), regions)
        self.depth = depth
        self._x = np.empty((body.n_visible, 3))
        self._p = np.empty((len(self.vertices), 3))
        self._w = np.empty(len(self.vertices), dtype=np.int32)

    def inside(self, vertices: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Visible vertex indices of the clothed skin inside another part.
        vertices: (>= n_visible, 3) skinned; normals: (n_visible, 3) unit."""
        x = self._x
        x[:] = vertices[: len(x)]
        self.grid.update(x)
        np.multiply(normals[self.vertices], -self.depth, out=self._p)
        self._p += x[self.vertices]
        winding_numbers(self._p, x, self.grid.tris, *self.grid.arrays(), self._w)
        return self.vertices[self._w >= 2]

    def __call__(self, vertices: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(len(BODY_REGIONS),) int: clothed vertices inside another part, per region."""
        self.inside(vertices, normals)
        return np.bincount(self.region_index[self._w >= 2], minlength=len(BODY_REGIONS))


@dataclass
class ClipReport:
    name: str
    frames: int = 0
    stage_ms: dict[str, np.ndarray] = field(default_factory=dict)  # per frame
    ankle_position_error: np.ndarray | None = None  # (frames, 2) m
    ankle_rotation_error: np.ndarray | None = None  # (frames, 2) rad
    floor_lift: np.ndarray | None = None  # (frames, 2) m
    lowest_sole: np.ndarray | None = None  # (frames,) m, lowest foot vertex height
    arm_turn: np.ndarray | None = None  # (frames, 2) rad the arms were turned out for clearance
    self_contact: np.ndarray | None = None  # (sampled frames, regions) `SelfContact` counts, if asked for
    skin_moved: np.ndarray | None = None  # (frames,) skin vertices the skin contact moved
    nan_frames: int = 0
    snapshots: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)  # (frame, verts, normals)

    def summary(self) -> str:
        pe = self.ankle_position_error.max(axis=1) * 1000
        re = np.rad2deg(self.ankle_rotation_error.max(axis=1))
        stages = "  ".join(f"{s} {np.median(self.stage_ms[s]):.3f}" for s in STAGES)
        return (f"{self.name}: {self.frames} frames | median ms/frame: {stages} | ankle error mm: "
                f"median {np.median(pe):.3f} p99 {np.percentile(pe, 99):.2f} max {pe.max():.2f} | "
                f"ankle rot deg p99 {np.percentile(re, 99):.2f} | lowest sole {self.lowest_sole.min() * 1000:.1f} mm"
                f" | arm turn deg median {np.rad2deg(np.median(self.arm_turn)):.1f} max "
                f"{np.rad2deg(self.arm_turn.max()):.1f} | skin contact: vertices moved median "
                f"{np.median(self.skin_moved):.0f} max {self.skin_moved.max()} | NaN frames {self.nan_frames}"
                + ("" if self.self_contact is None or not len(self.self_contact) else
                   "\n  clothed skin inside another part of the body, vertices per frame (mean over "
                   f"{len(self.self_contact)} frames): "
                   + "  ".join(f"{r} {c:.1f}" for r, c in zip(BODY_REGIONS, self.self_contact.mean(axis=0)))))


def foot_vertices(body: Body) -> np.ndarray:
    """Visible vertices that mostly follow a foot or toe bone."""
    names = body.skeleton.names
    feet = [names.index(n) for n in ("LeftFoot", "LeftToeBase", "RightFoot", "RightToeBase")]
    vis = np.arange(body.n_visible)
    dominant = body.weight_bones[vis, np.argmax(body.weight_values[vis], axis=1)]
    return vis[np.isin(dominant, feet)]


def run_clip(body: Body, path: str | Path, every: int = 1, snapshot_frames: list[int] | None = None,
             max_frames: int | None = None, ik: IKSettings | None = None, self_contact: int = 0,
             contact: ContactSettings | None = ContactSettings()) -> ClipReport:
    """self_contact: measure `SelfContact` on every n-th frame (0: not at all); contact: the skin
    contact of `BodyAnimator` (None: off)."""
    path = Path(path)
    report = ClipReport(path.stem)
    wanted = set(snapshot_frames or [])
    feet = foot_vertices(body)
    stage_ms = {s: [] for s in STAGES}
    pos_err, rot_err, lift, lowest, arm, inside, moved = [], [], [], [], [], [], []
    inside_test = SelfContact(body) if self_contact > 0 else None
    with BVHSource(path, every=every, max_frames=max_frames) as source:
        animator = BodyAnimator(body, source.skeleton, ik=ik, contact=contact)
        for frame in source:
            out = animator(frame.local_rot, frame.root_position)
            for s, sec in zip(STAGES, animator.stage_seconds):
                stage_ms[s].append(sec * 1000)
            r = out.retarget
            pos_err.append(r.ankle_position_error.copy())
            rot_err.append(r.ankle_rotation_error.copy())
            lift.append(r.floor_lift.copy())
            arm.append(r.arm_turn)
            lowest.append(out.vertices[feet, 1].min())
            if not (np.isfinite(out.vertices).all() and np.isfinite(out.normals).all()):
                report.nan_frames += 1
            if inside_test is not None and frame.index % self_contact == 0:
                inside.append(inside_test(out.vertices, out.normals))
            moved.append(animator.contact.moved if animator.contact is not None else 0)
            if frame.index in wanted:
                report.snapshots.append((frame.index, out.vertices.copy(), out.normals.copy()))
            report.frames += 1
    report.stage_ms = {s: np.array(v) for s, v in stage_ms.items()}
    report.ankle_position_error = np.array(pos_err).reshape(-1, 2)
    report.ankle_rotation_error = np.array(rot_err).reshape(-1, 2)
    report.floor_lift = np.array(lift).reshape(-1, 2)
    report.lowest_sole = np.array(lowest)
    report.arm_turn = np.array(arm).reshape(-1, 2)
    report.skin_moved = np.array(moved)
    if inside_test is not None:
        report.self_contact = np.array(inside).reshape(-1, len(BODY_REGIONS))
    return report


def render_snapshots(body: Body, report: ClipReport, out_dir: Path, renderer=None) -> Path:
    """One contact sheet per clip: each snapshot frame from the front and from a three-quarter view."""
    from .render import MeshDraw, Renderer, contact_sheet, orbit_camera, save_png

    own = renderer is None
    renderer = renderer or Renderer(360, 480)
    images = []
    tris = body.triangles
    for frame, verts, normals in report.snapshots:
        vis = verts[: body.n_visible]
        centre = np.array([vis[:, 0].mean(), vis[:, 1].min() + 0.5 * np.ptp(vis[:, 1]), vis[:, 2].mean()])
        for azimuth in (0.0, 60.0):
            cam = orbit_camera(centre, azimuth, distance=3.6, height=0.2)
            images.append(renderer.render([MeshDraw(vis, tris, normals, SKIN)], cam))
    if own:
        renderer.release()
    path = out_dir / f"body_{report.name}.png"
    save_png(path, contact_sheet(images, columns=4))
    return path
