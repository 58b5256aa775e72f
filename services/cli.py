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


def _start(args):
    """Data folder, output folder and (unless --no-png) a renderer, shared by the jobs."""
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    renderer = None
    if not args.no_png:
        from .render import Renderer

        renderer = Renderer(360, 480)
    return data_dir(args.data), out_dir, renderer


def cmd_body(args) -> int:
    from skinning.body import load_body

    from .body_job import SHOWCASE_FRAMES, render_snapshots, run_clip

    data, out_dir, renderer = _start(args)
    t0 = time.perf_counter()
    body = load_body(data)
    print(f"body: {len(body.vertices)} vertices ({body.n_visible} visible), {len(body.triangles)} triangles, "
          f"{len(body.skeleton.names)} bones, loaded in {time.perf_counter() - t0:.2f} s")
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


def cmd_cloth(args) -> int:
    from cloth.fabric import fabric as fabric_by_name
    from cloth.surface import SurfaceSettings
    from skinning.body import load_body

    from .body_job import SHOWCASE_FRAMES
    from .cloth_job import OUTFITS, render_cloth_snapshots, run_cloth_clip

    data, out_dir, renderer = _start(args)
    body = load_body(data)
    fabrics = fabric_by_name(args.fabric, args.fabrics) if args.fabric else None
    surface = None if args.coarse_only else SurfaceSettings(level=args.level)
    for outfit in args.outfit or list(OUTFITS):
        outfit_dir = Path(outfit) if Path(outfit).is_dir() else data / "garments" / outfit
        if not outfit_dir.is_dir():
            raise FileNotFoundError(f"outfit {outfit!r} not found (looked for {outfit_dir})")
        for clip in _clips(data, args.clip):
            frames = [f for f in SHOWCASE_FRAMES.get(clip.stem, [0, 100, 200, 300]) if f % args.every == 0]
            frames = [max(f, args.every) for f in frames]  # frame 0 is skipped (converter T-pose)
            report = run_cloth_clip(body, outfit_dir, clip, every=args.every, max_frames=args.max_frames,
                                    snapshot_frames=frames, fabrics=fabrics, surface=surface)
            print(report.summary())
            if renderer is not None and report.snapshots:
                print(f"  snapshots: {render_cloth_snapshots(body, report, report.models, out_dir, renderer)}")
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
    p = sub.add_parser("cloth", help="cloth (S101-S106) of outfits on motion clips; timings and PNG snapshots")
    p.add_argument("--level", type=int, default=6, help="PN tessellation level of the detailed surface (default 6)")
    p.add_argument("--coarse-only", action="store_true", help="only the coarse cloth (S101), no detailed surface")
    p.add_argument("--outfit", action="append", help="outfit folder name in <data>/garments or a path (default all)")
    p.add_argument("--clip", action="append", help="clip name in <data>/mocap or a BVH path (default all)")
    p.add_argument("--fabric", help="one fabric for every garment (default: a preset per garment)")
    p.add_argument("--fabrics", help="TOML file of fabrics (default: the presets, cloth/fabrics.toml)")
    p.add_argument("--out", default="out", help="output folder (default out/)")
    p.add_argument("--every", type=int, default=2, help="take one frame in N (default 2: 60 Hz)")
    p.add_argument("--max-frames", type=int, default=None, help="stop each clip after N frames")
    p.add_argument("--no-png", action="store_true", help="skip rendering snapshots")
    p.set_defaults(func=cmd_cloth)
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (FileNotFoundError, ValueError) as exc:
        print(f"tryon: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
