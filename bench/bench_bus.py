"""End-to-end latency and throughput of the services over the bus (separate OS processes).

A cloth service and mocap-ingest processes talk over zenoh on TCP loopback; this process
subscribes to the garments like a display would. Latency of a frame = arrival of its last garment
mesh here - publication of its body frame (same clock). Runs:
  * one session (one outfit, two garments) at 60 Hz input: p50/p99 latency, dropped frames;
  * the same at the clips' native 120 Hz;
  * where those runs' time goes: the body frame's trip to another process, the cloth service's
    stamps of each frame's garment messages, their trip to this subscriber;
  * sustained throughput: input as fast as possible;
  * concurrent 60 Hz sessions on one cloth service, 1..N: how many it holds (no dropped frame,
    latency not growing).
Run: .venv/bin/python bench/bench_bus.py [--level 6] [--seconds 8] [--max-sessions 3]
(--level 0: coarse cloth only; --frame-budget-ms MS: the cloth service holds its step to MS by the level).
"""

from __future__ import annotations

import argparse
import os
import platform
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench_cloth import cpu_name  # noqa: E402 - same folder
from services.bus import BusConfig, key, parse_key  # noqa: E402
from services.protocol import decode  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CLIP = "cmu_131_01_walk_3dsmax"
OUTFIT = "female_casualsuit01"
INGEST_OPTIONS: list[str] = []  # extra options of every mocap-ingest process (--no-skin-contact)
CLOTH_OPTIONS: list[str] = []  # extra options of the cloth service (--float32-meshes)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Arrivals:
    """Arrival time of every garment message of some sessions."""

    def __init__(self, bus, sessions: list[str]):
        self.lock = threading.Lock()
        self.frames: dict[tuple[str, int], dict] = {}  # (session, frame) -> {garment: (arrival, origin)}
        self.stamps: dict[tuple[str, int], dict] = {}  # (session, frame) -> {garment: its message's own stamp}
        self.body: dict[str, list[int]] = {s: [] for s in sessions}
        self.body_delay: dict[str, list[int]] = {s: [] for s in sessions}  # body frame arrival here - its stamp
        self.garment_bytes: dict[str, int] = {}  # garment -> size of its last message
        self.subs = []
        for s in sessions:
            self.subs.append(bus.declare_subscriber(key(s, "garment", "*"), self.on_garment))
            self.subs.append(bus.declare_subscriber(key(s, "body"), self.on_body))

    def on_garment(self, sample) -> None:
        now = time.time_ns()
        k = str(sample.key_expr)
        data = sample.payload.to_bytes()
        m = decode(data, k)
        if "preroll_s" in m.meta:  # the first frame waits for the session's pre-roll
            return
        with self.lock:
            self.garment_bytes[parse_key(k)[1][1]] = len(data)
            self.frames.setdefault((m.session, m.frame), {})[parse_key(k)[1][1]] = (now, m.origin_ns, m.meta)
            self.stamps.setdefault((m.session, m.frame), {})[parse_key(k)[1][1]] = m.stamp_ns

    def on_body(self, sample) -> None:
        now = time.time_ns()
        k = str(sample.key_expr)
        m = decode(sample.payload.to_bytes(), k)
        with self.lock:
            self.body[m.session].append(m.frame)
            self.body_delay[m.session].append(now - m.stamp_ns)

    def close(self):
        for s in self.subs:
            s.undeclare()

    def result(self, session: str, garments: int = 2):
        with self.lock:
            body = self.body[session][1:]  # frame 1 carries the pre-roll
            full = {f: g for (s, f), g in self.frames.items() if s == session and len(g) == garments}
        lat = np.array([max(a for a, _, _ in full[f].values()) - max(o for _, o, _ in full[f].values())
                        for f in body if f in full]) / 1e6
        dropped = sum(1 for f in body if f not in full)
        compute = np.array([sum(sum(v for k, v in meta.items() if k.endswith("_ms")) for _, _, meta in full[f].values())
                            for f in body if f in full])
        return lat, dropped, len(body), compute

    def levels(self, session: str) -> str:
        """The tessellation levels the session's garments came at, in order, with their frames
        (a cloth service holding a frame budget changes it: "6 x31, 5 x448")."""
        with self.lock:
            seq = [next(iter(g.values()))[2].get("level") for (s, f), g in sorted(self.frames.items()) if s == session]
        runs: list[list] = []
        for lv in seq:
            if runs and runs[-1][0] == lv:
                runs[-1][1] += 1
            else:
                runs.append([lv, 1])
        out = ", ".join(f"{lv} x{n}" for lv, n in runs) or "-"
        if len(runs) > 1:  # a frame budget changed it: the latency once at the last level
            lat = self.latency_at(session, runs[-1][0])
            out += f" (at {runs[-1][0]}: p50 {pct(lat, 50)} / p99 {pct(lat, 99)} ms)"
        return out

    def latency_at(self, session: str, level, garments: int = 2) -> np.ndarray:
        """Latency (ms) of the session's frames whose garments came at `level`, from the first of them on."""
        with self.lock:
            full = sorted((f, g) for (s, f), g in self.frames.items() if s == session and len(g) == garments)
        since = next((i for i, (_, g) in enumerate(full) if all(m.get("level") == level for _, _, m in g.values())),
                     len(full))
        return np.array([max(a for a, _, _ in g.values()) - max(o for _, o, _ in g.values())
                         for _, g in full[since:]]) / 1e6

    def breakdown(self, session: str, garments: int = 2) -> list[float]:
        """Where a frame's latency goes, p50 ms over its complete frames: the body frame's arrival
        in this (another) process, the cloth service's stamps of its first and last garment message
        (each stamped as it is encoded), and the last garment's arrival here, all after the body
        frame's publication; then the garment messages' own trip (arrival - stamp), p50 and p99."""
        with self.lock:
            full = {f: g for (s, f), g in self.frames.items() if s == session and len(g) == garments}
            stamps = {f: self.stamps[(session, f)] for f in full}
            body = np.array(self.body_delay[session][1:]) / 1e6
        origin = {f: max(o for _, o, _ in g.values()) for f, g in full.items()}
        first = np.array([min(stamps[f].values()) - origin[f] for f in full]) / 1e6
        last = np.array([max(stamps[f].values()) - origin[f] for f in full]) / 1e6
        end = np.array([max(a for a, _, _ in g.values()) - origin[f] for f, g in full.items()]) / 1e6
        trip = np.array([a - stamps[f][name] for f, g in full.items() for name, (a, _, _) in g.items()]) / 1e6
        med = [float(np.median(x)) if len(x) else float("nan") for x in (body, first, last, end, trip)]
        return med + [float(np.percentile(trip, 99)) if len(trip) else float("nan")]


def cli(*args) -> list[str]:
    return [sys.executable, "-m", "services.cli", *args]


def run(endpoint: str, sessions: list[str], every: int, pace: str, frames: int, level: int, patience: float = 20.0):
    """Ingest processes (one per session) against the running cloth service; returns Arrivals
    (`complete`: every session's last frame came back before `patience` seconds passed without
    a new garment mesh)."""
    bus = BusConfig(mode="client", listen=[], connect=[endpoint]).open()
    arrivals = Arrivals(bus, sessions)
    level_args = ["--coarse-only"] if level == 0 else ["--level", str(level)]
    procs = [subprocess.Popen(cli("ingest", "--session", s, "--clip", CLIP, "--pace", pace, "--every", str(every),
                                  "--max-frames", str(frames + 1), "--mode", "client", "--connect", endpoint,
                                  "--outfit", OUTFIT, *level_args, *INGEST_OPTIONS),
                              cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for s in sessions]
    for p in procs:
        p.wait()
    # wait for the cloth service to finish what is queued: the garments of every session's last frame
    last, still, done = None, 0.0, False
    while still < patience:
        time.sleep(0.25)
        with arrivals.lock:
            done = all(b and len(arrivals.frames.get((s, b[-1]), {})) == 2 for s, b in arrivals.body.items())
            n = len(arrivals.frames)
        if done:
            break
        still = still + 0.25 if n == last else 0.0
        last = n
    arrivals.close()
    bus.close()
    arrivals.complete = done
    return arrivals


def start_cloth(endpoint: str, level: int, catch_up: bool, pin_cores: str | None = None) -> subprocess.Popen:
    level_args = ["--coarse-only"] if level == 0 else ["--level", str(level)]
    cloth = subprocess.Popen(cli("cloth-service", "--listen", endpoint, "--outfit", OUTFIT, *level_args,
                                 *(["--catch-up"] if catch_up else []), *CLOTH_OPTIONS,
                                 *(["--pin-cores", pin_cores] if pin_cores else [])), cwd=ROOT,
                             stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    for line in cloth.stdout:
        if "ready" in line:
            break
    # models built, kernels compiled or loaded: a service whose numba cache is stale compiles
    # for minutes, and frames measured meanwhile would time the compiler
    if not run(endpoint, ["warmup"], 2, "fast", 20, level, patience=900.0).complete:
        cloth.terminate()
        raise SystemExit("the cloth service did not return the warm-up frames' garments")
    return cloth


def pct(lat: np.ndarray, q: float) -> str:
    """A latency percentile in whole ms, or "-" when no frame came back."""
    return f"{np.percentile(lat, q):.0f}" if len(lat) else "-"


def latency_rows(endpoint: str, seconds: float, level: int, label: str, breakdown: list[str]) -> None:
    """One row of the latency table per input rate; appends the run's `Arrivals.breakdown` row to
    breakdown (printed as a table of its own after the latency table)."""
    for rate, every in (("60 Hz", 2), ("120 Hz (native)", 1)):
        n = int(seconds * 120 / every)
        name = f"one-{label.strip('-').replace(' ', '-')}-{every}"  # a fresh session per run
        a = run(endpoint, [name], every, "realtime", n, level)
        lat, dropped, total, compute = a.result(name)
        print(f"| {label} | {rate} | {total} | {pct(lat, 50)} | {pct(lat, 99)} | {pct(lat, 100)} | {dropped} | "
              f"{np.median(compute) if len(compute) else float('nan'):.1f} | {a.levels(name)} |", flush=True)
        breakdown.append(f"| {label} | {rate} | " + " | ".join(f"{x:.2f}" for x in a.breakdown(name)) + " |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--level", type=int, default=6, help="PN level (0: coarse cloth only)")
    ap.add_argument("--seconds", type=float, default=8.0, help="length of each run in seconds of motion")
    ap.add_argument("--max-sessions", type=int, default=3)
    ap.add_argument("--pin-cores", metavar="LIST", default="auto",
                    help="passed to the cloth service: auto (its default), none, or cores (e.g. 0,1)")
    ap.add_argument("--no-skin-contact", action="store_true", help="passed to the mocap-ingest processes")
    ap.add_argument("--float32-meshes", action="store_true", help="passed to the cloth service")
    ap.add_argument("--frame-budget-ms", metavar="MS", help="passed to the cloth service: the level held to it")
    args = ap.parse_args()
    if args.frame_budget_ms:
        CLOTH_OPTIONS.extend(["--frame-budget-ms", args.frame_budget_ms])
    if args.no_skin_contact:
        INGEST_OPTIONS.append("--no-skin-contact")
    if args.float32_meshes:
        CLOTH_OPTIONS.append("--float32-meshes")
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    print(f"machine: {cpu_name()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    print(f"outfit {OUTFIT} (two garments), level {args.level or 'coarse only'}, clip {CLIP}; "
          f"cloth service, ingest and this subscriber in separate processes over TCP loopback"
          f"; cloth service --pin-cores {args.pin_cores} {' '.join(CLOTH_OPTIONS)}"
          f"; ingest {' '.join(INGEST_OPTIONS) or 'with the skin contact'}\n")
    print("| cloth service | input | frames | latency p50 ms | p99 ms | max ms | frames without garments | "
          "compute ms/frame | levels, frames at each |")
    print("|---|---|---|---|---|---|---|---|---|")
    breakdown: list[str] = []
    cloth = start_cloth(endpoint, args.level, catch_up=True, pin_cores=args.pin_cores)
    try:
        latency_rows(endpoint, args.seconds, args.level, "--catch-up", breakdown)
    finally:
        cloth.terminate()
        cloth.wait(10)
    cloth = start_cloth(endpoint, args.level, catch_up=False, pin_cores=args.pin_cores)
    try:
        latency_rows(endpoint, args.seconds, args.level, "in order", breakdown)
        print("\nwhere the time goes, p50 ms after a body frame's publication (its arrival in another process; "
              "the cloth service's stamps of its first and last garment; the last one's arrival), then a garment "
              "message's own trip, stamp to arrival, p50 / p99:\n")
        print("| cloth service | input | body here | first garment stamped | last stamped | last here | "
              "garment trip p50 | p99 |")
        print("|---|---|---|---|---|---|---|---|")
        print("\n".join(breakdown), flush=True)
        n = int(args.seconds * 60)
        t0 = time.perf_counter()
        a = run(endpoint, ["fast"], 2, "fast", n, args.level)
        lat, dropped, total, compute = a.result("fast")
        arr = sorted(max(x for x, _, _ in g.values()) for (s, _), g in a.frames.items() if s == "fast")
        rate = (len(arr) - 1) / ((arr[-1] - arr[0]) / 1e9)
        print(f"\nsustained throughput (input as fast as possible): {rate:.1f} frames/s "
              f"({total} frames, {dropped} dropped, run {time.perf_counter() - t0:.0f} s)")
        print("garment messages: " + ", ".join(f"{g} {n / 1000:.0f} kB" for g, n in sorted(a.garment_bytes.items()))
              + f" ({'float32' if args.float32_meshes else 'compact'})")
        print("\n| concurrent 60 Hz sessions | latency p50 ms | p99 ms | dropped | holds |")
        print("|---|---|---|---|---|")
        for k in range(1, args.max_sessions + 1):
            names = [f"s{k}-{i}" for i in range(k)]
            a = run(endpoint, names, 2, "realtime", n, args.level)
            lats, drops = [], 0
            growing = False
            for s in names:
                lat, dropped, total, _ = a.result(s)
                lats.append(lat)
                drops += dropped
                q = max(1, len(lat) // 4)
                growing |= len(lat) == 0 or np.median(lat[-q:]) > 2 * np.median(lat[:q]) + 10
            lat = np.concatenate(lats)
            holds = drops == 0 and not growing and len(lat) > 0 and np.percentile(lat, 99) < 100
            print(f"| {k} | {pct(lat, 50)} | {pct(lat, 99)} | {drops} | "
                  f"{'yes' if holds else 'no'} |", flush=True)
            if not holds:
                break
    finally:
        cloth.terminate()
        cloth.wait(10)


if __name__ == "__main__":
    main()
