"""`tryon session` (the README's main command) end to end, and the recording's integrity."""

import contextlib
import re
import socket
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from services.bus import parse_key
from services.cli import main
from services.protocol import decode
from services.recorder import read_recording
from tests.test_services import free_port, wait_until


def test_session_writes_rrd_recording_and_snapshots(tmp_path, capsys):
    rc = main(["session", "--session", "t1", "--max-frames", "9", "--level", "3", "--snapshot-frames", "4,8",
               "--out", str(tmp_path)])
    assert rc == 0
    out = capsys.readouterr().out
    assert "session t1: 8 frames" in out
    total, setup, fps = re.search(r"frames in ([\d.]+) s \(setup ([\d.]+) s: .* then ([\d.]+) frames/s\)", out).groups()
    assert 0.0 < float(setup) <= float(total) and float(fps) > 0.0  # the setup (pre-roll) told apart
    # the summary's counts are read once the cloth service has counted the last frame too
    assert re.search(r"cloth: received 8, published 16, rejected 0, dropped 0", out), out
    for stage in ("ik", "skinning", "s101", "pn", "collision", "deformation", "p50"):
        assert stage in out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t1.mcap", "t1.png", "t1.rrd"]  # no .part left
    kinds: dict[str, list[int]] = {}
    for k, payload, _ in read_recording(tmp_path / "t1.mcap"):
        what = "/".join(parse_key(k)[1])
        kinds.setdefault(what, []).append(decode(payload, k).frame)
    assert kinds["body"] == list(range(1, 9))
    garments = [w for w in kinds if w.startswith("garment/")]
    assert len(garments) == 2 and all(kinds[g] == list(range(1, 9)) for g in garments)
    assert "session" in kinds and "topology/body" in kinds
    # the .rrd carries the viewer layout: the 3D view and the two plots whose origins hold what the bridge logs
    rerun = Path(sys.executable).parent / "rerun"
    printed = subprocess.run([str(rerun), "rrd", "print", "-vvv", str(tmp_path / "t1.rrd")], capture_output=True,
                             text=True, check=True).stdout
    views = set(re.findall(r"\[(3D|TimeSeries)\]\s+┆ \[[^\]]+\]\s+┆ \[(/[^\]]*)\]", printed))
    assert views == {("3D", "/world"), ("TimeSeries", "/stats/stages"), ("TimeSeries", "/stats/latency"),
                     ("TimeSeries", "/stats/level")}
    entities = set(re.findall(r"entity_path: (/\S+)", printed))
    for origin in ("/world/garment/", "/stats/stages/", "/stats/latency/", "/stats/level/"):
        assert sum(e.startswith(origin) for e in entities) >= 2, origin  # both garments
    img = np.asarray(Image.open(tmp_path / "t1.png"))
    assert img.shape[1] == 4 * 360 and img.std() > 10  # two frames, two views each
    # garment colours: not only skin, floor and sky
    assert (np.abs(img[..., 2].astype(int) - img[..., 0].astype(int)) > 80).mean() > 0.005


def test_a_session_with_a_frame_budget_draws_each_snapshot_at_its_own_level(tmp_path, capsys):
    """A budget no step keeps: the session goes from level 4 to 3 on its way, and its snapshots
    show the garments of a frame before the change and of one after it, each drawn with the
    topology of its own level (before, a frame whose garments had another size than the last
    topology was drawn without them)."""
    rc = main(["session", "--session", "fb", "--max-frames", "100", "--level", "4", "--frame-budget-ms", "0.001",
               "--snapshot-frames", "4,96", "--no-rrd", "--out", str(tmp_path)])
    assert rc == 0
    out = capsys.readouterr().out
    assert re.search(r"cloth: received 99, published 198, .*level_changes 1, level at the end 3", out), out
    sizes = {}
    for k, payload, _ in read_recording(tmp_path / "fb.mcap"):
        if parse_key(k)[1][0] == "garment":
            m = decode(payload, k)
            sizes.setdefault(m.meta["level"], set()).add(m.frame)
    assert 4 in sizes[4] and 96 in sizes[3]  # the two snapshot frames at the two levels
    img = np.asarray(Image.open(tmp_path / "fb.png")).astype(int)
    width = img.shape[1] // 4
    for column in range(4):  # each frame from two sides, every one with the T-shirt's blue (the sky: b - r 8)
        r, g, b = (img[:, column * width:(column + 1) * width, c] for c in range(3))
        assert (b - r > 40).mean() > 0.01, column
        if column % 2 == 0:  # and from the front the jeans' red (the skin: r - g 44; from behind they are dark)
            assert (r - g > 70).mean() > 0.005, column


def test_a_coarse_only_session_without_recordings_writes_its_snapshots_alone(tmp_path, capsys):
    """`--coarse-only --no-record --no-rrd`: S101 alone (no surface stages timed), the garments'
    coarse meshes published every frame, and no .mcap or .rrd written."""
    rc = main(["session", "--session", "c1", "--max-frames", "7", "--coarse-only", "--no-record", "--no-rrd",
               "--snapshot-frames", "5", "--out", str(tmp_path)])
    assert rc == 0
    out = capsys.readouterr().out
    assert "(level coarse)" in out and "session c1: 6 frames" in out
    assert re.search(r"cloth: received 6, published 12, rejected 0, dropped 0", out), out
    assert "s101" in out and "deformation" not in out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c1.png"]


@pytest.mark.parametrize("argv, says", [
    (["session", "--outfit", "no-such-outfit"], "outfit 'no-such-outfit' not found"),
    (["session", "--fabric", "tweed"], "no fabric 'tweed'"),
    (["cloth", "--outfit", "female_casualsuit01", "--outfit", "no-such-outfit"], "outfit 'no-such-outfit' not found"),
    (["cloth-service", "--outfit", "no-such-outfit"], "outfit 'no-such-outfit' not found"),
])
def test_an_unknown_outfit_or_fabric_stops_the_command_before_it_starts(argv, says, tmp_path, capsys):
    """A mistyped outfit or fabric is named at once, with what there is, and nothing is written
    (before, `tryon session` ran the whole clip with every body frame rejected)."""
    assert main([*argv, "--out", str(tmp_path)] if argv[0] != "cloth-service" else argv) == 2
    err = capsys.readouterr().err
    assert says in err and "available:" in err
    assert "female_casualsuit01" in err or "denim" in err
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("config, says", [
    ('{ mode: "peer",\n  listen: ', "line 2"),  # cut off: JSON5 syntax, where
    ('{ scouting: { multicast: { enabled: "yes" } } }', "expected a boolean"),  # a key of the wrong type
])
@pytest.mark.parametrize("command", [["session", "--coarse-only", "--max-frames", "3"], ["router"]])
def test_a_malformed_zenoh_config_is_named_with_its_problem(config, says, command, tmp_path, capsys):
    """A zenoh config file that zenoh cannot read is reported with its path and zenoh's reason
    (before: a traceback from inside zenoh), and nothing is written."""
    path = tmp_path / "bus.json5"
    path.write_text(config)
    out = tmp_path / "out"
    assert main([*command, "--zenoh-config", str(path)] + (["--out", str(out)] if command[0] == "session" else [])) == 2
    err = capsys.readouterr().err
    assert f"tryon: zenoh config '{path}'" in err and says in err and ".rs:" not in err and "Traceback" not in err
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize("option, value", [("--max-frames", "0"), ("--max-frames", "-3"), ("--every", "0"),
                                           ("--every", "x")])
@pytest.mark.parametrize("command", ["session", "cloth", "ingest", "capture"])
def test_a_frame_count_below_one_is_refused_at_once(command, option, value, tmp_path, capsys):
    """--max-frames 0 or less ran a session of no frames and reported it as run."""
    with pytest.raises(SystemExit) as stop:
        main([command, option, value, "--out", str(tmp_path)])
    assert stop.value.code == 2
    assert f"argument {option}: must be a whole number >= 1, got" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("argv, option", [(["catalog", "--out", "x"], "--out"),
                                          (["session", "--max", "3"], "--max")])
def test_an_option_is_taken_by_its_whole_name_only(argv, option, capsys):
    """argparse took prefixes: `catalog --out X` was read as `--outfit X`, and the error named X as
    an outfit."""
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert f"unrecognized arguments: {option}" in err and "outfit" not in err.split("error:")[1]


@pytest.mark.parametrize("command", ["session", "cloth", "ingest", "capture"])
def test_a_clip_with_no_frame_after_its_first_is_refused_naming_it(command, tmp_path, capsys):
    """A one-frame clip (a user's single pose) ran a session of no frames: empty timings, exit 0.
    A session starts at the clip's second frame (CMU's first is the converter's T-pose)."""
    from skinning.data import data_dir

    lines = (data_dir() / "mocap" / "cmu_npybvh_example_75f.bvh").read_text().splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("Frame Time"))
    one = tmp_path / "one pose.bvh"
    one.write_text("\n".join([*(("Frames: 1" if line.startswith("Frames:") else line) for line in lines[:at + 1]),
                              lines[at + 1]]) + "\n")
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as stop:
        main([command, "--clip", str(one), *(["--out", str(out)] if command in ("session", "cloth") else [])])
    assert f"clip {one} has 1 frame" in str(stop.value.code) and "nothing to run" in str(stop.value.code)
    assert not out.exists()


@pytest.mark.parametrize("command", [["session", "--coarse-only", "--max-frames", "2", "--out"],
                                     ["cloth", "--coarse-only", "--max-frames", "2", "--out"],
                                     ["body", "--max-frames", "2", "--out"]])
def test_an_output_folder_that_is_a_file_is_refused_at_once(command, tmp_path, capsys):
    """--out naming a file: the session ran its setup and died in a FileExistsError traceback."""
    there = tmp_path / "notes.txt"
    there.write_text("mine")
    assert main([*command, str(there)]) == 2
    err = capsys.readouterr().err
    assert f"tryon: {there}: a file is there, not a folder" in err and "Traceback" not in err
    assert there.read_text() == "mine"


def test_a_recording_named_by_a_folder_is_refused_before_recording(tmp_path):
    """`tryon record --out FOLDER` recorded the whole session into FOLDER.part and then failed to
    rename it (IsADirectoryError): the recording was never finished. The recorder and the viewer's
    .rrd now refuse a folder before the first message (`tryon record` and `tryon viewer --save`
    then exit 2 with that line; not run here, as they would wait for a session)."""
    from services.bus import BusConfig
    from services.recorder import Recorder
    from services.viewer import RecordingSink

    with BusConfig(listen=[f"tcp/127.0.0.1:{free_port()}"]).open() as bus:
        with pytest.raises(ValueError, match=rf"{re.escape(str(tmp_path))}: is a folder; name the file to write"):
            Recorder(bus, "rec", tmp_path)
    with pytest.raises(ValueError, match=rf"{re.escape(str(tmp_path))}: is a folder; name the file to write"):
        RecordingSink("rec", rrd=tmp_path)
    assert not tmp_path.with_name(tmp_path.name + ".part").exists()
    inner = tmp_path / "new" / "deeper" / "s.mcap"  # a file in folders not made yet: made
    with BusConfig(listen=[f"tcp/127.0.0.1:{free_port()}"]).open() as bus:
        Recorder(bus, "rec", inner).close()
    assert list(read_recording(inner)) == []


@pytest.mark.parametrize("rate, every", [(30, 1), (60, 1), (100, 2), (120, 2), (240, 4)])
def test_without_every_a_clip_runs_nearest_60_hz(rate, every, tmp_path, capsys):
    """--every defaulted to 2, right for the CMU clips' 120 Hz: a user's 30 Hz clip ran at 15 Hz. Now
    the default takes the one frame in N that brings the clip nearest 60 Hz; given, --every stands."""
    from services.cli import _every
    from skinning.data import data_dir

    lines = (data_dir() / "mocap" / "cmu_npybvh_example_75f.bvh").read_text().splitlines()
    clip = tmp_path / f"at{rate}.bvh"
    clip.write_text("\n".join(f"Frame Time: {1 / rate:.8f}" if line.startswith("Frame Time") else line
                              for line in lines) + "\n")
    assert _every(None, clip) == every and _every(3, clip) == 3
    if rate == 30:
        assert main(["session", "--clip", str(clip), "--max-frames", "2", "--coarse-only", "--no-rrd", "--no-record",
                     "--no-png", "--out", str(tmp_path / "out")]) == 0
        assert "session demo: at30 at 30 Hz × " in capsys.readouterr().out


def test_a_fabrics_file_without_a_fabric_named_is_refused_not_ignored(tmp_path, capsys):
    """`tryon cloth --fabrics FILE` alone used to run with the outfit's presets, the file unread;
    now it is read (a malformed one is named) and the command asks which of its fabrics to wear."""
    from cloth.fabric import PRESETS_PATH

    mine = tmp_path / "mine.toml"
    mine.write_text(PRESETS_PATH.read_text().replace("[cotton]", "[my_cotton]"))
    out = tmp_path / "out"
    assert main(["cloth", "--fabrics", str(mine), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"--fabrics {mine} is the file --fabric picks from" in err and "my_cotton" in err
    broken = tmp_path / "broken.toml"
    broken.write_text("[my_cotton\n")
    assert main(["cloth", "--fabrics", str(broken), "--out", str(out)]) == 2
    assert f"{broken}: not valid TOML" in capsys.readouterr().err
    assert not out.exists()


def test_a_bus_endpoint_in_use_is_named_with_its_problem(capsys):
    """An endpoint to listen on that another process holds: the command says which and why."""
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        endpoint = f"tcp/127.0.0.1:{held.getsockname()[1]}"
        assert main(["router", "--listen", endpoint]) == 2
    err = capsys.readouterr().err
    assert f"tryon: the bus does not open (router; listen {endpoint})" in err and "in use" in err


@pytest.mark.parametrize("command", ["session", "cloth", "cloth-service"])
@pytest.mark.parametrize("level", ["0", "17", "six"])
def test_a_level_the_cloth_service_would_refuse_stops_the_command_at_once(command, level, tmp_path, capsys):
    """--level out of 1-16 (what a session description may ask for) is named by the option
    parser; before, `tryon session --level 0` ran the whole clip with every body frame rejected."""
    with pytest.raises(SystemExit) as stop:
        main([command, "--level", level, *(["--out", str(tmp_path)] if command != "cloth-service" else [])])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    got = level if level.isdigit() else repr(level)
    assert f"argument --level: must be an integer 1-16, got {got}" in err
    assert not any(tmp_path.iterdir())


def test_replay_rejects_a_truncated_recording(tmp_path):
    src = tmp_path / "x.mcap"
    src.write_bytes(b"\x89MCAP0\r\n" + b"\0" * 50)
    with pytest.raises(ValueError, match="x.mcap"):
        list(read_recording(src))
    with pytest.raises(FileNotFoundError):
        list(read_recording(tmp_path / "missing.mcap"))


def test_a_schema_1_recording_still_replays_and_an_unknown_one_is_refused(tmp_path):
    """Schema 2 dropped the body's normals; a recording made before (channels "tryon/1", body
    messages with normals) reads back message for message, one in an unknown encoding does not."""
    from mcap.writer import Writer

    from services.protocol import Message, encode

    body = Message("body", "old", 3, 0.05, {"vertices": np.ones((4, 3), np.float32),
                                            "normals": np.ones((4, 3), np.float32), "q": np.zeros(7)})
    v1 = bytearray(encode(body))
    v1[4:6] = (1).to_bytes(2, "little")
    for encoding, name in (("tryon/1", "v1.mcap"), ("tryon/9", "v9.mcap")):
        with open(tmp_path / name, "wb") as f:
            w = Writer(f)
            w.start()
            ch = w.register_channel("tryon/old/body", encoding, 0)
            w.add_message(ch, log_time=1, data=bytes(v1), publish_time=1)
            w.finish()
    [(k, payload, _)] = list(read_recording(tmp_path / "v1.mcap"))
    assert k == "tryon/old/body" and decode(payload, k).arrays["normals"].shape == (4, 3)
    with pytest.raises(ValueError, match="'tryon/9'"):
        list(read_recording(tmp_path / "v9.mcap"))


def test_tryon_replay_puts_a_recording_back_on_the_bus_under_another_session(tmp_path, capsys):
    """`tryon replay` (the command; `recorder.replay` has its own tests): every recorded frame, in
    order, under the session name asked for, to a subscriber on another bus endpoint; a pace below
    0 is refused before anything is published."""
    from mcap.writer import Writer

    from services.protocol import Message, encode

    path = tmp_path / "old.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        ch = w.register_channel("tryon/old/body", "tryon/2", 0)
        for frame in (1, 2, 3):
            msg = Message("body", "old", frame, frame / 60, {"vertices": np.full((4, 3), frame, np.float32),
                                                             "q": np.zeros(7)})
            w.add_message(ch, log_time=frame * 16_666_667, data=encode(msg), publish_time=frame * 16_666_667)
        w.finish()
    with _bus_collecting(["tryon/**"]) as (endpoint, got):
        rc = main(["replay", str(path), "--session", "new", "--speed", "4", "--linger", "0", "--wait-subscribers", "20",
                   "--connect", endpoint])
        wait_until(lambda: len(got) >= 3, 10, "the replayed frames")  # (on zenoh's threads, maybe later)
    assert rc == 0 and f"replay: 3 messages from {path}" in capsys.readouterr().out
    assert [(k, m.session, m.frame) for k, m in got] == [("tryon/new/body", "new", f) for f in (1, 2, 3)]
    assert [float(m.arrays["vertices"][0, 0]) for _, m in got] == [1.0, 2.0, 3.0]
    with pytest.raises(SystemExit):
        main(["replay", str(path), "--speed", "-1"])
    assert "argument --speed: must be a number >= 0, got -1" in capsys.readouterr().err


def test_tryon_capture_publishes_a_clip_as_a_live_pose_stream(capsys):
    """`tryon capture` (the reference capture publisher, as a command): one pose a frame to a
    subscriber on another bus endpoint, then the end (its latched skeleton is tested with the
    live ingest, tests/test_services.py)."""
    with _bus_collecting(["tryon/cap/pose", "tryon/cap/control"]) as (endpoint, got):
        rc = main(["capture", "--session", "cap", "--clip", "cmu_npybvh_example_75f", "--pace", "fast",
                   "--max-frames", "6", "--wait-subscribers", "20", "--connect", endpoint])
        wait_until(lambda: len(got) >= 6, 10, "the poses and the end")  # (on zenoh's threads, maybe later)
    assert rc == 0 and "capture cap: 5 poses published" in capsys.readouterr().out
    got = [m for _, m in got]
    poses = [m for m in got if m.kind == "pose"]
    assert [m.frame for m in poses] == [1, 2, 3, 4, 5]  # (frame 0, the converter's T-pose, is not sent)
    assert all(m.arrays["local_rotations"].shape[1] == 4 and np.isfinite(m.arrays["local_rotations"]).all()
               for m in poses)
    # (another key than the poses': zenoh keeps one key's order, not two keys')
    [end] = [m for m in got if m.kind == "control"]
    assert end.meta["event"] == "end" and end.meta["last_frame"] == 5


@contextlib.contextmanager
def _bus_collecting(key_exprs: list[str]):
    """A bus listening on a free loopback port, collecting every message on key_exprs, decoded:
    yields (its endpoint, the (key, Message) list, filled on zenoh's threads)."""
    from services.bus import BusConfig

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    got, lock = [], threading.Lock()

    def on(sample):
        with lock:
            got.append((str(sample.key_expr), decode(sample.payload.to_bytes(), str(sample.key_expr))))

    with BusConfig(listen=[endpoint]).open() as bus:
        subs = [bus.declare_subscriber(k, on) for k in key_exprs]
        try:
            yield endpoint, got
        finally:
            for sub in subs:
                sub.undeclare()


def test_a_live_session_streams_to_a_remote_display_at_the_clips_pace(tmp_path, capsys):
    """`tryon session --serve` (the README's live session), on free ports: the clip at its own
    pace, a display on another bus endpoint gets the body and both garments of the frames, the
    rerun stream's address is told, and with a frame budget no step keeps the garments go on at
    level 3."""
    rerun_port = free_port()
    with _bus_collecting(["tryon/live/body", "tryon/live/garment/*"]) as (endpoint, got):
        rc = main(["session", "--session", "live", "--serve", "--max-frames", "90", "--level", "4",
                   "--frame-budget-ms", "0.001", "--port", str(rerun_port), "--listen",
                   f"tcp/127.0.0.1:{free_port()}", "--connect", endpoint, "--no-rrd", "--no-png", "--out",
                   str(tmp_path)])
        wait_until(lambda: any(m.kind == "garment" and m.meta.get("level") == 3 for _, m in got), 10,
                   "garments at level 3 at the display")
    assert rc == 0
    out = capsys.readouterr().out
    assert f"rerun --connect rerun+http://<this-host>:{rerun_port}/proxy" in out
    assert "(live, at the clip's pace)" in out
    assert re.search(r"cloth: received 89, .*level_changes 1,.* level at the end 3", out), out  # (catch-up: skipped)
    frames = re.search(r"session live: (\d+) frames in", out).group(1)
    bodies = sorted(m.frame for k, m in got if m.kind == "body")
    assert len(bodies) == int(frames) == 89
    assert {parse_key(k)[1][1] for k, m in got if m.kind == "garment"} == {"female_casualsuit01.bottom",
                                                                           "female_casualsuit01.top"}
    # at the clip's pace: 88 frames of 1/60 s after the first (offline they take a fraction of that)
    stream = re.search(r"then ([\d.]+) frames/s", out).group(1)
    assert 45 < float(stream) < 70, stream


def test_a_session_stopped_with_sigterm_closes_its_files(tmp_path, cli_env):
    """`tryon session` stopped half-way by SIGTERM (a service manager, `kill`) ends the stream
    between frames and closes its files as at the clip's end: the .rrd and a complete MCAP
    recording (no .part left) in which every published body frame has its garments."""
    import signal
    import time

    log = tmp_path / "session.log"
    part = tmp_path / "t3.mcap.part"
    with open(log, "w") as fh:
        p = subprocess.Popen([sys.executable, "-m", "services.cli", "session", "--session", "t3", "--level", "3",
                              "--no-png", "--out", str(tmp_path)], env=cli_env, stdout=fh, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 300
        # frames are being recorded (the walk has about 1,200 at every other frame: far from its end)
        while not (part.exists() and part.stat().st_size > 1_000_000) and p.poll() is None:
            assert time.monotonic() < deadline, log.read_text()
            time.sleep(0.1)
        assert p.poll() is None, log.read_text()
        p.send_signal(signal.SIGTERM)
        assert p.wait(timeout=120) == 0, log.read_text()
    finally:
        if p.poll() is None:
            p.kill()
    assert sorted(q.name for q in tmp_path.iterdir()) == ["session.log", "t3.mcap", "t3.rrd"], log.read_text()
    frames: dict[str, list[int]] = {}
    for k, payload, _ in read_recording(tmp_path / "t3.mcap"):
        frames.setdefault("/".join(parse_key(k)[1]), []).append(decode(payload, k).frame)
    body = frames["body"]
    assert 2 <= len(body) < 1000 and body == list(range(1, len(body) + 1))
    assert all(frames[g] == body for g in frames if g.startswith("garment/")), "a garment frame is missing"
    assert "cloth: received" in log.read_text()  # the summary was printed


def test_a_live_snapshot_is_the_first_frame_of_its_window_with_the_most_garments():
    """A live session's cloth service publishes only the newest of the frames it fell behind on:
    each snapshot comes from the first frame after it that has the body and every garment."""
    from services.session import SessionTap, snapshot_choice

    tap = SessionTap.__new__(SessionTap)
    parts = {"body": None, "garment/top": None, "garment/bottom": None}
    tap.snapshot_frames, tap.window = [10, 20, 30], 4
    tap.frames = {10: {"body": None}, 11: {"body": None, "garment/top": None}, 12: dict(parts), 13: dict(parts),
                  20: dict(parts), 30: {"body": None}, 31: {"body": None}}
    assert snapshot_choice(tap) == [12, 20]  # 30's window has no garment: left out
    tap.window = 1
    assert snapshot_choice(tap) == [20]


def test_recordings_on_a_disk_running_low_are_finished_complete_and_the_session_goes_on(tmp_path, capsys,
                                                                                        monkeypatch):
    """A disk with less free than the recordings keep: the bus recording and the .rrd are each
    finished at once, complete (readable, no .part left), the summary says why, and every frame
    is still stepped and published."""
    import services.diskspace as diskspace

    usage = diskspace.shutil.disk_usage(tmp_path)
    monkeypatch.setattr(diskspace.shutil, "disk_usage", lambda folder: usage._replace(free=5 * 10**8))  # 0.5 GB
    rc = main(["session", "--session", "t4", "--max-frames", "9", "--level", "3", "--no-png", "--keep-free", "2",
               "--out", str(tmp_path)])
    assert rc == 0
    out = capsys.readouterr().out
    assert re.search(r"cloth: received 8, published 16, rejected 0", out), out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t4.mcap", "t4.rrd"]
    for label in ("rerun", "recording"):
        assert re.search(label + r": \S+ \(finished early: 500 MB left free on the disk of .* \(recordings keep "
                         r"2.00 GB free\)\)", out), out
    recorded = [parse_key(k)[1][0] for k, _, _ in read_recording(tmp_path / "t4.mcap")]
    assert 1 <= len(recorded) < 10  # finished after its first message, readable
    rerun = Path(sys.executable).parent / "rerun"
    subprocess.run([str(rerun), "rrd", "print", str(tmp_path / "t4.rrd")], capture_output=True, check=True)


def test_keep_free_must_not_be_negative(tmp_path, capsys):
    assert main(["session", "--keep-free", "-1", "--out", str(tmp_path)]) != 0
    assert "--keep-free must be >= 0 GB, got -1" in capsys.readouterr().err


def test_a_session_wears_a_garment_mesh_of_the_users_and_refuses_one_off_the_body(data, tmp_path, capsys):
    """`tryon session --outfit FILE`: a garment mesh a user brings, already on the rest body, is
    simulated and published like a shipped garment (one garment: the file's); one off the body
    stops the session after its first frame with why, exit 2, its recordings finished; a folder
    with no garment in it is named before anything starts."""
    import trimesh

    from cloth.garment import load_outfit
    from cloth.topology import triangulate
    from skinning.animate import BodyAnimator
    from skinning.body import load_body

    body = load_body(data)
    base = body.vertices + BodyAnimator(body, contact=None).world_offset
    jeans = load_outfit(data / "garments" / "female_casualsuit01", base)[1]
    tris, _ = triangulate(jeans.faces, jeans.vertices)
    trimesh.Trimesh(jeans.vertices, tris, process=False).export(tmp_path / "jeans.ply")
    out = tmp_path / "worn"
    assert main(["session", "--session", "mine", "--outfit", str(tmp_path / "jeans.ply"), "--max-frames", "6",
                 "--level", "2", "--no-png", "--out", str(out)]) == 0
    assert re.search(r"cloth: received 5, published 5, rejected 0", capsys.readouterr().out)
    published = {"/".join(parse_key(k)[1]) for k, _, _ in read_recording(out / "mine.mcap")}
    assert {k for k in published if k.startswith("garment/")} == {"garment/jeans"}

    trimesh.Trimesh(jeans.vertices + [0.0, 0.0, 0.3], tris, process=False).export(tmp_path / "beside.ply")
    out = tmp_path / "refused"
    assert main(["session", "--session", "off", "--outfit", str(tmp_path / "beside.ply"), "--max-frames", "60",
                 "--no-png", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "tryon: session off: the cloth service cannot serve it" in err
    assert "beside.ply: garment 'beside' does not lie on the rest body" in err
    assert sorted(p.name for p in out.iterdir()) == ["off.mcap", "off.rrd"]  # finished, no .part
    assert [decode(p, k).frame for k, p, _ in read_recording(out / "off.mcap") if parse_key(k)[1] == ("body",)] == [1]

    (tmp_path / "nothing").mkdir()
    assert main(["session", "--outfit", str(tmp_path / "nothing"), "--out", str(tmp_path / "none")]) == 2
    assert "nothing: no .mhclo file and no garment mesh" in capsys.readouterr().err
    assert not (tmp_path / "none").exists()


def test_a_session_wears_a_fabric_per_garment(tmp_path, capsys):
    """`tryon session --fabric top=silk`: the T-shirt is silk, the jeans keep their denim, as the
    garments' topology on the bus says; a garment the outfit lacks stops the session after its
    first frame, naming it and the garments there are, exit 2."""
    out = tmp_path / "silk"
    assert main(["session", "--session", "silk", "--fabric", "top=silk", "--max-frames", "4", "--level", "2",
                 "--no-png", "--out", str(out)]) == 0
    capsys.readouterr()
    made = {parse_key(k)[1][-1]: decode(p, k).meta["fabric"] for k, p, _ in read_recording(out / "silk.mcap")
            if parse_key(k)[1][:2] == ("topology", "garment")}
    assert made == {"female_casualsuit01.top": "silk", "female_casualsuit01.bottom": "denim"}
    out = tmp_path / "legs"
    assert main(["session", "--session", "legs", "--fabric", "legs=silk", "--max-frames", "30", "--no-png",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "no garment 'legs' in the outfit; it has ['female_casualsuit01.top'" in err, err


def test_the_catalog_lists_each_outfits_garments_and_the_fabrics(tmp_path, capsys):
    """`tryon catalog`: every outfit in the data folder with its garments (the names `--fabric
    garment=preset` takes), each one's default fabric and which hang from a waistband; then the
    fabric presets with their values; --outfit and --fabrics narrow it to those; an unknown outfit
    is named with what there is."""
    assert main(["catalog"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("outfits (3; --outfit NAME, or garments of several: --outfit A.top+B.bottom; ")
    assert "  female_casualsuit01: female_casualsuit01.top (cotton), female_casualsuit01.bottom (denim, waistband)" in out
    assert "  female_elegantsuit01: female_elegantsuit01.top (silk), female_elegantsuit01.bottom (cotton, waistband)" in out
    assert "female_sportsuit01.bottom (jersey, waistband)" in out
    for preset in ("cotton", "denim", "silk", "jersey"):
        assert re.search(rf"^  {preset}: stretch [\d.]+ N/m, .* strain limit [\d.]+ %$", out, re.M), preset
    from cloth.fabric import fabric

    stiff = "\n".join(f"{k} = {v!r}" for k, v in vars(fabric("denim")).items() if k != "name")
    (tmp_path / "mine.toml").write_text(f"[raw_denim]\n{stiff}\n")
    assert main(["catalog", "--outfit", "female_sportsuit01", "--fabrics", str(tmp_path / "mine.toml")]) == 0
    out = capsys.readouterr().out
    assert "outfits (1;" in out and "female_casualsuit01" not in out
    assert f"  raw_denim: stretch {fabric('denim').stretch_stiffness:g} N/m" in out and "cotton:" not in out
    assert main(["catalog", "--outfit", "no-such-outfit"]) == 2
    assert "outfit 'no-such-outfit' not found" in capsys.readouterr().err
    # garments of two outfits mixed (`cloth.garment.mix_terms`), each with its own default fabric
    assert main(["catalog", "--outfit", "female_sportsuit01.top+female_casualsuit01.bottom"]) == 0
    assert ("  female_sportsuit01.top+female_casualsuit01.bottom: female_sportsuit01.top (jersey), "
            "female_casualsuit01.bottom (denim, waistband)") in capsys.readouterr().out
    # a data folder without garments (a user's body and motion alone) is named, not an OS error's path
    (tmp_path / "bare").mkdir()
    assert main(["--data", str(tmp_path / "bare"), "catalog"]) == 2
    assert f"data folder {tmp_path / 'bare'} has no garments/ folder" in capsys.readouterr().err
