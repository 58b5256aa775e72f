"""`tryon` command line."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from skinning.data import ENV_VAR, data_dir


def _clips(data: Path, names: list[str] | None) -> list[Path]:
    mocap = data / "mocap"
    if not names:
        return sorted(mocap.glob("*.bvh"))
    out = []
    for name in names:
        p = Path(name)
        if not p.suffix:
            p = mocap / f"{name}.bvh"
        elif not p.exists():
            p = mocap / name
        if not p.exists():
            raise SystemExit(f"tryon: clip {name!r} not found (looked for {p})")
        out.append(p)
    return out


def cmd_body(args) -> int:
    from skinning.body import load_body

    from .body_job import SHOWCASE_FRAMES, render_snapshots, run_clip

    data = data_dir(args.data)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    body = load_body(data)
    print(f"body: {len(body.vertices)} vertices ({body.n_visible} visible), {len(body.triangles)} triangles, "
          f"{len(body.skeleton.names)} bones, loaded in {time.perf_counter() - t0:.2f} s")
    renderer = None
    if not args.no_png:
        from .render import Renderer

        renderer = Renderer(360, 480)
    for clip in _clips(data, args.clip):
        frames = SHOWCASE_FRAMES.get(clip.stem, [0, 100, 200, 300])
        frames = [f // args.every for f in frames if f % args.every == 0] if args.every > 1 else frames
        report = run_clip(body, clip, every=args.every, snapshot_frames=frames, max_frames=args.max_frames)
        print(report.summary())
        if renderer is not None and report.snapshots:
            print(f"  snapshots: {render_snapshots(body, report, out_dir, renderer)}")
    if renderer is not None:
        renderer.release()
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="tryon", description="Real-time virtual try-on.")
    parser.add_argument("--data", help=f"data folder (default: ${ENV_VAR} or ../shared/data)")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("body", help="retarget and skin motion clips; print timings, write PNG snapshots")
    p.add_argument("--clip", action="append", help="clip name in <data>/mocap or a BVH path (repeatable; default all)")
    p.add_argument("--out", default="out", help="output folder (default out/)")
    p.add_argument("--every", type=int, default=1, help="take one frame in N (2: 120 Hz clips at 60 Hz)")
    p.add_argument("--max-frames", type=int, default=None, help="stop each clip after N frames")
    p.add_argument("--no-png", action="store_true", help="skip rendering snapshots")
    p.set_defaults(func=cmd_body)
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (FileNotFoundError, ValueError) as exc:
        print(f"tryon: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
