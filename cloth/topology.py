"""Mesh topology helpers: components, edges, boundary loops, adjacency (built once, numpy)."""

from __future__ import annotations

import numpy as np


def connected_components(n_vertices: int, faces: np.ndarray) -> np.ndarray:
    """Component label per vertex (0..k-1, ordered by first vertex); faces (m, 3|4), -1 pads quads."""
    parent = np.arange(n_vertices)

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for face in faces:
        r0 = find(int(face[0]))
        for v in face[1:]:
            if v < 0:
                continue
            r = find(int(v))
            if r != r0:
                parent[r] = r0
    roots = np.array([find(i) for i in range(n_vertices)])
    _, labels = np.unique(roots, return_inverse=True)
    # relabel so that component 0 holds vertex 0, and so on in order of first appearance
    order = np.unique(labels, return_index=True)[1]
    rank = np.empty(len(order), dtype=np.int64)
    rank[np.argsort(order)] = np.arange(len(order))
    return rank[labels]


def polygon_edges(faces: np.ndarray) -> np.ndarray:
    """Directed edges (a, b) of every polygon, in winding order; faces (m, 3|4), -1 pads."""
    faces = np.asarray(faces)
    if faces.shape[1] == 3:
        return np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2)
    edges = []
    for face in faces:
        f = face[face >= 0]
        edges.extend(zip(f, np.roll(f, -1)))
    return np.asarray(edges, dtype=np.int64).reshape(-1, 2)


def unique_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undirected edges (sorted pairs) and how many faces use each."""
    e = np.sort(polygon_edges(faces), axis=1)
    edges, counts = np.unique(e, axis=0, return_counts=True)
    return edges, counts


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Closed boundary loops as vertex sequences (edges used by one face), longest first.

    A vertex where two loops touch (a pinch) appears in both."""
    directed = polygon_edges(faces)
    und = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(und, axis=0, return_inverse=True, return_counts=True)
    border = directed[counts[inverse.ravel()] == 1]
    out: dict[int, list[int]] = {}
    for a, b in border:
        out.setdefault(int(a), []).append(int(b))
    loops = []
    for start in list(out):
        while out.get(start):
            loop, v = [], start
            while out.get(v):
                loop.append(v)
                v = out[v].pop()
            loops.append(np.asarray(loop, dtype=np.int64))
    return sorted(loops, key=len, reverse=True)


def orient_faces(faces: np.ndarray) -> np.ndarray:
    """Flip faces so that neighbours agree on winding (each component keeps its majority winding)."""
    faces = np.asarray(faces).copy()
    owners: dict[tuple[int, int], list[int]] = {}
    for f, face in enumerate(faces):
        ring = face[face >= 0]
        for a, b in zip(ring, np.roll(ring, -1)):
            owners.setdefault((min(a, b), max(a, b)), []).append(f)
    flip = np.full(len(faces), -1, dtype=np.int64)  # -1 unvisited, 0 keep, 1 flip

    def winding(f: int, a: int, b: int) -> bool:
        ring = list(faces[f][faces[f] >= 0])
        k = ring.index(a)
        return ring[(k + 1) % len(ring)] == b

    for seed in range(len(faces)):
        if flip[seed] >= 0:
            continue
        flip[seed] = 0
        component, stack = [seed], [seed]
        while stack:
            f = stack.pop()
            ring = faces[f][faces[f] >= 0]
            for a, b in zip(ring, np.roll(ring, -1)):
                for g in owners[(min(a, b), max(a, b))]:
                    if g == f or flip[g] >= 0:
                        continue
                    same = winding(g, a, b)  # same direction on a shared edge = inconsistent
                    flip[g] = flip[f] ^ int(same)
                    component.append(g)
                    stack.append(g)
        if np.count_nonzero(flip[component]) * 2 > len(component):
            flip[component] ^= 1
    for f in np.flatnonzero(flip == 1):
        n = int(np.count_nonzero(faces[f] >= 0))
        faces[f, :n] = faces[f, :n][::-1]
    return faces


def triangulate(faces: np.ndarray, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of a tri/quad mesh, quads split along their shorter diagonal (SPEC S102 Decision).

    Returns (triangles (t, 3) int32, source face of each triangle (t,) int32)."""
    faces = np.asarray(faces)
    if faces.shape[1] == 3:
        return faces.astype(np.int32), np.arange(len(faces), dtype=np.int32)
    quad = faces[:, 3] >= 0
    a, b, c, d = faces.T
    d02 = np.linalg.norm(vertices[a] - vertices[c], axis=1)
    d13 = np.linalg.norm(vertices[b] - vertices[np.where(quad, d, b)], axis=1)
    use02 = (d02 <= d13) | ~quad  # a triangle is (a, b, c) as it is
    t1 = np.where(use02[:, None], np.stack([a, b, c], 1), np.stack([a, b, d], 1))
    t2 = np.where(use02[:, None], np.stack([a, c, d], 1), np.stack([b, c, d], 1))
    tris = np.concatenate([t1, t2[quad]])
    src = np.concatenate([np.arange(len(faces)), np.flatnonzero(quad)])
    order = np.argsort(src, kind="stable")
    return tris[order].astype(np.int32), src[order].astype(np.int32)


def vertex_neighbours(n_vertices: int, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CSR (start, ids) of each vertex's edge neighbours."""
    both = np.concatenate([edges, edges[:, ::-1]])
    order = np.lexsort((both[:, 1], both[:, 0]))
    both = both[order]
    start = np.zeros(n_vertices + 1, dtype=np.int64)
    np.add.at(start, both[:, 0] + 1, 1)
    return np.cumsum(start), both[:, 1].astype(np.int32)


def vertex_cells(n_vertices: int, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CSR (start, ids) of the cells (triangles (m, 3), edges (m, 2), ...) incident to each vertex."""
    owner = cells.ravel()
    cell = np.repeat(np.arange(len(cells), dtype=np.int32), cells.shape[1])
    order = np.argsort(owner, kind="stable")
    start = np.zeros(n_vertices + 1, dtype=np.int64)
    np.add.at(start, owner + 1, 1)
    return np.cumsum(start), cell[order]


def triangle_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    v = vertices[triangles]
    return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)


def triangle_neighbours(triangles: np.ndarray) -> np.ndarray:
    """(t, 3) int32: the triangle across edge (a, b), (b, c), (c, a) of each triangle, -1 on a
    boundary. Where more than two triangles share an edge (non-manifold), the first other one."""
    t = np.asarray(triangles, dtype=np.int64)
    n = len(t)
    e = np.stack([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]], axis=1).reshape(-1, 2)
    key = np.sort(e, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    k = key[order]
    same = np.all(k[1:] == k[:-1], axis=1)  # consecutive half-edges of one edge
    out = np.full(3 * n, -1, dtype=np.int64)
    first = order[:-1][same]
    second = order[1:][same]
    out[first] = second // 3
    out[second] = first // 3
    return out.reshape(n, 3).astype(np.int32)
