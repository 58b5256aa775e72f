"""Garment meshes: MakeHuman .mhclo fitting, any trimesh-readable mesh, split into garments.

A garment here is one connected piece of cloth in the body's rest pose, metres, Y up:
`Garment(name, vertices (n, 3) float64, faces (m, 4) int32 with -1 padding triangles)`.
The cloth package sees the body only as arrays, so fitting takes the body's rest
vertices (all of base.obj, helpers included: the mhclo files reference them).
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .geometry import nearest_vertices
from .topology import boundary_loops, connected_components, orient_faces

MAKEHUMAN_UNIT_M = 0.1  # mhclo offsets and OBJ coordinates are decimetres
# what a garment mesh of a user's may come as (trimesh reads them; OBJ through our reader, which keeps quads)
MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".stl", ".off")
# m: a garment mesh lies on the rest body when half its vertices are within this of the skin (the
# shipped garments, fitted: 9-16 mm; a file in other units or another frame is off by far more)
PLACED_MEDIAN = 0.05
# of the body's height above its lowest vertex: a garment that reaches no higher is worn from the
# waist, and its highest boundary loop grips the body (shipped: bottoms 0.57-0.60, tops 0.84-0.85)
WAIST_SHARE = 0.7


class GarmentError(ValueError):
    """A garment file is malformed; the message names the file (and line) and the problem."""


@dataclass
class Garment:
    name: str
    vertices: np.ndarray  # (n, 3) float64, metres, rest pose
    faces: np.ndarray  # (m, 4) int32, triangles padded with -1
    source_ids: np.ndarray  # (n,) vertex index in the file the garment came from

    @property
    def boundary_loops(self) -> list[np.ndarray]:
        return boundary_loops(self.faces)


@dataclass
class Mhclo:
    path: Path
    obj_file: str
    refs: np.ndarray  # (n, 3) int64 reference vertices of the base mesh
    weights: np.ndarray  # (n, 3) float64
    offsets: np.ndarray  # (n, 3) float64, scaled per axis by `scale`
    scale_refs: np.ndarray  # (3, 2) int64: x, y, z scale reference vertex pairs
    scale_den: np.ndarray  # (3,) float64
    delete_verts: np.ndarray  # base vertices hidden by the garment


def read_mhclo(path: str | Path) -> Mhclo:
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise GarmentError(f"{path}: cannot read: {exc}") from exc
    obj_file = None
    scale = {}
    rows: list[list[float]] = []
    deleted: list[int] = []
    section = None
    for lineno, raw in enumerate(lines, start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        words = line.split()
        key = words[0]
        try:
            if key == "obj_file":
                obj_file = words[1]
            elif key in ("x_scale", "y_scale", "z_scale"):
                scale[key[0]] = (int(words[1]), int(words[2]), float(words[3]))
            elif key == "verts":
                section = "verts"
            elif key == "delete_verts":
                section = "delete"
            elif section == "verts" and key[0].isdigit():
                if len(words) == 1:
                    rows.append([int(words[0]), 0, 0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0])
                elif len(words) == 9:
                    rows.append([float(w) for w in words])
                else:
                    raise GarmentError(f"{path}:{lineno}: vertex row needs 1 or 9 values, got {len(words)}")
            elif section == "delete" and key[0].isdigit():
                for w in words:  # "a - b" ranges are allowed by MakeHuman
                    if w != "-":
                        deleted.append(int(w))
            elif section == "verts" and not key[0].isdigit():
                section = None
        except GarmentError:
            raise
        except (ValueError, IndexError):
            raise GarmentError(f"{path}:{lineno}: cannot parse {raw.strip()!r}") from None
    if obj_file is None:
        raise GarmentError(f"{path}: no obj_file line")
    if len(scale) != 3:
        raise GarmentError(f"{path}: needs x_scale, y_scale and z_scale lines, found {sorted(scale)}")
    if not rows:
        raise GarmentError(f"{path}: no vertex rows after 'verts 0'")
    table = np.asarray(rows, dtype=np.float64)
    refs = table[:, :3].astype(np.int64)
    weights = table[:, 3:6]
    if np.any(np.abs(weights.sum(axis=1) - 1.0) > 1e-3):
        bad = int(np.argmax(np.abs(weights.sum(axis=1) - 1.0)))
        raise GarmentError(f"{path}: weights of vertex row {bad} do not sum to 1")
    return Mhclo(
        path=path,
        obj_file=obj_file,
        refs=refs,
        weights=weights,
        offsets=table[:, 6:9],
        scale_refs=np.array([scale[a][:2] for a in "xyz"], dtype=np.int64),
        scale_den=np.array([scale[a][2] for a in "xyz"]),
        delete_verts=np.asarray(deleted, dtype=np.int64),
    )


def fit_mhclo(clo: Mhclo, base_vertices: np.ndarray) -> np.ndarray:
    """Fitted positions w1*B[v1] + w2*B[v2] + w3*B[v3] + offset*s (units of base_vertices).

    base_vertices are in MakeHuman decimetres or metres; the offsets are decimetres
    relative to the scale, so the result is in the units of base_vertices."""
    n_base = len(base_vertices)
    if clo.refs.max() >= n_base or clo.scale_refs.max() >= n_base:
        raise GarmentError(f"{clo.path}: references vertex {max(clo.refs.max(), clo.scale_refs.max())}, "
                           f"the base mesh has {n_base}")
    pairs = base_vertices[clo.scale_refs]  # (3, 2, 3)
    s = np.abs(pairs[np.arange(3), 0, np.arange(3)] - pairs[np.arange(3), 1, np.arange(3)]) / clo.scale_den
    return np.einsum("nk,nkd->nd", clo.weights, base_vertices[clo.refs]) + clo.offsets * s


def _pad_faces(faces: list[list[int]] | np.ndarray, path: Path) -> np.ndarray:
    """(F, 4) int32 faces, triangles padded with -1; a polygon of more than four corners (an n-gon of a
    modelling tool's export) as a fan of triangles from its first corner, as trimesh reads one."""
    rows = []
    for i, f in enumerate(faces):
        f = list(f)
        if len(f) == 3 or len(f) == 4:
            rows.append(f + [-1] * (4 - len(f)))
        elif len(f) > 4:
            rows.extend([f[0], f[k], f[k + 1], -1] for k in range(1, len(f) - 1))
        else:
            raise GarmentError(f"{path}: face {i} has {len(f)} vertices; a face needs three or more")
    return np.array(rows, dtype=np.int32).reshape(-1, 4)


def read_obj_polygons(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices in file order and tri/quad faces of an OBJ (garment files are small and simple; a face of
    more corners as triangles, `_pad_faces`)."""
    verts, faces = [], []
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise GarmentError(f"{path}: cannot read: {exc}") from exc
    for lineno, raw in enumerate(text.splitlines(), start=1):
        words = raw.split()
        if not words:
            continue
        try:
            if words[0] == "v":
                verts.append([float(w) for w in words[1:4]])
                if len(verts[-1]) != 3:
                    raise ValueError
            elif words[0] == "f":
                ids = [int(w.split("/", 1)[0]) for w in words[1:]]
                faces.append([k - 1 if k > 0 else len(verts) + k for k in ids])
        except ValueError:
            raise GarmentError(f"{path}:{lineno}: cannot parse {raw.strip()!r}") from None
    v = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
    f = _pad_faces(faces, path)
    if len(f) == 0:
        raise GarmentError(f"{path}: no faces")
    if f.max() >= len(v) or f[f >= 0].min() < 0:
        raise GarmentError(f"{path}: a face references a vertex that does not exist")
    _check_finite(path, v)
    return v, f


def face_outward(garment: Garment, body_vertices: np.ndarray) -> Garment:
    """The garment with its faces wound so that their normals point away from the body it is
    fitted on (body_vertices (n, 3), m, in the garment's frame): the side S103 lifts to, the
    layering lifts along and the renderer lights. Each face votes with its area whether its
    normal points away from the body vertex nearest its centre; where most of the area says
    no (a mesh wound inwards), every face is reversed (`orient_faces` has made the winding
    consistent). The garment itself is returned when it already faces out."""
    f = np.asarray(garment.faces)
    v = np.asarray(garment.vertices, dtype=np.float64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    normal = np.cross(b - a, c - a)  # area-weighted (the first triangle of a quad)
    centre = (a + b + c) / 3.0
    body = np.ascontiguousarray(body_vertices, dtype=np.float64)
    near = np.zeros(len(f), dtype=np.int64)
    nearest_vertices(np.ascontiguousarray(centre), body, near, np.ones(len(body), dtype=np.uint8),
                     np.ones(len(f), dtype=np.uint8))
    away = np.einsum("ij,ij->i", normal, centre - body[near])
    area = np.linalg.norm(normal, axis=1)
    if np.sum(area[away > 0]) >= np.sum(area[away < 0]):
        return garment
    flipped = f.copy()
    for k in range(len(f)):  # each face's ring reversed, its -1 padding kept at the end
        n = int(np.count_nonzero(f[k] >= 0))
        flipped[k, :n] = f[k, :n][::-1]
    return Garment(garment.name, garment.vertices, flipped, garment.source_ids)


MIN_PIECE = 16  # vertices: a smaller connected piece is stray loose geometry (buttons, labels), not cloth


def split_garments(name: str, vertices: np.ndarray, faces: np.ndarray, min_vertices: int = MIN_PIECE) -> list[Garment]:
    """One Garment per connected component, named top to bottom (`name.top`, `name.bottom`)."""
    faces = orient_faces(faces)
    labels = connected_components(len(vertices), faces)
    used = np.zeros(len(vertices), dtype=bool)
    used[faces[faces >= 0]] = True
    parts = []
    for k in range(labels.max() + 1):
        ids = np.flatnonzero((labels == k) & used)
        if len(ids) < min_vertices:
            continue  # (stray loose geometry)
        remap = np.full(len(vertices), -1, dtype=np.int32)
        remap[ids] = np.arange(len(ids), dtype=np.int32)
        mine = labels[faces[:, 0]] == k
        f = np.where(faces[mine] >= 0, remap[faces[mine]], -1).astype(np.int32)
        parts.append((vertices[ids, 1].mean(), ids, f))
    parts.sort(key=lambda p: -p[0])
    if len(parts) == 1:  # one garment: its own name
        return [Garment(name, vertices[parts[0][1]].copy(), parts[0][2], parts[0][1])]
    if len(parts) == 2:
        suffixes = ["top", "bottom"]
    else:
        suffixes = [f"part{i}" for i in range(len(parts))]
    return [Garment(f"{name}.{s}", vertices[ids].copy(), f, ids) for s, (_, ids, f) in zip(suffixes, parts)]


def load_outfit(outfit_dir: str | Path, base_vertices_m: np.ndarray) -> list[Garment]:
    """A MakeHuman outfit folder (`<name>.mhclo` + its OBJ) fitted on the base body (metres)."""
    outfit_dir = Path(outfit_dir)
    clos = sorted(outfit_dir.glob("*.mhclo"))
    if not clos:
        raise GarmentError(f"{outfit_dir}: no .mhclo file")
    clo = read_mhclo(clos[0])
    obj_path = outfit_dir / clo.obj_file
    _, faces = read_obj_polygons(obj_path)
    if len(clo.refs) < faces.max() + 1:
        raise GarmentError(f"{clo.path}: {len(clo.refs)} vertex rows but {obj_path.name} uses "
                           f"{faces.max() + 1} vertices")
    fitted = fit_mhclo(clo, base_vertices_m / MAKEHUMAN_UNIT_M) * MAKEHUMAN_UNIT_M
    return split_garments(outfit_dir.name, fitted, faces)


def load_garment_file(path: str | Path, scale: float = 1.0) -> list[Garment]:
    """Any mesh trimesh reads (OBJ, PLY, GLB, ...), already placed on the rest body; `scale` to metres."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise GarmentError(f"{path}: no such file")
    if path.suffix.lower() == ".obj":
        vertices, faces = read_obj_polygons(path)  # keeps quads, which the coarse model prefers
    else:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                mesh = trimesh.load(path, force="mesh", process=False)
        except Exception as exc:  # trimesh raises many types for bad files
            raise GarmentError(f"{path}: trimesh cannot read it: {exc}") from exc
        if len(getattr(mesh, "faces", [])) == 0:
            raise GarmentError(f"{path}: no faces")
        _check_finite(path, np.asarray(mesh.vertices, dtype=np.float64))  # (before merging, which warns on them)
        mesh.merge_vertices(merge_tex=True, merge_norm=True)  # UV/normal seams would split the cloth
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        faces = np.full((len(mesh.faces), 4), -1, dtype=np.int32)
        faces[:, :3] = mesh.faces
    return split_garments(path.stem, vertices * scale, faces)


def _check_finite(path: Path, vertices: np.ndarray) -> None:
    """GarmentError naming the first vertex with a NaN or infinite coordinate (in file order)."""
    bad = np.flatnonzero(~np.isfinite(vertices).all(axis=1))
    if len(bad):
        raise GarmentError(f"{path}: vertex {bad[0]} has a coordinate that is not a finite number "
                           f"({', '.join(map(str, vertices[bad[0]]))})"
                           + (f", and {len(bad) - 1} more vertices" if len(bad) > 1 else ""))


def skin_distances(points: np.ndarray, skin: np.ndarray, rows: int = 256) -> np.ndarray:
    """(k,) each point's distance to the nearest skin vertex (setup only: blocks of `rows` points
    against every vertex, no index to build)."""
    skin = np.asarray(skin, dtype=np.float64)
    s2 = np.einsum("ij,ij->i", skin, skin)
    out = np.empty(len(points))
    for a in range(0, len(points), rows):
        p = np.asarray(points[a: a + rows], dtype=np.float64)
        d2 = np.einsum("ij,ij->i", p, p)[:, None] + s2[None, :] - 2.0 * p @ skin.T
        out[a: a + rows] = np.sqrt(np.maximum(d2.min(axis=1), 0.0))
    return out


def check_placed(garment: Garment, skin: np.ndarray, source: str | Path, samples: int = 2000) -> None:
    """GarmentError unless the garment lies on the rest body (`PLACED_MEDIAN`): a mesh a user
    brings is used where it is, so one in other units or another frame is refused, naming the
    file and what is expected, rather than simulated falling from where it floats."""
    v = garment.vertices[np.linspace(0, len(garment.vertices) - 1, min(samples, len(garment.vertices))).astype(int)]
    median = float(np.median(skin_distances(v, skin)))
    if not median <= PLACED_MEDIAN:
        raise GarmentError(
            f"{source}: garment {garment.name!r} does not lie on the rest body: half its vertices are more than "
            f"{median * 100:.0f} cm from the skin (a fitted garment's are within a few cm). A garment mesh must be "
            f"in metres, in the rest body's frame: Y up, feet on the floor y = 0, facing +Z (MakeHuman exports "
            f"decimetres about the body's middle unless told otherwise)")


def worn_from_waist(garment: Garment, skin: np.ndarray) -> bool:
    """Whether a garment hangs from the waist (trousers, a skirt; not a top or a dress): it
    reaches no higher than WAIST_SHARE of the body's height. Its highest boundary loop is then a
    waistband that grips the body."""
    floor, top = float(skin[:, 1].min()), float(skin[:, 1].max())
    return float(garment.vertices[:, 1].max()) < floor + WAIST_SHARE * (top - floor)


def garment_meshes(folder: Path) -> list[Path]:
    """The garment mesh files in a folder (`MESH_SUFFIXES`), in name order."""
    return sorted(p for p in Path(folder).iterdir() if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)


MIX = "+"  # joins the outfits, or single garments of them, that a mixed outfit is made of


def mix_terms(path: str | Path) -> list[tuple[Path, str | None]] | None:
    """A mixed outfit: `a+b.top` beside outfits a and b (its name's terms joined by MIX), each
    term an outfit there (all its garments) or one garment of one (`<outfit>.<part>`, as the
    garment is named: `female_casualsuit01.top`). Returns (the outfit's path, the garment's name
    or None for all) per term; None where path is not a mix (it exists, or has no MIX in its
    name). GarmentError naming a term that is neither, and the outfits there."""
    path = Path(path)
    if path.exists() or MIX not in path.name:
        return None
    terms: list[tuple[Path, str | None]] = []
    for term in path.name.split(MIX):
        outfit = term.rpartition(".")[0]
        if term and (path.parent / term).exists():
            terms.append((path.parent / term, None))
        elif outfit and (path.parent / outfit).is_dir():
            terms.append((path.parent / outfit, term))
        else:
            there = sorted(p.name for p in path.parent.glob("*") if p.is_dir() or p.suffix.lower() in MESH_SUFFIXES)
            raise GarmentError(f"outfit {path.name!r}: {term!r} is neither an outfit in {path.parent} nor a garment "
                               f"of one (<outfit>.<part>, as `tryon catalog` names them); there are {there}")
    return terms


def outfit_source(path: str | Path) -> str:
    """What an outfit path holds: "mhclo" (a MakeHuman outfit folder), "meshes" (a folder of
    garment mesh files), "mesh" (one garment mesh file), "mix" (garments of other outfits,
    `mix_terms`); GarmentError naming what was expected."""
    path = Path(path)
    terms = mix_terms(path)
    if terms is not None:
        for outfit, _ in terms:
            outfit_source(outfit)
        return "mix"
    if path.is_dir():
        if any(path.glob("*.mhclo")):
            return "mhclo"
        if garment_meshes(path):
            return "meshes"
        raise GarmentError(f"{path}: no .mhclo file and no garment mesh ({', '.join(MESH_SUFFIXES)})")
    if path.is_file():
        if path.suffix.lower() in MESH_SUFFIXES:
            return "mesh"
        raise GarmentError(f"{path}: not a garment mesh (one of {', '.join(MESH_SUFFIXES)}) or an outfit folder")
    raise GarmentError(f"{path}: no such file or folder")


def _load_mix(path: Path, base_vertices_m: np.ndarray, skin: np.ndarray) -> list[Garment]:
    """A mixed outfit's garments (`mix_terms`), in the order its name gives them."""
    garments: list[Garment] = []
    for outfit, name in mix_terms(path):
        pieces = load_garments(outfit, base_vertices_m, skin)
        if name is not None:
            chosen = [g for g in pieces if g.name == name]
            if not chosen:
                raise GarmentError(f"outfit {path.name!r}: {outfit.name} has no garment {name!r}; it has "
                                   f"{[g.name for g in pieces]}")
            pieces = chosen
        for g in pieces:
            if any(h.name == g.name for h in garments):
                raise GarmentError(f"outfit {path.name!r}: garment {g.name!r} comes twice")
            garments.append(g)
    return garments


def load_garments(path: str | Path, base_vertices_m: np.ndarray, skin: np.ndarray) -> list[Garment]:
    """An outfit's garments on the rest body (metres, world frame): a MakeHuman outfit folder
    (`load_outfit`, fitted on base_vertices_m, helpers included), or garment meshes already placed
    on the rest body (`load_garment_file`: one file, or every one in a folder), each checked to lie
    on the skin (`check_placed`; skin: the rest body's visible vertices), or garments of such
    outfits mixed (`mix_terms`)."""
    path = Path(path)
    kind = outfit_source(path)
    if kind == "mhclo":
        return load_outfit(path, base_vertices_m)
    if kind == "mix":
        return _load_mix(path, base_vertices_m, skin)
    garments: list[Garment] = []
    for f in [path] if kind == "mesh" else garment_meshes(path):
        pieces = load_garment_file(f)
        if not pieces:
            raise GarmentError(f"{f}: no piece of cloth in it (every connected piece has fewer than {MIN_PIECE} "
                               f"vertices)")
        for g in pieces:
            # named after the file: a bus key, so letters, digits, '_', '.' and '-' only
            g.name = re.sub(r"[^A-Za-z0-9_.\-]", "_", g.name)
            if any(h.name == g.name for h in garments):
                raise GarmentError(f"{f}: a garment named {g.name!r} came from another file of {path} already")
            check_placed(g, skin, f)
            garments.append(g)
    return garments
