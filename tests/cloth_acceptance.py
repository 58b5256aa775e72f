"""Measure an outfit through a clip with checks independent of the simulation code.

Per garment and frame: the deepest coarse particle (independent signed distance to the
skinned body, negative inside), the strain of every structural edge, the waistband's largest
distance from the body, the share of particles more than OFF_BODY from the skin (a garment
blown or thrown off the body), and NaN. Run directly for a table:
python -m tests.cloth_acceptance [clip ...] [--outfit NAME ...] (default: every clip and outfit)
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from services.cloth_job import OUTFITS, run_cloth_clip
from tests.signed_distance import SignedDistance

OFF_BODY = 0.10  # m: a particle farther than this from the skin is off the body
CLIPS = ["cmu_npybvh_example_75f", "cmu_131_01_walk_3dsmax", "cmu_13_29_jumping_jacks"]


def clips_and_outfits(argv: list[str], parents: tuple = ()) -> tuple[list[str], list[str]]:
    """The clips and outfits a table runs over: positional clip names, --outfit (repeatable).
    parents: parsers (add_help=False) of a table's own options, listed in --help too."""
    parser = argparse.ArgumentParser(parents=list(parents))
    parser.add_argument("clips", nargs="*", default=CLIPS)
    parser.add_argument("--outfit", action="append",
                        help="a shipped outfit, or garments of them mixed (female_sportsuit01.bottom+"
                             "female_elegantsuit01.bottom); default: every shipped outfit")
    args = parser.parse_args(argv)
    return args.clips, args.outfit or list(OUTFITS)


@dataclass
class GarmentRecord:
    name: str
    depth: list[float] = field(default_factory=list)  # per frame: most negative signed distance, m
    strain: list[np.ndarray] = field(default_factory=list)  # per frame: structural edge strains
    waist_gap: list[float] = field(default_factory=list)  # per frame: waistband's largest |distance|, m
    off_body: list[float] = field(default_factory=list)  # per frame: share of particles beyond OFF_BODY
    nan_frames: int = 0

    @property
    def strain_p99(self) -> float:
        return float(np.percentile(np.concatenate(self.strain), 99))

    @property
    def deepest(self) -> float:
        return float(min(self.depth))


def measure(body, data: Path, outfit: str, clip: str, every: int = 2,
            full: bool = True) -> tuple[list[GarmentRecord], object]:
    """full=False measures only NaN and the waistband (cheap enough for CI on every frame)."""
    sd = SignedDistance(body.triangles, body.n_visible)
    records: list[GarmentRecord] = []

    def on_frame(index, session, body_frame, positions):
        if not records:
            records.extend(GarmentRecord(s.model.name) for s in session.sims)
        skin = body_frame.vertices[: body.n_visible]
        checked = [x if full else x[sim.model.grip.astype(bool)] for sim, x in zip(session.sims, positions)]
        d_all = sd(skin, np.concatenate(checked))
        offset = 0
        for rec, sim, x, c in zip(records, session.sims, positions, checked):
            d = d_all[offset: offset + len(c)]
            offset += len(c)
            if not np.isfinite(x).all():
                rec.nan_frames += 1
                continue
            m = sim.model
            if m.grip.any():
                rec.waist_gap.append(float(np.abs(d[m.grip.astype(bool)] if full else d).max()))
            if not full:
                continue
            rec.depth.append(float(d.min()))
            rec.off_body.append(float(np.mean(d > OFF_BODY)))
            k = m.n_structural
            length = np.linalg.norm(x[m.spring_i[:k]] - x[m.spring_j[:k]], axis=1)
            rec.strain.append((length / m.rest_length[:k] - 1.0).astype(np.float32))

    report = run_cloth_clip(body, data / "garments" / outfit, data / "mocap" / f"{clip}.bvh", every=every,
                            on_frame=on_frame)
    return records, report


def main() -> None:
    from skinning.body import load_body
    from skinning.data import data_dir

    data = data_dir()
    body = load_body(data)
    clips, outfits = clips_and_outfits(sys.argv[1:])
    for clip in clips:
        for outfit in outfits:
            records, report = measure(body, data, outfit, clip)
            for r in records:
                gap = f"{max(r.waist_gap) * 100:5.1f} cm" if r.waist_gap else "   -    "
                s = np.concatenate(r.strain)
                print(f"{clip:26s} {r.name:28s} frames {len(r.depth):5d} deepest {r.deepest * 1000:7.2f} mm "
                      f"(frames < -1 mm: {sum(d < -0.001 for d in r.depth):4d}) strain p99 {r.strain_p99 * 100:5.1f} % "
                      f"max {s.max() * 100:5.1f} % waist {gap} off body {np.mean(r.off_body) * 100:4.1f} % "
                      f"(worst frame {max(r.off_body) * 100:4.1f} %) NaN {r.nan_frames} "
                      f"substeps {report.substeps} resets {report.resets}", flush=True)


if __name__ == "__main__":
    main()
