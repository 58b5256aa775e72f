"""`tryon` command line."""

from __future__ import annotations

import argparse
import contextlib
import functools
import math
import signal
import sys
import threading
import time
from pathlib import Path

from skinning.data import ENV_VAR, data_dir

from .diskspace import DEFAULT_MIN_FREE
from .outputs import output_folder
from .spin import LIVE_SPIN, check_cpus, default_cpus


def _clips(data: Path, names: list[str] | None, every: int | None = None, check: bool = False) -> list[Path]:
    """The clips named (all of <data>/mocap if none). check: the commands that run a session from
    START_FRAME on refuse a clip with no frame there at one frame in `every` (None: `_every`'s)."""
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
        if check:
            _check_session_frames(p, _every(every, p))
        note = _skeleton_note(p)
        if note:
            print(note, flush=True)
        out.append(p)
    return out


# frames per second a session runs at when --every is not given (the nearest a clip's rate allows)
SESSION_RATE = 60.0
EVERY_HELP = "take one frame in N (default: the N that brings the clip nearest 60 Hz, 2 for the 120 Hz CMU clips)"


@functools.lru_cache(maxsize=64)
def _clip_header(clip: Path):
    """A BVH clip's header (`skinning.bvh.BVHHeader`; read once per clip and command)."""
    from skinning.bvh import BVHReader

    reader = BVHReader(clip)
    try:
        return reader.header
    finally:
        reader.close()


def _skeleton_note(clip: Path) -> str | None:
    """What a clip of a skeleton other than CMU's leaves unmoved: the character's bones none of
    its joints is named as (they keep their rest pose relative to their parents). None: the CMU
    skeleton."""
    from skinning.bvh import OPTIONAL_BONES, bone_names_file
    from skinning.skeleton import CMU_BONES

    header = _clip_header(clip)
    if header.cmu:
        return None
    moved = sum(b in header.skeleton.names for b in CMU_BONES)
    # (of the bones a CMU clip moves: the fingers and hip joints are still in those too)
    still = [b for b in CMU_BONES if b not in header.skeleton.names and b not in OPTIONAL_BONES]
    follow = "follows its parent (name the joint for it" if len(still) == 1 else \
        "follow their parents (name the joints for them"
    unmoved = (f"; of those a CMU clip moves, {', '.join(still)} {follow} in {bone_names_file(clip).name})"
               if still else "")
    return (f"tryon: clip {clip.name} is not the CMU skeleton: its joints named as the character's bones drive "
            f"{moved} of the character's {len(CMU_BONES)} bones{unmoved}")


def _every(every: int | None, clip: Path) -> int:
    """--every, or where not given, the one frame in N that brings the clip nearest SESSION_RATE: 2 for
    the CMU clips' 120 Hz, 1 for a clip of 60 Hz or less (a 30 Hz clip taken at one frame in two ran
    at 15 Hz), 4 for 240 Hz."""
    if every is not None:
        return every
    return max(1, round(1.0 / _clip_header(clip).frame_time / SESSION_RATE))


def _check_session_frames(clip: Path, every: int) -> None:
    """SystemExit naming the clip when taking one frame in `every` leaves none from START_FRAME on
    (a session of a one-frame clip ran no frame and reported nothing)."""
    from .cloth_job import START_FRAME

    n = _clip_header(clip).n_frames
    taken = -(-n // every)
    if taken <= START_FRAME:
        raise SystemExit(f"tryon: clip {clip} has {n} frame{'s' if n != 1 else ''}; taking one in {every}, a session "
                         f"starts at its frame {START_FRAME * every} (the first frame of a CMU clip is the "
                         f"converter's T-pose), so there is nothing to run. For one pose, write it as two motion "
                         f"rows (more for the garments to settle), with --every 1")


def _body_arguments(p) -> None:
    p.add_argument("--arm-clearance", type=float, default=None, metavar="DEG",
                   help="smallest angle between a hanging arm and the torso's axis; the copied arms are turned out "
                        "to it so they do not pass through a broader character (default 10; 0: copy exactly)")
    p.add_argument("--no-hand-clearance", action="store_true",
                   help="leave a hand where the copied arm puts it, even inside the hip or a thigh; by default the "
                        "arm turns out until the hand rests a few millimetres in front of the skin")
    p.add_argument("--no-skin-contact", action="store_true",
                   help="leave the skin as linear blend skinning makes it where the body cuts through itself (behind "
                        "a bent knee, at the hip crease); by default the two skins meet halfway there")


def _contact(args):
    from skinning.contact import ContactSettings

    return None if args.no_skin_contact else ContactSettings()


def _ik(args):
    from skinning.retarget import IKSettings

    ik = IKSettings()
    if args.no_hand_clearance:
        ik.hand_clearance = None
    if args.arm_clearance is None:
        return ik
    if not 0.0 <= args.arm_clearance < 90.0:
        raise SystemExit(f"tryon: --arm-clearance must be in [0, 90) degrees, got {args.arm_clearance}")
    ik.arm_clearance_deg = args.arm_clearance
    return ik


def _count(text: str) -> int:
    """--max-frames, --every: a whole number of frames, at least 1 (0 or less would run a session of
    no frames, or none at all, and report it as if it had run)."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number >= 1, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be a whole number >= 1, got {n}")
    return n


def _budget_ms(text: str) -> float:
    """A frame budget in milliseconds: a number > 0."""
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number of milliseconds > 0, got {text!r}") from None
    if not 0.0 < x < math.inf:
        raise argparse.ArgumentTypeError(f"must be a number of milliseconds > 0, got {text}")
    return x


FRAME_BUDGET_HELP = ("hold each session's frames in the cloth service (their wait and their step) within this "
                     "many milliseconds (the 90th percentile over half a second): over it the detailed surface "
                     "goes on at a lower tessellation level (down "
                     "to 3), back up to --level when that fits again; the garments' wrinkles are carried over "
                     "and displays read the new topology (output no longer bit-reproducible). Default: none, "
                     "the level stays")


def _seconds(text: str) -> float:
    """A duration, a pace or a wait: a number >= 0 (a negative one was taken as 0 here and there, or
    failed deep inside with "sleep length must be non-negative")."""
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text!r}") from None
    if not x >= 0.0:  # (NaN too)
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text}")
    return x


def _level(text: str) -> int:
    """--level: a PN tessellation level the cloth service serves (1 to MAX_LEVEL)."""
    from .protocol import MAX_LEVEL

    try:
        level = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer 1-{MAX_LEVEL}, got {text!r}") from None
    if not 1 <= level <= MAX_LEVEL:
        raise argparse.ArgumentTypeError(f"must be an integer 1-{MAX_LEVEL}, got {level}")
    return level


def _frame_list(text: str) -> list[int]:
    try:
        frames = [int(f) for f in text.split(",") if f.strip()]
    except ValueError:
        raise SystemExit(f"tryon: frames {text!r}: expected comma-separated frame numbers") from None
    if not frames or min(frames) < 0:
        raise SystemExit(f"tryon: frames {text!r}: expected frame numbers >= 0")
    return frames


def _start(args):
    """Data folder, output folder and (unless --no-png) a renderer, shared by the jobs."""
    out_dir = output_folder(args.out)
    renderer = None
    if not args.no_png:
        from .render import Renderer

        renderer = Renderer(360, 480)
    return data_dir(args.data), out_dir, renderer


def cmd_body(args) -> int:
    from skinning.body import load_body

    from .body_job import render_snapshots, run_clip, showcase_frames

    ik = _ik(args)
    if args.self_contact < 0:
        raise SystemExit(f"tryon: --self-contact must be 0 (off) or a frame interval, got {args.self_contact}")
    data, out_dir, renderer = _start(args)
    t0 = time.perf_counter()
    body = load_body(data)
    print(f"body: {len(body.vertices)} vertices ({body.n_visible} visible), {len(body.triangles)} triangles, "
          f"{len(body.skeleton.names)} bones, loaded in {time.perf_counter() - t0:.2f} s")
    for clip in _clips(data, args.clip):
        frames = showcase_frames(clip.stem, args.every)
        report = run_clip(body, clip, every=args.every, snapshot_frames=frames, max_frames=args.max_frames,
                          ik=ik, self_contact=args.self_contact, contact=_contact(args))
        print(report.summary())
        if renderer is not None and report.snapshots:
            print(f"  snapshots: {render_snapshots(body, report, out_dir, renderer)}")
    if renderer is not None:
        renderer.release()
    return 0


def cmd_cloth(args) -> int:
    from cloth.fabric import FabricError, fabric_choice, load_fabrics
    from cloth.surface import SurfaceSettings
    from skinning.body import load_body

    from .body_job import showcase_frames
    from .cloth_job import OUTFITS, START_FRAME, find_outfit, render_cloth_snapshots, run_cloth_clip

    if args.fabrics and not args.fabric:  # (it was read by nobody: the garments kept their presets)
        names = sorted(load_fabrics(args.fabrics))  # (a malformed file is named first)
        raise FabricError(f"--fabrics {args.fabrics} is the file --fabric picks from ({', '.join(names)}): name "
                          f'the fabric too, e.g. --fabric {names[0] if names else "NAME"} or '
                          f'--fabric "top=NAME,bottom=NAME"')
    ik = _ik(args)
    clips = _clips(data_dir(args.data), args.clip, every=args.every, check=bool(args.clip))  # before any output
    data, out_dir, renderer = _start(args)
    body = load_body(data)
    fabrics = fabric_choice(args.fabric, args.fabrics) if args.fabric else None
    surface = None if args.coarse_only else SurfaceSettings(level=args.level)
    outfits = [find_outfit(data, outfit) for outfit in args.outfit or list(OUTFITS)]  # all checked first
    with _compiling_ahead(data, outfits[0], surface is not None):
        for outfit_dir in outfits:
            for clip in clips:
                every = _every(args.every, clip)
                # the first frame is skipped (converter T-pose)
                frames = (_frame_list(args.frames) if args.frames
                          else showcase_frames(clip.stem, every, START_FRAME))
                report = run_cloth_clip(body, outfit_dir, clip, every=every, max_frames=args.max_frames,
                                        snapshot_frames=frames, fabrics=fabrics, surface=surface, ik=ik,
                                        contact=_contact(args))
                print(report.summary())
                if renderer is not None and report.snapshots:
                    path = render_cloth_snapshots(body, report, report.models, out_dir, renderer,
                                                  close_up=args.close_up)
                    print(f"  snapshots: {path}")
    if renderer is not None:
        renderer.release()
    return 0


def _compiling_ahead(data: Path, outfit, surface: bool):
    """On a first run, the detailed surface's kernels compiled in a second process meanwhile
    (`services.warmup`); nothing where there is no surface to step."""
    from .cloth_job import find_outfit
    from .warmup import compiling_ahead

    return compiling_ahead(data, find_outfit(data, outfit)) if surface else contextlib.nullcontext()


def _logging(args) -> None:
    import logging

    logging.basicConfig(level=logging.DEBUG if getattr(args, "verbose", False) else logging.INFO,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s", stream=sys.stderr)


def _spec(args, data: Path | None = None):
    """The outfit, fabric and level the options name; with `data`, checked first (an unknown outfit
    or fabric stops the command with a message, before any service starts)."""
    from cloth.fabric import fabric_choice

    from .cloth_job import find_outfit
    from .cloth_service import OutfitSpec

    if data is not None:
        find_outfit(data, args.outfit)
        if args.fabric:
            fabric_choice(args.fabric)
    return OutfitSpec(args.outfit, args.fabric, None if args.coarse_only else args.level)


def _wait(stop_check=None) -> None:
    """Block until Ctrl-C or SIGTERM (`kill`, `docker stop`, systemd), or stop_check() is true;
    the caller then closes what it holds (a recorder its file, a service its sessions)."""
    with _stop_on_signals() as stop:
        while not stop.wait(0.2) and (stop_check is None or not stop_check()):
            pass


@contextlib.contextmanager
def _stop_on_signals():
    """An Event that Ctrl-C (SIGINT) or SIGTERM sets, for loops that publish on the main thread.

    A KeyboardInterrupt raised wherever the main thread happens to be (inside a zenoh call,
    between taking a lock and the `with` block that releases it) can leave the service
    unable to send its end message and exit; the loop checks the Event between frames
    instead and ends the session cleanly."""
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def cmd_session(args) -> int:
    from skinning.body import load_body

    from .bus import bus_config_from_args, check_session_name
    from .session import run_session

    ik = _ik(args)
    data = data_dir(args.data)
    session = check_session_name(args.session)
    clip = _clips(data, [args.clip], every=args.every, check=True)[0]
    every = _every(args.every, clip)
    spec = _spec(args, data)
    cfg = bus_config_from_args(args)
    if args.serve and not args.listen:
        cfg.listen = ["tcp/0.0.0.0:7447"]  # remote displays and services connect here
    body = load_body(data)
    frames = _frame_list(args.snapshot_frames) if args.snapshot_frames else []
    level = args.level if not args.coarse_only else "coarse"
    print(f"session {session}: {clip.stem} at {1.0 / (_clip_header(clip).frame_time * every):.4g} Hz × {args.outfit} "
          f"(level {level}), "
          f"bus {cfg.mode} listening on {', '.join(cfg.listen) or 'nothing'}")
    if args.serve:
        print(f"  serving: rerun viewer `rerun --connect rerun+http://<this-host>:{args.port}/proxy`; "
              f"zenoh displays connect to {cfg.listen[0]}; Ctrl-C to stop")
    # Ctrl-C or SIGTERM ends the stream between frames; what was published is still simulated,
    # and the .rrd, the recording and the snapshots are closed as at the clip's end
    with _stop_on_signals() as stop, _compiling_ahead(data, args.outfit, spec.level is not None):
        result = run_session(body, data, clip, session, Path(args.out), spec, every=every,
                             max_frames=args.max_frames, bus_config=cfg,
                             serve_port=args.port if args.serve else None,
                             web_port=args.web_port if args.serve else None, record=not args.no_record,
                             snapshot_frames=frames, png=not args.no_png, progress=True if args.progress else None,
                             ik=ik, contact=_contact(args), stop=stop, rrd=not args.no_rrd,
                             min_free=_keep_free(args),
                             frame_budget=None if args.frame_budget_ms is None else args.frame_budget_ms / 1000.0)
    print(result.summary())
    return 0


def cmd_ingest(args) -> int:
    from skinning.body import load_body
    from skinning.source import BVHSource

    from .bus import Stats, bus_config_from_args, check_session_name
    from .cloth_job import START_FRAME, outfit_checker
    from .ingest import BusPoseSource, IngestService

    _logging(args)
    ik = _ik(args)
    data = data_dir(args.data)
    session = check_session_name(args.session)
    body = load_body(data)
    with bus_config_from_args(args).open() as bus, _stop_on_signals() as stop:
        if args.live:
            source = BusPoseSource(bus, session, Stats("ingest", session), wait_skeleton=args.wait, stop=stop)
            start = 0
        else:
            clip = _clips(data, [args.clip], every=args.every, check=True)[0]
            source = BVHSource(clip, pace=args.pace, loop=args.loop, every=_every(args.every, clip),
                               max_frames=args.max_frames, loop_from=START_FRAME)
            start = START_FRAME
        desc = {"outfit": args.outfit, "fabric": args.fabric, "level": None if args.coarse_only else args.level,
                "clip": "live" if args.live else Path(source.path).stem}
        svc = IngestService(bus, session, body, source, desc, ik=ik, contact=_contact(args),
                            check_outfit=outfit_checker(data), float32_meshes=args.float32_meshes)
        try:
            n = svc.run(start_frame=start, stop=stop, wait_subscribers=args.wait_subscribers,
                        wait_ready=args.wait_ready)
        finally:
            time.sleep(0.2)
            svc.close()
            source.close()
        print(f"ingest {session}: {n} body frames published; {svc.stats.snapshot()['counts']}")
    return 0


def cmd_outfit(args) -> int:
    from .bus import bus_config_from_args, check_session_name
    from .ingest import request_outfit

    session = check_session_name(args.session)
    with bus_config_from_args(args).open() as bus:
        try:
            answer = request_outfit(bus, session, args.name, args.fabric, None if args.coarse_only else args.level,
                                    set_level=args.coarse_only or args.level is not None, timeout=args.timeout,
                                    wait=args.wait)
        except ValueError as err:
            raise SystemExit(f"tryon outfit: {err}") from None
    if not answer.get("accepted"):
        raise SystemExit(f"tryon outfit: refused: {answer.get('reason', 'no reason given')}")
    if args.wait <= 0:
        print(f"session {session}: outfit {args.name} from the frame after {answer.get('after_frame')}")
    elif answer.get("worn"):
        print(f"session {session}: outfit {args.name} worn from frame {answer.get('frame')}")
    elif answer.get("worn") is None:
        raise SystemExit(f"tryon outfit: accepted, but {answer.get('reason')} (it may still come)")
    else:
        raise SystemExit(f"tryon outfit: not worn: {answer.get('reason', 'no reason given')}")
    return 0


def cmd_catalog(args) -> int:
    """What there is to wear: each outfit (in <data>/garments, or the ones --outfit names), its
    garments (the names `--fabric garment=preset` takes) with the fabric each is made of by
    default and whether it hangs from a waistband; then the fabrics (the presets, or --fabrics)."""
    from cloth.fabric import PRESETS_PATH, load_fabrics
    from cloth.garment import GarmentError, outfit_source, worn_from_waist
    from skinning.animate import BodyAnimator
    from skinning.body import load_body

    from .cloth_job import find_outfit, garment_fabric_list, outfit_garments, outfit_name

    data = data_dir(args.data)
    if args.outfit:
        paths = [find_outfit(data, name) for name in args.outfit]
    else:
        if not (data / "garments").is_dir():
            raise FileNotFoundError(f"data folder {data} has no garments/ folder (an outfit folder each: "
                                    f"--outfit PATH names one elsewhere)")
        paths = []
        for path in sorted((data / "garments").iterdir()):
            with contextlib.suppress(GarmentError):
                outfit_source(path)
                paths.append(path)
    body = load_body(data)
    animator = BodyAnimator(body, contact=None)
    print(f"outfits ({len(paths)}; --outfit NAME, or garments of several: --outfit A.top+B.bottom; "
          f"--fabric GARMENT=FABRIC,...):")
    for path in paths:
        garments, _, skin = outfit_garments(body, animator, path)
        worn = [f"{g.name} ({fab.name}{', waistband' if worn_from_waist(g, skin) else ''})"
                for g, fab in zip(garments, garment_fabric_list(path, garments))]
        print(f"  {outfit_name(path)}: {', '.join(worn)}")
    source = Path(args.fabrics) if args.fabrics else PRESETS_PATH
    fabrics = load_fabrics(source)
    print(f"fabrics ({source}; --fabric NAME):")
    for name, f in fabrics.items():
        print(f"  {name}: stretch {f.stretch_stiffness:g} N/m, compression {f.compression_stiffness:g} N/m, "
              f"bending {f.bending_stiffness:g} N/m, density {f.density:g} kg/m², friction {f.friction:g}, "
              f"thickness {f.thickness * 1000:g} mm, strain limit {f.max_strain * 100:g} %")
    return 0


def cmd_cloth_service(args) -> int:
    from skinning.body import load_body

    from .bus import bus_config_from_args
    from .cloth_service import ClothService

    _logging(args)
    if not args.spin_ms >= 0.0:
        raise SystemExit(f"tryon cloth-service: --spin-ms must be 0 or more, got {args.spin_ms}")
    cpus = None
    if args.pin_cores == "auto":
        cpus = default_cpus()
    elif args.pin_cores != "none":
        try:
            cpus = check_cpus(int(c) for c in args.pin_cores.split(","))
        except ValueError as err:  # also a value that is not an integer
            raise SystemExit(f"tryon cloth-service: --pin-cores {args.pin_cores!r}: {err}") from None
    data = data_dir(args.data)
    spec = _spec(args, data)  # the default outfit and fabric
    body = load_body(data)
    with bus_config_from_args(args).open() as bus, _compiling_ahead(data, args.outfit, spec.level is not None):
        svc = ClothService(bus, body, data, spec, idle_seconds=args.idle, catch_up=args.catch_up,
                           spin=args.spin_ms / 1000.0, cpus=cpus, float32_meshes=args.float32_meshes,
                           frame_budget=None if args.frame_budget_ms is None else args.frame_budget_ms / 1000.0
                           ).start()
        print(f"cloth service ready (default outfit {args.outfit}); Ctrl-C to stop", flush=True)
        _wait()
        svc.stop()
    return 0


def _keep_free(args) -> int:
    """--keep-free GB in bytes."""
    if args.keep_free < 0:
        raise ValueError(f"--keep-free must be >= 0 GB, got {args.keep_free}")
    return int(args.keep_free * 1e9)


def _keep_free_argument(p) -> None:
    p.add_argument("--keep-free", type=float, default=DEFAULT_MIN_FREE / 1e9, metavar="GB",
                   help="disk space the recordings leave free: each is finished, complete, when less is left "
                        f"and the session goes on (default {DEFAULT_MIN_FREE / 1e9:.2f})")


def cmd_viewer(args) -> int:
    from .bus import bus_config_from_args, check_session_name
    from .viewer import RecordingSink, ViewerBridge

    _logging(args)
    session = check_session_name(args.session)
    if not (args.save or args.spawn or args.serve):
        raise ValueError("viewer: choose at least one of --save FILE.rrd, --spawn, --serve")
    with bus_config_from_args(args).open() as bus:
        sink = RecordingSink(session, rrd=args.save, spawn=args.spawn, serve_port=args.port if args.serve else None,
                             web_port=args.web_port, min_free=_keep_free(args))
        bridge = ViewerBridge(bus, session, sink).start()
        if sink.url:
            print(f"viewer: serving {sink.url}", flush=True)
        _wait(lambda: args.until_end and bridge.ended.is_set())
        time.sleep(0.3)
        bridge.stop()
        path = sink.close()
        print(f"viewer {session}: {bridge.stats.snapshot()['counts']}" + (f"; wrote {path}" if path else "")
              + (f" (finished early: {sink.stopped})" if sink.stopped else ""))
    return 0


def cmd_record(args) -> int:
    from .bus import bus_config_from_args, check_session_name, key
    from .protocol import MessageError, decode
    from .recorder import Recorder

    _logging(args)
    session = check_session_name(args.session)
    ended = []
    with bus_config_from_args(args).open() as bus:
        rec = Recorder(bus, session, args.out, min_free=_keep_free(args))

        def on_control(sample):
            try:
                m = decode(sample.payload.to_bytes(), str(sample.key_expr), session, "control")
                if m.meta.get("event") == "end" and m.meta.get("from") == "ingest":
                    ended.append(time.monotonic())
            except MessageError:
                pass

        sub = bus.declare_subscriber(key(session, "control"), on_control)
        print(f"recording {key(session, '**')} -> {args.out}; Ctrl-C to stop", flush=True)
        # after the end of the body stream, wait for the garments still being computed
        _wait(lambda: bool(ended) and time.monotonic() - ended[0] > args.linger)
        sub.undeclare()
        path = rec.close()
        print(f"recorder {session}: {rec.messages} messages -> {path}"
              + (f" (finished early: {rec.stopped})" if rec.stopped else ""))
    return 0


def cmd_replay(args) -> int:
    from .bus import bus_config_from_args
    from .recorder import replay

    _logging(args)
    kinds = set(args.only.split(",")) if args.only else None
    with bus_config_from_args(args).open() as bus:
        n = replay(bus, args.recording, session=args.session, speed=args.speed, kinds=kinds, linger=args.linger,
                   wait_subscribers=args.wait_subscribers)
        print(f"replay: {n} messages from {args.recording}")
    return 0


def cmd_capture(args) -> int:
    from skinning.source import BVHSource

    from .bus import bus_config_from_args, check_session_name
    from .cloth_job import START_FRAME
    from .ingest import publish_capture

    data = data_dir(args.data)
    session = check_session_name(args.session)
    clip = _clips(data, [args.clip], every=args.every, check=True)[0]
    with bus_config_from_args(args).open() as bus, \
            BVHSource(clip, pace=args.pace, every=_every(args.every, clip), max_frames=args.max_frames) as source:
        with _stop_on_signals() as stop:
            n = publish_capture(bus, session, source, start_frame=START_FRAME, stop=stop,
                                wait_subscribers=args.wait_subscribers)
        print(f"capture {session}: {n} poses published")
    return 0


def cmd_router(args) -> int:
    from .bus import BusConfig

    cfg = BusConfig(mode="router", listen=args.listen or ["tcp/0.0.0.0:7447"], connect=args.connect or [],
                    config_file=args.zenoh_config)
    with cfg.open() as bus:
        print(f"zenoh router {bus.info.zid()} listening on {', '.join(cfg.listen)}; Ctrl-C to stop", flush=True)
        _wait()
    return 0


def _outfit_arguments(p, level_default: int = 6) -> None:
    p.add_argument("--outfit", default="female_casualsuit01", help=OUTFIT_HELP)
    p.add_argument("--fabric", help=FABRIC_HELP)
    p.add_argument("--level", type=_level, default=level_default, help="PN tessellation level (default 6)")
    p.add_argument("--coarse-only", action="store_true", help="coarse cloth only (S101), no detailed surface")


FABRIC_HELP = ("a fabric preset for every garment, or one per garment: garment=preset pairs, "
               "\"top=silk,bottom=denim\" (a garment by its name or the part after its outfit's; default: a preset "
               "per garment)")
OUTFIT_HELP = ("outfit folder in <data>/garments, or a path: a MakeHuman outfit folder (.mhclo), a garment mesh "
               "(OBJ, PLY, GLB, ...) in metres already on the rest body (Y up, feet at y = 0, facing +Z), or a folder "
               "of those; or garments of the outfits there mixed, joined by '+' "
               "(female_casualsuit01.top+female_elegantsuit01.bottom); of two made for the same depth (two tops) the "
               "later is worn over the earlier")


class _Parser(argparse.ArgumentParser):
    """No option prefixes: `catalog --out X` would otherwise be read as `--outfit X` and the error
    would name X as an outfit."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)


def main(argv: list[str] | None = None) -> int:
    _clip_header.cache_clear()  # (a clip's header read once per command, afresh for the next)
    parser = _Parser(prog="tryon", description="Real-time virtual try-on.")
    parser.add_argument("--data", help=f"data folder (default: ${ENV_VAR} or ../shared/data)")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    p = sub.add_parser("body", help="retarget and skin motion clips; print timings, write PNG snapshots")
    p.add_argument("--clip", action="append", help="clip name in <data>/mocap or a BVH path (repeatable; default all)")
    p.add_argument("--out", default="out", help="output folder (default out/)")
    p.add_argument("--every", type=_count, default=1, help="take one frame in N (2: 120 Hz clips at 60 Hz)")
    p.add_argument("--max-frames", type=_count, default=None, help="stop each clip after N frames")
    p.add_argument("--no-png", action="store_true", help="skip rendering snapshots")
    p.add_argument("--self-contact", type=int, default=0, metavar="N",
                   help="every N-th frame, count the clothed skin vertices inside the body (where skinning makes "
                        "it cut through itself), per region (default 0: off)")
    _body_arguments(p)
    p.set_defaults(func=cmd_body)
    p = sub.add_parser("cloth", help="cloth (S101-S106) of outfits on motion clips; timings and PNG snapshots")
    p.add_argument("--level", type=_level, default=6,
                   help="PN tessellation level of the detailed surface (default 6)")
    p.add_argument("--coarse-only", action="store_true", help="only the coarse cloth (S101), no detailed surface")
    p.add_argument("--outfit", action="append", help=OUTFIT_HELP + " (default all)")
    p.add_argument("--clip", action="append", help="clip name in <data>/mocap or a BVH path (default all)")
    p.add_argument("--fabric", help=FABRIC_HELP + "; the fabrics from --fabrics")
    p.add_argument("--fabrics", help="TOML file of fabrics (default: the presets, cloth/fabrics.toml)")
    p.add_argument("--out", default="out", help="output folder (default out/)")
    p.add_argument("--every", type=_count, default=None, help=EVERY_HELP)
    p.add_argument("--max-frames", type=_count, default=None, help="stop each clip after N frames")
    p.add_argument("--no-png", action="store_true", help="skip rendering snapshots")
    p.add_argument("--frames", help="snapshot frames, comma-separated session frame numbers (default: a showcase "
                   "per clip)")
    p.add_argument("--close-up", action="store_true", help="snapshots from nearer, larger: the folds of the surface")
    _body_arguments(p)
    p.set_defaults(func=cmd_cloth)

    from .bus import add_bus_arguments

    p = sub.add_parser("session", help="a whole try-on session in one process: ingest, cloth, viewer (.rrd), "
                                       "recording (.mcap), PNG snapshots, timings")
    p.add_argument("--clip", default="cmu_131_01_walk_3dsmax", help="clip name in <data>/mocap or a BVH path")
    _outfit_arguments(p)
    p.add_argument("--session", default="demo", help="session name (default demo)")
    p.add_argument("--out", default="out", help="output folder (default out/)")
    p.add_argument("--every", type=_count, default=None, help=EVERY_HELP)
    p.add_argument("--max-frames", type=_count, default=None, help="stop after N frames")
    p.add_argument("--snapshot-frames", default="60,150,240,420",
                   help="frames to render as PNG (comma-separated; default 60,150,240,420)")
    p.add_argument("--serve", action="store_true", help="stay live: clip at its own pace, looped; rerun served "
                                                         "for remote viewers; bus on tcp/0.0.0.0:7447; Ctrl-C stops")
    p.add_argument("--port", type=int, default=9876, help="rerun gRPC port with --serve (default 9876)")
    p.add_argument("--web-port", type=int, default=None, help="also serve rerun's web viewer on this port")
    p.add_argument("--no-record", action="store_true", help="do not write the bus recording")
    p.add_argument("--no-rrd", action="store_true", help="do not write the rerun recording (.rrd)")
    p.add_argument("--frame-budget-ms", type=_budget_ms, default=None, metavar="MS", help=FRAME_BUDGET_HELP)
    _keep_free_argument(p)
    p.add_argument("--no-png", action="store_true", help="skip the PNG snapshots")
    p.add_argument("--progress", action="store_true", help="progress bar even when stderr is not a terminal")
    _body_arguments(p)
    add_bus_arguments(p)
    p.set_defaults(func=cmd_session)

    p = sub.add_parser("ingest", help="mocap-ingest service: BVH file or live pose stream -> tryon/<s>/body")
    p.add_argument("--session", default="demo")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--clip", default="cmu_131_01_walk_3dsmax", help="BVH clip (name or path)")
    src.add_argument("--live", action="store_true", help="read tryon/<s>/skeleton + tryon/<s>/pose from the bus")
    p.add_argument("--wait", type=_seconds, default=30.0, help="--live: seconds to wait for the skeleton")
    p.add_argument("--pace", default="realtime", choices=("realtime", "fast"), help="BVH pacing (default realtime)")
    p.add_argument("--loop", action="store_true", help="loop the clip")
    p.add_argument("--every", type=_count, default=None, help=EVERY_HELP)
    p.add_argument("--max-frames", type=_count, default=None)
    p.add_argument("--wait-subscribers", type=_seconds, default=10.0,
                   help="wait up to this many seconds for a body subscriber (cloth service) before the first frame")
    p.add_argument("--wait-ready", type=_seconds, default=30.0,
                   help="wait up to this many seconds for the cloth service to fit the outfit (pre-roll)")
    p.add_argument("--float32-meshes", action="store_true",
                   help="publish the body's vertices as float32 (12 bytes a vertex) rather than on a 16-bit grid "
                        "(6 bytes, at most 14 µm off)")
    _outfit_arguments(p)
    _body_arguments(p)
    add_bus_arguments(p)
    p.set_defaults(func=cmd_ingest)

    p = sub.add_parser("outfit", help="change the outfit of a running session (its ingest announces it again)")
    p.add_argument("name", help="outfit in the session's <data>/garments, or a path the cloth service can read "
                               "(as --outfit)")
    p.add_argument("--session", default="demo")
    p.add_argument("--fabric", help=FABRIC_HELP.replace("a preset per garment", "the session's"))
    p.add_argument("--level", type=_level, default=None, help="PN tessellation level (default: the session's)")
    p.add_argument("--coarse-only", action="store_true", help="coarse cloth only (S101), no detailed surface")
    p.add_argument("--timeout", type=_seconds, default=5.0, help="seconds to wait for the session's ingest to answer")
    p.add_argument("--wait", type=_seconds, default=60.0,
                   help="seconds to wait, once accepted, until the garments are on (the cloth service fits and "
                        "settles them; 0: return once accepted)")
    add_bus_arguments(p)
    p.set_defaults(func=cmd_outfit)

    p = sub.add_parser("catalog", help="the outfits (their garments and fabrics) and the fabric presets")
    p.add_argument("--outfit", action="append", help=OUTFIT_HELP + " (default: every one in <data>/garments)")
    p.add_argument("--fabrics", help="TOML file of fabrics to list (default: the presets, cloth/fabrics.toml)")
    p.set_defaults(func=cmd_catalog)

    p = sub.add_parser("cloth-service", help="cloth service: tryon/*/body -> tryon/<s>/garment/<name>, every session")
    _outfit_arguments(p)
    p.add_argument("--idle", type=_seconds, default=60.0, help="drop a session silent for this many seconds")
    p.add_argument("--catch-up", action="store_true",
                   help="when behind, simulate every body frame but build and publish the detailed surface only "
                        "for the newest (live displays stay current; output no longer bit-reproducible)")
    p.add_argument("--pin-cores", metavar="LIST", default="auto",
                   help="keep the serving thread on the first of these cores and a garment thread on each of the "
                        "others, e.g. 0,1; 'auto' (default): the process's cores, where there are two or more "
                        "and the platform pins threads (Linux); 'none': unpinned, one garment thread per core")
    p.add_argument("--spin-ms", type=_seconds, default=1000.0 * LIVE_SPIN,
                   help="after each frame, poll this long for the next before sleeping (default 20: a 60 Hz "
                        "session keeps the cores awake; an idle core can wake a millisecond late; 0: never poll)")
    p.add_argument("--float32-meshes", action="store_true",
                   help="publish garment positions and normals as float32 (24 bytes a vertex) rather than on a "
                        "16-bit grid with octahedral normals (10 bytes, at most 8 um and 0.004 deg off)")
    p.add_argument("--frame-budget-ms", type=_budget_ms, default=None, metavar="MS", help=FRAME_BUDGET_HELP)
    add_bus_arguments(p)
    p.set_defaults(func=cmd_cloth_service)

    p = sub.add_parser("viewer", help="viewer bridge: a session -> rerun (.rrd file, local viewer, or served)")
    p.add_argument("--session", default="demo")
    p.add_argument("--save", help="write the rerun recording to this .rrd file")
    p.add_argument("--spawn", action="store_true", help="spawn a local rerun viewer")
    p.add_argument("--serve", action="store_true", help="serve over gRPC for remote rerun viewers")
    p.add_argument("--port", type=int, default=9876, help="gRPC port with --serve (default 9876)")
    p.add_argument("--web-port", type=int, default=None, help="also serve rerun's web viewer on this port")
    p.add_argument("--until-end", action="store_true", help="stop when the session's body stream ends")
    _keep_free_argument(p)
    add_bus_arguments(p)
    p.set_defaults(func=cmd_viewer)

    p = sub.add_parser("record", help="record every bus message of a session to an MCAP file")
    p.add_argument("--session", default="demo")
    p.add_argument("--out", required=True, help="the .mcap file")
    p.add_argument("--linger", type=_seconds, default=2.0, help="seconds to keep recording after the body stream ends")
    _keep_free_argument(p)
    add_bus_arguments(p)
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("replay", help="replay an MCAP recording onto the bus")
    p.add_argument("recording")
    p.add_argument("--session", help="publish under this session name (default: the recorded one)")
    p.add_argument("--speed", type=_seconds, default=1.0,
                   help="1 original pace, 2 twice as fast, 0 as fast as possible")
    p.add_argument("--only", help="only these kinds, e.g. session,topology,body (feeds a fresh cloth service)")
    p.add_argument("--linger", type=_seconds, default=2.0, help="keep answering topology queries this long at the end")
    p.add_argument("--wait-subscribers", type=_seconds, default=0.0,
                   help="wait up to this many seconds for a subscriber on each key before its first message")
    add_bus_arguments(p)
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("capture", help="publish a BVH clip as a live pose stream (reference capture publisher)")
    p.add_argument("--session", default="demo")
    p.add_argument("--clip", default="cmu_131_01_walk_3dsmax")
    p.add_argument("--pace", default="realtime", choices=("realtime", "fast"))
    p.add_argument("--every", type=_count, default=None, help=EVERY_HELP)
    p.add_argument("--max-frames", type=_count, default=None)
    p.add_argument("--wait-subscribers", type=_seconds, default=10.0,
                   help="wait up to this many seconds for a pose subscriber (mocap-ingest) before the first pose")
    add_bus_arguments(p)
    p.set_defaults(func=cmd_capture)

    p = sub.add_parser("router", help="a zenoh router for several machines")
    p.add_argument("--listen", action="append", help="endpoint (default tcp/0.0.0.0:7447)")
    p.add_argument("--connect", action="append", help="another router to connect to")
    p.add_argument("--zenoh-config", help="zenoh JSON5 config file")
    p.set_defaults(func=cmd_router)
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (FileNotFoundError, ValueError, TimeoutError) as exc:
        print(f"tryon: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
