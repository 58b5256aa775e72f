"""Per-stage cost of the whole garment-frame (S101-S106), in the layout of SPEC.md's table.

For the dress-like outfit (elegantsuit: blouse + skirt) and the trouser-like one (casualsuit:
T-shirt + jeans) on the walk clip at 60 frames per second: medians in ms per frame of each
stage, summed over the outfit's garments, beside the patent's figures (Pentium 4, 2.5 GHz), and
the outfit's layering (cloth/layers.py: the top's surface kept over the bottom's; not in the patent).
Then how the surface cost grows with the tessellation level.
Run: .venv/bin/python bench/bench_surface.py [--frames 200] [--levels 4 6 8 10 12]
"""

from __future__ import annotations

import argparse
import os
import platform

import numpy as np

from bench_cloth import cpu_name  # same folder
from cloth.surface import SurfaceSettings
from services.cloth_job import run_cloth_clip
from skinning.body import load_body
from skinning.data import data_dir

PATENT = {  # SPEC.md: dress, blouse + pants (ms per frame)
    "integration": (16.0, 18.0), "collision": (4.6, 6.1), "PN triangles": (10.2, 14.1),
    "surface collision": (13.3, 17.2), "deformation": (25.8, 33.6),
}
OUTFITS = {"dress-like (blouse + skirt)": "female_elegantsuit01",
           "trouser-like (T-shirt + jeans)": "female_casualsuit01"}


def stage_medians(report, fast) -> dict[str, float]:
    """Sum over garments of each stage's per-frame median (ms): integration and collision from
    the profiled run `report`, the whole S101 step and the surface stages from `fast`."""
    out = {k: 0.0 for k in ("integration", "collision", "PN triangles", "surface collision", "deformation")}
    out["S101 total"] = 0.0
    out["layering"] = float(np.median(fast.layer_ms)) if fast.layer_ms else 0.0
    for name in report.garments:
        split = np.median(np.array(report.split_ms[name]), axis=0)
        surf = np.median(np.array(fast.surface_ms[name]), axis=0)
        out["integration"] += split[0]
        out["collision"] += split[1]
        out["PN triangles"] += surf[0]
        out["surface collision"] += surf[1]
        out["deformation"] += surf[2]
        out["S101 total"] += np.median(fast.stage_ms[name])
    return out


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--clip", default="cmu_131_01_walk_3dsmax")
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--levels", type=int, nargs="*", default=[4, 6, 8, 10, 12])
    parser.add_argument("--data")
    args = parser.parse_args()
    data = data_dir(args.data)
    body = load_body(data)
    clip = data / "mocap" / f"{args.clip}.bvh"
    run_cloth_clip(body, data / "garments" / "female_casualsuit01", clip, max_frames=5, profile=True,
                   surface=SurfaceSettings())  # compile
    print(f"machine: {cpu_name()}, {os.cpu_count()} cores, Python {platform.python_version()}; clip {args.clip} "
          f"at 60 Hz, {args.frames} frames, level 6; ms per frame (medians), patent in brackets")
    rows = {}
    verts = {}
    for label, outfit in OUTFITS.items():
        rep = run_cloth_clip(body, data / "garments" / outfit, clip, max_frames=args.frames, profile=True,
                             surface=SurfaceSettings(level=6))
        fast = run_cloth_clip(body, data / "garments" / outfit, clip, max_frames=args.frames,
                              surface=SurfaceSettings(level=6))
        rows[label] = stage_medians(rep, fast)
        verts[label] = rep.surface_triangles
    labels = list(OUTFITS)
    print(f"{'stage':22s}" + "".join(f"{lb:>34s}" for lb in labels))
    for k, stage in enumerate(("integration", "collision", "PN triangles", "surface collision", "deformation")):
        print(f"{stage:22s}" + "".join(f"{rows[lb][stage]:>24.2f} [{PATENT[stage][i]:5.1f}]   "
                                       for i, lb in enumerate(labels)))
    for i, lb in enumerate(labels):
        r = rows[lb]
        surface = r["PN triangles"] + r["surface collision"] + r["deformation"]
        total = r["S101 total"] + surface + r["layering"]
        patent_total = sum(PATENT[s][i] for s in PATENT)
        print(f"{lb}: S101 {r['S101 total']:.2f} ms, surface {surface:.2f} ms, layering {r['layering']:.2f} ms, "
              f"whole {total:.2f} ms per frame "
              f"({1000.0 / total:.0f} FPS; patent {patent_total:.1f} ms, {patent_total / total:.0f}x faster)")
    print("\nsurface cost by level, trouser-like outfit (ms per frame, both garments)")
    print(f"{'level':>5s} {'detailed verts':>14s} {'PN':>6s} {'collision':>9s} {'deformation':>11s} "
          f"{'us per 1k verts':>15s}")
    for level in args.levels:
        rep = run_cloth_clip(body, data / "garments" / "female_casualsuit01", clip, max_frames=min(args.frames, 100),
                             surface=SurfaceSettings(level=level))
        n = sum(int(t.max()) + 1 for t in rep.surface_triangles)
        med = sum(np.median(np.array(rep.surface_ms[g]), axis=0) for g in rep.garments)
        print(f"{level:5d} {n:14d} {med[0]:6.2f} {med[1]:9.2f} {med[2]:11.2f} {1000 * med.sum() / (n / 1000):15.0f}")


if __name__ == "__main__":
    main()
