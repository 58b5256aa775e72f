"""`tryon session`: a whole try-on session in one process on the embedded bus.

mocap-ingest (a BVH clip) -> cloth -> viewer bridge (.rrd) + recorder (.mcap) + PNG snapshots,
all talking over one zenoh peer session exactly as separate processes would. Offline, the
ingest waits for the cloth service (at most `window` frames ahead) so that no frame queues up;
with `serve`, the clip plays at its own pace, looped, for remote displays until Ctrl-C.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from skinning.body import Body
from skinning.contact import ContactSettings
from skinning.retarget import IKSettings
from skinning.source import BVHSource

from .bus import BusConfig, key, parse_key
from .cloth_job import START_FRAME, outfit_checker
from .cloth_service import ClothService, OutfitSpec
from .ingest import IngestService
from .protocol import MessageError, decode
from .diskspace import DEFAULT_MIN_FREE
from .outputs import output_folder
from .recorder import Recorder
from .spin import LIVE_SPIN
from .viewer import RecordingSink, VertexNormals, ViewerBridge, triangles_problem
from .wire import body_vertices, garment_mesh

# how long the ingest waits for its in-process cloth service to report the session ready (or failed)
EMBEDDED_WAIT_READY = 1800.0


class SessionFailed(ValueError):
    """The session's own cloth service cannot serve its outfit (the message says why): there is
    nothing to try on, so the session stops after its first frame, its recordings finished."""


class SessionTap:
    """Sees every body and garment message of a session (in order, none dropped): per-stage timings,
    end-to-end latency, and copies of the frames wanted as snapshots."""

    def __init__(self, bus, session: str, snapshot_frames: set[int], window: int = 1):
        """window: each snapshot frame and the window - 1 after it are kept, for a live session
        whose cloth service publishes only the newest of the frames it fell behind on (catch-up):
        the snapshot is the first of them with the most garments."""
        self.session = session
        self.snapshot_frames = sorted(snapshot_frames)
        self.wanted = {f + k for f in snapshot_frames for k in range(window)}
        self.window = window
        self.timings: dict[str, list[float]] = {}
        self.latency_ms: list[float] = []
        self.frames: dict[int, dict[str, tuple[np.ndarray, np.ndarray]]] = {}
        self.garment_frames = 0
        self.last_garment_frame = -1
        self.rejected = 0
        # every garment topology published while it runs, by (entity, vertex count): a snapshot frame's
        # garment is drawn with the topology of its own level, outfit or fabric, whatever came after it
        self.topologies: dict[tuple[str, int], dict] = {}
        self._lock = threading.Lock()
        self._subs = [bus.declare_subscriber(key(session, "body"), self),
                      bus.declare_subscriber(key(session, "garment", "*"), self),
                      bus.declare_subscriber(key(session, "topology", "garment", "*"), self._on_topology)]

    def _on_topology(self, sample) -> None:
        k = str(sample.key_expr)
        try:
            _, parts = parse_key(k)
            msg = decode(sample.payload.to_bytes(), k, self.session, parts[0])
            tris = np.array(msg.arrays["triangles"])
            n = msg.meta.get("n_vertices")
            problem = triangles_problem(tris, n)  # (the viewer bridge's check of a latched topology)
            if problem:
                raise MessageError(k, problem)
        except (MessageError, KeyError):
            self.rejected += 1
            return
        color = msg.meta.get("color", [0.7, 0.7, 0.7])
        with self._lock:
            self.topologies["world/" + "/".join(parts[1:]), n] = {
                "triangles": tris, "n_vertices": n, "color": tuple(float(c) for c in color[:3]), "shading": None}

    def __call__(self, sample) -> None:
        now = time.time_ns()
        k = str(sample.key_expr)
        try:
            _, parts = parse_key(k)
            msg = decode(sample.payload.to_bytes(), k, self.session, parts[0])
        except MessageError:
            self.rejected += 1
            return
        with self._lock:
            for name, v in msg.meta.items():
                if name.endswith("_ms"):
                    self.timings.setdefault(name if msg.kind == "body" else f"{parts[-1]}:{name}", []).append(v)
            if msg.kind == "garment" and "preroll_s" not in msg.meta:  # a first frame that waited for a pre-roll
                self.latency_ms.append((now - msg.origin_ns) / 1e6)
                self.garment_frames += 1
                self.last_garment_frame = max(self.last_garment_frame, msg.frame)
            if msg.frame in self.wanted:
                if msg.kind == "body":
                    pos, normals = body_vertices(msg.arrays), msg.arrays.get("normals")  # normals: none since schema 2
                else:
                    pos, normals = garment_mesh(msg.arrays)
                self.frames.setdefault(msg.frame, {})["/".join(parts)] = (
                    pos.copy(), None if normals is None else normals.copy())

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()


@dataclass
class SessionResult:
    session: str
    frames: int
    seconds: float
    rrd: Path | None
    recording: Path | None
    snapshots: Path | None
    stats: dict = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)  # median ms
    latency_ms: tuple[float, float] = (0.0, 0.0)  # p50, p99
    setup_seconds: float = 0.0  # of `seconds`: until the first body frame went out (models, kernels, pre-roll)
    live: bool = False  # served (--serve): frames at the clip's pace, not back to back

    def summary(self) -> str:
        streamed = max(self.seconds - self.setup_seconds, 1e-9)
        lines = [f"session {self.session}: {self.frames} frames in {self.seconds:.1f} s "
                 f"(setup {self.setup_seconds:.1f} s: "
                 f"garment models, pre-roll, and on a first run numba compiling; then "
                 f"{max(self.frames - 1, 0) / streamed:.1f} frames/s)"]
        body = {k: v for k, v in self.timings.items() if ":" not in k}
        lines.append("  body   median ms/frame: " + "  ".join(f"{k[:-3]} {v:.2f}" for k, v in body.items()))
        garments = sorted({k.split(":")[0] for k in self.timings if ":" in k})
        for g in garments:
            lines.append(f"  {g}  median ms/frame: " + "  ".join(
                f"{k.split(':')[1][:-3]} {v:.2f}" for k, v in self.timings.items() if k.startswith(g + ":")))
        how = "live, at the clip's pace" if self.live else "offline, one frame queued"
        lines.append(f"  body frame published -> garment mesh received ({how}): "
                     f"p50 {self.latency_ms[0]:.1f} ms, "
                     f"p99 {self.latency_ms[1]:.1f} ms")
        for what, s in self.stats.items():
            c = s["counts"]
            lines.append(f"  {what}: " + ", ".join(f"{k} {v}" for k, v in c.items())
                         + (f", level at the end {s['values']['level']}" if c.get("level_changes") else ""))
        stopped = {"rerun": self.stats.get("viewer", {}).get("values", {}).get("rrd_stopped"),
                   "recording": self.stats.get("recorder", {}).get("values", {}).get("stopped")}
        for label, p in (("rerun", self.rrd), ("recording", self.recording), ("snapshots", self.snapshots)):
            if p is not None:
                lines.append(f"  {label}: {p}" + (f" (finished early: {stopped[label]})" if stopped.get(label) else ""))
        return "\n".join(lines)


class Progress:
    """A one-line progress bar on stderr (only when it is a terminal, or when forced)."""

    def __init__(self, total: int | None, enabled: bool | None = None):
        self.total = total
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self.start = time.perf_counter()
        self._last = 0.0

    def update(self, n: int, force: bool = False) -> None:
        now = time.perf_counter()
        if not self.enabled or (not force and now - self._last < 0.25):
            return
        self._last = now
        rate = n / max(now - self.start, 1e-9)
        if self.total:
            done = int(30 * min(n, self.total) / self.total)
            bar = f"[{'#' * done}{'.' * (30 - done)}] {n}/{self.total}"
        else:
            bar = f"{n} frames"
        sys.stderr.write(f"\r  {bar}  {rate:5.1f} frames/s ")
        sys.stderr.flush()

    def finish(self, n: int) -> None:
        if self.enabled:
            self.update(n, force=True)
            sys.stderr.write("\n")


def snapshot_choice(tap: SessionTap) -> list[int]:
    """The frame drawn for each snapshot frame: in its window, the first with the body and the
    most garments (none where no frame of it has a garment)."""
    frames = []
    for w in tap.snapshot_frames:
        window = [f for f in range(w, w + tap.window) if "body" in tap.frames.get(f, {}) and len(tap.frames[f]) > 1]
        if window:
            frames.append(max(window, key=lambda f: (len(tap.frames[f]), -f)))
    return frames


def render_session_snapshots(body: Body, tap: SessionTap, topology: dict, out: Path) -> Path | None:
    from .render import MeshDraw, Renderer, contact_sheet, orbit_camera, save_png

    frames = snapshot_choice(tap)
    if not frames:
        return None
    renderer = Renderer(360, 480)
    images = []
    try:
        for f in frames:
            meshes = []
            for name, (pos, normals) in sorted(tap.frames[f].items()):
                ent = "world/" + name
                topo = topology.get(ent)
                if topo is None or len(pos) != topo["n_vertices"]:
                    # a garment of another level than the last (a frame budget, an outfit change): its own
                    topo = tap.topologies.get((ent, len(pos)))
                    if topo is None:
                        continue
                color = topo.get("color", (0.7, 0.7, 0.7))
                if normals is None:  # the body's: the viewer bridge's normals for it, when it built them
                    shading = topo.get("shading") or VertexNormals(topo["triangles"], len(pos))
                    normals = shading(pos)
                meshes.append(MeshDraw(pos.astype(np.float64), topo["triangles"], normals.astype(np.float64),
                                       tuple(color)))
            verts = tap.frames[f]["body"][0]
            centre = np.array([verts[:, 0].mean(), verts[:, 1].min() + 0.5 * np.ptp(verts[:, 1]), verts[:, 2].mean()])
            for az in (0.0, 150.0):
                images.append(renderer.render(meshes, orbit_camera(centre, az, distance=3.6, height=0.2)))
    finally:
        renderer.release()
    save_png(out, contact_sheet(images, columns=4))
    return out


def run_session(body: Body, data: Path, clip: Path, session: str, out_dir: Path, spec: OutfitSpec,
                every: int = 2, max_frames: int | None = None, bus_config: BusConfig | None = None,
                serve_port: int | None = None, web_port: int | None = None, record: bool = True,
                snapshot_frames: list[int] | None = None, png: bool = True, progress: bool | None = None,
                window: int = 1, stop: threading.Event | None = None, ik: IKSettings | None = None,
                contact: ContactSettings | None = ContactSettings(), rrd: bool = True,
                min_free: int = DEFAULT_MIN_FREE, frame_budget: float | None = None) -> SessionResult:
    """Run one session end to end in this process (see the module docstring). rrd, record: write
    the rerun and bus recordings; min_free: bytes they leave free on their disk (each is finished,
    complete, when fewer are: services.diskspace); frame_budget: the cloth service's
    (`ClothService`: seconds a frame may spend there, held by the level; None: the level stays)."""
    output_folder(out_dir)
    serve = serve_port is not None
    bus = (bus_config or BusConfig()).open()
    t_start = time.perf_counter()
    cloth = viewer = sink = recorder = tap = None
    try:
        # live (--serve): frames come at the clip's pace, and the service polls between them as
        # `tryon cloth-service` does; offline they come back to back and it never waits
        cloth = ClothService(bus, body, data, spec, sessions=session, catch_up=serve,
                             spin=LIVE_SPIN if serve else 0.0, frame_budget=frame_budget).start()
        sink = RecordingSink(session, rrd=out_dir / f"{session}.rrd" if rrd else None, serve_port=serve_port,
                             web_port=web_port, min_free=min_free)
        viewer = ViewerBridge(bus, session, sink, lossless=not serve).start()
        recorder = Recorder(bus, session, out_dir / f"{session}.mcap", min_free=min_free) if record else None
        tap = SessionTap(bus, session, set(snapshot_frames or []) if png else set(), window=8 if serve else 1)
        source = BVHSource(clip, pace="realtime" if serve else "fast", loop=serve, every=every,
                           max_frames=max_frames, loop_from=START_FRAME)
        total = None if serve else -(-source.header.n_frames // every) - START_FRAME
        if total and max_frames:
            total = min(total, max_frames - START_FRAME)
        bar = Progress(total, progress)
        description = {"outfit": spec.outfit, "fabric": spec.fabric, "level": spec.level, "clip": clip.stem}
        ingest = IngestService(bus, session, body, source, description, ik=ik, contact=contact,
                               check_outfit=outfit_checker(data))
        # one description + the body topology are latched before the first frame

        streaming_since = []  # when the first frame was out (the setup waits before it)
        failed: list[str] = []

        def before_frame(index: int) -> bool:
            if ingest.frames == 1 and ingest.cloth_failed is not None:
                failed.append(ingest.cloth_failed)  # the outfit the session was started with cannot be worn
                return False
            if ingest.frames and not streaming_since:
                streaming_since.append(time.perf_counter())
            if not serve:  # flow control: stay at most `window` frames ahead of the cloth
                cloth.wait_processed(ingest.frames - window)
            bar.update(ingest.frames)
            return True

        try:
            # the cloth service is ours: it reports ready, or failed, however long a first run's
            # compiling takes (over 5 minutes on a slow machine); the limit only guards a hang
            ingest.run(start_frame=START_FRAME, before_frame=before_frame, stop=stop, wait_subscribers=10,
                       wait_ready=EMBEDDED_WAIT_READY)
        except KeyboardInterrupt:
            ingest.end()
        if failed:
            raise SessionFailed(f"session {session}: the cloth service cannot serve it: {failed[0]}")
        # everything published so far is simulated, shown and recorded before the files close
        cloth.wait_processed(ingest.frames + 1, timeout=120)
        deadline = time.monotonic() + 10
        while tap.last_garment_frame < ingest.last_index and time.monotonic() < deadline:
            time.sleep(0.02)
        # a garment is published from its stepping thread before the service counts the body
        # frame it came from: the counts are read once that frame is counted too
        gs = cloth.sessions.get(session)
        while gs is not None and gs.stats.counts["received"] < ingest.frames and time.monotonic() < deadline:
            time.sleep(0.005)
        bar.finish(ingest.frames)
        seconds = time.perf_counter() - t_start
        stats = {"ingest": ingest.stats.snapshot()}
        stats["cloth"] = gs.stats.snapshot() if gs is not None else cloth.closed_stats.get(session, {"counts": {}})
        time.sleep(0.1)
        viewer.stop()
        stats["viewer"] = viewer.stats.snapshot()
        rrd = sink.close()
        rec_path = recorder.close() if recorder else None
        if recorder:
            stats["recorder"] = recorder.stats.snapshot()
        snap = None
        if png:
            # the garments worn before an outfit change too
            snap = render_session_snapshots(body, tap, {**viewer.worn_before, **viewer.topology},
                                            out_dir / f"{session}.png")
        lat = np.array(tap.latency_ms) if tap.latency_ms else np.zeros(1)
        timings = {k: float(np.median(v)) for k, v in tap.timings.items()}
        ingest.close()
        setup = (streaming_since[0] if streaming_since else time.perf_counter()) - t_start
        return SessionResult(session, ingest.frames, seconds, rrd, rec_path, snap, stats, timings,
                             (float(np.percentile(lat, 50)), float(np.percentile(lat, 99))), min(setup, seconds),
                             live=serve)
    finally:
        # (done already unless the session failed: both may be called again)
        if viewer is not None:
            viewer.stop()
        if sink is not None:
            sink.close()
        if tap is not None:
            tap.close()
        if cloth is not None:
            cloth.stop()
        if recorder is not None:
            recorder.close()
        bus.close()
