"""Measure the detailed surface (S102-S106) of an outfit through a clip, with checks that
share no code with cloth/: the independent signed distance of tests/signed_distance.py.

Per garment and frame: the deepest detailed vertex, NaN, detailed edges longer than the
maximum neighbour distance (where the reference surface alone is already longer, than its
length with the height difference allowed at rest: S106's Decision), and on coarse edges compressed by more than 2 %
the share of their arc-length deficit the wrinkles recovered; where a garment is worn over
another (cloth.layers), every tenth frame, the share of the inner one's vertices near the outer
one (more than 1 cm in from its edges) that stand farther from the skin than the outer's nearest
vertex there (showing through it; which
vertices are near is taken at rest by cloth.layers' rule, the distances are the independent ones),
and by rays (tests/rays.py, eighty-third session: the measure above misses crossings deeper than 1 cm and
inner vertices farther than 1 cm from the outer at rest): the share of the inner's vertices with the outer's
surface within 3 cm along their normal that have it only under them (the normals turned away from the body where
they point into it, eighty-fourth session: `away_from_body`).
Run directly for a table: python -m tests.surface_acceptance [clip ...] [--outfit NAME ...]
[--deep FILE]: FILE also gets one tab-separated row per detailed vertex-frame deeper than 1 mm, with what
S103 knew of it (`DEEP_COLUMNS`), the place to start a diagnosis of the depth bound.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field

import numpy as np

from cloth.layers import LAYER_BAND, layer_outfit, nearest, rest_surface
from cloth.surface import SurfaceSettings
from cloth.topology import unique_edges
from services.cloth_job import run_cloth_clip
from tests.cloth_acceptance import clips_and_outfits
from tests.rays import RayCaster
from tests.signed_distance import SignedDistance


@dataclass
class SurfaceRecord:
    name: str
    depth: list[float] = field(default_factory=list)  # per frame: most negative signed distance, m
    deep_vertices: int = 0  # vertex-frames deeper than 1 mm
    nan_frames: int = 0
    deep_rows: list[tuple] = field(default_factory=list)  # with `deep`: DEEP_COLUMNS per deep vertex-frame
    long_edges: int = 0  # edge-frames over the limit
    long_floored: int = 0  # of those, with both ends at their S103 floor
    beyond_d_max: int = 0  # edge-frames longer than d_max itself (the coarse cloth's stretch included)
    edges: int = 0
    recovered: list[float] = field(default_factory=list)  # per frame: median recovered share of the deficit
    max_height: float = 0.0
    # an inner garment (another worn over it, cloth.layers), every tenth frame: its vertices within
    # LAYER_BAND of the outer one's away from the outer's edges, and of those, the ones farther from
    # the skin than that outer vertex
    overlap: int = 0
    showing: int = 0
    # the same frames, by rays along each of its vertices' normals (tests/rays.py): its vertices with
    # the outer's surface within CROSS_REACH under or over them, those with it under only (showing
    # through it), and of those, with it more than CROSS_DEEP under
    covered: int = 0
    crossed: int = 0
    crossed_deep: int = 0
    # the same frames: its vertices whose normals point into the body (`away_from_body`), of those tested
    turned_in: int = 0
    normals_tested: int = 0


CROSS_REACH = 0.03  # m: how far the rays along an inner vertex's normal look for the outer garment
CROSS_DEEP = 0.005  # m: an outer surface farther than this under an inner vertex lets it show through plainly


NORMAL_STEP = 0.002  # m: the step either way along a normal that tells which way it points from the body


def away_from_body(sd: SignedDistance, body_x: np.ndarray, x: np.ndarray, n: np.ndarray) -> tuple[np.ndarray,
                                                                                                 np.ndarray]:
    """(normals, turned in): each vertex's normal n, turned over where it points into the body (the
    signed distance NORMAL_STEP along it less than NORMAL_STEP back: a fold of the garment turned
    inside out, its shading normals with it), and which were. The rays of `crossings` go along these:
    along a normal turned in, the garment over it reads as under it, and the vertex as showing through."""
    ahead = sd(body_x, x + NORMAL_STEP * n)
    back = sd(body_x, x - NORMAL_STEP * n)
    turned = ahead < back
    return np.where(turned[:, None], -n, n), turned


def crossings(rays: RayCaster, outer_x: np.ndarray, inner_x: np.ndarray, inner_n: np.ndarray,
              rim_face: np.ndarray) -> tuple[int, int, int]:
    """(covered, crossed, crossed deep): of an inner garment's vertices (inner_x, unit normals inner_n
    away from the body), how many have the outer garment's surface within CROSS_REACH along their
    normal either way, how many only inwards (the outer lies under them: they show through it), and
    of those how many by more than CROSS_DEEP. A ray that meets one of the outer's faces within
    LAYER_BAND of its edges at rest (rim_face: a hem tucked under the inner's waistband) is not counted."""
    inward, face_in = rays.first_hits(outer_x, inner_x, -inner_n, CROSS_REACH)
    outward, face_out = rays.first_hits(outer_x, inner_x, inner_n, CROSS_REACH)
    under = np.isfinite(inward) & ~rim_face[np.maximum(face_in, 0)]
    over = np.isfinite(outward) & ~rim_face[np.maximum(face_out, 0)]
    crossed = under & ~np.isfinite(outward)
    return int(np.sum(under | over)), int(crossed.sum()), int(np.sum(crossed & (inward > CROSS_DEEP)))


# per vertex-frame deeper than 1 mm (mm; S103's reading and state as `cloth.surface.SurfaceState` holds them
# after the frame: its reading (inf: untested), its distance to the other body parts, whether a walk there
# found the particle behind that part, n_i . n_body, the height and S106's floor and ceiling), whether the
# vertex is a coarse particle's, and the nearest skin vertex with its body region
DEEP_COLUMNS = ("frame", "garment", "vertex", "coarse", "depth", "s103", "other", "behind", "facing", "dh", "floor",
                "ceiling", "skin_vertex", "region")


def deep_rows(frame: int, name: str, p: np.ndarray, d: np.ndarray, state, n_coarse: int, skin: np.ndarray,
              region_names: list[str]) -> list[tuple]:
    """DEEP_COLUMNS for each of a garment's detailed vertices p deeper than 1 mm by the independent
    signed distances d (m), with S103's state (`SurfaceState`: sd, other, behind, facing, dh, floor,
    ceiling) and the nearest of the skin's vertices (its region from region_names)."""
    rows = []
    for i in np.flatnonzero(d < -0.001):
        v = int(np.argmin(np.sum((skin - p[i]) ** 2, axis=1)))
        mm = [round(float(a) * 1000, 2) for a in (d[i], state.sd[i], state.other[i], state.dh[i], state.floor[i],
                                                   state.ceiling[i])]
        rows.append((frame, name, int(i), int(i < n_coarse), *mm[:3], int(state.behind[i]),
                     round(float(state.facing[i]), 2), *mm[3:], v, region_names[v]))
    return rows


def measure(body, data, outfit: str, clip: str, every: int = 2, max_frames: int | None = None,
            settings: SurfaceSettings | None = None, deep: bool = False):
    """Records per garment of `outfit` over `clip` (and the session's report); deep: each
    record's deep_rows filled too."""
    sd = SignedDistance(body.triangles, body.n_visible)
    region_names: list[str] = []
    if deep:
        from skinning.body import BODY_REGIONS, body_regions
        names = {bit: name for name, bit in BODY_REGIONS.items()}
        region_names = [names.get(int(r), str(int(r))) for r in body_regions(body)]
    rays = {}  # outer garment: its RayCaster, and its faces within LAYER_BAND of its edges at rest
    records: list[SurfaceRecord] = []

    bands = {}  # (outer, inner): each one's detailed vertices within LAYER_BAND of the other at rest

    def on_frame(index, session, body_frame, positions):
        if not records:
            records.extend(SurfaceRecord(s.model.cloth.name) for s in session.surfaces)
            rest = [rest_surface(s.model) for s in session.surfaces]
            # the garment pairs worn one over the other (found even where the session's layering is off)
            models = [sf.model for sf in session.surfaces]
            worn_over = {(m.outer, m.inner) for m in session.outfit.over}  # two tops: as named (coarse_layers)
            for lm in layer_outfit(models, np.ascontiguousarray(session.outfit.rest_body[: body.n_visible]), worn_over):
                d_oi, _ = nearest(rest[lm.outer], rest[lm.inner])
                d_io, _ = nearest(rest[lm.inner], rest[lm.outer])
                # the outer's vertices more than LAYER_BAND in from its edges (a hem): an inner vertex
                # near the hem's last row may lie just beyond it, not under the outer garment
                tris = session.surfaces[lm.outer].model.tess.triangles
                edges, uses = unique_edges(tris)
                rim = np.unique(edges[uses == 1])
                d_rim, _ = nearest(rest[lm.outer], rest[lm.outer][rim])
                rays[lm.outer] = RayCaster(tris), np.any(d_rim[tris] < LAYER_BAND, axis=1)
                bands[lm.outer, lm.inner] = (np.flatnonzero((d_oi < LAYER_BAND) & (d_rim > LAYER_BAND)),
                                             np.flatnonzero(d_io < LAYER_BAND))
        skin = body_frame.vertices[: body.n_visible]
        skin_distance = []
        for rec, surf, (p, _) in zip(records, session.surfaces, session.detailed):
            skin_distance.append(None)
            if not np.isfinite(p).all():
                rec.nan_frames += 1
                continue
            m, s = surf.model, surf.state
            d = skin_distance[-1] = sd(skin, p)
            rec.depth.append(float(d.min()))
            rec.deep_vertices += int(np.sum(d < -0.001))
            if deep:
                rec.deep_rows += deep_rows(index, rec.name, p, d, s, m.tess.n_coarse, skin, region_names)
            length = np.linalg.norm(p[m.d_edges[:, 0]] - p[m.d_edges[:, 1]], axis=1)
            ref = np.linalg.norm(s.p_smoothed[m.d_edges[:, 0]] - s.p_smoothed[m.d_edges[:, 1]], axis=1)
            # S106's limit: d_max, or where the reference surface alone is longer, the height
            # difference allowed at rest on top of it (d_max² - rest²)
            rest2 = (m.d_max / m.cloth.fabric.max_neighbour_ratio) ** 2
            limit = np.where(ref > m.d_max, np.sqrt(ref**2 + m.d_max**2 - rest2), m.d_max)
            long = length > limit * (1 + 1e-9)
            rec.long_edges += int(np.sum(long))
            # held up by S103: both ends at the floor its lifts need (no height S106 may give shortens them)
            at_floor = s.dh <= s.floor + 1e-12
            rec.long_floored += int(np.sum(long & at_floor[m.d_edges[:, 0]] & at_floor[m.d_edges[:, 1]]))
            rec.beyond_d_max += int(np.sum(length > m.d_max * (1 + 1e-9)))
            rec.edges += len(length)
            rec.max_height = max(rec.max_height, float(s.dh.max()))
            ids = m.tess.edge_ids
            arc_ref = np.linalg.norm(np.diff(s.p_smoothed[ids], axis=1), axis=2).sum(axis=1)
            arc = np.linalg.norm(np.diff(p[ids], axis=1), axis=2).sum(axis=1)
            deficit = m.edge_rest - arc_ref
            comp = deficit > 0.02 * m.edge_rest
            if comp.any():
                rec.recovered.append(float(np.median((arc[comp] - arc_ref[comp]) / deficit[comp])))
        if index % 10 == 0:
            for (o, i), (bo, bi) in bands.items():
                if skin_distance[o] is None or skin_distance[i] is None:
                    continue
                po, pi = session.detailed[o][0][bo], session.detailed[i][0][bi]
                d2 = ((pi[:, None, :] - po[None, :, :]) ** 2).sum(axis=2)
                near = d2.argmin(axis=1)
                close = d2[np.arange(len(pi)), near] < LAYER_BAND**2
                records[i].overlap += int(close.sum())
                records[i].showing += int(np.sum(close & (skin_distance[i][bi] > skin_distance[o][bo][near])))
                inner_x = session.detailed[i][0]
                inner_n, turned = away_from_body(sd, skin, inner_x, session.detailed[i][1])
                records[i].turned_in += int(turned.sum())
                records[i].normals_tested += len(turned)
                counts = crossings(rays[o][0], session.detailed[o][0], inner_x, inner_n, rays[o][1])
                records[i].covered += counts[0]
                records[i].crossed += counts[1]
                records[i].crossed_deep += counts[2]

    report = run_cloth_clip(body, data / "garments" / outfit, data / "mocap" / f"{clip}.bvh", every=every,
                            max_frames=max_frames, on_frame=on_frame, surface=settings or SurfaceSettings())
    return records, report


def main() -> None:
    from skinning.body import load_body
    from skinning.data import data_dir

    data = data_dir()
    body = load_body(data)
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--deep", help="write each vertex-frame deeper than 1 mm to this file (tab-separated)")
    parser.add_argument("--level", type=int, default=None,
                        help="tessellation level (default SurfaceSettings', 6; the acceptance is at 6)")
    known, rest = parser.parse_known_args(sys.argv[1:])
    clips, outfits = clips_and_outfits(rest, (parser,))
    deep = open(known.deep, "w") if known.deep else None
    try:
        if deep:
            print("clip", *DEEP_COLUMNS, sep="\t", file=deep, flush=True)
        for clip in clips:
            for outfit in outfits:
                settings = None if known.level is None else SurfaceSettings(level=known.level)
                report(clip, measure(body, data, outfit, clip, settings=settings, deep=deep is not None)[0], deep)
    finally:
        if deep:
            deep.close()


def report(clip: str, records: list[SurfaceRecord], deep) -> None:
    """Print a clip's records, one line per garment; their deep rows to the open file `deep`."""
    for r in records if deep else ():
        for row in r.deep_rows:
            print(clip, *row, sep="\t", file=deep, flush=True)
    for r in records:
        d = np.array(r.depth)
        print(f"{clip:26s} {r.name:28s} frames {len(d):5d} deepest {d.min() * 1000:7.1f} mm "
              f"(frames < -1 mm: {int(np.sum(d < -0.001)):4d}, vertex-frames {r.deep_vertices:6d}) "
              f"long edges {r.long_edges / max(r.edges, 1) * 100:6.3f} % "
              f"(both ends at S103 floors {r.long_floored / max(r.edges, 1) * 100:6.3f} %, "
              f"beyond d_max {r.beyond_d_max / max(r.edges, 1) * 100:5.2f} %) "
              f"recovered {np.median(r.recovered) if r.recovered else float('nan'):5.2f} "
              f"max dh {r.max_height * 1000:5.1f} mm NaN {r.nan_frames}"
              + (f" showing through the garment over it {r.showing / r.overlap * 100:4.1f} %"
                 if r.overlap else "")
              + (f", by rays {r.crossed / r.covered * 100:4.1f} % (more than {CROSS_DEEP * 1000:.0f} mm "
                 f"{r.crossed_deep / r.covered * 100:4.1f} %; normals into the body "
                 f"{r.turned_in / r.normals_tested * 100:4.1f} %)" if r.covered else ""),
              flush=True)


if __name__ == "__main__":
    main()
