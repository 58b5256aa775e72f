"""Per-stage cost of the body pipeline: IK (retargeting), skinning all 19,158 vertices, the hand
clearance (with a second skinning where an arm turns), the skin contact, normals.

Medians over every frame of every shipped clip, in microseconds (whole numbers).
Run: .venv/bin/python bench/bench_body.py [--every 2]
"""

from __future__ import annotations

import argparse
import os
import platform

import numpy as np

from services.body_job import run_clip
from skinning.animate import STAGES
from skinning.body import load_body
from skinning.data import data_dir


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--every", type=int, default=1, help="1: native 120 Hz, 2: 60 Hz")
    parser.add_argument("--data")
    args = parser.parse_args()
    data = data_dir(args.data)
    body = load_body(data)
    run_clip(body, data / "mocap" / "cmu_npybvh_example_75f.bvh")  # compile / warm caches
    cpu = platform.machine()
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    print(f"machine: {cpu}, {os.cpu_count()} cores, Python {platform.python_version()}; "
          f"{'120' if args.every == 1 else f'{120 // args.every}'} Hz input")
    print(f"{'clip':32s} {'frames':>6s} " + " ".join(f"{s + ' us':>12s}" for s in STAGES) + f" {'total us':>9s}")
    for clip in sorted((data / "mocap").glob("*.bvh")):
        r = run_clip(body, clip, every=args.every)
        med = [np.median(r.stage_ms[s]) * 1000 for s in STAGES]
        total = np.median(sum(r.stage_ms[s] for s in STAGES)) * 1000
        print(f"{clip.stem:32s} {r.frames:6d} " + " ".join(f"{m:12.0f}" for m in med) + f" {total:9.0f}")


if __name__ == "__main__":
    main()
