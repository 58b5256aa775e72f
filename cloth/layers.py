"""Garments worn over one another: which one is outside where they overlap, found once at rest.

Each garment is simulated against the body alone (S101-S106 know no other cloth), so where a
top's hem overlaps a bottom's waistband both lie a few millimetres off the same skin, and the
one with the thicker collision layer (denim 4 mm against cotton 3 mm) comes out on top: the
jeans' wrinkles showed through the T-shirt's hem in a jagged line. Decision (layering): in the
band where two garments overlap at rest, the outer one's detailed surface keeps the inner
one's collision thickness plus LAYER_HEIGHT more off the body (S103's clearance, per detailed
vertex), and the inner one's heights (its wrinkles) stay under LAYER_HEIGHT there (S106's
ceiling), so the inner surface lies under the outer one. Which is outer is the garments'
own layering at rest: the one farther from the body where they overlap (the shipped tops sit
1-2 mm outside the bottoms' waistbands). Both weights ease to nothing over LAYER_RAMP beyond
the band, so no step shows where the band ends. The coarse cloth is unchanged: only the
detailed surfaces are layered, as only they are drawn.
"""

from __future__ import annotations

import math

import numpy as np

from .jit import kernel
from .pn import pn_surface
from .surface import SurfaceModel

LAYER_BAND = 0.01  # m: a detailed vertex this near the other garment's at rest lies in the overlap
LAYER_RAMP = 0.01  # m: beyond the band the layering eases off over this distance
LAYER_HEIGHT = 0.002  # m: the inner garment's heights in the overlap, and the gap above them


@kernel
def nearest_distances(points, targets, out):
    """out[i] = the distance from points[i] to the nearest of targets (brute force, once at setup:
    11,000 × 11,000 pairs in a fraction of a second)."""
    for i in range(points.shape[0]):
        best = np.inf
        for j in range(targets.shape[0]):
            d2 = ((points[i, 0] - targets[j, 0]) ** 2 + (points[i, 1] - targets[j, 1]) ** 2
                  + (points[i, 2] - targets[j, 2]) ** 2)
            if d2 < best:
                best = d2
        out[i] = math.sqrt(best)


def rest_surface(model: SurfaceModel) -> np.ndarray:
    """(N, 3) the detailed surface at rest: PN over the rest particles, no heights."""
    t = model.tess
    x = np.ascontiguousarray(model.cloth.rest_positions, dtype=np.float64)
    n, T = len(x), len(t.coarse_triangles)
    p, normals = np.zeros((t.n_vertices, 3)), np.zeros((t.n_vertices, 3))
    pn_surface(t, x, np.zeros((n, 3)), np.zeros((T, 10, 3)), np.zeros((T, 6, 3)), p, normals)
    return p


def overlap_weight(distance: np.ndarray) -> np.ndarray:
    """1 within LAYER_BAND of the other garment, easing linearly to 0 over LAYER_RAMP beyond."""
    return np.clip((LAYER_BAND + LAYER_RAMP - distance) / LAYER_RAMP, 0.0, 1.0)


def layer_outfit(models: list[SurfaceModel], body_rest: np.ndarray) -> list[tuple[int, int]]:
    """Set each garment's `layer_clearance` and `layer_cap` (see the module's Decision) for the
    garments of one outfit, fitted together on the body at rest (body_rest: (n, 3) its
    vertices, m). Returns the (outer, inner) pairs found, as indices into models."""
    rest = [rest_surface(m) for m in models]
    body = np.ascontiguousarray(body_rest, dtype=np.float64)
    pairs = []
    for a in range(len(models)):
        for b in range(a + 1, len(models)):
            d_ab = np.empty(len(rest[a]))
            d_ba = np.empty(len(rest[b]))
            nearest_distances(rest[a], rest[b], d_ab)
            nearest_distances(rest[b], rest[a], d_ba)
            in_a, in_b = d_ab < LAYER_BAND, d_ba < LAYER_BAND
            if not (in_a.any() and in_b.any()):
                continue
            # the garment farther from the body where they overlap is worn over the other
            from_body_a = np.empty(int(in_a.sum()))
            from_body_b = np.empty(int(in_b.sum()))
            nearest_distances(np.ascontiguousarray(rest[a][in_a]), body, from_body_a)
            nearest_distances(np.ascontiguousarray(rest[b][in_b]), body, from_body_b)
            outer, inner = (a, b) if np.median(from_body_a) >= np.median(from_body_b) else (b, a)
            d_outer, d_inner = (d_ab, d_ba) if outer == a else (d_ba, d_ab)
            lift = models[inner].cloth.fabric.thickness + LAYER_HEIGHT
            mo, mi = models[outer], models[inner]
            mo.layer_clearance[:] = np.maximum(mo.layer_clearance, overlap_weight(d_outer) * lift)
            cap = mi.settings.max_height - overlap_weight(d_inner) * (mi.settings.max_height - LAYER_HEIGHT)
            mi.layer_cap[:] = np.minimum(mi.layer_cap, cap)
            pairs.append((outer, inner))
    return pairs


__all__ = ["LAYER_BAND", "LAYER_HEIGHT", "LAYER_RAMP", "layer_outfit", "nearest_distances", "overlap_weight",
           "rest_surface"]
