"""viewer bridge: a session's body and garments on the bus -> rerun (file, local viewer, or served).

Topology (triangles, colour) is fetched from the latched tryon/<s>/topology/** and logged once as
static data; per frame only vertex positions and normals are logged. The bridge keeps only the
latest message per key: a viewer that lags shows the newest frame, and every frame overwritten
before it was shown is counted as dropped (stats `dropped`) - it never holds the pipeline back.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import zenoh

from skinning.skin import MeshNormals

from .bus import Stats, fetch_latched, key, parse_key
from .diskspace import DEFAULT_MIN_FREE, SpaceGuard
from .outputs import output_file
from .protocol import MessageError, decode
from .wire import body_vertices, garment_mesh, vertex_count

log = logging.getLogger("tryon.viewer")


def session_layout() -> rrb.Blueprint:
    """The viewer's default layout: the body and garments large, the per-stage timings, the
    latency and the tessellation level of each garment in a column beside them (rerun's
    automatic layout gives every plot as much room as the 3D view)."""
    return rrb.Blueprint(
        rrb.Horizontal(
            # the camera follows the body: a walk leaves the place where it started
            rrb.Spatial3DView(origin="/world", name="try-on",
                              eye_controls=rrb.EyeControls3D(tracking_entity="/world/body")),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="/stats/stages", name="stage ms per garment"),
                rrb.TimeSeriesView(origin="/stats/latency", name="latency ms, body published → garment shown"),
                # (a frame budget changes it: `services.frame_budget`)
                rrb.TimeSeriesView(origin="/stats/level", name="tessellation level per garment"),
                row_shares=[2, 2, 1],
            ),
            column_shares=[3, 1],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )


class _Streams:
    """The rerun streams a recording goes to (its file's, the live one's); each call goes to every
    one still open. None open: nothing is kept (a rerun stream without a sink buffers in memory)."""

    def __init__(self, streams: list):
        self.streams = streams

    def log(self, *args, **kwargs) -> None:
        for s in self.streams:
            s.log(*args, **kwargs)

    def set_time(self, *args, **kwargs) -> None:
        for s in self.streams:
            s.set_time(*args, **kwargs)

    def send_blueprint(self, blueprint) -> None:
        for s in self.streams:
            s.send_blueprint(blueprint)


class RecordingSink:
    """Where the rerun stream goes: an .rrd file (written as <file>.part, renamed when complete),
    a spawned local viewer, and/or a gRPC server that remote viewers connect to.

    The file has a rerun stream of its own (the live sinks share another): when its disk runs
    low (`services.diskspace`, checked by `check_space`), the file is finished there, complete,
    while the live viewers go on (a stream's sinks cannot be changed without restarting its
    gRPC server)."""

    def __init__(self, session: str, rrd: str | Path | None = None, spawn: bool = False,
                 serve_port: int | None = None, web_port: int | None = None, min_free: int = DEFAULT_MIN_FREE):
        self.rrd = Path(rrd) if rrd else None
        self.url = None
        self.stopped: str | None = None  # why the file was finished before close()
        self._file = None
        streams = []
        if self.rrd is not None:
            output_file(self.rrd)
            self._part = self.rrd.with_name(self.rrd.name + ".part")
            self._file = rr.RecordingStream("tryon", recording_id=session)
            self._file.set_sinks(rr.FileSink(str(self._part)))
            self._space = SpaceGuard(self.rrd.parent, min_free)
            streams.append(self._file)
        live = []
        if serve_port is not None:
            live.append(rr.GrpcServerSink(port=serve_port))
            self.url = f"rerun+http://127.0.0.1:{serve_port}/proxy"
        if spawn:  # a local viewer process, fed over gRPC beside the other sinks
            rr.spawn(connect=False)
            live.append(rr.GrpcSink())
        if live:
            stream = rr.RecordingStream("tryon", recording_id=session)
            stream.set_sinks(*live)
            streams.append(stream)
        self.rec = _Streams(streams)
        if web_port is not None and self.url is not None:
            rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=self.url)
        self.rec.send_blueprint(session_layout())
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)

    def check_space(self) -> str | None:
        """Finish the .rrd file if its disk is running low; returns why it was finished (None: it
        goes on, or there is none)."""
        if self._file is None:
            return None
        free = self._space.low()
        if free is None:
            return None
        self.stopped = self._space.why(free)
        log.warning("viewer: %s finished: %s; the live viewers go on", self.rrd, self.stopped)
        self._finish_file()
        return self.stopped

    def _finish_file(self) -> None:
        file, self._file = self._file, None
        self.rec.streams.remove(file)
        file.flush()
        file.disconnect()
        if self._part.exists():
            self._part.replace(self.rrd)

    def close(self) -> Path | None:
        if self._file is not None:
            self._finish_file()
        for s in self.rec.streams:
            s.flush()
            s.disconnect()
        self.rec.streams = []
        return self.rrd if self.rrd is not None and self.rrd.exists() else None


class LatestPerKey:
    """A subscriber callback that keeps the newest sample per key expression."""

    def __init__(self, stats: Stats):
        self.stats = stats
        self.latest: dict[str, zenoh.Sample] = {}
        self.cond = threading.Condition()

    def __call__(self, sample) -> None:
        k = str(sample.key_expr)
        with self.cond:
            if k in self.latest:
                self.stats.add("dropped")
            self.latest[k] = sample
            self.cond.notify()

    def take(self, timeout: float) -> list:
        """The samples waiting (waits up to `timeout` s for one), ordered by key."""
        with self.cond:
            if not self.latest:
                self.cond.wait(timeout)
            out, self.latest = self.latest, {}
        return [out[k] for k in sorted(out)]


class EveryFrame:
    """A subscriber callback that keeps every sample in arrival order (offline sessions: the .rrd
    gets every frame)."""

    def __init__(self, stats: Stats):
        self.samples: list = []
        self.cond = threading.Condition()

    def __call__(self, sample) -> None:
        with self.cond:
            self.samples.append(sample)
            self.cond.notify()

    def take(self, timeout: float) -> list:
        with self.cond:
            if not self.samples:
                self.cond.wait(timeout)
            out, self.samples = self.samples, []
        return out


def triangles_problem(triangles: np.ndarray, n_vertices) -> str | None:
    """What makes a latched topology unusable for a mesh of n_vertices (None: nothing)."""
    if not isinstance(n_vertices, int) or isinstance(n_vertices, bool) or n_vertices < 0:
        return f"meta 'n_vertices' must be an integer >= 0, got {n_vertices!r}"
    if triangles.size and (triangles.min() < 0 or triangles.max() >= n_vertices):
        return f"triangle indices run outside 0..{n_vertices - 1}"
    return None


class VertexNormals:
    """Area-weighted unit vertex normals of a mesh whose message carries none (the body since
    schema 2: half its bytes saved on the wire), for a display to shade it; buffers kept."""

    def __init__(self, triangles: np.ndarray, n_vertices: int):
        self._normals = MeshNormals(triangles, n_vertices)
        self._x = np.empty((n_vertices, 3))
        self._out = np.empty((n_vertices, 3))

    def __call__(self, positions: np.ndarray) -> np.ndarray:
        np.copyto(self._x, positions)
        return self._normals(self._x, self._out)


class ViewerBridge:
    SERVICE = "viewer"

    def __init__(self, bus: zenoh.Session, session: str, sink: RecordingSink, log_stats: bool = True,
                 lossless: bool = False):
        """lossless: show every frame (offline runs) instead of only the latest (live displays)."""
        self.bus, self.session, self.sink, self.rec = bus, session, sink, sink.rec
        self.stats = Stats(self.SERVICE, session)
        self.log_stats = log_stats
        self.latest = EveryFrame(self.stats) if lossless else LatestPerKey(self.stats)
        self.topology: dict[str, dict] = {}  # entity -> {"triangles", "n_vertices"}
        self.frames_shown: dict[str, int] = {}
        self.ended = threading.Event()
        self._outfit: list[str] | None = None  # garments of an outfit a cloth service just got ready
        self._outfit_lock = threading.Lock()
        self._gone: set[str] = set()  # garment entities of an outfit changed since: their late frames are let go
        self.worn_before: dict[str, dict] = {}  # the topology of garments worn before the last change (snapshots)
        self._subs = [bus.declare_subscriber(key(session, "body"), self.latest),
                      bus.declare_subscriber(key(session, "garment", "*"), self.latest),
                      bus.declare_subscriber(key(session, "control"), self._on_control),
                      bus.declare_subscriber(key(session, "status", "cloth"), self._on_status)]
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.fetch_topology()

    def _on_control(self, sample) -> None:
        msg = self.stats.decode(sample, self.session, "control")
        if msg is not None and msg.meta.get("event") == "end" and msg.meta.get("from") == "ingest":
            self.ended.set()

    def _on_status(self, sample) -> None:
        msg = self.stats.decode(sample, self.session, "control")
        if msg is not None and msg.meta.get("event") == "ready" and isinstance(msg.meta.get("garments"), list):
            with self._outfit_lock:
                self._outfit = [str(g) for g in msg.meta["garments"]]

    def _change_outfit(self) -> None:
        """After a cloth service got an outfit ready (at the session's start, or a change of
        clothes): every garment's topology is read again from the bus (a new outfit, fabric or
        level), and the garments that are no longer worn are cleared from the view."""
        with self._outfit_lock:
            names, self._outfit = self._outfit, None
        if names is None:
            return
        worn = {self.entity(("garment", g)) for g in names}
        for ent in [e for e in self.topology if e.startswith("world/garment/")]:
            self.worn_before[ent] = self.topology.pop(ent)
            if ent not in worn:
                self.rec.log(ent, rr.Clear(recursive=False))
                self.frames_shown.pop(ent, None)
                self._gone.add(ent)
        self._gone -= worn

    @staticmethod
    def entity(parts: tuple[str, ...]) -> str:
        return "world/" + "/".join(parts)

    def fetch_topology(self, timeout: float = 1.0) -> None:
        """Log the static part (triangles, colour) of every mesh whose topology is latched."""
        for k, msg in fetch_latched(self.bus, key(self.session, "topology", "**"), timeout, self.stats).items():
            ent = self.entity(parse_key(k)[1][1:])  # tryon/s/topology/garment/x -> world/garment/x
            if ent in self.topology:
                continue
            tris = np.array(msg.arrays["triangles"])
            color = msg.meta.get("color", [0.7, 0.7, 0.7])
            n = msg.meta.get("n_vertices", int(tris.max()) + 1 if tris.size else 0)
            problem = triangles_problem(tris, n)
            if problem:
                self.stats.reject(MessageError(k, problem))
                continue
            self.topology[ent] = {"triangles": tris, "n_vertices": n, "color": tuple(float(c) for c in color[:3]),
                                  "shading": None}
            self.rec.log(ent, rr.Mesh3D.from_fields(triangle_indices=tris,
                                                    albedo_factor=[int(255 * c) for c in color[:3]] + [255]),
                         static=True)

    def start(self) -> "ViewerBridge":
        self._thread = threading.Thread(target=self.serve, name="viewer-bridge", daemon=True)
        self._thread.start()
        return self

    def serve(self) -> None:
        while not self._stop.is_set():
            batch = self.latest.take(0.2)
            for sample in batch:
                try:
                    self.show(str(sample.key_expr), sample.payload.to_bytes())
                except MessageError as err:
                    self.stats.reject(err)
            self.stats.publish(self.bus)

    def show(self, key_expr: str, payload: bytes) -> None:
        session, parts = parse_key(key_expr)
        msg = decode(payload, key_expr, self.session, parts[0])
        ent = self.entity(parts)
        self._change_outfit()
        if ent in self._gone:
            return  # a frame of a garment taken off, still on its way
        if ent not in self.topology:
            self.fetch_topology()
            if ent not in self.topology:
                raise MessageError(key_expr, "no topology latched for this mesh yet")
        topo = self.topology[ent]
        n = vertex_count(msg.arrays)
        if n != topo["n_vertices"] and msg.kind == "garment":
            # the garment's new topology (another level), its frame ahead of the cloth service's
            # "ready" (another key, another thread): read it again rather than lose the frame
            old = self.topology.pop(ent)
            self.fetch_topology()
            topo = self.topology.setdefault(ent, old)
        if n != topo["n_vertices"]:
            raise MessageError(key_expr, f"{n} vertices, the topology has {topo['n_vertices']}")
        if msg.kind == "body":  # (compact: decoded into a fresh array, as the garments)
            pos, normals = body_vertices(msg.arrays), msg.arrays.get("normals")
        else:  # fresh arrays every frame: rerun may still hold the last frame's when it returns
            pos, normals = garment_mesh(msg.arrays)
        self.stats.add("received")
        stopped = self.sink.check_space()
        if stopped is not None:
            self.stats.values["rrd_stopped"] = stopped
        self.rec.set_time("frame", sequence=msg.frame)
        self.rec.set_time("session_time", duration=msg.time)
        if normals is None:  # the body (schema 2): shaded here, from the latched topology
            if topo["shading"] is None:
                topo["shading"] = VertexNormals(topo["triangles"], topo["n_vertices"])
            normals = topo["shading"](pos)
        self.rec.log(ent, rr.Mesh3D.from_fields(vertex_positions=pos, vertex_normals=normals))
        self.frames_shown[ent] = msg.frame
        if msg.kind == "garment":
            latency = (time.time_ns() - msg.origin_ns) / 1e6
            self.stats.values["latency_ms"] = round(latency, 3)
            if self.log_stats:
                name = parts[-1]
                for field in ("s101_ms", "pn_ms", "collision_ms", "deformation_ms", "layer_ms"):
                    if field in msg.meta:
                        self.rec.log(f"stats/stages/{name}/{field}", rr.Scalars(float(msg.meta[field])))
                self.rec.log(f"stats/latency/{name}", rr.Scalars(latency))
                level = msg.meta.get("level")
                if isinstance(level, int) and not isinstance(level, bool):  # (a frame budget may change it)
                    self.rec.log(f"stats/level/{name}", rr.Scalars(float(level)))

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        for sample in self.latest.take(0):  # show what is still pending
            try:
                self.show(str(sample.key_expr), sample.payload.to_bytes())
            except MessageError as err:
                self.stats.reject(err)
        for s in self._subs:
            s.undeclare()
        self._subs.clear()
        self.stats.publish(self.bus, force=True)
