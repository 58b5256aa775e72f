"""Per-stage cost of S101 (coarse cloth) per garment-frame, in the layout of SPEC.md's table.

For each outfit on the walk clip at 60 frames per second of motion: the whole S101 step
(body following, substeps, recovery, re-attachment) from the fused kernel, and a second,
profiled pass that times integration and collision separately (medians, microseconds).
Run: .venv/bin/python bench/bench_cloth.py [--clip NAME] [--every 2] [--union-passes 0]
"""

from __future__ import annotations

import argparse
import os
import platform

import numpy as np

from cloth.model import SimSettings
from services.cloth_job import OUTFITS, run_cloth_clip
from skinning.body import load_body
from skinning.data import data_dir


def cpu_name() -> str:
    try:
        return next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.machine()


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--clip", default="cmu_131_01_walk_3dsmax")
    parser.add_argument("--every", type=int, default=2, help="2: 60 Hz (default), 1: native 120 Hz")
    parser.add_argument("--outfits", nargs="*", default=list(OUTFITS))
    parser.add_argument("--data")
    parser.add_argument("--union-passes", type=int, default=SimSettings().union_passes,
                        help="SimSettings.union_passes (0: the union pass off, for an A/B of its cost)")
    args = parser.parse_args()
    settings = SimSettings(union_passes=args.union_passes)
    data = data_dir(args.data)
    body = load_body(data)
    clip = data / "mocap" / f"{args.clip}.bvh"
    run_cloth_clip(body, data / "garments" / args.outfits[0], data / "mocap" / "cmu_npybvh_example_75f.bvh",
                   max_frames=10, profile=True)  # compile
    print(f"machine: {cpu_name()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
          f"clip {args.clip} at {120 // args.every} Hz; union_passes {args.union_passes}")
    print(f"{'garment':30s} {'particles':>9s} {'springs':>7s} {'substeps':>8s} {'S101 us':>8s} "
          f"{'integration us':>14s} {'collision us':>12s} {'resets':>6s}")
    for outfit in args.outfits:
        fast = run_cloth_clip(body, data / "garments" / outfit, clip, every=args.every, settings=settings)
        prof = run_cloth_clip(body, data / "garments" / outfit, clip, every=args.every, profile=True,
                              settings=settings)
        for k, m in enumerate(fast.models):
            split = np.array(prof.split_ms[m.name])
            print(f"{m.name:30s} {m.n_particles:9d} {len(m.spring_i):7d} {fast.substeps[k]:8d} "
                  f"{np.median(fast.stage_ms[m.name]) * 1000:8.0f} {np.median(split[:, 0]) * 1000:14.0f} "
                  f"{np.median(split[:, 1]) * 1000:12.0f} {fast.resets[k]:6d}")


if __name__ == "__main__":
    main()
