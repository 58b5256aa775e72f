"""A small OBJ reader that keeps the file's vertex order and its `g` groups.

trimesh splits vertices at UV seams, but every MakeHuman index file (skin
weights, mhclo, proxies, joint cubes) refers to the `v` lines in file order,
so the body and garments are read here instead.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


class MeshFormatError(ValueError):
    """A mesh file is malformed; the message names the file, line and problem."""


@dataclass
class ObjMesh:
    vertices: np.ndarray  # (n, 3) float64, in the file's units
    faces: list[list[int]]  # polygons, 0-based vertex indices
    face_group: np.ndarray  # (len(faces),) int32 index into group_names
    group_names: list[str] = field(default_factory=list)

    def group_faces(self, name: str) -> list[list[int]]:
        gid = self.group_names.index(name)
        return [self.faces[i] for i in np.flatnonzero(self.face_group == gid)]

    def group_vertex_ids(self, name: str) -> np.ndarray:
        """Sorted ids of the vertices used by the group's faces."""
        faces = self.group_faces(name)
        return np.unique(np.fromiter((v for f in faces for v in f), dtype=np.int64))


def read_obj(path: str | Path) -> ObjMesh:
    """Read `v`, `f` and `g` records; everything else (vt, vn, s, usemtl) is skipped."""
    path = Path(path)
    verts: list[tuple[float, float, float]] = []
    faces: list[list[int]] = []
    face_group: list[int] = []
    groups: list[str] = []
    current = -1
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise MeshFormatError(f"{path}: cannot read: {exc}") from exc
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line[0] == "#":
            continue
        tag, _, rest = line.partition(" ")
        if tag == "v":
            parts = rest.split()
            if len(parts) < 3:
                raise MeshFormatError(f"{path}:{lineno}: vertex needs 3 coordinates, got {len(parts)}")
            try:
                xyz = (float(parts[0]), float(parts[1]), float(parts[2]))
            except ValueError:
                raise MeshFormatError(f"{path}:{lineno}: vertex coordinate is not a number: {rest!r}") from None
            if not all(np.isfinite(xyz)):
                raise MeshFormatError(f"{path}:{lineno}: vertex coordinate is not finite: {rest!r}")
            verts.append(xyz)
        elif tag == "f":
            idx = []
            for token in rest.split():
                head = token.split("/", 1)[0]
                try:
                    k = int(head)
                except ValueError:
                    raise MeshFormatError(f"{path}:{lineno}: face index is not an integer: {token!r}") from None
                # OBJ indices are 1-based; negative ones count back from the last vertex
                idx.append(k - 1 if k > 0 else len(verts) + k)
            if len(idx) < 3:
                raise MeshFormatError(f"{path}:{lineno}: face needs at least 3 vertices")
            faces.append(idx)
            if current < 0:
                groups.append("default")
                current = 0
            face_group.append(current)
        elif tag == "g":
            name = rest.strip() or "default"
            if name in groups:
                current = groups.index(name)
            else:
                groups.append(name)
                current = len(groups) - 1
    if not verts:
        raise MeshFormatError(f"{path}: no vertices")
    n = len(verts)
    for f in faces:
        for k in f:
            if not 0 <= k < n:
                raise MeshFormatError(f"{path}: face index {k + 1} out of range (file has {n} vertices)")
    return ObjMesh(
        vertices=np.asarray(verts, dtype=np.float64),
        faces=faces,
        face_group=np.asarray(face_group, dtype=np.int32),
        group_names=groups,
    )


def split_polygons(polys: list[list[int]], vertices: np.ndarray | None = None) -> np.ndarray:
    """Triangulate polygons as fans; quads are split along their shorter diagonal when
    vertices are given (better-shaped triangles), else along 0-2."""
    tris: list[tuple[int, int, int]] = []
    for f in polys:
        if len(f) == 4 and vertices is not None:
            a, b, c, d = f
            if np.sum((vertices[a] - vertices[c]) ** 2) <= np.sum((vertices[b] - vertices[d]) ** 2):
                tris += [(a, b, c), (a, c, d)]
            else:
                tris += [(a, b, d), (b, c, d)]
        else:
            for k in range(1, len(f) - 1):
                tris.append((f[0], f[k], f[k + 1]))
    return np.asarray(tris, dtype=np.int32).reshape(-1, 3)
